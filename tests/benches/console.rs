//! Measures the web console (README: Console, Measurements): what a first visit transfers, and
//! how long a 1,000,000-line program's toolpath takes to be served and drawn in headless
//! Chromium, and how smooth pages stay while machines run. A measurement, not a test:
//! `cargo bench -p fresa-tests --bench console` (all of it), or with section names after `--`
//! (`first-page`, `million`, `overview`, `running`) only those.

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../support/browser.rs"]
mod browser;

use browser::Browser;
use fresa_tests::Server;
use std::fmt::Write;
use std::time::{Duration, Instant};

const T: Duration = Duration::from_secs(120);

/// A million lines of zigzag cutting with a small full circle every 50 moves, over a 200 x 150 mm
/// part.
fn million_line_program() -> String {
    let mut p = String::with_capacity(24 << 20);
    p.push_str("G21 G90 G17\nG0 Z5\nG0 X0 Y0\nG1 Z-1 F1200\n");
    let mut line = 4;
    let mut i = 0u64;
    while line < 1_000_000 - 1 {
        let row = i / 400;
        let col = i % 400;
        let x = if row.is_multiple_of(2) {
            col as f64 * 0.5
        } else {
            (399 - col) as f64 * 0.5
        };
        let y = (row % 300) as f64 * 0.5;
        if i % 50 == 49 {
            // A full circle of 0.25 mm radius where the tool is, then on.
            let _ = writeln!(p, "G2 I0.25 J0");
            let _ = writeln!(p, "G1 X{x:.3} Y{y:.3}");
            line += 2;
        } else {
            let _ = writeln!(p, "X{x:.3} Y{y:.3}");
            line += 1;
        }
        i += 1;
    }
    p.push_str("M30\n");
    p
}

/// Frame gaps (from requestAnimationFrame) and long main-thread tasks over `ms` milliseconds,
/// with the status events an extra stream receives meanwhile:
/// [frames, p50, p99, max, gaps over 50 ms, status events, long tasks, longest task ms].
const FRAME_GAPS: &str = "const ms = arguments[0]; const done = arguments[arguments.length - 1]; \
     const gaps = []; let last = performance.now(); const tasks = []; \
     const po = new PerformanceObserver((l) => { for (const e of l.getEntries()) tasks.push(e.duration); }); \
     try { po.observe({ type: 'longtask' }); } catch (_) {} \
     let statuses = 0; const es = new EventSource('/api/v1/events?types=status'); \
     es.addEventListener('status', () => statuses++); \
     const end = last + ms; \
     function f(t) { gaps.push(t - last); last = t; if (t < end) requestAnimationFrame(f); \
       else { es.close(); po.disconnect(); gaps.sort((a, b) => a - b); \
         done([gaps.length, gaps[Math.floor(gaps.length * 0.5)], gaps[Math.floor(gaps.length * 0.99)], gaps[gaps.length - 1], \
               gaps.filter(g => g > 50).length, statuses, tasks.length, Math.max(0, ...tasks)]); } } \
     requestAnimationFrame(f);";

fn frame_gaps(b: &Browser, ms: u64) -> fresa_tests::serde_json::Value {
    b.js_async(&format!(
        "return (function() {{ {} }}).apply(null, [{ms}, arguments[arguments.length - 1]]);",
        FRAME_GAPS
    ))
}

fn print_gaps(what: &str, v: &fresa_tests::serde_json::Value) {
    println!(
        "{what}: {} frames, frame gap p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms, {} gaps over 50 ms; \
         {} status events received; {} long tasks (longest {:.0} ms)",
        v[0], v[1].as_f64().unwrap_or(0.0), v[2].as_f64().unwrap_or(0.0),
        v[3].as_f64().unwrap_or(0.0), v[4], v[5], v[6], v[7].as_f64().unwrap_or(0.0)
    );
}

fn main() {
    let only: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let want = |section: &str| only.is_empty() || only.iter().any(|o| o == section);
    let s = Server::start_demo();
    let http = reqwest::blocking::Client::builder()
        .timeout(T)
        .build()
        .unwrap();
    let b = Browser::start();
    // First: the first page is measured with nothing in the browser's cache.
    if want("first-page") {
        first_page(&s, &b, &http);
    }
    if want("million") {
        million(&s, &b, &http);
    }
    if want("overview") {
        overview(&s, &b);
    }
    if want("running") {
        running_job(&s, &b);
    }
}

fn first_page(s: &Server, b: &Browser, http: &reqwest::blocking::Client) {
    // 1. First page: every file a first visit loads, as gzip travels (what curl sees) ...
    let mut raw = 0usize;
    let mut gz = 0usize;
    for a in fresa_console::ASSETS {
        let path = if a.name == "index.html" {
            "/".to_string()
        } else {
            format!("/assets/{}", a.name)
        };
        let r = http
            .get(s.url(&path))
            .header("accept-encoding", "gzip")
            .send()
            .unwrap();
        gz += r.bytes().unwrap().len();
        raw += a.bytes.len();
    }
    println!(
        "first page: {} files, {raw} bytes uncompressed, {gz} bytes gzip-transferred",
        fresa_console::ASSETS.len()
    );
    // ... and as the browser counts it (Resource Timing transferSize, headers included).
    b.goto(&s.base);
    b.wait(
        "the overview",
        T,
        "return !!document.querySelector('[data-machine]');",
    );
    let browser_bytes = b.js("const n = performance.getEntriesByType('navigation')[0]; \
         return [n, ...performance.getEntriesByType('resource')] \
           .filter(e => !e.name.includes('/api/')).reduce((s, e) => s + e.transferSize, 0);");
    println!("first page in Chromium: {browser_bytes} bytes transferred (without API calls)");
}

fn million(s: &Server, b: &Browser, http: &reqwest::blocking::Client) {
    // 2. A 1M-line program: upload (not part of the measure), then served + drawn.
    let program = million_line_program();
    let lines = program.lines().count();
    let t = Instant::now();
    let job = s.upload(1, "million", program.into_bytes());
    let id = job["id"].as_i64().unwrap();
    println!(
        "uploaded {lines} lines in {:.2} s (stored and analysed)",
        t.elapsed().as_secs_f64()
    );
    for q in ["", "?max_vertices=1000000"] {
        let t = Instant::now();
        let r = http
            .get(s.url(&format!("/api/v1/jobs/{id}/toolpath{q}")))
            .header("accept-encoding", "gzip")
            .send()
            .unwrap();
        assert_eq!(r.status(), 200);
        let gz = r.bytes().unwrap().len();
        println!(
            "toolpath{q}: served in {:.2} s, {gz} bytes gzip-transferred",
            t.elapsed().as_secs_f64()
        );
    }
    for run in 1..=3 {
        b.goto(&format!("{}/#/jobs", s.base));
        b.wait(
            "the jobs page",
            T,
            "return !!document.getElementById('upload-file');",
        );
        let t = Instant::now();
        b.goto(&format!("{}/#/jobs/{id}", s.base));
        let v = b.wait(
            "the toolpath to be drawn",
            T,
            "const c = document.querySelector('canvas.toolpath'); \
             return c && c.dataset.drawMs ? [+c.dataset.vertices, +c.dataset.fetchMs, +c.dataset.drawMs] : null;",
        );
        let total = t.elapsed();
        println!(
            "run {run}: 1M-line toolpath opened, served and drawn in {:.2} s \
             ({} vertices; fetch {} ms, parse + upload + draw {} ms)",
            total.as_secs_f64(),
            v[0],
            v[1],
            v[2]
        );
    }
    b.screenshot("million-line-toolpath");
}

fn overview(s: &Server, b: &Browser) {
    // 3. Twenty machines running jobs on one overview: status events at the status rate for
    //    each; how smooth is the page? (frame gaps from requestAnimationFrame over 10 s)
    // The first 5000 lines of the zigzag: about two minutes of motion, with no program pause.
    let program: String = million_line_program()
        .lines()
        .take(5000)
        .map(|l| format!("{l}\n"))
        .collect();
    let mut machines = vec![1];
    for i in 2..=20 {
        machines.push(s.sim(&format!("mill-{i}"), 1.0).id);
    }
    for m in &machines {
        let job = s.upload(*m, "zigzag", program.clone());
        s.job_action(job["id"].as_i64().unwrap(), "start")
            .expect(200);
    }
    b.goto(&format!("{}/#/", s.base));
    b.wait(
        "20 cards",
        T,
        "return document.querySelectorAll('[data-machine]').length === 20;",
    );
    let stats = frame_gaps(b, 10_000);
    print_gaps("20 running machines on the overview for 10 s", &stats);
    b.screenshot("overview-20-machines");
}

/// 4. The run screen while a 1,000,000-line job runs in real time on a simulated machine: how
///    smooth the machine page (DRO, listing, toolpath with the executed part) and the job page
///    stay, 10 s each, status events at 10 Hz.
fn running_job(s: &Server, b: &Browser) {
    let m = s.sim("runner", 1.0);
    let t = Instant::now();
    let job = s.upload(m.id, "million-running", million_line_program().into_bytes());
    let id = job["id"].as_i64().unwrap();
    println!(
        "running: 1M lines uploaded in {:.2} s",
        t.elapsed().as_secs_f64()
    );
    s.job_action(id, "start").expect(200);
    s.wait_status(m.id, T, "the job running", |st| st["state"] == "running");
    for (what, page) in [
        ("machine page", format!("#/machines/{}", m.id)),
        ("job page", format!("#/jobs/{id}")),
    ] {
        b.goto(&format!("{}/{page}", s.base));
        b.wait(
            "the toolpath to be drawn",
            T,
            "const c = document.querySelector('canvas.toolpath'); return c && c.dataset.drawMs;",
        );
        let v = frame_gaps(b, 10_000);
        print_gaps(
            &format!("1M-line job running in real time, {what} for 10 s"),
            &v,
        );
    }
    b.screenshot("running-job");
    s.job_action(id, "cancel").expect(200);
}
