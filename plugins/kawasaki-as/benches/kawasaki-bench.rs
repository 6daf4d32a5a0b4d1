//! `kawasaki-bench`: streaming cost per line.
//!
//! 1. Overhead per line, stop-and-wait (legacy) and windowed (fresa-v1), with a zero-time
//!    simulated robot on loopback TCP: the plugin converts, sends, waits for `done`, and
//!    acknowledges every line; each event is serialised to JSON and parsed again on another
//!    thread, as the host and the server's event loop do.
//! 2. fresa-v1 pipelined throughput with a simulated 1 ms round trip, per window size
//!    (legacy with the same round trip for comparison).
//!
//! Run (from the workspace root):
//!   cargo bench -p fresa-kawasaki-as --bench kawasaki-bench
//! `cargo test --all-targets` runs it without `--bench`: a quick smoke run.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_kawasaki_as::sim::{self, SimConfig};
use fresa_kawasaki_as::{KawasakiMachine, Protocol};
use fresa_plugin_api::contract::Event;
use fresa_plugin_api::MachineBackend;
use serde_json::{json, Value};
use std::net::TcpListener;
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// `lines` lines, each one short feed move (one motion per line).
fn program(lines: usize) -> String {
    let mut s = String::from("G21 G90 G1 F600 X0 Y0 Z0\n");
    for i in 1..lines {
        s.push_str(&format!(
            "X{} Y{}\n",
            (i % 50) as f64 * 0.1,
            (i % 7) as f64 * 0.1
        ));
    }
    s
}

struct Outcome {
    lines: u32,
    elapsed: Duration,
    /// CPU time of the plugin's streaming thread plus the event consumer ("server side").
    server_cpu: Duration,
}

/// utime + stime of this process's threads named `names`, by thread id (Linux; empty elsewhere).
fn thread_cpu(names: &[&str]) -> Vec<(String, Duration)> {
    let tick = 100.0; // USER_HZ on Linux
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for t in dir.flatten() {
        let comm = std::fs::read_to_string(t.path().join("comm")).unwrap_or_default();
        if !names.contains(&comm.trim()) {
            continue;
        }
        let stat = std::fs::read_to_string(t.path().join("stat")).unwrap_or_default();
        // Fields after the `(comm)`: state is field 3, utime 14, stime 15.
        let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
        let f: Vec<&str> = rest.split_whitespace().collect();
        let ticks: f64 = f.get(11).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0)
            + f.get(12).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        out.push((
            t.file_name().to_string_lossy().into_owned(),
            Duration::from_secs_f64(ticks / tick),
        ));
    }
    out
}

fn run(
    protocol: Protocol,
    window: usize,
    rtt: Duration,
    lines: usize,
    dir: &std::path::Path,
) -> Outcome {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    sim::spawn(
        SimConfig {
            protocol,
            reply_delay: rtt,
            ..SimConfig::default()
        },
        listener,
    )
    .unwrap();
    // Events cross as JSON and are parsed on the consumer side, like host -> server.
    let (tx, rx) = mpsc::channel::<Vec<u8>>();
    let sink = Arc::new(move |e: &Event| {
        let _ = tx.send(serde_json::to_vec(e).unwrap());
    });
    let (done_tx, done_rx) = mpsc::channel::<u32>();
    std::thread::Builder::new()
        .name("bench-events".into())
        .spawn(move || {
            let mut last = 0;
            for bytes in rx {
                match serde_json::from_slice::<Event>(&bytes).unwrap() {
                    Event::LineAcknowledged { line, .. } => last = line,
                    Event::RunEnded { .. } => {
                        let _ = done_tx.send(last);
                    }
                    _ => {}
                }
            }
        })
        .unwrap();
    let m = KawasakiMachine::new(
        &json!({"address": addr.to_string(), "protocol": protocol.name(), "window": window}),
        sink,
        Arc::new(|_: &str| {}),
    )
    .unwrap();
    // A fresh file per round: legacy journals progress next to the program, per run id, and a
    // reused path would find this run already done.
    static ROUND: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let round = ROUND.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let path = dir.join(format!(
        "bench-{}-{window}-{lines}-{round}.nc",
        protocol.name()
    ));
    std::fs::write(&path, program(lines)).unwrap();
    let load: Value = m
        .request(json!({"op": "load_program", "run": 1, "path": path, "start_line": 1}))
        .unwrap();
    assert_eq!(load["lines"], lines as u64);
    let names = ["kawasaki-run-1", "bench-events"];
    let before: std::collections::HashMap<String, Duration> =
        thread_cpu(&names).into_iter().collect();
    let start = Instant::now();
    m.request(json!({"op": "run", "action": "start"})).unwrap();
    // The run thread ends with the run: sample its CPU time while it lives.
    let mut seen = std::collections::HashMap::new();
    let acked = loop {
        for (tid, cpu) in thread_cpu(&names) {
            seen.insert(tid, cpu);
        }
        match done_rx.recv_timeout(Duration::from_millis(20)) {
            Ok(a) => break a,
            Err(mpsc::RecvTimeoutError::Timeout) => continue,
            Err(e) => panic!("{e}"),
        }
    };
    let elapsed = start.elapsed();
    for (tid, cpu) in thread_cpu(&names) {
        seen.insert(tid, cpu);
    }
    let server_cpu = seen
        .iter()
        .map(|(tid, cpu)| cpu.saturating_sub(before.get(tid).copied().unwrap_or_default()))
        .sum();
    assert_eq!(acked as usize, lines, "every line acknowledged");
    Outcome {
        lines: acked,
        elapsed,
        server_cpu,
    }
}

fn report(what: &str, o: &Outcome) {
    let per_line = o.elapsed.as_secs_f64() / f64::from(o.lines);
    println!(
        "{what:<40} {:>6} lines {:>7.3} s {:>8.1} us/line {:>8.0} lines/s; server CPU {:>5.1} us/line",
        o.lines,
        o.elapsed.as_secs_f64(),
        per_line * 1e6,
        1.0 / per_line,
        o.server_cpu.as_secs_f64() / f64::from(o.lines) * 1e6
    );
}

fn main() {
    let smoke = !std::env::args().any(|a| a == "--bench");
    let dir = tempfile::tempdir().unwrap();
    let (zero_lines, rtt_lines) = if smoke { (200, 50) } else { (50_000, 3_000) };
    if smoke {
        println!("(smoke run: use `cargo bench` for real numbers)");
    }
    println!("zero-time robot (loopback TCP, no reply delay):");
    for _ in 0..if smoke { 1 } else { 3 } {
        report(
            "  legacy, stop-and-wait",
            &run(Protocol::Legacy, 1, Duration::ZERO, zero_lines, dir.path()),
        );
        report(
            "  fresa-v1, window 1 (stop-and-wait)",
            &run(Protocol::FresaV1, 1, Duration::ZERO, zero_lines, dir.path()),
        );
        report(
            "  fresa-v1, window 8",
            &run(Protocol::FresaV1, 8, Duration::ZERO, zero_lines, dir.path()),
        );
    }
    let rtt = Duration::from_millis(1);
    println!("simulated 1 ms round trip:");
    report(
        "  legacy, stop-and-wait",
        &run(Protocol::Legacy, 1, rtt, rtt_lines, dir.path()),
    );
    for window in [1, 2, 4, 8, 16] {
        report(
            &format!("  fresa-v1, window {window}"),
            &run(Protocol::FresaV1, window, rtt, rtt_lines, dir.path()),
        );
    }
}
