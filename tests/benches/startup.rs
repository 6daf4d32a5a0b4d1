//! Start-up and idle memory (issue #29; README: Measurements): from exec of `fresa serve` to
//! its first `/healthz` 200, and its RSS 3 s later split into private (anonymous) memory and the
//! file-backed pages of the binary and libraries (shared, clean, reclaimable page cache).
//! Two cases: a first start with `--demo` on a fresh data directory (migrations, demo machine,
//! simulated pendant), and a restart of a plain server on an existing one.
//! A measurement, not a test: `cargo bench -p fresa-tests --bench startup [-- RUNS]` (default
//! 10). `FRESA_BIN` names another `fresa` build (its directory must hold the plugins).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn healthy(port: u16) -> bool {
    let Ok(mut s) = TcpStream::connect(("127.0.0.1", port)) else {
        return false;
    };
    let _ = s.set_read_timeout(Some(Duration::from_secs(1)));
    let req = "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n";
    let mut head = [0u8; 12];
    s.write_all(req.as_bytes()).is_ok()
        && s.read_exact(&mut head).is_ok()
        && head.starts_with(b"HTTP/1.1 200")
}

/// `RssAnon` and `RssFile` of `pid`, MiB.
fn rss(pid: u32) -> (f64, f64) {
    let mib = |field| fresa_tests::status_kib(pid, field) as f64 / 1024.0;
    (mib("RssAnon"), mib("RssFile"))
}

/// One start: milliseconds to ready, and the RSS split 3 s later.
fn start(fresa: &PathBuf, data_dir: &std::path::Path, demo: bool) -> (f64, (f64, f64)) {
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut cmd = Command::new(fresa);
    cmd.arg("serve")
        .args(demo.then_some("--demo"))
        .args(["--listen", &format!("127.0.0.1:{port}"), "--data-dir"])
        .arg(data_dir)
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    let t0 = Instant::now();
    let mut child = cmd.spawn().unwrap();
    while !healthy(port) {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "fresa never got ready"
        );
        std::thread::sleep(Duration::from_micros(500));
    }
    let ready = t0.elapsed().as_secs_f64() * 1e3;
    std::thread::sleep(Duration::from_secs(3));
    let mem = rss(child.id());
    // SIGTERM, as a service manager stops it: the next restart finds a clean data directory.
    let _ = Command::new("kill").arg(child.id().to_string()).status();
    child.wait().unwrap();
    (ready, mem)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let runs: usize = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .map_or(10, |a| a.parse().expect("RUNS: a number"));
    let fresa = std::env::var_os("FRESA_BIN").map_or_else(fresa_tests::fresa_bin, PathBuf::from);
    let kept = tempfile::tempdir().unwrap();
    // The restarts' data directory, made once beforehand (migrations applied).
    start(&fresa, kept.path(), false);
    for (case, demo) in [
        ("first start --demo, fresh data directory", true),
        ("restart", false),
    ] {
        let results: Vec<_> = (0..runs)
            .map(|_| {
                let fresh = tempfile::tempdir().unwrap();
                start(&fresa, if demo { fresh.path() } else { kept.path() }, demo)
            })
            .collect();
        let ready: Vec<f64> = results.iter().map(|r| r.0).collect();
        let (lo, hi) = (
            ready.iter().copied().fold(f64::MAX, f64::min),
            ready.iter().copied().fold(0.0, f64::max),
        );
        println!(
            "{case}: ready p50 {:.1} ms (min {lo:.1}, max {hi:.1}, {runs} runs); idle RSS {:.1} MiB \
             private + {:.1} MiB file-backed",
            median(ready),
            median(results.iter().map(|r| r.1 .0).collect()),
            median(results.iter().map(|r| r.1 .1).collect()),
        );
    }
}
