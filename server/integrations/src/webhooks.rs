//! Webhook deliveries. One dispatcher reads the event bus and hands each persisted event to the
//! queue of every webhook whose filter wants it (`try_send`: a full queue drops the event and
//! counts it, so the bus and the machines never wait for a receiver). One worker per webhook
//! delivers its queue in order, retrying with doubling delays; a hanging receiver holds up only
//! its own queue, for at most the request timeout per attempt.
//!
//! Targets: deliveries go only where [`TargetPolicy`] allows (no loopback, link-local, metadata
//! services, ... unless `webhooks.allowed_hosts` lists the host). Names are resolved by
//! [`GuardedResolver`], which refuses a name if any of its addresses is refused, and the client
//! connects to the addresses it checked; addresses written in the URL are checked before each
//! attempt (the client does not resolve them). Deliveries use no proxy, so what is checked is
//! what is connected to.
//!
//! Signature: `Fresa-Signature: t=<unix seconds>,v1=<hex HMAC-SHA256(key, "<t>.<body>")>`,
//! where the key is the webhook's secret string (UTF-8 bytes, `whsec_...` included).

use fresa_core::config::WebhookSettings;
use fresa_core::events::{BusEvent, EventKind};
use fresa_core::integrations::IntegrationStats;
use fresa_core::store::{DeliveryOutcome, WebhookTarget};
use fresa_core::webhooks::{refusal_message, TargetPolicy};
use fresa_core::SharedApp;
use hmac::{Hmac, Mac};
use sha2::Sha256;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

/// The longest wait between two attempts.
const MAX_RETRY_DELAY: Duration = Duration::from_secs(300);

/// `t=<unix seconds>,v1=<hex HMAC-SHA256(secret, "<t>.<body>")>`.
pub fn signature(secret: &str, unix_seconds: u64, body: &[u8]) -> String {
    // HMAC takes keys of any length; `new_from_slice` cannot fail for it.
    let mut mac = match Hmac::<Sha256>::new_from_slice(secret.as_bytes()) {
        Ok(m) => m,
        Err(_) => return String::new(),
    };
    mac.update(unix_seconds.to_string().as_bytes());
    mac.update(b".");
    mac.update(body);
    format!(
        "t={unix_seconds},v1={}",
        hex::encode(mac.finalize().into_bytes())
    )
}

struct Worker {
    filter: Vec<String>,
    queue: mpsc::Sender<Arc<BusEvent>>,
    stop: CancellationToken,
}

/// Starts the dispatcher; it ends when the app shuts down.
pub fn spawn(app: SharedApp) -> tokio::task::JoinHandle<()> {
    // Subscribe before reading the list, so no event falls between the two.
    let rx = app.bus.subscribe();
    tokio::spawn(dispatch(app, rx))
}

/// A delivery's target was refused by the [`TargetPolicy`]; carried through the HTTP client's
/// error so the outcome can say why.
#[derive(Debug)]
struct Refused(String);

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Refused {}

/// Resolves delivery host names with the system resolver and refuses a name any of whose
/// addresses is refused; the client connects only to the addresses returned here, so a name
/// that changes between the check and the connection (DNS rebinding) gains nothing.
struct GuardedResolver {
    policy: Arc<TargetPolicy>,
}

impl reqwest::dns::Resolve for GuardedResolver {
    fn resolve(&self, name: reqwest::dns::Name) -> reqwest::dns::Resolving {
        let policy = self.policy.clone();
        let host = name.as_str().to_string();
        Box::pin(async move {
            let addrs: Vec<std::net::SocketAddr> =
                tokio::net::lookup_host((host.as_str(), 0)).await?.collect();
            if !policy.host_allowed(&host) {
                for a in &addrs {
                    if let Some(why) = policy.refused_address(a.ip()) {
                        let refused: Box<dyn std::error::Error + Send + Sync> =
                            Box::new(Refused(format!("{host} resolves to {why}")));
                        return Err(refused);
                    }
                }
            }
            let addrs: reqwest::dns::Addrs = Box::new(addrs.into_iter());
            Ok(addrs)
        })
    }
}

/// The refusal in a failed request's causes, if the resolver refused its target.
fn refusal_in(e: &reqwest::Error) -> Option<String> {
    let mut cause = std::error::Error::source(e);
    while let Some(c) = cause {
        if let Some(r) = c.downcast_ref::<Refused>() {
            return Some(r.0.clone());
        }
        cause = c.source();
    }
    None
}

/// Why the target is refused before connecting: an address written in the URL (the client
/// connects to it without resolving), or a name refused as such (`localhost`).
fn refused_as_written(policy: &TargetPolicy, url: &str) -> Option<String> {
    let parsed = reqwest::Url::parse(url).ok()?;
    policy.refused_host(&parsed.host()?)
}

/// The HTTP client of every delivery, and the policy its resolver applies.
#[derive(Clone)]
struct Sender {
    http: reqwest::Client,
    policy: Arc<TargetPolicy>,
}

async fn dispatch(app: SharedApp, mut rx: tokio::sync::broadcast::Receiver<Arc<BusEvent>>) {
    let policy = Arc::new(TargetPolicy::new(&app.settings));
    let client = match reqwest::Client::builder()
        .user_agent(concat!("fresa/", env!("CARGO_PKG_VERSION")))
        // A signed delivery goes where it was registered, not where a redirect points.
        .redirect(reqwest::redirect::Policy::none())
        // Through a proxy the proxy would resolve and connect: the checked address would not
        // be the one reached.
        .no_proxy()
        .dns_resolver(Arc::new(GuardedResolver {
            policy: policy.clone(),
        }))
        .build()
    {
        Ok(c) => c,
        Err(e) => {
            tracing::error!(error = %e, "webhooks disabled: cannot build the HTTP client");
            return;
        }
    };
    let mut workers: HashMap<i64, Worker> = HashMap::new();
    let client = Sender {
        http: client,
        policy,
    };
    sync_workers(&app, &client, &mut workers).await;
    // A stuck receiver makes every event a drop: one line a minute, with the count.
    let quiet = fresa_plugin_api::quiet::Quiet::per_minute();
    loop {
        let ev = tokio::select! {
            _ = app.shutdown.cancelled() => break,
            ev = rx.recv() => ev,
        };
        match ev {
            Ok(ev) => {
                // Live-only events (status at 10 Hz, progress) are for streams, not webhooks.
                if ev.id.is_none() {
                    continue;
                }
                if ev.is(EventKind::WebhookCreated) || ev.is(EventKind::WebhookDeleted) {
                    sync_workers(&app, &client, &mut workers).await;
                }
                // On a store shared by nodes each node delivers its own events (once each).
                if !app.bus.is_local(&ev) {
                    continue;
                }
                for (id, w) in &workers {
                    if !fresa_core::webhooks::matches(&w.filter, &ev.kind) {
                        continue;
                    }
                    if w.queue.try_send(ev.clone()).is_err() {
                        IntegrationStats::add(&app.integrations.webhook_dropped, 1);
                        if let Some(line) = quiet.admit(&format!("full-{id}"), || {
                            format!("webhook {id} queue full: event {:?} dropped", ev.id)
                        }) {
                            tracing::warn!("{line}");
                        }
                    }
                }
            }
            Err(RecvError::Lagged(n)) => {
                // Cannot say which webhooks wanted them; count them once, and reread the list
                // in case a created/deleted event was among them.
                IntegrationStats::add(&app.integrations.webhook_dropped, n);
                tracing::warn!(missed = n, "webhook dispatcher fell behind the event bus");
                sync_workers(&app, &client, &mut workers).await;
            }
            Err(RecvError::Closed) => break,
        }
    }
    for w in workers.values() {
        w.stop.cancel();
    }
}

/// Starts a worker for every new webhook and stops the workers of deleted ones.
async fn sync_workers(app: &SharedApp, client: &Sender, workers: &mut HashMap<i64, Worker>) {
    let targets = match app.store.webhook_targets().await {
        Ok(t) => t,
        Err(e) => {
            tracing::error!(error = %e, "cannot read webhooks");
            return;
        }
    };
    workers.retain(|id, w| {
        let keep = targets.iter().any(|t| t.id == *id);
        if !keep {
            w.stop.cancel();
        }
        keep
    });
    for t in targets {
        if workers.contains_key(&t.id) {
            continue;
        }
        let settings = app.settings.webhooks.clone();
        let (tx, rx) = mpsc::channel(settings.queue);
        let stop = app.shutdown.child_token();
        workers.insert(
            t.id,
            Worker {
                filter: t.event_filter(),
                queue: tx,
                stop: stop.clone(),
            },
        );
        tokio::spawn(work(app.clone(), client.clone(), t, settings, rx, stop));
    }
}

async fn work(
    app: SharedApp,
    client: Sender,
    target: WebhookTarget,
    settings: WebhookSettings,
    mut rx: mpsc::Receiver<Arc<BusEvent>>,
    stop: CancellationToken,
) {
    loop {
        let ev = tokio::select! {
            _ = stop.cancelled() => return,
            ev = rx.recv() => match ev { Some(ev) => ev, None => return },
        };
        let Some(outcome) = deliver(&app, &client, &target, &settings, &ev, &stop).await else {
            return;
        };
        let stats = &app.integrations;
        if outcome.ok {
            IntegrationStats::add(&stats.webhook_delivered, 1);
        } else {
            IntegrationStats::add(&stats.webhook_failed, 1);
            tracing::warn!(webhook = target.id, event = ?ev.id, status = ?outcome.status,
                error = ?outcome.error, attempts = outcome.attempts, "webhook delivery failed");
        }
        if let Err(e) = app.store.record_webhook_delivery(target.id, &outcome).await {
            tracing::error!(webhook = target.id, error = %e, "cannot record a webhook delivery");
        }
    }
}

/// One event to one webhook, with retries. None: stopped (deleted or shutting down).
async fn deliver(
    app: &SharedApp,
    client: &Sender,
    target: &WebhookTarget,
    settings: &WebhookSettings,
    ev: &BusEvent,
    stop: &CancellationToken,
) -> Option<DeliveryOutcome> {
    // Serialised once per event, shared with SSE and MQTT.
    let body = ev.json().as_bytes().to_vec();
    let delivery = format!("{}-{}", target.id, ev.id.unwrap_or(0));
    let mut delay = settings.retry_initial;
    let mut outcome = DeliveryOutcome {
        ok: false,
        status: None,
        error: None,
        attempts: 0,
    };
    for attempt in 1..=settings.max_attempts {
        if attempt > 1 {
            IntegrationStats::add(&app.integrations.webhook_retries, 1);
            tokio::select! {
                _ = stop.cancelled() => return None,
                _ = tokio::time::sleep(delay) => {}
            }
            delay = (delay * 2).min(MAX_RETRY_DELAY);
        }
        outcome.attempts = attempt;
        // Refused is final: retrying would ask for the same address again.
        let refuse = |mut outcome: DeliveryOutcome, why: &str| {
            IntegrationStats::add(&app.integrations.webhook_refused, 1);
            outcome.status = None;
            outcome.error = Some(refusal_message(why));
            Some(outcome)
        };
        if let Some(why) = refused_as_written(&client.policy, &target.url) {
            return refuse(outcome, &why);
        }
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        let request = client
            .http
            .post(&target.url)
            .timeout(settings.timeout)
            .header(reqwest::header::CONTENT_TYPE, "application/json")
            .header("Fresa-Event", ev.kind.as_str())
            .header("Fresa-Delivery", delivery.as_str())
            .header("Fresa-Signature", signature(&target.secret, now, &body))
            .body(body.clone())
            .send();
        let answer = tokio::select! {
            _ = stop.cancelled() => return None,
            a = request => a,
        };
        match answer {
            Ok(r) if r.status().is_success() => {
                outcome.ok = true;
                outcome.status = Some(r.status().as_u16());
                outcome.error = None;
                return Some(outcome);
            }
            Ok(r) => {
                outcome.status = Some(r.status().as_u16());
                outcome.error = Some(format!("answered {}", r.status()));
            }
            Err(e) => {
                if let Some(why) = refusal_in(&e) {
                    return refuse(outcome, &why);
                }
                outcome.status = None;
                outcome.error = Some(if e.is_timeout() {
                    format!("no answer within {} ms", settings.timeout.as_millis())
                } else {
                    format!("request failed: {e}")
                });
            }
        }
    }
    Some(outcome)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// RFC 4231 test case 2 checks the HMAC itself; this checks what we feed it.
    #[test]
    fn signature_is_hmac_sha256_over_timestamp_dot_body() {
        let sig = signature("key", 1_700_000_000, b"{\"a\":1}");
        let mut mac = Hmac::<Sha256>::new_from_slice(b"key").unwrap_or_else(|_| unreachable!());
        mac.update(b"1700000000.{\"a\":1}");
        let want = hex::encode(mac.finalize().into_bytes());
        assert_eq!(sig, format!("t=1700000000,v1={want}"));
        // RFC 4231, test case 2: HMAC-SHA256("Jefe", "what do ya want for nothing?").
        let mut mac = Hmac::<Sha256>::new_from_slice(b"Jefe").unwrap_or_else(|_| unreachable!());
        mac.update(b"what do ya want for nothing?");
        assert_eq!(
            hex::encode(mac.finalize().into_bytes()),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
    }
}
