//! The shop's records at scale (issue 28, part 2): 100,000 part records and 30 days of machine
//! state changes, then the cost of the API's queries (`GET /parts` with each filter, a deep
//! page, `GET /reports/utilisation` over 30 days).
//!
//! `cargo bench -p fresa-core --features test-support --bench records-bench [-- sqlite|postgres]`
//! (PostgreSQL: a throwaway local server, as in the store tests).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_core::records::split_by_day;
use fresa_core::store::{now_ms, PartFilter, PartRow, Store};
use std::time::{Duration, Instant};

const PARTS: i64 = 100_000;
const MACHINES: i64 = 10;
const JOBS: i64 = 2_000;
const DAYS: i64 = 30;
/// State changes per machine and day (a busy shop: a change every ~7 minutes).
const CHANGES_PER_DAY: i64 = 200;
const DAY_MS: i64 = 86_400_000;

fn part(i: i64, start: i64) -> PartRow {
    let ended = start + i * (DAYS * DAY_MS / PARTS);
    PartRow {
        id: 0,
        run_id: i + 1,
        job_id: i % JOBS + 1,
        machine_id: i % MACHINES + 1,
        machine_name: format!("m{}", i % MACHINES + 1),
        node: Some("bench".into()),
        program_name: format!("job-{}.nc", i % JOBS + 1),
        program_sha256: format!("{:064x}", i % JOBS),
        work_offset: "G54".into(),
        work_zero: Some(r#"{"x":10.0,"y":20.0,"z":-5.0,"a":0.0}"#.into()),
        part_zero: None,
        tool_table:
            r#"[{"tool":1,"diameter_mm":6.0,"length_mm":0.0,"description":"6 mm end mill"}]"#.into(),
        tool_table_sha256: format!("{:064x}", 7),
        operators: r#"["alice"]"#.into(),
        confirmations: "[]".into(),
        outcome: if i % 10 == 0 {
            "cancelled"
        } else {
            "completed"
        }
        .into(),
        message: None,
        line_count: 5000,
        from_line: None,
        last_line: 5000,
        lines_run: 5000,
        estimate_s: Some(600.0),
        actual_s: Some(612.5),
        started_at: Some(ended - 612_500),
        ended_at: ended,
    }
}

/// Median and worst of `n` runs of `f`.
async fn time<F, Fut, T>(n: usize, mut f: F) -> (Duration, Duration)
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = T>,
{
    let mut v = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        std::hint::black_box(f().await);
        v.push(t.elapsed());
    }
    v.sort();
    (v[n / 2], v[n - 1])
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

async fn measure(label: &str, store: Store) {
    let start = now_ms() - DAYS * DAY_MS;
    let t = Instant::now();
    for i in 0..PARTS {
        store.upsert_part(&part(i, start)).await.expect("part");
    }
    let fill = t.elapsed();
    for m in 1..=MACHINES {
        for k in 0..DAYS * CHANGES_PER_DAY {
            let state = ["cutting", "idle", "held", "cutting", "idle"][(k % 5) as usize];
            let since = start + k * (DAY_MS / CHANGES_PER_DAY) + m;
            store
                .insert_machine_state(m, state, since)
                .await
                .expect("state");
        }
    }
    println!(
        "{label}: {PARTS} part records written in {:.1} s ({:.0}/s, one transaction each); {} state changes",
        fill.as_secs_f64(),
        PARTS as f64 / fill.as_secs_f64(),
        MACHINES * DAYS * CHANGES_PER_DAY
    );
    let page = |f: PartFilter| {
        let store = store.clone();
        move || {
            let (store, f) = (store.clone(), f.clone());
            async move { store.parts(&f).await.expect("parts") }
        }
    };
    let base = PartFilter {
        limit: 101,
        ..Default::default()
    };
    let mid = start + 15 * DAY_MS;
    let cases: Vec<(&str, PartFilter)> = vec![
        ("newest page (100)", base.clone()),
        (
            "machine filter",
            PartFilter {
                machine: Some(3),
                ..base.clone()
            },
        ),
        (
            "job filter",
            PartFilter {
                job: Some(42),
                ..base.clone()
            },
        ),
        (
            "one day (from/to)",
            PartFilter {
                from: Some(mid),
                to: Some(mid + DAY_MS),
                ..base.clone()
            },
        ),
        (
            "machine + one day",
            PartFilter {
                machine: Some(3),
                from: Some(mid),
                to: Some(mid + DAY_MS),
                ..base.clone()
            },
        ),
        (
            "page at the middle (cursor)",
            PartFilter {
                before: Some((mid, i64::MAX)),
                ..base.clone()
            },
        ),
    ];
    for (name, f) in cases {
        let (p50, max) = time(50, page(f)).await;
        println!(
            "{label}: parts {name:<28} p50 {:>7.2} ms  max {:>7.2} ms",
            ms(p50),
            ms(max)
        );
    }
    let now = now_ms();
    let (p50, max) = time(10, || {
        let store = store.clone();
        async move {
            let mut days = 0;
            for m in 1..=MACHINES {
                let changes = store
                    .machine_states(m, now - DAYS * DAY_MS, now)
                    .await
                    .expect("states");
                days += split_by_day(&changes, now - DAYS * DAY_MS, now).len();
            }
            days
        }
    })
    .await;
    println!(
        "{label}: utilisation, {MACHINES} machines x {DAYS} days p50 {:>7.2} ms  max {:>7.2} ms",
        ms(p50),
        ms(max)
    );
}

#[tokio::main]
async fn main() {
    let which = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .unwrap_or_default();
    if which.is_empty() || which == "sqlite" {
        let dir = std::env::temp_dir().join(format!("fresa-records-bench-{}", std::process::id()));
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
