//! kawasaki-as end to end: the real `fresa` server, the real plugin, and `kawasaki-as-sim`
//! playing the controller (legacy = the seed's robot program, fresa-v1 = ours). Every motion
//! the simulated robot executes is compared with the expected mapped point, and resumes after
//! a dropped link or a SIGKILLed server must execute every motion exactly once.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::Unsupported;
use fresa_kawasaki_as::config::Speeds;
use fresa_kawasaki_as::convert::{Cmd, Convert, Mapping};
use fresa_tests::{bin_dir, corpus, Server};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

const T: Duration = Duration::from_secs(120);
const FUSION: &str = "fusion-1122_jig_28bit_first.nc";
const HELICAL: &str = "cncjs-helical-thread-milling.gcode";

/// A `kawasaki-as-sim` process, killed on drop.
struct Robot {
    child: Child,
    addr: String,
    log: PathBuf,
}

impl Drop for Robot {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Robot {
    fn start(dir: &Path, protocol: &str, extra: &[&str]) -> Robot {
        let log = dir.join(format!("robot-{protocol}-{}.log", rand_suffix()));
        let mut child = Command::new(bin_dir().join("kawasaki-as-sim"))
            .args(["--listen", "127.0.0.1:0", "--protocol", protocol])
            .arg("--log")
            .arg(&log)
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start kawasaki-as-sim");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let addr = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
            .to_string();
        Robot { child, addr, log }
    }

    fn entries(&self) -> Vec<Value> {
        std::fs::read_to_string(&self.log)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect()
    }

    /// Executed motions: (kind, point relative to part zero).
    fn moves(&self) -> Vec<(bool, [f64; 3])> {
        self.entries()
            .iter()
            .filter(|e| e["move"].is_string())
            .map(|e| {
                let to = e["to"].as_array().unwrap();
                (
                    e["move"] == "JMOVE",
                    [
                        to[0].as_f64().unwrap(),
                        to[1].as_f64().unwrap(),
                        to[2].as_f64().unwrap(),
                    ],
                )
            })
            .collect()
    }

    fn violations(&self) -> Vec<Value> {
        self.entries()
            .into_iter()
            .filter(|e| e.get("violation").is_some())
            .collect()
    }
}

fn rand_suffix() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static N: AtomicU64 = AtomicU64::new(0);
    N.fetch_add(1, Ordering::Relaxed)
}

/// The motions the robot must execute for `program`, from the plugin's converter with the
/// machine defaults.
fn expected(program: &str, unsupported: Unsupported) -> Vec<(bool, [f64; 3])> {
    let plan = Convert {
        mapping: Mapping::default(),
        speeds: Speeds::default(),
        arc_tolerance_mm: 0.01,
        unsupported,
    }
    .plan(program)
    .unwrap();
    plan.cmds
        .iter()
        .filter_map(|(_, c)| match c {
            Cmd::Move { rapid, to } => Some((*rapid, *to)),
            _ => None,
        })
        .collect()
}

#[track_caller]
fn assert_same_motions(got: &[(bool, [f64; 3])], want: &[(bool, [f64; 3])]) {
    assert_eq!(got.len(), want.len(), "number of executed motions");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert_eq!(g.0, w.0, "motion {i}: rapid vs cutting");
        for a in 0..3 {
            assert!(
                (g.1[a] - w.1[a]).abs() <= 1e-6,
                "motion {i}: executed {:?}, expected {:?}",
                g.1,
                w.1
            );
        }
    }
}

fn machine(s: &Server, robot: &Robot, protocol: &str, extra: Value) -> i64 {
    let mut config = json!({"address": robot.addr, "protocol": protocol});
    for (k, v) in extra.as_object().unwrap() {
        config[k] = v.clone();
    }
    s.create_machine(
        &json!({"name": format!("robot-{protocol}"), "backend": "kawasaki-as", "config": config}),
    )
}

fn upload(s: &Server, m: i64, program: &str) -> i64 {
    s.upload(m, "prog", program.as_bytes().to_vec())["id"]
        .as_i64()
        .unwrap()
}

fn run_corpus_file(protocol: &str, file: &str) {
    let s = Server::start();
    let robot = Robot::start(s.root(), protocol, &[]);
    // The helical file has `G42 D08` (cutter compensation): the machine skips such lines
    // with a warning instead of refusing the program.
    let m = machine(
        &s,
        &robot,
        protocol,
        json!({"unsupported": "skip_with_warning"}),
    );
    let program = std::fs::read_to_string(corpus(file)).unwrap();
    let job = upload(&s, m, &program);
    s.job_action(job, "start").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], j["line_count"], "{j}");
    assert_same_motions(
        &robot.moves(),
        &expected(&program, Unsupported::SkipWithWarning),
    );
    assert!(robot.violations().is_empty(), "{:?}", robot.violations());
    // The robot's part zero is in the history.
    let zeros = s
        .get(&format!("/api/v1/machines/{m}/part-zero"))
        .expect(200);
    let z = &zeros[0];
    assert_eq!(z["source"], "robot", "{zeros}");
    assert_eq!(
        (z["x"].as_f64(), z["y"].as_f64(), z["z"].as_f64()),
        (Some(-400.0), Some(0.0), Some(-30.0))
    );
    // A second job against the same zero adds no duplicate record.
    let job2 = upload(&s, m, "G21 G90\nG0 X1 Y1 Z5\n");
    s.job_action(job2, "start").expect(200);
    s.wait_job_state(job2, "completed", T);
    let zeros = s
        .get(&format!("/api/v1/machines/{m}/part-zero"))
        .expect(200);
    assert_eq!(zeros.as_array().unwrap().len(), 1, "{zeros}");
}

#[test]
fn legacy_fusion_program_runs_to_completion() {
    run_corpus_file("legacy", FUSION);
}

#[test]
fn legacy_helical_program_runs_to_completion() {
    run_corpus_file("legacy", HELICAL);
}

#[test]
fn fresa_v1_fusion_program_runs_to_completion() {
    run_corpus_file("fresa-v1", FUSION);
}

#[test]
fn fresa_v1_helical_program_runs_to_completion() {
    run_corpus_file("fresa-v1", HELICAL);
}

#[test]
fn helical_program_is_refused_without_the_skip_policy() {
    let s = Server::start();
    let robot = Robot::start(s.root(), "legacy", &[]);
    let m = machine(&s, &robot, "legacy", json!({}));
    let program = std::fs::read(corpus(HELICAL)).unwrap();
    let msg = s
        .post_bytes(&format!("/api/v1/jobs?machine={m}&name=h"), program)
        .expect_error(422, "invalid_gcode");
    assert!(msg.contains("line 5"), "{msg}");
}

fn envelope_violation(protocol: &str) {
    let s = Server::start();
    let robot = Robot::start(s.root(), protocol, &[]);
    let m = machine(&s, &robot, protocol, json!({}));
    // Line 4 leaves the box (X 151 > 150) after two good lines.
    let job = upload(&s, m, "G21 G90\nG0 X0 Y0 Z5\nG1 X10 F600\nG1 X151\nG1 X0\n");
    let r = s.job_action(job, "start");
    let msg = r.expect_error(422, "backend_rejected");
    assert!(msg.contains("out_of_envelope"), "{msg}");
    assert!(msg.contains("line 4") && msg.contains("X151.000"), "{msg}");
    let j = s.job(job);
    assert_eq!(j["state"], "failed", "{j}");
    // The robot got its greeting out, and then received nothing at all.
    let entries = robot.entries();
    assert!(
        entries.iter().any(|e| e["event"] == "connected"),
        "{entries:?}"
    );
    let received: Vec<_> = entries.iter().filter(|e| e.get("recv").is_some()).collect();
    assert!(received.is_empty(), "robot received {received:?}");
    assert!(robot.moves().is_empty());
}

/// The robot has no A axis: a program that turns A is refused at job start, naming the line,
/// and the robot receives nothing.
#[test]
fn a_axis_program_is_refused_naming_the_line_and_moves_nothing() {
    let s = Server::start();
    let robot = Robot::start(s.root(), "fresa-v1", &[]);
    let m = machine(&s, &robot, "fresa-v1", json!({}));
    let job = upload(
        &s,
        m,
        "G21 G90\nG0 X0 Y0 Z5\nG1 X10 F600\nG1 X20 A90\nG1 X0\n",
    );
    let msg = s
        .job_action(job, "start")
        .expect_error(422, "backend_rejected");
    assert!(msg.contains("line 4") && msg.contains("A axis"), "{msg}");
    assert_eq!(s.job(job)["state"], "failed");
    let received: Vec<_> = robot
        .entries()
        .into_iter()
        .filter(|e| e.get("recv").is_some())
        .collect();
    assert!(received.is_empty(), "robot received {received:?}");
    assert!(robot.moves().is_empty());
}

/// The robot's position is unknown until its run starts (the link opens then), so no
/// approach to a line can be planned or checked: a start at a line is refused `unsupported`
/// with that reason, and the robot receives nothing (not even a connection).
#[test]
fn a_start_at_a_line_is_refused_unsupported_saying_why_and_the_robot_gets_nothing() {
    let s = Server::start();
    let robot = Robot::start(s.root(), "fresa-v1", &[]);
    let m = machine(&s, &robot, "fresa-v1", json!({}));
    let job = upload(&s, m, &test_program());
    let msg = s
        .post(
            &format!("/api/v1/jobs/{job}/start"),
            &json!({"from_line": 10}),
        )
        .expect_error(422, "unsupported");
    assert!(
        msg.contains("kawasaki-as cannot start a program at a line safely")
            && msg.contains("link to the robot opens only when the run starts"),
        "{msg}"
    );
    let j = s.job(job);
    assert_eq!(
        (j["state"].as_str(), j["line"].as_i64()),
        (Some("failed"), Some(0)),
        "{j}"
    );
    s.job_action(job, "resume").expect_error(422, "unsupported");
    assert!(
        robot.entries().iter().all(|e| e["event"] != "connected"),
        "{:?}",
        robot.entries()
    );
    assert!(robot.moves().is_empty());
}

#[test]
fn legacy_envelope_violation_moves_nothing() {
    envelope_violation("legacy");
}

#[test]
fn fresa_v1_envelope_violation_moves_nothing() {
    envelope_violation("fresa-v1");
}

/// 120 lines: a rapid, then short moves with arcs (several motions per line).
fn test_program() -> String {
    let mut p = String::from("G21 G90\nG0 X0 Y0 Z5\nG1 Z-1 F300\n");
    for i in 0..40 {
        let (x, y) = (10 + i % 7, i % 10);
        p.push_str(&format!("G1 X{x} Y{y} F{}\n", 300 + 60 * (i % 5)));
        // A full circle of radius 2 back to the same point: many chords on one line.
        p.push_str(&format!("G2 X{x} Y{y} I-2 J0\n"));
        p.push_str("(comment)\n");
    }
    p.push_str("G0 Z5\nM30\n");
    p
}

fn link_drop(protocol: &str, mode: &str) {
    let s = Server::start();
    let robot = Robot::start(
        s.root(),
        protocol,
        &["--drop-after", "57", "--drop-mode", mode],
    );
    let m = machine(&s, &robot, protocol, json!({}));
    let program = test_program();
    let job = upload(&s, m, &program);
    s.job_action(job, "start").expect(200);
    let j = s.wait_job_state(job, "failed", T);
    assert!(j["line"].as_i64().unwrap() > 0, "{j}");
    assert_eq!(robot.moves().len(), 57, "the sim dropped after 57 motions");
    s.job_action(job, "resume").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], j["line_count"]);
    let want = expected(&program, Unsupported::Error);
    let got = robot.moves();
    if protocol == "legacy" && mode == "before-done" {
        // The legacy protocol cannot know whether a motion whose `done` was lost ran: it is
        // sent again. Repeating an absolute move is a move of length zero.
        assert_eq!(got.len(), want.len() + 1);
        assert_eq!(got[56], got[57], "the repeated motion is the one in flight");
        let mut dedup = got.clone();
        dedup.remove(57);
        assert_same_motions(&dedup, &want);
    } else {
        assert_same_motions(&got, &want);
    }
    assert!(robot.violations().is_empty(), "{:?}", robot.violations());
}

#[test]
fn legacy_link_drop_resumes_at_the_next_motion() {
    link_drop("legacy", "after-done");
}

#[test]
fn legacy_lost_done_repeats_only_the_motion_in_flight() {
    link_drop("legacy", "before-done");
}

#[test]
fn fresa_v1_link_drop_resumes_at_the_next_motion() {
    link_drop("fresa-v1", "after-done");
}

#[test]
fn fresa_v1_lost_done_is_still_exact() {
    link_drop("fresa-v1", "before-done");
}

fn kill_mid_job(protocol: &str) {
    let mut s = Server::start();
    // 1 mm moves: ~7-10 ms each at this time scale.
    let robot = Robot::start(s.root(), protocol, &["--time-scale", "0.1"]);
    // legacy journals acknowledged motions next to the stored program by default.
    let m = machine(&s, &robot, protocol, json!({}));
    let program = fresa_tests::back_and_forth(300, 1.0, 600.0);
    let job = upload(&s, m, &program);
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "line >= 60", |j| j["line"].as_i64().unwrap() >= 60);
    s.restart_after_kill();
    assert_eq!(s.job(job)["state"], "interrupted");
    s.job_action(job, "resume").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], 300);
    let want = expected(&program, Unsupported::Error);
    let got = robot.moves();
    if protocol == "legacy" && got.len() == want.len() + 1 {
        // The motion in flight when the server died was executed, its `done` went nowhere,
        // and the resume sent it again: one zero-length repeat, nothing else.
        let i = got.windows(2).position(|w| w[0] == w[1]).expect("a repeat");
        let mut dedup = got.clone();
        dedup.remove(i + 1);
        assert_same_motions(&dedup, &want);
    } else {
        assert_same_motions(&got, &want);
    }
    assert!(robot.violations().is_empty(), "{:?}", robot.violations());
}

#[test]
fn legacy_server_sigkill_then_resume() {
    kill_mid_job("legacy");
}

#[test]
fn fresa_v1_server_sigkill_then_resume_is_exact() {
    kill_mid_job("fresa-v1");
}

#[test]
fn resume_refuses_a_changed_part_zero_until_confirmed() {
    let s = Server::start();
    let robot = Robot::start(
        s.root(),
        "fresa-v1",
        &[
            "--drop-after",
            "20",
            "--part-zero-after-reconnect",
            "-390,5,-30",
        ],
    );
    let m = machine(&s, &robot, "fresa-v1", json!({}));
    let job = upload(&s, m, &test_program());
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "failed", T);
    let msg = s
        .job_action(job, "resume")
        .expect_error(409, "part_zero_changed");
    assert!(
        msg.contains("(-390.000, 5.000, -30.000)") && msg.contains("(-400.000, 0.000, -30.000)"),
        "{msg}"
    );
    let moved = robot.moves().len();
    assert_eq!(moved, 20, "nothing moved after the refusal");
    // The new zero joins the history (the report is persisted by the event loop).
    fresa_tests::wait_for(T, "the new part zero in the history", || {
        let zeros = s
            .get(&format!("/api/v1/machines/{m}/part-zero"))
            .expect(200);
        (zeros[0]["x"] == -390.0 && zeros[0]["source"] == "robot").then_some(())
    });
    let r = s.post(
        &format!("/api/v1/jobs/{job}/resume"),
        &json!({"confirm_part_zero": true}),
    );
    r.expect(200);
    s.wait_job_state(job, "completed", T);
}

#[test]
fn as_program_download() {
    let s = Server::start();
    let v1 = Robot::start(s.root(), "fresa-v1", &[]);
    let m = machine(&s, &v1, "fresa-v1", json!({"window": 6}));
    let r = s.get(&format!("/api/v1/machines/{m}/as-program"));
    assert_eq!(r.status, 200, "{}", r.text);
    assert!(r.text.starts_with(".PROGRAM fresa_v1()"), "{}", r.text);
    assert!(r.text.contains("window 6"));
    let legacy = Robot::start(s.root(), "legacy", &[]);
    let l = machine(&s, &legacy, "legacy", json!({}));
    let msg = s
        .get(&format!("/api/v1/machines/{l}/as-program"))
        .expect_error(409, "not_available");
    assert!(msg.contains("legacy"), "{msg}");
    let sim = s.sim("plain", 0.0);
    s.get(&format!("/api/v1/machines/{}/as-program", sim.id))
        .expect_error(404, "no_artifact");
}

#[test]
fn pause_stops_sending_and_cancel_sends_exit() {
    let s = Server::start();
    let robot = Robot::start(s.root(), "legacy", &["--time-scale", "0.1"]);
    let m = machine(&s, &robot, "legacy", json!({}));
    let job = upload(&s, m, &fresa_tests::back_and_forth(300, 1.0, 600.0));
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "line >= 5", |j| j["line"].as_i64().unwrap() >= 5);
    s.job_action(job, "pause").expect(200);
    s.wait_machine_state(m, "paused", T);
    // Once the motion in flight is done, every motion received was executed and acknowledged
    // (one motion per line), and nothing more is sent while paused.
    let received = |r: &Robot| {
        r.entries()
            .iter()
            .filter(|e| e["recv"].as_str().is_some_and(|m| m.contains("MOVE")))
            .count()
    };
    let settled = fresa_tests::wait_for(T, "the robot to settle", || {
        let line = s.job(job)["line"].as_i64().unwrap() as usize;
        (robot.moves().len() == line && received(&robot) == line).then_some(line)
    });
    assert!(settled < 300);
    assert_eq!(s.status(m)["state"], "paused");
    assert_eq!(received(&robot), settled);
    s.job_action(job, "resume").expect(200);
    s.wait_job(job, T, "more lines", |j| {
        j["line"].as_i64().unwrap() as usize > settled + 5
    });
    let r = s.job_action(job, "cancel").expect(200);
    assert_eq!(r["state"], "cancelled");
    fresa_tests::wait_for(T, "EXIT at the robot", || {
        robot
            .entries()
            .iter()
            .any(|e| e["recv"] == "EXIT")
            .then_some(())
    });
    assert!(robot.moves().len() < 300);
}

fn garbage_is_skipped(protocol: &str) {
    let s = Server::start();
    let robot = Robot::start(
        s.root(),
        protocol,
        &["--garbage-every", "7", "--reply-delay-ms", "1"],
    );
    let m = machine(&s, &robot, protocol, json!({}));
    let program = test_program();
    let job = upload(&s, m, &program);
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "completed", T);
    assert_same_motions(&robot.moves(), &expected(&program, Unsupported::Error));
    assert!(s.log().contains("malformed robot message"), "{}", s.log());
}

#[test]
fn legacy_garbage_from_the_robot_is_logged_and_skipped() {
    garbage_is_skipped("legacy");
}

#[test]
fn fresa_v1_garbage_from_the_robot_is_logged_and_skipped() {
    garbage_is_skipped("fresa-v1");
}

#[test]
fn sigterm_mid_job_closes_the_link_and_resume_completes() {
    let mut s = Server::start();
    let robot = Robot::start(s.root(), "legacy", &["--time-scale", "0.1"]);
    let m = machine(&s, &robot, "legacy", json!({}));
    let program = fresa_tests::back_and_forth(300, 1.0, 600.0);
    let job = upload(&s, m, &program);
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "line >= 40", |j| j["line"].as_i64().unwrap() >= 40);
    let status = s.terminate();
    assert!(status.success(), "{status}\n{}", s.log());
    s.spawn().unwrap();
    assert_eq!(s.job(job)["state"], "interrupted");
    s.job_action(job, "resume").expect(200);
    s.wait_job_state(job, "completed", T);
    let want = expected(&program, Unsupported::Error);
    let mut got = robot.moves();
    // As after a crash: at most the motion in flight is repeated, with length zero.
    if got.len() == want.len() + 1 {
        let i = got.windows(2).position(|w| w[0] == w[1]).expect("a repeat");
        got.remove(i + 1);
    }
    assert_same_motions(&got, &want);
}

/// Speeds (mm/s) of the motions the robot executed, in order: (JMOVE?, speed).
fn executed_speeds(robot: &Robot) -> Vec<(bool, f64)> {
    robot
        .entries()
        .iter()
        .filter(|e| e["move"].is_string())
        .map(|e| (e["move"] == "JMOVE", e["speed"].as_f64().unwrap()))
        .collect()
}

fn overrides(s: &Server, m: i64) -> [f64; 3] {
    let st = s.status(m);
    ["feed_override", "spindle_override", "rapid_override"].map(|k| st[k].as_f64().unwrap())
}

/// The seed's robot program (legacy) fixes its own speeds and ignores any other command
/// without an answer: a feed override is refused through the API with that reason, nothing
/// changes (the status still says 100, the robot still cuts at 15 mm/s), and 100 % is accepted.
#[test]
fn legacy_refuses_a_feed_override_saying_why_and_changes_nothing() {
    let s = Server::start();
    let robot = Robot::start(s.root(), "legacy", &[]);
    let m = machine(&s, &robot, "legacy", json!({}));
    s.wait_machine_state(m, "idle", T);
    let path = format!("/api/v1/machines/{m}/overrides");
    let msg = s
        .post(&path, &json!({"feed": 50}))
        .expect_error(422, "backend_rejected");
    assert!(
        msg.starts_with("unsupported:")
            && msg.contains("SPEED 15 MM/S ALWAYS")
            && msg.contains("Unknown commands are ignored by the robot without an answer"),
        "{msg}"
    );
    let msg = s
        .post(&path, &json!({"spindle": 120}))
        .expect_error(422, "backend_rejected");
    assert!(msg.contains("potentiometer"), "{msg}");
    assert_eq!(overrides(&s, m), [100.0, 100.0, 100.0]);
    s.post(&path, &json!({"feed": 100})).expect(200);

    let job = upload(&s, m, "G21 G90\nG0 X1 Y1 Z2\nG1 Z-1 F300\nG1 X5\n");
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "completed", T);
    assert_eq!(
        executed_speeds(&robot),
        [(true, 10.0), (false, 15.0), (false, 15.0)]
    );
    assert!(robot.violations().is_empty(), "{:?}", robot.violations());
    assert_eq!(overrides(&s, m), [100.0, 100.0, 100.0]);
}

/// fresa-v1 carries a feed override: set during a run (motions of 1 mm at F600 = 10 mm/s,
/// 0.1 s each on the simulated robot), every cutting motion from the first one sent after it
/// runs at 5 mm/s, by the robot's own log; only the motions already in the window (4) keep
/// 10 mm/s. Every motion is executed exactly once; rapid and spindle overrides are refused.
#[test]
fn fresa_v1_applies_a_feed_override_from_the_next_command_sent() {
    let s = Server::start();
    let robot = Robot::start(s.root(), "fresa-v1", &["--time-scale", "1"]);
    let m = machine(&s, &robot, "fresa-v1", json!({}));
    s.wait_machine_state(m, "idle", T);
    let path = format!("/api/v1/machines/{m}/overrides");
    for body in [json!({"rapid": 50}), json!({"feed": 50, "spindle": 80})] {
        let msg = s.post(&path, &body).expect_error(422, "backend_rejected");
        assert!(msg.starts_with("unsupported:"), "{msg}");
    }
    assert_eq!(overrides(&s, m), [100.0, 100.0, 100.0]);

    let mut program = String::from("G21 G90\nG0 X0 Y0 Z-1\n");
    program.push_str(&fresa_tests::back_and_forth(40, 1.0, 600.0));
    let job = upload(&s, m, &program);
    s.job_action(job, "start").expect(200);
    fresa_tests::wait_for(T, "10 motions executed", || {
        (executed_speeds(&robot).len() >= 10).then_some(())
    });
    let before = executed_speeds(&robot).len();
    let asked_ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64;
    let answer = s.post(&path, &json!({"feed": 50})).expect(200);
    assert_eq!(
        answer,
        json!({"feed": 50.0, "spindle": 100.0, "rapid": 100.0})
    );
    s.wait_job_state(job, "completed", T);
    assert_same_motions(&robot.moves(), &expected(&program, Unsupported::Error));
    assert!(robot.violations().is_empty(), "{:?}", robot.violations());
    let cuts: Vec<f64> = executed_speeds(&robot)
        .into_iter()
        .filter(|(rapid, _)| !rapid)
        .map(|(_, v)| v)
        .collect();
    assert_eq!(cuts.len(), 40);
    // 10 mm/s up to some motion, 5 mm/s from the next one on: one change, no way back.
    let first_slow = cuts
        .iter()
        .position(|v| *v == 5.0)
        .expect("no motion at 5 mm/s");
    assert!(cuts[..first_slow].iter().all(|v| *v == 10.0), "{cuts:?}");
    assert!(cuts[first_slow..].iter().all(|v| *v == 5.0), "{cuts:?}");
    // The motions the robot had executed (one rapid among them) and those in the window
    // when the override came: at most the window (4) and the one in progress.
    let late = first_slow + 1 - before;
    // When the first slow motion started: when the one before it ended, by the robot's clock.
    let ends: Vec<u64> = robot
        .entries()
        .iter()
        .filter(|e| e["move"].is_string())
        .map(|e| e["at_ms"].as_u64().unwrap())
        .collect();
    let cut_index = |k: usize| {
        executed_speeds(&robot)
            .iter()
            .enumerate()
            .filter(|(_, (rapid, _))| !rapid)
            .nth(k)
            .map(|(i, _)| i)
            .unwrap()
    };
    eprintln!(
        "kawasaki fresa-v1 feed override: {late} motion(s) at the old speed after the command; \
         the first at 5 mm/s started {} ms after it",
        ends[cut_index(first_slow) - 1].saturating_sub(asked_ms)
    );
    assert!(
        late <= 5,
        "{late} motions at 10 mm/s after the override: {cuts:?}"
    );
    // The SPEED of the override went out with sequence number 0 (not a program command).
    assert!(robot
        .entries()
        .iter()
        .any(|e| e["recv"] == "0,SPEED,5.000000" || e["recv"] == "0,SPEED,5"));
    assert_eq!(overrides(&s, m), [50.0, 100.0, 100.0]);
}
