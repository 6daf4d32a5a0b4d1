//! The MQTT bridge against a real broker: Debian's `mosquitto`, started here on an ephemeral
//! loopback port with a generated config. A missing broker fails the test naming the package.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_tests::serde_json::{json, Value};
use fresa_tests::{wait_for, Opts, Server};
use rumqttc::{Client, Event, MqttOptions, Packet, QoS};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

const T: Duration = Duration::from_secs(60);
const MOSQUITTO: &str = "/usr/sbin/mosquitto";

/// A mosquitto process on 127.0.0.1:`port`, killed on drop.
struct Broker {
    port: u16,
    dir: tempfile::TempDir,
    child: Option<Child>,
}

impl Broker {
    fn start() -> Broker {
        assert!(
            Path::new(MOSQUITTO).is_file(),
            "the MQTT tests need Debian's mosquitto broker ({MOSQUITTO}): apt-get install mosquitto"
        );
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let mut b = Broker {
            port,
            dir: tempfile::tempdir().unwrap(),
            child: None,
        };
        b.run();
        b
    }

    /// (Re)starts it on the same port and waits until it accepts connections.
    fn run(&mut self) {
        let conf = self.dir.path().join("mosquitto.conf");
        std::fs::write(
            &conf,
            format!(
                "listener {} 127.0.0.1\nallow_anonymous true\npersistence false\n",
                self.port
            ),
        )
        .unwrap();
        let child = Command::new(MOSQUITTO)
            .arg("-c")
            .arg(&conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start mosquitto");
        self.child = Some(child);
        wait_for(T, "mosquitto accepting connections", || {
            std::net::TcpStream::connect(("127.0.0.1", self.port))
                .ok()
                .map(|_| ())
        });
    }

    fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    fn url(&self) -> String {
        format!("mqtt://127.0.0.1:{}", self.port)
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A test client subscribed to `filters`; messages arrive on a channel.
struct Sub {
    client: Client,
    rx: mpsc::Receiver<(String, Value, bool)>,
}

impl Sub {
    fn new(broker: &Broker, filters: &[&str]) -> Sub {
        let id = format!("test-{}", rand_suffix());
        let mut opts = MqttOptions::new(id, "127.0.0.1", broker.port);
        opts.set_keep_alive(Duration::from_secs(30));
        // Room for the oversized messages the tests send.
        opts.set_max_packet_size(4 << 20, 4 << 20);
        let (client, mut conn) = Client::new(opts, 100);
        for f in filters {
            client.subscribe(*f, QoS::AtLeastOnce).unwrap();
        }
        let (tx, rx) = mpsc::channel();
        let (subscribed_tx, subscribed) = mpsc::channel();
        std::thread::spawn(move || {
            let mut acks = 0;
            for ev in conn.iter() {
                match ev {
                    Ok(Event::Incoming(Packet::SubAck(_))) => {
                        acks += 1;
                        let _ = subscribed_tx.send(acks);
                    }
                    Ok(Event::Incoming(Packet::Publish(p))) => {
                        let v = serde_json::from_slice(&p.payload).unwrap_or(Value::Null);
                        if tx.send((p.topic.clone(), v, p.retain)).is_err() {
                            return;
                        }
                    }
                    Ok(_) => {}
                    Err(_) => return,
                }
            }
        });
        // Subscribed once every filter is acknowledged.
        let n = filters.len();
        wait_for(T, "subscriptions acknowledged", || {
            subscribed.recv_timeout(T).ok().filter(|a| *a >= n)
        });
        Sub { client, rx }
    }

    /// Waits for a message on `topic` whose payload passes `pred`.
    #[track_caller]
    fn until(&self, topic: &str, pred: impl Fn(&Value, bool) -> bool) -> (Value, bool) {
        let deadline = std::time::Instant::now() + T;
        let mut seen = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.rx.recv_timeout(left) {
                Ok((t, v, retain)) => {
                    if t == topic && pred(&v, retain) {
                        return (v, retain);
                    }
                    seen.push(format!("{t} {v}"));
                }
                Err(_) => panic!("no message on {topic}; seen {seen:#?}"),
            }
        }
    }

    fn publish(&self, topic: &str, payload: &Value) {
        self.publish_bytes(topic, false, payload.to_string().into_bytes());
    }

    fn publish_bytes(&self, topic: &str, retain: bool, payload: Vec<u8>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, retain, payload)
            .unwrap();
    }
}

/// Leaves a retained message on the broker, as anyone allowed to publish there could; returns
/// once the broker has it (a subscriber got it).
fn leave_retained(broker: &Broker, topic: &str, payload: Vec<u8>) {
    let sub = Sub::new(broker, &[topic]);
    sub.publish_bytes(topic, true, payload);
    sub.until(topic, |_, _| true);
}

/// Knocks the bridge off the broker: a client connecting with the bridge's client id takes its
/// place (MQTT 3.1.1, 3.1.4), then leaves at once, so the bridge reconnects and subscribes anew.
fn take_over(broker: &Broker, client_id: &str) {
    let mut opts = MqttOptions::new(client_id, "127.0.0.1", broker.port);
    opts.set_keep_alive(Duration::from_secs(30));
    let (client, mut conn) = Client::new(opts, 10);
    for ev in conn.iter() {
        match ev {
            Ok(Event::Incoming(Packet::ConnAck(_))) => break,
            Ok(_) => {}
            Err(e) => panic!("taking over the bridge's client id: {e}"),
        }
    }
    client.disconnect().unwrap();
    for ev in conn.iter() {
        match ev {
            Ok(Event::Outgoing(rumqttc::Outgoing::Disconnect)) | Err(_) => break,
            Ok(_) => {}
        }
    }
}

/// A demo server whose bridge takes commands, with a known client id; waits until the broker
/// has its command subscriptions.
fn commanded_demo(broker: &Broker, client_id: &str) -> (Server, String) {
    let mut s = Server::unstarted(Opts {
        demo: true,
        ..Opts::default()
    });
    let operator = s.create_token("operator", "olga");
    s.write_config(&format!(
        "[mqtt]\nurl = \"{}\"\ntopic_prefix = \"t\"\ncommands = true\nclient_id = \"{client_id}\"\n",
        broker.url()
    ));
    s.spawn().unwrap();
    s.wait_machine_state(1, "idle", T);
    wait_for(T, "command subscriptions confirmed", || {
        (metric(&s, "fresa_mqtt_commands_ready") == 1.0).then_some(())
    });
    (s, operator)
}

/// Publishes a live (not retained) jog and waits for its answer on `cmd/results`.
fn live_jog(c: &Sub, token: &str, axis: &str, distance: f64, request_id: &str) -> Value {
    c.publish(
        "t/cmd/machines/1/jog",
        &json!({"axis": axis, "distance": distance, "request_id": request_id, "token": token}),
    );
    c.until("t/cmd/results", |v, _| v["request_id"] == request_id)
        .0
}

fn rand_suffix() -> u64 {
    fresa_tests::Rng::clock_seed() ^ u64::from(std::process::id())
}

fn metric(s: &Server, name: &str) -> f64 {
    let text = s.get("/metrics").text;
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {name} in /metrics:\n{text}"))
}

fn bridged_demo(broker: &Broker, extra: &str) -> Server {
    let mut s = Server::unstarted(Opts {
        demo: true,
        ..Opts::default()
    });
    s.write_config(&format!(
        "[mqtt]\nurl = \"{}\"\ntopic_prefix = \"t\"\n{extra}",
        broker.url()
    ));
    s.spawn().unwrap();
    s.wait_machine_state(1, "idle", T);
    wait_for(T, "bridge connected", || {
        (metric(&s, "fresa_mqtt_connected") == 1.0).then_some(())
    });
    s
}

/// What a client connecting now gets first on `t/machines/1/status` (the retained message),
/// polled with a fresh client until it shows `x`.
fn retained_status(broker: &Broker, x: f64) -> Value {
    wait_for(T, &format!("retained status at x={x}"), || {
        let sub = Sub::new(broker, &["t/machines/1/status"]);
        let (t, v, retain) = sub.rx.recv_timeout(T).expect("a retained status");
        assert_eq!(t, "t/machines/1/status");
        assert!(
            retain,
            "the first message after subscribing is the retained one: {v}"
        );
        x_is(&v, x).then_some(v)
    })
}

fn x_is(v: &Value, x: f64) -> bool {
    (v["machine_position"]["x"].as_f64().unwrap_or(f64::NAN) - x).abs() < 1e-6
}

#[test]
fn status_job_state_events_and_the_node_reach_the_broker() {
    let broker = Broker::start();
    let s = bridged_demo(&broker, "");
    let events = Sub::new(&broker, &["t/events/#"]);
    s.jog(1, "X", 3.0).expect(200);
    let (ev, _) = events.until("t/events/machine.jog", |_, _| true);
    assert_eq!(ev["type"], "machine.jog");
    assert_eq!(ev["data"]["distance"], 3.0);
    assert_eq!(ev["actor"], "local");

    // A client that connects later gets the retained status, with GET .../status's fields.
    let status = retained_status(&broker, 3.0);
    let late = Sub::new(&broker, &["t/nodes/+/online"]);
    let http = s.get("/api/v1/machines/1/status").expect(200);
    let keys = |v: &Value| {
        let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
        k.sort();
        k
    };
    assert_eq!(keys(&status), keys(&http), "{status} vs {http}");
    assert_eq!(status["machine"], 1);
    let (online, retained) = late.until_online_topic();
    assert!(retained && online["online"] == true, "{online}");

    // A job run to its end: its state is retained on jobs/<id>/state.
    let job = s.upload(1, "short", "G21 G90\nG0 X5\nG1 X6 F3000\nM2\n")["id"]
        .as_i64()
        .unwrap();
    let topic = format!("t/jobs/{job}/state");
    let live = Sub::new(&broker, &[&topic]);
    s.job_action(job, "start").expect(200);
    s.wait_job_state(job, "completed", T);
    // The job's end reaches the broker after the store has it: wait until the bridge has
    // published it, then a new subscriber must get it as the retained message.
    live.until(&topic, |v, _| v["state"] == "completed");
    let later = Sub::new(&broker, &[&topic]);
    let (state, retained) = later.until(&format!("t/jobs/{job}/state"), |v, _| {
        v["state"] == "completed"
    });
    assert!(retained);
    assert_eq!(state["job"], job);
    assert_eq!(state["machine"], 1);
    events.until("t/events/job.state", |v, _| {
        v["data"]["state"] == "completed"
    });

    // The server dies without a word: the broker publishes its last will.
    let watcher = Sub::new(&broker, &["t/nodes/+/online"]);
    watcher.until_online_topic();
    let mut s = s;
    s.kill();
    let (gone, _) = watcher.until_online(|v| v["online"] == false);
    assert_eq!(gone["online"], false);
}

impl Sub {
    /// The node's online message (its topic has the host name in it).
    fn until_online_topic(&self) -> (Value, bool) {
        self.until_online(|_| true)
    }

    fn until_online(&self, pred: impl Fn(&Value) -> bool) -> (Value, bool) {
        let deadline = std::time::Instant::now() + T;
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            let (t, v, retain) = self
                .rx
                .recv_timeout(left)
                .expect("no message on t/nodes/<node>/online");
            if t.starts_with("t/nodes/") && t.ends_with("/online") && pred(&v) {
                return (v, retain);
            }
        }
    }
}

#[test]
fn a_broker_outage_leaves_the_machines_alone_and_the_bridge_reconnects() {
    let mut broker = Broker::start();
    // A small queue, so the outage overflows it.
    let s = bridged_demo(&broker, "queue = 5\n");
    broker.stop();
    wait_for(T, "bridge sees the broker gone", || {
        (metric(&s, "fresa_mqtt_connected") == 0.0).then_some(())
    });
    // Machines answer as usual while the broker is away.
    let stream = s.events("types=status&machine=1", None);
    for i in 1..=5 {
        s.jog(1, "X", 1.0).expect(200);
        stream.until(T, &format!("status at x={i}"), |e| {
            x_is(&e.data["data"], f64::from(i))
        });
    }
    // What did not fit while the broker was away was dropped and counted, not waited for.
    assert!(metric(&s, "fresa_mqtt_dropped_total") > 0.0);
    broker.run();
    wait_for(T, "bridge reconnected", || {
        (metric(&s, "fresa_mqtt_connected") == 1.0
            && metric(&s, "fresa_mqtt_reconnects_total") >= 1.0)
            .then_some(())
    });
    // The restarted broker kept nothing (no persistence): the bridge republished the status.
    retained_status(&broker, 5.0);
    // And new events flow again.
    let events = Sub::new(&broker, &["t/events/#"]);
    s.jog(1, "X", 1.0).expect(200);
    events.until("t/events/machine.jog", |_, _| true);
}

#[test]
fn commands_need_a_token_with_the_operator_role() {
    let broker = Broker::start();
    let mut s = Server::unstarted(Opts {
        demo: true,
        ..Opts::default()
    });
    let operator = s.create_token("operator", "olga");
    let viewer = s.create_token("viewer", "victor");
    s.write_config(&format!(
        "[mqtt]\nurl = \"{}\"\ntopic_prefix = \"t\"\ncommands = true\n",
        broker.url()
    ));
    s.spawn().unwrap();
    s.wait_machine_state(1, "idle", T);
    wait_for(T, "bridge connected", || {
        (metric(&s, "fresa_mqtt_connected") == 1.0).then_some(())
    });
    // Commands reach the bridge only once the broker has its subscriptions.
    wait_for(T, "command subscriptions confirmed", || {
        (metric(&s, "fresa_mqtt_commands_ready") == 1.0).then_some(())
    });
    let c = Sub::new(&broker, &["t/cmd/results"]);
    let jog = "t/cmd/machines/1/jog";
    for (payload, code) in [
        (
            json!({"axis": "X", "distance": 2.0, "request_id": "a"}),
            "token_required",
        ),
        (
            json!({"axis": "X", "distance": 2.0, "request_id": "b", "token": "fresa_bogus"}),
            "invalid_token",
        ),
        (
            json!({"axis": "X", "distance": 2.0, "request_id": "c", "token": viewer}),
            "forbidden",
        ),
    ] {
        c.publish(jog, &payload);
        let rid = payload["request_id"].clone();
        let (answer, _) = c.until("t/cmd/results", |v, _| v["request_id"] == rid);
        assert_eq!(
            (answer["ok"].clone(), answer["code"].clone()),
            (json!(false), json!(code)),
            "{answer}"
        );
    }
    assert_eq!(metric(&s, "fresa_mqtt_commands_refused_total"), 3.0);
    // Refused means not done: nothing moved, nothing was logged as a jog.
    assert!(x_is(&s.status(1), 0.0));
    // The same limits as HTTP: past max_jog_mm is refused by the core.
    c.publish(
        jog,
        &json!({"axis": "X", "distance": 5000.0, "request_id": "d", "token": operator}),
    );
    let (answer, _) = c.until("t/cmd/results", |v, _| v["request_id"] == "d");
    assert_eq!(answer["code"], "jog_too_far", "{answer}");
    // With an operator token it is carried out, and audited as coming over MQTT.
    c.publish(
        jog,
        &json!({"axis": "X", "distance": 2.0, "request_id": "e", "token": operator}),
    );
    let (answer, _) = c.until("t/cmd/results", |v, _| v["request_id"] == "e");
    assert_eq!(answer["ok"], true, "{answer}");
    s.wait_status(1, T, "x = 2 after the MQTT jog", |st| x_is(st, 2.0));
    let stream = s.events("types=machine.jog", Some(0));
    let ev = stream.until(T, "the jog event", |e| e.event == "machine.jog");
    assert_eq!(ev.last().unwrap().data["actor"], "mqtt:olga");

    // While a jog runs a zero is refused as over HTTP, and jog/cancel ends the jog.
    c.publish(
        jog,
        &json!({"axis": "X", "distance": 40.0, "feed": 100.0, "request_id": "f", "token": operator}),
    );
    let (answer, _) = c.until("t/cmd/results", |v, _| v["request_id"] == "f");
    assert_eq!(answer["ok"], true, "{answer}");
    c.publish(
        "t/cmd/machines/1/commands",
        &json!({"command": "zero", "axis": "X", "request_id": "g", "token": operator}),
    );
    let (answer, _) = c.until("t/cmd/results", |v, _| v["request_id"] == "g");
    assert_eq!(answer["code"], "machine_moving", "{answer}");
    c.publish(
        "t/cmd/machines/1/jog/cancel",
        &json!({"request_id": "h", "token": operator}),
    );
    let (answer, _) = c.until("t/cmd/results", |v, _| v["request_id"] == "h");
    assert_eq!(answer["ok"], true, "{answer}");
    assert_eq!(answer["result"]["stopped"], true, "{answer}");
    let st = s.status(1);
    assert_eq!(st["state"], "idle", "stopped before the answer: {st}");
    assert!(st["machine_position"]["x"].as_f64().unwrap() < 42.0, "{st}");

    // An override through the same topic, checked against the machine's range.
    let mut answers = Vec::new();
    for (feed, id) in [(60.0, "i"), (900.0, "j")] {
        c.publish(
            "t/cmd/machines/1/commands",
            &json!({"command": "set_overrides", "feed": feed, "request_id": id, "token": operator}),
        );
        answers.push(c.until("t/cmd/results", |v, _| v["request_id"] == id).0);
    }
    assert_eq!(answers[0]["ok"], true, "{answers:?}");
    assert_eq!(answers[1]["code"], "override_out_of_range", "{answers:?}");
    assert_eq!(s.status(1)["feed_override"], 60.0);
}

#[test]
fn commands_are_off_by_default() {
    let broker = Broker::start();
    let mut s = Server::unstarted(Opts {
        demo: true,
        ..Opts::default()
    });
    let operator = s.create_token("operator", "olga");
    s.write_config(&format!(
        "[mqtt]\nurl = \"{}\"\ntopic_prefix = \"t\"\n",
        broker.url()
    ));
    s.spawn().unwrap();
    wait_for(T, "bridge connected", || {
        (metric(&s, "fresa_mqtt_connected") == 1.0).then_some(())
    });
    s.wait_machine_state(1, "idle", T);
    let c = Sub::new(&broker, &["t/cmd/results", "t/events/#"]);
    c.publish(
        "t/cmd/machines/1/jog",
        &json!({"axis": "X", "distance": 2.0, "token": operator}),
    );
    // An HTTP jog after it: by the time its event arrives, no command result came and the
    // machine did not move in X.
    s.jog(1, "Y", 1.0).expect(200);
    loop {
        let (t, v, _) = c.rx.recv_timeout(T).expect("the HTTP jog's event");
        assert_ne!(t, "t/cmd/results", "{v}");
        if t == "t/events/machine.jog" {
            assert_eq!(v["data"]["axis"], "Y", "{v}");
            break;
        }
    }
    assert!(x_is(&s.status(1), 0.0));
    assert_eq!(metric(&s, "fresa_mqtt_commands_refused_total"), 0.0);
    assert_eq!(
        metric(&s, "fresa_mqtt_commands_ready"),
        0.0,
        "nothing subscribed"
    );
}

fn run(cmd: &mut Command, what: &str) {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("{what}: {e} (apt-get install openssl mosquitto)"));
    assert!(
        out.status.success(),
        "{what}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn tls_and_a_password_reach_a_broker_that_requires_both() {
    let dir = tempfile::tempdir().unwrap();
    let p = |f: &str| dir.path().join(f);
    // A CA and a certificate for 127.0.0.1 signed by it (openssl, as an admin would).
    run(
        Command::new("openssl")
            .args([
                "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
            ])
            .args(["-subj", "/CN=fresa-test-ca", "-keyout"])
            .arg(p("ca.key"))
            .arg("-out")
            .arg(p("ca.pem")),
        "openssl CA",
    );
    run(
        Command::new("openssl")
            .args([
                "req",
                "-newkey",
                "rsa:2048",
                "-nodes",
                "-subj",
                "/CN=127.0.0.1",
                "-keyout",
            ])
            .arg(p("server.key"))
            .arg("-out")
            .arg(p("server.csr")),
        "openssl request",
    );
    std::fs::write(
        p("ext.cnf"),
        "subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n",
    )
    .unwrap();
    run(
        Command::new("openssl")
            .args(["x509", "-req", "-days", "2", "-CAcreateserial", "-in"])
            .arg(p("server.csr"))
            .arg("-CA")
            .arg(p("ca.pem"))
            .arg("-CAkey")
            .arg(p("ca.key"))
            .arg("-extfile")
            .arg(p("ext.cnf"))
            .arg("-out")
            .arg(p("server.pem")),
        "openssl sign",
    );
    run(
        Command::new("/usr/bin/mosquitto_passwd")
            .args(["-c", "-b"])
            .arg(p("passwd"))
            .args(["fresa", "s3cret"]),
        "mosquitto_passwd",
    );
    // Two listeners: TLS with a password for the server, plain loopback for the test's client.
    let mut broker = Broker::start();
    broker.stop();
    let tls_port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let conf = p("mosquitto.conf");
    std::fs::write(
        &conf,
        format!(
            // Started as root, mosquitto would drop to the `mosquitto` user, which cannot read
            // the test's private directory; for any other user `user` has no effect.
            "user root\nper_listener_settings true\npersistence false\n\
             listener {plain} 127.0.0.1\nallow_anonymous true\n\
             listener {tls_port} 127.0.0.1\nallow_anonymous false\npassword_file {pw}\n\
             cafile {ca}\ncertfile {cert}\nkeyfile {key}\n",
            plain = broker.port,
            pw = p("passwd").display(),
            ca = p("ca.pem").display(),
            cert = p("server.pem").display(),
            key = p("server.key").display(),
        ),
    )
    .unwrap();
    broker.child = Some(
        Command::new(MOSQUITTO)
            .arg("-c")
            .arg(&conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    for port in [broker.port, tls_port] {
        wait_for(T, "mosquitto listening", || {
            std::net::TcpStream::connect(("127.0.0.1", port))
                .ok()
                .map(|_| ())
        });
    }
    let start = |password: &str| {
        let mut s = Server::unstarted(Opts {
            demo: true,
            ..Opts::default()
        });
        s.write_config(&format!(
            "[mqtt]\nurl = \"mqtts://127.0.0.1:{tls_port}\"\ntopic_prefix = \"t\"\n\
             ca_file = \"{}\"\nusername = \"fresa\"\npassword = \"{password}\"\n",
            p("ca.pem").display()
        ));
        s.spawn().unwrap();
        s.wait_machine_state(1, "idle", T);
        s
    };
    let s = start("s3cret");
    wait_for(T, "bridge connected over TLS", || {
        (metric(&s, "fresa_mqtt_connected") == 1.0).then_some(())
    });
    s.jog(1, "X", 1.0).expect(200);
    retained_status(&broker, 1.0);
    drop(s);
    // A wrong password: the broker refuses it and the bridge stays disconnected (and retries).
    let s = start("wrong");
    let log = s.wait_log(T, "MQTT connect failed");
    assert!(!log.is_empty());
    assert_eq!(metric(&s, "fresa_mqtt_connected"), 0.0);
}

#[test]
fn retained_commands_are_never_run_even_across_reconnects() {
    let broker = Broker::start();
    // Left on the broker before the server starts, as anyone who can publish there (or who
    // captured a command with its token) could: a retained jog with a valid operator token, and
    // a retained message bigger than any command (and than the old client's 1 MiB packet limit).
    let mut s = Server::unstarted(Opts {
        demo: true,
        ..Opts::default()
    });
    let operator = s.create_token("operator", "olga");
    leave_retained(
        &broker,
        "t/cmd/machines/1/jog",
        json!({"axis": "X", "distance": 2.0, "token": operator})
            .to_string()
            .into_bytes(),
    );
    leave_retained(&broker, "t/cmd/jobs/1/start", vec![b'x'; 2 << 20]);
    let client_id = format!("fresa-retained-{}", rand_suffix());
    s.write_config(&format!(
        "[mqtt]\nurl = \"{}\"\ntopic_prefix = \"t\"\ncommands = true\nclient_id = \"{client_id}\"\n",
        broker.url()
    ));
    s.spawn().unwrap();
    s.wait_machine_state(1, "idle", T);
    wait_for(T, "command subscriptions confirmed", || {
        (metric(&s, "fresa_mqtt_commands_ready") == 1.0).then_some(())
    });
    let c = Sub::new(&broker, &["t/cmd/results"]);
    // The broker sends retained messages right after each subscription's acknowledgement, so
    // by the time a live command published now is answered, both retained ones were seen.
    // A live jog of Y runs (to `y`); the retained jog of X never did.
    let live_jog_runs = |request_id: &str, y: f64| {
        let answer = live_jog(&c, &operator, "Y", 1.0, request_id);
        assert_eq!(answer["ok"], true, "{answer}");
        s.wait_status(
            1,
            T,
            &format!("y = {y} after the live jog {request_id}"),
            |st| (st["machine_position"]["y"].as_f64().unwrap_or(f64::NAN) - y).abs() < 1e-6,
        );
        assert!(
            x_is(&s.status(1), 0.0),
            "the retained jog moved X: {}",
            s.status(1)
        );
    };
    live_jog_runs("live-1", 1.0);
    assert_eq!(metric(&s, "fresa_mqtt_retained_ignored_total"), 2.0);
    assert_eq!(metric(&s, "fresa_mqtt_reconnects_total"), 0.0);

    // Knocked off and back: the broker replays both retained messages to the new subscription.
    take_over(&broker, &client_id);
    wait_for(T, "bridge reconnected and subscribed", || {
        (metric(&s, "fresa_mqtt_reconnects_total") >= 1.0
            && metric(&s, "fresa_mqtt_commands_ready") == 1.0)
            .then_some(())
    });
    live_jog_runs("live-2", 2.0);
    assert_eq!(metric(&s, "fresa_mqtt_retained_ignored_total"), 4.0);
    // The retained oversized message did not knock the bridge off again.
    assert_eq!(metric(&s, "fresa_mqtt_reconnects_total"), 1.0);
    assert_eq!(metric(&s, "fresa_mqtt_connected"), 1.0);
    // No command ran for a retained message: no refusals were answered for them either.
    assert_eq!(metric(&s, "fresa_mqtt_commands_refused_total"), 0.0);

    // The audit log has the two live jogs and nothing else.
    let stream = s.events("types=machine.jog", Some(0));
    let mut jogs = Vec::new();
    stream.until(T, "the two live jogs", |e| {
        if e.event == "machine.jog" {
            jogs.push(e.data.clone());
        }
        jogs.len() >= 2
    });
    for j in &jogs {
        assert_eq!(
            (j["data"]["axis"].clone(), j["actor"].clone()),
            (json!("Y"), json!("mqtt:olga")),
            "{j}"
        );
    }
    // Said once per topic, not on every replay.
    let log = s.log();
    for topic in ["t/cmd/machines/1/jog", "t/cmd/jobs/1/start"] {
        let lines = log
            .lines()
            .filter(|l| l.contains("retained command message ignored") && l.contains(topic))
            .count();
        assert_eq!(lines, 1, "{topic}:\n{log}");
    }
}

#[test]
fn an_oversized_command_is_dropped_and_the_connection_kept() {
    let broker = Broker::start();
    let client_id = format!("fresa-oversized-{}", rand_suffix());
    let (s, operator) = commanded_demo(&broker, &client_id);
    let c = Sub::new(&broker, &["t/cmd/results"]);
    // 2 MiB: past the bridge's command limit (and the old client's 1 MiB packet limit).
    let mut big = json!({"axis": "X", "distance": 1.0, "token": operator}).to_string();
    big.push_str(&" ".repeat(2 << 20));
    c.publish_bytes("t/cmd/machines/1/jog", false, big.into_bytes());
    let (answer, _) = c.until("t/cmd/results", |v, _| v["code"] == "payload_too_large");
    assert_eq!(answer["ok"], false, "{answer}");
    assert_eq!(answer["topic"], "t/cmd/machines/1/jog", "{answer}");
    assert!(
        answer["message"]
            .as_str()
            .unwrap()
            .contains("max_command_bytes"),
        "{answer}"
    );
    // The next command runs, over the same connection.
    let answer = live_jog(&c, &operator, "X", 2.0, "after");
    assert_eq!(answer["ok"], true, "{answer}");
    s.wait_status(1, T, "x = 2 after the jog", |st| x_is(st, 2.0));
    assert_eq!(metric(&s, "fresa_mqtt_oversized_dropped_total"), 1.0);
    assert_eq!(metric(&s, "fresa_mqtt_reconnects_total"), 0.0);
    assert_eq!(metric(&s, "fresa_mqtt_connected"), 1.0);
    assert!(
        !s.log().contains("MQTT bridge lost the broker"),
        "{}",
        s.log()
    );
}

/// The latest status on each of the three outlets once they agree: `GET .../status`, the data
/// of the last SSE `status` event, and the last MQTT status message. Polls (the stream and the
/// broker deliver asynchronously) until the three are the same JSON value, or panics showing
/// them.
#[track_caller]
fn agreed_status(s: &Server, sse: &fresa_tests::Sse, sub: &Sub, machine: i64, what: &str) -> Value {
    let topic = format!("t/machines/{machine}/status");
    let (mut on_sse, mut on_mqtt) = (Value::Null, Value::Null);
    let deadline = std::time::Instant::now() + T;
    loop {
        while let Some(e) = sse.next(Duration::from_millis(1)) {
            if e.event == "status" {
                assert_eq!(e.data["type"], "status", "{:?}", e.data);
                assert_eq!(e.data["machine"], machine, "{:?}", e.data);
                on_sse = e.data["data"].clone();
            }
        }
        while let Ok((t, v, _)) = sub.rx.try_recv() {
            if t == topic {
                on_mqtt = v;
            }
        }
        let http = s.status(machine);
        if on_sse == http && on_mqtt == http {
            return http;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "{what}: the status differs\nHTTP: {http}\nSSE:  {on_sse}\nMQTT: {on_mqtt}"
        );
        // Wait for the next message on either outlet rather than spinning.
        if let Some(e) = sse.next(Duration::from_millis(50)) {
            if e.event == "status" {
                on_sse = e.data["data"].clone();
            }
        }
    }
}

/// Issue 24: the status is one view, serialised the same on the API, the event stream and the
/// broker: after a jog (no job) and while a job is paused (with its progress), the three are the
/// same JSON, and so is the retained message a late subscriber gets.
#[test]
fn the_status_is_the_same_json_on_http_sse_and_mqtt() {
    let broker = Broker::start();
    let s = bridged_demo(&broker, "");
    let m = s.sim("m", 0.1);
    let topic = format!("t/machines/{}/status", m.id);
    let sub = Sub::new(&broker, &[&topic]);
    let sse = s.events(&format!("types=status&machine={}", m.id), None);
    s.wait_machine_state(m.id, "idle", T);

    s.jog(m.id, "X", 3.0).expect(200);
    s.wait_status(m.id, T, "idle at x=3", |st| {
        st["state"] == "idle" && x_is(st, 3.0)
    });
    let after_jog = agreed_status(&s, &sse, &sub, m.id, "after a jog");
    assert_eq!(after_jog["machine"], m.id, "{after_jog}");
    assert!(after_jog["job"].is_null(), "{after_jog}");
    assert!(x_is(&after_jog, 3.0), "{after_jog}");

    // A paused job: the status carries its progress, the same on all three.
    let job = s.upload(m.id, "slow", fresa_tests::back_and_forth(200, 1.0, 600.0))["id"]
        .as_i64()
        .unwrap();
    s.job_action(job, "start").expect(200);
    s.wait_job(job, T, "line >= 5", |j| j["line"].as_i64().unwrap() >= 5);
    s.job_action(job, "pause").expect(200);
    s.wait_machine_state(m.id, "paused", T);
    let paused = agreed_status(&s, &sse, &sub, m.id, "with a paused job");
    assert_eq!(paused["job"]["job"], job, "{paused}");
    assert_eq!(paused["job"]["total_lines"], 200, "{paused}");
    assert!(paused["job"]["line"].as_i64().unwrap() >= 5, "{paused}");

    // What a client connecting now is given is the same status.
    let late = Sub::new(&broker, &[&topic]);
    let (retained, was_retained) = late.until(&topic, |_, _| true);
    assert!(was_retained, "{retained}");
    assert_eq!(retained, s.status(m.id));
    s.job_action(job, "cancel").expect(200);
}
