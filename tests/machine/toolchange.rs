//! Pauses that say why and manual tool changes (issue 26), and the tool length setter (issue
//! 25), on the real server with sim machines: the run and the machine agree (`paused` on both)
//! with the reason in the status, the job and the events; an M6 holds naming the tools, lets
//! the operator jog, and cycle start goes back to where it held and finishes every line once;
//! M1 follows the optional stop switch; a `refuse` policy refuses a program with M6 at start;
//! the setter measures tools whose tips reach different heights and zeroes Z again for the new
//! one, so the new tip reads the same Z at the same height.
//!
//! The sim machine's tools are physical (`tool_lengths` in its config: how far each tip reaches
//! below the spindle); its `probe` switch is touched by the tip, so the setter trips a longer
//! tool higher up. Fresa never sees those lengths: it measures them. (The sim's switch is a
//! plane at one Z, whatever the X and Y: the setter's X Y only decide where the machine goes.)

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{assert_every_line_once, Server, Sim};
use std::time::Duration;

const T: Duration = Duration::from_secs(30);

/// A sim machine with an execution log, `config` merged into its backend config.
fn sim(s: &Server, name: &str, config: Value) -> Sim {
    let log = s.data_dir().join(format!("exec-{name}.log"));
    let mut cfg = json!({"time_scale": 0, "execution_log": s.host_path(&log)});
    for (k, v) in config.as_object().unwrap() {
        cfg[k] = v.clone();
    }
    let id = s.create_machine(&json!({
        "name": name, "backend": "sim-machine", "max_jog_mm": 60.0,
        "max_probe_feed_mm_min": 1500.0, "config": cfg,
    }));
    s.wait_machine_state(id, "idle", T);
    Sim { id, log }
}

fn patch_settings(s: &Server, m: i64, body: Value) -> Value {
    s.send(
        s.req(
            reqwest::Method::PATCH,
            &format!("/api/v1/machines/{m}/run-settings"),
        )
        .json(&body),
    )
    .expect(200)
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-6
}

/// The machine holds with `kind`; its job (the view) says paused and why, the same way.
#[track_caller]
fn wait_held(s: &Server, m: i64, job: i64, kind: &str) -> (Value, Value) {
    let st = s.wait_status(m, T, &format!("held for {kind}"), |st| {
        st["state"] == "paused" && st["hold"]["kind"] == kind
    });
    let j = s.wait_job(job, T, &format!("paused for {kind}"), |j| {
        j["state"] == "paused" && j["hold"]["kind"] == kind
    });
    assert_eq!(j["hold"], st["hold"], "job and machine give one reason");
    assert_eq!(st["job"]["job"], job, "{st}");
    (st, j)
}

/// An `M6 T2` holds: spindle off, the reason names both tools and the table's description,
/// the job says the same; a jog during the hold moves the machine; cycle start goes back to
/// where the tip was at M6 before cutting on (the M0 after the next cut finds X where it was,
/// not where the jog left it), and the run finishes with every line executed once.
#[test]
fn an_m6_holds_naming_the_tools_a_jog_moves_and_cycle_start_finishes_every_line_once() {
    let s = Server::start();
    let m = sim(&s, "mill", json!({"tool": 1}));
    s.put(
        &format!("/api/v1/machines/{}/tools", m.id),
        &json!([{"tool": 1, "diameter_mm": 6, "description": "6 mm flat"},
                {"tool": 2, "diameter_mm": 3, "description": "3 mm drill"}]),
    )
    .expect(200);
    let program = "G21 G90\nG0 X10 Y5 Z5\nS8000 M3\nT2 M6\nG1 Z-1 F300\nM0 (MSG, check the hole)\nG0 Z5\nG0 X20\nM30\n";
    let (job, run) = s.upload_and_start(m.id, "two-tools", program);

    let (st, j) = wait_held(&s, m.id, job, "tool_change");
    let hold = &st["hold"];
    assert_eq!(hold["line"], 4, "{hold}");
    assert_eq!(hold["continue_with"], "cycle_start", "{hold}");
    assert_eq!(hold["tool_change"]["from"], 1, "{hold}");
    assert_eq!(hold["tool_change"]["to"], 2, "{hold}");
    assert_eq!(
        hold["tool_change"]["to_description"], "3 mm drill",
        "{hold}"
    );
    assert_eq!(
        hold["tool_change"]["from_description"], "6 mm flat",
        "{hold}"
    );
    let message = hold["message"].as_str().unwrap();
    assert!(
        message.contains("T1") && message.contains("T2") && message.contains("3 mm drill"),
        "{message}"
    );
    assert_eq!(st["outputs"]["spindle"], false, "the spindle stops: {st}");
    assert_eq!(j["run"]["message"], hold["message"], "{j}");
    assert!(close(num(&st["machine_position"]["x"]), 10.0), "{st}");

    // Jogging is allowed in this hold (and nowhere else during a run).
    s.jog(m.id, "X", 3.0).expect(200);
    let st = s.wait_status(m.id, T, "the jog moved X", |st| {
        st["state"] == "paused" && close(num(&st["machine_position"]["x"]), 13.0)
    });
    assert_eq!(st["hold"]["kind"], "tool_change", "still held: {st}");
    assert_eq!(s.job(job)["state"], "paused");
    // MDI stays refused: the hold is for jogging and probing.
    s.mdi(m.id, "G0 X0").expect_error(409, "machine_busy");

    // Cycle start: back to X10 Z5 (up, across, down), then the cut and the M0.
    s.command(m.id, "cycle_start", json!({})).expect(200);
    let (st, _) = wait_held(&s, m.id, job, "program_pause");
    assert_eq!(st["hold"]["program_message"], "check the hole", "{st}");
    let at = &st["machine_position"];
    assert!(
        close(num(&at["x"]), 10.0) && close(num(&at["y"]), 5.0) && close(num(&at["z"]), -1.0),
        "the cut after the change started where the tool was at M6: {st}"
    );
    s.command(m.id, "cycle_start", json!({})).expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert!(j.get("hold").is_none(), "{j}");
    assert_every_line_once(&m.executed(), run, 9);
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st.get("hold").is_none(), "{st}");
    assert!(close(num(&st["machine_position"]["x"]), 20.0), "{st}");
}

/// M0 with `(MSG, change clamp)`: machine and job both say `paused`, with the message, in the
/// status, the job view, the run's message and the `job.state` event; cycle start (the button
/// the hold names) goes on. A feed hold is `paused` on both too, and `resume` applies.
#[test]
fn m0_and_feed_hold_pause_job_and_machine_alike_saying_why() {
    let s = Server::start();
    let m = sim(&s, "router", json!({"time_scale": 0.2}));
    let events = s.events("types=job.state", None);
    let mut program = String::from("G21 G90\nG0 X1\nM0 (MSG, change clamp)\n");
    program.push_str(&fresa_tests::back_and_forth(300, 1.0, 600.0));
    let (job, run) = s.upload_and_start(m.id, "clamp", &program);

    let (st, j) = wait_held(&s, m.id, job, "program_pause");
    assert_eq!(st["hold"]["program_message"], "change clamp", "{st}");
    assert_eq!(st["hold"]["line"], 3, "{st}");
    assert_eq!(st["hold"]["continue_with"], "cycle_start", "{st}");
    assert!(
        st["hold"]["message"]
            .as_str()
            .unwrap()
            .contains("change clamp"),
        "{st}"
    );
    assert_eq!(j["run"]["message"], st["hold"]["message"], "{j}");
    let paused = events.until(T, "job.state paused", |e| {
        e.job() == Some(job) && e.state() == Some("paused")
    });
    let paused = &paused.last().unwrap().data["data"];
    assert_eq!(
        paused["hold"]["program_message"], "change clamp",
        "{paused}"
    );

    s.command(m.id, "cycle_start", json!({})).expect(200);
    s.wait_job(job, T, "running again", |j| {
        j["state"] == "running" && j.get("hold").is_none()
    });
    events.until(T, "job.state running", |e| {
        e.job() == Some(job) && e.state() == Some("running")
    });

    // A feed hold from anyone: both paused, `resume` is the button.
    s.wait_job(job, T, "a few lines more", |j| num(&j["line"]) >= 10.0);
    s.command(m.id, "feed_hold", json!({})).expect(200);
    let (st, _) = wait_held(&s, m.id, job, "feed_hold");
    assert_eq!(st["hold"]["continue_with"], "resume", "{st}");
    s.command(m.id, "resume", json!({})).expect(200);
    s.wait_job(job, T, "running after the feed hold", |j| {
        j["state"] == "running"
    });
    let j = s.wait_job_state(job, "completed", T);
    assert_every_line_once(&m.executed(), run, num(&j["line_count"]) as i64);
}

/// M1 is passed over with the optional stop off (the default) and holds with it on; the
/// switch is set through the API and recorded.
#[test]
fn m1_follows_the_optional_stop_switch() {
    let s = Server::start();
    let m = sim(&s, "lathe-ish", json!({}));
    let program = "G21 G90\nG0 X1\nM1 (MSG, look)\nG0 X2\nM30\n";
    let (job, run) = s.upload_and_start(m.id, "m1-off", program);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["run"]["id"], run);
    assert_every_line_once(&m.executed(), run, 5);

    let settings = patch_settings(&s, m.id, json!({"optional_stop": true}));
    assert_eq!(settings["optional_stop"], true, "{settings}");
    assert_eq!(settings["tool_change"], "hold", "the rest kept: {settings}");
    let (job, _) = s.upload_and_start(m.id, "m1-on", program);
    let (st, _) = wait_held(&s, m.id, job, "optional_stop");
    assert_eq!(st["hold"]["program_message"], "look", "{st}");
    assert!(close(num(&st["machine_position"]["x"]), 1.0), "{st}");
    s.job_action(job, "resume").expect(200);
    s.wait_job_state(job, "completed", T);
    let recorded = s.events("types=machine.run_settings", Some(0));
    let seen = recorded.until(T, "machine.run_settings", |e| {
        e.event == "machine.run_settings"
    });
    assert_eq!(seen.last().unwrap().data["data"]["optional_stop"], true);
}

/// `refuse`: a program with M6 is refused at start naming its line, and nothing moves;
/// `ignore`: M6 passes without a hold.
#[test]
fn a_refuse_policy_refuses_m6_at_start_naming_the_line_and_ignore_passes_it() {
    let s = Server::start();
    let m = sim(&s, "strict", json!({}));
    patch_settings(&s, m.id, json!({"tool_change": "refuse"}));
    let program = "G21 G90\nG0 X1\n(change)\nT3 M6\nG0 X2\nM30\n";
    let job = s.upload(m.id, "m6", program)["id"].as_i64().unwrap();
    let message = s
        .job_action(job, "start")
        .expect_error(409, "tool_change_refused");
    assert!(message.contains("line 4"), "{message}");
    assert_eq!(s.job(job)["state"], "ready");
    assert!(m.executed().is_empty(), "nothing ran");
    // A program without M6 still runs.
    let (plain, _) = s.upload_and_start(m.id, "plain", "G0 X1\nG0 X0\n");
    s.wait_job_state(plain, "completed", T);

    patch_settings(&s, m.id, json!({"tool_change": "ignore"}));
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    s.wait_job_state(job, "completed", T);
    assert_every_line_once(&m.executed(), run, 6);
    // Bad settings are refused naming the field, and change nothing.
    s.send(
        s.req(
            reqwest::Method::PATCH,
            &format!("/api/v1/machines/{}/run-settings", m.id),
        )
        .json(&json!({"tool_change": "sometimes"})),
    )
    .expect_error(422, "invalid_field");
    let now = s
        .get(&format!("/api/v1/machines/{}/run-settings", m.id))
        .expect(200);
    assert_eq!(now["tool_change"], "ignore", "{now}");
}

/// The sim of the setter tests: physical tools T1 (30 mm) and T2 (42.5 mm), T1 in; the
/// setter's (and the probe's) switch is touched by the tip at Z -60, so T1 trips it at machine
/// Z -30 and T2 at -17.5. Z travel -100..0.
fn setter_sim(s: &Server, name: &str) -> Sim {
    let m = sim(
        s,
        name,
        json!({
            "tool": 1, "tool_lengths": {"1": 30, "2": 42.5},
            "travel": {"z": [-100, 0]},
            "switches": {"probe": {"axis": "z", "at_or_below": -60}},
        }),
    );
    patch_settings(
        s,
        m.id,
        json!({"tool_setter": {"x": 100, "y": 50, "z": 0, "distance_mm": 55,
                               "feed_mm_min": 600, "reference_tool": 1}}),
    );
    m
}

fn measure(s: &Server, m: i64, tool: i64) -> Value {
    let r = s.post_empty(&format!("/api/v1/machines/{m}/tools/{tool}/measure"));
    if r.status != 200 {
        panic!("measure T{tool}: {r:?}\n{}", s.log());
    }
    r.body
}

fn probe_input(st: &Value) -> bool {
    st["inputs"]["probe"]
        .as_bool()
        .unwrap_or_else(|| panic!("no probe input in {st}"))
}

/// Measures T1 (the reference: length 0) and, during the tool change to T2, T2 (12.5 mm
/// longer): both lengths are stored, and the work offset's Z moves by 12.5 so T2's tip reads
/// Z 0 at the height where T1's did, where the switch is: the probe input (the tip on the
/// switch plane) is open just above work Z 0 and closed just below it, for both tools.
#[test]
fn the_setter_measures_two_tools_and_a_tool_change_zeroes_z_for_the_new_one() {
    let s = Server::start();
    let m = setter_sim(&s, "setter");
    s.post_empty(&format!("/api/v1/machines/{}/tools/2/measure", m.id))
        .expect_error(409, "reference_not_measured");

    let t1 = measure(&s, m.id, 1);
    assert!(close(num(&t1["trip_z"]), -30.0), "{t1}");
    assert!(close(num(&t1["length_mm"]), 0.0), "{t1}");
    let st = s.status(m.id);
    let at = &st["machine_position"];
    assert!(
        close(num(&at["x"]), 100.0) && close(num(&at["y"]), 50.0) && close(num(&at["z"]), 0.0),
        "back up at the setter: {st}"
    );

    // Zero Z with T1's tip on the switch plane (machine Z -30).
    s.jog(m.id, "Z", -30.0).expect(200);
    s.wait_status(m.id, T, "T1 on the plane", |st| {
        st["state"] == "idle" && close(num(&st["machine_position"]["z"]), -30.0)
    });
    s.command(m.id, "zero", json!({"axis": "Z"})).expect(200);

    let program = "G21 G90\nG0 Z0.05\nM0\nG0 Z5\nT2 M6\nG0 Z0.05\nM0\nG0 Z-0.05\nM0\nG0 Z5\nM30\n";
    let (job, run) = s.upload_and_start(m.id, "two-tools", program);
    let (st, _) = wait_held(&s, m.id, job, "program_pause");
    assert!(!probe_input(&st), "T1 0.05 above work Z 0: {st}");
    s.command(m.id, "cycle_start", json!({})).expect(200);
    let (st, _) = wait_held(&s, m.id, job, "tool_change");
    assert_eq!(st["hold"]["tool_change"]["length_compensation"], false);

    let t2 = measure(&s, m.id, 2);
    assert!(close(num(&t2["trip_z"]), -17.5), "{t2}");
    assert!(close(num(&t2["length_mm"]), 12.5), "{t2}");
    let r = &t2["rezero"];
    assert_eq!(r["from_tool"], 1, "{t2}");
    assert!(close(num(&r["before"]["z"]), -30.0), "{t2}");
    assert!(close(num(&r["after"]["z"]), -17.5), "{t2}");
    let tools = s
        .get(&format!("/api/v1/machines/{}/tools", m.id))
        .expect(200);
    let length = |n: i64| {
        num(&tools
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["tool"] == n)
            .unwrap()["length_mm"])
    };
    assert!(close(length(1), 0.0) && close(length(2), 12.5), "{tools}");
    let touch = s.events("types=machine.touch_off", Some(0));
    let seen = touch.until(T, "the re-zero recorded", |e| {
        e.data["data"]["source"] == "tool_setter"
    });
    let rec = &seen.last().unwrap().data["data"];
    assert!(close(num(&rec["after"]["z"]), -17.5), "{rec}");

    // Cycle start: T2's tip reads work Z like T1's did at the same height.
    s.command(m.id, "cycle_start", json!({})).expect(200);
    let (st, _) = wait_held(&s, m.id, job, "program_pause");
    assert!(close(num(&st["work_position"]["z"]), 0.05), "{st}");
    assert!(!probe_input(&st), "T2 0.05 above work Z 0: {st}");
    s.command(m.id, "cycle_start", json!({})).expect(200);
    s.wait_status(m.id, T, "the M0 on line 9", |st| {
        st["state"] == "paused" && st["hold"]["line"] == 9
    });
    let st = s.status(m.id);
    assert!(probe_input(&st), "T2 0.05 below work Z 0: {st}");
    s.command(m.id, "cycle_start", json!({})).expect(200);
    s.wait_job_state(job, "completed", T);
    assert_every_line_once(&m.executed(), run, 11);
}

/// With G43 in force at the change, the new tool's length applies at cycle start instead: the
/// measure tells the backend the new table and leaves the work offset alone, and T2's tip is
/// again where T1's was for the same program Z.
#[test]
fn with_g43_the_measured_length_applies_at_cycle_start_and_the_offset_stays() {
    let s = Server::start();
    let m = setter_sim(&s, "g43");
    measure(&s, m.id, 1);
    s.jog(m.id, "Z", -30.0).expect(200);
    s.wait_status(m.id, T, "T1 on the plane", |st| {
        st["state"] == "idle" && close(num(&st["machine_position"]["z"]), -30.0)
    });
    s.command(m.id, "zero", json!({"axis": "Z"})).expect(200);
    let program = "G21 G90\nG43 H1\nG0 Z5\nT2 M6\nG0 Z0.05\nM0\nG0 Z-0.05\nM0\nG49 G0 Z5\nM30\n";
    let (job, run) = s.upload_and_start(m.id, "g43", program);
    let (st, _) = wait_held(&s, m.id, job, "tool_change");
    assert_eq!(
        st["hold"]["tool_change"]["length_compensation"], true,
        "{st}"
    );
    let t2 = measure(&s, m.id, 2);
    assert!(t2["rezero"].is_null(), "{t2}");
    assert!(t2["note"].as_str().unwrap().contains("G43"), "{t2}");
    let offsets = s
        .get(&format!("/api/v1/machines/{}/offsets", m.id))
        .expect(200);
    assert!(
        close(num(&offsets["offsets"]["G54"]["z"]), -30.0),
        "{offsets}"
    );
    s.command(m.id, "cycle_start", json!({})).expect(200);
    let (st, _) = wait_held(&s, m.id, job, "program_pause");
    assert!(close(num(&st["machine_position"]["z"]), -17.45), "{st}");
    assert!(close(num(&st["work_position"]["z"]), 0.05), "{st}");
    assert!(!probe_input(&st), "{st}");
    s.command(m.id, "cycle_start", json!({})).expect(200);
    s.wait_status(m.id, T, "the M0 on line 8", |st| {
        st["state"] == "paused" && st["hold"]["line"] == 8
    });
    assert!(probe_input(&s.status(m.id)));
    s.command(m.id, "cycle_start", json!({})).expect(200);
    s.wait_job_state(job, "completed", T);
    assert_every_line_once(&m.executed(), run, 10);
}

/// STOP while the machine goes to the setter ends the measure there: nothing after it moves
/// (no probe starts), the answer says `stopped`, and nothing is stored.
#[test]
fn stop_during_a_measure_ends_it_and_stores_nothing() {
    let s = Server::start();
    // Real time: 200 mm of X at the 1000 mm/min jog feed takes 12 s.
    let m = sim(
        &s,
        "slow-setter",
        json!({"time_scale": 1, "tool": 1, "tool_lengths": {"1": 30},
               "travel": {"z": [-100, 0]},
               "switches": {"probe": {"axis": "z", "at_or_below": -60}}}),
    );
    patch_settings(
        &s,
        m.id,
        json!({"tool_setter": {"x": 200, "y": 0, "z": 0, "distance_mm": 55,
                               "feed_mm_min": 600, "reference_tool": 1}}),
    );
    let measuring = {
        let url = s.url(&format!("/api/v1/machines/{}/tools/1/measure", m.id));
        std::thread::spawn(move || {
            let r = reqwest::blocking::Client::new().post(url).send().unwrap();
            (r.status().as_u16(), r.text().unwrap())
        })
    };
    s.wait_status(m.id, T, "on its way to the setter", |st| {
        st["state"] == "jogging" && num(&st["machine_position"]["x"]) > 1.0
    });
    s.command(m.id, "stop", json!({})).expect(200);
    let (status, body) = measuring.join().unwrap();
    assert_eq!(status, 409, "{body}");
    assert!(body.contains("stopped"), "{body}");
    let st = s.wait_machine_state(m.id, "idle", T);
    let x = num(&st["machine_position"]["x"]);
    assert!(x < 200.0, "stopped on the way: {st}");
    assert!(
        close(num(&st["machine_position"]["z"]), 0.0),
        "no probe went down: {st}"
    );
    let settings = s
        .get(&format!("/api/v1/machines/{}/run-settings", m.id))
        .expect(200);
    assert!(settings["tool_setter_reference_z"].is_null(), "{settings}");
    let tools = s
        .get(&format!("/api/v1/machines/{}/tools", m.id))
        .expect(200);
    assert_eq!(tools, json!([]), "nothing stored");
}

/// The CLI: `fresa machine run-settings` changes and prints the settings, `fresa machine
/// measure-tool` prints what the setter found.
#[test]
fn the_cli_sets_run_settings_and_measures_a_tool() {
    let s = Server::start();
    let m = setter_sim(&s, "cli-setter");
    let id = m.id.to_string();
    let out = s.cli(&[
        "machine",
        "run-settings",
        &id,
        "--optional-stop",
        "on",
        "--tool-change",
        "refuse",
    ]);
    let text = fresa_tests::output_text(&out);
    assert!(out.status.success(), "{text}");
    let printed: Value = fresa_tests::serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(printed["optional_stop"], true, "{text}");
    assert_eq!(printed["tool_change"], "refuse", "{text}");
    let out = s.cli(&["machine", "run-settings", &id, "--optional-stop", "maybe"]);
    assert!(!out.status.success());
    let out = s.cli(&["machine", "measure-tool", &id, "--tool", "2"]);
    let text = fresa_tests::output_text(&out);
    assert!(!out.status.success(), "{text}");
    assert!(text.contains("reference_not_measured"), "{text}");
    let out = s.cli(&["machine", "measure-tool", &id, "--tool", "1"]);
    let text = fresa_tests::output_text(&out);
    assert!(out.status.success(), "{text}");
    assert!(
        text.contains("T1 tripped the setter at machine Z -30.0000; length 0.0000 mm"),
        "{text}"
    );
}
