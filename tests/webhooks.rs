//! Webhooks against local receivers on 127.0.0.1: signed deliveries that a receiver verifies,
//! the event filter, retries of a failing receiver, and a hanging receiver that holds up nothing
//! but its own queue.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{wait_for, Opts, Server};
use hmac::{Hmac, Mac};
use sha2::Sha256;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const T: Duration = Duration::from_secs(60);

/// One request a receiver got.
#[derive(Debug, Clone)]
struct Delivery {
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Delivery {
    fn header(&self, name: &str) -> &str {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
            .unwrap_or_else(|| panic!("no {name} header in {:?}", self.headers))
    }
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap()
    }
}

/// What a receiver answers: a status per request in turn (the last one repeats), or nothing.
#[derive(Clone)]
enum Answer {
    Statuses(Vec<u16>),
    Hang,
}

/// A minimal HTTP/1.1 receiver on an ephemeral loopback port, one thread per connection.
struct Receiver {
    url: String,
    got: Arc<Mutex<Vec<Delivery>>>,
    /// Connections accepted (a hanging receiver never answers them).
    connections: Arc<Mutex<usize>>,
}

impl Receiver {
    fn start(answer: Answer) -> Receiver {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/hook", listener.local_addr().unwrap());
        let got = Arc::new(Mutex::new(Vec::new()));
        let connections = Arc::new(Mutex::new(0));
        let (g, c) = (got.clone(), connections.clone());
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(stream) = stream else { return };
                *c.lock().unwrap() += 1;
                let (g, answer) = (g.clone(), answer.clone());
                std::thread::spawn(move || serve(stream, &g, &answer));
            }
        });
        Receiver {
            url,
            got,
            connections,
        }
    }

    fn deliveries(&self) -> Vec<Delivery> {
        self.got.lock().unwrap().clone()
    }

    fn wait_deliveries(&self, n: usize) -> Vec<Delivery> {
        wait_for(T, &format!("{n} deliveries"), || {
            let d = self.deliveries();
            (d.len() >= n).then_some(d)
        })
    }
}

fn serve(stream: TcpStream, got: &Mutex<Vec<Delivery>>, answer: &Answer) {
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    let mut out = stream;
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap_or(0) == 0 {
            return;
        }
        let mut headers = Vec::new();
        let mut len = 0;
        loop {
            let mut h = String::new();
            if reader.read_line(&mut h).unwrap_or(0) == 0 {
                return;
            }
            let h = h.trim_end();
            if h.is_empty() {
                break;
            }
            let (k, v) = h.split_once(':').unwrap();
            if k.eq_ignore_ascii_case("content-length") {
                len = v.trim().parse().unwrap();
            }
            headers.push((k.to_string(), v.trim().to_string()));
        }
        let mut body = vec![0; len];
        reader.read_exact(&mut body).unwrap();
        let n = {
            let mut g = got.lock().unwrap();
            g.push(Delivery { headers, body });
            g.len()
        };
        let status = match answer {
            Answer::Hang => {
                // Hold the connection open, answering nothing, until fresa gives up on it.
                let mut sink = Vec::new();
                let _ = reader.read_to_end(&mut sink);
                return;
            }
            Answer::Statuses(s) => s[(n - 1).min(s.len() - 1)],
        };
        let resp = format!("HTTP/1.1 {status} X\r\ncontent-length: 0\r\n\r\n");
        if out.write_all(resp.as_bytes()).is_err() {
            return;
        }
    }
}

/// What a receiver does: recompute the HMAC over `"<t>.<body>"` and compare, in constant time.
fn verify(secret: &str, d: &Delivery) -> bool {
    let sig = d.header("Fresa-Signature");
    let mut t = None;
    let mut v1 = None;
    for part in sig.split(',') {
        match part.split_once('=') {
            Some(("t", v)) => t = Some(v.to_string()),
            Some(("v1", v)) => v1 = Some(v.to_string()),
            _ => {}
        }
    }
    let (Some(t), Some(v1)) = (t, v1) else {
        return false;
    };
    let Ok(expected) = hex::decode(v1) else {
        return false;
    };
    let mut mac = Hmac::<Sha256>::new_from_slice(secret.as_bytes()).unwrap();
    mac.update(t.as_bytes());
    mac.update(b".");
    mac.update(&d.body);
    mac.verify_slice(&expected).is_ok()
}

fn metric(s: &Server, name: &str) -> u64 {
    let text = s.get("/metrics").text;
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {name} in /metrics:\n{text}"))
}

fn demo_with(config: &str) -> Server {
    let mut s = Server::unstarted(Opts {
        demo: true,
        ..Opts::default()
    });
    s.write_config(config);
    s.spawn().unwrap();
    s.wait_machine_state(1, "idle", T);
    s
}

#[test]
fn deliveries_are_signed_filtered_and_recorded() {
    let s = demo_with("");
    let rx = Receiver::start(Answer::Statuses(vec![200]));
    let created = s
        .post(
            "/api/v1/webhooks",
            &json!({"url": rx.url, "events": ["machine.jog", "job"]}),
        )
        .expect(201);
    let id = created["id"].as_i64().unwrap();
    let secret = created["secret"].as_str().unwrap().to_string();
    assert!(
        secret.starts_with("whsec_") && secret.len() > 40,
        "{secret}"
    );
    // The secret is shown once: never in the list or the webhook itself.
    let list = s.get("/api/v1/webhooks").expect(200);
    assert_eq!(list[0]["url"], rx.url.as_str());
    assert_eq!(list[0]["events"], json!(["machine.jog", "job"]));
    assert!(!list.to_string().contains(&secret));
    assert!(!s
        .get(&format!("/api/v1/webhooks/{id}"))
        .expect(200)
        .to_string()
        .contains(&secret));

    // Not in the filter, then in it: per webhook deliveries are in order, so once the jog has
    // arrived the command would have too.
    s.command(1, "zero", json!({"axis": "X"})).expect(200);
    s.jog(1, "X", 2.0).expect(200);
    let got = rx.wait_deliveries(1);
    assert_eq!(got.len(), 1, "{got:?}");
    let d = &got[0];
    assert_eq!(d.header("Fresa-Event"), "machine.jog");
    assert_eq!(d.header("content-type"), "application/json");
    let ev = d.json();
    assert_eq!(ev["type"], "machine.jog");
    assert_eq!(ev["machine"], 1);
    assert_eq!(ev["data"]["distance"], 2.0, "{ev}");
    let event_id = ev["id"].as_i64().unwrap();
    assert_eq!(d.header("Fresa-Delivery"), format!("{id}-{event_id}"));
    // The receiver's check passes, and fails for a changed body or another secret.
    assert!(
        verify(&secret, d),
        "signature {}",
        d.header("Fresa-Signature")
    );
    let mut tampered = d.clone();
    tampered.body = d.body.replace_last_digit();
    assert!(!verify(&secret, &tampered));
    assert!(!verify("whsec_other", d));
    // The timestamp is now (a receiver rejects old ones to stop replays).
    let t: u64 = d.header("Fresa-Signature")[2..12].parse().unwrap();
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs();
    assert!(now.abs_diff(t) < 600, "t={t} now={now}");

    let hook = wait_for(T, "the delivery recorded", || {
        let h = s.get(&format!("/api/v1/webhooks/{id}")).expect(200);
        (h["delivered"] == 1).then_some(h)
    });
    assert_eq!(hook["last_status"], 200);
    assert_eq!(hook["last_attempts"], 1);
    assert_eq!(hook["failed"], 0);

    // Deleted: no more deliveries, and 404 afterwards.
    s.send(s.req(reqwest::Method::DELETE, &format!("/api/v1/webhooks/{id}")))
        .expect(204);
    s.send(s.req(reqwest::Method::DELETE, &format!("/api/v1/webhooks/{id}")))
        .expect_error(404, "unknown_webhook");
    assert_eq!(metric(&s, "fresa_webhook_delivered_total"), 1);
}

trait ReplaceLastDigit {
    fn replace_last_digit(&self) -> Vec<u8>;
}

impl ReplaceLastDigit for Vec<u8> {
    fn replace_last_digit(&self) -> Vec<u8> {
        let mut b = self.clone();
        let i = b.iter().rposition(u8::is_ascii_digit).unwrap();
        b[i] = if b[i] == b'9' { b'8' } else { b[i] + 1 };
        b
    }
}

#[test]
fn bad_registrations_are_refused_naming_the_field() {
    let s = demo_with("");
    let msg = s
        .post("/api/v1/webhooks", &json!({"url": "ftp://x/y"}))
        .expect_error(422, "invalid_field");
    assert!(msg.contains("url"), "{msg}");
    let msg = s
        .post(
            "/api/v1/webhooks",
            &json!({"url": "http://127.0.0.1:1/", "events": ["job", "No Such"]}),
        )
        .expect_error(422, "invalid_field");
    assert!(msg.contains("events[1]"), "{msg}");
    s.post(
        "/api/v1/webhooks",
        &json!({"url": "http://127.0.0.1:1/", "secret": "mine"}),
    )
    .expect_error(400, "invalid_json");
}

#[test]
fn a_failing_receiver_gets_retries_with_the_same_delivery_id() {
    let s = demo_with("[webhooks]\nretry_initial_ms = 50\nmax_attempts = 3\n");
    // Two failures then success; then a receiver that always fails.
    let flaky = Receiver::start(Answer::Statuses(vec![500, 503, 200]));
    let broken = Receiver::start(Answer::Statuses(vec![500]));
    let flaky_id = s
        .post(
            "/api/v1/webhooks",
            &json!({"url": flaky.url, "events": ["machine.jog"]}),
        )
        .expect(201)["id"]
        .as_i64()
        .unwrap();
    let broken_id = s
        .post(
            "/api/v1/webhooks",
            &json!({"url": broken.url, "events": ["machine.jog"]}),
        )
        .expect(201)["id"]
        .as_i64()
        .unwrap();
    s.jog(1, "Y", 1.0).expect(200);
    let got = flaky.wait_deliveries(3);
    let ids: Vec<&str> = got.iter().map(|d| d.header("Fresa-Delivery")).collect();
    assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");
    let hook = wait_for(T, "flaky delivered", || {
        let h = s.get(&format!("/api/v1/webhooks/{flaky_id}")).expect(200);
        (h["delivered"] == 1).then_some(h)
    });
    assert_eq!(
        (hook["last_status"].clone(), hook["last_attempts"].clone()),
        (json!(200), json!(3))
    );

    assert_eq!(broken.wait_deliveries(3).len(), 3);
    let hook = wait_for(T, "broken given up", || {
        let h = s.get(&format!("/api/v1/webhooks/{broken_id}")).expect(200);
        (h["failed"] == 1).then_some(h)
    });
    assert_eq!(hook["last_status"], 500);
    assert_eq!(hook["last_attempts"], 3);
    assert_eq!(hook["delivered"], 0);
    assert!(
        hook["last_error"].as_str().unwrap().contains("500"),
        "{hook}"
    );
    // Exactly max_attempts: no fourth try.
    assert_eq!(broken.deliveries().len(), 3);
    assert_eq!(metric(&s, "fresa_webhook_retries_total"), 4);
    assert_eq!(metric(&s, "fresa_webhook_failed_total"), 1);
}

#[test]
fn a_hanging_receiver_does_not_hold_up_status_events_or_machines() {
    // A long timeout and a tiny queue: the receiver holds its first delivery, the queue fills.
    let s = demo_with("[webhooks]\ntimeout_ms = 60000\nqueue = 2\n");
    let hung = Receiver::start(Answer::Hang);
    let ok = Receiver::start(Answer::Statuses(vec![200]));
    s.post("/api/v1/webhooks", &json!({"url": hung.url}))
        .expect(201);
    s.post(
        "/api/v1/webhooks",
        &json!({"url": ok.url, "events": ["machine.jog"]}),
    )
    .expect(201);
    let stream = s.events("types=status&machine=1", None);
    // The demo machine starts at x = 0; every jog here is +1 mm.
    let mut x = 0.0;
    wait_for(T, "the hanging receiver holds a delivery", || {
        s.jog(1, "X", 1.0).expect(200);
        x += 1.0;
        (*hung.connections.lock().unwrap() >= 1 && !hung.deliveries().is_empty()).then_some(())
    });
    // While it hangs: jogs are answered, each one's position shows up in a status event, and
    // the other webhook gets every jog.
    let before = ok.deliveries().len();
    for _ in 0..6 {
        s.jog(1, "X", 1.0).expect(200);
        x += 1.0;
        stream.until(T, &format!("status at x={x}"), |e| {
            (e.data["data"]["machine_position"]["x"]
                .as_f64()
                .unwrap_or(f64::NAN)
                - x)
                .abs()
                < 1e-6
        });
    }
    let total = x as usize;
    assert!(before <= total);
    assert_eq!(
        ok.wait_deliveries(total).len(),
        total,
        "every jog delivered"
    );
    // The hung webhook's queue (2) overflowed: drops are counted, not waited for.
    assert!(metric(&s, "fresa_webhook_dropped_total") >= 1);
    assert_eq!(
        hung.deliveries().len(),
        1,
        "one delivery held, none after it"
    );
}
