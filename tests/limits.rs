//! Limits bind (issue 11): machine jog/feed limits must be sane numbers, absurd coordinates and
//! moves past the soft limits are refused before anything moves, and outputs cannot be switched
//! under a cutting run.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{back_and_forth, wait_for, Server, Sim};
use serde_json::{json, Value};
use std::time::Duration;

const T: Duration = Duration::from_secs(30);

#[test]
fn machine_jog_and_feed_limits_outside_sane_ranges_are_refused_naming_the_field() {
    let s = Server::start();
    for (i, (field, value)) in [
        ("max_jog_mm", json!(1e308)),
        ("max_jog_mm", json!(0)),
        ("max_jog_mm", json!(-1)),
        ("max_jog_mm", json!(1001)),
        ("max_feed_mm_min", json!(1e308)),
        ("max_feed_mm_min", json!(0)),
        ("max_feed_mm_min", json!(100001)),
    ]
    .into_iter()
    .enumerate()
    {
        // A name of its own per case, so a wrongly accepted one does not clash with the next.
        let mut body = json!({"name": format!("m{i}"), "backend": "sim-machine"});
        body[field] = value.clone();
        let r = s.post("/api/v1/machines", &body);
        assert_eq!(
            (r.status, r.body["code"].as_str()),
            (422, Some("invalid_field")),
            "{field} = {value}: {}",
            r.text
        );
        let msg = r.body["message"].as_str().unwrap_or("");
        assert!(msg.contains(field), "{field} = {value}: {msg}");
    }
    let machines = s.get("/api/v1/machines").expect(200);
    assert_eq!(machines, json!([]), "a refused machine was stored");
    // The maxima themselves are fine.
    let id = s.create_machine(&json!({"name": "m", "backend": "sim-machine",
                                      "max_jog_mm": 1000, "max_feed_mm_min": 100000}));
    let m = s.get(&format!("/api/v1/machines/{id}")).expect(200);
    assert_eq!(m["max_jog_mm"], 1000.0, "{m}");
    assert_eq!(m["max_feed_mm_min"], 100000.0, "{m}");
}

fn position(s: &Server, machine: i64) -> Value {
    s.status(machine)["machine_position"].clone()
}

#[test]
fn an_mdi_line_with_an_absurd_coordinate_is_refused_and_nothing_moves() {
    let s = Server::start();
    // No `travel`: only the server stands between the line and the motion.
    let m = s.sim("m", 1.0);
    let before = position(&s, m.id);
    let huge = format!("G0 X1{}", "0".repeat(30));
    for line in ["G0 X1e30", huge.as_str()] {
        let r = s.mdi(m.id, line);
        assert_eq!(r.status, 422, "MDI {line:?}: {}", r.text);
        let code = r.body["code"].as_str().unwrap_or("");
        assert!(
            matches!(code, "invalid_gcode" | "backend_rejected"),
            "MDI {line:?}: code {code:?}: {}",
            r.text
        );
        let msg = r.body["message"].as_str().unwrap_or("");
        assert!(
            msg.contains('X'),
            "MDI {line:?}: the message must name the axis: {msg}"
        );
        let st = s.status(m.id);
        assert_eq!(st["machine_position"], before, "MDI {line:?} moved: {st}");
        assert_eq!(st["state"], "idle", "MDI {line:?}: {st}");
    }
}

/// Soft limits X -10..300, Y -10..200, Z -100..0; machine at 0,0,0.
fn travel_machine(s: &Server) -> Sim {
    s.sim_with(
        "m",
        1.0,
        json!({"config": {
            "time_scale": 1.0,
            "execution_log": s.data_dir().join("exec-m.log"),
            "travel": {"x": [-10, 300], "y": [-10, 200], "z": [-100, 0]},
        }}),
    )
}

#[test]
fn jogs_mdi_lines_and_programs_past_travel_are_refused_before_any_motion() {
    let s = Server::start();
    let m = travel_machine(&s);
    let before = position(&s, m.id);
    let unmoved = |what: &str| {
        let st = s.status(m.id);
        assert_eq!(st["machine_position"], before, "{what} moved: {st}");
        assert_eq!(st["state"], "idle", "{what}: {st}");
        assert!(m.executed().is_empty(), "{what}: program lines ran");
    };

    for (axis, distance) in [("X", -20.0), ("Y", -11.0), ("Z", 1.0)] {
        let r = s.jog(m.id, axis, distance);
        assert_eq!(r.status, 422, "jog {axis} {distance}: {}", r.text);
        unmoved(&format!("jog {axis} {distance}"));
    }
    for line in ["G0 X400", "G1 Z5 F100", "G91 G0 Y-20"] {
        let r = s.mdi(m.id, line);
        assert_eq!(r.status, 422, "MDI {line:?}: {}", r.text);
        unmoved(&format!("MDI {line:?}"));
    }
    // The upload cannot know the machine's travel; the start must refuse it before line 1.
    let job = s.upload(m.id, "past", "G21 G90\nG0 X10 Y10\nG1 X400 F1000\n")["id"]
        .as_i64()
        .unwrap();
    let r = s.job_action(job, "start");
    assert_eq!(r.status, 422, "start of a program past travel: {}", r.text);
    unmoved("the program past travel");
}

#[test]
fn spindle_and_coolant_cannot_be_toggled_during_a_cutting_run_but_can_once_paused() {
    let s = Server::start();
    let m = s.sim("m", 1.0);
    // 100 ms a line, 30 s in all: running throughout the test.
    let (job, run) = s.upload_and_start(m.id, "cut", &back_and_forth(300, 1.0, 600.0));
    wait_for(T, "the run to execute a line", || {
        (m.count_of(run) >= 1).then_some(())
    });
    for output in ["spindle", "coolant"] {
        let msg = s
            .command(m.id, "toggle_output", json!({ "name": output }))
            .expect_error(409, "machine_busy");
        assert!(!msg.is_empty(), "{output}");
    }
    assert_eq!(s.job(job)["state"], "running");
    s.job_action(job, "pause").expect(200);
    for output in ["spindle", "coolant"] {
        let r = s.command(m.id, "toggle_output", json!({ "name": output }));
        assert_eq!(r.status, 200, "toggle {output} while paused: {}", r.text);
        assert_eq!(r.body["result"]["on"], true, "{output}: {}", r.text);
    }
    s.job_action(job, "cancel").expect(200);
}
