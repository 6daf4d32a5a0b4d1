//! `planner-bench`: throughput of the pure planner (no clock, no I/O).
//!
//! Run (from the workspace root):
//!   cargo bench -p fresa-parport-stepper --bench planner-bench
//! Under `cargo test --all-targets` (no `--bench` argument) it does a quick smoke run.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_parport_stepper::planner::{plan_program, Action, AxisLimits, Machine, Plan, Start};
use fresa_plugin_api::contract::WorkOffset;
use std::hint::black_box;
use std::time::{Duration, Instant};

fn machine() -> Machine {
    // The seed's router: 7 turns/cm x 200 steps = 140 steps/mm, 500 steps/s.
    let ax = AxisLimits {
        steps_per_mm: 140.0,
        max_rate: 500.0,
        start_rate: 100.0,
        accel: 2000.0,
    };
    Machine {
        axes: [ax, ax],
        tick_hz: 20_000.0,
        rapid_mm_min: 6000.0,
        lift_above_mm: 0.0,
        lift_settle_ticks: 1000,
        travel: [None, None],
    }
}

fn start() -> Start {
    Start {
        steps: [0, 0],
        z: 0.0,
        lift: false,
        offsets: [[0.0; 4]; 6],
        active: WorkOffset::G54,
    }
}

/// Walks every step of every move; returns (step slots, motor steps).
fn walk(plan: &Plan) -> (u64, u64) {
    let mut slots = 0u64;
    let mut motor = 0u64;
    let mut check = 0i64;
    for item in &plan.items {
        if let Action::Move(m) = &item.action {
            let mut prev = m.from;
            for s in m.steps() {
                slots += 1;
                motor += (s.pos[0] != prev[0]) as u64 + (s.pos[1] != prev[1]) as u64;
                prev = s.pos;
                check ^= s.tick as i64 ^ (s.deviation_mm.to_bits() as i64);
            }
        }
    }
    black_box(check);
    (slots, motor)
}

fn best_of(rounds: usize, mut f: impl FnMut() -> (u64, u64)) -> (Duration, (u64, u64)) {
    let mut best = Duration::MAX;
    let mut counts = (0, 0);
    for _ in 0..rounds {
        let t = Instant::now();
        counts = f();
        best = best.min(t.elapsed());
    }
    (best, counts)
}

fn report(name: &str, d: Duration, (slots, motor): (u64, u64)) {
    let s = d.as_secs_f64();
    println!(
        "{name:<38} {:>8.1} ms  {:>11} step slots  {:>7.1} M slots/s  {:>7.1} M motor steps/s",
        s * 1e3,
        slots,
        slots as f64 / s / 1e6,
        motor as f64 / s / 1e6
    );
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let rounds = if full { 5 } else { 1 };
    let repeats = if full { 200 } else { 2 };
    let m = machine();

    // The seed's diagonal (6 cm x 3 cm = 8400 x 4200 steps), back and forth.
    let mut prog = String::from("G21 G90 F600\n");
    for _ in 0..repeats {
        prog.push_str("G1 X60 Y30\nG1 X0 Y0\n");
    }
    let plan = plan_program(&m, &prog, &start(), 1).unwrap();
    let (d, c) = best_of(rounds, || walk(&plan));
    report("diagonals: step generation", d, c);
    let (d, c) = best_of(rounds, || {
        walk(&plan_program(&m, &prog, &start(), 1).unwrap())
    });
    report("diagonals: parse + plan + steps", d, c);

    // A real CAM program (short segments, arcs), from the shared corpus.
    let corpus = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/corpus/gcode/cncjs-tball-pocket.gcode"
    );
    match std::fs::read_to_string(corpus) {
        Ok(text) => {
            let plan = plan_program(&m, &text, &start(), 1).unwrap();
            let (d, c) = best_of(rounds, || walk(&plan));
            report("tball-pocket: step generation", d, c);
            let (d, c) = best_of(rounds, || {
                walk(&plan_program(&m, &text, &start(), 1).unwrap())
            });
            report("tball-pocket: parse + plan + steps", d, c);
        }
        Err(e) => println!("corpus program not found at {corpus}: {e} (skipped)"),
    }
}
