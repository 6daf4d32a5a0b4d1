//! Many event streams (README: Measurements, "Event streams"): a release-built `fresa serve
//! --demo` whose machine runs a slow job (so it sends `status` at `status_rate_hz`, 10 a
//! second), STREAMS clients following `GET /api/v1/events?types=status`, and meanwhile status
//! reads and one stop on fresh connections (control must get through however many streams are
//! open). Prints the server's CPU and RSS, the events each stream received a second and the
//! control requests' latency. A measurement, not a test:
//!
//! ```text
//! cargo build --release -p fresa-server -p fresa-sim-machine
//! ulimit -n 65536; cargo bench -p fresa-http --bench events [-- STREAMS SECONDS [MAX_CONNECTIONS]]
//! ```
//!
//! The config is `max_event_streams = STREAMS` (and `max_connections = MAX_CONNECTIONS` when
//! given: a build whose streams count against `max_connections` needs more than STREAMS).
//! `FRESA_BIN` names another `fresa` binary (its directory must hold the sim-machine plugin).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

fn main() {
    let nums: Vec<u64> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let streams = nums.first().copied().unwrap_or(10_000) as usize;
    let seconds = nums.get(1).copied().unwrap_or(10);
    let max_connections = nums.get(2).copied();

    let fresa = std::env::var_os("FRESA_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../target/release/fresa")
        });
    assert!(fresa.is_file(), "no {}", fresa.display());
    let root = std::env::temp_dir().join(format!("fresa-events-bench-{}", std::process::id()));
    std::fs::create_dir_all(&root).unwrap();
    let mut config =
        format!("max_event_streams = {streams}\nmax_event_streams_per_client = {streams}\n");
    if let Some(n) = max_connections {
        config.push_str(&format!("max_connections = {n}\n"));
    }
    std::fs::write(root.join("fresa.toml"), config).unwrap();
    let port = free_port();
    let mut server = Killed(
        Command::new(&fresa)
            .args(["serve", "--demo", "--listen"])
            .arg(format!("127.0.0.1:{port}"))
            .arg("--data-dir")
            .arg(root.join("data"))
            .arg("--config")
            .arg(root.join("fresa.toml"))
            .arg("--plugin-dir")
            .arg(fresa.parent().unwrap())
            .env("FRESA_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start fresa"),
    );
    let pid = server.0.id();
    let deadline = Instant::now() + Duration::from_secs(60);
    while request(port, "GET", "/api/v1/machines/1/status", "").is_none() {
        assert!(Instant::now() < deadline, "the server did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
    let rss_idle = rss_kib(pid);
    // A slow job: the machine moves for minutes, so its status changes at every tick.
    let program = "G21 G90\nG1 X400 F60\nG1 X0\nM30\n";
    let job = request(port, "POST", "/api/v1/jobs?machine=1&name=bench", program).unwrap();
    let id = json_number(&job, "\"id\":").expect("job id");
    request(port, "POST", &format!("/api/v1/jobs/{id}/start"), "").unwrap();

    let rt = tokio::runtime::Runtime::new().unwrap();
    let events = Arc::new(AtomicU64::new(0));
    let open = Arc::new(AtomicUsize::new(0));
    let refused = Arc::new(AtomicUsize::new(0));
    let t0 = Instant::now();
    // In batches, each answered before the next: at the connection cap a connection whose head
    // was not read yet may be closed to make room (see README: Limits), as a burst of thousands
    // of connects would see.
    for i in 0..streams {
        if i % 256 == 0 {
            let deadline = Instant::now() + Duration::from_secs(60);
            while open.load(Ordering::Relaxed) + refused.load(Ordering::Relaxed) < i {
                assert!(Instant::now() < deadline, "streams stopped opening at {i}");
                std::thread::sleep(Duration::from_millis(5));
            }
        }
        let (events, open, refused) = (events.clone(), open.clone(), refused.clone());
        rt.spawn(async move {
            let Ok(mut s) = tokio::net::TcpStream::connect(("127.0.0.1", port)).await else {
                refused.fetch_add(1, Ordering::Relaxed);
                return;
            };
            let head = format!(
                "GET /api/v1/events?types=status HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n"
            );
            if s.write_all(head.as_bytes()).await.is_err() {
                refused.fetch_add(1, Ordering::Relaxed);
                return;
            }
            let mut buf = vec![0u8; 4096];
            let mut first = true;
            // `event: status` split across two reads is counted by the read that ends it.
            let mut tail: Vec<u8> = Vec::new();
            loop {
                let n = match s.read(&mut buf).await {
                    Ok(0) | Err(_) => {
                        if first {
                            refused.fetch_add(1, Ordering::Relaxed);
                        }
                        return;
                    }
                    Ok(n) => n,
                };
                if first {
                    first = false;
                    if !buf.starts_with(b"HTTP/1.1 200") {
                        refused.fetch_add(1, Ordering::Relaxed);
                        return;
                    }
                    open.fetch_add(1, Ordering::Relaxed);
                }
                tail.extend_from_slice(&buf[..n]);
                let needle = b"event: status";
                let count = tail.windows(needle.len()).filter(|w| w == needle).count();
                events.fetch_add(count as u64, Ordering::Relaxed);
                let keep = tail.len().min(needle.len() - 1);
                let cut = tail.len() - keep;
                tail.drain(..cut);
            }
        });
    }
    let deadline = Instant::now() + Duration::from_secs(120);
    while open.load(Ordering::Relaxed) + refused.load(Ordering::Relaxed) < streams {
        assert!(
            Instant::now() < deadline,
            "only {} of {streams} streams open",
            open.load(Ordering::Relaxed)
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    println!(
        "{} streams open, {} refused, in {:.2} s",
        open.load(Ordering::Relaxed),
        refused.load(Ordering::Relaxed),
        t0.elapsed().as_secs_f64()
    );
    let cpu0 = cpu_ticks(pid);
    let ev0 = events.load(Ordering::Relaxed);
    let t1 = Instant::now();
    // Control meanwhile: status reads on fresh connections, 5 a second.
    let mut lat = Vec::new();
    while t1.elapsed() < Duration::from_secs(seconds) {
        let t = Instant::now();
        assert!(request(port, "GET", "/api/v1/machines/1/status", "").is_some());
        lat.push(t.elapsed());
        std::thread::sleep(Duration::from_millis(200));
    }
    let wall = t1.elapsed().as_secs_f64();
    let cpu = (cpu_ticks(pid) - cpu0) as f64 / 100.0;
    let received = events.load(Ordering::Relaxed) - ev0;
    let rss = rss_kib(pid);
    let t = Instant::now();
    let stop = request(
        port,
        "POST",
        "/api/v1/machines/1/commands",
        "{\"command\":\"stop\"}",
    );
    let stop_ms = t.elapsed().as_secs_f64() * 1000.0;
    lat.sort();
    let open_n = open.load(Ordering::Relaxed).max(1);
    println!(
        "server CPU {:.1} % of one core; RSS {} MiB idle, {} MiB with the streams; \
         {:.1} status events a second per stream ({received} in {wall:.1} s)",
        100.0 * cpu / wall,
        rss_idle / 1024,
        rss / 1024,
        received as f64 / wall / open_n as f64
    );
    println!(
        "status read on a fresh connection: p50 {:.2} ms, max {:.2} ms ({} reads); a stop: {} in {stop_ms:.1} ms",
        lat[lat.len() / 2].as_secs_f64() * 1000.0,
        lat[lat.len() - 1].as_secs_f64() * 1000.0,
        lat.len(),
        if stop.is_some() { "answered 200" } else { "NOT answered" },
    );
    drop(rt);
    let _ = server.0.kill();
    let _ = std::fs::remove_dir_all(&root);
}

struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// One request on a fresh connection; the body of a 2xx answer.
fn request(port: u16, method: &str, path: &str, body: &str) -> Option<String> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(10))).ok()?;
    let kind = if body.starts_with('{') {
        "content-type: application/json\r\n"
    } else {
        ""
    };
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{kind}Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .ok()?;
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).ok()?;
    let text = String::from_utf8_lossy(&answer).into_owned();
    text.starts_with("HTTP/1.1 2")
        .then(|| text.split_once("\r\n\r\n").map(|(_, b)| b.to_string()))
        .flatten()
}

fn json_number(text: &str, key: &str) -> Option<i64> {
    let rest = &text[text.find(key)? + key.len()..];
    let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

/// utime + stime of `pid`, in clock ticks (100 a second on Linux).
fn cpu_ticks(pid: u32) -> u64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    let after = &stat[stat.rfind(')').unwrap() + 2..];
    let f: Vec<&str> = after.split(' ').collect();
    f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap()
}

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}
