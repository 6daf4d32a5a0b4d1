//! Tokens: a server reachable from the network refuses to start without one, then every API
//! request needs one, with roles (viewer reads, operator runs jobs, admin configures machines).
//! Tests bind 0.0.0.0 but only ever talk to 127.0.0.1.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::json;
use fresa_tests::{output_text, Opts, Server};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

fn network_opts() -> Opts {
    Opts {
        listen: "0.0.0.0:0".into(),
        ..Opts::default()
    }
}

#[test]
fn a_network_server_without_tokens_refuses_to_start() {
    let mut s = Server::unstarted(network_opts());
    let err = s.spawn().expect_err("must refuse to start without a token");
    assert!(
        err.contains("no API token") && err.contains("fresa token create"),
        "{err}"
    );
}

#[test]
fn every_request_needs_a_valid_token_with_the_right_role() {
    let mut s = Server::unstarted(network_opts());
    let admin = s.create_token("admin", "alice");
    let operator = s.create_token("operator", "olga");
    let viewer = s.create_token("viewer", "victor");
    assert_ne!(admin, operator);
    s.spawn().unwrap();
    assert!(
        s.log().contains("every request needs an API token"),
        "{}",
        s.log()
    );

    // Health checks, the console and the API's description stay open; the API does not, and
    // neither does a path under it that does not exist (no listing of endpoints without a
    // token) nor `/metrics`. A path outside the API is a plain 404.
    s.get("/healthz").expect(200);
    s.get("/").expect(200);
    s.get("/api/v1/openapi.json").expect(200);
    let msg = s
        .get("/api/v1/machines")
        .expect_error(401, "token_required");
    assert!(msg.contains("Authorization: Bearer"), "{msg}");
    s.get("/api/v1/no-such-endpoint")
        .expect_error(401, "token_required");
    s.get("/metrics").expect_error(401, "token_required");
    s.get("/no-such-page").expect_error(404, "not_found");
    s.post(
        "/api/v1/machines",
        &json!({"name": "m", "backend": "sim-machine"}),
    )
    .expect_error(401, "token_required");
    s.send(
        s.req(reqwest::Method::GET, "/api/v1/events")
            .header("Last-Event-ID", "0"),
    )
    .expect_error(401, "token_required");

    s.token = Some("fresa_not_a_real_token".into());
    s.get("/api/v1/machines").expect_error(401, "invalid_token");
    s.token = Some(format!("{admin}x"));
    s.get("/api/v1/machines").expect_error(401, "invalid_token");

    // Viewer: may read, may not change anything.
    s.token = Some(viewer.clone());
    s.get("/api/v1/machines").expect(200);
    s.get("/api/v1/no-such-endpoint")
        .expect_error(404, "not_found");
    let msg = s
        .post(
            "/api/v1/machines",
            &json!({"name": "m", "backend": "sim-machine"}),
        )
        .expect_error(403, "forbidden");
    assert!(msg.contains("viewer") && msg.contains("victor"), "{msg}");

    // Operator: may not create machines (admin only).
    s.token = Some(operator.clone());
    s.post(
        "/api/v1/machines",
        &json!({"name": "m", "backend": "sim-machine"}),
    )
    .expect_error(403, "forbidden");

    // Admin creates a machine; the audit event names the token.
    s.token = Some(admin.clone());
    let m = s.sim("m", 0.0);
    assert_eq!(
        s.get("/api/v1/machines")
            .expect(200)
            .as_array()
            .unwrap()
            .len(),
        1
    );

    // Viewer cannot upload, jog or run; operator can.
    s.token = Some(viewer.clone());
    s.post_bytes(&format!("/api/v1/jobs?machine={}", m.id), "G0 X1\n")
        .expect_error(403, "forbidden");
    s.post(
        &format!("/api/v1/machines/{}/jog", m.id),
        &json!({"axis": "X", "distance": 1.0}),
    )
    .expect_error(403, "forbidden");
    s.assert_no_jobs();
    // A status poll is answered in front of the router (`status_polls`), still behind the gate.
    s.get(&format!("/api/v1/machines/{}/status", m.id))
        .expect(200);
    s.token = None;
    s.get(&format!("/api/v1/machines/{}/status", m.id))
        .expect_error(401, "token_required");
    s.token = Some("fresa_not_a_real_token".into());
    s.get(&format!("/api/v1/machines/{}/status", m.id))
        .expect_error(401, "invalid_token");

    s.token = Some(operator.clone());
    let job = s.upload(m.id, "j", "G0 X1\nG0 X0\n")["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "completed", T);
    s.post(
        &format!("/api/v1/machines/{}/part-zero", m.id),
        &json!({"source": "probe"}),
    )
    .expect(201);

    // The audit trail names who did what; a viewer can read it, over SSE with ?access_token=.
    s.token = None;
    let events = s.events(&format!("access_token={viewer}"), Some(0));
    let seen = events.until(T, "machine.part_zero", |e| e.event == "machine.part_zero");
    let actor = |kind: &str| {
        seen.iter()
            .find(|e| e.event == kind)
            .map(|e| e.data["actor"].clone())
            .unwrap_or_else(|| panic!("no {kind} in {seen:?}"))
    };
    assert_eq!(actor("machine.created"), "alice");
    assert_eq!(actor("job.created"), "olga");
    assert_eq!(actor("machine.part_zero"), "olga");
    let hist = {
        s.token = Some(viewer.clone());
        s.get(&format!("/api/v1/machines/{}/part-zero", m.id))
            .expect(200)
    };
    assert_eq!(hist[0]["actor"], "olga", "{hist}");

    // The CLI passes --token; without it the server's refusal is shown.
    s.token = None;
    let out = s.cli(&["machine", "list"]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("token_required"),
        "{}",
        output_text(&out)
    );
    s.token = Some(viewer);
    let out = s.cli(&["machine", "list"]);
    assert!(out.status.success(), "{}", output_text(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("sim-machine"));
}

#[test]
fn a_loopback_server_needs_no_token_but_checks_one_given() {
    let mut s = Server::start();
    let viewer = s.create_token("viewer", "v");
    s.get("/api/v1/machines").expect(200);
    s.token = Some("fresa_wrong".into());
    s.get("/api/v1/machines").expect_error(401, "invalid_token");
    // A token given is taken at its role even on loopback.
    s.token = Some(viewer);
    s.post(
        "/api/v1/machines",
        &json!({"name": "m", "backend": "sim-machine"}),
    )
    .expect_error(403, "forbidden");
    s.token = None;
    s.sim("m", 0.0);
}

/// `fresa token ARGS... --data-dir --config` on this server's data directory.
fn token_cli(s: &Server, args: &[&str]) -> std::process::Output {
    fresa_tests::fresa_cmd()
        .arg("token")
        .args(args)
        .arg("--data-dir")
        .arg(s.data_dir())
        .arg("--config")
        .arg(s.config_file())
        .output()
        .expect("run fresa token")
}

#[test]
fn tokens_are_listed_without_secrets_and_names_are_unique() {
    let s = Server::unstarted(network_opts());
    let admin = s.create_token("admin", "alice");
    let out = token_cli(&s, &["create", "--role", "viewer", "--name", "alice"]);
    assert!(!out.status.success(), "{}", output_text(&out));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("\"alice\" exists") && err.contains("token revoke"),
        "{err}"
    );
    let out = token_cli(
        &s,
        &[
            "create",
            "--role",
            "viewer",
            "--name",
            "kiosk",
            "--expires-in-days",
            "30",
        ],
    );
    assert!(out.status.success(), "{}", output_text(&out));
    let kiosk = String::from_utf8_lossy(&out.stdout).trim().to_string();

    let out = token_cli(&s, &["list"]);
    assert!(out.status.success(), "{}", output_text(&out));
    let list = String::from_utf8_lossy(&out.stdout).to_string();
    let row = |name: &str| {
        list.lines()
            .find(|l| l.starts_with(name))
            .unwrap_or_else(|| panic!("no {name} in\n{list}"))
            .to_string()
    };
    assert!(list.starts_with("NAME"), "{list}");
    assert!(
        row("alice").contains("admin") && row("alice").contains("never"),
        "{list}"
    );
    // kiosk: viewer, an expiry date (not "never"), never used.
    let k = row("kiosk");
    assert!(k.contains("viewer"), "{list}");
    assert_eq!(k.matches("never").count(), 1, "{list}");
    assert!(
        !list.contains(&admin) && !list.contains(&kiosk),
        "secrets listed:\n{list}"
    );
    assert_eq!(list.lines().count(), 3, "{list}");
}

/// Revocation goes through the database (`fresa token revoke` is another process). Anything
/// that changes state asks the database, so it is refused at once; a read may trust the
/// database's last "valid" for `READ_TOKEN_RECHECK_MS` (1 s), so a status poll with a token does
/// not wait for the database each time.
#[test]
fn a_revoked_token_stops_working_at_once() {
    let mut s = Server::unstarted(network_opts());
    let admin = s.create_token("admin", "alice");
    let ops = s.create_token("operator", "olga");
    let viewer = s.create_token("viewer", "victor");
    s.spawn().unwrap();
    s.token = Some(ops.clone());
    s.get("/api/v1/machines").expect(200);

    let out = token_cli(&s, &["revoke", "olga"]);
    assert!(out.status.success(), "{}", output_text(&out));
    // A change right after a read that was accepted: the database is asked, not the read's
    // answer (a valid operator would get 403 here: only admins create machines).
    s.post(
        "/api/v1/machines",
        &json!({"name": "m", "backend": "sim-machine"}),
    )
    .expect_error(401, "invalid_token");
    s.get("/api/v1/machines").expect_error(401, "invalid_token");

    // A token only read with stops working for reads too, once its last check is a second old.
    s.token = Some(viewer);
    s.get("/api/v1/machines").expect(200);
    let out = token_cli(&s, &["revoke", "victor"]);
    assert!(out.status.success(), "{}", output_text(&out));
    let deadline = std::time::Instant::now() + T;
    loop {
        let r = s.get("/api/v1/machines");
        if r.status == 401 {
            r.expect_error(401, "invalid_token");
            break;
        }
        r.expect(200);
        assert!(
            std::time::Instant::now() < deadline,
            "a revoked token still reads after {T:?}"
        );
        // Waiting out a time window, not for an event: there is nothing to wait on.
        std::thread::sleep(Duration::from_millis(100));
    }
    // Others are untouched; revoking again names what is missing.
    s.token = Some(admin);
    s.get("/api/v1/machines").expect(200);
    let out = token_cli(&s, &["revoke", "olga"]);
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("no token named \"olga\""),
        "{}",
        output_text(&out)
    );
    // The list shows when a token was last used.
    let out = token_cli(&s, &["list"]);
    let list = String::from_utf8_lossy(&out.stdout).to_string();
    let alice = list.lines().find(|l| l.starts_with("alice")).unwrap();
    assert!(!alice.ends_with("never"), "last use not recorded:\n{list}");
    assert!(!list.contains("olga"), "{list}");
}

#[test]
fn an_expired_token_gets_invalid_token() {
    let mut s = Server::unstarted(network_opts());
    let admin = s.create_token("admin", "alice");
    // 0.00002 days is under two seconds.
    let out = token_cli(
        &s,
        &[
            "create",
            "--role",
            "admin",
            "--name",
            "brief",
            "--expires-in-days",
            "0.00002",
        ],
    );
    assert!(out.status.success(), "{}", output_text(&out));
    let brief = String::from_utf8_lossy(&out.stdout).trim().to_string();
    s.spawn().unwrap();
    s.token = Some(brief);
    fresa_tests::wait_for(T, "the short-lived token to expire", || {
        let r = s.get("/api/v1/machines");
        (r.status == 401).then_some(r)
    })
    .expect_error(401, "invalid_token");
    let out = token_cli(&s, &["list"]);
    let list = String::from_utf8_lossy(&out.stdout).to_string();
    let row = list.lines().find(|l| l.starts_with("brief")).unwrap();
    assert!(row.contains("(expired)"), "{list}");
    s.token = Some(admin);
    s.get("/api/v1/machines").expect(200);
    // A day count that is not positive is refused by the CLI, naming the value.
    let out = token_cli(
        &s,
        &[
            "create",
            "--role",
            "viewer",
            "--name",
            "x",
            "--expires-in-days",
            "0",
        ],
    );
    assert!(!out.status.success(), "{}", output_text(&out));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("\"0\""),
        "{}",
        output_text(&out)
    );
}

#[test]
fn the_bearer_scheme_is_case_insensitive() {
    let mut s = Server::unstarted(network_opts());
    let viewer = s.create_token("viewer", "v");
    s.spawn().unwrap();
    let http = reqwest::blocking::Client::new();
    let get = |authorization: String| {
        let r = http
            .get(s.url("/api/v1/machines"))
            .header("authorization", authorization)
            .send()
            .unwrap();
        let status = r.status().as_u16();
        (status, r.text().unwrap())
    };
    for scheme in ["Bearer", "bearer", "BEARER", "bEaReR"] {
        let (status, text) = get(format!("{scheme} {viewer}"));
        assert_eq!(status, 200, "{scheme}: {text}");
    }
    // The token after a lower-case scheme is checked, not ignored.
    let (status, text) = get("bearer fresa_wrong".into());
    assert_eq!(status, 401, "{text}");
    assert!(text.contains("invalid_token"), "{text}");
}

/// A client whose connections come from `source` (any 127.x address is this host's on Linux).
#[cfg(target_os = "linux")]
fn client_from(source: [u8; 4]) -> reqwest::blocking::Client {
    reqwest::blocking::Client::builder()
        .local_address(std::net::IpAddr::from(source))
        .timeout(Duration::from_secs(30))
        .build()
        .unwrap()
}

#[test]
#[cfg(target_os = "linux")]
fn wrong_tokens_are_rate_limited_per_address_counted_and_logged_without_the_token() {
    let mut s = Server::unstarted(network_opts());
    let admin = s.create_token("admin", "alice");
    s.spawn().unwrap();
    let attacker = client_from([127, 0, 0, 2]);
    let try_token = |token: &str| {
        let r = attacker
            .get(s.url("/api/v1/machines"))
            .bearer_auth(token)
            .send()
            .unwrap();
        let status = r.status().as_u16();
        let retry = r.headers().get("retry-after").cloned();
        (status, retry, r.text().unwrap())
    };
    // The default: 20 failed attempts a minute from one address, then 429 until it slows down.
    for i in 0..20 {
        let (status, _, text) = try_token(&format!("fresa_guess_{i}"));
        assert_eq!(status, 401, "attempt {i}: {text}");
    }
    let (status, retry, text) = try_token("fresa_guess_20");
    assert_eq!(status, 429, "{text}");
    assert!(text.contains("too_many_auth_failures"), "{text}");
    assert!(text.contains("max_auth_failures_per_minute"), "{text}");
    let retry: u64 = retry
        .expect("Retry-After")
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!((1..=60).contains(&retry), "Retry-After: {retry}");
    // That address's tokens are not looked up meanwhile, valid or not.
    assert_eq!(try_token(&admin).0, 429);

    // The operator at another address is not locked out.
    let operator_get = |path: &str| s.send(s.req(reqwest::Method::GET, path).bearer_auth(&admin));
    operator_get("/api/v1/machines").expect(200);
    let metrics = operator_get("/metrics");
    assert_eq!(metrics.status, 200);
    let sample = |name: &str| -> f64 {
        metrics
            .text
            .lines()
            .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
            .unwrap_or_else(|| panic!("no {name} in\n{}", metrics.text))
    };
    assert_eq!(sample("fresa_auth_failures_total"), 20.0);
    assert_eq!(sample("fresa_auth_rate_limited_total"), 2.0);
    // Logged without the tokens, naming the address.
    let line = s.wait_log(T, "failed token attempt");
    assert!(line.contains("127.0.0.2"), "{line}");
    s.wait_log(T, "too many failed token attempts");
    assert!(!s.log().contains("fresa_guess_"), "{}", s.log());

    // Once it slows down, that address gets in with a valid token.
    fresa_tests::wait_for(T, "the limited address to be let in again", || {
        (try_token(&admin).0 == 200).then_some(())
    });
}
