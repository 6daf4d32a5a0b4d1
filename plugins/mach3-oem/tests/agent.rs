//! The agent over loopback TCP with the simulator behind it: handshake, batches, malformed
//! frames, and the safety rule that jogs end when their connection does.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_mach3_oem::agent::{Agent, AgentConfig};
use fresa_mach3_oem::client::{AgentClient, LinkError};
use fresa_mach3_oem::mach3::{Call, ErrorKind, Mach3};
use fresa_mach3_oem::protocol::CallResult;
use fresa_mach3_oem::sim::{Mach3Sim, ProbeSwitch, SimConfig};
use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

const SECRET: &str = "agent-test-secret";

fn start(watchdog: Duration) -> (String, Mach3Sim, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let mut sim = Mach3Sim::new(SimConfig::default());
    sim.do_oem_button(1021).unwrap(); // out of the start-up reset
    let cfg = AgentConfig {
        secret: SECRET.into(),
        call_timeout: Duration::from_secs(2),
        watchdog,
        program_dir: dir.path().to_path_buf(),
    };
    let handle = sim.clone();
    let agent = Agent::bind("127.0.0.1:0", cfg, Box::new(move || Box::new(handle))).unwrap();
    let addr = agent.local_addr().unwrap().to_string();
    std::thread::spawn(move || agent.serve());
    (addr, sim, dir)
}

fn client(addr: &str) -> AgentClient {
    AgentClient::new(addr.into(), SECRET.into(), Duration::from_secs(5))
}

fn wait_until(what: &str, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while !f() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn batches_run_in_order_and_report_each_result() {
    let (addr, _sim, dir) = start(Duration::from_secs(5));
    let mut c = client(&addr);
    let r = c
        .batch(
            vec![
                Call::Code {
                    line: "G91 G1 X(".into(),
                },
                Call::GetOemDro { code: 46 },
                Call::WriteProgram {
                    name: "p.nc".into(),
                    data: "G0 X1\n".into(),
                    first: true,
                    last: true,
                },
                Call::WriteProgram {
                    name: "../evil".into(),
                    data: String::new(),
                    first: true,
                    last: true,
                },
            ],
            false,
        )
        .unwrap();
    assert!(
        matches!(&r[0], CallResult::Err(e) if e.kind == ErrorKind::Invalid),
        "{r:?}"
    );
    assert_eq!(r[1], CallResult::Ok(serde_json::json!(1.0)));
    let CallResult::Ok(path) = &r[2] else {
        panic!("{r:?}")
    };
    let path = path.as_str().unwrap();
    assert_eq!(std::fs::read_to_string(path).unwrap(), "G0 X1\n");
    assert!(path.starts_with(dir.path().to_str().unwrap()), "{path}");
    assert!(
        matches!(&r[3], CallResult::Err(e) if e.kind == ErrorKind::Invalid),
        "{r:?}"
    );
}

#[test]
fn a_wrong_secret_is_refused() {
    let (addr, _sim, _dir) = start(Duration::from_secs(5));
    let mut c = AgentClient::new(addr, "not-the-secret".into(), Duration::from_secs(5));
    match c.connect() {
        Err(LinkError::Refused { error, .. }) => assert_eq!(error.kind, ErrorKind::Auth),
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_malformed_frame_is_answered_and_skipped() {
    let (addr, _sim, _dir) = start(Duration::from_secs(5));
    let stream = TcpStream::connect(&addr).unwrap();
    let mut r = BufReader::new(stream.try_clone().unwrap());
    let mut w = stream;
    let mut line = String::new();
    r.read_line(&mut line).unwrap();
    let hello: serde_json::Value = serde_json::from_str(&line).unwrap();
    let auth = fresa_mach3_oem::protocol::sign(SECRET, hello["nonce"].as_str().unwrap());
    writeln!(w, "{}", serde_json::json!({"protocol": 1, "auth": auth})).unwrap();
    line.clear();
    r.read_line(&mut line).unwrap();
    assert!(line.contains("\"ok\":true"), "{line}");
    writeln!(
        w,
        "{{\"id\": 7, \"calls\": [{{\"op\": \"launch_mach3\"}}]}}"
    )
    .unwrap();
    line.clear();
    r.read_line(&mut line).unwrap();
    let v: serde_json::Value = serde_json::from_str(&line).unwrap();
    assert_eq!(v["id"], 7, "{v}");
    assert_eq!(v["error"]["kind"], "protocol", "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("launch_mach3"),
        "{v}"
    );
    // The connection still works.
    writeln!(w, "{{\"id\": 8, \"calls\": [{{\"op\": \"is_estop\"}}]}}").unwrap();
    line.clear();
    r.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), r#"{"id":8,"results":[{"ok":false}]}"#);
}

#[test]
fn jogs_end_when_the_connection_is_lost_or_goes_quiet() {
    let (addr, mut sim, _dir) = start(Duration::from_millis(300));
    // Lost: the client goes away while jogging X+.
    let mut c = client(&addr);
    c.batch(
        vec![Call::JogOn {
            axis: 0,
            direction: 0,
        }],
        false,
    )
    .unwrap();
    assert!(sim.is_moving().unwrap());
    drop(c);
    wait_until("JogOff after disconnect", || !sim.is_moving().unwrap());
    // Quiet: the client stays connected but stops talking (a hung server): the watchdog.
    let mut c = client(&addr);
    c.batch(
        vec![Call::JogOn {
            axis: 1,
            direction: 1,
        }],
        false,
    )
    .unwrap();
    assert!(sim.is_moving().unwrap());
    wait_until("JogOff after the watchdog", || !sim.is_moving().unwrap());
    assert!(sim.get_oem_dro(801).unwrap() < 0.0, "Y jogged minus");
    drop(c);
}

/// A limit switch on Mach3 (its LED lit, reset latched as Mach3 does): the backend reports the
/// input and goes to alarm with an `alarm` event that names it.
#[test]
fn a_limit_led_shows_as_an_input_and_names_the_alarm() {
    use fresa_mach3_oem::backend::Mach3Backend;
    use fresa_plugin_api::contract::Event;
    use fresa_plugin_api::MachineBackend;
    use std::sync::{Arc, Mutex};

    let (addr, sim, _dir) = start(Duration::from_secs(5));
    let events = Arc::new(Mutex::new(Vec::<Event>::new()));
    let sink = events.clone();
    let backend = Mach3Backend::new(
        &serde_json::json!({"agent": addr, "secret": SECRET, "poll_hz": 50}),
        Arc::new(move |e: &Event| sink.lock().unwrap().push(e.clone())),
    )
    .unwrap();
    let status = |b: &Mach3Backend| b.request(serde_json::json!({"op": "status"})).unwrap();
    backend
        .request(serde_json::json!({"op": "connect"}))
        .unwrap();
    wait_until("idle with all lamps known", || {
        let st = status(&backend);
        st["state"] == "idle" && st["inputs"]["limit_x_max"] == false
    });
    sim.press_limit(0, true);
    wait_until("alarm", || status(&backend)["state"] == "alarm");
    let st = status(&backend);
    assert_eq!(st["inputs"]["limit_x_max"], true, "{st}");
    assert_eq!(st["inputs"]["estop"], true, "{st}");
    assert!(
        st["alarm"].as_str().unwrap().contains("limit_x_max"),
        "{st}"
    );
    wait_until("the alarm event", || {
        events.lock().unwrap().iter().any(
            |e| matches!(e, Event::Alarm { input, .. } if input.as_deref() == Some("limit_x_max")),
        )
    });
}

/// The agent names its protocol features in its hello; `get_var` reads Mach3's parameters,
/// where G31 leaves its trip.
#[test]
fn the_hello_names_get_var_and_it_reads_g31s_trip() {
    let (addr, sim, _dir) = start(Duration::from_secs(5));
    sim.set_probe(Some(ProbeSwitch {
        axis: 2,
        at: -2.0,
        below: true,
    }));
    let mut c = client(&addr);
    c.connect().unwrap();
    assert!(c.has_feature(fresa_mach3_oem::protocol::FEATURE_GET_VAR));
    c.batch(
        vec![Call::Code {
            line: "G90 G31 Z-5 F3000".into(),
        }],
        false,
    )
    .unwrap();
    let mut s = sim.clone();
    wait_until("the G31 ended", || !s.is_moving().unwrap());
    let r = c
        .batch(
            vec![Call::GetVar { var: 2002 }, Call::GetVar { var: -1 }],
            false,
        )
        .unwrap();
    assert!(
        matches!(&r[0], CallResult::Ok(v) if (v.as_f64().unwrap() + 2.0).abs() < 1e-9),
        "{r:?}"
    );
    assert!(
        matches!(&r[1], CallResult::Err(e) if e.kind == ErrorKind::Invalid),
        "{r:?}"
    );
}

/// An agent from before the feature list (its hello names none) answering every call with a
/// plausible value: the plugin talks to it as before, and refuses a probe (which needs
/// `get_var`) saying the agent must be updated, before anything moves.
#[test]
fn a_probe_through_an_agent_without_get_var_is_refused_naming_the_agent() {
    use fresa_mach3_oem::backend::Mach3Backend;
    use fresa_mach3_oem::protocol::{read_frame, write_frame, Request, Response};
    use fresa_plugin_api::MachineBackend;

    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let moved = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let seen = moved.clone();
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(stream) = stream else { return };
            let seen = seen.clone();
            std::thread::spawn(move || {
                let mut r = BufReader::new(stream.try_clone().unwrap());
                let mut w = stream;
                let hello = serde_json::json!({"agent": "fresa-mach3-agent", "protocol": 1,
                    "nonce": "00"});
                writeln!(w, "{hello}").unwrap();
                let mut buf = Vec::new();
                if !read_frame(&mut r, &mut buf).unwrap_or(false) {
                    return;
                }
                writeln!(w, "{{\"ok\":true}}").unwrap();
                while let Ok(true) = read_frame(&mut r, &mut buf) {
                    let req: Request = serde_json::from_slice(&buf).unwrap();
                    let results = req
                        .calls
                        .iter()
                        .map(|c| match c {
                            Call::GetOemLed { .. } | Call::IsMoving | Call::IsEstop => {
                                CallResult::Ok(false.into())
                            }
                            Call::GetOemDro { .. } => CallResult::Ok(0.0.into()),
                            _ => {
                                seen.store(true, std::sync::atomic::Ordering::SeqCst);
                                CallResult::Ok(serde_json::Value::Null)
                            }
                        })
                        .collect();
                    let answer = Response {
                        id: Some(req.id),
                        results,
                        error: None,
                    };
                    if write_frame(&mut w, &answer).is_err() {
                        return;
                    }
                }
            });
        }
    });
    let backend = Mach3Backend::new(
        &serde_json::json!({"agent": addr, "secret": "anything-at-all", "poll_hz": 50}),
        std::sync::Arc::new(|_: &fresa_plugin_api::contract::Event| {}),
    )
    .unwrap();
    backend
        .request(serde_json::json!({"op": "connect"}))
        .unwrap();
    wait_until("idle", || {
        backend
            .request(serde_json::json!({"op": "status"}))
            .unwrap()["state"]
            == "idle"
    });
    let e = backend
        .request(
            serde_json::json!({"op": "probe", "id": 1, "axis": "Z", "distance": -5.0,
            "feed": 100.0}),
        )
        .unwrap_err();
    assert_eq!(e.code, "unsupported", "{e:?}");
    assert!(e.message.contains("older"), "{e:?}");
    assert!(
        !moved.load(std::sync::atomic::Ordering::SeqCst),
        "nothing but reads reached Mach3"
    );
}

/// In process, the events a probe leaves: the status at rest (no longer `jogging`) comes
/// before `probe_ended`, whose trip is the switch's position and whose position is where
/// Mach3 came to rest; an override command is in Mach3's DRO when it returns.
#[test]
fn probe_ended_follows_the_status_at_rest_and_overrides_reach_the_dros() {
    use fresa_mach3_oem::backend::Mach3Backend;
    use fresa_plugin_api::contract::{Event, MachineState, ProbeOutcome};
    use fresa_plugin_api::MachineBackend;
    use std::sync::{Arc, Mutex};

    let (addr, mut sim, _dir) = start(Duration::from_secs(5));
    sim.set_probe(Some(ProbeSwitch {
        axis: 2,
        at: -10.0,
        below: true,
    }));
    let events = Arc::new(Mutex::new(Vec::<Event>::new()));
    let sink = events.clone();
    let backend = Mach3Backend::new(
        &serde_json::json!({"agent": addr, "secret": SECRET, "poll_hz": 50}),
        Arc::new(move |e: &Event| sink.lock().unwrap().push(e.clone())),
    )
    .unwrap();
    backend
        .request(serde_json::json!({"op": "connect"}))
        .unwrap();
    wait_until("idle", || {
        backend
            .request(serde_json::json!({"op": "status"}))
            .unwrap()["state"]
            == "idle"
    });
    backend
        .request(
            serde_json::json!({"op": "command", "command": "set_overrides", "feed": 40.0,
            "spindle": 110.0}),
        )
        .unwrap();
    assert_eq!(sim.get_oem_dro(821).unwrap(), 40.0);
    assert_eq!(sim.get_oem_dro(74).unwrap(), 110.0);
    // Real time: 10 mm at 600 mm/min to the plate takes 1 s. Under a 40 % feed override the
    // G31 is sent with F1500, so that it goes at the 600 asked for.
    backend
        .request(
            serde_json::json!({"op": "probe", "id": 9, "axis": "Z", "distance": -12.0,
            "feed": 600.0}),
        )
        .unwrap();
    assert_eq!(sim.get_oem_dro(818).unwrap(), 1500.0, "F of the G31");
    assert_eq!(sim.get_oem_dro(819).unwrap(), 31.0, "G31 under way");
    wait_until("probe_ended", || {
        events
            .lock()
            .unwrap()
            .iter()
            .any(|e| matches!(e, Event::ProbeEnded { .. }))
    });
    let events = events.lock().unwrap();
    let end = events
        .iter()
        .position(|e| matches!(e, Event::ProbeEnded { .. }))
        .unwrap();
    let Event::ProbeEnded {
        id,
        outcome,
        trip,
        position,
        ..
    } = &events[end]
    else {
        unreachable!()
    };
    assert_eq!((*id, *outcome), (9, ProbeOutcome::Tripped));
    assert!((trip.unwrap().z + 10.0).abs() < 1e-9, "{trip:?}");
    assert!(position.z < -10.0, "at rest past the trip: {position:?}");
    let last_status = events[..end]
        .iter()
        .rev()
        .find_map(|e| match e {
            Event::Status(s) => Some(s),
            _ => None,
        })
        .unwrap();
    assert_eq!(last_status.state, MachineState::Idle);
    assert_eq!(last_status.machine_position.z, position.z);
    // The modal state found is back: G0 and F0 (Mach3 started with none).
    assert_eq!(sim.get_oem_dro(818).unwrap(), 0.0, "F put back");
    assert_eq!(sim.get_oem_dro(819).unwrap(), 0.0, "G0 put back");
    assert!(events[..end].iter().any(|e| matches!(
        e,
        Event::StateChanged {
            to: MachineState::Jogging,
            ..
        }
    )));
}
