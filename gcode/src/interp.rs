//! The modal interpreter: lines -> canonical [`Motion`]s.
//!
//! Per line: lex into a fixed [`Block`], check every word against the modal
//! groups on a copy of the state, emit events in LinuxCNC's order of
//! execution, and commit the state only if the whole line was valid (so a
//! skipped line leaves no trace). No allocation per line except for messages.

use crate::arc::len2;
use crate::comp::{Comp, CompError, Side};
use crate::expr::{self, Params, SysView, SUB_PARAMS};
use crate::flow::{self, BlockKind, Flow, Frame, Keyword, OpenBlock, PendingCall, Skip};
use crate::lex::{
    bit, column, lex_line, make_error, Block, LexError, LineKind, POLAR_A, POLAR_MASK, POLAR_R,
};
use crate::{
    Config, ErrorKind, GcodeError, Motion, Plane, Point, RotaryMove, SpindleDirection, Unsupported,
    Warning, MAX_BLOCK_NESTING, MAX_COORDINATE_MM, MAX_DWELL_SECONDS, MAX_FEED, MAX_HELD_EVENTS,
    MAX_SPINDLE_RPM,
};
use serde::Serialize;
use std::f64::consts::TAU;
use std::io::BufRead;

mod start;
pub use start::{ModalState, StartError, StartRefusal, StartRefusalReason, WorkOffsetSet};

const MM_PER_INCH: f64 = 25.4;
/// Most turns accepted for one arc (P word): bounds the chords one line can
/// produce (thread milling uses tens).
const MAX_TURNS: f64 = 10_000.0;
/// Start and end closer than this (mm, in the plane) make an IJK arc a full circle.
const FULL_CIRCLE_EPS_MM: f64 = 1e-6;

/// Events of one line. An ordinary line yields at most 12 (message, debug
/// message, M6, spindle, coolant, dwell, G43/G49, work system, two G28 legs,
/// motion, stop); a fixed ring keeps push/pop inlined and allocation-free.
/// A canned cycle with pecks or L repeats makes more: those go to `overflow`
/// (allocated only then), behind the ring's events.
struct Queue {
    items: [Option<Motion>; QUEUE_CAP],
    head: usize,
    len: usize,
    overflow: std::collections::VecDeque<Motion>,
}

const QUEUE_CAP: usize = 16;

impl Queue {
    fn new() -> Self {
        Queue {
            items: Default::default(),
            head: 0,
            len: 0,
            overflow: std::collections::VecDeque::new(),
        }
    }
    /// Pushes happen only while a line runs, and a line starts with an
    /// empty queue: the ring is full before anything goes to `overflow`.
    #[inline]
    fn push_back(&mut self, m: Motion) {
        self.push_back_inlined(m);
    }
    /// [`Queue::push_back`], always inlined: for the plain move's one push per line (see
    /// [`Interpreter::execute_plain_move`]), where the motion is then built in its slot
    /// instead of on the stack and copied there by a call.
    #[inline(always)]
    fn push_back_inlined(&mut self, m: Motion) {
        if self.len < QUEUE_CAP {
            self.items[(self.head + self.len) % QUEUE_CAP] = Some(m);
            self.len += 1;
        } else {
            self.overflow.push_back(m);
        }
    }
    #[inline]
    fn pop_front(&mut self) -> Option<Motion> {
        if self.len == 0 {
            return self.pop_overflow();
        }
        let m = self.items[self.head].take();
        self.head = (self.head + 1) % QUEUE_CAP;
        self.len -= 1;
        m
    }
    /// The first event waiting, where it waits (see [`Interpreter::for_each_motion`]).
    #[inline]
    fn front(&self) -> Option<&Motion> {
        if self.len == 0 {
            return self.overflow.front();
        }
        self.items[self.head].as_ref()
    }
    /// Drops the first event waiting, once [`Queue::front`] has been looked at.
    #[inline]
    fn drop_front(&mut self) {
        if self.len == 0 {
            self.overflow.pop_front();
            return;
        }
        self.items[self.head] = None;
        self.head = (self.head + 1) % QUEUE_CAP;
        self.len -= 1;
    }
    #[inline(never)]
    fn pop_overflow(&mut self) -> Option<Motion> {
        self.overflow.pop_front()
    }
    /// Events waiting, in order.
    fn iter(&self) -> impl Iterator<Item = &Motion> {
        (0..self.len)
            .filter_map(|i| self.items[(self.head + i) % QUEUE_CAP].as_ref())
            .chain(self.overflow.iter())
    }
    /// Events waiting.
    #[inline]
    fn count(&self) -> usize {
        self.len + self.overflow.len()
    }
    /// Sets the XY start of the first move after the first `skip` events
    /// (the first move of a line after G40).
    #[cold]
    fn patch_first_move_from(&mut self, skip: usize, xy: [f64; 2]) {
        let ring = (skip.min(self.len)..self.len).map(|i| (self.head + i) % QUEUE_CAP);
        let mut found = None;
        for i in ring {
            if self.items[i]
                .as_ref()
                .is_some_and(|m| m.end_point().is_some())
            {
                found = Some(i);
                break;
            }
        }
        let m = match found {
            Some(i) => self.items[i].as_mut(),
            None => self
                .overflow
                .iter_mut()
                .skip(skip.saturating_sub(self.len))
                .find(|m| m.end_point().is_some()),
        };
        if let Some(
            Motion::Rapid { from, .. } | Motion::Linear { from, .. } | Motion::Arc { from, .. },
        ) = m
        {
            from[0] = xy[0];
            from[1] = xy[1];
        }
    }
    #[cold]
    fn shift_all(&mut self, off: Point, off_a: f64) {
        for m in self.items.iter_mut().flatten() {
            shift(m, off, off_a);
        }
        for m in self.overflow.iter_mut() {
            shift(m, off, off_a);
        }
    }
    fn clear(&mut self) {
        while self.len > 0 {
            self.pop_front();
        }
        self.overflow.clear();
        self.head = 0;
    }
}

/// The feed mode (G93/G94/G95): what an F word means.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum FeedMode {
    /// G94: units per minute.
    PerMinute,
    /// G93: 1/minutes, on every feed line.
    InverseTime,
    /// G95: units per spindle revolution.
    PerRevolution,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MotionMode {
    /// G80, or nothing programmed yet: axis words are an error.
    None,
    Rapid,
    Linear,
    Cw,
    Ccw,
    /// A motion-group code we do not implement (canned cycles, probing,
    /// threading), as code * 10: later axis words are rejected, not guessed.
    Unsupported(u16),
    /// Canned cycle G73, G81, G82, G83, G85, G89 (code * 10).
    Cycle(u16),
    /// G38.2..G38.5 (code * 10: 382..385), or Mach3's G31 (310).
    Probe(u16),
    /// G5 (cubic, 50) or G5.1 (quadratic, 51) spline in the XY plane.
    Spline(u16),
}

/// Sticky values of canned cycles (LinuxCNC `cycle_*`), mm / seconds.
#[derive(Debug, Clone, Copy, Default)]
struct CycleState {
    /// R and Z as last given (absolute in G90, increments in G91).
    r: f64,
    z: f64,
    q: f64,
    p: f64,
    /// Initial level: Z where the current series of cycles began.
    initial: Option<f64>,
    /// G99: retract to R (else G98: to the initial level).
    retract_to_r: bool,
}

#[derive(Debug, Clone, Copy)]
struct State {
    pos: Point,
    /// A axis, degrees, program coordinates.
    a: f64,
    motion: MotionMode,
    plane: Plane,
    inch: bool,
    absolute: bool,
    arc_absolute: bool,
    /// Last F word in mm/min, converted with the units of its own line: a
    /// later G20/G21 keeps the physical feed (grbl; LinuxCNC rescales it).
    feed: Option<f64>,
    /// G94 (units per minute), G93 (inverse time: F is 1/minutes, on every
    /// feed line), G95 (units per spindle revolution).
    feed_mode: FeedMode,
    rpm: f64,
    spindle: SpindleDirection,
    mist: bool,
    flood: bool,
    tool: u32,
    /// The tool in the spindle (M6, M61): G41/G42 without D use its radius.
    spindle_tool: u32,
    /// G43 H (the tool whose length is applied), `None` after G49 and at the start.
    tlo: Option<u32>,
    /// 0..9 for G54..G59.3.
    coord: u8,
    g28: Point,
    g30: Point,
    /// A of the G28 / G30 stored positions (degrees, work frame).
    g28_a: f64,
    g30_a: f64,
}

impl State {
    fn new(cfg: &Config) -> Self {
        State {
            pos: cfg.initial_position,
            a: cfg.initial_a_deg,
            motion: MotionMode::None,
            plane: Plane::XY,
            inch: false,
            absolute: true,
            arc_absolute: false,
            feed: None,
            feed_mode: FeedMode::PerMinute,
            rpm: 0.0,
            spindle: SpindleDirection::Off,
            mist: false,
            flood: false,
            tool: 0,
            spindle_tool: 0,
            tlo: None,
            coord: 0,
            g28: cfg.g28_position,
            g30: cfg.g30_position,
            g28_a: 0.0,
            g30_a: 0.0,
        }
    }
}

/// Streams [`Motion`]s from any [`BufRead`] (no whole-file buffering; one
/// line at a time, bounded by [`Config::max_line_bytes`]).
///
/// Iterating yields `Ok(Motion)` in program order; the first error is
/// yielded once and then the iterator ends. In-memory text:
/// `Interpreter::new(text.as_bytes(), Config::default())`.
pub struct Interpreter<R: BufRead> {
    reader: R,
    cfg: Config,
    line: Vec<u8>,
    line_no: u32,
    /// Source lines taken from the reader (line numbers of new lines).
    reader_line_no: u32,
    lines_read: u64,
    lines_executed: u64,
    linuxcnc_only: Option<u32>,
    /// First line that turned cutter compensation on (G41/G42/G41.1/G42.1).
    cutter_comp_line: Option<u32>,
    /// First G10 line (tool table or work offsets written by the program).
    g10_line: Option<u32>,
    // Kept out of `State`, which is copied twice per line: these change only
    // on cycle and G92 lines, which write them back when the line succeeded.
    cycle: CycleState,
    /// G92 / G52 offset in effect (mm): work-system frame = program + g92.
    g92: Point,
    /// The stored G92 values (#5211..), which G92.2 keeps and G92.3 restores.
    g92_saved: Point,
    /// The same for the A axis (degrees).
    g92_a: f64,
    g92_saved_a: f64,
    g92_active: bool,
    /// P and Q of the last G5 (end control point, relative to its end), for
    /// a following G5 without I and J.
    spline_pq: Option<(f64, f64)>,
    /// G10 L2/L20 changed a work offset (`params.work_offsets` is then the
    /// program's view, `cfg.work_offsets` still the machine's).
    offsets_changed: bool,
    /// M70's saved modal state; M73's, per call depth, restored on return.
    saved_modal: Option<State>,
    auto_restore: Vec<(usize, State)>,
    /// Cutter radius compensation (G41/G42) and the moves it holds back.
    comp: Comp,
    params: Params,
    flow: Flow,
    blk: Block,
    st: State,
    queue: Queue,
    warnings: Vec<Warning>,
    warnings_dropped: u64,
    done: bool,
    words_seen: bool,
    percent_open: bool,
    units_inch_seen: bool,
    work_systems: u16,
    /// A probing move was yielded; its result is applied before the next
    /// line is read (see [`Interpreter::probe_result`]).
    probe_pending: Option<PendingProbe>,
    /// [`Interpreter::state_at`] in progress: the line it stops before.
    start_at: Option<start::StartAt>,
    /// The line in `self.line` runs again instead of reading the next one (the line
    /// [`Interpreter::state_at`] stopped before).
    replay: bool,
    /// The line that turned on the cutter compensation in force.
    comp_since: Option<u32>,
    /// The last canned-cycle line with an L (repeats) word above 1, and its L.
    cycle_repeats: Option<(u32, f64)>,
}

/// A probing move whose result the rest of the program waits for.
#[derive(Debug, Clone, Copy)]
struct PendingProbe {
    from: Point,
    to: Point,
    /// The program's frame when it was made (motion frame = program + this).
    frame: Point,
    inch: bool,
    /// Mach3's G31: the trip also goes to #2000..#2002, where Mach3 programs read it.
    mach3: bool,
    result: Option<crate::ProbeResult>,
}

impl<R: BufRead> Interpreter<R> {
    /// A new interpreter at `config.initial_position`, in G17 G21 G90 G91.1 G94 G54 G80.
    pub fn new(reader: R, config: Config) -> Self {
        Interpreter {
            reader,
            st: State::new(&config),
            params: Params::new(config.work_offsets),
            flow: Flow::default(),
            reader_line_no: 0,
            lines_executed: 0,
            linuxcnc_only: None,
            cutter_comp_line: None,
            g10_line: None,
            // LinuxCNC's interpreter starts in G99 (retract to R).
            cycle: CycleState {
                retract_to_r: true,
                ..CycleState::default()
            },
            g92: [0.0; 3],
            g92_saved: [0.0; 3],
            g92_a: 0.0,
            g92_saved_a: 0.0,
            g92_active: false,
            spline_pq: None,
            offsets_changed: false,
            saved_modal: None,
            auto_restore: Vec::new(),
            comp: Comp::default(),
            cfg: config,
            line: Vec::with_capacity(256),
            line_no: 0,
            lines_read: 0,
            blk: Block::new(),
            queue: Queue::new(),
            warnings: Vec::new(),
            warnings_dropped: 0,
            done: false,
            words_seen: false,
            percent_open: false,
            units_inch_seen: false,
            work_systems: 0,
            probe_pending: None,
            start_at: None,
            replay: false,
            comp_since: None,
            cycle_repeats: None,
        }
    }

    /// What the probing move just yielded ([`Motion::Probe`]) found, from the
    /// backend that executed it; call before asking for the next motion. The
    /// tool's position becomes `rest`, #5061..#5063 the trip (program
    /// coordinates, program units) and #5070 1 (tripped) or 0.
    pub fn probe_result(&mut self, result: crate::ProbeResult) {
        if let Some(p) = self.probe_pending.as_mut() {
            p.result = Some(result);
        }
    }

    /// Applies the pending probe's result (or the stand-alone assumption).
    fn settle_probe(&mut self) {
        // Tested before `take`: taking moves the whole pending probe out and back for every
        // line, probing or not.
        if self.probe_pending.is_none() {
            return;
        }
        let Some(p) = self.probe_pending.take() else {
            return;
        };
        let assumption = self.cfg.probe_assumption;
        let r = p.result.unwrap_or_else(|| {
            if assumption == crate::ProbeAssumption::ContactAtStart {
                return crate::ProbeResult {
                    tripped: true,
                    trip: p.from,
                    rest: p.from,
                };
            }
            // LinuxCNC's stand-alone interpreter: no contact, and the tool
            // backed off from the end toward the start by 0.254 mm (0.01 in).
            let d = sub(p.from, p.to);
            let len = len3(p.from, p.to);
            // 0.01 in in an inch program, 0.254 mm in a metric one: the same.
            let back = 0.254;
            let rest = if len > 0.0 {
                std::array::from_fn(|i| p.to[i] + back * d[i] / len)
            } else {
                p.to
            };
            crate::ProbeResult {
                tripped: false,
                trip: p.to,
                rest,
            }
        });
        let unit = Self::scale(p.inch);
        let trip = sub(r.trip, p.frame);
        self.st.pos = sub(r.rest, p.frame);
        let trip = [trip[0] / unit, trip[1] / unit, trip[2] / unit];
        self.params.set_probe(trip, r.tripped);
        if p.mach3 {
            self.params.set_mach3_probe(trip);
        }
    }

    /// Lines skipped under [`Unsupported::SkipWithWarning`] and other notes
    /// (at most [`Config::max_warnings`]).
    pub fn warnings(&self) -> &[Warning] {
        &self.warnings
    }
    /// Warnings not kept because of [`Config::max_warnings`].
    pub fn warnings_dropped(&self) -> u64 {
        self.warnings_dropped
    }
    /// Source lines read so far.
    pub fn lines_read(&self) -> u64 {
        self.lines_read
    }
    /// First line that used LinuxCNC-only syntax: O-word control flow
    /// (`o<name> sub`, `if`, `while`, ...), named parameters (`#<x>`),
    /// `(debug,...)` / `(print,...)` or G38.x probing (Mach3 probes with G31). A backend that hands the program text
    /// to a controller with another dialect (Mach3) refuses it naming this line.
    pub fn linuxcnc_only_line(&self) -> Option<u32> {
        self.linuxcnc_only
    }
    /// First line that turned cutter radius compensation on (G41/G42,
    /// G41.1/G42.1). A backend whose controller compensates with its own tool
    /// table (Mach3) refuses the program naming this line.
    pub fn cutter_comp_line(&self) -> Option<u32> {
        self.cutter_comp_line
    }
    /// First G10 line (L1 tool table, L2/L20 work offsets). Fresa folds
    /// them into the motions; a backend whose controller would execute the
    /// text itself, and keep the change (Mach3), refuses the program naming it.
    pub fn g10_line(&self) -> Option<u32> {
        self.g10_line
    }
    /// Lines run (or passed over) so far: like [`Self::lines_read`], but a
    /// loop body or subroutine counts every time it runs.
    pub fn lines_executed(&self) -> u64 {
        self.lines_executed
    }
    /// Whether G20 (inch) was ever in effect.
    pub fn units_inch_seen(&self) -> bool {
        self.units_inch_seen
    }
    /// Bit i set if work system i (0 = G54 ... 8 = G59.3) was selected; G54 is always set.
    pub fn work_systems_used(&self) -> u16 {
        self.work_systems | 1
    }
    /// Position (program coordinates, mm) after the last line interpreted;
    /// motions of that line may still be waiting to be yielded.
    pub fn position(&self) -> Point {
        add(self.st.pos, self.frame())
    }

    /// From program coordinates to the frame motions are given in (the
    /// active work system with the machine's own offsets): G92/G52 plus what
    /// G10 L2/L20 changed in the active system's origin.
    #[inline]
    fn frame(&self) -> Point {
        if !self.offsets_changed {
            return self.g92;
        }
        let c = self.st.coord as usize;
        add(
            self.g92,
            sub(self.params.work_offsets[c], self.cfg.work_offsets[c]),
        )
    }
    /// A axis position (program coordinates, degrees), like [`Self::position`].
    pub fn position_a(&self) -> f64 {
        self.st.a + self.g92_a
    }
    /// The configuration in use.
    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// This interpreter's motions with arcs linearised at
    /// [`Config::arc_tolerance_mm`].
    pub fn linearised(self) -> crate::Linearise<Self> {
        let tol = self.cfg.arc_tolerance_mm;
        crate::linearise(self, tol)
    }

    fn warn(&mut self, w: Warning) {
        if self.warnings.len() < self.cfg.max_warnings {
            self.warnings.push(w);
        } else {
            self.warnings_dropped += 1;
        }
    }

    /// Reads the next line into `self.line` (without "\n" / "\r\n").
    /// Returns Ok(false) at end of input.
    #[inline(always)]
    fn read_line(&mut self) -> Result<bool, GcodeError> {
        self.line.clear();
        let mut any = false;
        // Whether the text taken is ASCII, tested in the reader's buffer as it is taken: the
        // line just copied, read back in 8-byte words, stalled the processor (loads that
        // straddle the copy's stores cannot be forwarded from them).
        let mut ascii = true;
        loop {
            let buf = match self.reader.fill_buf() {
                Ok(b) => b,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    return Err(GcodeError {
                        line: self.reader_line_no.saturating_add(1),
                        column: column(&self.line, self.line.len()),
                        kind: ErrorKind::Io,
                        message: format!("read error: {e}"),
                    })
                }
            };
            if buf.is_empty() {
                break;
            }
            any = true;
            if let Some(i) = memchr::memchr(b'\n', buf) {
                ascii &= buf[..i].is_ascii();
                self.line.extend_from_slice(&buf[..i]);
                self.reader.consume(i + 1);
                break;
            }
            let n = buf.len();
            ascii &= buf.is_ascii();
            self.line.extend_from_slice(buf);
            self.reader.consume(n);
            if self.line.len() > self.cfg.max_line_bytes {
                return Err(GcodeError {
                    line: self.reader_line_no.saturating_add(1),
                    column: 1,
                    kind: ErrorKind::Io,
                    message: format!("line longer than {} bytes", self.cfg.max_line_bytes),
                });
            }
        }
        if !any {
            return Ok(false);
        }
        self.reader_line_no = self.reader_line_no.saturating_add(1);
        self.line_no = self.reader_line_no;
        self.lines_read += 1;
        if self.line.len() > self.cfg.max_line_bytes {
            return Err(GcodeError {
                line: self.line_no,
                column: 1,
                kind: ErrorKind::Io,
                message: format!("line longer than {} bytes", self.cfg.max_line_bytes),
            });
        }
        if self.line.last() == Some(&b'\r') {
            self.line.pop();
        }
        // A UTF-8 byte order mark (Windows editors) is not part of the program.
        if self.line_no == 1 && self.line.starts_with(b"\xEF\xBB\xBF") {
            self.line.drain(..3);
        }
        if !ascii {
            if let Err(e) = std::str::from_utf8(&self.line) {
                return Err(GcodeError {
                    line: self.line_no,
                    column: column(&self.line, e.valid_up_to()),
                    kind: ErrorKind::Utf8,
                    message: "invalid UTF-8".to_string(),
                });
            }
        }
        Ok(true)
    }

    /// The next line to run into `self.line`: from the kept program text
    /// when control flow went back, else from the reader (kept once an O-word
    /// was seen). Ok(false) at the end of input.
    #[inline]
    fn next_line(&mut self) -> Result<bool, GcodeError> {
        if self.replay {
            self.replay = false;
            return Ok(true);
        }
        if !self.flow.buffering {
            return self.read_line();
        }
        if self.flow.pc < self.flow.prog.lines.len() {
            let (no, s, e) = self.flow.prog.lines[self.flow.pc];
            self.line.clear();
            self.line.extend_from_slice(&self.flow.prog.text[s..e]);
            self.line_no = no;
            self.flow.cur = self.flow.pc;
            self.flow.pc += 1;
            return Ok(true);
        }
        if !self.read_line()? {
            return Ok(false);
        }
        self.keep_line()?;
        Ok(true)
    }

    /// Keeps the current (just read) line for later jumps, within
    /// `Config::max_kept_program_bytes`.
    fn keep_line(&mut self) -> Result<(), GcodeError> {
        if self.flow.prog.text.len() + self.line.len() > self.cfg.max_kept_program_bytes {
            return Err(GcodeError {
                line: self.line_no,
                column: 1,
                kind: ErrorKind::Io,
                message: format!(
                    "a program with O-words or M98 is kept in memory, and this one is longer than {} bytes (Config::max_kept_program_bytes)",
                    self.cfg.max_kept_program_bytes
                ),
            });
        }
        let f = &mut self.flow;
        f.buffering = true;
        let s = f.prog.text.len();
        f.prog.text.extend_from_slice(&self.line);
        f.prog.lines.push((self.line_no, s, f.prog.text.len()));
        f.cur = f.prog.lines.len() - 1;
        f.pc = f.prog.lines.len();
        Ok(())
    }

    #[cold]
    fn note_linuxcnc_only(&mut self) {
        self.params.named_used = false;
        if self.linuxcnc_only.is_none() {
            self.linuxcnc_only = Some(self.line_no);
        }
    }

    fn err_at(&self, e: LexError) -> GcodeError {
        make_error(self.line_no, &self.line, e)
    }

    /// Moves cutter compensation still holds end where they are, at the end of the program
    /// or of the input, before the program's end.
    fn release_held(&mut self) -> Result<(), GcodeError> {
        if self.comp.held.is_empty() {
            return Ok(());
        }
        let mut out = Vec::new();
        self.comp.release(&mut out);
        let frame = self.frame();
        for mut m in out {
            shift(&mut m, frame, self.g92_a);
            // Checked like every line's events (the line's own check saw them held).
            if let Err((_, kind, message)) = check_motion_reach(&m, &Block::new()) {
                return Err(GcodeError {
                    line: m.line(),
                    column: 1,
                    kind,
                    message,
                });
            }
            self.queue.push_back(m);
        }
        Ok(())
    }

    /// End of input: fine unless a skip, call or block is still open.
    fn end_of_input(&mut self) -> Result<(), GcodeError> {
        self.done = true;
        self.release_held()?;
        let open = if let Some(skip) = &self.flow.skip {
            Some(format!(
                "file ended while looking for o<{}> {} (from line {})",
                skip.name,
                skip.until.first().map_or("", |k| k.name()),
                skip.from_line
            ))
        } else if let Some(f) = self.flow.frames.last() {
            Some(format!(
                "file ended inside subroutine o<{}> (called on line {})",
                f.name, f.call_line
            ))
        } else {
            self.flow.blocks.last().map(|b| {
                let line = self.flow.prog.lines.get(b.start).map_or(0, |l| l.0);
                format!(
                    "file ended inside o<{}> {} (line {line})",
                    b.name,
                    b.kind.keyword()
                )
            })
        };
        match open {
            Some(message) => Err(GcodeError {
                line: self.reader_line_no,
                column: 1,
                kind: ErrorKind::Invalid,
                message,
            }),
            None => Ok(()),
        }
    }

    /// A line passed over while skipping (false condition, a subroutine's
    /// definition, a search for a subroutine further down).
    fn skip_line(&mut self) -> Result<(), GcodeError> {
        let Some(at) = flow::o_at(&self.line) else {
            return Ok(());
        };
        // A malformed O-word in text that is not run is not an error here.
        let Ok(o) = flow::parse(&self.line, at) else {
            return Ok(());
        };
        if matches!(o.kw, Keyword::Sub | Keyword::Number) {
            self.flow
                .subs
                .entry(o.name.clone())
                .or_insert(self.flow.cur);
        }
        let Some(skip) = &self.flow.skip else {
            return Ok(());
        };
        if o.name != skip.name || !skip.until.contains(&o.kw) {
            return Ok(());
        }
        let Some(skip) = self.flow.skip.take() else {
            return Ok(());
        };
        if let Some(call) = skip.then_call {
            return self.enter(o.name, self.flow.cur, call);
        }
        if !skip.inclusive {
            // Run the matching line (else, elseif, endif) next.
            self.flow.pc = self.flow.cur;
        }
        Ok(())
    }

    fn skip_to(&mut self, name: String, until: &'static [Keyword], inclusive: bool) {
        self.flow.skip = Some(Skip {
            name,
            until,
            inclusive,
            then_call: None,
            from_line: self.line_no,
        });
    }

    /// Goes back to line index `idx` (a loop pass or an M98 repeat), counted
    /// against `Config::max_loop_iterations`.
    fn jump_back(&mut self, idx: usize) -> Result<(), GcodeError> {
        self.count_pass(0)?;
        self.flow.pc = idx;
        Ok(())
    }

    /// One more loop pass or subroutine call (the O-word at `at`), at most
    /// `Config::max_loop_iterations` in all: a call runs its body again as a pass does, and
    /// uncounted, nine levels of a thousand calls each (about 100 KB) multiply into 10^27 lines.
    fn count_pass(&mut self, at: usize) -> Result<(), GcodeError> {
        self.flow.jumps += 1;
        if self.flow.jumps > self.cfg.max_loop_iterations {
            return Err(self.err_at((
                at,
                ErrorKind::Invalid,
                format!(
                    "more than {} loop passes and subroutine calls (Config::max_loop_iterations)",
                    self.cfg.max_loop_iterations
                ),
            )));
        }
        Ok(())
    }

    /// Calls subroutine `name` (found now or by reading ahead).
    fn call(
        &mut self,
        name: String,
        args: [f64; SUB_PARAMS],
        m98_times: Option<u32>,
        at: usize,
    ) -> Result<(), GcodeError> {
        // The main program counts as a level, as in LinuxCNC.
        if self.flow.frames.len() + 1 >= self.cfg.max_call_depth {
            return Err(self.err_at((
                at,
                ErrorKind::Invalid,
                format!(
                    "subroutine calls nested deeper than {} (Config::max_call_depth)",
                    self.cfg.max_call_depth
                ),
            )));
        }
        self.count_pass(at)?;
        let call = PendingCall {
            args,
            return_to: self.flow.cur + 1,
            m98_times,
            call_line: self.line_no,
        };
        match self.flow.subs.get(&name) {
            Some(&idx) => self.enter(name, idx, call),
            None => {
                self.flow.skip = Some(Skip {
                    name,
                    until: if m98_times.is_some() {
                        &[Keyword::Number]
                    } else {
                        &[Keyword::Sub]
                    },
                    inclusive: true,
                    then_call: Some(call),
                    from_line: self.line_no,
                });
                Ok(())
            }
        }
    }

    fn enter(&mut self, name: String, idx: usize, call: PendingCall) -> Result<(), GcodeError> {
        let saved = self.params.sub_params();
        self.flow.frames.push(Frame {
            name,
            return_to: call.return_to,
            body: idx + 1,
            saved,
            blocks: std::mem::take(&mut self.flow.blocks),
            m98_left: call.m98_times.map(|n| n.saturating_sub(1)),
            call_line: call.call_line,
        });
        self.params.set_sub_params(&call.args);
        self.params.push_scope();
        self.flow.pc = idx + 1;
        Ok(())
    }

    fn ret(&mut self, value: Option<f64>) {
        let depth = self.flow.frames.len();
        if self.auto_restore.last().is_some_and(|a| a.0 == depth) {
            if let Some((_, saved)) = self.auto_restore.pop() {
                let mut st = self.st;
                restore_modal(
                    &self.params.work_offsets,
                    &mut self.queue,
                    &mut st,
                    &saved,
                    self.line_no,
                );
                self.st = st;
            }
        }
        if let Some(f) = self.flow.frames.pop() {
            self.params.set_sub_params(&f.saved);
            self.params.pop_scope();
            self.flow.blocks = f.blocks;
            self.flow.pc = f.return_to;
        }
        self.params.value = value.unwrap_or(0.0);
        self.params.value_returned = value.is_some();
    }

    /// Opens an O-word block, at most [`MAX_BLOCK_NESTING`] deep per call level.
    fn open_block(&mut self, at: usize, b: OpenBlock) -> Result<(), GcodeError> {
        if self.flow.blocks.len() >= MAX_BLOCK_NESTING {
            return Err(self.err_at((
                at,
                ErrorKind::Invalid,
                format!(
                    "o<{}> {}: O-word blocks nested deeper than the limit of {MAX_BLOCK_NESTING}",
                    b.name,
                    b.kind.keyword()
                ),
            )));
        }
        self.flow.blocks.push(b);
        Ok(())
    }

    /// Runs the O-word at `self.line[at]`.
    fn oword(&mut self, at: usize) -> Result<(), GcodeError> {
        if !self.flow.buffering {
            self.keep_line()?;
        }
        self.params.sys = sys_view(
            &self.st,
            self.g92,
            self.g92_saved,
            self.g92_a,
            self.g92_saved_a,
        );
        let o = flow::parse(&self.line, at).map_err(|e| self.err_at(e))?;
        let mut i = o.rest;
        let b = &self.line;
        let p = &mut self.params;
        let blanks = |i: &mut usize| {
            while *i < b.len() && (b[*i] == b' ' || b[*i] == b'\t') {
                *i += 1;
            }
        };
        // `[condition]` after if/elseif/while/repeat (and optional after return/endsub).
        let mut cond = |i: &mut usize, required: bool| -> Result<Option<f64>, LexError> {
            blanks(i);
            if b.get(*i) == Some(&b'[') {
                return expr::expression(b, i, p).map(Some);
            }
            if required {
                return Err((
                    *i,
                    ErrorKind::Syntax,
                    format!("o-word {} needs a [condition]", o.kw.name()),
                ));
            }
            Ok(None)
        };
        let value = match o.kw {
            Keyword::If | Keyword::ElseIf | Keyword::Repeat => cond(&mut i, true),
            Keyword::While => {
                // The `while` closing a `do` is evaluated like any other.
                cond(&mut i, true)
            }
            Keyword::Return | Keyword::EndSub => cond(&mut i, false),
            _ => Ok(None),
        };
        let value = value.map_err(|e| self.err_at(e))?;
        let mut args = [0.0; SUB_PARAMS];
        if o.kw == Keyword::Call {
            let b = &self.line;
            let mut n = 0;
            loop {
                while i < b.len() && (b[i] == b' ' || b[i] == b'\t') {
                    i += 1;
                }
                if b.get(i) != Some(&b'[') {
                    break;
                }
                if n == SUB_PARAMS {
                    return Err(self.err_at((
                        i,
                        ErrorKind::Invalid,
                        format!("more than {SUB_PARAMS} subroutine arguments"),
                    )));
                }
                args[n] = expr::expression(b, &mut i, &mut self.params)
                    .map_err(|e| make_error(self.line_no, &self.line, e))?;
                n += 1;
            }
        }
        rest_is_comment(&self.line, i).map_err(|e| self.err_at(e))?;
        let truth = value.is_some_and(|v| v != 0.0);
        let cur = self.flow.cur;
        let name = o.name;
        let top_is = |f: &Flow, kind: fn(BlockKind) -> bool, name: &str| {
            f.blocks
                .last()
                .is_some_and(|b| kind(b.kind) && b.name == name)
        };
        let mismatch = |what: &str| {
            (
                at,
                ErrorKind::Invalid,
                format!("o<{name}> {what} without a matching open block"),
            )
        };
        match o.kw {
            Keyword::Number => Ok(()),
            Keyword::Sub => {
                self.flow.subs.insert(name.clone(), cur);
                self.skip_to(name, &[Keyword::EndSub], true);
                Ok(())
            }
            Keyword::EndSub | Keyword::Return => {
                // `return` may carry any o-name (LinuxCNC's retval.ngc names
                // the enclosing if); `endsub` names its subroutine.
                let ok = self.flow.frames.last().is_some_and(|f| {
                    f.m98_left.is_none() && (o.kw == Keyword::Return || f.name == name)
                });
                if !ok {
                    return Err(self.err_at((
                        at,
                        ErrorKind::Invalid,
                        format!("o<{name}> {} outside subroutine o<{name}>", o.kw.name()),
                    )));
                }
                self.ret(value);
                Ok(())
            }
            Keyword::Call => self.call(name, args, None, at),
            Keyword::If => {
                self.open_block(
                    at,
                    OpenBlock {
                        name: name.clone(),
                        kind: BlockKind::If { taken: truth },
                        start: cur,
                        left: 0.0,
                    },
                )?;
                if !truth {
                    self.skip_to(
                        name,
                        &[Keyword::ElseIf, Keyword::Else, Keyword::EndIf],
                        false,
                    );
                }
                Ok(())
            }
            Keyword::ElseIf | Keyword::Else => {
                let Some(top) = self
                    .flow
                    .blocks
                    .last_mut()
                    .filter(|b| matches!(b.kind, BlockKind::If { .. }) && b.name == name)
                else {
                    return Err(self.err_at(mismatch(o.kw.name())));
                };
                if top.kind == (BlockKind::If { taken: true }) {
                    self.skip_to(name, &[Keyword::EndIf], false);
                } else if o.kw == Keyword::Else || truth {
                    top.kind = BlockKind::If { taken: true };
                } else {
                    self.skip_to(
                        name,
                        &[Keyword::ElseIf, Keyword::Else, Keyword::EndIf],
                        false,
                    );
                }
                Ok(())
            }
            Keyword::EndIf => {
                if !top_is(&self.flow, |k| matches!(k, BlockKind::If { .. }), &name) {
                    return Err(self.err_at(mismatch("endif")));
                }
                self.flow.blocks.pop();
                Ok(())
            }
            Keyword::Do => {
                self.open_block(
                    at,
                    OpenBlock {
                        name,
                        kind: BlockKind::Do,
                        start: cur,
                        left: 0.0,
                    },
                )?;
                Ok(())
            }
            Keyword::While => {
                if top_is(&self.flow, |k| k == BlockKind::Do, &name) {
                    let start = self.flow.blocks.last().map_or(cur, |b| b.start);
                    if truth {
                        return self.jump_back(start + 1);
                    }
                    self.flow.blocks.pop();
                    return Ok(());
                }
                let again = self.flow.blocks.last().is_some_and(|b| {
                    b.kind == BlockKind::While && b.name == name && b.start == cur
                });
                if truth {
                    if !again {
                        self.open_block(
                            at,
                            OpenBlock {
                                name,
                                kind: BlockKind::While,
                                start: cur,
                                left: 0.0,
                            },
                        )?;
                    }
                } else {
                    if again {
                        self.flow.blocks.pop();
                    }
                    self.skip_to(name, &[Keyword::EndWhile], true);
                }
                Ok(())
            }
            Keyword::EndWhile => {
                if !top_is(&self.flow, |k| k == BlockKind::While, &name) {
                    return Err(self.err_at(mismatch("endwhile")));
                }
                let start = self.flow.blocks.last().map_or(cur, |b| b.start);
                self.jump_back(start)
            }
            Keyword::Repeat => {
                let n = value.unwrap_or(0.0).round();
                if n >= 1.0 {
                    self.open_block(
                        at,
                        OpenBlock {
                            name,
                            kind: BlockKind::Repeat,
                            start: cur,
                            left: n,
                        },
                    )?;
                } else {
                    self.skip_to(name, &[Keyword::EndRepeat], true);
                }
                Ok(())
            }
            Keyword::EndRepeat => {
                if !top_is(&self.flow, |k| k == BlockKind::Repeat, &name) {
                    return Err(self.err_at(mismatch("endrepeat")));
                }
                let (start, left) = self.flow.blocks.last_mut().map_or((cur, 0.0), |b| {
                    b.left -= 1.0;
                    (b.start, b.left)
                });
                if left >= 1.0 {
                    return self.jump_back(start + 1);
                }
                self.flow.blocks.pop();
                Ok(())
            }
            Keyword::Break | Keyword::Continue => {
                let Some(pos) = self
                    .flow
                    .blocks
                    .iter()
                    .rposition(|b| b.name == name && !matches!(b.kind, BlockKind::If { .. }))
                else {
                    return Err(self.err_at(mismatch(o.kw.name())));
                };
                self.flow.blocks.truncate(pos + 1);
                let Some(b) = self.flow.blocks.last().cloned() else {
                    return Ok(());
                };
                if o.kw == Keyword::Break {
                    self.flow.blocks.pop();
                    let until: &'static [Keyword] = match b.kind {
                        BlockKind::While => &[Keyword::EndWhile],
                        BlockKind::Repeat => &[Keyword::EndRepeat],
                        _ => &[Keyword::While],
                    };
                    self.skip_to(name, until, true);
                    return Ok(());
                }
                match b.kind {
                    BlockKind::While => self.jump_back(b.start),
                    BlockKind::Do => self.jump_back(b.start + 1),
                    _ => {
                        // Like reaching endrepeat.
                        if let Some(t) = self.flow.blocks.last_mut() {
                            t.left -= 1.0;
                        }
                        if b.left - 1.0 >= 1.0 {
                            self.jump_back(b.start + 1)
                        } else {
                            self.flow.blocks.pop();
                            self.skip_to(name, &[Keyword::EndRepeat], true);
                            Ok(())
                        }
                    }
                }
            }
        }
    }

    /// M98 P<n> [L<times>] (call subprogram O<n>) and M99 (return from it).
    fn m98_m99(&mut self, code: u16) -> Result<(), GcodeError> {
        let blk = &self.blk;
        let allowed = bit(b'P') | bit(b'L') | bit(b'N');
        if blk.ng != 0 || blk.nm != 1 || blk.mask & !allowed != 0 {
            let off = blk.m[0].1 as usize;
            return Err(self.err_at((
                off,
                ErrorKind::Invalid,
                format!("{} must be alone on its line (with P and L)", mname(code)),
            )));
        }
        if !self.flow.buffering {
            self.keep_line()?;
        }
        if code == 990 {
            let Some(f) = self.flow.frames.last_mut().filter(|f| f.m98_left.is_some()) else {
                let off = self.blk.m[0].1 as usize;
                return Err(self.err_at((
                    off,
                    ErrorKind::Invalid,
                    "M99 outside an M98 subprogram".to_string(),
                )));
            };
            if let Some(left) = f.m98_left.filter(|&l| l > 0) {
                f.m98_left = Some(left - 1);
                let body = f.body;
                return self.jump_back(body);
            }
            self.ret(None);
            return Ok(());
        }
        let off = self.blk.m[0].1 as usize;
        let Some(p) = self
            .blk
            .get(b'P')
            .filter(|p| *p >= 0.0 && p.fract() == 0.0 && *p < 1e9)
        else {
            return Err(self.err_at((
                off,
                ErrorKind::Invalid,
                "M98 needs P<program number>".to_string(),
            )));
        };
        let times = match self.blk.get(b'L') {
            None => 1,
            Some(l) if l >= 0.0 && l.fract() == 0.0 && l <= 1e6 => l as u32,
            Some(_) => {
                let at = self.blk.pos_of(b'L') as usize;
                return Err(self.err_at((
                    at,
                    ErrorKind::Invalid,
                    "M98 L (repeats) must be a whole number".to_string(),
                )));
            }
        };
        if times == 0 {
            return Ok(());
        }
        let args = self.params.sub_params();
        self.call(format!("{}", p as u64), args, Some(times), off)
    }

    /// Reads and interprets one line; events go to the queue.
    fn step(&mut self) -> Result<(), GcodeError> {
        self.settle_probe();
        if !self.next_line()? {
            return self.end_of_input();
        }
        if self.start_at.is_some() && self.stops_here() {
            return Ok(());
        }
        self.lines_executed += 1;
        if self.flow.skip.is_some() {
            return self.skip_line();
        }
        let st = &self.st;
        let (g92, g92_saved) = (&self.g92, &self.g92_saved);
        let (g92_a, g92_saved_a) = (self.g92_a, self.g92_saved_a);
        let sys = || sys_view(st, *g92, *g92_saved, g92_a, g92_saved_a);
        let kind = match lex_line(
            &self.line,
            self.cfg.block_delete,
            &mut self.blk,
            &mut self.params,
            &sys,
        ) {
            Ok(k) => k,
            Err(e) => return self.fail(e),
        };
        match kind {
            LineKind::OWord(at) => {
                if self.params.named_used {
                    self.note_linuxcnc_only();
                }
                if self.linuxcnc_only.is_none()
                    && !matches!(flow::parse(&self.line, at), Ok(o) if o.kw == Keyword::Number)
                {
                    self.note_linuxcnc_only();
                }
                self.oword(at)
            }
            LineKind::Deleted => Ok(()),
            LineKind::Percent => {
                if !self.words_seen && !self.percent_open {
                    self.percent_open = true;
                } else {
                    // Like M2/M30: what compensation holds comes out first, and it ends
                    // (found by the grammar fuzz target: the held move came after the end, or
                    // with the stream stopping there, never).
                    self.release_held()?;
                    self.comp = Comp::default();
                    self.queue
                        .push_back(Motion::ProgramEnd { line: self.line_no });
                    if self.cfg.stop_at_program_end {
                        self.done = true;
                    }
                }
                Ok(())
            }
            LineKind::Words => {
                if self.blk.special {
                    // Parameters, assignments, debug messages, M98/M99.
                    if self.params.named_used || self.blk.debug.is_some() {
                        self.note_linuxcnc_only();
                    }
                    if !self.params.pending.is_empty() {
                        self.params.commit();
                    }
                    if let Some(&(code @ (980 | 990), _)) = self.blk.m[..self.blk.nm]
                        .iter()
                        .find(|m| m.0 == 980 || m.0 == 990)
                    {
                        self.words_seen = true;
                        return self.m98_m99(code);
                    }
                }
                if self.blk.mask == 0
                    && self.blk.ng == 0
                    && self.blk.nm == 0
                    && self.blk.msg.is_none()
                    && self.blk.debug.is_none()
                {
                    return Ok(());
                }
                self.words_seen = true;
                let r = if self.is_plain_move() {
                    self.execute_plain_move()
                } else {
                    self.execute()
                };
                match r {
                    Ok(()) => Ok(()),
                    Err(e) => {
                        self.queue.clear();
                        self.fail(e)
                    }
                }
            }
        }
    }

    /// Applies the unsupported-word policy to an error of this line.
    ///
    /// Skipping must not silently change what later lines do, so a line is
    /// only skipped if that is safe: one that also sets units, distance
    /// modes, plane or work system, or an incremental move (which would shift
    /// every later incremental move), stays an error; one that sets a motion
    /// mode leaves the motion mode unknown, so the following modal lines are
    /// skipped too until a G0/G1/G2/G3/G80 says what to do.
    fn fail(&mut self, e: LexError) -> Result<(), GcodeError> {
        let mut err = make_error(self.line_no, &self.line, e);
        if err.kind != ErrorKind::Unsupported
            || self.cfg.unsupported != Unsupported::SkipWithWarning
        {
            return Err(err);
        }
        let scan = lenient_scan(&self.line);
        let mut motion = None;
        for &code in &scan.g[..scan.ng] {
            match code {
                170 | 180 | 190 | 200 | 210 | 900 | 910 | 901 | 911 | 540..=593 => {
                    err.message = format!(
                        "{} (the line cannot be skipped: it also sets {}, which later lines depend on)",
                        err.message,
                        gname(code)
                    );
                    return Err(err);
                }
                0 | 10 | 20 | 30 | 800 | 330 | 331 | 382..=385 | 730 | 760 | 810..=890 => {
                    motion = Some(code);
                }
                _ => {}
            }
        }
        if scan.axes && !self.st.absolute {
            err.message = format!(
                "{} (the line cannot be skipped: it is an incremental (G91) move)",
                err.message
            );
            return Err(err);
        }
        if let Some(code) = motion {
            self.st.motion = MotionMode::Unsupported(code);
        }
        self.warn(Warning {
            line: err.line,
            column: err.column,
            message: format!("line skipped: {}", err.message),
        });
        Ok(())
    }

    #[inline]
    fn scale(inch: bool) -> f64 {
        if inch {
            MM_PER_INCH
        } else {
            1.0
        }
    }

    /// The line is the common CAM move, `[N..] [G0|G1] X.. Y.. Z.. [F..]`, in a state where
    /// nothing else changes how it runs: G0/G1 mode (or set on the line), G94, no cutter
    /// compensation, no G92/G52 or G10 offsets, no canned-cycle level to forget. Such a line
    /// (nine in ten of a CAM program's) takes [`Interpreter::execute_plain_move`], which does
    /// what [`Interpreter::execute_line`] would, without its classification of every word and
    /// group and its copy of the whole state. The conditions are the ones under which the
    /// general path runs no other branch; anything else takes the general path.
    #[inline(always)]
    fn is_plain_move(&self) -> bool {
        const WORDS: u32 = bit(b'X') | bit(b'Y') | bit(b'Z') | bit(b'F') | bit(b'N');
        const AXES: u32 = bit(b'X') | bit(b'Y') | bit(b'Z');
        let blk = &self.blk;
        let motion_ok = match blk.ng {
            0 => matches!(self.st.motion, MotionMode::Rapid | MotionMode::Linear),
            // Setting the motion mode also ends a series of canned cycles (their
            // initial level): left to the general path.
            1 => matches!(blk.g[0].0, 0 | 10) && self.cycle.initial.is_none(),
            _ => false,
        };
        motion_ok
            && blk.nm == 0
            && blk.mask & !WORDS == 0
            && blk.mask & AXES != 0
            && blk.msg.is_none()
            && blk.debug.is_none()
            && self.st.feed_mode == FeedMode::PerMinute
            && self.comp.side.is_none()
            && !self.comp.arc_not_allowed
            && !self.g92_active
            && !self.offsets_changed
    }

    /// [`Interpreter::execute_line`] for a line [`Interpreter::is_plain_move`] accepted: the
    /// same checks, events and errors in the same order (units, word ranges, feed, target,
    /// the move, the state, then the reach checks), on the state in place. As there, the state
    /// is written only after every check but the reach checks, which the general path also
    /// makes after its commit (`units_inch_seen`, which it sets before its move, aside).
    #[inline(always)]
    fn execute_plain_move(&mut self) -> Result<(), LexError> {
        let blk = &self.blk;
        let line = self.line_no;
        let motion = match blk.ng {
            0 => self.st.motion,
            _ if blk.g[0].0 == 0 => MotionMode::Rapid,
            _ => MotionMode::Linear,
        };
        let scale = Self::scale(self.st.inch);
        // `check_word_ranges`'s bounds for these words, tested at once; when one fails,
        // `check_word_ranges` itself finds the word to name (the first, in letter order).
        let within = |letter: u8, limit: f64| match blk.get(letter) {
            Some(v) => (v * scale).abs() <= limit,
            None => true,
        };
        if !(within(b'F', MAX_FEED)
            & within(b'X', MAX_COORDINATE_MM)
            & within(b'Y', MAX_COORDINATE_MM)
            & within(b'Z', MAX_COORDINATE_MM))
        {
            check_word_ranges(blk, scale, FeedMode::PerMinute)?;
        }
        let mut feed = self.st.feed;
        if let Some(f) = feed_word(blk)? {
            feed = Some(f * scale);
        }
        if self.st.inch {
            self.units_inch_seen = true;
        }
        let pos = self.st.pos;
        let mut target = pos;
        for (i, letter) in [b'X', b'Y', b'Z'].into_iter().enumerate() {
            if let Some(v) = blk.get(letter) {
                target[i] = if self.st.absolute {
                    v * scale
                } else {
                    pos[i] + v * scale
                };
            }
        }
        // No A word: A stays (`between` still decides, as on the general path).
        let a = RotaryMove::between(self.st.a, self.st.a);
        let m = if motion == MotionMode::Rapid {
            Motion::Rapid {
                line,
                from: pos,
                to: target,
                a,
            }
        } else {
            Motion::Linear {
                line,
                from: pos,
                to: target,
                feed_mm_min: match feed {
                    // The usual case, inline; `feed_mm_min` makes the errors (and passes NaN).
                    Some(f) if f > 0.0 => f,
                    _ => feed_mm_min(feed, blk)?,
                },
                a,
            }
        };
        self.queue.push_back_inlined(m);
        self.st.pos = target;
        self.st.motion = motion;
        self.st.feed = feed;
        // The reach checks below, at once for the usual case: this move the only event
        // queued, its end (the new position) and A within reach. Otherwise they run one by
        // one, for the error to name.
        let reach = |v: f64| v.abs() <= MAX_COORDINATE_MM;
        if self.queue.count() == 1 && target.iter().all(|&v| reach(v)) && reach(self.st.a) {
            return Ok(());
        }
        self.check_line_reach()
    }

    /// The line's queued motions and the programmed position within reach, one by one (so
    /// an error names the word and what is out of reach).
    fn check_line_reach(&self) -> Result<(), LexError> {
        for m in self.queue.iter() {
            check_motion_reach(m, &self.blk)?;
        }
        // Moves that cutter compensation holds back come out later: their programmed end.
        check_reach(
            "the programmed position is",
            &self.st.pos,
            Some(self.st.a),
            &self.blk,
        )
    }

    /// Interprets the lexed block. Works on a copy of the state and commits it
    /// at the end, so an error or a skipped line changes nothing.
    #[inline(always)]
    fn execute(&mut self) -> Result<(), LexError> {
        let mut comp = None;
        let r = self.execute_line(&mut comp);
        // Not committed: what the line did to compensation is undone.
        if let Some(mut c) = comp {
            c.rollback();
            self.comp = c;
        }
        r
    }

    /// [`Interpreter::execute`]; `comp` holds the compensation state while the line runs (taken
    /// from `self.comp`, and put back by the commit at the end).
    #[inline(always)]
    fn execute_line(&mut self, comp: &mut Option<Comp>) -> Result<(), LexError> {
        let blk = &self.blk;
        let line = self.line_no;
        let mut st = self.st;
        // Written back with the state when the line succeeds.
        let mut cycle_new: Option<CycleState> = None;
        let mut g92_new: Option<(Point, Point, f64, f64)> = None;
        let mut spline_pq_new: Option<Option<(f64, f64)>> = None;
        let mut g10_new: Option<([Point; 9], crate::ToolTable)> = None;

        // --- classify G words into modal groups -------------------------
        let mut g_motion: Option<(u16, u32)> = None;
        let mut g_plane = None;
        let mut g_dist = None;
        let mut g_arcdist = None;
        let mut g_feedmode = None;
        let mut g_units = None;
        let mut g_cutter = None;
        let mut g_tlo = None;
        let mut g_coord = None;
        let mut g_path = None;
        let mut g_retract = None;
        let mut g_nonmodal: Option<(u16, u32)> = None;
        for &(code, off) in &blk.g[..blk.ng] {
            const MOTION: [u16; 18] = [
                0, 10, 20, 30, 50, 51, 800, 730, 810, 820, 830, 850, 890, 310, 382, 383, 384, 385,
            ];
            let is_motion = MOTION.contains(&code);
            let slot = match code {
                _ if is_motion => &mut g_motion,
                330 | 331 | 760 | 840 | 860..=880 => {
                    // Remember it so that following modal lines are rejected
                    // rather than run as the previous G0/G1.
                    self.st.motion = MotionMode::Unsupported(code);
                    return Err(unsupported_g(
                        code,
                        off,
                        "tapping, boring cycles with spindle stops and threading are not implemented",
                    ));
                }
                170 | 180 | 190 => &mut g_plane,
                900 | 910 => &mut g_dist,
                901 | 911 => &mut g_arcdist,
                930 | 940 | 950 => &mut g_feedmode,
                200 | 210 => &mut g_units,
                400 | 410 | 420 | 411 | 421 => &mut g_cutter,
                430 | 490 => &mut g_tlo,
                540 | 550 | 560 | 570 | 580 | 590 | 591 | 592 | 593 => &mut g_coord,
                610 | 611 | 640 => &mut g_path,
                980 | 990 => &mut g_retract,
                40 | 100 | 280 | 281 | 300 | 301 | 530 | 520 | 920..=923 => &mut g_nonmodal,
                _ => return Err(unknown_g(code, off)),
            };
            if let Some((prev, _)) = *slot {
                // G80 beside another motion code (`G0 G80 X..`, the "safe start" line of
                // Fanuc-, Haas-, Vectric- and Mach3-style posts) is dropped and the other code
                // applies, in either order, as LinuxCNC's rs274 does.
                if is_motion && code == 800 {
                    continue;
                }
                if is_motion && prev == 800 {
                    *slot = Some((code, off));
                    continue;
                }
                return Err((
                    off as usize,
                    ErrorKind::Invalid,
                    format!(
                        "{} and {} are in the same modal group",
                        gname(prev),
                        gname(code)
                    ),
                ));
            }
            *slot = Some((code, off));
        }

        // --- M words --------------------------------------------------
        let mut m_stop: Option<(u16, u32)> = None;
        let mut m_spindle: Option<(u16, u32)> = None;
        let mut m_tool = false;
        let (mut m_mist, mut m_flood, mut m_cool_off) = (false, false, false);
        let mut m_state: Option<(u16, u32)> = None;
        let mut m_set_tool: Option<(u16, u32)> = None;
        for &(code, off) in &blk.m[..blk.nm] {
            let slot = match code {
                0 | 10 | 20 | 300 => &mut m_stop,
                30 | 40 | 50 => &mut m_spindle,
                700 | 710 | 720 | 730 => &mut m_state,
                610 => &mut m_set_tool,
                60 => {
                    if m_tool {
                        return Err(same_group_m(60, 60, off));
                    }
                    m_tool = true;
                    continue;
                }
                70 | 80 | 90 => {
                    // M7 and M8 may be combined; M9 with either is a conflict.
                    let flag = match code {
                        70 => &mut m_mist,
                        80 => &mut m_flood,
                        _ => &mut m_cool_off,
                    };
                    if *flag {
                        return Err(same_group_m(code, code, off));
                    }
                    *flag = true;
                    if m_cool_off && (m_mist || m_flood) {
                        return Err((
                            off as usize,
                            ErrorKind::Invalid,
                            "M9 with M7/M8 on one line".to_string(),
                        ));
                    }
                    continue;
                }
                _ => {
                    return Err((
                        off as usize,
                        ErrorKind::Unsupported,
                        format!("{} is not supported", mname(code)),
                    ))
                }
            };
            if let Some((prev, _)) = *slot {
                return Err(same_group_m(prev, code, off));
            }
            *slot = Some((code, off));
        }

        // --- which words are used --------------------------------------
        let axis_mask = bit(b'X') | bit(b'Y') | bit(b'Z') | bit(b'A') | POLAR_MASK;
        let has_axes = blk.mask & axis_mask != 0;
        let ijk_mask = bit(b'I') | bit(b'J') | bit(b'K');
        let has_ijk = blk.mask & ijk_mask != 0;
        let has_r = blk.has(b'R');

        if let Some((code, _)) = g_feedmode {
            let mode = match code {
                930 => FeedMode::InverseTime,
                950 => FeedMode::PerRevolution,
                _ => FeedMode::PerMinute,
            };
            // A feed of another mode means something else: it must be given
            // again (LinuxCNC zeroes it). G94 in G94 keeps it (grbl; LinuxCNC
            // would zero it too, refusing a later F-less feed move).
            if mode != st.feed_mode {
                st.feed_mode = mode;
                st.feed = None;
            }
        }
        if blk.has(b'D') && !matches!(g_cutter, Some((410 | 420 | 411 | 421, _))) {
            return Err((
                blk.pos_of(b'D') as usize,
                ErrorKind::Invalid,
                "D word with no G41/G42/G41.1/G42.1 on the line".to_string(),
            ));
        }
        // Cutter compensation state, taken only when a line touches it (it
        // holds moves, so it is not part of the copied `State`); it records
        // what the line changes, so that `execute` can undo it.
        let comp_was_on = self.comp.side.is_some();
        *comp = if g_cutter.is_some() || comp_was_on || self.comp.arc_not_allowed {
            let mut c = std::mem::take(&mut self.comp);
            c.begin_line();
            Some(c)
        } else {
            None
        };
        if comp_was_on {
            comp_forbidden(&st, g_plane, g_units, g_coord, g_nonmodal, g_motion)?;
        }

        // Motion mode after this line; the previous one decides which cycle
        // words are sticky.
        let motion_before = st.motion;
        if let Some((code, _)) = g_motion {
            st.motion = match code {
                0 => MotionMode::Rapid,
                10 => MotionMode::Linear,
                20 => MotionMode::Cw,
                30 => MotionMode::Ccw,
                50 | 51 => MotionMode::Spline(code),
                730 | 810 | 820 | 830 | 850 | 890 => MotionMode::Cycle(code),
                310 | 382..=385 => MotionMode::Probe(code),
                _ => MotionMode::None,
            };
            if self.cycle.initial.is_some() && !matches!(st.motion, MotionMode::Cycle(_)) {
                cycle_new.get_or_insert(self.cycle).initial = None;
            }
        }
        if let Some((code, _)) = g_retract {
            cycle_new.get_or_insert(self.cycle).retract_to_r = code == 990;
        }
        let cycle = match st.motion {
            MotionMode::Cycle(c) => Some(c),
            _ => None,
        };
        let nonmodal = g_nonmodal.map(|g| g.0);
        let uses_axes_nonmodal = matches!(nonmodal, Some(100 | 280 | 300 | 920 | 520));
        if uses_axes_nonmodal && has_axes && g_motion.is_some_and(|g| g.0 != 800) {
            let (code, off) = g_nonmodal.unwrap_or((0, 0));
            return Err((
                off as usize,
                ErrorKind::Invalid,
                format!(
                    "{} and a motion G code both use the axis words",
                    gname(code)
                ),
            ));
        }
        let is_arc = matches!(st.motion, MotionMode::Cw | MotionMode::Ccw);
        let motion_here = !uses_axes_nonmodal && (has_axes || (is_arc && (has_ijk || has_r)));
        if g_nonmodal.is_some_and(|g| g.0 == 530)
            && !(motion_here && matches!(st.motion, MotionMode::Rapid | MotionMode::Linear))
        {
            let off = g_nonmodal.map_or(0, |g| g.1);
            return Err((
                off as usize,
                ErrorKind::Invalid,
                "G53 needs G0 or G1 with axis words".to_string(),
            ));
        }
        if motion_here {
            match st.motion {
                MotionMode::None => {
                    return Err((
                        first_of(blk, axis_mask | ijk_mask | bit(b'R')),
                        ErrorKind::Invalid,
                        "axis words with no motion mode active (G80 or none programmed yet)"
                            .to_string(),
                    ))
                }
                MotionMode::Unsupported(code) => {
                    return Err((
                        first_of(blk, axis_mask),
                        ErrorKind::Unsupported,
                        format!(
                            "axis words while the motion mode is unknown ({} was on an unsupported or skipped line)",
                            gname(code)
                        ),
                    ))
                }
                _ => {}
            }
        }
        // Words no command on this line uses.
        let arc_motion = motion_here && is_arc;
        let spline = match st.motion {
            MotionMode::Spline(code) if motion_here => Some(code),
            _ => None,
        };
        if has_r && (cycle.is_some() || nonmodal == Some(100)) {
            // R of a canned cycle, or G10 L1's radius.
        } else if has_ijk && !has_r && spline.is_some() {
            // Control point offsets of G5 / G5.1.
        } else if (has_ijk || has_r) && !arc_motion {
            return Err((
                first_of(blk, ijk_mask | bit(b'R')),
                ErrorKind::Invalid,
                "I/J/K/R words without a G2/G3 arc on the line".to_string(),
            ));
        }
        if blk.has(b'P')
            && !(matches!(nonmodal, Some(40 | 100))
                || arc_motion
                || g_path.is_some_and(|g| g.0 == 640)
                || matches!(cycle, Some(820 | 890))
                || spline == Some(50))
        {
            return Err((
                blk.pos_of(b'P') as usize,
                ErrorKind::Invalid,
                "P word with no G4, G2/G3 or G64 on the line".to_string(),
            ));
        }
        if blk.has(b'Q')
            && g_path.map(|g| g.0) != Some(640)
            && !matches!(cycle, Some(730 | 830))
            && spline != Some(50)
            && m_set_tool.is_none()
        {
            return Err((
                blk.pos_of(b'Q') as usize,
                ErrorKind::Unsupported,
                "Q word is not supported here".to_string(),
            ));
        }
        if blk.has(b'L') && cycle.is_none() && nonmodal != Some(100) {
            return Err((
                blk.pos_of(b'L') as usize,
                ErrorKind::Unsupported,
                "L word (G10 / canned cycle repeats) is not supported".to_string(),
            ));
        }
        if blk.has(b'H') && g_tlo.map(|g| g.0) != Some(430) {
            return Err((
                blk.pos_of(b'H') as usize,
                ErrorKind::Invalid,
                "H word without G43".to_string(),
            ));
        }

        // --- execute in LinuxCNC order ----------------------------------
        let queue = &mut self.queue;
        // 1. message (attached to M0/M1 if on the same line)
        let pause_here = matches!(m_stop, Some((0 | 10, _)));
        let mut pause_msg = None;
        if let Some((s, e)) = blk.debug {
            self.params.sys = sys_view(
                &self.st,
                self.g92,
                self.g92_saved,
                self.g92_a,
                self.g92_saved_a,
            );
            let text = expr::substitute(&self.line[s..e], &mut self.params)
                .trim()
                .to_string();
            queue.push_back(Motion::Message { line, text });
        }
        if let Some((s, e)) = blk.msg {
            let text = String::from_utf8_lossy(&self.line[s..e]).trim().to_string();
            if pause_here {
                pause_msg = Some(text);
            } else {
                queue.push_back(Motion::Message { line, text });
            }
        }
        // Units first for everything numeric on this line (G20/G21 apply to
        // the whole block, as in grbl; LinuxCNC gives the same result).
        if let Some((code, _)) = g_units {
            st.inch = code == 200;
        }
        let scale = Self::scale(st.inch);
        check_word_ranges(blk, scale, st.feed_mode)?;
        // 3. feed
        if let Some(f) = feed_word(blk)? {
            // Inverse time is 1/minutes, no length: not scaled by G20.
            st.feed = Some(if st.feed_mode == FeedMode::InverseTime {
                f
            } else {
                f * scale
            });
        }
        // 4. spindle speed
        let s_word = blk.get(b'S');
        if let Some(s) = s_word {
            if s < 0.0 {
                return Err((
                    blk.pos_of(b'S') as usize,
                    ErrorKind::Invalid,
                    "negative spindle speed".to_string(),
                ));
            }
            st.rpm = s;
        }
        // 5. tool select
        if let Some(t) = blk.get(b'T') {
            if t < 0.0 || t.fract() != 0.0 || t > f64::from(u32::MAX) {
                return Err((
                    blk.pos_of(b'T') as usize,
                    ErrorKind::Invalid,
                    "T must be a non-negative integer".to_string(),
                ));
            }
            st.tool = t as u32;
        }
        // M61 Q: the tool in the spindle is Q, without a change (LinuxCNC).
        if let Some((_, off)) = m_set_tool {
            match blk.get(b'Q') {
                Some(q) if q >= 0.0 && q.fract() == 0.0 && q <= f64::from(u32::MAX) => {
                    st.tool = q as u32;
                    st.spindle_tool = st.tool;
                }
                _ => {
                    return Err((
                        off as usize,
                        ErrorKind::Invalid,
                        "M61 needs Q with a tool number (a non-negative integer)".to_string(),
                    ))
                }
            }
        }
        // 6. tool change
        if m_tool {
            st.spindle_tool = st.tool;
            if let Some(c) = comp.as_mut() {
                if !c.held.is_empty() {
                    absorb(queue, c)?;
                    release(queue, c);
                }
                // LinuxCNC reads the position back after a tool change:
                // after G40 the tool is where compensation left it.
                if let Some(d) = c.detached.take() {
                    st.pos[0] = d[0];
                    st.pos[1] = d[1];
                }
            }
            queue.push_back(Motion::ToolChange {
                line,
                tool: st.tool,
            });
        }
        // 7. spindle
        if let Some((code, _)) = m_spindle {
            st.spindle = match code {
                30 => SpindleDirection::Clockwise,
                40 => SpindleDirection::CounterClockwise,
                _ => SpindleDirection::Off,
            };
        }
        if m_spindle.is_some() || (s_word.is_some() && st.spindle != SpindleDirection::Off) {
            queue.push_back(Motion::Spindle {
                line,
                direction: st.spindle,
                rpm: st.rpm,
            });
        }
        // 8. coolant
        if m_mist || m_flood || m_cool_off {
            if m_cool_off {
                st.mist = false;
                st.flood = false;
            }
            st.mist |= m_mist;
            st.flood |= m_flood;
            queue.push_back(Motion::Coolant {
                line,
                mist: st.mist,
                flood: st.flood,
            });
        }
        // 10. dwell
        if nonmodal == Some(40) {
            let Some(p) = blk.get(b'P') else {
                let off = g_nonmodal.map_or(0, |g| g.1);
                return Err((
                    off as usize,
                    ErrorKind::Invalid,
                    "G4 needs P (seconds)".to_string(),
                ));
            };
            let p = dwell_seconds(p, blk.pos_of(b'P') as usize)?;
            queue.push_back(Motion::Dwell { line, seconds: p });
        }
        // 11. plane
        if let Some((code, _)) = g_plane {
            st.plane = match code {
                170 => Plane::XY,
                180 => Plane::ZX,
                _ => Plane::YZ,
            };
        }
        if st.inch {
            self.units_inch_seen = true;
        }
        // 13. cutter radius compensation
        if let (Some((code, off)), Some(c)) = (g_cutter, comp.as_mut()) {
            if code == 400 {
                absorb(queue, c)?;
                let mut out = Vec::new();
                c.off(st.pos, &mut out);
                for m in out {
                    queue.push_back(m);
                }
            } else {
                comp_on(c, &self.cfg, blk, &st, code, off as usize, scale)?;
            }
        }
        // 14. tool length offset: program coordinates are unchanged.
        if let Some((code, _)) = g_tlo {
            let tool = if code == 430 {
                match blk.get(b'H') {
                    Some(h) if h >= 0.0 && h.fract() == 0.0 && h <= f64::from(u32::MAX) => {
                        Some(h as u32)
                    }
                    Some(_) => {
                        return Err((
                            blk.pos_of(b'H') as usize,
                            ErrorKind::Invalid,
                            "H must be a non-negative integer".to_string(),
                        ))
                    }
                    None => Some(st.tool),
                }
            } else {
                None
            };
            st.tlo = tool;
            queue.push_back(Motion::ToolLengthOffset { line, tool });
        }
        // 15. work coordinate system
        if let Some((code, _)) = g_coord {
            let idx: u8 = match code {
                591 => 6,
                592 => 7,
                593 => 8,
                c => ((c - 540) / 10) as u8,
            };
            let old = self.params.work_offsets[st.coord as usize];
            let new = self.params.work_offsets[idx as usize];
            for i in 0..3 {
                st.pos[i] += old[i] - new[i];
            }
            st.coord = idx;
            self.work_systems |= 1 << idx;
            queue.push_back(Motion::WorkOffset {
                line,
                system: idx + 1,
            });
        }
        // 17. distance modes
        if let Some((code, _)) = g_dist {
            st.absolute = code == 900;
        }
        if let Some((code, _)) = g_arcdist {
            st.arc_absolute = code == 901;
        }

        // Target of the axis words (program coordinates, mm).
        let machine = nonmodal == Some(530);
        let mut target = st.pos;
        for (i, letter) in [b'X', b'Y', b'Z'].into_iter().enumerate() {
            if let Some(v) = blk.get(letter) {
                target[i] = if machine {
                    v * scale - self.params.work_offsets[st.coord as usize][i] - self.g92[i]
                } else if st.absolute {
                    v * scale
                } else {
                    st.pos[i] + v * scale
                };
            }
        }

        // A: degrees whatever G20/G21 say; work systems have no A offset.
        let mut target_a = st.a;
        if let Some(v) = blk.get(b'A') {
            target_a = if machine {
                v - self.g92_a
            } else if st.absolute {
                v
            } else {
                st.a + v
            };
        }

        if blk.mask & POLAR_MASK != 0 && !matches!(st.motion, MotionMode::Cycle(_)) {
            if machine {
                return Err((
                    first_of(blk, POLAR_MASK),
                    ErrorKind::Invalid,
                    "polar coordinates (@ ^) with G53".to_string(),
                ));
            }
            let (x, y) = polar_xy(blk, st.absolute, st.pos, scale)?;
            target[0] = x;
            target[1] = y;
        }

        // 19. G28 / G30 (go to stored position), G28.1 / G30.1 (store).
        match nonmodal {
            Some(280 | 300) => {
                // Stored positions are in the work system's frame.
                let stored = sub(
                    if nonmodal == Some(280) {
                        st.g28
                    } else {
                        st.g30
                    },
                    self.g92,
                );
                let stored_a = if nonmodal == Some(280) {
                    st.g28_a
                } else {
                    st.g30_a
                } - self.g92_a;
                let (mut end, mut end_a);
                if has_axes {
                    if target != st.pos || target_a != st.a {
                        queue.push_back(Motion::Rapid {
                            line,
                            from: st.pos,
                            to: target,
                            a: RotaryMove::between(st.a, target_a),
                        });
                    }
                    end = target;
                    for (i, letter) in [b'X', b'Y', b'Z'].into_iter().enumerate() {
                        if blk.has(letter) {
                            end[i] = stored[i];
                        }
                    }
                    end_a = target_a;
                    if blk.has(b'A') {
                        end_a = stored_a;
                    }
                } else {
                    end = stored;
                    end_a = stored_a;
                }
                queue.push_back(Motion::Rapid {
                    line,
                    from: target,
                    to: end,
                    a: RotaryMove::between(target_a, end_a),
                });
                st.pos = end;
                st.a = end_a;
            }
            Some(281) => {
                st.g28 = add(st.pos, self.g92);
                st.g28_a = st.a + self.g92_a;
            }
            Some(301) => {
                st.g30 = add(st.pos, self.g92);
                st.g30_a = st.a + self.g92_a;
            }
            Some(100) => {
                let at = g_nonmodal.map_or(0, |g| g.1) as usize;
                let comp_on = comp.as_ref().is_some_and(|c| c.side.is_some());
                let mut offsets = self.params.work_offsets;
                let mut tools = self.cfg.tools.clone();
                let changed = g10(blk, &mut st, &mut offsets, &mut tools, comp_on, scale, at)?;
                if let Some((l, system, origin)) = changed {
                    queue.push_back(Motion::WorkOffsetChange {
                        line,
                        l,
                        system,
                        origin,
                    });
                }
                g10_new = Some((offsets, tools));
            }
            // G92 family and G52: the origin moves; motions keep coming out
            // in the work system's frame (`Iterator::next` adds the offset),
            // so no backend has to know about it.
            Some(code @ (920 | 520 | 921 | 922 | 923)) => {
                if matches!(code, 920 | 520) && !has_axes {
                    let off = g_nonmodal.map_or(0, |g| g.1);
                    return Err((
                        off as usize,
                        ErrorKind::Invalid,
                        format!("{} needs at least one axis word", gname(code)),
                    ));
                }
                let (mut g92, mut saved) = (self.g92, self.g92_saved);
                for (i, letter) in [b'X', b'Y', b'Z'].into_iter().enumerate() {
                    let frame = st.pos[i] + g92[i];
                    match code {
                        920 | 520 => {
                            if let Some(v) = blk.get(letter) {
                                let v = v * scale;
                                g92[i] = if code == 920 { frame - v } else { v };
                                saved[i] = g92[i];
                            }
                        }
                        921 => {
                            g92[i] = 0.0;
                            saved[i] = 0.0;
                        }
                        922 => g92[i] = 0.0,
                        _ => g92[i] = saved[i],
                    }
                    st.pos[i] = frame - g92[i];
                }
                let (mut g92_a, mut saved_a) = (self.g92_a, self.g92_saved_a);
                let frame_a = st.a + g92_a;
                match code {
                    920 | 520 => {
                        if let Some(v) = blk.get(b'A') {
                            g92_a = if code == 920 { frame_a - v } else { v };
                            saved_a = g92_a;
                        }
                    }
                    921 => {
                        g92_a = 0.0;
                        saved_a = 0.0;
                    }
                    922 => g92_a = 0.0,
                    _ => g92_a = saved_a,
                }
                st.a = frame_a - g92_a;
                g92_new = Some((g92, saved, g92_a, saved_a));
                queue.push_back(Motion::OffsetChange {
                    line,
                    code,
                    offset: g92,
                    offset_a: g92_a,
                });
            }
            _ => {}
        }

        // 20. motion
        let comp_on = comp.as_ref().is_some_and(Comp::active);
        if motion_here && target_a != st.a {
            let why = match st.motion {
                MotionMode::Cw | MotionMode::Ccw => Some((
                    ErrorKind::Unsupported,
                    "A axis motion with an arc (G2/G3) is not supported",
                )),
                MotionMode::Cycle(_) => Some((ErrorKind::Invalid, "A axis word in a canned cycle")),
                MotionMode::Spline(_) => Some((
                    ErrorKind::Invalid,
                    "A axis word with a spline (G5/G5.1 move X and Y only)",
                )),
                _ if comp_on => Some((
                    ErrorKind::Unsupported,
                    "A axis motion with cutter compensation (G41/G42) is not supported",
                )),
                _ => None,
            };
            if let Some((kind, why)) = why {
                return Err((blk.pos_of(b'A') as usize, kind, why.to_string()));
            }
        }
        if motion_here && comp_on && matches!(st.motion, MotionMode::Probe(_)) {
            return Err((
                first_of(blk, axis_mask),
                ErrorKind::Invalid,
                "cannot probe with cutter radius compensation on (G40 first)".to_string(),
            ));
        }
        let mut probe_new: Option<(Point, Point, bool)> = None;
        if motion_here && comp_on {
            if let Some(c) = comp.as_mut() {
                let at = first_of(blk, axis_mask | ijk_mask | bit(b'R'));
                compensated_move(
                    &self.cfg, queue, c, &st, blk, target, machine, line, at, scale,
                )?;
                st.pos = target;
            }
        } else if motion_here {
            let queued_before = queue.count();
            if let Some(c) = comp.as_mut() {
                if c.arc_not_allowed && is_arc {
                    return Err((
                        first_of(blk, axis_mask | ijk_mask | bit(b'R')),
                        ErrorKind::Invalid,
                        "the move just after turning cutter compensation off (G40) must be straight, not an arc"
                            .to_string(),
                    ));
                }
                c.arc_not_allowed = false;
            }
            match st.motion {
                MotionMode::Rapid => {
                    queue.push_back(Motion::Rapid {
                        line,
                        from: st.pos,
                        to: target,
                        a: RotaryMove::between(st.a, target_a),
                    });
                }
                MotionMode::Linear => {
                    let mut feed = feed_mm_min(st.feed, blk)?;
                    if st.feed_mode != FeedMode::PerMinute {
                        // A rotary-only move's length is in degrees (LinuxCNC).
                        let mut length = len3(st.pos, target);
                        if length == 0.0 {
                            length = (target_a - st.a).abs();
                        }
                        feed = feed_in_mode(&st, blk, feed, length)?;
                    }
                    queue.push_back(Motion::Linear {
                        line,
                        from: st.pos,
                        to: target,
                        feed_mm_min: feed,
                        a: RotaryMove::between(st.a, target_a),
                    });
                }
                MotionMode::Spline(code) => {
                    if machine {
                        let off = g_nonmodal.map_or(0, |g| g.1);
                        return Err((
                            off as usize,
                            ErrorKind::Invalid,
                            "G53 with a spline".to_string(),
                        ));
                    }
                    let feed = feed_mm_min(st.feed, blk)?;
                    spline_pq_new = Some(spline_motion(
                        &self.cfg,
                        queue,
                        &st,
                        blk,
                        code,
                        target,
                        feed,
                        scale,
                        line,
                        if motion_before == MotionMode::Spline(50) {
                            self.spline_pq
                        } else {
                            None
                        },
                    )?);
                }
                MotionMode::Cw | MotionMode::Ccw => {
                    if machine {
                        let off = g_nonmodal.map_or(0, |g| g.1);
                        return Err((
                            off as usize,
                            ErrorKind::Invalid,
                            "G53 with an arc".to_string(),
                        ));
                    }
                    let feed = feed_mm_min(st.feed, blk)?;
                    let mut m = arc_motion_of(
                        &self.cfg,
                        &st,
                        blk,
                        target,
                        st.motion == MotionMode::Cw,
                        feed,
                        scale,
                        line,
                    )?;
                    if st.feed_mode != FeedMode::PerMinute {
                        let length =
                            crate::ArcGeometry::from_motion(&m).map_or(0.0, |g| g.length());
                        let f = feed_in_mode(&st, blk, feed, length)?;
                        if let Motion::Arc { feed_mm_min, .. } = &mut m {
                            *feed_mm_min = f;
                        }
                    }
                    queue.push_back(m);
                }
                MotionMode::Cycle(code) => {
                    if machine {
                        let off = g_nonmodal.map_or(0, |g| g.1);
                        return Err((
                            off as usize,
                            ErrorKind::Invalid,
                            "G53 with a canned cycle".to_string(),
                        ));
                    }
                    let first = motion_before != MotionMode::Cycle(code);
                    if let Some(l) = blk.get(b'L').filter(|l| *l > 1.0) {
                        self.cycle_repeats = Some((line, l));
                    }
                    let mut cyc = cycle_new.unwrap_or(self.cycle);
                    target = canned_cycle(queue, &mut st, &mut cyc, blk, code, first, scale, line)?;
                    cycle_new = Some(cyc);
                }
                MotionMode::Probe(code) => {
                    let at = first_of(blk, axis_mask);
                    let name = gname(code);
                    if machine {
                        let off = g_nonmodal.map_or(0, |g| g.1);
                        return Err((off as usize, ErrorKind::Invalid, format!("G53 with {name}")));
                    }
                    if st.feed_mode == FeedMode::InverseTime {
                        return Err((
                            at,
                            ErrorKind::Invalid,
                            format!("{name} cannot probe in inverse time feed mode (G93)"),
                        ));
                    }
                    if target_a != st.a {
                        return Err((
                            blk.pos_of(b'A') as usize,
                            ErrorKind::Unsupported,
                            format!("{name} with an A axis move is not supported"),
                        ));
                    }
                    let feed = feed_mm_min(st.feed, blk)?;
                    // LinuxCNC's rule (rs274 2.9): a G38.2/G38.4 that would not move at all is
                    // an error; G38.3/G38.5 may (smartprobe.ngc relies on it).
                    if matches!(code, 382 | 384) && len3(st.pos, target) < 1e-9 {
                        return Err((
                            at,
                            ErrorKind::Invalid,
                            format!(
                                "{name}: the start point is too close to the probe point (it \
                                 would not move)"
                            ),
                        ));
                    }
                    // Mach3's G31 probes for contact and, like G38.3, ends without error when
                    // the whole move ran.
                    queue.push_back(Motion::Probe {
                        line,
                        from: st.pos,
                        to: target,
                        feed_mm_min: feed,
                        contact: matches!(code, 310 | 382 | 383),
                        must_trip: matches!(code, 382 | 384),
                    });
                    probe_new = Some((st.pos, target, code == 310));
                }
                MotionMode::None | MotionMode::Unsupported(_) => {}
            }
            st.pos = target;
            st.a = target_a;
            // The first move after G40 leaves from the compensated point.
            if let Some(d) = comp.as_mut().and_then(|c| c.detached.take()) {
                queue.patch_first_move_from(queued_before, d);
            }
        } else if let Some(c) = comp.as_mut() {
            // Events of a line without a move wait behind held moves.
            absorb(queue, c)?;
        }

        // M70-M73: save, invalidate, restore the modal state (LinuxCNC).
        if let Some((code, off)) = m_state {
            match code {
                700 => self.saved_modal = Some(st),
                710 => self.saved_modal = None,
                720 => {
                    let Some(saved) = self.saved_modal else {
                        return Err((
                            off as usize,
                            ErrorKind::Invalid,
                            "M72 with no state saved by M70".to_string(),
                        ));
                    };
                    restore_modal(&self.params.work_offsets, queue, &mut st, &saved, line);
                }
                _ => {
                    // M73: restored when this subroutine returns.
                    let depth = self.flow.frames.len();
                    if !self.auto_restore.last().is_some_and(|a| a.0 == depth) {
                        self.auto_restore.push((depth, st));
                    }
                }
            }
        }

        // 21. stops: what compensation holds is released first.
        if m_stop.is_some() {
            if let Some(c) = comp.as_mut() {
                absorb(queue, c)?;
                release(queue, c);
                if !matches!(m_stop, Some((0 | 10, _))) {
                    *c = Comp::default();
                }
            }
        }
        let mut end = false;
        match m_stop {
            Some((0, _)) | Some((10, _)) => queue.push_back(Motion::Pause {
                line,
                optional: m_stop.is_some_and(|m| m.0 == 10),
                message: pause_msg,
            }),
            Some(_) => {
                queue.push_back(Motion::ProgramEnd { line });
                end = true;
            }
            None => {}
        }
        if end {
            if self.cfg.stop_at_program_end {
                self.done = true;
            } else {
                // M2/M30 reset (LinuxCNC): XY plane, absolute, G54, G94,
                // spindle and coolant off; position is kept.
                let (keep, keep_a) = (st.pos, st.a);
                let inch = st.inch;
                st = State::new(&self.cfg);
                st.pos = keep;
                st.a = keep_a;
                st.inch = inch;
                // G80 and G99 again; G92 offsets survive M2 (LinuxCNC).
                cycle_new = Some(CycleState {
                    retract_to_r: true,
                    ..CycleState::default()
                });
            }
        }
        self.st = st;
        if let Some(mut c) = comp.take() {
            c.commit();
            self.comp = c;
            if self.cutter_comp_line.is_none() && self.comp.side.is_some() {
                self.cutter_comp_line = Some(line);
            }
            if g_cutter.is_some_and(|g| g.0 != 400) {
                self.comp_since = Some(line);
            }
        }
        if let Some(c) = cycle_new {
            self.cycle = c;
        }
        if let Some(pq) = spline_pq_new {
            self.spline_pq = pq;
        }
        if let Some((offsets, tools)) = g10_new {
            self.g10_line.get_or_insert(line);
            if offsets != self.params.work_offsets {
                self.offsets_changed = true;
            }
            self.params.work_offsets = offsets;
            self.cfg.tools = tools;
        }
        if let Some((g92, saved, g92_a, saved_a)) = g92_new {
            self.g92 = g92;
            self.g92_saved = saved;
            self.g92_a = g92_a;
            self.g92_saved_a = saved_a;
            self.g92_active = g92 != [0.0; 3] || g92_a != 0.0;
        }
        if let Some((from, to, mach3)) = probe_new {
            // G38.x is LinuxCNC's probe: Mach3 knows only its own G31.
            if !mach3 {
                self.note_linuxcnc_only();
            }
            let frame = self.frame();
            self.probe_pending = Some(PendingProbe {
                from: add(from, frame),
                to: add(to, frame),
                frame,
                inch: self.st.inch,
                mach3,
                result: None,
            });
        }
        if self.g92_active || self.offsets_changed {
            // Into the work system's frame. Lines that change the offset
            // move nothing, so the offset after the line holds for all of
            // its motions.
            let frame = self.frame();
            if frame != [0.0; 3] || self.g92_a != 0.0 {
                self.queue.shift_all(frame, self.g92_a);
            }
        }
        // What the words add up to (G91 steps, offsets, cycle repeats, compensation) stays
        // within reach too; checked before any event of the line comes out.
        self.check_line_reach()
    }
}

/// Words whose value is a length (mm after G20/G21): coordinates, arc centre offsets and
/// radius (also a canned cycle's R level and G10 L1's tool radius), the polar radius `@`.
const LENGTH_WORDS: u32 = bit(b'X')
    | bit(b'Y')
    | bit(b'Z')
    | bit(b'I')
    | bit(b'J')
    | bit(b'K')
    | bit(b'R')
    | (1 << POLAR_R);
/// Words in degrees: the A axis and the polar angle `^`.
const ANGLE_WORDS: u32 = bit(b'A') | (1 << POLAR_A);

/// Every number a line gives within the crate's bounds ([`MAX_COORDINATE_MM`], [`MAX_FEED`],
/// [`MAX_SPINDLE_RPM`]), named at its word: a value no machine can run is a typo or an attack,
/// and must fail the upload check, not the job.
#[inline]
/// The line's F word, refused if negative.
fn feed_word(blk: &Block) -> Result<Option<f64>, LexError> {
    match blk.get(b'F') {
        Some(f) if f < 0.0 => Err((
            blk.pos_of(b'F') as usize,
            ErrorKind::Invalid,
            "negative feed rate".to_string(),
        )),
        f => Ok(f),
    }
}

fn check_word_ranges(blk: &Block, scale: f64, feed_mode: FeedMode) -> Result<(), LexError> {
    let present = blk.mask & (LENGTH_WORDS | ANGLE_WORDS | bit(b'F') | bit(b'S'));
    if present == 0 {
        return Ok(());
    }
    // Only the words present, lowest letter first (the order errors are found in).
    let mut rest = present;
    while rest != 0 {
        let i = rest.trailing_zeros() as usize;
        rest &= rest - 1;
        let v = blk.vals[i];
        let bit_i = 1u32 << i;
        let (value, limit, unit) = if bit_i & LENGTH_WORDS != 0 {
            (v * scale, MAX_COORDINATE_MM, "mm")
        } else if bit_i & ANGLE_WORDS != 0 {
            (v, MAX_COORDINATE_MM, "degrees")
        } else if bit_i == bit(b'F') {
            match feed_mode {
                // Inverse time is 1/minutes, no length: not scaled by G20.
                FeedMode::InverseTime => (v, MAX_FEED, "/min (G93)"),
                FeedMode::PerRevolution => (v * scale, MAX_FEED, "mm/rev"),
                FeedMode::PerMinute => (v * scale, MAX_FEED, "mm/min"),
            }
        } else {
            (v, MAX_SPINDLE_RPM, "rpm")
        };
        if value.is_nan() || value.abs() > limit {
            return Err(out_of_range(blk, i, value, limit, unit));
        }
    }
    Ok(())
}

#[cold]
fn out_of_range(blk: &Block, i: usize, value: f64, limit: f64, unit: &str) -> LexError {
    let letter = match i {
        POLAR_R => '@',
        POLAR_A => '^',
        _ => (b'A' + i as u8) as char,
    };
    let why = if unit == "mm" || unit == "degrees" {
        " (no machine reaches that far from its origin)"
    } else {
        ""
    };
    (
        blk.pos[i] as usize,
        ErrorKind::Invalid,
        format!(
            "{letter}={} {unit} is beyond the limit of {} {unit}{why}",
            show(value),
            show(limit)
        ),
    )
}

/// A number for a message: plain up to 1e15, then with an exponent (not 300 digits).
fn show(v: f64) -> String {
    if v.abs() < 1e15 {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// A dwell time (G4 P, G82/G89 P) at word offset `at`: from 0 to [`MAX_DWELL_SECONDS`].
fn dwell_seconds(p: f64, at: usize) -> Result<f64, LexError> {
    if p < 0.0 {
        return Err((at, ErrorKind::Invalid, "negative dwell time".to_string()));
    }
    if p > MAX_DWELL_SECONDS {
        return Err((
            at,
            ErrorKind::Invalid,
            format!(
                "dwell P={} s is longer than the limit of {} s (24 h)",
                show(p),
                show(MAX_DWELL_SECONDS)
            ),
        ));
    }
    Ok(p)
}

/// The points and offsets of one event within [`MAX_COORDINATE_MM`].
#[inline]
fn check_motion_reach(m: &Motion, blk: &Block) -> Result<(), LexError> {
    match m {
        Motion::Rapid { to, a, .. } | Motion::Linear { to, a, .. } => {
            check_reach("the move ends at", to, a.map(|a| a.to), blk)
        }
        Motion::Arc { to, centre, .. } => {
            check_reach("the arc ends at", to, None, blk)?;
            check_reach("the arc centre is at", centre, None, blk)?;
            // Its chords go where the arc bulges, beyond both ends.
            if let Some(g) = crate::ArcGeometry::from_motion(m) {
                if arc_clearly_within_reach(&g) {
                    return Ok(());
                }
                let (lo, hi) = g.bounds();
                check_reach("the arc reaches", &lo, None, blk)?;
                check_reach("the arc reaches", &hi, None, blk)?;
            }
            Ok(())
        }
        Motion::OffsetChange {
            offset, offset_a, ..
        } => check_reach("the origin offset is", offset, Some(*offset_a), blk),
        Motion::WorkOffsetChange { origin, .. } => {
            check_reach("the work offset is", origin, None, blk)
        }
        _ => Ok(()),
    }
}

/// The arc stays well inside [`MAX_COORDINATE_MM`] without its exact bounds (an `atan2` and
/// up to four extrema): in the plane it keeps within the larger radius of its centre, along
/// the normal between its two ends. The margin (1 mm, far above the rounding of those sums)
/// makes this only say yes where the exact bounds pass too; otherwise they decide.
#[inline]
fn arc_clearly_within_reach(g: &crate::ArcGeometry) -> bool {
    let limit = MAX_COORDINATE_MM - 1.0;
    let (a, b, n) = g.axes;
    let r = g.r0.max(g.r1);
    g.centre[a].abs() + r <= limit
        && g.centre[b].abs() + r <= limit
        && g.from[n].abs() <= limit
        && g.to[n].abs() <= limit
}

#[inline]
fn check_reach(what: &str, p: &Point, a: Option<f64>, blk: &Block) -> Result<(), LexError> {
    let within = |v: f64| v.abs() <= MAX_COORDINATE_MM;
    if p.iter().all(|&v| within(v)) && a.map_or(true, within) {
        return Ok(());
    }
    Err(beyond_reach(what, p, a, blk))
}

#[cold]
fn beyond_reach(what: &str, p: &Point, a: Option<f64>, blk: &Block) -> LexError {
    let axes = [(b'X', p[0]), (b'Y', p[1]), (b'Z', p[2])];
    let (letter, v, unit) = axes
        .into_iter()
        .map(|(l, v)| (l, v, "mm"))
        .chain(a.map(|v| (b'A', v, "degrees")))
        .find(|&(_, v, _)| v.is_nan() || v.abs() > MAX_COORDINATE_MM)
        .unwrap_or((b'X', p[0], "mm"));
    // At that axis's word if the line has one, else at its first coordinate or G word.
    let at = if blk.has(letter) {
        blk.pos_of(letter) as usize
    } else if blk.mask & (LENGTH_WORDS | ANGLE_WORDS) != 0 || blk.ng == 0 {
        first_of(blk, LENGTH_WORDS | ANGLE_WORDS)
    } else {
        blk.g[0].1 as usize
    };
    (
        at,
        ErrorKind::Invalid,
        format!(
            "{what} {}={} {unit}, beyond the limit of {} {unit} (no machine reaches that far from its origin)",
            letter as char,
            show(v),
            show(MAX_COORDINATE_MM)
        ),
    )
}

/// Most chords one spline line may make: bounds the memory a line can take.
const MAX_SPLINE_CHORDS: f64 = 1_000_000.0;

/// G5 (cubic) / G5.1 (quadratic) spline in the XY plane as chords within
/// the arc tolerance (LinuxCNC's NURBS_FEED of order 4 / 3: Bézier curves
/// from the current point to X/Y, control points at I/J from the start and
/// P/Q from the end). Returns the P/Q a following G5 continues from.
#[cold]
#[allow(clippy::too_many_arguments)]
fn spline_motion(
    cfg: &Config,
    queue: &mut Queue,
    st: &State,
    blk: &Block,
    code: u16,
    to: Point,
    feed: f64,
    scale: f64,
    line: u32,
    continue_from: Option<(f64, f64)>,
) -> Result<Option<(f64, f64)>, LexError> {
    let name = if code == 50 { "G5" } else { "G5.1" };
    let at = first_of(blk, bit(b'X') | bit(b'Y') | bit(b'I') | bit(b'J'));
    let invalid = |at: usize, m: String| (at, ErrorKind::Invalid, m);
    if st.plane != Plane::XY {
        return Err(invalid(at, format!("{name} needs the XY plane (G17)")));
    }
    if blk.has(b'Z') {
        return Err(invalid(
            blk.pos_of(b'Z') as usize,
            format!("{name} moves X and Y only (Z word given)"),
        ));
    }
    if blk.mask & POLAR_MASK != 0 {
        return Err(invalid(at, format!("polar coordinates with {name}")));
    }
    let from = st.pos;
    let p0 = [from[0], from[1]];
    let p3 = [to[0], to[1]];
    let (ctrl, pq) = if code == 51 {
        let (i, j) = (blk.get(b'I'), blk.get(b'J'));
        let (i, j) = (i.unwrap_or(0.0) * scale, j.unwrap_or(0.0) * scale);
        if i == 0.0 && j == 0.0 {
            return Err(invalid(
                at,
                "G5.1 needs an I or J control point offset (not both zero)".to_string(),
            ));
        }
        ([p0[0] + i, p0[1] + j], None)
    } else {
        let (Some(p), Some(q)) = (blk.get(b'P'), blk.get(b'Q')) else {
            return Err(invalid(at, "G5 needs both P and Q".to_string()));
        };
        let (p, q) = (p * scale, q * scale);
        let (i, j) = match (blk.get(b'I'), blk.get(b'J'), continue_from) {
            (Some(i), Some(j), _) => (i * scale, j * scale),
            (None, None, Some((p, q))) => (-p, -q),
            (None, None, None) => {
                return Err(invalid(
                    at,
                    "G5 needs I and J unless it continues a previous G5".to_string(),
                ))
            }
            _ => return Err(invalid(at, "G5 needs both I and J, or neither".to_string())),
        };
        ([p0[0] + i, p0[1] + j], Some((p, q)))
    };
    // Bézier control polygon: cubic (p0, c1, c2, p3) or quadratic (p0, c1, p3).
    let c2 = pq.map(|(p, q)| [p3[0] + p, p3[1] + q]);
    let d2 = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| {
        len2(a[0] - 2.0 * b[0] + c[0], a[1] - 2.0 * b[1] + c[1])
    };
    // Largest second derivative over the curve: a chord of parameter step h
    // deviates at most M h^2 / 8 from it.
    let m = match c2 {
        Some(c2) => 6.0 * d2(p0, ctrl, c2).max(d2(ctrl, c2, p3)),
        None => 2.0 * d2(p0, ctrl, p3),
    };
    let tol = cfg.arc_tolerance_mm.max(crate::MIN_TOLERANCE_MM);
    let n = (m / (8.0 * tol)).sqrt().ceil().max(1.0);
    if !n.is_finite() || n > MAX_SPLINE_CHORDS {
        return Err(invalid(
            at,
            format!("{name} would make more than {MAX_SPLINE_CHORDS} chords"),
        ));
    }
    let n = n as u32;
    let eval = |t: f64| -> [f64; 2] {
        let u = 1.0 - t;
        match c2 {
            Some(c2) => {
                let (b0, b1, b2, b3) = (u * u * u, 3.0 * u * u * t, 3.0 * u * t * t, t * t * t);
                [
                    b0 * p0[0] + b1 * ctrl[0] + b2 * c2[0] + b3 * p3[0],
                    b0 * p0[1] + b1 * ctrl[1] + b2 * c2[1] + b3 * p3[1],
                ]
            }
            None => {
                let (b0, b1, b2) = (u * u, 2.0 * u * t, t * t);
                [
                    b0 * p0[0] + b1 * ctrl[0] + b2 * p3[0],
                    b0 * p0[1] + b1 * ctrl[1] + b2 * p3[1],
                ]
            }
        }
    };
    let point = |k: u32| -> Point {
        if k == n {
            return to;
        }
        let p = eval(f64::from(k) / f64::from(n));
        [p[0], p[1], from[2]]
    };
    let feed = if st.feed_mode == FeedMode::PerMinute {
        feed
    } else {
        let length: f64 = (1..=n).map(|k| len3(point(k - 1), point(k))).sum();
        feed_in_mode(st, blk, feed, length)?
    };
    let mut prev = from;
    for k in 1..=n {
        let next = point(k);
        queue.push_back(Motion::Linear {
            line,
            from: prev,
            to: next,
            feed_mm_min: feed,
            a: None,
        });
        prev = next;
    }
    Ok(pq)
}

/// G10 L1 (tool table: `P` tool, `R` radius, `Z` length), L2 (work system
/// `P` 1..9, 0 = the active one, origin set to X/Y/Z, absolute even in G91)
/// and L20 (origin set so that the current position reads X/Y/Z), as
/// LinuxCNC's convert_setup. Returns (L, system 1..9, new origin) for L2/L20.
/// The tool table and offsets changed are the program's view only.
#[cold]
fn g10(
    blk: &Block,
    st: &mut State,
    offsets: &mut [Point; 9],
    tools: &mut crate::ToolTable,
    comp_on: bool,
    scale: f64,
    at: usize,
) -> Result<Option<(u8, u8, Point)>, LexError> {
    let invalid = |at: usize, m: String| (at, ErrorKind::Invalid, m);
    let l = match blk.get(b'L') {
        Some(l) if l == 1.0 || l == 2.0 || l == 20.0 => l as u8,
        Some(l) => {
            return Err((
                blk.pos_of(b'L') as usize,
                ErrorKind::Unsupported,
                format!("G10 L{l} is not supported (L1, L2 and L20 are)"),
            ))
        }
        None => {
            return Err(invalid(
                at,
                "G10 needs an L word (L1, L2 or L20)".to_string(),
            ))
        }
    };
    let p_at = blk.pos_of(b'P') as usize;
    let p = match blk.get(b'P') {
        Some(p) if p >= 0.0 && p.fract() == 0.0 && p <= f64::from(u32::MAX) => p as u32,
        Some(_) => return Err(invalid(p_at, format!("G10 L{l} P must be a whole number"))),
        None => return Err(invalid(at, format!("G10 L{l} needs P"))),
    };
    if l == 1 {
        let Some(tool) = tools.get_mut(&p) else {
            return Err((
                p_at,
                ErrorKind::Unsupported,
                format!("G10 L1 P{p}: tool {p} is not in the machine's tool table"),
            ));
        };
        if let Some(r) = blk.get(b'R') {
            tool.diameter_mm = 2.0 * r * scale;
        }
        if let Some(z) = blk.get(b'Z') {
            tool.length_mm = z * scale;
        }
        return Ok(None);
    }
    if blk.has(b'R') {
        return Err((
            blk.pos_of(b'R') as usize,
            ErrorKind::Unsupported,
            "G10 R (a rotated coordinate system) is not supported".to_string(),
        ));
    }
    if p > 9 {
        return Err(invalid(
            p_at,
            format!("G10 L{l} P{p}: P must be 0 (the active system) or 1..9 (G54..G59.3)"),
        ));
    }
    let idx = if p == 0 {
        st.coord as usize
    } else {
        p as usize - 1
    };
    if comp_on && idx == st.coord as usize {
        return Err(invalid(
            at,
            "cannot change the active coordinate system with cutter radius compensation on"
                .to_string(),
        ));
    }
    let old = offsets[idx];
    let mut new = old;
    let active = offsets[st.coord as usize];
    for (i, letter) in [b'X', b'Y', b'Z'].into_iter().enumerate() {
        if let Some(v) = blk.get(letter) {
            new[i] = if l == 2 {
                v * scale
            } else {
                // The machine position (program's view) less the value.
                st.pos[i] + active[i] - v * scale
            };
        }
    }
    if idx == st.coord as usize {
        for i in 0..3 {
            st.pos[i] += old[i] - new[i];
        }
    }
    offsets[idx] = new;
    Ok(Some((l, idx as u8 + 1, new)))
}

/// Moves this line's events so far behind the moves compensation holds.
#[cold]
fn absorb(queue: &mut Queue, c: &mut Comp) -> Result<(), LexError> {
    if !c.held.is_empty() {
        while let Some(m) = queue.pop_front() {
            c.hold_event(m);
        }
        if c.held.len() > MAX_HELD_EVENTS {
            return Err((
                0,
                ErrorKind::Invalid,
                format!(
                    "more than {MAX_HELD_EVENTS} events wait for the next move under cutter compensation (G41/G42): program a move or G40"
                ),
            ));
        }
    }
    Ok(())
}

/// Releases what compensation holds, unchanged, into the queue.
#[cold]
fn release(queue: &mut Queue, c: &mut Comp) {
    let mut out = Vec::new();
    c.release(&mut out);
    for m in out {
        queue.push_back(m);
    }
}

fn comp_err(at: usize, e: CompError) -> LexError {
    (at, e.0, e.1)
}

/// G41/G42 (D = tool number; without D the tool in the spindle) and
/// G41.1/G42.1 (D = diameter), as LinuxCNC.
#[cold]
fn comp_on(
    c: &mut Comp,
    cfg: &Config,
    blk: &Block,
    st: &State,
    code: u16,
    off: usize,
    scale: f64,
) -> Result<(), LexError> {
    let name = gname(code);
    if st.plane != Plane::XY {
        return Err((
            off,
            ErrorKind::Unsupported,
            format!("{name}: cutter radius compensation is only supported in the XY plane (G17)"),
        ));
    }
    if c.side.is_some() {
        return Err((
            off,
            ErrorKind::Invalid,
            format!("{name}: cutter radius compensation is already on (G40 first)"),
        ));
    }
    let d_at = blk.pos_of(b'D') as usize;
    let diameter = if matches!(code, 411 | 421) {
        match blk.get(b'D') {
            Some(d) => d * scale,
            None => {
                return Err((
                    off,
                    ErrorKind::Invalid,
                    format!("{name} with no D word (the tool diameter)"),
                ))
            }
        }
    } else {
        let tool = match blk.get(b'D') {
            Some(d) if d >= 0.0 && d.fract() == 0.0 && d <= f64::from(u32::MAX) => Some(d as u32),
            Some(_) => {
                return Err((
                    d_at,
                    ErrorKind::Invalid,
                    format!("{name}: D must be a tool number (a non-negative whole number)"),
                ))
            }
            None => None,
        };
        match (tool, tool.or(Some(st.spindle_tool)).and_then(|t| cfg.tools.get(&t))) {
            (_, Some(t)) => t.diameter_mm,
            // Unsupported, not Invalid: the program is fine, the machine
            // lacks the tool (the skip policy may skip the line).
            (Some(t), None) => {
                return Err((
                    d_at,
                    ErrorKind::Unsupported,
                    format!(
                        "{name} D{t}: tool {t} is not in the machine's tool table (cutter compensation needs its diameter)"
                    ),
                ))
            }
            // LinuxCNC: no tool in the spindle has no radius.
            (None, None) if st.spindle_tool == 0 => 0.0,
            (None, None) => {
                return Err((
                    off,
                    ErrorKind::Unsupported,
                    format!(
                        "{name} without D uses the tool in the spindle, T{}, which is not in the tool table",
                        st.spindle_tool
                    ),
                ))
            }
        }
    };
    let mut side = if matches!(code, 410 | 411) {
        Side::Left
    } else {
        Side::Right
    };
    let mut radius = diameter / 2.0;
    if radius < 0.0 {
        radius = -radius;
        side = if side == Side::Left {
            Side::Right
        } else {
            Side::Left
        };
    }
    c.side = Some(side);
    c.radius = radius;
    c.first = true;
    c.tool = [st.pos[0], st.pos[1]];
    Ok(())
}

/// What LinuxCNC refuses while cutter compensation is on.
#[cold]
fn comp_forbidden(
    st: &State,
    g_plane: Option<(u16, u32)>,
    g_units: Option<(u16, u32)>,
    g_coord: Option<(u16, u32)>,
    g_nonmodal: Option<(u16, u32)>,
    g_motion: Option<(u16, u32)>,
) -> Result<(), LexError> {
    let refuse = |g: (u16, u32), what: &str| {
        Err((
            g.1 as usize,
            ErrorKind::Invalid,
            format!(
                "{}: cannot {what} with cutter radius compensation on (G40 first)",
                gname(g.0)
            ),
        ))
    };
    if let Some(g) = g_plane.filter(|g| g.0 != 170) {
        return refuse(g, "change planes");
    }
    if let Some(g) = g_units.filter(|g| (g.0 == 200) != st.inch) {
        return refuse(g, "change units");
    }
    if let Some(g) = g_coord {
        return refuse(g, "change the coordinate system");
    }
    if let Some(g) = g_nonmodal {
        match g.0 {
            280 | 300 | 281 | 301 => return refuse(g, "use G28/G30"),
            530 => return refuse(g, "use G53"),
            520 | 920..=923 => return refuse(g, "change axis offsets"),
            _ => {}
        }
    }
    if let Some(g) = g_motion.filter(|g| matches!(g.0, 730 | 810..=890)) {
        return refuse(g, "use canned cycles");
    }
    Ok(())
}

/// A G0/G1/G2/G3 while cutter compensation is on.
#[cold]
#[allow(clippy::too_many_arguments)]
fn compensated_move(
    cfg: &Config,
    queue: &mut Queue,
    c: &mut Comp,
    st: &State,
    blk: &Block,
    target: Point,
    machine: bool,
    line: u32,
    at: usize,
    scale: f64,
) -> Result<(), LexError> {
    if machine {
        return Err((
            at,
            ErrorKind::Invalid,
            "G53 with cutter radius compensation on".to_string(),
        ));
    }
    absorb(queue, c)?;
    let mut out = Vec::new();
    match st.motion {
        MotionMode::Rapid => c
            .straight(line, true, 0.0, st.pos, target, st.inch, &mut out)
            .map_err(|e| comp_err(at, e))?,
        MotionMode::Linear => {
            let mut feed = feed_mm_min(st.feed, blk)?;
            if st.feed_mode != FeedMode::PerMinute {
                feed = feed_in_mode(st, blk, feed, len3(st.pos, target))?;
            }
            c.straight(line, false, feed, st.pos, target, st.inch, &mut out)
                .map_err(|e| comp_err(at, e))?;
        }
        MotionMode::Cw | MotionMode::Ccw => {
            let feed = feed_mm_min(st.feed, blk)?;
            let mut m = arc_motion_of(
                cfg,
                st,
                blk,
                target,
                st.motion == MotionMode::Cw,
                feed,
                scale,
                line,
            )?;
            if st.feed_mode != FeedMode::PerMinute {
                let length = crate::ArcGeometry::from_motion(&m).map_or(0.0, |g| g.length());
                let f = feed_in_mode(st, blk, feed, length)?;
                if let Motion::Arc { feed_mm_min, .. } = &mut m {
                    *feed_mm_min = f;
                }
            }
            c.arc(&m, st.inch, &mut out).map_err(|e| comp_err(at, e))?;
        }
        _ => {
            return Err((
                at,
                ErrorKind::Invalid,
                "canned cycles with cutter radius compensation on".to_string(),
            ));
        }
    }
    for m in out {
        queue.push_back(m);
    }
    Ok(())
}

#[inline]
fn len3(a: Point, b: Point) -> f64 {
    let (dx, dy, dz) = (b[0] - a[0], b[1] - a[1], b[2] - a[2]);
    (dx * dx + dy * dy + dz * dz).sqrt()
}

/// mm/min of a feed move in G93 (F = 1/minutes for this move of `length`
/// mm, F required on the line) or G95 (F mm per revolution x spindle speed).
#[cold]
fn feed_in_mode(st: &State, blk: &Block, feed: f64, length: f64) -> Result<f64, LexError> {
    let at = first_of(blk, bit(b'X') | bit(b'Y') | bit(b'Z') | bit(b'F'));
    match st.feed_mode {
        FeedMode::InverseTime => {
            if !blk.has(b'F') {
                return Err((
                    at,
                    ErrorKind::Invalid,
                    "inverse-time feed (G93) needs F on every feed move".to_string(),
                ));
            }
            // A move of no length takes no time at any rate.
            Ok(if length > 0.0 { length * feed } else { feed })
        }
        FeedMode::PerRevolution => {
            if st.spindle == SpindleDirection::Off || st.rpm <= 0.0 {
                return Err((
                    at,
                    ErrorKind::Invalid,
                    "feed per revolution (G95) with the spindle stopped".to_string(),
                ));
            }
            Ok(feed * st.rpm)
        }
        FeedMode::PerMinute => Ok(feed),
    }
}

/// Most moves one canned-cycle line may make (pecks x repeats): bounds the
/// memory a line like `G83 Q0.000001 L100000` could take.
const MAX_CYCLE_MOVES: f64 = 1_000_000.0;

/// Expands a canned cycle (XY plane) into the moves LinuxCNC makes
/// (interp_cycles.cc: CYCLE_MACRO and convert_cycle_g*), returns the end.
#[allow(clippy::too_many_arguments)]
fn canned_cycle(
    queue: &mut Queue,
    st: &mut State,
    cyc: &mut CycleState,
    blk: &Block,
    code: u16,
    first: bool,
    scale: f64,
    line: u32,
) -> Result<Point, LexError> {
    let here = first_of(blk, bit(b'X') | bit(b'Y') | bit(b'Z'));
    let invalid = |at: usize, msg: String| (at, ErrorKind::Invalid, msg);
    let name = gname(code);
    if st.plane != Plane::XY {
        return Err((
            here,
            ErrorKind::Unsupported,
            format!("{name} is only supported in the XY plane (G17)"),
        ));
    }
    let feed = match st.feed {
        Some(f) if f > 0.0 => f,
        _ => {
            return Err(invalid(
                here,
                format!("{name} with no feed rate (F) programmed"),
            ))
        }
    };
    let feed = match st.feed_mode {
        FeedMode::PerMinute => feed,
        FeedMode::InverseTime => {
            return Err(invalid(
                here,
                format!("{name} in inverse-time feed (G93): LinuxCNC refuses it too"),
            ))
        }
        FeedMode::PerRevolution => feed_in_mode(st, blk, feed, 0.0)?,
    };
    if first && !blk.has(b'Z') {
        return Err(invalid(
            here,
            format!("{name} needs Z (the bottom of the hole)"),
        ));
    }
    let z_word = blk.get(b'Z').map_or(cyc.z, |z| z * scale);
    let r_word = match blk.get(b'R') {
        Some(r) => r * scale,
        None if !first => cyc.r,
        None => return Err(invalid(here, format!("{name} needs R (the retract plane)"))),
    };
    let repeats = match blk.get(b'L') {
        None => 1.0,
        Some(l) if l >= 1.0 && l.fract() == 0.0 => l,
        Some(_) => {
            return Err(invalid(
                blk.pos_of(b'L') as usize,
                "L (repeats) must be a whole number of at least 1".to_string(),
            ))
        }
    };
    let mut q = 0.0;
    if matches!(code, 730 | 830) {
        q = match blk.get(b'Q') {
            Some(v) => v * scale,
            None if !first => cyc.q,
            None => return Err(invalid(here, format!("{name} needs Q (the peck depth)"))),
        };
        if q <= 0.0 {
            let at = if blk.has(b'Q') {
                blk.pos_of(b'Q') as usize
            } else {
                here
            };
            return Err(invalid(
                at,
                format!("{name} Q (peck depth) must be positive"),
            ));
        }
    }
    let mut dwell = 0.0;
    if matches!(code, 820 | 890) {
        dwell = match blk.get(b'P') {
            Some(v) => dwell_seconds(v, blk.pos_of(b'P') as usize)?,
            None if !first => cyc.p,
            None => return Err(invalid(here, format!("{name} needs P (dwell seconds)"))),
        };
    }
    let mut current_z = st.pos[2];
    let mut old_z = *cyc.initial.get_or_insert(current_z);
    let (mut x, mut y, r, bottom, dx, dy);
    // Polar increments (G91 @ ^) turn about the origin on every repeat.
    let (mut dr, mut da) = (0.0, 0.0);
    if st.absolute {
        if blk.mask & POLAR_MASK != 0 {
            (x, y) = polar_xy(blk, true, st.pos, scale)?;
        } else {
            x = blk.get(b'X').map_or(st.pos[0], |v| v * scale);
            y = blk.get(b'Y').map_or(st.pos[1], |v| v * scale);
        }
        (dx, dy) = (0.0, 0.0);
        r = r_word;
        bottom = z_word;
    } else {
        dx = blk.get(b'X').map_or(0.0, |v| v * scale);
        dy = blk.get(b'Y').map_or(0.0, |v| v * scale);
        if blk.mask & (1 << POLAR_R) != 0 {
            dr = blk.vals[POLAR_R] * scale;
        }
        if blk.mask & (1 << POLAR_A) != 0 {
            da = blk.vals[POLAR_A].to_radians();
        }
        (x, y) = (st.pos[0], st.pos[1]);
        r = r_word + old_z;
        bottom = r + z_word;
    }
    if r < bottom {
        return Err(invalid(
            here,
            format!("{name}: R ({r:.4} mm) is below Z ({bottom:.4} mm)"),
        ));
    }
    let pecks = if q > 0.0 {
        ((r - bottom) / q).ceil()
    } else {
        1.0
    };
    if pecks * repeats * 3.0 > MAX_CYCLE_MOVES {
        return Err(invalid(
            here,
            format!("{name} would make more than {MAX_CYCLE_MOVES} moves (peck depth and repeats)"),
        ));
    }
    let mut at = st.pos;
    let rapid = |q: &mut Queue, at: &mut Point, to: Point| {
        q.push_back(Motion::Rapid {
            line,
            from: *at,
            to,
            a: None,
        });
        *at = to;
    };
    let feed_to = |q: &mut Queue, at: &mut Point, to: Point| {
        q.push_back(Motion::Linear {
            line,
            from: *at,
            to,
            feed_mm_min: feed,
            a: None,
        });
        *at = to;
    };
    // Below the R plane: first straight up to it.
    if old_z < r {
        let up = [at[0], at[1], r];
        rapid(queue, &mut at, up);
        old_z = r;
        current_z = r;
    }
    let clear = if cyc.retract_to_r { r } else { old_z };
    // LinuxCNC 2.9 (the installed rs274): pecks back off 0.010 inch.
    let peck_clearance = 0.254;
    for k in 0..repeats as u64 {
        x += dx;
        y += dy;
        if dr != 0.0 || da != 0.0 {
            if x == 0.0 && y == 0.0 {
                return Err(invalid(
                    here,
                    "incremental polar move at the origin (no angle to start from)".to_string(),
                ));
            }
            let (rad, ang) = (x.hypot(y) + dr, y.atan2(x) + da);
            (x, y) = (rad * ang.cos(), rad * ang.sin());
        }
        if k == 0 && current_z > r {
            rapid(queue, &mut at, [x, y, current_z]);
            rapid(queue, &mut at, [x, y, r]);
        } else {
            rapid(queue, &mut at, [x, y, clear]);
            if clear > r {
                rapid(queue, &mut at, [x, y, r]);
            }
        }
        match code {
            730 | 830 => {
                let mut depth = r - q;
                while depth > bottom {
                    feed_to(queue, &mut at, [x, y, depth]);
                    if code == 830 {
                        rapid(queue, &mut at, [x, y, r]);
                    }
                    rapid(queue, &mut at, [x, y, depth + peck_clearance]);
                    depth -= q;
                }
                feed_to(queue, &mut at, [x, y, bottom]);
                rapid(queue, &mut at, [x, y, clear]);
            }
            820 => {
                feed_to(queue, &mut at, [x, y, bottom]);
                queue.push_back(Motion::Dwell {
                    line,
                    seconds: dwell,
                });
                rapid(queue, &mut at, [x, y, clear]);
            }
            850 => {
                feed_to(queue, &mut at, [x, y, bottom]);
                feed_to(queue, &mut at, [x, y, r]);
                rapid(queue, &mut at, [x, y, clear]);
            }
            890 => {
                feed_to(queue, &mut at, [x, y, bottom]);
                queue.push_back(Motion::Dwell {
                    line,
                    seconds: dwell,
                });
                feed_to(queue, &mut at, [x, y, clear]);
            }
            _ => {
                feed_to(queue, &mut at, [x, y, bottom]);
                rapid(queue, &mut at, [x, y, clear]);
            }
        }
    }
    cyc.r = r_word;
    cyc.z = z_word;
    cyc.q = q;
    cyc.p = dwell;
    Ok([x, y, clear])
}

/// M72 / M73's return: back to the saved units, distance modes, plane, feed,
/// speed, spindle, coolant, work system and motion mode (position, stored
/// G28/G30 positions and tool stay), with the events a change needs.
#[cold]
fn restore_modal(
    offsets: &[Point; 9],
    queue: &mut Queue,
    st: &mut State,
    saved: &State,
    line: u32,
) {
    if saved.coord != st.coord {
        let old = offsets[st.coord as usize];
        let new = offsets[saved.coord as usize];
        for i in 0..3 {
            st.pos[i] += old[i] - new[i];
        }
        queue.push_back(Motion::WorkOffset {
            line,
            system: saved.coord + 1,
        });
    }
    if saved.spindle != st.spindle || saved.rpm != st.rpm {
        queue.push_back(Motion::Spindle {
            line,
            direction: saved.spindle,
            rpm: saved.rpm,
        });
    }
    if saved.mist != st.mist || saved.flood != st.flood {
        queue.push_back(Motion::Coolant {
            line,
            mist: saved.mist,
            flood: saved.flood,
        });
    }
    let (pos, a, tool, g28, g30) = (st.pos, st.a, st.tool, st.g28, st.g30);
    let (g28_a, g30_a, tlo) = (st.g28_a, st.g30_a, st.tlo);
    *st = *saved;
    // No event changes the tool length offset here, so it stays as it is.
    st.tlo = tlo;
    st.pos = pos;
    st.a = a;
    st.tool = tool;
    st.g28 = g28;
    st.g30 = g30;
    st.g28_a = g28_a;
    st.g30_a = g30_a;
}

/// X and Y of a move written with LinuxCNC's polar words (`@` radius, `^`
/// angle in degrees, about the origin; interp_find.cc `find_ends`).
#[cold]
fn polar_xy(blk: &Block, absolute: bool, pos: Point, scale: f64) -> Result<(f64, f64), LexError> {
    let at = first_of(blk, POLAR_MASK);
    if blk.has(b'X') || blk.has(b'Y') {
        return Err((
            at,
            ErrorKind::Invalid,
            "X or Y words with polar coordinates (@ ^)".to_string(),
        ));
    }
    let r_word = (blk.mask & (1 << POLAR_R) != 0).then(|| blk.vals[POLAR_R] * scale);
    let a_word = (blk.mask & (1 << POLAR_A) != 0).then(|| blk.vals[POLAR_A].to_radians());
    let (x, y) = (pos[0], pos[1]);
    let at_origin = x == 0.0 && y == 0.0;
    let (r, a) = if absolute {
        if a_word.is_none() && at_origin {
            return Err((
                at,
                ErrorKind::Invalid,
                "polar radius without an angle at the origin".to_string(),
            ));
        }
        (
            r_word.unwrap_or_else(|| x.hypot(y)),
            a_word.unwrap_or_else(|| y.atan2(x)),
        )
    } else {
        if at_origin {
            return Err((
                at,
                ErrorKind::Invalid,
                "incremental polar move at the origin (no angle to start from)".to_string(),
            ));
        }
        (
            x.hypot(y) + r_word.unwrap_or(0.0),
            y.atan2(x) + a_word.unwrap_or(0.0),
        )
    };
    Ok((r * a.cos(), r * a.sin()))
}

#[inline]
fn add(a: Point, b: Point) -> Point {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline]
fn sub(a: Point, b: Point) -> Point {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// A motion from program coordinates into the work system's frame.
#[cold]
fn shift(m: &mut Motion, off: Point, off_a: f64) {
    match m {
        Motion::Rapid { from, to, a, .. } | Motion::Linear { from, to, a, .. } => {
            *from = add(*from, off);
            *to = add(*to, off);
            if let Some(a) = a {
                a.from += off_a;
                a.to += off_a;
            }
        }
        Motion::Probe { from, to, .. } => {
            *from = add(*from, off);
            *to = add(*to, off);
        }
        Motion::Arc {
            from, to, centre, ..
        } => {
            *from = add(*from, off);
            *to = add(*to, off);
            *centre = add(*centre, off);
        }
        _ => {}
    }
}

/// What system parameters (#5420, `#<_x>`, ...) read.
fn sys_view(st: &State, g92: Point, g92_saved: Point, g92_a: f64, g92_saved_a: f64) -> SysView {
    SysView {
        pos: st.pos,
        pos_a: st.a,
        g28_a: st.g28_a,
        g30_a: st.g30_a,
        g92_a,
        g92_saved_a,
        inch: st.inch,
        absolute: st.absolute,
        coord: st.coord,
        tool: st.tool,
        g28: st.g28,
        g30: st.g30,
        g92,
        g92_saved,
        feed_mm_min: st.feed.unwrap_or(0.0),
        rpm: st.rpm,
        plane: match st.plane {
            Plane::XY => 170,
            Plane::ZX => 180,
            Plane::YZ => 190,
        },
        motion_g10: match st.motion {
            MotionMode::Rapid => 0,
            MotionMode::Linear => 10,
            MotionMode::Cw => 20,
            MotionMode::Ccw => 30,
            MotionMode::None => 800,
            MotionMode::Unsupported(c)
            | MotionMode::Cycle(c)
            | MotionMode::Spline(c)
            | MotionMode::Probe(c) => i32::from(c),
        },
    }
}

/// Only blanks and comments may follow an O-word's arguments.
fn rest_is_comment(b: &[u8], mut i: usize) -> Result<(), LexError> {
    while i < b.len() {
        match b[i] {
            b' ' | b'\t' | b'\r' => i += 1,
            b';' => return Ok(()),
            b'(' => match b[i..].iter().position(|&c| c == b')') {
                Some(n) => i += n + 1,
                None => return Err((i, ErrorKind::Syntax, "unclosed comment '('".to_string())),
            },
            c => {
                return Err((
                    i,
                    ErrorKind::Syntax,
                    format!("unexpected '{}' after the O-word", c as char),
                ))
            }
        }
    }
    Ok(())
}

/// The feed in force (`feed`, mm/min) for a feed move of this line, or the error naming it.
fn feed_mm_min(feed: Option<f64>, blk: &Block) -> Result<f64, LexError> {
    match feed {
        None => Err((
            first_of(
                blk,
                bit(b'X') | bit(b'Y') | bit(b'Z') | bit(b'I') | bit(b'J') | bit(b'K') | bit(b'R'),
            ),
            ErrorKind::Invalid,
            "feed move with no feed rate (F) programmed".to_string(),
        )),
        Some(f) if f <= 0.0 => Err((
            if blk.has(b'F') {
                blk.pos_of(b'F') as usize
            } else {
                first_of(blk, bit(b'X') | bit(b'Y') | bit(b'Z'))
            },
            ErrorKind::Invalid,
            "feed move with zero feed rate".to_string(),
        )),
        Some(f) => Ok(f),
    }
}

/// Builds a [`Motion::Arc`] from the current line (grbl / LinuxCNC rules).
#[allow(clippy::too_many_arguments)]
fn arc_motion_of(
    cfg: &Config,
    st: &State,
    blk: &Block,
    to: Point,
    clockwise: bool,
    feed: f64,
    scale: f64,
    line: u32,
) -> Result<Motion, LexError> {
    let (a, b, n) = st.plane.axes();
    const AXIS: [u8; 3] = [b'X', b'Y', b'Z'];
    const OFFSET: [u8; 3] = [b'I', b'J', b'K'];
    let from = st.pos;
    // Column for arc errors; only computed when there is one.
    let arc_at = || {
        first_of(
            blk,
            bit(b'X') | bit(b'Y') | bit(b'Z') | bit(b'I') | bit(b'J') | bit(b'K') | bit(b'R'),
        )
    };
    // An offset along the plane normal means the program expects another plane.
    if let Some(v) = blk.get(OFFSET[n]) {
        if v != 0.0 {
            return Err((
                blk.pos_of(OFFSET[n]) as usize,
                ErrorKind::Invalid,
                format!(
                    "{} word given for an arc in the {} plane",
                    OFFSET[n] as char,
                    plane_name(st.plane)
                ),
            ));
        }
    }
    let has_plane_offset = blk.has(OFFSET[a]) || blk.has(OFFSET[b]);
    let (da, db) = (to[a] - from[a], to[b] - from[b]);
    let chord = len2(da, db);
    let mut centre = from;
    if let Some(r_word) = blk.get(b'R') {
        if has_plane_offset {
            return Err((
                blk.pos_of(b'R') as usize,
                ErrorKind::Invalid,
                "arc with both R and I/J/K".to_string(),
            ));
        }
        if !(blk.has(AXIS[a]) || blk.has(AXIS[b])) {
            return Err((
                blk.pos_of(b'R') as usize,
                ErrorKind::Arc,
                format!(
                    "R arc needs an end point in the {} plane",
                    plane_name(st.plane)
                ),
            ));
        }
        if chord < FULL_CIRCLE_EPS_MM {
            return Err((
                blk.pos_of(b'R') as usize,
                ErrorKind::Arc,
                "R arc with the same start and end point (use I/J/K for a full circle)".to_string(),
            ));
        }
        let r = r_word.abs() * scale;
        let half = chord / 2.0;
        if half - r > cfg.arc_radius_abs_tolerance_mm {
            return Err((
                blk.pos_of(b'R') as usize,
                ErrorKind::Arc,
                format!(
                    "arc radius {r:.4} mm too small to reach the end point ({half:.4} mm away)"
                ),
            ));
        }
        // Slightly too small R (within tolerance) is a half circle (LinuxCNC).
        let h = if half >= r {
            0.0
        } else {
            (r * r - half * half).sqrt()
        };
        // grbl: positive R and G2 put the centre right of the chord.
        let mut side = if clockwise { -1.0 } else { 1.0 };
        if r_word < 0.0 {
            side = -side;
        }
        // Left normal of the chord, unit length.
        let (pa, pb) = (-db / chord, da / chord);
        centre[a] = from[a] + da / 2.0 + side * h * pa;
        centre[b] = from[b] + db / 2.0 + side * h * pb;
    } else {
        if !has_plane_offset {
            return Err((
                arc_at(),
                ErrorKind::Arc,
                format!(
                    "arc needs R or {}/{} offsets in the {} plane",
                    OFFSET[a] as char,
                    OFFSET[b] as char,
                    plane_name(st.plane)
                ),
            ));
        }
        if st.arc_absolute {
            if !(blk.has(OFFSET[a]) && blk.has(OFFSET[b])) {
                return Err((
                    arc_at(),
                    ErrorKind::Arc,
                    "G90.1 arc needs both centre words of the plane".to_string(),
                ));
            }
            centre[a] = blk.get(OFFSET[a]).unwrap_or(0.0) * scale;
            centre[b] = blk.get(OFFSET[b]).unwrap_or(0.0) * scale;
        } else {
            centre[a] = from[a] + blk.get(OFFSET[a]).unwrap_or(0.0) * scale;
            centre[b] = from[b] + blk.get(OFFSET[b]).unwrap_or(0.0) * scale;
        }
        let r0 = len2(from[a] - centre[a], from[b] - centre[b]);
        let r1 = len2(to[a] - centre[a], to[b] - centre[b]);
        if r0 == 0.0 || r1 == 0.0 {
            return Err((
                arc_at(),
                ErrorKind::Arc,
                "arc with zero radius (centre on an end point)".to_string(),
            ));
        }
        let d = (r1 - r0).abs();
        if d > cfg.arc_radius_max_error_mm
            || (d > cfg.arc_radius_abs_tolerance_mm && d > cfg.arc_radius_rel_error * r0)
        {
            return Err((
                arc_at(),
                ErrorKind::Arc,
                format!(
                    "radius to end of arc ({r1:.4} mm) differs from radius to start ({r0:.4} mm) by {d:.4} mm"
                ),
            ));
        }
    }
    // A huge radius (a typo, or 1e30 in a file) would make linearise emit
    // billions of chords for one line; no machine has such an arc.
    let r_max = len2(from[a] - centre[a], from[b] - centre[b]);
    if r_max.is_nan() || r_max > cfg.max_arc_radius_mm {
        return Err((
            arc_at(),
            ErrorKind::Arc,
            format!(
                "arc radius {r_max:.4} mm is larger than the {} mm limit",
                cfg.max_arc_radius_mm
            ),
        ));
    }
    centre[n] = from[n];
    let turns = match blk.get(b'P') {
        None => 1,
        Some(p) if p >= 1.0 && p.fract() == 0.0 && p <= MAX_TURNS => p as u32,
        Some(_) => {
            return Err((
                blk.pos_of(b'P') as usize,
                ErrorKind::Invalid,
                format!("arc P (turns) must be an integer from 1 to {MAX_TURNS}"),
            ))
        }
    };
    let (u0, v0) = (from[a] - centre[a], from[b] - centre[b]);
    let (u1, v1) = (to[a] - centre[a], to[b] - centre[b]);
    let mut sweep = if chord < FULL_CIRCLE_EPS_MM {
        TAU
    } else {
        let ang = (u0 * v1 - v0 * u1).atan2(u0 * u1 + v0 * v1);
        let s = if clockwise { -ang } else { ang };
        if s < 0.0 {
            s + TAU
        } else {
            s
        }
    };
    sweep += TAU * f64::from(turns - 1);
    Ok(Motion::Arc {
        line,
        from,
        to,
        centre,
        plane: st.plane,
        clockwise,
        feed_mm_min: feed,
        turns,
        sweep_rad: sweep,
    })
}

/// G codes and axis words of a line that could not be lexed, found leniently
/// (comments skipped, unparsable numbers ignored).
struct Scan {
    g: [u16; 16],
    ng: usize,
    axes: bool,
}

fn lenient_scan(b: &[u8]) -> Scan {
    let mut scan = Scan {
        g: [0; 16],
        ng: 0,
        axes: false,
    };
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'(' => {
                i += b[i..]
                    .iter()
                    .position(|&c| c == b')')
                    .unwrap_or(b.len() - i);
            }
            b';' => break,
            c => {
                let up = c & !0x20;
                if up == b'G' || up == b'X' || up == b'Y' || up == b'Z' || up == b'A' {
                    let mut j = i + 1;
                    if let Ok(v) = crate::lex::parse_number(b, &mut j) {
                        if up == b'G' {
                            let t = v * 10.0;
                            if (0.0..9999.5).contains(&t) && scan.ng < scan.g.len() {
                                scan.g[scan.ng] = (t + 0.5) as u16;
                                scan.ng += 1;
                            }
                        } else {
                            scan.axes = true;
                        }
                        i = j;
                        continue;
                    }
                }
            }
        }
        i += 1;
    }
    scan
}

/// Byte offset of the first present word among `mask` (0 if none).
fn first_of(blk: &Block, mask: u32) -> usize {
    let mut best = u32::MAX;
    for i in 0..28 {
        if blk.mask & mask & (1 << i) != 0 {
            best = best.min(blk.pos[i]);
        }
    }
    if best == u32::MAX {
        0
    } else {
        best as usize
    }
}

fn plane_name(p: Plane) -> &'static str {
    match p {
        Plane::XY => "XY (G17)",
        Plane::ZX => "XZ (G18)",
        Plane::YZ => "YZ (G19)",
    }
}

fn gname(code: u16) -> String {
    if code % 10 == 0 {
        format!("G{}", code / 10)
    } else {
        format!("G{}.{}", code / 10, code % 10)
    }
}

fn mname(code: u16) -> String {
    if code % 10 == 0 {
        format!("M{}", code / 10)
    } else {
        format!("M{}.{}", code / 10, code % 10)
    }
}

#[cold]
fn unsupported_g(code: u16, off: u32, why: &str) -> LexError {
    (
        off as usize,
        ErrorKind::Unsupported,
        format!("{} is not supported: {why}", gname(code)),
    )
}

#[cold]
fn unknown_g(code: u16, off: u32) -> LexError {
    (
        off as usize,
        ErrorKind::Unsupported,
        format!("{} is not supported", gname(code)),
    )
}

#[cold]
fn same_group_m(a: u16, b: u16, off: u32) -> LexError {
    (
        off as usize,
        ErrorKind::Invalid,
        format!("{} and {} are in the same modal group", mname(a), mname(b)),
    )
}

impl<R: BufRead> Interpreter<R> {
    /// Runs the program to its end, as iterating does, handing each motion to `f` where it
    /// waits in the queue instead of moving it out: a [`Motion`] is a hundred bytes, and
    /// copying each out of the queue and through `Option<Result<..>>` cost [`crate::analyse`]
    /// (which keeps nothing of it) a tenth of its time. The same motions in the same order;
    /// the first error, the interpreter's or `f`'s, ends it.
    pub(crate) fn for_each_motion<E: From<GcodeError>>(
        &mut self,
        mut f: impl FnMut(&Motion) -> Result<(), E>,
    ) -> Result<(), E> {
        loop {
            while let Some(m) = self.queue.front() {
                let r = f(m);
                self.queue.drop_front();
                r?;
            }
            if self.done {
                return Ok(());
            }
            if let Err(e) = self.step() {
                self.done = true;
                self.queue.clear();
                return Err(e.into());
            }
        }
    }
}

impl<R: BufRead> Iterator for Interpreter<R> {
    type Item = Result<Motion, GcodeError>;

    #[inline]
    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(m) = self.queue.pop_front() {
                return Some(Ok(m));
            }
            if self.done {
                return None;
            }
            if let Err(e) = self.step() {
                self.done = true;
                self.queue.clear();
                return Some(Err(e));
            }
        }
    }
}
