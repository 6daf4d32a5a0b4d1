//! The OpenAPI description (`GET /api/v1/openapi.json`) against the real server.
//!
//! The router and the description are built from the same `routes!(handler)` lines (see
//! `server/http/src/openapi.rs`). These tests check both directions:
//! * every documented operation is routed and guarded by the role the document states
//!   (`documented_operations_are_routed_with_their_role`), and each documented example request
//!   gets its documented status, with a body that matches the documented schema
//!   (`documented_examples_get_their_documented_status`);
//! * no route is added around the description (`routes_are_only_added_with_their_description`);
//! * the document is valid OpenAPI 3.1 for a real validator (`openapi-spec-validator`);
//! * first requests at once all get the one document, made once
//!   (`first_requests_at_once_get_the_same_document`).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{workspace_root, Opts, Server};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// Operations whose example cannot get its success status on the demo server, and why.
const NOT_ON_THE_DEMO: &[(&str, &str, &str)] = &[
    (
        "get",
        "/api/v1/machines/{id}/as-program",
        "only a kawasaki-as fresa-v1 machine has one (tests/backends/kawasaki.rs downloads it)",
    ),
    (
        "post",
        "/api/v1/machines/{id}/jog/keepalive",
        "only while a continuous jog is held (machine::api's continuous-jog test keeps one alive)",
    ),
    (
        "post",
        "/api/v1/machines/{id}/find-centre",
        "only with the tool in a bore or over a boss (machine::probing finds both on round sim walls)",
    ),
    (
        "get",
        "/api/v1/machines/{id}/height-maps/{hid}",
        "only once a grid was probed (machine::heightmap probes them and reads them back)",
    ),
    (
        "delete",
        "/api/v1/machines/{id}/height-maps/{hid}",
        "only once a grid was probed (machine::heightmap deletes a stopped one)",
    ),
    (
        "get",
        "/api/v1/machines/{id}/height-maps/{hid}/fit",
        "only with a probed map and a job (machine::heightmap checks fits and overhangs)",
    ),
    (
        "post",
        "/api/v1/machines/{id}/queue/release",
        "only while a queue holds (jobs::queue stops a part and releases the queue)",
    ),
];

struct Op {
    path: String,
    method: String,
    op: Value,
}

impl Op {
    fn role(&self) -> &str {
        self.op["x-fresa-role"]
            .as_str()
            .unwrap_or_else(|| panic!("{} {} has no x-fresa-role", self.method, self.path))
    }

    fn params(&self, place: &str) -> Vec<&Value> {
        self.op["parameters"]
            .as_array()
            .map(|ps| ps.iter().filter(|p| p["in"] == place).collect())
            .unwrap_or_default()
    }

    /// The path with its parameters' examples, and the query parameters that have one.
    fn example_url(&self) -> String {
        let mut url = self.path.clone();
        for p in self.params("path") {
            let name = p["name"].as_str().unwrap();
            let example = match &p["example"] {
                Value::String(s) => s.clone(),
                Value::Null => panic!(
                    "{} {}: path parameter {name} has no example",
                    self.method, self.path
                ),
                v => v.to_string(),
            };
            url = url.replace(&format!("{{{name}}}"), &example);
        }
        let query: Vec<String> = self
            .params("query")
            .iter()
            .filter(|p| !p["example"].is_null())
            .map(|p| {
                let v = match &p["example"] {
                    Value::String(s) => s.clone(),
                    v => v.to_string(),
                };
                format!("{}={v}", p["name"].as_str().unwrap())
            })
            .collect();
        if !query.is_empty() {
            url = format!("{url}?{}", query.join("&"));
        }
        url
    }

    /// The documented example body: (content type, bytes), from the first content type that has
    /// one. A required body without an example is a gap in the document.
    fn example_body(&self) -> Option<(String, Vec<u8>)> {
        let body = &self.op["requestBody"];
        if body.is_null() {
            return None;
        }
        let content = body["content"].as_object().unwrap();
        for (ctype, c) in content {
            match &c["example"] {
                Value::Null => continue,
                Value::String(s) if ctype != "application/json" => {
                    return Some((ctype.clone(), s.clone().into_bytes()))
                }
                v => return Some((ctype.clone(), serde_json::to_vec(v).unwrap())),
            }
        }
        assert!(
            body["required"] != true,
            "{} {}: a required request body without an example",
            self.method,
            self.path
        );
        None
    }

    /// The lowest documented 2xx status.
    fn success(&self) -> u16 {
        self.op["responses"]
            .as_object()
            .unwrap()
            .keys()
            .filter_map(|k| k.parse::<u16>().ok())
            .filter(|s| (200..300).contains(s))
            .min()
            .unwrap_or_else(|| panic!("{} {} documents no success", self.method, self.path))
    }
}

fn operations(doc: &Value) -> Vec<Op> {
    let mut ops = Vec::new();
    for (path, item) in doc["paths"].as_object().unwrap() {
        for (method, op) in item.as_object().unwrap() {
            if op.get("responses").is_some() {
                ops.push(Op {
                    path: path.clone(),
                    method: method.clone(),
                    op: op.clone(),
                });
            }
        }
    }
    ops
}

fn document(s: &Server) -> Value {
    let r = s.get("/api/v1/openapi.json");
    assert_eq!(r.status, 200, "{}", r.text);
    r.body
}

/// The document is made on its first request (on a blocking thread): several first requests
/// at once wait for the same one, and every answer, then and later, is the same bytes.
#[test]
fn first_requests_at_once_get_the_same_document() {
    let s = Server::start();
    let path = "/api/v1/openapi.json";
    let first: Vec<(u16, String)> = std::thread::scope(|scope| {
        let asking: Vec<_> = (0..6)
            .map(|_| {
                scope.spawn(|| {
                    let r = s.req(reqwest::Method::GET, path).send().unwrap();
                    (r.status().as_u16(), r.text().unwrap())
                })
            })
            .collect();
        asking.into_iter().map(|t| t.join().unwrap()).collect()
    });
    let later = s.get(path);
    assert_eq!(later.status, 200);
    for (status, text) in &first {
        assert_eq!(*status, 200, "{text}");
        assert!(
            *text == later.text,
            "a first answer differs from a later one"
        );
    }
    assert_eq!(later.body["openapi"], "3.1.0");
}

struct Answer {
    status: u16,
    body: Value,
    text: String,
}

/// Sends `op`'s example request; an event stream's body is not read (it does not end).
fn send_example(s: &Server, op: &Op, token: Option<&str>) -> Answer {
    let client = reqwest::blocking::Client::builder()
        .timeout(T)
        .build()
        .unwrap();
    let method = reqwest::Method::from_bytes(op.method.to_uppercase().as_bytes()).unwrap();
    let mut rb = client.request(method, s.url(&op.example_url()));
    if let Some(t) = token {
        rb = rb.bearer_auth(t);
    }
    if let Some((ctype, body)) = op.example_body() {
        rb = rb.header("content-type", ctype).body(body);
    }
    let r = rb
        .send()
        .unwrap_or_else(|e| panic!("{} {}: {e}", op.method, op.path));
    let status = r.status().as_u16();
    let streaming = r
        .headers()
        .get("content-type")
        .is_some_and(|v| v.as_bytes().starts_with(b"text/event-stream"));
    if streaming {
        return Answer {
            status,
            body: Value::Null,
            text: String::new(),
        };
    }
    let text = r.text().unwrap_or_default();
    Answer {
        status,
        body: serde_json::from_str(&text).unwrap_or(Value::Null),
        text,
    }
}

/// Runs tests/openapi_check.py on the document (and recorded responses). A missing validator
/// is a failure naming the install command (tests/run installs it).
fn python_check(doc: &Value, responses: Option<&Value>) {
    let dir = tempfile::tempdir().unwrap();
    let doc_file = dir.path().join("openapi.json");
    std::fs::write(&doc_file, serde_json::to_vec(doc).unwrap()).unwrap();
    let mut cmd = std::process::Command::new("python3");
    cmd.arg(workspace_root().join("tests/openapi_check.py"))
        .arg(&doc_file);
    if let Some(r) = responses {
        let f = dir.path().join("responses.json");
        std::fs::write(&f, serde_json::to_vec(r).unwrap()).unwrap();
        cmd.arg(f);
    }
    let out = cmd.output().unwrap_or_else(|e| {
        panic!("python3 is needed to validate the OpenAPI document ({e}): apt-get install python3")
    });
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert_ne!(
        out.status.code(),
        Some(3),
        "the OpenAPI validator is missing: pip install openapi-spec-validator\n{text}"
    );
    assert!(out.status.success(), "OpenAPI validation failed:\n{text}");
}

#[test]
fn the_document_is_valid_openapi_3_1_and_public() {
    let mut s = Server::unstarted(Opts {
        listen: "0.0.0.0:0".into(),
        demo: true,
        ..Opts::default()
    });
    s.create_token("viewer", "v");
    s.spawn().unwrap();
    // No token: the description is public, like /healthz (the API itself is not).
    s.get("/api/v1/machines")
        .expect_error(401, "token_required");
    let doc = document(&s);
    assert_eq!(doc["openapi"], "3.1.0");
    assert!(doc["components"]["securitySchemes"]["bearer"].is_object());
    // The SSE payload and the error body are described.
    let events = &doc["paths"]["/api/v1/events"]["get"]["responses"]["200"]["content"];
    assert_eq!(
        events["text/event-stream"]["schema"]["$ref"],
        "#/components/schemas/Event"
    );
    for field in ["id", "type", "machine", "actor", "time", "data"] {
        assert!(
            doc["components"]["schemas"]["Event"]["properties"][field].is_object(),
            "Event.{field}"
        );
    }
    python_check(&doc, None);
    // Made on the first request and kept: the next answer is the same text.
    let (first, again) = (
        s.get("/api/v1/openapi.json").text,
        s.get("/api/v1/openapi.json").text,
    );
    assert!(first.len() > 100_000, "{} bytes", first.len());
    assert_eq!(first, again);
}

#[test]
fn documented_operations_are_routed_with_their_role() {
    let mut s = Server::unstarted(Opts {
        listen: "0.0.0.0:0".into(),
        demo: true,
        ..Opts::default()
    });
    let viewer = s.create_token("viewer", "victor");
    let operator = s.create_token("operator", "olga");
    s.spawn().unwrap();
    s.token = Some(viewer.clone());
    s.wait_machine_state(1, "idle", T);
    let doc = document(&s);
    let ops = operations(&doc);
    assert!(ops.len() >= 25, "only {} operations documented", ops.len());
    let mut roles = std::collections::BTreeMap::new();
    for op in &ops {
        let what = format!("{} {}", op.method.to_uppercase(), op.path);
        // A route the router lacks gets the fallback: 404 `not_found` or 405.
        let routed = |a: &Answer| a.status != 405 && a.body["code"] != "not_found";
        match op.role() {
            "none" => {
                let a = send_example(&s, op, None);
                assert!(
                    routed(&a) && a.status != 401,
                    "{what}: {} {}",
                    a.status,
                    a.text
                );
            }
            "viewer" => {
                let a = send_example(&s, op, Some(&viewer));
                assert!(
                    routed(&a) && a.status != 401 && a.status != 403,
                    "{what} as a viewer: {} {}",
                    a.status,
                    a.text
                );
                let a = send_example(&s, op, None);
                assert_eq!(a.status, 401, "{what} without a token: {}", a.text);
            }
            role @ ("operator" | "admin") => {
                // The role check answers before the handler runs: only a routed, guarded
                // operation says `forbidden`.
                let below = if role == "admin" { &operator } else { &viewer };
                let a = send_example(&s, op, Some(below));
                assert_eq!(
                    (a.status, a.body["code"].as_str()),
                    (403, Some("forbidden")),
                    "{what} with a role below {role}: {}",
                    a.text
                );
                assert!(a.body["message"].as_str().unwrap().contains(role));
            }
            other => panic!("{what}: unknown role {other}"),
        }
        roles.insert(what, op.role().to_string());
    }
    // Spot checks against the README's table, so a wrong annotation cannot pass by itself.
    for (what, role) in [
        ("POST /api/v1/machines", "admin"),
        ("POST /api/v1/machines/{id}/jog", "operator"),
        ("GET /api/v1/machines/{id}/status", "viewer"),
        ("DELETE /api/v1/pendants/{id}", "admin"),
        ("PATCH /api/v1/pendants/{id}", "operator"),
        ("POST /api/v1/webhooks", "admin"),
        ("GET /api/v1/webhooks", "admin"),
        ("DELETE /api/v1/webhooks/{id}", "admin"),
        ("GET /healthz", "none"),
        ("GET /api/v1/openapi.json", "none"),
    ] {
        assert_eq!(roles.get(what).map(String::as_str), Some(role), "{what}");
    }
}

#[test]
fn documented_examples_get_their_documented_status() {
    let probe = Server::start_demo();
    let doc = document(&probe);
    drop(probe);
    let ops = operations(&doc);
    let mut recorded = Vec::new();
    // Reads share one server (they change nothing); every other example gets a fresh one, so
    // no example depends on another's side effects.
    let shared = Server::start_demo();
    shared.wait_machine_state(1, "idle", T);
    let mut prepared = std::collections::BTreeSet::new();
    for op in &ops {
        let what = format!("{} {}", op.method.to_uppercase(), op.path);
        if NOT_ON_THE_DEMO
            .iter()
            .any(|(m, p, _)| *m == op.method && *p == op.path)
        {
            continue;
        }
        let fresh;
        let s = if op.method == "get" {
            &shared
        } else {
            fresh = Server::start_demo();
            fresh.wait_machine_state(1, "idle", T);
            &fresh
        };
        // `/X/{id}...` needs an X: create one with the collection's own documented example.
        if let Some(rest) = op.path.strip_prefix("/api/v1/") {
            if let Some((collection, _)) = rest.split_once("/{") {
                let parent = format!("/api/v1/{collection}");
                let once = op.method != "get" || prepared.insert(parent.clone());
                let create = ops.iter().find(|o| o.path == parent && o.method == "post");
                if let (true, Some(create)) = (once, create) {
                    let a = send_example(s, create, None);
                    assert_eq!(a.status, create.success(), "setup {parent}: {}", a.text);
                }
            }
        }
        // Queue operations (issue 28) act on a job, and an entry's and the confirm on a queued
        // part: the jobs example's program, queued by the queue's own example.
        if op.method != "get" && op.path.contains("queue") {
            let example = |p: &str| ops.iter().find(|o| o.path == p && o.method == "post");
            let job = example("/api/v1/jobs").expect("the upload is documented");
            let a = send_example(s, job, None);
            assert_eq!(a.status, job.success(), "setup a job: {}", a.text);
            if op.path.contains("{entry}") || op.path.ends_with("/confirm") {
                let add = example("/api/v1/machines/{id}/queue").expect("queue add documented");
                let a = send_example(s, add, None);
                assert_eq!(a.status, add.success(), "setup a queued part: {}", a.text);
            }
        }
        let a = send_example(s, op, None);
        assert_eq!(
            a.status,
            op.success(),
            "{what} (example {}): {}",
            op.example_url(),
            a.text
        );
        if !a.body.is_null() {
            recorded.push(json!({"path": op.path, "method": op.method,
                                  "status": a.status, "body": a.body}));
        }
    }
    assert!(recorded.len() >= 20, "only {} JSON answers", recorded.len());
    // Each JSON answer matches the schema the document gives for it.
    python_check(&doc, Some(&json!(recorded)));
}

#[test]
fn routes_are_only_added_with_their_description() {
    let dir = workspace_root().join("server/http/src");
    let mut sources = String::new();
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "rs") {
            let text = std::fs::read_to_string(&p).unwrap();
            // A plain axum router (not `OpenApiRouter::new()`) would take routes the
            // description never sees.
            let plain_router = text
                .match_indices("Router::new()")
                .any(|(i, _)| !text[..i].ends_with("OpenApi"));
            assert!(!plain_router, "{} builds a plain axum Router", p.display());
            for forbidden in [".route(", ".route_service(", ".nest_service("] {
                assert!(
                    !text.contains(forbidden),
                    "{} uses `{forbidden}`: add routes as `.routes(needs(ROLE, routes!(handler)))` \
                     with a `#[utoipa::path]` on the handler, so the OpenAPI description has them",
                    p.display()
                );
            }
            sources.push_str(&text);
        }
    }
    // Every `routes!(...)` is wrapped in `needs(ROLE, ...)` or `public(...)`.
    let pieces: Vec<&str> = sources.split(".routes(").skip(1).collect();
    assert!(pieces.len() >= 25, "{} routes found", pieces.len());
    for piece in pieces {
        let head = &piece[..piece.find("routes!(").expect("routes! inside .routes(")];
        assert!(
            head.contains("needs(") || head.contains("public("),
            "a route without a stated role: .routes({}",
            &piece[..piece.len().min(80)]
        );
    }
}
