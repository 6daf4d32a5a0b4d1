//! The run-time estimate against real runs: corpus programs run on real-time sim machines
//! (scaled), timed by the sim's execution log (each line stamped when it finished), compared
//! with the upload's `estimated_seconds` and, mid-run, with the status's `remaining_s`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{corpus, Server};
use std::time::Duration;

const T: Duration = Duration::from_secs(120);

/// Three corpus programs without program pauses, each scaled to run about 10 s (their
/// nominal times are 4-8 min; 663, 1008 and 6549 lines).
const PROGRAMS: [(&str, f64); 3] = [
    ("fusion-1122_jig_28bit_first.nc", 0.025),
    ("linuxcnc-arcspiral.ngc", 0.04),
    ("fusion-1055_utab_265bit.nc", 0.025),
];

/// How far `measured` is from `expected`, as a fraction of `expected`.
fn error(measured: f64, expected: f64) -> f64 {
    (measured - expected).abs() / expected
}

/// The check: the estimate of a real-time sim job is within 5 % of its duration, for
/// three corpus programs; and half-way, the time left the status shows is within 5 % of the
/// time the rest of the run took. Both from the sim's own record (line stamps), in machine
/// time (stamps divided by the time scale).
#[test]
fn the_estimate_and_the_time_left_are_within_5_percent_of_real_time_sim_runs() {
    let s = Server::start();
    let mut report = Vec::new();
    // One after another: each is watched half-way.
    for (i, (name, scale)) in PROGRAMS.iter().enumerate() {
        let sim = s.sim(&format!("estimate-{i}"), *scale);
        s.wait_machine_state(sim.id, "idle", T);
        let program = std::fs::read(corpus(name)).unwrap();
        let up = s.upload(sim.id, name, program);
        let estimate = up["analysis"]["estimated_seconds"].as_f64().unwrap();
        assert!(
            up["analysis"].get("time_table").is_none(),
            "the answer leaves the time table out: {up}"
        );
        let job = up["id"].as_i64().unwrap();
        let lines = up["line_count"].as_i64().unwrap();
        let run = s.job_action(job, "start").expect(200)["run"]["id"]
            .as_i64()
            .unwrap();
        let (sim, job, run, name, scale, estimate, lines) =
            (&sim, &job, &run, *name, *scale, &estimate, &lines);
        // Half-way: the line the status speaks of, and its time left.
        let st = s.wait_status(sim.id, T, "half-way", |st| {
            st["job"]["line"].as_i64().unwrap_or(0) >= lines / 2
        });
        let at_line = st["job"]["line"].as_i64().unwrap();
        let left = st["job"]["remaining_s"].as_f64().unwrap_or_else(|| {
            panic!("no remaining_s in the status: {st}");
        });
        s.wait_job_state(*job, "completed", T);
        let times = sim.line_times(*run);
        let stamp = |line: i64| -> f64 {
            times
                .iter()
                .find(|(l, _)| *l == line)
                .map(|(_, t)| *t as f64)
                .unwrap_or_else(|| panic!("line {line} not stamped in {name}"))
        };
        let (first, last) = (times[0].1 as f64, times[times.len() - 1].1 as f64);
        let took = (last - first) / 1000.0 / scale;
        let rest = (last - stamp(at_line)) / 1000.0 / scale;
        report.push(format!(
            "{name}: estimate {estimate:.1} s, took {took:.1} s ({:+.2} %); at line {at_line} \
             {left:.1} s left, took {rest:.1} s ({:+.2} %)",
            (estimate - took) / took * 100.0,
            (left - rest) / rest * 100.0
        ));
        assert!(
            error(*estimate, took) < 0.05,
            "the estimate is off by more than 5 %: {report:?}"
        );
        assert!(
            error(left, rest) < 0.05,
            "the time left is off by more than 5 %: {report:?}"
        );
    }
    eprintln!("{}", report.join("\n"));
}

/// The time left follows the feed override: at 50 % the feed part of what is left doubles, in
/// the status at once (a real-time job).
#[test]
fn the_time_left_follows_the_feed_override() {
    let s = Server::start();
    let sim = s.sim("override-estimate", 0.05);
    s.wait_machine_state(sim.id, "idle", T);
    let program = std::fs::read(corpus("fusion-1122_jig_28bit_first.nc")).unwrap();
    let up = s.upload(sim.id, "jig", program);
    let job = up["id"].as_i64().unwrap();
    s.job_action(job, "start").expect(200);
    let before = s.wait_status(sim.id, T, "under way", |st| {
        st["job"]["line"].as_i64().unwrap_or(0) >= 20
    });
    let left = before["job"]["remaining_s"].as_f64().unwrap();
    s.post(
        &format!("/api/v1/machines/{}/overrides", sim.id),
        &fresa_tests::serde_json::json!({"feed": 50}),
    )
    .expect(200);
    // The jig spends 99.7 % of its time cutting: at 50 % nearly twice as much is left.
    let after = s.wait_status(sim.id, T, "the override in the time left", |st| {
        st["feed_override"] == 50.0
    });
    let slower = after["job"]["remaining_s"].as_f64().unwrap();
    assert!(
        slower > 1.8 * left * 0.95 && slower < 2.0 * left,
        "time left {left:.1} s at 100 %, {slower:.1} s at 50 %"
    );
    s.job_action(job, "cancel").expect(200);
}
