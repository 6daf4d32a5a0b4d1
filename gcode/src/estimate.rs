//! Run-time estimate with the machine's acceleration and cornering: each move's time on a
//! trapezoidal speed profile, the speed at each junction planned with a bounded look-ahead
//! (forward and backward passes, as a motion controller's planner does), and a compact table of
//! cumulative times by line so a running job's remaining time can be read off at any line and
//! scaled by the overrides in force.
//!
//! Memory is bounded: at most [`LOOKAHEAD`] moves wait for their junction speeds, and the table
//! keeps at most [`MAX_MARKS`] marks (thinned by halves as a program grows).

use crate::arc::ArcGeometry;
use crate::{Motion, Point};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// Moves held for the look-ahead; when full, the older half is planned as if the machine
/// had to stop at the end of the newest (the result changes only for programs whose moves
/// are so short that this many of them fit within one braking distance).
pub const LOOKAHEAD: usize = 256;
/// Most marks kept in a [`TimeTable`].
pub const MAX_MARKS: usize = 512;

/// How a machine moves, for the time estimate. A backend describes its own (the contract's
/// `motion_profile`); the default is a machine that changes speed at once.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MotionProfile {
    /// G0 speed, mm/min.
    pub rapid_mm_min: f64,
    /// Lowest feed the machine runs, mm/min (a programmed F below it is raised); 0: none.
    pub min_feed_mm_min: f64,
    /// Highest feed the machine runs, mm/min (a programmed F above it is capped); 0: no cap.
    pub max_feed_mm_min: f64,
    /// Path acceleration, mm/s²; 0: speed changes at once (no ramps, no cornering limit).
    pub accel_mm_s2: f64,
    /// The largest step in any axis's speed a corner may make without slowing to it, mm/s
    /// (what a stepper can start or stop at without a ramp). At a corner the path slows until
    /// no axis's speed jumps by more; 0: the machine stops at every corner.
    pub corner_jump_mm_s: f64,
    /// The limits above are each axis's, not the path's (a step generator whose axes run at
    /// their own rates): a straight move's top speed and acceleration are the limits divided by
    /// the largest share of the move any one axis makes, so a diagonal runs faster than either
    /// axis alone. Arcs keep the path limits (their direction turns all the way).
    pub per_axis: bool,
}

impl Default for MotionProfile {
    fn default() -> Self {
        MotionProfile {
            rapid_mm_min: 5000.0,
            min_feed_mm_min: 0.0,
            max_feed_mm_min: 0.0,
            accel_mm_s2: 0.0,
            corner_jump_mm_s: 0.0,
            per_axis: false,
        }
    }
}

/// Cumulative time at the end of a line: feed moves (scaled by the feed override), rapids
/// (scaled by the rapid override) and the rest (dwells, rotary-only moves), seconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TimeMark {
    pub line: u32,
    pub feed_s: f64,
    pub rapid_s: f64,
    pub other_s: f64,
}

/// Where the time of a program goes, by line: marks in line order, the last one the end.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TimeTable {
    pub marks: Vec<TimeMark>,
}

impl TimeTable {
    /// Time left after `line` has run, with the feed and rapid overrides in percent.
    /// Between two marks the time is taken to pass evenly over the lines.
    pub fn remaining_after(&self, line: u32, feed_pct: f64, rapid_pct: f64) -> f64 {
        let Some(end) = self.marks.last() else {
            return 0.0;
        };
        let at = self.at(line);
        let scale = |pct: f64| if pct > 0.0 { 100.0 / pct } else { 1.0 };
        ((end.feed_s - at.feed_s) * scale(feed_pct)
            + (end.rapid_s - at.rapid_s) * scale(rapid_pct)
            + (end.other_s - at.other_s))
            .max(0.0)
    }

    /// The whole program's time at 100 %.
    pub fn total(&self) -> f64 {
        self.marks
            .last()
            .map_or(0.0, |m| m.feed_s + m.rapid_s + m.other_s)
    }

    /// The cumulative times once `line` has run (interpolated between marks).
    fn at(&self, line: u32) -> TimeMark {
        let zero = TimeMark {
            line: 0,
            feed_s: 0.0,
            rapid_s: 0.0,
            other_s: 0.0,
        };
        let i = self.marks.partition_point(|m| m.line <= line);
        let before = if i == 0 { zero } else { self.marks[i - 1] };
        let Some(after) = self.marks.get(i) else {
            return before;
        };
        let span = f64::from(after.line.saturating_sub(before.line));
        let t = if span > 0.0 {
            f64::from(line.saturating_sub(before.line)) / span
        } else {
            1.0
        };
        let lerp = |a: f64, b: f64| a + (b - a) * t;
        TimeMark {
            line,
            feed_s: lerp(before.feed_s, after.feed_s),
            rapid_s: lerp(before.rapid_s, after.rapid_s),
            other_s: lerp(before.other_s, after.other_s),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Feed,
    Rapid,
}

/// One move waiting for its junction speeds.
#[derive(Debug, Clone, Copy)]
struct Pending {
    line: u32,
    kind: Kind,
    len: f64,
    /// Cruise speed, mm/s.
    v: f64,
    /// Acceleration along the path, mm/s².
    a: f64,
    /// Unit direction at the end (the next junction's; an arc's differs from its start's).
    dir_out: Point,
    /// The highest speed the junction into this move allows (mm/s).
    cap_in: f64,
}

/// The estimator: feed it a program's motions in order, then [`Estimator::finish`].
#[derive(Debug)]
pub struct Estimator {
    profile: MotionProfile,
    queue: VecDeque<Pending>,
    /// Speed the first queued move is entered at (the previous move's planned exit).
    entry: f64,
    feed_s: f64,
    rapid_s: f64,
    other_s: f64,
    table: TimeTable,
    /// Lines between two kept marks (doubles when the table fills).
    stride: u32,
    last_line: u32,
    /// Scratch for [`Estimator::plan`], kept between calls.
    entry_max: Vec<f64>,
}

impl Estimator {
    pub fn new(profile: MotionProfile) -> Estimator {
        Estimator {
            profile,
            queue: VecDeque::new(),
            entry: 0.0,
            feed_s: 0.0,
            rapid_s: 0.0,
            other_s: 0.0,
            table: TimeTable::default(),
            stride: 1,
            last_line: 0,
            entry_max: Vec::new(),
        }
    }

    fn a(&self) -> f64 {
        self.profile.accel_mm_s2
    }

    /// The path speed of a feed move (mm/s); `reach` scales the machine's cap (see
    /// [`MotionProfile::per_axis`]).
    fn feed_speed(&self, feed_mm_min: f64, reach: f64) -> f64 {
        let p = &self.profile;
        let mut f = feed_mm_min.max(p.min_feed_mm_min);
        if p.max_feed_mm_min > 0.0 {
            f = f.min(p.max_feed_mm_min * reach);
        }
        f / 60.0
    }

    fn rapid_speed(&self, reach: f64) -> f64 {
        let r = if self.profile.rapid_mm_min > 0.0 {
            self.profile.rapid_mm_min
        } else {
            5000.0
        };
        r * reach / 60.0
    }

    /// How much faster than one axis's limits a straight move along `dir` may run: 1 for path
    /// limits; with per-axis limits, 1 / the largest component of the unit direction.
    fn reach(&self, dir: Point) -> f64 {
        let major = dir.iter().fold(0.0_f64, |m, c| m.max(c.abs()));
        if self.profile.per_axis && major > 1e-12 {
            1.0 / major
        } else {
            1.0
        }
    }

    /// Takes one motion of the program.
    pub fn push(&mut self, m: &Motion) {
        let len = match *m {
            Motion::Rapid { from, to, .. }
            | Motion::Linear { from, to, .. }
            | Motion::Probe { from, to, .. } => dist(from, to),
            _ => 0.0,
        };
        self.push_straight_len(m, len);
    }

    /// [`Estimator::push`] with the length of a rapid, linear or probing move already known
    /// (`len` = its `from`-`to` distance, computed as [`dist`] does; ignored for other
    /// motions): the analysis measures it too, and a square root per move is worth sparing.
    #[inline]
    pub(crate) fn push_straight_len(&mut self, m: &Motion, len: f64) {
        let line = m.line();
        match *m {
            Motion::Rapid { from, to, .. } => {
                self.straight(line, Kind::Rapid, from, to, len, None);
            }
            Motion::Linear {
                from,
                to,
                feed_mm_min,
                a,
                ..
            } => {
                let d = len;
                match a {
                    // A rotary-only move: its feed is degrees per minute, no junctions.
                    Some(r) if d == 0.0 => {
                        self.stop(line);
                        let v = self.feed_speed(feed_mm_min, 1.0);
                        if v > 0.0 {
                            self.other_s += (r.to - r.from).abs() / v;
                        }
                        self.mark(line);
                    }
                    _ => self.straight(line, Kind::Feed, from, to, len, Some(feed_mm_min)),
                }
            }
            Motion::Probe {
                from,
                to,
                feed_mm_min,
                ..
            } => {
                // Probing stops where it trips: planned as its whole way, from and to a stop.
                self.stop(line);
                self.straight(line, Kind::Feed, from, to, len, Some(feed_mm_min));
                self.stop(line);
            }
            Motion::Arc { feed_mm_min, .. } => {
                if let Some(g) = ArcGeometry::from_motion(m) {
                    let reach = self.arc_reach(&g);
                    let mut v = self.feed_speed(feed_mm_min, reach);
                    let a = self.a() * reach;
                    // Around a curve the path's centripetal acceleration v²/r is the
                    // machine's too.
                    let r = g.r0.max(g.r1);
                    if a > 0.0 && r > 0.0 {
                        v = v.min((a * r).sqrt());
                    }
                    let eps = 1e-4;
                    let dir_in = unit(g.from, g.point_at(eps));
                    let dir_out = unit(g.point_at(1.0 - eps), g.to);
                    self.enqueue(line, Kind::Feed, g.length(), (v, a), dir_in, dir_out);
                }
            }
            Motion::Dwell { seconds, .. } => {
                self.stop(line);
                self.other_s += seconds.max(0.0);
                self.mark(line);
            }
            // The machine stands still for these (spindle and coolant wait for the motion
            // to end; a pause or a tool change stops it).
            Motion::Spindle { .. }
            | Motion::Coolant { .. }
            | Motion::ToolChange { .. }
            | Motion::Pause { .. }
            | Motion::ProgramEnd { .. } => self.stop(line),
            _ => {}
        }
        self.last_line = self.last_line.max(line);
    }

    /// [`Estimator::reach`] averaged over an arc, whose direction turns (the harmonic mean
    /// of 32 chords: time, not speed, adds up along the path). A step generator runs an arc as
    /// short straight moves, each at its own axes' limits.
    fn arc_reach(&self, g: &ArcGeometry) -> f64 {
        const CHORDS: u32 = 32;
        if !self.profile.per_axis {
            return 1.0;
        }
        let mut slowness = 0.0;
        let mut prev = g.from;
        for i in 1..=CHORDS {
            let p = g.point_at(f64::from(i) / f64::from(CHORDS));
            slowness += 1.0 / self.reach(unit(prev, p));
            prev = p;
        }
        f64::from(CHORDS) / slowness
    }

    /// A straight move of `len` = `dist(from, to)` at `feed_mm_min` (None: a rapid).
    #[inline]
    fn straight(
        &mut self,
        line: u32,
        kind: Kind,
        from: Point,
        to: Point,
        len: f64,
        feed_mm_min: Option<f64>,
    ) {
        if len <= 0.0 {
            return;
        }
        let speed = |e: &Self, reach: f64| match feed_mm_min {
            Some(f) => e.feed_speed(f, reach),
            None => e.rapid_speed(reach),
        };
        if self.a() <= 0.0 && !self.profile.per_axis {
            // No junctions to plan and no axis shares: the direction is not needed.
            let v = speed(self, 1.0);
            if v > 0.0 && len.is_finite() && v.is_finite() {
                self.add(line, kind, len / v);
            }
            return;
        }
        // `unit(from, to)` without computing the length again (same divisions, same bits).
        let d = [
            (to[0] - from[0]) / len,
            (to[1] - from[1]) / len,
            (to[2] - from[2]) / len,
        ];
        let reach = self.reach(d);
        let v = speed(self, reach);
        let a = self.a() * reach;
        self.enqueue(line, kind, len, (v, a), d, d);
    }

    /// Queues a move of `len` mm at cruise speed and acceleration `(v, a)`.
    fn enqueue(
        &mut self,
        line: u32,
        kind: Kind,
        len: f64,
        (v, a): (f64, f64),
        dir_in: Point,
        dir_out: Point,
    ) {
        if !(len > 0.0 && v > 0.0 && len.is_finite() && v.is_finite()) {
            return;
        }
        if a <= 0.0 {
            // Speed changes at once: the move takes its length at its speed.
            self.add(line, kind, len / v);
            return;
        }
        let cap_in = match self.queue.back() {
            Some(prev) => self.junction_cap(prev.dir_out, dir_in).min(prev.v).min(v),
            None => 0.0,
        };
        self.queue.push_back(Pending {
            line,
            kind,
            len,
            v,
            a,
            dir_out,
            cap_in,
        });
        if self.queue.len() >= LOOKAHEAD {
            self.plan(LOOKAHEAD / 2);
        }
    }

    /// The highest speed at which no axis's speed changes by more than the corner jump.
    fn junction_cap(&self, a: Point, b: Point) -> f64 {
        let jump = (0..3).map(|i| (b[i] - a[i]).abs()).fold(0.0, f64::max);
        if jump < 1e-12 {
            f64::INFINITY
        } else {
            self.profile.corner_jump_mm_s / jump
        }
    }

    /// The machine stops here (a dwell, a spindle change): everything queued is planned to
    /// end at rest.
    fn stop(&mut self, line: u32) {
        let n = self.queue.len();
        self.plan(n);
        self.entry = 0.0;
        self.last_line = self.last_line.max(line);
    }

    /// Plans the queued moves with a stop after the last one, and releases the first `n`.
    fn plan(&mut self, n: usize) {
        let len = self.queue.len();
        if len == 0 {
            return;
        }
        // Backward: the fastest entry each move allows given it can still slow to the next.
        let mut entry_max = std::mem::take(&mut self.entry_max);
        entry_max.clear();
        entry_max.resize(len, 0.0);
        let mut exit = 0.0_f64;
        for k in (0..len).rev() {
            let m = self.queue[k];
            let reachable = (exit * exit + 2.0 * m.a * m.len).sqrt();
            let cap = if k == 0 {
                self.entry.min(m.v)
            } else {
                m.cap_in
            };
            entry_max[k] = cap.min(reachable);
            exit = entry_max[k];
        }
        // Forward: from the known entry, as fast as acceleration allows within those caps.
        let mut v_in = self.entry.min(entry_max[0]);
        let n = n.min(len);
        for k in 0..n {
            let m = self.queue[k];
            let next_cap = entry_max.get(k + 1).copied().unwrap_or(0.0);
            let v_out = next_cap.min((v_in * v_in + 2.0 * m.a * m.len).sqrt());
            let t = trapezoid(m.len, m.v, v_in, v_out, m.a);
            self.add(m.line, m.kind, t);
            v_in = v_out;
        }
        self.queue.drain(..n);
        self.entry = v_in;
        self.entry_max = entry_max;
    }

    fn add(&mut self, line: u32, kind: Kind, seconds: f64) {
        match kind {
            Kind::Feed => self.feed_s += seconds,
            Kind::Rapid => self.rapid_s += seconds,
        }
        self.mark(line);
    }

    /// Records the cumulative times at `line`, keeping at most [`MAX_MARKS`]: the newest mark
    /// moves along with the program until it is a stride past the one before it, then stays.
    fn mark(&mut self, line: u32) {
        // Lines run out of order in loops and subroutine calls: time is kept by the furthest
        // line reached, so the table only goes forward (a loop's time lands on its last line).
        let line = line.max(self.table.marks.last().map_or(0, |m| m.line));
        let mark = TimeMark {
            line,
            feed_s: self.feed_s,
            rapid_s: self.rapid_s,
            other_s: self.other_s,
        };
        let marks = &mut self.table.marks;
        let n = marks.len();
        if n >= 1 && marks[n - 1].line == line {
            marks[n - 1] = mark;
            return;
        }
        if n >= 2 && marks[n - 1].line.saturating_sub(marks[n - 2].line) < self.stride {
            marks[n - 1] = mark;
        } else {
            marks.push(mark);
        }
        if marks.len() >= MAX_MARKS {
            // Thin by half: every other mark goes, the newest stays.
            let newest = marks.len() - 1;
            let mut i = 0;
            marks.retain(|_| {
                let keep = i % 2 == 1 || i == newest;
                i += 1;
                keep
            });
            self.stride = self.stride.saturating_mul(2);
        }
    }

    /// Plans what is left (the program ends at rest) and answers the table; its last mark is
    /// the last line that did anything.
    pub fn finish(mut self) -> TimeTable {
        let n = self.queue.len();
        self.plan(n);
        let mark = TimeMark {
            line: self
                .last_line
                .max(self.table.marks.last().map_or(0, |m| m.line)),
            feed_s: self.feed_s,
            rapid_s: self.rapid_s,
            other_s: self.other_s,
        };
        match self.table.marks.last_mut() {
            Some(last) if last.line == mark.line => *last = mark,
            _ => self.table.marks.push(mark),
        }
        self.table
    }
}

/// Seconds to run `len` mm cruising at `v` (mm/s), entering at `v_in` and leaving at `v_out`,
/// accelerating at `a` (mm/s²).
fn trapezoid(len: f64, v: f64, v_in: f64, v_out: f64, a: f64) -> f64 {
    let v_in = v_in.min(v);
    let v_out = v_out.min(v);
    let d_acc = (v * v - v_in * v_in) / (2.0 * a);
    let d_dec = (v * v - v_out * v_out) / (2.0 * a);
    if d_acc + d_dec <= len {
        (v - v_in) / a + (v - v_out) / a + (len - d_acc - d_dec) / v
    } else {
        // Never reaches `v`: up to the peak where the two ramps meet, then down.
        let peak = ((2.0 * a * len + v_in * v_in + v_out * v_out) / 2.0)
            .sqrt()
            .max(v_in)
            .max(v_out);
        (peak - v_in) / a + (peak - v_out) / a
    }
}

/// The distance from `a` to `b`; `analysis` measures moves the same way, to the bit.
#[inline]
pub(crate) fn dist(a: Point, b: Point) -> f64 {
    let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

fn unit(a: Point, b: Point) -> Point {
    let l = dist(a, b);
    if l > 0.0 {
        [(b[0] - a[0]) / l, (b[1] - a[1]) / l, (b[2] - a[2]) / l]
    } else {
        [0.0; 3]
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::{Config, Interpreter};

    fn table(program: &str, p: MotionProfile) -> TimeTable {
        let mut e = Estimator::new(p);
        for m in Interpreter::new(program.as_bytes(), Config::default()) {
            e.push(&m.unwrap());
        }
        e.finish()
    }

    #[test]
    fn without_acceleration_a_move_takes_its_length_at_its_speed() {
        let t = table("G1 X100 F600\nG0 X0\nG4 P2\n", MotionProfile::default());
        // 100 mm at 10 mm/s, 100 mm at 5000 mm/min, 2 s.
        let end = *t.marks.last().unwrap();
        assert!((end.feed_s - 10.0).abs() < 1e-9, "{t:?}");
        assert!((end.rapid_s - 1.2).abs() < 1e-9, "{t:?}");
        assert!((end.other_s - 2.0).abs() < 1e-9, "{t:?}");
        // At 50 % feed the feed part doubles.
        assert!((t.remaining_after(0, 50.0, 100.0) - 23.2).abs() < 1e-9);
        // After line 1 only the rapid and the dwell are left.
        assert!((t.remaining_after(1, 100.0, 100.0) - 3.2).abs() < 1e-9);
    }

    #[test]
    fn acceleration_adds_the_ramps_and_corners_slow_the_path() {
        let p = MotionProfile {
            accel_mm_s2: 100.0,
            corner_jump_mm_s: 0.0,
            ..MotionProfile::default()
        };
        // One 100 mm move at 10 mm/s from and to rest: 0.1 s up, 0.1 s down, 0.5 mm each,
        // 99 mm cruising: 10.1 s.
        let one = table("G1 X100 F600\n", p).total();
        assert!((one - 10.1).abs() < 1e-9, "{one}");
        // Two collinear halves flow through (same time); a right angle stops (two ramps more).
        let straight = table("G1 X50 F600\nG1 X100\n", p).total();
        assert!((straight - 10.1).abs() < 1e-9, "{straight}");
        let corner = table("G1 X50 F600\nG1 Y50\n", p).total();
        assert!((corner - 10.2).abs() < 1e-9, "{corner}");
        // With a corner jump of 10 mm/s the right angle is taken at speed: |Δv| = 10 per axis.
        let soft = MotionProfile {
            corner_jump_mm_s: 10.0,
            ..p
        };
        let corner = table("G1 X50 F600\nG1 Y50\n", soft).total();
        assert!((corner - 10.1).abs() < 1e-9, "{corner}");
        // Too short to reach the feed: a triangle. 1 mm at a = 100: peak sqrt(100) = 10 mm/s
        // exactly at the middle: 0.2 s.
        let short = table("G1 X1 F6000\n", p).total();
        assert!((short - 0.2).abs() < 1e-9, "{short}");
    }

    /// Per-axis limits: a 3-4-5 diagonal's X makes 4/5 of it, so its path may run at 5/4 of
    /// the axis limit (and accelerate 5/4 as hard); an X-only move keeps the limit.
    #[test]
    fn per_axis_limits_let_a_diagonal_run_faster_than_one_axis() {
        let p = MotionProfile {
            rapid_mm_min: 600.0,
            max_feed_mm_min: 600.0,
            per_axis: true,
            ..MotionProfile::default()
        };
        let diagonal = table(
            "G1 X40 Y30 F6000
",
            p,
        )
        .total();
        assert!((diagonal - 50.0 / 12.5).abs() < 1e-9, "{diagonal}");
        let along_x = table(
            "G0 X40
", p,
        )
        .total();
        assert!((along_x - 4.0).abs() < 1e-9, "{along_x}");
        // A programmed feed under the cap is the path's feed either way.
        let slow = table(
            "G1 X40 Y30 F300
",
            p,
        )
        .total();
        assert!((slow - 10.0).abs() < 1e-9, "{slow}");
        let path = MotionProfile {
            per_axis: false,
            ..p
        };
        let diagonal = table(
            "G1 X40 Y30 F6000
",
            path,
        )
        .total();
        assert!((diagonal - 5.0).abs() < 1e-9, "{diagonal}");
    }

    /// A loop runs its lines again: the table stays in line order (its time on the furthest
    /// line reached) and sums every pass.
    #[test]
    fn loops_keep_the_table_in_line_order_and_count_every_pass() {
        let program =
            "F600\n#1=0\nO1 while [#1 lt 3]\nG1 X10\nG1 X0\n#1=[#1+1]\nO1 endwhile\nG1 Y10\n";
        let t = table(program, MotionProfile::default());
        assert!(t.marks.windows(2).all(|w| w[0].line < w[1].line), "{t:?}");
        // Six 1 s moves in the loop and one after it.
        assert!((t.total() - 7.0).abs() < 1e-9, "{t:?}");
    }

    #[test]
    fn the_table_stays_bounded_and_interpolates_by_line() {
        let mut program = String::new();
        for i in 0..100_000 {
            program.push_str(&format!("G1 X{} F600\n", if i % 2 == 0 { 10 } else { 0 }));
        }
        let t = table(&program, MotionProfile::default());
        assert!(t.marks.len() <= MAX_MARKS, "{}", t.marks.len());
        assert_eq!(t.marks.last().unwrap().line, 100_000);
        // Every line is 1 s: half-way leaves half.
        assert!((t.total() - 100_000.0).abs() < 1e-6);
        let half = t.remaining_after(50_000, 100.0, 100.0);
        assert!((half - 50_000.0).abs() < 1.0, "{half}");
        assert!(t.marks.windows(2).all(|w| w[0].line < w[1].line));
    }
}
