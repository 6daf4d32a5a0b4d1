//! Drives `SimMachine` directly (its events go to a channel) and once through the real C ABI.
//! Waiting is always on events, with a generous timeout that only guards against hangs.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_plugin_api::contract::{
    Event, IoValue, MachineState, MachineStatus, OffsetTable, RunOutcome,
};
use fresa_plugin_api::MachineBackend;
use fresa_sim_machine::SimMachine;
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::mpsc::{channel, Receiver};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const GUARD: Duration = Duration::from_secs(60);

struct Rig {
    m: SimMachine,
    rx: Receiver<Event>,
}

fn machine(cfg: Value) -> Rig {
    let (tx, rx) = channel();
    let tx = Mutex::new(tx);
    let m = SimMachine::new(
        &cfg,
        Arc::new(move |e: &Event| {
            let _ = tx.lock().unwrap().send(e.clone());
        }),
    )
    .unwrap();
    let rig = Rig { m, rx };
    rig.call(json!({"op": "connect"}));
    // Drop what connecting emitted, so no stale `idle` is waited on.
    while rig.rx.try_recv().is_ok() {}
    rig
}

impl Rig {
    fn call(&self, req: Value) -> Value {
        self.m
            .request(req.clone())
            .unwrap_or_else(|e| panic!("{req} failed: {e}"))
    }

    fn status(&self) -> MachineStatus {
        serde_json::from_value(self.call(json!({"op": "status"}))).unwrap()
    }

    /// Collects events until one matches `stop` (included); panics after `GUARD`.
    fn until(&self, mut stop: impl FnMut(&Event) -> bool) -> Vec<Event> {
        let deadline = Instant::now() + GUARD;
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let e = self
                .rx
                .recv_timeout(left)
                .unwrap_or_else(|_| panic!("event not seen in time; got {seen:?}"));
            let done = stop(&e);
            seen.push(e);
            if done {
                return seen;
            }
        }
    }

    fn until_state(&self, state: MachineState) -> Vec<Event> {
        self.until(|e| matches!(e, Event::StateChanged { to, .. } if *to == state))
    }

    /// Waits until the machine reports `idle` with nothing queued (jogs may queue up, each
    /// ending in `idle` when the motion thread is faster than the requests).
    fn wait_idle(&self) {
        while self.status().state != MachineState::Idle {
            self.until_state(MachineState::Idle);
        }
    }

    fn until_run_ended(&self, run: i64) -> (Vec<Event>, RunOutcome, Option<String>) {
        let events = self.until(|e| matches!(e, Event::RunEnded { run: r, .. } if *r == run));
        match events.last() {
            Some(Event::RunEnded {
                outcome, message, ..
            }) => (events.clone(), *outcome, message.clone()),
            _ => unreachable!(),
        }
    }
}

fn acks(events: &[Event], run: i64) -> Vec<u32> {
    events
        .iter()
        .filter_map(|e| match e {
            Event::LineAcknowledged { run: r, line } if *r == run => Some(*line),
            _ => None,
        })
        .collect()
}

fn temp_path(name: &str) -> PathBuf {
    static N: AtomicU32 = AtomicU32::new(0);
    let dir = std::env::temp_dir().join(format!(
        "fresa-sim-machine-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::SeqCst)
    ));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn program(text: &str) -> String {
    let p = temp_path("prog.nc");
    std::fs::write(&p, text).unwrap();
    p.to_string_lossy().into_owned()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-6
}

const INSTANT: fn() -> Value = || json!({"time_scale": 0});

#[test]
fn status_shape_before_and_after_connect() {
    let (tx, _rx) = channel();
    let tx = Mutex::new(tx);
    let m = SimMachine::new(
        &json!({}),
        Arc::new(move |e: &Event| {
            let _ = tx.lock().unwrap().send(e.clone());
        }),
    )
    .unwrap();
    let off = m.request(json!({"op": "status"})).unwrap();
    assert_eq!(off["state"], "offline");
    assert!(off["reason"].is_string());
    let e = m
        .request(json!({"op":"jog","axis":"X","distance":1.0}))
        .unwrap_err();
    assert_eq!(e.code, "offline");

    let st = m.request(json!({"op": "connect"})).unwrap();
    assert_eq!(st["state"], "idle");
    for key in ["machine_position", "work_position"] {
        for axis in ["x", "y", "z", "a"] {
            assert_eq!(st[key][axis], 0.0, "{key}.{axis} in {st}");
        }
    }
    assert_eq!(st["feed_override"], 100.0);
    assert_eq!(st["active_offset"], "G54");
    assert!(st.get("run").is_none() && st.get("line").is_none());
    // connect is idempotent
    assert_eq!(m.request(json!({"op": "connect"})).unwrap(), st);

    let table: OffsetTable =
        serde_json::from_value(m.request(json!({"op": "get_offsets"})).unwrap()).unwrap();
    assert_eq!(table.offsets.len(), 6);

    // An operation of a newer contract: unsupported, not malformed.
    let e = m.request(json!({"op": "fly"})).unwrap_err();
    assert_eq!(e.code, "unsupported");
    assert!(e.message.contains("fly"), "{}", e.message);
    let e = m.request(json!({"op": "jog", "axis": "Q"})).unwrap_err();
    assert_eq!(e.code, "invalid_request");
}

#[test]
fn jog_moves_exactly_distance_and_queues() {
    let rig = machine(json!({"time_scale": 0.001}));
    rig.call(json!({"op":"jog","axis":"X","distance":12.5,"feed":3000}));
    let events = rig.until_state(MachineState::Idle);
    assert!(events.iter().any(|e| matches!(
        e,
        Event::StateChanged {
            to: MachineState::Jogging,
            ..
        }
    )));
    let st = rig.status();
    assert_eq!(st.state, MachineState::Idle);
    assert_eq!(st.machine_position.x, 12.5);
    assert_eq!(st.machine_position.y, 0.0);

    // Several jogs in a row are executed in order, each incrementally.
    rig.call(json!({"op":"jog","axis":"A","distance":90.0}));
    rig.call(json!({"op":"jog","axis":"A","distance":-30.0}));
    rig.call(json!({"op":"jog","axis":"Z","distance":-2.25}));
    rig.wait_idle();
    let st = rig.status();
    assert!(close(st.machine_position.a, 60.0), "{st:?}");
    assert!(close(st.machine_position.z, -2.25), "{st:?}");
    assert!(close(st.machine_position.x, 12.5), "{st:?}");

    let e = rig
        .m
        .request(json!({"op":"jog","axis":"X","distance":1.0,"feed":-5}))
        .unwrap_err();
    assert_eq!(e.code, "invalid_request");
}

#[test]
fn jog_respects_travel() {
    let rig = machine(json!({"time_scale": 0, "travel": {"x": [0, 100]}}));
    let e = rig
        .m
        .request(json!({"op":"jog","axis":"X","distance":-1.0}))
        .unwrap_err();
    assert_eq!(e.code, "out_of_travel");
    assert!(e.message.contains('X'), "{}", e.message);
    rig.call(json!({"op":"jog","axis":"X","distance":100.0}));
    rig.until_state(MachineState::Idle);
    assert_eq!(rig.status().machine_position.x, 100.0);

    // A jog is checked from where the moves before it end, not from where the axis is now.
    let slow = machine(json!({"travel": {"x": [0, 100]}}));
    slow.call(json!({"op":"jog","axis":"X","distance":60.0,"feed":1.0}));
    let e = slow
        .m
        .request(json!({"op":"jog","axis":"X","distance":60.0}))
        .unwrap_err();
    assert_eq!(e.code, "out_of_travel");
    slow.call(json!({"op":"command","command":"stop"}));
    assert_eq!(slow.status().state, MachineState::Idle);
}

#[test]
fn zero_home_and_go_to_zero() {
    let rig = machine(INSTANT());
    rig.call(json!({"op":"jog","axis":"X","distance":10.0}));
    rig.call(json!({"op":"jog","axis":"Y","distance":-5.0}));
    rig.call(json!({"op":"jog","axis":"Z","distance":-3.0}));
    rig.wait_idle();

    let answer = rig.call(json!({"op":"command","command":"zero"}));
    let table: OffsetTable = serde_json::from_value(answer["offsets"].clone()).unwrap();
    assert_eq!(table.offsets[0].1.to_array(), [10.0, -5.0, -3.0, 0.0]);
    let st = rig.status();
    assert_eq!(st.work_position.to_array(), [0.0; 4]);
    assert_eq!(st.machine_position.to_array(), [10.0, -5.0, -3.0, 0.0]);

    // Zero one axis of another offset.
    rig.call(json!({"op":"command","command":"select_offset","offset":"G55"}));
    rig.call(json!({"op":"command","command":"zero","axis":"Y"}));
    let table: OffsetTable = serde_json::from_value(rig.call(json!({"op":"get_offsets"}))).unwrap();
    assert_eq!(table.active, fresa_plugin_api::contract::WorkOffset::G55);
    assert_eq!(table.offsets[1].1.to_array(), [0.0, -5.0, 0.0, 0.0]);
    let st = rig.status();
    assert_eq!(st.work_position.to_array(), [10.0, 0.0, -3.0, 0.0]);
    rig.call(json!({"op":"command","command":"select_offset","offset":"G54"}));

    rig.call(json!({"op":"command","command":"home"}));
    let st = rig.status();
    assert_eq!(st.machine_position.to_array(), [0.0; 4]);
    assert_eq!(st.work_position.to_array(), [-10.0, 5.0, 3.0, 0.0]);

    // The jogs above may have left `idle` transitions queued: drop them, so the `idle` waited
    // on is the one that ends go-to-zero.
    while rig.rx.try_recv().is_ok() {}
    rig.call(json!({"op":"command","command":"go_to_zero"}));
    let events = rig.until_state(MachineState::Idle);
    // Z goes up first (here it is already above work zero), so Z never dips below it.
    for e in &events {
        if let Event::Status(s) = e {
            assert!(s.machine_position.z >= -3.0 - 1e-9, "{s:?}");
        }
    }
    assert_eq!(rig.status().work_position.to_array(), [0.0; 4]);

    rig.call(json!({"op":"set_offset","offset":"G54","values":{"x":1,"y":2,"z":3,"a":4}}));
    let st = rig.status();
    assert_eq!(st.work_position.to_array(), [9.0, -7.0, -6.0, -4.0]);
}

const DEMO: &str = "%\n\
(demo: G0 / G1 / G2)\n\
G21 G90 G17\n\
\n\
G0 X10 Y0 Z5\n\
G1 Z-1 F300\n\
G1 X20 F600 ; a cut\n\
G2 X30 Y0 I5 J0\n\
G0 Z5\n\
M30\n\
%\n";

#[test]
fn program_runs_to_completion_and_acks_every_line_once() {
    let log = temp_path("exec.log");
    let rig = machine(json!({"time_scale": 0, "execution_log": log}));
    // Work zero at machine (100, 50, -20).
    rig.call(json!({"op":"set_offset","offset":"G54","values":{"x":100,"y":50,"z":-20}}));
    let path = program(DEMO);
    let loaded = rig.call(json!({"op":"load_program","run":1,"path":path,"start_line":1}));
    assert_eq!(loaded, json!({"lines": 11, "start_line": 1}));
    rig.call(json!({"op":"run","action":"start"}));
    let (events, outcome, message) = rig.until_run_ended(1);
    assert_eq!(outcome, RunOutcome::Completed, "{message:?}");
    assert_eq!(acks(&events, 1), (1..=11).collect::<Vec<_>>());
    rig.until_state(MachineState::Idle);

    let st = rig.status();
    assert_eq!(st.state, MachineState::Idle);
    let w = st.work_position.to_array();
    assert!(
        close(w[0], 30.0) && close(w[1], 0.0) && close(w[2], 5.0),
        "{st:?}"
    );
    let m = st.machine_position.to_array();
    assert!(
        close(m[0], 130.0) && close(m[1], 50.0) && close(m[2], -15.0),
        "{st:?}"
    );
    assert_eq!(st.run, None);

    // Each entry is the run and line, stamped with when the line finished (in order).
    let logged: Vec<Value> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let lines: Vec<Value> = logged
        .iter()
        .map(|e| json!({"run": e["run"], "line": e["line"]}))
        .collect();
    let expected: Vec<Value> = (1..=11).map(|l| json!({"run":1,"line":l})).collect();
    assert_eq!(lines, expected);
    let stamps: Vec<u64> = logged
        .iter()
        .map(|e| e["at_ms"].as_u64().expect("a finished line is stamped"))
        .collect();
    assert!(stamps.windows(2).all(|w| w[0] <= w[1]), "{stamps:?}");
}

#[test]
fn arc_moves_are_interpolated_not_cut_short() {
    // A half circle through Y=5 at time scale 0: the path must pass near the top of the arc.
    let rig = machine(json!({"time_scale": 0, "status_interval_ms": 0}));
    let path = program("G21 G90\nG1 X0 Y0 F1000\nG2 X10 Y0 I5 J0\n");
    rig.call(json!({"op":"load_program","run":2,"path":path,"start_line":1}));
    rig.call(json!({"op":"command","command":"cycle_start"}));
    let (events, outcome, _) = rig.until_run_ended(2);
    assert_eq!(outcome, RunOutcome::Completed);
    let top = events
        .iter()
        .filter_map(|e| match e {
            Event::Status(s) => Some(s.machine_position.y),
            _ => None,
        })
        .fold(f64::MIN, f64::max);
    assert!(top > 4.9, "highest Y seen {top}");
}

#[test]
fn feed_hold_then_resume_completes() {
    // 100 mm at 600 mm/min = 10 s, scaled to 1 s.
    let rig = machine(json!({"time_scale": 0.1}));
    let path = program("G21 G90\nG1 X100 F600\nG0 Z10\n");
    rig.call(json!({"op":"load_program","run":3,"path":path,"start_line":1}));
    rig.call(json!({"op":"run","action":"start"}));
    rig.call(json!({"op":"command","command":"feed_hold"}));
    let events = rig.until(|e| matches!(e, Event::Status(s) if s.state == MachineState::Paused));
    let held = rig.status();
    assert_eq!(held.state, MachineState::Paused);
    assert_eq!(held.run, Some(3));
    assert!(held.machine_position.x < 100.0, "{held:?}");
    // The status sent when the hold took effect shows the same, unmoving position.
    let at_hold = events.iter().rev().find_map(|e| match e {
        Event::Status(s) => Some(s.clone()),
        _ => None,
    });
    assert_eq!(
        at_hold.map(|s| s.machine_position),
        Some(held.machine_position)
    );
    assert!(!acks(&events, 3).contains(&2));
    // Jogging is refused while a program is held.
    let e = rig
        .m
        .request(json!({"op":"jog","axis":"X","distance":1.0}))
        .unwrap_err();
    assert_eq!(e.code, "busy");

    rig.call(json!({"op":"command","command":"resume"}));
    let (rest, outcome, _) = rig.until_run_ended(3);
    assert_eq!(outcome, RunOutcome::Completed);
    let mut all = acks(&events, 3);
    all.extend(acks(&rest, 3));
    assert_eq!(all, vec![1, 2, 3]);
    let st = rig.status();
    assert_eq!(st.machine_position.x, 100.0);
    assert_eq!(st.machine_position.z, 10.0);
}

#[test]
fn stop_cancels_the_run() {
    // 1000 mm at 100 mm/min: ten minutes of real time, so it is surely still running.
    let rig = machine(json!({}));
    let path = program("G21\nG1 X1000 F100\nG0 Z10\n");
    rig.call(json!({"op":"load_program","run":4,"path":path,"start_line":1}));
    rig.call(json!({"op":"run","action":"start"}));
    let e = rig
        .m
        .request(json!({"op":"jog","axis":"X","distance":1.0}))
        .unwrap_err();
    assert_eq!(e.code, "busy");
    rig.call(json!({"op":"command","command":"stop"}));
    // stop returns once motion has ended.
    let st = rig.status();
    assert_eq!(st.state, MachineState::Idle);
    assert!(st.machine_position.x < 1000.0);
    let (events, outcome, _) = rig.until_run_ended(4);
    assert_eq!(outcome, RunOutcome::Cancelled);
    assert!(!acks(&events, 4).contains(&2));
    // The machine is usable again.
    rig.call(json!({"op":"jog","axis":"Y","distance":1.0,"feed":1e6}));
    rig.wait_idle();

    // run cancel works the same on a held program.
    rig.call(json!({"op":"load_program","run":5,"path":path,"start_line":1}));
    rig.call(json!({"op":"run","action":"start"}));
    rig.call(json!({"op":"run","action":"pause"}));
    rig.call(json!({"op":"run","action":"cancel"}));
    let (_, outcome, _) = rig.until_run_ended(5);
    assert_eq!(outcome, RunOutcome::Cancelled);
    assert_eq!(rig.status().state, MachineState::Idle);
}

#[test]
fn resume_from_line_skips_earlier_lines_but_keeps_modal_state() {
    let rig = machine(INSTANT());
    // Inches, incremental, feed 10 in/min: all set before line 4.
    let path = program("G20\nG91\nG1 X1 F10\nG1 X1\nG1 X1\n");
    let loaded = rig.call(json!({"op":"load_program","run":6,"path":path,"start_line":4}));
    assert_eq!(loaded, json!({"lines": 5, "start_line": 4}));
    rig.call(json!({"op":"run","action":"start"}));
    let (events, outcome, _) = rig.until_run_ended(6);
    assert_eq!(outcome, RunOutcome::Completed);
    assert_eq!(acks(&events, 6), vec![4, 5]);
    let st = rig.status();
    // Line 4 goes to X2in and line 5 to X3in, in program coordinates, from where it was.
    assert!(close(st.machine_position.x, 76.2), "{st:?}");
    assert!(close(st.feed, 254.0), "{st:?}");
}

/// A start inside the program with a preamble: the steps run in order before the start line
/// (each recorded in the execution log with where the machine was before and after it), then
/// the lines from the start on; the spindle and coolant it switched on go off at the end.
#[test]
fn a_preamble_runs_before_the_start_line_and_is_logged() {
    let log = temp_path("exec.log");
    let rig = machine(json!({"time_scale": 0, "execution_log": log, "travel": {"z": [-50, 50]}}));
    let path = program("G21 G90\nG0 X10 Y5 Z5\nM3 S1000 M8\nG1 Z-1 F300\nG1 X20\nG1 Y10\nM5 M9\n");
    let preamble = json!({
        "line": 5,
        "from": {"x": 0, "y": 0, "z": 0, "a": 0},
        "steps": [
            {"step": "move", "z": 5},
            {"step": "offset", "offset": "G54"},
            {"step": "spindle", "direction": "cw", "rpm": 1000},
            {"step": "coolant", "mist": false, "flood": true},
            {"step": "move", "x": 10, "y": 5},
            {"step": "move", "z": -1, "feed": 300},
        ]
    });
    let loaded = rig.call(
        json!({"op":"load_program","run":21,"path":path,"start_line":5,
                                 "preamble": preamble}),
    );
    assert_eq!(
        loaded,
        json!({"lines": 7, "start_line": 5, "preamble": true})
    );
    rig.call(json!({"op":"run","action":"start"}));
    let (events, outcome, message) = rig.until_run_ended(21);
    assert_eq!(outcome, RunOutcome::Completed, "{message:?}");
    assert_eq!(acks(&events, 21), vec![5, 6, 7]);
    // The spindle and coolant were on while it cut, and are off at the end.
    let lit = events.iter().any(|e| {
        matches!(e, Event::Status(s) if s.outputs.get("spindle") == Some(&Some(IoValue::On(true)))
            && s.outputs.get("coolant_flood") == Some(&Some(IoValue::On(true))))
    });
    assert!(lit, "{events:?}");
    let st = rig.status();
    assert_eq!(st.outputs.get("spindle"), Some(&Some(IoValue::On(false))));
    assert_eq!(st.machine_position.to_array(), [20.0, 10.0, -1.0, 0.0]);
    let records: Vec<Value> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let steps: Vec<&Value> = records
        .iter()
        .filter(|r| r.get("preamble_step").is_some())
        .collect();
    assert_eq!(steps.len(), 6, "{records:?}");
    assert_eq!(steps[0]["from"], json!([0.0, 0.0, 0.0, 0.0]));
    assert_eq!(steps[0]["to"], json!([0.0, 0.0, 5.0, 0.0]));
    assert_eq!(steps[4]["to"], json!([10.0, 5.0, 5.0, 0.0]));
    assert_eq!(steps[5]["to"], json!([10.0, 5.0, -1.0, 0.0]));
    // The preamble comes first, then the lines from the start on; resume still reads the
    // lines only.
    let first_line = records
        .iter()
        .position(|r| r.get("line").is_some())
        .unwrap();
    assert!(records[..first_line]
        .iter()
        .all(|r| r.get("preamble_step").is_some()));
}

/// A preamble is refused before anything is loaded when the machine is not where it was
/// planned from or one of its moves leaves the travel; one planned for another line than the
/// execution log makes the run start from is kept but refused at start.
#[test]
fn a_preamble_is_checked_before_it_is_accepted() {
    let log = temp_path("exec.log");
    let cfg = json!({"time_scale": 0, "execution_log": log, "travel": {"z": [-50, 50]}});
    let rig = machine(cfg);
    let path = program("G0 X1\nG0 X2\nG0 X3\nG0 X4\n");
    let load = |preamble: Value, run: i64, start: u32| {
        rig.m.request(
            json!({"op":"load_program","run":run,"path":path,"start_line":start,
                              "preamble": preamble}),
        )
    };
    let moved = json!({"line": 2, "from": {"x": 5}, "steps": []});
    assert_eq!(load(moved, 30, 2).unwrap_err().code, "machine_moved");
    let high = json!({"line": 2, "from": {}, "steps": [{"step": "move", "z": 60}]});
    let e = load(high, 30, 2).unwrap_err();
    assert_eq!(e.code, "out_of_travel");
    assert!(e.message.contains("preamble step 1"), "{e}");
    let bad = json!({"line": 2, "from": {}, "steps": [{"step": "move", "z": 1, "feed": 0}]});
    assert_eq!(load(bad, 30, 2).unwrap_err().code, "invalid_request");

    // Lines 1 and 2 of run 31 are in the log: a preamble for line 2 does not lead to line 3.
    rig.call(json!({"op":"load_program","run":31,"path":path,"start_line":1}));
    rig.call(json!({"op":"run","action":"start"}));
    rig.until_run_ended(31);
    let text: String = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .filter(|l| !l.contains("\"line\":3") && !l.contains("\"line\":4"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(&log, text).unwrap();
    let rig = machine(json!({"time_scale": 0, "execution_log": log}));
    let here = rig.status().machine_position;
    let for_2 = json!({"line": 2, "from": here, "steps": [{"step": "move", "x": 1}]});
    let loaded = rig.call(
        json!({"op":"load_program","run":31,"path":path,"start_line":2,
                                 "preamble": for_2}),
    );
    assert_eq!(loaded, json!({"lines": 4, "start_line": 3}));
    let e = rig
        .m
        .request(json!({"op":"run","action":"start"}))
        .unwrap_err();
    assert_eq!(e.code, "start_line_moved");
    assert!(e.message.contains("line 3"), "{e}");
    assert_eq!(rig.status().state, MachineState::Idle, "nothing moved");
    // With every line logged there is nothing to approach: the preamble is dropped and the
    // run completes at once.
    let all = std::fs::read_to_string(&log).unwrap()
        + "{\"run\":31,\"line\":3}\n{\"run\":31,\"line\":4}\n";
    std::fs::write(&log, all).unwrap();
    let rig = machine(json!({"time_scale": 0, "execution_log": log}));
    let here = rig.status().machine_position;
    let for_3 = json!({"line": 3, "from": here, "steps": [{"step": "move", "x": 1}]});
    let loaded = rig.call(
        json!({"op":"load_program","run":31,"path":path,"start_line":3,
                                 "preamble": for_3}),
    );
    assert_eq!(loaded, json!({"lines": 4, "start_line": 5}));
    rig.call(json!({"op":"run","action":"start"}));
    let (events, outcome, _) = rig.until_run_ended(31);
    assert_eq!(outcome, RunOutcome::Completed);
    assert!(acks(&events, 31).is_empty());
    assert_eq!(rig.status().machine_position, here, "nothing moved");

    // A start the interpreter refuses (inside a loop) is refused at load.
    let looped = program("#1=0\no1 while [#1 LT 2]\nG0 X[#1]\n#1=[#1+1]\no1 endwhile\n");
    let e = rig
        .m
        .request(json!({"op":"load_program","run":32,"path":looped,"start_line":3}))
        .unwrap_err();
    assert_eq!(e.code, "start_refused");
    assert!(
        e.message.starts_with("line 3: ") && e.message.contains("loop"),
        "{e}"
    );
}

#[test]
fn resume_is_idempotent_with_the_execution_log() {
    let log = temp_path("exec.log");
    let cfg = json!({"time_scale": 0, "execution_log": log});
    let path = program("G21 G90\nG0 X1\nM0\nG0 X2\nG0 X3\n");
    {
        let rig = machine(cfg.clone());
        rig.call(json!({"op":"load_program","run":7,"path":path,"start_line":1}));
        rig.call(json!({"op":"run","action":"start"}));
        // M0 on line 3 pauses the run; it is stopped there, as if the server went down.
        let events = rig.until_state(MachineState::Paused);
        assert_eq!(acks(&events, 7), vec![1, 2]);
        rig.call(json!({"op":"command","command":"stop"}));
        let (_, outcome, _) = rig.until_run_ended(7);
        assert_eq!(outcome, RunOutcome::Cancelled);
    }
    // A new instance on the same log resumes run 7 after the last logged line.
    let rig = machine(cfg);
    let loaded = rig.call(json!({"op":"load_program","run":7,"path":path,"start_line":1}));
    assert_eq!(loaded, json!({"lines": 5, "start_line": 3}));
    rig.call(json!({"op":"run","action":"start"}));
    let events = rig.until_state(MachineState::Paused);
    assert!(acks(&events, 7).is_empty());
    rig.call(json!({"op":"run","action":"resume"}));
    let (events, outcome, _) = rig.until_run_ended(7);
    assert_eq!(outcome, RunOutcome::Completed);
    assert_eq!(acks(&events, 7), vec![3, 4, 5]);
    assert_eq!(rig.status().machine_position.x, 3.0);

    let logged: Vec<u32> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| {
            serde_json::from_str::<Value>(l).unwrap()["line"]
                .as_u64()
                .unwrap() as u32
        })
        .collect();
    assert_eq!(logged, vec![1, 2, 3, 4, 5]);

    // Another run id is not affected; a fully logged run starts past its end and completes.
    let other = rig.call(json!({"op":"load_program","run":8,"path":path,"start_line":2}));
    assert_eq!(other["start_line"], 2);
    let done = rig.call(json!({"op":"load_program","run":7,"path":path,"start_line":1}));
    assert_eq!(done["start_line"], 6);
    rig.call(json!({"op":"run","action":"start"}));
    let (events, outcome, _) = rig.until_run_ended(7);
    assert_eq!(outcome, RunOutcome::Completed);
    assert!(acks(&events, 7).is_empty());
}

#[test]
fn invalid_program_is_rejected_with_its_line() {
    let rig = machine(INSTANT());
    let path = program("G21 G90\nG0 X1\nG1 X5 Y5 Q!\nG0 X0\n");
    let e = rig
        .m
        .request(json!({"op":"load_program","run":9,"path":path,"start_line":1}))
        .unwrap_err();
    assert_eq!(e.code, "invalid_program");
    assert!(e.message.starts_with("line 3"), "{}", e.message);

    let e = rig
        .m
        .request(json!({"op":"load_program","run":9,"path":"/nonexistent/p.nc","start_line":1}))
        .unwrap_err();
    assert!(e.message.contains("/nonexistent/p.nc"), "{}", e.message);

    let e = rig
        .m
        .request(json!({"op":"command","command":"cycle_start"}))
        .unwrap_err();
    assert_eq!(e.code, "no_program");

    let far = program("G0 X1\n");
    let e = rig
        .m
        .request(json!({"op":"load_program","run":9,"path":far,"start_line":3}))
        .unwrap_err();
    assert_eq!(e.code, "invalid_request");
}

#[test]
fn program_outside_travel_is_rejected_before_motion() {
    let rig = machine(json!({"time_scale": 0, "travel": {"z": [-50, 0]}}));
    let path = program("G21 G90\nG0 Z-10\nG1 Z-60 F100\n");
    let e = rig
        .m
        .request(json!({"op":"load_program","run":10,"path":path,"start_line":1}))
        .unwrap_err();
    assert_eq!(e.code, "out_of_travel");
    assert!(e.message.starts_with("line 3"), "{}", e.message);
}

#[test]
fn invalid_config_is_rejected_naming_the_key() {
    for (cfg, key) in [
        (json!({"time_scale": "fast"}), "time_scale"),
        (json!({"rapid": 100}), "rapid"),
        (json!({"status_interval_ms": -1}), "status_interval_ms"),
    ] {
        let e = SimMachine::new(&cfg, Arc::new(|_: &Event| {}))
            .err()
            .unwrap();
        assert_eq!(e.code, "invalid_config");
        assert!(e.message.contains(key), "{}", e.message);
    }
    let e = SimMachine::new(
        &json!({"execution_log": "/nonexistent-dir/x.log"}),
        Arc::new(|_: &Event| {}),
    )
    .err()
    .unwrap();
    assert_eq!(e.code, "invalid_config");
    assert!(e.message.contains("execution_log"), "{}", e.message);
}

#[test]
fn large_program_runs_instantly_at_time_scale_zero() {
    let mut text = String::from("G21 G90 G1 F1000\n");
    for i in 0..40_000 {
        text.push_str(&format!("X{} Y{}\n", i % 100, (i / 100) % 50));
    }
    let rig = machine(INSTANT());
    let path = program(&text);
    let loaded = rig.call(json!({"op":"load_program","run":11,"path":path,"start_line":1}));
    assert_eq!(loaded["lines"], 40_001);
    rig.call(json!({"op":"run","action":"start"}));
    let (events, outcome, _) = rig.until_run_ended(11);
    assert_eq!(outcome, RunOutcome::Completed);
    let acked = acks(&events, 11);
    assert_eq!(acked.len(), 40_001);
    assert!(acked.windows(2).all(|w| w[1] == w[0] + 1));
}

/// Runs every program of the shared corpus (when present) to completion at time scale 0.
#[test]
fn corpus_programs_run_to_completion() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/corpus/gcode");
    let Ok(entries) = std::fs::read_dir(&dir) else {
        eprintln!("corpus folder {} is absent: skipping", dir.display());
        return;
    };
    let rig = machine(INSTANT());
    let mut ran = 0;
    for (run, entry) in (100..).zip(entries) {
        let path = entry.unwrap().path();
        let loaded = match rig
            .m
            .request(json!({"op":"load_program","run":run,"path":path,"start_line":1}))
        {
            Ok(v) => v,
            // What the G-code interpreter refuses is its business (and its tests'); it must
            // be refused cleanly, with a line number, before any motion.
            Err(e) if e.code == "invalid_program" && e.message.starts_with("line ") => {
                eprintln!("{}: refused: {}", path.display(), e.message);
                continue;
            }
            Err(e) => panic!("{}: {e}", path.display()),
        };
        ran += 1;
        let lines = loaded["lines"].as_u64().unwrap() as u32;
        rig.call(json!({"op":"run","action":"start"}));
        // M0 pauses the run: press resume whenever that happens.
        let events = rig.until(|e| {
            if matches!(
                e,
                Event::StateChanged {
                    to: MachineState::Paused,
                    ..
                }
            ) {
                rig.call(json!({"op":"run","action":"resume"}));
            }
            matches!(e, Event::RunEnded { .. })
        });
        assert!(
            matches!(
                events.last(),
                Some(Event::RunEnded {
                    outcome: RunOutcome::Completed,
                    ..
                })
            ),
            "{}: {:?}",
            path.display(),
            events.last()
        );
        assert_eq!(
            acks(&events, run),
            (1..=lines).collect::<Vec<_>>(),
            "{}",
            path.display()
        );
        rig.until_state(MachineState::Idle);
        rig.call(json!({"op":"command","command":"home"}));
    }
    assert!(ran > 0, "no corpus program could be loaded");
}

/// The same machine through the real C ABI, as the server loads it.
#[test]
fn works_through_the_c_abi() {
    use fresa_plugin_api::host::{HostSink, PluginLibrary};
    struct Sink(Mutex<std::sync::mpsc::Sender<Value>>);
    impl HostSink for Sink {
        fn event(&self, event: Value) {
            let _ = self.0.lock().unwrap().send(event);
        }
        fn log(&self, _level: u32, _message: &str) {}
    }
    // `cargo test` leaves this package's cdylib beside the test binary.
    let lib = fresa_plugin_api::built_library("fresa_sim_machine")
        .expect("libfresa_sim_machine not built beside the test");
    let library = PluginLibrary::load(&lib).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(library.name(), "sim-machine");

    let (tx, rx) = channel();
    let sink: Arc<dyn HostSink> = Arc::new(Sink(Mutex::new(tx)));
    let bad = library.create(&json!({"time_scale": true}), sink.clone());
    assert!(bad.err().unwrap().to_string().contains("time_scale"));

    let instance = library.create(&json!({"time_scale": 0}), sink).unwrap();
    let st = instance.call(&json!({"op":"connect"})).unwrap();
    assert_eq!(st["state"], "idle");
    instance
        .call(&json!({"op":"jog","axis":"Y","distance":7.0}))
        .unwrap();
    let deadline = Instant::now() + GUARD;
    loop {
        let e = rx
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
            .unwrap();
        if e["event"] == "state_changed" && e["from"] == "jogging" && e["to"] == "idle" {
            break;
        }
    }
    let st = instance.call(&json!({"op":"status"})).unwrap();
    assert_eq!(st["machine_position"]["y"], 7.0);
    // The typed host calls: the request serialised straight to the call's bytes.
    use fresa_plugin_api::contract::Request;
    assert_eq!(instance.call_request(&Request::Status).unwrap(), st);
    let typed: MachineStatus = instance.request(&Request::Status).unwrap();
    assert_eq!(typed.machine_position.y, 7.0);
    let e = instance
        .call_request(&Request::Mdi {
            line: "G4 P1".into(),
        })
        .unwrap_err();
    assert!(e.to_string().contains("unsupported"), "{e}");
    instance.call(&json!({"op":"shutdown"})).unwrap();
    assert_eq!(
        instance.call(&json!({"op":"status"})).unwrap()["state"],
        "offline"
    );
}

#[test]
fn spindle_and_coolant_switch_and_toggle() {
    let rig = machine(INSTANT());
    let toggle =
        |name: &str| rig.call(json!({"op":"command","command":"toggle_output","name":name}));
    assert_eq!(toggle("spindle"), json!({"output":"spindle","on":true}));
    assert_eq!(toggle("spindle"), json!({"output":"spindle","on":false}));
    assert_eq!(toggle("coolant"), json!({"output":"coolant","on":true}));
    let off = rig.call(json!({"op":"command","command":"set_output","name":"coolant","on":false}));
    assert_eq!(off, json!({"output":"coolant","on":false}));
    let e = rig
        .m
        .request(json!({"op":"command","command":"toggle_output","name":"z_lift"}))
        .unwrap_err();
    assert_eq!(e.code, "unsupported");
    assert!(e.message.contains("z_lift"), "{}", e.message);
    // Reset switches both off, as a controller's reset does.
    toggle("spindle");
    rig.call(json!({"op":"command","command":"reset"}));
    assert_eq!(toggle("spindle")["on"], true);
}

#[test]
fn mdi_moves_as_the_line_says_and_keeps_no_modal_state() {
    let rig = machine(json!({"time_scale": 0, "travel": {"z": [-50, 10]}}));
    rig.call(json!({"op":"jog","axis":"X","distance":4.0}));
    rig.wait_idle();
    // G91 applies to this line only: the next line is absolute again.
    rig.call(json!({"op":"mdi","line":"G91 G1 X1 Z-2 F600"}));
    rig.wait_idle();
    assert_eq!(
        rig.status().machine_position.to_array(),
        [5.0, 0.0, -2.0, 0.0]
    );
    rig.call(json!({"op":"mdi","line":"G0 Z5"}));
    rig.wait_idle();
    let st = rig.status();
    assert_eq!(st.machine_position.to_array(), [5.0, 0.0, 5.0, 0.0]);
    assert_eq!(
        st.feed, 1000.0,
        "the feed from before the MDI lines (the jog's) is back"
    );

    for (line, code) in [
        ("G1 X1 Q", "invalid_gcode"),
        ("G0 Z5\nG0 Z6", "invalid_gcode"),
        ("G4 P1", "unsupported"),
        ("G0 Z20", "out_of_travel"),
    ] {
        let e = rig.m.request(json!({"op":"mdi","line":line})).unwrap_err();
        assert_eq!(e.code, code, "{line}: {}", e.message);
    }
    assert_eq!(
        rig.status().machine_position.to_array(),
        [5.0, 0.0, 5.0, 0.0]
    );
}

#[test]
fn alarm_at_connect_refuses_motion_until_reset() {
    let rig = machine(json!({"time_scale": 0, "alarm_at_connect": "limit switch X+"}));
    let st = rig.status();
    assert_eq!(st.state, MachineState::Alarm);
    assert_eq!(st.alarm.as_deref(), Some("limit switch X+"));
    for req in [
        json!({"op":"jog","axis":"X","distance":1.0}),
        json!({"op":"mdi","line":"G0 X1"}),
        json!({"op":"command","command":"toggle_output","name":"spindle"}),
    ] {
        let e = rig.m.request(req.clone()).unwrap_err();
        assert_eq!(e.code, "alarm", "{req}");
    }
    rig.call(json!({"op":"command","command":"reset"}));
    assert_eq!(rig.status().state, MachineState::Idle);
    rig.call(json!({"op":"jog","axis":"X","distance":1.0}));
    rig.wait_idle();
    assert_eq!(rig.status().machine_position.x, 1.0);
}

/// Lines of `run` in the execution log at `log`.
fn logged(log: &std::path::Path, run: i64) -> usize {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["run"] == run)
        .count()
}

/// Polls `status` until nothing moves and no run is in progress.
fn wait_motion_idle(rig: &Rig) {
    let deadline = Instant::now() + GUARD;
    loop {
        let st = rig.status();
        if st.state == MachineState::Idle && st.run.is_none() {
            return;
        }
        assert!(Instant::now() < deadline, "never idle: {st:?}");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// In real time: once `run cancel`, `run pause`, `command stop` or `command feed_hold` has
/// answered, no program line starts any more (at most the one in flight is logged), and a
/// stopped run's end was emitted before the answer.
#[test]
fn stop_cancel_and_hold_answer_only_once_no_new_line_starts() {
    let log = temp_path("exec.log");
    let rig = machine(json!({"time_scale": 1.0, "execution_log": log}));
    // ~1 ms moves between lines without motion (which must not slip through a hold either).
    let text: String = (1..=3000)
        .map(|i| format!("G1 X{} F60000\n(comment)\n", i % 2))
        .collect();
    let path = program(&text);
    let actions = [
        json!({"op":"run","action":"cancel"}),
        json!({"op":"command","command":"stop"}),
        json!({"op":"run","action":"pause"}),
        json!({"op":"command","command":"feed_hold"}),
    ];
    let mut run = 100;
    let mut most = 0;
    for delay_us in [0, 200, 1000, 3000, 7000] {
        for action in &actions {
            run += 1;
            rig.call(json!({"op":"load_program","run":run,"path":path,"start_line":1}));
            while rig.rx.try_recv().is_ok() {}
            rig.call(json!({"op":"run","action":"start"}));
            // The delay is the stimulus (where in the run the request lands), not a wait.
            std::thread::sleep(Duration::from_micros(delay_us));
            rig.call(action.clone());
            let at_answer = logged(&log, run);
            most = most.max(at_answer);
            let holds = action["action"] == "pause" || action["command"] == "feed_hold";
            if holds {
                assert_eq!(rig.status().state, MachineState::Paused, "{action}");
                // Held: give the motion thread ample time to (wrongly) go on.
                std::thread::sleep(Duration::from_millis(20));
                assert!(
                    logged(&log, run) <= at_answer + 1,
                    "{action} after {delay_us} us"
                );
                rig.call(json!({"op":"run","action":"cancel"}));
            } else {
                let ended = std::iter::from_fn(|| rig.rx.try_recv().ok()).any(|e| {
                    matches!(e, Event::RunEnded { run: r, outcome: RunOutcome::Cancelled, .. }
                        if r == run)
                });
                assert!(ended, "run_ended not emitted before {action} answered");
            }
            wait_motion_idle(&rig);
            let at_idle = logged(&log, run);
            assert!(
                at_idle <= at_answer + 1,
                "{action} after {delay_us} us: {at_answer} lines at the answer, {at_idle} at idle"
            );
        }
    }
    // The later requests landed mid-run, not before the first line.
    assert!(most > 0, "no request landed after a line was executed");
}

#[test]
fn huge_or_overflowing_targets_are_refused_without_travel() {
    let rig = machine(INSTANT());
    for (req, what) in [
        (json!({"op":"jog","axis":"X","distance":1e308}), "jog"),
        (json!({"op":"jog","axis":"A","distance":-2e6}), "jog"),
    ] {
        let e = rig.m.request(req.clone()).unwrap_err();
        assert_eq!(e.code, "out_of_travel", "{req}: {e}");
        assert!(e.message.contains(what), "{e}");
    }
    // The G-code reader refuses coordinates beyond any machine's reach before the travel check.
    for (line, what) in [
        ("G0 X99999999999", "X=99999999999 mm"),
        ("G1 Y2000000 F100", "Y=2000000 mm"),
    ] {
        let e = rig.m.request(json!({"op":"mdi","line":line})).unwrap_err();
        assert_eq!(e.code, "invalid_gcode", "{line}: {e}");
        assert!(e.message.contains(what), "{e}");
    }
    // Two jogs that are each in range but overflow together: the second is refused.
    rig.call(json!({"op":"jog","axis":"Y","distance":900000.0,"feed":1e9}));
    let e = rig
        .m
        .request(json!({"op":"jog","axis":"Y","distance":900000.0}))
        .unwrap_err();
    assert_eq!(e.code, "out_of_travel");
    rig.wait_idle();
    let path = program("G0 Z-5\nG0 X10000000\n");
    let e = rig
        .m
        .request(json!({"op":"load_program","run":1,"path":path,"start_line":1}))
        .unwrap_err();
    assert_eq!(e.code, "invalid_program", "{e}");
    assert!(e.message.contains("line 2, column 4: X=10000000 mm"), "{e}");
    // The motion thread is alive: a normal jog still completes.
    rig.call(json!({"op":"jog","axis":"X","distance":1.0}));
    rig.wait_idle();
    assert_eq!(
        rig.status().machine_position.to_array(),
        [1.0, 900000.0, 0.0, 0.0]
    );
}

/// Moving onto a limit switch presses it: the status shows it at once, motion ends where the
/// switch was reached, the alarm names it; after reset the axis jogs off it (a switch that
/// stays pressed does not trip again) and the lamp goes out. A probe only shows.
#[test]
fn switches_press_by_position_trip_named_alarms_and_release() {
    let rig = machine(json!({
        "time_scale": 0.05,
        "switches": {"limit_x_max": {"axis": "x", "at_or_above": 5},
                     "probe": {"axis": "z", "at_or_below": -2}}
    }));
    let st = rig.status();
    assert_eq!(st.inputs.get("limit_x_max"), Some(&Some(false)));
    assert_eq!(st.inputs.get("probe"), Some(&Some(false)));
    assert_eq!(st.inputs.get("estop"), None, "not simulated: not reported");
    assert_eq!(st.outputs.get("spindle"), Some(&Some(IoValue::On(false))));

    rig.call(json!({"op": "jog", "axis": "X", "distance": 10.0, "feed": 3000}));
    let seen = rig.until(|e| matches!(e, Event::Alarm { .. }));
    let pressed = seen
        .iter()
        .any(|e| matches!(e, Event::Status(s) if s.inputs.get("limit_x_max") == Some(&Some(true))));
    assert!(pressed, "a status event showed the switch: {seen:?}");
    match seen.last() {
        Some(Event::Alarm { message, input }) => {
            assert_eq!(input.as_deref(), Some("limit_x_max"));
            assert!(message.contains("limit_x_max"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    rig.until_state(MachineState::Alarm);
    let st = rig.status();
    let x = st.machine_position.x;
    assert!(
        (5.0..10.0).contains(&x),
        "stopped at the switch, not the target: {x}"
    );
    assert_eq!(
        st.alarm.as_deref().map(|a| a.contains("limit_x_max")),
        Some(true)
    );

    rig.call(json!({"op": "command", "command": "reset"}));
    // Off the switch whatever the overshoot was (it stopped short of the 10 mm target; a
    // loaded machine's longer slices overshoot further past X 5).
    rig.call(json!({"op": "jog", "axis": "X", "distance": -6.0, "feed": 3000}));
    rig.wait_idle();
    let st = rig.status();
    assert_eq!(st.state, MachineState::Idle, "{st:?}");
    assert_eq!(st.inputs.get("limit_x_max"), Some(&Some(false)));

    // A probe touching shows, and trips nothing.
    rig.call(json!({"op": "jog", "axis": "Z", "distance": -3.0, "feed": 3000}));
    rig.wait_idle();
    let st = rig.status();
    assert_eq!(st.inputs.get("probe"), Some(&Some(true)));
    assert_eq!(st.alarm, None);

    // Outputs show what was switched.
    rig.call(json!({"op": "command", "command": "toggle_output", "name": "coolant"}));
    assert_eq!(
        rig.status().outputs.get("coolant_flood"),
        Some(&Some(IoValue::On(true)))
    );
}

fn held(rig: &Rig) -> MachineStatus {
    loop {
        let st = rig.status();
        if st.state == MachineState::Paused && st.hold.is_some() {
            return st;
        }
        rig.until(|e| matches!(e, Event::Status(s) if s.state == MachineState::Paused));
    }
}

/// Issue 26: M6 with tool-change holds on: spindle off, up to the change position's Z and
/// across, the new tool in (a longer one trips the probe higher up), held with the reason;
/// jogs and a probe run in the hold (a feed hold ends a jog, not the run); cycle start goes
/// back up, across and down to where the tip was, then on. M1 holds only with the optional
/// stop on. Every line is acknowledged once.
#[test]
fn a_tool_change_holds_serves_jogs_and_probes_and_goes_back_on_cycle_start() {
    use fresa_plugin_api::contract::HoldKind;
    let rig = machine(json!({
        "time_scale": 0, "tool": 1, "tool_lengths": {"1": 10, "2": 25},
        "switches": {"probe": {"axis": "z", "at_or_below": -50}},
    }));
    let path = program(
        "G21 G90\nG0 X5 Y5 Z-2\nM3 S1000\nM1 (MSG, skipped)\nT2 M6\nG1 Z-3 F100\nM1 (MSG, not skipped)\nM30\n",
    );
    rig.call(
        json!({"op":"load_program","run":7,"path":path,"start_line":1,
                    "tool_change": {"position": {"x": 50, "y": 0, "z": 10}}}),
    );
    rig.call(json!({"op":"run","action":"start"}));
    let st = held(&rig);
    let hold = st.hold.clone().unwrap();
    assert_eq!(hold.kind, HoldKind::ToolChange, "M1 passed: {hold:?}");
    let tc = hold.tool_change.unwrap();
    assert_eq!(
        (tc.from, tc.to, tc.length_compensation),
        (Some(1), 2, false)
    );
    assert_eq!(hold.line, Some(5));
    assert_eq!(st.outputs.get("spindle"), Some(&Some(IoValue::On(false))));
    let at = st.machine_position.to_array();
    assert!(
        close(at[0], 50.0) && close(at[1], 0.0) && close(at[2], 10.0),
        "{st:?}"
    );

    // A jog in the hold moves; MDI does not.
    rig.call(json!({"op":"jog","axis":"Z","distance":-20.0}));
    let st = held(&rig);
    assert!(close(st.machine_position.z, -10.0), "{st:?}");
    assert!(rig.m.request(json!({"op":"mdi","line":"G0 X1"})).is_err());
    // A probe in the hold: T2's tip (25 mm) meets the switch at machine Z -25.
    rig.call(json!({"op":"probe","id":9,"axis":"Z","distance":-30.0,"feed":100.0}));
    let ended = rig.until(|e| matches!(e, Event::ProbeEnded { id: 9, .. }));
    match ended.last() {
        Some(Event::ProbeEnded { trip: Some(t), .. }) => assert!(close(t.z, -25.0), "{t:?}"),
        other => panic!("{other:?}"),
    }
    assert_eq!(
        rig.status().hold.map(|h| h.kind),
        Some(HoldKind::ToolChange)
    );
    // Cycle start: back to X5 Y5 Z-2 (up to Z10 first), then the cut, then the M1 (on).
    rig.call(json!({"op":"run","action":"resume"}));
    let (events, outcome, message) = rig.until_run_ended(7);
    assert_eq!(outcome, RunOutcome::Completed, "{message:?}");
    assert_eq!(acks(&events, 7), (5..=8).collect::<Vec<_>>());
    let st = rig.status();
    let at = st.machine_position.to_array();
    assert!(
        close(at[0], 5.0) && close(at[1], 5.0) && close(at[2], -3.0),
        "{st:?}"
    );
    // Tool 2 is in now; with the optional stop on, M1 holds.
    let path = program("G0 Z0\nM1 (MSG, look)\nG0 Z1\n");
    rig.call(json!({"op":"load_program","run":8,"path":path,"start_line":1,"optional_stop":true}));
    rig.call(json!({"op":"run","action":"start"}));
    let hold = held(&rig).hold.unwrap();
    assert_eq!(hold.kind, HoldKind::OptionalStop);
    assert_eq!(hold.program_message.as_deref(), Some("look"));
    rig.call(json!({"op":"command","command":"cycle_start"}));
    let (_, outcome, _) = rig.until_run_ended(8);
    assert_eq!(outcome, RunOutcome::Completed);
}

/// A feed hold during a jog of a tool-change hold ends the jog where it is; the run stays
/// held, and a stop then cancels it.
#[test]
fn a_feed_hold_ends_a_tool_change_jog_not_the_run() {
    use fresa_plugin_api::contract::HoldKind;
    // Jog 50 mm at 100 mm/min: 30 s at time scale 1, so it is surely under way.
    let rig = machine(json!({"time_scale": 1}));
    let path = program("G0 X1\nT3 M6\nG0 X2\n");
    rig.call(json!({"op":"load_program","run":4,"path":path,"start_line":1,"tool_change":{}}));
    rig.call(json!({"op":"run","action":"start"}));
    held(&rig);
    rig.call(json!({"op":"jog","axis":"Y","distance":50.0,"feed":100.0}));
    rig.until(|e| matches!(e, Event::Status(s) if s.machine_position.y > 0.0));
    // Cycle start waits for the jog to end.
    let e = rig
        .m
        .request(json!({"op":"command","command":"cycle_start"}))
        .unwrap_err();
    assert_eq!(e.code, "busy");
    rig.call(json!({"op":"command","command":"feed_hold"}));
    let st = rig.status();
    assert_eq!(st.state, MachineState::Paused, "{st:?}");
    assert_eq!(st.hold.as_ref().map(|h| h.kind), Some(HoldKind::ToolChange));
    let y = st.machine_position.y;
    assert!(y > 0.0 && y < 50.0, "{st:?}");
    rig.call(json!({"op":"command","command":"stop"}));
    let (_, outcome, _) = rig.until_run_ended(4);
    assert_eq!(outcome, RunOutcome::Cancelled);
    assert_eq!(rig.status().state, MachineState::Idle);
}

/// The surface z = 0.1 + 0.01 x - 0.02 y + 0.001 x y probed on a 3 x 3 grid over X 0..20,
/// Y 0..10 (bilinear, so the map reproduces it exactly inside the area).
fn saddle(x: f64, y: f64) -> f64 {
    0.1 + 0.01 * x - 0.02 * y + 0.001 * x * y
}

fn saddle_map() -> Value {
    let mut z = Vec::new();
    for j in 0..3 {
        for i in 0..3 {
            z.push(saddle(10.0 * f64::from(i), 5.0 * f64::from(j)));
        }
    }
    json!({"x0": 0, "y0": 0, "dx": 10, "dy": 5, "nx": 3, "ny": 3, "z": z})
}

/// A height-mapped run: every move's Z gets the map's correction, and a long move is split
/// where it crosses grid lines, so the path follows the map cell by cell (seen in the status
/// of every piece at time scale 0); outside the area the edge's correction holds. The
/// execution log records where each line ended.
#[test]
fn a_height_map_corrects_z_along_the_split_path() {
    let log = temp_path("exec.log");
    let rig = machine(json!({"time_scale": 0, "status_interval_ms": 0, "execution_log": log}));
    let path = program("G21 G90\nG0 X-5 Y1 Z1\nG1 X25 Y9 Z-0.1 F600\nG1 X10 Y5\n");
    let loaded = rig.call(
        json!({"op":"load_program","run":3,"path":path,"start_line":1,
                                 "height_map": saddle_map()}),
    );
    assert_eq!(
        loaded,
        json!({"lines": 4, "start_line": 1, "height_map": true})
    );
    rig.call(json!({"op":"run","action":"start"}));
    let (events, outcome, message) = rig.until_run_ended(3);
    assert_eq!(outcome, RunOutcome::Completed, "{message:?}");
    // Program Z along line 3 (X -5 -> 25, Z 1 -> -0.1), and the correction there.
    let line3_z = |x: f64| 1.0 + (x + 5.0) / 30.0 * (-1.1);
    let corr = |x: f64, y: f64| saddle(x.clamp(0.0, 20.0), y.clamp(0.0, 10.0));
    let positions: Vec<[f64; 4]> = events
        .iter()
        .filter_map(|e| match e {
            Event::Status(s) => Some(s.machine_position.to_array()),
            _ => None,
        })
        .collect();
    // Line 3 crosses X 0, 10 and 20 (at Y 7/3, 5, 23/3): a piece ends on each, corrected.
    for x in [0.0, 10.0, 20.0] {
        let p = positions
            .iter()
            .find(|p| close(p[0], x) && p[1] > 1.5 && p[1] < 8.5)
            .unwrap_or_else(|| panic!("no piece ended at X {x}: {positions:?}"));
        let want = line3_z(x) + corr(p[0], p[1]);
        assert!(close(p[2], want), "X {x}: Z {} != {want}", p[2]);
    }
    // The log's end positions: line 2 outside the area (corner's correction), line 3 outside
    // past X 20 (the edge's), line 4 at a grid point.
    let logged: Vec<Value> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let end_z = |line: u64| {
        let e = logged.iter().find(|e| e["line"] == line).unwrap();
        e["pos"][2]
            .as_f64()
            .unwrap_or_else(|| panic!("no pos in {e}"))
    };
    assert!(close(end_z(2), 1.0 + saddle(0.0, 1.0)), "{logged:?}");
    assert!(close(end_z(3), -0.1 + saddle(20.0, 9.0)), "{logged:?}");
    assert!(close(end_z(4), -0.1 + saddle(10.0, 5.0)), "{logged:?}");
}

/// What a height-mapped program cannot do is refused at load, naming the line; a malformed
/// map is refused naming the field.
#[test]
fn height_mapped_programs_that_probe_or_change_offset_are_refused() {
    let rig =
        machine(json!({"time_scale": 0, "switches": {"probe": {"axis": "z", "at_or_below": -5}}}));
    for (text, line) in [
        ("G0 X1\nG38.2 Z-10 F100\n", "line 2"),
        ("G0 X1\nG55\nG0 X2\n", "line 2"),
    ] {
        let e = rig
            .m
            .request(
                json!({"op":"load_program","run":4,"path":program(text),"start_line":1,
                            "height_map": saddle_map()}),
            )
            .unwrap_err();
        assert_eq!(e.code, "unsupported", "{e}");
        assert!(e.message.starts_with(line), "{e}");
    }
    let mut bad = saddle_map();
    bad["nx"] = json!(4);
    let e = rig
        .m
        .request(
            json!({"op":"load_program","run":4,"path":program("G0 X1\n"),"start_line":1,
                        "height_map": bad}),
        )
        .unwrap_err();
    assert_eq!(e.code, "invalid_request");
    assert!(e.message.contains("height_map.z"), "{e}");
    // The travel check includes the correction: Z -0.05 is inside -1..0, corrected it is not.
    let rig = machine(json!({"time_scale": 0, "travel": {"z": [-1, 0]}}));
    let e = rig
        .m
        .request(
            json!({"op":"load_program","run":5,"path":program("G1 X10 Y5 Z-0.05 F100\n"),
                        "start_line":1, "height_map": saddle_map()}),
        )
        .unwrap_err();
    assert_eq!(e.code, "out_of_travel", "{e}");
}

/// A probing move onto a tilted surface trips at the surface's height under the tool.
#[test]
fn a_probe_trips_on_a_tilted_surface_at_its_height_there() {
    let rig = machine(json!({"time_scale": 0, "switches": {"probe": {
        "axis": "z", "at_or_below": -1, "slope_x": 0.01, "slope_y": -0.02}}}));
    for (x, y) in [(0.0, 0.0), (10.0, 0.0), (20.0, 5.0)] {
        let here = rig.status().machine_position;
        rig.call(json!({"op":"jog","axis":"X","distance": x - here.x, "feed": 3000}));
        rig.wait_idle();
        if y != here.y {
            rig.call(json!({"op":"jog","axis":"Y","distance": y - here.y, "feed": 3000}));
            rig.wait_idle();
        }
        let z = rig.status().machine_position.z;
        rig.call(json!({"op":"probe","id":1,"axis":"Z","distance": -5.0 - z,"feed":300}));
        let seen = rig.until(|e| matches!(e, Event::ProbeEnded { .. }));
        let Some(Event::ProbeEnded {
            trip: Some(trip), ..
        }) = seen.last()
        else {
            panic!("{seen:?}");
        };
        let want = -1.0 + 0.01 * x - 0.02 * y;
        assert!(
            close(trip.z, want),
            "at X{x} Y{y}: trip {} != {want}",
            trip.z
        );
        rig.call(json!({"op":"jog","axis":"Z","distance": 2.0, "feed": 3000}));
        rig.wait_idle();
    }
}
