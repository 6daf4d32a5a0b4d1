//! The backend driven directly (no server), against the in-process simulator on loopback.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_kawasaki_as::sim::{self, SimConfig};
use fresa_kawasaki_as::{KawasakiMachine, Protocol};
use fresa_plugin_api::contract::{Event, MachineState, RunOutcome};
use fresa_plugin_api::MachineBackend;
use serde_json::{json, Value};
use std::net::TcpListener;
use std::sync::{mpsc, Arc};
use std::time::Duration;

const T: Duration = Duration::from_secs(30);

struct Rig {
    m: KawasakiMachine,
    rx: mpsc::Receiver<Event>,
    dir: tempfile::TempDir,
    sim: Arc<sim::Sim>,
}

fn rig(protocol: Protocol, sim_cfg: SimConfig) -> Rig {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let sim = sim::spawn(
        SimConfig {
            protocol,
            ..sim_cfg
        },
        listener,
    )
    .unwrap();
    let (tx, rx) = mpsc::channel();
    let tx = std::sync::Mutex::new(tx);
    let m = KawasakiMachine::new(
        &json!({"address": addr.to_string(), "protocol": protocol.name()}),
        Arc::new(move |e: &Event| {
            let _ = tx.lock().unwrap().send(e.clone());
        }),
        Arc::new(|_: &str| {}),
    )
    .unwrap();
    Rig {
        m,
        rx,
        dir: tempfile::tempdir().unwrap(),
        sim,
    }
}

impl Rig {
    fn call(&self, v: Value) -> Value {
        self.m.request(v).unwrap()
    }

    fn load(&self, run: i64, program: &str) -> Value {
        let path = self.dir.path().join(format!("p{run}.nc"));
        std::fs::write(&path, program).unwrap();
        self.call(json!({"op": "load_program", "run": run, "path": path, "start_line": 1}))
    }

    /// Events until `pred` matches (inclusive).
    fn until(&self, mut pred: impl FnMut(&Event) -> bool) -> Vec<Event> {
        let mut seen = Vec::new();
        loop {
            let e = self
                .rx
                .recv_timeout(T)
                .unwrap_or_else(|_| panic!("no matching event; seen {seen:?}"));
            let done = pred(&e);
            seen.push(e);
            if done {
                return seen;
            }
        }
    }
}

fn acked(events: &[Event]) -> Vec<u32> {
    events
        .iter()
        .filter_map(|e| match e {
            Event::LineAcknowledged { line, .. } => Some(*line),
            _ => None,
        })
        .collect()
}

fn every_line_once(protocol: Protocol) {
    let r = rig(protocol, SimConfig::default());
    let program = "(start)\nG21 G90\n\nG0 X1 Y1 Z2\nG1 Z-1 F300\nG2 X1 Y1 I1 J0\n; note\nG4 P0.01\nG1 X5\nM30\n";
    let loaded = r.load(1, program);
    assert_eq!(loaded, json!({"lines": 10, "start_line": 1}));
    let answer = r.call(json!({"op": "run", "action": "start"}));
    assert_eq!(answer["part_zero"]["x"], -400.0);
    let events = r.until(|e| matches!(e, Event::RunEnded { .. }));
    assert_eq!(acked(&events), (1..=10).collect::<Vec<_>>());
    assert!(events
        .iter()
        .any(|e| matches!(e, Event::PartZeroReported { run: Some(1), .. })));
    assert!(matches!(
        events.last(),
        Some(Event::RunEnded {
            run: 1,
            outcome: RunOutcome::Completed,
            ..
        })
    ));
    assert!(r.sim.motions() > 10, "the circle is many chords");
}

#[test]
fn legacy_acknowledges_every_line_once_in_order() {
    every_line_once(Protocol::Legacy);
}

#[test]
fn fresa_v1_acknowledges_every_line_once_in_order() {
    every_line_once(Protocol::FresaV1);
}

fn m0_pauses(protocol: Protocol) {
    let r = rig(protocol, SimConfig::default());
    r.load(1, "G21 G90 G0 X1\nM0\nG0 X2\n");
    r.call(json!({"op": "run", "action": "start"}));
    r.until(|e| {
        matches!(
            e,
            Event::StateChanged {
                to: MachineState::Paused,
                ..
            }
        )
    });
    let motions = r.sim.motions();
    assert_eq!(motions, 1, "nothing after M0 is sent");
    r.call(json!({"op": "run", "action": "resume"}));
    r.until(|e| {
        matches!(
            e,
            Event::RunEnded {
                outcome: RunOutcome::Completed,
                ..
            }
        )
    });
    assert_eq!(r.sim.motions(), 2);
}

#[test]
fn legacy_m0_pauses_until_resumed() {
    m0_pauses(Protocol::Legacy);
}

#[test]
fn fresa_v1_m0_pauses_until_resumed() {
    m0_pauses(Protocol::FresaV1);
}

#[test]
fn what_a_robot_cannot_do_is_refused_clearly() {
    let r = rig(Protocol::Legacy, SimConfig::default());
    let e =
        r.m.request(json!({"op": "jog", "axis": "X", "distance": 1.0}))
            .unwrap_err();
    assert_eq!(e.code, "unsupported");
    assert!(e.message.contains("pendant"), "{}", e.message);
    let e =
        r.m.request(json!({"op": "get_artifact", "name": "as-program"}))
            .unwrap_err();
    assert_eq!(e.code, "not_available");
    let e =
        r.m.request(json!({"op": "get_artifact", "name": "plc"}))
            .unwrap_err();
    assert_eq!(e.code, "unknown_artifact");
    let e =
        r.m.request(json!({"op": "run", "action": "start"}))
            .unwrap_err();
    assert_eq!(e.code, "no_program");
    let path = r.dir.path().join("bad.nc");
    std::fs::write(&path, "G1 X1 F100\nG1 X2 Q3\n").unwrap();
    let e =
        r.m.request(json!({"op": "load_program", "run": 1, "path": path, "start_line": 1}))
            .unwrap_err();
    assert_eq!(e.code, "invalid_program");
    assert!(e.message.contains("line 2"), "{}", e.message);
}

#[test]
fn an_unreachable_robot_is_named() {
    // A port nobody listens on: bind, note it, close.
    let addr = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let m = KawasakiMachine::new(
        &json!({"address": addr.to_string()}),
        Arc::new(|_: &Event| {}),
        Arc::new(|_: &str| {}),
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.nc");
    std::fs::write(&path, "G0 X1\n").unwrap();
    m.request(json!({"op": "load_program", "run": 1, "path": path, "start_line": 1}))
        .unwrap();
    let e = m
        .request(json!({"op": "run", "action": "start"}))
        .unwrap_err();
    assert_eq!(e.code, "robot_unreachable");
    assert!(e.message.contains(&addr.to_string()), "{}", e.message);
}

/// A cancel answers only once the run is over: nothing more is sent, the robot has finished the
/// moves it had, and `run_ended` (cancelled) has already been emitted. So the robot's motion
/// count is final at the answer.
fn cancel_is_final_when_answered(protocol: Protocol) {
    // 1 mm moves at 10 mm/s: 0.1 s each, in real time.
    let r = rig(
        protocol,
        SimConfig {
            time_scale: 1.0,
            ..SimConfig::default()
        },
    );
    let program: String = (0..200)
        .map(|i| format!("G1 X{} F600\n", (i % 2) + 1))
        .collect();
    r.load(1, &format!("G21 G90\n{program}"));
    r.call(json!({"op": "run", "action": "start"}));
    r.until(|e| matches!(e, Event::LineAcknowledged { line, .. } if *line >= 4));
    r.call(json!({"op": "run", "action": "cancel"}));
    let at_answer = r.sim.motions();
    let seen: Vec<Event> = r.rx.try_iter().collect();
    assert!(
        seen.iter().any(|e| matches!(
            e,
            Event::RunEnded {
                run: 1,
                outcome: RunOutcome::Cancelled,
                ..
            }
        )),
        "run_ended is emitted before the cancel answers: {seen:?}"
    );
    assert_eq!(r.m.status().unwrap().state, MachineState::Idle);
    // A fresh run on the same link proves the robot took nothing more of the old one.
    r.load(2, "G21 G90\nG0 X0\n");
    r.call(json!({"op": "run", "action": "start"}));
    r.until(|e| matches!(e, Event::RunEnded { run: 2, .. }));
    assert_eq!(
        r.sim.motions(),
        at_answer + 1,
        "only run 2's one move came after the answer"
    );
    assert!(
        at_answer < 200,
        "the cancel stopped the run early ({at_answer} moves)"
    );
}

#[test]
fn legacy_cancel_is_final_when_answered() {
    cancel_is_final_when_answered(Protocol::Legacy);
}

#[test]
fn fresa_v1_cancel_is_final_when_answered() {
    cancel_is_final_when_answered(Protocol::FresaV1);
}

/// What each protocol can do with overrides: legacy none (its robot program fixes its speeds),
/// fresa-v1 the feed. A refusal names the reason and changes nothing; 100 % is always fine.
#[test]
fn overrides_are_refused_where_the_protocol_cannot_carry_them() {
    let set = |r: &Rig, body: Value| {
        let mut req = json!({"op": "command", "command": "set_overrides"});
        for (k, v) in body.as_object().unwrap() {
            req[k] = v.clone();
        }
        r.m.request(req)
    };
    let overrides = |r: &Rig| {
        let st = r.call(json!({"op": "status"}));
        [
            &st["feed_override"],
            &st["spindle_override"],
            &st["rapid_override"],
        ]
        .map(|v| v.as_f64().unwrap())
    };
    let legacy = rig(Protocol::Legacy, SimConfig::default());
    let e = set(&legacy, json!({"feed": 50})).unwrap_err();
    assert_eq!(e.code, "unsupported");
    assert!(
        e.message.contains("15 mm/s") && e.message.contains("fresa-v1"),
        "{}",
        e.message
    );
    let e = set(&legacy, json!({"rapid": 50})).unwrap_err();
    assert!(e.message.contains("10 mm/s"), "{}", e.message);
    set(&legacy, json!({"feed": 100, "rapid": 100})).unwrap();
    assert_eq!(overrides(&legacy), [100.0; 3]);

    let v1 = rig(Protocol::FresaV1, SimConfig::default());
    let e = set(&v1, json!({"feed": 50, "spindle": 120})).unwrap_err();
    assert_eq!(e.code, "unsupported");
    assert!(e.message.contains("potentiometer"), "{}", e.message);
    let e = set(&v1, json!({"rapid": 25})).unwrap_err();
    assert!(e.message.contains("rapid_mm_s"), "{}", e.message);
    let e = set(&v1, json!({"feed": -5})).unwrap_err();
    assert_eq!(e.code, "invalid_request");
    assert_eq!(overrides(&v1), [100.0; 3], "a refusal changes nothing");
    set(&v1, json!({"feed": 50})).unwrap();
    assert_eq!(overrides(&v1), [50.0, 100.0, 100.0]);
}

/// fresa-v1 under a 40 % feed override: every SPEED the robot takes is the program's, scaled
/// (F600 = 10 mm/s -> 4 mm/s, below the 5 mm/s clamp for programs; F1200 = 20 mm/s clamped to
/// 15 -> 6 mm/s), and every cutting motion runs at it; rapids keep the program's rapid speed.
#[test]
fn fresa_v1_sends_the_programmed_speed_scaled_by_the_feed_override() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("robot.log");
    let r = rig(
        Protocol::FresaV1,
        SimConfig {
            log: Some(log.clone()),
            ..SimConfig::default()
        },
    );
    r.m.request(json!({"op": "command", "command": "set_overrides", "feed": 40}))
        .unwrap();
    r.load(
        1,
        "G21 G90\nG0 X1 Y1 Z2\nG1 Z-1 F600\nG1 X5\nG1 X9 F1200\nG0 Z5\nM30\n",
    );
    r.call(json!({"op": "run", "action": "start"}));
    r.until(|e| {
        matches!(
            e,
            Event::RunEnded {
                outcome: RunOutcome::Completed,
                ..
            }
        )
    });
    let moves: Vec<(String, f64)> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter(|e| e["move"].is_string())
        .map(|e| {
            (
                e["move"].as_str().unwrap().to_string(),
                e["speed"].as_f64().unwrap(),
            )
        })
        .collect();
    let want = [
        ("JMOVE", 10.0),
        ("LMOVE", 4.0),
        ("LMOVE", 4.0),
        ("LMOVE", 6.0),
        ("JMOVE", 10.0),
    ];
    assert_eq!(moves.len(), want.len(), "{moves:?}");
    for ((kind, speed), (wk, ws)) in moves.iter().zip(want) {
        assert_eq!(kind, wk, "{moves:?}");
        assert!((speed - ws).abs() < 1e-6, "{moves:?}");
    }
}
