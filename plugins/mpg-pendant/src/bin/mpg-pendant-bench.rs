//! `mpg-pendant-bench`: N0451 -> N51 round trip through the real transport on loopback (each
//! fake pendant polls as fast as it gets answers, all pendants at once), and codec throughput.
//! Run: `cargo run --release -p fresa-mpg-pendant --bin mpg-pendant-bench`.

use clap::Parser;
use fresa_mpg_pendant::codec::{Decoded, Decoder, Frame, Info, FRAME_LEN};
use fresa_mpg_pendant::transport::{Config, Transport};
use fresa_plugin_api::contract::{Axis, AxisValues, PendantJob, PendantKey};
use std::io::{Read, Write};
use std::net::TcpListener;
use std::time::{Duration, Instant};

#[derive(Parser)]
struct Args {
    /// Pendant counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,50")]
    pendants: Vec<usize>,
    /// Timed polls per pendant (after 100 warm-up polls).
    #[arg(long, default_value_t = 500)]
    polls: usize,
    /// Polls per second per pendant (the firmware polls once per main-loop pass); 0 = as fast
    /// as answers come (a flood far beyond what pendants do).
    #[arg(long, default_value_t = 50.0)]
    rate_hz: f64,
    /// Frames for the codec throughput test.
    #[arg(long, default_value_t = 1_000_000)]
    frames: usize,
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// One fake pendant: accepts the transport, polls N0451 and times each N51 answer.
fn pendant(listener: TcpListener, polls: usize, rate_hz: f64) -> Result<Vec<Duration>, String> {
    let (mut s, _) = listener.accept().map_err(|e| e.to_string())?;
    s.set_nodelay(true).map_err(|e| e.to_string())?;
    let poll = Frame::Request(Info::Positions).encode();
    let mut decoder = Decoder::new();
    let mut buf = [0u8; 4096];
    let mut out = Vec::with_capacity(polls);
    let period = (rate_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / rate_hz));
    let mut next = Instant::now();
    for i in 0..polls + 100 {
        if let Some(p) = period {
            next += p;
            std::thread::sleep(next.saturating_duration_since(Instant::now()));
        }
        let t = Instant::now();
        s.write_all(&poll).map_err(|e| e.to_string())?;
        'answer: loop {
            let n = s.read(&mut buf).map_err(|e| e.to_string())?;
            if n == 0 {
                return Err("transport closed".into());
            }
            decoder.push(&buf[..n]);
            while let Some(d) = decoder.pop() {
                if matches!(d, Decoded::Frame(Frame::Positions(_))) {
                    break 'answer;
                }
            }
        }
        if i >= 100 {
            out.push(t.elapsed());
        }
    }
    Ok(out)
}

fn round_trip(n: usize, polls: usize, rate_hz: f64) -> Result<(), String> {
    let mut listeners = Vec::new();
    let mut transports = Vec::new();
    for _ in 0..n {
        let l = TcpListener::bind("127.0.0.1:0").map_err(|e| e.to_string())?;
        let addr = l.local_addr().map_err(|e| e.to_string())?.to_string();
        let cfg: Config = serde_json::from_value(serde_json::json!({"address": addr}))
            .map_err(|e| e.to_string())?;
        let t = Transport::start(cfg, Box::new(|_| {}), Box::new(|_, _| {}))?;
        t.set_status(
            AxisValues {
                x: 12.5,
                y: -3.25,
                z: 0.1,
                a: 0.0,
            },
            Some(PendantJob {
                elapsed_s: 1,
                estimated_s: 2,
                total_lines: 3,
                line: 1,
            }),
            None,
        );
        transports.push(t);
        listeners.push(l);
    }
    let handles: Vec<_> = listeners
        .into_iter()
        .map(|l| std::thread::spawn(move || pendant(l, polls, rate_hz)))
        .collect();
    let mut all = Vec::new();
    for h in handles {
        all.extend(h.join().map_err(|_| "pendant thread panicked")??);
    }
    all.sort_unstable();
    let rate = if rate_hz > 0.0 {
        format!("{rate_hz} Hz")
    } else {
        "flood".to_string()
    };
    println!(
        "round trip N0451->N51, {n:>2} pendant(s) at {rate}, {} polls: p50 {:>7.1} us  p99 {:>7.1} us  max {:>8.1} us",
        all.len(),
        percentile(&all, 0.50).as_secs_f64() * 1e6,
        percentile(&all, 0.99).as_secs_f64() * 1e6,
        all.last().copied().unwrap_or_default().as_secs_f64() * 1e6,
    );
    drop(transports);
    Ok(())
}

fn codec(frames: usize) {
    let kinds = [
        Frame::Jog {
            step: 0.01,
            axis: Axis::X,
            count: 12,
        },
        Frame::Key(PendantKey::ZeroZ),
        Frame::Request(Info::Positions),
        Frame::Positions(AxisValues {
            x: 1.0,
            y: -2.0,
            z: 3.5,
            a: 0.0,
        }),
    ];
    let t = Instant::now();
    let mut stream = Vec::with_capacity(frames * FRAME_LEN);
    for i in 0..frames {
        stream.extend_from_slice(&kinds[i % kinds.len()].encode());
    }
    let enc = t.elapsed();
    let t = Instant::now();
    let mut d = Decoder::new();
    let mut n = 0usize;
    // TCP-like reads: 1460-byte segments that cut frames anywhere.
    for chunk in stream.chunks(1460) {
        d.push(chunk);
        while let Some(x) = d.pop() {
            if matches!(x, Decoded::Frame(_)) {
                n += 1;
            }
        }
    }
    let dec = t.elapsed();
    assert_eq!(n, frames, "decoder lost frames");
    println!(
        "codec: encode {:.2} M frames/s, decode {:.2} M frames/s ({frames} mixed frames, 1460-byte reads)",
        frames as f64 / enc.as_secs_f64() / 1e6,
        frames as f64 / dec.as_secs_f64() / 1e6,
    );
}

fn main() {
    let args = Args::parse();
    for n in &args.pendants {
        if let Err(e) = round_trip(*n, args.polls, args.rate_hz) {
            eprintln!("round trip with {n} pendants failed: {e}");
            std::process::exit(1);
        }
    }
    codec(args.frames);
}
