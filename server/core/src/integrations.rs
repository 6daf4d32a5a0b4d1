//! What the integrations (`fresa-integrations`: webhook deliveries, the MQTT bridge) count, kept
//! here so `/metrics` can read it without the HTTP layer depending on them. Only counters: the
//! integrations own their queues and connections.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

#[derive(Debug, Default)]
pub struct IntegrationStats {
    /// Webhook deliveries answered 2xx.
    pub webhook_delivered: AtomicU64,
    /// Deliveries that failed every attempt.
    pub webhook_failed: AtomicU64,
    /// Attempts after the first.
    pub webhook_retries: AtomicU64,
    /// Events not delivered because a webhook's queue was full (or its reader fell behind).
    pub webhook_dropped: AtomicU64,
    /// Messages handed to the MQTT client.
    pub mqtt_published: AtomicU64,
    /// Messages dropped because the bridge's queue was full (broker slow or gone).
    pub mqtt_dropped: AtomicU64,
    /// Whether the bridge is connected to the broker now.
    pub mqtt_connected: AtomicBool,
    /// Whether the broker has confirmed the command subscriptions (with `commands = true`).
    pub mqtt_commands_ready: AtomicBool,
    /// Successful connections after the first.
    pub mqtt_reconnects: AtomicU64,
    /// Command messages refused (bad token, role, payload).
    pub mqtt_commands_refused: AtomicU64,
    /// Webhook deliveries refused because the target's address is one webhooks may not reach.
    pub webhook_refused: AtomicU64,
    /// Retained messages on the command topics, ignored (a retained command is never fresh).
    pub mqtt_retained_ignored: AtomicU64,
    /// Command messages over `mqtt.max_command_bytes`, dropped.
    pub mqtt_oversized_dropped: AtomicU64,
}

impl IntegrationStats {
    pub fn add(counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::Relaxed);
    }

    /// Prometheus text for every counter.
    pub fn prometheus(&self) -> String {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        let mut out = String::new();
        for (name, help, v) in [
            (
                "fresa_webhook_delivered_total",
                "Webhook deliveries answered 2xx.",
                get(&self.webhook_delivered),
            ),
            (
                "fresa_webhook_failed_total",
                "Webhook deliveries that failed every attempt.",
                get(&self.webhook_failed),
            ),
            (
                "fresa_webhook_retries_total",
                "Webhook attempts after the first.",
                get(&self.webhook_retries),
            ),
            (
                "fresa_webhook_dropped_total",
                "Events not delivered to a webhook because its queue was full.",
                get(&self.webhook_dropped),
            ),
            (
                "fresa_mqtt_published_total",
                "Messages handed to the MQTT client.",
                get(&self.mqtt_published),
            ),
            (
                "fresa_mqtt_dropped_total",
                "MQTT messages dropped because the bridge's queue was full.",
                get(&self.mqtt_dropped),
            ),
            (
                "fresa_mqtt_reconnects_total",
                "MQTT reconnections after the first connection.",
                get(&self.mqtt_reconnects),
            ),
            (
                "fresa_mqtt_commands_refused_total",
                "MQTT command messages refused.",
                get(&self.mqtt_commands_refused),
            ),
            (
                "fresa_webhook_refused_total",
                "Webhook deliveries refused because the target address may not be reached.",
                get(&self.webhook_refused),
            ),
            (
                "fresa_mqtt_retained_ignored_total",
                "Retained messages on the MQTT command topics, ignored.",
                get(&self.mqtt_retained_ignored),
            ),
            (
                "fresa_mqtt_oversized_dropped_total",
                "MQTT command messages over mqtt.max_command_bytes, dropped.",
                get(&self.mqtt_oversized_dropped),
            ),
        ] {
            out.push_str(&format!(
                "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}\n"
            ));
        }
        out.push_str(&format!(
            "# HELP fresa_mqtt_connected 1 while the MQTT bridge is connected.\n# TYPE fresa_mqtt_connected gauge\nfresa_mqtt_connected {}\n",
            u8::from(self.mqtt_connected.load(Ordering::Relaxed))
        ));
        out.push_str(&format!(
            "# HELP fresa_mqtt_commands_ready 1 while the broker has confirmed the MQTT command subscriptions.\n# TYPE fresa_mqtt_commands_ready gauge\nfresa_mqtt_commands_ready {}\n",
            u8::from(self.mqtt_commands_ready.load(Ordering::Relaxed))
        ));
        out
    }
}
