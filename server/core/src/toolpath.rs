//! A program's toolpath for previews: the moves the gcode crate interprets, as a compact binary
//! polyline with a move kind and source line per vertex, simplified so it never exceeds a vertex
//! budget (a million-line program still loads in a browser) while keeping its shape.
//!
//! Format (all little-endian; the README's "Toolpath format" describes it for clients):
//!
//! ```text
//! offset  size      field
//! 0       4         magic "FTP1"
//! 4       4  u32    n: vertex count
//! 8       4  u32    moves: moves read before decimation
//! 12      4  f32    decimation: every point of the program's path lies within this distance
//!                   (mm) of the polyline, and every point of the polyline within it of the
//!                   path (0: every move kept)
//! 16      24 f32x6  bounds min x,y,z, max x,y,z of every move's end (and the start)
//! 40      8         reserved (zero)
//! 48      12n f32   x,y,z per vertex (program coordinates, mm)
//! 48+12n  4n  u32   source line of the move that ends at the vertex
//! 48+16n  n   u8    kind of the move that ends at the vertex: 0 start, 1 rapid, 2 cut
//! ```
//!
//! Simplification: every vertex is a point of the exact path (the end of a move), in order. A
//! run of moves of one kind is replaced by the straight segment from its first to its last end
//! point only when every end point in between lies within the tolerance of that segment; the
//! segment is then within the tolerance of the moves too (their projection onto it covers it).
//! A stroke's turning point is therefore kept unless the stroke is shorter than the tolerance.
//! The tolerance starts at zero (every move kept) and doubles only when the kept vertices pass
//! the budget, and then the kept vertices are simplified again with it, so the distance reported
//! is the sum of the tolerances applied (at most twice the last). Time and memory: one pass over
//! the moves, each checked as a segment's end against at most [`WINDOW`] pending moves (the
//! look-ahead continues past a move that does not qualify, up to [`LOOK_PAST`] of them, so a
//! dense zig-zag is thinned stroke by stroke rather than cut at its first turn), and at most
//! `max_vertices` + [`WINDOW`] vertices kept; each re-simplification is one such pass over the
//! kept vertices, and there are at most as many as the tolerance doubles.

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
/// Moves a segment may stand for in one pass: what a move is checked against at most, so the
/// work per move is bounded by it.
pub const WINDOW: usize = 128;
/// Moves in a row that may fail to qualify as a segment's end before the best one found is
/// kept: enough to step over several strokes of a dense zig-zag (whose turning points qualify
/// every other move), few enough that a curve is not checked far past its last good end.
pub const LOOK_PAST: usize = 16;

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
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

/// A simplified toolpath.
#[derive(Debug, Default)]
pub struct Toolpath {
    /// Kept vertices; the last is the anchor the pending moves start from.
    vertices: Vec<Vertex>,
    /// Moves after the anchor not yet decided.
    pending: Window,
    moves: u64,
    /// Current tolerance (mm); 0 keeps every move. Doubled whenever the budget is reached.
    tolerance: f32,
    /// Bound of the distance between the kept polyline and the exact path: the sum of the
    /// tolerances the kept vertices went through.
    error: f32,
    /// Once the tolerance exceeds the path's size, kinds alone could still exceed the budget
    /// (rapids and cuts alternating); then they merge too, a cut winning.
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
            t.push(Vertex { p, line, kind }, max);
        }
        t.finish(max);
        Ok(Some(t))
    }

    pub fn len(&self) -> usize {
        self.vertices.len() + self.pending.moves.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The bound reported as `decimation`: how far the polyline may be from the exact path.
    pub fn decimation_mm(&self) -> f32 {
        self.error
    }

    /// Takes the end of the next move.
    fn push(&mut self, v: Vertex, max: usize) {
        if self.tolerance == 0.0 {
            self.vertices.push(v);
        } else {
            let (tolerance, merge_kinds) = (self.tolerance as f64, self.merge_kinds);
            self.pending
                .push(&mut self.vertices, v, tolerance, merge_kinds);
        }
        while self.vertices.len() > max {
            self.coarsen();
        }
    }

    /// Decides every pending move, then keeps coarsening until the budget holds.
    fn finish(&mut self, max: usize) {
        let (tolerance, merge_kinds) = (self.tolerance as f64, self.merge_kinds);
        self.pending
            .flush(&mut self.vertices, tolerance, merge_kinds);
        while self.vertices.len() > max {
            self.coarsen();
        }
    }

    /// Doubles the tolerance and simplifies the kept vertices again with it.
    fn coarsen(&mut self) {
        let size = dist(self.lo, self.hi);
        self.tolerance = if self.tolerance > 0.0 {
            self.tolerance * 2.0
        } else {
            (size * 1e-5).max(1e-4)
        };
        self.merge_kinds = self.tolerance > size.max(1e-3);
        // The vertices kept so far were within `error` of the path; simplified again, they are
        // within `error + tolerance` (and new moves within `tolerance`).
        self.error += self.tolerance;
        let (tolerance, merge_kinds) = (self.tolerance as f64, self.merge_kinds);
        let old = std::mem::take(&mut self.vertices);
        let mut again = Window::default();
        let mut rest = old.into_iter();
        if let Some(first) = rest.next() {
            self.vertices.push(first);
        }
        for v in rest {
            again.push(&mut self.vertices, v, tolerance, merge_kinds);
        }
        again.flush(&mut self.vertices, tolerance, merge_kinds);
        // The moves still pending follow the last vertex, which a pass always keeps; their
        // choice so far was made with the smaller tolerance, and stays valid under this one.
    }

    /// The binary form described in the module documentation.
    pub fn encode(&self) -> Vec<u8> {
        let all = || self.vertices.iter().chain(self.pending.moves.iter());
        let n = self.len();
        let mut out = Vec::with_capacity(HEADER_BYTES + 17 * n);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(n as u32).to_le_bytes());
        out.extend_from_slice(&(self.moves.min(u32::MAX as u64) as u32).to_le_bytes());
        out.extend_from_slice(&self.error.to_le_bytes());
        for c in self.lo.iter().chain(self.hi.iter()) {
            out.extend_from_slice(&c.to_le_bytes());
        }
        out.extend_from_slice(&[0; 8]);
        for v in all() {
            for c in v.p {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        for v in all() {
            out.extend_from_slice(&v.line.to_le_bytes());
        }
        out.extend(all().map(|v| v.kind as u8));
        out
    }
}

/// The moves after the last kept vertex (the anchor) not yet decided, and which of them the
/// segment from the anchor may stand for so far.
#[derive(Debug, Default)]
struct Window {
    moves: Vec<Vertex>,
    /// The farthest move (index) whose segment from the anchor passes within the tolerance of
    /// every move before it, all of one kind (unless kinds merge). The first always does.
    best: usize,
    /// Moves since `best` that did not qualify.
    misses: usize,
    /// A kind boundary was met: nothing after it may qualify.
    closed: bool,
    /// Moves to judge again after a vertex was kept, the next one last.
    replay: Vec<Vertex>,
}

impl Window {
    /// Adds the next move, keeping a vertex into `kept` whenever the look-ahead is exhausted.
    fn push(&mut self, kept: &mut Vec<Vertex>, v: Vertex, tolerance: f64, merge_kinds: bool) {
        self.add(kept, v, tolerance, merge_kinds);
        while let Some(m) = self.replay.pop() {
            self.add(kept, m, tolerance, merge_kinds);
        }
    }

    /// Decides every move left.
    fn flush(&mut self, kept: &mut Vec<Vertex>, tolerance: f64, merge_kinds: bool) {
        while !self.moves.is_empty() {
            self.keep_best(kept, merge_kinds);
            while let Some(m) = self.replay.pop() {
                self.add(kept, m, tolerance, merge_kinds);
            }
        }
    }

    fn add(&mut self, kept: &mut Vec<Vertex>, v: Vertex, tolerance: f64, merge_kinds: bool) {
        self.moves.push(v);
        let Some(anchor) = kept.last().copied() else {
            return;
        };
        self.judge_last(anchor, tolerance, merge_kinds);
        if self.moves.len() >= WINDOW || self.misses >= LOOK_PAST || self.closed {
            self.keep_best(kept, merge_kinds);
        }
    }

    /// Whether the newest move qualifies as the segment's end.
    fn judge_last(&mut self, anchor: Vertex, tolerance: f64, merge_kinds: bool) {
        let j = self.moves.len() - 1;
        if j == 0 {
            self.best = 0;
            self.misses = 0;
            self.closed = false;
            return;
        }
        if self.closed || (!merge_kinds && self.moves[j].kind != self.moves[0].kind) {
            self.closed = true;
            return;
        }
        let a = to_f64(anchor.p);
        let b = to_f64(self.moves[j].p);
        if self.moves[..j]
            .iter()
            .all(|q| segment_distance(to_f64(q.p), a, b) <= tolerance)
        {
            self.best = j;
            self.misses = 0;
        } else {
            self.misses += 1;
        }
    }

    /// Keeps the best move as a vertex; the moves after it are judged again from there (they
    /// go to `replay`, in front of any already waiting there).
    fn keep_best(&mut self, kept: &mut Vec<Vertex>, merge_kinds: bool) {
        if self.moves.is_empty() {
            return;
        }
        let j = self.best;
        let mut v = self.moves[j];
        if merge_kinds {
            v.kind = self.moves[..=j].iter().fold(v.kind, |k, p| k.max(p.kind));
        }
        kept.push(v);
        self.replay.extend(self.moves.drain(j + 1..).rev());
        self.moves.clear();
        self.best = 0;
        self.misses = 0;
        self.closed = false;
    }
}

/// Distance from `p` to the segment `a`-`b`.
fn segment_distance(p: [f64; 3], a: [f64; 3], b: [f64; 3]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let ap = [p[0] - a[0], p[1] - a[1], p[2] - a[2]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2];
    let t = if len2 > 0.0 {
        ((ap[0] * ab[0] + ap[1] * ab[1] + ap[2] * ab[2]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let d = [ap[0] - t * ab[0], ap[1] - t * ab[1], ap[2] - t * ab[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

fn to_f32(p: [f64; 3]) -> [f32; 3] {
    [p[0] as f32, p[1] as f32, p[2] as f32]
}

fn to_f64(p: [f32; 3]) -> [f64; 3] {
    [p[0] as f64, p[1] as f64, p[2] as f64]
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

    /// The exact path as the gcode crate gives it (start, then every rapid, linear and arc
    /// chord end), with the source line of each point.
    fn exact_path(prog: &str) -> Vec<([f64; 3], u32)> {
        let cfg = Config {
            arc_tolerance_mm: PREVIEW_ARC_TOLERANCE_MM,
            ..Config::default()
        };
        let mut out = vec![(cfg.initial_position, 0)];
        for m in Interpreter::new(prog.as_bytes(), cfg).linearised() {
            match m.unwrap() {
                Motion::Rapid { to, line, .. }
                | Motion::Linear { to, line, .. }
                | Motion::Arc { to, line, .. } => out.push((to, line)),
                _ => {}
            }
        }
        out
    }

    fn seg(p: [f64; 3], a: [f32; 3], b: [f32; 3]) -> f64 {
        segment_distance(p, to_f64(a), to_f64(b))
    }

    /// Builds the toolpath of `prog` with `max` vertices and checks it against the exact path:
    /// its vertices are points of the path in order (same line), every point of the path lies
    /// within the reported decimation distance of the drawn segment standing for it, and every
    /// drawn segment (sampled) lies within that distance of the moves it stands for. Returns
    /// the drawn points and the distance.
    fn checked(prog: &str, max: usize) -> (Vec<[f32; 3]>, f32) {
        let exact = exact_path(prog);
        let t = Toolpath::build(prog.as_bytes(), Config::default(), max).unwrap();
        let bytes = t.encode();
        let (pts, lines, _) = decode(&bytes);
        let d = f32::from_le_bytes(bytes[12..16].try_into().unwrap()) as f64;
        assert!(
            pts.len() <= max,
            "{} vertices for a budget of {max}",
            pts.len()
        );
        assert_eq!(t.moves as usize, exact.len() - 1);
        // f32 storage: a few units in the last place of the largest coordinate.
        let size = exact
            .iter()
            .flat_map(|(p, _)| p.iter())
            .fold(1.0f64, |m, c| m.max(c.abs()));
        let slack = size * 1e-6 + 1e-6;
        // Align each drawn vertex with the exact point it is.
        let mut at = Vec::with_capacity(pts.len());
        let mut i = 0;
        for (k, (p, line)) in pts.iter().zip(&lines).enumerate() {
            while i < exact.len() && !(to_f32(exact[i].0) == *p && exact[i].1 == *line) {
                i += 1;
            }
            assert!(
                i < exact.len(),
                "vertex {k} {p:?} (line {line}) is not on the path in order"
            );
            at.push(i);
            i += 1;
        }
        assert_eq!(at[0], 0, "starts at the start");
        assert_eq!(*at.last().unwrap(), exact.len() - 1, "ends at the end");
        for k in 1..pts.len() {
            let (a, b) = (pts[k - 1], pts[k]);
            let moves = &exact[at[k - 1]..=at[k]];
            // Path -> drawn: every exact point (the segment's moves are straight between them).
            for (p, line) in moves {
                let e = seg(*p, a, b);
                assert!(
                    e <= d + slack,
                    "line {line} {p:?} is {e} mm from the drawn {a:?}-{b:?} (decimation {d})"
                );
            }
            // Drawn -> path: points along the drawn segment, against those moves.
            for s in 1..8 {
                let f = s as f64 / 8.0;
                let q: [f64; 3] =
                    std::array::from_fn(|c| a[c] as f64 + f * (b[c] as f64 - a[c] as f64));
                let e = moves
                    .windows(2)
                    .map(|w| segment_distance(q, w[0].0, w[1].0))
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    e <= d + slack,
                    "drawn point {q:?} is {e} mm from the path (decimation {d})"
                );
            }
        }
        (pts, d as f32)
    }

    /// `rows` strokes from X0 to X`w` and back, each one move, `pitch` apart in Y.
    fn zigzag(rows: usize, w: f64, pitch: f64) -> String {
        let mut p = String::from("G21 G90\nG1 F1000\n");
        for i in 0..rows {
            let x = if i % 2 == 0 { w } else { 0.0 };
            p.push_str(&format!("X{x} Y{:.5}\n", i as f64 * pitch));
        }
        p
    }

    #[test]
    fn a_dense_zigzag_keeps_its_strokes() {
        // The issue's case: 3,000 strokes in 10 x 7 mm with a budget of 1,000 came back as 3
        // vertices.
        let (pts, d) = checked(&zigzag(3000, 10.0, 7.0 / 3000.0), 1000);
        assert!(pts.len() > 500, "{} vertices", pts.len());
        let left = pts.iter().filter(|p| p[0] == 0.0).count();
        let right = pts.iter().filter(|p| p[0] == 10.0).count();
        assert!(left > 200 && right > 200, "{left} at X0, {right} at X10");
        assert!(d < 0.1, "decimation {d} mm");
        // Alternating strokes one move each, far more than the budget.
        let (pts, d) = checked(&zigzag(40_000, 200.0, 0.005), 5000);
        eprintln!("zigzag: {} vertices, decimation {d}", pts.len());
        let right = pts.iter().filter(|p| p[0] == 200.0).count();
        assert!(right > 500, "{right} vertices at X200 of {}", pts.len());
        assert!(d < 1.0, "decimation {d} mm");
    }

    #[test]
    fn a_raster_of_small_steps_is_thinned_along_its_rows() {
        // 150 rows of 400 collinear 0.5 mm steps, with a lift between rows.
        let mut p = String::from("G21 G90 G1 F1000\n");
        for row in 0..150 {
            let y = row as f64 * 0.5;
            for col in 0..400 {
                let x = if row % 2 == 0 { col } else { 399 - col } as f64 * 0.5;
                p.push_str(&format!("X{x} Y{y}\n"));
            }
            p.push_str("G0 Z1\nG1 Z0\n");
        }
        let (pts, d) = checked(&p, 1000);
        // Collinear steps merge: every row's two ends remain, exactly.
        for row in 0..150 {
            let y = row as f32 * 0.5;
            for x in [0.0, 199.5] {
                assert!(
                    pts.iter().any(|p| p[0] == x && p[1] == y),
                    "row {row} lost its end at X{x}"
                );
            }
        }
        assert!(d < 0.01, "decimation {d}");
    }

    #[test]
    fn a_spiral_of_arcs_keeps_its_turns() {
        let mut p = String::from("G21 G90 G17 G1 F500\nX1 Y0\n");
        // Half turns, each 0.1 mm wider than the last (centre halfway): an arc spiral.
        let mut x0: f64 = 1.0;
        for _ in 0..100 {
            let x1 = -(x0.abs() + 0.25) * x0.signum();
            p.push_str(&format!("G3 X{x1:.4} Y0 I{:.4} J0\n", (x0 + x1) / 2.0 - x0));
            x0 = x1;
        }
        let moves = exact_path(&p).len();
        let (pts, d) = checked(&p, 2000);
        eprintln!(
            "spiral: {moves} moves, {} vertices, decimation {d}",
            pts.len()
        );
        assert!(moves > 2000, "{moves} moves");
        // Still a spiral: its outermost turn reaches about the final radius on both sides,
        // and its turns (0.5 mm apart) stay apart.
        let max_x = pts.iter().map(|p| p[0]).fold(f32::MIN, f32::max);
        let min_x = pts.iter().map(|p| p[0]).fold(f32::MAX, f32::min);
        assert!(max_x > 24.0 && min_x < -24.0, "{min_x}..{max_x}");
        assert!(d < 0.25, "decimation {d}");
    }

    #[test]
    fn tiny_detail_is_kept_while_the_budget_allows_and_bounded_after() {
        // A 100 mm square with a 0.02 mm notch in one side.
        let square = "G21 G90 G1 F300\nX50\nY-0.02\nX50.02\nY0\nX100\nY100\nX0\nY0\n";
        let (pts, d) = checked(square, 1000);
        assert_eq!(d, 0.0);
        assert_eq!(pts.len(), 9, "every move kept");
        // Repeated many times over a budget: gone only as far as the reported distance says.
        let many = square.repeat(2000);
        let (_, d) = checked(&many, 1000);
        assert!(d > 0.0);
    }

    #[test]
    fn alternating_kinds_and_the_budget_hold_on_adversarial_input() {
        let mut p = String::from("G21 G90\n");
        for i in 0..5000 {
            p.push_str(&format!(
                "G0 X{} Y{}\nG1 X{} Y{} F100\n",
                i % 7,
                i % 3,
                (i * 3) % 11,
                i % 5
            ));
        }
        checked(&p, 1000);
    }

    #[test]
    fn errors_name_line_and_column() {
        let e = Toolpath::build("G0 X1\nG1 X2 Q3 F1\n".as_bytes(), Config::default(), 1000)
            .unwrap_err();
        assert_eq!((e.line, e.column), (2, 7));
    }
}
