//! Start-up, machine listing, jogging, zeroing, work offsets and part zero over the REST API.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{Server, Sim};
use std::time::Duration;

const T: Duration = Duration::from_secs(30);

fn axis(v: &Value, a: &str) -> f64 {
    v[a].as_f64()
        .unwrap_or_else(|| panic!("no number {a} in {v}"))
}

#[track_caller]
fn assert_close(got: f64, want: f64, what: &str) {
    assert!(
        (got - want).abs() < 1e-9,
        "{what}: expected {want}, got {got}"
    );
}

#[test]
fn demo_server_starts_is_healthy_and_lists_the_demo_machine() {
    let s = Server::start_demo();
    let h = s.get("/healthz").expect(200);
    assert_eq!(h["status"], "ok");

    let machines = s.get("/api/v1/machines").expect(200);
    let list = machines.as_array().expect("machines is an array");
    assert_eq!(list.len(), 1, "{machines}");
    let demo = &list[0];
    assert!(demo["id"].as_i64().is_some(), "{demo}");
    assert_eq!(demo["name"], "demo");
    assert_eq!(demo["backend"], "sim-machine");
    let id = demo["id"].as_i64().unwrap();
    // The demo machine connects at start-up.
    let st = s.wait_machine_state(id, "idle", T);
    assert_eq!(st["active_offset"], "G54");
    assert!(st["job"].is_null(), "no job yet: {st}");
    // The plugin is reported loaded.
    let plugins = s.get("/api/v1/plugins").expect(200);
    assert!(
        plugins.to_string().contains("sim-machine"),
        "plugins: {plugins}"
    );
    // Unknown endpoints are JSON errors too.
    s.get("/api/v1/nope").expect_error(404, "not_found");

    // A restart with --demo again does not create a second demo machine.
    let mut s = s;
    s.restart_after_kill();
    let list = s.get("/api/v1/machines").expect(200);
    assert_eq!(list.as_array().unwrap().len(), 1, "{list}");
}

fn jog(s: &Server, m: &Sim, axis_name: &str, distance: f64) {
    let r = s
        .post(
            &format!("/api/v1/machines/{}/jog", m.id),
            &json!({"axis": axis_name, "distance": distance}),
        )
        .expect(200);
    assert_eq!(r["ok"], true);
}

/// `GET /status?until=STATE` answers once the machine is in that state (a jog's own answer
/// comes while it moves), 409 `wait_timeout` when it is not within `timeout_s`, and refuses a
/// state that does not exist.
#[test]
fn status_until_waits_for_the_state_and_says_when_it_did_not_come() {
    let s = Server::start();
    let m = s.sim("m", 1.0).id;
    s.jog(m, "X", 20.0).expect(200);
    let st = s
        .get(&format!("/api/v1/machines/{m}/status?until=idle"))
        .expect(200);
    assert_eq!(st["state"], "idle", "{st}");
    assert!(
        (st["machine_position"]["x"].as_f64().unwrap() - 20.0).abs() < 1e-9,
        "{st}"
    );
    let msg = s
        .get(&format!(
            "/api/v1/machines/{m}/status?until=running&timeout_s=0.2"
        ))
        .expect_error(409, "wait_timeout");
    assert!(msg.contains("still idle"), "{msg}");
    s.get(&format!("/api/v1/machines/{m}/status?until=sleeping"))
        .expect_error(400, "invalid_query");
    s.get(&format!(
        "/api/v1/machines/{m}/status?until=idle&timeout_s=600"
    ))
    .expect_error(400, "invalid_query");
}

/// A plain status poll is answered in front of the router (`status_polls`): its answer is the
/// route's to the byte, status, headers and body, as the router gives it for a poll with a query.
#[test]
fn a_plain_status_poll_answers_what_the_route_answers() {
    let s = Server::start();
    let m = s.sim("m", 1.0).id;
    s.jog(m, "X", 5.0).expect(200);
    s.get(&format!("/api/v1/machines/{m}/status?until=idle"))
        .expect(200);
    let fetch = |path: &str| {
        let r = s.req(reqwest::Method::GET, path).send().unwrap();
        let mut headers: Vec<(String, Vec<u8>)> = r
            .headers()
            .iter()
            .filter(|(name, _)| *name != "date")
            .map(|(name, value)| (name.to_string(), value.as_bytes().to_vec()))
            .collect();
        headers.sort();
        (r.status().as_u16(), headers, r.text().unwrap())
    };
    let polled = fetch(&format!("/api/v1/machines/{m}/status"));
    let routed = fetch(&format!(
        "/api/v1/machines/{m}/status?until=idle&timeout_s=0"
    ));
    assert_eq!(polled, routed);
    assert_eq!(polled.0, 200);
    let st: Value = fresa_tests::serde_json::from_str(&polled.2).unwrap();
    assert!(
        (axis(&st["machine_position"], "x") - 5.0).abs() < 1e-9,
        "{st}"
    );
    // A machine that does not exist is the router's 404, as before.
    s.get("/api/v1/machines/999/status")
        .expect_error(404, "unknown_machine");
}

/// A continuous jog moves while its keep-alives come and stops when they stop (the deadman
/// cancels it, as `jog/cancel` does); it is bounded by `max_jog_mm` and one at a time.
#[test]
fn a_continuous_jog_moves_while_kept_alive_and_stops_when_the_keep_alives_stop() {
    let s = Server::start();
    let m = s.sim_with("m", 1.0, json!({"max_jog_mm": 100.0})).id;
    let jog = format!("/api/v1/machines/{m}/jog");
    let keepalive = format!("/api/v1/machines/{m}/jog/keepalive");
    for bad in [
        json!({"axis": "X", "continuous": true}),
        json!({"axis": "X", "continuous": true, "direction": "up"}),
        json!({"axis": "X", "continuous": true, "direction": "+", "distance": 5}),
        json!({"axis": "X", "direction": "+", "distance": 5}),
    ] {
        s.post(&jog, &bad).expect_error(422, "invalid_field");
    }
    s.post_empty(&keepalive)
        .expect_error(409, "no_continuous_jog");

    // 600 mm/min = 10 mm/s: the whole 100 mm would take 10 s.
    let start = json!({"axis": "X", "direction": "+", "feed": 600, "continuous": true});
    s.post(&jog, &start).expect(200);
    s.post(&jog, &start).expect_error(409, "machine_busy");
    // The client holds the key for about a second: keep-alives every 100 ms (the cadence is
    // what is tested here, not a wait for something to happen).
    for _ in 0..10 {
        std::thread::sleep(Duration::from_millis(100));
        s.post_empty(&keepalive).expect(200);
    }
    // Then it lets go without a word.
    let st = s.wait_machine_state(m, "idle", T);
    let x = st["machine_position"]["x"].as_f64().unwrap();
    // About 1 s of motion plus at most the deadman's 250 ms: far from the 100 mm it may go.
    assert!(
        x > 5.0 && x < 50.0,
        "moved while held, stopped soon after: x = {x}"
    );
    s.post_empty(&keepalive)
        .expect_error(409, "no_continuous_jog");
    let events = s.events("types=machine.jog_cancel", Some(0));
    let cancel = events
        .until(T, "the deadman's cancel", |e| {
            e.event == "machine.jog_cancel"
        })
        .pop()
        .unwrap();
    assert!(
        cancel.data["actor"]
            .as_str()
            .unwrap()
            .starts_with("deadman:"),
        "{:?}",
        cancel.data
    );
    // Released: another continuous jog may start, and jog/cancel ends it at once.
    s.post(&jog, &start).expect(200);
    s.post_empty(&format!("/api/v1/machines/{m}/jog/cancel"))
        .expect(200);
    s.post_empty(&keepalive)
        .expect_error(409, "no_continuous_jog");
}

#[test]
fn jog_zero_offsets_and_part_zero() {
    let mut s = Server::start();
    let m = s.sim_with(
        "mill",
        0.0,
        json!({"max_jog_mm": 10.0, "max_feed_mm_min": 2000.0}),
    );
    let st = s.wait_machine_state(m.id, "idle", T);
    assert_close(axis(&st["work_position"], "x"), 0.0, "initial x");

    // Jogs are relative and asynchronous: wait for idle, then the position is exact.
    jog(&s, &m, "X", 5.5);
    jog(&s, &m, "Y", -2.25);
    jog(&s, &m, "X", 1.25);
    // The status may lag the jog requests: wait for idle at the expected place (a wrong
    // distance shows up as a timeout with the last status).
    let st = s.wait_status(
        m.id,
        Duration::from_secs(10),
        "idle at x 6.75, y -2.25",
        |st| {
            st["state"] == "idle"
                && (axis(&st["work_position"], "x") - 6.75).abs() < 1e-9
                && (axis(&st["work_position"], "y") + 2.25).abs() < 1e-9
        },
    );
    assert_close(axis(&st["work_position"], "x"), 6.75, "work x after jogs");
    assert_close(axis(&st["work_position"], "y"), -2.25, "work y after jogs");
    assert_close(
        axis(&st["machine_position"], "x"),
        6.75,
        "machine x after jogs",
    );

    // Jog limits: too far names the limit; too fast names the feed limit; bad axis is refused.
    let msg = s
        .post(
            &format!("/api/v1/machines/{}/jog", m.id),
            &json!({"axis": "X", "distance": 10.5}),
        )
        .expect_error(422, "jog_too_far");
    assert!(msg.contains("10") && msg.contains("10.5"), "{msg}");
    let msg = s
        .post(
            &format!("/api/v1/machines/{}/jog", m.id),
            &json!({"axis": "X", "distance": 1.0, "feed": 2500.0}),
        )
        .expect_error(422, "feed_out_of_range");
    assert!(msg.contains("2000"), "{msg}");
    let r = s.post(
        &format!("/api/v1/machines/{}/jog", m.id),
        &json!({"axis": "Q", "distance": 1.0}),
    );
    assert!((400..500).contains(&r.status), "bad axis: {r:?}");
    assert!(r.body["code"].is_string(), "{r:?}");
    s.post(
        &format!("/api/v1/machines/{}/jog", m.id),
        &json!({"axis": "X", "distance": 0.0}),
    )
    .expect_error(422, "invalid_field");
    // None of the refused jogs moved the machine.
    let st = s.status(m.id);
    assert_close(
        axis(&st["machine_position"], "x"),
        6.75,
        "x after refused jogs",
    );

    // Zero X: work X becomes 0, G54.x takes the machine position and is persisted.
    let r = s
        .post(
            &format!("/api/v1/machines/{}/commands", m.id),
            &json!({"command": "zero", "axis": "X"}),
        )
        .expect(200);
    assert_eq!(r["ok"], true, "{r}");
    let st = s.status(m.id);
    assert_close(axis(&st["work_position"], "x"), 0.0, "work x after zero");
    assert_close(
        axis(&st["work_position"], "y"),
        -2.25,
        "work y unchanged by zero X",
    );
    let machine_x = axis(&st["machine_position"], "x");
    assert_close(machine_x, 6.75, "machine x after zero");
    let off = s
        .get(&format!("/api/v1/machines/{}/offsets", m.id))
        .expect(200);
    assert_eq!(off["active"], "G54");
    assert_close(axis(&off["offsets"]["G54"], "x"), machine_x, "G54.x");
    assert_close(axis(&off["offsets"]["G54"], "y"), 0.0, "G54.y");

    // Set and read G55; selecting it changes the work position accordingly.
    let r = s
        .put(
            &format!("/api/v1/machines/{}/offsets/G55", m.id),
            &json!({"x": 1.5, "z": -3.0}),
        )
        .expect(200);
    assert_eq!(r["offset"], "G55", "{r}");
    let off = s
        .get(&format!("/api/v1/machines/{}/offsets", m.id))
        .expect(200);
    assert_close(axis(&off["offsets"]["G55"], "x"), 1.5, "G55.x");
    assert_close(axis(&off["offsets"]["G55"], "y"), 0.0, "G55.y");
    assert_close(axis(&off["offsets"]["G55"], "z"), -3.0, "G55.z");
    assert_eq!(off["active"], "G54", "setting G55 does not select it");
    s.put(
        &format!("/api/v1/machines/{}/offsets/G60", m.id),
        &json!({"x": 1.0}),
    )
    .expect_error(404, "unknown_offset");
    s.post(
        &format!("/api/v1/machines/{}/commands", m.id),
        &json!({"command": "select_offset", "offset": "G55"}),
    )
    .expect(200);
    let st = s.status(m.id);
    assert_eq!(st["active_offset"], "G55", "{st}");
    assert_close(axis(&st["work_position"], "x"), 6.75 - 1.5, "work x in G55");
    assert_close(axis(&st["work_position"], "z"), 3.0, "work z in G55");
    let off = s
        .get(&format!("/api/v1/machines/{}/offsets", m.id))
        .expect(200);
    assert_eq!(off["active"], "G55");

    // Unknown commands are refused with the list of commands.
    let msg = s
        .post(
            &format!("/api/v1/machines/{}/commands", m.id),
            &json!({"command": "self_destruct"}),
        )
        .expect_error(422, "invalid_command");
    assert!(
        msg.contains("self_destruct") || msg.contains("cycle_start"),
        "{msg}"
    );

    // Part zero: explicit source and note, then an empty body (current position, source api).
    let row = s
        .post(
            &format!("/api/v1/machines/{}/part-zero", m.id),
            &json!({"source": "probe", "note": "left front corner"}),
        )
        .expect(201);
    assert_eq!(row["source"], "probe", "{row}");
    assert_eq!(row["actor"], "local", "{row}");
    assert_eq!(row["note"], "left front corner");
    assert_close(axis(&row, "x"), 6.75, "part zero x = machine x");
    assert_close(axis(&row, "y"), -2.25, "part zero y = machine y");
    let row2 = s
        .post_empty(&format!("/api/v1/machines/{}/part-zero", m.id))
        .expect(201);
    assert_eq!(row2["source"], "api", "{row2}");
    let row3 = s
        .post(
            &format!("/api/v1/machines/{}/part-zero", m.id),
            &json!({"position": {"x": 1.0, "y": 2.0, "z": 3.0, "a": 0.0}, "source": "manual"}),
        )
        .expect(201);
    assert_close(axis(&row3, "z"), 3.0, "explicit part zero z");
    let hist = s
        .get(&format!("/api/v1/machines/{}/part-zero", m.id))
        .expect(200);
    let hist = hist.as_array().expect("history array").clone();
    assert_eq!(hist.len(), 3, "{hist:?}");
    let mut sources: Vec<&str> = hist.iter().map(|r| r["source"].as_str().unwrap()).collect();
    sources.sort();
    assert_eq!(sources, ["api", "manual", "probe"]);
    assert!(hist.iter().all(|r| r["actor"] == "local"), "{hist:?}");
    s.post(
        &format!("/api/v1/machines/{}/part-zero", m.id),
        &json!({"bogus": 1}),
    )
    .expect_error(400, "invalid_json");

    // Offsets and the active offset survive a restart (the backend is re-seeded from the store).
    s.restart_after_kill();
    let off = s
        .get(&format!("/api/v1/machines/{}/offsets", m.id))
        .expect(200);
    assert_eq!(off["active"], "G55", "{off}");
    assert_close(
        axis(&off["offsets"]["G54"], "x"),
        6.75,
        "G54.x after restart",
    );
    assert_close(
        axis(&off["offsets"]["G55"], "z"),
        -3.0,
        "G55.z after restart",
    );
    let st = s.wait_machine_state(m.id, "idle", T);
    assert_eq!(st["active_offset"], "G55", "{st}");
    assert_close(
        axis(&st["work_position"], "x"),
        axis(&st["machine_position"], "x") - 1.5,
        "work x = machine x - G55.x after restart",
    );
    let hist = s
        .get(&format!("/api/v1/machines/{}/part-zero", m.id))
        .expect(200);
    assert_eq!(hist.as_array().unwrap().len(), 3);
}

#[test]
fn machine_names_are_unique_and_unknown_machines_are_404() {
    let s = Server::start();
    let m = s.sim("a", 0.0);
    let msg = s
        .post(
            "/api/v1/machines",
            &json!({"name": "a", "backend": "sim-machine", "config": {"time_scale": 0.0}}),
        )
        .expect_error(409, "name_taken");
    assert!(msg.contains("\"a\""), "{msg}");
    let one = s.get(&format!("/api/v1/machines/{}", m.id)).expect(200);
    assert_eq!(one["name"], "a");
    let missing = m.id + 100;
    for path in [
        format!("/api/v1/machines/{missing}"),
        format!("/api/v1/machines/{missing}/status"),
        format!("/api/v1/machines/{missing}/offsets"),
        format!("/api/v1/machines/{missing}/part-zero"),
    ] {
        let msg = s.get(&path).expect_error(404, "unknown_machine");
        assert!(msg.contains(&missing.to_string()), "{path}: {msg}");
    }
    s.post(
        &format!("/api/v1/machines/{missing}/jog"),
        &json!({"axis": "X", "distance": 1.0}),
    )
    .expect_error(404, "unknown_machine");
    s.get("/api/v1/machines/abc")
        .expect_error(400, "invalid_path");
}

#[test]
fn metrics_report_machine_states_and_job_runs_in_prometheus_text() {
    let s = Server::start_demo();
    let id = s.get("/api/v1/machines").expect(200)[0]["id"]
        .as_i64()
        .unwrap();
    s.wait_machine_state(id, "idle", T);
    let r = s.get("/metrics");
    assert_eq!(r.status, 200);
    let text = r.text;
    assert!(
        text.contains(&format!(
            "fresa_machine_state{{machine=\"{id}\",name=\"demo\",state=\"idle\"}} 1"
        )),
        "{text}"
    );
    // Every workspace plugin is loaded (their number grows as backends are added).
    let loaded = s.get("/api/v1/plugins").expect(200)["plugins"]
        .as_array()
        .unwrap()
        .len();
    assert!(loaded >= 1);
    assert!(
        text.contains(&format!("fresa_plugins_loaded {loaded}\n")),
        "{text}"
    );
    assert!(text.contains("fresa_plugin_load_failures 0"), "{text}");
    assert!(text.contains("# TYPE fresa_job_runs gauge"), "{text}");
}

/// Machine X positions and states read across `span` (several polls).
fn positions_across(s: &Server, m: i64, span: Duration) -> Vec<(f64, String)> {
    let end = std::time::Instant::now() + span;
    let mut seen = Vec::new();
    loop {
        let st = s.status(m);
        seen.push((
            axis(&st["machine_position"], "x"),
            st["state"].as_str().unwrap_or("").to_string(),
        ));
        if std::time::Instant::now() >= end {
            return seen;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn jog_cancel_stops_the_jog_under_way_and_drops_the_queued_taps() {
    let s = Server::start();
    // Real time: each 10 mm tap at 600 mm/min takes a second.
    let m = s.sim("mill", 1.0);
    s.wait_machine_state(m.id, "idle", T);
    for _ in 0..3 {
        s.post(
            &format!("/api/v1/machines/{}/jog", m.id),
            &json!({"axis": "X", "distance": 10.0, "feed": 600.0}),
        )
        .expect(200);
    }
    let r = s
        .post_empty(&format!("/api/v1/machines/{}/jog/cancel", m.id))
        .expect(200);
    assert_eq!(r["ok"], true, "{r}");
    assert_eq!(r["stopped"], true, "a jog was under way: {r}");
    // Answered once motion stopped: the next status is already still.
    let st = s.status(m.id);
    assert_eq!(st["state"], "idle", "{st}");
    let x = axis(&st["machine_position"], "x");
    assert!(x < 30.0, "three taps would be 30 mm; x = {x}");
    let seen = positions_across(&s, m.id, Duration::from_secs(2));
    assert!(
        seen.iter()
            .all(|(sx, state)| (sx - x).abs() < 1e-9 && state == "idle"),
        "a queued tap moved the machine after jog/cancel (x was {x}): {seen:?}"
    );
    // Recorded, under the caller's name.
    let events = s.events("types=machine.jog_cancel", Some(0));
    let e = events
        .until(T, "the jog cancel event", |e| {
            e.event == "machine.jog_cancel"
        })
        .pop()
        .unwrap();
    assert_eq!(e.data["actor"], "local", "{e:?}");
    assert_eq!(e.data["machine"], m.id, "{e:?}");
    // Nothing to cancel: still 200, and it says so.
    let r = s
        .post_empty(&format!("/api/v1/machines/{}/jog/cancel", m.id))
        .expect(200);
    assert_eq!(r["stopped"], false, "{r}");
    s.post_empty("/api/v1/machines/999/jog/cancel")
        .expect_error(404, "unknown_machine");
    // The CLI's verb for it.
    let out = s.cli(&["machine", "jog-cancel", &m.id.to_string()]);
    let text = fresa_tests::output_text(&out);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("queued jogs dropped"), "{text}");
}

#[test]
fn part_zero_zeroing_and_offsets_are_refused_while_the_machine_moves() {
    let s = Server::start();
    let m = s.sim("mill", 1.0);
    s.wait_machine_state(m.id, "idle", T);
    // 50 mm at 100 mm/min: half a minute of motion, ample for the refusals below.
    s.post(
        &format!("/api/v1/machines/{}/jog", m.id),
        &json!({"axis": "X", "distance": 50.0, "feed": 100.0}),
    )
    .expect(200);
    let base = format!("/api/v1/machines/{}", m.id);
    let mut refusals = vec![
        s.post_empty(&format!("{base}/part-zero")),
        s.post(
            &format!("{base}/part-zero"),
            &json!({"position": {"x": 1.0, "y": 2.0, "z": 3.0, "a": 0.0}}),
        ),
        s.command(m.id, "zero", json!({"axis": "X"})),
        s.command(m.id, "zero", json!({})),
        s.command(m.id, "select_offset", json!({"offset": "G55"})),
    ];
    refusals.push(s.put(&format!("{base}/offsets/G55"), &json!({"x": 1.0})));
    let still_moving = s.status(m.id)["state"] == "jogging";
    for r in refusals {
        let msg = r.expect_error(409, "machine_moving");
        assert!(msg.contains("jogging"), "{msg}");
    }
    assert!(
        still_moving,
        "the jog ended before the refusals were checked"
    );
    s.post_empty(&format!("{base}/jog/cancel")).expect(200);

    // Nothing was recorded: no part zero, offsets as they were, no audit event for either.
    let hist = s.get(&format!("{base}/part-zero")).expect(200);
    assert_eq!(hist.as_array().unwrap().len(), 0, "{hist}");
    let off = s.get(&format!("{base}/offsets")).expect(200);
    assert_eq!(off["active"], "G54", "{off}");
    assert_close(axis(&off["offsets"]["G54"], "x"), 0.0, "G54.x");
    let g55x = off["offsets"]["G55"]["x"].as_f64().unwrap_or(0.0);
    assert_close(g55x, 0.0, "G55.x");
    let seen = s
        .events("", Some(0))
        .until(T, "the jog cancel", |e| e.event == "machine.jog_cancel");
    let recorded: Vec<&str> = seen
        .iter()
        .filter(|e| {
            matches!(
                e.event.as_str(),
                "machine.part_zero" | "machine.offsets" | "machine.command"
            )
        })
        .map(|e| e.event.as_str())
        .collect();
    assert!(recorded.is_empty(), "recorded while moving: {recorded:?}");

    // Standing still, the same requests are carried out.
    let row = s.post_empty(&format!("{base}/part-zero")).expect(201);
    assert!(row["x"].as_f64().unwrap() > 0.0, "{row}");
    s.command(m.id, "zero", json!({"axis": "X"})).expect(200);
}

/// Issue 27: a zero's `machine.offsets` event (the offsets the backend computed) comes after
/// its `machine.command` and names the same actor, as the command did it.
#[test]
fn a_zeros_offsets_event_follows_its_command_and_names_who() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    s.wait_machine_state(m.id, "idle", T);
    s.command(m.id, "zero", json!({"axis": "X"})).expect(200);
    let seen = s
        .events("types=machine.command,machine.offsets", Some(0))
        .until(T, "the zero's offsets event", |e| {
            e.event == "machine.offsets"
        });
    let offsets = seen.last().unwrap();
    let command = seen
        .iter()
        .position(|e| e.event == "machine.command" && e.data["data"]["command"] == "zero")
        .unwrap_or_else(|| panic!("no zero command before its offsets: {seen:?}"));
    assert_eq!(command + 1, seen.len() - 1, "{seen:?}");
    assert_eq!(offsets.data["actor"], "local", "{:?}", offsets.data);
    assert_eq!(offsets.data["actor"], seen[command].data["actor"]);
    assert!(offsets.id > seen[command].id);
}
