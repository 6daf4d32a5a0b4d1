//! The command-line client against a real server.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json;
use fresa_tests::{assert_every_line_once, corpus, fresa_cmd, output_text, Server};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn stdout(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

#[test]
fn machine_list_shows_the_demo_machine() {
    let s = Server::start_demo();
    let listed = s.get("/api/v1/machines").expect(200);
    let demo = listed[0]["id"].as_i64().unwrap();
    // The node that drives it: this server, named after the host by default.
    let node = listed[0]["node"].as_str().unwrap().to_string();
    assert!(!node.is_empty());
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
        [
            demo.to_string().as_str(),
            "demo",
            "sim-machine",
            &node,
            "idle"
        ]
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
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cannot reach") && err.contains("--server") && err.contains("FRESA_URL"),
        "says how to name another server: {}",
        output_text(&out)
    );
}

#[test]
fn machine_list_aligns_its_columns() {
    let s = Server::start();
    s.sim("a-machine-with-a-rather-long-name", 0.0);
    s.sim("m2", 0.0);
    let out = s.cli(&["machine", "list"]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 3, "{text}");
    // Every column starts at the same character in every row.
    let starts = |l: &str| -> Vec<usize> {
        let mut v = vec![0];
        let b = l.as_bytes();
        for i in 1..b.len() {
            if b[i] != b' ' && b[i - 1] == b' ' {
                v.push(i);
            }
        }
        v
    };
    let header = starts(lines[0]);
    assert_eq!(header.len(), 5, "{text}");
    for l in &lines[1..] {
        assert_eq!(starts(l), header, "{text}");
    }
}

#[test]
fn job_watch_prints_lines_with_elapsed_and_remaining_when_not_a_terminal() {
    let s = Server::start();
    let m = s.sim("m", 0.03);
    let file = corpus("cncjs-arc-xz-plane.gcode");
    let (id, _) = s.upload_and_start(m.id, "arc", &std::fs::read_to_string(&file).unwrap());
    let out = s.cli(&["job", "watch", &id.to_string()]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    let progress: Vec<&str> = text.lines().filter(|l| l.starts_with("line ")).collect();
    assert!(!progress.is_empty(), "{text}");
    for l in &progress {
        assert!(
            l.contains('%') && l.contains("elapsed ") && l.contains("remaining "),
            "{l}"
        );
    }
    // The time left is the server's estimate by line (`remaining_s`), so it is known from the
    // first line and only goes down (a rate extrapolated from the lines so far is neither).
    let left: Vec<u64> = progress
        .iter()
        .map(|l| {
            let t = l.rsplit("remaining ").next().unwrap().trim();
            let parts: Vec<u64> = t
                .split(':')
                .map(|p| p.parse().unwrap_or_else(|_| panic!("{l}")))
                .collect();
            parts[0] * 3600 + parts[1] * 60 + parts[2]
        })
        .collect();
    assert!(left.windows(2).all(|w| w[0] >= w[1]), "{text}");
    // No terminal, no escape sequences.
    assert!(!text.contains('\u{1b}'), "{text:?}");
    let last = text.lines().last().unwrap();
    assert!(
        last.starts_with("completed at line") && last.contains("elapsed"),
        "{text}"
    );
}

#[test]
fn job_watch_draws_a_progress_bar_on_a_terminal() {
    let s = Server::start();
    let m = s.sim("m", 0.03);
    let file = corpus("cncjs-arc-xz-plane.gcode");
    let (id, _) = s.upload_and_start(m.id, "arc", &std::fs::read_to_string(&file).unwrap());
    // python3's pty module gives the CLI a terminal (python3 is in tests/run's list).
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import pty, sys; sys.exit(pty.spawn(sys.argv[1:]) >> 8)",
        ])
        .arg(fresa_tests::fresa_bin())
        .args(["job", "watch", &id.to_string(), "--server", &s.base])
        .output()
        .expect("python3 (apt-get install python3)");
    let text = stdout(&out);
    assert!(out.status.success(), "{}", output_text(&out));
    assert!(
        text.contains("remaining") && text.contains("elapsed"),
        "{text:?}"
    );
    assert!(
        text.contains("[=") || text.contains("=>"),
        "no bar in {text:?}"
    );
    // The bar is drawn in place (carriage returns / escapes), then the end is a plain line.
    assert!(text.contains('\r') || text.contains('\u{1b}'), "{text:?}");
    let last = text.lines().rfind(|l| !l.trim().is_empty()).unwrap();
    assert!(last.contains("completed at line"), "{text:?}");
}

/// `job watch` succeeds only for a completed job (a script's `watch && next` stops after a
/// cancelled one) and ends quietly, not with a panic, when its reader goes away (`| head -1`).
#[test]
#[cfg(unix)] // SIGPIPE
fn job_watch_exits_non_zero_for_a_cancelled_job_and_quietly_into_a_closed_pipe() {
    use std::io::{BufRead, Read};
    use std::os::unix::process::ExitStatusExt;
    let s = Server::start();
    let m = s.sim("m", 1.0);
    let (id, _) = s.upload_and_start(m.id, "long", &fresa_tests::back_and_forth(2000, 1.0, 600.0));
    let mut child = fresa_cmd()
        .args(["job", "watch", &id.to_string(), "--server", &s.base])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut reader = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut first = String::new();
    reader.read_line(&mut first).unwrap();
    assert!(first.starts_with(&format!("job {id} ")), "{first:?}");
    drop(reader); // the reader is gone, as `head -1` is after one line
    s.job_action(id, "pause").expect(200); // a state line for watch to write
    let status = fresa_tests::wait_for(T, "job watch to end", || child.try_wait().unwrap());
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(
        status.signal(),
        Some(13),
        "ended by SIGPIPE: {status} {err}"
    );

    s.job_action(id, "cancel").expect(200);
    s.wait_job_state(id, "cancelled", T);
    let out = s.cli(&["job", "watch", &id.to_string()]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(stdout(&out).contains("cancelled"), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains(&format!("job {id} ended cancelled")),
        "{}",
        output_text(&out)
    );
}

/// `fresa events` with a filter that can never match says so instead of printing nothing.
#[test]
fn events_refuses_unknown_types_and_machines() {
    let s = Server::start();
    for (args, needle) in [
        (["events", "--types", "bogus"], "bogus"),
        (["events", "--machine", "99"], "unknown_machine"),
    ] {
        let out = s.cli(&args);
        assert!(!out.status.success(), "{}", output_text(&out));
        assert!(
            String::from_utf8_lossy(&out.stderr).contains(needle),
            "{}",
            output_text(&out)
        );
    }
}

#[test]
fn events_follows_the_stream_with_filters() {
    let s = Server::start_demo();
    s.wait_machine_state(1, "idle", T);
    s.jog(1, "X", 1.0).expect(200);
    s.wait_machine_state(1, "idle", T);
    s.command(1, "zero", serde_json::json!({"axis": "X"}))
        .expect(200);
    let mut child = fresa_cmd()
        .args(["events", "--types", "machine.jog", "--after", "0", "--json"])
        .args(["--server", &s.base])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stdout).lines() {
            let Ok(line) = line else { return };
            if tx.send(line).is_err() {
                return;
            }
        }
    });
    // The replayed jog, then a live one; the command is filtered out.
    s.wait_machine_state(1, "idle", T);
    s.jog(1, "Y", 2.0).expect(200);
    let mut got = Vec::new();
    while got.len() < 2 {
        let line = rx.recv_timeout(T).expect("an event line");
        let v: serde_json::Value = serde_json::from_str(&line).unwrap();
        got.push(v);
    }
    child.kill().ok();
    child.wait().ok();
    assert!(got.iter().all(|v| v["type"] == "machine.jog"), "{got:?}");
    assert_eq!(got[0]["data"]["axis"], "X");
    assert_eq!(got[1]["data"]["axis"], "Y");

    // The plain format: id, UTC time, type, machine, actor, data.
    let mut child = fresa_cmd()
        .args([
            "events",
            "--types",
            "machine",
            "--machine",
            "1",
            "--after",
            "0",
        ])
        .args(["--server", &s.base])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut first = String::new();
    use std::io::BufRead;
    std::io::BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    child.kill().ok();
    child.wait().ok();
    let words: Vec<&str> = first.split_whitespace().collect();
    assert!(words[0].starts_with('#'), "{first}");
    assert!(words[1].ends_with('Z') && words[1].contains('T'), "{first}");
    assert!(words[2].starts_with("machine."), "{first}");
    assert_eq!(words[3], "machine=1", "{first}");
}

#[test]
fn gcode_check_refuses_nesting_bombs_and_absurd_numbers_without_aborting() {
    let dir = tempfile::tempdir().unwrap();
    let check = |name: &str, text: String| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        fresa_cmd()
            .args(["gcode", "check"])
            .arg(&path)
            .output()
            .unwrap()
    };
    for (name, text, parts) in [
        // As deep as a line may be (64 KiB): before the nesting bound, `gcode check` overflowed
        // its 8 MiB main thread from about 20,000 levels and died of SIGABRT.
        (
            "deep.nc",
            format!(
                "G21\nG1 X{}1{} F100\n",
                "[".repeat(30_000),
                "]".repeat(30_000)
            ),
            &["line 2, column 69", "limit of 64 levels"][..],
        ),
        (
            "deeper.nc",
            format!("G21\nG1 X{}1 F100\n", "-[".repeat(32_000)),
            &["line 2, column 69", "limit of 64 levels"],
        ),
        // 100,000 levels do not fit in one line: the line limit answers first.
        (
            "deepest.nc",
            format!(
                "G21\nG1 X{}1{} F100\n",
                "[".repeat(100_000),
                "]".repeat(100_000)
            ),
            &["line 2, column 1", "longer than 65536 bytes"],
        ),
        (
            "inf.nc",
            "G21 G90\nG1 X[10**300*10**300] F100\n".to_string(),
            &["line 2, column 13", "not a finite number"],
        ),
        (
            "dwell.nc",
            "G21 G90\nG4 P[10**300]\n".to_string(),
            &["line 2, column 4", "86400 s"],
        ),
    ] {
        let out = check(name, text);
        let text = output_text(&out);
        assert_eq!(out.status.code(), Some(1), "{name}: {text}");
        let err = String::from_utf8_lossy(&out.stderr);
        for p in parts {
            assert!(err.contains(p), "{name}: no {p:?} in {text}");
        }
    }
}

/// `gcode check` fails on what an upload fails on, in the same words, and says what a plain OK
/// would hide: no motion, no program end, the tools, dwell and maxima.
#[test]
fn gcode_check_gives_the_uploads_first_error_and_warns_where_ok_would_mislead() {
    let s = Server::start();
    let m = s.sim("m", 0.0);
    let dir = tempfile::tempdir().unwrap();
    let check = |path: &std::path::Path, extra: &[&str]| {
        fresa_cmd()
            .args(["gcode", "check"])
            .arg(path)
            .args(extra)
            .output()
            .unwrap()
    };
    let file = |name: &str, data: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, data).unwrap();
        p
    };

    let binary = b"G0 X1\nG1\0X2 F100\n";
    let upload = s
        .post_bytes(
            &format!("/api/v1/jobs?machine={}&name=bin", m.id),
            binary.to_vec(),
        )
        .expect_error(422, "binary_program");
    let out = check(&file("bin.nc", binary), &[]);
    assert_eq!(out.status.code(), Some(1), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains(&upload),
        "the upload's words ({upload:?}): {}",
        output_text(&out)
    );
    let out = check(dir.path(), &[]);
    assert_eq!(out.status.code(), Some(1), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("is a directory"),
        "{}",
        output_text(&out)
    );
    let out = check(&file("ok.nc", b"G0 X1\n"), &["--rapid", "0"]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("more than 0"),
        "{}",
        output_text(&out)
    );

    let out = check(
        &file("no-end.nc", b"G21 T2 M6\nG4 P1.5\nS8000 M3\nG1 X10 F300\n"),
        &[],
    );
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    for part in [
        "tools            T2",
        "dwell            1.5 s",
        "max feed         300.0 mm/min",
        "max spindle      8000 rpm",
        "warning: no program end (M2 or M30)",
    ] {
        assert!(text.contains(part), "no {part:?} in {text}");
    }
    assert!(!text.contains("moves nothing"), "{text}");
    let out = check(&file("still.nc", b"(only a comment)\nM30\n"), &[]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    assert!(
        text.contains("warning: the program moves nothing"),
        "{text}"
    );
    assert!(!text.contains("no program end"), "{text}");
}

/// `fresa events` without `--types` leaves out the 10 Hz `status` events, which would drown
/// everything else; `--types status` asks for them.
#[test]
fn events_hides_status_unless_asked() {
    use std::io::BufRead;
    let s = Server::start();
    let m = s.sim("m", 1.0);
    // `--after 0` replays the machine's `machine.created` first: once it is printed, the
    // stream is subscribed and sees everything live from then on.
    let follow = |types: Option<&str>| {
        let mut cmd = fresa_cmd();
        cmd.args(["events", "--after", "0", "--machine", &m.id.to_string()])
            .args(["--server", &s.base]);
        if let Some(t) = types {
            cmd.args(["--types", t]);
        }
        let mut child = cmd.stdout(std::process::Stdio::piped()).spawn().unwrap();
        let (tx, rx) = std::sync::mpsc::channel::<String>();
        let stdout = child.stdout.take().unwrap();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout)
                .lines()
                .map_while(Result::ok)
            {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        (child, rx)
    };
    let until = |rx: &std::sync::mpsc::Receiver<String>, what: &str| -> Vec<String> {
        let mut seen = Vec::new();
        let deadline = std::time::Instant::now() + T;
        loop {
            assert!(
                std::time::Instant::now() < deadline,
                "no {what} in {seen:?}"
            );
            if let Ok(l) = rx.recv_timeout(Duration::from_millis(100)) {
                let done = l.contains(what);
                seen.push(l);
                if done {
                    return seen;
                }
            }
        }
    };
    let (mut plain, plain_rx) = follow(None);
    let (mut status, status_rx) = follow(Some("status,machine.created,machine.command"));
    until(&plain_rx, " machine.created ");
    until(&status_rx, " machine.created ");
    s.jog(m.id, "X", 10.0).expect(200);
    s.wait_machine_state(m.id, "idle", T);
    s.command(m.id, "zero", serde_json::json!({"axis": "X"}))
        .expect(200);
    let with = until(&status_rx, " machine.command ");
    assert!(
        with.iter().any(|l| l.contains(" status ")),
        "--types status shows them: {with:?}"
    );
    // Everything the jog caused came before the zero's command, in stream order.
    let without = until(&plain_rx, " machine.command ");
    assert!(
        without.iter().any(|l| l.contains(" machine.jog ")),
        "{without:?}"
    );
    assert!(
        without.iter().all(|l| !l.contains(" status ")),
        "{without:?}"
    );
    let _ = plain.kill();
    let _ = status.kill();
    let _ = (plain.wait(), status.wait());
}

/// The README's "Try it with curl" block, run as written (only the address swapped for the test
/// server's) against the demo: every request succeeds (curl fails on an HTTP error, and the
/// script stops there), and the machine and job end as the block says.
#[test]
fn the_readmes_curl_walk_through_runs_top_to_bottom() {
    let s = Server::start_demo();
    s.wait_machine_state(1, "idle", T);
    let root = fresa_tests::workspace_root();
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let block = readme
        .split("## Try it with curl")
        .nth(1)
        .and_then(|s| s.split("```sh\n").nth(1))
        .and_then(|s| s.split("```").next())
        .expect("the README's curl block");
    let script = format!(
        "set -euo pipefail\ncurl() {{ command curl --fail-with-body -S --max-time 90 \"$@\"; echo; }}\n{}",
        block.replace("http://127.0.0.1:7878", &s.base)
    );
    let out = std::process::Command::new("bash")
        .arg("-c")
        .arg(&script)
        .current_dir(&root)
        .output()
        .expect("bash");
    assert!(out.status.success(), "{}", output_text(&out));
    let offsets = s.get("/api/v1/machines/1/offsets").expect(200);
    let g55 = &offsets["offsets"]["G55"];
    assert_eq!(
        (g55["x"].as_f64(), g55["y"].as_f64()),
        (Some(10.0), Some(20.0)),
        "{offsets}"
    );
    let job = s.job(1);
    assert_eq!(
        (job["name"].as_str(), job["state"].as_str()),
        (Some("spiral"), Some("cancelled")),
        "{job}"
    );
    // X was zeroed where the 5 mm jog ended, not on the way (the block waits for idle).
    let g54 = &offsets["offsets"]["G54"];
    assert!((g54["x"].as_f64().unwrap() - 5.0).abs() < 1e-6, "{offsets}");
}

/// `fresa machine touch-off` sets Z from the plate and says what it changed; `fresa machine
/// probe` prints the trip, and exits non-zero when the whole distance ran without contact.
#[test]
fn machine_touch_off_and_probe_print_what_they_found() {
    let s = Server::start();
    let m = s.create_machine(&serde_json::json!({
        "name": "router", "backend": "sim-machine",
        "config": {"time_scale": 0, "travel": {"z": [-100, 0]},
                   "switches": {"probe": {"axis": "z", "at_or_below": -20}}},
    }));
    s.wait_machine_state(m, "idle", T);
    let id = m.to_string();
    let out = s.cli(&[
        "machine",
        "touch-off",
        &id,
        "--plate",
        "15",
        "--distance",
        "50",
        "--feed",
        "200",
    ]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    assert!(
        text.contains("machine Z -20.0000") && text.contains("-> -35.0000"),
        "{text}"
    );
    assert!(text.contains("Z now reads 20.0000"), "{text}");
    // `fresa machine probe ID --distance 10 --feed 200` and more.
    let probe = |more: &[&str]| {
        let mut args = vec!["machine", "probe", &id, "--distance", "10", "--feed", "200"];
        args.extend_from_slice(more);
        s.cli(&args)
    };
    let stderr = |out: &std::process::Output| String::from_utf8_lossy(&out.stderr).into_owned();
    // Back down onto the plate from 5 mm above it (Z -15 in machine terms).
    let out = probe(&["--toward", "-"]);
    assert!(out.status.success(), "{}", output_text(&out));
    assert!(
        stdout(&out).contains("tripped at X0.0000 Y0.0000 Z-20.0000"),
        "{}",
        output_text(&out)
    );
    // Looking for contact upwards while touching: refused outright.
    let out = probe(&["--toward", "+"]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        stderr(&out).contains("probe_already_in_state"),
        "{}",
        output_text(&out)
    );
    // Up off the plate until it opens.
    let out = probe(&["--toward", "+", "--release", "--json"]);
    assert!(out.status.success(), "{}", output_text(&out));
    let v: serde_json::Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(v["outcome"], "tripped", "{v}");
    // Further up there is nothing to touch.
    let out = probe(&["--toward", "+"]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        stderr(&out).contains("no contact within 10 mm"),
        "{}",
        output_text(&out)
    );
    // An edge touch-off needs its direction (and the tool's diameter): the server says which.
    let out = s.cli(&[
        "machine",
        "touch-off",
        &id,
        "--axis",
        "x",
        "--plate",
        "0",
        "--tool-diameter",
        "6",
        "--distance",
        "5",
        "--feed",
        "200",
    ]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        stderr(&out).contains("field `toward`"),
        "{}",
        output_text(&out)
    );
    // `gcode check` says a program probes, and what that means for its checks.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("probe.ngc");
    std::fs::write(&p, "G21 F100\nG38.2 Z-10\nG0 Z[#5063+2]\nG38.3 X5\nM2\n").unwrap();
    let out = fresa_cmd()
        .args(["gcode", "check"])
        .arg(&p)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    assert!(
        text.contains("probing          2 probing moves, first on line 2"),
        "{}",
        output_text(&out)
    );
    // Line 3 goes where the first probe tripped, and line 4's probe starts from there (its
    // target X5 keeps Z, so it differs too).
    assert!(
        text.contains("probe-dependent  2 moves, first on line 3"),
        "{}",
        output_text(&out)
    );
}

/// `fresa machine height-map` probes a grid, follows it and prints the heights (rows from the
/// highest Y down); `fresa job start ID --height-map HID` runs a job with it.
#[test]
fn machine_height_map_probes_a_grid_and_job_start_applies_it() {
    let s = Server::start();
    let m = s.create_machine(&serde_json::json!({
        "name": "leveller", "backend": "sim-machine",
        "config": {"time_scale": 0, "travel": {"z": [-20, 10]},
                   "switches": {"probe": {"axis": "z", "at_or_below": -1, "slope_x": 0.01}}},
    }));
    s.wait_machine_state(m, "idle", T);
    let id = m.to_string();
    let out = s.cli(&[
        "machine",
        "height-map",
        &id,
        "--x0",
        "0",
        "--x1",
        "10",
        "--y0",
        "-5",
        "--y1",
        "5",
        "--nx",
        "2",
        "--ny",
        "3",
        "--clearance",
        "1",
        "--distance",
        "4",
        "--feed",
        "300",
    ]);
    assert!(out.status.success(), "{}", output_text(&out));
    let text = stdout(&out);
    assert!(text.contains("(complete): 6 of 6 points"), "{text}");
    // The top row (Y 5): Z -1 at X 0, -0.9 at X 10.
    let top = text
        .lines()
        .find(|l| l.trim_start().starts_with("5.000"))
        .unwrap_or_else(|| panic!("no Y 5 row: {text}"));
    let cols: Vec<&str> = top.split_whitespace().collect();
    assert_eq!(cols, ["5.000", "-1.0000", "-0.9000"], "{text}");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("6/6"),
        "progress on stderr: {}",
        output_text(&out)
    );
    let hid = s
        .get(&format!("/api/v1/machines/{m}/height-maps"))
        .expect(200)[0]["id"]
        .as_i64()
        .unwrap();
    let job = s.upload(
        m,
        "cut.nc",
        "G0 Z1\nG0 X2 Y0\nG1 Z-0.1 F300\nG1 X8\nG0 Z1\n",
    )["id"]
        .as_i64()
        .unwrap();
    let out = s.cli(&[
        "job",
        "start",
        &job.to_string(),
        "--height-map",
        &hid.to_string(),
    ]);
    assert!(out.status.success(), "{}", output_text(&out));
    assert!(
        stdout(&out).contains(&format!("height map {hid}")),
        "{}",
        output_text(&out)
    );
    s.wait_job_state(job, "completed", T);
    assert_eq!(s.job(job)["run"]["height_map_id"], hid);
    // Too many points: the server's refusal, exit non-zero.
    let out = s.cli(&[
        "machine",
        "height-map",
        &id,
        "--x0",
        "0",
        "--x1",
        "10",
        "--y0",
        "0",
        "--y1",
        "5",
        "--nx",
        "51",
        "--ny",
        "2",
    ]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("invalid_field"),
        "{}",
        output_text(&out)
    );
}
