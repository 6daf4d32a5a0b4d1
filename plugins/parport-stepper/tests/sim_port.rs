//! The output loop on a simulated port, in virtual time (no waiting; ticks are counted): what
//! reaches the coils is decoded back into motor positions and checked.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_parport_stepper::coils::CoilMap;
use fresa_parport_stepper::pins;
use fresa_parport_stepper::port::{Register, Write};
use fresa_parport_stepper::{Config, Stepper, Timing};
use fresa_plugin_api::contract::{Event, ProbeOutcome};
use fresa_plugin_api::MachineBackend;
use serde_json::{json, Value};
use std::io::Write as _;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

struct Rig {
    m: Stepper,
    cfg: Config,
    events: Arc<Mutex<Vec<Event>>>,
    _dir: tempfile_dir::Dir,
}

mod tempfile_dir {
    pub struct Dir(pub std::path::PathBuf);
    impl Dir {
        pub fn new(tag: &str) -> Dir {
            let p = std::env::temp_dir().join(format!(
                "parport-test-{tag}-{}-{:?}",
                std::process::id(),
                std::time::SystemTime::now()
            ));
            std::fs::create_dir_all(&p).unwrap();
            Dir(p)
        }
    }
    impl Drop for Dir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

fn rig(tag: &str, config: Value) -> Rig {
    rig_timed(tag, config, Timing::Virtual)
}

fn rig_timed(tag: &str, config: Value, timing: Timing) -> Rig {
    let cfg = Config::from_json(&config).unwrap();
    let events = Arc::new(Mutex::new(Vec::new()));
    let sink = events.clone();
    let m = Stepper::new(
        &config,
        Arc::new(move |e: &Event| sink.lock().unwrap().push(e.clone())),
        Arc::new(|_, _| {}),
        timing,
    )
    .unwrap();
    m.request(json!({"op":"connect"})).unwrap();
    Rig {
        m,
        cfg,
        events,
        _dir: tempfile_dir::Dir::new(tag),
    }
}

impl Rig {
    fn run(&self, program: &str) -> Event {
        let path = self._dir.0.join("p.nc");
        std::fs::File::create(&path)
            .unwrap()
            .write_all(program.as_bytes())
            .unwrap();
        self.m
            .request(json!({"op":"load_program","run":1,"path":path,"start_line":1}))
            .unwrap();
        self.m
            .request(json!({"op":"run","action":"start"}))
            .unwrap();
        self.wait(|e| matches!(e, Event::RunEnded { .. }))
    }

    fn wait(&self, f: impl Fn(&Event) -> bool) -> Event {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Some(e) = self.events.lock().unwrap().iter().find(|e| f(e)) {
                return e.clone();
            }
            assert!(Instant::now() < deadline, "timed out waiting for an event");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Polls the status until `f` holds (I/O shows after the debounce time).
    fn wait_status(&self, f: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let st = self.m.request(json!({"op":"status"})).unwrap();
            if f(&st) {
                return st;
            }
            assert!(Instant::now() < deadline, "status never matched: {st}");
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// Waits until the loop has switched every coil off, then returns the writes.
    fn writes_after_idle(&self) -> Vec<Write> {
        let port = self.m.sim_port.clone().unwrap();
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let w: Vec<Write> = port.lock().writes.iter().copied().collect();
            let last_data = w.iter().rev().find(|w| w.register == Register::Data);
            if last_data.is_some_and(|w| w.value == 0) {
                return w;
            }
            assert!(Instant::now() < deadline, "coils never switched off");
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

/// Replays the data writes: positions of each motor after every write, checking that every
/// energised pattern follows the last energised one legally (same or one step either way).
fn replay(coils: &[CoilMap; 2], writes: &[Write]) -> Vec<(u64, [i64; 2])> {
    let mut pos = [0i64; 2];
    let mut last: [Option<u8>; 2] = [None; 2];
    let mut out = Vec::new();
    for w in writes.iter().filter(|w| w.register == Register::Data) {
        for i in 0..2 {
            let p = coils[i].gather(w.value);
            if p == 0 {
                continue;
            }
            let e = coils[i].excitation;
            let seq = e.sequence();
            match last[i] {
                None => {
                    // First energising: from position 0's pattern or one step away.
                    assert!(
                        e.is_legal_transition(e.pattern(0), p),
                        "axis {i}: first pattern {p:04b} skips a phase"
                    );
                }
                Some(prev) => {
                    assert!(
                        e.is_legal_transition(prev, p),
                        "axis {i}: {prev:04b} -> {p:04b} skips a phase at tick {}",
                        w.tick
                    );
                }
            }
            let prev = last[i].unwrap_or(e.pattern(0));
            let a = seq.iter().position(|x| *x == prev).unwrap() as i64;
            let b = seq.iter().position(|x| *x == p).unwrap() as i64;
            let n = seq.len() as i64;
            let d = (b - a).rem_euclid(n);
            pos[i] += match d {
                0 => 0,
                1 => 1,
                _ => -1,
            };
            last[i] = Some(p);
        }
        out.push((w.tick, pos));
    }
    out
}

fn sim(extra: Value) -> Value {
    let mut c = json!({"port":"sim","axes":{"x":{"steps_per_mm":20,"max_rate":2000,"accel":20000},
                                            "y":{"steps_per_mm":20,"max_rate":2000,"accel":20000}}});
    for (k, v) in extra.as_object().unwrap() {
        c[k] = v.clone();
    }
    c
}

#[test]
fn diagonal_is_straight_and_ends_exactly_then_coils_go_off() {
    let r = rig("diag", sim(json!({})));
    let end = r.run("G21 G90\nG1 X60 Y30 F600\nG1 X-7.5 Y12.25\n");
    assert!(
        matches!(
            end,
            Event::RunEnded {
                outcome: fresa_plugin_api::contract::RunOutcome::Completed,
                ..
            }
        ),
        "{end:?}"
    );
    let writes = r.writes_after_idle();
    let path = replay(&r.cfg.coils, &writes);
    // Line 2: (0,0) -> (1200, 600) steps; every point within one step of the line.
    let mut worst: f64 = 0.0;
    let mut corner = None;
    for (_, p) in &path {
        if corner.is_none() {
            let d = (p[0] as f64 * 600.0 - p[1] as f64 * 1200.0).abs() / (1200.0f64.hypot(600.0));
            worst = worst.max(d);
            if *p == [1200, 600] {
                corner = Some(*p);
            }
        }
    }
    assert!(corner.is_some(), "reached the corner");
    assert!(worst <= 1.0, "deviation {worst} steps");
    let last = path.last().unwrap().1;
    assert_eq!(last, [-150, 245], "exact final step counts");
    // Idle de-energise: the final all-off write comes 15 ms (300 ticks at 20 kHz) after the
    // last step, not earlier and not much later.
    let off = writes
        .iter()
        .rev()
        .find(|w| w.register == Register::Data)
        .unwrap();
    assert_eq!(off.value, 0);
    let last_step = path
        .windows(2)
        .rev()
        .find(|w| w[0].1 != w[1].1)
        .map(|w| w[1].0)
        .unwrap();
    let idle = off.tick - last_step;
    assert!(
        (300..=302).contains(&idle),
        "de-energised after {idle} ticks"
    );
    // Status agrees.
    let st = r.m.request(json!({"op":"status"})).unwrap();
    assert_eq!(st["machine_position"]["x"], -7.5);
    assert_eq!(st["machine_position"]["y"], 12.25);
}

#[test]
fn arcs_stay_near_the_circle_and_report_deviation_per_line() {
    for exc in ["full_step", "wave", "half_step"] {
        let r = rig(
            "arc",
            sim(
                json!({"axes":{"x":{"steps_per_mm":20,"max_rate":2000,"accel":20000,"excitation":exc},
                               "y":{"steps_per_mm":20,"max_rate":2000,"accel":20000,"excitation":exc}}}),
            ),
        );
        r.run("G21 G90\nG0 X10 Y0\nG3 X-10 Y0 I-10 J0 F600\n");
        let writes = r.writes_after_idle();
        let path = replay(&r.cfg.coils, &writes);
        let start = path.iter().position(|(_, p)| *p == [200, 0]).unwrap();
        let mut worst: f64 = 0.0;
        for (_, p) in &path[start..] {
            let rad = (p[0] as f64).hypot(p[1] as f64);
            worst = worst.max((rad - 200.0).abs());
        }
        assert!(worst <= 1.0, "{exc}: {worst} steps off the circle");
        assert_eq!(path.last().unwrap().1, [-200, 0]);
        let reports: Vec<_> = r
            .events
            .lock()
            .unwrap()
            .iter()
            .filter_map(|e| match e {
                Event::LineReport {
                    line,
                    max_deviation_mm,
                    percent,
                    ..
                } => Some((*line, *max_deviation_mm, *percent)),
                _ => None,
            })
            .collect();
        assert_eq!(reports.iter().map(|r| r.0).collect::<Vec<_>>(), [2, 3]);
        assert!(reports[1].1 > 0.0 && reports[1].1 <= 0.05, "{reports:?}");
        assert_eq!(reports[1].2, 100.0);
    }
}

#[test]
fn limit_input_stops_within_one_tick_alarms_and_fails_the_run() {
    let r = rig(
        "limit",
        sim(
            json!({"inputs":[{"pin":10,"function":"limit_x"},{"pin":11,"function":"estop","active_low":true}],
                   "sim_inputs":[{"after_writes":100,"pin":10,"level":"high"}]}),
        ),
    );
    let end = r.run("G1 X50 Y5 F600\n");
    match &end {
        Event::RunEnded {
            outcome, message, ..
        } => {
            assert_eq!(*outcome, fresa_plugin_api::contract::RunOutcome::Failed);
            assert_eq!(message.as_deref(), Some("limit switch limit_x (pin 10)"));
        }
        other => panic!("{other:?}"),
    }
    let st = r.m.request(json!({"op":"status"})).unwrap();
    assert_eq!(st["state"], "alarm");
    assert_eq!(st["alarm"], "limit switch limit_x (pin 10)");
    // The alarm event names the input that tripped it.
    let alarm = r.wait(|e| matches!(e, Event::Alarm { .. }));
    assert_eq!(
        alarm,
        Event::Alarm {
            message: "limit switch limit_x (pin 10)".into(),
            input: Some("limit_x".into())
        }
    );
    // The status shows the switch pressed once it has held for the debounce time, and the
    // e-stop (active low, held high by the quiet level) released.
    let st = r.wait_status(|s| s["inputs"]["limit_x"] == true);
    assert_eq!(st["inputs"]["estop"], false);
    assert_eq!(st["outputs"]["z_lift"], false);
    let port = r.m.sim_port.clone().unwrap();
    let p = port.lock();
    let limit_seen = p
        .status_changes
        .iter()
        .find(|(_, v)| pins::input_level(*v, 10))
        .map(|(t, _)| *t)
        .expect("the loop read the limit");
    let data: Vec<_> = p
        .writes
        .iter()
        .filter(|w| w.register == Register::Data)
        .collect();
    // The 100th write (a step) set the input; it was read at the next tick, in which the only
    // write is all coils off, and nothing is written after it.
    let trip_write = data.iter().position(|w| w.tick >= limit_seen).unwrap();
    assert_eq!(trip_write, 100);
    assert_eq!(data[trip_write].value, 0);
    assert_eq!(
        data[trip_write].tick, limit_seen,
        "stopped in the tick that saw the input"
    );
    assert!(
        limit_seen - data[99].tick <= 40,
        "read within one step period"
    );
    assert_eq!(data.len(), 101, "no write after the stop");
    drop(p);
    // Motion is refused until reset.
    let e =
        r.m.request(json!({"op":"jog","axis":"X","distance":-1.0}))
            .unwrap_err();
    assert_eq!(e.code, "alarm");
    r.m.request(json!({"op":"command","command":"reset"}))
        .unwrap();
    assert_eq!(
        r.m.request(json!({"op":"status"})).unwrap()["state"],
        "idle"
    );
}

#[test]
fn z_lift_output_and_jogs() {
    let r = rig("lift", sim(json!({"z_lift":{"pin":16}})));
    r.m.request(json!({"op":"command","command":"set_output","name":"z_lift","on":true}))
        .unwrap();
    let port = r.m.sim_port.clone().unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let lifted = port
            .lock()
            .writes
            .iter()
            .rev()
            .find(|w| w.register == Register::Control)
            .is_some_and(|w| pins::output_level(w.value, 16));
        if lifted {
            break;
        }
        assert!(Instant::now() < deadline, "lift never switched on");
        std::thread::sleep(Duration::from_millis(2));
    }
    r.m.request(json!({"op":"jog","axis":"X","distance":2.5,"feed":600}))
        .unwrap();
    r.m.request(json!({"op":"jog","axis":"Y","distance":-1.0,"feed":600}))
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let st = r.m.request(json!({"op":"status"})).unwrap();
        if st["state"] == "idle" {
            assert_eq!(st["machine_position"]["x"], 2.5);
            assert_eq!(st["machine_position"]["y"], -1.0);
            break;
        }
        assert!(Instant::now() < deadline, "jogs never finished: {st}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn feed_hold_ramps_down_and_resume_ramps_up_on_the_same_line() {
    // Real ticks at 5 kHz: 1000 steps/s cruise = a step every 5 ticks; the hold ramp is
    // 1000 / 4000 = 0.25 s.
    let r = rig_timed(
        "hold",
        json!({"port":"sim","tick_hz":5000,"spin_us":0,"realtime_priority":false,
               "axes":{"x":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":4000},
                       "y":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":4000}}}),
        Timing::Real,
    );
    let path = r._dir.0.join("p.nc");
    std::fs::write(&path, "G1 X100 Y20 F60000\n").unwrap();
    r.m.request(json!({"op":"load_program","run":1,"path":path,"start_line":1}))
        .unwrap();
    r.m.request(json!({"op":"run","action":"start"})).unwrap();
    let poll = |what: &str, f: &dyn Fn(&Value) -> bool| {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let st = r.m.request(json!({"op":"status"})).unwrap();
            if f(&st) {
                return st;
            }
            assert!(Instant::now() < deadline, "timed out: {what}; {st}");
            std::thread::sleep(Duration::from_millis(2));
        }
    };
    poll("cruising", &|st| {
        st["machine_position"]["x"].as_f64().unwrap() > 15.0
    });
    r.m.request(json!({"op":"run","action":"pause"})).unwrap();
    // Held: wait for the coils to go off (no step for 15 ms), then resume.
    let port = r.m.sim_port.clone().unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while port
        .lock()
        .writes
        .iter()
        .rev()
        .find(|w| w.register == Register::Data)
        .is_none_or(|w| w.value != 0)
    {
        assert!(Instant::now() < deadline, "never came to rest");
        std::thread::sleep(Duration::from_millis(2));
    }
    r.m.request(json!({"op":"run","action":"resume"})).unwrap();
    r.wait(|e| matches!(e, Event::RunEnded { .. }));
    let writes: Vec<Write> = port.lock().writes.iter().copied().collect();
    let path = replay(&r.cfg.coils, &writes);
    assert_eq!(
        path.last().unwrap().1,
        [2000, 400],
        "exact end after hold and resume"
    );
    // Step ticks of the major axis (X).
    let steps: Vec<u64> = path
        .windows(2)
        .filter(|w| w[0].1[0] != w[1].1[0])
        .map(|w| w[1].0)
        .collect();
    let gaps: Vec<u64> = steps.windows(2).map(|w| w[1] - w[0]).collect();
    let (hold, _) = gaps.iter().enumerate().max_by_key(|(_, g)| **g).unwrap();
    let cruise = *gaps.iter().min().unwrap();
    assert!(cruise <= 6, "cruised at {cruise} ticks a step");
    // Slowed down before the stop and started slowly after it: the step periods around the
    // hold are several times the cruise period, and they change gradually.
    assert!(
        gaps[hold - 1] >= 4 * cruise,
        "{:?}",
        &gaps[hold - 10..hold + 10]
    );
    assert!(
        gaps[hold + 1] >= 4 * cruise,
        "{:?}",
        &gaps[hold - 10..hold + 10]
    );
    let before = &gaps[hold - 30..hold];
    assert!(
        before.windows(2).all(|w| w[1] + 1 >= w[0]),
        "deceleration never speeds up: {before:?}"
    );
}

#[test]
fn e_stop_alarms_while_active_and_reset_waits_for_its_release() {
    let r = rig(
        "estop",
        sim(
            json!({"inputs":[{"pin":15,"function":"estop","active_low":true}],
                   "sim_inputs":[{"after_writes":5,"pin":15,"level":"low"}]}),
        ),
    );
    r.m.request(json!({"op":"jog","axis":"Y","distance":5.0,"feed":600}))
        .unwrap();
    let alarm = r.wait(|e| matches!(e, Event::Alarm { .. }));
    assert_eq!(
        alarm,
        Event::Alarm {
            message: "e-stop (pin 15)".into(),
            input: Some("estop".into())
        }
    );
    let st = r.m.request(json!({"op":"status"})).unwrap();
    assert_eq!(st["state"], "alarm");
    let y = st["machine_position"]["y"].as_f64().unwrap();
    assert!(y > 0.0 && y < 0.5, "stopped after a few steps: {y}");
    let e =
        r.m.request(json!({"op":"command","command":"reset"}))
            .unwrap_err();
    assert!(
        e.message.contains("e-stop (pin 15) is still active"),
        "{}",
        e.message
    );
    assert_eq!(
        r.m.request(json!({"op":"status"})).unwrap()["state"],
        "alarm"
    );
}

/// In real ticks: once cancel, stop, pause or feed hold has answered, no program line starts
/// any more (at most the one in flight is logged); a stopped run's end was emitted before the
/// answer. Holds answer once the timeline has ramped to a stop.
#[test]
fn stop_cancel_and_hold_answer_only_once_no_new_line_starts() {
    let dir = tempfile_dir::Dir::new("stops");
    let log = dir.0.join("exec.log");
    let r = rig_timed(
        "stops",
        json!({"port":"sim","tick_hz":5000,"spin_us":0,"realtime_priority":false,
               "execution_log": log,
               "axes":{"x":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":20000},
                       "y":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":20000}}}),
        Timing::Real,
    );
    let path = r._dir.0.join("p.nc");
    let text: String = (1..=400)
        .map(|i| format!("G1 X{} F60000\n(comment)\n", (i % 2) as f64 * 0.5))
        .collect();
    std::fs::write(&path, text).unwrap();
    let logged = |run: i64| {
        std::fs::read_to_string(&log)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| serde_json::from_str::<Value>(l).ok())
            .filter(|v| v["run"] == run)
            .count()
    };
    let idle = || {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let st = r.m.request(json!({"op":"status"})).unwrap();
            if st["state"] == "idle" && st.get("run").is_none() {
                return;
            }
            assert!(Instant::now() < deadline, "never idle: {st}");
            std::thread::sleep(Duration::from_millis(1));
        }
    };
    let mut most = 0;
    for (run, delay_ms, action) in [
        (1, 0, json!({"op":"run","action":"cancel"})),
        (2, 40, json!({"op":"run","action":"cancel"})),
        (3, 60, json!({"op":"command","command":"stop"})),
        (4, 50, json!({"op":"run","action":"pause"})),
        (5, 70, json!({"op":"command","command":"feed_hold"})),
    ] {
        r.m.request(json!({"op":"load_program","run":run,"path":path,"start_line":1}))
            .unwrap();
        r.events.lock().unwrap().clear();
        r.m.request(json!({"op":"run","action":"start"})).unwrap();
        // The delay is the stimulus (where in the run the request lands), not a wait.
        std::thread::sleep(Duration::from_millis(delay_ms));
        r.m.request(action.clone()).unwrap();
        let at_answer = logged(run);
        most = most.max(at_answer);
        let holds = action["action"] == "pause" || action["command"] == "feed_hold";
        if holds {
            std::thread::sleep(Duration::from_millis(30));
            assert_eq!(
                logged(run),
                at_answer,
                "{action}: a line started while held"
            );
            r.m.request(json!({"op":"run","action":"cancel"})).unwrap();
        } else {
            let ended = r
                .events
                .lock()
                .unwrap()
                .iter()
                .any(|e| matches!(e, Event::RunEnded { run: r, .. } if *r == run));
            assert!(ended, "run_ended not emitted before {action} answered");
        }
        idle();
        let late = logged(run) - at_answer;
        assert!(late <= 1, "{action}: {late} lines logged after the answer");
    }
    assert_ne!(most, 0, "every request landed before the first line ended");
}

#[test]
fn huge_jog_targets_are_refused_without_travel() {
    let r = rig("huge", sim(json!({})));
    for d in [1e308, -2e6] {
        let e =
            r.m.request(json!({"op":"jog","axis":"X","distance":d}))
                .unwrap_err();
        assert_eq!(e.code, "out_of_travel", "{e}");
    }
    r.m.request(json!({"op":"jog","axis":"Y","distance":1.0}))
        .unwrap();
}

/// Inputs are reported by name, unknown until the first read, then debounced: a pin that
/// bounces shorter than `input_debounce_ms` (300 ms here, far above a step period even on a
/// loaded machine) never shows, one that holds shows (as a status
/// event), and a probe or door input shows without tripping anything.
#[test]
fn inputs_show_debounced_by_name_and_only_limits_and_e_stop_trip() {
    let r = rig_timed(
        "io",
        sim(json!({
            "inputs":[{"pin":10,"function":"limit_x_max"},{"pin":12,"function":"probe"},
                      {"pin":13,"function":"door"}],
            "input_debounce_ms": 300,
            // Pin 12 (probe) goes active for one write, then for good two writes later.
            "sim_inputs":[{"after_writes":3,"pin":12,"level":"high"},
                          {"after_writes":4,"pin":12,"level":"low"},
                          {"after_writes":6,"pin":12,"level":"high"}],
            "realtime_priority": false
        })),
        Timing::Real,
    );
    let st = r.wait_status(|s| s["inputs"]["limit_x_max"] == false);
    assert_eq!(st["inputs"]["door"], false);
    assert!(
        st["inputs"].get("limit_y").is_none(),
        "unsupported names are absent"
    );
    r.m.request(json!({"op":"jog","axis":"Y","distance":2.0,"feed":600}))
        .unwrap();
    let st = r.wait_status(|s| s["inputs"]["probe"] == true && s["state"] == "idle");
    assert_eq!(st["alarm"], Value::Null, "a probe does not trip: {st}");
    // Every change went out as a status event; the one-write bounce never showed.
    let shown: Vec<Value> = r
        .events
        .lock()
        .unwrap()
        .iter()
        .filter_map(|e| match e {
            Event::Status(s) => Some(serde_json::to_value(s.inputs["probe"]).unwrap()),
            _ => None,
        })
        .collect();
    let mut changes = shown.clone();
    changes.dedup();
    assert_eq!(
        changes,
        vec![Value::Null, json!(false), json!(true)],
        "{shown:?}"
    );
}

// ----- probing -----

/// Pin 12 is the probe (active high); the sim axes run at 20 steps/mm with the default
/// `start_rate` of 100 steps/s, so every probe is clamped to 300 mm/min: a step every 200 ticks
/// at the default 20 kHz.
fn probe_rig(tag: &str, script: Value) -> Rig {
    let r = rig(
        tag,
        sim(json!({"inputs":[{"pin":12,"function":"probe"}], "sim_inputs": script})),
    );
    // The kit refuses a probe whose level is not known yet: wait for the first read to show.
    r.wait_status(|s| s["inputs"]["probe"].is_boolean());
    r
}

fn probe_ended(r: &Rig) -> Event {
    r.wait(|e| matches!(e, Event::ProbeEnded { .. }))
}

/// Ticks of the data writes that moved a motor, with the position after each.
fn step_ticks(path: &[(u64, [i64; 2])]) -> Vec<(u64, [i64; 2])> {
    path.windows(2)
        .filter(|w| w[0].1 != w[1].1)
        .map(|w| w[1])
        .collect()
}

#[test]
fn probe_stops_in_the_tick_that_reads_the_pin_and_latches_that_steps_position() {
    // Data write 1 is the all-off write of the first idle tick, so write 41 is the 40th step
    // (X = -2 mm); the pin goes high just after it.
    let r = probe_rig(
        "probe-trip",
        json!([{"after_writes":41,"pin":12,"level":"high"}]),
    );
    r.m.request(json!({"op":"probe","id":7,"axis":"X","distance":-5.0,"feed":600}))
        .unwrap();
    let (trip, position) = match probe_ended(&r) {
        Event::ProbeEnded {
            id,
            outcome,
            trip,
            position,
            message,
        } => {
            assert_eq!(id, 7);
            assert_eq!(outcome, ProbeOutcome::Tripped, "{message:?}");
            (trip.expect("a trip position"), position)
        }
        _ => unreachable!(),
    };
    assert_eq!(trip.x, -2.0, "{trip:?}");
    assert_eq!(trip.y, 0.0);
    assert_eq!(position, trip, "zero overshoot: at rest where it tripped");
    let st = r.m.request(json!({"op":"status"})).unwrap();
    assert_eq!(st["state"], "idle");
    assert_eq!(st["alarm"], Value::Null, "a probe's trip is no alarm");
    assert_eq!(st["machine_position"]["x"], -2.0);

    // The coils hold after the trip and go off by the idle timeout only.
    let writes = r.writes_after_idle();
    let port = r.m.sim_port.clone().unwrap();
    let seen = port
        .lock()
        .status_changes
        .iter()
        .find(|(_, v)| pins::input_level(*v, 12))
        .map(|(t, _)| *t)
        .expect("the loop read the probe");
    let path = replay(&r.cfg.coils, &writes);
    let steps = step_ticks(&path);
    let &(last_step, at_trip) = steps.last().unwrap();
    assert_eq!(steps.len(), 40, "40 steps, then none");
    assert!(
        seen >= last_step,
        "read at {seen}, last step at {last_step}"
    );
    assert_eq!(
        seen - last_step,
        1,
        "the pin set by the step write at tick {last_step} is read in the next tick"
    );
    assert!(
        path.iter()
            .filter(|(t, _)| *t >= seen)
            .all(|(_, p)| *p == at_trip),
        "no step in or after the tick that read the pin"
    );
    assert_eq!(at_trip, [-40, 0]);
    assert_eq!(
        [trip.x * 20.0, trip.y * 20.0],
        [at_trip[0] as f64, at_trip[1] as f64],
        "the trip is the decoded motor position of that tick"
    );
    // The only data write from the trip tick on is the idle all-off, a timeout after the
    // last step (300 ticks of the default 15 ms at 20 kHz), not at the trip.
    let after: Vec<_> = writes
        .iter()
        .filter(|w| w.register == Register::Data && w.tick >= seen)
        .collect();
    assert_eq!(after.len(), 1, "{after:?}");
    assert_eq!(after[0].value, 0);
    let idle = after[0].tick - last_step;
    assert!((300..=302).contains(&idle), "coils off after {idle} ticks");
    // Clamped to the start rate (100 steps/s = 200 ticks a step): no faster, no ramp.
    let gaps: Vec<u64> = steps.windows(2).map(|w| w[1].0 - w[0].0).collect();
    assert!(gaps.iter().all(|g| (199..=201).contains(g)), "{gaps:?}");
}

#[test]
fn probe_that_never_trips_runs_its_whole_distance() {
    let r = probe_rig("probe-miss", json!([]));
    r.m.request(json!({"op":"probe","id":1,"axis":"Y","distance":3.0,"feed":120}))
        .unwrap();
    match probe_ended(&r) {
        Event::ProbeEnded {
            outcome,
            trip,
            position,
            ..
        } => {
            assert_eq!(outcome, ProbeOutcome::NotTripped);
            assert_eq!(trip, None);
            assert_eq!((position.x, position.y), (0.0, 3.0));
        }
        _ => unreachable!(),
    }
    let st = r.m.request(json!({"op":"status"})).unwrap();
    assert_eq!(st["state"], "idle");
    assert_eq!(st["machine_position"]["y"], 3.0);
    let path = replay(&r.cfg.coils, &r.writes_after_idle());
    assert_eq!(
        path.last().unwrap().1,
        [0, 60],
        "every step of the distance"
    );
}

#[test]
fn probe_refusals_name_the_reason() {
    // No probe input.
    let r = rig("probe-none", sim(json!({})));
    let e =
        r.m.request(json!({"op":"probe","id":1,"axis":"X","distance":-1.0,"feed":100}))
            .unwrap_err();
    assert_eq!(e.code, "unsupported", "{e}");
    assert!(e.message.contains("no probe input"), "{}", e.message);
    drop(r);

    // The probe reads contact already (high from the first write on).
    let r = probe_rig(
        "probe-state",
        json!([{"after_writes":0,"pin":12,"level":"high"}]),
    );
    r.wait_status(|s| s["inputs"]["probe"] == true);
    let e =
        r.m.request(json!({"op":"probe","id":2,"axis":"X","distance":-1.0,"feed":100}))
            .unwrap_err();
    assert_eq!(e.code, "probe_already_in_state", "{e}");
    // Z is the lift, A does not exist.
    for (axis, why) in [
        ("Z", "Z is a tool lift (on/off)"),
        ("A", "this machine has no A axis"),
    ] {
        let e =
            r.m.request(
                json!({"op":"probe","id":3,"axis":axis,"distance":-1.0,"feed":100,
                              "until":"release"}),
            )
            .unwrap_err();
        assert_eq!(e.code, "unsupported", "{e}");
        assert!(
            e.message
                .starts_with(&format!("parport-stepper cannot probe {axis}: {why}")),
            "{}",
            e.message
        );
    }
    let st = r.m.request(json!({"op":"status"})).unwrap();
    assert_eq!(st["state"], "idle");
    assert_eq!(st["machine_position"]["x"], 0.0);
    assert!(r
        .events
        .lock()
        .unwrap()
        .iter()
        .all(|e| !matches!(e, Event::ProbeEnded { .. })));
}

#[test]
fn probe_until_release_trips_when_the_pin_goes_inactive() {
    // In contact from the first write; released just after the 20th step (write 21).
    let r = probe_rig(
        "probe-release",
        json!([{"after_writes":0,"pin":12,"level":"high"},
               {"after_writes":21,"pin":12,"level":"low"}]),
    );
    r.wait_status(|s| s["inputs"]["probe"] == true);
    r.m.request(
        json!({"op":"probe","id":4,"axis":"Y","distance":2.0,"feed":300,"until":"release"}),
    )
    .unwrap();
    let (trip, position) = match probe_ended(&r) {
        Event::ProbeEnded {
            outcome,
            trip,
            position,
            message,
            ..
        } => {
            assert_eq!(outcome, ProbeOutcome::Tripped, "{message:?}");
            (trip.unwrap(), position)
        }
        _ => unreachable!(),
    };
    assert_eq!((trip.x, trip.y), (0.0, 1.0), "{trip:?}");
    assert_eq!(position, trip);
    let writes = r.writes_after_idle();
    let port = r.m.sim_port.clone().unwrap();
    let released = port
        .lock()
        .status_changes
        .iter()
        .rev()
        .find(|(_, v)| !pins::input_level(*v, 12))
        .map(|(t, _)| *t)
        .unwrap();
    let steps = step_ticks(&replay(&r.cfg.coils, &writes));
    let &(last_step, at) = steps.last().unwrap();
    assert_eq!(at, [0, 20]);
    assert_eq!(released - last_step, 1, "stopped in the tick that read it");
}

/// In real ticks: stop or feed hold during a probe ends it `stopped`, reported before the
/// request answers, and no step is written after the answer.
#[test]
fn stop_or_feed_hold_during_a_probe_ends_it_stopped_with_no_step_after() {
    for (tag, command) in [("probe-stop", "stop"), ("probe-hold", "feed_hold")] {
        // 50 steps/s start rate at 20 steps/mm: clamped to 150 mm/min, a step every 20 ms.
        let r = rig_timed(
            tag,
            json!({"port":"sim","tick_hz":5000,"spin_us":0,"realtime_priority":false,
                   "inputs":[{"pin":12,"function":"probe"}],
                   "axes":{"x":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":20000},
                           "y":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":20000}}}),
            Timing::Real,
        );
        r.wait_status(|s| s["inputs"]["probe"] == false);
        r.m.request(json!({"op":"probe","id":9,"axis":"X","distance":-10.0,"feed":1000}))
            .unwrap();
        let port = r.m.sim_port.clone().unwrap();
        let deadline = Instant::now() + Duration::from_secs(30);
        // Under way: a few steps written (10 mm take 4 s, so the stop lands mid-move).
        loop {
            let w: Vec<Write> = port.lock().writes.iter().copied().collect();
            if replay(&r.cfg.coils, &w)
                .last()
                .is_some_and(|p| p.1[0] <= -3)
            {
                break;
            }
            assert!(Instant::now() < deadline, "{tag}: the probe never moved");
            std::thread::sleep(Duration::from_millis(2));
        }
        r.m.request(json!({"op":"command","command":command}))
            .unwrap();
        let at_answer: Vec<Write> = port.lock().writes.iter().copied().collect();
        let ended = r
            .events
            .lock()
            .unwrap()
            .iter()
            .find(|e| matches!(e, Event::ProbeEnded { .. }))
            .cloned();
        let position = match ended {
            Some(Event::ProbeEnded {
                outcome,
                trip,
                position,
                ..
            }) => {
                assert_eq!(outcome, ProbeOutcome::Stopped, "{tag}");
                assert_eq!(trip, None);
                position
            }
            other => panic!("{tag}: probe_ended not emitted before the answer: {other:?}"),
        };
        let st = r.m.request(json!({"op":"status"})).unwrap();
        assert_eq!(st["state"], "idle", "{tag}");
        let stopped_at = replay(&r.cfg.coils, &at_answer).last().unwrap().1;
        let all = replay(&r.cfg.coils, &r.writes_after_idle());
        assert_eq!(
            all.last().unwrap().1,
            stopped_at,
            "{tag}: a step after the answer"
        );
        assert!(stopped_at[0] < -2 && stopped_at[0] > -200, "{stopped_at:?}");
        assert_eq!(position.x * 20.0, stopped_at[0] as f64, "{tag}");
    }
}

/// X steps of a run: (tick, when written) of each, from the recorded writes.
fn x_steps(r: &Rig) -> Vec<(u64, Instant, i64)> {
    let port = r.m.sim_port.clone().unwrap();
    let writes: Vec<Write> = port.lock().writes.iter().copied().collect();
    let data: Vec<&Write> = writes
        .iter()
        .filter(|w| w.register == Register::Data)
        .collect();
    let path = replay(&r.cfg.coils, &writes);
    let mut out = Vec::new();
    let mut x = 0;
    for (w, (_, p)) in data.iter().zip(&path) {
        if p[0] != x {
            x = p[0];
            out.push((w.tick, w.at, x));
        }
    }
    out
}

/// Step rate (steps/s) over windows of `n` steps: (tick at the window's middle, rate).
fn windowed_rates(ticks: &[u64], n: usize, hz: f64) -> Vec<(f64, f64)> {
    (0..ticks.len().saturating_sub(n))
        .step_by(n)
        .map(|i| {
            let span = (ticks[i + n] - ticks[i]) as f64;
            ((ticks[i] + ticks[i + n]) as f64 / 2.0, n as f64 * hz / span)
        })
        .collect()
}

/// In real ticks at 5 kHz (X: 1000 steps/s top, 4000 steps/s²), a feed move at 800 steps/s
/// gets a 150 % override (1200 asked, capped at the axis's 1000) and then a 50 % one: the step
/// rate settles to each, the change between never exceeds the acceleration (step rates over
/// windows of 20 steps, from the recorded port writes), no step comes sooner than the top rate
/// allows, and the move ends on its exact step. Prints the latency from each command to the
/// first step that moved differently from a run without overrides (the same plan, stepped in
/// virtual time) and the time to settle.
#[test]
fn feed_overrides_during_a_move_ramp_to_the_new_rate_within_the_limits() {
    let config = json!({"port":"sim","tick_hz":5000,"spin_us":0,"realtime_priority":false,
        "axes":{"x":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":4000},
                "y":{"steps_per_mm":20,"max_rate":1000,"start_rate":50,"accel":4000}}});
    let hz = 5000.0;
    let program = "G1 X100 F2400\n";
    // The same program with no override, for the step-by-step comparison.
    let base = rig("override-base", config.clone());
    base.run(program);
    base.writes_after_idle();
    let base_ticks: Vec<u64> = x_steps(&base).iter().map(|s| s.0).collect();
    assert_eq!(base_ticks.len(), 2000);

    let r = rig_timed("override", config, Timing::Real);
    let path = r._dir.0.join("p.nc");
    std::fs::write(&path, program).unwrap();
    r.m.request(json!({"op":"load_program","run":1,"path":path,"start_line":1}))
        .unwrap();
    r.m.request(json!({"op":"run","action":"start"})).unwrap();
    let mut commands = Vec::new();
    for (past_mm, feed) in [(15.0, 150.0), (40.0, 50.0)] {
        r.wait_status(|st| st["machine_position"]["x"].as_f64().unwrap() > past_mm);
        let at = Instant::now();
        r.m.request(json!({"op":"command","command":"set_overrides","feed":feed}))
            .unwrap();
        commands.push((at, feed));
    }
    let st = r.m.request(json!({"op":"status"})).unwrap();
    assert_eq!(st["feed_override"], 50.0, "{st}");
    r.wait(|e| matches!(e, Event::RunEnded { .. }));
    r.writes_after_idle();
    let steps = x_steps(&r);
    assert_eq!(steps.last().unwrap().2, 2000, "exact end");
    assert_eq!(
        steps.len(),
        2000,
        "one write per step, none lost or doubled"
    );
    let ticks: Vec<u64> = steps.iter().map(|s| s.0).collect();
    let gaps: Vec<u64> = ticks.windows(2).map(|w| w[1] - w[0]).collect();
    assert!(
        gaps.iter().all(|g| *g >= 5),
        "a step sooner than 1000 steps/s allows: {:?}",
        gaps.iter().min()
    );
    // Rates over windows of 20 steps: never changing faster than the acceleration (plus the
    // error of measuring on whole ticks: a tick in 100..250).
    let rates = windowed_rates(&ticks, 20, hz);
    for w in rates.windows(2) {
        let dt = (w[1].0 - w[0].0) / hz;
        let accel = (w[1].1 - w[0].1).abs() / dt;
        assert!(
            accel <= 4000.0 * 1.3,
            "{:.0} -> {:.0} steps/s in {:.1} ms: {accel:.0} steps/s²",
            w[0].1,
            w[1].1,
            dt * 1000.0
        );
    }
    // Each override: where it first changed the stepping and where the rate settled.
    let mut from = 0;
    let _ = &gaps;
    let mut report = Vec::new();
    for (k, (at, feed)) in commands.iter().enumerate() {
        let want = (800.0 * feed / 100.0_f64).min(1000.0);
        // The tick when the command was given: interpolated between the writes around it.
        let before = steps.iter().rposition(|s| s.1 <= *at).unwrap();
        let cmd_tick =
            steps[before].0 as f64 + at.duration_since(steps[before].1).as_secs_f64() * hz;
        // The first step that is a tick or more off where it would have been without this
        // override: the run without overrides for the first, the settled 5 ticks a step for
        // the second (a ramp's first steps move by less than a tick: this sees a change within
        // about 10 ms of its start).
        let expected = |i: usize| -> f64 {
            if k == 0 {
                (base_ticks[i] + ticks[0] - base_ticks[0]) as f64
            } else {
                ticks[before] as f64 + 5.0 * (i - before) as f64
            }
        };
        let changed = (before.max(from)..ticks.len())
            .find(|&i| (ticks[i] as f64 - expected(i)).abs() >= 1.0)
            .unwrap();
        let first_changed_tick = ticks[changed] as f64;
        // Settled: the first window from which the rate stays within 2 % of the new one.
        let next_cmd_tick = commands
            .get(k + 1)
            .map(|(a, _)| {
                let i = steps.iter().rposition(|s| s.1 <= *a).unwrap();
                ticks[i] as f64
            })
            .unwrap_or(ticks[ticks.len() - 60] as f64);
        let inside: Vec<&(f64, f64)> = rates
            .iter()
            .filter(|(t, _)| *t > first_changed_tick && *t < next_cmd_tick)
            .collect();
        let settled = inside
            .iter()
            .position(|(_, v)| (v - want).abs() > 0.02 * want)
            .map(|_| {
                let last_off = inside
                    .iter()
                    .rposition(|(_, v)| (v - want).abs() > 0.02 * want)
                    .unwrap();
                inside[last_off + 1..].first().map(|w| w.0)
            })
            .unwrap_or(inside.first().map(|w| w.0))
            .unwrap_or_else(|| panic!("override {feed} %: never settled at {want} steps/s"));
        assert!(
            inside
                .iter()
                .filter(|(t, _)| *t >= settled)
                .all(|(_, v)| (v - want).abs() <= 0.02 * want),
            "override {feed} %: {inside:?}"
        );
        assert!(
            inside.len() >= 5,
            "override {feed} %: too short at the new rate to tell: {inside:?}"
        );
        from = changed;
        report.push(format!(
            "feed {feed} % ({want} steps/s): first changed step {:.1} ms after the command, settled {:.1} ms after that (the ramp alone: {:.1} ms)",
            (first_changed_tick - cmd_tick) / hz * 1000.0,
            (settled - first_changed_tick) / hz * 1000.0,
            (want - if k == 0 { 800.0 } else { 1000.0 }).abs() / 4000.0 * 1000.0
        ));
    }
    eprintln!("{}", report.join("\n"));
}

/// A loop that spins every whole tick never sleeps. Under the kernel's real-time throttling
/// (`kernel.sched_rt_runtime_us` >= 0, a stock kernel) SCHED_FIFO would have it stopped about
/// 50 ms each second, so it takes the highest normal priority (nice -20) instead; with no
/// throttling it takes SCHED_FIFO. Read back from the kernel, for the output thread itself.
#[test]
fn a_loop_that_spins_whole_ticks_is_not_left_to_real_time_throttling() {
    // As the plugin reads it: a limit it cannot read counts as no throttling.
    let throttled = fresa_parport_stepper::output::rt_throttle_limit().is_some();
    // The output thread logs how it is scheduled once it has asked; the sink, called on that
    // thread, reads the thread's own scheduling then (/proc/thread-self/stat: nice, policy).
    let (tx, rx) = std::sync::mpsc::channel();
    let tx = Mutex::new(tx);
    let log = Arc::new(move |_level, line: &str| {
        if line.contains("priority") {
            let stat = std::fs::read_to_string("/proc/thread-self/stat").unwrap();
            let fields: Vec<String> = stat[stat.rfind(')').unwrap() + 2..]
                .split(' ')
                .map(str::to_string)
                .collect();
            // Fields 19 (nice) and 41 (policy: 0 normal, 1 SCHED_FIFO), counted from 1.
            let _ = tx.lock().unwrap().send((
                line.to_string(),
                fields[16].parse::<i32>().unwrap(),
                fields[38].parse::<u32>().unwrap(),
            ));
        }
    });
    // 40 kHz with spin_us at the 25 us period: the whole tick spins (the loop is idle here).
    let m = Stepper::new(
        &sim(json!({"tick_hz": 40000, "spin_us": 25, "realtime_priority": true})),
        Arc::new(|_: &Event| {}),
        log,
        Timing::Real,
    )
    .unwrap();
    let (line, nice, policy) = rx.recv_timeout(Duration::from_secs(30)).unwrap();
    drop(m);
    let refused = line.contains("could NOT");
    if throttled {
        assert!(
            line.contains("kernel.sched_rt_runtime_us") && line.contains("nice -20"),
            "{line}"
        );
        assert_eq!(policy, 0, "not SCHED_FIFO under throttling: {line}");
        if !refused {
            assert_eq!(nice, -20, "{line}");
        }
    } else {
        assert!(line.contains("SCHED_FIFO"), "{line}");
        if !refused {
            assert_eq!(policy, 1, "{line}");
        }
    }
}
