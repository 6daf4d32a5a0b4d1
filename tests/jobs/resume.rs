//! Crash safety: a server killed with SIGKILL (or stopped with SIGTERM) mid-job comes back with
//! the job `interrupted` at its last acknowledged line, and resuming it runs every remaining
//! line exactly once: the execution log, across all processes, holds each line once, in order.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{assert_every_line_once, back_and_forth, Server, Sim};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);
/// 300 lines of 1 mm at 600 mm/min: 10 ms a line at time scale 0.1, about 3 s in all.
const LINES: i64 = 300;

fn last_logged(m: &Sim, run: i64) -> i64 {
    m.executed()
        .iter()
        .filter(|e| e.0 == run)
        .map(|e| e.1)
        .max()
        .unwrap_or(0)
}

/// After a restart: the job is interrupted at a line between `at_least` and what the log holds,
/// the log did not grow, the machine is idle and the interruption is in the event log.
/// `(nth, exact_event)`: this is the job's `nth` interruption; its `job.state interrupted` event
/// names the job's line exactly (after SIGKILL it is written at start-up; on SIGTERM
/// acknowledgements may still land after it).
fn check_interrupted(
    s: &Server,
    m: &Sim,
    (job, run): (i64, i64),
    at_least: i64,
    logged: i64,
    (nth, exact_event): (usize, bool),
) -> i64 {
    let j = s.job(job);
    assert_eq!(j["state"], "interrupted", "{j}");
    assert_eq!(j["run"]["id"], run, "same run: {j}");
    let line = j["line"].as_i64().unwrap();
    assert!(
        line >= at_least && line <= logged,
        "interrupted at line {line}; acknowledged before the kill: {at_least}; logged: {logged}"
    );
    assert!(line < LINES, "the job had not finished: {j}");
    assert_eq!(last_logged(m, run), logged, "nothing ran before the resume");
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "{st}");
    let events = s.events("types=job.state", Some(0));
    let mut count = 0;
    let got = events.until(T, "the interrupted state", |e| {
        if e.job() == Some(job) && e.state() == Some("interrupted") {
            count += 1;
        }
        count == nth
    });
    let event_line = got.last().unwrap().data["data"]["line"].as_i64().unwrap();
    if exact_event {
        assert_eq!(event_line, line, "{:?}", got.last());
    } else {
        assert!(event_line <= line, "{:?}", got.last());
    }
    assert!(got.last().unwrap().data["data"]["run"] == run);
    // Nothing but resume or cancel may be done with it; a pause is refused.
    s.job_action(job, "pause").expect_error(409, "not_running");
    line
}

/// Uploads and starts a job long enough (at the sim's time scale) to be caught mid-run.
fn start_slow_job(s: &Server, m: &Sim) -> (i64, i64) {
    let job = s.upload(m.id, "slow", back_and_forth(LINES as usize, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    (job, run)
}

#[test]
fn sigkill_mid_job_then_resume_executes_every_line_exactly_once() {
    let mut s = Server::start();
    let m = s.sim("m", 0.1);
    let (job, run) = start_slow_job(&s, &m);

    // First crash, early in the job.
    let acked = s.wait_job(job, T, "line >= 40", |j| j["line"].as_i64().unwrap() >= 40)["line"]
        .as_i64()
        .unwrap();
    s.restart_after_kill();
    let logged = last_logged(&m, run);
    let line = check_interrupted(&s, &m, (job, run), acked, logged, (1, true));

    // Resume, let it get further, crash again.
    let r = s.job_action(job, "resume").expect(200);
    assert!(
        matches!(r["state"].as_str(), Some("running" | "completed")),
        "{r}"
    );
    assert_eq!(r["run"]["id"], run, "resume continues the same run");
    let acked = s.wait_job(job, T, "20 more lines", |j| {
        j["line"].as_i64().unwrap() >= line + 20
    })["line"]
        .as_i64()
        .unwrap();
    s.restart_after_kill();
    let logged = last_logged(&m, run);
    check_interrupted(&s, &m, (job, run), acked, logged, (2, true));

    // Resume to the end.
    s.job_action(job, "resume").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], LINES, "{j}");
    assert_every_line_once(&m.executed(), run, LINES);

    // A completed job stays completed across another restart and cannot be resumed.
    s.restart_after_kill();
    assert_eq!(s.job(job)["state"], "completed");
    s.job_action(job, "resume")
        .expect_error(409, "not_resumable");
}

#[test]
fn sigterm_mid_job_interrupts_it_and_resume_completes_it() {
    let mut s = Server::start();
    let m = s.sim("m", 0.1);
    let (job, run) = start_slow_job(&s, &m);
    let acked = s.wait_job(job, T, "line >= 30", |j| j["line"].as_i64().unwrap() >= 30)["line"]
        .as_i64()
        .unwrap();
    let status = s.terminate();
    assert!(
        status.success(),
        "clean shutdown exits 0: {status}\n{}",
        s.log()
    );
    assert!(s.log().contains("stopped"), "{}", s.log());
    s.spawn().unwrap();
    let logged = last_logged(&m, run);
    // A clean stop leaves the run interrupted, not cancelled (the backend reports the run it
    // stops on shutdown as cancelled; that report must not win).
    check_interrupted(&s, &m, (job, run), acked, logged, (1, false));

    s.job_action(job, "resume").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], LINES);
    assert_every_line_once(&m.executed(), run, LINES);
}

#[test]
fn an_interrupted_job_can_be_cancelled_instead() {
    let mut s = Server::start();
    let m = s.sim("m", 0.1);
    let job = s.upload(m.id, "slow", back_and_forth(LINES as usize, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "line >= 10", |j| j["line"].as_i64().unwrap() >= 10);
    s.restart_after_kill();
    assert_eq!(s.job(job)["state"], "interrupted");
    let r = s.job_action(job, "cancel").expect(200);
    assert_eq!(r["state"], "cancelled", "{r}");
    s.job_action(job, "resume")
        .expect_error(409, "not_resumable");
    // The machine is free for other work.
    let other = s.upload(m.id, "short", "G0 X1\n")["id"].as_i64().unwrap();
    s.job_action(other, "start").expect(200);
    s.wait_job_state(other, "completed", T);
}
