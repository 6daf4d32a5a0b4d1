//! Several nodes on one PostgreSQL store (issue 16): two real `fresa serve` processes share a
//! throwaway PostgreSQL. A machine driven by node A is jogged and runs a job through node B's
//! API; both nodes' event streams carry the same events; node A killed mid-job shows its machine
//! offline on B, and after A restarts the run is interrupted and resumes through B with every
//! line executed once (the sim-machine's execution log is the independent record).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{assert_every_line_once, back_and_forth, wait_for, Opts, Server, SseEvent};
use serde_json::{json, Value};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);
/// 300 lines of 1 mm at 600 mm/min: about 3 s at time scale 0.1.
const LINES: i64 = 300;

/// A fresh database on this test process's throwaway PostgreSQL.
fn fresh_database() -> String {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(fresa_core::store::test_postgres::fresh_database())
}

/// A node of the store at `url`, beating fast so a lost node shows within a test's patience.
fn node(database: &str, name: &str) -> Server {
    let mut s = Server::unstarted(Opts::default());
    s.write_config(&format!(
        "database_url = \"{database}\"\nnode_name = \"{name}\"\n\
         node_heartbeat_ms = 100\nnode_offline_after_ms = 1500\n"
    ));
    s.spawn()
        .unwrap_or_else(|e| panic!("node {name} did not start: {e}"));
    s
}

fn machine_on(s: &Server, id: i64) -> Value {
    s.get(&format!("/api/v1/machines/{id}")).expect(200)
}

/// The ids of the events of `kind` read from `sse` until one matches `pred`.
fn first_event(sse: &fresa_tests::Sse, what: &str, pred: impl Fn(&SseEvent) -> bool) -> SseEvent {
    sse.until(T, what, |e| pred(e)).pop().unwrap()
}

#[test]
fn a_machine_on_node_a_is_jogged_and_runs_a_job_through_node_b() {
    let db = fresh_database();
    let a = node(&db, "hall-a");
    let b = node(&db, "hall-b");
    let m = a.sim("router", 0.1);

    // B lists A's machine, with its owner and its state from A's heartbeat.
    let seen = wait_for(T, "node B to list A's machine as idle", || {
        let v = machine_on(&b, m.id);
        (v["state"] == "idle").then_some(v)
    });
    assert_eq!(seen["node"], "hall-a", "{seen}");
    assert_eq!(machine_on(&a, m.id)["node"], "hall-a");

    // GET /nodes: both nodes, reachable, each with its machines.
    let nodes = wait_for(T, "both nodes in GET /nodes", || {
        let v = b.get("/api/v1/nodes").expect(200);
        (v.as_array().unwrap().len() == 2).then_some(v)
    });
    let by_name = |n: &str| {
        nodes
            .as_array()
            .unwrap()
            .iter()
            .find(|x| x["name"] == n)
            .cloned()
            .unwrap()
    };
    assert_eq!(by_name("hall-a")["machines"], json!([m.id]), "{nodes}");
    assert_eq!(by_name("hall-b")["machines"], json!([]), "{nodes}");
    assert_eq!(by_name("hall-b")["this_node"], true);
    assert_eq!(by_name("hall-a")["reachable"], true);
    assert_eq!(by_name("hall-a")["url"], a.base, "{nodes}");

    // Subscribed on both nodes before anything happens.
    let on_a = a.events("types=machine.jog,job.state", None);
    let on_b = b.events("types=machine.jog,job.state", None);

    // A jog through B moves A's machine (A's own status says so) and is audited once, on A,
    // under the caller's name; both streams carry that one event.
    b.jog(m.id, "X", 5.0).expect(200);
    a.wait_status(m.id, T, "X at 5 after the jog sent to B", |s| {
        (s["work_position"]["x"].as_f64().unwrap() - 5.0).abs() < 1e-6 && s["state"] == "idle"
    });
    let jog_a = first_event(&on_a, "the jog on A's stream", |e| e.event == "machine.jog");
    let jog_b = first_event(&on_b, "the jog on B's stream", |e| e.event == "machine.jog");
    assert_eq!(jog_a.id, jog_b.id, "one event, one id: {jog_a:?} {jog_b:?}");
    assert_eq!(jog_b.data["node"], "hall-a", "{jog_b:?}");
    assert_eq!(jog_b.data["actor"], "local", "{jog_b:?}");
    assert_eq!(jog_b.data["machine"], m.id);
    // Live status (a transient event) reaches B's stream from A too.
    let on_b_status = b.events(&format!("types=status&machine={}", m.id), None);
    b.jog(m.id, "Y", 1.0).expect(200);
    first_event(&on_b_status, "A's live status on B's stream", |e| {
        e.event == "status"
            && e.data["node"] == "hall-a"
            && (e.data["data"]["work_position"]["y"].as_f64() == Some(1.0))
    });
    // A pendant on node B cannot drive A's machine: its keys would go to a task B lacks.
    let p = b
        .post(
            "/api/v1/pendants",
            &json!({"name": "p-b", "address": "127.0.0.1:9", "dialect": "firmware"}),
        )
        .expect(201)["id"]
        .as_i64()
        .unwrap();
    let msg = b
        .req(reqwest::Method::PATCH, &format!("/api/v1/pendants/{p}"))
        .json(&json!({"machine": m.id}));
    let msg = b.send(msg).expect_error(422, "machine_on_other_node");
    assert!(msg.contains("node hall-a"), "{msg}");
    // B's status read of the remote machine is A's live answer.
    let st = b.status(m.id);
    assert!(
        (st["work_position"]["x"].as_f64().unwrap() - 5.0).abs() < 1e-6,
        "{st}"
    );

    // A job uploaded to B (its program goes into the store), started through B, runs on A.
    let program = back_and_forth(40, 1.0, 6000.0);
    let job = b.upload(m.id, "via-b", program.clone())["id"]
        .as_i64()
        .unwrap();
    let started = b.job_action(job, "start").expect(200);
    let run = started["run"]["id"].as_i64().unwrap();
    let done = b.wait_job_state(job, "completed", T);
    assert_eq!(done["line"], 40, "{done}");
    assert_every_line_once(&m.executed(), run, 40);
    for (name, sse) in [("A", &on_a), ("B", &on_b)] {
        first_event(
            sse,
            &format!("job {job} completed on {name}'s stream"),
            |e| e.job() == Some(job) && e.state() == Some("completed"),
        );
    }
    // A had no copy of the program: it fetched it from the store and checked its hash.
    let sha = fresa_tests::sha256_hex(program.as_bytes());
    assert!(a.programs_dir().join(format!("{sha}.nc")).is_file());
    assert_eq!(a.get(&format!("/api/v1/jobs/{job}/gcode")).text, program);

    // Both nodes list the same jobs from the store.
    assert_eq!(a.job(job)["state"], "completed");
    assert_eq!(a.get("/api/v1/jobs").body, b.get("/api/v1/jobs").body);

    // A request claiming to come from a node must carry the store's node secret.
    let before = a.status(m.id)["work_position"].clone();
    let forged = reqwest::blocking::Client::new()
        .post(a.url(&format!("/api/v1/machines/{}/jog", m.id)))
        .header("x-fresa-node-token", "not-the-secret")
        .header("x-fresa-caller-role", "admin")
        .json(&json!({"axis": "X", "distance": 1.0}))
        .send()
        .unwrap();
    assert_eq!(forged.status().as_u16(), 401);
    let body: Value = forged.json().unwrap();
    assert_eq!(body["code"], "invalid_node_token", "{body}");
    let after = a.status(m.id)["work_position"].clone();
    assert_eq!(before, after, "the forged jog moved the machine");
}

#[test]
fn node_a_killed_mid_job_shows_offline_on_b_and_the_run_resumes_through_b() {
    let db = fresh_database();
    let mut a = node(&db, "hall-a");
    let b = node(&db, "hall-b");
    let m = a.sim("router", 0.1);
    let job = b.upload(m.id, "slow", back_and_forth(LINES as usize, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let run = b.job_action(job, "start").expect(200)["run"]["id"]
        .as_i64()
        .unwrap();
    let acked = b.wait_job(job, T, "line >= 40", |j| j["line"].as_i64().unwrap() >= 40)["line"]
        .as_i64()
        .unwrap();

    a.kill();
    // B: the machine is offline because its node is gone, and says since when.
    let v = wait_for(T, "B to show A's machine offline", || {
        let v = machine_on(&b, m.id);
        (v["state"] == "offline").then_some(v)
    });
    let reason = v["reason"].as_str().unwrap();
    assert!(
        reason.starts_with("node hall-a unreachable since "),
        "{reason}"
    );
    assert_eq!(b.status(m.id)["state"], "offline");
    let nodes = b.get("/api/v1/nodes").expect(200);
    let a_row = nodes
        .as_array()
        .unwrap()
        .iter()
        .find(|n| n["name"] == "hall-a")
        .unwrap();
    assert_eq!(a_row["reachable"], false, "{nodes}");
    // Nothing is sent to a machine whose node is gone.
    let msg = b.jog(m.id, "X", 1.0).expect_error(503, "node_unreachable");
    assert!(msg.contains("node hall-a unreachable since"), "{msg}");
    b.job_action(job, "cancel")
        .expect_error(503, "node_unreachable");
    let logged = m.lines_of(run).last().copied().unwrap_or(0);
    assert!(logged >= acked, "log {logged} < acknowledged {acked}");

    // A comes back (on a new port): its run is interrupted at its last acknowledged line.
    a.spawn().unwrap();
    let j = b.wait_job_state(job, "interrupted", T);
    let line = j["line"].as_i64().unwrap();
    assert!(
        line >= acked && line <= logged,
        "interrupted at {line}: acked {acked}, logged {logged}"
    );
    wait_for(T, "B to show the machine idle again", || {
        (machine_on(&b, m.id)["state"] == "idle").then_some(())
    });

    // Resumed through B: completes on A, every line exactly once across both processes.
    b.job_action(job, "resume").expect(200);
    let done = b.wait_job_state(job, "completed", T);
    assert_eq!(done["line"], LINES, "{done}");
    assert_every_line_once(&m.executed(), run, LINES);
}

#[test]
fn an_admin_moves_a_machine_to_another_node() {
    let db = fresh_database();
    let a = node(&db, "hall-a");
    let b = node(&db, "hall-b");
    // No execution log: a backend's files live in its node's data directory.
    let id = a.create_machine(
        &json!({"name": "router", "backend": "sim-machine", "config": {"time_scale": 0.1}}),
    );
    let m = fresa_tests::Sim {
        id,
        log: a.data_dir().join("none"),
    };
    wait_for(T, "B to see the machine idle", || {
        (machine_on(&b, m.id)["state"] == "idle").then_some(())
    });
    // Its handwheel, on A's network, bound to it.
    let pendant = a
        .post(
            "/api/v1/pendants",
            &json!({"name": "wheel", "address": "127.0.0.1:9", "dialect": "firmware", "machine": m.id}),
        )
        .expect(201)["id"]
        .as_i64()
        .unwrap();
    b.put(
        &format!("/api/v1/machines/{}/node", m.id),
        &json!({"node": "no such name!"}),
    )
    .expect_error(422, "invalid_field");
    let moved = b
        .put(
            &format!("/api/v1/machines/{}/node", m.id),
            &json!({"node": "hall-b"}),
        )
        .expect(200);
    assert_eq!(moved["node"], "hall-b");
    // B starts driving it within a heartbeat; A lets it go.
    wait_for(T, "B to drive the machine", || {
        let v = machine_on(&b, m.id);
        (v["state"] == "idle" && v["node"] == "hall-b").then_some(())
    });
    b.jog(m.id, "Y", 2.0).expect(200);
    let st = a.wait_status(m.id, T, "A reports Y at 2 (forwarded to B)", |s| {
        (s["work_position"]["y"].as_f64().unwrap() - 2.0).abs() < 1e-6
    });
    assert_eq!(st["state"], "idle");
    let events = b.events("types=machine.node", Some(0));
    let e = first_event(&events, "the move in the audit log", |e| {
        e.event == "machine.node"
    });
    assert_eq!(e.data["data"], json!({"from": "hall-a", "to": "hall-b"}));

    // The pendant bound to it moved along: B opens its link, A closes it.
    let p = wait_for(T, "B to run the pendant", || {
        let r = b.get(&format!("/api/v1/pendants/{pendant}"));
        (r.status == 200).then_some(r.body)
    });
    assert_eq!(p["machine"], m.id, "{p}");
    wait_for(T, "A to let the pendant go", || {
        (a.get(&format!("/api/v1/pendants/{pendant}")).status == 404).then_some(())
    });
    // Carried back alone to A, it loses the binding: its machine is on B.
    let moved = a
        .put(
            &format!("/api/v1/pendants/{pendant}/node"),
            &json!({"node": "hall-a"}),
        )
        .expect(200);
    assert_eq!(moved["machine"], Value::Null, "{moved}");
    let p = wait_for(T, "A to run the pendant again", || {
        let r = a.get(&format!("/api/v1/pendants/{pendant}"));
        (r.status == 200).then_some(r.body)
    });
    assert_eq!(p["machine"], Value::Null, "{p}");
}

/// A forwarded request whose node never answers must not be reported as "nothing was sent":
/// the node may have carried it out. One that cannot connect at all was never sent.
#[test]
fn a_node_that_takes_a_request_but_never_answers_is_not_reported_as_unreached() {
    let db = fresh_database();
    let b = node(&db, "hall-b");
    let m = b.create_machine(
        &json!({"name": "router", "backend": "sim-machine", "config": {"time_scale": 0.0}}),
    );
    // "ghost" is a node whose address accepts a connection, reads the request and hangs up.
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let ghost_url = format!("http://{}", listener.local_addr().unwrap());
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(mut conn) = conn else { return };
            let mut buf = [0u8; 4096];
            let _ = std::io::Read::read(&mut conn, &mut buf);
            drop(conn);
        }
    });
    // A port nothing listens on: the connection is refused.
    let closed_url = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        format!("http://{}", l.local_addr().unwrap())
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let store = rt.block_on(fresa_core::store::Store::connect(&db)).unwrap();
    b.put(
        &format!("/api/v1/machines/{m}/node"),
        &json!({"node": "ghost"}),
    )
    .expect(200);
    // B lets the machine go at its next heartbeat; from then on it forwards.
    wait_for(T, "B to let the machine go to the ghost", || {
        let v = machine_on(&b, m);
        (v["reason"] == "node ghost has not started yet").then_some(())
    });
    // A registration is a fresh heartbeat: the ghost counts as reachable right after it.
    rt.block_on(store.register_node("ghost", &ghost_url, "0"))
        .unwrap();
    let msg = b.jog(m, "X", 1.0).expect_error(504, "node_no_answer");
    assert!(msg.contains("may have been carried out"), "{msg}");
    rt.block_on(store.register_node("ghost", &closed_url, "0"))
        .unwrap();
    let msg = b.jog(m, "X", 1.0).expect_error(503, "node_unreachable");
    assert!(
        msg.contains("could not be reached") && msg.contains("nothing was sent"),
        "{msg}"
    );
}
