//! Machine I/O end to end on the sim machine: a limit switch pressed by moving onto it shows
//! live as `machine.io`, in the status, the CLI and `/metrics`; the alarm names the input (also
//! in the audit log) and motion stops at the switch.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::json;
use fresa_tests::Server;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

#[test]
fn a_limit_switch_trips_shows_everywhere_and_the_axis_jogs_off_it() {
    let s = Server::start();
    let events = s.events("types=machine", None);
    let m = s.create_machine(&json!({
        "name": "switched", "backend": "sim-machine", "max_jog_mm": 50.0,
        "config": {"time_scale": 0.05, "switches": {
            "limit_x_max": {"axis": "x", "at_or_above": 5},
            "probe": {"axis": "z", "at_or_below": -20}}}
    }));
    let st = s.wait_machine_state(m, "idle", T);
    assert_eq!(
        st["inputs"],
        json!({"limit_x_max": false, "probe": false}),
        "supported inputs only, all known: {st}"
    );
    assert_eq!(
        st["outputs"],
        json!({"spindle": false, "coolant_flood": false})
    );

    s.jog(m, "X", 10.0).expect(200);
    // The state change can be published a moment before the status that carries its reason.
    let st = s.wait_status(m, T, "alarm with its reason", |st| {
        st["state"] == "alarm" && st["alarm"].is_string()
    });
    assert_eq!(st["inputs"]["limit_x_max"], true, "{st}");
    assert!(
        st["alarm"].as_str().unwrap().contains("limit_x_max"),
        "the alarm names the input: {st}"
    );
    let x = st["machine_position"]["x"].as_f64().unwrap();
    assert!(
        (5.0..10.0).contains(&x),
        "motion stopped at the switch: x={x}"
    );

    // Live: machine.io with the change (the rate-limited status stream could miss it).
    let seen = events.until(T, "machine.io limit_x_max on", |e| {
        e.event == "machine.io" && e.data["data"]["changed"]["limit_x_max"] == true
    });
    let io = &seen.last().unwrap().data;
    assert_eq!(io["machine"], m);
    assert_eq!(io["data"]["inputs"]["limit_x_max"], true, "{io}");
    assert!(io.get("id").is_none(), "machine.io is live only: {io}");
    // The audit log keeps the alarm with the input's name.
    let audit = s.events("types=machine.alarm", Some(0));
    let alarm = audit.until(T, "persisted alarm", |e| e.event == "machine.alarm");
    assert_eq!(alarm.last().unwrap().data["data"]["input"], "limit_x_max");

    // Where people look: the CLI and the metrics.
    let out = s.cli(&["machine", "status", &m.to_string()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("state:    alarm"), "{text}");
    assert!(text.contains("limit_x_max ON"), "{text}");
    assert!(text.contains("probe off"), "{text}");
    assert!(text.contains("coolant_flood off"), "{text}");
    let metrics = s.get("/metrics").text;
    assert!(
        metrics.contains(&format!(
            "fresa_machine_input{{machine=\"{m}\",io=\"limit_x_max\"}} 1"
        )),
        "{metrics}"
    );

    // Reset, then jog off the switch: it does not trip again on the way, and the lamp goes out.
    s.command(m, "reset", json!({})).expect(200);
    s.jog(m, "X", -2.0).expect(200);
    let st = s.wait_status(m, T, "off the switch", |st| {
        st["state"] == "idle" && st["inputs"]["limit_x_max"] == false
    });
    assert_eq!(st["alarm"], json!(null), "{st}");
    events.until(T, "machine.io limit_x_max off", |e| {
        e.event == "machine.io" && e.data["data"]["changed"]["limit_x_max"] == false
    });

    // An output switched shows at once, with its own machine.io.
    s.command(m, "toggle_output", json!({"name": "spindle"}))
        .expect(200);
    assert_eq!(s.status(m)["outputs"]["spindle"], true);
    events.until(T, "machine.io spindle on", |e| {
        e.event == "machine.io" && e.data["data"]["changed"]["spindle"] == true
    });
}
