//! Feed, spindle and rapid overrides over the REST API and the CLI: what they do to a running
//! job (measured on the sim machine's own execution log, which stamps each finished line), the
//! machine's range, and the record they leave.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::json;
use fresa_tests::{Server, Sim};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// The median time a line took, ms, over the lines `from..=to` of `run` (each line's end
/// minus the previous one's).
fn median_line_ms(sim: &Sim, run: i64, from: i64, to: i64) -> f64 {
    let times = sim.line_times(run);
    let mut spans: Vec<f64> = times
        .windows(2)
        .filter(|w| w[1].0 >= from && w[1].0 <= to)
        .map(|w| w[1].1 as f64 - w[0].1 as f64)
        .collect();
    assert!(
        spans.len() as i64 >= to - from,
        "lines {from}..={to} of run {run} not all stamped: {times:?}"
    );
    spans.sort_by(f64::total_cmp);
    spans[spans.len() / 2]
}

fn overrides(s: &Server, m: i64) -> [f64; 3] {
    let st = s.status(m);
    ["feed_override", "spindle_override", "rapid_override"].map(|k| {
        st[k]
            .as_f64()
            .unwrap_or_else(|| panic!("no {k} in the status {st}"))
    })
}

/// The check: a 50 % feed override set while a real-time job runs makes each line
/// take twice as long from then on (lines of 5 mm at 600 mm/min: 0.5 s of machine time, 0.1 s
/// at time scale 0.2), by the sim's execution log; the status and the answer say 50.
#[test]
fn a_50_percent_feed_override_during_a_run_makes_each_line_take_twice_as_long() {
    let s = Server::start();
    let sim = s.sim("mill", 0.2);
    let m = sim.id;
    s.wait_machine_state(m, "idle", T);
    let (job, run) = s.upload_and_start(m, "strokes", &fresa_tests::back_and_forth(40, 5.0, 600.0));
    fresa_tests::wait_for(T, "line 12 executed", || {
        (sim.count_of(run) >= 12).then_some(())
    });
    let answer = s
        .post(
            &format!("/api/v1/machines/{m}/overrides"),
            &json!({"feed": 50}),
        )
        .expect(200);
    assert_eq!(
        answer,
        json!({"feed": 50.0, "spindle": 100.0, "rapid": 100.0})
    );
    // The line under way when it came is the only one in between; later ones are all at 50 %.
    let set_at = sim.count_of(run) as i64 + 2;
    assert_eq!(overrides(&s, m), [50.0, 100.0, 100.0]);
    s.wait_job_state(job, "completed", T);
    fresa_tests::assert_every_line_once(&sim.executed(), run, 40);
    let full = median_line_ms(&sim, run, 3, 11);
    let half = median_line_ms(&sim, run, set_at, 40);
    let ratio = half / full;
    eprintln!("feed override: {full} ms a line at 100 %, {half} ms at 50 % (x{ratio:.2})");
    assert!(
        (1.7..=2.3).contains(&ratio),
        "a line took {full} ms at 100 % and {half} ms at 50 % (ratio {ratio:.2}); expected about 2"
    );
    // Jogs keep their own feed: the override is for programs. The override stays in force.
    assert_eq!(overrides(&s, m), [50.0, 100.0, 100.0]);
}

/// A 25 % rapid override slows the G0 lines four times and leaves the G1 lines as they were
/// (both 10 mm at 600 mm/min nominal, the sim's rapid rate set to 600; 0.1 s a G1 line at
/// time scale 0.1).
#[test]
fn a_rapid_override_slows_g0_and_not_g1() {
    let s = Server::start();
    let sim = s.sim_with(
        "router",
        0.1,
        json!({"config": {"time_scale": 0.1, "rapid_mm_min": 600.0,
                          "execution_log": s.host_path(&s.data_dir().join("exec-router.log"))}}),
    );
    let m = sim.id;
    s.wait_machine_state(m, "idle", T);
    s.post(
        &format!("/api/v1/machines/{m}/overrides"),
        &json!({"rapid": 25}),
    )
    .expect(200);
    let mut program = String::from("G21 G90 G1 F600 X0\n");
    for _ in 0..10 {
        program.push_str("G0 X10\nG1 X0\n");
    }
    let (job, run) = s.upload_and_start(m, "rapids", &program);
    s.wait_job_state(job, "completed", T);
    let times = sim.line_times(run);
    assert_eq!(times.len(), 21, "{times:?}");
    let span = |line: i64| {
        let i = times.iter().position(|t| t.0 == line).unwrap();
        (times[i].1 - times[i - 1].1) as f64
    };
    let mut g0: Vec<f64> = (0..10).map(|k| span(2 + 2 * k)).collect();
    let mut g1: Vec<f64> = (0..10).map(|k| span(3 + 2 * k)).collect();
    g0.sort_by(f64::total_cmp);
    g1.sort_by(f64::total_cmp);
    let (g0, g1) = (g0[5], g1[5]);
    eprintln!("rapid override 25 %: G0 line {g0} ms, G1 line {g1} ms");
    assert!(
        (3.3..=4.7).contains(&(g0 / g1)),
        "a G0 line took {g0} ms and a G1 line {g1} ms at a 25 % rapid override; expected 4:1"
    );
}

/// Each override is checked against the machine's range before anything reaches the backend,
/// naming the field and the range; a refused request changes nothing. The range is the
/// machine's own (`override_limits`), checked when the machine is made.
#[test]
fn overrides_outside_the_machines_range_are_refused_naming_the_field() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    s.wait_machine_state(m, "idle", T);
    let path = format!("/api/v1/machines/{m}/overrides");
    let msg = s
        .post(&path, &json!({"feed": 250, "spindle": 100}))
        .expect_error(422, "override_out_of_range");
    assert!(msg.contains("`feed`") && msg.contains("10 to 200"), "{msg}");
    let msg = s
        .post(&path, &json!({"rapid": 150}))
        .expect_error(422, "override_out_of_range");
    assert!(
        msg.contains("`rapid`") && msg.contains("25 to 100"),
        "{msg}"
    );
    let msg = s.post(&path, &json!({})).expect_error(422, "invalid_field");
    assert!(msg.contains("at least one"), "{msg}");
    let r = s.post(&path, &json!({"feed": 50, "fed": 60}));
    assert_eq!(r.status, 400, "{}", r.text);
    assert!(r.text.contains("fed"), "{}", r.text);
    assert_eq!(overrides(&s, m), [100.0, 100.0, 100.0]);

    // The same check on every path: a command through /commands meets it too.
    s.post(
        &format!("/api/v1/machines/{m}/commands"),
        &json!({"command": "set_overrides", "spindle": 20}),
    )
    .expect_error(422, "override_out_of_range");
    s.post(
        &format!("/api/v1/machines/{m}/commands"),
        &json!({"command": "set_overrides", "spindle": 120}),
    )
    .expect(200);
    assert_eq!(overrides(&s, m), [100.0, 120.0, 100.0]);

    // A machine allowed up to 300 % feed; a range that does not hold 100 % is refused.
    let fast = s.create_machine(&json!({
        "name": "fast", "backend": "sim-machine", "config": {"time_scale": 0.0},
        "override_limits": {"feed_max": 300},
    }));
    let view = s.get(&format!("/api/v1/machines/{fast}")).expect(200);
    assert_eq!(
        view["override_limits"],
        json!({"feed_min": 10.0, "feed_max": 300.0, "spindle_min": 50.0, "spindle_max": 150.0, "rapid_min": 25.0})
    );
    s.wait_machine_state(fast, "idle", T);
    s.post(
        &format!("/api/v1/machines/{fast}/overrides"),
        &json!({"feed": 250}),
    )
    .expect(200);
    let r = s.post(
        "/api/v1/machines",
        &json!({"name": "odd", "backend": "sim-machine", "override_limits": {"feed_min": 150}}),
    );
    let msg = r.expect_error(422, "invalid_field");
    assert!(msg.contains("override_limits.feed_min"), "{msg}");
}

/// An override is recorded as `machine.command` under who set it, and the CLI sets and prints
/// the overrides in force.
#[test]
fn an_override_is_audited_and_the_cli_sets_and_shows_it() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    s.wait_machine_state(m, "idle", T);
    let out = s.cli(&[
        "machine",
        "override",
        &m.to_string(),
        "--feed",
        "80",
        "--rapid",
        "50",
    ]);
    assert!(out.status.success(), "{out:?}");
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        text.contains("feed 80%") && text.contains("rapid 50%") && text.contains("spindle 100%"),
        "{text}"
    );
    let out = s.cli(&["machine", "override", &m.to_string()]);
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("feed 80%"),
        "{out:?}"
    );
    let out = s.cli(&["machine", "override", &m.to_string(), "--feed", "5"]);
    assert!(!out.status.success(), "{out:?}");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("override_out_of_range"),
        "{out:?}"
    );
    let events = s.events("types=machine.command", Some(0));
    let seen = events.until(T, "the override command", |e| {
        e.data["data"]["command"] == "set_overrides"
    });
    let e = seen.last().unwrap();
    assert_eq!(e.data["data"]["feed"], 80.0);
    assert_eq!(e.data["data"]["rapid"], 50.0);
    assert!(e.data["data"].get("spindle").is_none(), "{:?}", e.data);
    assert!(e.data["actor"].is_string(), "{:?}", e.data);
}
