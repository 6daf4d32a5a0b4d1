//! How long an override takes to reach Mach3: (1) the agent batch that sets the FRO DRO, over
//! loopback TCP, through the agent's Mach3 thread, to the simulator and back (the DRO is
//! changed before the answer leaves, so this bounds "command to DRO changed" on the Fresa
//! side); (2) the plugin's whole `set_overrides` (that batch, then the status refresh the
//! answer waits for). The real Mach3 adds its own COM call and its planner's reaction, which
//! are not measured here. `cargo bench` measures; without `--bench` it only smoke-runs.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_mach3_oem::agent::{Agent, AgentConfig};
use fresa_mach3_oem::backend::Mach3Backend;
use fresa_mach3_oem::client::AgentClient;
use fresa_mach3_oem::mach3::{Call, Mach3};
use fresa_mach3_oem::sim::{Mach3Sim, SimConfig};
use fresa_plugin_api::backend::MachineBackend;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn summary(what: &str, mut times: Vec<Duration>) {
    times.sort();
    let n = times.len();
    let total: Duration = times.iter().sum();
    let pct = |p: f64| times[((n - 1) as f64 * p) as usize];
    println!(
        "{what}: {n} in {total:?}: mean {:?}, p50 {:?}, p99 {:?}, max {:?}",
        total / n as u32,
        pct(0.5),
        pct(0.99),
        times[n - 1]
    );
}

fn main() {
    let measure = std::env::args().any(|a| a == "--bench");
    let rounds = if measure { 5_000 } else { 20 };
    let dir = std::env::temp_dir().join(format!("mach3-override-bench-{}", std::process::id()));
    let mut sim = Mach3Sim::new(SimConfig::default());
    sim.do_oem_button(1021).unwrap(); // out of the start-up reset
    let mut check = sim.clone();
    let cfg = AgentConfig {
        secret: "bench-secret".into(),
        call_timeout: Duration::from_secs(2),
        watchdog: Duration::from_secs(5),
        program_dir: dir.clone(),
    };
    let agent = Agent::bind("127.0.0.1:0", cfg, Box::new(move || Box::new(sim))).unwrap();
    let addr = agent.local_addr().unwrap().to_string();
    std::thread::spawn(move || agent.serve());

    let mut client = AgentClient::new(addr.clone(), "bench-secret".into(), Duration::from_secs(5));
    let mut times = Vec::with_capacity(rounds);
    for k in 0..rounds {
        let value = 50.0 + (k % 2) as f64;
        let t = Instant::now();
        client
            .batch(vec![Call::SetOemDro { code: 821, value }], true)
            .unwrap();
        times.push(t.elapsed());
        assert_eq!(check.get_oem_dro(821).unwrap(), value);
    }
    summary("set FRO (one agent batch, DRO changed inside it)", times);

    // The plugin itself; its poller runs at 10 Hz alongside, as in service.
    let backend = Mach3Backend::new(
        &serde_json::json!({"agent": addr, "secret": "bench-secret"}),
        Arc::new(|_: &fresa_plugin_api::contract::Event| {}),
    )
    .unwrap();
    backend.connect().unwrap();
    let mut times = Vec::with_capacity(rounds);
    for k in 0..rounds {
        let value = 60.0 + (k % 2) as f64;
        let t = Instant::now();
        backend.set_overrides(Some(value), None, None).unwrap();
        times.push(t.elapsed());
        assert_eq!(check.get_oem_dro(821).unwrap(), value);
    }
    summary(
        "plugin set_overrides (set, then the status the answer reports)",
        times,
    );
    let _ = std::fs::remove_dir_all(dir);
}
