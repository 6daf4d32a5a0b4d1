//! Bad input: every refusal is a 4xx JSON error whose message names the problem, and leaves
//! nothing half-written (no machine, no job, no file in `programs/` but the stored `<sha>.nc`).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{corpus, sha256_hex, Opts, Resp, Server};

const LIMIT: u64 = 4096;

struct Fixture {
    s: Server,
    machine: i64,
    good_file: String,
}

impl Fixture {
    fn new() -> Fixture {
        let s = Server::start_with(Opts {
            max_upload_bytes: Some(LIMIT),
            ..Opts::default()
        });
        let machine = s.sim("m", 0.0).id;
        let good = "G21 G90\nG0 X1 Y1\nG1 X2 F300\n";
        s.upload(machine, "good", good);
        Fixture {
            s,
            machine,
            good_file: format!("{}.nc", sha256_hex(good.as_bytes())),
        }
    }

    /// Nothing was added by a refused request.
    #[track_caller]
    fn assert_untouched(&self, what: &str) {
        let jobs = self.s.get("/api/v1/jobs").expect(200);
        assert_eq!(jobs.as_array().unwrap().len(), 1, "{what}: jobs {jobs}");
        assert_eq!(
            self.s.program_files(),
            std::slice::from_ref(&self.good_file),
            "{what}: stray files in programs/"
        );
        let machines = self.s.get("/api/v1/machines").expect(200);
        assert_eq!(
            machines.as_array().unwrap().len(),
            1,
            "{what}: machines {machines}"
        );
    }

    fn upload(&self, query: &str, body: impl Into<Vec<u8>>) -> Resp {
        self.s.post_bytes(&format!("/api/v1/jobs?{query}"), body)
    }

    fn upload_to_m(&self, body: impl Into<Vec<u8>>) -> Resp {
        self.upload(&format!("machine={}&name=x", self.machine), body)
    }
}

#[track_caller]
fn contains(msg: &str, parts: &[&str]) {
    for p in parts {
        assert!(msg.contains(p), "message {msg:?} does not name {p:?}");
    }
}

#[test]
fn bad_machine_requests_are_refused_and_create_nothing() {
    let f = Fixture::new();
    let s = &f.s;
    let post_raw = |body: &str, content_type: Option<&str>| {
        let mut rb = s
            .req(reqwest::Method::POST, "/api/v1/machines")
            .body(body.to_string());
        if let Some(ct) = content_type {
            rb = rb.header("content-type", ct);
        }
        s.send(rb)
    };

    // Malformed JSON and a missing content type.
    post_raw("{\"name\": \"x\", ", Some("application/json")).expect_error(400, "invalid_json");
    f.assert_untouched("malformed json");
    post_raw(r#"{"name":"x","backend":"sim-machine"}"#, None).expect_error(415, "invalid_json");
    f.assert_untouched("no content type");
    // An unknown field is named.
    let msg = s
        .post(
            "/api/v1/machines",
            &json!({"name": "x", "backend": "sim-machine", "colour": "red"}),
        )
        .expect_error(400, "invalid_json");
    contains(&msg, &["colour"]);
    // Unknown backend plugin: names it and what is loaded.
    let msg = s
        .post(
            "/api/v1/machines",
            &json!({"name": "x", "backend": "grbl-9000"}),
        )
        .expect_error(422, "unknown_backend");
    contains(&msg, &["grbl-9000", "sim-machine"]);
    f.assert_untouched("unknown backend");

    // Plugin config rejected: the plugin's reason, naming the key, is passed on.
    for (config, key) in [
        (json!({"time_scale": "fast"}), "time_scale"),
        (json!({"time_scale": -1.0}), "time_scale"),
        (json!({"rapid": 1000}), "rapid"),
        (json!({"travel": {"x": [2.0, 1.0]}}), "travel.x"),
    ] {
        let msg = s
            .post(
                "/api/v1/machines",
                &json!({"name": "x", "backend": "sim-machine", "config": config}),
            )
            .expect_error(422, "invalid_config");
        contains(&msg, &[key]);
        f.assert_untouched(&format!("config {config}"));
    }
    // Fields the server itself checks.
    for (body, field) in [
        (json!({"name": "  ", "backend": "sim-machine"}), "name"),
        (
            json!({"name": "x", "backend": "sim-machine", "config": [1]}),
            "config",
        ),
        (
            json!({"name": "x", "backend": "sim-machine", "max_jog_mm": -1.0}),
            "max_jog_mm",
        ),
        (
            json!({"name": "x", "backend": "sim-machine", "max_feed_mm_min": 0.0}),
            "max_feed_mm_min",
        ),
    ] {
        let msg = s
            .post("/api/v1/machines", &body)
            .expect_error(422, "invalid_field");
        contains(&msg, &[field]);
        f.assert_untouched(&format!("body {body}"));
    }

    // Unknown ids.
    let msg = s.get("/api/v1/jobs/999").expect_error(404, "unknown_job");
    contains(&msg, &["999"]);
    s.get("/api/v1/jobs/999/gcode")
        .expect_error(404, "unknown_job");
    s.job_action(999, "start").expect_error(404, "unknown_job");
    s.get("/api/v1/machines/999/status")
        .expect_error(404, "unknown_machine");
    s.post("/api/v1/machines/999/commands", &json!({"command": "home"}))
        .expect_error(404, "unknown_machine");
    s.put("/api/v1/machines/999/offsets/G54", &json!({"x": 1.0}))
        .expect_error(404, "unknown_machine");
    f.assert_untouched("unknown ids");
}

#[test]
fn bad_uploads_are_refused_and_leave_no_job_and_no_file() {
    let f = Fixture::new();

    let msg = f
        .upload("machine=999&name=x", "G0 X1\n")
        .expect_error(404, "unknown_machine");
    contains(&msg, &["999"]);
    f.assert_untouched("unknown machine");
    let msg = f
        .upload("name=x", "G0 X1\n")
        .expect_error(400, "missing_field");
    contains(&msg, &["machine"]);
    f.upload("machine=abc", "G0 X1\n")
        .expect_error(400, "invalid_query");
    f.assert_untouched("missing machine");

    f.upload_to_m("").expect_error(400, "empty_program");
    f.assert_untouched("empty");

    let msg = f
        .upload_to_m(b"G0 X1\nG1\0X2\n".to_vec())
        .expect_error(422, "binary_program");
    contains(&msg, &["line 2, column 3"]);
    f.assert_untouched("binary");

    let msg = f
        .upload_to_m(b"G0 X1\n(caf\xe9)\nG0 X2\n".to_vec())
        .expect_error(422, "not_utf8");
    contains(&msg, &["line 2, column 5", "0xe9"]);
    f.assert_untouched("latin-1");
    let msg = f
        .upload_to_m(b"G0 X1\n(\xc3".to_vec())
        .expect_error(422, "not_utf8");
    contains(&msg, &["line 2"]);
    f.assert_untouched("truncated utf-8");

    // Over the limit: valid G-code, just too much of it.
    let big = "G1 X1 F100\n".repeat(LIMIT as usize / 11 + 10);
    assert!(big.len() as u64 > LIMIT);
    let msg = f.upload_to_m(big).expect_error(413, "too_large");
    contains(&msg, &[&LIMIT.to_string()]);
    f.assert_untouched("too large");
    // Exactly at the limit is fine.
    let mut exact = "G0 X1\n".repeat(LIMIT as usize / 6);
    while (exact.len() as u64) < LIMIT {
        exact.push('\n');
    }
    assert_eq!(exact.len() as u64, LIMIT);
    let up = f.upload_to_m(exact.clone()).expect(201);
    assert_eq!(up["sha256"], sha256_hex(exact.as_bytes()).as_str());
    let id = up["id"].as_i64().unwrap();
    f.s.job_action(id, "start").expect(200);
    f.s.wait_job_state(id, "completed", std::time::Duration::from_secs(60));

    let f = Fixture::new();
    let program = "G0 X1\nG0 X2\n";
    let wrong = "0".repeat(64);
    let msg = f
        .upload(
            &format!("machine={}&name=x&sha256={wrong}", f.machine),
            program,
        )
        .expect_error(422, "sha256_mismatch");
    contains(&msg, &[&sha256_hex(program.as_bytes()), &wrong]);
    f.assert_untouched("sha256 mismatch");

    for (program, code_pos) in [
        ("G21\nG0 X[1/0]\n", "line 2, column 7"),
        ("G21\nO100 endwhile\nG0 X1\n", "line 2, column 1"),
        ("G0 X1\nG1 X2 X3\n", "line 2, column 7"),
        ("G0 X1\nG1 XA\n", "line 2, column 4"),
    ] {
        let msg = f.upload_to_m(program).expect_error(422, "invalid_gcode");
        contains(&msg, &[code_pos]);
        f.assert_untouched(program);
    }
    // A corpus file the interpreter refuses (cutter compensation).
    let data = std::fs::read(corpus("cncjs-helical-thread-milling.gcode")).unwrap();
    let msg = f.upload_to_m(data).expect_error(422, "invalid_gcode");
    contains(&msg, &["line 5, column 5"]);
    f.assert_untouched("corpus file with D word");

    // Multipart without a file part, or with a part the server does not know.
    let s = &f.s;
    let form = reqwest::blocking::multipart::Form::new().text("machine", f.machine.to_string());
    s.send(s.req(reqwest::Method::POST, "/api/v1/jobs").multipart(form))
        .expect_error(400, "invalid_multipart");
    let form = reqwest::blocking::multipart::Form::new()
        .text("machine", f.machine.to_string())
        .text("priority", "high")
        .part(
            "file",
            reqwest::blocking::multipart::Part::bytes(b"G0 X1\n".to_vec()).file_name("a.nc"),
        );
    let msg = s
        .send(s.req(reqwest::Method::POST, "/api/v1/jobs").multipart(form))
        .expect_error(400, "invalid_multipart");
    contains(&msg, &["priority"]);
    let form = reqwest::blocking::multipart::Form::new()
        .text("machine", "999")
        .part(
            "file",
            reqwest::blocking::multipart::Part::bytes(b"G0 X1\n".to_vec()).file_name("a.nc"),
        );
    s.send(s.req(reqwest::Method::POST, "/api/v1/jobs").multipart(form))
        .expect_error(404, "unknown_machine");
    f.assert_untouched("multipart");

    // Errors from everywhere share one shape.
    let r: Value = f.upload_to_m("").body;
    let keys: Vec<&String> = r.as_object().unwrap().keys().collect();
    assert_eq!(keys, ["code", "message"]);
}

/// Programs that once killed the server (the reader recursed once per nesting level, and 3,000
/// to 12,000 levels overflowed the upload thread's stack) with the line and column where the
/// level past `MAX_EXPRESSION_DEPTH` (64) starts.
fn nesting_bombs() -> Vec<(String, String, &'static str)> {
    let closed = |open: &str, close: &str, n: usize| {
        format!("G1 X{}1{} F100\n", open.repeat(n), close.repeat(n))
    };
    vec![
        (
            "[[..]] x4000".into(),
            closed("[", "]", 4000),
            "line 1, column 69",
        ),
        (
            "#[#[..]] x4000".into(),
            closed("#[", "]", 4000),
            "line 1, column 69",
        ),
        (
            "abs[abs[..]] x4000".into(),
            closed("abs[", "]", 4000),
            "line 1, column 264",
        ),
        (
            "o1 if [[..]] x4000".into(),
            format!(
                "o1 if [{}1{}]\nG0 X1\no1 endif\n",
                "[".repeat(4000),
                "]".repeat(4000)
            ),
            "line 1, column 71",
        ),
        (
            "#### x12000".into(),
            format!("G1 X{}1 F100\n", "#".repeat(12_000)),
            "line 1, column 69",
        ),
        (
            "[1+[1+..]] x10000".into(),
            closed("[1+", "]", 10_000),
            "line 1, column 197",
        ),
        // As deep as a line may be long (64 KiB): the closing brackets never come.
        (
            "[ x50000".into(),
            format!("G1 X{}1\n", "[".repeat(50_000)),
            "line 1, column 69",
        ),
        (
            "#[ x25000".into(),
            format!("G1 X{}1\n", "#[".repeat(25_000)),
            "line 1, column 69",
        ),
        (
            "# x50000".into(),
            format!("G1 X{}1\n", "#".repeat(50_000)),
            "line 1, column 69",
        ),
        (
            "-[ x25000".into(),
            format!("G1 X{}1\n", "-[".repeat(25_000)),
            "line 1, column 69",
        ),
        (
            "abs[ x15000".into(),
            format!("G1 X{}1\n", "abs[".repeat(15_000)),
            "line 1, column 264",
        ),
        (
            "bomb after good lines".into(),
            format!("G21 G90\nG0 X1\n#1 = {}1\n", "[".repeat(50_000)),
            "line 3, column 70",
        ),
    ]
}

#[test]
fn nesting_bombs_are_refused_at_upload_and_a_running_job_carries_on() {
    let s = Server::start();
    // A job on another machine runs for the whole test: 300 moves of 1 mm at 600 mm/min.
    let busy = s.sim("busy", 1.0);
    let (job, run) = s.upload_and_start(
        busy.id,
        "busy",
        &fresa_tests::back_and_forth(300, 1.0, 600.0),
    );
    s.wait_job_state(job, "running", std::time::Duration::from_secs(60));
    let target = s.sim("target", 0.0).id;
    let files = s.program_files();
    let upload = |body: &str| {
        s.post_bytes(
            &format!("/api/v1/jobs?machine={target}&name=bad"),
            body.to_string(),
        )
    };
    let alive = |what: &str| {
        s.get("/healthz").expect(200);
        let st = s.status(busy.id);
        assert_eq!(st["state"], "running", "after {what}: {st}");
        assert_eq!(s.job(job)["state"], "running", "after {what}");
    };
    for (what, program, at) in nesting_bombs() {
        let msg = upload(&program).expect_error(422, "invalid_gcode");
        contains(&msg, &[at, "limit of 64 levels"]);
        alive(&what);
    }
    // Nothing of any of them was stored.
    let jobs = s.get("/api/v1/jobs").expect(200);
    assert_eq!(jobs.as_array().unwrap().len(), 1, "jobs: {jobs}");
    assert_eq!(s.program_files(), files, "stray files in programs/");
    // The running job was never disturbed: it ends with every line run once.
    s.wait_job_state(job, "completed", std::time::Duration::from_secs(120));
    fresa_tests::assert_every_line_once(&busy.executed(), run, 300);
}

#[test]
fn absurd_numbers_are_refused_at_upload_naming_the_word_not_at_job_start() {
    let f = Fixture::new();
    // Numbers no machine can run: refused at upload, naming the word, not at job start.
    for (program, parts) in [
        (
            "G21 G90\nG1 X[10**300*10**300] F100\n",
            &["line 2, column 13", "'*'", "not a finite number"][..],
        ),
        (
            "G21 G90\nG4 P[10**300]\n",
            &["line 2, column 4", "P=1e300", "86400 s"],
        ),
        ("G4 P100000\n", &["line 1, column 4", "86400 s"]),
        (
            "G0 X[10**300]\n",
            &["line 1, column 4", "X=1e300 mm", "1000000 mm"],
        ),
        ("G0 Y2000000\n", &["line 1, column 4", "Y=2000000 mm"]),
        (
            "G91 G0 Z-600000\nZ-600000\n",
            &["line 2, column 1", "Z=-1200000 mm"],
        ),
        ("G1 X1 F[10**20]\n", &["line 1, column 7", "F=1e20 mm/min"]),
        ("S[10**300] M3\n", &["line 1, column 1", "S=1e300 rpm"]),
        (
            "G0 X1\nG92 X[-10**7]\n",
            &["line 2, column 5", "X=-10000000 mm"],
        ),
    ] {
        let msg = f.upload_to_m(program).expect_error(422, "invalid_gcode");
        contains(&msg, parts);
        f.assert_untouched(program);
    }
}
