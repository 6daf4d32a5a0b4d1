//! Start at a line (issue 26): `POST /jobs/{id}/start {"from_line": N}` runs lines N.. only,
//! after a preamble whose modal state is the interpreter's at N and whose approach goes up to
//! the safe Z before it moves across (the sim's execution log records each preamble step with
//! where the machine was before and after it); starts that cannot be made safely are refused
//! with the reason and the line and start nothing; a resume after `kill -9` goes through the
//! same preamble and runs every line exactly once.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{assert_every_line_once, corpus, Server, Sim};
use serde_json::{json, Value};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// Every record of the execution log (lines and preamble steps), in order.
fn records(m: &Sim) -> Vec<Value> {
    std::fs::read_to_string(&m.log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

/// The preamble steps the sim logged for `run`.
fn preamble_of(m: &Sim, run: i64) -> Vec<Value> {
    records(m)
        .into_iter()
        .filter(|r| r["run"] == run && r.get("preamble_step").is_some())
        .collect()
}

fn xyz(v: &Value) -> [f64; 4] {
    std::array::from_fn(|i| v[i].as_f64().unwrap())
}

/// The machine never went below `safe_z` while X, Y or A moved: each step is a straight move,
/// so its ends bound it.
#[track_caller]
fn assert_above_while_moving_across(steps: &[Value], safe_z: f64) {
    for s in steps {
        let (from, to) = (xyz(&s["from"]), xyz(&s["to"]));
        let across = [0, 1, 3].iter().any(|&i| (from[i] - to[i]).abs() > 1e-9);
        if across {
            assert!(
                from[2] >= safe_z - 1e-9 && to[2] >= safe_z - 1e-9,
                "moved across below the safe Z {safe_z}: {s}"
            );
        }
    }
}

/// Lines `from..=to` of `run` once each, in order, and nothing else of it.
#[track_caller]
fn assert_lines_once(m: &Sim, run: i64, from: i64, to: i64) {
    let got = m.lines_of(run);
    let want: Vec<i64> = (from..=to).collect();
    assert!(
        got == want,
        "run {run}: expected lines {from}..={to} once each in order; got {} entries, first {:?}",
        got.len(),
        got.iter().take(5).collect::<Vec<_>>()
    );
}

#[test]
fn a_start_at_a_line_runs_the_preamble_of_the_interpreters_state_then_lines_n_on_only() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    // The machine stands below the program's highest Z and away from the start point.
    s.jog(m.id, "Z", -5.0).expect(200);
    s.jog(m.id, "X", -20.0).expect(200);
    s.wait_status(m.id, T, "the jogs done", |st| {
        st["state"] == "idle" && st["machine_position"]["x"] == -20.0
    });
    let text = std::fs::read_to_string(corpus("fusion-1122_jig_28bit_first.nc")).unwrap();
    let lines = text.lines().count() as i64;
    let job = s.upload(m.id, "jig", text.clone())["id"].as_i64().unwrap();
    const N: u32 = 300;

    let preview = s
        .get(&format!("/api/v1/jobs/{job}/start-preview?from_line={N}"))
        .expect(200);
    // The state is the interpreter's at N, computed here on its own from where the machine
    // stands (work offsets zero).
    let mut interp = fresa_gcode::Interpreter::new(
        text.as_bytes(),
        fresa_gcode::Config {
            initial_position: [-20.0, 0.0, -5.0],
            ..Default::default()
        },
    );
    let state = interp.state_at(N).unwrap();
    assert_eq!(preview["state"], serde_json::to_value(&state).unwrap());
    assert_eq!(state.highest_z, Some(10.0));
    assert_eq!(preview["safe_z"], 10.0);
    assert_eq!(preview["approach_feed_mm_min"], 1000.0);
    let start = [state.position[0], state.position[1], state.position[2], 0.0];
    assert_eq!(
        xyz(&json!([
            preview["start"]["x"],
            preview["start"]["y"],
            preview["start"]["z"],
            preview["start"]["a"]
        ])),
        start
    );
    let gcode = preview["gcode"].as_str().unwrap();
    assert!(
        gcode.contains("G53 G0 Z10\nG54\nS5000 M3\nM9\nG53 G0 X29.29 Y19.965\nG53 G1 Z-4 F1000"),
        "{gcode}"
    );

    let r = s
        .post(
            &format!("/api/v1/jobs/{job}/start"),
            &json!({"from_line": N}),
        )
        .expect(200);
    assert_eq!(r["run"]["from_line"], N, "{r}");
    let run = r["run"]["id"].as_i64().unwrap();
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], lines, "{j}");
    assert_eq!(j["run"]["from_line"], N);

    // Lines N.. only, once each; lines before N were never acknowledged.
    assert_lines_once(&m, run, i64::from(N), lines);
    // The preamble: the steps previewed, in order, before the first line.
    let steps = preamble_of(&m, run);
    let planned = preview["preamble"]["steps"].as_array().unwrap();
    assert_eq!(steps.len(), planned.len(), "{steps:?}");
    for (done, plan) in steps.iter().zip(planned) {
        assert_eq!(&done["step"], plan);
    }
    let all = records(&m);
    let first_line = all
        .iter()
        .position(|r| r["run"] == run && r.get("line").is_some());
    let last_step = all
        .iter()
        .rposition(|r| r["run"] == run && r.get("preamble_step").is_some());
    assert!(last_step < first_line, "the preamble ran before line {N}");
    // Up first, from where the machine stood, to the safe Z; never across below it; and it
    // ends at the program's position before line N.
    assert_eq!(xyz(&steps[0]["from"]), [-20.0, 0.0, -5.0, 0.0]);
    assert_eq!(xyz(&steps[0]["to"]), [-20.0, 0.0, 10.0, 0.0]);
    assert_above_while_moving_across(&steps, 10.0);
    let end = xyz(&steps.last().unwrap()["to"]);
    assert!(
        (0..4).all(|i| (end[i] - start[i]).abs() < 1e-9),
        "the approach ended at {end:?}, the program was at {start:?} before line {N}"
    );
    // M5 M30 at the end: the spindle the preamble started is off again.
    assert_eq!(s.status(m.id)["outputs"]["spindle"], false);
}

#[test]
fn starts_that_cannot_be_made_safely_are_refused_with_the_reason_and_the_line_and_start_nothing() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    s.put(
        &format!("/api/v1/machines/{}/tools", m.id),
        &json!([{"tool": 1, "diameter_mm": 6.0}]),
    )
    .expect(200);
    let cases: [(&str, u32, &str, &[&str]); 6] = [
        (
            "G21 G90\nG0 X0 Y0 Z5\nG91 G81 X5 Z-2 R1 L3 F100\nG90 G80 G0 Z10\n",
            3,
            "start_in_canned_cycle_repeat",
            &["line 3: ", "(L3)"],
        ),
        (
            "G21 G90\n#1=0\no100 while [#1 LT 3]\nG1 X[#1] F100\n#1=[#1+1]\no100 endwhile\nG0 X0\n",
            4,
            "start_in_loop",
            &["line 4: ", "o<100> while (line 3)"],
        ),
        (
            "G21 G90\nG0 X-10 Y-10\nG41 D1\nG1 X0 Y0 F100\nG1 X10\nG1 Y10\nG40\nG0 X-10 Y-10\n",
            5,
            "start_under_cutter_compensation",
            &["line 5: ", "turned on at line 3"],
        ),
        (
            "G21 G90\nG0 X1\no<s> call\nM2\no<s> sub\nG1 X2 F100\no<s> endsub\n",
            6,
            "start_in_subroutine",
            &["line 6: ", "called on line 3"],
        ),
        (
            "G0 X1\nG0 X2\n",
            3,
            "start_past_end",
            &["line 3: ", "(2 lines)"],
        ),
        ("G0 X1\nG0 X2\n", 0, "invalid_field", &["from_line"]),
    ];
    let before = s.status(m.id)["machine_position"].clone();
    for (program, line, code, says) in cases {
        let job = s.upload(m.id, code, program)["id"].as_i64().unwrap();
        let e = s
            .get(&format!(
                "/api/v1/jobs/{job}/start-preview?from_line={line}"
            ))
            .expect_error(422, code);
        for part in says {
            assert!(e.contains(part), "{code}: {e}");
        }
        let e = s
            .post(
                &format!("/api/v1/jobs/{job}/start"),
                &json!({"from_line": line}),
            )
            .expect_error(422, code);
        for part in says {
            assert!(e.contains(part), "{code}: {e}");
        }
        let j = s.job(job);
        assert_eq!(j["state"], "ready", "no run was created: {j}");
        assert!(j["run"].is_null(), "{j}");
    }
    assert!(m.executed().is_empty(), "{:?}", m.executed());
    assert!(records(&m).is_empty());
    let st = s.status(m.id);
    assert_eq!(st["machine_position"], before, "nothing moved");
    assert_eq!(st["state"], "idle");
}

/// A run killed mid-job (the server with its in-process sim) resumes through the preamble of
/// its next line: the restarted sim stands at machine zero, below the program's working height
/// and away from it, so the resume goes up to the program's highest Z, across, and down at
/// feed; every line runs exactly once across both processes.
#[test]
fn a_resume_after_kill_9_goes_through_the_preamble_and_runs_every_line_once() {
    let mut s = Server::start();
    let m = s.sim("m", 0.1);
    const LINES: i64 = 300;
    let mut program = String::from("G21 G90 G0 Z8\nG0 X2 Y3\nG1 Z-1 F600\n");
    for i in 4..=LINES {
        program.push_str(&format!("G1 X{}\n", if i % 2 == 0 { 3 } else { 2 }));
    }
    let job = s.upload(m.id, "zigzag", program)["id"].as_i64().unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    s.wait_job(job, T, "line >= 40", |j| j["line"].as_i64().unwrap() >= 40);
    s.kill();
    // The sim logged lines whose acknowledgements the killed server never stored: as if it
    // had run five more (the store's line is then behind the log, as after a kill that lands
    // between the two).
    let stored = m.lines_of(run).into_iter().max().unwrap();
    let mut log = std::fs::OpenOptions::new()
        .append(true)
        .open(&m.log)
        .unwrap();
    for line in stored + 1..=stored + 5 {
        let entry = format!("{{\"run\":{run},\"line\":{line}}}\n");
        std::io::Write::write_all(&mut log, entry.as_bytes()).unwrap();
    }
    drop(log);
    s.spawn().unwrap();
    let j = s.job(job);
    assert_eq!(j["state"], "interrupted");
    assert!(j["line"].as_i64().unwrap() <= stored, "{j}");
    let logged = stored + 5;
    assert!(
        preamble_of(&m, run).is_empty(),
        "a start from line 1 has none"
    );

    let preview = s
        .get(&format!(
            "/api/v1/jobs/{job}/start-preview?from_line={}",
            logged + 1
        ))
        .expect(200);
    assert_eq!(preview["safe_z"], 8.0, "{preview}");
    let r = s.job_action(job, "resume").expect(200);
    assert_eq!(r["run"]["id"], run);
    s.wait_job_state(job, "completed", T);
    assert_every_line_once(&m.executed(), run, LINES);

    // The resume went through the preamble of the line after the last one logged: the
    // store's line was behind it, the backend's log decided, and the preamble was planned
    // again for its line.
    let steps = preamble_of(&m, run);
    assert!(!steps.is_empty(), "the resume ran a preamble");
    assert_eq!(
        xyz(&steps[0]["from"]),
        [0.0; 4],
        "from where the new sim stands"
    );
    assert_eq!(xyz(&steps[0]["to"]), [0.0, 0.0, 8.0, 0.0], "up first");
    assert_above_while_moving_across(&steps, 8.0);
    let end = xyz(&steps.last().unwrap()["to"]);
    let x = if logged % 2 == 0 { 3.0 } else { 2.0 };
    assert_eq!(end, [x, 3.0, -1.0, 0.0], "at line {logged}'s end");
    let down = steps.last().unwrap();
    assert_eq!(
        down["step"]["feed"], 600.0,
        "down at the program's feed: {down}"
    );
    // Every preamble step came before the first line of the resumed part.
    let all = records(&m);
    let last_step = all
        .iter()
        .rposition(|r| r["run"] == run && r.get("preamble_step").is_some());
    let resumed = all
        .iter()
        .position(|r| r["run"] == run && r["line"].as_i64() == Some(logged + 1));
    assert!(last_step < resumed, "{last_step:?} {resumed:?}");
}

#[test]
fn the_cli_previews_and_starts_at_a_line() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let job = s.upload(
        m.id,
        "p",
        "G21 G90\nG0 Z5\nG0 X10 Y10\nG1 Z-1 F200\nG1 X20\nG1 Y20\n",
    )["id"]
        .as_i64()
        .unwrap();
    let id = job.to_string();
    let out = s.cli(&["job", "start-preview", &id, "--from-line", "5"]);
    let text = fresa_tests::output_text(&out);
    assert!(out.status.success(), "{text}");
    assert!(
        text.contains("G53 G0 Z5\nG54\nM5\nM9\nG53 G0 X10 Y10\nG53 G1 Z-1 F200"),
        "{text}"
    );
    let out = s.cli(&["job", "start-preview", &id, "--from-line", "9"]);
    let text = fresa_tests::output_text(&out);
    assert!(
        !out.status.success() && text.contains("start_past_end"),
        "{text}"
    );
    let out = s.cli(&["job", "start", &id, "--from-line", "5"]);
    let text = fresa_tests::output_text(&out);
    assert!(
        out.status.success() && text.contains("from line 5"),
        "{text}"
    );
    let j = s.wait_job_state(job, "completed", T);
    let run = j["run"]["id"].as_i64().unwrap();
    assert_eq!(m.lines_of(run), vec![5, 6]);
}
