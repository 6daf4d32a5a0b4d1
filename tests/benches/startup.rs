//! Start-up and idle memory (issue #29; README: Measurements): from exec of `fresa serve` to
//! its first `/healthz` 200, and its RSS 3 s later split into private (anonymous) memory and the
//! file-backed pages of the binary and libraries (shared, clean, reclaimable page cache).
//! Two cases: a first start with `--demo` on a fresh data directory (migrations, demo machine,
//! simulated pendant), and a restart of a plain server on an existing one.
//! Then, for each case, one more start whose idle working set is read: the pages it touches in
//! the 10 s after that RSS reading (the accessed bits cleared through `/proc/PID/clear_refs`,
//! then smaps' `Referenced` summed). The RSS also holds what the start touched once (the routing
//! table, migrations) and the binary's pages the kernel maps around each fault; this says how
//! much of it the idle server actually uses.
//! Last, a first start `--demo` that is used (the OpenAPI document, 300 status polls, the
//! console's files), then left idle for 30 s: the memory a server that has served keeps while it waits.
//! First it says how many of the names `server/link/hot-functions.txt` lists the binary still
//! defines (see that directory's README).
//! A measurement, not a test: `cargo bench -p fresa-tests --bench startup [-- RUNS]` (default
//! 10). `FRESA_BIN` names another `fresa` build (its directory must hold the plugins).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// One GET on a connection of its own: the whole answer (`Connection: close`), or None when the
/// server does not take the connection or answer within a second.
fn get(port: u16, path: &str) -> Option<Vec<u8>> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(1))).ok()?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).ok()?;
    Some(answer)
}

fn healthy(port: u16) -> bool {
    get(port, "/healthz").is_some_and(|answer| answer.starts_with(b"HTTP/1.1 200"))
}

/// `RssAnon` and `RssFile` of `pid`, MiB.
fn rss(pid: u32) -> (f64, f64) {
    let mib = |field| fresa_tests::status_kib(pid, field) as f64 / 1024.0;
    (mib("RssAnon"), mib("RssFile"))
}

/// The pages `pid` touches during `window` from now, MiB: private (no file behind them), of the
/// `fresa` binary, and of the shared libraries. The last is an upper bound: a library's page
/// cache is shared, and another process's use can mark it referenced too.
fn working_set(pid: u32, window: Duration) -> [f64; 3] {
    std::fs::write(format!("/proc/{pid}/clear_refs"), "1").unwrap();
    std::thread::sleep(window);
    let mut kib = [0u64; 3];
    for m in fresa_tests::smaps(pid) {
        let which = match m.path.as_str() {
            path if path.starts_with('/') && path.ends_with("/fresa") => 1,
            path if path.starts_with('/') => 2,
            _ => 0,
        };
        kib[which] += m.kib("Referenced");
    }
    kib.map(|k| k as f64 / 1024.0)
}

/// A running `fresa serve`, stopped (SIGTERM) when dropped.
struct Started {
    child: std::process::Child,
    port: u16,
    /// From exec to the first `/healthz` 200.
    ready_ms: f64,
}

impl Started {
    /// RSS as `rss` gives it, after `wait`.
    fn rss_after(&self, wait: Duration) -> (f64, f64) {
        std::thread::sleep(wait);
        rss(self.child.id())
    }

    /// [`get`], which must answer 200.
    fn get(&self, path: &str) -> Vec<u8> {
        let answer = get(self.port, path).unwrap_or_else(|| panic!("GET {path}: no answer"));
        assert!(answer.starts_with(b"HTTP/1.1 200"), "GET {path}");
        answer
    }

    /// What its first users do: the OpenAPI document (after which the server unmaps the code
    /// only describing ran), 300 status polls, the console's page and every file it links.
    fn use_it(&self) {
        self.get("/api/v1/openapi.json");
        for _ in 0..300 {
            self.get("/api/v1/machines/1/status");
        }
        let page = String::from_utf8_lossy(&self.get("/")).into_owned();
        for attribute in ["src=\"", "href=\""] {
            for link in page.split(attribute).skip(1) {
                let link = link.split('"').next().unwrap_or_default();
                if !link.starts_with("http") {
                    self.get(&format!("/{}", link.trim_start_matches('/')));
                }
            }
        }
    }
}

impl Drop for Started {
    fn drop(&mut self) {
        // SIGTERM, as a service manager stops it: the next restart finds a clean data directory.
        let _ = Command::new("kill")
            .arg(self.child.id().to_string())
            .status();
        let _ = self.child.wait();
    }
}

/// Starts `fresa serve` and waits until it answers.
fn start(fresa: &PathBuf, data_dir: &std::path::Path, demo: bool) -> Started {
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
    let child = cmd.spawn().unwrap();
    while !healthy(port) {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "fresa never got ready"
        );
        std::thread::sleep(Duration::from_micros(500));
    }
    let ready_ms = t0.elapsed().as_secs_f64() * 1e3;
    Started {
        child,
        port,
        ready_ms,
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Of the names `server/link/hot-functions.txt` lists: how many the binary defines, how many of
/// those its code begins with (the link order applied), and how many it lists (`nm -n`). The
/// list goes stale as names change (see `server/link/README.md`).
fn hot_functions_found(fresa: &std::path::Path) -> Option<(usize, usize, usize)> {
    let list = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../server/link/hot-functions.txt"),
    )
    .ok()?;
    let listed: std::collections::HashSet<&str> = list.lines().filter(|l| !l.is_empty()).collect();
    let nm = Command::new("nm")
        .args(["-n", "--defined-only"])
        .arg(fresa)
        .output()
        .ok()?;
    // Functions in address order: `address t|T name`.
    let code: Vec<&str> = std::str::from_utf8(&nm.stdout)
        .ok()?
        .lines()
        .filter_map(|l| match l.split_whitespace().collect::<Vec<_>>()[..] {
            [_, "t" | "T", name] => Some(name),
            _ => None,
        })
        .collect();
    let found = code.iter().filter(|n| listed.contains(*n)).count();
    let first = code
        .iter()
        .take(found)
        .filter(|n| listed.contains(*n))
        .count();
    Some((found, first, listed.len()))
}

fn main() {
    let runs: usize = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .map_or(10, |a| a.parse().expect("RUNS: a number"));
    let fresa = std::env::var_os("FRESA_BIN").map_or_else(fresa_tests::fresa_bin, PathBuf::from);
    match hot_functions_found(&fresa) {
        Some((found, first, listed)) => println!(
            "server/link/hot-functions.txt: {found} of its {listed} names are in this binary \
             (record the list again below about 90 %), {first} of them first in its code \
             (a release build for x86-64 Linux links them first)"
        ),
        None => println!("server/link/hot-functions.txt: not compared (no nm, or no list)"),
    }
    let kept = tempfile::tempdir().unwrap();
    let idle = Duration::from_secs(3);
    // The restarts' data directory, made once beforehand (migrations applied).
    drop(start(&fresa, kept.path(), false));
    for (case, demo) in [
        ("first start --demo, fresh data directory", true),
        ("restart", false),
    ] {
        let results: Vec<_> = (0..runs)
            .map(|_| {
                let fresh = tempfile::tempdir().unwrap();
                let server = start(&fresa, if demo { fresh.path() } else { kept.path() }, demo);
                (server.ready_ms, server.rss_after(idle))
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
        let fresh = tempfile::tempdir().unwrap();
        let dir = if demo { fresh.path() } else { kept.path() };
        let window = Duration::from_secs(10);
        let server = start(&fresa, dir, demo);
        let (private, file) = server.rss_after(idle);
        let [own, binary, libraries] = working_set(server.child.id(), window);
        println!(
            "  of an RSS of {private:.1} + {file:.1} MiB, touched in the next {} s: {own:.1} MiB \
             private, {binary:.1} MiB of the binary, {libraries:.1} MiB of shared libraries (at most)",
            window.as_secs()
        );
    }
    // Used, then left alone: the memory a server that has served keeps while it waits.
    let fresh = tempfile::tempdir().unwrap();
    let server = start(&fresa, fresh.path(), true);
    let before = server.rss_after(idle);
    server.use_it();
    let settle = Duration::from_secs(30);
    let (private, file) = server.rss_after(settle);
    println!(
        "first start --demo, used (the OpenAPI document, 300 status polls, the console), then {} s \
         idle: RSS {private:.1} MiB private + {file:.1} MiB file-backed (before use {:.1} + {:.1})",
        settle.as_secs(),
        before.0,
        before.1
    );
}
