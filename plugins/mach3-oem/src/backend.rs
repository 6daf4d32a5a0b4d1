//! The `mach3-oem` machine backend: Fresa's backend contract mapped onto Mach3's OEM buttons,
//! DROs and LEDs, through the agent. A poller thread reads the whole status in one batch at
//! `poll_hz`, turns DRO 816 into line acknowledgements and LED 804 into the end of a run.
//! Requests never wait on anything but the agent link, which has a timeout.

use crate::client::{AgentClient, LinkError};
use crate::codes::{Code, IO_LEDS};
use crate::config::Config;
use crate::mach3::{Call, ErrorKind};
use crate::protocol::{CallResult, FEATURE_GET_VAR, PROGRAM_CHUNK_BYTES};
use fresa_plugin_api::backend::{LoadProgram, MachineBackend};
use fresa_plugin_api::contract::{
    io, Axis, AxisValues, Event, IoValue, MachineState, MachineStatus, OffsetTable, OutputName,
    Probe, ProbeOutcome, ProbeUntil, ProgramLoaded, RunAction, RunAnswer, RunOutcome, WorkOffset,
};
use fresa_plugin_api::{Host, PluginError};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Why a height map is refused: Fresa can only correct points it sends itself.
pub const HEIGHT_MAP_REFUSAL: &str = "mach3-oem cannot apply a height map: Mach3 interprets the \
     program file itself, so Fresa never sees the points it cuts (use Mach3's own \
     auto-levelling, or a backend that streams points: sim-machine, kawasaki-as)";

pub type EventSink = Arc<dyn Fn(&Event) + Send + Sync>;

/// Why mach3-oem does not start a program at a line. Mach3 is handed the file and starts it at
/// its Line DRO without rebuilding the modal state of the lines before (units, distance mode,
/// work offset, spindle), and its own "Run from here" (OEM button 1016) opens a dialog on
/// Mach3's screen for the operator to confirm its preparatory move: from outside, Fresa can
/// neither carry out a safe approach in Mach3's modal state nor confirm Mach3's.
pub const NO_PREAMBLE: &str = "mach3-oem cannot start a program at a line safely: Mach3 starts a \
    file at its Line DRO without rebuilding the modal state of the lines before (units, \
    distance mode, work offset, spindle), and its own Run from here (OEM button 1016) asks the \
    operator to confirm its preparatory move on Mach3's screen; use Run from here at the Mach3 \
    PC instead";

/// How long a started run may show no "running" LED before it counts as ended (Mach3 lights it
/// a moment after cycle start; a very short program may also finish between two polls).
const START_GRACE: Duration = Duration::from_secs(2);
/// How long a stop or cancel waits for Mach3 to stop running the program.
const STOP_WAIT: Duration = Duration::from_secs(5);
const BACKOFF_MIN: Duration = Duration::from_millis(200);
const BACKOFF_MAX: Duration = Duration::from_secs(5);
/// How long reset waits for LED 800 to go out.
const RESET_CONFIRM: Duration = Duration::from_secs(2);
/// How long the rapid override's LED may take to light after its toggle was pressed.
const TOGGLE_CONFIRM: Duration = Duration::from_millis(500);
/// G31's trip: Mach3's parameters #2000-#2003 (X, Y, Z, A, in work coordinates).
const VAR_PROBE_X: i16 = 2000;
/// How far (mm) a G31 may come to rest from its end and still count as having run its whole
/// distance: the line's 4 decimals, with room for Mach3's own rounding to steps.
const PROBE_END_TOLERANCE: f64 = 0.001;
/// How far (mm) a reported trip may lie outside the probed path (the G31's start to where it
/// came to rest) and still be believed.
const PROBE_TRIP_TOLERANCE: f64 = 0.01;

struct Link {
    client: AgentClient,
    /// After a failed connect: no new attempt before this.
    retry_at: Option<Instant>,
    backoff: Duration,
    last_error: String,
}

#[derive(Debug, Clone, Copy)]
struct Loaded {
    run: i64,
    lines: u32,
    start_line: u32,
    /// The last line that does anything (trailing comments and blank lines do not): a run
    /// that ends there without M2/M30 completed.
    last_active_line: u32,
}

/// A G31 sent by `probe`, followed by the poller until its motion ended.
#[derive(Debug, Clone, Copy)]
struct ProbeTrack {
    id: u64,
    axis: Axis,
    /// The probed axis's machine position when the G31 was sent.
    start: f64,
    /// Where the G31 line ends on that axis, work coordinates (as sent).
    target_work: f64,
    started: Instant,
    saw_moving: bool,
    stop_requested: bool,
    /// Motion ended: the outcome is read next (`Inner::finish_probe`).
    ended: bool,
}

#[derive(Debug, Clone, Copy)]
struct RunTrack {
    loaded: Loaded,
    acked: u32,
    saw_running: bool,
    started: Instant,
    stop_requested: bool,
}

struct Shared {
    status: MachineStatus,
    polled: bool,
    loaded: Option<Loaded>,
    run: Option<RunTrack>,
    /// Machine origins of G54..G59 as last read or set (Mach3 shows only the active one).
    offsets: [[f64; 4]; 6],
    probe: Option<ProbeTrack>,
    /// The MDI line that puts back the modal state a probe changed (G90, G31, F), until it
    /// has been sent to a Mach3 out of reset.
    restore: Option<String>,
    shutdown: bool,
}

struct Inner {
    cfg: Config,
    sink: EventSink,
    link: Mutex<Link>,
    shared: Mutex<Shared>,
    wake: Condvar,
    /// Held for a whole poll (read + apply), so an older reading never overwrites a newer one.
    polling: Mutex<()>,
}

pub struct Mach3Backend {
    inner: Arc<Inner>,
    poller: Mutex<Option<JoinHandle<()>>>,
}

fn offline(reason: String) -> MachineStatus {
    let (inputs, outputs) = io_maps(None);
    MachineStatus {
        state: MachineState::Offline,
        reason: Some(reason),
        inputs,
        outputs,
        ..Default::default()
    }
}

type Inputs = BTreeMap<String, Option<bool>>;
type Outputs = BTreeMap<String, Option<IoValue>>;

/// The status's inputs and outputs from the I/O LEDs (`None`: every supported name unknown,
/// as while Mach3 does not answer). The e-stop input is the reset LED.
fn io_maps(p: Option<&Poll>) -> (Inputs, Outputs) {
    let lit = |code: Code| -> Option<bool> {
        let i = IO_LEDS.iter().position(|(c, _, _)| *c == code)?;
        p.map(|p| p.io_leds.get(i).copied().unwrap_or(false))
    };
    let mut inputs: Inputs = BTreeMap::new();
    let mut outputs: Outputs = BTreeMap::new();
    inputs.insert(io::ESTOP.into(), p.map(|p| p.estop));
    for (code, name, is_output) in IO_LEDS {
        if !is_output {
            inputs.insert((*name).into(), lit(*code));
        }
    }
    let cw = lit(Code::SpindleCwLed);
    let ccw = lit(Code::SpindleCcwLed);
    let on = |v: Option<bool>| v.map(IoValue::On);
    outputs.insert(io::SPINDLE.into(), on(cw.zip(ccw).map(|(a, b)| a || b)));
    outputs.insert(io::SPINDLE_CCW.into(), on(ccw));
    outputs.insert(io::COOLANT_FLOOD.into(), on(lit(Code::FloodLed)));
    outputs.insert(io::COOLANT_MIST.into(), on(lit(Code::MistLed)));
    (inputs, outputs)
}

fn mach3_error(e: &crate::mach3::Mach3Error) -> PluginError {
    match e.kind {
        ErrorKind::NotRunning => PluginError::new(
            "offline",
            format!("Mach3 is not running on the agent's PC: {}", e.message),
        ),
        ErrorKind::Invalid => PluginError::invalid(format!("Mach3 refused: {}", e.message)),
        _ => PluginError::new("mach3_error", e.message.clone()),
    }
}

fn link_error(e: &LinkError) -> PluginError {
    PluginError::new("offline", e.to_string())
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(0.0)
}

/// How probe `t` ended, from Mach3 at rest (`p`) and its trip parameters #2000-#2003 (work
/// coordinates): `(outcome, trip in machine coordinates, message)`. Mach3's G31 leaves no
/// flag saying whether it touched; the probe input still active where the axis came to rest
/// (pressed against the plate) says it did, as Mach3's own probing macros take it.
fn probe_outcome(
    t: &ProbeTrack,
    p: &Poll,
    vars: Result<Vec<f64>, String>,
) -> (ProbeOutcome, Option<AxisValues>, Option<String>) {
    let i = t.axis.index();
    let rest = p.work[i] + p.fixture[i];
    let failed = |m: String| (ProbeOutcome::Failed, None, Some(m));
    if p.estop {
        return failed("Mach3 went into reset during the probe (e-stop or a limit switch)".into());
    }
    if p.led(Code::ProbeLed) {
        let vars = match vars {
            Ok(v) if v.len() == 4 => v,
            Ok(_) => return failed("the probe touched, but Mach3's trip was not read".into()),
            Err(e) => {
                return failed(format!(
                    "the probe touched, but Mach3's trip (#2000-#2003) could not be read: {e}"
                ))
            }
        };
        let trip: [f64; 4] = std::array::from_fn(|k| vars[k] + p.fixture[k]);
        let (lo, hi) = (t.start.min(rest), t.start.max(rest));
        if (lo - PROBE_TRIP_TOLERANCE..=hi + PROBE_TRIP_TOLERANCE).contains(&trip[i]) {
            return (
                ProbeOutcome::Tripped,
                Some(AxisValues::from_array(trip)),
                None,
            );
        }
        return failed(format!(
            "Mach3 shows the probe touching, but its trip #{} = {:.4} (machine {:.4}) is not \
             between where the G31 started ({:.4}) and where it stopped ({rest:.4})",
            i as i16 + VAR_PROBE_X,
            vars[i],
            trip[i],
            t.start
        ));
    }
    if t.stop_requested {
        return (
            ProbeOutcome::Stopped,
            None,
            Some("stopped before the probe touched".into()),
        );
    }
    let short = (p.work[i] - t.target_work).abs();
    if short <= PROBE_END_TOLERANCE {
        return (ProbeOutcome::NotTripped, None, None);
    }
    if !t.saw_moving && (rest - t.start).abs() <= 1e-9 {
        return failed(
            "Mach3 did not move for the G31 line (see Mach3's status line for why)".into(),
        );
    }
    failed(format!(
        "the G31 came to rest {short:.3} mm short of its end with the probe open (stopped on \
         the Mach3 screen, or a soft limit?)"
    ))
}

/// The status batch's answers (`Inner::status_calls`, in its order) as a [`Poll`]; the first
/// that failed says why (Mach3 not running, not answering).
fn parse_poll(results: Vec<CallResult>) -> Result<Poll, String> {
    let mut values = Vec::with_capacity(results.len());
    for r in results {
        match r {
            CallResult::Ok(v) => values.push(v),
            CallResult::Err(e) if e.kind == ErrorKind::NotRunning => {
                return Err(format!(
                    "Mach3 is not running on the agent's PC ({}); retrying",
                    e.message
                ))
            }
            CallResult::Err(e) => return Err(format!("Mach3 did not answer: {e}; retrying")),
        }
    }
    // Taken in `status_calls`' order: DROs, then LEDs.
    let mut next = values.iter();
    let mut take = move || next.next();
    let n = |v: Option<&Value>| v.map(num).unwrap_or(0.0);
    let b = |v: Option<&Value>| v.and_then(Value::as_bool).unwrap_or(false);
    let work = std::array::from_fn(|_| n(take()));
    let fixture = std::array::from_fn(|_| n(take()));
    let (fixture_number, line, feed) = (n(take()), n(take()), n(take()));
    let (fro, sro, rapid_override) = (n(take()), n(take()), n(take()));
    let (estop, running, paused) = (b(take()), b(take()), b(take()));
    let (moving, rapid_override_on) = (b(take()), b(take()));
    Ok(Poll {
        work,
        fixture,
        fixture_number,
        line,
        feed,
        fro,
        sro,
        rapid_override,
        estop,
        running,
        paused,
        moving,
        rapid_override_on,
        io_leds: (0..IO_LEDS.len()).map(|_| b(take())).collect(),
    })
}

/// The status batch: what is read, in this order.
struct Poll {
    work: [f64; 4],
    fixture: [f64; 4],
    fixture_number: f64,
    line: f64,
    feed: f64,
    fro: f64,
    sro: f64,
    rapid_override: f64,
    estop: bool,
    running: bool,
    paused: bool,
    moving: bool,
    /// "Override of rapid feeds" is on: the rapid override DRO is in force.
    rapid_override_on: bool,
    /// The LEDs of `IO_LEDS`, in its order.
    io_leds: Vec<bool>,
}

impl Poll {
    fn led(&self, code: Code) -> bool {
        IO_LEDS
            .iter()
            .position(|(c, _, _)| *c == code)
            .and_then(|i| self.io_leds.get(i).copied())
            .unwrap_or(false)
    }
}

/// The modal state a jog, MDI line or probe changes, as read before it.
struct Modal {
    incremental: bool,
    /// DRO 819: 0 (G0), 1 (G1), or another motion mode that cannot be re-entered alone.
    motion: i64,
    feed: f64,
    /// Feed override, %.
    fro: f64,
}

impl Modal {
    /// The MDI line that puts it back. G2/G3 cannot be re-entered without an arc, so then the
    /// motion mode is left to the next program line, unless `motion_fallback` names one.
    fn restore(&self, motion_fallback: Option<&str>) -> String {
        let mut line = String::from(if self.incremental { "G91" } else { "G90" });
        match (self.motion, motion_fallback) {
            (0, _) => line.push_str(" G0"),
            (1, _) => line.push_str(" G1"),
            (_, Some(g)) => {
                line.push(' ');
                line.push_str(g);
            }
            (_, None) => {}
        }
        // F0 too: the F a move or probe set must not stay behind.
        if self.feed.is_finite() && self.feed >= 0.0 {
            line.push_str(&format!(" F{}", self.feed));
        }
        line
    }

    /// The F that makes a move go at `feed` mm/min under this feed override (Mach3 applies
    /// FRO to MDI moves; jogs and probes keep their own feed).
    fn own_feed(&self, feed: f64, what: &str) -> Result<f64, PluginError> {
        if !(self.fro.is_finite() && self.fro > 0.0) {
            return Err(PluginError::new(
                "busy",
                format!(
                    "cannot {what}: Mach3's feed override is {} %, so nothing would move; set \
                     it above 0 first",
                    self.fro
                ),
            ));
        }
        Ok(feed * 100.0 / self.fro)
    }
}

impl Inner {
    fn lock(&self) -> MutexGuard<'_, Shared> {
        self.shared.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn emit(&self, events: Vec<Event>) {
        for e in &events {
            (self.sink)(e);
        }
    }

    /// One agent request; connects (respecting the backoff) when not connected.
    fn batch(&self, calls: Vec<Call>, urgent: bool) -> Result<Vec<CallResult>, LinkError> {
        let mut link = self.link.lock().unwrap_or_else(|e| e.into_inner());
        if !link.client.is_connected() {
            if let Some(at) = link.retry_at {
                if Instant::now() < at {
                    return Err(LinkError::Unreachable {
                        addr: self.cfg.agent.clone(),
                        message: format!("{} (retrying)", link.last_error),
                    });
                }
            }
        }
        match link.client.batch(calls, urgent) {
            Ok(r) => {
                link.retry_at = None;
                link.backoff = BACKOFF_MIN;
                Ok(r)
            }
            Err(e) => {
                link.last_error = match &e {
                    LinkError::Unreachable { message, .. } => message.clone(),
                    LinkError::Refused { error, .. } => error.to_string(),
                };
                link.retry_at = Some(Instant::now() + link.backoff);
                link.backoff = (link.backoff * 2).min(BACKOFF_MAX);
                Err(e)
            }
        }
    }

    /// Runs `calls` and returns their values, or the first failure.
    fn exec(&self, calls: Vec<Call>, urgent: bool) -> Result<Vec<Value>, PluginError> {
        let results = self.batch(calls, urgent).map_err(|e| link_error(&e))?;
        results
            .into_iter()
            .map(|r| match r {
                CallResult::Ok(v) => Ok(v),
                CallResult::Err(e) => Err(mach3_error(&e)),
            })
            .collect()
    }

    fn button(&self, code: Code, urgent: bool) -> Result<(), PluginError> {
        let code = self.cfg.codes.get(code);
        self.exec(vec![Call::DoOemButton { code }], urgent)
            .map(|_| ())
    }

    fn status_calls(&self) -> Vec<Call> {
        let c = &self.cfg.codes;
        let mut calls = Vec::with_capacity(18);
        for i in 0..4 {
            calls.push(Call::GetOemDro {
                code: c.axis(Code::PosX, i),
            });
        }
        for i in 0..4 {
            calls.push(Call::GetOemDro {
                code: c.axis(Code::FixtureX, i),
            });
        }
        for code in [
            Code::FixtureNumber,
            Code::Line,
            Code::Feed,
            Code::FeedOverride,
            Code::SpindleOverride,
            Code::RapidOverride,
        ] {
            calls.push(Call::GetOemDro { code: c.get(code) });
        }
        for code in [
            Code::EstopLed,
            Code::RunningLed,
            Code::PausedLed,
            Code::MovingLed,
            Code::RapidOverrideLed,
        ] {
            calls.push(Call::GetOemLed { code: c.get(code) });
        }
        for (code, _, _) in IO_LEDS {
            calls.push(Call::GetOemLed { code: c.get(*code) });
        }
        calls
    }

    fn read_poll(&self) -> Result<Poll, String> {
        let results = self
            .batch(self.status_calls(), false)
            .map_err(|e| format!("{e}; retrying"))?;
        parse_poll(results)
    }

    /// Reads the status from Mach3 and publishes what changed: status, state, line
    /// acknowledgements and the end of a run.
    fn poll(&self) {
        let _one_at_a_time = self.polling.lock().unwrap_or_else(|e| e.into_inner());
        let polled = self.read_poll();
        let mut sh = self.lock();
        let mut events = Vec::new();
        let status = match polled {
            Err(reason) => {
                if let Some(t) = sh.run.take() {
                    events.push(Event::RunEnded {
                        run: t.loaded.run,
                        outcome: RunOutcome::Failed,
                        message: Some(format!(
                            "lost Mach3 after line {} ({reason}); Mach3 may still be running the \
                             program: check the machine, then resume the job",
                            t.acked
                        )),
                    });
                }
                if let Some(t) = sh.probe.take() {
                    events.push(Event::ProbeEnded {
                        id: t.id,
                        outcome: ProbeOutcome::Failed,
                        trip: None,
                        position: sh.status.machine_position,
                        message: Some(format!(
                            "lost Mach3 during the probe ({reason}); Mach3 may still be moving: \
                             check the machine"
                        )),
                    });
                }
                offline(reason)
            }
            Ok(p) => self.track(&mut sh, &p, &mut events),
        };
        self.publish(&mut sh, status, events);
        let ended = sh.probe.filter(|t| t.ended);
        let put_back = match (&sh.probe, sh.status.state) {
            (None, MachineState::Idle) => sh.restore.clone(),
            _ => None,
        };
        drop(sh);
        if let Some(t) = ended {
            self.finish_probe(t);
        } else if let Some(line) = put_back {
            self.put_back(line);
        }
    }

    /// Publishes `status` and what it implies (state change, alarm), then `events`, in the
    /// order they happened. Under the lock, so events leave in the order states were seen.
    fn publish(&self, sh: &mut Shared, status: MachineStatus, mut events: Vec<Event>) {
        let before = sh.status.clone();
        sh.polled = true;
        if status.state != before.state {
            events.insert(
                0,
                Event::StateChanged {
                    from: before.state,
                    to: status.state,
                },
            );
            if status.state == MachineState::Alarm && before.state != MachineState::Offline {
                // Into reset while connected: the audit log records why (and which switch).
                let input = status
                    .inputs
                    .iter()
                    .find(|(name, v)| name.starts_with(io::LIMIT) && **v == Some(true))
                    .map(|(name, _)| name.clone());
                events.push(Event::Alarm {
                    message: status.alarm.clone().unwrap_or_default(),
                    input,
                });
            }
        }
        if status != before {
            sh.status = status.clone();
            events.insert(0, Event::Status(status));
        }
        self.emit(events);
    }

    /// Sends the line that puts back the modal state a probe changed (its motion had ended
    /// while Mach3 was in reset, or the link dropped before it could be sent).
    fn put_back(&self, line: String) {
        if self
            .exec(vec![Call::Code { line: line.clone() }], false)
            .is_ok()
        {
            let mut sh = self.lock();
            if sh.restore.as_ref() == Some(&line) {
                sh.restore = None;
            }
        }
    }

    /// The probe's motion ended: reads Mach3 again (everything now at rest), its trip
    /// (#2000-#2003) and, in the same batch, puts back the modal state; then publishes the
    /// status and, after it (the state has left `jogging`), `probe_ended`. If the link fails
    /// here, the next poll reports the probe lost.
    fn finish_probe(&self, t: ProbeTrack) {
        let mut calls = self.status_calls();
        let n = calls.len();
        calls.extend((0..4).map(|k| Call::GetVar {
            var: VAR_PROBE_X + k,
        }));
        let restore = self.lock().restore.clone();
        if let Some(line) = &restore {
            calls.push(Call::Code { line: line.clone() });
        }
        let Ok(mut results) = self.batch(calls, false) else {
            return;
        };
        let tail = results.split_off(n.min(results.len()));
        let Ok(p) = parse_poll(results) else {
            return;
        };
        let vars: Result<Vec<f64>, String> = tail
            .iter()
            .take(4)
            .map(|r| match r {
                CallResult::Ok(v) => Ok(num(v)),
                CallResult::Err(e) => Err(e.to_string()),
            })
            .collect();
        // Mach3 ignores MDI in reset: the line is sent again once it is out of it.
        let restored = !p.estop && matches!(tail.get(4), Some(CallResult::Ok(_)));
        let mut sh = self.lock();
        if sh.probe.map(|x| x.id) != Some(t.id) {
            return;
        }
        sh.probe = None;
        if restored && sh.restore == restore {
            sh.restore = None;
        }
        let mut events = Vec::new();
        let status = self.track(&mut sh, &p, &mut events);
        let (outcome, trip, message) = probe_outcome(&t, &p, vars);
        events.push(Event::ProbeEnded {
            id: t.id,
            outcome,
            trip,
            position: status.machine_position,
            message,
        });
        self.publish(&mut sh, status, events);
    }

    fn track(&self, sh: &mut Shared, p: &Poll, events: &mut Vec<Event>) -> MachineStatus {
        let active = match p.fixture_number.round() as i64 {
            n @ 1..=6 => WorkOffset::ALL[(n - 1) as usize],
            _ => WorkOffset::G54,
        };
        sh.offsets[active.index()] = p.fixture;
        let machine: [f64; 4] = std::array::from_fn(|i| p.work[i] + p.fixture[i]);
        let base = f64::from(self.cfg.line_dro_base);
        let dro_line = (p.line - base).max(0.0).round() as u32;
        // DRO 816 shows the line being executed: every line before it is done.
        let current = dro_line.saturating_add(1);
        let state = if p.estop {
            MachineState::Alarm
        } else if p.paused {
            MachineState::Paused
        } else if p.running {
            MachineState::Running
        } else if p.moving {
            MachineState::Jogging
        } else {
            MachineState::Idle
        };
        let (inputs, outputs) = io_maps(Some(p));
        // Mach3 latches reset when a limit switch trips: the alarm names the switch.
        let limit = inputs
            .iter()
            .find(|(name, v)| name.starts_with(io::LIMIT) && **v == Some(true))
            .map(|(name, _)| name.clone());
        let mut status = MachineStatus {
            state,
            machine_position: AxisValues::from_array(machine),
            work_position: AxisValues::from_array(p.work),
            feed: p.feed,
            feed_override: p.fro,
            spindle_override: p.sro,
            // The DRO is in force only while Mach3 overrides rapids (button 287, LED 109).
            rapid_override: if p.rapid_override_on {
                p.rapid_override
            } else {
                100.0
            },
            active_offset: active,
            run: None,
            line: None,
            alarm: p.estop.then(|| match &limit {
                Some(l) => format!(
                    "Mach3 is in reset: limit switch {l} is active; send reset and jog off it"
                ),
                None => "Mach3 is in reset (e-stop latched): send reset".to_string(),
            }),
            reason: None,
            inputs,
            outputs,
            hold: None,
        };
        if let Some(mut t) = sh.probe.filter(|t| !t.ended) {
            t.saw_moving |= p.moving;
            let moved = (machine[t.axis.index()] - t.start).abs() > 1e-9;
            let settled = !p.moving
                && !p.paused
                && (t.saw_moving || moved || t.started.elapsed() >= START_GRACE);
            if p.estop || settled {
                t.ended = true;
            } else if status.state == MachineState::Idle {
                // Sent and not moving yet: as good as under way.
                status.state = MachineState::Jogging;
            }
            sh.probe = Some(t);
        }
        let Some(mut t) = sh.run else {
            return status;
        };
        let run = t.loaded.run;
        if p.running {
            t.saw_running = true;
        }
        if p.running || p.paused {
            let done = current.saturating_sub(1).min(t.loaded.lines);
            if done > t.acked && done >= t.loaded.start_line {
                t.acked = done;
                events.push(Event::LineAcknowledged { run, line: done });
            }
            status.run = Some(run);
            status.line = Some(current);
            sh.run = Some(t);
            return status;
        }
        if !t.saw_running && t.started.elapsed() < START_GRACE && !p.estop {
            status.run = Some(run);
            status.line = Some(t.loaded.start_line);
            sh.run = Some(t);
            return status;
        }
        // The run is over; say how.
        let (outcome, message) = if t.stop_requested {
            (RunOutcome::Cancelled, None)
        } else if p.estop {
            (
                RunOutcome::Failed,
                Some(format!("Mach3 went into reset (e-stop) at line {current}")),
            )
        } else if dro_line == 0 || current >= t.loaded.last_active_line.min(t.loaded.lines) {
            // M2/M30 rewinds DRO 816 to the first line; a program without them ends on its last.
            if t.acked < t.loaded.lines {
                events.push(Event::LineAcknowledged {
                    run,
                    line: t.loaded.lines,
                });
            }
            (RunOutcome::Completed, None)
        } else {
            (
                RunOutcome::Failed,
                Some(format!(
                    "Mach3 stopped at line {current} of {} (stopped on the Mach3 screen?)",
                    t.loaded.lines
                )),
            )
        };
        events.push(Event::RunEnded {
            run,
            outcome,
            message,
        });
        sh.run = None;
        status
    }

    fn poller(self: Arc<Self>) {
        loop {
            self.poll();
            let sh = self.lock();
            if sh.shutdown {
                return;
            }
            let (sh, _) = self
                .wake
                .wait_timeout(sh, self.cfg.poll_interval)
                .unwrap_or_else(|e| e.into_inner());
            if sh.shutdown {
                return;
            }
        }
    }

    // ----- requests -----

    fn status(&self) -> MachineStatus {
        if !self.lock().polled {
            self.poll();
        }
        self.lock().status.clone()
    }

    fn require(&self, what: &str, allowed: &[MachineState]) -> Result<MachineStatus, PluginError> {
        let st = self.lock().status.clone();
        if allowed.contains(&st.state) {
            return Ok(st);
        }
        Err(match st.state {
            MachineState::Offline => PluginError::new(
                "offline",
                format!(
                    "cannot {what}: {}",
                    st.reason.as_deref().unwrap_or("Mach3 is offline")
                ),
            ),
            MachineState::Alarm => PluginError::new(
                "alarm",
                format!("cannot {what}: Mach3 is in reset (e-stop); send reset first"),
            ),
            s => PluginError::new(
                "busy",
                format!("cannot {what} while Mach3 is {}", s.as_str()),
            ),
        })
    }

    /// An MDI jog in G91 that puts back the distance mode, motion mode and feed it found.
    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<Value, PluginError> {
        let feed = feed.unwrap_or(self.cfg.jog_feed_mm_min);
        if !(distance.is_finite() && feed.is_finite() && feed > 0.0) {
            return Err(PluginError::invalid(format!(
                "jog needs a finite distance and a feed > 0, got {distance} mm at {feed} mm/min"
            )));
        }
        self.require("jog", &[MachineState::Idle, MachineState::Jogging])?;
        if self.lock().probe.is_some() {
            return Err(PluginError::new("busy", "cannot jog while Mach3 probes"));
        }
        let modal = self.read_modal("jog")?;
        // Mach3 applies its feed override to MDI moves; a jog keeps its own feed.
        let f = modal.own_feed(feed, "jog")?;
        self.mdi_then_restore(
            format!("G91 G1 {}{distance} F{f}", axis.letter()),
            modal.restore(None),
        )
    }

    /// One operator MDI line, followed by the line that puts back the modal state it found.
    fn mdi(&self, line: &str) -> Result<Value, PluginError> {
        if line.trim().is_empty() || line.contains(['\n', '\r']) {
            return Err(PluginError::new(
                "invalid_gcode",
                format!("MDI takes exactly one non-empty line, got {line:?}"),
            ));
        }
        self.require("run MDI", &[MachineState::Idle])?;
        let restore = self.read_modal("run MDI")?.restore(None);
        self.mdi_then_restore(line.to_string(), restore)
    }

    /// Reads distance mode, motion mode, feed and feed override; refuses while a program runs
    /// or in reset.
    fn read_modal(&self, what: &str) -> Result<Modal, PluginError> {
        let c = &self.cfg.codes;
        let modal = self.exec(
            vec![
                Call::GetOemLed {
                    code: c.get(Code::IncrementalLed),
                },
                Call::GetOemDro {
                    code: c.get(Code::MotionMode),
                },
                Call::GetOemDro {
                    code: c.get(Code::Feed),
                },
                Call::GetOemLed {
                    code: c.get(Code::RunningLed),
                },
                Call::IsEstop,
                Call::GetOemDro {
                    code: c.get(Code::FeedOverride),
                },
            ],
            false,
        )?;
        if modal[3].as_bool().unwrap_or(true) {
            return Err(PluginError::new(
                "busy",
                format!("cannot {what}: a program is running"),
            ));
        }
        if modal[4].as_bool().unwrap_or(true) {
            return Err(PluginError::new(
                "alarm",
                format!("cannot {what}: Mach3 is in reset (e-stop); send reset first"),
            ));
        }
        Ok(Modal {
            incremental: modal[0].as_bool().unwrap_or(false),
            motion: num(&modal[1]).round() as i64,
            feed: num(&modal[2]),
            fro: modal[5].as_f64().unwrap_or(100.0),
        })
    }

    fn mdi_then_restore(&self, line: String, restore: String) -> Result<Value, PluginError> {
        let results = self
            .batch(
                vec![
                    Call::Code { line },
                    // Same batch: runs right after the move is queued, even if it failed.
                    Call::Code { line: restore },
                ],
                false,
            )
            .map_err(|e| link_error(&e))?;
        for r in results {
            if let CallResult::Err(e) = r {
                return Err(mach3_error(&e));
            }
        }
        self.poll();
        Ok(json!({}))
    }

    /// Reset is a toggle in Mach3: press it only when reset is latched, or it latches.
    fn reset(&self) -> Result<Value, PluginError> {
        let led = self.cfg.codes.get(Code::EstopLed);
        let latched = |v: &[Value]| v.iter().any(|x| x.as_bool().unwrap_or(false));
        let state = self.exec(vec![Call::GetOemLed { code: led }, Call::IsEstop], true)?;
        if latched(&state) {
            self.button(Code::Reset, true)?;
            let deadline = Instant::now() + RESET_CONFIRM;
            loop {
                let state = self.exec(vec![Call::GetOemLed { code: led }, Call::IsEstop], true)?;
                if !latched(&state) {
                    break;
                }
                if Instant::now() >= deadline {
                    return Err(PluginError::new(
                        "reset_failed",
                        "Mach3 is still in reset after pressing Reset: is an e-stop input active?",
                    ));
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        } else {
            // Not latched: a reset here only means "stop"; pressing Reset would latch it.
            self.stop()?;
        }
        self.poll();
        Ok(json!({}))
    }

    fn stop(&self) -> Result<(), PluginError> {
        {
            let mut sh = self.lock();
            if let Some(t) = sh.run.as_mut() {
                t.stop_requested = true;
            }
            if let Some(t) = sh.probe.as_mut() {
                t.stop_requested = true;
            }
        }
        self.button(Code::Stop, true)
    }

    /// All six offsets. Mach3 shows only the active fixture's (DROs 830-835), so when idle
    /// each fixture is selected in turn by MDI and the active one selected again, all in one
    /// batch (nothing runs in between); while busy the others come from what was last seen.
    fn offsets(&self) -> Result<OffsetTable, PluginError> {
        let c = &self.cfg.codes;
        let fixture = |calls: &mut Vec<Call>| {
            calls.extend((0..4).map(|i| Call::GetOemDro {
                code: c.axis(Code::FixtureX, i),
            }))
        };
        let mut calls = vec![Call::GetOemDro {
            code: c.get(Code::FixtureNumber),
        }];
        fixture(&mut calls);
        let v = self.exec(calls, false)?;
        let active = match num(&v[0]).round() as i64 {
            n @ 1..=6 => WorkOffset::ALL[(n - 1) as usize],
            _ => WorkOffset::G54,
        };
        let values: [f64; 4] = std::array::from_fn(|i| num(&v[1 + i]));
        self.lock().offsets[active.index()] = values;
        if self.lock().status.state == MachineState::Idle {
            let mut calls = Vec::new();
            for o in WorkOffset::ALL {
                calls.push(Call::Code {
                    line: o.name().to_string(),
                });
                fixture(&mut calls);
            }
            calls.push(Call::Code {
                line: active.name().to_string(),
            });
            let v = self.exec(calls, false)?;
            let mut sh = self.lock();
            for (k, o) in WorkOffset::ALL.into_iter().enumerate() {
                sh.offsets[o.index()] = std::array::from_fn(|i| num(&v[k * 5 + 1 + i]));
            }
        }
        let sh = self.lock();
        Ok(OffsetTable {
            active,
            offsets: WorkOffset::ALL
                .into_iter()
                .map(|o| (o, AxisValues::from_array(sh.offsets[o.index()])))
                .collect(),
        })
    }

    fn set_offset(&self, offset: WorkOffset, values: AxisValues) -> Result<Value, PluginError> {
        let v = values.to_array();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(PluginError::invalid("offset values must be finite numbers"));
        }
        self.require("change offsets", &[MachineState::Idle, MachineState::Alarm])?;
        let number = self.exec(
            vec![Call::GetOemDro {
                code: self.cfg.codes.get(Code::FixtureNumber),
            }],
            false,
        )?;
        let active = num(&number[0]).round() as usize == offset.index() + 1;
        let calls = if active {
            (0..4)
                .map(|i| Call::SetOemDro {
                    code: self.cfg.codes.axis(Code::FixtureX, i),
                    value: v[i],
                })
                .collect()
        } else {
            let p = offset.index() + 1;
            vec![Call::Code {
                line: format!("G10 L2 P{p} X{} Y{} Z{} A{}", v[0], v[1], v[2], v[3]),
            }]
        };
        self.exec(calls, false)?;
        self.lock().offsets[offset.index()] = v;
        self.poll();
        Ok(json!({}))
    }

    /// Sets the overrides given through Mach3's DROs: FRO (821), spindle override (74), rapid
    /// override (223). Mach3 applies the rapid override only while "override of rapid feeds"
    /// is on (button 287, a toggle; LED 109), so a rapid override switches it on, reading the
    /// LED first: pressing a toggle blindly could switch it off. That comes first: if it
    /// fails, the rapid DRO is put back and nothing else is set. Allowed during a run (that
    /// is when an operator needs it), sent ahead of queued agent work.
    fn set_overrides(
        &self,
        feed: Option<f64>,
        spindle: Option<f64>,
        rapid: Option<f64>,
    ) -> Result<Value, PluginError> {
        for (field, v) in [("feed", feed), ("spindle", spindle), ("rapid", rapid)] {
            if let Some(v) = v.filter(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(PluginError::invalid(format!(
                    "`{field}` override must be a positive percentage, got {v}"
                )));
            }
        }
        if let Some(r) = rapid.filter(|r| *r > 100.0) {
            return Err(PluginError::invalid(format!(
                "`rapid` override is at most 100 % (Mach3's rapid rate), got {r}"
            )));
        }
        let st = self.lock().status.clone();
        if st.state == MachineState::Offline {
            return Err(PluginError::new(
                "offline",
                format!(
                    "cannot set overrides: {}",
                    st.reason.as_deref().unwrap_or("Mach3 is offline")
                ),
            ));
        }
        let c = &self.cfg.codes;
        if let Some(value) = rapid {
            let code = c.get(Code::RapidOverride);
            // Setting the DRO while the toggle is off puts nothing in force yet.
            let was = self.exec(
                vec![
                    Call::GetOemDro { code },
                    Call::SetOemDro { code, value },
                    Call::GetOemLed {
                        code: c.get(Code::RapidOverrideLed),
                    },
                ],
                true,
            )?;
            if !was[2].as_bool().unwrap_or(false) {
                if let Err(e) = self.rapid_override_on() {
                    let value = num(&was[0]);
                    // Best effort: the error is what the caller must hear.
                    let _ = self.exec(vec![Call::SetOemDro { code, value }], true);
                    return Err(e);
                }
            }
        }
        let calls: Vec<Call> = [(Code::FeedOverride, feed), (Code::SpindleOverride, spindle)]
            .into_iter()
            .filter_map(|(code, v)| {
                v.map(|value| Call::SetOemDro {
                    code: c.get(code),
                    value,
                })
            })
            .collect();
        if !calls.is_empty() {
            self.exec(calls, true)?;
        }
        self.poll();
        Ok(json!({}))
    }

    /// Presses the rapid-override toggle and waits for its LED. Should it not light, the
    /// toggle is pressed again so Mach3 is left as it was, and the error names both codes.
    fn rapid_override_on(&self) -> Result<(), PluginError> {
        let c = &self.cfg.codes;
        let (button, led) = (
            c.get(Code::RapidOverrideToggle),
            c.get(Code::RapidOverrideLed),
        );
        let lit = |v: Vec<Value>| v.last().and_then(Value::as_bool).unwrap_or(false);
        let pressed = self.exec(
            vec![
                Call::DoOemButton { code: button },
                Call::GetOemLed { code: led },
            ],
            true,
        )?;
        if lit(pressed) {
            return Ok(());
        }
        let deadline = Instant::now() + TOGGLE_CONFIRM;
        while Instant::now() < deadline {
            // Polling the LED, as reset does.
            std::thread::sleep(Duration::from_millis(50));
            if lit(self.exec(vec![Call::GetOemLed { code: led }], true)?) {
                return Ok(());
            }
        }
        self.exec(vec![Call::DoOemButton { code: button }], true)?;
        Err(PluginError::new(
            "mach3_error",
            format!(
                "pressed Mach3's \"override of rapid feeds\" toggle (button {button}) but its LED \
                 {led} did not light, so it was pressed again to leave it as it was and no \
                 override was changed. Check `codes.rapid_override_toggle` and \
                 `codes.led_rapid_override` against this Mach3's screen set"
            ),
        ))
    }

    /// Starts a probing move as Mach3's G31, which stops when the probe input (LED 825)
    /// becomes active and keeps where in #2000-#2005. Sent in G90 with the end in work
    /// coordinates, as Mach3's probing macros send it, with F such that the move goes at
    /// `feed` whatever the feed override; the line putting back G90/G91, G0/G1 and F is sent
    /// once the motion ended (a line queued behind a G31 could wait as long as the probe).
    /// The poller follows it to its end and reports `probe_ended`.
    fn probe(&self, p: Probe) -> Result<(), PluginError> {
        if !(p.distance.is_finite() && p.distance != 0.0) {
            return Err(PluginError::invalid(format!(
                "probe distance must be a finite number other than 0, got {}",
                p.distance
            )));
        }
        if !(p.feed.is_finite() && p.feed > 0.0) {
            return Err(PluginError::invalid(format!(
                "probe feed must be greater than 0 mm/min, got {}",
                p.feed
            )));
        }
        if p.until == ProbeUntil::Release {
            return Err(PluginError::new(
                "unsupported",
                "mach3-oem cannot probe for the probe's release (G38.4/G38.5): Mach3's G31 \
                 only stops when the probe input becomes active (contact)",
            ));
        }
        self.require("probe", &[MachineState::Idle])?;
        if self.lock().probe.is_some() {
            return Err(PluginError::new("busy", "a probe is already under way"));
        }
        let has_get_var = self
            .link
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .client
            .has_feature(FEATURE_GET_VAR);
        if !has_get_var {
            return Err(PluginError::new(
                "unsupported",
                format!(
                    "the Mach3 agent at {} is older than this plugin: it cannot read Mach3's \
                     probe trip (GetVar); install the current fresa-mach3-agent to probe",
                    self.cfg.agent
                ),
            ));
        }
        // A line still owed by an earlier probe goes first, or this one would take the
        // state that probe left for the one to put back.
        let owed = self.lock().restore.clone();
        if let Some(line) = owed {
            self.put_back(line);
            if self.lock().restore.is_some() {
                return Err(PluginError::new(
                    "busy",
                    "cannot probe: the modal state an earlier probe changed could not be put \
                     back yet (Mach3 did not take the MDI line); try again",
                ));
            }
        }
        let modal = self.read_modal("probe")?;
        let f = modal.own_feed(p.feed, "probe")?;
        let c = &self.cfg.codes;
        let i = p.axis.index();
        let now = self.exec(
            vec![
                Call::GetOemLed {
                    code: c.get(Code::ProbeLed),
                },
                Call::GetOemDro {
                    code: c.axis(Code::PosX, i),
                },
                Call::GetOemDro {
                    code: c.axis(Code::FixtureX, i),
                },
            ],
            false,
        )?;
        if now[0].as_bool().unwrap_or(true) {
            return Err(PluginError::new(
                "probe_already_in_state",
                format!(
                    "the probe is already in contact (Mach3's probe input, LED {}, is lit): \
                     nothing to probe for (check the clip and the plate)",
                    c.get(Code::ProbeLed)
                ),
            ));
        }
        let (work, fixture) = (num(&now[1]), num(&now[2]));
        // As sent (4 decimals), so "ran its whole distance" compares with what Mach3 got.
        let target = format!("{:.4}", work + p.distance);
        let target_work: f64 = target.parse().unwrap_or(work + p.distance);
        let line = format!("G90 G31 {}{target} F{f:.4}", p.axis.letter());
        {
            let mut sh = self.lock();
            // G31 stays modal in Mach3: if the motion mode found cannot be re-entered (G2/G3),
            // G1 is put back rather than leave a probe mode behind.
            sh.restore = Some(modal.restore(Some("G1")));
            sh.probe = Some(ProbeTrack {
                id: p.id,
                axis: p.axis,
                start: work + fixture,
                target_work,
                started: Instant::now(),
                saw_moving: false,
                stop_requested: false,
                ended: false,
            });
        }
        if let Err(e) = self.exec(vec![Call::Code { line }], false) {
            // The restore line stays pending: the next idle poll sends it.
            self.lock().probe = None;
            return Err(e);
        }
        self.poll();
        Ok(())
    }

    fn load_program(
        &self,
        run: i64,
        path: &str,
        start_line: u32,
        tools: fresa_gcode::ToolTable,
        max_segments: u64,
    ) -> Result<ProgramLoaded, PluginError> {
        if start_line == 0 {
            return Err(PluginError::invalid(
                "start_line is 1-based: 0 is not a line",
            ));
        }
        self.require("load a program", &[MachineState::Idle, MachineState::Alarm])?;
        // Read from the file (checked, then sent in chunks), never held whole.
        let (file, lines) = fresa_plugin_api::kit::open_program(path)?;
        let unreadable = |e: std::io::Error| {
            PluginError::new("program_unreadable", format!("cannot read {path}: {e}"))
        };
        // Validate the whole program before anything reaches Mach3 (which linearises it
        // itself: the work budget bounds what that costs it).
        let config = fresa_gcode::Config {
            tools,
            ..Default::default()
        };
        let reader =
            std::io::BufReader::with_capacity(1 << 16, file.try_clone().map_err(unreadable)?);
        let interp = fresa_gcode::Interpreter::new(reader, config);
        let mut last_active_line = 1;
        let budget = fresa_gcode::WorkBudget::new(max_segments, 0.002);
        let mut motions = fresa_gcode::budgeted(interp, budget);
        for m in motions.by_ref() {
            let m = m.map_err(|e| match e.kind {
                fresa_gcode::ErrorKind::Budget => PluginError::new(
                    "work_budget_exceeded",
                    format!("{e}; the budget is the server's `max_program_segments`"),
                ),
                _ => PluginError::new("invalid_program", e.to_string()),
            })?;
            last_active_line = last_active_line.max(m.line());
        }
        // Mach3 gets the text itself, and it does not speak LinuxCNC's
        // O-word control flow or named parameters: refuse before it sees any.
        // Mach3 would compensate with its own tool table, which Fresa does not know: the path
        // it cuts could differ from the one checked here.
        let interp = motions.inner();
        if let Some(line) = interp.cutter_comp_line() {
            return Err(PluginError::new(
                "invalid_program",
                format!(
                    "line {line}: cutter radius compensation (G41/G42) is not sent to Mach3, \
                     which would use its own tool table; compensate in CAM instead"
                ),
            ));
        }
        // Mach3 would write G10's offsets and tools into its own tables and keep them; the
        // store is the source of truth for work offsets.
        if let Some(line) = interp.g10_line() {
            return Err(PluginError::new(
                "invalid_program",
                format!(
                    "line {line}: G10 would change Mach3's own offsets or tool table for good; \
                     set work offsets through Fresa (PUT /machines/{{id}}/offsets) instead"
                ),
            ));
        }
        if let Some(line) = interp.linuxcnc_only_line() {
            return Err(PluginError::new(
                "invalid_program",
                format!(
                    "line {line}: LinuxCNC-only syntax (O-word sub/if/while, #<named> parameters, \
                     (debug,...) or G38.x probing) that Mach3 does not run; use numbered \
                     parameters, M98/M99 and G31"
                ),
            ));
        }
        if start_line > lines.saturating_add(1) {
            return Err(PluginError::invalid(format!(
                "start_line {start_line} is past the end of the program ({lines} lines)"
            )));
        }
        let name = format!("fresa-run-{run}.nc");
        let mut file = file;
        std::io::Seek::rewind(&mut file).map_err(unreadable)?;
        let mut chunks = Chunks::new(file, PROGRAM_CHUNK_BYTES);
        let mut next = chunks.next_chunk().map_err(unreadable)?;
        let mut first = true;
        let stored = loop {
            let data = next.unwrap_or_default();
            next = chunks.next_chunk().map_err(unreadable)?;
            let last = next.is_none();
            let v = self.exec(
                vec![Call::WriteProgram {
                    name: name.clone(),
                    data,
                    first,
                    last,
                }],
                false,
            )?;
            first = false;
            if last {
                break v.into_iter().next().unwrap_or(Value::Null);
            }
        };
        let stored = stored.as_str().map(str::to_owned).ok_or_else(|| {
            PluginError::new(
                "mach3_error",
                "the agent did not say where it stored the program",
            )
        })?;
        let line_dro = f64::from(start_line - 1 + self.cfg.line_dro_base);
        self.exec(
            vec![
                Call::LoadFile { path: stored },
                Call::SetOemDro {
                    code: self.cfg.codes.get(Code::Line),
                    value: line_dro,
                },
            ],
            false,
        )?;
        let mut sh = self.lock();
        if let Some(old) = sh.loaded.replace(Loaded {
            run,
            lines,
            start_line,
            last_active_line,
        }) {
            if old.run != run {
                self.emit(vec![Event::RunEnded {
                    run: old.run,
                    outcome: RunOutcome::Cancelled,
                    message: Some(format!("replaced by run {run} before it started")),
                }]);
            }
        }
        Ok(ProgramLoaded::new(lines, start_line))
    }

    fn start(&self) -> Result<Value, PluginError> {
        let st = self.require("start", &[MachineState::Idle, MachineState::Paused])?;
        if st.state == MachineState::Paused {
            self.button(Code::CycleStart, false)?;
            self.poll();
            return Ok(json!({}));
        }
        let loaded = self.lock().loaded.take().ok_or_else(|| {
            PluginError::new(
                "no_program",
                "no program is loaded: send load_program first",
            )
        })?;
        if loaded.start_line > loaded.lines {
            self.emit(vec![Event::RunEnded {
                run: loaded.run,
                outcome: RunOutcome::Completed,
                message: None,
            }]);
            return Ok(json!({}));
        }
        self.lock().run = Some(RunTrack {
            loaded,
            acked: loaded.start_line - 1,
            saw_running: false,
            started: Instant::now(),
            stop_requested: false,
        });
        if let Err(e) = self.button(Code::CycleStart, false) {
            self.lock().run = None;
            return Err(e);
        }
        self.poll();
        Ok(json!({}))
    }

    /// Presses an OEM button and refreshes the status.
    fn press(&self, code: i16) -> Result<(), PluginError> {
        self.exec(vec![Call::DoOemButton { code }], false)?;
        self.poll();
        Ok(())
    }

    /// Cancels the run: a loaded, unstarted one ends at once; a running one is stopped.
    fn cancel(&self) -> Result<(), PluginError> {
        let pending = self.lock().loaded.take();
        if let Some(l) = pending {
            self.emit(vec![Event::RunEnded {
                run: l.run,
                outcome: RunOutcome::Cancelled,
                message: Some("cancelled before it started".into()),
            }]);
        }
        if self.lock().run.is_some() {
            self.stop()?;
            self.wait_run_over()?;
        }
        Ok(())
    }

    /// After a stop: polls Mach3 until it no longer runs the program (or probes) and the
    /// run's `run_ended` (the probe's `probe_ended`) has been emitted, so a cancel or stop is
    /// never answered while Mach3 still cuts. Mach3 still moving after [`STOP_WAIT`] answers
    /// `stop_unconfirmed`.
    fn wait_run_over(&self) -> Result<(), PluginError> {
        let deadline = Instant::now() + STOP_WAIT;
        loop {
            self.poll();
            let (run, probe) = {
                let sh = self.lock();
                (sh.run.is_some(), sh.probe.is_some())
            };
            if !run && !probe {
                return Ok(());
            }
            if Instant::now() >= deadline {
                let what = if run {
                    "the program running"
                } else {
                    "the probe moving"
                };
                return Err(PluginError::new(
                    "stop_unconfirmed",
                    format!("Mach3 still reports {what} {STOP_WAIT:?} after Stop"),
                ));
            }
            // Polling the controller, at about the status rate.
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn feed_hold(&self) -> Result<(), PluginError> {
        if self.lock().probe.is_some() {
            // Held, a G31 would go on probing at the next cycle start; a probe ends at a hold
            // (`stopped`) on every backend, so it is stopped instead.
            self.stop()?;
            return self.wait_run_over();
        }
        self.button(Code::FeedHold, true)?;
        self.poll();
        Ok(())
    }

    fn resume(&self) -> Result<(), PluginError> {
        self.press(self.cfg.codes.get(Code::Resume))
    }

    fn shutdown(&self) {
        let moving = self.lock().status.state.is_busy();
        if moving {
            // Best effort: the server is going away and motion must not outlive it.
            let _ = self.stop();
        }
        {
            let mut sh = self.lock();
            sh.shutdown = true;
            sh.status = offline("shut down".into());
        }
        self.wake.notify_all();
        self.link
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .client
            .disconnect();
    }
}

/// Splits `text` into pieces of at most `max` bytes, on character boundaries; never empty.
/// A UTF-8 program file (checked already) in pieces of at most `max` bytes, cut on character
/// boundaries, read as they are taken: memory is one piece, whatever the program's length.
struct Chunks<R> {
    reader: R,
    max: usize,
    /// Bytes read but not yet handed out (the start of a character cut by the last read).
    carry: Vec<u8>,
    done: bool,
    started: bool,
}

impl<R: std::io::Read> Chunks<R> {
    fn new(reader: R, max: usize) -> Chunks<R> {
        Chunks {
            reader,
            max: max.max(4),
            carry: Vec::new(),
            done: false,
            started: false,
        }
    }

    /// The next piece; `None` after the last. An empty file is one empty piece.
    fn next_chunk(&mut self) -> std::io::Result<Option<String>> {
        if self.done {
            return Ok(None);
        }
        let mut buf = std::mem::take(&mut self.carry);
        let had = buf.len();
        buf.resize(self.max, 0);
        let mut len = had;
        while len < self.max {
            match self.reader.read(&mut buf[len..]) {
                Ok(0) => break,
                Ok(n) => len += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        buf.truncate(len);
        if len < self.max {
            self.done = true;
            // The end of a file whose length is a multiple of `max`: no empty last piece.
            if len == 0 && self.started {
                return Ok(None);
            }
        } else {
            // Cut before a character the piece's end splits: its bytes start the next piece.
            let mut cut = len;
            while cut > 0 && (buf[cut - 1] & 0xC0) == 0x80 {
                cut -= 1;
            }
            if cut > 0 && buf[cut - 1] >= 0xC0 {
                cut -= 1;
            } else {
                cut = len;
            }
            self.carry = buf.split_off(cut);
        }
        self.started = true;
        String::from_utf8(buf)
            .map(Some)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))
    }
}

impl Mach3Backend {
    pub fn new(config: &Value, sink: EventSink) -> Result<Mach3Backend, PluginError> {
        let cfg = Config::from_json(config)?;
        let client = AgentClient::new(cfg.agent.clone(), cfg.secret.clone(), cfg.timeout);
        let inner = Arc::new(Inner {
            link: Mutex::new(Link {
                client,
                retry_at: None,
                backoff: BACKOFF_MIN,
                last_error: String::new(),
            }),
            shared: Mutex::new(Shared {
                status: offline("not connected yet".into()),
                polled: false,
                loaded: None,
                run: None,
                offsets: [[0.0; 4]; 6],
                probe: None,
                restore: None,
                shutdown: false,
            }),
            wake: Condvar::new(),
            polling: Mutex::new(()),
            cfg,
            sink,
        });
        let worker = Arc::clone(&inner);
        let poller = std::thread::Builder::new()
            .name("mach3-oem poll".into())
            .spawn(move || worker.poller())
            .map_err(|e| PluginError::new("internal", format!("cannot start the poller: {e}")))?;
        Ok(Mach3Backend {
            inner,
            poller: Mutex::new(Some(poller)),
        })
    }
}

impl MachineBackend for Mach3Backend {
    fn create(host: Host, config: Value) -> Result<Self, PluginError> {
        Mach3Backend::new(&config, Arc::new(move |event| host.emit(event)))
    }

    fn connect(&self) -> Result<MachineStatus, PluginError> {
        self.inner.poll();
        self.inner.wake.notify_all();
        Ok(self.inner.lock().status.clone())
    }

    fn status(&self) -> Result<MachineStatus, PluginError> {
        Ok(self.inner.status())
    }

    /// A start at a line (a preamble) is refused: see [`NO_PREAMBLE`].
    fn load_program(&self, p: LoadProgram) -> Result<ProgramLoaded, PluginError> {
        if p.preamble.is_some() {
            return Err(PluginError::new("unsupported", NO_PREAMBLE));
        }
        if p.height_map.is_some() {
            return Err(PluginError::new("unsupported", HEIGHT_MAP_REFUSAL));
        }
        let tools =
            fresa_gcode::tool_table(p.tools.iter().map(|t| (t.tool, t.diameter_mm, t.length_mm)));
        let budget = p.max_segments.unwrap_or(fresa_gcode::DEFAULT_MAX_SEGMENTS);
        self.inner
            .load_program(p.run, &p.path, p.start_line, tools, budget)
    }

    fn run(&self, action: RunAction) -> Result<RunAnswer, PluginError> {
        match action {
            RunAction::Start => self.inner.start().map(drop)?,
            RunAction::Pause => self.inner.feed_hold()?,
            RunAction::Resume => self.inner.resume()?,
            RunAction::Cancel => self.inner.cancel()?,
        }
        Ok(RunAnswer::default())
    }

    fn feed_hold(&self) -> Result<(), PluginError> {
        self.inner.feed_hold()
    }

    fn resume(&self) -> Result<(), PluginError> {
        self.inner.resume()
    }

    fn stop(&self) -> Result<(), PluginError> {
        self.inner.stop()?;
        self.inner.wait_run_over()
    }

    fn reset(&self) -> Result<(), PluginError> {
        self.inner.reset().map(drop)
    }

    fn shutdown(&self) -> Result<(), PluginError> {
        self.inner.shutdown();
        Ok(())
    }

    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<(), PluginError> {
        self.inner.jog(axis, distance, feed).map(drop)
    }

    fn home(&self, axis: Option<Axis>) -> Result<(), PluginError> {
        let inner = &self.inner;
        inner.require("home", &[MachineState::Idle])?;
        inner.press(match axis {
            Some(a) => inner.cfg.codes.axis(Code::RefX, a.index()),
            None => inner.cfg.codes.get(Code::HomeAll),
        })
    }

    fn zero(&self, axis: Option<Axis>) -> Result<Option<OffsetTable>, PluginError> {
        let inner = &self.inner;
        inner.require("zero", &[MachineState::Idle])?;
        inner.press(match axis {
            Some(a) => inner.cfg.codes.axis(Code::ZeroX, a.index()),
            None => inner.cfg.codes.get(Code::ZeroAll),
        })?;
        inner.offsets().map(Some)
    }

    fn go_to_zero(&self) -> Result<(), PluginError> {
        self.inner.require("go to zero", &[MachineState::Idle])?;
        self.inner.press(self.inner.cfg.codes.get(Code::GoToZero))
    }

    fn select_offset(&self, offset: WorkOffset) -> Result<(), PluginError> {
        self.inner
            .require("select an offset", &[MachineState::Idle])?;
        self.inner.exec(
            vec![Call::Code {
                line: offset.name().to_string(),
            }],
            false,
        )?;
        self.inner.poll();
        Ok(())
    }

    fn set_output(&self, name: OutputName, on: bool) -> Result<Value, PluginError> {
        let codes = &self.inner.cfg.codes;
        match name {
            // Flood has OEM buttons; the spindle is switched by MDI M3/M5 (Mach3's own).
            OutputName::Coolant => {
                self.inner
                    .press(codes.get(if on { Code::FloodOn } else { Code::FloodOff }))?;
            }
            OutputName::Spindle => {
                self.inner.mdi(if on { "M3" } else { "M5" })?;
            }
            // The Z lift belongs to the screen set's macros.
            OutputName::ZLift => {
                return Err(PluginError::new(
                    "unsupported",
                    "mach3-oem cannot switch \"z_lift\": use set_output with on true/false for spindle or coolant",
                ))
            }
        }
        Ok(json!({"output": name, "on": on}))
    }

    /// Reads the output's LED(s) back from Mach3, then switches it the other way.
    fn toggle_output(&self, name: OutputName) -> Result<Value, PluginError> {
        let leds: &[Code] = match name {
            OutputName::Spindle => &[Code::SpindleCwLed, Code::SpindleCcwLed],
            OutputName::Coolant => &[Code::FloodLed],
            // set_output explains why there is no z_lift.
            OutputName::ZLift => return self.set_output(name, true),
        };
        let codes = &self.inner.cfg.codes;
        let lit = self.inner.exec(
            leds.iter()
                .map(|c| Call::GetOemLed {
                    code: codes.get(*c),
                })
                .collect(),
            false,
        )?;
        let on = lit.iter().any(|v| v.as_bool().unwrap_or(false));
        self.set_output(name, !on)
    }

    fn get_offsets(&self) -> Result<OffsetTable, PluginError> {
        self.inner.offsets()
    }

    fn set_offset(&self, offset: WorkOffset, values: AxisValues) -> Result<(), PluginError> {
        self.inner.set_offset(offset, values).map(drop)
    }

    fn mdi(&self, line: &str) -> Result<(), PluginError> {
        self.inner.mdi(line).map(drop)
    }

    /// Mach3's G31 through the agent; its trip read back from #2000-#2003 (see `Inner::probe`).
    fn probe(&self, probe: Probe) -> Result<(), PluginError> {
        self.inner.probe(probe)
    }

    fn set_overrides(
        &self,
        feed: Option<f64>,
        spindle: Option<f64>,
        rapid: Option<f64>,
    ) -> Result<(), PluginError> {
        self.inner.set_overrides(feed, spindle, rapid).map(drop)
    }
}

impl Drop for Mach3Backend {
    fn drop(&mut self) {
        self.inner.lock().shutdown = true;
        self.inner.wake.notify_all();
        let handle = self.poller.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Chunks;

    /// Mach3 runs the program file itself: a height map is refused, saying why, before the
    /// agent is even asked (none listens here).
    #[test]
    #[allow(clippy::unwrap_used)]
    fn a_height_map_is_refused_naming_why() {
        use fresa_plugin_api::MachineBackend;
        use serde_json::json;
        let b = super::Mach3Backend::new(
            &json!({"agent": "127.0.0.1:9", "secret": "x"}),
            std::sync::Arc::new(|_: &fresa_plugin_api::contract::Event| {}),
        )
        .unwrap();
        let e = b
            .request(
                json!({"op": "load_program", "run": 1, "path": "/nonexistent.nc",
                "start_line": 1, "height_map": {"x0": 0, "y0": 0, "dx": 1, "dy": 1, "nx": 2,
                "ny": 2, "z": [0, 0, 0, 0]}}),
            )
            .unwrap_err();
        assert_eq!(e.code, "unsupported", "{e}");
        assert!(e.message.contains("Mach3 interprets"), "{e}");
    }

    #[test]
    #[allow(clippy::unwrap_used)]
    fn chunks_split_on_char_boundaries() {
        let chunks = |text: &str, max: usize| {
            let mut c = Chunks::new(text.as_bytes(), max);
            let mut out = Vec::new();
            while let Some(piece) = c.next_chunk().unwrap() {
                out.push(piece);
            }
            out
        };
        assert_eq!(chunks("", 4), vec![""]);
        assert_eq!(chunks("abcdefgh", 4), vec!["abcd", "efgh"]);
        assert_eq!(chunks("abcdefghi", 4), vec!["abcd", "efgh", "i"]);
        // A character cut by the end of a piece goes whole into the next one.
        assert_eq!(chunks("abcé bc", 4), vec!["abc", "é b", "c"]);
        assert_eq!(chunks("ab€cdefg", 4), vec!["ab", "€c", "defg"]);
        // Reassembled, they are the program.
        let text = "G1 X1 (é€)\n".repeat(1000);
        assert_eq!(chunks(&text, 64).concat(), text);
        assert!(chunks(&text, 64).iter().all(|c| c.len() <= 64));
    }
}
