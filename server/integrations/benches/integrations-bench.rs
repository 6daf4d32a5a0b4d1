//! Throughput of the integrations, in-process on a real `App` (fresh data directory, no
//! machines), against a local mosquitto and a local HTTP receiver:
//! * events/s through the MQTT bridge (persisted events, recorded on the bus, received by a
//!   subscriber on the broker);
//! * the process's added CPU per 1,000 status messages with the bridge on (vs. off);
//! * webhook deliveries/s (1 and 8 webhooks).
//!
//! `cargo bench -p fresa-integrations --bench integrations-bench` (needs /usr/sbin/mosquitto).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fresa_core::events::EventKind;
use fresa_core::{App, SharedApp};
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use serde_json::json;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// This process's CPU time (user + system). The bench's CPU figures are measured on Linux;
/// elsewhere this is zero and they read 0.
#[cfg(not(unix))]
fn cpu_time() -> Duration {
    Duration::ZERO
}

#[cfg(unix)]
fn cpu_time() -> Duration {
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage writes into the struct we own.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// mosquitto, its port, and the directory holding its config (kept while it runs).
struct Broker(
    std::process::Child,
    u16,
    #[allow(dead_code)] tempfile::TempDir,
);

impl Drop for Broker {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn broker() -> Broker {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let dir = tempfile::tempdir().unwrap();
    let conf = dir.path().join("m.conf");
    std::fs::write(
        &conf,
        format!("listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nmax_queued_messages 1000000\n"),
    )
    .unwrap();
    let child = std::process::Command::new("/usr/sbin/mosquitto")
        .arg("-c")
        .arg(&conf)
        .spawn()
        .expect("mosquitto (apt-get install mosquitto)");
    let deadline = Instant::now() + Duration::from_secs(10);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "mosquitto did not start");
        std::thread::sleep(Duration::from_millis(20));
    }
    Broker(child, port, dir)
}

async fn app(dir: &std::path::Path, mqtt_port: Option<u16>) -> SharedApp {
    let conf = dir.join("fresa.toml");
    // The receivers are on loopback, which webhooks may target only when allowed.
    let mut toml = String::from("[webhooks]\nqueue = 100000\nallowed_hosts = [\"127.0.0.1\"]\n");
    if let Some(p) = mqtt_port {
        toml.push_str(&format!(
            "[mqtt]\nurl = \"mqtt://127.0.0.1:{p}\"\ntopic_prefix = \"b\"\nqueue = 100000\n"
        ));
    }
    std::fs::write(&conf, toml).unwrap();
    let settings = fresa_core::config::Settings::resolve(fresa_core::config::Overrides {
        data_dir: Some(dir.join("data")),
        config: Some(conf),
        plugin_dirs: vec![dir.to_path_buf()],
        ..Default::default()
    })
    .unwrap();
    App::start(settings).await.unwrap()
}

/// A subscriber counting what arrives on `filter`.
async fn subscriber(port: u16, filter: &str) -> Arc<AtomicU64> {
    let mut opts = MqttOptions::new(format!("bench-{}", std::process::id()), "127.0.0.1", port);
    opts.set_keep_alive(Duration::from_secs(30));
    opts.set_inflight(1000);
    let (client, mut el) = AsyncClient::new(opts, 1000);
    client.subscribe(filter, QoS::AtLeastOnce).await.unwrap();
    let count = Arc::new(AtomicU64::new(0));
    let (c, subscribed) = (count.clone(), Arc::new(tokio::sync::Notify::new()));
    let s2 = subscribed.clone();
    tokio::spawn(async move {
        let _client = client;
        loop {
            match el.poll().await {
                Ok(Event::Incoming(Packet::SubAck(_))) => s2.notify_one(),
                Ok(Event::Incoming(Packet::Publish(_))) => {
                    c.fetch_add(1, Ordering::Relaxed);
                }
                Ok(_) => {}
                Err(_) => return,
            }
        }
    });
    subscribed.notified().await;
    count
}

async fn wait_until(what: &str, limit: Duration, f: impl Fn() -> bool) {
    let deadline = Instant::now() + limit;
    while !f() {
        assert!(Instant::now() < deadline, "timed out: {what}");
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
}

async fn mqtt_events_per_second(n: u64) {
    let b = broker();
    let dir = tempfile::tempdir().unwrap();
    let app = app(dir.path(), Some(b.1)).await;
    let integrations = fresa_integrations::start(app.clone());
    wait_until("bridge connected", Duration::from_secs(10), || {
        app.integrations.mqtt_connected.load(Ordering::Relaxed)
    })
    .await;
    let got = subscriber(b.1, "b/events/#").await;
    let start = Instant::now();
    for i in 0..n {
        app.bus
            .record(
                EventKind::MachineCommand,
                None,
                Some("bench"),
                json!({"i": i}),
            )
            .await
            .unwrap();
    }
    let recorded = start.elapsed();
    wait_until(
        "all events at the subscriber",
        Duration::from_secs(120),
        || got.load(Ordering::Relaxed) >= n,
    )
    .await;
    let all = start.elapsed();
    let dropped = app.integrations.mqtt_dropped.load(Ordering::Relaxed);
    println!(
        "mqtt: {n} persisted events recorded in {:.2} s ({:.0}/s, SQLite included); all at the subscriber after {:.2} s: {:.0} events/s end to end; dropped {dropped}",
        recorded.as_secs_f64(),
        n as f64 / recorded.as_secs_f64(),
        all.as_secs_f64(),
        n as f64 / all.as_secs_f64()
    );
    app.shutdown.cancel();
    integrations.join(Duration::from_secs(2)).await;
}

/// CPU of the whole process for `n` status events (in batches the bridge keeps up with).
/// With `measure_at_broker`, a subscriber in this process also counts what reaches the broker
/// (its CPU is then in the total: use that run for the rate only).
async fn status_cpu(n: u64, mqtt_port: Option<u16>, measure_at_broker: bool) -> Duration {
    let dir = tempfile::tempdir().unwrap();
    let app = app(dir.path(), mqtt_port).await;
    let integrations = fresa_integrations::start(app.clone());
    if mqtt_port.is_some() {
        wait_until("bridge connected", Duration::from_secs(10), || {
            app.integrations.mqtt_connected.load(Ordering::Relaxed)
        })
        .await;
    }
    // A listener like the bridge's, so "off" still pays for the bus fan-out to one reader.
    let mut rx = app.bus.subscribe();
    let seen = Arc::new(AtomicU64::new(0));
    let s2 = seen.clone();
    tokio::spawn(async move {
        while rx.recv().await.is_ok() {
            s2.fetch_add(1, Ordering::Relaxed);
        }
    });
    let status = json!({"state": "idle", "machine_position": {"x": 0.0, "y": 0.0, "z": 0.0, "a": 0.0},
        "work_position": {"x": 0.0, "y": 0.0, "z": 0.0, "a": 0.0}, "feed": 0.0, "feed_override": 100.0,
        "active_offset": "G54"});
    let at_broker = match mqtt_port {
        Some(p) if measure_at_broker => Some(subscriber(p, "b/machines/+/status").await),
        _ => None,
    };
    let before = cpu_time();
    let started = Instant::now();
    let mut sent = 0;
    while sent < n {
        for i in 0..1000 {
            let mut s = status.clone();
            s["machine_position"]["x"] = json!((sent + i) as f64);
            app.bus
                .transient(EventKind::Status, Some(1 + (i % 8) as i64), s);
        }
        sent += 1000;
        wait_until("the bus readers caught up", Duration::from_secs(60), || {
            seen.load(Ordering::Relaxed) >= sent
                && (mqtt_port.is_none()
                    || app.integrations.mqtt_published.load(Ordering::Relaxed)
                        + app.integrations.mqtt_dropped.load(Ordering::Relaxed)
                        >= sent)
        })
        .await;
    }
    let cpu = cpu_time() - before;
    if let Some(got) = at_broker {
        wait_until("status at the subscriber", Duration::from_secs(120), || {
            got.load(Ordering::Relaxed) >= n
        })
        .await;
        let t = started.elapsed();
        println!(
            "mqtt: {n} status messages through the bridge to a subscriber in {:.2} s: {:.0} messages/s (dropped {})",
            t.as_secs_f64(),
            n as f64 / t.as_secs_f64(),
            app.integrations.mqtt_dropped.load(Ordering::Relaxed)
        );
    }
    app.shutdown.cancel();
    integrations.join(Duration::from_secs(2)).await;
    cpu
}

/// A minimal keep-alive HTTP receiver answering 204 to everything.
async fn receiver() -> (String, Arc<AtomicU64>) {
    use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
    let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/hook", l.local_addr().unwrap());
    let count = Arc::new(AtomicU64::new(0));
    let c = count.clone();
    tokio::spawn(async move {
        while let Ok((s, _)) = l.accept().await {
            let c = c.clone();
            tokio::spawn(async move {
                let (r, mut w) = s.into_split();
                let mut r = BufReader::new(r);
                loop {
                    let mut len = 0usize;
                    let mut line = String::new();
                    loop {
                        line.clear();
                        if r.read_line(&mut line).await.unwrap_or(0) == 0 {
                            return;
                        }
                        let t = line.trim_end();
                        if t.is_empty() {
                            break;
                        }
                        if let Some(v) = t.to_ascii_lowercase().strip_prefix("content-length:") {
                            len = v.trim().parse().unwrap_or(0);
                        }
                    }
                    let mut body = vec![0; len];
                    if r.read_exact(&mut body).await.is_err() {
                        return;
                    }
                    c.fetch_add(1, Ordering::Relaxed);
                    if w.write_all(b"HTTP/1.1 204 No Content\r\n\r\n")
                        .await
                        .is_err()
                    {
                        return;
                    }
                }
            });
        }
    });
    (url, count)
}

async fn webhook_deliveries(n: u64, hooks: u64) {
    let dir = tempfile::tempdir().unwrap();
    let app = app(dir.path(), None).await;
    let integrations = fresa_integrations::start(app.clone());
    let (url, got) = receiver().await;
    for _ in 0..hooks {
        fresa_core::webhooks::create(&app, &url, vec!["machine.command".into()], "bench")
            .await
            .unwrap();
    }
    let start = Instant::now();
    for i in 0..n {
        app.bus
            .record(
                EventKind::MachineCommand,
                None,
                Some("bench"),
                json!({"i": i}),
            )
            .await
            .unwrap();
    }
    let want = n * hooks;
    wait_until("all deliveries", Duration::from_secs(300), || {
        app.integrations.webhook_delivered.load(Ordering::Relaxed) >= want
    })
    .await;
    let t = start.elapsed();
    assert!(got.load(Ordering::Relaxed) >= want);
    println!(
        "webhooks: {want} deliveries ({n} events x {hooks} webhook(s)) in {:.2} s: {:.0} deliveries/s",
        t.as_secs_f64(),
        want as f64 / t.as_secs_f64()
    );
    app.shutdown.cancel();
    integrations.join(Duration::from_secs(2)).await;
}

#[tokio::main]
async fn main() {
    // `cargo bench` passes `--bench`; nothing to parse.
    mqtt_events_per_second(20_000).await;
    let b = broker();
    let n = 100_000;
    let off = status_cpu(n, None, false).await;
    let on = status_cpu(n, Some(b.1), false).await;
    status_cpu(n, Some(b.1), true).await;
    println!(
        "status: {n} messages, process CPU {:.0} ms without the bridge, {:.0} ms with it: +{:.2} ms CPU per 1,000 status messages",
        off.as_secs_f64() * 1e3,
        on.as_secs_f64() * 1e3,
        (on.as_secs_f64() - off.as_secs_f64()) * 1e3 / (n as f64 / 1000.0)
    );
    webhook_deliveries(5_000, 1).await;
    webhook_deliveries(2_000, 8).await;
}
