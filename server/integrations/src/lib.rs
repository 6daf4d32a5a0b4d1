//! Fresa's outward integrations, fed by the core's event bus and never blocking it: signed
//! webhook deliveries ([`webhooks`]) and the MQTT bridge ([`mqtt`]). Each keeps bounded queues
//! and counts what it drops in `App::integrations` (shown by `/metrics`).

pub mod mqtt;
pub mod webhooks;

use fresa_core::SharedApp;

/// The running integrations; they stop when the app's shutdown token is cancelled.
pub struct Integrations {
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

/// Starts webhook deliveries (always: with no webhooks registered they cost one idle task) and
/// the MQTT bridge when one is configured.
pub fn start(app: SharedApp) -> Integrations {
    let mut tasks = vec![webhooks::spawn(app.clone())];
    if let Some(settings) = app.settings.mqtt.clone() {
        tasks.extend(mqtt::spawn(app, settings));
    }
    Integrations { tasks }
}

impl Integrations {
    /// Waits at most `limit` for the tasks to finish after shutdown was signalled.
    pub async fn join(self, limit: std::time::Duration) {
        let all = futures_join(self.tasks);
        if tokio::time::timeout(limit, all).await.is_err() {
            tracing::warn!("integrations did not stop within {limit:?}");
        }
    }
}

async fn futures_join(tasks: Vec<tokio::task::JoinHandle<()>>) {
    for t in tasks {
        let _ = t.await;
    }
}
