//! The agent over loopback TCP with the simulator behind it: handshake, batches, malformed
//! frames, and the safety rule that jogs end when their connection does.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_mach3_oem::agent::{Agent, AgentConfig};
use fresa_mach3_oem::client::{AgentClient, LinkError};
use fresa_mach3_oem::mach3::{Call, ErrorKind, Mach3};
use fresa_mach3_oem::protocol::CallResult;
use fresa_mach3_oem::sim::{Mach3Sim, SimConfig};
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
