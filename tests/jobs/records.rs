//! The shop's records (issue 28, part 2): a part record per run that ended (checked against the
//! runs, the sim's execution log and the audit log; CSV against JSON), utilisation against the
//! sim's execution log, a maintenance interval raising `machine.maintenance_due` once and its
//! "done" audited, counters that survive restarts and never go backwards, and part records on
//! PostgreSQL.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{self, json, Value};
use fresa_tests::{assert_every_line_once, back_and_forth, sha256_hex, wait_for, Server};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// The part records of `machine` once there are `n`, newest first.
fn parts_of(s: &Server, machine: i64, n: usize) -> Vec<Value> {
    wait_for(T, &format!("{n} part records of machine {machine}"), || {
        let v = s
            .get(&format!("/api/v1/parts?machine={machine}"))
            .expect(200);
        let parts = v["parts"].as_array().cloned().unwrap_or_default();
        (parts.len() >= n).then_some(parts)
    })
}

/// RFC 4180 as the server writes it: fields separated by commas, quoted ones with `""` for a
/// quote; rows end with a newline.
fn parse_csv(text: &str) -> Vec<Vec<String>> {
    let mut rows = Vec::new();
    let (mut row, mut field) = (Vec::new(), String::new());
    let (mut quoted, mut chars) = (false, text.chars().peekable());
    while let Some(c) = chars.next() {
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                field.push('"');
                chars.next();
            }
            (true, '"') => quoted = false,
            (true, c) => field.push(c),
            (false, '"') => quoted = true,
            (false, ',') => row.push(std::mem::take(&mut field)),
            (false, '\n') => {
                row.push(std::mem::take(&mut field));
                rows.push(std::mem::take(&mut row));
            }
            (false, c) => field.push(c),
        }
    }
    assert!(
        field.is_empty() && row.is_empty(),
        "CSV ends mid-row: {text}"
    );
    rows
}

fn get_csv(s: &Server, path: &str) -> Vec<Vec<String>> {
    let r = s
        .req(reqwest::Method::GET, path)
        .header("accept", "text/csv")
        .send()
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let ct = r.headers()["content-type"].to_str().unwrap().to_string();
    assert!(ct.starts_with("text/csv"), "{ct}");
    parse_csv(&r.text().unwrap())
}

/// A completed and a cancelled run give two part records with the right outcome, lines,
/// program and operator (the audit log's), and the CSV says what the JSON says.
#[test]
fn part_records_match_the_runs_and_their_csv_matches_the_json() {
    let s = Server::start();
    let me = s.get("/api/v1/whoami").expect(200)["name"]
        .as_str()
        .unwrap()
        .to_string();
    let m = s.sim("parts", 0.1);
    s.wait_machine_state(m.id, "idle", T);

    // A short program to completion.
    let short = back_and_forth(20, 1.0, 600.0);
    let a = s.upload(m.id, "short.nc", short.clone());
    let a_id = a["id"].as_i64().unwrap();
    s.job_action(a_id, "start").expect(200);
    let done = s.wait_job_state(a_id, "completed", T);
    let a_run = done["run"]["id"].as_i64().unwrap();
    assert_every_line_once(&m.executed(), a_run, 20);

    // A long one, cancelled part-way.
    let long = back_and_forth(600, 1.0, 600.0);
    let b = s.upload(m.id, "long.nc", long.clone());
    let b_id = b["id"].as_i64().unwrap();
    s.job_action(b_id, "start").expect(200);
    s.wait_status(m.id, T, "a few lines run", |st| {
        st["job"]["line"].as_i64().unwrap_or(0) >= 5
    });
    s.job_action(b_id, "cancel").expect(200);
    let cancelled = s.wait_job_state(b_id, "cancelled", T);
    let b_run = cancelled["run"]["id"].as_i64().unwrap();
    let b_line = cancelled["line"].as_i64().unwrap();

    let parts = parts_of(&s, m.id, 2);
    assert_eq!(parts.len(), 2, "{parts:#?}");
    // Newest first.
    let (pb, pa) = (&parts[0], &parts[1]);
    assert_eq!(
        (pa["run"].as_i64(), pb["run"].as_i64()),
        (Some(a_run), Some(b_run))
    );
    assert_eq!(pa["outcome"], "completed", "{pa}");
    assert_eq!(pb["outcome"], "cancelled", "{pb}");
    assert_eq!(pa["program_sha256"], sha256_hex(short.as_bytes()).as_str());
    assert_eq!(pb["program_sha256"], sha256_hex(long.as_bytes()).as_str());
    assert_eq!(
        (pa["program_name"].as_str(), pa["job"].as_i64()),
        (Some("short.nc"), Some(a_id))
    );
    assert_eq!(
        (pa["lines_run"].as_i64(), pa["last_line"].as_i64()),
        (Some(20), Some(20))
    );
    assert_eq!(pa["line_count"], 20);
    // The cancelled run: its last acknowledged line, which the sim executed (and no more were
    // acknowledged than executed).
    assert_eq!(pb["last_line"].as_i64(), Some(b_line), "{pb}");
    assert_eq!(pb["lines_run"].as_i64(), Some(b_line));
    assert!(
        m.count_of(b_run) as i64 >= b_line && b_line < 600,
        "executed {} acknowledged {b_line}",
        m.count_of(b_run)
    );
    for p in [pa, pb] {
        assert_eq!(p["operators"], json!([me.clone()]), "{p}");
        assert_eq!(p["machine"], m.id);
        assert_eq!(p["work_offset"], "G54");
        assert!(p["estimate_s"].as_f64().unwrap() > 0.0, "{p}");
        let actual = p["actual_s"].as_f64().unwrap();
        let span = (p["ended_at"].as_i64().unwrap() - p["started_at"].as_i64().unwrap()) as f64;
        assert!((actual - span / 1000.0).abs() < 1e-6 && actual > 0.0, "{p}");
        assert_eq!(p["tool_table_sha256"].as_str().unwrap().len(), 64);
        assert_eq!(p["confirmations"], json!([]), "no queue, no confirmations");
    }
    // The completed run's actual time against the sim's own record of its lines.
    let times = m.line_times(a_run);
    let logged = (times.last().unwrap().1 - times.first().unwrap().1) as f64 / 1000.0;
    assert!(
        pa["actual_s"].as_f64().unwrap() >= logged,
        "the run lasted at least as long as its lines: {pa} vs {logged}"
    );

    // Filters: by job, by time.
    let only_a = s.get(&format!("/api/v1/parts?job={a_id}")).expect(200);
    assert_eq!(only_a["parts"].as_array().unwrap().len(), 1, "{only_a}");
    assert_eq!(only_a["parts"][0]["run"], a_run);
    let after = pa["ended_at"].as_i64().unwrap() + 1;
    let later = s
        .get(&format!("/api/v1/parts?machine={}&from={after}", m.id))
        .expect(200);
    assert_eq!(later["parts"].as_array().unwrap().len(), 1, "{later}");
    assert_eq!(later["parts"][0]["run"], b_run);
    // Pages: one per page, the cursor leads to the older one.
    let p1 = s
        .get(&format!("/api/v1/parts?machine={}&limit=1", m.id))
        .expect(200);
    assert_eq!(p1["parts"][0]["run"], b_run);
    let cursor = p1["next"].as_str().expect("a next page").to_string();
    let p2 = s
        .get(&format!(
            "/api/v1/parts?machine={}&limit=1&cursor={cursor}",
            m.id
        ))
        .expect(200);
    assert_eq!(p2["parts"][0]["run"], a_run);
    assert!(p2.get("next").is_none(), "{p2}");
    s.get("/api/v1/parts?limit=0")
        .expect_error(400, "invalid_query");
    s.get("/api/v1/parts?from=yesterday")
        .expect_error(400, "invalid_query");

    // CSV: the same records, field for field.
    let rows = get_csv(&s, &format!("/api/v1/parts?machine={}", m.id));
    let header = &rows[0];
    assert_eq!(rows.len(), 3, "{rows:?}");
    let col = |row: &Vec<String>, name: &str| -> String {
        let i = header
            .iter()
            .position(|h| h == name)
            .unwrap_or_else(|| panic!("no column {name}: {header:?}"));
        row[i].clone()
    };
    for (row, p) in rows[1..].iter().zip([pb, pa]) {
        for key in [
            "id",
            "run",
            "job",
            "machine",
            "line_count",
            "last_line",
            "lines_run",
            "started_at",
            "ended_at",
        ] {
            assert_eq!(col(row, key), p[key].to_string(), "{key}: {row:?} vs {p}");
        }
        for key in [
            "program_name",
            "program_sha256",
            "outcome",
            "work_offset",
            "tool_table_sha256",
            "machine_name",
        ] {
            assert_eq!(col(row, key), p[key].as_str().unwrap(), "{key}");
        }
        assert_eq!(col(row, "operators"), me);
        let est: f64 = col(row, "estimate_s").parse().unwrap();
        assert!((est - p["estimate_s"].as_f64().unwrap()).abs() < 0.001);
        let act: f64 = col(row, "actual_s").parse().unwrap();
        assert!((act - p["actual_s"].as_f64().unwrap()).abs() < 0.001);
    }

    // The CLI prints the server's CSV, and its table names both runs.
    let mid = m.id.to_string();
    let out = s.cli(&["parts", "--machine", &mid, "--csv"]);
    assert!(out.status.success(), "{}", fresa_tests::output_text(&out));
    assert_eq!(parse_csv(&String::from_utf8_lossy(&out.stdout)), rows);
    let out = s.cli(&["parts", "--machine", &mid]);
    let table = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success() && table.contains("cancelled") && table.contains("short.nc"),
        "{table}"
    );
}

/// The utilisation report's cutting seconds against the sim's execution log.
///
/// Tolerance: the machine's state changes are stamped when its tracker sees the status the
/// machine's task publishes (it wakes on each one; the sim reports a state change as an event at
/// once), so each end of the cutting interval is late by the event's way through the plugin
/// sink and the task plus the tracker's wake-up: milliseconds, under a loaded 2-core CI box
/// tens of them. The log stamps each line when it finished; the first line is a non-motion line
/// (it finishes as the run starts) and the machine goes idle when the last line finishes. So
/// the two spans agree to within 0.5 s (two ends, each a generous 250 ms).
#[test]
fn utilisation_cutting_seconds_match_the_execution_log() {
    let s = Server::start();
    let m = s.sim("util", 0.1);
    s.wait_machine_state(m.id, "idle", T);
    let program = format!("G21 G90\n{}", back_and_forth(400, 1.0, 600.0));
    let up = s.upload(m.id, "util.nc", program);
    let id = up["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    let job = s.wait_job_state(id, "completed", T);
    let run = job["run"]["id"].as_i64().unwrap();
    let times = m.line_times(run);
    assert_eq!(times.len(), 401);
    let logged = (times.last().unwrap().1 - times.first().unwrap().1) as f64 / 1000.0;
    assert!(
        logged > 2.0,
        "the run is long enough to measure: {logged} s"
    );
    s.wait_machine_state(m.id, "idle", T);

    // The state change to idle is written as it is seen: poll until the report has it.
    let report = wait_for(T, "the run's cutting time in the report", || {
        let r = s.get("/api/v1/reports/utilisation").expect(200);
        let mine = r["machines"]
            .as_array()
            .unwrap()
            .iter()
            .find(|x| x["machine"] == m.id)
            .cloned()?;
        (mine["total"]["cutting"].as_f64()? >= logged - 0.5
            && mine["total"]["idle"].as_f64()? > 0.0)
            .then_some(mine)
    });
    let cutting = report["total"]["cutting"].as_f64().unwrap();
    assert!(
        (cutting - logged).abs() <= 0.5,
        "cutting {cutting} s, execution log {logged} s: {report}"
    );
    assert_eq!(report["total"]["alarm"], 0.0);
    let days = report["days"].as_array().unwrap();
    let sum: f64 = days.iter().map(|d| d["cutting"].as_f64().unwrap()).sum();
    assert!(
        (sum - cutting).abs() < 1e-6,
        "days add up to the total: {report}"
    );

    // CSV: the same seconds.
    let rows = get_csv(&s, "/api/v1/reports/utilisation");
    assert_eq!(rows[0][..4], ["machine", "name", "day", "cutting_s"]);
    let csv_cutting: f64 = rows[1..]
        .iter()
        .filter(|r| r[0] == m.id.to_string())
        .map(|r| r[3].parse::<f64>().unwrap())
        .sum();
    assert!(csv_cutting >= cutting - 0.001, "{rows:?} vs {report}");
    // The metrics count the same states.
    let metrics = s.get("/metrics").text;
    assert!(
        metrics.contains(&format!(
            "fresa_machine_state_seconds_total{{machine=\"{}\",state=\"cutting\"}}",
            m.id
        )),
        "{metrics}"
    );
    let out = s.cli(&["report", "utilisation", "--json"]);
    assert!(out.status.success(), "{}", fresa_tests::output_text(&out));
    let cli: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(
        cli["machines"]
            .as_array()
            .unwrap()
            .iter()
            .any(|x| x["machine"] == m.id && x["total"]["cutting"].as_f64() >= Some(cutting)),
        "{cli}"
    );
    s.get("/api/v1/reports/utilisation?from=2026-01-02&to=2026-01-01")
        .expect_error(400, "invalid_query");
    s.get("/api/v1/reports/utilisation?from=2020-01-01&to=2026-01-01")
        .expect_error(400, "invalid_query");
}

/// The spindle-hours counter of the machine `m`.
fn spindle_hours(s: &Server, m: i64) -> f64 {
    s.get(&format!("/api/v1/machines/{m}/counters")).expect(200)["spindle_hours"]
        .as_f64()
        .unwrap()
}

/// A tiny spindle interval (0.0005 h = 1.8 s) raises `machine.maintenance_due` exactly once
/// however long the spindle runs on; marking it done is audited and starts it again.
#[test]
fn a_spindle_interval_raises_maintenance_due_once_and_done_is_audited() {
    let s = Server::start();
    let me = s.get("/api/v1/whoami").expect(200)["name"]
        .as_str()
        .unwrap()
        .to_string();
    let m = s.sim_with(
        "maint",
        1.0,
        json!({"maintenance": [{"name": "lubricate", "every_spindle_hours": 0.0005}]}),
    );
    s.wait_machine_state(m.id, "idle", T);
    let events = s.events("types=machine", Some(0));
    s.command(m.id, "set_output", json!({"name": "spindle", "on": true}))
        .expect(200);
    // Due once past 0.0005 h; then the spindle runs on for two more intervals.
    wait_for(T, "the interval to be due", || {
        let c = s
            .get(&format!("/api/v1/machines/{}/counters", m.id))
            .expect(200);
        (c["maintenance"][0]["due"] == true).then_some(())
    });
    wait_for(T, "three intervals of spindle time", || {
        (spindle_hours(&s, m.id) >= 0.0015).then_some(())
    });
    s.command(m.id, "set_output", json!({"name": "spindle", "on": false}))
        .expect(200);
    let metrics = s.get("/metrics").text;
    assert!(
        metrics.contains(&format!(
            "fresa_maintenance_due{{machine=\"{}\",name=\"lubricate\"}} 1",
            m.id
        )),
        "{metrics}"
    );

    let done = s
        .post_empty(&format!(
            "/api/v1/machines/{}/maintenance/lubricate/done",
            m.id
        ))
        .expect(200);
    assert_eq!(done["due"], false, "{done}");
    assert!(done["since_done"].as_f64().unwrap() < 0.0005, "{done}");
    assert_eq!(done["done_by"], me.as_str());
    s.post_empty(&format!("/api/v1/machines/{}/maintenance/oil/done", m.id))
        .expect_error(404, "unknown_maintenance");

    // The audit log up to the "done": exactly one due for this machine, then the done, by us.
    let seen = events.until(T, "maintenance_done", |e| {
        e.event == "machine.maintenance_done"
    });
    let due: Vec<_> = seen
        .iter()
        .filter(|e| e.event == "machine.maintenance_due" && e.data["machine"] == m.id)
        .collect();
    assert_eq!(
        due.len(),
        1,
        "one due per crossing: {:#?}",
        due.iter().map(|e| &e.data).collect::<Vec<_>>()
    );
    assert_eq!(due[0].data["data"]["name"], "lubricate");
    assert_eq!(due[0].data["data"]["counter"], "spindle_hours");
    assert!(due[0].id.is_some(), "persisted (the audit log)");
    let done_event = seen.last().unwrap();
    assert_eq!(done_event.data["actor"], me.as_str());
    assert_eq!(done_event.data["data"]["name"], "lubricate");
    let c = s
        .get(&format!("/api/v1/machines/{}/counters", m.id))
        .expect(200);
    assert_eq!(c["maintenance"][0]["due"], false, "{c}");

    // Refused intervals name the field.
    let bad = s
        .post(
            "/api/v1/machines",
            &json!({"name": "bad", "backend": "sim-machine",
                    "maintenance": [{"name": "x", "every_spindle_hours": 1, "every_jobs": 2}]}),
        )
        .expect_error(422, "invalid_field");
    assert!(bad.contains("maintenance[0]"), "{bad}");
}

/// Counters survive a clean restart unchanged or higher, and a kill -9 loses at most the last
/// persist interval (5 s); they never go backwards across either.
#[test]
fn counters_survive_restarts_and_never_go_backwards() {
    let mut s = Server::start();
    let m = s.sim("count", 1.0);
    s.wait_machine_state(m.id, "idle", T);
    // Slow enough for the status the tracker samples to see each end (distance is summed
    // between status samples).
    let job = s.upload(m.id, "j.nc", back_and_forth(3, 20.0, 1200.0));
    s.job_action(job["id"].as_i64().unwrap(), "start")
        .expect(200);
    s.wait_job_state(job["id"].as_i64().unwrap(), "completed", T);
    s.command(m.id, "set_output", json!({"name": "spindle", "on": true}))
        .expect(200);
    let mut last = 0.0;
    wait_for(T, "some spindle time", || {
        let h = spindle_hours(&s, m.id);
        assert!(h >= last, "went backwards: {h} < {last}");
        last = h;
        (h > 1.0 / 3600.0).then_some(())
    });
    let before = s
        .get(&format!("/api/v1/machines/{}/counters", m.id))
        .expect(200);
    assert_eq!(before["jobs"], 1, "{before}");
    assert!(
        before["distance_mm"]["x"].as_f64().unwrap() >= 5.0,
        "{before}"
    );

    // A clean stop stores them as they were.
    s.terminate();
    s.spawn().unwrap();
    let after = wait_for(T, "counters read back", || {
        let c = s
            .get(&format!("/api/v1/machines/{}/counters", m.id))
            .expect(200);
        (c["loaded"] == true).then_some(c)
    });
    for key in ["spindle_hours", "motion_hours", "jobs"] {
        assert!(
            after[key].as_f64().unwrap() >= before[key].as_f64().unwrap(),
            "{key}: {before} -> {after}"
        );
    }
    assert!(after["distance_mm"]["x"].as_f64() >= before["distance_mm"]["x"].as_f64());

    // kill -9 after more spindle time: at most the last interval is lost, never what a
    // clean stop stored.
    s.command(m.id, "set_output", json!({"name": "spindle", "on": true}))
        .expect(200);
    let base = after["spindle_hours"].as_f64().unwrap();
    wait_for(T, "spindle time past two persist intervals", || {
        (spindle_hours(&s, m.id) > base + 12.0 / 3600.0).then_some(())
    });
    let seen = spindle_hours(&s, m.id);
    s.restart_after_kill();
    let back = wait_for(T, "counters read back after kill -9", || {
        let c = s
            .get(&format!("/api/v1/machines/{}/counters", m.id))
            .expect(200);
        (c["loaded"] == true).then_some(c)
    });
    let h = back["spindle_hours"].as_f64().unwrap();
    assert!(h >= base, "never below the stored value: {h} < {base}");
    // The persist interval plus the spindle reading's own lag (one tick).
    assert!(
        h >= seen - 7.0 / 3600.0,
        "lost more than an interval: {h} vs {seen}"
    );
}

/// Part records and counters on PostgreSQL.
#[test]
fn part_records_and_counters_on_postgresql() {
    let db = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(fresa_core::store::test_postgres::fresh_database());
    let mut s = Server::start_with_config(&format!("database_url = \"{db}\"\n"));
    let m = s.sim("pg", 0.0);
    s.wait_machine_state(m.id, "idle", T);
    let program = back_and_forth(30, 1.0, 600.0);
    let up = s.upload(m.id, "pg.nc", program.clone());
    let id = up["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    let job = s.wait_job_state(id, "completed", T);
    let parts = parts_of(&s, m.id, 1);
    assert_eq!(parts[0]["run"], job["run"]["id"]);
    assert_eq!(parts[0]["outcome"], "completed");
    assert_eq!(parts[0]["lines_run"], 30);
    assert_eq!(
        parts[0]["program_sha256"],
        sha256_hex(program.as_bytes()).as_str()
    );
    let rows = get_csv(&s, &format!("/api/v1/parts?job={id}"));
    assert_eq!(rows.len(), 2, "{rows:?}");
    // Counters stored upwards on PostgreSQL too (GREATEST), across a restart.
    let before = wait_for(T, "a job counted", || {
        let c = s
            .get(&format!("/api/v1/machines/{}/counters", m.id))
            .expect(200);
        (c["jobs"] == 1).then_some(c)
    });
    s.terminate();
    s.spawn().unwrap();
    let after = wait_for(T, "counters read back", || {
        let c = s
            .get(&format!("/api/v1/machines/{}/counters", m.id))
            .expect(200);
        (c["loaded"] == true).then_some(c)
    });
    assert_eq!(after["jobs"], before["jobs"], "{after}");
    let r = s.get("/api/v1/reports/utilisation").expect(200);
    assert!(
        r["machines"]
            .as_array()
            .unwrap()
            .iter()
            .any(|x| x["machine"] == m.id),
        "{r}"
    );
}
