//! `kawasaki-as-sim`: a loopback Kawasaki controller running the legacy (seed) or the fresa-v1
//! robot program. Prints `listening on ADDR` on stdout once it accepts connections.

use clap::Parser;
use fresa_kawasaki_as::sim::{self, DropMode, SimConfig};
use fresa_kawasaki_as::Protocol;
use std::io::Write;
use std::net::TcpListener;
use std::path::PathBuf;
use std::time::Duration;

#[derive(Parser)]
#[command(about = "Simulated Kawasaki controller running the legacy or fresa-v1 robot program")]
struct Args {
    /// Address to listen on (port 0 picks one).
    #[arg(long, default_value = "127.0.0.1:55000")]
    listen: String,
    /// Robot program: legacy (the seed's FRESADORA) or fresa-v1.
    #[arg(long, default_value = "legacy", value_parser = ["legacy", "fresa-v1"])]
    protocol: String,
    /// Part zero reported to the client, robot base coordinates: X,Y,Z.
    #[arg(long, default_value = "-400,0,-30", value_parser = parse_xyz, allow_hyphen_values = true)]
    part_zero: [f64; 3],
    /// Part zero reported on the second and later connections (an operator who re-taught it).
    #[arg(long, value_parser = parse_xyz, allow_hyphen_values = true)]
    part_zero_after_reconnect: Option<[f64; 3]>,
    /// Multiplies motion time (distance / speed); 0 = instant.
    #[arg(long, default_value_t = 0.0)]
    time_scale: f64,
    /// Delay of every reply, ms (simulated round trip).
    #[arg(long, default_value_t = 0.0)]
    reply_delay_ms: f64,
    /// Drop the connection after this many executed motions (once).
    #[arg(long)]
    drop_after: Option<u64>,
    /// Whether the dropped motion's `done` is sent first.
    #[arg(long, value_enum, default_value = "after-done")]
    drop_mode: DropMode,
    /// Send a garbage message before every n-th motion's `done`.
    #[arg(long)]
    garbage_every: Option<u64>,
    /// fresa-v1: rapid speed, mm/s.
    #[arg(long, default_value_t = 10.0)]
    rapid_mm_s: f64,
    /// fresa-v1: commands the robot can queue.
    #[arg(long, default_value_t = 64)]
    queue: usize,
    /// JSON-lines log of every received message and executed motion.
    #[arg(long)]
    log: Option<PathBuf>,
}

fn parse_xyz(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split([',', ' '])
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<f64>().map_err(|e| format!("{t:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match v.as_slice() {
        [x, y, z] => Ok([*x, *y, *z]),
        _ => Err(format!("expected X,Y,Z, got {s:?}")),
    }
}

fn main() -> std::process::ExitCode {
    let a = Args::parse();
    let cfg = SimConfig {
        protocol: if a.protocol == "fresa-v1" {
            Protocol::FresaV1
        } else {
            Protocol::Legacy
        },
        part_zero: a.part_zero,
        part_zero_after_reconnect: a.part_zero_after_reconnect,
        time_scale: a.time_scale.max(0.0),
        reply_delay: Duration::from_secs_f64(a.reply_delay_ms.max(0.0) / 1000.0),
        drop_after: a.drop_after,
        drop_mode: a.drop_mode,
        garbage_every: a.garbage_every,
        rapid_mm_s: a.rapid_mm_s,
        queue: a.queue.max(1),
        log: a.log,
    };
    let listener = match TcpListener::bind(&a.listen) {
        Ok(l) => l,
        Err(e) => {
            eprintln!("kawasaki-as-sim: cannot listen on {}: {e}", a.listen);
            return std::process::ExitCode::FAILURE;
        }
    };
    let sim = match sim::Sim::new(cfg) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("kawasaki-as-sim: cannot open the log: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    match listener.local_addr() {
        Ok(addr) => {
            let mut out = std::io::stdout();
            let _ = writeln!(out, "listening on {addr}");
            let _ = out.flush();
        }
        Err(e) => {
            eprintln!("kawasaki-as-sim: {e}");
            return std::process::ExitCode::FAILURE;
        }
    }
    sim.serve(listener);
    std::process::ExitCode::SUCCESS
}
