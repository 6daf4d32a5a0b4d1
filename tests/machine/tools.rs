//! Machines' tool tables (`/api/v1/machines/{id}/tools`): validation naming the field, roles,
//! persistence across a restart, the audit event, and the upload check and the backend using
//! the machine's own table for cutter compensation (G41/G42 D).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json;
use fresa_tests::serde_json::{json, Value};
use fresa_tests::{output_text, Opts, Server};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn tools_path(m: i64) -> String {
    format!("/api/v1/machines/{m}/tools")
}

#[test]
fn tool_tables_are_validated_and_survive_a_restart() {
    let mut s = Server::start();
    let m = s.sim("m", 0.0).id;
    let path = tools_path(m);
    assert_eq!(s.get(&path).expect(200), json!([]));

    // Each mistake names the field.
    for (body, field) in [
        (
            json!([{"tool": 1, "diameter_mm": 6.0}, {"tool": 2, "diameter_mm": "wide"}]),
            "diameter_mm",
        ),
        (
            json!([{"tool": 1, "diameter_mm": 6.0}, {"tool": 2, "diameter_mm": 1e9}]),
            "tools[1].diameter_mm",
        ),
        (json!([{"tool": 0, "diameter_mm": 6.0}]), "tools[0].tool"),
        (
            json!([{"tool": 3, "diameter_mm": 6.0}, {"tool": 3, "diameter_mm": 4.0}]),
            "tool 3 is listed twice",
        ),
        (
            json!([{"tool": 3, "diameter_mm": 6.0, "description": "a\u{7}b"}]),
            "tools[0].description",
        ),
        (json!([{"tool": 3, "diameter": 6.0}]), "diameter"),
    ] {
        let r = s.put(&path, &body);
        assert!(
            r.status == 422 || r.status == 400,
            "{body}: {} {}",
            r.status,
            r.text
        );
        assert!(r.text.contains(field), "{body}: {}", r.text);
    }
    assert_eq!(s.get(&path).expect(200), json!([]), "nothing stored");

    let table = json!([
        {"tool": 8, "diameter_mm": 3.175, "length_mm": 42.5, "description": "1/8 in end mill"},
        {"tool": 1, "diameter_mm": 6.0},
    ]);
    let stored = s.put(&path, &table).expect(200);
    assert_eq!(stored[0]["tool"], 1, "sorted by number: {stored}");
    assert_eq!(stored[1]["length_mm"], 42.5);
    s.put(
        &format!("{path}/4"),
        &json!({"diameter_mm": 10.0, "description": "10 mm"}),
    )
    .expect(200);
    s.put(&format!("{path}/4"), &json!({"diameter_mm": f64::MAX}))
        .expect_error(422, "invalid_field");
    s.send(s.req(reqwest::Method::DELETE, &format!("{path}/1")))
        .expect(204);
    s.send(s.req(reqwest::Method::DELETE, &format!("{path}/1")))
        .expect_error(404, "unknown_tool");
    s.get(&tools_path(999)).expect_error(404, "unknown_machine");
    s.put(&tools_path(999), &json!([]))
        .expect_error(404, "unknown_machine");

    let before = s.get(&path).expect(200);
    let numbers: Vec<i64> = before
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["tool"].as_i64().unwrap())
        .collect();
    assert_eq!(numbers, [4, 8]);
    s.restart_after_kill();
    assert_eq!(s.get(&path).expect(200), before);

    // Every change is in the audit log, with who made it.
    let events = s.events("types=machine.tools", Some(0));
    // Replace, set tool 4, delete tool 1 (the refused requests changed nothing).
    let seen: Vec<Value> = (0..3)
        .map(|_| events.next(T).expect("a machine.tools event").data)
        .collect();
    assert!(seen[0]["data"]["replaced"] == true, "{seen:?}");
    assert_eq!(seen[1]["data"]["set"]["tool"], 4, "{seen:?}");
    assert_eq!(seen[2]["data"]["deleted"], 1, "{seen:?}");
    assert!(seen.iter().all(|e| e["machine"] == m), "{seen:?}");
}

#[test]
fn viewers_read_tool_tables_and_only_admins_change_them() {
    let mut s = Server::unstarted(Opts {
        listen: "0.0.0.0:0".into(),
        ..Opts::default()
    });
    let admin = s.create_token("admin", "alice");
    let operator = s.create_token("operator", "olga");
    let viewer = s.create_token("viewer", "victor");
    s.spawn().unwrap();
    s.token = Some(admin.clone());
    let m = s.sim("m", 0.0).id;
    let path = tools_path(m);
    let body = json!([{"tool": 1, "diameter_mm": 6.0}]);
    for token in [&viewer, &operator] {
        s.token = Some(token.clone());
        s.get(&path).expect(200);
        s.put(&path, &body).expect_error(403, "forbidden");
        s.put(&format!("{path}/1"), &json!({"diameter_mm": 6.0}))
            .expect_error(403, "forbidden");
        s.send(s.req(reqwest::Method::DELETE, &format!("{path}/1")))
            .expect_error(403, "forbidden");
    }
    s.token = Some(admin);
    s.put(&path, &body).expect(200);
}

/// A pocket side cut with compensation: the tool runs left of X0 -> X40, i.e. at Y = +radius.
const COMPENSATED: &str = "G21 G90 F600\nG0 X-10 Y-10 Z2\nG41 D3 G1 X0 Y0\nG1 Z-1\nG1 X40\nG1 Y20\nG0 Z2\nG40 G0 X50 Y30\nM2\n";

#[test]
fn uploads_use_their_machines_tool_table() {
    let s = Server::start();
    let thin = s.sim("thin", 0.0).id;
    let thick = s.sim("thick", 0.0).id;
    let none = s.sim("none", 0.0).id;
    s.put(&tools_path(thin), &json!([{"tool": 3, "diameter_mm": 2.0}]))
        .expect(200);
    s.put(
        &tools_path(thick),
        &json!([{"tool": 3, "diameter_mm": 10.0}]),
    )
    .expect(200);

    let a = s.upload(thin, "thin", COMPENSATED);
    let b = s.upload(thick, "thick", COMPENSATED);
    let cut = |j: &Value| j["analysis"]["cutting_bounds"].clone();
    // X0 -> X40 left of the path runs at Y = +r; the X40 side runs at X = 40 - r.
    assert_eq!(cut(&a)["max"][0], 39.0, "{a}");
    assert_eq!(cut(&b)["max"][0], 35.0, "{b}");
    assert_ne!(cut(&a), cut(&b));

    // A machine without tool 3 refuses the program, naming line and D word.
    let msg = s
        .post_bytes("/api/v1/jobs?machine=3&name=none", COMPENSATED)
        .expect_error(422, "invalid_gcode");
    assert!(
        msg.contains("line 3, column 5") && msg.contains("D3") && msg.contains("tool table"),
        "{msg}"
    );
    assert_eq!(none, 3);

    // The backend runs the compensated path the check validated.
    let id = b["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    s.wait_job_state(id, "completed", T);
}

#[test]
fn the_cli_loads_tool_tables_and_checks_programs_with_one() {
    let s = Server::start();
    let m = s.sim("m", 0.0).id;
    let dir = s.root().join("cli-tools");
    std::fs::create_dir_all(&dir).unwrap();
    let table = dir.join("tools.json");
    std::fs::write(
        &table,
        r#"[{"tool": 3, "diameter_mm": 4.0, "description": "4 mm end mill"}]"#,
    )
    .unwrap();
    let m_str = m.to_string();
    let out = s.cli(&[
        "machine",
        "tools",
        &m_str,
        "--load",
        table.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", output_text(&out));
    let listed = s.cli(&["machine", "tools", &m_str]);
    let text = String::from_utf8_lossy(&listed.stdout);
    assert!(
        text.contains("4 mm end mill") && text.contains('3'),
        "{text}"
    );
    assert_eq!(s.get(&tools_path(m)).expect(200)[0]["diameter_mm"], 4.0);

    // `fresa gcode check --tools` takes the same file (and what the API gives).
    let program = dir.join("p.ngc");
    std::fs::write(&program, COMPENSATED).unwrap();
    let check = |tools: Option<&std::path::Path>| {
        let mut cmd = fresa_tests::fresa_cmd();
        cmd.args(["gcode", "check", "--json"]).arg(&program);
        if let Some(t) = tools {
            cmd.arg("--tools").arg(t);
        }
        cmd.output().unwrap()
    };
    let ok = check(Some(&table));
    assert!(ok.status.success(), "{}", output_text(&ok));
    let a: Value = serde_json::from_slice(&ok.stdout).unwrap();
    assert_eq!(a["cutting_bounds"]["max"][0], 38.0, "{a}");
    let missing = check(None);
    assert!(!missing.status.success());
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(
        err.contains("line 3, column 5") && err.contains("D3"),
        "{err}"
    );
    std::fs::write(&table, r#"{"tool": 3}"#).unwrap();
    let bad = check(Some(&table));
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("JSON array"),
        "{}",
        output_text(&bad)
    );
}

#[test]
fn g10_offsets_are_folded_in_and_the_stored_analysis_shows_them() {
    let s = Server::start();
    let m = s.sim("m", 0.0).id;
    let program =
        "G21 G90 F600\nG0 X0 Y0 Z5\nG10 L2 P1 X10 Y5\nG1 X1 Y1\nG10 L20 P0 X0\nG1 X2\nM2\n";
    let job = s.upload(m, "g10", program);
    let notes = &job["analysis"]["offset_changes"];
    assert_eq!(notes[0]["command"], "G10 L2 P1", "{job}");
    assert_eq!(notes[0]["offset"], json!([10.0, 5.0, 0.0]), "{job}");
    assert_eq!(notes[1]["command"], "G10 L20 P1", "{job}");
    // X1 Y1 in the moved G54 is X11 Y6 in the machine's own; after L20 X0 there, X2 is X13.
    assert_eq!(job["analysis"]["cutting_bounds"]["max"][0], 13.0, "{job}");
    let id = job["id"].as_i64().unwrap();
    s.job_action(id, "start").expect(200);
    s.wait_job_state(id, "completed", T);
    // The last status may still be on its way when the store says completed.
    let st = s.wait_status(m, T, "idle after the G10 job", |st| st["state"] == "idle");
    assert_eq!(st["work_position"]["x"], 13.0, "{st}");
    // The machine's stored offsets are the store's, unchanged by the program.
    let off = s.get(&format!("/api/v1/machines/{m}/offsets")).expect(200);
    assert_eq!(off["offsets"]["G54"]["x"], 0.0, "{off}");
}
