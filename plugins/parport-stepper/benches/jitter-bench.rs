//! `jitter-bench`: how close the output loop keeps its writes to their absolute deadlines, on
//! the simulated port (which timestamps every write), stepping both motors every tick.
//!
//! Run (from the workspace root):
//!   cargo bench -p fresa-parport-stepper --bench jitter-bench -- [--hz 20000] [--secs 5] [--cpu N] [--spin-us 20] [--no-rt | --fifo]
//! `--cpu N` pins the loop to CPU N (pick an idle one). The loop asks for the scheduling the
//! plugin's output thread would (`output::scheduling`: SCHED_FIFO, or nice -20 when it spins
//! whole ticks under the kernel's real-time throttling) and reports it; `--no-rt` asks for
//! none, `--fifo` for SCHED_FIFO whatever the throttling.
//! Under `cargo test --all-targets` (no `--bench` argument) it does a quick smoke run.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_parport_stepper::output::{
    pin_to_cpu, rt_throttle_limit, scheduling, tight_timer_slack, Output, Pacer, Scheduling,
};
use fresa_parport_stepper::port::{Register, SharedSimPort, SimPort};
use fresa_parport_stepper::Config;
use std::sync::{Arc, Mutex};
use std::time::Duration;

fn arg(name: &str) -> Option<f64> {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let hz = arg("--hz").unwrap_or(20_000.0);
    let secs = arg("--secs").unwrap_or(if full { 5.0 } else { 0.05 });
    let spin_us = arg("--spin-us").unwrap_or(20.0);
    if let Some(cpu) = arg("--cpu") {
        if let Err(e) = pin_to_cpu(cpu as usize) {
            println!("could not pin to CPU {cpu}: {e}");
        }
    }
    // As the plugin's output thread does.
    if let Err(e) = tight_timer_slack() {
        println!("could not set the timer slack: {e}");
    }
    let flag = |name: &str| std::env::args().any(|a| a == name);
    let always_spins = spin_us >= 1e6 / hz;
    let sched = if flag("--fifo") {
        Scheduling::RealTime
    } else {
        scheduling(!flag("--no-rt"), always_spins, rt_throttle_limit())
    };
    let applied = sched.apply();
    let ticks = (hz * secs) as u64;
    let config = serde_json::json!({"port": "sim", "tick_hz": hz, "spin_us": spin_us,
        "axes": {"x": {"max_rate": hz / 2.0}, "y": {"max_rate": hz / 2.0}}});
    let cfg = Config::from_json(&config).unwrap();
    let port = SharedSimPort(Arc::new(Mutex::new(SimPort::new(
        vec![],
        vec![],
        (ticks as usize + 16) * 2,
    ))));
    let period = Duration::from_secs_f64(1.0 / hz);
    let mut out = Output::new(
        &cfg,
        Box::new(port.clone()),
        Pacer::new(Some(period), Duration::from_secs_f64(spin_us / 1e6)),
        false,
    );
    out.pacer.restart();
    // deadlines[k]: when tick k + 1 is due (the loop waits for it at the end of tick k).
    let mut deadlines = Vec::with_capacity(ticks as usize);
    for k in 0..ticks {
        out.begin().unwrap();
        // Each motor steps every other tick, alternating: a data write every tick.
        let p = (k / 2) as i64;
        out.step([p, p + (k % 2) as i64]);
        out.end(true).unwrap();
        deadlines.push(out.pacer.deadline());
    }
    let writes: Vec<_> = port
        .lock()
        .writes
        .iter()
        .filter(|w| w.register == Register::Data)
        .copied()
        .collect();
    // Lateness of each write against its tick's absolute deadline (the write follows the
    // wait for that deadline). After an overrun the schedule shifts, so later ticks are
    // measured against the shifted deadlines.
    let mut late: Vec<f64> = writes
        .iter()
        .filter(|w| w.tick >= 1)
        .map(|w| {
            let due = deadlines[w.tick as usize - 1];
            w.at.saturating_duration_since(due).as_secs_f64() * 1e6
        })
        .collect();
    late.sort_by(|a, b| a.total_cmp(b));
    let mut gaps: Vec<f64> = writes
        .windows(2)
        .map(|w| (w[1].at - w[0].at).as_secs_f64() * 1e6 - period.as_secs_f64() * 1e6)
        .map(f64::abs)
        .collect();
    gaps.sort_by(|a, b| a.total_cmp(b));
    println!(
        "{hz} Hz, {ticks} ticks, spin {spin_us} us, scheduling: {sched:?}{}",
        match &applied {
            Ok(()) => String::new(),
            Err(e) => format!(" NOT applied ({e})"),
        }
    );
    println!(
        "lateness vs absolute deadline: p50 {:.1} us  p99 {:.1} us  max {:.1} us",
        percentile(&late, 0.5),
        percentile(&late, 0.99),
        late.last().unwrap()
    );
    // A stall (throttled, preempted) shows as one write late by its length: the schedule
    // shifts after it.
    let stalls: Vec<f64> = late.iter().copied().filter(|&us| us > 1000.0).collect();
    println!(
        "stalls over 1 ms: {}, {:.1} ms in all",
        stalls.len(),
        stalls.iter().fold(0.0, |a, b| a + b) / 1000.0
    );
    println!(
        "period error |interval - {:.0} us|: p50 {:.1} us  p99 {:.1} us  max {:.1} us; overruns {}",
        period.as_secs_f64() * 1e6,
        percentile(&gaps, 0.5),
        percentile(&gaps, 0.99),
        gaps.last().unwrap(),
        out.pacer.overruns
    );
}
