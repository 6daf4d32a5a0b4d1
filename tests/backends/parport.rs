//! The parport-stepper backend end to end through the server's API, on its simulated port:
//! a program run (with the process monitor's line reports on the event stream), jog, zero, the
//! Z-lift output, and a limit input that stops the job with an alarm naming the input, shown
//! live as `machine.io` and in the status.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{assert_every_line_once, back_and_forth, read_exec_log, Server, SseEvent};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// A fast simulated router: 20 steps/mm, 2000 steps/s, 5 kHz ticks.
fn parport_machine(s: &Server, name: &str, extra: Value) -> i64 {
    let mut config = json!({
        "port": "sim",
        "tick_hz": 5000,
        "spin_us": 0,
        "realtime_priority": false,
        "execution_log": s.data_dir().join(format!("exec-{name}.log")),
        "axes": {
            "x": {"steps_per_mm": 20, "max_rate": 2000, "accel": 40000},
            "y": {"steps_per_mm": 20, "max_rate": 2000, "accel": 40000}
        },
        "z_lift": {"settle_ms": 5}
    });
    for (k, v) in extra.as_object().unwrap() {
        config[k] = v.clone();
    }
    s.create_machine(&json!({"name": name, "backend": "parport-stepper", "config": config}))
}

fn axis(st: &Value, pos: &str, a: &str) -> f64 {
    st[pos][a]
        .as_f64()
        .unwrap_or_else(|| panic!("no {pos}.{a} in {st}"))
}

#[test]
fn runs_a_program_with_line_reports_then_jogs_zeroes_and_lifts() {
    let s = Server::start();
    let m = parport_machine(&s, "router", json!({}));
    s.wait_machine_state(m, "idle", T);
    let events = s.events("types=job.line_report", None);

    let program =
        "G21 G90\nG0 Z5\nG0 X10 Y5\nG1 Z-1 F300\nG1 X20 Y10 F1200\nG2 X30 Y10 I5 J0\nG0 Z5\nM2\n";
    let job = s.upload(m, "part.nc", program);
    let id = job["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    let done = s.wait_job_state(id, "completed", T);
    assert_eq!(done["line"], 8, "{done}");
    let st = s.wait_machine_state(m, "idle", T);
    assert_eq!(axis(&st, "machine_position", "x"), 30.0);
    assert_eq!(axis(&st, "machine_position", "y"), 10.0);
    assert_eq!(axis(&st, "machine_position", "z"), 5.0);

    // The process monitor: one report per line that moved XY, with the deviation, the percent
    // done and the time left, ending at 100 %.
    let seen = events.until(T, "line report of line 6", |e: &SseEvent| {
        e.data["data"]["line"] == 6
    });
    let reports: Vec<&Value> = seen.iter().map(|e| &e.data["data"]).collect();
    let lines: Vec<i64> = reports
        .iter()
        .map(|r| r["line"].as_i64().unwrap())
        .collect();
    assert_eq!(lines, [3, 5, 6], "{reports:?}");
    for r in &reports {
        assert_eq!(r["job"], id);
        let dev = r["max_deviation_mm"].as_f64().unwrap();
        // Within one step (0.05 mm) of the programmed line.
        assert!((0.0..=0.05).contains(&dev), "{r}");
    }
    let last = reports[2];
    assert!(last["percent"].as_f64().unwrap() > 50.0, "{last}");
    assert!(last["remaining_s"].as_f64().unwrap() >= 0.0, "{last}");

    // Jog (bounded by the host), zero, and the Z lift by hand.
    s.post(
        &format!("/api/v1/machines/{m}/jog"),
        &json!({"axis": "X", "distance": -2.5, "feed": 600}),
    )
    .expect(200);
    let st = s.wait_status(m, T, "jog done", |st| {
        st["state"] == "idle" && st["machine_position"]["x"] == 27.5
    });
    assert_eq!(axis(&st, "machine_position", "y"), 10.0);
    s.post(
        &format!("/api/v1/machines/{m}/commands"),
        &json!({"command": "zero", "axis": "X"}),
    )
    .expect(200);
    let st = s.status(m);
    assert_eq!(axis(&st, "work_position", "x"), 0.0);
    let r = s
        .post(
            &format!("/api/v1/machines/{m}/commands"),
            &json!({"command": "set_output", "name": "z_lift", "on": false}),
        )
        .expect(200);
    assert_eq!(r["result"]["z_lift"], false, "{r}");
    let e = s
        .post(
            &format!("/api/v1/machines/{m}/commands"),
            &json!({"command": "set_output", "name": "vacuum", "on": true}),
        )
        .expect_error(422, "invalid_command");
    assert!(e.contains("vacuum"), "{e}");
    // Spindle is a known output name, but this machine has none.
    let e = s
        .post(
            &format!("/api/v1/machines/{m}/commands"),
            &json!({"command": "toggle_output", "name": "spindle"}),
        )
        .expect_error(422, "backend_rejected");
    assert!(e.contains("unsupported") && e.contains("spindle"), "{e}");
    let r = s
        .post(
            &format!("/api/v1/machines/{m}/commands"),
            &json!({"command": "toggle_output", "name": "z_lift"}),
        )
        .expect(200);
    assert_eq!(r["result"]["z_lift"], true, "{r}");
}

#[test]
fn a_limit_input_stops_the_job_with_an_alarm_naming_the_input_and_shows_on_the_status() {
    let s = Server::start();
    let io_events = s.events("types=machine", None);
    let m = parport_machine(
        &s,
        "limited",
        json!({
            "inputs": [{"pin": 10, "function": "limit_x"}, {"pin": 15, "function": "estop", "active_low": true}],
            "sim_inputs": [{"after_writes": 60, "pin": 10, "level": "high"}]
        }),
    );
    // Both inputs known and released before anything moves.
    let st = s.wait_status(m, T, "inputs read", |st| {
        st["state"] == "idle" && st["inputs"] == json!({"limit_x": false, "estop": false})
    });
    assert_eq!(st["outputs"]["z_lift"], false, "{st}");
    let job = s.upload(m, "long.nc", "G21 G90\nG1 X40 Y2 F1200\nG1 X0 Y0\n");
    let id = job["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    let failed = s.wait_job(id, T, "failed", |j| j["state"] == "failed");
    let alarm = "limit switch limit_x (pin 10)";
    assert!(
        failed.to_string().contains(alarm),
        "the job names the input: {failed}"
    );
    // The state change can be published a moment before the status that carries its reason.
    let st = s.wait_status(m, T, "alarm with its reason", |st| {
        st["state"] == "alarm" && st["alarm"].is_string()
    });
    assert_eq!(st["alarm"], alarm, "{st}");
    // Stopped early: 60 coil writes is about 3 mm at 20 steps/mm, far from X40.
    let x = axis(&st, "machine_position", "x");
    assert!(x > 0.0 && x < 5.0, "stopped at x={x}");
    // The change went out live as machine.io, and the alarm is in the audit log with the
    // input's name.
    let seen = io_events.until(T, "machine.io with limit_x pressed", |e| {
        e.event == "machine.io" && e.data["data"]["changed"]["limit_x"] == true
    });
    let io = seen.last().unwrap();
    assert_eq!(io.data["machine"], m, "{io:?}");
    assert_eq!(io.data["data"]["inputs"]["estop"], false, "{io:?}");
    let audit = s.events("types=machine.alarm", Some(0));
    let recorded = audit.until(T, "the persisted alarm", |e| e.event == "machine.alarm");
    let recorded = &recorded.last().unwrap().data;
    assert_eq!(recorded["data"]["input"], "limit_x", "{recorded}");
    assert_eq!(recorded["data"]["message"], alarm, "{recorded}");
    // No motion until reset.
    let e = s
        .post(
            &format!("/api/v1/machines/{m}/jog"),
            &json!({"axis": "X", "distance": -1.0}),
        )
        .expect_error(422, "backend_rejected");
    assert!(e.contains(&format!("in alarm ({alarm})")), "{e}");
    s.post(
        &format!("/api/v1/machines/{m}/commands"),
        &json!({"command": "reset"}),
    )
    .expect(200);
    s.wait_machine_state(m, "idle", T);
}

#[test]
fn pause_resume_and_resume_after_a_crash_run_every_line_once() {
    const LINES: i64 = 200;
    let mut s = Server::start();
    let m = parport_machine(
        &s,
        "crashy",
        json!({"axes": {
            "x": {"steps_per_mm": 20, "max_rate": 2000, "start_rate": 1000, "accel": 40000},
            "y": {"steps_per_mm": 20, "max_rate": 2000, "start_rate": 1000, "accel": 40000}
        }}),
    );
    let log = s.data_dir().join("exec-crashy.log");
    s.wait_machine_state(m, "idle", T);
    // 200 lines of 1 mm (20 steps) at 3000 mm/min: about 25 ms a line.
    let job = s.upload(m, "slow.nc", back_and_forth(LINES as usize, 1.0, 3000.0))["id"]
        .as_i64()
        .unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    s.wait_job(job, T, "line >= 20", |j| j["line"].as_i64().unwrap() >= 20);

    // Feed hold: machine and job report paused (the motors ramp down; that the steps stop is
    // checked on the simulated port's ticks in the plugin's own tests), then resume continues.
    s.job_action(job, "pause").expect(200);
    s.wait_machine_state(m, "paused", T);
    let held = s.wait_job_state(job, "paused", T)["line"].as_i64().unwrap();
    s.job_action(job, "resume").expect(200);
    s.wait_job(job, T, "well past the hold", |j| {
        j["line"].as_i64().unwrap() >= held + 10
    });

    // Crash mid-run, come back, resume: every line exactly once.
    s.wait_job(job, T, "line >= 60", |j| j["line"].as_i64().unwrap() >= 60);
    assert!(!read_exec_log(&log).is_empty());
    s.restart_after_kill();
    let j = s.job(job);
    assert_eq!(j["state"], "interrupted", "{j}");
    s.wait_machine_state(m, "idle", T);
    s.job_action(job, "resume").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], LINES, "{j}");
    assert_every_line_once(&read_exec_log(&log), run, LINES);

    // Cancel stops a run at once.
    let other = s.upload(m, "again.nc", back_and_forth(LINES as usize, 1.0, 3000.0))["id"]
        .as_i64()
        .unwrap();
    s.job_action(other, "start").expect(200);
    s.wait_job(other, T, "line >= 5", |j| j["line"].as_i64().unwrap() >= 5);
    s.job_action(other, "cancel").expect(200);
    let j = s.wait_job_state(other, "cancelled", T);
    assert!(j["line"].as_i64().unwrap() < LINES, "{j}");
    s.wait_machine_state(m, "idle", T);
}

/// A start at a line on the LPT router: the preview plans up to the program's highest Z (the
/// lift), across and down; the run executes lines N.. only and ends where the whole program
/// ends.
#[test]
fn a_start_at_a_line_lifts_moves_across_and_runs_lines_n_on_only() {
    let s = Server::start();
    let m = parport_machine(&s, "from-line", json!({}));
    s.wait_machine_state(m, "idle", T);
    let program =
        "G21 G90\nG0 Z5\nG0 X10 Y5\nG1 Z-1 F300\nG1 X20 Y10 F1200\nG2 X30 Y10 I5 J0\nG0 Z5\nM2\n";
    let job = s.upload(m, "part.nc", program)["id"].as_i64().unwrap();
    let p = s
        .get(&format!("/api/v1/jobs/{job}/start-preview?from_line=5"))
        .expect(200);
    assert_eq!(p["safe_z"], 5.0, "{p}");
    let gcode = p["gcode"].as_str().unwrap();
    assert!(
        gcode.contains("G53 G0 Z5\nG54\nM5\nM9\nG53 G0 X10 Y5\nG53 G1 Z-1 F300"),
        "{gcode}"
    );
    let io = s.events(&format!("types=machine.io&machine={m}"), None);
    let r = s
        .post(
            &format!("/api/v1/jobs/{job}/start"),
            &json!({"from_line": 5}),
        )
        .expect(200);
    let run = r["run"]["id"].as_i64().unwrap();
    s.wait_job_state(job, "completed", T);
    // The lift went up for the move across, down to the start point's Z, up again at line 7
    // (without the preamble line 5 would start with the lift down, where it stood).
    let mut lift = Vec::new();
    io.until(T, "three lift changes", |e: &SseEvent| {
        if let Some(on) = e.data["data"]["changed"]["z_lift"].as_bool() {
            lift.push(on);
        }
        lift.len() == 3
    });
    assert_eq!(lift, [true, false, true]);
    let log = read_exec_log(&s.data_dir().join("exec-from-line.log"));
    let lines: Vec<i64> = log.iter().filter(|e| e.0 == run).map(|e| e.1).collect();
    assert_eq!(lines, [5, 6, 7, 8]);
    let st = s.wait_machine_state(m, "idle", T);
    assert_eq!(axis(&st, "machine_position", "x"), 30.0);
    assert_eq!(axis(&st, "machine_position", "y"), 10.0);
    assert_eq!(axis(&st, "machine_position", "z"), 5.0);
}

/// Two steppers and a Z output have no A axis: a program that turns A is refused at job
/// start naming the line, before any step (no line executed, the position unchanged).
#[test]
fn an_a_axis_program_is_refused_naming_the_line_before_anything_moves() {
    let s = Server::start();
    let m = parport_machine(&s, "no-a", json!({}));
    s.wait_machine_state(m, "idle", T);
    let log = s.data_dir().join("exec-no-a.log");
    let job = s.upload(
        m,
        "rotary.nc",
        "G21 G90\nG0 X5 Y5\nG1 X10 F600\nG1 X20 A45\nM2\n",
    )["id"]
        .as_i64()
        .unwrap();
    let msg = s
        .job_action(job, "start")
        .expect_error(422, "backend_rejected");
    assert!(msg.contains("line 4") && msg.contains("A axis"), "{msg}");
    assert_eq!(s.job(job)["state"], "failed");
    assert!(read_exec_log(&log).is_empty(), "no line ran");
    let st = s.status(m);
    assert_eq!(axis(&st, "machine_position", "x"), 0.0, "{st}");
    assert_eq!(axis(&st, "machine_position", "y"), 0.0, "{st}");
}

fn overrides(s: &Server, m: i64) -> [f64; 3] {
    let st = s.status(m);
    ["feed_override", "spindle_override", "rapid_override"].map(|k| {
        st[k]
            .as_f64()
            .unwrap_or_else(|| panic!("no {k} in the status {st}"))
    })
}

/// The median time a line of `run` took, ms, over the lines `from..=to`, from the plugin's
/// execution log (each line's end stamp minus the previous one's).
fn median_line_ms(log: &fresa_tests::Sim, run: i64, from: i64, to: i64) -> f64 {
    let times = log.line_times(run);
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

/// The check on the stepper: a 50 % feed override set during a run makes every later
/// line take twice as long (lines of 1 mm at 600 mm/min: 20 steps at 200 steps/s, 0.1 s), by
/// the plugin's own execution log; a spindle override is refused naming why and changes
/// nothing, also when it comes with a feed override.
#[test]
fn a_50_percent_feed_override_doubles_the_line_times_and_a_spindle_one_is_refused() {
    let s = Server::start();
    let m = parport_machine(&s, "over", json!({}));
    let log = fresa_tests::Sim {
        id: m,
        log: s.data_dir().join("exec-over.log"),
    };
    s.wait_machine_state(m, "idle", T);
    let path = format!("/api/v1/machines/{m}/overrides");
    let msg = s
        .post(&path, &json!({"feed": 80, "spindle": 120}))
        .expect_error(422, "backend_rejected");
    assert!(
        msg.starts_with("unsupported:") && msg.contains("spindle"),
        "{msg}"
    );
    assert_eq!(overrides(&s, m), [100.0, 100.0, 100.0]);

    let (job, run) = s.upload_and_start(m, "strokes", &back_and_forth(40, 1.0, 600.0));
    fresa_tests::wait_for(T, "line 12 executed", || {
        (log.count_of(run) >= 12).then_some(())
    });
    let answer = s.post(&path, &json!({"feed": 50})).expect(200);
    assert_eq!(
        answer,
        json!({"feed": 50.0, "spindle": 100.0, "rapid": 100.0})
    );
    // The line under way and the ~60 ms of motion queued ahead are the only ones in between.
    let set_at = log.count_of(run) as i64 + 2;
    s.wait_job_state(job, "completed", T);
    assert_every_line_once(&read_exec_log(&log.log), run, 40);
    let full = median_line_ms(&log, run, 3, 11);
    let half = median_line_ms(&log, run, set_at, 40);
    let ratio = half / full;
    eprintln!("parport feed override: {full} ms a line at 100 %, {half} ms at 50 % (x{ratio:.2})");
    assert!(
        (1.7..=2.3).contains(&ratio),
        "a line took {full} ms at 100 % and {half} ms at 50 % (ratio {ratio:.2}); expected about 2"
    );
    let st = s.wait_machine_state(m, "idle", T);
    assert_eq!(axis(&st, "machine_position", "x"), 0.0, "{st}");
    assert_eq!(overrides(&s, m), [50.0, 100.0, 100.0]);
}

/// parport-stepper's Z is an on/off tool lift, so it refuses a job with a height map before
/// anything moves, naming why (the run fails at its start; nothing is executed).
#[test]
fn a_job_with_a_height_map_is_refused_naming_the_z_lift() {
    let mut s = Server::start();
    let m = parport_machine(&s, "lifter", json!({}));
    s.wait_machine_state(m, "idle", T);
    // A grid cannot be probed here (its probing axes are X and Y): the map is stored straight
    // into the (stopped) server's database, as one measured elsewhere would be.
    s.terminate();
    let db = s.data_dir().join("fresa.db");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let hid = rt.block_on(async {
        let store = fresa_core::store::Store::open(&db).await.unwrap();
        let points = json!([0.0, 0.1, -0.1, 0.05]).to_string();
        let id = store
            .insert_height_map(fresa_core::store::NewHeightMap {
                machine_id: m,
                area: [0.0, 10.0, 0.0, 10.0],
                nx: 2,
                ny: 2,
                clearance: 2.0,
                distance: 5.0,
                feed: 100.0,
                offset: [0.0; 3],
                points: &points,
                created_by: "test",
            })
            .await
            .unwrap();
        assert!(store
            .finish_height_map(id, "complete", &points, None)
            .await
            .unwrap());
        id
    });
    drop(rt);
    s.spawn().unwrap();
    s.wait_machine_state(m, "idle", T);
    let job = s.upload(m, "pcb.nc", "G21 G90\nG0 X1 Y1\nG1 X5 Y5 F300\n")["id"]
        .as_i64()
        .unwrap();
    let msg = s
        .post(
            &format!("/api/v1/jobs/{job}/start"),
            &json!({"height_map": hid}),
        )
        .expect_error(422, "height_map_unsupported");
    assert!(msg.contains("Z is an on/off tool lift"), "{msg}");
    let j = s.job(job);
    assert_eq!(j["state"], "failed", "{j}");
    assert_eq!(j["run"]["height_map_id"], hid, "{j}");
    let st = s.status(m);
    assert_eq!(
        axis(&st, "machine_position", "x"),
        0.0,
        "nothing moved: {st}"
    );
    assert!(read_exec_log(&s.data_dir().join("exec-lifter.log")).is_empty());
}
