//! The command-line client against a real server.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{assert_every_line_once, corpus, fresa_cmd, output_text, Server};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn stdout(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

#[test]
fn machine_list_shows_the_demo_machine() {
    let s = Server::start_demo();
    let demo = s.get("/api/v1/machines").expect(200)[0]["id"]
        .as_i64()
        .unwrap();
    s.wait_machine_state(demo, "idle", T);
    let out = s.cli(&["machine", "list"]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    let row = text
        .lines()
        .find(|l| l.contains("demo"))
        .unwrap_or_else(|| panic!("no demo row: {text}"));
    let cols: Vec<&str> = row.split_whitespace().collect();
    assert_eq!(
        cols,
        [demo.to_string().as_str(), "demo", "sim-machine", "idle"]
    );
    assert!(text.lines().next().unwrap().contains("NAME"), "{text}");
}

#[test]
fn job_submit_start_then_watch_until_completed() {
    let s = Server::start();
    // The program takes ~34 s of machine time; at scale 0.03 about 1 s, so watch sees it live.
    let m = s.sim("m", 0.03);
    let file = corpus("cncjs-arc-xz-plane.gcode");
    let data = std::fs::read(&file).unwrap();
    let out = s.cli(&[
        "job",
        "submit",
        file.to_str().unwrap(),
        "--machine",
        &m.id.to_string(),
        "--start",
    ]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    let id: i64 = text
        .split_whitespace()
        .nth(1)
        .and_then(|w| w.parse().ok())
        .unwrap_or_else(|| panic!("no job id in {text:?}"));
    assert!(text.contains(&fresa_tests::sha256_hex(&data)), "{text}");
    assert!(text.contains(&format!("job {id} running")), "{text}");
    let job = s.job(id);
    assert_eq!(
        job["name"], "cncjs-arc-xz-plane.gcode",
        "the file name is the job name"
    );

    let out = s.cli(&["job", "watch", &id.to_string()]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    assert!(
        text.lines().last().unwrap_or("").contains("completed"),
        "{}",
        output_text(&out)
    );
    // watch returns only at the end: the job is completed by then.
    let job = s.job(id);
    assert_eq!(job["state"], "completed", "{job}");
    assert_every_line_once(&m.executed(), job["run"]["id"].as_i64().unwrap(), 3);

    // Watching a finished job prints its state and returns at once.
    let out = s.cli(&["job", "watch", &id.to_string()]);
    assert!(out.status.success(), "{}", output_text(&out));
    assert!(stdout(&out).contains("completed"), "{}", output_text(&out));
}

#[test]
fn cli_errors_name_the_problem_and_exit_non_zero() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let bad = corpus("cncjs-helical-thread-milling.gcode");
    let out = s.cli(&[
        "job",
        "submit",
        bad.to_str().unwrap(),
        "--machine",
        &m.id.to_string(),
    ]);
    assert!(!out.status.success(), "{}", output_text(&out));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("invalid_gcode") && err.contains("line 5, column 5"),
        "{}",
        output_text(&out)
    );
    s.assert_no_jobs();

    let out = s.cli(&["job", "watch", "4242"]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("unknown_job"),
        "{}",
        output_text(&out)
    );

    // No server there: a clear message, not a panic.
    let out = fresa_cmd()
        .args(["machine", "list", "--server", "http://127.0.0.1:9"])
        .output()
        .unwrap();
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("cannot reach"),
        "{}",
        output_text(&out)
    );
}
