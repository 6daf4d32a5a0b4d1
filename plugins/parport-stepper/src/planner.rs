//! The pure planner: a program (or a jog) becomes a timeline of output actions on a tick grid,
//! with no clock and no I/O, so it is tested and benchmarked on its own.
//!
//! Every move is a straight line in step space: the axis with more steps (major) steps on a
//! trapezoidal velocity profile, the other follows with a Bresenham interleave, so at every
//! major step the minor axis is within half a step of the ideal line, and both end on the exact
//! step counts. Z is a tool lift (on/off), not interpolated.

use fresa_gcode::{budgeted, linearise, Budgeted, Interpreter, Linearise, Motion, WorkBudget};
use fresa_plugin_api::contract::{Preamble, PreambleStep, WorkOffset};
use std::collections::VecDeque;
use std::io::BufRead;

/// Chord tolerance for arcs, mm.
pub const ARC_TOLERANCE_MM: f64 = 0.002;

/// Speed limits of one stepper axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisLimits {
    pub steps_per_mm: f64,
    /// Highest step rate, steps/s.
    pub max_rate: f64,
    /// Rate the motor can start and stop at without a ramp, steps/s.
    pub start_rate: f64,
    /// Acceleration, steps/s².
    pub accel: f64,
}

/// Everything the planner needs to know about the machine.
#[derive(Debug, Clone, PartialEq)]
pub struct Machine {
    pub axes: [AxisLimits; 2],
    /// Output ticks per second.
    pub tick_hz: f64,
    /// G0 and go-to-zero speed, mm/min (capped by the axes' max rates).
    pub rapid_mm_min: f64,
    /// Work Z above this is "tool lifted".
    pub lift_above_mm: f64,
    /// Time the lift needs to settle before XY moves on, ticks.
    pub lift_settle_ticks: u64,
    /// Soft limits, machine mm, per XY axis.
    pub travel: [Option<(f64, f64)>; 2],
}

/// How this machine moves, for the host's run-time estimate: the slower axis's acceleration,
/// top rate and no-ramp rate, in mm, as per-axis limits (each axis runs at its own rate, so a
/// diagonal is faster than either axis alone; the corner rule is that no axis's speed jumps
/// by more than its start rate). The Z lift's switching and settling are not in it.
pub fn motion_profile(m: &Machine) -> fresa_plugin_api::contract::MotionProfile {
    let min = |f: fn(&AxisLimits) -> f64| {
        m.axes
            .iter()
            .map(|a| f(a) / a.steps_per_mm)
            .fold(f64::INFINITY, f64::min)
    };
    let max_feed = min(|a| a.max_rate) * 60.0;
    fresa_plugin_api::contract::MotionProfile {
        rapid_mm_min: m.rapid_mm_min.min(max_feed),
        min_feed_mm_min: 0.0,
        max_feed_mm_min: max_feed,
        accel_mm_s2: min(|a| a.accel),
        corner_jump_mm_s: min(|a| a.start_rate),
        per_axis: true,
    }
}

/// A trapezoidal (or triangular) profile over `n` steps of the major axis: from `v_in`
/// up to at most `v` at `a`, cruise, down to `v_out`. When motion already under way enters
/// above the top speed (an override lowered it), the first ramp slows down to `v` instead
/// ([`Profile::entering`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Profile {
    n: u64,
    v_in: f64,
    v_out: f64,
    v: f64,
    a: f64,
    /// Steps spent on the first ramp (accelerating, or slowing down from above `v`) / on the
    /// last (decelerating).
    d_acc: f64,
    d_dec: f64,
    t_acc: f64,
    total: f64,
    /// The first ramp slows down (entry above the top speed).
    slowing_in: bool,
}

impl Profile {
    /// Rates in steps/s, `a` in steps/s². Entry and exit rates that the move is too short to
    /// join at `a` are lowered until it can.
    pub fn new(n: u64, v_max: f64, v_in: f64, v_out: f64, a: f64) -> Profile {
        let nf = n as f64;
        let mut v_in = v_in.min(v_max);
        let mut v_out = v_out.min(v_max);
        // Reachable within the move at all (the junction planner keeps this true; this only
        // guards against rounding).
        v_out = v_out.min((v_in * v_in + 2.0 * a * nf).sqrt());
        v_in = v_in.min((v_out * v_out + 2.0 * a * nf).sqrt());
        let mut v = v_max;
        let mut d_acc = (v * v - v_in * v_in) / (2.0 * a);
        let mut d_dec = (v * v - v_out * v_out) / (2.0 * a);
        if d_acc + d_dec > nf {
            // Triangle: the peak where the two ramps meet.
            v = ((2.0 * a * nf + v_in * v_in + v_out * v_out) / 2.0)
                .sqrt()
                .max(v_in)
                .max(v_out);
            d_acc = ((v * v - v_in * v_in) / (2.0 * a)).clamp(0.0, nf);
            d_dec = (nf - d_acc).max(0.0);
        }
        let t_acc = (v - v_in) / a;
        let t_dec = (v - v_out) / a;
        let total = t_acc + (nf - d_acc - d_dec).max(0.0) / v + t_dec;
        Profile {
            n,
            v_in,
            v_out,
            v,
            a,
            d_acc,
            d_dec,
            t_acc,
            total,
            slowing_in: false,
        }
    }

    /// A profile whose entry rate is fixed by motion already under way (re-timed for an
    /// override): `v_in` is kept as it is, also above `v_max` (the move then slows down to
    /// `v_max` at `a` first), and an exit rate `v_in` cannot slow down to within the `n` steps
    /// is raised to the one it can (slowing down all the way). The rate never jumps.
    pub fn entering(n: u64, v_max: f64, v_in: f64, v_out: f64, a: f64) -> Profile {
        let nf = n as f64;
        let slowest = (v_in * v_in - 2.0 * a * nf).max(0.0).sqrt();
        let fastest = (v_in * v_in + 2.0 * a * nf).sqrt();
        // (A margin, so an exit the junction planner made reachable is kept bit for bit.)
        let v_out = if slowest > v_out * (1.0 + 1e-12) {
            slowest
        } else {
            v_out.min(fastest)
        };
        // (Within rounding of the top speed: path speeds converted back to steps.)
        if v_in <= v_max * (1.0 + 1e-9) {
            return Profile::new(n, v_max, v_in, v_out, a);
        }
        // Slow down to the top speed (or to the exit, if that is above it), cruise, slow down
        // to the exit.
        let v = v_max.max(v_out);
        let d_acc = ((v_in * v_in - v * v) / (2.0 * a)).clamp(0.0, nf);
        let d_dec = ((v * v - v_out * v_out) / (2.0 * a)).clamp(0.0, nf - d_acc);
        let t_acc = (v_in - v) / a;
        let t_dec = (v - v_out) / a;
        let total = t_acc + (nf - d_acc - d_dec).max(0.0) / v + t_dec;
        Profile {
            n,
            v_in,
            v_out,
            v,
            a,
            d_acc,
            d_dec,
            t_acc,
            total,
            slowing_in: true,
        }
    }

    fn ramp_time(&self, v0: f64, s: f64) -> f64 {
        ((v0 * v0 + 2.0 * self.a * s).sqrt() - v0) / self.a
    }

    /// Seconds from the start of the move until the major axis has made `s` steps.
    pub fn time_at(&self, s: f64) -> f64 {
        let nf = self.n as f64;
        if s <= self.d_acc {
            if self.slowing_in {
                (self.v_in - (self.v_in * self.v_in - 2.0 * self.a * s).max(0.0).sqrt()) / self.a
            } else {
                self.ramp_time(self.v_in, s)
            }
        } else if s < nf - self.d_dec {
            self.t_acc + (s - self.d_acc) / self.v
        } else {
            self.total - self.ramp_time(self.v_out, (nf - s).max(0.0))
        }
    }

    /// The major axis's rate (steps/s) once it has made `s` steps.
    pub fn rate_at(&self, s: f64) -> f64 {
        let nf = self.n as f64;
        if s <= self.d_acc {
            let sign = if self.slowing_in { -1.0 } else { 1.0 };
            (self.v_in * self.v_in + sign * 2.0 * self.a * s)
                .max(0.0)
                .sqrt()
        } else if s < nf - self.d_dec {
            self.v
        } else {
            (self.v_out * self.v_out + 2.0 * self.a * (nf - s).max(0.0)).sqrt()
        }
    }

    pub fn seconds(&self) -> f64 {
        self.total
    }

    pub fn peak_rate(&self) -> f64 {
        self.v
    }

    pub fn entry_rate(&self) -> f64 {
        self.v_in
    }

    pub fn exit_rate(&self) -> f64 {
        self.v_out
    }
}

/// Which override a move follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pace {
    /// A programmed feed move (G1, G2, G3): the feed override.
    Feed,
    /// G0 and go-to-zero: the rapid override.
    Rapid,
    /// Jogs and probing moves: their own feed, no override.
    Fixed,
}

/// Feed and rapid override as factors (1.0 = 100 %).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scale {
    pub feed: f64,
    pub rapid: f64,
}

impl Default for Scale {
    fn default() -> Self {
        Scale {
            feed: 1.0,
            rapid: 1.0,
        }
    }
}

/// One straight move in step space, or a piece of one (a long move is given out to the output
/// thread in pieces, so an override can re-time the rest of it).
#[derive(Debug, Clone, PartialEq)]
pub struct Move {
    /// Where the line starts (the interleave's origin) and ends, steps.
    pub from: [i64; 2],
    pub to: [i64; 2],
    /// The programmed line, machine mm: the deviation is measured against it.
    pub ideal: [[f64; 2]; 2],
    pub steps_per_mm: [f64; 2],
    /// Starts at this piece's first step (it may run past its last: a piece cut off the front
    /// of a move keeps the move's profile).
    pub profile: Profile,
    tick_hz: f64,
    /// Tick of the last step, counted from the start of the piece (the piece's length).
    pub ticks: u64,
    /// Limits of this move in major-axis steps: top rate, no-ramp rate, acceleration.
    v_max: f64,
    v_start: f64,
    accel: f64,
    /// Length (mm, of the stepped line, this piece's part of it) and unit direction, for
    /// junction speeds.
    length_mm: f64,
    unit: [f64; 2],
    /// Major-axis steps of the whole line, per mm of its path.
    per_mm: f64,
    /// Steps of the line made before this piece, and this piece's steps.
    first: u64,
    count: u64,
    /// Seconds from the piece's first tick to its profile's start (the part of a tick the
    /// piece before it was rounded by): pieces of a move step when the whole move would,
    /// with no drift from rounding each.
    phase: f64,
    /// The override it follows and its limits before any (major-axis steps/s): the axes' top
    /// rate, the programmed feed's (infinite without one), the no-ramp rate.
    pace: Pace,
    axes_max: f64,
    feed_max: f64,
    ramp_free: f64,
}

/// One step of a move: the new position (both axes) and how far it is from the programmed line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepEvent {
    /// Tick, counted from the start of the move (>= 1, strictly increasing).
    pub tick: u64,
    pub pos: [i64; 2],
    pub deviation_mm: f64,
}

/// The top rate (major-axis steps/s) of a move of `pace` under `scale`: the feed override
/// scales the programmed feed (never above what the axes allow), the rapid override the rapid
/// speed the axes allow.
fn top_rate(pace: Pace, axes_max: f64, feed_max: f64, scale: Scale) -> f64 {
    match pace {
        Pace::Feed => axes_max.min(feed_max * scale.feed),
        Pace::Rapid => axes_max.min(feed_max) * scale.rapid,
        Pace::Fixed => axes_max.min(feed_max),
    }
}

impl Move {
    /// A move from step position `from` to `to`; `ideal` the programmed line in machine mm;
    /// `feed_mm_min` the path feed (None = as fast as the axes allow). No override applies.
    pub fn new(
        machine: &Machine,
        from: [i64; 2],
        to: [i64; 2],
        ideal: [[f64; 2]; 2],
        feed_mm_min: Option<f64>,
    ) -> Move {
        Move::paced(
            machine,
            from,
            to,
            ideal,
            feed_mm_min,
            Pace::Fixed,
            Scale::default(),
        )
    }

    /// [`Move::new`] for a move that follows the `pace` override, at `scale`.
    pub fn paced(
        machine: &Machine,
        from: [i64; 2],
        to: [i64; 2],
        ideal: [[f64; 2]; 2],
        feed_mm_min: Option<f64>,
        pace: Pace,
        scale: Scale,
    ) -> Move {
        let d = [
            (to[0] - from[0]).unsigned_abs(),
            (to[1] - from[1]).unsigned_abs(),
        ];
        let n = d[0].max(d[1]);
        let nf = n.max(1) as f64;
        // Limits of each axis, expressed in major-axis steps.
        let mut axes_max = f64::INFINITY;
        let mut v0 = f64::INFINITY;
        let mut a = f64::INFINITY;
        for (i, ax) in machine.axes.iter().enumerate() {
            if d[i] > 0 {
                let k = nf / d[i] as f64;
                axes_max = axes_max.min(ax.max_rate * k);
                v0 = v0.min(ax.start_rate * k);
                a = a.min(ax.accel * k);
            }
        }
        if !axes_max.is_finite() {
            axes_max = 1.0;
            v0 = 1.0;
            a = 1.0;
        }
        let length_mm = (0..2)
            .map(|i| (d[i] as f64 / machine.axes[i].steps_per_mm).powi(2))
            .sum::<f64>()
            .sqrt();
        let mut feed_max = f64::INFINITY;
        if let Some(f) = feed_mm_min.filter(|f| *f > 0.0 && length_mm > 0.0) {
            let seconds = length_mm / (f / 60.0);
            feed_max = nf / seconds;
        }
        let v_max = top_rate(pace, axes_max, feed_max, scale);
        let unit = if length_mm > 0.0 {
            [
                (to[0] - from[0]) as f64 / machine.axes[0].steps_per_mm / length_mm,
                (to[1] - from[1]) as f64 / machine.axes[1].steps_per_mm / length_mm,
            ]
        } else {
            [0.0, 0.0]
        };
        let per_mm = if length_mm > 0.0 {
            n as f64 / length_mm
        } else {
            1.0
        };
        let mut m = Move {
            from,
            to,
            ideal,
            steps_per_mm: [machine.axes[0].steps_per_mm, machine.axes[1].steps_per_mm],
            profile: Profile::new(n, v_max, v0, v0, a),
            tick_hz: machine.tick_hz,
            ticks: 0,
            v_max,
            v_start: v0.min(v_max),
            accel: a,
            length_mm,
            unit,
            per_mm,
            first: 0,
            count: n,
            phase: 0.0,
            pace,
            axes_max,
            feed_max,
            ramp_free: v0,
        };
        m.ticks = m.last_tick();
        m
    }

    /// Tick of the last step, in closed form: steps are at least two ticks apart at any rate
    /// the config allows (`max_rate <= tick_hz / 2`), so rounding never has to push one later
    /// and the last step lands at the rounded end time (the proptest checks this).
    fn last_tick(&self) -> u64 {
        let n = self.count;
        if n == 0 {
            return 0;
        }
        self.tick_of(n).max(n)
    }

    /// Tick of step `k` of this piece (rounded; counted from the piece's start).
    fn tick_of(&self, k: u64) -> u64 {
        ((self.phase + self.profile.time_at(k as f64)) * self.tick_hz).round() as u64
    }

    /// Major-axis steps per mm of path.
    fn steps_per_path_mm(&self) -> f64 {
        self.per_mm
    }

    /// Re-times the move to enter at `v_in` and leave at `v_out` (path mm/s). An entry above
    /// the top speed (motion under way when an override lowered it) slows down to it.
    pub fn set_junction_speeds(&mut self, v_in: f64, v_out: f64) {
        let k = self.steps_per_path_mm();
        self.profile = Profile::entering(self.count, self.v_max, v_in * k, v_out * k, self.accel);
        self.ticks = self.last_tick();
    }

    /// Applies overrides: the top speed for `scale` (a move with its own feed keeps it), and
    /// the stand-alone profile from and to the no-ramp rate (the junction planner re-times it
    /// when it has neighbours or motion under way before it).
    pub fn relimit(&mut self, scale: Scale) {
        if self.pace == Pace::Fixed {
            return;
        }
        self.v_max = top_rate(self.pace, self.axes_max, self.feed_max, scale);
        self.v_start = self.ramp_free.min(self.v_max);
        self.profile = Profile::new(
            self.count,
            self.v_max,
            self.ramp_free,
            self.ramp_free,
            self.accel,
        );
        self.ticks = self.last_tick();
    }

    /// Path speeds (mm/s): top, no-ramp, and acceleration (mm/s²).
    fn path_limits(&self) -> (f64, f64, f64) {
        let k = self.steps_per_path_mm();
        (self.v_max / k, self.v_start / k, self.accel / k)
    }

    /// Major-axis steps of this piece.
    pub fn major_steps(&self) -> u64 {
        self.count
    }

    /// Path speed (mm/s) at the end of this piece.
    pub fn exit_speed(&self) -> f64 {
        self.profile.rate_at(self.count as f64) / self.steps_per_path_mm()
    }

    /// The most steps from the start of this piece that are made within `ticks`.
    fn steps_within(&self, ticks: u64) -> u64 {
        let (mut lo, mut hi) = (0, self.count);
        while lo < hi {
            let mid = lo + (hi - lo).div_ceil(2);
            if self.tick_of(mid) <= ticks {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        lo
    }

    /// Cuts this piece after its first `k` steps (0 < k < its steps): it keeps its profile
    /// for them; the rest, returned, starts at the rate reached there and ends as this did.
    fn split_off(&mut self, k: u64) -> Move {
        let mut rest = self.clone();
        rest.first = self.first + k;
        rest.count = self.count - k;
        rest.length_mm = rest.count as f64 / self.per_mm;
        rest.profile = Profile::entering(
            rest.count,
            self.v_max,
            self.profile.rate_at(k as f64),
            self.profile.exit_rate(),
            self.accel,
        );
        self.count = k;
        self.length_mm = k as f64 / self.per_mm;
        self.ticks = self.last_tick();
        rest.phase = self.phase + self.profile.time_at(k as f64) - self.ticks as f64 / self.tick_hz;
        rest.ticks = rest.last_tick();
        rest
    }

    /// Path speed at the top of the profile, mm/min.
    pub fn peak_feed_mm_min(&self) -> f64 {
        let d = [
            (self.to[0] - self.from[0]) as f64 / self.steps_per_mm[0],
            (self.to[1] - self.from[1]) as f64 / self.steps_per_mm[1],
        ];
        let n = ((self.to[0] - self.from[0]).abs())
            .max((self.to[1] - self.from[1]).abs())
            .max(1) as f64;
        self.profile.peak_rate() / n * d[0].hypot(d[1]) * 60.0
    }

    /// The steps of this piece, in order.
    pub fn steps(&self) -> MoveSteps<'_> {
        let d = [self.to[0] - self.from[0], self.to[1] - self.from[1]];
        let n = d[0].abs().max(d[1].abs());
        let a = self.ideal[0];
        let dir = [self.ideal[1][0] - a[0], self.ideal[1][1] - a[1]];
        let len2 = dir[0] * dir[0] + dir[1] * dir[1];
        let sign = [d[0].signum(), d[1].signum()];
        let inc = [2 * d[0].abs(), 2 * d[1].abs()];
        // The interleave after the steps made before this piece, in closed form: the
        // accumulator starts at n and gains `inc` a step, giving a step each time it passes
        // a multiple of 2n.
        let mut pos = self.from;
        let mut acc = [n, n];
        if self.first > 0 {
            for i in 0..2 {
                let t = i128::from(n) + i128::from(self.first) * i128::from(inc[i]);
                let two_n = 2 * i128::from(n);
                pos[i] += sign[i] * i64::try_from(t / two_n).unwrap_or(0);
                acc[i] = i64::try_from(t % two_n).unwrap_or(0);
            }
        }
        MoveSteps {
            m: self,
            k: 0,
            pos,
            sign,
            inc,
            acc,
            two_n: 2 * n,
            last_tick: 0,
            origin: a,
            dir,
            inv_len2: if len2 > 0.0 { 1.0 / len2 } else { 0.0 },
            mm_per_step: [1.0 / self.steps_per_mm[0], 1.0 / self.steps_per_mm[1]],
        }
    }

    /// Where this piece starts, steps.
    pub fn start_pos(&self) -> [i64; 2] {
        self.steps().pos
    }
}

/// Iterator over the steps of a [`Move`].
pub struct MoveSteps<'a> {
    m: &'a Move,
    k: u64,
    pos: [i64; 2],
    sign: [i64; 2],
    inc: [i64; 2],
    /// Bresenham accumulators, starting at n (half a step) so minor steps round to nearest.
    acc: [i64; 2],
    two_n: i64,
    last_tick: u64,
    origin: [f64; 2],
    dir: [f64; 2],
    inv_len2: f64,
    mm_per_step: [f64; 2],
}

impl Iterator for MoveSteps<'_> {
    type Item = StepEvent;

    #[inline]
    fn next(&mut self) -> Option<StepEvent> {
        if self.k >= self.m.count {
            return None;
        }
        self.k += 1;
        for i in 0..2 {
            self.acc[i] += self.inc[i];
            if self.acc[i] >= self.two_n {
                self.acc[i] -= self.two_n;
                self.pos[i] += self.sign[i];
            }
        }
        let tick = self.m.tick_of(self.k).max(self.last_tick + 1);
        self.last_tick = tick;
        // Distance from the stepped point to the programmed segment, mm.
        let p = [
            self.pos[0] as f64 * self.mm_per_step[0] - self.origin[0],
            self.pos[1] as f64 * self.mm_per_step[1] - self.origin[1],
        ];
        let u = ((p[0] * self.dir[0] + p[1] * self.dir[1]) * self.inv_len2).clamp(0.0, 1.0);
        let e = [p[0] - u * self.dir[0], p[1] - u * self.dir[1]];
        Some(StepEvent {
            tick,
            pos: self.pos,
            deviation_mm: (e[0] * e[0] + e[1] * e[1]).sqrt(),
        })
    }
}

/// What one plan item does.
// Moves are nearly every item of a plan: boxing them would allocate once a move for nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    Move(Move),
    /// Tool lift on (up) or off (down) for commanded machine Z `z`, then wait `settle` ticks.
    Lift {
        on: bool,
        settle: u64,
        z: f64,
    },
    /// G4: wait this many ticks.
    Dwell(u64),
    /// M0: hold until resumed.
    Pause,
    /// G54..G59 in the program: later moves use this offset.
    UseOffset(WorkOffset),
}

impl Action {
    /// Ticks the item takes on the timeline.
    pub fn ticks(&self) -> u64 {
        match self {
            Action::Move(m) => m.ticks,
            Action::Lift { settle, .. } => *settle,
            Action::Dwell(t) => *t,
            Action::Pause | Action::UseOffset(_) => 0,
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Item {
    /// 1-based source line (0 for jogs).
    pub line: u32,
    /// Planned tick at which the item starts (pauses excluded).
    pub start_tick: u64,
    pub action: Action,
}

/// A plan: items in order, each starting where the one before ended.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Plan {
    /// Source lines of the program (0 for jogs).
    pub lines: u32,
    pub items: Vec<Item>,
    pub total_ticks: u64,
    /// Where the plan leaves the machine: XY steps, Z machine mm, lift.
    pub end_steps: [i64; 2],
    pub end_z: f64,
    pub end_lift: bool,
    pub end_offset: Option<WorkOffset>,
}

/// Where the machine is when a plan starts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Start {
    pub steps: [i64; 2],
    /// Z, machine mm (commanded; Z is a lift).
    pub z: f64,
    pub lift: bool,
    /// Machine origin of G54..G59 (XYZA).
    pub offsets: [[f64; 4]; 6],
    pub active: WorkOffset,
}

/// Moves of one chain (consecutive moves with nothing between them) held back at most, waiting
/// for the moves after them to show how fast they may end. Junction speeds are exact as soon as
/// the moves ahead leave room to slow down (a few moves on any real program); only a chain of
/// more than this many moves too short to do so is planned as if it stopped at the end of the
/// look-ahead, which is slower but always safe.
pub const LOOKAHEAD_MOVES: usize = 4096;

/// A move waiting in the look-ahead, with what the junction planner needs of it.
#[derive(Debug)]
struct Pending {
    item: Item,
    /// Top, no-ramp and acceleration path speeds (mm/s, mm/s²), and length (mm).
    limits: (f64, f64, f64),
    length_mm: f64,
    unit: [f64; 2],
    /// Sum of `2 a L` over the chain's moves up to this one: the square of the speed a move
    /// can slow down from to a stop by the end of the look-ahead is the difference of two.
    room: f64,
    /// The junction to the next move (once it has arrived): its cap, the highest speed the
    /// corner allows, and the backward pass's value, set when it is released.
    cap: f64,
    back: f64,
}

/// Lets consecutive moves flow into each other instead of stopping at every junction (the
/// chords of an arc, a polyline): the speed at a junction is the highest at which no axis's
/// velocity jumps by more than its no-ramp `start_rate`, never above either move's top speed
/// nor below the stop-to-stop speed, then lowered by a backward and a forward pass so that
/// every move can reach its exit speed from its entry speed at its acceleration. Anything
/// between moves (lift, dwell, pause, offset change) is a full stop.
///
/// Items go in as they are planned and come out (in order) once their timing is final, with a
/// look-ahead of at most [`LOOKAHEAD_MOVES`] moves. The backward pass can only raise a
/// junction's value as more moves arrive, never above its cap; a junction whose cap the moves
/// ahead can already slow down from (even if they then stopped) has its final value, and so
/// has every junction before it: those moves are released, their values computed by the same
/// backward and forward passes as over whole chains, so the plan is the same as blending whole
/// chains at once. Which junction that is comes from running sums (`room`), in constant time
/// per move.
#[derive(Debug)]
struct Blender {
    start_mm: [f64; 2],
    window: VecDeque<Pending>,
    /// Number of moves ever released: the window's first move has this index.
    base: u64,
    /// `room` of the window's newest move.
    room: f64,
    /// Junctions (by move index) that could be the newest final one, with the `room` they need
    /// (`room` before them plus their cap squared): increasing in both, since a later junction
    /// that needs no more room makes an earlier one irrelevant.
    candidates: VecDeque<(u64, f64)>,
    /// Moves of the current chain released so far.
    released: usize,
    /// The entry speed of the window's first move, once moves of its chain were released.
    entry: f64,
    ready: VecDeque<Item>,
}

/// Margin on the room a junction needs before it counts as final: the running sums are not
/// the nested square roots of the backward pass bit for bit.
const ROOM_MARGIN: f64 = 1e-9;

impl Blender {
    fn new(machine: &Machine) -> Blender {
        Blender {
            start_mm: [
                machine.axes[0].start_rate / machine.axes[0].steps_per_mm,
                machine.axes[1].start_rate / machine.axes[1].steps_per_mm,
            ],
            window: VecDeque::new(),
            base: 0,
            room: 0.0,
            candidates: VecDeque::new(),
            released: 0,
            entry: 0.0,
            ready: VecDeque::new(),
        }
    }

    /// A blender whose first move continues motion already under way at `entry` (path mm/s):
    /// the plan re-timed for an override after the moves given out so far.
    fn continuing(machine: &Machine, entry: f64) -> Blender {
        Blender {
            released: 1,
            entry,
            ..Blender::new(machine)
        }
    }

    fn push(&mut self, item: Item) {
        let Action::Move(m) = &item.action else {
            self.flush();
            self.ready.push_back(item);
            return;
        };
        let limits = m.path_limits();
        let (length_mm, unit) = (m.length_mm, m.unit);
        let before = self.room;
        self.room += 2.0 * limits.2 * length_mm;
        self.window.push_back(Pending {
            item,
            limits,
            length_mm,
            unit,
            room: self.room,
            cap: 0.0,
            back: 0.0,
        });
        let n = self.window.len();
        if n < 2 {
            return;
        }
        let (a, b) = (&self.window[n - 2], &self.window[n - 1]);
        let mut cap = a.limits.0.min(b.limits.0);
        for (ax, start) in self.start_mm.iter().enumerate() {
            let jump = (a.unit[ax] - b.unit[ax]).abs();
            if jump > 1e-12 {
                cap = cap.min(start / jump);
            }
        }
        let cap = cap.max(a.limits.1.min(b.limits.1));
        self.window[n - 2].cap = cap;
        let needs = before + cap * cap * (1.0 + ROOM_MARGIN);
        while self.candidates.back().is_some_and(|c| c.1 >= needs) {
            self.candidates.pop_back();
        }
        self.candidates.push_back((self.base + n as u64 - 2, needs));
        // The newest junction the moves ahead leave room to slow down from.
        let have = self.room * (1.0 - ROOM_MARGIN);
        let mut last_final = None;
        while let Some(&(j, _)) = self.candidates.front().filter(|c| c.1 <= have) {
            last_final = Some(j);
            self.candidates.pop_front();
        }
        if let Some(j) = last_final {
            let k = usize::try_from(j - self.base).unwrap_or(0);
            // Its value is its cap; the backward pass from it gives the ones before it.
            self.window[k].back = self.window[k].cap;
            for i in (0..k).rev() {
                let after = &self.window[i + 1];
                let reach =
                    (after.back * after.back + 2.0 * after.limits.2 * after.length_mm).sqrt();
                let p = &mut self.window[i];
                p.back = p.cap.min(reach);
            }
            for _ in 0..=k {
                self.release_first();
            }
        }
        if self.window.len() > LOOKAHEAD_MOVES {
            // Out of look-ahead: the first junction gets the value it would have if the moves
            // seen so far then stopped (lower than its final one, so always safe).
            let first = &self.window[0];
            let room = (self.room - first.room).max(0.0) * (1.0 - ROOM_MARGIN);
            let back = first.cap.min(room.sqrt());
            self.window[0].back = back;
            if self.candidates.front().is_some_and(|c| c.0 == self.base) {
                self.candidates.pop_front();
            }
            self.release_first();
        }
    }

    /// Releases the window's first move, which has a move after it: its exit speed is the
    /// forward pass's value at its junction.
    fn release_first(&mut self) {
        let Some(mut p) = self.window.pop_front() else {
            return;
        };
        self.base += 1;
        let v_in = if self.released == 0 {
            p.limits.1
        } else {
            self.entry
        };
        let room = 2.0 * p.limits.2 * p.length_mm;
        let reach = (v_in * v_in + room).sqrt();
        let mut v_out = p.back.min(reach);
        // An entry fixed by motion under way when an override lowered the speeds may be too
        // fast to slow down to this junction's value within the move: it slows down as fast as
        // it may instead. That is never faster than the plan it replaces, which could stop in
        // time from the same speed, so no corner or stop is taken faster than it allows.
        let slowest = v_in * v_in - room;
        if slowest > v_out * v_out * (1.0 + 1e-9) {
            v_out = slowest.sqrt();
        }
        if let Action::Move(m) = &mut p.item.action {
            m.set_junction_speeds(v_in, v_out);
        }
        self.entry = v_out;
        self.released += 1;
        self.ready.push_back(p.item);
    }

    /// The chain ends here: everything waiting is released, the last move ending at its no-ramp
    /// speed (a chain of one move keeps the profile it was made with).
    fn flush(&mut self) {
        // The backward pass from the chain's true end.
        let n = self.window.len();
        if let Some(last) = self.window.back() {
            let mut next = last.limits.1;
            for k in (0..n - 1).rev() {
                let after = &self.window[k + 1];
                let reach = (next * next + 2.0 * after.limits.2 * after.length_mm).sqrt();
                let p = &mut self.window[k];
                p.back = p.cap.min(reach);
                next = p.back;
            }
        }
        while self.window.len() > 1 {
            self.release_first();
        }
        if let Some(mut p) = self.window.pop_front() {
            self.base += 1;
            if self.released > 0 {
                if let Action::Move(m) = &mut p.item.action {
                    m.set_junction_speeds(self.entry, p.limits.1);
                }
            }
            self.ready.push_back(p.item);
        }
        self.released = 0;
        self.room = 0.0;
        self.candidates.clear();
    }
}

/// Builds plans; keeps the running position between items.
pub struct Builder<'a> {
    machine: &'a Machine,
    blender: Blender,
    steps: [i64; 2],
    z: f64,
    lift: bool,
    offset: [f64; 4],
    end_offset: Option<WorkOffset>,
    /// Programmed XY end of the last move, machine mm (unquantised): the next ideal line
    /// starts here.
    ideal_xy: [f64; 2],
    /// The overrides moves are planned for.
    scale: Scale,
    /// Path speed (mm/s) at the end of the last item given out, when it was a move.
    last_exit: Option<f64>,
}

impl<'a> Builder<'a> {
    pub fn new(machine: &'a Machine, start: &Start) -> Builder<'a> {
        Builder {
            machine,
            blender: Blender::new(machine),
            steps: start.steps,
            z: start.z,
            lift: start.lift,
            offset: start.offsets[start.active.index()],
            end_offset: None,
            ideal_xy: [
                start.steps[0] as f64 / machine.axes[0].steps_per_mm,
                start.steps[1] as f64 / machine.axes[1].steps_per_mm,
            ],
            scale: Scale::default(),
            last_exit: None,
        }
    }

    /// Plans the moves that follow an override at `scale`.
    pub fn scaled(mut self, scale: Scale) -> Builder<'a> {
        self.scale = scale;
        self
    }

    /// The next timed item, if one is ready; with `piece_ticks`, a move longer than that is
    /// given out in pieces (each at most that long, at least one step), the rest kept back so
    /// that [`Builder::retime`] can still change it.
    fn take_ready(&mut self, piece_ticks: Option<u64>) -> Option<Item> {
        let mut item = self.blender.ready.pop_front()?;
        if let (Some(max), Action::Move(m)) = (piece_ticks, &mut item.action) {
            if m.ticks > max && m.count > 1 {
                let k = m.steps_within(max).clamp(1, m.count - 1);
                let rest = m.split_off(k);
                self.blender.ready.push_front(Item {
                    line: item.line,
                    start_tick: 0,
                    action: Action::Move(rest),
                });
            }
        }
        self.last_exit = match &item.action {
            Action::Move(m) => Some(m.exit_speed()),
            _ => None,
        };
        Some(item)
    }

    /// Re-plans everything not given out yet for the overrides `scale`: every waiting move
    /// gets its new top speed and the junction speeds are planned again, the first move
    /// continuing from the speed the last one given out ends at (if it is a move of the same
    /// chain). Where that speed is above what the new plan wants, it slows down at the axes'
    /// acceleration. Moves given out already keep their timing.
    pub fn retime(&mut self, scale: Scale) {
        if scale == self.scale {
            return;
        }
        self.scale = scale;
        let old = std::mem::replace(&mut self.blender, Blender::new(self.machine));
        let pending: Vec<Item> = old
            .ready
            .into_iter()
            .chain(old.window.into_iter().map(|p| p.item))
            .collect();
        if let (Some(entry), Some(Action::Move(_))) =
            (self.last_exit, pending.first().map(|i| &i.action))
        {
            self.blender = Blender::continuing(self.machine, entry);
        }
        for mut item in pending {
            if let Action::Move(m) = &mut item.action {
                m.relimit(scale);
            }
            self.blender.push(item);
        }
    }

    fn push(&mut self, line: u32, action: Action) {
        // Timed when it leaves the look-ahead.
        self.blender.push(Item {
            line,
            start_tick: 0,
            action,
        });
    }

    /// The kit's soft-limit check (shared with jogs): also refuses non-finite or huge targets.
    fn check_travel(&self, machine_xy: [f64; 2], z: f64) -> Result<(), String> {
        let [x, y] = self.machine.travel;
        fresa_plugin_api::kit::check_travel(
            &[x, y, None, None],
            [machine_xy[0], machine_xy[1], z, 0.0],
        )
    }

    fn set_lift(&mut self, line: u32, on: bool, z: f64) {
        if on != self.lift {
            self.lift = on;
            self.push(
                line,
                Action::Lift {
                    on,
                    settle: self.machine.lift_settle_ticks,
                    z,
                },
            );
        }
    }

    /// A straight move to machine XY `to` (mm) and machine Z `z`. Lifting happens before the XY
    /// motion, lowering after it (Z is not interpolated).
    pub fn move_to(
        &mut self,
        line: u32,
        to: [f64; 2],
        z: f64,
        feed_mm_min: Option<f64>,
        pace: Pace,
    ) -> Result<(), String> {
        self.check_travel(to, z)?;
        let lift = z - self.offset[2] > self.machine.lift_above_mm;
        if lift {
            self.set_lift(line, true, z);
        }
        let spm = [
            self.machine.axes[0].steps_per_mm,
            self.machine.axes[1].steps_per_mm,
        ];
        let target = [
            (to[0] * spm[0]).round() as i64,
            (to[1] * spm[1]).round() as i64,
        ];
        if target != self.steps {
            let m = Move::paced(
                self.machine,
                self.steps,
                target,
                [self.ideal_xy, to],
                feed_mm_min,
                pace,
                self.scale,
            );
            self.steps = target;
            self.push(line, Action::Move(m));
        }
        self.ideal_xy = to;
        if !lift {
            self.set_lift(line, false, z);
        }
        self.z = z;
        Ok(())
    }

    pub fn dwell(&mut self, line: u32, seconds: f64) {
        let ticks = (seconds.max(0.0) * self.machine.tick_hz).round() as u64;
        if ticks > 0 {
            self.push(line, Action::Dwell(ticks));
        }
    }

    pub fn pause(&mut self, line: u32) {
        self.push(line, Action::Pause);
    }

    pub fn use_offset(&mut self, line: u32, o: WorkOffset, offsets: &[[f64; 4]; 6]) {
        self.offset = offsets[o.index()];
        self.end_offset = Some(o);
        self.push(line, Action::UseOffset(o));
    }

    pub fn position(&self) -> ([i64; 2], f64) {
        (self.steps, self.z)
    }

    /// The whole plan (jogs, go to zero: a few moves).
    pub fn finish(mut self, lines: u32) -> Plan {
        self.blender.flush();
        let mut plan = Plan {
            lines,
            ..Plan::default()
        };
        let mut tick = 0;
        for mut item in self.blender.ready.drain(..) {
            item.start_tick = tick;
            tick += item.action.ticks();
            plan.items.push(item);
        }
        plan.total_ticks = tick;
        plan.end_steps = self.steps;
        plan.end_z = self.z;
        plan.end_lift = self.lift;
        plan.end_offset = self.end_offset;
        plan
    }
}

/// Plans a whole G-code program, validating all of it first. Lines before `start_line` are
/// interpreted for their modal state but not executed: the first executed move starts from
/// where the machine is. Errors name the line (and column for G-code errors).
pub fn plan_program(
    machine: &Machine,
    text: &str,
    start: &Start,
    start_line: u32,
) -> Result<Plan, String> {
    plan_program_with_tools(machine, text, start, start_line, Default::default())
}

/// [`plan_program`] with the machine's tool table (G41/G42 `D`): the items of
/// [`ProgramStream`] collected.
pub fn plan_program_with_tools(
    machine: &Machine,
    text: &str,
    start: &Start,
    start_line: u32,
    tools: fresa_gcode::ToolTable,
) -> Result<Plan, String> {
    let lines = u32::try_from(text.lines().count()).unwrap_or(u32::MAX);
    let mut stream = ProgramStream::new(
        machine,
        text.as_bytes(),
        (lines, start_line),
        start,
        None,
        tools,
        fresa_gcode::DEFAULT_MAX_SEGMENTS,
    );
    let mut plan = Plan {
        lines,
        ..Plan::default()
    };
    for item in stream.by_ref() {
        plan.items.push(item?);
    }
    let end = stream.end();
    plan.total_ticks = end.total_ticks;
    plan.end_steps = end.steps;
    plan.end_z = end.z;
    plan.end_lift = end.lift;
    plan.end_offset = end.offset;
    Ok(plan)
}

/// Where a program leaves the machine, and how long it takes: what [`ProgramStream::end`]
/// knows once the stream has ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanEnd {
    pub total_ticks: u64,
    pub steps: [i64; 2],
    pub z: f64,
    pub lift: bool,
    pub offset: Option<WorkOffset>,
}

/// A program planned as it is read: the items of [`plan_program`], in order, each timed on the
/// plan's timeline, with memory bounded by the look-ahead whatever the program's length (its
/// moves and arc chords within a work budget of `max_segments`). The lines before where the
/// program first runs `start_line` are interpreted for their modal state but not executed
/// (`Interpreter::state_at`; a start there it refuses is the stream's error); a preamble's
/// steps come first, as items of line 0. Ends after the first error (named by line; what was
/// planned before it comes out first, ending at rest).
pub struct ProgramStream<'m, R: BufRead> {
    machine: &'m Machine,
    motions: Linearise<Budgeted<Interpreter<R>>>,
    builder: Builder<'m>,
    lines: u32,
    /// Past the last line (a run with every line done): interpreted, nothing run.
    run_nothing: bool,
    /// The error is the interpreter's refusal of the start line.
    start_refused: bool,
    offsets: [[f64; 4]; 6],
    offsets_now: [f64; 4],
    tick: u64,
    error: Option<String>,
    done: bool,
    /// Longest piece of a move given out at once, ticks (None: whole moves).
    piece_ticks: Option<u64>,
}

impl<'m, R: BufRead> ProgramStream<'m, R> {
    /// `(lines, start_line)`: the program's length and the line it starts from.
    pub fn new(
        machine: &'m Machine,
        reader: R,
        (lines, start_line): (u32, u32),
        start: &Start,
        preamble: Option<&Preamble>,
        tools: fresa_gcode::ToolTable,
        max_segments: u64,
    ) -> ProgramStream<'m, R> {
        let off = start.offsets[start.active.index()];
        let work = [
            start.steps[0] as f64 / machine.axes[0].steps_per_mm - off[0],
            start.steps[1] as f64 / machine.axes[1].steps_per_mm - off[1],
            start.z - off[2],
        ];
        let mut config = fresa_gcode::Config {
            initial_position: work,
            arc_tolerance_mm: ARC_TOLERANCE_MM,
            tools,
            ..Default::default()
        };
        for (i, o) in start.offsets.iter().enumerate() {
            config.work_offsets[i] = [o[0], o[1], o[2]];
        }
        let mut interp = Interpreter::new(reader, config);
        let run_nothing = start_line > lines;
        let state = if start_line > 1 && !run_nothing {
            Some(interp.state_at(start_line))
        } else {
            None
        };
        let budget = WorkBudget::new(max_segments, ARC_TOLERANCE_MM);
        let mut stream = ProgramStream {
            machine,
            motions: linearise(budgeted(interp, budget), ARC_TOLERANCE_MM),
            builder: Builder::new(machine, start),
            lines,
            run_nothing,
            start_refused: false,
            offsets: start.offsets,
            offsets_now: off,
            tick: 0,
            error: None,
            done: false,
            piece_ticks: None,
        };
        let began = match state {
            Some(Ok(state)) => {
                // The work system the lines before left (no action: the preamble selects it).
                if let Some(o) = offset_of(state.work_offset) {
                    stream.offsets_now = stream.offsets[o.index()];
                    stream.builder.offset = stream.offsets_now;
                }
                preamble.map_or(Ok(()), |p| stream.approach(p))
            }
            Some(Err(e)) => {
                stream.start_refused = matches!(e, fresa_gcode::StartError::Refused(_));
                Err(e.to_string())
            }
            None => Ok(()),
        };
        if let Err(e) = began {
            stream.error = Some(e);
            stream.done = true;
            stream.builder.blender.flush();
        }
        stream
    }

    /// Plans a preamble's steps (line 0: nothing is acknowledged for them). The machine has no
    /// spindle or coolant output, so only its offset and moves do something here.
    fn approach(&mut self, p: &Preamble) -> Result<(), String> {
        for (i, step) in p.steps.iter().enumerate() {
            match *step {
                PreambleStep::Offset { offset } => {
                    self.offsets_now = self.offsets[offset.index()];
                    self.builder.use_offset(0, offset, &self.offsets);
                }
                PreambleStep::Move { feed, .. } => {
                    let (steps, z) = self.builder.position();
                    let here = [
                        steps[0] as f64 / self.machine.axes[0].steps_per_mm,
                        steps[1] as f64 / self.machine.axes[1].steps_per_mm,
                        z,
                        0.0,
                    ];
                    let Some(to) = step.target(here) else {
                        continue;
                    };
                    if to[3] != 0.0 {
                        return Err(format!(
                            "preamble step {}: A{}: this machine has no A axis",
                            i + 1,
                            to[3]
                        ));
                    }
                    // The approach's rapids and its feed down follow the overrides as the
                    // program's own moves do.
                    let pace = if feed.is_some() {
                        Pace::Feed
                    } else {
                        Pace::Rapid
                    };
                    let feed = feed.or(Some(self.machine.rapid_mm_min));
                    self.builder
                        .move_to(0, [to[0], to[1]], to[2], feed, pace)
                        .map_err(|e| format!("preamble step {}: {e}", i + 1))?;
                }
                PreambleStep::Spindle { .. } | PreambleStep::Coolant { .. } => {}
            }
        }
        Ok(())
    }

    /// Whether the stream's error is a start the interpreter refuses (see
    /// `Interpreter::state_at`).
    pub fn start_refused(&self) -> bool {
        self.start_refused
    }

    /// Plans for the overrides `scale` (before the first item is taken).
    pub fn scaled(mut self, scale: Scale) -> Self {
        self.builder.scale = scale;
        self
    }

    /// Gives long moves out in pieces of at most `ticks`, so that [`Retimable::retime`] reaches
    /// the rest of a move under way.
    pub fn in_pieces(mut self, ticks: u64) -> Self {
        self.piece_ticks = Some(ticks.max(1));
        self
    }

    /// The plan's length and where it leaves the machine (complete once the stream has ended).
    pub fn end(&self) -> PlanEnd {
        PlanEnd {
            total_ticks: self.tick,
            steps: self.builder.steps,
            z: self.builder.z,
            lift: self.builder.lift,
            offset: self.builder.end_offset,
        }
    }

    /// Plans one motion.
    fn take(&mut self, motion: Motion) -> Result<(), String> {
        let lines = self.lines;
        let line = motion.line().clamp(1, lines.max(1));
        // Two steppers and a Z output: no A axis. Refused whole (wherever the run
        // starts), before anything moves.
        if let Some(a) = motion.rotary() {
            return Err(format!(
                "line {line}: A axis motion (to A{}): this machine has no A axis",
                a.to
            ));
        }
        if matches!(motion, Motion::Probe { .. }) {
            return Err(no_probing_in_programs(line));
        }
        let run = !self.run_nothing;
        let off = self.offsets_now;
        let b = &mut self.builder;
        match motion {
            Motion::Rapid { to, .. } if run => {
                let m = [to[0] + off[0], to[1] + off[1]];
                b.move_to(
                    line,
                    m,
                    to[2] + off[2],
                    Some(self.machine.rapid_mm_min),
                    Pace::Rapid,
                )
                .map_err(|e| format!("line {line}: {e}"))?;
            }
            Motion::Linear {
                to, feed_mm_min, ..
            }
            | Motion::Arc {
                to, feed_mm_min, ..
            } if run => {
                let m = [to[0] + off[0], to[1] + off[1]];
                b.move_to(line, m, to[2] + off[2], Some(feed_mm_min), Pace::Feed)
                    .map_err(|e| format!("line {line}: {e}"))?;
            }
            Motion::Dwell { seconds, .. } if run => b.dwell(line, seconds),
            Motion::Pause {
                optional: false, ..
            } if run => b.pause(line),
            Motion::WorkOffset { system, .. } => {
                if let Some(o) = usize::from(system)
                    .checked_sub(1)
                    .and_then(|i| WorkOffset::ALL.get(i))
                {
                    self.offsets_now = self.offsets[o.index()];
                    if run {
                        b.use_offset(line, *o, &self.offsets);
                    } else {
                        b.offset = self.offsets_now;
                    }
                }
            }
            _ => {}
        }
        Ok(())
    }
}

impl<R: BufRead> Iterator for ProgramStream<'_, R> {
    type Item = Result<Item, String>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(mut item) = self.builder.take_ready(self.piece_ticks) {
                item.start_tick = self.tick;
                self.tick += item.action.ticks();
                return Some(Ok(item));
            }
            if self.done {
                return self.error.take().map(Err);
            }
            let taken = match self.motions.next() {
                None => {
                    self.done = true;
                    Ok(())
                }
                Some(Ok(m)) => self.take(m),
                Some(Err(e)) => Err(e.to_string()),
            };
            if let Err(e) = taken {
                self.error = Some(e);
                self.done = true;
            }
            if self.done {
                self.builder.blender.flush();
            }
        }
    }
}

/// A plan given out item by item that can be re-planned for new overrides as it goes: what the
/// output thread runs through the plan queue.
pub trait Retimable: Iterator<Item = Result<Item, String>> {
    /// Re-plans what has not been given out yet for the overrides `scale`.
    fn retime(&mut self, scale: Scale);
}

impl<R: BufRead> Retimable for ProgramStream<'_, R> {
    fn retime(&mut self, scale: Scale) {
        self.builder.retime(scale);
        if self.done {
            // The program's last chain ended with the file.
            self.builder.blender.flush();
        }
    }
}

/// A few moves built whole (go to zero), given out like a program: re-timed for overrides,
/// in pieces.
pub struct PlanStream<'m> {
    builder: Builder<'m>,
    piece_ticks: u64,
    tick: u64,
}

impl<'m> PlanStream<'m> {
    pub fn new(mut builder: Builder<'m>, piece_ticks: u64) -> PlanStream<'m> {
        builder.blender.flush();
        PlanStream {
            builder,
            piece_ticks: piece_ticks.max(1),
            tick: 0,
        }
    }
}

impl Iterator for PlanStream<'_> {
    type Item = Result<Item, String>;

    fn next(&mut self) -> Option<Self::Item> {
        let mut item = self.builder.take_ready(Some(self.piece_ticks))?;
        item.start_tick = self.tick;
        self.tick += item.action.ticks();
        Some(Ok(item))
    }
}

impl Retimable for PlanStream<'_> {
    fn retime(&mut self, scale: Scale) {
        self.builder.retime(scale);
        self.builder.blender.flush();
    }
}

/// The machine's work offset of work system `system` (1..6 = G54..G59); `None` for
/// G59.1..G59.3, which it does not have.
fn offset_of(system: u8) -> Option<WorkOffset> {
    usize::from(system)
        .checked_sub(1)
        .and_then(|i| WorkOffset::ALL.get(i))
        .copied()
}

/// Why a program that probes is refused whole here, before anything moves.
fn no_probing_in_programs(line: u32) -> String {
    format!(
        "line {line}: G38 probing inside a program is not supported by parport-stepper yet \
         (probe with POST /machines/{{id}}/probe or touch-off)"
    )
}

/// The planner as it was before it streamed (whole chains blended at once), kept as the
/// reference the streaming planner must equal.
#[cfg(test)]
#[allow(dead_code)]
mod reference {
    use super::*;

    /// Builds plans; keeps the running position between items.
    pub struct Builder<'a> {
        machine: &'a Machine,
        plan: Plan,
        steps: [i64; 2],
        z: f64,
        lift: bool,
        offset: [f64; 4],
        tick: u64,
        /// Programmed XY end of the last move, machine mm (unquantised): the next ideal line
        /// starts here.
        ideal_xy: [f64; 2],
    }

    impl<'a> Builder<'a> {
        pub fn new(machine: &'a Machine, start: &Start) -> Builder<'a> {
            Builder {
                machine,
                plan: Plan::default(),
                steps: start.steps,
                z: start.z,
                lift: start.lift,
                offset: start.offsets[start.active.index()],
                tick: 0,
                ideal_xy: [
                    start.steps[0] as f64 / machine.axes[0].steps_per_mm,
                    start.steps[1] as f64 / machine.axes[1].steps_per_mm,
                ],
            }
        }

        fn push(&mut self, line: u32, action: Action) {
            let ticks = action.ticks();
            self.plan.items.push(Item {
                line,
                start_tick: self.tick,
                action,
            });
            self.tick += ticks;
        }

        /// The kit's soft-limit check (shared with jogs): also refuses non-finite or huge targets.
        fn check_travel(&self, machine_xy: [f64; 2], z: f64) -> Result<(), String> {
            let [x, y] = self.machine.travel;
            fresa_plugin_api::kit::check_travel(
                &[x, y, None, None],
                [machine_xy[0], machine_xy[1], z, 0.0],
            )
        }

        fn set_lift(&mut self, line: u32, on: bool, z: f64) {
            if on != self.lift {
                self.lift = on;
                self.push(
                    line,
                    Action::Lift {
                        on,
                        settle: self.machine.lift_settle_ticks,
                        z,
                    },
                );
            }
        }

        /// A straight move to machine XY `to` (mm) and machine Z `z`. Lifting happens before the XY
        /// motion, lowering after it (Z is not interpolated).
        pub fn move_to(
            &mut self,
            line: u32,
            to: [f64; 2],
            z: f64,
            feed_mm_min: Option<f64>,
            pace: Pace,
        ) -> Result<(), String> {
            self.check_travel(to, z)?;
            let lift = z - self.offset[2] > self.machine.lift_above_mm;
            if lift {
                self.set_lift(line, true, z);
            }
            let spm = [
                self.machine.axes[0].steps_per_mm,
                self.machine.axes[1].steps_per_mm,
            ];
            let target = [
                (to[0] * spm[0]).round() as i64,
                (to[1] * spm[1]).round() as i64,
            ];
            if target != self.steps {
                let m = Move::paced(
                    self.machine,
                    self.steps,
                    target,
                    [self.ideal_xy, to],
                    feed_mm_min,
                    pace,
                    Scale::default(),
                );
                self.steps = target;
                self.push(line, Action::Move(m));
            }
            self.ideal_xy = to;
            if !lift {
                self.set_lift(line, false, z);
            }
            self.z = z;
            Ok(())
        }

        pub fn dwell(&mut self, line: u32, seconds: f64) {
            let ticks = (seconds.max(0.0) * self.machine.tick_hz).round() as u64;
            if ticks > 0 {
                self.push(line, Action::Dwell(ticks));
            }
        }

        pub fn pause(&mut self, line: u32) {
            self.push(line, Action::Pause);
        }

        pub fn use_offset(&mut self, line: u32, o: WorkOffset, offsets: &[[f64; 4]; 6]) {
            self.offset = offsets[o.index()];
            self.plan.end_offset = Some(o);
            self.push(line, Action::UseOffset(o));
        }

        pub fn position(&self) -> ([i64; 2], f64) {
            (self.steps, self.z)
        }

        pub fn finish(mut self, lines: u32) -> Plan {
            blend_junctions(self.machine, &mut self.plan.items);
            let mut tick = 0;
            for item in &mut self.plan.items {
                item.start_tick = tick;
                tick += item.action.ticks();
            }
            self.tick = tick;
            self.plan.lines = lines;
            self.plan.total_ticks = self.tick;
            self.plan.end_steps = self.steps;
            self.plan.end_z = self.z;
            self.plan.end_lift = self.lift;
            self.plan
        }
    }

    /// Lets consecutive moves flow into each other instead of stopping at every junction (the
    /// chords of an arc, a polyline): the speed at a junction is the highest at which no axis's
    /// velocity jumps by more than its no-ramp `start_rate`, never above either move's top speed
    /// nor below the stop-to-stop speed, then lowered by a backward and a forward pass so that
    /// every move can reach its exit speed from its entry speed at its acceleration. Anything
    /// between moves (lift, dwell, pause, offset change) is a full stop.
    fn blend_junctions(machine: &Machine, items: &mut [Item]) {
        let mut i = 0;
        while i < items.len() {
            let run = items[i..]
                .iter()
                .take_while(|it| matches!(it.action, Action::Move(_)))
                .count();
            if run >= 2 {
                let moves: Vec<&mut Move> = items[i..i + run]
                    .iter_mut()
                    .filter_map(|it| match &mut it.action {
                        Action::Move(m) => Some(m),
                        _ => None,
                    })
                    .collect();
                blend_chain(machine, moves);
            }
            i += run.max(1);
        }
    }

    fn blend_chain(machine: &Machine, mut moves: Vec<&mut Move>) {
        let n = moves.len();
        let limits: Vec<(f64, f64, f64)> = moves.iter().map(|m| m.path_limits()).collect();
        let start_mm = [
            machine.axes[0].start_rate / machine.axes[0].steps_per_mm,
            machine.axes[1].start_rate / machine.axes[1].steps_per_mm,
        ];
        let mut junction: Vec<f64> = (0..n - 1)
            .map(|k| {
                let (a, b) = (&moves[k], &moves[k + 1]);
                let mut v = limits[k].0.min(limits[k + 1].0);
                for (ax, start) in start_mm.iter().enumerate() {
                    let jump = (a.unit[ax] - b.unit[ax]).abs();
                    if jump > 1e-12 {
                        v = v.min(start / jump);
                    }
                }
                v.max(limits[k].1.min(limits[k + 1].1))
            })
            .collect();
        // Backward: each move must be able to slow down to its exit speed.
        let mut next = limits[n - 1].1;
        for k in (0..n - 1).rev() {
            let reach = (next * next + 2.0 * limits[k + 1].2 * moves[k + 1].length_mm).sqrt();
            junction[k] = junction[k].min(reach);
            next = junction[k];
        }
        // Forward: each move must be able to speed up to its exit speed.
        let mut prev = limits[0].1;
        for k in 0..n - 1 {
            let reach = (prev * prev + 2.0 * limits[k].2 * moves[k].length_mm).sqrt();
            junction[k] = junction[k].min(reach);
            prev = junction[k];
        }
        for (k, m) in moves.iter_mut().enumerate() {
            let v_in = if k == 0 { limits[0].1 } else { junction[k - 1] };
            let v_out = if k == n - 1 { limits[k].1 } else { junction[k] };
            m.set_junction_speeds(v_in, v_out);
        }
    }

    /// Plans a whole G-code program, validating all of it first. Lines before `start_line` are
    /// interpreted for their modal state but not executed: the first executed move starts from
    /// where the machine is. Errors name the line (and column for G-code errors).
    pub fn _plan_program(
        machine: &Machine,
        text: &str,
        start: &Start,
        start_line: u32,
    ) -> Result<Plan, String> {
        plan_program_with_tools(machine, text, start, start_line, Default::default())
    }

    /// [`plan_program`] with the machine's tool table (G41/G42 `D`).
    pub fn plan_program_with_tools(
        machine: &Machine,
        text: &str,
        start: &Start,
        start_line: u32,
        tools: fresa_gcode::ToolTable,
    ) -> Result<Plan, String> {
        let lines = u32::try_from(text.lines().count()).unwrap_or(u32::MAX);
        let off = start.offsets[start.active.index()];
        let work = [
            start.steps[0] as f64 / machine.axes[0].steps_per_mm - off[0],
            start.steps[1] as f64 / machine.axes[1].steps_per_mm - off[1],
            start.z - off[2],
        ];
        let mut config = fresa_gcode::Config {
            initial_position: work,
            arc_tolerance_mm: ARC_TOLERANCE_MM,
            tools,
            ..Default::default()
        };
        for (i, o) in start.offsets.iter().enumerate() {
            config.work_offsets[i] = [o[0], o[1], o[2]];
        }
        let interp = Interpreter::new(text.as_bytes(), config);
        let mut b = Builder::new(machine, start);
        let mut offsets_now = off;
        for motion in linearise(interp, ARC_TOLERANCE_MM) {
            let motion = motion.map_err(|e| e.to_string())?;
            let line = motion.line().clamp(1, lines.max(1));
            // Two steppers and a Z output: no A axis. Refused whole (wherever the run
            // starts), before anything moves.
            if let Some(a) = motion.rotary() {
                return Err(format!(
                    "line {line}: A axis motion (to A{}): this machine has no A axis",
                    a.to
                ));
            }
            if matches!(motion, Motion::Probe { .. }) {
                return Err(no_probing_in_programs(line));
            }
            let run = line >= start_line;
            match motion {
                Motion::Rapid { to, .. } if run => {
                    let m = [to[0] + offsets_now[0], to[1] + offsets_now[1]];
                    b.move_to(
                        line,
                        m,
                        to[2] + offsets_now[2],
                        Some(machine.rapid_mm_min),
                        Pace::Rapid,
                    )
                    .map_err(|e| format!("line {line}: {e}"))?;
                }
                Motion::Linear {
                    to, feed_mm_min, ..
                }
                | Motion::Arc {
                    to, feed_mm_min, ..
                } if run => {
                    let m = [to[0] + offsets_now[0], to[1] + offsets_now[1]];
                    b.move_to(
                        line,
                        m,
                        to[2] + offsets_now[2],
                        Some(feed_mm_min),
                        Pace::Feed,
                    )
                    .map_err(|e| format!("line {line}: {e}"))?;
                }
                Motion::Dwell { seconds, .. } if run => b.dwell(line, seconds),
                Motion::Pause {
                    optional: false, ..
                } if run => b.pause(line),
                Motion::WorkOffset { system, .. } => {
                    if let Some(o) = usize::from(system)
                        .checked_sub(1)
                        .and_then(|i| WorkOffset::ALL.get(i))
                    {
                        offsets_now = start.offsets[o.index()];
                        if run {
                            b.use_offset(line, *o, &start.offsets);
                        } else {
                            b.offset = offsets_now;
                        }
                    }
                }
                _ => {}
            }
        }
        Ok(b.finish(lines))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use proptest::prelude::*;

    pub fn machine() -> Machine {
        let ax = AxisLimits {
            steps_per_mm: 140.0,
            max_rate: 500.0,
            start_rate: 100.0,
            accel: 2000.0,
        };
        Machine {
            axes: [ax, ax],
            tick_hz: 20_000.0,
            rapid_mm_min: 6000.0,
            lift_above_mm: 0.0,
            lift_settle_ticks: 100,
            travel: [None, None],
        }
    }

    fn start() -> Start {
        Start {
            steps: [0, 0],
            z: 0.0,
            lift: false,
            offsets: [[0.0; 4]; 6],
            active: WorkOffset::G54,
        }
    }

    /// Checks the DDA line property of a move: every step moves each axis by at most one
    /// step, the minor axis is within half a step of the ideal line at every major step, and
    /// the move ends on the exact target.
    fn check_line(from: [i64; 2], to: [i64; 2]) {
        let m = machine();
        let mv = Move::new(&m, from, to, [[0.0; 2], [0.0; 2]], None);
        let d = [to[0] - from[0], to[1] - from[1]];
        let n = d[0].abs().max(d[1].abs());
        let major = if d[0].abs() >= d[1].abs() { 0 } else { 1 };
        let mut prev = from;
        let mut prev_tick = 0;
        let mut count = 0;
        for s in mv.steps() {
            count += 1;
            assert!(s.tick > prev_tick, "ticks strictly increase");
            prev_tick = s.tick;
            for (now, before) in s.pos.iter().zip(prev) {
                assert!((now - before).abs() <= 1, "one step per axis per slot");
            }
            let k = (s.pos[major] - from[major]).abs() as f64;
            for i in 0..2 {
                let ideal = from[i] as f64 + d[i] as f64 * k / n as f64;
                assert!(
                    (s.pos[i] as f64 - ideal).abs() <= 0.5 + 1e-9,
                    "{from:?}->{to:?}: axis {i} at {:?} vs ideal {ideal}",
                    s.pos
                );
            }
            prev = s.pos;
        }
        assert_eq!(count, n);
        assert_eq!(prev, to);
        assert_eq!(mv.ticks, prev_tick, "closed-form length = last step");
    }

    #[test]
    fn the_seeds_diagonal_is_a_straight_line() {
        // 6 cm x 3 cm at 7 turns/cm x 200 steps: 8400 x 4200 steps, no dog-leg.
        check_line([0, 0], [8400, 4200]);
        check_line([10, -5], [-3, 40]);
        check_line([0, 0], [0, 7]);
        check_line([0, 0], [0, 0]);
    }

    #[test]
    fn profile_is_a_trapezoid_within_the_limits() {
        let m = machine();
        let mv = Move::new(&m, [0, 0], [8400, 4200], [[0.0; 2], [60.0, 30.0]], None);
        // X is major at 500 steps/s; Y does half of that.
        assert!((mv.profile.peak_rate() - 500.0).abs() < 1e-9);
        let steps: Vec<_> = mv.steps().collect();
        let min_gap = steps
            .windows(2)
            .map(|w| w[1].tick - w[0].tick)
            .min()
            .unwrap();
        // 500 steps/s at 20 kHz = 40 ticks.
        assert!(min_gap >= 39, "gap {min_gap}");
        let first_gap = steps[1].tick - steps[0].tick;
        assert!(first_gap > 100, "starts slow: {first_gap}");
        // Cruise time 8400/500 = 16.8 s, plus the ramps.
        let secs = mv.ticks as f64 / 20_000.0;
        assert!(secs > 16.8 && secs < 17.2, "{secs}");
    }

    #[test]
    fn arcs_follow_the_circle() {
        let m = machine();
        let prog = "G21 G90\nG0 X10 Y0\nG2 X0 Y-10 I-10 J0 F300\n";
        let plan = plan_program(&m, prog, &start(), 1).unwrap();
        let mut worst: f64 = 0.0;
        let mut end = [0, 0];
        for item in &plan.items {
            if let Action::Move(mv) = &item.action {
                for s in mv.steps() {
                    if item.line == 3 {
                        let p = [s.pos[0] as f64 / 140.0, s.pos[1] as f64 / 140.0];
                        let r = (p[0] * p[0] + p[1] * p[1]).sqrt();
                        worst = worst.max((r - 10.0).abs());
                        assert!(s.deviation_mm <= 1.0 / 140.0 + 1e-9);
                    }
                    end = s.pos;
                }
            }
        }
        // Within one step (plus the chord tolerance) of the circle.
        assert!(worst <= 1.0 / 140.0 + ARC_TOLERANCE_MM, "{worst}");
        assert_eq!(end, [0, -1400]);
        assert_eq!(plan.end_steps, [0, -1400]);
    }

    /// Step ticks of each axis over a whole plan (timeline ticks).
    fn axis_step_ticks(plan: &Plan) -> [Vec<u64>; 2] {
        let mut out = [Vec::new(), Vec::new()];
        for item in &plan.items {
            if let Action::Move(mv) = &item.action {
                let mut prev = mv.from;
                for s in mv.steps() {
                    for (i, ticks) in out.iter_mut().enumerate() {
                        if s.pos[i] != prev[i] {
                            ticks.push(item.start_tick + s.tick);
                        }
                    }
                    prev = s.pos;
                }
            }
        }
        out
    }

    #[test]
    fn arc_chords_flow_into_each_other_and_corners_slow_down() {
        let m = machine();
        // A full circle of r = 10 mm at F600 (10 mm/s = 1400 steps/s, capped at 500).
        let arc = plan_program(&m, "G0 X10\nG2 X10 Y0 I-10 J0 F600\n", &start(), 1).unwrap();
        let chords = arc.items.iter().filter(|i| i.line == 2).count();
        assert!(chords > 50, "{chords} chords");
        // Versus stopping at every chord (each move on its own, start_rate in and out).
        let (mut blended, mut stop_to_stop) = (0.0, 0.0);
        for item in arc.items.iter().filter(|i| i.line == 2) {
            if let Action::Move(mv) = &item.action {
                blended += mv.profile.seconds();
                stop_to_stop +=
                    Profile::new(mv.profile.n, mv.v_max, mv.v_start, mv.v_start, mv.accel)
                        .seconds();
            }
        }
        // Circumference 62.8 mm with the faster axis capped at 500 steps/s: 3.6..5 mm/s.
        assert!(blended < 17.5, "circle took {blended} s");
        assert!(
            blended < 0.6 * stop_to_stop,
            "blended {blended} s vs stop-to-stop {stop_to_stop} s"
        );
        // Never faster than max_rate on either axis (500 steps/s = 40 ticks; rounding: 39).
        for ticks in axis_step_ticks(&arc) {
            for w in ticks.windows(2) {
                assert!(w[1] - w[0] >= 39, "step gap {} ticks", w[1] - w[0]);
            }
        }
        // A right-angle corner: the junction speed is the no-ramp speed, not the cruise.
        let corner = plan_program(&m, "G1 X20 F6000\nG1 Y20\n", &start(), 1).unwrap();
        let speeds: Vec<_> = corner
            .items
            .iter()
            .filter_map(|i| match &i.action {
                Action::Move(mv) => Some((mv.profile.entry_rate(), mv.profile.exit_rate())),
                _ => None,
            })
            .collect();
        assert_eq!(speeds, [(100.0, 100.0), (100.0, 100.0)]);
        // Collinear segments join at full speed.
        let line = plan_program(&m, "G1 X20 F6000\nG1 X40\n", &start(), 1).unwrap();
        match &line.items[0].action {
            Action::Move(mv) => assert_eq!(mv.profile.exit_rate(), 500.0),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn lift_goes_up_before_and_down_after_xy() {
        let m = machine();
        let plan = plan_program(&m, "G0 Z5\nG0 X1\nG1 X2 Z-1 F100\n", &start(), 1).unwrap();
        let kinds: Vec<_> = plan
            .items
            .iter()
            .map(|i| match &i.action {
                Action::Lift { on, .. } => format!("{}:lift{on}", i.line),
                Action::Move(_) => format!("{}:move", i.line),
                other => format!("{other:?}"),
            })
            .collect();
        assert_eq!(
            kinds,
            ["1:lifttrue", "2:move", "3:move", "3:liftfalse"],
            "{kinds:?}"
        );
    }

    #[test]
    fn travel_and_gcode_errors_name_the_line() {
        let mut m = machine();
        m.travel = [Some((0.0, 50.0)), None];
        let e = plan_program(&m, "G0 X10\nG0 X60\n", &start(), 1).unwrap_err();
        assert!(e.starts_with("line 2: X=60.0000"), "{e}");
        let e = plan_program(&m, "G0 X10\nG1 X20\n", &start(), 1).unwrap_err();
        assert!(e.contains("line 2"), "{e}");
    }

    #[test]
    fn start_line_skips_motion_but_keeps_modes() {
        let m = machine();
        let plan = plan_program(&m, "G91\nG0 X1\nG0 X1\n", &start(), 3).unwrap();
        // Lines 1-2 are interpreted (G91, X at 1) but not run; line 3 goes straight from
        // where the machine is to the program's X2.
        assert_eq!(plan.items.len(), 1);
        assert_eq!(plan.items[0].line, 3);
        assert_eq!(plan.end_steps, [280, 0]);
    }

    /// A preamble comes first as items of line 0: the lift goes up before the XY move to the
    /// start point and down after it (Z is not interpolated), then the program from its start
    /// line; a step outside the travel, or one that turns an A axis, is the stream's error.
    #[test]
    fn a_preamble_is_planned_before_the_start_line() {
        let mut m = machine();
        m.travel = [Some((-100.0, 100.0)), None];
        let text = "G21 G90\nG0 Z5\nG0 X10 Y5\nG1 Z-1 F300\nG1 X20\n";
        let pre: Preamble = serde_json::from_value(serde_json::json!({
            "line": 5, "from": {},
            "steps": [{"step": "move", "z": 5}, {"step": "offset", "offset": "G54"},
                      {"step": "spindle", "direction": "cw", "rpm": 1000},
                      {"step": "move", "x": 10, "y": 5}, {"step": "move", "z": -1, "feed": 300}]
        }))
        .unwrap();
        let lines = text.lines().count() as u32;
        let stream = ProgramStream::new(
            &m,
            text.as_bytes(),
            (lines, 5),
            &start(),
            Some(&pre),
            Default::default(),
            u64::MAX,
        );
        let items: Vec<Item> = stream.map(Result::unwrap).collect();
        let kinds: Vec<(u32, &str)> = items
            .iter()
            .map(|i| {
                let k = match &i.action {
                    Action::Move(_) => "move",
                    Action::Lift { on: true, .. } => "up",
                    Action::Lift { on: false, .. } => "down",
                    Action::UseOffset(_) => "offset",
                    _ => "other",
                };
                (i.line, k)
            })
            .collect();
        assert_eq!(
            kinds,
            vec![
                (0, "up"),
                (0, "offset"),
                (0, "move"),
                (0, "down"),
                (5, "move")
            ]
        );
        let far: Preamble = serde_json::from_value(serde_json::json!({
            "line": 5, "from": {}, "steps": [{"step": "move", "x": 1000}]
        }))
        .unwrap();
        let turn: Preamble = serde_json::from_value(serde_json::json!({
            "line": 5, "from": {}, "steps": [{"step": "move", "a": 90}]
        }))
        .unwrap();
        for (p, says) in [(far, "outside the travel"), (turn, "no A axis")] {
            let mut stream = ProgramStream::new(
                &m,
                text.as_bytes(),
                (lines, 5),
                &start(),
                Some(&p),
                Default::default(),
                u64::MAX,
            );
            let e = stream.find_map(Result::err).unwrap();
            assert!(
                e.starts_with("preamble step 1: ") && e.contains(says),
                "{e}"
            );
        }
    }

    /// The host's run-time estimate (fresa-gcode's trapezoids with look-ahead, given this
    /// machine's `motion_profile`) against this planner's own timeline, on X/Y programs (the Z
    /// lift is not in the profile): a long line, a polyline with corners, a zig-zag of short
    /// strokes and arcs. Prints both; within 2 % each (before per-axis limits: +8 to +12 %).
    #[test]
    fn the_hosts_estimate_follows_this_planner() {
        let m = machine();
        let mut zigzag = String::from("G21 G90 F1200\n");
        for i in 0..200 {
            zigzag.push_str(&format!(
                "G1 X{} Y{}\n",
                if i % 2 == 0 { 20 } else { 0 },
                i as f64 * 0.2
            ));
        }
        let programs = [
            ("line", "G21 G90\nG1 X100 Y40 F3000\n".to_string()),
            (
                "square",
                "G21 G90 F2000\nG1 X30\nG1 Y30\nG1 X0\nG1 Y0\nG0 X50 Y50\n".to_string(),
            ),
            ("zigzag", zigzag),
            (
                "arcs",
                "G21 G90\nG0 X10 Y0\nG3 X-10 Y0 I-10 J0 F1500\nG3 X10 Y0 I10 J0\nG2 X30 Y0 I10 J0\n"
                    .to_string(),
            ),
        ];
        let p = motion_profile(&m);
        let profile = fresa_gcode::MotionProfile {
            rapid_mm_min: p.rapid_mm_min,
            min_feed_mm_min: p.min_feed_mm_min,
            max_feed_mm_min: p.max_feed_mm_min,
            accel_mm_s2: p.accel_mm_s2,
            corner_jump_mm_s: p.corner_jump_mm_s,
            per_axis: p.per_axis,
        };
        let opts = fresa_gcode::AnalysisOptions {
            profile: Some(profile),
            ..Default::default()
        };
        for (name, text) in programs {
            let planned =
                plan_program(&m, &text, &start(), 1).unwrap().total_ticks as f64 / m.tick_hz;
            let estimated = fresa_gcode::analyse(text.as_bytes(), &opts)
                .unwrap()
                .estimated_seconds;
            let err = (estimated - planned) / planned;
            eprintln!(
                "{name}: planner {planned:.3} s, estimate {estimated:.3} s ({:+.1} %)",
                err * 100.0
            );
            assert!(
                err.abs() < 0.02,
                "{name}: planner {planned} s, estimate {estimated} s"
            );
        }
    }

    /// The streaming planner against the whole-chain planner of before, item by item (bit for
    /// bit: the same floats come out of the same formulas).
    fn same_as_before(m: &Machine, text: &str, start: &Start, start_line: u32) {
        let new = plan_program(m, text, start, start_line);
        let old =
            reference::plan_program_with_tools(m, text, start, start_line, Default::default());
        if let (Ok(a), Ok(b)) = (&new, &old) {
            let first = a.items.iter().zip(&b.items).position(|(x, y)| x != y);
            assert!(
                first.is_none() && a.items.len() == b.items.len(),
                "{text:.60}: {} vs {} items, first difference at {first:?}: {:?} vs {:?}",
                a.items.len(),
                b.items.len(),
                first.map(|i| &a.items[i]),
                first.map(|i| &b.items[i])
            );
        }
        assert_eq!(new, old, "{text:.200}");
    }

    /// The programs of this crate's tests (these and tests/sim_port.rs) and the shared corpus.
    fn test_programs() -> Vec<String> {
        let mut v: Vec<String> = [
            "G21 G90\nG0 X10 Y0\nG2 X0 Y-10 I-10 J0 F300\n",
            "G0 X10\nG2 X10 Y0 I-10 J0 F600\n",
            "G1 X20 F6000\nG1 Y20\n",
            "G1 X20 F6000\nG1 X40\n",
            "G0 Z5\nG0 X1\nG1 X2 Z-1 F100\n",
            "G0 X10\nG1 X20\n",
            "G91\nG0 X1\nG0 X1\n",
            "G21 G90\nG1 X60 Y30 F600\nG1 X-7.5 Y12.25\n",
            "G21 G90\nG0 X10 Y0\nG3 X-10 Y0 I-10 J0 F600\n",
            "G1 X50 Y5 F600\n",
            "G1 X100 Y20 F60000\n",
            "G0 X1\nG4 P0.5\nG1 X2 F100\nM0\nG1 X3\nG55\nG1 X4\nG0 Z3\nG1 X5\nG1 Z-1\n",
        ]
        .map(String::from)
        .to_vec();
        v.push(
            (0..2000)
                .map(|i| format!("G1 X{} F60000\n(comment)\n", (i % 2) as f64 * 0.5))
                .collect(),
        );
        let corpus =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/corpus/gcode");
        for e in std::fs::read_dir(&corpus).unwrap() {
            v.push(std::fs::read_to_string(e.unwrap().path()).unwrap());
        }
        v
    }

    #[test]
    fn the_streaming_planner_plans_what_the_whole_chain_planner_did() {
        let m = machine();
        let mut offsets = [[0.0; 4]; 6];
        offsets[1] = [5.0, -3.0, 0.0, 0.0];
        let shifted = Start {
            steps: [140, -70],
            offsets,
            ..start()
        };
        let mut fast = machine();
        for ax in &mut fast.axes {
            ax.max_rate = 10_000.0;
            ax.start_rate = 50.0;
            ax.accel = 500.0;
        }
        fast.lift_above_mm = 0.5;
        for text in test_programs() {
            for start_line in [1, 3] {
                same_as_before(&m, &text, &start(), start_line);
                same_as_before(&fast, &text, &shifted, start_line);
            }
        }
    }

    #[test]
    fn the_look_ahead_is_bounded_and_what_it_cuts_short_stays_safe() {
        // A fast machine with slow acceleration on a straight line of short moves: braking
        // from full speed takes metres, far more than the look-ahead's 4096 moves of 0.03 mm.
        let mut m = machine();
        for ax in &mut m.axes {
            ax.max_rate = 10_000.0;
            ax.start_rate = 100.0;
            ax.accel = 50.0;
        }
        let prog: String = (1..=3 * LOOKAHEAD_MOVES)
            .map(|i| format!("G1 X{} F100000\n", i as f64 * 0.03))
            .collect();
        let lines = prog.lines().count() as u32;
        let mut stream = ProgramStream::new(
            &m,
            prog.as_bytes(),
            (lines, 1),
            &start(),
            None,
            Default::default(),
            u64::MAX,
        );
        let mut items = Vec::new();
        while let Some(item) = stream.next() {
            assert!(stream.builder.blender.window.len() <= LOOKAHEAD_MOVES);
            items.push(item.unwrap());
        }
        assert_eq!(items.len(), 3 * LOOKAHEAD_MOVES);
        // Every junction is entered at the speed the move before it left with, and each move
        // can go from its entry to its exit speed within its length.
        let mut exit: Option<f64> = None;
        for item in &items {
            let Action::Move(mv) = &item.action else {
                panic!("{item:?}")
            };
            let p = mv.profile;
            if let Some(e) = exit {
                let k = mv.steps_per_path_mm();
                let entry = p.entry_rate() / k;
                assert!((entry - e).abs() <= 1e-6 * e.max(1.0), "{entry} vs {e}");
            }
            let reach = (p.entry_rate().powi(2) + 2.0 * mv.accel * p.n as f64).sqrt();
            assert!(p.exit_rate() <= reach + 1e-9);
            exit = Some(p.exit_rate() / mv.steps_per_path_mm());
        }
        // The whole-chain planner went faster; the bounded one, planning a stop at the end of
        // what it can see, is slower (never faster).
        let whole =
            reference::plan_program_with_tools(&m, &prog, &start(), 1, Default::default()).unwrap();
        let (ours, theirs): (u64, u64) = (
            items.iter().map(|i| i.action.ticks()).sum(),
            whole.total_ticks,
        );
        assert!(ours > theirs, "{ours} <= {theirs}");
    }

    /// A program streamed in pieces of `piece` ticks; after `cut` items the overrides become
    /// `scale` (None: never). Every item, in order.
    fn streamed(
        m: &Machine,
        text: &str,
        piece: u64,
        cut: usize,
        scale: Option<Scale>,
    ) -> Vec<Item> {
        let lines = text.lines().count() as u32;
        let mut s = ProgramStream::new(
            m,
            text.as_bytes(),
            (lines, 1),
            &start(),
            None,
            Default::default(),
            u64::MAX,
        )
        .in_pieces(piece);
        let mut items = Vec::new();
        while let Some(item) = s.next() {
            items.push(item.unwrap());
            if items.len() == cut {
                if let Some(scale) = scale {
                    s.retime(scale);
                }
            }
        }
        items
    }

    /// Every step of a plan: (absolute tick, position).
    fn all_steps(items: &[Item]) -> Vec<(u64, [i64; 2])> {
        let mut out = Vec::new();
        for item in items {
            if let Action::Move(mv) = &item.action {
                out.extend(mv.steps().map(|s| (item.start_tick + s.tick, s.pos)));
            }
        }
        out
    }

    /// The limits a plan must keep whatever the overrides did: the rate never jumps (each move
    /// or piece enters at the speed the one before it left), never changes faster than the
    /// acceleration (checked on the profile, step by step), never goes above the axes' top
    /// rate, starts and stops at the no-ramp rate, and takes no corner faster than a plan
    /// with no override would allow.
    fn check_limits(m: &Machine, items: &[Item]) {
        let start_mm = [
            m.axes[0].start_rate / m.axes[0].steps_per_mm,
            m.axes[1].start_rate / m.axes[1].steps_per_mm,
        ];
        let mut prev: Option<&Move> = None;
        for item in items {
            let Action::Move(mv) = &item.action else {
                if let Some(p) = prev.take() {
                    let exit = p.exit_speed() * p.per_mm;
                    assert!(
                        exit <= p.ramp_free * (1.0 + 1e-6),
                        "stops from {exit} > {}",
                        p.ramp_free
                    );
                }
                continue;
            };
            let p = mv.profile;
            let entry = p.rate_at(0.0) / mv.per_mm;
            match prev {
                None => assert!(
                    p.rate_at(0.0) <= mv.ramp_free * (1.0 + 1e-6),
                    "starts at {} > {}",
                    p.rate_at(0.0),
                    mv.ramp_free
                ),
                Some(q) => {
                    let exit = q.exit_speed();
                    assert!(
                        (entry - exit).abs() <= 1e-6 * exit.max(1.0),
                        "line {}: enters at {entry} mm/s, the move before left at {exit}",
                        item.line
                    );
                    if q.unit != mv.unit {
                        // A corner: no faster than its no-ramp speed or the stop-to-stop one.
                        let mut cap = f64::INFINITY;
                        for (ax, s) in start_mm.iter().enumerate() {
                            let jump = (q.unit[ax] - mv.unit[ax]).abs();
                            if jump > 1e-12 {
                                cap = cap.min(s / jump);
                            }
                        }
                        let floor = (q.ramp_free / q.per_mm).min(mv.ramp_free / mv.per_mm);
                        assert!(
                            entry <= cap.max(floor) * (1.0 + 1e-6),
                            "line {}: corner at {entry} mm/s, allowed {cap} / {floor}",
                            item.line
                        );
                    }
                }
            }
            // Step by step: v² changes by at most 2a a step, never above the axes' top rate.
            let mut v0 = p.rate_at(0.0);
            assert!(
                v0 <= mv.axes_max * (1.0 + 1e-6),
                "enters at {v0} > {}",
                mv.axes_max
            );
            for k in 1..=mv.count {
                let v = p.rate_at(k as f64);
                assert!(
                    v <= mv.axes_max * (1.0 + 1e-6),
                    "{v} steps/s > {}",
                    mv.axes_max
                );
                assert!(
                    (v * v - v0 * v0).abs() <= 2.0 * mv.accel * (1.0 + 1e-6) + 1e-6,
                    "line {} step {k}: {v0} -> {v} steps/s at {} steps/s²",
                    item.line,
                    mv.accel
                );
                v0 = v;
            }
            // The timing follows the profile.
            assert!((p.time_at(p.n as f64) - p.seconds()).abs() < 1e-9);
            prev = Some(mv);
        }
        if let Some(p) = prev {
            assert!(p.exit_speed() * p.per_mm <= p.ramp_free * (1.0 + 1e-6));
        }
    }

    #[test]
    fn moves_given_out_in_pieces_step_as_whole_moves() {
        let m = machine();
        for text in test_programs().iter().take(13) {
            // (Some are refused whole: those are the error tests'.)
            let Ok(whole) = plan_program(&m, text, &start(), 1) else {
                continue;
            };
            let pieces = streamed(&m, text, 200, 0, None);
            let (a, b) = (all_steps(&whole.items), all_steps(&pieces));
            assert_eq!(
                a.iter().map(|s| s.1).collect::<Vec<_>>(),
                b.iter().map(|s| s.1).collect::<Vec<_>>(),
                "{text:.60}"
            );
            // Each piece starts its profile where the one before ended in exact time, so the
            // steps are where the whole move put them, within rounding (no drift).
            let cuts = pieces.len() - whole.items.len();
            let worst = a.iter().zip(&b).map(|(x, y)| x.0.abs_diff(y.0)).max();
            assert!(
                worst <= Some(1),
                "{text:.60}: {worst:?} ticks off after {cuts} cuts"
            );
            for item in &pieces {
                if let Action::Move(mv) = &item.action {
                    assert!(
                        mv.ticks <= 200 || mv.count == 1,
                        "a piece of {} ticks",
                        mv.ticks
                    );
                }
            }
            check_limits(&m, &pieces);
        }
    }

    #[test]
    fn an_override_re_times_the_move_under_way_from_the_next_piece() {
        let m = machine();
        // 100 mm at 2 mm/s = 280 steps/s (the axes allow 500), given out in 10 ms pieces.
        let text = "G1 X100 F120\n";
        for (scale, want) in [(0.5, 140.0), (1.5, 420.0), (2.0, 500.0), (0.1, 28.0)] {
            let items = streamed(
                &m,
                text,
                200,
                30,
                Some(Scale {
                    feed: scale,
                    rapid: 1.0,
                }),
            );
            check_limits(&m, &items);
            let moves: Vec<&Move> = items
                .iter()
                .filter_map(|i| match &i.action {
                    Action::Move(mv) => Some(mv),
                    _ => None,
                })
                .collect();
            // Before: the programmed feed. From the next piece on: the overridden one, reached
            // at the axes' acceleration (2000 steps/s²) from 280 steps/s.
            assert!((moves[29].profile.peak_rate() - 280.0).abs() < 1e-6);
            assert!((moves[30].profile.rate_at(0.0) - 280.0).abs() < 1e-6);
            assert!((moves[30].v_max - want).abs() < 1e-6, "{}", moves[30].v_max);
            // It gets there in the time the acceleration needs and stays until the final
            // stop, never outside the two speeds meanwhile.
            let ramp = (want - 280.0_f64).abs() / 2000.0 * 20_000.0;
            let stop = (want - 100.0) / 2000.0 * 20_000.0;
            let cut_at = items[30].start_tick as f64;
            let end = all_steps(&items).last().unwrap().0 as f64;
            for (item, mv) in items.iter().zip(&moves).skip(30) {
                let t = item.start_tick as f64;
                let v = mv.profile.rate_at(mv.count as f64 / 2.0);
                if t > cut_at + ramp + 220.0 && t + mv.ticks as f64 + stop + 220.0 < end {
                    assert!(
                        (v - want).abs() < 1e-6,
                        "scale {scale}: {v} steps/s, want {want}"
                    );
                } else {
                    assert!(
                        v <= want.max(280.0) + 1e-6 && v >= want.min(100.0) - 1e-6,
                        "{v}"
                    );
                }
            }
            assert_eq!(all_steps(&items).last().unwrap().1, [14_000, 0]);
        }
        // G0 follows the rapid override (of the rate the axes allow: 500 steps/s), not the feed.
        let items = streamed(
            &m,
            "G0 X100\n",
            200,
            5,
            Some(Scale {
                feed: 2.0,
                rapid: 0.25,
            }),
        );
        check_limits(&m, &items);
        let Action::Move(mv) = &items[items.len() / 2].action else {
            panic!()
        };
        assert!(
            (mv.profile.rate_at(1.0) - 125.0).abs() < 1e-6,
            "{:?}",
            mv.profile
        );
    }

    #[test]
    fn a_cut_slowed_down_mid_chain_decelerates_across_the_short_moves_ahead() {
        // Collinear moves of 0.1 mm (14 steps) at F200 (467 steps/s): slowing to 10 % at
        // 2000 steps/s² takes 54 steps, more than the rest of any of them.
        let m = machine();
        let prog: String = (1..=60)
            .map(|i| format!("G1 X{} F200\n", i as f64 * 0.1))
            .collect();
        let base = streamed(&m, &prog, 200, 0, None);
        for cut in [10, 11, 25] {
            let items = streamed(
                &m,
                &prog,
                200,
                cut,
                Some(Scale {
                    feed: 0.1,
                    rapid: 1.0,
                }),
            );
            check_limits(&m, &items);
            assert_eq!(
                all_steps(&items).last().unwrap().1,
                all_steps(&base).last().unwrap().1
            );
            // Slower in the end: the override did apply.
            let ticks = |v: &[Item]| all_steps(v).last().unwrap().0;
            assert!(
                ticks(&items) > 3 * ticks(&base),
                "{} vs {}",
                ticks(&items),
                ticks(&base)
            );
        }
    }

    #[test]
    fn overrides_during_the_corpus_keep_every_limit_and_the_path() {
        let m = machine();
        let corpus =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/corpus/gcode");
        let text = std::fs::read_to_string(corpus.join("fusion-1122_jig_28bit_first.nc")).unwrap();
        let base = streamed(&m, &text, 200, 0, None);
        let path: Vec<_> = all_steps(&base).into_iter().map(|s| s.1).collect();
        for (cut, scale) in [(7, (0.3, 0.5)), (50, (2.0, 0.25)), (400, (0.1, 1.0))] {
            let items = streamed(
                &m,
                &text,
                200,
                cut,
                Some(Scale {
                    feed: scale.0,
                    rapid: scale.1,
                }),
            );
            check_limits(&m, &items);
            let got: Vec<_> = all_steps(&items).into_iter().map(|s| s.1).collect();
            assert!(got == path, "the override at item {cut} changed the path");
        }
    }

    proptest! {
        #[test]
        fn streamed_polylines_equal_the_whole_chain_plan(
            pts in proptest::collection::vec((-50i32..50, -50i32..50, 0u8..4), 2..40),
        ) {
            let m = machine();
            let mut prog = String::from("G1 F3000\n");
            for (x, y, kind) in &pts {
                prog.push_str(&match kind {
                    0 => format!("G1 X{} Y{}\n", *x as f64 / 7.0, *y as f64 / 3.0),
                    1 => format!("G0 X{} Y{}\n", *x as f64 / 5.0, *y as f64 / 9.0),
                    2 => format!("G2 X{} Y{} R40\n", *x as f64 / 7.0, *y as f64 / 3.0),
                    _ => "G4 P0.01\n".to_string(),
                });
            }
            let new = plan_program(&m, &prog, &start(), 1);
            let old = reference::plan_program_with_tools(&m, &prog, &start(), 1, Default::default());
            prop_assert_eq!(new, old);
        }

        #[test]
        fn blended_polylines_at_the_top_rate_keep_one_step_per_tick(
            pts in proptest::collection::vec((-50i32..50, -50i32..50), 2..6),
        ) {
            // max_rate = tick_hz / 2: the tightest the config allows.
            let mut m = machine();
            for ax in &mut m.axes {
                ax.max_rate = 10_000.0;
                ax.start_rate = 500.0;
                ax.accel = 200_000.0;
            }
            let mut prog = String::from("G1 F100000\n");
            for (x, y) in &pts {
                prog.push_str(&format!("G1 X{} Y{}\n", *x as f64 / 7.0, *y as f64 / 3.0));
            }
            let plan = plan_program(&m, &prog, &start(), 1).unwrap();
            let mut last_tick = None;
            for item in &plan.items {
                if let Action::Move(mv) = &item.action {
                    let steps: Vec<_> = mv.steps().collect();
                    prop_assert_eq!(mv.ticks, steps.last().unwrap().tick);
                    for s in &steps {
                        let t = item.start_tick + s.tick;
                        prop_assert!(last_tick.is_none_or(|l| t > l), "two steps in tick {}", t);
                        last_tick = Some(t);
                    }
                }
            }
        }

        #[test]
        fn overrides_at_any_moment_keep_the_limits_and_the_path(
            pts in proptest::collection::vec((-50i32..50, -50i32..50, 0u8..4), 2..25),
            cut in 0usize..60,
            feed in 0.1f64..2.0,
            rapid in 0.25f64..1.0,
            piece in 20u64..400,
        ) {
            let m = machine();
            let mut prog = String::from("G1 F900\n");
            for (x, y, kind) in &pts {
                prog.push_str(&match kind {
                    0 => format!("G1 X{} Y{}\n", *x as f64 / 7.0, *y as f64 / 3.0),
                    1 => format!("G0 X{} Y{}\n", *x as f64 / 5.0, *y as f64 / 9.0),
                    2 => format!("G2 X{} Y{} R40\n", *x as f64 / 7.0, *y as f64 / 3.0),
                    _ => "G4 P0.01\n".to_string(),
                });
            }
            // (Random arcs can be impossible ones: those programs are refused whole.)
            prop_assume!(plan_program(&m, &prog, &start(), 1).is_ok());
            let base = streamed(&m, &prog, piece, 0, None);
            let items = streamed(&m, &prog, piece, cut, Some(Scale { feed, rapid }));
            check_limits(&m, &items);
            let a: Vec<_> = all_steps(&base).into_iter().map(|s| s.1).collect();
            let b: Vec<_> = all_steps(&items).into_iter().map(|s| s.1).collect();
            prop_assert_eq!(a, b);
        }

        #[test]
        fn dda_lines_stay_within_half_a_step(
            fx in -3000i64..3000, fy in -3000i64..3000,
            tx in -3000i64..3000, ty in -3000i64..3000,
        ) {
            check_line([fx, fy], [tx, ty]);
        }
    }
}
