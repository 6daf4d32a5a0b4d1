//! Writes the benchmark's synthetic programs to a file, for end-to-end
//! measurements (an upload to `fresa serve`, `fresa gcode check`):
//!
//!   cargo run --release -p fresa-gcode --example synth -- cam 200 /tmp/cam.nc
//!   cargo run --release -p fresa-gcode --example synth -- parametric 50 /tmp/param.ngc
//!
//! The size is in MB (10^6 bytes); the programs are those of
//! `benches/support/synth.rs` (deterministic, the same every time).
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../benches/support/synth.rs"]
mod synth;

use std::io::Write;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let usage = "usage: synth cam|parametric MB FILE";
    let kind = args.get(1).expect(usage);
    let mb: f64 = args.get(2).expect(usage).parse().expect("MB");
    let path = args.get(3).expect(usage);
    let bytes = (mb * 1e6) as u64;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(path).unwrap());
    let n = match kind.as_str() {
        "cam" => synth::cam(bytes, &mut out),
        "parametric" => synth::parametric(bytes, &mut out),
        _ => panic!("{usage}"),
    }
    .unwrap();
    out.flush().unwrap();
    println!("{n} bytes written to {path}");
}
