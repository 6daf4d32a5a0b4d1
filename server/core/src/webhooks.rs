//! Registering webhooks (the HTTP admin routes call these). Deliveries are made by
//! `fresa-integrations`, which rereads the list when it sees `webhook.created` or
//! `webhook.deleted` on the event bus.

use crate::app::App;
use crate::error::{Error, Result};
use crate::store::WebhookRow;

/// Longest URL accepted.
const MAX_URL: usize = 2000;
/// Most event types in one filter.
const MAX_FILTER: usize = 100;

/// A new webhook and its signing secret (shown to the caller once, never again).
pub struct NewWebhook {
    pub row: WebhookRow,
    pub secret: String,
}

fn check_url(url: &str) -> Result<()> {
    let rest = url
        .strip_prefix("http://")
        .or_else(|| url.strip_prefix("https://"))
        .ok_or_else(|| {
            Error::invalid(
                "invalid_field",
                format!("field `url`: {url:?} must start with http:// or https://"),
            )
        })?;
    let host = rest.split(['/', '?', '#']).next().unwrap_or("");
    if host.is_empty() || host.starts_with(':') {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `url`: {url:?} has no host"),
        ));
    }
    if url.len() > MAX_URL || url.chars().any(|c| c.is_whitespace() || c.is_control()) {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `url`: at most {MAX_URL} characters, no spaces or control characters"),
        ));
    }
    Ok(())
}

fn check_filter(events: &[String]) -> Result<()> {
    if events.len() > MAX_FILTER {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `events`: at most {MAX_FILTER} types"),
        ));
    }
    for (i, t) in events.iter().enumerate() {
        let ok = !t.is_empty()
            && t.len() <= 100
            && t.chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '.' || c == '_');
        if !ok {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `events[{i}]`: {t:?} is not an event type (e.g. \"job.state\" or \"job\")"
                ),
            ));
        }
    }
    Ok(())
}

/// Whether an event of type `kind` passes `filter` (`job` matches `job.*`; empty passes all).
pub fn matches(filter: &[String], kind: &str) -> bool {
    filter.is_empty()
        || filter.iter().any(|t| {
            kind == t
                || (kind.starts_with(t.as_str()) && kind.as_bytes().get(t.len()) == Some(&b'.'))
        })
}

pub async fn create(app: &App, url: &str, events: Vec<String>, actor: &str) -> Result<NewWebhook> {
    check_url(url)?;
    check_filter(&events)?;
    let secret = format!("whsec_{}", hex::encode(rand::random::<[u8; 32]>()));
    let row = app
        .store
        .insert_webhook(url, &events, &secret, actor)
        .await?;
    app.bus
        .record_or_log(
            "webhook.created",
            None,
            Some(actor),
            serde_json::json!({"id": row.id, "url": row.url, "events": events}),
        )
        .await;
    Ok(NewWebhook { row, secret })
}

pub async fn delete(app: &App, id: i64, actor: &str) -> Result<()> {
    if !app.store.delete_webhook(id).await? {
        return Err(Error::not_found(
            "unknown_webhook",
            format!("no webhook with id {id}"),
        ));
    }
    app.bus
        .record_or_log(
            "webhook.deleted",
            None,
            Some(actor),
            serde_json::json!({"id": id}),
        )
        .await;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_match_by_type_or_prefix() {
        let f = vec!["job".to_string(), "machine.alarm".to_string()];
        assert!(matches(&f, "job.state"));
        assert!(matches(&f, "machine.alarm"));
        assert!(!matches(&f, "jobs.x"));
        assert!(!matches(&f, "machine.jog"));
        assert!(matches(&[], "anything"));
    }

    #[test]
    fn bad_urls_and_filters_are_named() {
        for bad in ["ftp://x", "http://", "http:// x", "x"] {
            assert!(check_url(bad).is_err(), "{bad}");
        }
        assert!(check_url("http://127.0.0.1:9/hook").is_ok());
        assert!(check_filter(&["Job!".into()]).is_err());
    }
}
