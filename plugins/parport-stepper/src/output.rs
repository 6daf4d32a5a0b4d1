//! The output side of the loop: coil and lift registers, input decoding, idle de-energising
//! and tick pacing with absolute deadlines. Owned by the one output thread.

use crate::coils::CoilMap;
use crate::config::{Config, Input, InputFunction};
use crate::pins;
use crate::port::Port;
use std::io;
use std::time::{Duration, Instant};

/// Keeps ticks on absolute deadlines: sleep until close to the deadline, then spin.
pub struct Pacer {
    /// `None`: virtual time (tests), never waits.
    period: Option<Duration>,
    spin: Duration,
    next: Instant,
    /// Times the loop fell so far behind that it gave up catching up.
    pub overruns: u64,
    /// How late each wait ended against its deadline, over the current window.
    lateness: Lateness,
}

/// Lateness figures of the output loop over a window of ticks, microseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatenessReport {
    pub p50_us: f64,
    pub p99_us: f64,
    pub max_us: f64,
    pub ticks: u64,
}

/// Buckets of [`LATENESS_BUCKET_NS`]: 0 to 200 us; later ticks count in the last one (the
/// maximum is kept exactly).
const LATENESS_BUCKETS: usize = 400;
const LATENESS_BUCKET_NS: u64 = 500;

/// A fixed histogram of lateness (no allocation in the loop, one increment a tick).
struct Lateness {
    counts: Box<[u32; LATENESS_BUCKETS]>,
    n: u64,
    max_ns: u64,
    /// Ticks per window (10 s of ticks: each report is a `machine.io` event, so not too
    /// often); 0: not recorded (virtual time).
    window: u64,
    ready: Option<LatenessReport>,
}

impl Lateness {
    fn new(period: Option<Duration>) -> Lateness {
        let window = period.map_or(0, |p| (10.0 / p.as_secs_f64()).ceil() as u64);
        Lateness {
            counts: Box::new([0; LATENESS_BUCKETS]),
            n: 0,
            max_ns: 0,
            window,
            ready: None,
        }
    }

    #[inline]
    fn record(&mut self, late: Duration) {
        if self.window == 0 {
            return;
        }
        let ns = u64::try_from(late.as_nanos()).unwrap_or(u64::MAX);
        let b = ((ns / LATENESS_BUCKET_NS) as usize).min(LATENESS_BUCKETS - 1);
        self.counts[b] += 1;
        self.max_ns = self.max_ns.max(ns);
        self.n += 1;
        if self.n >= self.window {
            self.ready = Some(self.report());
            self.counts.fill(0);
            self.n = 0;
            self.max_ns = 0;
        }
    }

    /// The upper edge of the bucket holding quantile `q` (so a figure is never too low).
    fn quantile_us(&self, q: f64) -> f64 {
        let want = ((self.n as f64) * q).ceil().max(1.0) as u64;
        let mut seen = 0u64;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += u64::from(c);
            if seen >= want {
                let edge = (i as u64 + 1) * LATENESS_BUCKET_NS;
                return edge.min(self.max_ns.max(1)) as f64 / 1000.0;
            }
        }
        self.max_ns as f64 / 1000.0
    }

    fn report(&self) -> LatenessReport {
        LatenessReport {
            p50_us: self.quantile_us(0.5),
            p99_us: self.quantile_us(0.99),
            max_us: self.max_ns as f64 / 1000.0,
            ticks: self.n,
        }
    }
}

impl Pacer {
    pub fn new(period: Option<Duration>, spin: Duration) -> Pacer {
        Pacer {
            period,
            spin,
            next: Instant::now(),
            overruns: 0,
            lateness: Lateness::new(period),
        }
    }

    /// Deadlines count from now on (after idling).
    pub fn restart(&mut self) {
        self.next = Instant::now();
    }

    /// The deadline of the tick being waited for (or last waited for).
    pub fn deadline(&self) -> Instant {
        self.next
    }

    /// The lateness of the last full window (10 s of ticks), once: the loop's real jitter on
    /// this PC, for the status.
    pub fn take_lateness(&mut self) -> Option<LatenessReport> {
        self.lateness.ready.take()
    }

    /// Waits for the next tick's deadline: sleeps until `spin` before it (the kernel's wake-up
    /// is late by tens of microseconds on a stock kernel), then spins to it.
    pub fn wait(&mut self) {
        let Some(period) = self.period else { return };
        self.next += period;
        let now = Instant::now();
        if now > self.next + period {
            // A whole tick missed (preempted, overloaded): shift the schedule instead of
            // catching up, since a burst of late ticks would step a motor faster than its
            // max rate and lose steps. Motion is delayed, never compressed.
            self.lateness.record(now - (self.next - period));
            self.next = now;
            self.overruns += 1;
            return;
        }
        if self.next > now + self.spin {
            std::thread::sleep(self.next - now - self.spin);
        }
        let mut t = Instant::now();
        while t < self.next {
            std::hint::spin_loop();
            t = Instant::now();
        }
        self.lateness.record(t - self.next);
    }
}

/// Register state and I/O of the output loop.
pub struct Output {
    port: Box<dyn Port>,
    coils: [CoilMap; 2],
    pub pos: [i64; 2],
    energised: [bool; 2],
    last_step: [u64; 2],
    idle_ticks: u64,
    written_data: Option<u8>,
    control: u8,
    written_control: Option<u8>,
    lift_pin: u8,
    lift_invert: bool,
    inputs: Vec<Input>,
    /// Inputs active at the last read (bit per entry of `inputs`).
    active: u32,
    /// Debounced levels, as the status shows them (bit per entry of `inputs`), and since when
    /// each input's read level has differed from its shown one.
    shown: u32,
    differs_since: Vec<Option<Instant>>,
    debounce: Duration,
    /// The shown levels changed since the machine last took them (true at first: the first
    /// read makes them known).
    shown_changed: bool,
    /// Global tick counter (never frozen, unlike a plan's timeline).
    pub tick: u64,
    pub pacer: Pacer,
}

impl Output {
    pub fn new(cfg: &Config, port: Box<dyn Port>, pacer: Pacer, lift: bool) -> Output {
        let idle_ticks = (cfg.idle_off.as_secs_f64() * cfg.machine.tick_hz).ceil() as u64;
        let mut out = Output {
            port,
            coils: cfg.coils,
            pos: [0, 0],
            energised: [false; 2],
            last_step: [0; 2],
            idle_ticks: idle_ticks.max(1),
            written_data: None,
            control: 0,
            written_control: None,
            lift_pin: cfg.lift_pin,
            lift_invert: cfg.lift_invert,
            inputs: cfg.inputs.clone(),
            active: 0,
            shown: 0,
            differs_since: vec![None; cfg.inputs.len()],
            debounce: cfg.input_debounce,
            shown_changed: true,
            tick: 0,
            pacer,
        };
        out.set_lift(lift);
        out
    }

    /// Starts a tick: reads the inputs. Returns an input that trips the machine: an e-stop
    /// while active, a limit when it becomes active (so the axis can be jogged off it).
    pub fn begin(&mut self) -> io::Result<Option<Input>> {
        self.port.begin_tick(self.tick);
        let status = self.port.read_status()?;
        let mut trip = None;
        let mut active = 0;
        for (i, input) in self.inputs.iter().enumerate() {
            if pins::input_level(status, input.pin) != input.active_low {
                active |= 1 << i;
                let edge = self.active & (1 << i) == 0;
                if trip.is_none()
                    && input.function.trips()
                    && (edge || input.function == InputFunction::EStop)
                {
                    trip = Some(*input);
                }
            }
        }
        self.active = active;
        self.debounce_shown();
        Ok(trip)
    }

    /// Moves each input's shown level to its read level once that has held for the debounce
    /// time. Reads the clock only while some input differs.
    fn debounce_shown(&mut self) {
        let differing = self.active ^ self.shown;
        if differing == 0 {
            self.differs_since.iter_mut().for_each(|d| *d = None);
            return;
        }
        let now = Instant::now();
        for (i, since) in self.differs_since.iter_mut().enumerate() {
            let bit = 1 << i;
            if differing & bit == 0 {
                *since = None;
                continue;
            }
            let start = *since.get_or_insert(now);
            if now.duration_since(start) >= self.debounce {
                self.shown ^= bit;
                *since = None;
                self.shown_changed = true;
            }
        }
    }

    /// The shown input levels by status name, when they changed since the last call. Inputs
    /// sharing a name (two pins of one limit chain) show active when any of them is.
    pub fn take_shown_inputs(&mut self) -> Option<Vec<(String, Option<bool>)>> {
        if !std::mem::take(&mut self.shown_changed) {
            return None;
        }
        let mut levels: Vec<(String, Option<bool>)> = Vec::new();
        for (i, input) in self.inputs.iter().enumerate() {
            let on = self.shown & (1 << i) != 0;
            let name = input.function.io_name();
            match levels.iter_mut().find(|(n, _)| *n == name) {
                Some((_, level)) => *level = Some(level.unwrap_or(false) || on),
                None => levels.push((name, Some(on))),
            }
        }
        Some(levels)
    }

    /// Whether an input of `function` read active at the start of this tick: the raw level
    /// (not the debounced one the status shows), so a probing move reacts within the tick that
    /// reads the pin. Inputs sharing a function count as one (active when any of them is).
    pub fn input_active(&self, function: InputFunction) -> bool {
        self.inputs
            .iter()
            .enumerate()
            .any(|(i, inp)| self.active & (1 << i) != 0 && inp.function == function)
    }

    /// An active e-stop input, if any (for refusing reset).
    pub fn estop_active(&self) -> Option<Input> {
        self.inputs
            .iter()
            .enumerate()
            .find(|(i, inp)| self.active & (1 << i) != 0 && inp.function == InputFunction::EStop)
            .map(|(_, inp)| *inp)
    }

    /// Moves the motors to `pos` in this tick (each axis by at most one step).
    pub fn step(&mut self, pos: [i64; 2]) {
        for (i, p) in pos.into_iter().enumerate() {
            if p != self.pos[i] {
                self.pos[i] = p;
                self.energised[i] = true;
                self.last_step[i] = self.tick;
            }
        }
    }

    pub fn set_lift(&mut self, on: bool) {
        self.control = pins::control_register([(self.lift_pin, on != self.lift_invert)]);
    }

    /// Switches every coil off now (alarm).
    pub fn coils_off(&mut self) {
        self.energised = [false; 2];
    }

    pub fn coils_on(&self) -> bool {
        self.energised.iter().any(|e| *e)
    }

    /// Ends a tick: de-energises idle motors, writes what changed, and (when `wait`) waits for
    /// the next tick's deadline.
    pub fn end(&mut self, wait: bool) -> io::Result<()> {
        let mut data = 0;
        for i in 0..2 {
            if self.energised[i] && self.tick - self.last_step[i] >= self.idle_ticks {
                self.energised[i] = false;
            }
            if self.energised[i] {
                data |= self.coils[i].register_bits(self.pos[i]);
            }
        }
        if self.written_data != Some(data) {
            self.port.write_data(data)?;
            self.written_data = Some(data);
        }
        if self.written_control != Some(self.control) {
            self.port.write_control(self.control)?;
            self.written_control = Some(self.control);
        }
        if wait {
            self.pacer.wait();
        }
        self.tick += 1;
        Ok(())
    }
}

/// A libc call's result as these functions report it: Err holds the OS's reason.
#[cfg(target_os = "linux")]
fn os_status(r: libc::c_int) -> Result<(), String> {
    if r == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error().to_string())
    }
}

/// A CPU number a `cpu_set_t` can hold (the CPU_* macros index it unchecked).
#[cfg(target_os = "linux")]
fn cpu_in_range(cpu: usize) -> Result<(), String> {
    if cpu < libc::CPU_SETSIZE as usize {
        Ok(())
    } else {
        Err(format!("CPU {cpu} is out of range"))
    }
}

#[cfg(not(target_os = "linux"))]
fn not_on_this_os() -> Result<(), String> {
    Err("only implemented on Linux".into())
}

/// Sets the calling thread's timer slack to 1 ns: a normal thread's sleeps may end up to
/// 50 us late (the default slack), which is a whole tick at 20 kHz. (Real-time threads have
/// none.) Err says why not.
pub fn tight_timer_slack() -> Result<(), String> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: PR_SET_TIMERSLACK takes a plain integer argument; no memory is passed.
        let r = unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0) };
        os_status(r)
    }
    #[cfg(not(target_os = "linux"))]
    not_on_this_os()
}

/// Pins the calling thread to CPU `cpu` (an isolated or otherwise idle core keeps other work
/// from delaying ticks). Err says why not.
pub fn pin_to_cpu(cpu: usize) -> Result<(), String> {
    #[cfg(target_os = "linux")]
    {
        cpu_in_range(cpu)?;
        // SAFETY: a zeroed cpu_set_t is valid; CPU_SET writes within it (cpu checked above);
        // sched_setaffinity reads it for the calling thread.
        let r = unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            libc::CPU_SET(cpu, &mut set);
            libc::sched_setaffinity(0, std::mem::size_of_val(&set), &set)
        };
        os_status(r)
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = cpu;
        not_on_this_os()
    }
}

/// Lets the calling thread run on every CPU the process may use except `cpu`, the output
/// loop's own. A thread the pinned output thread starts (the planner) inherits its one CPU and
/// its priority, and woken there every millisecond it delayed a tick by ~10 µs each time
/// (loop lateness p99 12.5 µs at 40 kHz in the server, 0.5 µs once moved). Err says why not:
/// then it stays where it was.
pub fn avoid_cpu(cpu: usize) -> Result<(), String> {
    #[cfg(target_os = "linux")]
    {
        cpu_in_range(cpu)?;
        // SAFETY: a zeroed cpu_set_t is valid; sched_getaffinity fills it and CPU_CLR and
        // CPU_COUNT stay within it (cpu checked above); sched_setaffinity reads it.
        unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            // The main thread (its id is the process's) keeps the CPUs the process was given.
            os_status(libc::sched_getaffinity(
                libc::getpid(),
                std::mem::size_of_val(&set),
                &mut set,
            ))?;
            libc::CPU_CLR(cpu, &mut set);
            if libc::CPU_COUNT(&set) == 0 {
                return Err(format!("CPU {cpu} is the only one this process may use"));
            }
            os_status(libc::sched_setaffinity(
                0,
                std::mem::size_of_val(&set),
                &set,
            ))
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = cpu;
        not_on_this_os()
    }
}

/// Gives the calling thread the highest normal (`SCHED_OTHER`) priority, nice -20: it then
/// gets nearly all of a CPU it shares, and the kernel's real-time throttling never applies
/// to it. Err says why not (lowering a nice value needs `CAP_SYS_NICE` or `RLIMIT_NICE`).
pub fn highest_normal_priority() -> Result<(), String> {
    fresa_plugin_api::priority::set_thread_nice(HIGHEST_NICE)
}

/// The nice value `highest_normal_priority` asks for.
pub const HIGHEST_NICE: i32 = -20;

/// Asks for real-time (SCHED_FIFO) priority for the calling thread. Err says why not.
pub fn realtime_priority() -> Result<(), String> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: plain syscalls on the calling thread with a valid, initialised parameter.
        let r = unsafe {
            let param = libc::sched_param {
                sched_priority: libc::sched_get_priority_min(libc::SCHED_FIFO).max(1),
            };
            libc::sched_setscheduler(0, libc::SCHED_FIFO, &param)
        };
        os_status(r)
    }
    #[cfg(not(target_os = "linux"))]
    not_on_this_os()
}

/// How the output thread asks to be scheduled.
#[derive(Debug, PartialEq, Eq)]
pub enum Scheduling {
    /// As the thread started (`realtime_priority: false`, or virtual time).
    AsStarted,
    /// `SCHED_FIFO`.
    RealTime,
    /// Nice -20. A loop that spins every whole tick never sleeps, and under the kernel's
    /// real-time throttling a `SCHED_FIFO` thread that never sleeps is stopped for the rest of
    /// each second once it has run `rt_limit` µs of it (measured: ~50 ms stalls, the CPU idle
    /// meanwhile). A normal thread is never throttled; at nice -20 it keeps nearly all of its
    /// CPU, and other work delays it only when that work runs on the same CPU.
    HighestNormal { rt_limit: i64 },
}

pub fn scheduling(want_rt: bool, always_spins: bool, rt_limit: Option<i64>) -> Scheduling {
    match (want_rt, always_spins, rt_limit) {
        (false, _, _) => Scheduling::AsStarted,
        (true, true, Some(rt_limit)) => Scheduling::HighestNormal { rt_limit },
        (true, _, _) => Scheduling::RealTime,
    }
}

impl Scheduling {
    /// Asks the kernel for it, for the calling thread. Err says why not.
    pub fn apply(&self) -> Result<(), String> {
        match self {
            Scheduling::AsStarted => Ok(()),
            Scheduling::RealTime => realtime_priority(),
            Scheduling::HighestNormal { .. } => highest_normal_priority(),
        }
    }
}

/// The kernel's real-time runtime limit (`kernel.sched_rt_runtime_us`) when real-time threads
/// are throttled (None: not throttled, or not known).
pub fn rt_throttle_limit() -> Option<i64> {
    let text = std::fs::read_to_string("/proc/sys/kernel/sched_rt_runtime_us").ok()?;
    let v: i64 = text.trim().parse().ok()?;
    (v >= 0).then_some(v)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The window's figures come from the recorded lateness, never below it (bucket upper
    /// edges), with the maximum exact; a new window starts empty.
    #[test]
    fn lateness_windows_report_quantiles_and_the_exact_maximum() {
        // 1 kHz: a window is 10,000 ticks.
        let mut l = Lateness::new(Some(Duration::from_millis(1)));
        for i in 0..9_850u64 {
            l.record(Duration::from_nanos(200 + i % 100)); // bucket 0
        }
        for _ in 0..149 {
            l.record(Duration::from_micros(7)); // 149 ticks at 7 us: the 99th percentile
        }
        assert!(l.ready.is_none());
        l.record(Duration::from_millis(3)); // beyond the histogram: max only
        let r = l.ready.take().unwrap();
        assert_eq!(r.ticks, 10_000);
        assert_eq!(r.p50_us, 0.5);
        assert_eq!(r.p99_us, 7.5);
        assert_eq!(r.max_us, 3000.0);
        l.record(Duration::from_micros(1));
        assert_eq!(l.n, 1);
        assert_eq!(l.max_ns, 1000);
        // Virtual time records nothing.
        let mut v = Lateness::new(None);
        v.record(Duration::from_micros(5));
        assert_eq!((v.n, v.ready), (0, None));
    }

    /// The CPUs the calling thread may run on, as the kernel lists them ("0-1", "1").
    #[cfg(target_os = "linux")]
    fn cpus_allowed() -> String {
        let status = std::fs::read_to_string("/proc/thread-self/status").unwrap();
        status
            .lines()
            .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
            .unwrap()
            .trim()
            .to_string()
    }

    /// A thread started by the pinned output thread inherits its CPU; `avoid_cpu` moves it to
    /// the process's other CPUs (this test needs two, as the project's machines have).
    #[cfg(target_os = "linux")]
    #[test]
    fn a_thread_the_pinned_loop_starts_leaves_the_loops_cpu() {
        let cpus = std::thread::available_parallelism().unwrap().get();
        assert!(cpus >= 2, "this test needs 2 CPUs, the machine has {cpus}");
        let last = cpus - 1;
        let (inherited, moved) = std::thread::spawn(move || {
            pin_to_cpu(last).unwrap();
            std::thread::spawn(move || {
                let inherited = cpus_allowed();
                avoid_cpu(last).unwrap();
                (inherited, cpus_allowed())
            })
            .join()
            .unwrap()
        })
        .join()
        .unwrap();
        assert_eq!(inherited, last.to_string());
        let moved: Vec<usize> = moved
            .split(',')
            .flat_map(|r| match r.split_once('-') {
                Some((a, b)) => (a.parse().unwrap()..=b.parse().unwrap()).collect::<Vec<_>>(),
                None => vec![r.parse().unwrap()],
            })
            .collect();
        assert!(!moved.is_empty() && !moved.contains(&last), "{moved:?}");
    }

    #[test]
    fn only_a_loop_that_spins_whole_ticks_under_throttling_gives_up_sched_fifo() {
        use Scheduling::*;
        assert_eq!(scheduling(false, true, Some(950_000)), AsStarted);
        assert_eq!(scheduling(false, false, None), AsStarted);
        assert_eq!(scheduling(true, false, Some(950_000)), RealTime);
        assert_eq!(scheduling(true, true, None), RealTime);
        assert_eq!(
            scheduling(true, true, Some(950_000)),
            HighestNormal { rt_limit: 950_000 }
        );
    }
}
