//! Whole-program analysis in one streaming pass (constant memory).

use crate::arc::{ArcGeometry, WorkBudget};
use crate::estimate::{dist, Estimator, MotionProfile, TimeTable};
use crate::{Config, GcodeError, Interpreter, Motion, Point, SpindleDirection, Warning};
use serde::{Deserialize, Serialize};
use std::io::BufRead;

/// Axis-aligned box, mm, program coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Bounds {
    pub min: Point,
    pub max: Point,
}

impl Bounds {
    /// A box holding only `p`.
    pub fn point(p: Point) -> Self {
        Bounds { min: p, max: p }
    }
    /// Grows the box to hold `p`.
    #[inline]
    pub fn include(&mut self, p: Point) {
        for (i, &v) in p.iter().enumerate() {
            self.min[i] = self.min[i].min(v);
            self.max[i] = self.max[i].max(v);
        }
    }
    /// Size along X, Y, Z.
    pub fn size(&self) -> Point {
        [
            self.max[0] - self.min[0],
            self.max[1] - self.min[1],
            self.max[2] - self.min[2],
        ]
    }
}

fn grow(b: &mut Option<Bounds>, lo: Point, hi: Point) {
    match b {
        Some(b) => {
            b.include(lo);
            b.include(hi);
        }
        None => {
            let mut nb = Bounds::point(lo);
            nb.include(hi);
            *b = Some(nb);
        }
    }
}

/// Result of [`analyse`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Analysis {
    /// Source lines read (up to the program end).
    pub lines: u64,
    /// Lines that produced at least one rapid, linear or arc move.
    pub motion_lines: u64,
    /// Bounds of feed moves (G1/G2/G3), arcs by their exact extrema.
    pub cutting_bounds: Option<Bounds>,
    /// Bounds of rapid moves (G0, G28/G30, G53 G0), start points included.
    pub rapid_bounds: Option<Bounds>,
    pub cutting_length_mm: f64,
    pub rapid_length_mm: f64,
    /// Run time at 100 % overrides with the machine's [`MotionProfile`] (its rapid rate,
    /// acceleration and cornering; without one, rapids at `rapid_mm_min` and no acceleration):
    /// the total of `time_table`.
    pub estimated_seconds: f64,
    /// Cumulative time by line (at most [`crate::estimate::MAX_MARKS`] marks): a running job's
    /// remaining time at any line, under any override.
    pub time_table: TimeTable,
    pub warnings: Vec<Warning>,
    /// Warnings beyond [`Config::max_warnings`] (counted, not kept).
    pub warnings_dropped: u64,
    pub units_inch_seen: bool,
    pub rapid_moves: u64,
    pub linear_moves: u64,
    pub arc_moves: u64,
    pub dwell_seconds: f64,
    /// Tools loaded by M6, in first-use order (at most 1000 kept).
    pub tools: Vec<u32>,
    /// The first M6 line: a machine whose tool-change policy is `refuse` refuses the
    /// program naming it.
    pub first_tool_change_line: Option<u32>,
    /// Highest feed of a feed move, mm/min (0 if none).
    pub max_feed_mm_min: f64,
    /// Highest spindle speed programmed with the spindle on.
    pub max_spindle_rpm: f64,
    /// M2/M30 or a closing `%` was reached.
    pub program_end: bool,
    /// Lines where the program moved its own origin (G92, G92.1, G92.2,
    /// G92.3, G52), in order, at most 100 kept (`offset_change_count` counts
    /// all). Bounds and lengths already include these offsets: they are in
    /// the work system's frame.
    pub offset_changes: Vec<OffsetChangeNote>,
    pub offset_change_count: u64,
    /// Range the rotary A axis moves over (degrees, program coordinates),
    /// `None` if A never moves.
    pub a_bounds: Option<RotaryBounds>,
    /// First line with A motion: a machine without an A axis refuses the
    /// program naming it.
    pub first_a_line: Option<u32>,
    /// Probing moves (G38.2-G38.5), counted with the cutting moves' bounds
    /// and time for their whole distance (the worst case).
    pub probe_moves: u64,
    /// The first probing line: a machine without a probe input refuses the
    /// program naming it, and the moves after it may depend on where the
    /// probe trips (analysed here as if it ran its whole way untripped).
    pub first_probe_line: Option<u32>,
    /// Moves whose end point depends on where a probe trips (see
    /// [`probe_spread`]; 0 until it has been merged in).
    pub probe_dependent_moves: u64,
    /// The first line with such a move.
    pub first_probe_dependent_line: Option<u32>,
    /// From this line on the program's path depends on a probe's result in a
    /// way the two cases of [`probe_spread`] cannot bound (control flow that
    /// reads the result): checked with the no-contact assumption only, and by
    /// the machine before each move.
    pub probe_paths_unchecked_from: Option<u32>,
    /// Segments the program linearises to (moves, and arcs as chords at
    /// [`Config::arc_tolerance_mm`]): the work it causes, at most
    /// [`AnalysisOptions::max_segments`].
    pub segments: u64,
}

/// Range of the A axis, degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RotaryBounds {
    pub min: f64,
    pub max: f64,
}

/// One origin change made by the program (see [`Analysis::offset_changes`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OffsetChangeNote {
    pub line: u32,
    /// `G92`, `G92.1`, `G92.2`, `G92.3`, `G52`, or `G10 L2 P1` / `G10 L20 P2`.
    pub command: String,
    /// G92/G52: the offset in effect afterwards, mm (program = work frame -
    /// offset). G10: the work system's new origin (machine coordinates, mm).
    pub offset: Point,
    /// The A axis's offset afterwards, degrees (left out when 0).
    #[serde(skip_serializing_if = "is_zero")]
    pub offset_a: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// Settings for [`analyse`] (missing fields take their defaults when deserialised).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AnalysisOptions {
    /// Speed assumed for rapids, mm/min (default 5000).
    pub rapid_mm_min: f64,
    pub config: Config,
    /// The work budget: a program that linearises to more segments is an
    /// [`crate::ErrorKind::Budget`] error at the line where it ran out (counted
    /// from each arc's radius and sweep, so the check stays cheap for a huge arc).
    /// Default [`crate::DEFAULT_MAX_SEGMENTS`].
    pub max_segments: u64,
    /// How the machine moves, for the time estimate; absent: rapids at `rapid_mm_min`, no
    /// acceleration.
    pub profile: Option<MotionProfile>,
}

impl Default for AnalysisOptions {
    fn default() -> Self {
        AnalysisOptions {
            rapid_mm_min: 5000.0,
            config: Config::default(),
            max_segments: crate::DEFAULT_MAX_SEGMENTS,
            profile: None,
        }
    }
}

/// Grows `b` by a straight move from `from` to `to`. `last` is the point `b` took in last
/// (the end of the move before, when it was one of these): a move that starts there, as
/// nearly every move does, adds only its end. Taking in a point again changes nothing (`min`
/// and `max` of a value and itself, to the bit), so the bounds are the same either way.
#[inline]
fn grow_move(b: &mut Option<Bounds>, last: &mut Option<Point>, from: Point, to: Point) {
    match (b.as_mut(), *last) {
        (Some(bounds), Some(l)) if l.map(f64::to_bits) == from.map(f64::to_bits) => {
            bounds.include(to)
        }
        _ => grow(b, from, to),
    }
    *last = Some(to);
}

/// How a program's path depends on where its probes trip: the program run as
/// if every probe found no contact (the assumption [`analyse`] makes) and as
/// if every probe touched at once, side by side.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct ProbeSpread {
    /// Moves whose end point differs between the two cases.
    pub dependent_moves: u64,
    pub first_dependent_line: Option<u32>,
    /// Bounds of the contact-at-once case, to merge with the analysis's.
    pub cutting_bounds: Option<Bounds>,
    pub rapid_bounds: Option<Bounds>,
    /// Where the two cases stopped following the same lines (a loop or
    /// branch on the result, or an error only one case meets).
    pub unchecked_from_line: Option<u32>,
}

impl Analysis {
    /// Takes in what [`probe_spread`] found: the bounds become those of both
    /// cases (the worst case the machine's travel is checked against).
    pub fn merge_probe_spread(&mut self, s: &ProbeSpread) {
        self.probe_dependent_moves = s.dependent_moves;
        self.first_probe_dependent_line = s.first_dependent_line;
        self.probe_paths_unchecked_from = s.unchecked_from_line;
        for (mine, theirs) in [
            (&mut self.cutting_bounds, s.cutting_bounds),
            (&mut self.rapid_bounds, s.rapid_bounds),
        ] {
            if let Some(b) = theirs {
                grow(mine, b.min, b.max);
            }
        }
    }
}

/// Runs the program twice in step, from two readers of the same text: with
/// every probe taken to find no contact, and with every probe taken to touch
/// at its start ([`crate::ProbeAssumption`]), and compares their moves. The
/// two cases are the ends of what each probe can return, so a move whose end
/// depends linearly on a result lies between them. Stops where the two stop
/// following the same lines (a loop on #5070 does), saying where. Bounded by
/// the same work budget as [`analyse`], per case.
pub fn probe_spread<R1: BufRead, R2: BufRead>(
    no_contact: R1,
    contact: R2,
    opts: &AnalysisOptions,
) -> ProbeSpread {
    let with = |assumption| Config {
        probe_assumption: assumption,
        ..opts.config.clone()
    };
    let mut a = Interpreter::new(no_contact, with(crate::ProbeAssumption::NoContact));
    let mut b = Interpreter::new(contact, with(crate::ProbeAssumption::ContactAtStart));
    let mut budget_a = WorkBudget::new(opts.max_segments, opts.config.arc_tolerance_mm);
    let mut budget_b = WorkBudget::new(opts.max_segments, opts.config.arc_tolerance_mm);
    let mut s = ProbeSpread::default();
    loop {
        let (ma, mb) = match (a.next(), b.next()) {
            (None, None) => break,
            (Some(Ok(ma)), Some(Ok(mb)))
                if ma.line() == mb.line()
                    && std::mem::discriminant(&ma) == std::mem::discriminant(&mb)
                    && budget_a.charge(&ma).is_ok()
                    && budget_b.charge(&mb).is_ok() =>
            {
                (ma, mb)
            }
            (ma, mb) => {
                let line = |m: Option<Result<Motion, GcodeError>>| match m {
                    Some(Ok(m)) => Some(m.line()),
                    Some(Err(e)) => Some(e.line),
                    None => None,
                };
                s.unchecked_from_line = match (line(ma), line(mb)) {
                    (Some(x), Some(y)) => Some(x.min(y)),
                    (x, y) => x.or(y),
                };
                break;
            }
        };
        if ma.end_point() != mb.end_point() {
            s.dependent_moves += 1;
            s.first_dependent_line.get_or_insert(mb.line());
        }
        match mb {
            Motion::Rapid { from, to, .. } => grow(&mut s.rapid_bounds, from, to),
            Motion::Linear { from, to, .. } | Motion::Probe { from, to, .. } => {
                grow(&mut s.cutting_bounds, from, to)
            }
            Motion::Arc { .. } => {
                if let Some(g) = ArcGeometry::from_motion(&mb) {
                    let (lo, hi) = g.bounds();
                    grow(&mut s.cutting_bounds, lo, hi);
                }
            }
            _ => {}
        }
    }
    s
}

/// Interprets the whole program and summarises it; the first error stops it.
pub fn analyse<R: BufRead>(reader: R, opts: &AnalysisOptions) -> Result<Analysis, GcodeError> {
    let mut it = Interpreter::new(reader, opts.config.clone());
    let mut a = Analysis {
        lines: 0,
        motion_lines: 0,
        cutting_bounds: None,
        rapid_bounds: None,
        cutting_length_mm: 0.0,
        rapid_length_mm: 0.0,
        estimated_seconds: 0.0,
        time_table: TimeTable::default(),
        warnings: Vec::new(),
        warnings_dropped: 0,
        units_inch_seen: false,
        rapid_moves: 0,
        linear_moves: 0,
        arc_moves: 0,
        dwell_seconds: 0.0,
        tools: Vec::new(),
        first_tool_change_line: None,
        max_feed_mm_min: 0.0,
        max_spindle_rpm: 0.0,
        program_end: false,
        offset_changes: Vec::new(),
        offset_change_count: 0,
        a_bounds: None,
        first_a_line: None,
        probe_moves: 0,
        first_probe_line: None,
        probe_dependent_moves: 0,
        first_probe_dependent_line: None,
        probe_paths_unchecked_from: None,
        segments: 0,
    };
    let mut budget = WorkBudget::new(opts.max_segments, opts.config.arc_tolerance_mm);
    let rapid_rate = if opts.rapid_mm_min > 0.0 {
        opts.rapid_mm_min
    } else {
        5000.0
    };
    let mut last_motion_line = 0u32;
    // Work systems that moves happened in (bit 0 = G54), to warn once where
    // the bounds start mixing frames.
    let mut active_system = 1u8;
    let mut moved_in = 0u16;
    let mut mixed_at = None;
    let mut estimator = Estimator::new(opts.profile.unwrap_or(MotionProfile {
        rapid_mm_min: rapid_rate,
        ..MotionProfile::default()
    }));
    // The last point the rapid and the cutting bounds took in (see `grow_move`).
    let mut rapid_last: Option<Point> = None;
    let mut cut_last: Option<Point> = None;
    it.for_each_motion(|m: &Motion| -> Result<(), GcodeError> {
        budget.charge(m)?;
        // A straight move's length, measured once for the estimate and the path length.
        let (is_move, len) = match *m {
            Motion::Rapid { from, to, .. }
            | Motion::Linear { from, to, .. }
            | Motion::Probe { from, to, .. } => (true, dist(from, to)),
            Motion::Arc { .. } => (true, 0.0),
            _ => (false, 0.0),
        };
        estimator.push_straight_len(m, len);
        let line = m.line();
        if is_move {
            if line != last_motion_line {
                a.motion_lines += 1;
                last_motion_line = line;
            }
            moved_in |= 1 << (active_system - 1);
            if mixed_at.is_none() && moved_in.count_ones() > 1 {
                mixed_at = Some((line, active_system));
            }
        }
        if let Motion::WorkOffset { system, .. } = *m {
            active_system = system;
        }
        if let Some(r) = m.rotary() {
            a.first_a_line.get_or_insert(line);
            let (lo, hi) = (r.from.min(r.to), r.from.max(r.to));
            let b = a.a_bounds.get_or_insert(RotaryBounds { min: lo, max: hi });
            b.min = b.min.min(lo);
            b.max = b.max.max(hi);
        }
        match *m {
            Motion::Rapid { from, to, .. } => {
                a.rapid_moves += 1;
                a.rapid_length_mm += len;
                grow_move(&mut a.rapid_bounds, &mut rapid_last, from, to);
            }
            Motion::Linear {
                from,
                to,
                feed_mm_min,
                ..
            } => {
                a.linear_moves += 1;
                a.cutting_length_mm += len;
                a.max_feed_mm_min = a.max_feed_mm_min.max(feed_mm_min);
                grow_move(&mut a.cutting_bounds, &mut cut_last, from, to);
            }
            Motion::Arc { feed_mm_min, .. } => {
                a.arc_moves += 1;
                if let Some(g) = ArcGeometry::from_motion(m) {
                    let d = g.length();
                    a.cutting_length_mm += d;
                    let (lo, hi) = g.bounds();
                    grow(&mut a.cutting_bounds, lo, hi);
                    cut_last = None;
                }
                a.max_feed_mm_min = a.max_feed_mm_min.max(feed_mm_min);
            }
            Motion::Probe { line, from, to, .. } => {
                a.probe_moves += 1;
                a.first_probe_line.get_or_insert(line);
                grow_move(&mut a.cutting_bounds, &mut cut_last, from, to);
            }
            Motion::Dwell { seconds, .. } => a.dwell_seconds += seconds,
            Motion::Spindle { rpm, direction, .. } if direction != SpindleDirection::Off => {
                a.max_spindle_rpm = a.max_spindle_rpm.max(rpm);
            }
            Motion::ToolChange { tool, line } => {
                a.first_tool_change_line.get_or_insert(line);
                if !a.tools.contains(&tool) && a.tools.len() < 1000 {
                    a.tools.push(tool);
                }
            }
            Motion::ProgramEnd { .. } => a.program_end = true,
            Motion::WorkOffsetChange {
                line,
                l,
                system,
                origin,
            } => {
                a.offset_change_count += 1;
                if a.offset_changes.len() < 100 {
                    a.offset_changes.push(OffsetChangeNote {
                        line,
                        command: format!("G10 L{l} P{system}"),
                        offset: origin,
                        offset_a: 0.0,
                    });
                }
            }
            Motion::OffsetChange {
                line,
                code,
                offset,
                offset_a,
            } => {
                a.offset_change_count += 1;
                if a.offset_changes.len() < 100 {
                    a.offset_changes.push(OffsetChangeNote {
                        line,
                        command: if code % 10 == 0 {
                            format!("G{}", code / 10)
                        } else {
                            format!("G{}.{}", code / 10, code % 10)
                        },
                        offset,
                        offset_a,
                    });
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    a.time_table = estimator.finish();
    a.estimated_seconds = a.time_table.total();
    a.segments = budget.used();
    a.lines = it.lines_read();
    a.units_inch_seen = it.units_inch_seen();
    a.warnings = it.warnings().to_vec();
    a.warnings_dropped = it.warnings_dropped();
    if let Some((line, system)) = mixed_at {
        a.warnings.push(Warning {
            line,
            column: 1,
            message: format!(
                "moves in more than one work coordinate system (here {}); bounds and lengths mix their frames",
                system_name(system)
            ),
        });
    }
    Ok(a)
}

fn system_name(system: u8) -> String {
    match system {
        1..=6 => format!("G{}", 53 + system),
        _ => format!("G59.{}", system - 6),
    }
}
