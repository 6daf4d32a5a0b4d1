//! A hung plugin does not starve STOP (issue 11). A tiny C backend (`tests/fixtures/
//! hang_plugin.c`, backend `hang`) answers everything at once except `jog`, which sleeps for a
//! minute. With `plugin_call_timeout_ms = 500`: the first jog times out (504), the machine is
//! then `unresponsive` and further jogs are refused at once (503) without new threads, `stop`
//! still gets through, another machine is unaffected, `/healthz` says `degraded`, and SIGTERM
//! still ends the process cleanly although the jog is still hung. Pause and cancel of a running
//! job are answered while an ordinary call (`as-program`) still hangs.

#![cfg(unix)]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{thread_count, workspace_root, Opts, Server};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::Duration;

/// Builds the hang plugin into `dir` as `libfresa_hang.so`.
fn build_hang_plugin(dir: &Path) -> PathBuf {
    let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let out = dir.join("libfresa_hang.so");
    let src = workspace_root().join("tests/fixtures/hang_plugin.c");
    let output = Command::new(&cc)
        .args([
            "-std=c11", "-Wall", "-Wextra", "-Werror", "-shared", "-fPIC",
        ])
        .arg("-I")
        .arg(workspace_root().join("plugin-api/include"))
        .arg(&src)
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap_or_else(|e| panic!("cannot run the C compiler `{cc}` (set $CC): {e}"));
    assert!(
        output.status.success(),
        "compiling {} failed:\n{}",
        src.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    out
}

/// The other machine keeps answering jog and stop with 200.
#[track_caller]
fn other_machine_answers(s: &Server, sim: i64, when: &str) {
    let r = s.jog(sim, "X", 1.0);
    assert_eq!(r.status, 200, "sim jog {when}: {}", r.text);
    let r = s.command(sim, "stop", json!({}));
    assert_eq!(r.status, 200, "sim stop {when}: {}", r.text);
}

#[track_caller]
fn assert_unresponsive(v: &Value, what: &str) {
    assert_eq!(v["state"], "unresponsive", "{what}: {v}");
    assert!(
        v["reason"].as_str().is_some_and(|r| !r.trim().is_empty()),
        "{what}: an unresponsive machine needs a reason: {v}"
    );
}

/// The hang plugin, built once per test process into a directory of its own under Cargo's
/// scratch directory for integration tests (so nothing is left in /tmp).
fn hang_plugin_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join("fresa-hang-plugin")
            .join(std::process::id().to_string());
        std::fs::create_dir_all(&dir).expect("create the plugin directory");
        build_hang_plugin(&dir);
        dir
    })
}

/// A server with the hang plugin and a 500 ms plugin call timeout, a `hang` machine H and a
/// sim machine S: `(server, H, S)`.
fn server_with_hang_machine() -> (Server, i64, i64) {
    let mut s = Server::unstarted(Opts {
        extra_plugin_dirs: vec![hang_plugin_dir().to_path_buf()],
        ..Opts::default()
    });
    s.write_config("plugin_call_timeout_ms = 500\n");
    s.spawn()
        .unwrap_or_else(|e| panic!("server did not start: {e}"));
    let loaded = s.get("/api/v1/plugins").expect(200);
    assert!(
        loaded["plugins"]
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p["name"] == "hang"),
        "the hang plugin was not loaded: {loaded}"
    );
    let h = s.create_machine(&json!({"name": "H", "backend": "hang"}));
    let sim = s.sim("S", 0.0).id;
    let st = s.status(h);
    assert_eq!(st["state"], "idle");
    // A C plugin written before machine I/O existed: it loads and reports none.
    assert_eq!(
        (&st["inputs"], &st["outputs"]),
        (&json!({}), &json!({})),
        "{st}"
    );
    (s, h, sim)
}

#[test]
fn a_hung_jog_times_out_then_the_machine_is_unresponsive_and_refuses_jogs_at_once() {
    let (s, h, _) = server_with_hang_machine();
    s.jog(h, "X", 1.0).expect_error(504, "backend_timeout");
    // The server's request log names a server error at ERROR (with DEBUG off, as by default).
    let line = s.wait_log(
        Duration::from_secs(10),
        "request failed with a server error",
    );
    for part in [
        "ERROR",
        "method=POST",
        &format!("/api/v1/machines/{h}/jog"),
        "status=504",
    ] {
        assert!(
            line.contains(part),
            "{part:?} is not in the log line {line:?}"
        );
    }
    assert_unresponsive(
        &s.get(&format!("/api/v1/machines/{h}")).expect(200),
        "GET machine H",
    );
    assert_unresponsive(&s.status(h), "GET machine H status");

    // Further jogs are refused at once, without a thread each.
    let pid = s.pid().unwrap();
    let before = thread_count(pid);
    for _ in 0..50 {
        s.jog(h, "X", 1.0).expect_error(503, "machine_unresponsive");
    }
    let after = thread_count(pid);
    assert!(
        after <= before + 4,
        "50 refused jogs grew the server from {before} to {after} threads"
    );
    assert_unresponsive(&s.status(h), "GET machine H status after 50 jogs");
}

#[test]
fn stop_and_another_machine_still_answer_while_a_jog_hangs() {
    let (s, h, sim) = server_with_hang_machine();
    other_machine_answers(&s, sim, "before the hang");
    let r = s.jog(h, "X", 1.0);
    assert_eq!(r.status, 504, "the hung jog: {}", r.text);
    other_machine_answers(&s, sim, "after H's jog timed out");
    // Stop has its own lane: it answers while the jog still hangs in the plugin.
    let r = s.command(h, "stop", json!({}));
    assert_eq!(r.status, 200, "stop on H while its jog hangs: {}", r.text);
    for _ in 0..10 {
        let _ = s.jog(h, "X", 1.0);
    }
    let r = s.command(h, "stop", json!({}));
    assert_eq!(
        r.status, 200,
        "stop on H after more jogs were tried: {}",
        r.text
    );
    other_machine_answers(&s, sim, "after stop on H");
}

#[test]
fn healthz_is_degraded_naming_the_unresponsive_machine() {
    let (s, h, _) = server_with_hang_machine();
    let health = s.get("/healthz").expect(200);
    assert_eq!(health["status"], "ok", "before the hang: {health}");
    let r = s.jog(h, "X", 1.0);
    assert_eq!(r.status, 504, "the hung jog: {}", r.text);
    let health = s.get("/healthz").expect(200);
    assert_eq!(health["status"], "degraded", "{health}");
    let listed = health["unresponsive_machines"]
        .as_array()
        .unwrap_or_else(|| panic!("no unresponsive_machines list: {health}"));
    assert!(
        listed.len() == 1 && (listed[0] == h || listed[0] == "H"),
        "unresponsive_machines must list H (id {h}) only: {health}"
    );
}

#[test]
fn sigterm_exits_cleanly_while_a_plugin_call_still_hangs() {
    let (mut s, h, sim) = server_with_hang_machine();
    let r = s.jog(h, "X", 1.0);
    assert_eq!(r.status, 504, "the hung jog: {}", r.text);
    other_machine_answers(&s, sim, "after H's jog timed out");
    // The jog sleeps for a minute in the plugin; the process must not wait for it.
    s.send_sigterm();
    let status = s.wait_exit(Duration::from_secs(20), "SIGTERM with a hung plugin call");
    assert!(status.success(), "exit status {status}:\n{}", s.log());
}

/// Pause and cancel of the running job are never queued behind an ordinary call: while H's
/// `as-program` call hangs in the plugin (the plugin marks the moment it begins) and the call
/// timeout is 30 s, pause and then cancel are answered with the run's new state, and the hung
/// request is still outstanding both times. The audit log (replayed from the start) records
/// running, paused, cancelled, in that order.
#[test]
fn pause_and_cancel_of_the_running_job_overtake_a_call_under_way() {
    let mut s = Server::unstarted(Opts {
        extra_plugin_dirs: vec![hang_plugin_dir().to_path_buf()],
        ..Opts::default()
    });
    s.write_config("plugin_call_timeout_ms = 30000\n");
    s.spawn()
        .unwrap_or_else(|e| panic!("server did not start: {e}"));
    let mark = s.root().join("hang-began");
    let h = s.create_machine(&json!({
        "name": "H", "backend": "hang", "config": {"mark": s.host_path(&mark)}
    }));
    let (job, run) = s.upload_and_start(h, "p.nc", "G1 X1 F100\n");
    assert_eq!(s.job(job)["state"], "running");

    let url = s.url(&format!("/api/v1/machines/{h}/as-program"));
    let hung = std::thread::spawn(move || {
        let client = reqwest::blocking::Client::builder()
            .timeout(Duration::from_secs(120))
            .build()
            .expect("client");
        client.get(url).send().map(|r| r.status().as_u16())
    });
    fresa_tests::wait_for(
        Duration::from_secs(20),
        "the as-program call to reach the plugin",
        || mark.exists().then_some(()),
    );

    let paused = s.job_action(job, "pause").expect(200);
    assert_eq!(paused["state"], "paused", "{paused}");
    assert!(
        !hung.is_finished(),
        "pause was answered only after the call it should overtake"
    );
    let cancelled = s.job_action(job, "cancel").expect(200);
    assert_eq!(cancelled["state"], "cancelled", "{cancelled}");
    assert!(
        !hung.is_finished(),
        "cancel was answered only after the call it should overtake"
    );
    assert_eq!(s.job(job)["state"], "cancelled");

    let events = s.events("types=job.state", Some(0));
    let seen = events.until(
        Duration::from_secs(10),
        "the cancel in the audit log",
        |e| e.data["data"]["run"] == run && e.state() == Some("cancelled"),
    );
    let states: Vec<_> = seen
        .iter()
        .filter(|e| e.data["data"]["run"] == run)
        .filter_map(|e| e.state())
        .collect();
    assert_eq!(states, ["running", "paused", "cancelled"]);
}
