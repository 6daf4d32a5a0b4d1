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
        Receiver::start_on("127.0.0.1".parse().unwrap(), 0, answer)
    }

    fn start_on(ip: std::net::IpAddr, port: u16, answer: Answer) -> Receiver {
        let listener = TcpListener::bind((ip, port)).unwrap();
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
    let s = demo_with(LOOPBACK_RECEIVERS);
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
    let s = demo_with(LOOPBACK_RECEIVERS);
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
    let s = demo_with(
        "[webhooks]\nretry_initial_ms = 50\nmax_attempts = 3\nallowed_hosts = [\"127.0.0.1\"]\n",
    );
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
    let s =
        demo_with("[webhooks]\ntimeout_ms = 60000\nqueue = 2\nallowed_hosts = [\"127.0.0.1\"]\n");
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

/// The receivers in these tests listen on 127.0.0.1, which webhooks may target only when the
/// config opts it in.
const LOOPBACK_RECEIVERS: &str = "[webhooks]\nallowed_hosts = [\"127.0.0.1\"]\n";

#[test]
fn a_webhook_cannot_drive_this_servers_own_api() {
    let s = demo_with("");
    // Deliveries from loopback are the `local` admin: a hook on this server's own routes would
    // start jobs (or anything else) whenever an event fires.
    let job = s.upload(1, "short", "G21 G90\nG0 X1\nM2\n")["id"]
        .as_i64()
        .unwrap();
    let url = s.url(&format!("/api/v1/jobs/{job}/start"));
    let msg = s
        .post(
            "/api/v1/webhooks",
            &json!({"url": url, "events": ["machine"]}),
        )
        .expect_error(422, "webhook_target_refused");
    assert!(msg.contains("loopback"), "{msg}");
    assert!(msg.contains("webhooks.allowed_hosts"), "{msg}");
    assert_eq!(s.get("/api/v1/webhooks").expect(200), json!([]));
    s.command(1, "zero", json!({"axis": "X"})).expect(200);
    assert_eq!(s.job(job)["state"], "ready", "{}", s.job(job));
}

#[test]
fn bad_webhook_urls_are_refused_with_their_codes() {
    let s = demo_with("");
    let refused = "webhook_target_refused";
    let invalid = "invalid_field";
    for (url, code, says) in [
        (
            "http://169.254.169.254/latest/meta-data/",
            refused,
            "link-local",
        ),
        ("http://[fe80::1]/", refused, "link-local"),
        (
            "http://metadata.google.internal/computeMetadata/v1/",
            refused,
            "metadata",
        ),
        ("http://METADATA.google.internal./x", refused, "metadata"),
        (
            "http://100.100.100.200/latest/meta-data/",
            refused,
            "metadata",
        ),
        (
            "http://127.0.0.1:7878/api/v1/jobs/1/start",
            refused,
            "loopback",
        ),
        ("http://2130706433/", refused, "loopback"),
        ("http://127.1/", refused, "loopback"),
        ("http://0x7f.1/", refused, "loopback"),
        ("http://017700000001/", refused, "loopback"),
        ("http://%31%32%37.0.0.1/", refused, "loopback"),
        ("http://[::1]:8080/", refused, "loopback"),
        ("http://[::ffff:127.0.0.1]/", refused, "loopback"),
        ("http://[::ffff:169.254.169.254]/", refused, "link-local"),
        ("http://localhost:1/", refused, "loopback"),
        ("http://erp.localhost/", refused, "loopback"),
        ("http://0.0.0.0:7878/", refused, "unspecified"),
        ("http://0/", refused, "unspecified"),
        ("http://[::]/", refused, "unspecified"),
        ("http://224.0.0.1/", refused, "multicast"),
        ("http://[ff02::1]/", refused, "multicast"),
        ("http://255.255.255.255/", refused, "broadcast"),
        ("http:///api/v1/jobs/1/start", invalid, "host"),
        ("http://:80/", invalid, "host"),
        ("http://erp.example.com:99999/", invalid, "port"),
        ("http://erp.example.com:0/", invalid, "port"),
        ("ftp://erp.example.com/", invalid, "http"),
        ("file:///etc/passwd", invalid, "http"),
        ("http://user:pw@erp.example.com/", invalid, "user"),
        ("http://erp.example.com@127.0.0.1/", invalid, "user"),
        ("http://[::1/", invalid, "url"),
    ] {
        // An event type that never happens: even code that let one through sends it nothing.
        let r = s.post(
            "/api/v1/webhooks",
            &json!({"url": url, "events": ["test.never"]}),
        );
        assert_eq!(
            (r.status, r.body["code"].as_str()),
            (422, Some(code)),
            "{url}: {}",
            r.text
        );
        let msg = r.body["message"].as_str().unwrap();
        assert!(msg.contains(says) && msg.contains("url"), "{url}: {msg}");
    }
    assert_eq!(s.get("/api/v1/webhooks").expect(200), json!([]));
    // The shop's LAN is the normal place for a receiver (an ERP): private addresses and names
    // are accepted (and, filtered on that same event type, never sent anything).
    for url in [
        "http://10.0.0.5:8080/erp",
        "http://172.16.0.1/hook",
        "http://192.168.1.20/hook",
        "http://[fd12::1]/hook",
        "https://erp.example.com/hook",
    ] {
        let id = s
            .post(
                "/api/v1/webhooks",
                &json!({"url": url, "events": ["test.never"]}),
            )
            .expect(201)["id"]
            .as_i64()
            .unwrap();
        s.send(s.req(reqwest::Method::DELETE, &format!("/api/v1/webhooks/{id}")))
            .expect(204);
    }
}

#[test]
fn the_allow_list_opts_one_loopback_host_in_and_nothing_else() {
    let s = demo_with(LOOPBACK_RECEIVERS);
    let rx = Receiver::start(Answer::Statuses(vec![200]));
    s.post(
        "/api/v1/webhooks",
        &json!({"url": rx.url, "events": ["machine.jog"]}),
    )
    .expect(201);
    for (url, says) in [
        ("http://localhost:1/", "loopback"),
        ("http://[::1]:1/", "loopback"),
        ("http://169.254.169.254/", "link-local"),
    ] {
        let msg = s
            .post(
                "/api/v1/webhooks",
                &json!({"url": url, "events": ["test.never"]}),
            )
            .expect_error(422, "webhook_target_refused");
        assert!(msg.contains(says), "{url}: {msg}");
    }
    s.jog(1, "X", 1.0).expect(200);
    assert_eq!(
        rx.wait_deliveries(1)[0].header("Fresa-Event"),
        "machine.jog"
    );
}

/// The machine's host name, which the system resolver maps to this machine (here through
/// /etc/hosts to a loopback address): a real name whose addresses only resolving shows.
fn host_name_resolving_to_loopback() -> (String, std::net::IpAddr) {
    use std::net::ToSocketAddrs;
    let name = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .unwrap()
        .trim()
        .to_string();
    let addrs: Vec<_> = (name.as_str(), 0)
        .to_socket_addrs()
        .unwrap_or_else(|e| panic!("this test needs the host name {name:?} to resolve: {e}"))
        .map(|a| a.ip())
        .collect();
    assert!(
        !addrs.is_empty() && addrs.iter().all(|a| a.is_loopback()),
        "this test needs the host name {name:?} to resolve to loopback only (as Debian's \
         /etc/hosts has it); it resolves to {addrs:?}"
    );
    (name, addrs[0])
}

#[test]
fn a_name_that_resolves_to_loopback_is_refused_at_delivery() {
    let (name, ip) = host_name_resolving_to_loopback();
    let s = demo_with("[webhooks]\nretry_initial_ms = 50\nmax_attempts = 3\n");
    let listener = TcpListener::bind((ip, 0)).unwrap();
    let port = listener.local_addr().unwrap().port();
    drop(listener);
    // A receiver on that address: what the old code would have delivered to.
    let rx = Receiver::start_on(ip, port, Answer::Statuses(vec![200]));
    let url = format!("http://{name}:{port}/hook");
    // A name is not resolved at registration (its addresses can change before any delivery).
    let id = s
        .post(
            "/api/v1/webhooks",
            &json!({"url": url, "events": ["machine.jog"]}),
        )
        .expect(201)["id"]
        .as_i64()
        .unwrap();
    s.jog(1, "X", 1.0).expect(200);
    let hook = wait_for(T, "the delivery's outcome", || {
        let h = s.get(&format!("/api/v1/webhooks/{id}")).expect(200);
        (h["delivered"] != 0 || h["failed"] != 0).then_some(h)
    });
    assert_eq!(
        (hook["delivered"].clone(), hook["failed"].clone()),
        (json!(0), json!(1)),
        "{hook}"
    );
    let error = hook["last_error"].as_str().unwrap();
    assert!(
        error.contains("refused") && error.contains("loopback") && error.contains(&ip.to_string()),
        "{error}"
    );
    // Refused is final: not retried.
    assert_eq!(hook["last_attempts"], 1, "{hook}");
    assert_eq!(hook["last_status"], Value::Null, "{hook}");
    assert_eq!(metric(&s, "fresa_webhook_refused_total"), 1);
    assert_eq!(*rx.connections.lock().unwrap(), 0);
    assert!(rx.deliveries().is_empty());
}

#[test]
fn a_loopback_webhook_registered_before_is_refused_at_delivery() {
    // Registered while the config allowed it (or by an older version that checked nothing).
    let mut s = demo_with(LOOPBACK_RECEIVERS);
    let rx = Receiver::start(Answer::Statuses(vec![200]));
    let id = s
        .post(
            "/api/v1/webhooks",
            &json!({"url": rx.url, "events": ["machine.jog"]}),
        )
        .expect(201)["id"]
        .as_i64()
        .unwrap();
    s.kill();
    s.write_config("");
    s.spawn().unwrap();
    s.wait_machine_state(1, "idle", T);
    s.jog(1, "X", 1.0).expect(200);
    let hook = wait_for(T, "the delivery's outcome", || {
        let h = s.get(&format!("/api/v1/webhooks/{id}")).expect(200);
        (h["delivered"] != 0 || h["failed"] != 0).then_some(h)
    });
    assert_eq!(hook["failed"], 1, "{hook}");
    let error = hook["last_error"].as_str().unwrap();
    assert!(
        error.contains("refused") && error.contains("loopback"),
        "{error}"
    );
    assert_eq!(*rx.connections.lock().unwrap(), 0);
}

/// This machine's own addresses other than loopback and link-local ones, from the kernel's
/// tables (IPv4: the `/32 host LOCAL` entries; IPv6: the interface addresses).
fn own_addresses() -> Vec<std::net::IpAddr> {
    let mut out = Vec::new();
    let trie = std::fs::read_to_string("/proc/net/fib_trie").unwrap_or_default();
    let mut last = None;
    for line in trie.lines() {
        let t = line.trim();
        if let Some(a) = t.strip_prefix("|-- ") {
            last = a.parse::<std::net::Ipv4Addr>().ok();
        } else if t.starts_with("/32 host LOCAL") {
            if let Some(a) = last.filter(|a| !a.is_loopback()) {
                out.push(std::net::IpAddr::V4(a));
            }
        }
    }
    let v6 = std::fs::read_to_string("/proc/net/if_inet6").unwrap_or_default();
    for line in v6.lines() {
        let Some(hex) = line.split_whitespace().next() else {
            continue;
        };
        let Ok(bits) = u128::from_str_radix(hex, 16) else {
            continue;
        };
        let a = std::net::Ipv6Addr::from(bits);
        if !a.is_loopback() && a.segments()[0] & 0xffc0 != 0xfe80 {
            out.push(std::net::IpAddr::V6(a));
        }
    }
    out.sort();
    out.dedup();
    out
}

#[test]
fn this_machines_own_addresses_are_refused_even_in_private_ranges() {
    let own = own_addresses();
    assert!(
        !own.is_empty(),
        "this test needs a non-loopback address on this machine (from /proc/net/fib_trie or \
         /proc/net/if_inet6)"
    );
    let s = demo_with("");
    for ip in own {
        let host = match ip {
            std::net::IpAddr::V4(a) => a.to_string(),
            std::net::IpAddr::V6(a) => format!("[{a}]"),
        };
        let url = format!("http://{host}:7878/api/v1/jobs/1/start");
        let msg = s
            .post(
                "/api/v1/webhooks",
                &json!({"url": url, "events": ["test.never"]}),
            )
            .expect_error(422, "webhook_target_refused");
        assert!(msg.contains("this server's own address"), "{url}: {msg}");
    }
}
