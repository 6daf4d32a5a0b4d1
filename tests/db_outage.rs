//! The database restarted under a running job (issue 16, Faults). A server on a PostgreSQL of
//! this test's own (stopped like a crash, `pg_ctl stop -m immediate`, and started again):
//! while it is down no new motion starts (jog, MDI, job start and resume answer 503
//! `database_unavailable` naming the database), `/healthz` says `degraded` with the database's
//! outage, a running job goes on to its end, and pause and cancel still stop motion. When the
//! database returns, what was kept in memory lands: the run's stored line is the last line of the
//! sim's execution log, its end state is stored, no line ran twice, and the audit log holds the
//! job's state transitions.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_core::store::test_postgres::DedicatedPostgres;
use fresa_tests::{assert_every_line_once, back_and_forth, wait_for, Opts, Server, Sim};
use serde_json::Value;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);
/// 1 mm lines at 600 mm/min: 10 ms a line at time scale 0.1; 800 lines take about 8 s, long
/// enough to stop the database mid-job and check the refusals before the job ends.
const LINES: i64 = 800;
const TIME_SCALE: f64 = 0.1;

/// A server on a fresh database of `pg`.
fn server_on(pg: &DedicatedPostgres) -> Server {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let url = rt.block_on(pg.fresh_database());
    let mut s = Server::unstarted(Opts::default());
    s.write_config(&format!("database_url = \"{url}\"\n"));
    s.spawn()
        .unwrap_or_else(|e| panic!("server did not start: {e}"));
    s
}

fn start_slow_job(s: &Server, m: &Sim) -> (i64, i64) {
    let job = s.upload(m.id, "slow", back_and_forth(LINES as usize, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let run = s.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    (job, run)
}

/// Stops the database and waits until the server has noticed (`/healthz` names the outage).
fn stop_database(s: &Server, pg: &DedicatedPostgres) -> Value {
    pg.stop();
    let health = wait_for(T, "/healthz to report the database outage", || {
        let h = s.get("/healthz").expect(200);
        h.get("database").is_some().then_some(h)
    });
    assert_eq!(health["status"], "degraded", "{health}");
    assert_eq!(health["database"]["status"], "unavailable", "{health}");
    let message = health["database"]["message"].as_str().unwrap();
    assert!(
        message.contains(&format!("127.0.0.1:{}", pg.port)) && message.contains("since"),
        "the outage names the database and since when: {message}"
    );
    health
}

/// A refusal for want of the database: 503, and a message naming it.
#[track_caller]
fn refused(r: fresa_tests::Resp, pg: &DedicatedPostgres) {
    let message = r.expect_error(503, "database_unavailable");
    assert!(
        message.contains(&format!("127.0.0.1:{}", pg.port)),
        "the refusal names the database: {message}"
    );
}

fn last_logged(m: &Sim, run: i64) -> i64 {
    m.lines_of(run).into_iter().max().unwrap_or(0)
}

/// The job's `job.state` events from the audit log, replayed from the start.
fn job_states(s: &Server, job: i64, until_state: &str) -> Vec<String> {
    let events = s.events("types=job.state", Some(0));
    let got = events.until(
        T,
        &format!("job {job} {until_state} in the audit log"),
        |e| e.job() == Some(job) && e.state() == Some(until_state),
    );
    got.iter()
        .filter(|e| e.job() == Some(job))
        .map(|e| e.state().unwrap_or_default().to_string())
        .collect()
}

#[test]
fn a_running_job_finishes_through_a_database_outage_and_every_line_is_stored_once() {
    let pg = DedicatedPostgres::start();
    let s = server_on(&pg);
    let m = s.sim("mill", TIME_SCALE);
    let spare = s.upload(m.id, "spare", "G1 X1 F600\n")["id"]
        .as_i64()
        .unwrap();
    let (job, run) = start_slow_job(&s, &m);
    wait_for(T, "the job to execute its first lines", || {
        (m.count_of(run) >= 20).then_some(())
    });

    stop_database(&s, &pg);
    let at_outage = m.count_of(run);
    // No new motion of any kind while the database is down.
    refused(s.jog(m.id, "X", 1.0), &pg);
    refused(s.mdi(m.id, "G0 X1"), &pg);
    refused(s.job_action(spare, "start"), &pg);

    // The running job goes on to its end with the database still down: the program is on the
    // node, and stopping mid-cut would spoil the part.
    wait_for(
        T,
        "the job to run to its last line during the outage",
        || (last_logged(&m, run) == LINES).then_some(()),
    );
    assert!(m.count_of(run) > at_outage, "lines ran during the outage");
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "the run ended in memory: {st}");
    assert!(
        s.get("/healthz").expect(200).get("database").is_some(),
        "the database was down all along"
    );

    pg.restart();
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["run"]["id"], run, "{j}");
    assert_eq!(
        j["line"].as_i64(),
        Some(last_logged(&m, run)),
        "the stored line is the last executed one: {j}"
    );
    assert_every_line_once(&m.executed(), run, LINES);
    let states = job_states(&s, job, "completed");
    assert_eq!(states, ["running", "completed"], "audit log of job {job}");
    let h = wait_for(T, "/healthz ok again", || {
        let h = s.get("/healthz").expect(200);
        (h["status"] == "ok").then_some(h)
    });
    assert!(h.get("database").is_none(), "{h}");
    // New motion is allowed again.
    s.job_action(spare, "start").expect(200);
    s.wait_job_state(spare, "completed", T);
}

#[test]
fn pause_and_cancel_stop_a_job_during_an_outage_and_are_stored_when_it_ends() {
    let pg = DedicatedPostgres::start();
    let s = server_on(&pg);
    let m = s.sim("mill", TIME_SCALE);
    let (job, run) = start_slow_job(&s, &m);
    wait_for(T, "the job to execute its first lines", || {
        (m.count_of(run) >= 20).then_some(())
    });
    stop_database(&s, &pg);

    let paused = s.job_action(job, "pause").expect(200);
    assert_eq!(paused["state"], "paused", "{paused}");
    let st = s.status(m.id);
    assert_eq!(st["job"]["run"], run, "{st}");
    refused(s.job_action(job, "resume"), &pg);
    let r = s.job_action(job, "cancel");
    if r.status != 200 {
        panic!("cancel: {r:?}\n{}", s.log());
    }
    let cancelled = r.body;
    assert_eq!(cancelled["state"], "cancelled", "{cancelled}");
    // Answered once motion stopped: the machine is idle and the run is over in memory.
    let st = s.wait_machine_state(m.id, "idle", T);
    assert!(st["job"].is_null(), "{st}");
    let executed = last_logged(&m, run);
    assert!(executed < LINES, "cancelled mid-job");

    pg.restart();
    let j = s.wait_job_state(job, "cancelled", T);
    assert_eq!(
        j["line"].as_i64(),
        Some(executed),
        "the stored line is the last executed one: {j}"
    );
    assert_eq!(
        last_logged(&m, run),
        executed,
        "nothing ran after the cancel"
    );
    let lines = m.lines_of(run);
    assert!(
        lines.iter().copied().eq(1..=executed),
        "every line up to {executed} once, in order"
    );
    let states = job_states(&s, job, "cancelled");
    assert_eq!(
        states,
        ["running", "paused", "cancelled"],
        "audit log of job {job}"
    );
}
