//! Store write paths on SQLite and PostgreSQL: acknowledged-line writes per second (each its own
//! transaction, as a machine task writes them) and event append latency.
//!
//! `cargo bench -p fresa-core --features test-support --bench store-bench [-- sqlite|postgres]`
//! (PostgreSQL: a throwaway local server, as in the store tests; fsync off there, so the
//! numbers compare the code paths, not disks).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_core::store::{NewJob, Store};
use std::time::{Duration, Instant};

const ACKS: i64 = 3000;
const EVENTS: usize = 2000;

async fn measure(label: &str, store: Store) {
    let m = store
        .insert_machine(
            "bench",
            "sim-machine",
            &serde_json::json!({}),
            50.0,
            1000.0,
            300.0,
        )
        .await
        .expect("machine");
    let j = store
        .insert_job(NewJob {
            name: "bench",
            machine_id: m,
            sha256: "x",
            size_bytes: 1,
            line_count: ACKS,
            analysis: None,
            source: "bench",
        })
        .await
        .expect("job");
    let run = store
        .start_run(j, m)
        .await
        .expect("run")
        .map_err(|_| "busy")
        .expect("free machine");
    let t = Instant::now();
    for line in 1..=ACKS {
        store.ack_line(run.id, line).await.expect("ack");
    }
    let acks_per_s = ACKS as f64 / t.elapsed().as_secs_f64();
    let mut lat: Vec<Duration> = Vec::with_capacity(EVENTS);
    for i in 0..EVENTS {
        let t = Instant::now();
        store
            .append_event(
                "machine.jog",
                Some(m),
                Some("bench"),
                &format!("{{\"i\":{i}}}"),
            )
            .await
            .expect("event");
        lat.push(t.elapsed());
    }
    lat.sort();
    let pct = |p: f64| lat[((lat.len() as f64 - 1.0) * p) as usize].as_secs_f64() * 1e6;
    println!(
        "{label:<10} acknowledged-line writes: {acks_per_s:>8.0}/s   event append: p50 {:>6.0} µs  p99 {:>6.0} µs",
        pct(0.5),
        pct(0.99)
    );
}

#[tokio::main]
async fn main() {
    // `cargo bench` passes `--bench`; the first other argument picks the database.
    let which = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .unwrap_or_default();
    if which.is_empty() || which == "sqlite" {
        let dir = std::env::temp_dir().join(format!("fresa-store-bench-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let store = Store::open(&dir.join("bench.db")).await.expect("sqlite");
        measure("sqlite", store).await;
        std::fs::remove_dir_all(&dir).ok();
    }
    #[cfg(feature = "test-support")]
    if which.is_empty() || which == "postgres" {
        let url = fresa_core::store::test_postgres::fresh_database().await;
        let store = Store::connect(&url).await.expect("postgres");
        measure("postgres", store).await;
    }
}
