//! Jobs: upload, run to completion (execution log checked line by line), download, pause /
//! resume / cancel, and refusing a second job on a busy machine.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{assert_every_line_once, back_and_forth, corpus, sha256_hex, Server, Sim};
use std::time::{Duration, Instant};

const T: Duration = Duration::from_secs(60);

fn line_count(data: &[u8]) -> i64 {
    let n = data.iter().filter(|b| **b == b'\n').count() as i64;
    if data.last() == Some(&b'\n') {
        n
    } else {
        n + 1
    }
}

fn run_id(job: &Value) -> i64 {
    job["run"]["id"]
        .as_i64()
        .unwrap_or_else(|| panic!("job has no run: {job}"))
}

/// Uploads `data`, checks what the upload reports, runs it to completion and checks the job, the
/// execution log and the stored program.
fn run_corpus_file(s: &Server, m: &Sim, name: &str, data: &[u8], multipart: bool) {
    let sha = sha256_hex(data);
    let up = if multipart {
        let form = reqwest::blocking::multipart::Form::new()
            .text("machine", m.id.to_string())
            .part(
                "file",
                reqwest::blocking::multipart::Part::bytes(data.to_vec())
                    .file_name(name.to_string()),
            );
        s.send(s.req(reqwest::Method::POST, "/api/v1/jobs").multipart(form))
            .expect(201)
    } else {
        s.post_bytes(
            &format!("/api/v1/jobs?machine={}&name={name}&sha256={sha}", m.id),
            data.to_vec(),
        )
        .expect(201)
    };
    let id = up["id"].as_i64().expect("job id");
    let lines = line_count(data);
    assert_eq!(up["sha256"], sha.as_str(), "{up}");
    assert_eq!(up["line_count"], lines, "{up}");
    assert!(up["analysis"].is_object(), "analysis: {up}");

    let job = s.job(id);
    assert_eq!(job["state"], "ready", "{job}");
    assert_eq!(job["line"], 0);
    assert_eq!(
        job["name"], name,
        "multipart file name or ?name= is the job name"
    );
    assert_eq!(job["machine"], m.id);

    // The stored program is byte-identical to the upload.
    let r = s
        .req(reqwest::Method::GET, &format!("/api/v1/jobs/{id}/gcode"))
        .send()
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let body = r.bytes().unwrap();
    assert!(body.as_ref() == data, "GET gcode differs from the upload");

    let started = s.job_action(id, "start").expect(200);
    assert!(
        matches!(started["state"].as_str(), Some("running" | "completed")),
        "{started}"
    );
    let job = s.wait_job_state(id, "completed", Duration::from_secs(120));
    assert_eq!(job["line"], lines, "last acknowledged line: {job}");
    assert_eq!(job["line_count"], lines);
    assert_eq!(job["percent"].as_f64(), Some(100.0), "{job}");
    let run = run_id(&job);
    assert_every_line_once(&m.executed(), run, lines);
    // Only this run is in the log.
    assert!(m.executed().iter().all(|(r, _)| *r == run));

    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "no current job after completion: {st}");
    assert!(
        s.program_files().contains(&format!("{sha}.nc")),
        "{:?}",
        s.program_files()
    );
}

#[test]
fn corpus_job_runs_to_completion_every_line_executed_once() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let name = "fusion-1122_jig_28bit_first.nc";
    let data = std::fs::read(corpus(name)).unwrap();
    run_corpus_file(&s, &m, name, &data, false);

    // The same program again is a second job on the same stored file.
    let again = s.upload(m.id, "again", data.clone());
    assert_ne!(again["id"], Value::Null);
    let jobs = s.get("/api/v1/jobs").expect(200);
    assert_eq!(jobs.as_array().unwrap().len(), 2, "{jobs}");
    assert_eq!(s.program_files(), [format!("{}.nc", sha256_hex(&data))]);
}

#[test]
fn large_corpus_job_uploaded_as_multipart_runs_to_completion() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let name = "cncjs-tball-pocket.gcode";
    let data = std::fs::read(corpus(name)).unwrap();
    run_corpus_file(&s, &m, name, &data, true);
}

/// 200 lines of 1 mm at 600 mm/min: 10 ms a line at time scale 0.1, about 2 s in all.
fn slow_program() -> String {
    back_and_forth(200, 1.0, 600.0)
}

#[test]
fn pause_holds_the_job_resume_completes_it_and_busy_machines_refuse_a_second_job() {
    let s = Server::start();
    let m = s.sim("m", 0.1);
    let program = slow_program();
    let id = s.upload(m.id, "slow", program.clone())["id"]
        .as_i64()
        .unwrap();
    let other = s.upload(m.id, "other", "G0 X1\n")["id"].as_i64().unwrap();

    // Pausing or resuming a job never started is a conflict, not a crash.
    s.job_action(id, "pause").expect_error(409, "not_started");
    s.job_action(id, "resume").expect_error(409, "not_started");

    let r = s.job_action(id, "start").expect(200);
    assert_eq!(r["state"], "running", "{r}");
    s.wait_job(id, T, "line >= 20", |j| j["line"].as_i64().unwrap() >= 20);

    // While it runs: a second job, the same job again and jogs are refused.
    let msg = s
        .job_action(other, "start")
        .expect_error(409, "machine_busy");
    assert!(!msg.is_empty());
    s.job_action(id, "start").expect_error(409, "machine_busy");
    s.post(
        &format!("/api/v1/machines/{}/jog", m.id),
        &json!({"axis": "X", "distance": 1.0}),
    )
    .expect_error(409, "machine_busy");
    s.job_action(id, "resume")
        .expect_error(409, "not_resumable");
    let st = s.status(m.id);
    assert_eq!(st["job"]["job"], id, "status shows the running job: {st}");
    assert_eq!(st["job"]["total_lines"], 200, "{st}");

    let r = s.job_action(id, "pause").expect(200);
    assert_eq!(r["state"], "paused", "{r}");
    s.wait_machine_state(m.id, "paused", T);
    assert_eq!(s.job(id)["state"], "paused");
    s.job_action(id, "pause").expect_error(409, "not_running");

    // Once the acknowledgements in flight are in, nothing advances while paused.
    let held = fresa_tests::wait_for(T, "job line to catch up with the execution log", || {
        let logged = m.executed().last().map_or(0, |e| e.1);
        let line = s.job(id)["line"].as_i64().unwrap();
        (line == logged).then_some(line)
    });
    assert!((20..200).contains(&held), "held at line {held}");
    let log_len = m.executed().len();
    let watch_until = Instant::now() + Duration::from_millis(400);
    while Instant::now() < watch_until {
        let j = s.job(id);
        assert_eq!(j["line"], held, "line advanced while paused: {j}");
        assert_eq!(j["state"], "paused");
        assert_eq!(
            m.executed().len(),
            log_len,
            "execution log grew while paused"
        );
        assert_eq!(s.status(m.id)["state"], "paused");
        std::thread::sleep(Duration::from_millis(20));
    }

    let r = s.job_action(id, "resume").expect(200);
    assert_eq!(r["state"], "running", "{r}");
    let job = s.wait_job_state(id, "completed", T);
    assert_eq!(job["line"], 200);
    let run = run_id(&job);
    assert_every_line_once(&m.executed(), run, 200);

    // Finished jobs can be neither resumed nor cancelled; the machine is free again.
    let msg = s
        .job_action(id, "resume")
        .expect_error(409, "not_resumable");
    assert!(msg.contains("completed"), "{msg}");
    s.job_action(id, "cancel")
        .expect_error(409, "not_cancellable");
    s.job_action(id, "explode")
        .expect_error(404, "unknown_action");
    s.wait_machine_state(m.id, "idle", T);
    s.job_action(other, "start").expect(200);
    s.wait_job_state(other, "completed", T);
}

#[test]
fn cancel_stops_the_job_and_a_new_start_runs_it_again_from_the_top() {
    let s = Server::start();
    let m = s.sim("m", 0.1);
    let id = s.upload(m.id, "slow", slow_program())["id"]
        .as_i64()
        .unwrap();
    s.job_action(id, "start").expect(200);
    s.wait_job(id, T, "line >= 5", |j| j["line"].as_i64().unwrap() >= 5);
    let r = s.job_action(id, "cancel").expect(200);
    assert_eq!(r["state"], "cancelled", "{r}");
    let job = s.job(id);
    assert_eq!(job["state"], "cancelled");
    let first_run = run_id(&job);
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "{st}");

    // The log holds a prefix of the program, each line once, and stops there.
    let log: Vec<i64> = m
        .executed()
        .iter()
        .filter(|e| e.0 == first_run)
        .map(|e| e.1)
        .collect();
    assert!(log.len() >= 5 && log.len() < 200, "{} lines ran", log.len());
    assert!(log.iter().copied().eq(1..=log.len() as i64), "{log:?}");
    s.job_action(id, "cancel")
        .expect_error(409, "not_cancellable");
    s.job_action(id, "resume")
        .expect_error(409, "not_resumable");

    // Starting it again is a new run from line 1.
    let r = s.job_action(id, "start").expect(200);
    let second_run = r["run"]["id"].as_i64().unwrap();
    assert_ne!(second_run, first_run);
    let job = s.wait_job_state(id, "completed", T);
    assert_eq!(job["line"], 200);
    assert_every_line_once(&m.executed(), second_run, 200);
    let after: Vec<i64> = m
        .executed()
        .iter()
        .filter(|e| e.0 == first_run)
        .map(|e| e.1)
        .collect();
    assert_eq!(after, log, "the cancelled run did not continue");
}

/// A client that starts the next job the moment the last one reads `completed` is not refused
/// as `machine_busy` because the machine's cached status still says `running`.
#[test]
fn the_next_job_starts_as_soon_as_the_last_one_completed() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let id = s.upload(m.id, "short", back_and_forth(20, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    for round in 0..10 {
        let r = s.job_action(id, "start");
        assert_eq!(r.status, 200, "round {round}: {}", r.body);
        s.wait_job_state(id, "completed", T);
    }
}

/// A LinuxCNC-style program (a loop, a canned cycle, G92) is accepted by the upload check, its
/// stored analysis shows the origin change, and the machine ends where rs274 would put it.
#[test]
fn a_linuxcnc_style_program_with_a_loop_a_cycle_and_g92_runs() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let program = "G21 G90 F600\nG0 X10 Y0 Z5\nG92 X0\n#1 = 0\n\
                   o1 while [#1 LT 3]\n  G81 X[#1 * 5] Y0 Z-1 R1\n  #1 = [#1 + 1]\no1 endwhile\n\
                   G80\nG0 X20 Z10\nM2\n";
    let up = s.upload(m.id, "linuxcnc", program);
    let a = &up["analysis"];
    assert_eq!(a["offset_change_count"], 1, "{a}");
    assert_eq!(a["offset_changes"][0]["command"], "G92", "{a}");
    assert_eq!(a["offset_changes"][0]["line"], 3, "{a}");
    assert_eq!(a["offset_changes"][0]["offset"][0], 10.0, "{a}");
    // Three holes at work X 10, 15, 20 (G92 X0 at X10), each one feed from R1 down to Z-1.
    assert_eq!(a["linear_moves"], 3, "{a}");
    assert_eq!(a["cutting_bounds"]["min"][2], -1.0, "{a}");
    assert_eq!(a["cutting_bounds"]["min"][0], 10.0, "{a}");
    assert_eq!(a["cutting_bounds"]["max"][0], 20.0, "{a}");
    let job = s.job(up["id"].as_i64().unwrap());
    assert_eq!(job["analysis"]["offset_change_count"], 1, "stored: {job}");

    let id = up["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    s.wait_job_state(id, "completed", T);
    // G0 X20 after G92 X0 (set at X10) ends at work X30 (once the status has caught up).
    let st = s.wait_status(m.id, T, "idle after the G92 job", |st| {
        st["state"] == "idle"
    });
    assert_eq!(st["work_position"]["x"], 30.0, "{st}");
    assert_eq!(st["work_position"]["z"], 10.0, "{st}");
}

/// The A axis: the upload's analysis gives its range and first line, the sim-machine turns
/// it (the status shows A, through G92 and G91 as rs274 computes them), and a program that
/// would turn A past the machine's travel is refused before anything moves, naming the line.
#[test]
fn sim_machine_runs_a_axis_moves_and_checks_a_travel() {
    let s = Server::start();
    let m = s.sim_with(
        "rotary",
        0.0,
        json!({"config": {
            "time_scale": 0.0,
            "execution_log": s.data_dir().join("exec-rotary.log"),
            "travel": {"a": [-360, 360]},
        }}),
    );
    let program = "G21 G90\nG0 X5 A30\nG1 X10 A90 F600\nG91 G1 A-45\nG90 G92 A0\nG1 A10\nM2\n";
    let up = s.upload(m.id, "rotary", program);
    let a = &up["analysis"];
    assert_eq!(a["first_a_line"], 2, "{a}");
    assert_eq!(a["a_bounds"]["min"], 0.0, "{a}");
    assert_eq!(a["a_bounds"]["max"], 90.0, "{a}");
    assert_eq!(a["offset_changes"][0]["offset_a"], 45.0, "{a}");
    let id = up["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    s.wait_job_state(id, "completed", T);
    // A30, A90, -45 -> 45, G92 A0 there (offset 45), A10 -> 55 in machine coordinates. The
    // status may still be on its way when the store says completed: wait for it to be idle.
    let st = s.wait_status(m.id, T, "idle after the rotary job", |st| {
        st["state"] == "idle"
    });
    assert_eq!(st["machine_position"]["a"], 55.0, "{st}");
    assert_eq!(st["machine_position"]["x"], 10.0, "{st}");

    // Line 3 would turn A to 400 degrees, past the travel: nothing moves.
    let executed = m.executed().len();
    let job = s.upload(m.id, "too-far", "G21 G90\nG0 A100\nG1 X1 A400 F600\n")["id"]
        .as_i64()
        .unwrap();
    let r = s.job_action(job, "start");
    assert!(r.status >= 400, "{r:?}");
    assert!(r.text.contains("line 3"), "{}", r.text);
    let st = s.status(m.id);
    assert_eq!(st["machine_position"]["a"], 55.0, "nothing moved: {st}");
    assert_eq!(m.executed().len(), executed, "no line executed");
}
