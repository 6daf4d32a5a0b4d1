//! A Mach3 simulator: models what the adapter relies on, with Mach3's own codes, so the agent
//! and the plugin can be tested end to end on any OS.
//!
//! * Axis DROs 800-805 show work coordinates (machine position minus the active fixture's
//!   offset, DROs 830-835; fixture number in DRO 46). MDI `Code()` understands G0 G1 G90 G91
//!   G54-G59 `G10 L2 P..` F and X..C words, keeps G90/G91, G0/G1 and F modal between calls and
//!   queues the moves; LED 48 lights in G90, LED 49 in G91 (as in Mach3's `Mach3Led.h`).
//! * `LoadFile` interprets the whole file with `fresa-gcode`; cycle start (1000) runs it from
//!   the line in DRO 816 (0-based), advancing DRO 816 and the elapsed time in DRO 814 (DRO 815 is
//!   the estimate). M0 pauses, M2/M30 end the run and rewind DRO 816 to 0. LED 804 = running.
//! * Feed hold (1001) pauses everything (LED 805); resume (1005) or cycle start continue.
//!   Stop (1003) ends motion and the run, keeping the line. Rewind (1002) sets the line to 0.
//! * Reset (1021) is a toggle like Mach3's: it latches or clears the reset/e-stop state
//!   (LED 800, `IsEstop`; the simulator starts latched, as Mach3 does). While latched nothing
//!   moves and buttons other than reset, and MDI, are ignored.
//! * Zero buttons (1007-1013) set the active fixture offset so the axis reads 0; ref buttons
//!   (105, 1022-1027) set the machine position to 0 at once; GotoZs (1017) rapids to work zero
//!   (Z up first). `JogOn`/`JogOff` move an axis continuously. LED 999 / `IsMoving`: motion.
//! * Overrides, applied to the move under way at every step, as Mach3 applies them: the feed
//!   override (FRO, DRO 821) to feed moves (G1, arcs, G31) of programs and MDI; the rapid
//!   override (DRO 223) to rapids only while "override of rapid feeds" is toggled on (button
//!   287, a toggle; LED 109 lit), else rapids run at the full rapid rate whatever DRO 223 says;
//!   the spindle override (DRO 74) scales the programmed S (DRO 817) into the overridden speed
//!   (DRO 202). Continuous jogs keep their own speed.
//! * Probing: an optional probe switch (`SimConfig::probe`; LED 825, Mach3's "Digitise In")
//!   and MDI `G31`, Mach3's probe move: a feed move that stops when the probe input becomes
//!   active. The machine position where it did (interpolated within the step) goes, in work
//!   coordinates, into parameters #2000-#2005 (`GetVar`), then the axis stops past it by the
//!   overshoot of a real stop: one kernel period of travel (`probe_latency_s`) plus the
//!   deceleration distance v²/2a (`probe_decel_mm_s2`). A G31 that runs its whole distance
//!   leaves its end in #2000-#2005; one that starts with the probe already active trips where
//!   it stands; Stop leaves the parameters as they were. G31 is modal (DRO 819 reads 31).
//!
//! Motion is feed-rate true, with times multiplied by `time_scale` (0 = instant). The elapsed
//! DRO (814) counts machine time while a program runs (at `time_scale` 1 the same as Mach3's
//! wall clock), so it shows what overrides did to a run whatever the host's load.

use crate::mach3::{Mach3, Mach3Error, Mach3Result};
use fresa_gcode::{linearise, Interpreter, Motion};
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

/// Time between two simulation steps.
const TICK: Duration = Duration::from_millis(2);
const AXES: usize = 6;

/// Mach3's own codes, as the simulator understands them.
mod code {
    pub const CYCLE_START: i16 = 1000;
    pub const FEED_HOLD: i16 = 1001;
    pub const REWIND: i16 = 1002;
    pub const STOP: i16 = 1003;
    pub const RESUME: i16 = 1005;
    pub const ZERO_ALL: i16 = 1007;
    pub const ZERO_X: i16 = 1008;
    pub const GOTO_ZERO: i16 = 1017;
    pub const RESET: i16 = 1021;
    pub const REF_ALL: i16 = 105;
    pub const REF_X: i16 = 1022;
    pub const DRO_X: i16 = 800;
    pub const DRO_VEL_X: i16 = 806;
    pub const DRO_ELAPSED: i16 = 814;
    pub const DRO_ESTIMATE: i16 = 815;
    pub const DRO_LINE: i16 = 816;
    pub const DRO_FEED: i16 = 818;
    pub const DRO_MOTION_MODE: i16 = 819;
    pub const DRO_FRO: i16 = 821;
    pub const DRO_TOOL: i16 = 824;
    pub const DRO_FIXTURE_X: i16 = 830;
    pub const DRO_FIXTURE_NUMBER: i16 = 46;
    pub const LED_ESTOP: i16 = 800;
    pub const LED_RUNNING: i16 = 804;
    pub const LED_PAUSED: i16 = 805;
    pub const LED_REFERENCED_X: i16 = 807;
    pub const LED_MOVING: i16 = 999;
    pub const LED_PROBE: i16 = 825;
    pub const LED_RAPID_OVERRIDE: i16 = 109;
    pub const RAPID_OVERRIDE_TOGGLE: i16 = 287;
    pub const DRO_SPINDLE_OVERRIDE: i16 = 74;
    pub const DRO_RAPID_OVERRIDE: i16 = 223;
    pub const DRO_SPINDLE_REQUESTED: i16 = 817;
    pub const DRO_SPINDLE_OVERRIDDEN: i16 = 202;
    /// G31's trip: #2000-#2005 = X..C.
    pub const VAR_PROBE_X: i16 = 2000;
    pub const LED_ABSOLUTE: i16 = 48;
    pub const LED_INCREMENTAL: i16 = 49;
    pub const FLOOD_ON: i16 = 224;
    pub const FLOOD_OFF: i16 = 225;
    pub const MIST_ON: i16 = 226;
    pub const MIST_OFF: i16 = 227;
    pub const LED_SPINDLE_CW: i16 = 11;
    pub const LED_SPINDLE_CCW: i16 = 12;
    pub const LED_FLOOD: i16 = 13;
    pub const LED_MIST: i16 = 14;
    /// X++ limit; X--, Y++, Y--, Z++, Z-- follow.
    pub const LED_LIMIT_X_MAX: i16 = 36;
}

/// Simulator settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimConfig {
    /// Multiplies every motion and dwell time: 1.0 = real time, 0.0 = instant.
    pub time_scale: f64,
    pub rapid_mm_min: f64,
    /// Speed of `JogOn` jogs.
    pub jog_feed_mm_min: f64,
    /// The probe input (a touch plate); `None`: nothing ever touches it.
    pub probe: Option<ProbeSwitch>,
    /// How long Mach3 takes to see the probe input change: one period of its driver's kernel
    /// (25 kHz, Mach3's default).
    pub probe_latency_s: f64,
    /// The deceleration with which the axis stops after a trip, mm/s².
    pub probe_decel_mm_s2: f64,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            time_scale: 1.0,
            rapid_mm_min: 5000.0,
            jog_feed_mm_min: 600.0,
            probe: None,
            probe_latency_s: 1.0 / 25_000.0,
            probe_decel_mm_s2: 1000.0,
        }
    }
}

/// A probe input that is active while one axis's machine position is at or below (or at or
/// above) a point: a touch plate under the tool, or a part's edge beside it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeSwitch {
    /// 0..5 = X..C.
    pub axis: usize,
    pub at: f64,
    /// Active at or below `at` (else at or above).
    pub below: bool,
}

impl ProbeSwitch {
    fn active(&self, pos: &[f64; AXES]) -> bool {
        let p = pos[self.axis];
        if self.below {
            p <= self.at
        } else {
            p >= self.at
        }
    }

    /// `z<=-20`, `x>=35.5`: the axis, the side and the machine position.
    pub fn parse(text: &str) -> Result<ProbeSwitch, String> {
        let bad = || {
            format!(
                "probe switch {text:?}: use AXIS<=POS (active at or below) or AXIS>=POS, e.g. z<=-20"
            )
        };
        let (axis, rest, below) = match (text.split_once("<="), text.split_once(">=")) {
            (Some((a, r)), None) => (a, r, true),
            (None, Some((a, r))) => (a, r, false),
            _ => return Err(bad()),
        };
        let axis = match axis.trim().to_ascii_lowercase().as_str() {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            "a" => 3,
            "b" => 4,
            "c" => 5,
            _ => return Err(bad()),
        };
        let at: f64 = rest.trim().parse().map_err(|_| bad())?;
        if !at.is_finite() {
            return Err(bad());
        }
        Ok(ProbeSwitch { axis, at, below })
    }
}

/// How fast a move goes. Overrides are applied while it runs, at every step.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Speed {
    /// A feed move (G1, arcs, G31), mm/min: the feed override applies.
    Feed(f64),
    /// A rapid: the rapid override applies while toggled on.
    Rapid,
    /// mm/min, no override (the stop after a probe trip).
    Fixed(f64),
}

/// The modal motion mode MDI axis words use (DRO 819 shows its G number).
#[derive(Debug, Clone, Copy, PartialEq)]
enum MotionMode {
    Rapid,
    Feed,
    Probe,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Step {
    /// To a point in program (work) coordinates; rapid when `feed` is `None`.
    /// `a`: where the A axis ends (degrees), when the move turns it.
    Move {
        to: [f64; 3],
        a: Option<f64>,
        feed: Option<f64>,
    },
    Dwell(f64),
    Pause,
    UseFixture(usize),
    /// M3/M4/M5 and S: direction (1 CW, -1 CCW, 0 off) and speed.
    Spindle(i8, f64),
    End,
}

#[derive(Debug)]
struct Program {
    /// `(1-based source line, step)`, in execution order.
    steps: Vec<(u32, Step)>,
    estimate_s: f64,
}

/// A straight move (or a dwell, when `length` is 0) in progress.
#[derive(Debug, Clone, Copy)]
struct Active {
    start: [f64; AXES],
    target: [f64; AXES],
    /// Path length (mm; degrees count as mm, as in the estimate).
    length: f64,
    /// How much of it is done.
    done: f64,
    speed: Speed,
    /// Seconds of dwell left (a dwell has no length).
    dwell_s: f64,
    /// A G31 move still looking for the probe.
    probing: bool,
}

/// An MDI or go-to-zero move waiting its turn.
#[derive(Debug, Clone, Copy)]
struct Queued {
    target: [f64; AXES],
    speed: Speed,
    probing: bool,
}

#[derive(Debug)]
struct State {
    cfg: SimConfig,
    pos: [f64; AXES],
    fixtures: [[f64; AXES]; 6],
    fixture: usize,
    incremental: bool,
    motion: MotionMode,
    feed: f64,
    fro: f64,
    /// Spindle speed override, %.
    sro: f64,
    /// Rapid override, % (DRO 223), in force only while `rapid_override_on`.
    rapid_override: f64,
    /// "Override of rapid feeds" (button 287 toggles it; LED 109).
    rapid_override_on: bool,
    /// Programmed spindle speed (S).
    spindle_rpm: f64,
    /// G-code parameters (`GetVar`); G31 writes #2000-#2005.
    vars: HashMap<i16, f64>,
    tool: f64,
    estop: bool,
    /// Spindle: 0 off, 1 clockwise (M3), -1 counter-clockwise (M4).
    spindle: i8,
    flood: bool,
    mist: bool,
    /// Limit switches X++, X--, Y++, Y--, Z++, Z-- (pressed by tests).
    limits: [bool; 6],
    referenced: [bool; AXES],
    program: Option<Program>,
    running: bool,
    paused: bool,
    /// Index of the next program step while running.
    cursor: usize,
    /// DRO 816: 0-based line.
    line: usize,
    elapsed_s: f64,
    /// MDI and go-to-zero moves.
    queue: VecDeque<Queued>,
    active: Option<Active>,
    jogs: [f64; AXES],
    other_dros: HashMap<i16, f64>,
    /// Mach3 "closed": every call fails as `MK_E_UNAVAILABLE` would.
    closed: bool,
}

struct Core {
    state: Mutex<State>,
    stop: Condvar,
}

/// A simulated Mach3. Cheap to clone (all clones are the same Mach3); its motion thread ends
/// when the last clone is dropped.
#[derive(Clone)]
pub struct Mach3Sim {
    core: Arc<Core>,
}

fn distance(from: &[f64; AXES], to: &[f64; AXES]) -> f64 {
    from.iter()
        .zip(to)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt()
}

fn seconds(from: &[f64; AXES], to: &[f64; AXES], feed: f64) -> f64 {
    if feed > 0.0 {
        distance(from, to) / feed * 60.0
    } else {
        0.0
    }
}

fn lerp(a: &[f64; AXES], b: &[f64; AXES], f: f64) -> [f64; AXES] {
    std::array::from_fn(|i| a[i] + (b[i] - a[i]) * f)
}

impl State {
    fn work(&self, axis: usize) -> f64 {
        self.pos[axis] - self.fixtures[self.fixture][axis]
    }

    fn moving(&self) -> bool {
        !self.paused
            && (self.active.is_some()
                || !self.queue.is_empty()
                || self.jogs.iter().any(|j| *j != 0.0)
                || self.running)
    }

    /// Reset latched: motion ends and, as on a real controller, spindle and coolant go off.
    fn latch_reset(&mut self) {
        self.estop = true;
        self.halt();
        self.spindle = 0;
        self.flood = false;
        self.mist = false;
    }

    fn halt(&mut self) {
        self.queue.clear();
        self.active = None;
        self.running = false;
        self.paused = false;
        self.jogs = [0.0; AXES];
    }

    /// Where queued motion ends (the base of an incremental MDI move).
    fn planned_end(&self) -> [f64; AXES] {
        self.queue
            .back()
            .map(|q| q.target)
            .or(self.active.map(|a| a.target))
            .unwrap_or(self.pos)
    }

    fn start_move(&mut self, target: [f64; AXES], speed: Speed, probing: bool) {
        if probing && self.cfg.probe.is_some_and(|p| p.active(&self.pos)) {
            // G31 with the probe already active: Mach3 takes the trip where the tool stands.
            self.set_trip(self.pos);
            self.active = None;
            return;
        }
        self.active = Some(Active {
            start: self.pos,
            target,
            length: distance(&self.pos, &target),
            done: 0.0,
            speed,
            dwell_s: 0.0,
            probing,
        });
    }

    fn start_dwell(&mut self, seconds: f64) {
        self.active = Some(Active {
            start: self.pos,
            target: self.pos,
            length: 0.0,
            done: 0.0,
            speed: Speed::Fixed(0.0),
            dwell_s: seconds,
            probing: false,
        });
    }

    /// Mach3's #2000-#2005: a machine position in the active fixture's work coordinates.
    fn set_trip(&mut self, machine: [f64; AXES]) {
        for (k, p) in machine.iter().enumerate() {
            let work = p - self.fixtures[self.fixture][k];
            self.vars.insert(code::VAR_PROBE_X + k as i16, work);
        }
    }

    /// mm/min a move goes at now, overrides applied.
    fn speed(&self, speed: Speed) -> f64 {
        match speed {
            Speed::Feed(f) => f * self.fro / 100.0,
            Speed::Rapid if self.rapid_override_on => {
                self.cfg.rapid_mm_min * self.rapid_override / 100.0
            }
            Speed::Rapid => self.cfg.rapid_mm_min,
            Speed::Fixed(f) => f,
        }
    }

    /// Advances the active move by at most `budget` machine seconds; returns the seconds used,
    /// or `None` when it cannot advance (an override of 0 %: Mach3 holds it there).
    fn advance(&mut self, budget: f64) -> Option<f64> {
        let mut a = self.active?;
        if a.length <= 0.0 {
            let t = budget.min(a.dwell_s);
            a.dwell_s -= t;
            self.active = (a.dwell_s > 0.0).then_some(a);
            return Some(t);
        }
        let v = self.speed(a.speed) / 60.0;
        if v <= 0.0 {
            return None;
        }
        let left = a.length - a.done;
        let t = budget.min(left / v);
        let before = self.pos;
        let done_before = a.done;
        let finished = t * v >= left;
        a.done = if finished { a.length } else { a.done + t * v };
        self.pos = if finished {
            a.target
        } else {
            lerp(&a.start, &a.target, a.done / a.length)
        };
        if a.probing {
            if let Some(switch) = self.cfg.probe {
                if !switch.active(&before) && switch.active(&self.pos) {
                    let (b, e) = (before[switch.axis], self.pos[switch.axis]);
                    let f = ((switch.at - b) / (e - b)).clamp(0.0, 1.0);
                    let trip = lerp(&before, &self.pos, f);
                    self.set_trip(trip);
                    self.stop_after_trip(&a, trip, done_before + (a.done - done_before) * f, v);
                    return Some(t * f);
                }
            }
            if finished {
                // The whole distance without contact: Mach3 leaves the end in #2000-#2005.
                self.set_trip(a.target);
            }
        }
        self.active = (!finished).then_some(a);
        Some(t)
    }

    /// A probe tripped at `trip` (`done` along `a`) while moving at `v` mm/s: Mach3 sees it one
    /// kernel period later and decelerates, so the axis comes to rest past the trip.
    fn stop_after_trip(&mut self, a: &Active, trip: [f64; AXES], done: f64, v: f64) {
        self.pos = trip;
        let latency = self.cfg.probe_latency_s.max(0.0);
        let decel = self.cfg.probe_decel_mm_s2;
        let braking = if decel > 0.0 {
            v * v / (2.0 * decel)
        } else {
            0.0
        };
        let over = (v * latency + braking).min(a.length - done).max(0.0);
        let time = latency + if decel > 0.0 { v / decel } else { 0.0 };
        self.active = None;
        if over > 0.0 && time > 0.0 {
            let stop_at = lerp(&a.start, &a.target, (done + over) / a.length);
            self.start_move(stop_at, Speed::Fixed(over / time * 60.0), false);
        }
    }

    /// Advances the simulation by `dt` of real time.
    fn tick(&mut self, dt: f64) {
        if self.estop {
            return;
        }
        let mut budget = if self.cfg.time_scale == 0.0 {
            f64::INFINITY
        } else {
            dt / self.cfg.time_scale
        };
        if !self.paused {
            // Continuous jogs run in real time: an operator holds them.
            let jog_step = self.cfg.jog_feed_mm_min / 60.0 * dt;
            for (p, j) in self.pos.iter_mut().zip(self.jogs) {
                *p += j * jog_step;
            }
        }
        while budget > 0.0 && !self.paused {
            if self.active.is_some() {
                let Some(t) = self.advance(budget) else { break };
                budget -= t;
                if self.running {
                    self.elapsed_s += t;
                }
                continue;
            }
            if let Some(q) = self.queue.pop_front() {
                self.start_move(q.target, q.speed, q.probing);
                continue;
            }
            if !self.running {
                break;
            }
            self.next_program_step();
        }
    }

    fn next_program_step(&mut self) {
        let Some((line, step)) = self
            .program
            .as_ref()
            .and_then(|p| p.steps.get(self.cursor).copied())
        else {
            // Ran off the end without M2/M30: Mach3 stops on the last line.
            self.running = false;
            return;
        };
        self.cursor += 1;
        self.line = line.saturating_sub(1) as usize;
        match step {
            Step::Move { to, a, feed } => {
                let mut target = self.pos;
                for i in 0..3 {
                    target[i] = to[i] + self.fixtures[self.fixture][i];
                }
                if let Some(a) = a {
                    target[3] = a + self.fixtures[self.fixture][3];
                }
                if let Some(f) = feed {
                    self.feed = f;
                }
                self.start_move(target, feed.map_or(Speed::Rapid, Speed::Feed), false);
            }
            Step::Dwell(s) => self.start_dwell(s),
            Step::Pause => self.paused = true,
            Step::UseFixture(f) => self.fixture = f,
            Step::Spindle(direction, rpm) => {
                self.spindle = direction;
                self.spindle_rpm = rpm;
            }
            Step::End => {
                self.running = false;
                self.line = 0;
            }
        }
    }

    fn cycle_start(&mut self) {
        if self.paused {
            self.paused = false;
            return;
        }
        if self.running || self.active.is_some() || !self.queue.is_empty() {
            return;
        }
        let Some(p) = &self.program else { return };
        // Start at the line in DRO 816; the modal effects of the lines before it carry over.
        let start = p
            .steps
            .partition_point(|(l, _)| (l.saturating_sub(1) as usize) < self.line);
        let (mut fixture, mut feed) = (self.fixture, self.feed);
        for (_, s) in &p.steps[..start] {
            match s {
                Step::UseFixture(f) => fixture = *f,
                Step::Move { feed: Some(f), .. } => feed = *f,
                _ => {}
            }
        }
        self.fixture = fixture;
        self.feed = feed;
        self.cursor = start;
        self.elapsed_s = 0.0;
        self.running = true;
    }

    fn button(&mut self, code: i16) {
        if code == code::RESET {
            self.estop = !self.estop;
            if self.estop {
                self.latch_reset();
            }
            return;
        }
        if self.estop {
            return;
        }
        match code {
            code::CYCLE_START => self.cycle_start(),
            code::FEED_HOLD if self.moving() => self.paused = true,
            code::RESUME => self.paused = false,
            code::STOP => self.halt(),
            code::REWIND if !self.running => self.line = 0,
            code::RAPID_OVERRIDE_TOGGLE => self.rapid_override_on = !self.rapid_override_on,
            code::FLOOD_ON => self.flood = true,
            code::FLOOD_OFF => self.flood = false,
            code::MIST_ON => self.mist = true,
            code::MIST_OFF => self.mist = false,
            code::ZERO_ALL => self.fixtures[self.fixture] = self.pos,
            c if (code::ZERO_X..code::ZERO_X + AXES as i16).contains(&c) => {
                let i = (c - code::ZERO_X) as usize;
                self.fixtures[self.fixture][i] = self.pos[i];
            }
            code::REF_ALL if !self.moving() => {
                self.pos = [0.0; AXES];
                self.referenced = [true; AXES];
            }
            c if (code::REF_X..code::REF_X + AXES as i16).contains(&c) && !self.moving() => {
                let i = (c - code::REF_X) as usize;
                self.pos[i] = 0.0;
                self.referenced[i] = true;
            }
            code::GOTO_ZERO if !self.moving() => {
                let zero = self.fixtures[self.fixture];
                let mut up = self.pos;
                up[2] = up[2].max(zero[2]);
                let mut over = zero;
                over[2] = up[2];
                for target in [up, over, zero] {
                    self.queue.push_back(Queued {
                        target,
                        speed: Speed::Rapid,
                        probing: false,
                    });
                }
            }
            // Mach3 ignores buttons it has no use for in the current state.
            _ => {}
        }
    }

    fn mdi(&mut self, line: &str) -> Mach3Result<()> {
        if self.estop {
            return Ok(()); // Mach3 ignores MDI while in reset.
        }
        if self.running {
            return Err(Mach3Error::invalid("MDI is ignored while a program runs"));
        }
        let words = parse_words(line)?;
        let mut target: [Option<f64>; AXES] = [None; AXES];
        let (mut g10, mut l, mut p) = (false, None, None);
        for (letter, value) in words {
            match letter {
                'G' => match value {
                    0.0 => self.motion = MotionMode::Rapid,
                    1.0 => self.motion = MotionMode::Feed,
                    31.0 => self.motion = MotionMode::Probe,
                    90.0 => self.incremental = false,
                    91.0 => self.incremental = true,
                    10.0 => g10 = true,
                    v if (54.0..=59.0).contains(&v) && v.fract() == 0.0 => {
                        self.fixture = (v - 54.0) as usize
                    }
                    v => {
                        return Err(Mach3Error::invalid(format!(
                            "the simulator does not model G{v} in MDI"
                        )))
                    }
                },
                'F' => self.feed = value,
                'S' => self.spindle_rpm = value.max(0.0),
                'M' => match value {
                    3.0 => self.spindle = 1,
                    4.0 => self.spindle = -1,
                    5.0 => self.spindle = 0,
                    7.0 => self.mist = true,
                    8.0 => self.flood = true,
                    9.0 => (self.mist, self.flood) = (false, false),
                    // Other M codes do not change what the simulator models.
                    _ => {}
                },
                'L' => l = Some(value),
                'P' => p = Some(value),
                'X' | 'Y' | 'Z' | 'A' | 'B' | 'C' => {
                    let i = "XYZABC".find(letter).unwrap_or(0);
                    target[i] = Some(value);
                }
                // Spindle, coolant, tool words do not move the simulated machine.
                _ => {}
            }
        }
        if g10 {
            let n = match (l, p) {
                (Some(l), Some(p)) if l == 2.0 && (1.0..=6.0).contains(&p) && p.fract() == 0.0 => {
                    p as usize - 1
                }
                _ => {
                    return Err(Mach3Error::invalid(
                        "the simulator models G10 only as G10 L2 P1..P6",
                    ))
                }
            };
            for (i, v) in target.iter().enumerate() {
                if let Some(v) = v {
                    self.fixtures[n][i] = *v;
                }
            }
            return Ok(());
        }
        if target.iter().all(Option::is_none) {
            return Ok(());
        }
        let speed = match self.motion {
            MotionMode::Rapid => Speed::Rapid,
            _ if self.feed > 0.0 => Speed::Feed(self.feed),
            MotionMode::Feed => {
                return Err(Mach3Error::invalid("G1 with feed rate 0: set F first"))
            }
            MotionMode::Probe => {
                return Err(Mach3Error::invalid("G31 with feed rate 0: set F first"))
            }
        };
        let base = self.planned_end();
        let end: [f64; AXES] = std::array::from_fn(|i| match target[i] {
            Some(v) if self.incremental => base[i] + v,
            Some(v) => v + self.fixtures[self.fixture][i],
            None => base[i],
        });
        self.queue.push_back(Queued {
            target: end,
            speed,
            probing: self.motion == MotionMode::Probe,
        });
        Ok(())
    }

    fn load(&mut self, path: &str) -> Mach3Result<()> {
        if self.running {
            return Err(Mach3Error::invalid(
                "cannot load a file while a program runs",
            ));
        }
        let text = std::fs::read_to_string(path).map_err(|e| {
            Mach3Error::new(
                crate::mach3::ErrorKind::Io,
                format!("cannot read {path}: {e}"),
            )
        })?;
        let mut config = fresa_gcode::Config {
            initial_position: [self.work(0), self.work(1), self.work(2)],
            initial_a_deg: self.work(3),
            ..Default::default()
        };
        for (i, f) in self.fixtures.iter().enumerate() {
            config.work_offsets[i] = [f[0], f[1], f[2]];
        }
        let mut steps = Vec::new();
        let mut estimate_s = 0.0;
        let mut at = config.initial_position;
        let mut at_a = config.initial_a_deg;
        for m in linearise(Interpreter::new(text.as_bytes(), config), 0.01) {
            let m = m.map_err(|e| Mach3Error::invalid(e.to_string()))?;
            let line = m.line();
            // This simulator plans a program whole when it is loaded, so a move that depends
            // on where a G31 tripped cannot be planned: it runs G31 as MDI only (the real Mach3
            // runs it in programs too).
            if matches!(m, Motion::Probe { .. }) {
                return Err(Mach3Error::invalid(format!(
                    "line {line}: this simulated Mach3 runs G31 only as MDI, not in a program"
                )));
            }
            let step = match m {
                Motion::Rapid { to, a, .. } => Step::Move {
                    to,
                    a: a.map(|a| a.to),
                    feed: None,
                },
                Motion::Linear {
                    to, feed_mm_min, a, ..
                } => Step::Move {
                    to,
                    a: a.map(|a| a.to),
                    feed: Some(feed_mm_min),
                },
                Motion::Arc {
                    to, feed_mm_min, ..
                } => Step::Move {
                    to,
                    a: None,
                    feed: Some(feed_mm_min),
                },
                Motion::Dwell { seconds, .. } => Step::Dwell(seconds.max(0.0)),
                Motion::Pause {
                    optional: false, ..
                } => Step::Pause,
                Motion::WorkOffset { system, .. } if (1..=6).contains(&system) => {
                    Step::UseFixture(usize::from(system) - 1)
                }
                Motion::ProgramEnd { .. } => Step::End,
                Motion::Spindle { direction, rpm, .. } => Step::Spindle(
                    match direction {
                        fresa_gcode::SpindleDirection::Clockwise => 1,
                        fresa_gcode::SpindleDirection::CounterClockwise => -1,
                        fresa_gcode::SpindleDirection::Off => 0,
                    },
                    rpm,
                ),
                _ => continue,
            };
            if let Step::Move { to, a, feed } = step {
                let f = feed.unwrap_or(self.cfg.rapid_mm_min);
                let a = a.unwrap_or(at_a);
                estimate_s += seconds(
                    &[at[0], at[1], at[2], at_a, 0.0, 0.0],
                    &[to[0], to[1], to[2], a, 0.0, 0.0],
                    f,
                );
                at = to;
                at_a = a;
            }
            steps.push((line, step));
        }
        self.program = Some(Program { steps, estimate_s });
        self.line = 0;
        self.paused = false;
        Ok(())
    }

    fn dro(&self, c: i16) -> f64 {
        match c {
            c if (code::DRO_X..code::DRO_X + AXES as i16).contains(&c) => {
                self.work((c - code::DRO_X) as usize)
            }
            c if (code::DRO_VEL_X..code::DRO_VEL_X + AXES as i16).contains(&c) => 0.0,
            c if (code::DRO_FIXTURE_X..code::DRO_FIXTURE_X + AXES as i16).contains(&c) => {
                self.fixtures[self.fixture][(c - code::DRO_FIXTURE_X) as usize]
            }
            code::DRO_ELAPSED => self.elapsed_s,
            code::DRO_ESTIMATE => self.program.as_ref().map_or(0.0, |p| p.estimate_s),
            code::DRO_LINE => self.line as f64,
            code::DRO_FEED => self.feed,
            code::DRO_MOTION_MODE => match self.motion {
                MotionMode::Rapid => 0.0,
                MotionMode::Feed => 1.0,
                MotionMode::Probe => 31.0,
            },
            code::DRO_FRO => self.fro,
            code::DRO_SPINDLE_OVERRIDE => self.sro,
            code::DRO_RAPID_OVERRIDE => self.rapid_override,
            code::DRO_SPINDLE_REQUESTED => self.spindle_rpm,
            code::DRO_SPINDLE_OVERRIDDEN => self.spindle_rpm * self.sro / 100.0,
            code::DRO_TOOL => self.tool,
            code::DRO_FIXTURE_NUMBER => (self.fixture + 1) as f64,
            other => self.other_dros.get(&other).copied().unwrap_or(0.0),
        }
    }

    fn set_dro(&mut self, c: i16, v: f64) {
        match c {
            c if (code::DRO_X..code::DRO_X + AXES as i16).contains(&c) => {
                let i = (c - code::DRO_X) as usize;
                self.fixtures[self.fixture][i] = self.pos[i] - v;
            }
            c if (code::DRO_FIXTURE_X..code::DRO_FIXTURE_X + AXES as i16).contains(&c) => {
                self.fixtures[self.fixture][(c - code::DRO_FIXTURE_X) as usize] = v;
            }
            code::DRO_LINE if !self.running => self.line = v.max(0.0) as usize,
            code::DRO_FRO => self.fro = v.clamp(0.0, 300.0),
            code::DRO_SPINDLE_OVERRIDE => self.sro = v.clamp(0.0, 300.0),
            // Mach3's rapid override slows rapids; it never makes them faster than the rate.
            code::DRO_RAPID_OVERRIDE => self.rapid_override = v.clamp(0.0, 100.0),
            code::DRO_TOOL => self.tool = v,
            code::DRO_FIXTURE_NUMBER if (1.0..=6.0).contains(&v) => self.fixture = v as usize - 1,
            other => {
                self.other_dros.insert(other, v);
            }
        }
    }

    fn led(&self, c: i16) -> bool {
        match c {
            code::LED_ESTOP => self.estop,
            code::LED_RUNNING => self.running,
            code::LED_PAUSED => self.paused,
            code::LED_MOVING => self.moving(),
            code::LED_PROBE => self.cfg.probe.is_some_and(|p| p.active(&self.pos)),
            code::LED_RAPID_OVERRIDE => self.rapid_override_on,
            code::LED_ABSOLUTE => !self.incremental,
            code::LED_INCREMENTAL => self.incremental,
            code::LED_SPINDLE_CW => self.spindle == 1,
            code::LED_SPINDLE_CCW => self.spindle == -1,
            code::LED_FLOOD => self.flood,
            code::LED_MIST => self.mist,
            c if (code::LED_LIMIT_X_MAX..code::LED_LIMIT_X_MAX + 6).contains(&c) => {
                self.limits[(c - code::LED_LIMIT_X_MAX) as usize]
            }
            c if (code::LED_REFERENCED_X..code::LED_REFERENCED_X + AXES as i16).contains(&c) => {
                self.referenced[(c - code::LED_REFERENCED_X) as usize]
            }
            _ => false,
        }
    }
}

/// Splits an MDI line into `(letter, number)` words; `( )` and `;` comments are skipped.
fn parse_words(line: &str) -> Mach3Result<Vec<(char, f64)>> {
    let mut words = Vec::new();
    let mut chars = line.char_indices().peekable();
    while let Some((col, c)) = chars.next() {
        match c {
            ' ' | '\t' => {}
            '(' => {
                for (_, c) in chars.by_ref() {
                    if c == ')' {
                        break;
                    }
                }
            }
            ';' => break,
            c if c.is_ascii_alphabetic() => {
                let mut num = String::new();
                while let Some((_, d)) = chars.peek() {
                    if d.is_ascii_digit() || matches!(d, '.' | '-' | '+') || *d == ' ' {
                        if *d != ' ' {
                            num.push(*d);
                        }
                        chars.next();
                    } else {
                        break;
                    }
                }
                let value: f64 = num.parse().map_err(|_| {
                    Mach3Error::invalid(format!(
                        "MDI {line:?}, column {}: `{c}` needs a number",
                        col + 1
                    ))
                })?;
                words.push((c.to_ascii_uppercase(), value));
            }
            other => {
                return Err(Mach3Error::invalid(format!(
                    "MDI {line:?}, column {}: unexpected {other:?}",
                    col + 1
                )))
            }
        }
    }
    Ok(words)
}

impl Mach3Sim {
    pub fn new(cfg: SimConfig) -> Mach3Sim {
        let core = Arc::new(Core {
            state: Mutex::new(State {
                cfg,
                pos: [0.0; AXES],
                fixtures: [[0.0; AXES]; 6],
                fixture: 0,
                incremental: false,
                motion: MotionMode::Rapid,
                feed: 0.0,
                fro: 100.0,
                sro: 100.0,
                rapid_override: 100.0,
                rapid_override_on: false,
                spindle_rpm: 0.0,
                vars: HashMap::new(),
                tool: 0.0,
                estop: true,
                spindle: 0,
                flood: false,
                mist: false,
                limits: [false; 6],
                referenced: [false; AXES],
                program: None,
                running: false,
                paused: false,
                cursor: 0,
                line: 0,
                elapsed_s: 0.0,
                queue: VecDeque::new(),
                active: None,
                jogs: [0.0; AXES],
                other_dros: HashMap::new(),
                closed: false,
            }),
            stop: Condvar::new(),
        });
        let weak = Arc::downgrade(&core);
        // If the thread cannot start the simulator does not move; tests would show it at once.
        let _ = std::thread::Builder::new()
            .name("mach3-sim motion".into())
            .spawn(move || motion_thread(weak));
        Mach3Sim { core }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.core.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The state of a running Mach3, or the error a closed one gives.
    fn open(&self) -> Mach3Result<MutexGuard<'_, State>> {
        let st = self.lock();
        if st.closed {
            return Err(Mach3Error::new(
                crate::mach3::ErrorKind::NotRunning,
                "Mach3 is not running (simulated MK_E_UNAVAILABLE)",
            ));
        }
        Ok(st)
    }

    /// Simulates closing Mach3 (`false`) and starting it again (`true`): a restarted Mach3
    /// comes back in reset, with nothing loaded and nothing moving.
    pub fn set_running(&self, running: bool) {
        let mut st = self.lock();
        if running && st.closed {
            st.latch_reset();
            st.program = None;
            st.line = 0;
        }
        st.closed = !running;
    }

    /// Moves the probe switch (`None`: nothing touches the probe), as an operator places a
    /// touch plate.
    pub fn set_probe(&self, probe: Option<ProbeSwitch>) {
        self.lock().cfg.probe = probe;
    }

    /// Presses (or releases) limit switch `which` (0 X++, 1 X--, 2 Y++, 3 Y--, 4 Z++, 5 Z--):
    /// its LED lights and, as Mach3 does on a limit, reset latches and motion stops.
    pub fn press_limit(&self, which: usize, pressed: bool) {
        let mut st = self.lock();
        if let Some(l) = st.limits.get_mut(which) {
            *l = pressed;
            if pressed {
                st.latch_reset();
            }
        }
    }
}

fn motion_thread(core: Weak<Core>) {
    let mut last = Instant::now();
    loop {
        let Some(core) = core.upgrade() else { return };
        let st = core.state.lock().unwrap_or_else(|e| e.into_inner());
        let (mut st, _) = core
            .stop
            .wait_timeout(st, TICK)
            .unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        st.tick(now.duration_since(last).as_secs_f64());
        last = now;
    }
}

impl Mach3 for Mach3Sim {
    fn do_oem_button(&mut self, code: i16) -> Mach3Result<()> {
        self.open()?.button(code);
        Ok(())
    }
    fn get_oem_dro(&mut self, code: i16) -> Mach3Result<f64> {
        Ok(self.open()?.dro(code))
    }
    fn set_oem_dro(&mut self, code: i16, value: f64) -> Mach3Result<()> {
        self.open()?.set_dro(code, value);
        Ok(())
    }
    fn get_oem_led(&mut self, code: i16) -> Mach3Result<bool> {
        Ok(self.open()?.led(code))
    }
    fn code(&mut self, line: &str) -> Mach3Result<()> {
        self.open()?.mdi(line)
    }
    fn load_file(&mut self, path: &str) -> Mach3Result<()> {
        self.open()?.load(path)
    }
    fn jog_on(&mut self, axis: i16, direction: i16) -> Mach3Result<()> {
        let mut st = self.open()?;
        if !st.estop && !st.running {
            st.jogs[axis.clamp(0, AXES as i16 - 1) as usize] =
                if direction == 0 { 1.0 } else { -1.0 };
        }
        Ok(())
    }
    fn jog_off(&mut self, axis: i16) -> Mach3Result<()> {
        self.open()?.jogs[axis.clamp(0, AXES as i16 - 1) as usize] = 0.0;
        Ok(())
    }
    fn is_moving(&mut self) -> Mach3Result<bool> {
        Ok(self.open()?.moving())
    }
    fn is_estop(&mut self) -> Mach3Result<bool> {
        Ok(self.open()?.estop)
    }
    fn get_var(&mut self, var: i16) -> Mach3Result<f64> {
        Ok(self.open()?.vars.get(&var).copied().unwrap_or(0.0))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    fn sim(time_scale: f64) -> Mach3Sim {
        let mut m = Mach3Sim::new(SimConfig {
            time_scale,
            ..Default::default()
        });
        m.do_oem_button(code::RESET).unwrap(); // leave the start-up reset
        m
    }

    fn wait_still(m: &mut Mach3Sim) {
        let deadline = Instant::now() + Duration::from_secs(20);
        while m.is_moving().unwrap() {
            assert!(Instant::now() < deadline, "still moving");
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    #[test]
    fn starts_in_reset_and_reset_toggles() {
        let mut m = Mach3Sim::new(SimConfig::default());
        assert!(m.is_estop().unwrap());
        assert!(m.get_oem_led(code::LED_ESTOP).unwrap());
        m.code("G91 G1 X5 F100").unwrap();
        assert!(!m.is_moving().unwrap(), "nothing moves in reset");
        m.do_oem_button(code::RESET).unwrap();
        assert!(!m.is_estop().unwrap());
        m.do_oem_button(code::RESET).unwrap();
        assert!(m.is_estop().unwrap());
    }

    #[test]
    fn mdi_moves_are_modal_and_exact() {
        let mut m = sim(0.0);
        m.code("G91 G1 X1.5 F600").unwrap();
        wait_still(&mut m);
        assert!(m.get_oem_led(code::LED_INCREMENTAL).unwrap());
        m.code("Y-2").unwrap(); // still G91 G1
        wait_still(&mut m);
        assert_eq!(m.get_oem_dro(code::DRO_X).unwrap(), 1.5);
        assert_eq!(m.get_oem_dro(code::DRO_X + 1).unwrap(), -2.0);
        assert_eq!(m.get_oem_dro(code::DRO_MOTION_MODE).unwrap(), 1.0);
        m.code("G90 G0 X10").unwrap();
        wait_still(&mut m);
        assert!(!m.get_oem_led(code::LED_INCREMENTAL).unwrap());
        assert_eq!(m.get_oem_dro(code::DRO_X).unwrap(), 10.0);
        assert!(m.code("G1 X(").is_err());
    }

    #[test]
    fn zero_buttons_and_fixture_dros() {
        let mut m = sim(0.0);
        m.code("G0 X4 Y5 Z6").unwrap();
        wait_still(&mut m);
        m.do_oem_button(code::ZERO_X + 1).unwrap();
        assert_eq!(m.get_oem_dro(code::DRO_X + 1).unwrap(), 0.0);
        assert_eq!(m.get_oem_dro(code::DRO_FIXTURE_X + 1).unwrap(), 5.0);
        assert_eq!(m.get_oem_dro(code::DRO_X).unwrap(), 4.0);
        m.set_oem_dro(code::DRO_FIXTURE_X, 1.0).unwrap();
        assert_eq!(m.get_oem_dro(code::DRO_X).unwrap(), 3.0);
        m.code("G10 L2 P2 X7").unwrap();
        m.code("G55").unwrap();
        assert_eq!(m.get_oem_dro(code::DRO_FIXTURE_NUMBER).unwrap(), 2.0);
        assert_eq!(m.get_oem_dro(code::DRO_X).unwrap(), -3.0);
    }

    #[test]
    fn program_runs_holds_and_rewinds_at_m30() {
        let dir = std::env::temp_dir().join(format!("mach3-sim-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.nc");
        std::fs::write(&path, "G21 G90\nG1 X10 F600\nG1 X0\nG1 Y10\nM30\n").unwrap();
        let mut m = sim(0.2); // 1 s of machine time a line -> 0.2 s
        m.load_file(path.to_str().unwrap()).unwrap();
        assert!(m.get_oem_dro(code::DRO_ESTIMATE).unwrap() > 2.9);
        m.do_oem_button(code::CYCLE_START).unwrap();
        assert!(m.get_oem_led(code::LED_RUNNING).unwrap());
        m.do_oem_button(code::FEED_HOLD).unwrap();
        assert!(m.get_oem_led(code::LED_PAUSED).unwrap());
        let x = m.get_oem_dro(code::DRO_X).unwrap();
        std::thread::sleep(Duration::from_millis(50)); // nothing may move while held
        assert_eq!(m.get_oem_dro(code::DRO_X).unwrap(), x);
        m.do_oem_button(code::RESUME).unwrap();
        let mut lines = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(20);
        while m.get_oem_led(code::LED_RUNNING).unwrap() {
            lines.push(m.get_oem_dro(code::DRO_LINE).unwrap());
            assert!(Instant::now() < deadline);
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(lines.contains(&2.0), "{lines:?}");
        assert_eq!(m.get_oem_dro(code::DRO_LINE).unwrap(), 0.0, "M30 rewinds");
        assert_eq!(m.get_oem_dro(code::DRO_X + 1).unwrap(), 10.0);
        assert!(m.get_oem_dro(code::DRO_ELAPSED).unwrap() > 0.0);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Runs `program` to its end at time scale 0 and answers the run's elapsed machine time.
    fn run_elapsed(m: &mut Mach3Sim, dir: &std::path::Path, program: &str) -> f64 {
        let path = dir.join("o.nc");
        std::fs::write(&path, program).unwrap();
        m.load_file(path.to_str().unwrap()).unwrap();
        m.do_oem_button(code::CYCLE_START).unwrap();
        wait_still(m);
        m.get_oem_dro(code::DRO_ELAPSED).unwrap()
    }

    #[test]
    fn overrides_scale_feeds_and_rapids_only_while_the_rapid_toggle_is_on() {
        let dir = tempfile::tempdir().unwrap();
        let mut m = sim(0.0);
        // 10 mm at F600 (1 s) and 10 mm of rapid at 5000 mm/min (0.12 s).
        let program = "G21 G90\nG1 X10 F600\nG0 X0\nM30\n";
        let close = |a: f64, b: f64| (a - b).abs() < 1e-9;
        assert!(close(run_elapsed(&mut m, dir.path(), program), 1.12));
        m.set_oem_dro(code::DRO_FRO, 50.0).unwrap();
        assert!(close(run_elapsed(&mut m, dir.path(), program), 2.12));
        m.set_oem_dro(code::DRO_FRO, 100.0).unwrap();
        // Rapid override set, but not toggled on: rapids run at the full rate.
        m.set_oem_dro(code::DRO_RAPID_OVERRIDE, 25.0).unwrap();
        assert!(!m.get_oem_led(code::LED_RAPID_OVERRIDE).unwrap());
        assert!(close(run_elapsed(&mut m, dir.path(), program), 1.12));
        m.do_oem_button(code::RAPID_OVERRIDE_TOGGLE).unwrap();
        assert!(m.get_oem_led(code::LED_RAPID_OVERRIDE).unwrap());
        assert!(close(run_elapsed(&mut m, dir.path(), program), 1.48));
        // Above 100 % is not a rapid override Mach3 takes.
        m.set_oem_dro(code::DRO_RAPID_OVERRIDE, 150.0).unwrap();
        assert_eq!(m.get_oem_dro(code::DRO_RAPID_OVERRIDE).unwrap(), 100.0);
        // The spindle override scales the programmed S.
        m.code("M3 S1000").unwrap();
        m.set_oem_dro(code::DRO_SPINDLE_OVERRIDE, 120.0).unwrap();
        assert_eq!(m.get_oem_dro(code::DRO_SPINDLE_REQUESTED).unwrap(), 1000.0);
        assert_eq!(m.get_oem_dro(code::DRO_SPINDLE_OVERRIDDEN).unwrap(), 1200.0);
    }

    #[test]
    fn the_feed_override_changes_the_move_under_way() {
        let m = sim(1.0);
        // The lock holds the motion thread off: these steps are the only ones taken.
        let mut st = m.lock();
        st.mdi("G90 G1 X10 F600").unwrap(); // 1 s at 100 %
        st.tick(0.5);
        assert!((st.pos[0] - 5.0).abs() < 1e-9, "{:?}", st.pos);
        st.set_dro(code::DRO_FRO, 50.0);
        st.tick(0.5);
        assert!(
            (st.pos[0] - 7.5).abs() < 1e-9,
            "half speed from then on: {:?}",
            st.pos
        );
        st.tick(1.0);
        assert_eq!(st.pos[0], 10.0);
        assert!(!st.moving());
    }

    fn probing_sim(at: f64, time_scale: f64) -> Mach3Sim {
        let mut m = Mach3Sim::new(SimConfig {
            time_scale,
            probe: Some(ProbeSwitch {
                axis: 2,
                at,
                below: true,
            }),
            ..Default::default()
        });
        m.do_oem_button(code::RESET).unwrap();
        m
    }

    fn trip(m: &mut Mach3Sim) -> [f64; 3] {
        std::array::from_fn(|i| m.get_var(code::VAR_PROBE_X + i as i16).unwrap())
    }

    #[test]
    fn g31_stops_past_the_probe_and_keeps_the_trip_in_2000_to_2002() {
        let mut m = probing_sim(-20.0, 0.0);
        m.code("G0 X3").unwrap();
        m.set_oem_dro(code::DRO_FIXTURE_X + 2, -5.0).unwrap(); // G54 Z: work = machine + 5
        assert!(!m.get_oem_led(code::LED_PROBE).unwrap());
        m.code("G90 G31 Z-50 F300").unwrap();
        wait_still(&mut m);
        assert_eq!(
            m.get_oem_dro(code::DRO_MOTION_MODE).unwrap(),
            31.0,
            "G31 is modal"
        );
        assert!(
            m.get_oem_led(code::LED_PROBE).unwrap(),
            "resting on the plate"
        );
        // The trip, in work coordinates: machine Z -20 is work Z -15.
        let t = trip(&mut m);
        assert!((t[2] + 15.0).abs() < 1e-9, "{t:?}");
        assert_eq!(t[0], 3.0);
        // At 300 mm/min (5 mm/s): 5 mm/s x 40 us + 25 / 2000 mm past the trip.
        let rest = m.get_oem_dro(code::DRO_X + 2).unwrap() - 5.0;
        let overshoot = -20.0 - rest;
        assert!(
            (overshoot - (5.0 / 25_000.0 + 25.0 / 2000.0)).abs() < 1e-9,
            "{overshoot}"
        );
        // Already touching: a G31 trips where it stands and does not move.
        let z = m.get_oem_dro(code::DRO_X + 2).unwrap();
        m.code("G31 Z-60").unwrap();
        wait_still(&mut m);
        assert_eq!(m.get_oem_dro(code::DRO_X + 2).unwrap(), z);
        assert!((trip(&mut m)[2] - z).abs() < 1e-9);
        // Off the plate and a G31 that never reaches it: the end goes into #2002.
        m.code("G0 Z0").unwrap();
        m.set_probe(Some(ProbeSwitch {
            axis: 2,
            at: -80.0,
            below: true,
        }));
        m.code("G31 Z-30").unwrap();
        wait_still(&mut m);
        assert_eq!(m.get_oem_dro(code::DRO_X + 2).unwrap(), -30.0);
        assert_eq!(trip(&mut m)[2], -30.0);
        assert!(!m.get_oem_led(code::LED_PROBE).unwrap());
    }

    #[test]
    fn stop_during_g31_leaves_the_trip_parameters_alone() {
        let mut m = probing_sim(-20.0, 1.0);
        let mut st = m.lock();
        st.mdi("G90 G31 Z-50 F600").unwrap();
        st.tick(1.0); // 10 mm down
        assert!((st.pos[2] + 10.0).abs() < 1e-9, "{:?}", st.pos);
        st.button(code::STOP);
        st.tick(1.0);
        assert!(!st.moving());
        drop(st);
        assert_eq!(trip(&mut m), [0.0; 3], "untouched");
        assert!((m.get_oem_dro(code::DRO_X + 2).unwrap() + 10.0).abs() < 1e-9);
    }

    #[test]
    fn probe_switches_parse() {
        assert_eq!(
            ProbeSwitch::parse("z<=-20").unwrap(),
            ProbeSwitch {
                axis: 2,
                at: -20.0,
                below: true
            }
        );
        assert_eq!(
            ProbeSwitch::parse("X>=35.5").unwrap(),
            ProbeSwitch {
                axis: 0,
                at: 35.5,
                below: false
            }
        );
        for bad in ["z<-20", "q<=1", "z<=x", "z<=inf", ""] {
            assert!(ProbeSwitch::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn jog_on_runs_until_jog_off() {
        let mut m = sim(1.0);
        m.jog_on(2, 1).unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while m.get_oem_dro(code::DRO_X + 2).unwrap() > -0.1 {
            assert!(Instant::now() < deadline);
            std::thread::sleep(Duration::from_millis(2));
        }
        assert!(m.is_moving().unwrap());
        m.jog_off(2).unwrap();
        assert!(!m.is_moving().unwrap());
        let z = m.get_oem_dro(code::DRO_X + 2).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(m.get_oem_dro(code::DRO_X + 2).unwrap(), z);
    }
}
