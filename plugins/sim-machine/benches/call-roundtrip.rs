//! One plugin call round trip: host `Instance` -> C ABI -> sim-machine `status` -> back, the
//! path every server request to a machine takes. `cargo bench -p fresa-sim-machine --bench
//! call-roundtrip` measures; without `--bench` (e.g. `cargo test --all-targets`) it only
//! smoke-runs a few calls.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_plugin_api::contract::{MachineStatus, Request};
use fresa_plugin_api::host::{HostSink, Instance, PluginLibrary};
use serde_json::{json, Value};
use std::sync::Arc;
use std::time::Instant;

struct Quiet;
impl HostSink for Quiet {
    fn event(&self, _event: Value) {}
    fn log(&self, _level: u32, _message: &str) {}
}

fn instance() -> Instance {
    let lib = fresa_plugin_api::built_library("fresa_sim_machine")
        .expect("libfresa_sim_machine not built beside the bench");
    let library = PluginLibrary::load(&lib).unwrap();
    let instance = library
        .create(&json!({"time_scale": 0}), Arc::new(Quiet))
        .unwrap();
    instance.call_request(&Request::Connect).unwrap();
    instance
}

/// Median ns per call over 5 batches of `n` calls.
fn measure(n: u32, mut call: impl FnMut()) -> f64 {
    let mut batches: Vec<f64> = (0..5)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..n {
                call();
            }
            t.elapsed().as_nanos() as f64 / f64::from(n)
        })
        .collect();
    batches.sort_by(f64::total_cmp);
    batches[2]
}

fn main() {
    let measure_it = std::env::args().any(|a| a == "--bench");
    let n = if measure_it { 100_000 } else { 100 };
    let inst = instance();
    let status_value = json!({"op": "status"});
    // Warm up (caches, allocator, CPU clock) before the first row.
    measure(n / 5, || {
        inst.call(&status_value).unwrap();
    });
    let rows = [
        (
            "call_request(&Request::Status) -> Value",
            measure(n, || {
                inst.call_request(&Request::Status).unwrap();
            }),
        ),
        (
            "request::<MachineStatus>(&Request::Status)",
            measure(n, || {
                let _: MachineStatus = inst.request(&Request::Status).unwrap();
            }),
        ),
        (
            "call(&Value) (the Value path)",
            measure(n, || {
                inst.call(&status_value).unwrap();
            }),
        ),
    ];
    for (what, ns) in rows {
        println!("{what:<45} {ns:>9.0} ns/call");
    }
}
