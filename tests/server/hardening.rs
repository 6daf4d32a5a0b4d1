//! Hostile web pages and loose inputs (issue 12): a browser page on another origin, or one
//! reaching the server under a rebound DNS name, changes nothing; secrets stay out of URLs and
//! logs; names, addresses, command fields, multipart forms and backend file paths are checked.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{Opts, Server};
use reqwest::Method;

const PROGRAM: &str = "G21 G90\nG0 X1 Y1\nG1 X2 F300\n";

fn port(s: &Server) -> u16 {
    s.base.rsplit(':').next().unwrap().parse().unwrap()
}

#[test]
fn a_page_on_another_origin_can_neither_upload_nor_start_a_job() {
    let s = Server::start();
    let m = s.sim("m", 0.0).id;
    let evil = "http://evil.example";
    let upload = s.send(
        s.req(Method::POST, &format!("/api/v1/jobs?machine={m}&name=x"))
            .header("content-type", "text/plain")
            .header("origin", evil)
            .body(PROGRAM),
    );
    let msg = upload.expect_error(403, "cross_origin");
    assert!(msg.contains("evil.example"), "{msg}");
    s.assert_no_jobs();
    assert!(s.upload_temp_files().is_empty());

    // A job stored by a legitimate client cannot be started, paused or cancelled from the page.
    let job = s.upload(m, "ok", PROGRAM)["id"].as_i64().unwrap();
    for action in ["start", "pause", "resume", "cancel"] {
        s.send(
            s.req(Method::POST, &format!("/api/v1/jobs/{job}/{action}"))
                .header("origin", evil),
        )
        .expect_error(403, "cross_origin");
    }
    s.send(
        s.req(Method::POST, &format!("/api/v1/machines/{m}/part-zero"))
            .header("origin", "null"),
    )
    .expect_error(403, "cross_origin");
    // A browser that only says the request is cross-site is refused too.
    s.send(
        s.req(Method::POST, &format!("/api/v1/jobs/{job}/start"))
            .header("sec-fetch-site", "cross-site"),
    )
    .expect_error(403, "cross_origin");
    assert_eq!(s.job(job)["state"], "ready", "the job never ran");

    // Reading is not a change, and the server's own pages (same origin) may act.
    s.send(s.req(Method::GET, "/api/v1/jobs").header("origin", evil))
        .expect(200);
    let own = format!("http://127.0.0.1:{}", port(&s));
    s.send(
        s.req(Method::POST, &format!("/api/v1/jobs/{job}/start"))
            .header("origin", own),
    )
    .expect(200);
    // And so may curl, which sends no Origin.
    s.wait_job_state(job, "completed", std::time::Duration::from_secs(30));
}

#[test]
fn a_rebound_host_name_reaches_nothing_unless_it_is_allowed() {
    let s = Server::start_with_config(
        "allowed_hosts = [\"fresa.shop.lan\"]\ncors_origins = [\"http://tablet.lan:8080\"]\n",
    );
    let p = port(&s);
    for host in [format!("evil.example:{p}"), "evil.example".to_string()] {
        let msg = s
            .send(s.req(Method::GET, "/api/v1/machines").header("host", &host))
            .expect_error(403, "host_not_allowed");
        assert!(msg.contains("allowed_hosts"), "{msg}");
    }
    for host in [
        format!("localhost:{p}"),
        format!("127.0.0.1:{p}"),
        format!("fresa.shop.lan:{p}"),
    ] {
        s.send(s.req(Method::GET, "/api/v1/machines").header("host", &host))
            .expect(200);
    }
    // CORS: deny by default, the listed origin gets its headers (and a preflight answer).
    let pre = |origin: &str| {
        s.req(Method::OPTIONS, "/api/v1/machines")
            .header("origin", origin)
            .header("access-control-request-method", "POST")
            .send()
            .unwrap()
    };
    let allowed = pre("http://tablet.lan:8080");
    assert_eq!(
        allowed
            .headers()
            .get("access-control-allow-origin")
            .and_then(|v| v.to_str().ok()),
        Some("http://tablet.lan:8080")
    );
    let denied = pre("http://evil.example");
    assert!(denied
        .headers()
        .get("access-control-allow-origin")
        .is_none());
    // The listed origin may also change things.
    s.send(
        s.req(Method::POST, "/api/v1/machines")
            .header("origin", "http://tablet.lan:8080")
            .json(&json!({"name": "t", "backend": "sim-machine"})),
    )
    .expect(201);
}

#[test]
fn tokens_in_urls_are_refused_outside_the_event_stream_and_never_logged() {
    let mut s = Server::unstarted(Opts {
        log: Some("debug".into()),
        ..Opts::default()
    });
    let secret = s.create_token("admin", "alice");
    s.spawn().unwrap();
    let msg = s
        .send(
            s.req(
                Method::POST,
                &format!("/api/v1/machines?access_token={secret}"),
            )
            .json(&json!({"name": "m", "backend": "sim-machine"})),
        )
        .expect_error(400, "token_in_query");
    assert!(msg.contains("/api/v1/events"), "{msg}");
    s.send(s.req(
        Method::GET,
        &format!("/api/v1/machines?access_token={secret}"),
    ))
    .expect_error(400, "token_in_query");
    // The event stream (EventSource cannot send headers) takes it.
    let events = s.events(&format!("access_token={secret}"), Some(0));
    drop(events);
    // A header token too, to see it is not logged either.
    s.send(s.req(Method::GET, "/api/v1/plugins").bearer_auth(&secret))
        .expect(200);
    s.wait_log(std::time::Duration::from_secs(10), "access_token=REDACTED");
    let log = s.log();
    assert!(
        !log.contains(&secret),
        "the secret appears in the debug log:\n{log}"
    );
}

#[test]
fn loose_inputs_are_refused_naming_what_is_wrong() {
    let s = Server::start();
    let m = s.sim("m", 0.0).id;
    // Names: bounded, no control characters.
    let long = "x".repeat(101);
    let msg = s
        .post(
            "/api/v1/machines",
            &json!({"name": long, "backend": "sim-machine"}),
        )
        .expect_error(422, "invalid_field");
    assert!(msg.contains("at most 100"), "{msg}");
    let msg = s
        .post(
            "/api/v1/machines",
            &json!({"name": "a\u{0}b", "backend": "sim-machine"}),
        )
        .expect_error(422, "invalid_field");
    assert!(msg.contains("U+0000"), "{msg}");
    let msg = s
        .post_bytes(&format!("/api/v1/jobs?machine={m}&name=a%0Ab"), PROGRAM)
        .expect_error(422, "invalid_field");
    assert!(msg.contains("control"), "{msg}");
    s.assert_no_jobs();
    let metrics = s.get("/metrics").text;
    assert!(!metrics.contains('\0'));

    // A misspelt query parameter is not ignored (the job would get no name, or the wrong one).
    let msg = s
        .post_bytes(&format!("/api/v1/jobs?machine={m}&nmae=x"), PROGRAM)
        .expect_error(400, "invalid_query");
    assert!(msg.contains("nmae"), "{msg}");
    s.assert_no_jobs();

    // Pendant addresses are parsed.
    for bad in ["::::", "a b:8001", "-x.local"] {
        let msg = s
            .post("/api/v1/pendants", &json!({"name": "p", "address": bad}))
            .expect_error(422, "invalid_field");
        assert!(msg.contains("address"), "{bad}: {msg}");
    }

    // A command with a field it does not have is refused, like every other body.
    let msg = s
        .post(
            &format!("/api/v1/machines/{m}/commands"),
            &json!({"command": "zero", "axsi": "X"}),
        )
        .expect_error(422, "invalid_command");
    assert!(msg.contains("axsi"), "{msg}");
    s.post(
        &format!("/api/v1/machines/{m}/commands"),
        &json!({"command": "zero", "axis": "X"}),
    )
    .expect(200);

    // Two programs in one form are not stored joined.
    let form = reqwest::blocking::multipart::Form::new()
        .text("machine", m.to_string())
        .part(
            "file",
            reqwest::blocking::multipart::Part::text(PROGRAM).file_name("a.nc"),
        )
        .part(
            "file",
            reqwest::blocking::multipart::Part::text(PROGRAM).file_name("b.nc"),
        );
    let msg = s
        .send(s.req(Method::POST, "/api/v1/jobs").multipart(form))
        .expect_error(400, "invalid_multipart");
    assert!(msg.contains("more than one"), "{msg}");
    s.assert_no_jobs();
    assert!(s.upload_temp_files().is_empty());

    // Wrong method: a JSON error, not an empty body.
    let r = s.send(s.req(Method::DELETE, "/api/v1/machines"));
    assert_eq!(r.status, 405, "{}", r.text);
    assert_eq!(r.body["code"], "method_not_allowed", "{}", r.text);

    // Too long a URL, too large a JSON body: JSON errors too.
    let r = s.get(&format!("/api/v1/machines?x={}", "a".repeat(9000)));
    assert_eq!(
        (r.status, r.body["code"].as_str()),
        (414, Some("uri_too_long")),
        "{}",
        r.text
    );
    // One byte over axum's default 2 MiB JSON limit: the whole body is sent (so the answer is
    // not lost to a connection closed under a client still writing).
    let r = s.send(
        s.req(Method::POST, "/api/v1/machines")
            .header("content-type", "application/json")
            .body(vec![b' '; (2 << 20) + 1]),
    );
    assert_eq!(
        (r.status, r.body["code"].as_str()),
        (413, Some("too_large")),
        "{}",
        r.text
    );

    // Backend files stay in the data directory.
    for bad in ["/etc/fresa-test-owned.log", "../escape.log"] {
        let msg = s
            .post(
                "/api/v1/machines",
                &json!({"name": "evil", "backend": "sim-machine",
                        "config": {"execution_log": bad}}),
            )
            .expect_error(422, "invalid_field");
        assert!(msg.contains("config.execution_log"), "{msg}");
    }
    assert!(!std::path::Path::new("/etc/fresa-test-owned.log").exists());
    let id = s.create_machine(&json!({"name": "ok", "backend": "sim-machine",
                                      "config": {"execution_log": "ok.log"}}));
    let machine: Value = s.get(&format!("/api/v1/machines/{id}")).expect(200);
    let path = machine["config"]["execution_log"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(
        std::path::Path::new(&path).starts_with(s.data_dir()),
        "{path}"
    );
}

/// Sends `head` (and `body`) on a fresh connection as written, with `Connection: close`, and
/// returns the status and the answer's JSON body: for requests reqwest cannot send (two Host
/// headers, none, an absolute-form target).
fn raw(s: &Server, head: &str, body: &str) -> (u16, Value) {
    use std::io::{Read, Write};
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port(s))).unwrap();
    c.set_read_timeout(Some(std::time::Duration::from_secs(30)))
        .unwrap();
    let length = if body.is_empty() {
        String::new()
    } else {
        format!(
            "Content-Type: application/json\r\nContent-Length: {}\r\n",
            body.len()
        )
    };
    write!(c, "{head}{length}Connection: close\r\n\r\n{body}").unwrap();
    let mut answer = String::new();
    c.read_to_string(&mut answer).unwrap();
    let status = answer
        .get(9..12)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP answer: {answer:?}"));
    let json = answer
        .split_once("\r\n\r\n")
        .and_then(|(_, b)| serde_json_body(b))
        .unwrap_or(Value::Null);
    (status, json)
}

/// The JSON of a body that may be chunked.
fn serde_json_body(body: &str) -> Option<Value> {
    fresa_tests::serde_json::from_str(body).ok().or_else(|| {
        let start = body.find('{')?;
        let end = body.rfind('}')?;
        fresa_tests::serde_json::from_str(&body[start..=end]).ok()
    })
}

#[track_caller]
fn expect_raw_error(got: (u16, Value), status: u16, code: &str) -> String {
    assert_eq!(got.0, status, "expected {status} {code}: {}", got.1);
    assert_eq!(got.1["code"], code, "{}", got.1);
    got.1["message"].as_str().unwrap().to_string()
}

#[test]
fn one_host_that_names_this_server_and_agrees_with_an_absolute_target() {
    let s = Server::start();
    let m = s.sim("m", 0.0).id;
    let own = format!("127.0.0.1:{}", port(&s));
    let list = "/api/v1/machines";
    let get = |target: &str, hosts: &[&str]| {
        let hosts: String = hosts.iter().map(|h| format!("Host: {h}\r\n")).collect();
        raw(&s, &format!("GET {target} HTTP/1.1\r\n{hosts}"), "")
    };
    assert_eq!(get(list, &[&own]).0, 200, "the plain request works");

    // Two Host headers, whichever comes first (and even when both are right).
    for hosts in [
        [own.as_str(), "evil.example"],
        ["evil.example", &own],
        [&own, &own],
    ] {
        let msg = expect_raw_error(get(list, &hosts), 400, "duplicate_host");
        assert!(msg.contains("Host"), "{msg}");
    }

    // An absolute-form target: its authority is what the request is addressed to.
    let msg = expect_raw_error(
        get(&format!("http://evil.example{list}"), &[&own]),
        403,
        "host_not_allowed",
    );
    assert!(msg.contains("evil.example"), "{msg}");
    expect_raw_error(
        get(&format!("http://evil.example{list}"), &["evil.example"]),
        403,
        "host_not_allowed",
    );
    // Naming this server, but not as the Host header does.
    let localhost = format!("localhost:{}", port(&s));
    let msg = expect_raw_error(
        get(&format!("http://{localhost}{list}"), &[&own]),
        400,
        "host_mismatch",
    );
    assert!(msg.contains(&localhost) && msg.contains(&own), "{msg}");
    assert_eq!(get(&format!("http://{own}{list}"), &[&own]).0, 200);

    // No Host at all: HTTP/1.1 requires one, and without it there is no name to check.
    expect_raw_error(get(list, &[]), 400, "host_required");

    // None of the refused motion requests moves the machine: only the last jog does.
    let jog = format!("/api/v1/machines/{m}/jog");
    let body = r#"{"axis": "X", "distance": 1.0}"#;
    let post = |target: &str, hosts: &[&str]| {
        let hosts: String = hosts.iter().map(|h| format!("Host: {h}\r\n")).collect();
        raw(&s, &format!("POST {target} HTTP/1.1\r\n{hosts}"), body)
    };
    expect_raw_error(post(&jog, &[]), 400, "host_required");
    expect_raw_error(post(&jog, &[&own, "evil.example"]), 400, "duplicate_host");
    expect_raw_error(
        post(&format!("http://evil.example{jog}"), &[&own]),
        403,
        "host_not_allowed",
    );
    let half = r#"{"axis": "X", "distance": 0.5}"#;
    let ok = raw(&s, &format!("POST {jog} HTTP/1.1\r\nHost: {own}\r\n"), half);
    assert_eq!(ok.0, 200, "{}", ok.1);
    let st = s.wait_status(m, std::time::Duration::from_secs(30), "idle, moved", |st| {
        st["state"] == "idle" && st["work_position"]["x"].as_f64().is_some_and(|x| x > 0.25)
    });
    let x = st["work_position"]["x"].as_f64().unwrap();
    assert!(
        (x - 0.5).abs() < 1e-9,
        "x = {x}: a refused jog moved the machine"
    );
}
