//! Probing and touch-off over the REST API, on sim machines whose `probe` switch sits at a known
//! height: the offset a touch-off sets, what a probe that never touches leaves, what is refused
//! before anything moves, and that STOP or a vanished client ends a probe.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::Server;
use std::io::Write as _;
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

const T: Duration = Duration::from_secs(30);

/// A sim machine whose probe closes at machine Z <= `probe_at`, Z travel -100..0.
fn probing_sim(s: &Server, name: &str, time_scale: f64, probe_at: f64) -> i64 {
    s.create_machine(&json!({
        "name": name,
        "backend": "sim-machine",
        "max_jog_mm": 60.0,
        "max_probe_feed_mm_min": 1500.0,
        "config": {
            "time_scale": time_scale,
            "travel": {"z": [-100, 0]},
            "switches": {"probe": {"axis": "z", "at_or_below": probe_at}},
        },
    }))
}

/// The first recorded event of type `ty` (replayed from the start of the log).
fn first_event(s: &Server, ty: &str) -> fresa_tests::SseEvent {
    let events = s.events(&format!("types={ty}"), Some(0));
    let mut seen = events.until(T, ty, |e| e.event == ty);
    seen.pop().unwrap()
}

fn z(v: &Value) -> f64 {
    v["z"]
        .as_f64()
        .unwrap_or_else(|| panic!("no number z in {v}"))
}

fn g54(s: &Server, m: i64) -> Value {
    let offsets = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    let g54 = offsets["offsets"]["G54"].clone();
    assert!(g54.is_object(), "no G54 in {offsets}");
    g54
}

/// The Z touch-off of the pendant's design (a 15 mm plate): the probe closes at machine Z -20,
/// so G54's Z becomes -35 and the tool tip reads Z 15 where it touched. The trip is latched at
/// the switch (exact); the tool rests past it by the stopping distance (the overshoot, at most
/// a few 5 ms slices at 1200 mm/min) and then retracts 5 mm, so the work Z reads
/// 15 + 5 - overshoot. The answer, the stored offset, the status and the audit log agree.
#[test]
fn a_z_touch_off_sets_the_offset_so_z_reads_the_plate_and_retracts() {
    let s = Server::start();
    let m = probing_sim(&s, "router", 1.0, -20.0);
    s.wait_machine_state(m, "idle", T);
    let before = g54(&s, m);
    let r = s
        .post(
            &format!("/api/v1/machines/{m}/touch-off"),
            &json!({"axis": "Z", "plate_mm": 15, "distance": 50, "feed": 1200, "retract_mm": 5}),
        )
        .expect(200);
    assert!(
        (z(&r["trip"]) + 20.0).abs() < 1e-9,
        "trip at the switch: {r}"
    );
    let overshoot = r["overshoot_mm"].as_f64().unwrap();
    assert!(
        (0.0..2.0).contains(&overshoot),
        "stopped soon after the trip: {r}"
    );
    assert!(
        (z(&r["after"]) + 35.0).abs() < 1e-9,
        "G54 Z = -20 - 15: {r}"
    );
    assert_eq!(z(&r["before"]), 0.0, "{r}");
    assert_eq!(r["offset"], "G54");
    assert!(
        (z(&r["work_position"]) - (20.0 - overshoot)).abs() < 1e-6,
        "retracted 5 mm above the trip's 15: {r}"
    );
    // The answer came once the retract ended.
    let st = s.status(m);
    assert_eq!(st["state"], "idle", "{st}");
    assert!(
        (z(&st["work_position"]) - z(&r["work_position"])).abs() < 1e-9,
        "{st}"
    );
    assert_eq!(st["inputs"]["probe"], false, "off the plate again: {st}");
    // Stored (the offsets the server keeps), X and Y untouched.
    let now = g54(&s, m);
    assert!((now["z"].as_f64().unwrap() + 35.0).abs() < 1e-9, "{now}");
    assert_eq!(now["x"], before["x"]);
    assert_eq!(now["y"], before["y"]);
    // Audited with the offset before and after, and the probe that found it.
    let events = s.events("types=machine.touch_off,machine.probe", Some(0));
    let seen = events.until(T, "the touch-off's audit event", |e| {
        e.event == "machine.touch_off"
    });
    let probe = seen.iter().find(|e| e.event == "machine.probe").unwrap();
    assert_eq!(probe.data["data"]["axis"], "Z", "{:?}", probe.data);
    assert_eq!(probe.data["data"]["distance"], -50.0, "{:?}", probe.data);
    let touch = seen.last().unwrap();
    assert_eq!(touch.data["data"]["plate_mm"], 15.0, "{:?}", touch.data);
    assert!((z(&touch.data["data"]["after"]) + 35.0).abs() < 1e-9);
    assert_eq!(z(&touch.data["data"]["before"]), 0.0);
    assert!(touch.data["actor"].is_string(), "{:?}", touch.data);
}

/// A probe that runs its whole distance without touching changes no offset and says so; the
/// scripting endpoint answers `not_tripped` with where it stopped. Everything that cannot be
/// probed is refused before anything moves, naming why.
#[test]
fn a_probe_that_never_touches_changes_nothing_and_refusals_name_the_reason() {
    let s = Server::start();
    let m = probing_sim(&s, "far", 0.0, -80.0);
    s.wait_machine_state(m, "idle", T);
    let touch = format!("/api/v1/machines/{m}/touch-off");
    let msg = s
        .post(
            &touch,
            &json!({"axis": "Z", "plate_mm": 15, "distance": 30, "feed": 600}),
        )
        .expect_error(422, "probe_not_tripped");
    assert!(msg.contains("30 mm"), "{msg}");
    assert_eq!(z(&g54(&s, m)), 0.0, "no offset changed");
    let st = s.wait_machine_state(m, "idle", T);
    assert!((z(&st["machine_position"]) + 30.0).abs() < 1e-9, "{st}");

    let probe = format!("/api/v1/machines/{m}/probe");
    let r = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "-", "distance": 10, "feed": 600}),
        )
        .expect(200);
    assert_eq!(r["outcome"], "not_tripped", "{r}");
    assert!(r["trip"].is_null(), "{r}");
    assert!((z(&r["position"]) + 40.0).abs() < 1e-9, "{r}");
    // And now down onto it: the probe closes at -80.
    let r = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "-", "distance": 50, "feed": 600}),
        )
        .expect(200);
    assert_eq!(r["outcome"], "tripped", "{r}");
    assert!((z(&r["trip"]) + 80.0).abs() < 1e-9, "{r}");

    // Refused: already touching (the probe is closed here), and contact sought again.
    let msg = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "-", "distance": 5, "feed": 600}),
        )
        .expect_error(409, "probe_already_in_state");
    assert!(msg.contains("in contact"), "{msg}");
    // Looking for the release instead is allowed: up off the plate.
    let r = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "+", "distance": 5, "feed": 600, "until": "release"}),
        )
        .expect(200);
    assert_eq!(r["outcome"], "tripped", "{r}");
    for (body, status, code) in [
        // Beyond the machine's own limits, before the backend sees it.
        (
            json!({"axis": "Z", "toward": "-", "distance": 61, "feed": 600}),
            422,
            "probe_too_far",
        ),
        (
            json!({"axis": "Z", "toward": "-", "distance": 5, "feed": 1600}),
            422,
            "feed_out_of_range",
        ),
        (
            json!({"axis": "Z", "toward": "-", "distance": 0, "feed": 600}),
            422,
            "invalid_field",
        ),
        (
            json!({"axis": "Z", "toward": "down", "distance": 5, "feed": 600}),
            422,
            "invalid_field",
        ),
        // The whole distance must be inside the travel (Z stops at -100).
        (
            json!({"axis": "Z", "toward": "-", "distance": 30, "feed": 600}),
            422,
            "out_of_travel",
        ),
    ] {
        s.post(&probe, &body).expect_error(status, code);
    }
    // An edge touch-off needs its direction and the tool's diameter; A is no edge.
    for (body, code, needle) in [
        (
            json!({"axis": "X", "plate_mm": 0, "distance": 5, "feed": 600, "tool_diameter_mm": 6}),
            "invalid_field",
            "toward",
        ),
        (
            json!({"axis": "Y", "toward": "+", "plate_mm": 0, "distance": 5, "feed": 600}),
            "invalid_field",
            "tool_diameter_mm",
        ),
        (
            json!({"axis": "A", "toward": "+", "plate_mm": 0, "distance": 5, "feed": 600}),
            "probe_unsupported",
            "rotary",
        ),
    ] {
        let msg = s.post(&touch, &body).expect_error(422, code);
        assert!(msg.contains(needle), "{body}: {msg}");
    }
    s.post(
        &touch,
        &json!({"axis": "Z", "plate_mm": 150, "distance": 5, "feed": 600}),
    )
    .expect_error(422, "invalid_field");
    // A machine with no probe input cannot probe at all.
    let plain = s.sim("plain", 0.0).id;
    s.wait_machine_state(plain, "idle", T);
    let msg = s
        .post(
            &format!("/api/v1/machines/{plain}/probe"),
            &json!({"axis": "Z", "toward": "-", "distance": 5, "feed": 100}),
        )
        .expect_error(422, "probe_unsupported");
    assert!(msg.contains("no probe input"), "{msg}");
}

/// STOP during a probe ends it: the probe's own answer says `stopped` (only once motion
/// ended), no offset changes, and the machine rests where it stopped, far from the end.
#[test]
fn stop_during_a_touch_off_stops_it_and_changes_nothing() {
    let s = std::sync::Arc::new(Server::start());
    let m = probing_sim(&s, "stopped", 1.0, -95.0);
    s.wait_machine_state(m, "idle", T);
    let prober = {
        let s = s.clone();
        std::thread::spawn(move || {
            s.post(
                &format!("/api/v1/machines/{m}/touch-off"),
                &json!({"axis": "Z", "plate_mm": 10, "distance": 50, "feed": 300}),
            )
        })
    };
    s.wait_status(m, T, "probing down", |st| {
        st["state"] == "jogging" && z(&st["machine_position"]) < -0.5
    });
    s.command(m, "stop", json!({})).expect(200);
    let msg = prober.join().unwrap().expect_error(409, "stopped");
    assert!(msg.contains("stopped"), "{msg}");
    let st = s.status(m);
    assert_eq!(st["state"], "idle", "{st}");
    let at = z(&st["machine_position"]);
    assert!(at > -40.0, "stopped well before the 50 mm end: {st}");
    assert_eq!(z(&g54(&s, m)), 0.0, "no offset changed");
}

/// A client that sends a touch-off and goes away while the machine probes for it: the server
/// stops the probe (recorded as a jog cancel by `lost:<actor>`), as it stops a lost pendant's
/// motion.
#[test]
fn a_probe_whose_client_goes_away_is_stopped() {
    let s = Server::start();
    let m = probing_sim(&s, "lost", 1.0, -95.0);
    s.wait_machine_state(m, "idle", T);
    let port: u16 = s.base.rsplit(':').next().unwrap().parse().unwrap();
    let mut c = TcpStream::connect_timeout(&SocketAddr::from(([127, 0, 0, 1], port)), T).unwrap();
    let body = json!({"axis": "Z", "toward": "-", "distance": 50, "feed": 300}).to_string();
    write!(
        c,
        "POST /api/v1/machines/{m}/probe HTTP/1.1\r\nhost: 127.0.0.1\r\n\
         content-type: application/json\r\ncontent-length: {}\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    s.wait_status(m, T, "probing down", |st| {
        st["state"] == "jogging" && z(&st["machine_position"]) < -0.5
    });
    drop(c);
    let st = s.wait_machine_state(m, "idle", T);
    assert!(
        z(&st["machine_position"]) > -40.0,
        "stopped soon after the client left, not at the 50 mm end: {st}"
    );
    let cancel = first_event(&s, "machine.jog_cancel");
    assert!(
        cancel.data["actor"]
            .as_str()
            .is_some_and(|a| a.starts_with("lost:")),
        "{:?}",
        cancel.data
    );
}

/// Several clients probe one machine at once: exactly one probe moves, the others are refused
/// as busy before anything moves for them; while it probes a jog is refused too, and the one
/// that ran sets the only offset.
#[test]
fn concurrent_probes_one_moves_the_rest_are_refused() {
    let s = std::sync::Arc::new(Server::start());
    let m = probing_sim(&s, "crowded", 1.0, -10.0);
    s.wait_machine_state(m, "idle", T);
    let start = std::sync::Arc::new(std::sync::Barrier::new(4));
    let clients: Vec<_> = (0..4)
        .map(|_| {
            let (s, start) = (s.clone(), start.clone());
            std::thread::spawn(move || {
                start.wait();
                s.post(
                    &format!("/api/v1/machines/{m}/touch-off"),
                    &json!({"axis": "Z", "plate_mm": 5, "distance": 20, "feed": 600}),
                )
            })
        })
        .collect();
    // While one probes, a jog is refused (the machine is taken).
    s.wait_status(m, T, "probing down", |st| st["state"] == "jogging");
    let jog = s.jog(m, "X", 1.0);
    assert_eq!(jog.status, 409, "a jog during a probe: {}", jog.text);
    let answers: Vec<_> = clients.into_iter().map(|c| c.join().unwrap()).collect();
    let ok: Vec<_> = answers.iter().filter(|a| a.status == 200).collect();
    assert_eq!(
        ok.len(),
        1,
        "exactly one probe ran: {:?}",
        answers.iter().map(|a| &a.text).collect::<Vec<_>>()
    );
    for a in answers.iter().filter(|a| a.status != 200) {
        assert_eq!(a.status, 409, "{}", a.text);
        assert!(
            a.text.contains("busy") || a.text.contains("probes"),
            "{}",
            a.text
        );
    }
    assert!(
        (z(&ok[0].body["after"]) + 15.0).abs() < 1e-9,
        "{}",
        ok[0].text
    );
    assert!((z(&g54(&s, m)) + 15.0).abs() < 1e-9);
    // One probe was asked of the machine (the refused ones never reached its queue as motion).
    let events = s.events("types=machine.probe,machine.touch_off", Some(0));
    let seen = events.until(T, "the touch-off", |e| e.event == "machine.touch_off");
    assert_eq!(
        seen.iter().filter(|e| e.event == "machine.probe").count(),
        1,
        "{:?}",
        seen.iter().map(|e| &e.data).collect::<Vec<_>>()
    );
}

/// A sim machine with an execution log whose probe closes at machine Z <= `probe_at`.
fn logged_probing_sim(s: &Server, name: &str, probe_at: f64) -> fresa_tests::Sim {
    let log = s.data_dir().join(format!("exec-{name}.log"));
    let id = s.create_machine(&json!({
        "name": name,
        "backend": "sim-machine",
        "config": {
            "time_scale": 0,
            "execution_log": s.host_path(&log),
            "switches": {"probe": {"axis": "z", "at_or_below": probe_at}},
        },
    }));
    s.wait_machine_state(id, "idle", T);
    fresa_tests::Sim { id, log }
}

/// A program that probes runs with the real trip fed back: the moves after a G38.2 follow
/// #5063 where the sim's probe switch really closed (not the stand-alone assumption the upload
/// analysis makes), every line runs once, and a G38.2 that never touches fails the run naming
/// its line. A machine without a probe input refuses such a program before anything moves.
#[test]
fn a_program_that_probes_uses_where_the_probe_really_tripped() {
    let s = Server::start();
    let m = logged_probing_sim(&s, "prober", -20.0);
    let program =
        "G21 G90\nG38.2 Z-50 F300\nG0 Z[#5063 + 5]\nG38.2 Z-50\nG0 Z[#5063 + 10] X[#5070]\nM2\n";
    let up = s.upload(m.id, "probe-twice.ngc", program);
    assert_eq!(up["analysis"]["probe_moves"], 2, "{up}");
    assert_eq!(up["analysis"]["first_probe_line"], 2, "{up}");
    // Lines 3 and 5 move to where the probes tripped; the second probe's own target does not
    // depend on the first's result.
    assert_eq!(up["analysis"]["probe_dependent_moves"], 2, "{up}");
    assert_eq!(up["analysis"]["first_probe_dependent_line"], 3, "{up}");
    assert_eq!(
        up["analysis"]["probe_paths_unchecked_from"],
        Value::Null,
        "{up}"
    );
    let job = up["id"].as_i64().unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    s.wait_job_state(job, "completed", T);
    let st = s.wait_machine_state(m.id, "idle", T);
    // Trip at -20 both times: Z -20 + 10, and X = #5070 = 1 (it tripped).
    assert!((z(&st["machine_position"]) + 10.0).abs() < 1e-9, "{st}");
    assert_eq!(st["machine_position"]["x"], 1.0, "{st}");
    fresa_tests::assert_every_line_once(&m.executed(), run, 6);

    // Never touching: the run fails at the probe's line, saying so.
    let far = logged_probing_sim(&s, "far-prober", -80.0);
    let job = s.upload(far.id, "miss.ngc", "G38.2 Z-30 F600\nG0 Z0\nM2\n")["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    let j = s.wait_job(job, T, "failed", |j| j["state"] == "failed");
    let msg = j["run"]["message"].as_str().unwrap_or_default();
    assert!(
        msg.contains("line 1") && msg.contains("without the probe touching"),
        "{j}"
    );
    let st = s.wait_machine_state(far.id, "idle", T);
    assert!(
        (z(&st["machine_position"]) + 30.0).abs() < 1e-9,
        "line 2 never ran: {st}"
    );

    // No probe input: refused at start, nothing moved.
    let plain = s.sim("plain", 0.0);
    let job = s.upload(plain.id, "probe.ngc", "G0 Z5\nG38.2 Z-5 F100\nM2\n")["id"]
        .as_i64()
        .unwrap();
    let msg = s
        .job_action(job, "start")
        .expect_error(422, "backend_rejected");
    assert!(
        msg.contains("line 2") && msg.contains("no probe input"),
        "{msg}"
    );
    assert!(plain.executed().is_empty());
    assert_eq!(z(&s.status(plain.id)["machine_position"]), 0.0);
}

/// A Mach3-dialect autoleveller (probe points with G31, each trip kept from #2002, then the
/// cut follows them) runs on a sim machine with the real trips: the plate's top at machine
/// Z -3 gives #2002 = -3 at both points, so the cut ends 1 mm above it, and X follows #2000.
#[test]
fn a_mach3_autoleveller_with_g31_runs_on_the_real_trips() {
    let s = Server::start();
    let m = logged_probing_sim(&s, "leveller", -3.0);
    let program = "G21 G90\nG0 Z5\nG0 X0 Y0\nG31 Z-10 F100\n#500=#2002\nG0 Z5\nG0 X10 Y0\n\
                   G31 Z-10\n#501=#2002\nG0 Z5\nG0 X[#2000 - 10] Y0 Z[#500 + 1]\n\
                   G1 X10 Z[#501 + 1] F300\nM2\n";
    let up = s.upload(m.id, "leveller.tap", program);
    assert_eq!(up["analysis"]["probe_moves"], 2, "{up}");
    let job = up["id"].as_i64().unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    s.wait_job_state(job, "completed", T);
    let st = s.wait_machine_state(m.id, "idle", T);
    // Without the real trips (the upload's assumption: no contact at Z -10) Z would be -9.
    assert!((z(&st["machine_position"]) + 2.0).abs() < 1e-9, "{st}");
    assert_eq!(st["machine_position"]["x"], 10.0, "{st}");
    fresa_tests::assert_every_line_once(&m.executed(), run, 13);
}

/// LinuxCNC's own probing samples run to the end on a sim machine over a flat plate:
/// gridprobe.ngc (65 G38.2 moves in a grid) and smartprobe.ngc (2601 points, each lifting with
/// G38.5 and moving over with G38.3 until the way is clear, then G38.2 down). Their moves
/// that do not depend on the probe's result are compared with rs274 in the G-code
/// conformance test.
#[test]
fn linuxcncs_gridprobe_and_smartprobe_run_on_a_sim_machine() {
    let s = Server::start();
    // The plate's top at Z -1 mm: both programs probe down to -0.5 in / -0.1 in.
    let m = logged_probing_sim(&s, "grid", -1.0);
    for name in ["gridprobe.ngc", "smartprobe.ngc"] {
        let path = std::path::Path::new("/usr/share/linuxcnc/ncfiles").join(name);
        let program = std::fs::read(&path).unwrap_or_else(|e| {
            panic!(
                "{}: {e} (install the linuxcnc-uspace package)",
                path.display()
            )
        });
        let up = s.upload(m.id, name, program);
        assert!(up["analysis"]["probe_moves"].as_u64().unwrap() > 60, "{up}");
        // smartprobe loops on #5070; gridprobe only writes the results out (LOG).
        if name == "smartprobe.ngc" {
            assert!(
                up["analysis"]["probe_paths_unchecked_from"].is_u64(),
                "{up}"
            );
        }
        let job = up["id"].as_i64().unwrap();
        let run = s.job_action(job, "start").expect(200)["run"]["id"]
            .as_i64()
            .unwrap();
        let j = s.wait_job_state(job, "completed", Duration::from_secs(120));
        let lines = j["line_count"].as_i64().unwrap();
        fresa_tests::assert_every_line_once(&m.executed(), run, lines);
    }
}

/// Edge finding: probing toward +X onto a plate held against the part's left edge, with a
/// 6 mm tool, puts X 0 on the part's edge: the switch closes at machine X 30 (the plate's
/// face), the part's edge is 2 mm (the plate) further, the tool's centre 3 mm (its radius)
/// short of the face. Toward -X on the right edge mirrors it.
#[test]
fn an_x_edge_touch_off_puts_zero_on_the_parts_edge() {
    let s = Server::start();
    let m = s.create_machine(&json!({
        "name": "edges", "backend": "sim-machine",
        "config": {"time_scale": 0, "switches": {"probe": {"axis": "x", "at_or_above": 30}}},
    }));
    s.wait_machine_state(m, "idle", T);
    let r = s
        .post(
            &format!("/api/v1/machines/{m}/touch-off"),
            &json!({"axis": "X", "toward": "+", "plate_mm": 2, "tool_diameter_mm": 6,
                    "distance": 40, "feed": 300, "retract_mm": 5}),
        )
        .expect(200);
    let x = |v: &Value| v["x"].as_f64().unwrap();
    assert!((x(&r["trip"]) - 30.0).abs() < 1e-9, "{r}");
    // The tool's centre at the trip reads -(2 + 3): G54 X = 30 + 5.
    assert!((x(&r["after"]) - 35.0).abs() < 1e-9, "{r}");
    assert_eq!(z(&r["after"]), 0.0, "Z untouched: {r}");
    // Retracted 5 mm back toward -X.
    assert!((x(&r["work_position"]) + 10.0).abs() < 1e-6, "{r}");
    let stored = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    assert_eq!(stored["offsets"]["G54"]["x"], 35.0, "{stored}");
    let e = first_event(&s, "machine.touch_off");
    assert_eq!(e.data["data"]["tool_diameter_mm"], 6.0, "{:?}", e.data);
    assert_eq!(e.data["data"]["axis"], "X", "{:?}", e.data);
}

/// A sim machine whose probe is a round wall (`bore` or `boss`: `{"x", "y", "diameter"[,
/// "top_z"]}`), met by the tool's centre; instant (time scale 0).
fn round_sim(s: &Server, name: &str, shape: Value) -> i64 {
    let m = s.create_machine(&json!({
        "name": name,
        "backend": "sim-machine",
        "max_jog_mm": 60.0,
        "max_probe_feed_mm_min": 1500.0,
        "config": {"time_scale": 0, "switches": {"probe": shape}},
    }));
    s.wait_machine_state(m, "idle", T);
    m
}

fn xy(v: &Value) -> (f64, f64) {
    (v["x"].as_f64().unwrap(), v["y"].as_f64().unwrap())
}

/// Centre finding: a bore of 46 mm (the sim's wall at radius 20 around machine X30 Y20, met
/// by a 6 mm tool's centre) from a start off its centre, and a 14 mm boss (radius 10 around
/// X-40 Y10, top at Z -5) from above it: each ends on the centre with both diameters right and
/// G54's X/Y there, recorded as a touch-off; a bore with no wall within the distance changes
/// nothing and says so.
#[test]
fn a_bore_and_a_boss_centre_are_found_and_zeroed() {
    let s = Server::start();
    let close = |a: f64, b: f64| (a - b).abs() < 1e-3;

    let bore = round_sim(
        &s,
        "bore",
        json!({"bore": {"x": 30, "y": 20, "diameter": 40}}),
    );
    s.jog(bore, "X", 25.0).expect(200);
    s.jog(bore, "Y", 17.0).expect(200);
    s.wait_machine_state(bore, "idle", T);
    let r = s
        .post(
            &format!("/api/v1/machines/{bore}/find-centre"),
            &json!({"kind": "bore", "tool_diameter_mm": 6, "distance": 30, "feed": 600}),
        )
        .expect(200);
    let (cx, cy) = xy(&r["centre"]);
    assert!(close(cx, 30.0) && close(cy, 20.0), "{r}");
    assert!(close(r["diameter_x"].as_f64().unwrap(), 46.0), "{r}");
    assert!(close(r["diameter_y"].as_f64().unwrap(), 46.0), "{r}");
    let (ox, oy) = xy(&g54(&s, bore));
    assert!(close(ox, 30.0) && close(oy, 20.0), "G54 on the centre");
    let (wx, wy) = xy(&s.status(bore)["work_position"]);
    assert!(close(wx, 0.0) && close(wy, 0.0), "X/Y read 0 on the centre");
    let touch = first_event(&s, "machine.touch_off");
    assert_eq!(
        touch.data["data"]["source"], "bore_centre",
        "{:?}",
        touch.data
    );

    // Too short a distance to reach the wall: nothing changes.
    let e = s
        .post(
            &format!("/api/v1/machines/{bore}/find-centre"),
            &json!({"kind": "bore", "tool_diameter_mm": 6, "distance": 5, "feed": 600,
                    "set_zero": true}),
        )
        .expect_error(422, "probe_not_tripped");
    assert!(e.contains("X+"), "{e}");
    assert_eq!(xy(&g54(&s, bore)), (30.0, 20.0));

    // A boss: up above it, down beside it at each side.
    let boss = round_sim(
        &s,
        "boss",
        json!({"boss": {"x": -40, "y": 10, "diameter": 20, "top_z": -5}}),
    );
    s.jog(boss, "X", -39.0).expect(200);
    s.jog(boss, "Y", 11.5).expect(200);
    s.wait_machine_state(boss, "idle", T);
    let r = s
        .post(
            &format!("/api/v1/machines/{boss}/find-centre"),
            &json!({"kind": "boss", "tool_diameter_mm": 6, "boss_diameter_mm": 14,
                    "clearance_mm": 5, "depth_mm": 10, "feed": 600, "set_zero": false}),
        )
        .expect(200);
    let (cx, cy) = xy(&r["centre"]);
    assert!(close(cx, -40.0) && close(cy, 10.0), "{r}");
    assert!(close(r["diameter_x"].as_f64().unwrap(), 14.0), "{r}");
    assert!(close(r["diameter_y"].as_f64().unwrap(), 14.0), "{r}");
    assert!(
        r["offset"].is_null(),
        "set_zero false leaves the offset: {r}"
    );
    let st = s.status(boss);
    assert_eq!(
        z(&st["machine_position"]),
        0.0,
        "back up where it started: {st}"
    );
    // A boss needs its diameter and depth.
    s.post(
        &format!("/api/v1/machines/{boss}/find-centre"),
        &json!({"kind": "boss", "tool_diameter_mm": 6, "feed": 600}),
    )
    .expect_error(422, "invalid_field");
}
