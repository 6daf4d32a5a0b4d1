//! Status polls against the framework's limit (README: Measurements, "Status reads"): a
//! release-built `fresa serve --demo` and a bare axum route serving the very bytes fresa answers
//! for `GET /api/v1/machines/1/status`, each pinned to CPU 0, loaded in turn by `wrk` pinned to
//! CPU 1, several rounds each (A B A B, so drift on a shared machine hits both alike).
//! A measurement, not a test:
//!
//! ```text
//! cargo build --release -p fresa-server -p fresa-sim-machine
//! cargo bench -p fresa-http --bench status [-- ROUNDS SECONDS CONNECTIONS]
//! ```
//!
//! `FRESA_BIN` names another `fresa` binary (its directory must hold the sim-machine plugin),
//! e.g. an older build to compare against. `--token` makes a viewer token first and sends it
//! with every request (to both servers: the bare route ignores it), as a client on the network
//! must. Needs `wrk` and `taskset` on PATH.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const PATH: &str = "/api/v1/machines/1/status";

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    // The bare server: `status --bare PORT FILE` (this binary started again by itself).
    if args.first().map(String::as_str) == Some("--bare") {
        bare(args[1].parse().unwrap(), &args[2]);
        return;
    }
    let with_token = args.iter().any(|a| a == "--token");
    let nums: Vec<u64> = args.iter().filter_map(|a| a.parse().ok()).collect();
    let rounds = nums.first().copied().unwrap_or(5);
    let seconds = nums.get(1).copied().unwrap_or(8);
    let connections = nums.get(2).copied().unwrap_or(32);

    let fresa = std::env::var_os("FRESA_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target/release/fresa"));
    assert!(
        fresa.is_file(),
        "no {} (cargo build --release -p fresa-server -p fresa-sim-machine)",
        fresa.display()
    );
    let data = tempdir();
    let token = with_token.then(|| create_token(&fresa, &data.join("data")));
    let fresa_port = free_port();
    let mut server = Killed(
        Command::new("taskset")
            .args(["-c", "0"])
            .arg(&fresa)
            .args(["serve", "--demo", "--listen"])
            .arg(format!("127.0.0.1:{fresa_port}"))
            .arg("--data-dir")
            .arg(data.join("data"))
            .arg("--plugin-dir")
            .arg(fresa.parent().unwrap())
            .env("FRESA_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start fresa"),
    );
    let body = wait_for_status(fresa_port);
    let file = data.join("status.json");
    std::fs::write(&file, &body).unwrap();
    let bare_port = free_port();
    let bare = Killed(
        Command::new("taskset")
            .args(["-c", "0"])
            .arg(std::env::current_exe().unwrap())
            .arg("--bare")
            .arg(bare_port.to_string())
            .arg(&file)
            .spawn()
            .expect("start the bare server"),
    );
    let bare_body = wait_for_status(bare_port);
    assert_eq!(
        bare_body.len(),
        body.len(),
        "the bare route serves other bytes"
    );
    println!(
        "{} bytes of status JSON; wrk -t1 -c{connections} -d{seconds}s, {rounds} rounds each{}",
        body.len(),
        if token.is_some() {
            ", with a token"
        } else {
            ""
        }
    );
    // Two figures per round: requests a second (what a client sees, but on a shared machine
    // it moves with whatever else runs), and the server's CPU time per request (user + system,
    // from /proc), which the neighbours disturb much less. Each as fresa / bare, so higher is
    // better for both.
    let (mut by_rate, mut by_cpu) = (Vec::new(), Vec::new());
    // Disturbance only ever slows a round down, so each server's best round is the least
    // disturbed figure of it.
    let (mut best_fresa, mut best_bare) = (0f64, 0f64);
    for round in 1..=rounds {
        let f = wrk(
            &server.0,
            fresa_port,
            seconds,
            connections,
            token.as_deref(),
        );
        let b = wrk(&bare.0, bare_port, seconds, connections, token.as_deref());
        println!(
            "round {round}: fresa {:>7.0} req/s {:>5.2} us CPU/req   bare axum {:>7.0} req/s {:>5.2} us CPU/req   {:>5.1} % {:>5.1} %",
            f.rate, f.cpu_us, b.rate, b.cpu_us,
            100.0 * f.rate / b.rate,
            100.0 * b.cpu_us / f.cpu_us
        );
        best_fresa = best_fresa.max(f.rate);
        best_bare = best_bare.max(b.rate);
        by_rate.push(f.rate / b.rate);
        by_cpu.push(b.cpu_us / f.cpu_us);
    }
    for (what, ratios) in [
        ("requests/s", &mut by_rate),
        ("CPU per request", &mut by_cpu),
    ] {
        ratios.sort_by(f64::total_cmp);
        println!(
            "median fresa / bare axum by {what}: {:.1} % (min {:.1} %, max {:.1} %)",
            100.0 * ratios[ratios.len() / 2],
            100.0 * ratios[0],
            100.0 * ratios[ratios.len() - 1]
        );
    }
    println!(
        "best round each: fresa {best_fresa:.0} req/s, bare axum {best_bare:.0} req/s: {:.1} %",
        100.0 * best_fresa / best_bare
    );
    let _ = server.0.kill();
    let _ = std::fs::remove_dir_all(&data);
}

/// A process killed when dropped (also when the bench panics).
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The same route with nothing around it: what axum and hyper cost by themselves, on a runtime
/// built as fresa builds its own (`Runtime::new`).
fn bare(port: u16, file: &str) {
    let body = axum::body::Bytes::from(std::fs::read(file).unwrap());
    let app = axum::Router::new().route(
        PATH,
        axum::routing::get(move || {
            let body = body.clone();
            async move {
                (
                    [(axum::http::header::CONTENT_TYPE, "application/json")],
                    body,
                )
            }
        }),
    );
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let l = tokio::net::TcpListener::bind(SocketAddr::from(([127, 0, 0, 1], port)))
            .await
            .unwrap();
        axum::serve(l, app).await.unwrap();
    });
}

/// A viewer token in the data directory `fresa serve` is about to open; gives its secret.
fn create_token(fresa: &std::path::Path, data: &std::path::Path) -> String {
    let out = Command::new(fresa)
        .args(["token", "create", "--role", "viewer", "--name", "bench"])
        .arg("--data-dir")
        .arg(data)
        .output()
        .expect("run fresa token create");
    assert!(out.status.success(), "fresa token create failed: {out:?}");
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    text.lines()
        .map(str::trim)
        .find(|l| l.starts_with("fresa_"))
        .unwrap_or_else(|| panic!("no secret in: {text}"))
        .to_string()
}

/// One `wrk` run's figures.
struct Load {
    rate: f64,
    /// The server's CPU time (user + system) per request, in microseconds.
    cpu_us: f64,
}

/// Requests a second with `wrk` (on CPU 1), and what they cost `server` in CPU time.
fn wrk(server: &Child, port: u16, seconds: u64, connections: u64, token: Option<&str>) -> Load {
    let mut wrk = Command::new("taskset");
    wrk.args(["-c", "1", "wrk", "-t1"]);
    if let Some(token) = token {
        wrk.arg("-H").arg(format!("Authorization: Bearer {token}"));
    }
    let cpu_before = cpu_seconds(server.id());
    let out = wrk
        .arg(format!("-c{connections}"))
        .arg(format!("-d{seconds}s"))
        .arg(format!("http://127.0.0.1:{port}{PATH}"))
        .output()
        .expect("run wrk (apt-get install wrk)");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        !text.contains("Non-2xx"),
        "some answers were not 200:\n{text}"
    );
    let cpu = cpu_seconds(server.id()) - cpu_before;
    let rate: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("Requests/sec:"))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no Requests/sec in wrk's output:\n{text}"));
    // "  1234567 requests in 8.00s, ..."
    let requests: f64 = text
        .lines()
        .find_map(|l| l.trim().split_once(" requests in "))
        .and_then(|(n, _)| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("no request count in wrk's output:\n{text}"));
    Load {
        rate,
        cpu_us: 1e6 * cpu / requests,
    }
}

/// A process's CPU time so far (user + system, all threads), from `/proc/PID/stat`.
fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // utime and stime are the 14th and 15th fields; counted after the command name's `)`,
    // since the name may hold blanks.
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    ticks / clock_ticks_per_second()
}

fn clock_ticks_per_second() -> f64 {
    static TICKS: std::sync::OnceLock<f64> = std::sync::OnceLock::new();
    *TICKS.get_or_init(|| {
        let out = Command::new("getconf").arg("CLK_TCK").output().unwrap();
        String::from_utf8_lossy(&out.stdout).trim().parse().unwrap()
    })
}

fn get(port: u16) -> Option<Vec<u8>> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(
        s,
        "GET {PATH} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).ok()?;
    let split = answer.windows(4).position(|w| w == b"\r\n\r\n")?;
    answer
        .starts_with(b"HTTP/1.1 200")
        .then(|| answer[split + 4..].to_vec())
}

fn wait_for_status(port: u16) -> Vec<u8> {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if let Some(body) = get(port) {
            return body;
        }
        assert!(Instant::now() < deadline, "no status from port {port}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn tempdir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("fresa-status-bench-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}
