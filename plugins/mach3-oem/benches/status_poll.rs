//! How long one status poll takes: the plugin's batch of 16 DRO/LED reads, over loopback TCP,
//! through the agent's Mach3 thread, to the simulator, and back. `cargo bench` measures; without
//! `--bench` (e.g. under `cargo test --all-targets`) it only smoke-runs a few batches.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_mach3_oem::agent::{Agent, AgentConfig};
use fresa_mach3_oem::client::AgentClient;
use fresa_mach3_oem::mach3::Call;
use fresa_mach3_oem::sim::{Mach3Sim, SimConfig};
use std::time::{Duration, Instant};

fn status_batch() -> Vec<Call> {
    let mut calls: Vec<Call> = [800, 801, 802, 803, 830, 831, 832, 833, 46, 816, 818, 821]
        .into_iter()
        .map(|code| Call::GetOemDro { code })
        .collect();
    calls.extend([800, 804, 805, 999].map(|code| Call::GetOemLed { code }));
    calls
}

fn main() {
    let measure = std::env::args().any(|a| a == "--bench");
    let batches = if measure { 20_000 } else { 50 };
    let dir = std::env::temp_dir().join(format!("mach3-bench-{}", std::process::id()));
    let sim = Mach3Sim::new(SimConfig::default());
    let cfg = AgentConfig {
        secret: "bench-secret".into(),
        call_timeout: Duration::from_secs(2),
        watchdog: Duration::from_secs(5),
        program_dir: dir.clone(),
    };
    let agent = Agent::bind("127.0.0.1:0", cfg, Box::new(move || Box::new(sim))).unwrap();
    let addr = agent.local_addr().unwrap().to_string();
    std::thread::spawn(move || agent.serve());
    let mut client = AgentClient::new(addr, "bench-secret".into(), Duration::from_secs(5));
    for _ in 0..100.min(batches) {
        client.batch(status_batch(), false).unwrap();
    }
    let mut times = Vec::with_capacity(batches);
    let start = Instant::now();
    for _ in 0..batches {
        let t = Instant::now();
        let r = client.batch(status_batch(), false).unwrap();
        times.push(t.elapsed());
        assert_eq!(r.len(), 16);
    }
    let total = start.elapsed();
    times.sort();
    let pct = |p: f64| times[((times.len() - 1) as f64 * p) as usize];
    println!(
        "status poll (16 calls, loopback, simulator): {batches} batches in {total:?}: \
         mean {:?}, p50 {:?}, p99 {:?}, max {:?}, {:.0} batches/s",
        total / batches as u32,
        pct(0.5),
        pct(0.99),
        times[times.len() - 1],
        batches as f64 / total.as_secs_f64()
    );
    let _ = std::fs::remove_dir_all(dir);
}
