//! Status reads on a node whose machines are remote (README: Several nodes, Measurements): two
//! release-built nodes on a throwaway PostgreSQL, a sim machine on node A, and clients reading
//! `GET /machines/{id}/status` from A (local) and from B (forwarded to A) for a few seconds each.
//! A measurement, not a test: `cargo bench -p fresa-tests --bench nodes`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{wait_for, Opts, Server};
use std::time::{Duration, Instant};

const CLIENTS: usize = 4;
const RUN_FOR: Duration = Duration::from_secs(4);

fn node(database: &str, name: &str) -> Server {
    let mut s = Server::unstarted(Opts::default());
    s.write_config(&format!(
        "database_url = \"{database}\"\nnode_name = \"{name}\"\nnode_heartbeat_ms = 200\n"
    ));
    s.spawn().unwrap();
    s
}

/// `CLIENTS` threads reading `url` for `RUN_FOR`: requests per second and latency percentiles.
fn hammer(url: &str) -> (f64, Duration, Duration) {
    let start = Instant::now();
    let threads: Vec<_> = (0..CLIENTS)
        .map(|_| {
            let url = url.to_string();
            std::thread::spawn(move || {
                let client = reqwest::blocking::Client::new();
                let mut lat = Vec::new();
                while start.elapsed() < RUN_FOR {
                    let t = Instant::now();
                    let r = client.get(&url).send().unwrap();
                    assert_eq!(r.status().as_u16(), 200);
                    let _ = r.bytes().unwrap();
                    lat.push(t.elapsed());
                }
                lat
            })
        })
        .collect();
    let mut lat: Vec<Duration> = threads
        .into_iter()
        .flat_map(|t| t.join().unwrap())
        .collect();
    let secs = start.elapsed().as_secs_f64();
    lat.sort();
    let pct = |p: f64| lat[((lat.len() - 1) as f64 * p) as usize];
    (lat.len() as f64 / secs, pct(0.5), pct(0.99))
}

fn main() {
    let db = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(fresa_core::store::test_postgres::fresh_database());
    let a = node(&db, "bench-a");
    let b = node(&db, "bench-b");
    let m = a.sim("m", 1.0);
    wait_for(Duration::from_secs(30), "B to see the machine", || {
        (b.get(&format!("/api/v1/machines/{}", m.id)).body["state"] == "idle").then_some(())
    });
    let path = format!("/api/v1/machines/{}/status", m.id);
    println!("status reads, {CLIENTS} clients, {RUN_FOR:?} each, release build, 2-core machine:");
    for (label, server) in [("local (node A)", &a), ("remote (node B -> A)", &b)] {
        let (rps, p50, p99) = hammer(&server.url(&path));
        println!(
            "  {label:<22} {rps:>8.0} req/s   p50 {:>7.2} ms   p99 {:>7.2} ms",
            p50.as_secs_f64() * 1e3,
            p99.as_secs_f64() * 1e3
        );
    }
    let list = "/api/v1/machines";
    let (rps, p50, p99) = hammer(&b.url(list));
    println!(
        "  {:<22} {rps:>8.0} req/s   p50 {:>7.2} ms   p99 {:>7.2} ms",
        "machine list on B",
        p50.as_secs_f64() * 1e3,
        p99.as_secs_f64() * 1e3
    );
}
