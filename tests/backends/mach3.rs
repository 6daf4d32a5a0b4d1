//! The `mach3-oem` backend end to end: the server's HTTP API -> plugin -> loopback TCP ->
//! `fresa-mach3-agent --simulate` -> simulated Mach3. The test reads Mach3's DROs and LEDs
//! itself through the agent protocol, so "what Mach3 shows" is checked, not what the plugin
//! says about it.
//!
//! Every test that starts an agent runs twice, once per agent build that ships (`Build`): the
//! Linux binary and the 32-bit Windows 7 `fresa-mach3-agent.exe` under 32-bit Wine (built by
//! `plugins/mach3-oem/build-win7-agent`, which `tests/run` does). A new agent test goes in
//! `on_every_agent!` at the bottom.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_mach3_oem::client::{AgentClient, LinkError};
use fresa_mach3_oem::mach3::{Call, ErrorKind};
use fresa_mach3_oem::protocol::CallResult;
use fresa_tests::{bin_dir, corpus, wait_for, wine, Server};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);
const SECRET: &str = "test-secret-0123456789";
/// 663 lines, G54, M30 at the end; about 410 s of machine time -> about 4 s at 0.01.
const PROGRAM: &str = "fusion-1122_jig_28bit_first.nc";
const TIME_SCALE: f64 = 0.01;

/// Which agent binary a test runs against.
#[derive(Clone, Copy, Debug)]
enum Build {
    /// `target/<profile>/fresa-mach3-agent`, this machine's own build.
    Linux,
    /// `target/i686-win7-windows-gnu/<profile>/fresa-mach3-agent.exe` under 32-bit Wine.
    Win7Wine32,
}

/// A `fresa-mach3-agent --simulate` process; killed when dropped.
struct Agent {
    build: Build,
    child: Child,
    stdin: ChildStdin,
    addr: String,
    _programs: tempfile::TempDir,
}

impl Agent {
    fn start(build: Build, listen: &str) -> Agent {
        Agent::start_with(build, listen, &[])
    }

    /// [`Agent::start`] with more command-line options.
    fn start_with(build: Build, listen: &str, options: &[&str]) -> Agent {
        Agent::start_scaled(build, listen, TIME_SCALE, options)
    }

    /// [`Agent::start_with`] with its own time scale (1.0: real time).
    fn start_scaled(build: Build, listen: &str, time_scale: f64, options: &[&str]) -> Agent {
        let programs = tempfile::tempdir().unwrap();
        let (mut cmd, program_dir) = match build {
            Build::Linux => (
                Command::new(bin_dir().join("fresa-mach3-agent")),
                programs.path().display().to_string(),
            ),
            Build::Win7Wine32 => (
                wine::command32(wine::win7_agent_exe()),
                wine::path(programs.path()),
            ),
        };
        let mut child = cmd
            .args(["--simulate", "--listen", listen, "--time-scale"])
            .arg(time_scale.to_string())
            .arg("--program-dir")
            .arg(program_dir)
            .args(options)
            .env("FRESA_MACH3_SECRET", SECRET)
            .env_remove("FRESA_MACH3_SECRET_FILE")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("start the {build:?} fresa-mach3-agent: {e}"));
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = BufReader::new(stdout).read_line(&mut line);
            let _ = tx.send(line);
        });
        let line = rx.recv_timeout(T).expect("the agent prints its address");
        let addr = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
            .to_string();
        let stdin = child.stdin.take().unwrap();
        Agent {
            build,
            child,
            stdin,
            addr,
            _programs: programs,
        }
    }

    /// The operator presses a button on the (simulated) Mach3 screen.
    fn press(&mut self, code: i16) {
        self.operator(&format!("button {code}"));
    }

    /// An operator action on the simulated Mach3 (see the agent's `--simulate`).
    fn operator(&mut self, action: &str) {
        writeln!(self.stdin, "{action}").unwrap();
        self.stdin.flush().unwrap();
    }

    fn client(&self) -> AgentClient {
        AgentClient::new(self.addr.clone(), SECRET.into(), Duration::from_secs(5))
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Agent {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Reads Mach3 directly: one value per call. The agent's watchdog drops a connection that was
/// quiet for 3 s, so a stale one is replaced once.
fn mach3(client: &mut AgentClient, calls: Vec<Call>) -> Vec<Value> {
    client
        .batch(calls.clone(), false)
        .or_else(|_| client.batch(calls, false))
        .unwrap()
        .into_iter()
        .map(|r| match r {
            CallResult::Ok(v) => v,
            CallResult::Err(e) => panic!("Mach3 call failed: {e}"),
        })
        .collect()
}

fn dro(client: &mut AgentClient, code: i16) -> f64 {
    mach3(client, vec![Call::GetOemDro { code }])[0]
        .as_f64()
        .unwrap()
}

fn led(client: &mut AgentClient, code: i16) -> bool {
    mach3(client, vec![Call::GetOemLed { code }])[0]
        .as_bool()
        .unwrap()
}

fn machine(s: &Server, name: &str, agent: &Agent) -> i64 {
    s.create_machine(&json!({
        "name": name, "backend": "mach3-oem", "max_jog_mm": 20.0,
        "config": {"agent": agent.addr, "secret": SECRET, "poll_hz": 20},
    }))
}

fn command(s: &Server, m: i64, body: Value) -> Value {
    s.post(&format!("/api/v1/machines/{m}/commands"), &body)
        .expect(200)
}

fn jog(s: &Server, m: i64, axis: &str, distance: f64) {
    s.post(
        &format!("/api/v1/machines/{m}/jog"),
        &json!({"axis": axis, "distance": distance, "feed": 600.0}),
    )
    .expect(200);
}

fn pos(st: &Value, kind: &str, axis: &str) -> f64 {
    st[kind][axis].as_f64().unwrap_or(0.0)
}

/// Waits until the machine is idle with work X and Y exactly at the given values.
fn wait_idle_at(s: &Server, m: i64, x: f64, y: f64) -> Value {
    s.wait_status(m, T, &format!("idle at work x {x}, y {y}"), |st| {
        st["state"] == "idle"
            && pos(st, "work_position", "x") == x
            && pos(st, "work_position", "y") == y
    })
}

/// Mach3 starts in reset, like the real one: the machine shows an alarm until reset.
fn reset_to_idle(s: &Server, m: i64) {
    let st = s.wait_machine_state(m, "alarm", T);
    assert!(st["alarm"].as_str().unwrap().contains("reset"), "{st}");
    command(s, m, json!({"command": "reset"}));
    s.wait_machine_state(m, "idle", T);
}

fn jog_zero_and_offsets_drive_mach3_dros_and_restore_the_distance_mode(build: Build) {
    let agent = Agent::start(build, "127.0.0.1:0");
    let mut mach = agent.client();
    let s = Server::start();
    let m = machine(&s, "mach3", &agent);

    // In reset nothing may move: the jog is refused and Mach3 was not touched.
    let st = s.wait_machine_state(m, "alarm", T);
    assert!(st["alarm"].as_str().unwrap().contains("reset"), "{st}");
    let r = s.post(
        &format!("/api/v1/machines/{m}/jog"),
        &json!({"axis": "X", "distance": 1.0}),
    );
    assert_eq!(r.status, 422, "{r:?}");
    assert!(
        r.body["message"].as_str().unwrap().contains("alarm"),
        "{r:?}"
    );
    command(&s, m, json!({"command": "reset"}));
    s.wait_machine_state(m, "idle", T);
    assert!(!led(&mut mach, 800), "reset cleared Mach3's reset LED");

    // Mach3 left in G91 G0 F250 by someone: the jog is exact and puts all of it back.
    mach3(
        &mut mach,
        vec![Call::Code {
            line: "G91 G0 F250".into(),
        }],
    );
    jog(&s, m, "X", 1.5);
    wait_idle_at(&s, m, 1.5, 0.0);
    assert_eq!(dro(&mut mach, 800), 1.5, "X DRO");
    assert!(led(&mut mach, 49), "G91 restored");
    assert_eq!(dro(&mut mach, 819), 0.0, "G0 restored");
    assert_eq!(dro(&mut mach, 818), 250.0, "F250 restored");

    // Now in G90 G1 F300: the jog is still incremental, and G90 G1 F300 come back.
    mach3(
        &mut mach,
        vec![Call::Code {
            line: "G90 G1 F300".into(),
        }],
    );
    jog(&s, m, "Y", -2.25);
    jog(&s, m, "X", 1.25);
    let st = wait_idle_at(&s, m, 2.75, -2.25);
    assert_eq!(pos(&st, "machine_position", "x"), 2.75);
    assert!(!led(&mut mach, 49) && led(&mut mach, 48), "G90 restored");
    assert_eq!(dro(&mut mach, 819), 1.0, "G1 restored");
    assert_eq!(dro(&mut mach, 818), 300.0, "F300 restored");

    // Zero X presses Mach3's zero button: the fixture offset takes the machine position.
    let r = command(&s, m, json!({"command": "zero", "axis": "X"}));
    let g54 = &r["result"]["offsets"]["offsets"][0];
    assert_eq!(g54[0], "G54", "{r}");
    assert_eq!(g54[1]["x"], 2.75, "{r}");
    let st = s.wait_status(m, T, "work x 0 after zero", |st| {
        pos(st, "work_position", "x") == 0.0
    });
    assert_eq!(pos(&st, "work_position", "y"), -2.25, "{st}");
    assert_eq!(dro(&mut mach, 830), 2.75, "X fixture DRO");

    // The active offset is written to the fixture DROs; another one through G10 L2.
    s.put(
        &format!("/api/v1/machines/{m}/offsets/G54"),
        &json!({"x": 10.0}),
    )
    .expect(200);
    assert_eq!(dro(&mut mach, 830), 10.0);
    s.wait_status(m, T, "work x -7.25", |st| {
        pos(st, "work_position", "x") == -7.25
    });
    s.put(
        &format!("/api/v1/machines/{m}/offsets/G55"),
        &json!({"x": 1.5, "z": -3.0}),
    )
    .expect(200);
    assert_eq!(dro(&mut mach, 46), 1.0, "G54 still active in Mach3");
    assert_eq!(dro(&mut mach, 830), 10.0, "G54 untouched");
    command(&s, m, json!({"command": "select_offset", "offset": "G55"}));
    let st = s.wait_status(m, T, "G55 active", |st| st["active_offset"] == "G55");
    assert_eq!(pos(&st, "work_position", "x"), 2.75 - 1.5, "{st}");
    assert_eq!(pos(&st, "work_position", "z"), 3.0, "{st}");
    assert_eq!(dro(&mut mach, 46), 2.0);
    // Reading all offsets visits each fixture and leaves G55 selected.
    let off = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    assert_eq!(off["active"], "G55", "{off}");
    assert_eq!(off["offsets"]["G54"]["x"], 10.0, "{off}");
    assert_eq!(off["offsets"]["G55"]["z"], -3.0, "{off}");
    assert_eq!(dro(&mut mach, 46), 2.0, "G55 still selected in Mach3");

    // A program without M2/M30, over before the first poll sees it run, with trailing
    // comment and blank lines: Mach3 stops on its last active line, which is completion.
    let job = s.upload(m, "short", "G21 G90\nG1 X1 F600\nG1 X2\n(done)\n\n")["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"], 5, "{j}");
    assert_eq!(dro(&mut mach, 800), 2.0);

    // LinuxCNC's O-word control flow passes the upload check, but Mach3 gets the
    // text itself and does not run it: refused naming the line, before anything moves.
    let job = s.upload(m, "o-words", "G21 G90\no1 if [1]\nG1 X3 F600\no1 endif\n")["id"]
        .as_i64()
        .unwrap();
    let r = s.job_action(job, "start");
    assert!(r.status >= 400, "{r:?}");
    assert!(
        r.text.contains("line 2") && r.text.contains("LinuxCNC-only"),
        "{}",
        r.text
    );
    assert_eq!(dro(&mut mach, 800), 2.0, "nothing moved");
    // So does LinuxCNC's G38.2 probe (Mach3 probes with G31).
    let job = s.upload(m, "g38", "G21 G90 F100\nG38.2 Z-5\nM2\n")["id"]
        .as_i64()
        .unwrap();
    let r = s.job_action(job, "start");
    assert!(r.status >= 400, "{r:?}");
    assert!(
        r.text.contains("line 2") && r.text.contains("G38"),
        "{}",
        r.text
    );
    assert_eq!(dro(&mut mach, 800), 2.0, "nothing moved");

    // The A axis: Mach3 turns it (its A DRO), and the status shows it.
    let job = s.upload(m, "rotary", "G21 G90\nG1 X3 A45 F600\nG1 A90\nM30\n")["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "completed", T);
    assert_eq!(dro(&mut mach, 803), 90.0, "A DRO");
    let st = s.wait_status(m, T, "work a 90", |st| {
        pos(st, "work_position", "a") == 90.0
    });
    assert_eq!(pos(&st, "work_position", "x"), 3.0, "{st}");
    let x_before = dro(&mut mach, 800);
    // Cutter compensation passes the upload check with Fresa's tool table, but Mach3 would
    // compensate with its own: refused naming the line, before anything moves.
    s.put(
        &format!("/api/v1/machines/{m}/tools"),
        &json!([{"tool": 1, "diameter_mm": 6.0}]),
    )
    .expect(200);
    let job = s.upload(m, "comp", "G21 G90 F600\nG0 X-10 Y0\nG41 D1 G1 X0\nG1 X5\n")["id"]
        .as_i64()
        .unwrap();
    let r = s.job_action(job, "start");
    assert!(r.status >= 400, "{r:?}");
    assert!(
        r.text.contains("line 3") && r.text.contains("own tool table"),
        "{}",
        r.text
    );
    assert_eq!(dro(&mut mach, 800), x_before, "nothing moved");
    // G10 would change Mach3's fixture table for good: refused the same way.
    let job = s.upload(m, "g10", "G21 G90 F600\nG10 L2 P2 X5\nG1 X4\n")["id"]
        .as_i64()
        .unwrap();
    let r = s.job_action(job, "start");
    assert!(r.status >= 400, "{r:?}");
    assert!(
        r.text.contains("line 2") && r.text.contains("G10"),
        "{}",
        r.text
    );
    assert_eq!(dro(&mut mach, 800), x_before, "nothing moved");
}

fn a_program_runs_to_completion_with_progress_feed_hold_and_reset_toggles_right(build: Build) {
    let mut agent = Agent::start(build, "127.0.0.1:0");
    let mut mach = agent.client();
    let s = Server::start();
    let m = machine(&s, "mach3", &agent);
    reset_to_idle(&s, m);

    let program = std::fs::read(corpus(PROGRAM)).unwrap();
    let job = s.upload(m, "jig", program)["id"].as_i64().unwrap();
    let total = s.job(job)["line_count"].as_i64().unwrap();
    s.job_action(job, "start").expect(200);
    let j = s.wait_job(job, T, "progress", |j| {
        j["state"] == "running" && j["line"].as_i64().unwrap() > 20
    });
    assert!(j["line"].as_i64().unwrap() < total, "{j}");
    assert!(led(&mut mach, 804), "Mach3 runs the program");

    // Feed hold: Mach3 pauses and nothing moves until resumed.
    s.job_action(job, "pause").expect(200);
    s.wait_machine_state(m, "paused", T);
    assert!(led(&mut mach, 805));
    let at = |c: &mut AgentClient| [dro(c, 800), dro(c, 801), dro(c, 802), dro(c, 816)];
    let held = at(&mut mach);
    std::thread::sleep(Duration::from_millis(200)); // observing stillness, not synchronising
    assert_eq!(at(&mut mach), held, "nothing moves in feed hold");
    s.job_action(job, "resume").expect(200);

    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"].as_i64().unwrap(), total, "{j}");
    assert_eq!(j["percent"], 100.0, "{j}");
    assert_eq!(dro(&mut mach, 816), 0.0, "M30 rewound Mach3");
    let st = s.wait_machine_state(m, "idle", T);
    assert!(st["job"].is_null(), "{st}");

    // Cancel mid-run: Mach3 is stopped (Stop button) and the run ends cancelled, not failed.
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "progress of the second run", |j| {
        j["state"] == "running" && j["line"].as_i64().unwrap() > 5
    });
    // The answer comes once it is true: Mach3 no longer runs the program, and no line
    // starts after it.
    let answer = s.job_action(job, "cancel").expect(200);
    assert_eq!(answer["state"], "cancelled", "{answer}");
    assert!(
        !led(&mut mach, 804),
        "Mach3 stopped before the cancel answered"
    );
    let line_at_answer = dro(&mut mach, 816);
    s.wait_machine_state(m, "idle", T);
    assert_eq!(
        dro(&mut mach, 816),
        line_at_answer,
        "no line after the answer"
    );

    // Reset when not in reset must not press Mach3's Reset toggle (that would latch it).
    for _ in 0..2 {
        command(&s, m, json!({"command": "reset"}));
        assert!(!led(&mut mach, 800), "reset never toggles into e-stop");
        assert_eq!(s.status(m)["state"], "idle");
    }
    // The operator hits Reset on the Mach3 screen: alarm; reset clears it, twice is still clear.
    agent.press(1021);
    s.wait_machine_state(m, "alarm", T);
    for _ in 0..2 {
        command(&s, m, json!({"command": "reset"}));
        assert!(!led(&mut mach, 800));
        assert_eq!(s.status(m)["state"], "idle");
    }
}

fn losing_the_agent_mid_job_goes_offline_and_the_job_resumes_later(build: Build) {
    let mut agent = Agent::start(build, "127.0.0.1:0");
    let s = Server::start();
    let m = machine(&s, "mach3", &agent);
    reset_to_idle(&s, m);
    let job = s.upload(m, "jig", std::fs::read(corpus(PROGRAM)).unwrap())["id"]
        .as_i64()
        .unwrap();
    let total = s.job(job)["line_count"].as_i64().unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "progress", |j| j["line"].as_i64().unwrap() > 20);

    agent.kill();
    let st = s.wait_machine_state(m, "offline", T);
    assert!(
        st["reason"].as_str().unwrap().contains("agent"),
        "the reason names the agent: {st}"
    );
    let j = s.wait_job_state(job, "failed", T);
    let stopped_at = j["line"].as_i64().unwrap();
    assert!(stopped_at > 20 && stopped_at < total, "{j}");
    assert!(
        j["run"]["message"].as_str().unwrap().contains("resume"),
        "{j}"
    );
    // The server stays responsive; machine calls fail at once with the reason.
    let r = s.post(
        &format!("/api/v1/machines/{m}/jog"),
        &json!({"axis": "X", "distance": 1.0}),
    );
    assert!(
        r.body["message"].as_str().unwrap().contains("agent"),
        "{r:?}"
    );

    // The agent comes back (Mach3 restarted with it, in reset): the plugin reconnects by itself.
    let agent = Agent::start(agent.build, &agent.addr.clone());
    reset_to_idle(&s, m);
    s.job_action(job, "resume").expect(200);
    let st = s.wait_status(m, T, "running the resumed run", |st| st["line"].is_u64());
    assert!(
        st["line"].as_i64().unwrap() > stopped_at,
        "resumed after line {stopped_at}: {st}"
    );
    let j = s.wait_job_state(job, "completed", T);
    assert_eq!(j["line"].as_i64().unwrap(), total, "{j}");
    drop(agent);
}

/// Mach3 cannot start a file at a line safely from outside (it does not rebuild the modal
/// state at its Line DRO; its own Run from here needs the operator at its screen): a start at
/// a line is refused `unsupported` with that reason, and Mach3 is sent nothing. The run it
/// made is failed, and a resume of it is refused the same way (nothing of it ever ran).
fn a_start_at_a_line_is_refused_unsupported_saying_why(build: Build) {
    let agent = Agent::start(build, "127.0.0.1:0");
    let s = Server::start();
    let m = machine(&s, "mach3", &agent);
    reset_to_idle(&s, m);
    let job = s.upload(m, "jig", std::fs::read(corpus(PROGRAM)).unwrap())["id"]
        .as_i64()
        .unwrap();
    let mut mach = agent.client();
    let line_dro = dro(&mut mach, 816);
    let msg = s
        .post(
            &format!("/api/v1/jobs/{job}/start"),
            &json!({"from_line": 300}),
        )
        .expect_error(422, "unsupported");
    assert!(
        msg.contains("mach3-oem cannot start a program at a line safely")
            && msg.contains("Run from here"),
        "{msg}"
    );
    let j = s.job(job);
    assert_eq!(j["state"], "failed", "{j}");
    assert_eq!(j["run"]["from_line"], 300, "{j}");
    assert_eq!(j["line"], 0, "{j}");
    let msg = s.job_action(job, "resume").expect_error(422, "unsupported");
    assert!(msg.contains("Run from here"), "{msg}");
    // Mach3 got no program (its line DRO was not set) and ran nothing.
    assert_eq!(dro(&mut mach, 816), line_dro);
    assert!(!led(&mut mach, 804), "Mach3 is not running a program");
    assert_eq!(s.status(m)["state"], "idle");
}

fn mach3_closing_shows_offline_with_that_reason_and_recovers(build: Build) {
    let agent = Agent::start(build, "127.0.0.1:0");
    let s = Server::start();
    let m = machine(&s, "mach3", &agent);
    reset_to_idle(&s, m);
    let mut stdin = &agent.stdin;
    writeln!(stdin, "close").unwrap();
    let st = s.wait_machine_state(m, "offline", T);
    assert!(
        st["reason"]
            .as_str()
            .unwrap()
            .contains("Mach3 is not running"),
        "{st}"
    );
    writeln!(stdin, "open").unwrap();
    // Mach3 restarted comes back in reset.
    s.wait_machine_state(m, "alarm", T);
    wait_for(T, "status answers", || Some(s.status(m)));
}

#[test]
fn an_agent_that_never_answers_or_is_absent_gives_offline_not_a_hang() {
    // Accepts connections (the kernel does) but never says hello.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    // Nothing listens here once the listener is dropped.
    let absent = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let s = Server::start();
    for (name, addr, why) in [
        ("silent", silent.local_addr().unwrap().to_string(), "hello"),
        ("absent", absent.to_string(), "agent"),
    ] {
        let m = s.create_machine(&json!({
            "name": name, "backend": "mach3-oem",
            "config": {"agent": addr, "secret": SECRET, "timeout_ms": 300},
        }));
        let st = s.wait_machine_state(m, "offline", T);
        let reason = st["reason"].as_str().unwrap();
        assert!(reason.contains(&addr) && reason.contains(why), "{st}");
        // Commands fail with the reason instead of hanging.
        let r = s.post(
            &format!("/api/v1/machines/{m}/commands"),
            &json!({"command": "cycle_start"}),
        );
        assert!(r.status >= 400, "{r:?}");
        assert!(
            r.body["message"].as_str().unwrap().contains("offline"),
            "{r:?}"
        );
    }
    drop(silent);
}

fn mdi_lines_restore_the_modal_state_and_outputs_switch(build: Build) {
    let agent = Agent::start(build, "127.0.0.1:0");
    let mut mach = agent.client();
    let s = Server::start();
    let m = machine(&s, "mach3", &agent);
    reset_to_idle(&s, m);

    // Mach3 in G90 G1 F300: an incremental rapid MDI line moves and all three come back.
    mach3(
        &mut mach,
        vec![Call::Code {
            line: "G90 G1 F300".into(),
        }],
    );
    s.post(
        &format!("/api/v1/machines/{m}/mdi"),
        &json!({"line": "G91 G0 X2 Y-1"}),
    )
    .expect(200);
    wait_idle_at(&s, m, 2.0, -1.0);
    assert!(!led(&mut mach, 49) && led(&mut mach, 48), "G90 restored");
    assert_eq!(dro(&mut mach, 819), 1.0, "G1 restored");
    assert_eq!(dro(&mut mach, 818), 300.0, "F300 restored");

    // Coolant by the flood buttons, spindle by M3/M5 (toggles: see the read-back test).
    for (name, on) in [("coolant", true), ("spindle", true), ("spindle", false)] {
        let r = command(
            &s,
            m,
            json!({"command": "set_output", "name": name, "on": on}),
        );
        assert_eq!(r["result"], json!({"output": name, "on": on}), "{r}");
    }
    let e = s
        .post(
            &format!("/api/v1/machines/{m}/commands"),
            &json!({"command": "toggle_output", "name": "z_lift"}),
        )
        .expect_error(422, "backend_rejected");
    assert!(e.contains("unsupported"), "{e}");
    // The spindle's MDI also left the modal state alone.
    assert!(!led(&mut mach, 49) && led(&mut mach, 48), "still G90");
    assert_eq!(dro(&mut mach, 818), 300.0, "still F300");
}

/// With Mach3's output LEDs read back, spindle and coolant toggle: each toggle reads the LED,
/// switches the other way, and the status shows what Mach3 shows.
fn spindle_and_coolant_toggle_with_read_back_and_show_in_the_status(build: Build) {
    let agent = Agent::start(build, "127.0.0.1:0");
    let mut mach = agent.client();
    let s = Server::start();
    let m = machine(&s, "mach3-io", &agent);
    reset_to_idle(&s, m);
    let st = s.status(m);
    assert_eq!(st["inputs"]["estop"], false, "{st}");
    assert_eq!(st["inputs"]["limit_x_max"], false, "{st}");
    assert_eq!(st["outputs"]["spindle"], false, "{st}");

    let on = command(
        &s,
        m,
        json!({"command": "toggle_output", "name": "spindle"}),
    );
    assert_eq!(on["result"]["on"], true, "{on}");
    assert!(led(&mut mach, 11), "Mach3's spindle CW LED is lit");
    s.wait_status(m, T, "spindle on", |st| {
        st["outputs"]["spindle"] == true && st["outputs"]["spindle_ccw"] == false
    });
    let off = command(
        &s,
        m,
        json!({"command": "toggle_output", "name": "spindle"}),
    );
    assert_eq!(off["result"]["on"], false, "{off}");
    assert!(!led(&mut mach, 11));
    s.wait_status(m, T, "spindle off", |st| st["outputs"]["spindle"] == false);

    // Someone switches flood on at the Mach3 screen: the status shows it, and a toggle turns
    // it off rather than on.
    mach3(&mut mach, vec![Call::DoOemButton { code: 224 }]);
    s.wait_status(m, T, "flood on", |st| {
        st["outputs"]["coolant_flood"] == true
    });
    let t = command(
        &s,
        m,
        json!({"command": "toggle_output", "name": "coolant"}),
    );
    assert_eq!(t["result"]["on"], false, "{t}");
    assert!(!led(&mut mach, 13), "flood LED out");
}

/// The agent protocol as the shipped binary speaks it (the crate's own `tests/agent.rs` checks
/// the same rules in-process): a wrong secret is refused, a malformed frame is answered and
/// skipped, and a jog ends when its connection is lost or goes quiet, seen from a second
/// connection as Mach3's own `IsMoving`.
fn the_protocol_refuses_bad_secrets_and_frames_and_releases_jogs_of_a_lost_link(build: Build) {
    let mut agent = Agent::start_with(build, "127.0.0.1:0", &["--watchdog-ms", "300"]);
    let mut wrong = AgentClient::new(agent.addr.clone(), "not-the-secret".into(), T);
    match wrong.connect() {
        Err(LinkError::Refused { error, .. }) => assert_eq!(error.kind, ErrorKind::Auth),
        other => panic!("a wrong secret must be refused: {other:?}"),
    }

    let stream = TcpStream::connect(&agent.addr).unwrap();
    let mut r = BufReader::new(stream.try_clone().unwrap());
    let mut w = stream;
    let mut line = String::new();
    r.read_line(&mut line).unwrap();
    let hello: Value = serde_json::from_str(&line).unwrap();
    assert_eq!(hello["agent"], "fresa-mach3-agent", "{hello}");
    let auth = fresa_mach3_oem::protocol::sign(SECRET, hello["nonce"].as_str().unwrap());
    writeln!(w, "{}", json!({"protocol": 1, "auth": auth})).unwrap();
    line.clear();
    r.read_line(&mut line).unwrap();
    assert!(line.contains("\"ok\":true"), "{line}");
    writeln!(w, r#"{{"id": 7, "calls": [{{"op": "launch_mach3"}}]}}"#).unwrap();
    line.clear();
    r.read_line(&mut line).unwrap();
    let v: Value = serde_json::from_str(&line).unwrap();
    assert_eq!(v["id"], 7, "{v}");
    assert_eq!(v["error"]["kind"], "protocol", "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("launch_mach3"),
        "{v}"
    );
    // The connection still works (the simulated Mach3 starts in reset, as the real one does).
    writeln!(w, r#"{{"id": 8, "calls": [{{"op": "is_estop"}}]}}"#).unwrap();
    line.clear();
    r.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), r#"{"id":8,"results":[{"ok":true}]}"#);
    drop((r, w));

    agent.press(1021); // out of the start-up reset, as the operator would
    let mut watcher = agent.client();
    let moving = |c: &mut AgentClient| mach3(c, vec![Call::IsMoving])[0] == json!(true);
    wait_for(T, "the reset released", || {
        (mach3(&mut watcher, vec![Call::IsEstop])[0] == json!(false)).then_some(())
    });
    // Lost: the jogging connection closes.
    let mut jogger = agent.client();
    mach3(
        &mut jogger,
        vec![Call::JogOn {
            axis: 0,
            direction: 0,
        }],
    );
    assert!(moving(&mut watcher), "JogOn X+ moves");
    drop(jogger);
    wait_for(T, "JogOff after the connection closed", || {
        (!moving(&mut watcher)).then_some(())
    });
    // Quiet: the jogging connection stays open but says nothing past the watchdog.
    let mut jogger = agent.client();
    mach3(
        &mut jogger,
        vec![Call::JogOn {
            axis: 1,
            direction: 1,
        }],
    );
    assert!(moving(&mut watcher), "JogOn Y- moves");
    wait_for(T, "JogOff after the watchdog", || {
        (!moving(&mut watcher)).then_some(())
    });
    assert!(dro(&mut watcher, 801) < 0.0, "Y jogged minus");
    drop(jogger);
}

// ---- overrides (issue 26) ----------------------------------------------------------------

/// Forty G1 lines of 20 mm at F600: 80 s of machine time (0.8 s at the agent's time scale,
/// long enough to hold it midway on a loaded machine).
fn feed_program() -> String {
    let mut p = String::from("G21 G90 G54\n");
    for _ in 0..20 {
        p.push_str("G1 X20 F600\nG1 X0\n");
    }
    p.push_str("M30\n");
    p
}

/// Six rapids of 50 mm at the simulator's 5000 mm/min: 3.6 s of machine time.
fn rapid_program() -> String {
    let mut p = String::from("G21 G90 G54\n");
    for _ in 0..3 {
        p.push_str("G0 X50\nG0 X0\n");
    }
    p.push_str("M30\n");
    p
}

/// Runs `job` to completion and answers Mach3's own elapsed-time DRO (814): the run's machine
/// time in the simulator, whatever the host's load.
fn elapsed_of_run(s: &Server, mach: &mut AgentClient, job: i64) -> f64 {
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "completed", T);
    dro(mach, 814)
}

fn overrides_of(st: &Value) -> [f64; 3] {
    ["feed_override", "spindle_override", "rapid_override"].map(|k| st[k].as_f64().unwrap())
}

/// Feed, spindle and rapid overrides go into Mach3's DROs (821, 74, 223) before the answer,
/// the status reads them back, and Mach3 honours them: a run at a 50 % feed override takes
/// twice the machine time (Mach3's elapsed DRO), one whose override changes while it is held
/// mid-run takes the mix, and a rapid override is in force only while Mach3's "override of
/// rapid feeds" toggle is on (switched on by the plugin, off again by the operator on the
/// Mach3 screen: the status then says 100). A machine whose toggle LED code is wrong is refused
/// and nothing changes.
fn overrides_go_to_mach3s_dros_and_slow_its_run(build: Build) {
    let mut agent = Agent::start(build, "127.0.0.1:0");
    let mut mach = agent.client();
    let s = Server::start();
    let m = machine(&s, "mach3", &agent);
    reset_to_idle(&s, m);
    assert_eq!(overrides_of(&s.status(m)), [100.0, 100.0, 100.0]);
    let path = format!("/api/v1/machines/{m}/overrides");

    let feed_job = s.upload(m, "feeds", feed_program())["id"].as_i64().unwrap();
    let full = elapsed_of_run(&s, &mut mach, feed_job);
    assert!((full - 80.0).abs() < 1e-6, "80 s of feed moves: {full}");

    // The latency an operator sees: HTTP request to answer, the DRO already set by then.
    let mut times = Vec::new();
    for k in 0..20 {
        let feed = if k % 2 == 0 { 60.0 } else { 50.0 };
        let t = std::time::Instant::now();
        let r = s
            .post(&path, &json!({"feed": feed, "spindle": 120}))
            .expect(200);
        times.push(t.elapsed());
        assert_eq!(r, json!({"feed": feed, "spindle": 120.0, "rapid": 100.0}));
        assert_eq!(
            dro(&mut mach, 821),
            feed,
            "Mach3's FRO is set when the answer comes"
        );
    }
    times.sort();
    eprintln!(
        "mach3 override: POST /overrides answered in min {:?}, median {:?}, max {:?} ({build:?} agent)",
        times[0],
        times[times.len() / 2],
        times[times.len() - 1]
    );
    assert_eq!(dro(&mut mach, 74), 120.0, "spindle override DRO");
    assert_eq!(overrides_of(&s.status(m)), [50.0, 120.0, 100.0]);
    let half = elapsed_of_run(&s, &mut mach, feed_job);
    assert!(
        (half - 2.0 * full).abs() < 1e-6,
        "{full} s at 100 %, {half} s at 50 %"
    );

    // Changed during a run: held mid-run at 50 %, resumed at 100 %. What was left of the
    // run at 50 % takes half that time.
    s.job_action(feed_job, "start").expect(200);
    s.wait_job(feed_job, T, "past line 3", |j| {
        j["state"] == "running" && j["line"].as_i64().unwrap() > 3
    });
    s.job_action(feed_job, "pause").expect(200);
    s.wait_machine_state(m, "paused", T);
    let held = dro(&mut mach, 814);
    s.post(&path, &json!({"feed": 100})).expect(200);
    assert_eq!(
        s.status(m)["state"],
        "paused",
        "an override does not resume a run"
    );
    s.job_action(feed_job, "resume").expect(200);
    s.wait_job_state(feed_job, "completed", T);
    let mixed = dro(&mut mach, 814);
    let expected = held + (half - held) / 2.0;
    assert!(
        held > 0.0 && (mixed - expected).abs() < 1e-6,
        "held at {held} s of {half}; then at 100 %: {mixed}, expected {expected}"
    );

    // The spindle override scales Mach3's programmed speed.
    s.mdi(m, "M3 S1000").expect(200);
    assert_eq!(dro(&mut mach, 202), 1200.0, "overridden spindle speed");
    s.mdi(m, "M5").expect(200);

    // Rapids: 3.6 s at the rapid rate; a 25 % override switches Mach3's rapid override on.
    let rapid_job = s.upload(m, "rapids", rapid_program())["id"]
        .as_i64()
        .unwrap();
    let rapid_full = elapsed_of_run(&s, &mut mach, rapid_job);
    assert!((rapid_full - 3.6).abs() < 1e-6, "{rapid_full}");
    assert!(!led(&mut mach, 109), "Mach3 starts with rapid override off");
    let r = s.post(&path, &json!({"rapid": 25})).expect(200);
    assert_eq!(r["rapid"], 25.0, "{r}");
    assert!(led(&mut mach, 109), "rapid override switched on");
    assert_eq!(dro(&mut mach, 223), 25.0);
    let slow = elapsed_of_run(&s, &mut mach, rapid_job);
    assert!((slow - 4.0 * rapid_full).abs() < 1e-6, "{slow} s at 25 %");
    // The operator switches rapid override off on the Mach3 screen: the DRO still says 25,
    // but rapids run at full speed again, and the status says what is in force.
    agent.press(287);
    s.wait_status(m, T, "rapid override 100 once off", |st| {
        st["rapid_override"] == 100.0
    });
    assert_eq!(dro(&mut mach, 223), 25.0);
    let again = elapsed_of_run(&s, &mut mach, rapid_job);
    assert!((again - rapid_full).abs() < 1e-6, "{again}");
    s.post(&path, &json!({"rapid": 50})).expect(200);
    assert!(led(&mut mach, 109), "switched on again, not toggled off");
    assert_eq!(overrides_of(&s.status(m)), [100.0, 120.0, 50.0]);

    // A Mach3 whose toggle lamp is not where the config says: the toggle is pressed, does not
    // light the configured LED, is pressed back, and nothing changes.
    agent.press(287); // rapid override off again
    s.wait_status(m, T, "rapid override off", |st| {
        st["rapid_override"] == 100.0
    });
    let odd = s.create_machine(&json!({
        "name": "odd-leds", "backend": "mach3-oem",
        "config": {"agent": agent.addr, "secret": SECRET, "poll_hz": 20,
                   "codes": {"led_rapid_override": 108}},
    }));
    s.wait_machine_state(odd, "idle", T);
    let msg = s
        .post(
            &format!("/api/v1/machines/{odd}/overrides"),
            &json!({"rapid": 25, "feed": 80}),
        )
        .expect_error(422, "backend_rejected");
    assert!(msg.contains("led_rapid_override"), "{msg}");
    assert!(!led(&mut mach, 109), "the toggle was put back");
    assert_eq!(dro(&mut mach, 223), 50.0, "the rapid DRO was put back");
    assert_eq!(dro(&mut mach, 821), 100.0, "no feed override set either");
}

// ---- probing (issue 25) ------------------------------------------------------------------

fn probing_machine(s: &Server, name: &str, agent: &Agent) -> i64 {
    s.create_machine(&json!({
        "name": name, "backend": "mach3-oem", "max_jog_mm": 60.0,
        "max_probe_feed_mm_min": 1200.0,
        "config": {"agent": agent.addr, "secret": SECRET, "poll_hz": 20},
    }))
}

fn z(v: &Value) -> f64 {
    v["z"].as_f64().unwrap_or_else(|| panic!("no z in {v}"))
}

/// A Z touch-off on Mach3: a G31 through the agent down onto a plate whose top is at machine
/// Z -20 (the simulated Mach3's probe input), the trip read back from #2000-#2002, G54 Z set
/// so Z reads the plate's 15 mm there, a 5 mm retract. Mach3's own DROs say the same, and
/// the modal state the operator left (G91 G0 F250) is back. Overshoots at three feeds are
/// printed (the README's figures).
fn a_z_touch_off_on_mach3_sets_g54_from_g31s_trip(build: Build) {
    let agent = Agent::start_with(build, "127.0.0.1:0", &["--probe", "z<=-20"]);
    let mut mach = agent.client();
    let s = Server::start();
    let m = probing_machine(&s, "mach3-probe", &agent);
    reset_to_idle(&s, m);
    let st = s.status(m);
    assert_eq!(
        st["inputs"]["probe"], false,
        "Mach3's probe input (LED 825): {st}"
    );
    mach3(
        &mut mach,
        vec![Call::Code {
            line: "G91 G0 F250".into(),
        }],
    );
    let r = s
        .post(
            &format!("/api/v1/machines/{m}/touch-off"),
            &json!({"axis": "Z", "plate_mm": 15, "distance": 50, "feed": 300, "retract_mm": 5}),
        )
        .expect(200);
    assert!(
        (z(&r["trip"]) + 20.0).abs() < 1e-9,
        "trip at the plate: {r}"
    );
    let overshoot = r["overshoot_mm"].as_f64().unwrap();
    assert!(
        overshoot > 0.0 && overshoot < 0.1,
        "Mach3 stops a little past the trip: {r}"
    );
    assert!(
        (z(&r["after"]) + 35.0).abs() < 1e-9,
        "G54 Z = -20 - 15: {r}"
    );
    assert!(
        (z(&r["work_position"]) - (20.0 - overshoot)).abs() < 1e-6,
        "5 mm above the trip's 15: {r}"
    );
    // Mach3 itself: the fixture DRO, the work Z DRO, the trip parameter, the modal state.
    assert!((dro(&mut mach, 832) + 35.0).abs() < 1e-9, "G54 Z in Mach3");
    assert!((dro(&mut mach, 802) - (20.0 - overshoot)).abs() < 1e-6);
    let trip = mach3(&mut mach, vec![Call::GetVar { var: 2002 }])[0]
        .as_f64()
        .unwrap();
    assert!(
        (trip + 20.0).abs() < 1e-9,
        "#2002 (work Z then: G54 was 0) {trip}"
    );
    assert!(led(&mut mach, 49), "G91 put back");
    assert_eq!(dro(&mut mach, 819), 0.0, "G0 put back, not G31");
    assert_eq!(dro(&mut mach, 818), 250.0, "F250 put back");
    let st = s.status(m);
    assert_eq!(st["state"], "idle", "{st}");
    assert_eq!(st["inputs"]["probe"], false, "off the plate: {st}");
    let stored = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    assert!(
        (z(&stored["offsets"]["G54"]) + 35.0).abs() < 1e-9,
        "{stored}"
    );

    // Trip to stop at three feeds (the scripting endpoint, from 5 mm above the plate).
    for feed in [100.0, 300.0, 1200.0] {
        let r = s
            .post(
                &format!("/api/v1/machines/{m}/probe"),
                &json!({"axis": "Z", "toward": "-", "distance": 10, "feed": feed}),
            )
            .expect(200);
        assert_eq!(r["outcome"], "tripped", "{r}");
        assert!((z(&r["trip"]) + 20.0).abs() < 1e-9, "{r}");
        eprintln!(
            "mach3 probe at {feed} mm/min: overshoot {:.4} mm ({build:?} agent)",
            r["overshoot_mm"].as_f64().unwrap()
        );
        s.jog(m, "Z", 5.0).expect(200);
        s.wait_status(m, T, "up off the plate", |st| {
            st["state"] == "idle" && st["inputs"]["probe"] == false
        });
    }
}

/// A probe that runs its whole distance touches nothing and changes nothing; onto the plate
/// it trips; already touching it is refused, as is probing for the release (Mach3's G31 has
/// none). The plate is moved by the operator between them.
fn a_mach3_probe_that_never_touches_changes_nothing(build: Build) {
    let mut agent = Agent::start_with(build, "127.0.0.1:0", &["--probe", "z<=-80"]);
    let mut mach = agent.client();
    let s = Server::start();
    let m = probing_machine(&s, "mach3-far", &agent);
    reset_to_idle(&s, m);
    let msg = s
        .post(
            &format!("/api/v1/machines/{m}/touch-off"),
            &json!({"axis": "Z", "plate_mm": 15, "distance": 30, "feed": 600}),
        )
        .expect_error(422, "probe_not_tripped");
    assert!(msg.contains("30 mm"), "{msg}");
    assert_eq!(dro(&mut mach, 832), 0.0, "no offset changed in Mach3");
    assert_eq!(dro(&mut mach, 802), -30.0, "ran its whole distance");
    let probe = format!("/api/v1/machines/{m}/probe");
    let r = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "-", "distance": 10, "feed": 600}),
        )
        .expect(200);
    assert_eq!(r["outcome"], "not_tripped", "{r}");
    assert!(r["trip"].is_null(), "{r}");
    assert!((z(&r["position"]) + 40.0).abs() < 1e-9, "{r}");
    let r = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "-", "distance": 50, "feed": 600}),
        )
        .expect(200);
    assert_eq!(r["outcome"], "tripped", "{r}");
    assert!((z(&r["trip"]) + 80.0).abs() < 1e-9, "{r}");
    s.wait_status(m, T, "the probe input lit", |st| {
        st["inputs"]["probe"] == true
    });
    let msg = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "-", "distance": 5, "feed": 600}),
        )
        .expect_error(409, "probe_already_in_state");
    assert!(msg.contains("825"), "{msg}");
    let msg = s
        .post(
            &probe,
            &json!({"axis": "Z", "toward": "+", "distance": 5, "feed": 600, "until": "release"}),
        )
        .expect_error(422, "probe_unsupported");
    assert!(msg.contains("G31") && msg.contains("release"), "{msg}");
    // The operator takes the plate away: the input goes out.
    agent.operator("probe off");
    s.wait_status(m, T, "the probe input out", |st| {
        st["inputs"]["probe"] == false
    });
    assert!(!led(&mut mach, 49) && led(&mut mach, 48), "still G90");
    assert_eq!(
        dro(&mut mach, 819),
        0.0,
        "G0 (Mach3's start-up mode), not G31"
    );
}

/// STOP during a probe on Mach3 stops it: the touch-off answers `stopped` once Mach3 no
/// longer moves, far from the end, no offset changes, and the modal state is put back.
fn stop_during_a_mach3_probe_stops_it_and_changes_nothing(build: Build) {
    // Real time: the probe lasts 10 s, long enough to stop it midway.
    let mut agent = Agent::start_scaled(build, "127.0.0.1:0", 1.0, &["--probe", "z<=-95"]);
    let mut mach = agent.client();
    let s = std::sync::Arc::new(Server::start());
    let m = probing_machine(&s, "mach3-stop", &agent);
    reset_to_idle(&s, m);
    let prober = {
        let s = s.clone();
        std::thread::spawn(move || {
            s.post(
                &format!("/api/v1/machines/{m}/touch-off"),
                &json!({"axis": "Z", "plate_mm": 10, "distance": 50, "feed": 300}),
            )
        })
    };
    s.wait_status(m, T, "probing down", |st| {
        st["state"] == "jogging" && z(&st["machine_position"]) < -0.5
    });
    assert_eq!(dro(&mut mach, 819), 31.0, "Mach3 runs a G31");
    s.command(m, "stop", json!({})).expect(200);
    let msg = prober.join().unwrap().expect_error(409, "stopped");
    assert!(msg.contains("stopped"), "{msg}");
    assert!(!mach3(&mut mach, vec![Call::IsMoving])[0].as_bool().unwrap());
    let st = s.status(m);
    assert_eq!(st["state"], "idle", "{st}");
    assert!(z(&st["machine_position"]) > -40.0, "stopped midway: {st}");
    assert_eq!(dro(&mut mach, 832), 0.0, "no offset changed");
    assert_eq!(dro(&mut mach, 819), 0.0, "G31 replaced by the G0 found");

    // In real time, how long after the trip the answer comes: the plate 2 mm below, probed
    // at 300 mm/min (0.4 s to the trip, then Mach3's stop); the rest is Fresa's part (the
    // poll that sees the motion end, reading the trip, the HTTP answer).
    let start = z(&st["machine_position"]);
    // The plate moved in two steps the status shows, so it is in place before the request.
    agent.operator("probe z<=1000");
    s.wait_status(m, T, "the probe input lit", |st| {
        st["inputs"]["probe"] == true
    });
    agent.operator(&format!("probe z<={}", start - 2.0));
    s.wait_status(m, T, "the probe input out", |st| {
        st["inputs"]["probe"] == false
    });
    let t = std::time::Instant::now();
    let r = s
        .post(
            &format!("/api/v1/machines/{m}/probe"),
            &json!({"axis": "Z", "toward": "-", "distance": 5, "feed": 300}),
        )
        .expect(200);
    let answered = t.elapsed().as_secs_f64();
    assert_eq!(r["outcome"], "tripped", "{r}");
    let to_trip = (start - z(&r["trip"])) / 5.0;
    eprintln!(
        "mach3 probe in real time: trip {to_trip:.3} s after the request, answered after \
         {answered:.3} s: {:.0} ms from the trip to the answer ({build:?} agent, poll 20 Hz)",
        (answered - to_trip) * 1000.0
    );
}

/// `mod NAME { linux, win7_32bit_wine }`: the test `NAME(build)` against each agent build.
macro_rules! on_every_agent {
    ($($name:ident),* $(,)?) => {$(
        mod $name {
            #[test]
            fn linux() {
                super::$name(super::Build::Linux)
            }
            #[test]
            fn win7_32bit_wine() {
                super::$name(super::Build::Win7Wine32)
            }
        }
    )*};
}

on_every_agent!(
    the_protocol_refuses_bad_secrets_and_frames_and_releases_jogs_of_a_lost_link,
    jog_zero_and_offsets_drive_mach3_dros_and_restore_the_distance_mode,
    a_program_runs_to_completion_with_progress_feed_hold_and_reset_toggles_right,
    losing_the_agent_mid_job_goes_offline_and_the_job_resumes_later,
    a_start_at_a_line_is_refused_unsupported_saying_why,
    mach3_closing_shows_offline_with_that_reason_and_recovers,
    mdi_lines_restore_the_modal_state_and_outputs_switch,
    spindle_and_coolant_toggle_with_read_back_and_show_in_the_status,
    overrides_go_to_mach3s_dros_and_slow_its_run,
    a_z_touch_off_on_mach3_sets_g54_from_g31s_trip,
    a_mach3_probe_that_never_touches_changes_nothing,
    stop_during_a_mach3_probe_stops_it_and_changes_nothing,
);
