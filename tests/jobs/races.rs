//! Cancel, stop and pause mean it (issue 11): on a real-time sim machine, once `cancel`, the
//! machine `stop` command or `pause` has answered 200, at most the one segment in flight may
//! still complete; no further program line starts, and a finished run's stored line never
//! rises afterwards. Each is tried many times with a varying delay (0..4 ms) after the start,
//! to hit the windows where the run is being loaded, started or between two lines.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{assert_every_line_once, back_and_forth, Resp, Server, Sim};
use serde_json::json;
use std::time::{Duration, Instant};

const T: Duration = Duration::from_secs(30);
/// Lines of the test program.
const LINES: usize = 400;

/// 400 moves of 0.05 mm at 600 mm/min: 5 ms a line in real time, 2 s for the whole program, so
/// a run is always caught mid-program and a line ends every few milliseconds.
fn program() -> String {
    back_and_forth(LINES, 0.05, 600.0)
}

/// The delay between the start's answer and the stopping request in try `i`: 0..4 ms. This is
/// the variable under test (where in the run the request lands), not a synchronisation.
fn delay(i: usize) -> Duration {
    Duration::from_millis((i % 5) as u64)
}

/// Execution-log lines of all runs so far (every earlier try has settled).
fn total(m: &Sim) -> usize {
    m.executed().len()
}

/// Starts `job` and sends `request` `d` after it: after the start's answer, or, when
/// `concurrent`, after the start request was sent (so it can land while the run is being
/// created, loaded or started). Returns the request's answer, the log length right after that
/// answer, and the start's answer.
fn start_then(
    s: &Server,
    m: &Sim,
    job: i64,
    d: Duration,
    concurrent: bool,
    request: impl FnOnce() -> Resp + Send,
) -> (Resp, usize, Resp) {
    if concurrent {
        std::thread::scope(|sc| {
            let started = sc.spawn(|| s.job_action(job, "start"));
            std::thread::sleep(d);
            let answer = request();
            let at = total(m);
            (answer, at, started.join().expect("start thread"))
        })
    } else {
        let started = s.job_action(job, "start");
        assert_eq!(started.status, 200, "start: {}", started.text);
        std::thread::sleep(d);
        let answer = request();
        let at = total(m);
        (answer, at, started)
    }
}

/// When the stopping request raced the start and was refused (the run did not exist yet, or
/// the backend had not got it): nothing was promised, so it is sent again now that the start
/// answered. Returns the 200 answer and the log length right after it, or `None` when the
/// start itself did not go through (nothing to stop).
fn retry_if_refused(
    first: (Resp, usize),
    started: &Resp,
    what: &str,
    again: impl FnOnce() -> Resp,
    m: &Sim,
) -> Option<(Resp, usize)> {
    let (answer, at) = first;
    assert!(
        started.status < 500,
        "{what}: start answered {}: {}",
        started.status,
        started.text
    );
    if answer.status == 200 {
        return Some((answer, at));
    }
    assert!(
        matches!(answer.status, 409 | 422),
        "{what}: refused with {}: {}",
        answer.status,
        answer.text
    );
    if started.status != 200 {
        return None;
    }
    let answer = again();
    assert_eq!(answer.status, 200, "{what}, once started: {}", answer.text);
    Some((answer, total(m)))
}

/// A run that was stopped: what the test saw once the machine was idle again.
struct Ended {
    job: i64,
    run: i64,
    /// The job's stored `line` once the machine was idle.
    line: i64,
    /// Execution-log lines of the run once the machine was idle.
    logged: usize,
}

/// Once the machine is idle after a stopping request that answered when the log held
/// `at_answer` lines (all runs): at most one more line (the segment in flight) was logged.
/// Returns what to re-check later.
fn settle(s: &Server, m: &Sim, job: i64, at_answer: usize, what: &str) -> Ended {
    s.wait_machine_state(m.id, "idle", T);
    let after = total(m);
    assert!(
        after <= at_answer + 1,
        "{what}: the execution log held {at_answer} lines when the request answered 200, \
         {after} once the machine was idle (at most 1 more may finish)"
    );
    let j = s.job(job);
    let run = j["run"]["id"]
        .as_i64()
        .unwrap_or_else(|| panic!("{what}: no run: {j}"));
    Ended {
        job,
        run,
        line: j["line"].as_i64().unwrap(),
        logged: m.count_of(run),
    }
}

/// Later (after all tries): no stopped run's stored line rose and its log did not grow.
fn recheck(s: &Server, m: &Sim, ended: &[Ended], state: &str) {
    for e in ended {
        let j = s.job(e.job);
        assert_eq!(j["run"]["id"], e.run, "{j}");
        assert_eq!(j["state"], state, "{j}");
        assert_eq!(
            j["line"].as_i64().unwrap(),
            e.line,
            "run {}: the stored line rose after the machine was idle: {j}",
            e.run
        );
        assert_eq!(
            m.count_of(e.run),
            e.logged,
            "run {}: lines were executed after the machine was idle",
            e.run
        );
        assert_every_line_once(&m.executed(), e.run, e.logged as i64);
    }
}

/// Three tries in four send the request while the start is in flight (the start's own work
/// takes a few milliseconds, so its phases are swept in 150 µs steps over 0..4.5 ms); every
/// fourth sends it 0..4 ms after the start answered.
fn concurrent(i: usize) -> bool {
    i % 4 != 3
}

/// The delay of try `i` (see [`concurrent`]).
fn delay_of(i: usize) -> Duration {
    if concurrent(i) {
        Duration::from_micros((i as u64 * 150) % 4500)
    } else {
        delay(i / 4)
    }
}

#[test]
fn cancel_stops_the_run_within_one_line_and_its_line_never_rises() {
    let s = Server::start();
    let m = s.sim("m", 1.0);
    let mut ended = Vec::new();
    for i in 0..40 {
        let what = format!("cancel try {i} (concurrent with start: {})", concurrent(i));
        let job = s.upload(m.id, &format!("cancel-{i}"), program())["id"]
            .as_i64()
            .unwrap();
        let (answer, at, started) = start_then(&s, &m, job, delay_of(i), concurrent(i), || {
            s.job_action(job, "cancel")
        });
        let Some((answer, at)) = retry_if_refused(
            (answer, at),
            &started,
            &what,
            || s.job_action(job, "cancel"),
            &m,
        ) else {
            continue;
        };
        assert_eq!(answer.body["state"], "cancelled", "{what}: {}", answer.text);
        let j = s.job(job);
        assert_eq!(j["state"], "cancelled", "{what}: right after cancel: {j}");
        ended.push(settle(&s, &m, job, at, &what));
    }
    assert!(
        ended.len() >= 20,
        "only {} tries got to cancel a run",
        ended.len()
    );
    recheck(&s, &m, &ended, "cancelled");
}

#[test]
fn machine_stop_ends_the_run_cancelled_within_one_line_and_its_line_never_rises() {
    let s = Server::start();
    let m = s.sim("m", 1.0);
    let mut ended = Vec::new();
    // Only after the start answered: a stop that overtakes a start still in flight may
    // legitimately find nothing to stop, and the start then runs.
    for i in 0..30 {
        let what = format!("stop try {i}");
        let job = s.upload(m.id, &format!("stop-{i}"), program())["id"]
            .as_i64()
            .unwrap();
        let (answer, at, _) = start_then(&s, &m, job, delay(i), false, || {
            s.command(m.id, "stop", json!({}))
        });
        assert_eq!(answer.status, 200, "{what}: {}", answer.text);
        // A stop aborts the program; the backend reports the run cancelled (as for cancel).
        s.wait_job_state(job, "cancelled", T);
        ended.push(settle(&s, &m, job, at, &what));
    }
    recheck(&s, &m, &ended, "cancelled");
}

#[test]
fn pause_holds_the_run_within_one_line_until_resume() {
    let s = Server::start();
    let m = s.sim("m", 1.0);
    let mut paused = 0;
    for i in 0..16 {
        let what = format!("pause try {i} (concurrent with start: {})", concurrent(i));
        let job = s.upload(m.id, &format!("pause-{i}"), program())["id"]
            .as_i64()
            .unwrap();
        let (answer, at, started) = start_then(&s, &m, job, delay_of(i), concurrent(i), || {
            s.job_action(job, "pause")
        });
        let Some((answer, at_answer)) = retry_if_refused(
            (answer, at),
            &started,
            &what,
            || s.job_action(job, "pause"),
            &m,
        ) else {
            continue;
        };
        paused += 1;
        assert_eq!(answer.body["state"], "paused", "{what}: {}", answer.text);
        let j = s.job(job);
        assert_eq!(j["state"], "paused", "{what}: right after pause: {j}");
        let run = j["run"]["id"].as_i64().unwrap();
        // Held: the machine is not executing (paused, or idle when the pause overtook the
        // start of motion; the spec is about lines, not about which of the two it shows).
        s.wait_status(m.id, T, "the machine to hold", |st| {
            matches!(st["state"].as_str(), Some("paused" | "idle"))
        });
        // An observation window, not a synchronisation: 100 ms is 20 lines' worth of motion,
        // and the log must not grow by more than the one segment in flight during it.
        let window = Instant::now() + Duration::from_millis(100);
        let mut most = total(&m);
        while Instant::now() < window {
            most = most.max(total(&m));
            std::thread::sleep(Duration::from_millis(5));
        }
        let before_resume = total(&m).max(most);
        assert!(
            before_resume <= at_answer + 1,
            "{what}: the execution log held {at_answer} lines when pause answered 200, \
             {before_resume} while paused (at most 1 more may finish)"
        );
        assert_eq!(s.job(job)["state"], "paused", "{what}");

        let answer = s.job_action(job, "resume").expect(200);
        assert_eq!(answer["state"], "running", "{what}: {answer}");
        let resumed_at = m.count_of(run);
        wait_lines(
            &m,
            run,
            resumed_at + 2,
            &format!("{what}: run after resume"),
        );
        s.job_action(job, "cancel").expect(200);
        s.wait_machine_state(m.id, "idle", T);
        // Paused and resumed: every line up to where it was cancelled ran once, in order.
        let lines = m.count_of(run);
        assert_every_line_once(&m.executed(), run, lines as i64);
    }
    assert!(paused >= 8, "only {paused} tries got to pause a run");
}

fn wait_lines(m: &Sim, run: i64, n: usize, what: &str) {
    fresa_tests::wait_for(T, &format!("{what}: {n} lines logged"), || {
        (m.count_of(run) >= n).then_some(())
    });
}
