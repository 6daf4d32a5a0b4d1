//! MPG pendants end to end: the real `fresa` server, the real `mpg-pendant` transport plugin,
//! the real `mpg-pendant-sim` binary playing the handwheel, and the sim machine.

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[cfg(target_os = "linux")]
use fresa_plugin_api::priority::nice_in_stat;
use fresa_tests::{bin_dir, corpus, wait_for, Server, SseEvent};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

const T: Duration = Duration::from_secs(60);

/// A running `mpg-pendant-sim`, driven through its stdin; its stdout lines are collected.
struct PendantSim {
    child: Child,
    stdin: ChildStdin,
    rx: mpsc::Receiver<String>,
    /// Every line printed so far.
    seen: Vec<String>,
    addr: String,
}

impl PendantSim {
    fn start() -> PendantSim {
        Self::start_with(&["--quiet-polls"])
    }

    fn start_with(args: &[&str]) -> PendantSim {
        let mut child = Command::new(bin_dir().join("mpg-pendant-sim"))
            .args(["--listen", "127.0.0.1:0"])
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("start mpg-pendant-sim");
        let stdin = child.stdin.take().unwrap();
        let out = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(out).lines() {
                let Ok(l) = l else { return };
                if tx.send(l).is_err() {
                    return;
                }
            }
        });
        let first = rx.recv_timeout(T).expect("sim prints where it listens");
        let addr = first
            .strip_prefix("listening on ")
            .expect(&first)
            .to_string();
        PendantSim {
            child,
            stdin,
            rx,
            seen: vec![first],
            addr,
        }
    }

    /// Waits for a printed line matching `pred` (also among lines already printed after `from`).
    #[track_caller]
    fn wait_line_from(&mut self, from: usize, what: &str, pred: impl Fn(&str) -> bool) -> usize {
        let deadline = Instant::now() + T;
        loop {
            if let Some(i) = self.seen[from..].iter().position(|l| pred(l)) {
                return from + i;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(l) => self.seen.push(l),
                Err(_) => panic!("sim never printed {what}; saw {:?}", self.seen),
            }
        }
    }

    /// Runs one command and waits for its `ok`.
    #[track_caller]
    fn cmd(&mut self, line: &str) {
        let from = self.seen.len();
        writeln!(self.stdin, "{line}").unwrap();
        self.stdin.flush().unwrap();
        let i = self.wait_line_from(from, &format!("ok {line}"), |l| {
            l == format!("ok {line}") || l.starts_with(&format!("error {line}"))
        });
        assert!(self.seen[i].starts_with("ok "), "{}", self.seen[i]);
    }

    fn received(&self, prefix: &str) -> usize {
        self.received_since(0, prefix)
    }

    fn received_since(&self, from: usize, prefix: &str) -> usize {
        self.seen[from..]
            .iter()
            .filter(|l| l.starts_with(&format!("recv {prefix}")))
            .count()
    }

    /// Waits until `n` frames starting with `prefix` were received after line `from`.
    #[track_caller]
    fn wait_received_since(&mut self, from: usize, prefix: &str, n: usize) {
        let deadline = Instant::now() + T;
        while self.received_since(from, prefix) < n {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(l) => self.seen.push(l),
                Err(_) => panic!(
                    "sim received {} of {n} {prefix} frames after line {from}; saw {:?}",
                    self.received_since(from, prefix),
                    &self.seen[from..]
                ),
            }
        }
    }
}

impl Drop for PendantSim {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn add_pendant(s: &Server, name: &str, addr: &str, machine: Option<i64>, config: Value) -> i64 {
    s.post(
        "/api/v1/pendants",
        &json!({"name": name, "address": addr, "machine": machine, "dialect": "firmware", "config": config}),
    )
    .expect(201)["id"]
        .as_i64()
        .unwrap()
}

fn wait_connected(s: &Server, id: i64, connected: bool) {
    wait_for(T, &format!("pendant {id} connected={connected}"), || {
        let p = s.get(&format!("/api/v1/pendants/{id}")).expect(200);
        (p["connected"] == connected).then_some(())
    });
}

fn work(s: &Server, m: i64) -> [f64; 4] {
    let st = s.status(m);
    let w = &st["work_position"];
    ["x", "y", "z", "a"].map(|k| w[k].as_f64().unwrap())
}

#[track_caller]
fn wait_work(s: &Server, m: i64, what: &str, pred: impl Fn([f64; 4]) -> bool) -> [f64; 4] {
    let st = s.wait_status(m, T, what, |st| {
        st["state"] == "idle"
            && pred(["x", "y", "z", "a"].map(|k| st["work_position"][k].as_f64().unwrap()))
    });
    ["x", "y", "z", "a"].map(|k| st["work_position"][k].as_f64().unwrap())
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-9
}

/// Waits for the persisted event matching `pred`, replaying the log from the start.
#[track_caller]
fn wait_event(s: &Server, what: &str, pred: impl Fn(&SseEvent) -> bool) -> SseEvent {
    let stream = s.events("", Some(0));
    stream.until(T, what, |e| pred(e)).pop().unwrap()
}

/// The firmware's "Set cero" routine (0.0001-step Z- frames until the plate closes, then
/// `ZeroZ`) with a 15 mm plate: Z reads 15 where the plate closed, on the status and the LCD,
/// and the touch-off is in the audit log with the offset before and after. A `ZeroZ` after an
/// ordinary wheel move still zeroes; a plate thickness that is not one is refused.
#[test]
fn set_cero_on_a_15_mm_touch_plate_leaves_z_reading_15() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    for bad in [json!(0), json!(-1), json!(150), json!("15")] {
        let r = s.post(
            "/api/v1/pendants",
            &json!({"name": "bad", "address": "127.0.0.1:9", "config": {"touch_plate_mm": bad}}),
        );
        let msg = r.expect_error(422, "invalid_field");
        assert!(msg.contains("config.touch_plate_mm"), "{msg}");
    }
    let mut sim = PendantSim::start();
    let p = add_pendant(
        &s,
        "wheel",
        &sim.addr,
        Some(m),
        json!({"touch_plate_mm": 15}),
    );
    wait_connected(&s, p, true);

    // The plate's top is 0.5 mm below where the tool starts: 50 steps of 0.01 mm.
    sim.cmd("set-cero -0.5");
    let w = wait_work(&s, m, "Z reads the plate's thickness", |w| {
        close(w[2], 15.0)
    });
    assert!(
        close(w[0], 0.0) && close(w[1], 0.0),
        "only Z changed: {w:?}"
    );
    let st = s.status(m);
    let machine_z = st["machine_position"]["z"].as_f64().unwrap();
    assert!(close(machine_z, -0.5), "the tool stayed on the plate: {st}");
    sim.wait_line_from(0, "Z 15 on the LCD", |l| {
        l == "recv N51E+00000.0000x+00000.0000y+00015.0000z+00000.0000aF"
    });
    let e = wait_event(&s, "the touch-off", |e| e.event == "machine.touch_off");
    assert_eq!(e.data["actor"], format!("pendant:{p}"), "{:?}", e.data);
    let d = &e.data["data"];
    assert_eq!(
        (d["axis"].as_str(), d["plate_mm"].as_f64()),
        (Some("Z"), Some(15.0)),
        "{d}"
    );
    assert!(close(d["before"]["z"].as_f64().unwrap(), 0.0), "{d}");
    // The offset that makes Z read 15 at machine Z -0.5 (the sim reads work = machine - offset).
    assert!(close(d["after"]["z"].as_f64().unwrap(), -15.5), "{d}");
    let offsets = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    assert!(
        close(offsets["offsets"]["G54"]["z"].as_f64().unwrap(), -15.5),
        "the store keeps the new offset: {offsets}"
    );

    // ZeroZ after an ordinary wheel move (not the routine's 0.0001 steps) zeroes Z, plate or not.
    sim.cmd("jog Z -3 0.1");
    wait_work(&s, m, "z = 14.7", |w| close(w[2], 14.7));
    sim.cmd("key ZeroZ");
    wait_work(&s, m, "z zeroed", |w| close(w[2], 0.0));
}

#[test]
fn wheel_keys_macros_and_the_lcd_drive_the_bound_machine() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    // The hello went out in the firmware dialect.
    sim.wait_line_from(0, "the hello frame", |l| l.starts_with("recv N04Conected"));

    // Wheel: exactly count x step on the selected axis.
    sim.cmd("jog X 250 0.01");
    wait_work(&s, m, "x = 2.5", |w| close(w[0], 2.5));
    sim.cmd("jog Y -3 1");
    let w = wait_work(&s, m, "y = -3", |w| close(w[1], -3.0));
    assert!(close(w[0], 2.5), "{w:?}");
    // The LCD's N0451 poll is answered from the cache the core pushes.
    sim.wait_line_from(0, "positions on the LCD", |l| {
        l == "recv N51E+00002.5000x-00003.0000y+00000.0000z+00000.0000aF"
    });

    // Touch plate "Set cero": small Z steps down, then ZeroZ.
    for _ in 0..5 {
        sim.cmd("jog Z -100 0.0001");
    }
    wait_work(&s, m, "z = -0.05", |w| close(w[2], -0.05));
    sim.cmd("key ZeroZ");
    wait_work(&s, m, "work z zeroed", |w| close(w[2], 0.0));
    let st = s.status(m);
    assert!(
        close(st["machine_position"]["z"].as_f64().unwrap(), -0.05),
        "{st}"
    );

    // Zero all, then move and go home (work zero).
    sim.cmd("key Zero");
    wait_work(&s, m, "all zero", |w| w.iter().all(|v| close(*v, 0.0)));
    sim.cmd("jog X 10 0.1");
    wait_work(&s, m, "x = 1", |w| close(w[0], 1.0));
    sim.cmd("key HOME");
    wait_work(&s, m, "back at work zero", |w| {
        w.iter().all(|v| close(*v, 0.0))
    });
    for k in ["ZeroX", "ZeroY", "ZeroA"] {
        sim.cmd(&format!("key {k}"));
    }

    // Macros: M1 configured through the API, M2 left unassigned.
    s.send(
        s.req(reqwest::Method::PATCH, &format!("/api/v1/pendants/{p}"))
            .json(&json!({"macros": {"M1": {"type": "jog", "axis": "A", "distance": 2.0}}})),
    )
    .expect(200);
    assert_eq!(
        s.get(&format!("/api/v1/pendants/{p}")).expect(200)["macros"]["M1"]["axis"],
        "A"
    );
    sim.cmd("key M1");
    wait_work(&s, m, "a = 2 from M1", |w| close(w[3], 2.0));
    sim.cmd("key M2");
    let refused = wait_event(&s, "M2 refused", |e| {
        e.event == "pendant.refused" && e.data["data"]["code"] == "macro_unassigned"
    });
    assert_eq!(refused.data["actor"], format!("pendant:{p}"));

    // Rebind to a slower machine for the program keys: Start runs the newest job, Pause holds
    // it, Start resumes it, Stop ends it (4000 mm at 600 mm/min, time scale 0.05: ~20 s).
    let slow = s.sim("slow", 0.05).id;
    s.send(
        s.req(reqwest::Method::PATCH, &format!("/api/v1/pendants/{p}"))
            .json(&json!({"machine": slow})),
    )
    .expect(200);
    let job = s.upload(slow, "long", fresa_tests::back_and_forth(4000, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    sim.cmd("key Rewind");
    sim.cmd("key Start");
    let started = wait_event(&s, "job started by the pendant", |e| {
        e.event == "job.state" && e.job() == Some(job) && e.state() == Some("running")
    });
    assert_eq!(started.data["actor"], format!("pendant:{p}"));
    sim.cmd("key Pause");
    s.wait_job_state(job, "paused", T);
    sim.cmd("key Start");
    s.wait_job_state(job, "running", T);
    sim.cmd("key Stop");
    s.wait_job_state(job, "cancelled", T);
    sim.cmd("key Reset");

    // Every action is in the audit log under the pendant's id.
    let actor = format!("pendant:{p}");
    let stream = s.events("", Some(0));
    let seen = stream.until(T, "the reset command", |e| {
        e.event == "machine.command" && e.data["data"]["command"] == "reset"
    });
    let by_pendant: Vec<&SseEvent> = seen.iter().filter(|e| e.data["actor"] == actor).collect();
    // Wheel counts that arrive while the machine still jogs join into one jog, so the number
    // of jogs may vary; the distance per axis may not.
    let mut moved = std::collections::BTreeMap::<String, f64>::new();
    for e in by_pendant.iter().filter(|e| e.event == "machine.jog") {
        let d = &e.data["data"];
        *moved
            .entry(d["axis"].as_str().unwrap().to_string())
            .or_default() += d["distance"].as_f64().unwrap();
    }
    let want = [("A", 2.0), ("X", 2.5 + 1.0), ("Y", -3.0), ("Z", -0.05)];
    assert_eq!(
        moved.len(),
        want.len(),
        "wheel jogs and the M1 jog: {moved:?}"
    );
    for (axis, d) in want {
        assert!((moved[axis] - d).abs() < 1e-9, "{axis}: {moved:?}");
    }
    let commands: Vec<String> = by_pendant
        .iter()
        .filter(|e| e.event == "machine.command")
        .map(|e| {
            let d = &e.data["data"];
            format!(
                "{}{}",
                d["command"].as_str().unwrap(),
                d["axis"]
                    .as_str()
                    .map(|a| format!(" {a}"))
                    .unwrap_or_default()
            )
        })
        .collect();
    assert_eq!(
        commands,
        [
            "zero Z",
            "zero",
            "go_to_zero",
            "zero X",
            "zero Y",
            "zero A",
            "stop",
            "reset"
        ]
    );
    let job_states: Vec<&str> = by_pendant
        .iter()
        .filter(|e| e.event == "job.state")
        .map(|e| e.state().unwrap())
        .collect();
    assert_eq!(
        job_states,
        ["running", "paused", "running"],
        "start, pause, resume"
    );
    assert!(by_pendant.iter().any(|e| e.event == "pendant.rewind"));
    assert!(by_pendant.iter().any(|e| e.event == "pendant.connected"));
}

#[test]
fn jogs_over_the_limit_unbound_pendants_and_the_document_dialect_move_nothing() {
    let s = Server::start();
    let m = s.sim_with("mill", 0.0, json!({"max_jog_mm": 5.0})).id;
    let mut sim = PendantSim::start();
    let p = s
        .post(
            "/api/v1/pendants",
            &json!({"name": "w", "address": sim.addr, "machine": m, "dialect": "document",
                    "config": {"heartbeat_ms": 50}}),
        )
        .expect(201)["id"]
        .as_i64()
        .unwrap();
    wait_connected(&s, p, true);
    sim.wait_line_from(0, "the document hello", |l| l.starts_with("recv N54"));
    sim.wait_line_from(0, "a document heartbeat", |l| l.starts_with("recv N55Vivo"));

    // 600 x 0.01 = 6 mm > 5 mm: refused, not clamped.
    sim.cmd("jog X 600 0.01");
    let e = wait_event(&s, "jog refused", |e| e.event == "pendant.refused");
    assert_eq!(e.data["data"]["code"], "jog_too_far", "{e:?}");
    assert!(
        e.data["data"]["reason"].as_str().unwrap().contains("5 mm"),
        "{e:?}"
    );
    // A following allowed jog proves the refused one never moved.
    sim.cmd("jog X 100 0.01");
    let w = wait_work(&s, m, "x = 1", |w| close(w[0], 1.0));
    assert!(close(w[0], 1.0), "{w:?}");

    // Unbind: the wheel moves nothing.
    s.send(
        s.req(reqwest::Method::PATCH, &format!("/api/v1/pendants/{p}"))
            .json(&json!({"machine": null})),
    )
    .expect(200);
    assert_eq!(
        s.get("/api/v1/pendants").expect(200)[0]["machine"],
        Value::Null
    );
    sim.cmd("jog X 100 0.01");
    sim.cmd("key Zero");
    let e = wait_event(&s, "unbound refusal", |e| {
        e.event == "pendant.refused"
            && e.data["data"]["code"] == "not_bound"
            && e.data["data"]["input"]["key"] == "zero"
    });
    assert_eq!(e.data["actor"], format!("pendant:{p}"));
    assert!(close(work(&s, m)[0], 1.0));

    // Bad API input is named.
    let msg = s
        .post(
            "/api/v1/pendants",
            &json!({"name": "x", "address": "h:1", "dialect": "klingon"}),
        )
        .expect_error(422, "invalid_field");
    assert!(msg.contains("dialect"), "{msg}");
    let msg = s
        .post(
            "/api/v1/pendants",
            &json!({"name": "x", "address": "h:1", "config": {"heartbeat": 5}}),
        )
        .expect_error(422, "invalid_config");
    assert!(msg.contains("heartbeat"), "{msg}");
    let msg = s
        .post(
            "/api/v1/pendants",
            &json!({"name": "x", "address": "h:1", "machine": 999}),
        )
        .expect_error(422, "unknown_machine");
    assert!(msg.contains("999"), "{msg}");
    let msg = s
        .post("/api/v1/pendants", &json!({"name": "w", "address": "h:1"}))
        .expect_error(409, "name_taken");
    assert!(msg.contains("pendant named \"w\""), "{msg}");
    let msg = s
        .post("/api/v1/pendants", &json!({"name": "  ", "address": "h:1"}))
        .expect_error(422, "invalid_field");
    assert!(msg.contains("`name`"), "{msg}");
    assert_eq!(
        s.get("/api/v1/pendants")
            .expect(200)
            .as_array()
            .unwrap()
            .len(),
        1
    );

    // Deleting a pendant closes its link.
    let before = sim.seen.len();
    s.send(s.req(reqwest::Method::DELETE, &format!("/api/v1/pendants/{p}")))
        .expect(204);
    sim.wait_line_from(before, "the link closed", |l| l.starts_with("disconnected"));
    assert!(s
        .get("/api/v1/pendants")
        .expect(200)
        .as_array()
        .unwrap()
        .is_empty());
    s.get(&format!("/api/v1/pendants/{p}"))
        .expect_error(404, "unknown_pendant");
}

fn normalised(text: &str) -> String {
    let mut t = text.replace("\r\n", "\n");
    if !t.ends_with('\n') {
        t.push('\n');
    }
    t
}

#[test]
fn a_40k_line_upload_becomes_a_job_identical_to_the_file_and_then_n53() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    let file = corpus("cncjs-tball-pocket.gcode");
    // No gaps (a test cannot wait 40 minutes): lines end with \n so reads may merge them.
    sim.cmd(&format!("upload {} gap=0 end=lf", file.display()));
    sim.wait_line_from(0, "N53", |l| {
        l == "recv N53Confirm:Gcode-load*******************************F"
    });
    let jobs = s.get(&format!("/api/v1/jobs?machine={m}")).expect(200);
    let jobs = jobs.as_array().unwrap();
    assert_eq!(jobs.len(), 1, "{jobs:?}");
    assert_eq!(jobs[0]["source"], format!("pendant:{p}"));
    let id = jobs[0]["id"].as_i64().unwrap();
    let stored = s.get(&format!("/api/v1/jobs/{id}/gcode")).text;
    let original = std::fs::read_to_string(&file).unwrap();
    assert!(
        stored == normalised(&original),
        "stored program differs from the file"
    );
    assert_eq!(jobs[0]["line_count"], original.lines().count() as i64);
    assert_eq!(
        jobs[0]["sha256"],
        fresa_tests::sha256_hex(stored.as_bytes())
    );
}

#[test]
fn firmware_paced_upload_with_n_lines_and_count_mismatches() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    let dir = tempfile::tempdir().unwrap();
    let prog = dir.path().join("p.nc");
    let text = "G21 G90\nN10 G1 X5 F300\nN20 G1 Y5\nN0451 G0 Z1\nM2\n";
    std::fs::write(&prog, text).unwrap();

    // More lines than declared, then a wrong character count: no job, no N53, an event saying
    // why. (Fewer lines than declared are blank lines the firmware does not send: see below.)
    sim.cmd(&format!("upload {} gap=0 end=lf lines+=-1", prog.display()));
    let e = wait_event(&s, "line count rejection", |e| {
        e.event == "pendant.upload_rejected"
    });
    assert!(
        e.data["data"]["reason"]
            .as_str()
            .unwrap()
            .contains("more lines than the 4 its N03START declared"),
        "{e:?}"
    );
    sim.cmd(&format!("upload {} gap=0 end=lf chars+=3", prog.display()));
    let e = wait_event(&s, "char count rejection", |e| {
        e.event == "pendant.upload_rejected" && e.data["data"]["code"] == "char_count_mismatch"
    });
    assert!(
        e.data["data"]["reason"]
            .as_str()
            .unwrap()
            .contains("declared"),
        "{e:?}"
    );
    s.assert_no_jobs();
    assert_eq!(sim.received("N53"), 0);

    // Like the firmware: one send per line, no newline, lines starting with N. The end of a read
    // is the end of a line; gaps a bit above the firmware's 50-70 ms keep a loaded test machine
    // from merging two sends into one read.
    sim.cmd(&format!("upload {} gap=120-150 end=none", prog.display()));
    sim.wait_line_from(0, "N53", |l| l.starts_with("recv N53Confirm"));
    assert_eq!(sim.received("N53"), 1);
    let jobs = s.get("/api/v1/jobs").expect(200);
    let id = jobs[0]["id"].as_i64().unwrap();
    assert_eq!(s.get(&format!("/api/v1/jobs/{id}/gcode")).text, text);
}

#[test]
fn a_dropped_link_reconnects_and_a_lost_pendant_stops_its_jog() {
    let s = Server::start();
    // Real time: a 40 mm jog at 1000 mm/min takes 2.4 s, long enough to lose the pendant mid-way.
    let m = s.sim("mill", 1.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(
        &s,
        "wheel",
        &sim.addr,
        Some(m),
        json!({"backoff_max_ms": 200}),
    );
    wait_connected(&s, p, true);

    // The server notices a dropped link and reconnects by itself.
    let first = sim.wait_line_from(0, "the first connection", |l| l.starts_with("connected"));
    sim.cmd("drop");
    sim.wait_line_from(first + 1, "a second connection", |l| {
        l.starts_with("connected")
    });
    wait_event(&s, "lost event", |e| {
        e.event == "pendant.lost" && e.data["data"]["pendant"] == p
    });
    wait_connected(&s, p, true);
    sim.cmd("jog X 1 0.1");
    wait_work(&s, m, "x = 0.1 after reconnect", |w| close(w[0], 0.1));

    // Lose the pendant mid-jog: the jog it started is stopped.
    sim.cmd("jog X 400 0.1");
    s.wait_machine_state(m, "jogging", T);
    drop(sim);
    let lost = wait_event(&s, "lost with stop", |e| {
        e.event == "pendant.lost" && e.data["data"]["stopped"] == true
    });
    assert_eq!(lost.data["actor"], format!("pendant:{p}"));
    let w = wait_work(&s, m, "stopped", |_| true);
    assert!(w[0] > 0.1 && w[0] < 40.0, "the jog was not stopped: {w:?}");
    wait_connected(&s, p, false);
}

#[test]
fn a_silent_pendant_is_declared_lost() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(
        &s,
        "wheel",
        &sim.addr,
        Some(m),
        json!({"lost_after_ms": 300}),
    );
    wait_connected(&s, p, true);
    sim.cmd("poll 0");
    let e = wait_event(&s, "silence", |e| e.event == "pendant.lost");
    assert!(
        e.data["data"]["reason"]
            .as_str()
            .unwrap()
            .contains("silent"),
        "{e:?}"
    );
}

#[test]
fn fifty_pendants_on_one_machine_at_once() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let mut sims: Vec<PendantSim> = (0..50).map(|_| PendantSim::start()).collect();
    let ids: Vec<i64> = sims
        .iter()
        .enumerate()
        .map(|(i, sim)| add_pendant(&s, &format!("p{i}"), &sim.addr, Some(m), json!({})))
        .collect();
    for id in &ids {
        wait_connected(&s, *id, true);
    }
    for sim in sims.iter_mut() {
        sim.cmd("jog Y 1 0.01");
    }
    wait_work(&s, m, "y = 50 x 0.01", |w| close(w[1], 0.5));
    // Every pendant's LCD shows it.
    for sim in sims.iter_mut() {
        sim.cmd("poll 20");
    }
    let list = s.get("/api/v1/pendants").expect(200);
    assert_eq!(list.as_array().unwrap().len(), 50);
    let off: Vec<_> = list
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| !(p["connected"] == true && p["machine"] == m))
        .collect();
    if !off.is_empty() {
        // Diagnostics only: what the log says about the links.
        let stream = s.events("types=pendant.lost", Some(0));
        let mut lost = Vec::new();
        while let Some(e) = stream.next(Duration::from_secs(1)) {
            lost.push(e.data);
        }
        panic!("not connected or not bound: {off:?}; pendant.lost events: {lost:?}");
    }
}

/// Nice values of the server's threads with this name (`/proc/PID/task/*/comm`, field 19 of
/// each task's `stat`).
#[cfg(target_os = "linux")]
fn thread_nices(pid: u32, name: &str) -> Vec<i32> {
    let mut nices = Vec::new();
    for task in std::fs::read_dir(format!("/proc/{pid}/task")).unwrap() {
        let dir = task.unwrap().path();
        let Ok(comm) = std::fs::read_to_string(dir.join("comm")) else {
            continue; // the thread ended meanwhile
        };
        if comm.trim_end() != name {
            continue;
        }
        let Ok(stat) = std::fs::read_to_string(dir.join("stat")) else {
            continue;
        };
        nices.push(nice_in_stat(&stat).unwrap());
    }
    nices
}

/// Through the server and the plugin ABI: a pendant's link thread runs at nice -10 and says
/// so in the server's log, and the server's other threads keep their priority. (The suite runs
/// as root; the refused case is the plugin's own test.)
#[cfg(target_os = "linux")]
#[test]
fn a_pendants_link_thread_runs_at_nice_minus_10_in_the_server() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    let line = s.wait_log(T, "the link's thread");
    assert!(
        line.contains("runs at nice -10"),
        "this test needs CAP_SYS_NICE (run it as root, as tests/run does): {line}"
    );
    let pid = s.pid().unwrap();
    assert_eq!(thread_nices(pid, "mpg-pendant"), vec![-10]);
    let server_nice =
        nice_in_stat(&std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap()).unwrap();
    assert_ne!(server_nice, -10, "the whole server was raised");
    // A second pendant's link gets its own raised thread.
    let sim2 = PendantSim::start();
    let p2 = add_pendant(&s, "wheel2", &sim2.addr, Some(m), json!({}));
    wait_connected(&s, p2, true);
    assert_eq!(thread_nices(pid, "mpg-pendant"), vec![-10, -10]);
}

#[test]
fn the_demo_starts_a_simulated_pendant_bound_to_the_demo_machine() {
    let s = Server::start_demo();
    let machine = s.get("/api/v1/machines").expect(200)[0]["id"]
        .as_i64()
        .unwrap();
    let list = s.get("/api/v1/pendants").expect(200);
    assert_eq!(list[0]["name"], "demo-pendant", "{list}");
    assert_eq!(list[0]["machine"], machine);
    let id = list[0]["id"].as_i64().unwrap();
    wait_connected(&s, id, true);
}

fn patch_pendant(s: &Server, p: i64, body: Value) -> fresa_tests::Resp {
    s.send(
        s.req(reqwest::Method::PATCH, &format!("/api/v1/pendants/{p}"))
            .json(&body),
    )
}

#[test]
fn macros_toggle_the_spindle_and_run_mdi_lines_and_bad_ones_are_refused() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    patch_pendant(
        &s,
        p,
        json!({"macros": {
            "M1": {"type": "toggle", "output": "spindle"},
            "M2": {"type": "mdi", "line": "G91 G1 X2 Z-1 F600"},
            "M3": {"type": "mdi", "line": "G0 X5"},
        }}),
    )
    .expect(200);
    let actor = format!("pendant:{p}");

    // M1 twice: the spindle goes on, then back off.
    sim.cmd("key M1");
    sim.cmd("key M1");
    let stream = s.events("", Some(0));
    let mut toggles = Vec::new();
    stream.until(T, "two spindle toggles", |e| {
        if e.event == "machine.command" && e.data["data"]["command"] == "toggle_output" {
            assert_eq!(e.data["actor"], actor, "{e:?}");
            assert_eq!(e.data["data"]["name"], "spindle", "{e:?}");
            toggles.push(e.data["data"]["on"].as_bool().unwrap());
        }
        toggles.len() == 2
    });
    assert_eq!(toggles, [true, false]);

    // M2 moves incrementally; M3 is absolute again (the G91 of M2 did not stay behind).
    sim.cmd("key M2");
    wait_work(&s, m, "x = 2, z = -1 from M2", |w| {
        close(w[0], 2.0) && close(w[2], -1.0)
    });
    sim.cmd("key M3");
    let w = wait_work(&s, m, "x = 5 from M3", |w| close(w[0], 5.0));
    assert!(close(w[2], -1.0) && close(w[1], 0.0), "{w:?}");
    let mdi = wait_event(&s, "the MDI line in the audit log", |e| {
        e.event == "machine.mdi" && e.data["data"]["line"] == "G0 X5"
    });
    assert_eq!(mdi.data["actor"], actor);

    // An override macro (slow the cut down from the machine); outside the range it is refused.
    patch_pendant(
        &s,
        p,
        json!({"macros": {"M4": {"type": "command", "command": "set_overrides", "feed": 50}}}),
    )
    .expect(200);
    sim.cmd("key M4");
    s.wait_status(m, T, "feed override 50 from M4", |st| {
        st["feed_override"] == 50.0
    });
    patch_pendant(
        &s,
        p,
        json!({"macros": {"M4": {"type": "command", "command": "set_overrides", "feed": 500}}}),
    )
    .expect(200);
    sim.cmd("key M4");
    let refused = wait_event(&s, "M4 refused", |e| {
        e.event == "pendant.refused" && e.data["data"]["code"] == "override_out_of_range"
    });
    assert_eq!(refused.data["actor"], actor);
    assert_eq!(s.status(m)["feed_override"], 50.0);
    patch_pendant(&s, p, json!({"macros": {"M4": null}})).expect(200);

    // Bad macros are refused naming slot and field; nothing of that request is applied.
    for (bad, field) in [
        (json!({"type": "mdi", "line": "G1 X("}), "macros.M4.line"),
        (
            json!({"type": "mdi", "line": "G0 X1\nG0 X2"}),
            "macros.M4.line",
        ),
        (json!({"type": "mdi", "line": " "}), "macros.M4.line"),
        (json!({"type": "toggle", "output": "vacuum"}), "macros.M4"),
        (json!({"type": "toggle"}), "macros.M4"),
        (
            json!({"type": "command", "command": "set_overrides", "fed": 50}),
            "macros.M4",
        ),
    ] {
        let msg = patch_pendant(
            &s,
            p,
            json!({"macros": {"M1": {"type": "toggle", "output": "coolant"}, "M4": bad}}),
        )
        .expect_error(422, "invalid_field");
        assert!(msg.contains(field), "{bad}: {msg}");
    }
    let macros = &s.get(&format!("/api/v1/pendants/{p}")).expect(200)["macros"];
    assert_eq!(macros["M1"]["output"], "spindle", "{macros}");
    assert_eq!(macros["M4"], Value::Null, "{macros}");

    // The same MDI path over HTTP, with the same check.
    let msg = s
        .post(
            &format!("/api/v1/machines/{m}/mdi"),
            &json!({"line": "G1 X("}),
        )
        .expect_error(422, "invalid_gcode");
    assert!(msg.contains("column"), "{msg}");
    s.post(
        &format!("/api/v1/machines/{m}/mdi"),
        &json!({"line": "G0 Y1"}),
    )
    .expect(200);
    wait_work(&s, m, "y = 1 from HTTP MDI", |w| close(w[1], 1.0));
}

#[test]
fn a_pendant_on_a_machine_in_alarm_moves_nothing_but_may_reset_it() {
    let s = Server::start();
    let m = s
        .sim_with(
            "alarmed",
            0.0,
            json!({"config": {"time_scale": 0, "alarm_at_connect": "limit switch X+"}}),
        )
        .id;
    s.wait_machine_state(m, "alarm", T);
    let job = s.upload(m, "short", fresa_tests::back_and_forth(4, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    patch_pendant(
        &s,
        p,
        json!({"macros": {"M1": {"type": "mdi", "line": "G0 X3"}}}),
    )
    .expect(200);

    sim.cmd("jog X 100 0.01");
    sim.cmd("key Start");
    sim.cmd("key M1");
    let actor = format!("pendant:{p}");
    let stream = s.events("", Some(0));
    let mut refused = Vec::new();
    stream.until(T, "three refusals", |e| {
        if e.event == "pendant.refused" {
            assert_eq!(e.data["actor"], actor, "{e:?}");
            assert_eq!(e.data["data"]["code"], "machine_alarm", "{e:?}");
            assert!(
                e.data["data"]["reason"]
                    .as_str()
                    .unwrap()
                    .contains("limit switch X+"),
                "{e:?}"
            );
            refused.push(e.data["data"]["input"].clone());
        }
        refused.len() == 3
    });
    assert_eq!(refused[0]["jog"]["axis"], "X", "{refused:?}");
    assert_eq!(refused[1]["key"], "start", "{refused:?}");
    assert_eq!(refused[2]["key"], "m1", "{refused:?}");
    let st = s.status(m);
    assert_eq!(st["state"], "alarm", "{st}");
    assert!(work(&s, m).iter().all(|v| close(*v, 0.0)), "{st}");
    assert_eq!(s.job(job)["state"], "ready", "the job never started");

    // Reset is allowed in alarm and clears it; then the wheel moves the machine.
    sim.cmd("key Reset");
    let reset = wait_event(&s, "reset by the pendant", |e| {
        e.event == "machine.command" && e.data["data"]["command"] == "reset"
    });
    assert_eq!(reset.data["actor"], actor);
    s.wait_machine_state(m, "idle", T);
    sim.cmd("jog X 100 0.01");
    wait_work(&s, m, "x = 1 after reset", |w| close(w[0], 1.0));
}

/// A server with a sim machine and a bound pendant whose simulator prints every poll answer
/// (so answers can be counted), and a program file of `lines` small moves.
struct UploadRig {
    s: Server,
    m: i64,
    p: i64,
    sim: PendantSim,
    prog: std::path::PathBuf,
    /// Holds `prog`: bind it (`_dir`, not `_` or `..`) for as long as the file is needed.
    _dir: tempfile::TempDir,
}

fn upload_rig(lines: usize, config: Value) -> UploadRig {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let sim = PendantSim::start_with(&["--poll-hz", "20"]);
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), config);
    wait_connected(&s, p, true);
    let dir = tempfile::tempdir().unwrap();
    let prog = dir.path().join("p.nc");
    let text: Vec<String> = (0..lines)
        .map(|i| format!("G1 X{} Y{} F600", i % 50, (i * 7) % 40))
        .collect();
    std::fs::write(&prog, text.join("\n")).unwrap();
    UploadRig {
        s,
        m,
        p,
        sim,
        prog,
        _dir: dir,
    }
}

#[test]
fn firmware_blank_lines_are_counted_but_not_sent_and_the_upload_is_accepted() {
    let s = Server::start();
    let m = s.sim("mill", 0.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    let dir = tempfile::tempdir().unwrap();
    let prog = dir.path().join("fusion.nc");
    // Like Fusion 360 output: 3 blank lines among 9.
    let text = "%\n(T1 D=6 FLAT)\n\nG21 G90\nG0 Z5\n\nG1 X5 F300\n\nM30\n";
    std::fs::write(&prog, text).unwrap();

    // The firmware: one send per line, nothing at all for a blank line, START declares 9.
    sim.cmd(&format!(
        "upload {} gap=120-150 end=none blank=drop",
        prog.display()
    ));
    sim.wait_line_from(0, "N53", |l| l.starts_with("recv N53Confirm"));
    let e = wait_event(&s, "upload event", |e| e.event == "pendant.upload");
    assert_eq!(e.data["data"]["declared_lines"], 9, "{e:?}");
    assert_eq!(e.data["data"]["blank_lines_dropped"], 3, "{e:?}");
    assert_eq!(e.data["data"]["lines"], 6, "{e:?}");
    let jobs = s.get("/api/v1/jobs").expect(200);
    let id = jobs[0]["id"].as_i64().unwrap();
    let without_blanks: String = text
        .lines()
        .filter(|l| !l.is_empty())
        .map(|l| format!("{l}\n"))
        .collect();
    assert_eq!(
        s.get(&format!("/api/v1/jobs/{id}/gcode")).text,
        without_blanks
    );

    // Fewer lines is only accepted with the exact character count.
    sim.cmd(&format!(
        "upload {} gap=0 end=lf blank=drop chars+=1",
        prog.display()
    ));
    wait_event(&s, "char count rejection", |e| {
        e.event == "pendant.upload_rejected" && e.data["data"]["code"] == "char_count_mismatch"
    });
    assert_eq!(sim.received("N53"), 1);
    assert_eq!(
        s.get("/api/v1/jobs").expect(200).as_array().unwrap().len(),
        1
    );
}

#[test]
fn stop_in_the_middle_of_an_upload_aborts_it_and_the_next_polls_are_answered() {
    let UploadRig {
        s,
        m,
        mut sim,
        prog,
        _dir,
        ..
    } = upload_rig(40, json!({}));

    // STOP after 5 of 40 lines: no N03FIN; the firmware's main loop polls N0451 again.
    sim.cmd(&format!(
        "upload {} gap=0 end=lf stop-after=5",
        prog.display()
    ));
    let stopped = sim.wait_line_from(0, "upload-stopped", |l| l == "upload-stopped lines=5");
    // Every poll is answered: the first five after STOP.
    sim.wait_received_since(stopped, "N51", 5);
    let e = wait_event(&s, "abort recorded", |e| {
        e.event == "pendant.upload_rejected"
    });
    let reason = e.data["data"]["reason"].as_str().unwrap();
    assert!(
        reason.contains("upload aborted after 5 of 40 lines") && reason.contains("N0451"),
        "{e:?}"
    );
    s.assert_no_jobs();

    // The link is fine: the wheel moves the machine and a whole upload is loaded.
    sim.cmd("jog X 3 0.1");
    wait_work(&s, m, "x = 0.3", |w| close(w[0], 0.3));
    sim.cmd(&format!("upload {} gap=0 end=lf", prog.display()));
    sim.wait_line_from(stopped, "N53", |l| l.starts_with("recv N53Confirm"));
    assert_eq!(
        s.get("/api/v1/jobs").expect(200).as_array().unwrap().len(),
        1
    );
}

#[test]
fn a_file_over_255_lines_that_the_firmware_re_sends_forever_is_rejected_naming_the_limit() {
    let UploadRig {
        s,
        p,
        mut sim,
        prog,
        _dir,
        ..
    } = upload_rig(300, json!({}));

    // The 8-bit counter wraps after 255: lines 0..255 again and again, never N03FIN, until the
    // operator gives up and presses STOP (here after 2,000 lines).
    sim.cmd(&format!(
        "upload {} gap=0 end=lf wrap8 stop-after=2000",
        prog.display()
    ));
    let stopped = sim.wait_line_from(0, "upload-stopped", |l| l == "upload-stopped lines=2000");
    let e = wait_event(&s, "rejection", |e| e.event == "pendant.upload_rejected");
    let reason = e.data["data"]["reason"].as_str().unwrap();
    assert!(
        reason.contains("more lines than the 300 its N03START declared")
            && reason.contains("8-bit line counter")
            && reason.contains("255 lines"),
        "{e:?}"
    );
    // Rejected once, while the pendant was still sending; the abort that followed is not
    // another rejection.
    sim.wait_received_since(stopped, "N51", 5);
    // A jog after it, as a marker: every event of the upload is recorded before it.
    sim.cmd("jog X 1 0.1");
    let events = s
        .events("", Some(0))
        .until(T, "the jog after the upload", |e| e.event == "machine.jog");
    let rejected = events
        .iter()
        .filter(|e| e.event == "pendant.upload_rejected")
        .count();
    assert_eq!(rejected, 1, "{events:?}");
    s.assert_no_jobs();
    assert_eq!(sim.received("N53"), 0);
    let p = s.get(&format!("/api/v1/pendants/{p}")).expect(200);
    assert_eq!(p["connected"], true);
}

#[test]
fn an_upload_without_n03fin_times_out_naming_the_firmware_limit() {
    let UploadRig {
        s,
        mut sim,
        prog,
        _dir,
        ..
    } = upload_rig(300, json!({"upload_idle_ms": 300}));
    // A pendant that stops sending mid-upload and does not poll: only the time-out ends it.
    sim.cmd("poll 0");
    sim.cmd(&format!(
        "upload {} gap=0 end=lf stop-after=100",
        prog.display()
    ));
    let e = wait_event(&s, "time-out", |e| e.event == "pendant.upload_rejected");
    let reason = e.data["data"]["reason"].as_str().unwrap();
    assert!(
        reason.contains("no N03FIN for 300 ms after 100 of 300 lines")
            && reason.contains("8-bit line counter"),
        "{e:?}"
    );
    s.assert_no_jobs();
    // Back in frame mode: a poll is answered.
    let from = sim.seen.len();
    sim.cmd("poll 20");
    sim.wait_received_since(from, "N51", 1);
}

// ---- misbehaving pendants: floods, STOP behind a backlog, motion and zeroing ----

/// A pendant played over a raw socket, speaking the 53-character protocol by hand: the test is
/// the TCP server the plugin connects to, and can flood it faster than any firmware would.
struct RawPendant {
    listener: std::net::TcpListener,
    addr: String,
}

impl RawPendant {
    fn start() -> RawPendant {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        RawPendant { listener, addr }
    }

    /// The plugin's connection (it connects at once when the pendant is added).
    fn accept(&self) -> std::net::TcpStream {
        self.listener.set_nonblocking(true).unwrap();
        let stream = wait_for(T, "the server to connect to the raw pendant", || {
            self.listener.accept().ok().map(|(s, _)| s)
        });
        stream.set_nonblocking(false).unwrap();
        stream
    }
}

/// One wheel frame: `N01S<step %06.4f><axis><sign><count %04d>`, `*` to C52, `F`.
fn wheel_frame(axis: char, count: i32, step: f64) -> Vec<u8> {
    let sign = if count < 0 { '-' } else { '+' };
    let mut f = format!("N01S{step:06.4}{axis}{sign}{:04}", count.abs());
    while f.len() < 52 {
        f.push('*');
    }
    f.push('F');
    assert_eq!(f.len(), 53, "{f}");
    f.into_bytes()
}

/// One action frame, the word at both ends: `N02Stop***...StopF`.
fn key_frame(word: &str) -> Vec<u8> {
    let mut f = format!("N02{word}");
    while f.len() < 52 - word.len() {
        f.push('*');
    }
    f.push_str(word);
    f.push('F');
    assert_eq!(f.len(), 53, "{f}");
    f.into_bytes()
}

/// Writes `frames` copies of `frame` (then `tail`) on a thread, as fast as the link takes them.
fn flood(
    mut stream: std::net::TcpStream,
    frame: Vec<u8>,
    frames: usize,
    tail: Vec<u8>,
) -> std::thread::JoinHandle<std::net::TcpStream> {
    std::thread::spawn(move || {
        let chunk: Vec<u8> = frame.repeat(1000);
        let mut left = frames;
        while left > 0 {
            let n = left.min(1000);
            stream.write_all(&chunk[..frame.len() * n]).unwrap();
            left -= n;
        }
        stream.write_all(&tail).unwrap();
        stream
    })
}

/// A raw pendant that never reconnects or times out by itself: only what the test does to
/// the link changes its state.
fn raw_pendant_config() -> Value {
    json!({"lost_after_ms": 600000, "backoff_initial_ms": 600000, "backoff_max_ms": 600000})
}

/// Polls the status across `span` (several reads) and returns the machine X positions seen,
/// with the states.
fn positions_across(s: &Server, m: i64, span: Duration) -> Vec<(f64, String)> {
    let end = Instant::now() + span;
    let mut seen = Vec::new();
    loop {
        let st = s.status(m);
        seen.push((
            st["machine_position"]["x"].as_f64().unwrap(),
            st["state"].as_str().unwrap_or("").to_string(),
        ));
        if Instant::now() >= end {
            return seen;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[track_caller]
fn assert_still(seen: &[(f64, String)], since: f64, what: &str) {
    assert!(seen.len() >= 5, "{seen:?}");
    assert!(
        seen.iter()
            .all(|(x, state)| close(*x, since) && state != "jogging"),
        "{what}: the machine moved after it was stopped (x was {since}): {seen:?}"
    );
}

#[test]
fn a_wheel_flood_then_a_closed_link_drops_the_backlog_and_stop_leaves_the_machine_still() {
    let s = Server::start();
    // Real time, 1000 mm/min: 300,000 frames of 0.01 mm are 3 m, minutes of motion.
    let m = s.sim("mill", 1.0).id;
    let pendant = RawPendant::start();
    let p = add_pendant(&s, "flood", &pendant.addr, Some(m), raw_pendant_config());
    let link = pendant.accept();
    wait_connected(&s, p, true);
    let pid = s.pid().unwrap();
    let rss_before = fresa_tests::rss_kib(pid);

    let writer = flood(link, wheel_frame('X', 1, 0.01), 300_000, Vec::new());
    let mut rss_peak = rss_before;
    while !writer.is_finished() {
        rss_peak = rss_peak.max(fresa_tests::rss_kib(pid));
        std::thread::sleep(Duration::from_millis(20));
    }
    // The pendant closes its link with the backlog still there.
    drop(writer.join().unwrap());
    let closed = Instant::now();
    // The link, not the backlog: not connected once the link is gone.
    wait_for(T, "the pendant not connected after its link closed", || {
        rss_peak = rss_peak.max(fresa_tests::rss_kib(pid));
        let p = s.get(&format!("/api/v1/pendants/{p}")).expect(200);
        (p["connected"] == false).then_some(())
    });
    println!(
        "flood: link closed -> pendant not connected in {:?}",
        closed.elapsed()
    );
    // Its loss stops the jog it started.
    let lost = wait_event(&s, "the lost pendant's jog stopped", |e| {
        e.event == "pendant.lost" && e.data["data"]["pendant"] == p
    });
    assert_eq!(lost.data["data"]["stopped"], true, "{lost:?}");

    let stop_sent = Instant::now();
    s.command(m, "stop", json!({})).expect(200);
    let stopped = s.wait_status(m, T, "idle after STOP", |st| st["state"] == "idle");
    println!(
        "flood: STOP answered, machine idle {:?} after STOP was sent",
        stop_sent.elapsed()
    );
    let x = stopped["machine_position"]["x"].as_f64().unwrap();
    let seen = positions_across(&s, m, Duration::from_secs(2));
    assert_still(&seen, x, "after the lost pendant's flood and STOP");
    // Well short of the 3 m the flood asked for: the loss dropped it.
    assert!(x > 0.0 && x < 100.0, "x = {x}");
    for _ in 0..10 {
        rss_peak = rss_peak.max(fresa_tests::rss_kib(pid));
    }
    println!(
        "flood: server RSS {} KiB before, {} KiB peak ({} KiB more); x = {x} mm after STOP",
        rss_before,
        rss_peak,
        rss_peak - rss_before
    );
    // Bounded: the backlog is one coalesced entry, not 300,000 events (the unbounded queue
    // grew by about 250 MB).
    assert!(
        rss_peak - rss_before < 64 * 1024,
        "the server's memory grew by {} KiB during the flood",
        rss_peak - rss_before
    );
}

#[test]
fn a_stop_key_behind_a_wheel_flood_overtakes_it_and_nothing_queued_moves_afterwards() {
    let s = Server::start();
    let m = s.sim("mill", 1.0).id;
    let pendant = RawPendant::start();
    let p = add_pendant(&s, "flood", &pendant.addr, Some(m), raw_pendant_config());
    let link = pendant.accept();
    wait_connected(&s, p, true);
    let sent = Instant::now();
    let writer = flood(link, wheel_frame('X', 1, 0.01), 300_000, key_frame("Stop"));
    let stop = wait_event(&s, "the pendant's STOP", |e| {
        e.event == "machine.command"
            && e.data["data"]["command"] == "stop"
            && e.data["actor"] == format!("pendant:{p}")
    });
    assert!(stop.id.is_some());
    let st = s.wait_status(m, T, "idle after the STOP key", |st| st["state"] == "idle");
    println!(
        "STOP key behind 300,000 wheel frames: machine idle {:?} after the flood began",
        sent.elapsed()
    );
    let x = st["machine_position"]["x"].as_f64().unwrap();
    let seen = positions_across(&s, m, Duration::from_secs(2));
    assert_still(&seen, x, "after the pendant's STOP key");
    // The link is still up: it was a STOP, not a loss.
    let _link = writer.join().unwrap();
    assert_eq!(
        s.get(&format!("/api/v1/pendants/{p}")).expect(200)["connected"],
        true
    );
}

#[test]
fn zero_keys_while_the_machine_moves_are_refused_as_machine_moving() {
    let s = Server::start();
    let m = s.sim("mill", 1.0).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m), json!({}));
    wait_connected(&s, p, true);
    // 50 mm at 100 mm/min: half a minute of motion.
    s.post(
        &format!("/api/v1/machines/{m}/jog"),
        &json!({"axis": "X", "distance": 50.0, "feed": 100.0}),
    )
    .expect(200);
    s.wait_machine_state(m, "jogging", T);
    sim.cmd("key ZeroX");
    let e = wait_event(&s, "ZeroX refused", |e| {
        e.event == "pendant.refused" && e.data["data"]["input"]["key"] == "zero_x"
    });
    assert_eq!(e.data["data"]["code"], "machine_moving", "{e:?}");
    s.post_empty(&format!("/api/v1/machines/{m}/jog/cancel"))
        .expect(200);
    // Nothing was zeroed: G54 is untouched.
    let off = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    let g54x = off["offsets"]["G54"]["x"].as_f64().unwrap_or(0.0);
    assert!(close(g54x, 0.0), "{off}");
}

#[test]
fn a_nesting_bomb_uploaded_from_the_sd_card_is_refused_and_the_server_and_link_live_on() {
    let UploadRig {
        s,
        m,
        mut sim,
        prog,
        _dir,
        ..
    } = upload_rig(20, json!({}));
    let dir = tempfile::tempdir().unwrap();
    // 4,000 and 50,000 levels: a pendant needs no credentials, and before the nesting bound
    // either one overflowed the upload thread's stack and aborted the whole server.
    let bombs = [
        (
            "brackets.nc",
            format!(
                "G21 G90\nG1 X{}1{} F100\n",
                "[".repeat(4000),
                "]".repeat(4000)
            ),
            "line 2, column 69",
        ),
        (
            "hashes.nc",
            format!("G21 G90\nG1 X{}1 F100\n", "#".repeat(50_000)),
            "line 2, column 69",
        ),
    ];
    for (i, (name, text, at)) in bombs.iter().enumerate() {
        let file = dir.path().join(name);
        std::fs::write(&file, text).unwrap();
        sim.cmd(&format!("upload {} gap=0 end=lf", file.display()));
        // Replayed from the start: this bomb's rejection is the (i+1)-th.
        let mut n = 0;
        let seen = s.events("", Some(0)).until(T, "the bomb's rejection", |e| {
            n += usize::from(e.event == "pendant.upload_rejected");
            n == i + 1
        });
        let e = seen.last().unwrap();
        assert_eq!(e.data["data"]["code"], "invalid_gcode", "{e:?}");
        let reason = e.data["data"]["reason"].as_str().unwrap();
        assert!(
            reason.contains(at) && reason.contains("limit of 64 levels"),
            "{name}: {reason}"
        );
        s.get("/healthz").expect(200);
        s.assert_no_jobs();
    }
    assert_eq!(sim.received("N53"), 0);
    // The server and the link are fine: the wheel moves the machine and a good file loads.
    sim.cmd("jog X 3 0.1");
    wait_work(&s, m, "x = 0.3", |w| close(w[0], 0.3));
    sim.cmd(&format!("upload {} gap=0 end=lf", prog.display()));
    sim.wait_line_from(0, "N53", |l| l.starts_with("recv N53Confirm"));
    assert_eq!(
        s.get("/api/v1/jobs").expect(200).as_array().unwrap().len(),
        1
    );
}

/// Issue 26: why the machine holds is on the pendant's LCD, in the status line of its `N52`
/// answer: an M0's `(MSG, change clamp)` while the run holds there, and the Start key (cycle
/// start) goes on. A pendant with `stop_program_on_lost` that is lost pauses the run it
/// started, and the machine and the job name the lost pendant as the reason.
#[test]
fn the_lcd_shows_why_the_machine_holds_and_a_lost_pendant_is_named_as_the_reason() {
    let s = Server::start();
    // 4000 mm at 600 mm/min, time scale 0.05: ~20 s, long enough to lose the pendant mid-run.
    let m = s.sim("mill", 0.05).id;
    let mut sim = PendantSim::start();
    let p = add_pendant(
        &s,
        "wheel",
        &sim.addr,
        Some(m),
        json!({"stop_program_on_lost": true}),
    );
    wait_connected(&s, p, true);
    let mut program = String::from("G21 G90\nG0 X1\nM0 (MSG, change clamp)\n");
    program.push_str(&fresa_tests::back_and_forth(4000, 1.0, 600.0));
    let job = s.upload(m, "clamp", program)["id"].as_i64().unwrap();
    sim.cmd("key Start");
    let st = s.wait_status(m, T, "held at the M0", |st| {
        st["state"] == "paused" && st["hold"]["kind"] == "program_pause"
    });
    assert_eq!(st["hold"]["program_message"], "change clamp", "{st}");
    let j = s.wait_job_state(job, "paused", T);
    assert_eq!(j["hold"]["program_message"], "change clamp", "{j}");
    let from = sim.seen.len();
    sim.cmd("poll-job 20");
    sim.wait_line_from(from, "the M0's message on the LCD", |l| {
        l.starts_with("recv N52") && l.contains("LA0002M0 change clamp*")
    });
    sim.cmd("poll-job 0");

    // Start is cycle start: the run goes on, on the machine and the job.
    sim.cmd("key Start");
    s.wait_job_state(job, "running", T);
    s.wait_job(job, T, "past the M0", |j| j["line"].as_i64().unwrap() > 5);

    // Lost: the run it started is paused, and says why.
    sim.cmd("drop");
    let st = s.wait_status(m, T, "held for the lost pendant", |st| {
        st["state"] == "paused" && st["hold"]["kind"] == "pendant_lost"
    });
    assert!(
        st["hold"]["message"]
            .as_str()
            .unwrap()
            .contains(&format!("pendant {p}")),
        "{st}"
    );
    assert_eq!(st["hold"]["continue_with"], "resume", "{st}");
    let j = s.wait_job_state(job, "paused", T);
    assert_eq!(j["hold"]["kind"], "pendant_lost", "{j}");
    s.job_action(job, "cancel").expect(200);
}

/// Issue 28: while the machine's job queue waits for the next part, the LCD says so and START
/// confirms it (the queue's part starts, not the machine's newest job).
#[test]
fn start_confirms_the_next_part_of_a_waiting_queue_and_the_lcd_says_so() {
    let s = Server::start();
    let m = s.sim("mill", 0.1);
    let mut sim = PendantSim::start();
    let p = add_pendant(&s, "wheel", &sim.addr, Some(m.id), json!({}));
    wait_connected(&s, p, true);
    let lines = 30;
    let program = fresa_tests::back_and_forth(lines, 1.0, 600.0);
    let job = s.upload(m.id, "bracket", program.clone())["id"]
        .as_i64()
        .unwrap();
    let queue = format!("/api/v1/machines/{}/queue", m.id);
    s.post(&queue, &json!({"job": job, "count": 2})).expect(200);
    // Newer than the queue's job: a Start with no queue waiting would start this one.
    let newer = s.upload(m.id, "newer", program)["id"].as_i64().unwrap();
    let lcd = |sim: &mut PendantSim, text: &str| {
        let from = sim.seen.len();
        sim.cmd("poll-job 20");
        sim.wait_line_from(from, text, |l| {
            l.starts_with("recv N52") && l.contains(&format!("{text}*"))
        });
        sim.cmd("poll-job 0");
    };
    let mut runs = Vec::new();
    for part in 1..=2 {
        lcd(&mut sim, &format!("PART {part}/2 START"));
        sim.cmd("key Start");
        let confirmed = s
            .events("types=queue.confirm", Some(0))
            .until(T, "the pendant's confirm", |e| {
                e.data["data"]["part"] == part
            })
            .pop()
            .unwrap();
        assert_eq!(
            confirmed.data["actor"],
            format!("pendant:{p}"),
            "{:?}",
            confirmed.data
        );
        let run = confirmed.data["data"]["run"].as_i64().unwrap();
        wait_for(T, "the part to complete", || {
            let q = s.get(&queue).expect(200);
            (q["state"] != "running" && m.count_of(run) == lines).then_some(())
        });
        runs.push(run);
    }
    let logged: std::collections::BTreeSet<i64> = m.executed().iter().map(|e| e.0).collect();
    assert_eq!(
        logged,
        runs.iter().copied().collect(),
        "the two confirmed parts ran"
    );
    assert_eq!(s.get(&queue).expect(200)["state"], "idle");
    assert!(s.job(newer)["run"].is_null(), "the newer job never ran");
}
