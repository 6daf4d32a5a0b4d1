//! The MQTT bridge to an external broker (`[mqtt]` in the config, or `FRESA_MQTT_URL`).
//!
//! Published (topics under `topic_prefix`, default `fresa`):
//! * `machines/<id>/status` (retained, QoS 0): the machine's status, the same JSON as
//!   `GET /api/v1/machines/{id}/status`; sent when the machine task sends a `status` event (at most
//!   `status_rate_hz`, only on change) and again for every machine after each (re)connection.
//! * `jobs/<id>/state` (retained, QoS 1): the `job.state` event's data on every run transition.
//! * `events/<type>` (QoS 1): every persisted event, as on the event stream.
//! * `nodes/<node>/online` (retained, QoS 1): `{"online": true, ...}` after connecting; the broker
//!   publishes the last will `{"online": false}` if the link dies, and a clean shutdown sends it.
//!
//! Commands (only with `commands = true`): `cmd/machines/<id>/jog`, `cmd/machines/<id>/jog/cancel`
//! (ends the jog under way and drops queued ones, like `POST .../jog/cancel`),
//! `cmd/machines/<id>/commands`, `cmd/jobs/<id>/<start|pause|resume|cancel>`; the payload is the HTTP body plus `"token"` (an
//! API token with the role the HTTP call needs: operator) and an optional `"request_id"`. They
//! call the same core functions as the HTTP handlers; each answer goes to `cmd/results`.
//! A retained message on a command topic is never run: it is not fresh (the broker hands it to
//! every new subscription, so it would run again on each reconnect). Payloads over
//! `max_command_bytes` are dropped and answered `payload_too_large`; the client accepts packets
//! of any size MQTT allows, so no message can make it drop the connection.
//!
//! Nothing here waits for the broker: messages go into the client's bounded queue with
//! `try_publish`; a full queue (broker slow or gone) drops the message and counts it.

use fresa_core::config::MqttSettings;
use fresa_core::events::{BusEvent, EventKind};
use fresa_core::integrations::IntegrationStats;
use fresa_core::SharedApp;
use rumqttc::{AsyncClient, Event, EventLoop, LastWill, MqttOptions, Packet, QoS};
use serde::Deserialize;
use serde_json::{json, Value};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::broadcast::error::RecvError;

/// Reconnection delays: doubling from the first to the last.
const BACKOFF_FIRST: Duration = Duration::from_millis(200);
const BACKOFF_MAX: Duration = Duration::from_secs(30);
/// Command messages handled at once; more are refused (`busy`) rather than queued.
const MAX_COMMANDS_IN_FLIGHT: usize = 16;
/// MQTT 3.1.1's largest packet (remaining length 268,435,455). The client drops the connection
/// on a packet over its limit, and nothing tells a 3.1.1 broker that limit: with any lower
/// one, one big message from anyone who may publish knocks the bridge off, and a retained one
/// keeps it off. So the client takes what MQTT allows (the broker's `message_size_limit`
/// bounds it) and the bridge drops oversized commands itself.
const MQTT_MAX_PACKET: usize = 268_435_455;
/// Command topics whose ignored retained message was logged (each once); past this many, the
/// rest are only counted.
const MAX_RETAINED_TOPICS_LOGGED: usize = 1000;

/// Topics, all under the configured prefix.
#[derive(Clone)]
pub struct Topics {
    prefix: String,
    node: String,
}

impl Topics {
    pub fn new(prefix: &str, node: &str) -> Self {
        Topics {
            prefix: prefix.to_string(),
            // `+`, `#` and `/` would change the topic's shape.
            node: node.replace(['+', '#', '/'], "_"),
        }
    }
    pub fn status(&self, machine: i64) -> String {
        format!("{}/machines/{machine}/status", self.prefix)
    }
    pub fn job_state(&self, job: i64) -> String {
        format!("{}/jobs/{job}/state", self.prefix)
    }
    pub fn event(&self, kind: &str) -> String {
        format!("{}/events/{}", self.prefix, kind.replace(['+', '#'], "_"))
    }
    pub fn online(&self) -> String {
        format!("{}/nodes/{}/online", self.prefix, self.node)
    }
    /// Not `cmd/#`: that would include `cmd/results`, our own answers.
    pub fn command_filters(&self) -> [String; 2] {
        [
            format!("{}/cmd/machines/#", self.prefix),
            format!("{}/cmd/jobs/#", self.prefix),
        ]
    }
    pub fn results(&self) -> String {
        format!("{}/cmd/results", self.prefix)
    }
}

fn online_payload(online: bool, node: &str) -> Vec<u8> {
    json!({"online": online, "node": node, "version": env!("CARGO_PKG_VERSION")})
        .to_string()
        .into_bytes()
}

/// Starts the bridge; it ends when the app shuts down (after saying it goes offline).
pub fn spawn(app: SharedApp, settings: MqttSettings) -> Vec<tokio::task::JoinHandle<()>> {
    let topics = Topics::new(&settings.topic_prefix, &settings.node);
    let mut opts = MqttOptions::new(&settings.client_id, &settings.host, settings.port);
    opts.set_keep_alive(Duration::from_secs(15));
    opts.set_clean_session(true);
    opts.set_max_packet_size(MQTT_MAX_PACKET, 1 << 20);
    opts.set_last_will(LastWill::new(
        topics.online(),
        online_payload(false, &settings.node),
        QoS::AtLeastOnce,
        true,
    ));
    if let (Some(u), p) = (&settings.username, &settings.password) {
        opts.set_credentials(u, p.clone().unwrap_or_default());
    }
    if settings.tls {
        match tls_config(&settings) {
            Ok(t) => {
                opts.set_transport(rumqttc::Transport::tls_with_config(t));
            }
            Err(e) => {
                tracing::error!(error = %e, "MQTT bridge disabled: TLS setup failed");
                return Vec::new();
            }
        }
    }
    let (client, eventloop) = AsyncClient::new(opts, settings.queue);
    tracing::info!(broker = %format!("{}:{}", settings.host, settings.port), prefix = %settings.topic_prefix,
        commands = settings.commands, "MQTT bridge starting");
    let rx = app.bus.subscribe();
    vec![
        tokio::spawn(publish_events(
            app.clone(),
            client.clone(),
            topics.clone(),
            rx,
        )),
        tokio::spawn(drive(app, client, eventloop, topics, settings)),
    ]
}

fn tls_config(settings: &MqttSettings) -> Result<rumqttc::TlsConfiguration, String> {
    let mut roots = rustls::RootCertStore::empty();
    match &settings.ca_file {
        Some(path) => {
            let pem =
                std::fs::read(path).map_err(|e| format!("mqtt.ca_file {}: {e}", path.display()))?;
            for cert in rustls_pemfile::certs(&mut pem.as_slice()) {
                let cert = cert.map_err(|e| format!("mqtt.ca_file {}: {e}", path.display()))?;
                roots
                    .add(cert)
                    .map_err(|e| format!("mqtt.ca_file {}: {e}", path.display()))?;
            }
        }
        None => {
            for cert in rustls_native_certs::load_native_certs().certs {
                let _ = roots.add(cert);
            }
        }
    }
    let config = rustls::ClientConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .map_err(|e| e.to_string())?
    .with_root_certificates(roots)
    .with_no_client_auth();
    Ok(rumqttc::TlsConfiguration::Rustls(Arc::new(config)))
}

/// Hands a message to the client's queue, or drops and counts it.
/// A command's answer, on the results topic.
fn answer_on_results(
    app: &SharedApp,
    client: &AsyncClient,
    topics: &Topics,
    answer: &serde_json::Value,
) {
    offer(
        app,
        client,
        topics.results(),
        QoS::AtLeastOnce,
        false,
        answer.to_string().into_bytes(),
    );
}

fn offer(
    app: &SharedApp,
    client: &AsyncClient,
    topic: String,
    qos: QoS,
    retain: bool,
    payload: Vec<u8>,
) {
    match client.try_publish(topic, qos, retain, payload) {
        Ok(()) => IntegrationStats::add(&app.integrations.mqtt_published, 1),
        Err(_) => IntegrationStats::add(&app.integrations.mqtt_dropped, 1),
    }
}

/// Reads the event bus and offers what it sees to the broker; never waits for the network.
async fn publish_events(
    app: SharedApp,
    client: AsyncClient,
    topics: Topics,
    mut rx: tokio::sync::broadcast::Receiver<Arc<BusEvent>>,
) {
    loop {
        let ev = tokio::select! {
            _ = app.shutdown.cancelled() => return,
            ev = rx.recv() => ev,
        };
        let ev = match ev {
            Ok(ev) => ev,
            Err(RecvError::Lagged(n)) => {
                IntegrationStats::add(&app.integrations.mqtt_dropped, n);
                continue;
            }
            Err(RecvError::Closed) => return,
        };
        // Each node's bridge publishes what happens on it (its own machines).
        if !app.bus.is_local(&ev) {
            continue;
        }
        for (topic, qos, retain, payload) in messages(&topics, &ev) {
            offer(&app, &client, topic, qos, retain, payload);
        }
    }
}

/// What one bus event becomes on the broker.
fn messages(topics: &Topics, ev: &BusEvent) -> Vec<(String, QoS, bool, Vec<u8>)> {
    let mut out = Vec::new();
    if ev.is(EventKind::Status) {
        // The event's data is the status view `GET /machines/{id}/status` answers with.
        if let Some(m) = ev.machine {
            let body = ev.data_json().as_bytes().to_vec();
            out.push((topics.status(m), QoS::AtMostOnce, true, body));
        }
        return out;
    }
    if ev.id.is_none() {
        // Other live-only events (progress, line reports) stay on the event stream.
        return out;
    }
    if ev.is(EventKind::JobState) {
        if let Some(job) = ev.data["job"].as_i64() {
            let mut body = ev.data.clone();
            if let Some(o) = body.as_object_mut() {
                o.insert("machine".into(), json!(ev.machine));
                o.insert("time".into(), json!(ev.time));
            }
            out.push((
                topics.job_state(job),
                QoS::AtLeastOnce,
                true,
                body.to_string().into_bytes(),
            ));
        }
    }
    out.push((
        topics.event(&ev.kind),
        QoS::AtLeastOnce,
        false,
        ev.json().as_bytes().to_vec(),
    ));
    out
}

/// Part of what is announced on connecting.
enum Announce {
    /// The node's birth message.
    Online,
    /// A machine's current status (retained).
    Status(i64),
}

/// What a consumer needs after the broker lost it: the birth message and every machine's status.
async fn announcement(app: &SharedApp) -> Vec<Announce> {
    let mut v = vec![Announce::Online];
    v.extend(app.machines.all().iter().map(|m| Announce::Status(m.id)));
    v
}

/// Offers the announcement's parts in order and keeps those the queue had no room for, to try
/// again when it moves (a status is taken fresh each time).
async fn announce(
    app: &SharedApp,
    client: &AsyncClient,
    topics: &Topics,
    settings: &MqttSettings,
    left: &mut Vec<Announce>,
) {
    while let Some(next) = left.first() {
        let (topic, qos, body) = match next {
            Announce::Online => (
                topics.online(),
                QoS::AtLeastOnce,
                online_payload(true, &settings.node),
            ),
            Announce::Status(id) => {
                let Some(m) = app.machines.get(*id) else {
                    left.remove(0);
                    continue;
                };
                // The same view as `GET /machines/{id}/status` and the `status` event.
                let body = serde_json::to_vec(&m.status_view()).unwrap_or_default();
                (topics.status(*id), QoS::AtMostOnce, body)
            }
        };
        if client.try_publish(topic, qos, true, body).is_err() {
            return;
        }
        IntegrationStats::add(&app.integrations.mqtt_published, 1);
        left.remove(0);
    }
}

/// Polls the connection (rumqttc reconnects on the next poll after an error), with doubling
/// delays between failed attempts; announces the node and the machines' status on each
/// connection; hands command messages to their own tasks.
async fn drive(
    app: SharedApp,
    client: AsyncClient,
    mut eventloop: EventLoop,
    topics: Topics,
    settings: MqttSettings,
) {
    let mut backoff = BACKOFF_FIRST;
    let mut connections = 0u64;
    // What of the announcement did not fit in the queue yet.
    let mut to_announce: Vec<Announce> = Vec::new();
    // Subscription acknowledgements since the last connection.
    let mut sub_acks = 0u32;
    let in_flight = Arc::new(tokio::sync::Semaphore::new(MAX_COMMANDS_IN_FLIGHT));
    let mut retained_logged: std::collections::HashSet<String> = Default::default();
    let stats = &app.integrations;
    // A command refused before it runs is answered on the results topic at once.
    let refuse = |answer: serde_json::Value| answer_on_results(&app, &client, &topics, &answer);
    loop {
        let polled = tokio::select! {
            _ = app.shutdown.cancelled() => break,
            p = eventloop.poll() => p,
        };
        match polled {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                connections += 1;
                if connections > 1 {
                    IntegrationStats::add(&stats.mqtt_reconnects, 1);
                }
                stats.mqtt_connected.store(true, Ordering::Relaxed);
                backoff = BACKOFF_FIRST;
                tracing::info!(reconnects = connections - 1, "MQTT bridge connected");
                sub_acks = 0;
                to_announce = announcement(&app).await;
                announce(&app, &client, &topics, &settings, &mut to_announce).await;
                if settings.commands {
                    for filter in topics.command_filters() {
                        if let Err(e) = client.try_subscribe(filter, QoS::AtLeastOnce) {
                            tracing::warn!(error = %e, "cannot subscribe to the MQTT command topics");
                        }
                    }
                }
            }
            Ok(Event::Incoming(Packet::Publish(p))) if settings.commands => {
                if p.retain {
                    // Sent because we (re)subscribed, not because someone commanded now.
                    IntegrationStats::add(&stats.mqtt_retained_ignored, 1);
                    if retained_logged.len() < MAX_RETAINED_TOPICS_LOGGED
                        && retained_logged.insert(p.topic.clone())
                    {
                        tracing::warn!(topic = %p.topic, bytes = p.payload.len(),
                            "retained command message ignored: a retained command is never \
                             fresh (clear it on the broker with an empty retained message)");
                    }
                    continue;
                }
                if p.payload.is_empty() {
                    // How a retained message is cleared; not a command.
                    continue;
                }
                if p.payload.len() > settings.max_command_bytes {
                    IntegrationStats::add(&stats.mqtt_oversized_dropped, 1);
                    let answer = json!({"topic": p.topic, "ok": false, "code": "payload_too_large",
                        "message": format!("the command payload has {} bytes; at most {} \
                            (mqtt.max_command_bytes)", p.payload.len(), settings.max_command_bytes)});
                    refuse(answer);
                    continue;
                }
                let Ok(permit) = in_flight.clone().try_acquire_owned() else {
                    IntegrationStats::add(&stats.mqtt_commands_refused, 1);
                    let answer = json!({"topic": p.topic, "ok": false, "code": "busy",
                        "message": format!("more than {MAX_COMMANDS_IN_FLIGHT} commands in flight")});
                    refuse(answer);
                    continue;
                };
                let (app, client, topics) = (app.clone(), client.clone(), topics.clone());
                tokio::spawn(async move {
                    let answer = command(&app, &topics, &p.topic, &p.payload).await;
                    if answer["ok"] != true {
                        IntegrationStats::add(&app.integrations.mqtt_commands_refused, 1);
                    }
                    answer_on_results(&app, &client, &topics, &answer);
                    drop(permit);
                });
            }
            Ok(Event::Incoming(Packet::SubAck(_))) => {
                // Both command filters are asked for at once; the broker answers in order.
                sub_acks += 1;
                if sub_acks >= 2 {
                    stats.mqtt_commands_ready.store(true, Ordering::Relaxed);
                }
            }
            Ok(Event::Outgoing(_)) if !to_announce.is_empty() => {
                // The queue was full of what waited for the broker; now that it moves, go on.
                announce(&app, &client, &topics, &settings, &mut to_announce).await;
            }
            Ok(_) => {}
            Err(e) => {
                stats.mqtt_commands_ready.store(false, Ordering::Relaxed);
                if stats.mqtt_connected.swap(false, Ordering::Relaxed) {
                    tracing::warn!(error = %e, "MQTT bridge lost the broker; reconnecting");
                } else if backoff == BACKOFF_FIRST {
                    // The first failure in a row says why; the retries after it stay quiet.
                    tracing::warn!(error = %e, "MQTT connect failed; retrying with backoff");
                } else {
                    tracing::debug!(error = %e, retry_in = ?backoff, "MQTT connect failed");
                }
                tokio::select! {
                    _ = app.shutdown.cancelled() => break,
                    _ = tokio::time::sleep(backoff) => {}
                }
                backoff = (backoff * 2).min(BACKOFF_MAX);
            }
        }
    }
    // A clean shutdown is not a crash: say so (the broker would publish the will otherwise
    // only after the keep-alive runs out), then disconnect. Bounded: the broker may be gone.
    if stats.mqtt_connected.load(Ordering::Relaxed) {
        offer(
            &app,
            &client,
            topics.online(),
            QoS::AtLeastOnce,
            true,
            online_payload(false, &settings.node),
        );
        let _ = client.try_disconnect();
        let flush = async {
            loop {
                match eventloop.poll().await {
                    Ok(Event::Outgoing(rumqttc::Outgoing::Disconnect)) | Err(_) => return,
                    Ok(_) => {}
                }
            }
        };
        let _ = tokio::time::timeout(Duration::from_secs(1), flush).await;
    }
    stats.mqtt_connected.store(false, Ordering::Relaxed);
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JogBody {
    axis: fresa_plugin_api::contract::Axis,
    distance: f64,
    #[serde(default)]
    feed: Option<f64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct ResumeBody {
    #[serde(default)]
    confirm_part_zero: bool,
    #[serde(default)]
    confirm_line: Option<i64>,
}

/// One command message: check the token and its role, then call the same core function the
/// HTTP handler calls. Returns the answer published on `cmd/results`.
async fn command(app: &SharedApp, topics: &Topics, topic: &str, payload: &[u8]) -> Value {
    let mut answer = match run_command(app, topics, topic, payload).await {
        Ok(result) => json!({"ok": true, "result": result}),
        Err(e) => json!({"ok": false, "code": e.code, "message": e.message}),
    };
    answer["topic"] = json!(topic);
    if let Ok(Value::Object(o)) = serde_json::from_slice::<Value>(payload) {
        if let Some(id) = o.get("request_id") {
            answer["request_id"] = id.clone();
        }
    }
    answer
}

async fn run_command(
    app: &SharedApp,
    topics: &Topics,
    topic: &str,
    payload: &[u8],
) -> fresa_core::Result<Value> {
    use fresa_core::Error;
    let mut body: serde_json::Map<String, Value> = serde_json::from_slice(payload)
        .map_err(|e| Error::bad_request("invalid_json", format!("command payload: {e}")))?;
    let token = body
        .remove("token")
        .and_then(|t| t.as_str().map(str::to_string))
        .ok_or_else(|| {
            Error::new(
                fresa_core::ErrorKind::BadRequest,
                "token_required",
                "field `token`: every command needs an API token (role operator)",
            )
        })?;
    body.remove("request_id");
    let caller = app
        .store
        .token_by_hash(fresa_core::store::TokenHash::of(&token).as_str())
        .await?
        .ok_or_else(|| {
            Error::new(
                fresa_core::ErrorKind::BadRequest,
                "invalid_token",
                "the API token is not valid",
            )
        })?;
    if !matches!(&*caller.role, "operator" | "admin") {
        return Err(Error::new(
            fresa_core::ErrorKind::BadRequest,
            "forbidden",
            format!(
                "token {:?} has role {}; this command needs operator",
                caller.name, caller.role
            ),
        ));
    }
    let actor = format!("mqtt:{}", caller.name);
    let rest = topic
        .strip_prefix(&format!("{}/cmd/", topics.prefix))
        .unwrap_or_default();
    let parts: Vec<&str> = rest.split('/').collect();
    let id_of = |s: &str| {
        s.parse::<i64>().map_err(|_| {
            Error::bad_request("invalid_topic", format!("{s:?} in {topic:?} is not an id"))
        })
    };
    let body = Value::Object(body);
    match parts.as_slice() {
        ["machines", id, "jog"] => {
            let m = machine(app, id_of(id)?).await?;
            let j: JogBody = serde_json::from_value(body)
                .map_err(|e| Error::invalid("invalid_field", format!("jog: {e}")))?;
            m.jog(j.axis, j.distance, j.feed, &actor).await?;
            Ok(json!(null))
        }
        ["machines", id, "jog", "cancel"] => {
            let m = machine(app, id_of(id)?).await?;
            m.cancel_jogs(&actor).await
        }
        ["machines", id, "commands"] => {
            let m = machine(app, id_of(id)?).await?;
            let cmd = fresa_core::machine::limits::parse_command(&body)?;
            m.command(cmd, &actor).await
        }
        ["jobs", id, action] => {
            let id = id_of(id)?;
            use fresa_core::jobs;
            let run = match *action {
                "start" => jobs::start(app, id, &actor).await?,
                "pause" => jobs::pause(app, id, &actor).await?,
                "cancel" => jobs::cancel(app, id, &actor).await?,
                "resume" => {
                    let r: ResumeBody = serde_json::from_value(body)
                        .map_err(|e| Error::invalid("invalid_field", format!("resume: {e}")))?;
                    jobs::resume(app, id, &actor, r.confirm_part_zero, r.confirm_line).await?
                }
                other => {
                    return Err(Error::not_found(
                        "unknown_action",
                        format!("no job action {other:?} (start, pause, resume, cancel)"),
                    ))
                }
            };
            Ok(json!({"job": id, "run": run.id, "state": run.state}))
        }
        _ => Err(Error::not_found(
            "unknown_topic",
            format!("{topic:?} is not a command topic (cmd/machines/<id>/jog, cmd/machines/<id>/jog/cancel, cmd/machines/<id>/commands, cmd/jobs/<id>/<action>)"),
        )),
    }
}

async fn machine(
    app: &SharedApp,
    id: i64,
) -> fresa_core::Result<Arc<fresa_core::machine::Machine>> {
    app.machines.get(id).ok_or_else(|| {
        fresa_core::Error::not_found("unknown_machine", format!("no machine with id {id}"))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_keep_their_shape() {
        let t = Topics::new("shop/fresa", "host+1/x");
        assert_eq!(t.status(3), "shop/fresa/machines/3/status");
        assert_eq!(t.job_state(7), "shop/fresa/jobs/7/state");
        assert_eq!(t.event("job.state"), "shop/fresa/events/job.state");
        assert_eq!(t.online(), "shop/fresa/nodes/host_1_x/online");
        assert_eq!(
            t.command_filters(),
            ["shop/fresa/cmd/machines/#", "shop/fresa/cmd/jobs/#"]
        );
    }
}
