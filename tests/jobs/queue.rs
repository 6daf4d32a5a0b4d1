//! Job queues per machine (issue 28): parts run one after another, each only after an
//! operator's confirm; a STOP holds the queue until it is released; a restart leaves a waiting
//! queue waiting and starts nothing; dispatch gives a part to a free machine. The sim
//! machine's execution log is the record of what ran, the audit log of what was confirmed.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::{assert_every_line_once, back_and_forth, wait_for, Opts, Server, Sim};
use serde_json::{json, Value};
use std::collections::BTreeSet;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn queue(s: &Server, m: i64) -> Value {
    s.get(&format!("/api/v1/machines/{m}/queue")).expect(200)
}

/// Polls the queue until it is in `state`; returns it.
#[track_caller]
fn wait_queue(s: &Server, m: i64, state: &str) -> Value {
    wait_for(T, &format!("machine {m}'s queue to be {state}"), || {
        let q = queue(s, m);
        (q["state"] == state).then_some(q)
    })
}

fn confirm(s: &Server, m: i64) -> i64 {
    let v = s
        .post_empty(&format!("/api/v1/machines/{m}/queue/confirm"))
        .expect(200);
    assert_eq!(v["machine"], m, "{v}");
    v["run"].as_i64().unwrap()
}

/// The runs the execution log holds.
fn runs_logged(m: &Sim) -> BTreeSet<i64> {
    m.executed().into_iter().map(|(r, _)| r).collect()
}

fn add(s: &Server, m: i64, job: i64, count: i64, confirm_between: bool) -> Value {
    s.post(
        &format!("/api/v1/machines/{m}/queue"),
        &json!({"job": job, "count": count, "confirm_between": confirm_between}),
    )
    .expect(200)
}

#[test]
fn three_parts_run_one_after_another_each_only_after_its_confirm() {
    let s = Server::start();
    // 30 lines of 1 mm at 600 mm/min, time scale 0.1: about 0.3 s a part.
    let m = s.sim("mill", 0.1);
    let lines = 30;
    let job = s.upload(m.id, "bracket", back_and_forth(lines, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let q = add(&s, m.id, job, 3, true);
    // The first part waits for a confirm too: nothing starts because parts were added.
    assert_eq!(q["state"], "waiting_confirm", "{q}");
    assert_eq!(q["entries"][0]["count"], 3, "{q}");
    assert_eq!(q["entries"][0]["done"], 0, "{q}");
    assert_eq!(q["entries"][0]["state"], "waiting_confirm", "{q}");

    let mut confirmed = BTreeSet::new();
    for part in 1..=3 {
        // Before this confirm the log holds exactly the parts confirmed so far.
        assert_eq!(runs_logged(&m), confirmed, "before confirming part {part}");
        let run = confirm(&s, m.id);
        assert!(confirmed.insert(run), "run {run} was confirmed twice");
        let q = queue(&s, m.id);
        assert!(
            q["run"] == run || q["state"] != "running",
            "part {part}: the queue runs another run: {q}"
        );
        let next = if part < 3 { "waiting_confirm" } else { "idle" };
        let q = wait_queue(&s, m.id, next);
        assert_eq!(
            s.get(&format!("/api/v1/jobs/{job}")).expect(200)["run"]["id"],
            run
        );
        assert_every_line_once(&m.executed(), run, lines as i64);
        if part < 3 {
            assert_eq!(q["entries"][0]["done"], part, "{q}");
        } else {
            assert_eq!(q["entries"], json!([]), "{q}");
        }
    }
    assert_eq!(
        runs_logged(&m),
        confirmed,
        "three runs, each a confirmed one"
    );
    s.post_empty(&format!("/api/v1/machines/{}/queue/confirm", m.id))
        .expect_error(409, "queue_not_waiting");

    // The audit log names each confirmed run, with its machine and entry.
    let mut n = 0;
    let seen: Vec<Value> = s
        .events("types=queue.confirm", Some(0))
        .until(T, "three queue.confirm events", |_| {
            n += 1;
            n == 3
        })
        .iter()
        .map(|e| e.data["data"].clone())
        .collect();
    let runs: BTreeSet<i64> = seen.iter().map(|d| d["run"].as_i64().unwrap()).collect();
    assert_eq!(runs, confirmed, "{seen:?}");
    for d in &seen {
        assert_eq!(d["machine"], m.id, "{d}");
        assert!(d["entry"].is_i64(), "{d}");
    }
}

#[test]
fn a_stop_during_part_two_holds_the_queue_until_it_is_released() {
    let s = Server::start();
    // 300 lines: about 3 s a part at time scale 0.1, so part 2 is caught mid-run.
    let m = s.sim("mill", 0.1);
    let lines = 300;
    let job = s.upload(m.id, "bracket", back_and_forth(lines, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    // Without a confirm between parts: part 2 follows part 1 by itself.
    add(&s, m.id, job, 3, false);
    let first = confirm(&s, m.id);
    let second = wait_for(T, "part 2 to start by itself", || {
        let q = queue(&s, m.id);
        let run = q["run"].as_i64()?;
        (q["state"] == "running" && run != first).then_some(run)
    });
    assert_every_line_once(&m.executed(), first, lines as i64);
    wait_for(T, "part 2 to run a few lines", || {
        (m.count_of(second) >= 3).then_some(())
    });
    // A confirm while a part runs is refused and starts nothing.
    s.post_empty(&format!("/api/v1/machines/{}/queue/confirm", m.id))
        .expect_error(409, "queue_not_waiting");
    s.command(m.id, "stop", json!({})).expect(200);
    let q = wait_queue(&s, m.id, "held");
    let reason = q["reason"].as_str().unwrap();
    assert!(reason.contains("cancelled"), "{q}");
    assert_eq!(
        q["entries"][0]["done"], 1,
        "the stopped part is not counted: {q}"
    );
    s.wait_machine_state(m.id, "idle", T);
    // Held: nothing starts, and a confirm is refused naming the hold.
    let msg = s
        .post_empty(&format!("/api/v1/machines/{}/queue/confirm", m.id))
        .expect_error(409, "queue_not_waiting");
    assert!(msg.contains("held"), "{msg}");
    assert_eq!(queue(&s, m.id)["state"], "held");
    assert_eq!(
        runs_logged(&m),
        BTreeSet::from([first, second]),
        "nothing after the stopped part"
    );
    // The hold is in the audit log with its reason.
    let hold = s
        .events("types=queue.hold", Some(0))
        .until(T, "queue.hold", |_| true)
        .pop()
        .unwrap();
    assert_eq!(hold.data["data"]["run"], second, "{:?}", hold.data);

    // Released: the next part waits for a confirm (never starts by itself after a hold).
    let q = s
        .post_empty(&format!("/api/v1/machines/{}/queue/release", m.id))
        .expect(200);
    assert_eq!(q["state"], "waiting_confirm", "{q}");
    assert_eq!(
        runs_logged(&m),
        BTreeSet::from([first, second]),
        "nothing started on release"
    );
    let third = confirm(&s, m.id);
    wait_for(T, "the confirmed part to complete", || {
        (m.count_of(third) == lines).then_some(())
    });
    s.command(m.id, "stop", json!({})).expect(200);
}

#[test]
fn a_kill_while_the_queue_waits_leaves_it_waiting_and_nothing_starts() {
    let mut s = Server::start();
    let m = s.sim("mill", 0.1);
    let lines = 30;
    let job = s.upload(m.id, "bracket", back_and_forth(lines, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    add(&s, m.id, job, 2, true);
    let first = confirm(&s, m.id);
    let q = wait_queue(&s, m.id, "waiting_confirm");
    assert_eq!(q["entries"][0]["done"], 1, "{q}");
    s.restart_after_kill();
    let q = queue(&s, m.id);
    assert_eq!(q["state"], "waiting_confirm", "after the restart: {q}");
    assert_eq!(q["entries"][0]["done"], 1, "{q}");
    s.wait_machine_state(m.id, "idle", T);
    assert_eq!(runs_logged(&m), BTreeSet::from([first]), "nothing started");
    // The confirm after the restart starts part 2, which completes.
    let second = confirm(&s, m.id);
    wait_queue(&s, m.id, "idle");
    assert_every_line_once(&m.executed(), second, lines as i64);
    assert_eq!(runs_logged(&m), BTreeSet::from([first, second]));
}

#[test]
fn a_kill_while_a_part_runs_brings_the_queue_back_held() {
    let mut s = Server::start();
    let m = s.sim("mill", 0.1);
    let lines = 300;
    let job = s.upload(m.id, "bracket", back_and_forth(lines, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    add(&s, m.id, job, 2, false);
    let first = confirm(&s, m.id);
    wait_for(T, "part 1 to run a few lines", || {
        (m.count_of(first) >= 3).then_some(())
    });
    s.restart_after_kill();
    let q = wait_queue(&s, m.id, "held");
    assert!(q["reason"].as_str().unwrap().contains("interrupted"), "{q}");
    assert_eq!(q["entries"][0]["done"], 0, "{q}");
    s.wait_machine_state(m.id, "idle", T);
    assert_eq!(runs_logged(&m), BTreeSet::from([first]), "nothing started");
    s.post_empty(&format!("/api/v1/machines/{}/queue/release", m.id))
        .expect(200);
    assert_eq!(queue(&s, m.id)["state"], "waiting_confirm");
}

#[test]
fn dispatch_gives_the_part_to_the_free_machine_and_names_why_others_refused() {
    let s = Server::start();
    let busy = s.sim("busy", 0.1);
    let free = s.sim("free", 0.1);
    let lines = 30;
    // Busy with a long job (about 30 s) for the whole test.
    let (long_job, long_run) =
        s.upload_and_start(busy.id, "long", &back_and_forth(3000, 1.0, 600.0));
    s.wait_job_state(long_job, "running", T);
    let job = s.upload(busy.id, "bracket", back_and_forth(lines, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let v = s
        .post(
            "/api/v1/queue",
            &json!({"job": job, "machines": [busy.id, free.id]}),
        )
        .expect(200);
    assert_eq!(v["machine"], free.id, "{v}");
    assert_eq!(v["refused"][0]["machine"], busy.id, "{v}");
    assert_eq!(v["refused"][0]["code"], "machine_busy", "{v}");
    let run = v["run"].as_i64().unwrap();
    let copy = v["job"].as_i64().unwrap();
    assert_ne!(copy, job, "a job of the chosen machine: {v}");
    s.wait_job_state(copy, "completed", T);
    assert_every_line_once(&free.executed(), run, lines as i64);
    assert!(
        !runs_logged(&busy).contains(&run),
        "the part did not run on the busy machine"
    );

    // Again: the free machine runs the same job (no second copy of the program). The job is
    // completed when its last line ran; the machine says idle on its next status read, and
    // dispatch takes only an idle machine, so wait for that as a client would.
    s.wait_machine_state(free.id, "idle", T);
    let again = s
        .post(
            "/api/v1/queue",
            &json!({"job": job, "machines": [busy.id, free.id]}),
        )
        .expect(200);
    assert_eq!(
        (&again["machine"], &again["job"]),
        (&v["machine"], &v["job"]),
        "{again}"
    );
    let run2 = again["run"].as_i64().unwrap();
    wait_for(T, "the second part to complete", || {
        (free.count_of(run2) == lines).then_some(())
    });
    s.wait_job_state(copy, "completed", T);
    // Both busy now: 409 naming why each refused.
    let (_, other_run) = s.upload_and_start(free.id, "long2", &back_and_forth(3000, 1.0, 600.0));
    let r = s.post(
        "/api/v1/queue",
        &json!({"job": job, "machines": [busy.id, free.id]}),
    );
    assert_eq!(r.status, 409, "{}", r.text);
    assert_eq!(r.body["code"], "no_machine_free", "{}", r.text);
    let refused = r.body["refused"].as_array().unwrap();
    assert_eq!(refused.len(), 2, "{}", r.text);
    assert!(
        refused.iter().all(|x| x["code"] == "machine_busy"),
        "{}",
        r.text
    );
    assert!(!runs_logged(&free).contains(&long_run) && other_run != long_run);
    s.command(busy.id, "stop", json!({})).expect(200);
    s.command(free.id, "stop", json!({})).expect(200);
}

/// A part given to another machine is checked as that machine's own upload would be: with its
/// tool table. A machine without the program's cutter refuses it naming the line; the machine
/// that has it runs a job whose analysis is its own (its cutter's bounds, not the source's).
#[test]
fn dispatch_checks_the_program_with_the_chosen_machines_tool_table() {
    const COMPENSATED: &str =
        "G21 G90 F600\nG0 X-10 Y-10 Z2\nG41 D3 G1 X0 Y0\nG1 Z-1\nG1 X40\nG1 Y20\nG0 Z2\nG40 G0 X50 Y30\nM2\n";
    let s = Server::start();
    let thin = s.sim("thin", 0.0);
    let none = s.sim("none", 0.0);
    let thick = s.sim("thick", 0.0);
    for (m, d) in [(thin.id, 2.0), (thick.id, 10.0)] {
        s.put(
            &format!("/api/v1/machines/{m}/tools"),
            &json!([{"tool": 3, "diameter_mm": d}]),
        )
        .expect(200);
    }
    let job = s.upload(thin.id, "compensated", COMPENSATED);
    assert_eq!(job["analysis"]["cutting_bounds"]["max"][0], 39.0, "{job}");
    let v = s
        .post(
            "/api/v1/queue",
            &json!({"job": job["id"], "machines": [none.id, thick.id]}),
        )
        .expect(200);
    assert_eq!(v["machine"], thick.id, "{v}");
    let refused = &v["refused"][0];
    assert_eq!(
        (&refused["machine"], &refused["code"]),
        (&json!(none.id), &json!("invalid_gcode")),
        "{v}"
    );
    let why = refused["message"].as_str().unwrap_or_default();
    assert!(why.contains("line 3") && why.contains("D3"), "{v}");
    let copy = s.get(&format!("/api/v1/jobs/{}", v["job"])).expect(200);
    assert_eq!(
        copy["analysis"]["cutting_bounds"]["max"][0], 35.0,
        "the copy's analysis is the thick cutter's: {copy}"
    );
    s.wait_job_state(v["job"].as_i64().unwrap(), "completed", T);
    assert!(!runs_logged(&none).contains(&v["run"].as_i64().unwrap()));
}

#[test]
fn queue_changes_are_audited_and_entries_reorder_and_leave() {
    let s = Server::start();
    let m = s.sim("mill", 0.1);
    let a = s.upload(m.id, "a", back_and_forth(10, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let b = s.upload(m.id, "b", back_and_forth(10, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    add(&s, m.id, a, 2, true);
    let q = add(&s, m.id, b, 1, true);
    let (ea, eb) = (
        q["entries"][0]["id"].as_i64().unwrap(),
        q["entries"][1]["id"].as_i64().unwrap(),
    );
    let q = s
        .post(
            &format!("/api/v1/machines/{}/queue/{eb}/move", m.id),
            &json!({"position": 1}),
        )
        .expect(200);
    assert_eq!(q["entries"][0]["id"], eb, "{q}");
    assert_eq!(q["entries"][0]["state"], "waiting_confirm", "{q}");
    assert_eq!(q["entries"][1]["state"], "queued", "{q}");
    // The next part is b's now.
    let run = confirm(&s, m.id);
    let started = s.get(&format!("/api/v1/jobs/{b}")).expect(200);
    assert_eq!(started["run"]["id"], run, "{started}");
    wait_queue(&s, m.id, "waiting_confirm");
    s.send(s.req(
        reqwest::Method::DELETE,
        &format!("/api/v1/machines/{}/queue/{ea}", m.id),
    ))
    .expect(200);
    assert_eq!(queue(&s, m.id)["state"], "idle");
    s.post(
        &format!("/api/v1/machines/{}/queue", m.id),
        &json!({"job": a, "count": 0}),
    )
    .expect_error(422, "invalid_field");
    let kinds: Vec<String> = s
        .events(
            "types=queue.add,queue.move,queue.confirm,queue.remove,queue.done",
            Some(0),
        )
        .until(T, "queue.done", |e| e.event == "queue.done")
        .iter()
        .map(|e| e.event.clone())
        .collect();
    for k in [
        "queue.add",
        "queue.move",
        "queue.confirm",
        "queue.remove",
        "queue.done",
    ] {
        assert!(kinds.iter().any(|x| x == k), "{k} missing from {kinds:?}");
    }
}

/// A fresh database on this test process's throwaway PostgreSQL.
fn fresh_database() -> String {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(fresa_core::store::test_postgres::fresh_database())
}

/// A node of the store at `database`, beating fast (as `store::nodes` does).
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

#[test]
fn on_postgresql_a_waiting_queue_survives_a_kill_and_dispatch_reaches_another_node() {
    let db = fresh_database();
    let mut s = node(&db, "hall-a");
    let m = s.sim("mill", 0.1);
    let lines = 30;
    let job = s.upload(m.id, "bracket", back_and_forth(lines, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    add(&s, m.id, job, 2, true);
    let first = confirm(&s, m.id);
    wait_queue(&s, m.id, "waiting_confirm");
    s.restart_after_kill();
    let q = queue(&s, m.id);
    assert_eq!(q["state"], "waiting_confirm", "after the restart: {q}");
    assert_eq!(q["entries"][0]["done"], 1, "{q}");
    assert_eq!(runs_logged(&m), BTreeSet::from([first]), "nothing started");
    let second = confirm(&s, m.id);
    wait_queue(&s, m.id, "idle");
    assert_every_line_once(&m.executed(), second, lines as i64);

    // Dispatch through another node: it asks hall-a, which drives the machine.
    let b = node(&db, "hall-b");
    wait_for(T, "node B to see the machine idle", || {
        let v = b.get(&format!("/api/v1/machines/{}", m.id)).expect(200);
        (v["state"] == "idle").then_some(())
    });
    let v = b
        .post("/api/v1/queue", &json!({"job": job, "machines": [m.id]}))
        .expect(200);
    assert_eq!(v["machine"], m.id, "{v}");
    let third = v["run"].as_i64().unwrap();
    wait_for(
        T,
        "the dispatched part to complete on hall-a's machine",
        || (m.count_of(third) == lines).then_some(()),
    );
    assert_every_line_once(&m.executed(), third, lines as i64);
}

#[test]
fn the_cli_adds_lists_and_confirms() {
    let s = Server::start();
    let m = s.sim("mill", 0.1);
    let job = s.upload(m.id, "bracket", back_and_forth(30, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    let (id, job_s) = (m.id.to_string(), job.to_string());
    let text = |o: std::process::Output| {
        assert!(o.status.success(), "{}", fresa_tests::output_text(&o));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let out = text(s.cli(&["queue", "add", &id, "--job", &job_s, "--count", "2"]));
    assert!(out.contains("waiting_confirm"), "{out}");
    let out = text(s.cli(&["queue", "list", &id]));
    assert!(
        out.contains("waiting_confirm") && out.contains("ENTRY"),
        "{out}"
    );
    let out = text(s.cli(&["queue", "confirm", &id]));
    assert!(out.contains("run"), "{out}");
    let q = wait_queue(&s, m.id, "waiting_confirm");
    assert_eq!(q["entries"][0]["done"], 1, "{q}");
    let out = text(s.cli(&["queue", "list", &id, "--json"]));
    let v: Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["entries"][0]["done"], 1, "{v}");
    // Refusals name the problem and fail the command.
    let o = s.cli(&["queue", "release", &id]);
    assert!(!o.status.success());
    assert!(
        fresa_tests::output_text(&o).contains("queue_not_held"),
        "{}",
        fresa_tests::output_text(&o)
    );
}

#[test]
fn a_refused_start_keeps_the_queue_waiting_and_dispatch_skips_a_machine_past_whose_travel_it_goes()
{
    let s = Server::start();
    // Soft limits X -10..100: the program below (X 150) leaves them.
    let small = s.sim_with(
        "small",
        0.1,
        json!({"config": {
            "time_scale": 0.1,
            "execution_log": s.data_dir().join("exec-small.log"),
            "travel": {"x": [-10, 100], "y": [-10, 200], "z": [-100, 0]},
        }}),
    );
    let big = s.sim("big", 0.1);
    let mut program = String::from("G21 G90\nG0 X150\n");
    for i in 0..10 {
        program.push_str(&format!("G1 X{} F3000\n", 150 + i % 2));
    }
    let lines = 12;
    let job = s.upload(small.id, "wide", program)["id"].as_i64().unwrap();
    let q = add(&s, small.id, job, 1, true);
    let entry = q["entries"][0]["id"].as_i64().unwrap();
    // The confirm gets the start's refusal; the queue still waits and nothing ran.
    let r = s.post_empty(&format!("/api/v1/machines/{}/queue/confirm", small.id));
    assert_eq!(r.status, 422, "{}", r.text);
    let q = queue(&s, small.id);
    assert_eq!(q["state"], "waiting_confirm", "{q}");
    assert_eq!(q["entries"][0]["done"], 0, "{q}");
    assert!(
        small.executed().is_empty(),
        "nothing ran on the small machine"
    );

    // Dispatch: the small machine (its queue emptied) refuses the program, the big one runs it.
    s.send(s.req(
        reqwest::Method::DELETE,
        &format!("/api/v1/machines/{}/queue/{entry}", small.id),
    ))
    .expect(200);
    let v = s
        .post(
            "/api/v1/queue",
            &json!({"job": job, "machines": [small.id, big.id]}),
        )
        .expect(200);
    assert_eq!(v["machine"], big.id, "{v}");
    assert_eq!(v["refused"][0]["machine"], small.id, "{v}");
    assert_eq!(
        v["refused"][0]["code"], r.body["code"],
        "the start's own refusal: {v}"
    );
    let run = v["run"].as_i64().unwrap();
    wait_for(T, "the part to complete on the big machine", || {
        (big.count_of(run) == lines).then_some(())
    });
    assert_every_line_once(&big.executed(), run, lines as i64);
    assert!(
        small.executed().is_empty(),
        "nothing ran on the small machine"
    );
}
