//! The simulated machine: the shared state handling of `fresa_plugin_api::kit` plus the one
//! motion thread the machine owns. Requests only change state and queue work; the motion
//! thread moves the axes in small time slices, so stop and feed hold take effect within one
//! slice.

use crate::config::Config;
use crate::program::{self, Plan, Refusal, Step};
use fresa_plugin_api::backend::{LoadProgram, MachineBackend};
use fresa_plugin_api::contract::{
    io, Axis, IoValue, MachineState, MachineStatus, OutputName, ProgramLoaded,
};
use fresa_plugin_api::exec_log::ExecLog;
use fresa_plugin_api::kit::{self, Events, Interrupted, Job, KitConfig, Loaded, MotionThread};
use fresa_plugin_api::{Host, PluginError};
use serde_json::{json, Value};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, MutexGuard};
use std::time::{Duration, Instant};

pub use fresa_plugin_api::kit::EventSink;

/// Most segments one MDI line may make: its moves are all checked, then queued together.
const MDI_MAX_SEGMENTS: u64 = 1_000_000;

/// Longest time the motion thread goes without looking at stop / feed hold.
const SLICE: Duration = Duration::from_millis(5);

// The simulated machine keeps nothing beyond the kit's state: its outputs (spindle, flood
// coolant) and switch inputs are the kit's I/O maps.
type Kit = kit::Kit<Plan, ()>;
type State = kit::State<Plan, ()>;

/// The output's name in the status, or why the simulated machine has none of that name.
fn output_key(name: OutputName) -> Result<&'static str, PluginError> {
    match name {
        OutputName::Spindle => Ok(io::SPINDLE),
        OutputName::Coolant => Ok(io::COOLANT_FLOOD),
        OutputName::ZLift => Err(PluginError::new(
            "unsupported",
            format!("sim-machine has no output {:?}", name.as_str()),
        )),
    }
}

fn off_outputs() -> [(String, Option<IoValue>); 2] {
    [io::SPINDLE, io::COOLANT_FLOOD].map(|k| (k.to_string(), Some(IoValue::On(false))))
}

/// A simulated 4-axis machine. Thread-safe; dropping it stops motion and joins its thread.
pub struct SimMachine {
    core: Arc<Core>,
    worker: MotionThread,
}

struct Core {
    cfg: Config,
    kit: Kit,
}

/// Length a feed applies to (LinuxCNC's rule): the XYZ path, or the A turn in degrees when
/// only A moves.
fn distance(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let xyz = a[..3]
        .iter()
        .zip(&b[..3])
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt();
    if xyz > 0.0 {
        xyz
    } else {
        (a[3] - b[3]).abs()
    }
}

impl Core {
    /// Reads the switches at the current position into the status. Answers the limit or
    /// e-stop that has just become active, if any (a switch that stays pressed trips once,
    /// so the axis can be jogged off it after a reset).
    fn sense(&self, sh: &mut State, ev: &mut Events) -> Option<String> {
        let mut trip = None;
        let levels: Vec<(String, Option<bool>)> = self
            .cfg
            .switches
            .iter()
            .map(|sw| {
                let on = sw.active_at(&sh.pos);
                let was_on = sh.inputs.get(&sw.name) == Some(&Some(true));
                if on && !was_on && sw.trips() && trip.is_none() {
                    trip = Some(sw.name.clone());
                }
                (sw.name.clone(), Some(on))
            })
            .collect();
        sh.set_io(levels, [], ev);
        trip
    }

    // ----- motion thread -----

    fn worker(self: Arc<Self>) {
        while let Some(job) = self.kit.wait_for_job() {
            let run = job.run();
            let result = catch_unwind(AssertUnwindSafe(|| self.run_job(job)))
                .unwrap_or_else(|_| Err(Interrupted::Failed("internal error (panic)".into())));
            self.kit.finish_job(run, result, |_| {});
        }
    }

    /// A move target the motion thread is about to start: outside the travel is an alarm
    /// (requests check before queueing, so this only guards against a bug).
    fn check(&self, target: [f64; 4]) -> Result<(), Interrupted> {
        self.cfg
            .check_travel(target)
            .map_err(|m| Interrupted::Alarm(format!("soft limit: {m}")))
    }

    fn run_job(&self, job: Job<Plan>) -> Result<(), Interrupted> {
        match job {
            Job::Jog(jog) => {
                let target = jog.target(self.kit.lock().pos);
                self.check(target)?;
                self.move_to(target, jog.feed)
            }
            Job::GoToZero => {
                let path = self.kit.lock().go_to_zero_path();
                path.into_iter()
                    .try_for_each(|p| self.move_to(p, self.cfg.rapid_mm_min))
            }
            Job::Mdi(moves) => {
                // An MDI line's feed is not left behind as the programmed feed.
                let feed = self.kit.lock().feed;
                let result = moves.iter().try_for_each(|&(to, f)| {
                    self.check(to)?;
                    self.move_to(to, f)
                });
                self.kit.lock().feed = feed;
                result
            }
            Job::Program(l) => self.run_program(l),
        }
    }

    fn run_program(&self, l: Loaded<Plan>) -> Result<(), Interrupted> {
        // Interpreted again as it runs (it was checked whole at load): memory stays flat.
        let failed = |e: fresa_gcode::GcodeError| Interrupted::Failed(e.to_string());
        let mut steps = l.plan.steps().map_err(failed)?.peekable();
        // Lines before the start line are interpreted but not executed: only their modal
        // effects carry over.
        while let Some(Ok((line, _))) = steps.peek() {
            if *line >= l.start_line {
                break;
            }
            if let Some(Ok((_, step))) = steps.next() {
                self.kit.with(|sh, _| match step {
                    Step::Move { feed: Some(f), .. } => sh.feed = f,
                    Step::UseOffset(o) => sh.active = o,
                    _ => {}
                });
            }
        }
        for line in l.start_line..=l.plan.lines {
            // No new line starts while held or after a stop, even one without motion.
            self.kit.line_gate()?;
            self.kit.with(|sh, _| sh.line = Some(line));
            while let Some(next) = steps.next_if(|s| s.as_ref().map_or(true, |(sl, _)| *sl <= line))
            {
                let (_, step) = next.map_err(failed)?;
                self.run_step(&step)?;
            }
            self.kit.lines_done(l.run, line..=line, Vec::new())?;
        }
        Ok(())
    }

    fn run_step(&self, step: &Step) -> Result<(), Interrupted> {
        match *step {
            Step::Move { to, a, feed } => {
                let target = {
                    let sh = self.kit.lock();
                    program::machine_target(to, a, &sh.offsets[sh.active.index()], sh.pos[3])
                };
                self.check(target)?;
                self.move_to(target, feed.unwrap_or(self.cfg.rapid_mm_min))
            }
            Step::Dwell(seconds) => self.timed(None, seconds.max(0.0) * self.cfg.time_scale, 0.0),
            Step::Pause => {
                self.kit.with(|sh, ev| self.kit.program_pause(sh, ev));
                self.timed(None, 0.0, 0.0)
            }
            Step::UseOffset(o) => {
                self.kit.with(|sh, ev| {
                    if sh.active != o {
                        sh.active = o;
                        sh.push_status(ev);
                    }
                });
                Ok(())
            }
        }
    }

    fn move_to(&self, target: [f64; 4], feed: f64) -> Result<(), Interrupted> {
        let start = self.kit.lock().pos;
        let seconds = self.cfg.move_seconds(distance(&start, &target), feed);
        self.timed(Some((start, target)), seconds, feed)
    }

    /// Spends `seconds` (already scaled) of un-held time, moving linearly from `start` to
    /// `target` when given. Holds while the machine is paused; returns early on abort.
    fn timed(
        &self,
        path: Option<([f64; 4], [f64; 4])>,
        seconds: f64,
        feed: f64,
    ) -> Result<(), Interrupted> {
        let mut sh = self.kit.lock();
        if path.is_some() {
            sh.feed = feed;
        }
        self.timed_locked(sh, path, seconds)
    }

    fn timed_locked<'a>(
        &'a self,
        mut sh: MutexGuard<'a, State>,
        path: Option<([f64; 4], [f64; 4])>,
        seconds: f64,
    ) -> Result<(), Interrupted> {
        let mut done = 0.0;
        let mut last = Instant::now();
        loop {
            if self.kit.aborted() || sh.shutdown {
                return Err(Interrupted::Aborted);
            }
            if sh.state == MachineState::Paused {
                // Feed hold: the position stays where the last slice left it.
                self.kit.note_held(&mut sh);
                sh = self.kit.wait(sh);
                last = Instant::now();
                continue;
            }
            let now = Instant::now();
            done += now.duration_since(last).as_secs_f64();
            last = now;
            let frac = if seconds <= 0.0 {
                1.0
            } else {
                (done / seconds).min(1.0)
            };
            if let Some((a, b)) = path {
                sh.pos = if frac >= 1.0 {
                    b
                } else {
                    std::array::from_fn(|i| a[i] + (b[i] - a[i]) * frac)
                };
                if !self.cfg.switches.is_empty() {
                    let mut ev = Vec::new();
                    let trip = self.sense(&mut sh, &mut ev);
                    if !ev.is_empty() {
                        self.kit.release(sh, ev);
                        sh = self.kit.lock();
                    }
                    if let Some(input) = trip {
                        // Motion ends in the slice that reached the switch.
                        let at = sh.pos;
                        return Err(Interrupted::Tripped {
                            message: format!(
                                "input {input} tripped at X{:.3} Y{:.3} Z{:.3} A{:.3}",
                                at[0], at[1], at[2], at[3]
                            ),
                            input,
                        });
                    }
                }
                let due = sh
                    .last_status
                    .is_none_or(|t| now.duration_since(t) >= self.cfg.status_interval);
                if due {
                    let mut ev = Vec::new();
                    sh.push_status(&mut ev);
                    self.kit.release(sh, ev);
                    sh = self.kit.lock();
                }
            }
            if frac >= 1.0 {
                return Ok(());
            }
            // Finite: travel checks bound every distance, and feeds are positive.
            let wait = Duration::try_from_secs_f64(seconds - done)
                .unwrap_or(SLICE)
                .min(SLICE);
            sh = self.kit.wait_timeout(sh, wait);
        }
    }
}

impl SimMachine {
    /// Creates a machine from its JSON config; its events go to `sink`.
    pub fn new(config: &Value, sink: EventSink) -> Result<SimMachine, PluginError> {
        let cfg = Config::from_json(config)?;
        let log = match &cfg.execution_log {
            Some(path) => Some(ExecLog::open(path)?),
            None => None,
        };
        let kit_cfg = KitConfig {
            jog_feed_mm_min: cfg.jog_feed_mm_min,
            travel: cfg.travel,
        };
        let core = Arc::new(Core {
            cfg,
            kit: Kit::new(kit_cfg, sink, log, ()),
        });
        core.kit.with(|sh, ev| {
            sh.set_io([], off_outputs(), ev);
            core.sense(sh, ev);
        });
        let worker_core = Arc::clone(&core);
        let worker = MotionThread::spawn("sim-machine motion", move || worker_core.worker())?;
        Ok(SimMachine { core, worker })
    }

    fn kit(&self) -> &Kit {
        &self.core.kit
    }

    /// Switches spindle or coolant (`None` = toggle). Switching on is refused in alarm;
    /// switching off never is. Answers the new state.
    fn output(&self, name: OutputName, on: Option<bool>) -> Result<Value, PluginError> {
        let key = output_key(name)?;
        self.kit().with(|sh, ev| {
            sh.require_online()?;
            let current = sh.outputs.get(key) == Some(&Some(IoValue::On(true)));
            let new = on.unwrap_or(!current);
            if new && !current {
                sh.require_no_alarm(&format!("switch the {} on", name.as_str()))?;
            }
            sh.set_io([], [(key.to_string(), Some(IoValue::On(new)))], ev);
            Ok(json!({"output": name, "on": new}))
        })
    }
}

impl MachineBackend for SimMachine {
    fresa_plugin_api::kit_backend_methods!();

    fn create(host: Host, config: Value) -> Result<Self, PluginError> {
        SimMachine::new(&config, Arc::new(move |event| host.emit(event)))
    }

    fn connect(&self) -> Result<MachineStatus, PluginError> {
        Ok(self
            .kit()
            .connect(self.core.cfg.alarm_at_connect.as_deref()))
    }

    // The simulated machine has no part zero of its own to compare.
    fn load_program(&self, p: LoadProgram) -> Result<ProgramLoaded, PluginError> {
        let kit = self.kit();
        let start = kit.logged_start(p.run, p.start_line)?;
        let (work, offsets, active, a) = {
            let sh = kit.lock();
            sh.require_still("load a program")?;
            let st = sh.status();
            (
                st.work_position.to_array(),
                sh.offsets,
                sh.active,
                sh.pos[3],
            )
        };
        let (file, lines) = kit::open_program(&p.path)?;
        let xyz = offsets.map(|o| [o[0], o[1], o[2]]);
        let tools =
            fresa_gcode::tool_table(p.tools.iter().map(|t| (t.tool, t.diameter_mm, t.length_mm)));
        let budget = p.max_segments.unwrap_or(fresa_gcode::DEFAULT_MAX_SEGMENTS);
        let plan = program::plan_file(file, lines, work, xyz, tools, budget);
        plan.check(&offsets, active, a, |p| self.core.cfg.check_travel(p))
            .map_err(|r| match r {
                Refusal::Gcode(e) if e.kind == fresa_gcode::ErrorKind::Budget => PluginError::new(
                    "work_budget_exceeded",
                    format!("{e}; the budget is the server's `max_program_segments`"),
                ),
                Refusal::Gcode(e) => PluginError::new("invalid_program", e.to_string()),
                Refusal::Travel(m) => PluginError::new("out_of_travel", m),
            })?;
        kit.install_plan(p.run, plan, lines, p.start_line, start)
    }

    fn reset(&self) -> Result<(), PluginError> {
        self.kit().reset(|sh| {
            // As a controller's reset does: spindle and coolant off. (The status event goes
            // out with the reset's state change.)
            sh.outputs.extend(off_outputs());
            Ok(())
        })
    }

    fn jog(&self, axis: Axis, distance: f64, feed: Option<f64>) -> Result<(), PluginError> {
        self.kit().jog(axis, distance, feed)
    }

    fn home(&self, axis: Option<Axis>) -> Result<(), PluginError> {
        self.kit().home(axis, |sh, axis| match axis {
            Some(a) => sh.pos[a.index()] = 0.0,
            None => sh.pos = [0.0; 4],
        })?;
        // Homing declares a new position: the switches read there (no trip, nothing moved).
        self.kit().with(|sh, ev| self.core.sense(sh, ev));
        Ok(())
    }

    fn set_output(&self, name: OutputName, on: bool) -> Result<Value, PluginError> {
        self.output(name, Some(on))
    }

    fn toggle_output(&self, name: OutputName) -> Result<Value, PluginError> {
        self.output(name, None)
    }

    /// One MDI line: interpreted alone from the current work position (so G91/G90, F and
    /// motion mode in it last for this line only), every move checked against `travel`
    /// before any starts, then run like a jog (state `jogging`, stop/feed hold end it).
    fn mdi(&self, line: &str) -> Result<(), PluginError> {
        if line.contains(['\n', '\r']) {
            return Err(PluginError::new(
                "invalid_gcode",
                "MDI takes exactly one line (no line breaks)",
            ));
        }
        let (work, offsets, active, mut a) = {
            let sh = self.kit().lock();
            sh.require_online()?;
            sh.require_no_alarm("run MDI")?;
            sh.require_still("run MDI")?;
            (
                sh.status().work_position.to_array(),
                sh.offsets,
                sh.active,
                sh.pos[3],
            )
        };
        let plan = program::plan(
            line,
            work,
            offsets.map(|o| [o[0], o[1], o[2]]),
            fresa_gcode::ToolTable::new(),
        )
        .with_max_segments(MDI_MAX_SEGMENTS);
        let invalid = |e: fresa_gcode::GcodeError| {
            PluginError::new("invalid_gcode", format!("MDI {line:?}: {e}"))
        };
        let mut moves = Vec::new();
        for step in plan.steps().map_err(invalid)? {
            let (_, step) = step.map_err(invalid)?;
            match step {
                Step::Move { to, a: to_a, feed } => {
                    let target = program::machine_target(to, to_a, &offsets[active.index()], a);
                    a = target[3];
                    self.core.cfg.check_travel(target).map_err(|m| {
                        PluginError::new("out_of_travel", format!("MDI {line:?} refused: {m}"))
                    })?;
                    moves.push((target, feed.unwrap_or(self.core.cfg.rapid_mm_min)));
                }
                other => {
                    return Err(PluginError::new(
                        "unsupported",
                        format!(
                            "sim-machine MDI runs moves only; {line:?} has {}",
                            match other {
                                Step::Dwell(_) => "a dwell",
                                Step::Pause => "a program pause",
                                _ => "a work offset change",
                            }
                        ),
                    ))
                }
            }
        }
        self.kit().queue_mdi(moves, offsets, active)
    }
}

impl Drop for SimMachine {
    fn drop(&mut self) {
        self.core.kit.end_motion_thread();
        self.worker.join();
    }
}
