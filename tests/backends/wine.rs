//! The Windows build, run under Wine: the cross-built `fresa.exe` loads the `fresa_*.dll`
//! plugins through the C ABI, serves on a loopback port with a temporary data directory, runs
//! a corpus program to `completed` on a sim-machine, and stops cleanly on Ctrl-C (motion
//! stopped, the running job `interrupted`, resumable after a restart). Then the one-PC Mach3
//! set-up: the 32-bit Windows 7 `fresa-mach3-agent.exe --simulate` and `fresa.exe` with a
//! `mach3-oem` machine, both under Wine, and the check that this agent is a 32-bit program
//! importing nothing Windows 7 lacks. (`backends::mach3` runs every agent test against the same
//! 32-bit agent too.)
//!
//! Needs the Windows programs (`cargo build --workspace --target x86_64-pc-windows-gnu` and
//! `plugins/mach3-oem/build-win7-agent`, which `tests/run` does first) and Debian's
//! `wine`/`wine64`/`wine32:i386`; each missing piece fails the test naming the command or
//! package (see `support/wine.rs`).

#![cfg(target_os = "linux")]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{corpus, wait_for, wine, Opts, Server};
use serde_json::json;
use std::io::{BufRead, BufReader};
use std::process::{Child, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// Wine's first start of a process is slower than Linux's; generous, and only a bound.
const T: Duration = Duration::from_secs(120);

fn wine_server() -> Server {
    Server::start_with(Opts {
        wine: true,
        ..Opts::default()
    })
}

#[test]
fn fresa_exe_runs_a_corpus_program_on_the_sim_machine_dll_and_stops_cleanly_on_ctrl_c() {
    let mut s = wine_server();
    let health = s.get("/healthz").expect(200);
    assert_eq!(health["status"], "ok", "{health}");

    // The plugins are the DLLs beside fresa.exe, loaded through the C ABI.
    let plugins = s.get("/api/v1/plugins").expect(200);
    let sim = plugins["plugins"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "sim-machine")
        .unwrap_or_else(|| panic!("sim-machine not loaded: {plugins}"));
    assert!(
        sim["path"]
            .as_str()
            .unwrap()
            .ends_with("fresa_sim_machine.dll"),
        "{sim}"
    );
    assert_eq!(plugins["failures"], json!([]), "{plugins}");

    let m = s.sim("m", 0.0);
    let program = std::fs::read(corpus("linuxcnc-arcspiral.ngc")).unwrap();
    let job = s.upload(m.id, "spiral", program)["id"].as_i64().unwrap();
    let total = s.job(job)["line_count"].as_i64().unwrap();
    s.job_action(job, "start").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"].as_i64().unwrap(), total, "{j}");
    assert_eq!(j["percent"], 100.0, "{j}");
    // The Windows process wrote the backend's execution log where the Linux path says.
    let executed = std::fs::read_to_string(&m.log).unwrap();
    assert!(
        !executed.is_empty(),
        "empty execution log {}",
        m.log.display()
    );

    // A real-time run, interrupted by Ctrl-C (Wine turns SIGINT into the console's Ctrl-C).
    let slow = s.sim("slow", 1.0);
    let program = std::fs::read(corpus("linuxcnc-arcspiral.ngc")).unwrap();
    let job = s.upload(slow.id, "spiral-slow", program)["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "running past its first line", |j| {
        j["state"] == "running" && j["line"].as_i64().unwrap() >= 1
    });
    s.send_signal("INT");
    let status = s.wait_exit(T, "after Ctrl-C");
    assert!(status.success(), "{status}\n{}", s.log());
    let log = s.log();
    let stopped = log.find("motion stopped").expect("`motion stopped` logged");
    let drained = log.find("draining connections").expect("drain logged");
    assert!(
        stopped < drained,
        "motion stops before connections drain:\n{log}"
    );
    assert!(log.contains("run interrupted by shutdown"), "{log}");

    // Started again on the same data directory (the lock was released): the run is
    // `interrupted`, and resumes.
    s.spawn()
        .unwrap_or_else(|e| panic!("restart under Wine: {e}"));
    let j = s.job(job);
    assert_eq!(j["state"], "interrupted", "{j}");
    s.job_action(job, "resume").expect(200);
    s.wait_job_state(job, "running", T);
    s.job_action(job, "cancel").expect(200);
}

const SECRET: &str = "test-secret-0123456789";

/// The 32-bit Windows 7 `fresa-mach3-agent.exe --simulate` under Wine; killed when dropped.
struct Agent {
    child: Child,
    addr: String,
    _programs: tempfile::TempDir,
}

impl Agent {
    fn start() -> Agent {
        let programs = tempfile::tempdir().unwrap();
        let mut child = wine::command32(wine::win7_agent_exe())
            .args([
                "--simulate",
                "--listen",
                "127.0.0.1:0",
                "--time-scale",
                "0.01",
            ])
            .arg("--program-dir")
            .arg(wine::path(programs.path()))
            .env("FRESA_MACH3_SECRET", SECRET)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("start the 32-bit fresa-mach3-agent.exe under wine");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    // Nobody listens any more; keep draining so the agent never blocks.
                }
            }
        });
        let addr = wait_for(T, "the agent's `listening on` line", || {
            let line = rx.recv_timeout(Duration::from_millis(100)).ok()?;
            line.trim()
                .strip_prefix("listening on ")
                .map(str::to_string)
        });
        Agent {
            child,
            addr,
            _programs: programs,
        }
    }
}

impl Drop for Agent {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The one-PC set-up, all Windows programs: the 32-bit agent (here simulating Mach3) and the server
/// with a `mach3-oem` machine, a corpus program run to `completed`.
#[test]
fn mach3_agent_exe_and_fresa_exe_run_a_corpus_program_to_completion() {
    let agent = Agent::start();
    let s = wine_server();
    let m = s.create_machine(&json!({
        "name": "mach3", "backend": "mach3-oem", "max_jog_mm": 20.0,
        "config": {"agent": agent.addr, "secret": SECRET, "poll_hz": 20},
    }));
    // The simulated Mach3 starts in reset, like the real one.
    let st = s.wait_machine_state(m, "alarm", T);
    assert!(st["alarm"].as_str().unwrap().contains("reset"), "{st}");
    s.command(m, "reset", json!({})).expect(200);
    s.wait_machine_state(m, "idle", T);

    let program = std::fs::read(corpus("fusion-1122_jig_28bit_first.nc")).unwrap();
    let job = s.upload(m, "jig", program)["id"].as_i64().unwrap();
    let total = s.job(job)["line_count"].as_i64().unwrap();
    s.job_action(job, "start").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"].as_i64().unwrap(), total, "{j}");
    s.wait_machine_state(m, "idle", T);
}

/// `fresa.exe service ARGS` in the service test's own Wine prefix: exit status and output.
fn fresa_service(args: &[&str]) -> (bool, String) {
    let exe = wine::windows_bin_dir().join("fresa.exe");
    let mut cmd = wine::command_in(wine::service_prefix(), &exe);
    cmd.arg("service").args(args);
    let (status, out) = wine::output_within(
        cmd,
        T,
        &format!("fresa.exe service {}", args.join(" ")),
        "install Wine with `apt-get install wine wine64`",
    );
    (status.success(), out)
}

/// Uninstalls the service however the test ends, so the prefix never keeps it.
struct Uninstall(String);

impl Drop for Uninstall {
    fn drop(&mut self) {
        let _ = fresa_service(&["uninstall", "--data-dir", &self.0]);
    }
}

/// `fresa service install | start | status | stop | uninstall` against Wine's service manager:
/// the service `Fresa` runs `fresa.exe service run`, logs to `<data dir>\logs`, serves, and a
/// stop takes the graceful path (the running job `interrupted`). Wine has no setting for
/// "restart after an error exit", so install says so in a warning here; the restart actions
/// themselves are accepted. The Event Log is only Wine's debug channel here: not checked.
#[test]
fn fresa_service_installs_serves_stops_gracefully_and_uninstalls_under_wine() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    std::fs::write(data.join("fresa.toml"), "listen = \"127.0.0.1:0\"\n").unwrap();
    let data_arg = wine::path(&data);

    // Left over from an earlier run that was killed: start clean.
    if !fresa_service(&["status"]).1.contains("not installed") {
        let (ok, out) = fresa_service(&["uninstall"]);
        assert!(ok, "{out}");
    }
    let (ok, out) = fresa_service(&["install", "--data-dir", &data_arg]);
    let _uninstall = Uninstall(data_arg.clone());
    assert!(ok && out.contains("installed service Fresa"), "{out}");
    let (ok, out) = fresa_service(&["install", "--data-dir", &data_arg]);
    assert!(!ok && out.contains("already installed"), "{out}");
    // Wine starts automatic services whenever the prefix boots (its server exits 3 s after
    // the last Wine process), so it may already be running here.
    let status = fresa_service(&["status"]).1;
    assert!(
        status.contains("Fresa: stopped") || status.contains("Fresa: running"),
        "{status}"
    );
    assert_eq!(
        std::fs::read_to_string(data.join("fresa.toml")).unwrap(),
        "listen = \"127.0.0.1:0\"\n",
        "install keeps an existing config"
    );

    let (ok, out) = fresa_service(&["start"]);
    assert!(ok && out.contains("running"), "{out}");
    assert!(fresa_service(&["status"]).1.contains("Fresa: running"));

    // The port it picked, from its own log file.
    let log_text = || {
        std::fs::read_dir(data.join("logs"))
            .map(|d| {
                d.filter_map(|e| std::fs::read_to_string(e.ok()?.path()).ok())
                    .collect::<String>()
            })
            .unwrap_or_default()
    };
    let base = wait_for(T, "`service Fresa running on` in the log file", || {
        let text = log_text();
        let rest = text.split("service Fresa running on ").nth(1)?;
        Some(rest.split_whitespace().next()?.to_string())
    });
    let http = reqwest::blocking::Client::new();
    let health = http.get(format!("{base}/healthz")).send().unwrap();
    assert_eq!(health.status().as_u16(), 200);

    // A job running in real time when the stop comes.
    let machine: serde_json::Value = http
        .post(format!("{base}/api/v1/machines"))
        .json(&json!({"name": "m", "backend": "sim-machine", "config": {"time_scale": 1.0}}))
        .send()
        .unwrap()
        .json()
        .unwrap();
    let m = machine["id"].as_i64().unwrap();
    let program = std::fs::read(corpus("linuxcnc-arcspiral.ngc")).unwrap();
    let job: serde_json::Value = http
        .post(format!("{base}/api/v1/jobs?machine={m}&name=spiral"))
        .body(program)
        .send()
        .unwrap()
        .json()
        .unwrap();
    let job = job["id"].as_i64().unwrap();
    let started = http
        .post(format!("{base}/api/v1/jobs/{job}/start"))
        .send()
        .unwrap();
    assert_eq!(started.status().as_u16(), 200);

    let (ok, out) = fresa_service(&["stop"]);
    assert!(ok && out.contains("Fresa stopped"), "{out}");
    let text = log_text();
    let stopped = text
        .find("motion stopped")
        .expect("`motion stopped` in the log");
    assert!(
        text.find("run interrupted by shutdown")
            .is_some_and(|i| i < stopped),
        "the running job is interrupted before motion is reported stopped:\n{text}"
    );
    assert!(text.contains("fresa::serve: stopped"), "{text}");
    assert!(
        http.get(format!("{base}/healthz")).send().is_err(),
        "nothing listens after stop"
    );

    // Without --data-dir: the folder named is the one the service was installed with.
    let (ok, out) = fresa_service(&["uninstall"]);
    assert!(
        ok && out.contains("removed") && out.contains(&data_arg),
        "{out}"
    );
    assert!(fresa_service(&["status"]).1.contains("not installed"));
    assert!(data.join("fresa.db").is_file(), "uninstall keeps the data");
}

/// `parport-stepper` on Windows: a real port (Linux ppdev) is refused when the machine is
/// added, naming the platform; the simulated port works.
#[test]
fn the_parport_dll_refuses_a_real_port_naming_the_platform_and_accepts_sim() {
    let s = wine_server();
    let msg = s
        .post(
            "/api/v1/machines",
            &json!({"name": "lpt", "backend": "parport-stepper",
                    "config": {"port": "/dev/parport0"}}),
        )
        .expect_error(422, "invalid_config");
    assert!(
        msg.contains("/dev/parport0") && msg.contains("ppdev") && msg.contains("windows"),
        "{msg}"
    );
    let sim = s.create_machine(&json!({
        "name": "lpt-sim", "backend": "parport-stepper",
        "config": {"port": "sim", "realtime_priority": false},
    }));
    s.wait_machine_state(sim, "idle", T);
    let machines = s.get("/api/v1/machines").expect(200);
    assert_eq!(machines.as_array().unwrap().len(), 1, "{machines}");
}

/// What Windows 7 lacks and newer Rust builds import (each would stop the agent from starting
/// there, "entry point not found" or "DLL not found"): `dll!function`, `dll!` for any function
/// of that DLL, `!function` from any DLL.
const NEWER_THAN_WINDOWS_7: &[(&str, &str)] = &[
    (
        "bcryptprimitives.dll!ProcessPrng",
        "Windows 10: std's random numbers on *-pc-windows-*",
    ),
    ("!WaitOnAddress", "Windows 8: std's locks on *-pc-windows-*"),
    ("!WakeByAddressSingle", "Windows 8: std's locks"),
    ("!WakeByAddressAll", "Windows 8: std's locks"),
    (
        "!GetSystemTimePreciseAsFileTime",
        "Windows 8: std's SystemTime",
    ),
    ("!SetThreadDescription", "Windows 10 1607: thread names"),
    ("!GetThreadDescription", "Windows 10 1607: thread names"),
    ("!CreateFile2", "Windows 8"),
    ("!CopyFile2", "Windows 8"),
    ("!GetOverlappedResultEx", "Windows 8"),
    (
        "combase.dll!",
        "Windows 8: the `windows` crate's COM support",
    ),
    (
        "api-ms-win-core-winrt-error-l1-1-0.dll!",
        "Windows 8: the `windows` crate's errors",
    ),
    (
        "api-ms-win-core-synch-l1-2-0.dll!",
        "Windows 8: std's WaitOnAddress",
    ),
    (
        "ucrtbase.dll!",
        "the Universal CRT: Windows 10, an update on 7",
    ),
    (
        "propsys.dll!",
        "not on every Windows 7 install (Windows Search)",
    ),
];

/// Why `exe` would not load on 32-bit Windows 7: empty when it would.
fn windows_7_problems(exe: &std::path::Path) -> Vec<String> {
    let facts = wine::pe_facts(exe);
    let reviewed_path =
        fresa_tests::workspace_root().join("tests/fixtures/wine/win7-agent-imports.txt");
    let reviewed = std::fs::read_to_string(&reviewed_path).unwrap();
    let reviewed: std::collections::HashSet<&str> = reviewed
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .collect();
    let mut problems = Vec::new();
    if !facts.pe32 || facts.machine != 0x14c {
        problems.push(format!(
            "not a 32-bit (PE32, i386) program: PE32 {}, machine 0x{:x}",
            facts.pe32, facts.machine
        ));
    }
    for (what, v) in [
        ("subsystem", facts.subsystem_version),
        ("OS", facts.os_version),
    ] {
        if v > (6, 1) {
            problems.push(format!(
                "its {what} version {}.{} is above Windows 7's 6.1",
                v.0, v.1
            ));
        }
    }
    for import in &facts.imports {
        let (dll, function) = import.split_once('!').unwrap();
        let newer = NEWER_THAN_WINDOWS_7.iter().find(|(pattern, _)| {
            let (d, f) = pattern.split_once('!').unwrap();
            (d.is_empty() || d == dll) && (f.is_empty() || f == function)
        });
        if let Some((_, why)) = newer {
            problems.push(format!("imports {import} ({why})"));
        } else if !reviewed.contains(import.as_str()) {
            problems.push(format!(
                "imports {import}, not in {} (check it against Windows 7, then add it)",
                reviewed_path.display()
            ));
        }
    }
    problems
}

/// The agent that ships for Mach3 PCs is a 32-bit program that imports only what Windows 7 has;
/// the ordinary x86_64 build of the same source fails the same check (Windows 10's
/// `ProcessPrng`), which shows the check can fail.
#[test]
fn the_mach3_agent_for_windows_7_is_32_bit_and_imports_nothing_windows_7_lacks() {
    let problems = windows_7_problems(wine::win7_agent_exe());
    assert!(
        problems.is_empty(),
        "{} would not load on 32-bit Windows 7:\n{}",
        wine::win7_agent_exe().display(),
        problems.join("\n")
    );
    let facts = wine::pe_facts(wine::win7_agent_exe());
    assert!(
        facts
            .imports
            .iter()
            .any(|i| i == "oleaut32.dll!GetActiveObject"),
        "the agent attaches to Mach3 through COM: {:?}",
        facts.imports
    );

    let x64 = wine::windows_bin_dir().join("fresa-mach3-agent.exe");
    let problems = windows_7_problems(&x64);
    assert!(
        problems.iter().any(|p| p.contains("not a 32-bit"))
            && problems
                .iter()
                .any(|p| p.contains("bcryptprimitives.dll!ProcessPrng")),
        "the x86_64 build should fail the check: {problems:?}"
    );
}
