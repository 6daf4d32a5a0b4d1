//! Synthetic programs for throughput measurements, deterministic (a fixed
//! seed), shared by `benches/gcode-bench.rs` and `examples/synth.rs` (which
//! writes them to files for end-to-end upload measurements).
//!
//! * [`cam`]: what CAM post-processors emit: modal G1 moves with 4-decimal
//!   coordinates, a feed now and then, G2/G3 arcs (I/J, end point on the
//!   circle), Z following a surface, Z steps and a comment every few hundred
//!   lines. About 23 bytes a line (8.6 M lines in 200 MB).
//! * [`parametric`]: the same kind of path written with parameters,
//!   expressions, functions and O-word control flow (`if`, a `sub` called
//!   with arguments).
#![allow(dead_code)]

use std::io::{self, Write};

/// xorshift64*: small, fast, reproducible.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    /// Uniform in [lo, hi).
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next() >> 11) as f64 / (1u64 << 53) as f64)
    }
}

/// Rounds to 4 decimals, as the program text carries it.
fn r4(v: f64) -> f64 {
    (v * 1e4).round() / 1e4
}

/// A CAM-style program of at least `bytes` bytes (ends with M30).
pub fn cam(bytes: u64, out: &mut impl Write) -> io::Result<u64> {
    let mut w = Counting { out, n: 0 };
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    writeln!(w, "%")?;
    writeln!(w, "(synthetic CAM program, {bytes} bytes)")?;
    writeln!(w, "(T1 D=6. CR=0. - ZMIN=-3. - flat end mill)")?;
    writeln!(w, "G90 G94 G17")?;
    writeln!(w, "G21")?;
    writeln!(w, "T1 M6")?;
    writeln!(w, "S12000 M3")?;
    writeln!(w, "G54")?;
    writeln!(w, "G0 X0. Y0.")?;
    writeln!(w, "Z5.")?;
    writeln!(w, "G1 Z-1. F300.")?;
    let (mut x, mut y, mut z) = (0.0f64, 0.0f64, -1.0f64);
    let mut line = 0u64;
    let mut in_g1 = true;
    while w.n < bytes {
        line += 1;
        if line % 500 == 0 {
            writeln!(w, "(pass {})", line / 500)?;
            continue;
        }
        if line % 97 == 0 {
            // Step down or back up between -3 and -0.5.
            z = r4((z + rng.range(-0.5, 0.5)).clamp(-3.0, -0.5));
            writeln!(w, "G1 Z{z:.4} F300.")?;
            in_g1 = true;
            continue;
        }
        if line % 23 == 0 {
            // An arc from the current point around a centre 1..8 mm away,
            // sweeping 10..120 degrees.
            let r = rng.range(1.0, 8.0);
            let th = rng.range(0.0, std::f64::consts::TAU);
            let (i, j) = (r4(-r * th.cos()), r4(-r * th.sin()));
            let (cx, cy) = (x + i, y + j);
            let cw = rng.next() & 1 == 0;
            let sweep = rng.range(10f64.to_radians(), 120f64.to_radians());
            let start = (y - cy).atan2(x - cx);
            let end = if cw { start - sweep } else { start + sweep };
            let rr = (i * i + j * j).sqrt();
            let (ex, ey) = (r4(cx + rr * end.cos()), r4(cy + rr * end.sin()));
            if ex.abs() > 150.0 || ey.abs() > 150.0 {
                continue;
            }
            writeln!(
                w,
                "G{} X{ex:.4} Y{ey:.4} I{i:.4} J{j:.4}",
                if cw { 2 } else { 3 }
            )?;
            (x, y) = (ex, ey);
            in_g1 = false;
            continue;
        }
        // A short straight move, pulled back towards the middle, following a
        // surface in Z (3D finishing) on most lines.
        let nx = r4(x + rng.range(-2.0, 2.0) - x * 0.01);
        let ny = r4(y + rng.range(-2.0, 2.0) - y * 0.01);
        let nz = r4((z + rng.range(-0.05, 0.05)).clamp(-3.0, -0.5));
        if !in_g1 {
            writeln!(w, "G1 X{nx:.4} Y{ny:.4} F1200.")?;
            in_g1 = true;
        } else if line % 7 == 0 {
            writeln!(w, "X{nx:.4}")?;
            (x, y) = (nx, y);
            continue;
        } else if line % 5 == 0 {
            writeln!(w, "X{nx:.4} Y{ny:.4}")?;
        } else {
            writeln!(w, "X{nx:.4} Y{ny:.4} Z{nz:.4}")?;
            z = nz;
        }
        (x, y) = (nx, ny);
    }
    writeln!(w, "G0 Z5.")?;
    writeln!(w, "M5")?;
    writeln!(w, "M30")?;
    writeln!(w, "%")?;
    Ok(w.n)
}

/// A parametric program of at least `bytes` bytes: the same kind of
/// zigzag, each move computed from parameters; an O-word `if` every pass
/// and a subroutine called with arguments for the arcs.
pub fn parametric(bytes: u64, out: &mut impl Write) -> io::Result<u64> {
    let mut w = Counting { out, n: 0 };
    writeln!(w, "(synthetic parametric program, {bytes} bytes)")?;
    writeln!(w, "G90 G94 G17 G21")?;
    writeln!(w, "#<_pfeed> = 1200")?;
    writeln!(w, "#<_pstep> = 0.25")?;
    writeln!(w, "#1 = 0 (x)")?;
    writeln!(w, "#2 = 0 (angle)")?;
    writeln!(w, "#3 = -1 (depth)")?;
    writeln!(
        w,
        "o100 sub (arc of radius #1 around the current point's left)"
    )?;
    writeln!(w, "  #10 = [#5420 - #1]")?;
    writeln!(w, "  G3 X#10 Y#5421 I[-#1 / 2] J0 F#<_pfeed>")?;
    writeln!(w, "o100 endsub")?;
    writeln!(w, "S12000 M3")?;
    writeln!(w, "G0 X0 Y0 Z5")?;
    writeln!(w, "G1 Z#3 F300")?;
    let mut pass = 0u64;
    while w.n < bytes {
        pass += 1;
        writeln!(w, "(pass {pass})")?;
        for k in 0..40 {
            match k % 8 {
                0 => writeln!(w, "#1 = [#1 + #<_pstep>]")?,
                1 => writeln!(w, "#2 = [#2 + 3.6]")?,
                2 => writeln!(w, "G1 X[#1 * 0.5 + 10] Y[SIN[#2] * 25] F#<_pfeed>")?,
                3 => writeln!(w, "G1 X[COS[#2] * 25 + #1 / 4] Y[#1 MOD 50]")?,
                4 => writeln!(w, "#<y> = [ABS[#2 MOD 90 - 45] - 20]")?,
                5 => writeln!(w, "G1 Y#<y>")?,
                6 => writeln!(w, "X[#5420 + 0.5] Y[#5421 - 0.25]")?,
                _ => writeln!(w, "G1 X[FIX[#1 * 10] / 10] Y[SQRT[ABS[#<y>]]]")?,
            }
        }
        writeln!(w, "o101 if [#1 GT 100]")?;
        writeln!(w, "  #1 = 0")?;
        writeln!(w, "o101 endif")?;
        writeln!(w, "o100 call [2.5]")?;
    }
    writeln!(w, "G0 Z5")?;
    writeln!(w, "M5")?;
    writeln!(w, "M2")?;
    Ok(w.n)
}

struct Counting<'a, W: Write> {
    out: &'a mut W,
    n: u64,
}
impl<W: Write> Write for Counting<'_, W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let k = self.out.write(buf)?;
        self.n += k as u64;
        Ok(k)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }
}
