//! A program's toolpath for previews: the moves the gcode crate interprets, as a compact binary
//! polyline with a move kind and source line per vertex, decimated so it never exceeds a vertex
//! budget (a million-line program still loads in a browser).
//!
//! Format (all little-endian; the README's "Toolpath format" describes it for clients):
//!
//! ```text
//! offset  size      field
//! 0       4         magic "FTP1"
//! 4       4  u32    n: vertex count
//! 8       4  u32    moves: moves read before decimation
//! 12      4  f32    decimation: the smallest distance (mm) kept between merged vertices (0: none)
//! 16      24 f32x6  bounds min x,y,z, max x,y,z of every move's end (and the start)
//! 40      8         reserved (zero)
//! 48      12n f32   x,y,z per vertex (program coordinates, mm)
//! 48+12n  4n  u32   source line of the move that ends at the vertex
//! 48+16n  n   u8    kind of the move that ends at the vertex: 0 start, 1 rapid, 2 cut
//! ```

use fresa_gcode::{budgeted, linearise, Config, GcodeError, Interpreter, Motion, WorkBudget};
use std::io::BufRead;
use std::sync::atomic::{AtomicBool, Ordering};

pub const MAGIC: &[u8; 4] = b"FTP1";
pub const HEADER_BYTES: usize = 48;
/// Default and bounds of the vertex budget a client may ask for.
pub const DEFAULT_MAX_VERTICES: usize = 250_000;
pub const MIN_MAX_VERTICES: usize = 1_000;
pub const MAX_MAX_VERTICES: usize = 2_000_000;
/// Chord tolerance for arcs in a preview: a tenth of the cutting tolerance's precision is not
/// visible on a screen, and coarser chords keep the vertex count down.
const PREVIEW_ARC_TOLERANCE_MM: f64 = 0.01;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Kind {
    Start = 0,
    Rapid = 1,
    Cut = 2,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Vertex {
    p: [f32; 3],
    line: u32,
    kind: Kind,
}

/// A decimated toolpath.
#[derive(Debug, Default)]
pub struct Toolpath {
    vertices: Vec<Vertex>,
    moves: u64,
    /// Current merge distance (mm); doubled whenever the budget is reached.
    min_step: f32,
    /// Once the merge distance exceeds the path's size, kinds alone could still exceed the
    /// budget (rapids and cuts alternating); then they merge too, a cut winning.
    merge_kinds: bool,
    /// Bounds of every point seen (merged ones too), kept as they arrive.
    lo: [f32; 3],
    hi: [f32; 3],
}

impl Toolpath {
    /// Interprets the whole program (arcs as chords) and keeps at most `max_vertices` vertices.
    pub fn build<R: BufRead>(
        reader: R,
        config: Config,
        max_vertices: usize,
    ) -> Result<Toolpath, GcodeError> {
        let never = AtomicBool::new(false);
        Self::build_bounded(
            reader,
            config,
            max_vertices,
            fresa_gcode::DEFAULT_MAX_SEGMENTS,
            &never,
        )
        .map(|t| t.unwrap_or_default())
    }

    /// [`Toolpath::build`] within a work budget of `max_segments` (an
    /// [`fresa_gcode::ErrorKind::Budget`] error naming the line where it ran out), abandoned
    /// (`Ok(None)`) soon after `cancel` is set: the client that asked for it has gone.
    pub fn build_bounded<R: BufRead>(
        reader: R,
        mut config: Config,
        max_vertices: usize,
        max_segments: u64,
        cancel: &AtomicBool,
    ) -> Result<Option<Toolpath>, GcodeError> {
        config.arc_tolerance_mm = config.arc_tolerance_mm.max(PREVIEW_ARC_TOLERANCE_MM);
        let budget = WorkBudget::new(max_segments, config.arc_tolerance_mm);
        let start = config.initial_position;
        let max = max_vertices.max(2);
        let mut t = Toolpath {
            lo: to_f32(start),
            hi: to_f32(start),
            ..Toolpath::default()
        };
        t.vertices.push(Vertex {
            p: to_f32(start),
            line: 0,
            kind: Kind::Start,
        });
        let tolerance = config.arc_tolerance_mm;
        let motions = linearise(
            budgeted(Interpreter::new(reader, config), budget),
            tolerance,
        );
        for (i, m) in motions.enumerate() {
            // Often enough to stop within a millisecond or so, rarely enough to cost nothing.
            if i % 4096 == 0 && cancel.load(Ordering::Relaxed) {
                return Ok(None);
            }
            let (to, kind, line) = match m? {
                Motion::Rapid { to, line, .. } => (to, Kind::Rapid, line),
                Motion::Linear { to, line, .. } | Motion::Arc { to, line, .. } => {
                    (to, Kind::Cut, line)
                }
                _ => continue,
            };
            t.moves += 1;
            let p = to_f32(to);
            for (i, c) in p.iter().enumerate() {
                t.lo[i] = t.lo[i].min(*c);
                t.hi[i] = t.hi[i].max(*c);
            }
            t.push(Vertex {
                p: to_f32(to),
                line,
                kind,
            });
            while t.vertices.len() > max {
                t.coarsen();
            }
        }
        Ok(Some(t))
    }

    pub fn len(&self) -> usize {
        self.vertices.len()
    }

    pub fn is_empty(&self) -> bool {
        self.vertices.is_empty()
    }

    /// Adds a vertex, merging it into the previous one when that one ended a move of the same
    /// kind less than `min_step` from the vertex before it (the merged vertex takes the new end
    /// point and line, so the path's end points and progress stay exact).
    fn push(&mut self, v: Vertex) {
        let n = self.vertices.len();
        if n >= 2 && self.min_step > 0.0 {
            let prev = self.vertices[n - 1];
            let anchor = self.vertices[n - 2];
            let same_kind = prev.kind == v.kind || self.merge_kinds;
            if same_kind && prev.kind != Kind::Start && dist(anchor.p, v.p) < self.min_step {
                self.vertices[n - 1] = Vertex {
                    kind: if self.merge_kinds {
                        prev.kind.max_cut(v.kind)
                    } else {
                        v.kind
                    },
                    ..v
                };
                return;
            }
        }
        self.vertices.push(v);
    }

    /// Doubles the merge distance and re-applies it to what is kept so far.
    fn coarsen(&mut self) {
        let size = dist(self.lo, self.hi);
        self.min_step = if self.min_step > 0.0 {
            self.min_step * 2.0
        } else {
            (size * 1e-5).max(1e-4)
        };
        self.merge_kinds = self.min_step > size.max(1e-3);
        let old = std::mem::take(&mut self.vertices);
        for v in old {
            self.push(v);
        }
    }

    /// The binary form described in the module documentation.
    pub fn encode(&self) -> Vec<u8> {
        let n = self.vertices.len();
        let mut out = Vec::with_capacity(HEADER_BYTES + 17 * n);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(n as u32).to_le_bytes());
        out.extend_from_slice(&(self.moves.min(u32::MAX as u64) as u32).to_le_bytes());
        out.extend_from_slice(&self.min_step.to_le_bytes());
        for c in self.lo.iter().chain(self.hi.iter()) {
            out.extend_from_slice(&c.to_le_bytes());
        }
        out.extend_from_slice(&[0; 8]);
        for v in &self.vertices {
            for c in v.p {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        for v in &self.vertices {
            out.extend_from_slice(&v.line.to_le_bytes());
        }
        out.extend(self.vertices.iter().map(|v| v.kind as u8));
        out
    }
}

impl Kind {
    fn max_cut(self, other: Kind) -> Kind {
        if self == Kind::Cut || other == Kind::Cut {
            Kind::Cut
        } else {
            other
        }
    }
}

fn to_f32(p: [f64; 3]) -> [f32; 3] {
    [p[0] as f32, p[1] as f32, p[2] as f32]
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn decode(b: &[u8]) -> (Vec<[f32; 3]>, Vec<u32>, Vec<u8>) {
        assert_eq!(&b[..4], MAGIC);
        let n = u32::from_le_bytes(b[4..8].try_into().unwrap()) as usize;
        assert_eq!(b.len(), HEADER_BYTES + 17 * n);
        let f = |o: usize| f32::from_le_bytes(b[o..o + 4].try_into().unwrap());
        let pts = (0..n)
            .map(|i| {
                let o = HEADER_BYTES + 12 * i;
                [f(o), f(o + 4), f(o + 8)]
            })
            .collect();
        let lines = (0..n)
            .map(|i| {
                let o = HEADER_BYTES + 12 * n + 4 * i;
                u32::from_le_bytes(b[o..o + 4].try_into().unwrap())
            })
            .collect();
        let kinds = b[HEADER_BYTES + 16 * n..].to_vec();
        (pts, lines, kinds)
    }

    #[test]
    fn small_program_is_kept_exactly() {
        let prog = "G21 G90\nG0 X10 Y5\nG1 Z-1 F100\nG1 X20\nG0 Z5\nM30\n";
        let t = Toolpath::build(prog.as_bytes(), Config::default(), 1000).unwrap();
        let (pts, lines, kinds) = decode(&t.encode());
        assert_eq!(
            pts,
            vec![
                [0.0, 0.0, 0.0],
                [10.0, 5.0, 0.0],
                [10.0, 5.0, -1.0],
                [20.0, 5.0, -1.0],
                [20.0, 5.0, 5.0]
            ]
        );
        assert_eq!(lines, vec![0, 2, 3, 4, 5]);
        assert_eq!(kinds, vec![0, 1, 2, 2, 1]);
    }

    #[test]
    fn a_long_program_stays_within_the_budget_and_keeps_its_ends() {
        let mut prog = String::from("G21 G90 G1 F1000\n");
        for i in 0..20_000 {
            let y = (i / 100) as f64;
            let x = if (i / 100) % 2 == 0 {
                (i % 100) as f64
            } else {
                (99 - i % 100) as f64
            };
            prog.push_str(&format!("X{x} Y{y}\n"));
            if i % 1000 == 999 {
                prog.push_str("G0 Z5\nG1 Z0\n");
            }
        }
        let t = Toolpath::build(prog.as_bytes(), Config::default(), 1000).unwrap();
        assert!(t.len() <= 1000, "{}", t.len());
        assert!(t.len() > 100, "{}", t.len());
        let (pts, lines, kinds) = decode(&t.encode());
        let last_line = prog.lines().count() as u32;
        assert_eq!(*lines.last().unwrap(), last_line);
        assert_eq!(*pts.last().unwrap(), [0.0, 199.0, 0.0]);
        assert!(
            lines.windows(2).all(|w| w[0] <= w[1]),
            "lines never go back"
        );
        // Every rapid lift survives decimation.
        assert_eq!(kinds.iter().filter(|&&k| k == 1).count(), 20);
    }

    #[test]
    fn alternating_kinds_still_fit_the_budget() {
        let mut prog = String::from("G21 G90\n");
        for i in 0..5000 {
            prog.push_str(&format!("G0 X{} \nG1 Y{} F100\n", i % 7, i % 5));
        }
        let t = Toolpath::build(prog.as_bytes(), Config::default(), 1000).unwrap();
        assert!(t.len() <= 1000, "{}", t.len());
    }

    #[test]
    fn the_work_budget_bounds_it_and_a_cancelled_build_stops() {
        let huge = "G0 X0 Y0\nG2 X0 Y0 I400000 J0 P10000 F100\n";
        let go = AtomicBool::new(false);
        let e = Toolpath::build_bounded(huge.as_bytes(), Config::default(), 1000, 1_000_000, &go)
            .unwrap_err();
        assert_eq!((e.line, e.kind), (2, fresa_gcode::ErrorKind::Budget), "{e}");
        // Within the budget but cancelled: abandoned at the next check, not built.
        let stop = AtomicBool::new(true);
        let t = Toolpath::build_bounded(huge.as_bytes(), Config::default(), 1000, u64::MAX, &stop)
            .unwrap();
        assert!(t.is_none());
    }

    #[test]
    fn errors_name_line_and_column() {
        let e = Toolpath::build("G0 X1\nG1 X2 Q3 F1\n".as_bytes(), Config::default(), 1000)
            .unwrap_err();
        assert_eq!((e.line, e.column), (2, 7));
    }
}
