//! Streaming uses constant memory: a synthetic program far larger than the
//! reader's buffer leaves the process high-water mark (VmHWM) almost where
//! it was. Its own test binary, so no other test's allocations count.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_gcode::*;
use std::io::{BufReader, Read};

fn vm_hwm_kib() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Produces `left` bytes by repeating `unit`, holding only one copy.
struct Repeat {
    unit: Vec<u8>,
    pos: usize,
    left: usize,
}
impl Read for Repeat {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = (self.unit.len() - self.pos).min(buf.len()).min(self.left);
        buf[..n].copy_from_slice(&self.unit[self.pos..self.pos + n]);
        self.pos = (self.pos + n) % self.unit.len();
        self.left -= n;
        Ok(n)
    }
}

#[test]
fn a_large_program_streams_in_constant_memory() {
    let Some(before) = vm_hwm_kib() else {
        eprintln!("no /proc/self/status here; memory not measured");
        return;
    };
    // Arcs in two planes, modal lines, comments: ~140 bytes per repeat.
    let unit = b"G17 G90 G21\nG0 X10 Y0 Z1 (start)\nG1 Z-1 F600\nG3 X0 Y10 I-10 J0\n\
        G2 X-10 Y0 R10\nG18 G2 X10 Z-1 I10 K0\nG17 G1 X0 Y0\nX5\n"
        .to_vec();
    // Whole copies only, so the last line is not cut in half (~8 MiB, ~0.5 M
    // lines; debug builds are slow).
    let total = unit.len() * 60_000;
    let reader = BufReader::with_capacity(
        64 * 1024,
        Repeat {
            unit,
            pos: 0,
            left: total,
        },
    );
    let mut it = linearise(Interpreter::new(reader, Config::default()), 0.002);
    let mut n = 0u64;
    for m in it.by_ref() {
        m.unwrap();
        n += 1;
    }
    assert!(it.inner().lines_read() > 250_000);
    assert!(n > it.inner().lines_read());
    let after = vm_hwm_kib().unwrap();
    let grown_kib = after.saturating_sub(before);
    assert!(
        grown_kib < 4 * 1024,
        "peak RSS grew by {grown_kib} KiB while streaming {} MiB",
        total >> 20
    );
}
