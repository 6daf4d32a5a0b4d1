//! Pendant polls beside busy machines (issue #29; README: Measurements): the release-built
//! server with PENDANTS fake firmware pendants, each polling N0451 at 50 Hz as the firmware's
//! main loop does and timing the N51 answer, while MACHINES real-time sim machines loop jobs and
//! STREAMS clients follow the event stream. Prints the poll round trip's p50, p99 and max, and
//! the server's CPU and RSS over the measured window. Then, under the same load, the same
//! pendants are answered by a bare reference (a thread per link that decodes each poll and
//! writes a canned N51 frame, at the priority fresa's link threads take): the floor this
//! machine's scheduler allows.
//! The fake pendants' threads run at nice -20 when allowed: a pendant is an ESP32 with a CPU of
//! its own, so its wake-up behind the busy machines on these 2 cores is not the server's
//! latency. `--no-raise` turns fresa's `raise_priority` off (and runs the bare answerer at
//! normal priority), for the figure before it.
//! A measurement, not a test: `cargo bench -p fresa-tests --bench pendants [-- [--no-raise]
//! PENDANTS MACHINES STREAMS SECS]` (defaults 100 5 50 10).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_mpg_pendant::codec::{Decoded, Decoder, Frame, Info};
use fresa_mpg_pendant::transport::LINK_NICE;
use fresa_plugin_api::priority::set_thread_nice;
use fresa_tests::{back_and_forth, cpu_ticks, rss_kib, Server};
use serde_json::json;
use std::io::{Read, Write};
use std::net::TcpListener;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

const POLL_HZ: f64 = 50.0;
const WARM_UP: Duration = Duration::from_secs(2);
const T: Duration = Duration::from_secs(60);

/// The bare reference for one pendant: connects to it as the server would and answers each
/// poll with a fixed N51 frame, until the pendant closes. `raise`: at fresa's link priority.
fn bare_answerer(addr: std::net::SocketAddr, raise: bool) {
    if raise {
        set_thread_nice(LINK_NICE).expect("the bare answerer's priority (needs CAP_SYS_NICE)");
    }
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_nodelay(true).unwrap();
    let answer = Frame::Positions(Default::default()).encode();
    let mut decoder = Decoder::new();
    let mut buf = [0u8; 4096];
    loop {
        let n = match s.read(&mut buf) {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        decoder.push(&buf[..n]);
        while let Some(d) = decoder.pop() {
            if matches!(d, Decoded::Frame(Frame::Request(Info::Positions)))
                && s.write_all(&answer).is_err()
            {
                return;
            }
        }
    }
}

/// One fake pendant: takes the server's connection, polls N0451 at `POLL_HZ` until `stop`, and
/// returns the round trips of the polls sent after `measure_from`.
fn pendant(listener: TcpListener, measure_from: Instant, stop: &AtomicBool) -> Vec<Duration> {
    // The device's own CPU (see the top); without the permission it shares the scheduler.
    let _ = set_thread_nice(-20);
    let (mut s, _) = listener.accept().unwrap();
    s.set_nodelay(true).unwrap();
    s.set_read_timeout(Some(T)).unwrap();
    let poll = Frame::Request(Info::Positions).encode();
    let mut decoder = Decoder::new();
    let mut buf = [0u8; 4096];
    let mut out = Vec::new();
    let period = Duration::from_secs_f64(1.0 / POLL_HZ);
    let mut next = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        next += period;
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
        let t = Instant::now();
        s.write_all(&poll).unwrap();
        'answer: loop {
            let n = s.read(&mut buf).expect("the server answers every poll");
            assert!(n > 0, "the server closed a pendant's link");
            decoder.push(&buf[..n]);
            while let Some(d) = decoder.pop() {
                if matches!(d, Decoded::Frame(Frame::Positions(_))) {
                    break 'answer;
                }
            }
        }
        if t >= measure_from {
            out.push(t.elapsed());
        }
    }
    out
}

/// Polls `pendants` fake pendants for `secs` after the warm-up; `connect` makes each one's
/// link (registers it with the server, or starts a bare answerer). Returns the sorted round
/// trips and the measured window.
fn measure(
    pendants: u64,
    secs: u64,
    connect: impl Fn(u64, std::net::SocketAddr) + Sync,
    during: impl FnOnce(Duration) -> (u64, u64),
) -> (Vec<Duration>, Duration, (u64, u64)) {
    let stop = AtomicBool::new(false);
    let measure_from = Instant::now() + WARM_UP;
    let (mut rtt, window, seen) = std::thread::scope(|scope| {
        let polls: Vec<_> = (0..pendants)
            .map(|i| {
                let l = TcpListener::bind("127.0.0.1:0").unwrap();
                let addr = l.local_addr().unwrap();
                let stop = &stop;
                let h = scope.spawn(move || pendant(l, measure_from, stop));
                connect(i, addr);
                h
            })
            .collect();
        std::thread::sleep(measure_from.saturating_duration_since(Instant::now()));
        let t0 = Instant::now();
        let seen = during(Duration::from_secs(secs));
        let window = t0.elapsed();
        stop.store(true, Ordering::Relaxed);
        let rtt: Vec<Duration> = polls.into_iter().flat_map(|h| h.join().unwrap()).collect();
        (rtt, window, seen)
    });
    rtt.sort_unstable();
    (rtt, window, seen)
}

fn summary(rtt: &[Duration]) -> String {
    let pct = |p: f64| rtt[((rtt.len() - 1) as f64 * p).round() as usize].as_secs_f64() * 1e6;
    format!(
        "{} polls, round trip p50 {:.0} us, p99 {:.0} us, max {:.0} us",
        rtt.len(),
        pct(0.5),
        pct(0.99),
        rtt.last().unwrap().as_secs_f64() * 1e6
    )
}

fn main() {
    let arg = |i: usize, default: u64| {
        std::env::args()
            .skip(1)
            .filter(|a| !a.starts_with('-'))
            .nth(i)
            .map_or(default, |a| {
                a.parse().expect("numbers: PENDANTS MACHINES STREAMS SECS")
            })
    };
    let (pendants, machines, streams, secs) = (arg(0, 100), arg(1, 5), arg(2, 50), arg(3, 10));
    let raise = !std::env::args().any(|a| a == "--no-raise");
    let devices = match std::thread::spawn(|| set_thread_nice(-20)).join().unwrap() {
        Ok(()) => "at nice -20".to_string(),
        Err(e) => format!("at normal priority (nice -20 refused: {e})"),
    };
    let s = Server::start();
    let pid = s.pid().unwrap();
    let ids: Vec<i64> = (0..machines.max(1))
        .map(|i| s.sim(&format!("busy{i}"), 1.0).id)
        .collect();
    let followers: Vec<_> = (0..streams).map(|_| s.events("", None)).collect();
    let load_stop = AtomicBool::new(false);
    std::thread::scope(|scope| {
        // Each busy machine runs 2 s jobs back to back: 100 lines of 2 mm at 6000 mm/min.
        for (i, &m) in ids.iter().enumerate().take(machines as usize) {
            let (s, stop) = (&s, &load_stop);
            scope.spawn(move || {
                let program = back_and_forth(100, 2.0, 6000.0);
                // The end of each job is read from the event stream: polling the job would load
                // the server with requests a shop's clients do not make.
                let ends = s.events(&format!("machine={m}&types=job.state"), None);
                while !stop.load(Ordering::Relaxed) {
                    let (job, _) = s.upload_and_start(m, &format!("loop{i}"), &program);
                    ends.until(T, "the job's completion", |e| {
                        e.job() == Some(job) && e.state() == Some("completed")
                    });
                }
            });
        }
        let (fresa, window, (cpu, rss)) = measure(
            pendants,
            secs,
            |i, addr| {
                s.post(
                    "/api/v1/pendants",
                    &json!({"name": format!("p{i}"), "address": addr.to_string(),
                            "machine": ids[i as usize % ids.len()], "dialect": "firmware",
                            "config": {"raise_priority": raise}}),
                )
                .expect(201);
            },
            |secs| {
                let c0 = cpu_ticks(pid);
                std::thread::sleep(secs);
                (cpu_ticks(pid) - c0, rss_kib(pid))
            },
        );
        let (bare, _, _) = measure(
            pendants,
            secs,
            |_, addr| {
                std::thread::spawn(move || bare_answerer(addr, raise));
            },
            |secs| {
                std::thread::sleep(secs);
                (0, 0)
            },
        );
        load_stop.store(true, Ordering::Relaxed);
        println!(
            "{pendants} pendants at {POLL_HZ} Hz ({devices}), {machines} busy machines, \
             {streams} event streams, {:.1} s each; links {}:\n  fresa: {}; server CPU {:.1} % of \
             one core, RSS {:.1} MiB\n  bare answerer, same load: {}",
            window.as_secs_f64(),
            if raise {
                format!("at nice {LINK_NICE}")
            } else {
                "at normal priority (--no-raise)".to_string()
            },
            summary(&fresa),
            cpu as f64 / window.as_secs_f64(),
            rss as f64 / 1024.0,
            summary(&bare),
        );
    });
    drop(followers);
}
