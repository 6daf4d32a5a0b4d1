//! `GET /api/v1/events`: Server-Sent Events. Persisted events carry their id and are replayed
//! after `Last-Event-ID`; transient ones (status, progress) are live only. A client that falls
//! behind gets an explicit `resync` event, then the persisted events it missed; so does one
//! whose `Last-Event-ID` is older than what retention has deleted, then what remains.

use super::error::{ApiError, Query};
use crate::admission::Admission;
use crate::auth::{ByToken, Caller};
use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::HeaderMap;
use axum::response::{IntoResponse, Response};
use axum::Extension;
use fresa_core::events::{BusEvent, EventKind};
use fresa_core::SharedApp;
use serde::Deserialize;
use std::sync::Arc;
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::mpsc::Sender;

#[derive(Deserialize, Default, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct Filter {
    /// Comma-separated event types; `job` matches `job.*`.
    types: Option<String>,
    machine: Option<i64>,
    /// Alternative to the `Last-Event-ID` header (for clients that cannot set headers).
    after: Option<i64>,
}

struct Matcher {
    types: Vec<String>,
    machine: Option<i64>,
}

impl Matcher {
    fn matches(&self, e: &BusEvent) -> bool {
        if let Some(m) = self.machine {
            if e.machine != Some(m) {
                return false;
            }
        }
        self.types.is_empty() || self.types.iter().any(|t| type_matches(e.kind.as_str(), t))
    }
}

/// A `types` entry matches its own type and, as a group, every `<entry>.*` type.
fn type_matches(kind: &str, filter: &str) -> bool {
    kind == filter || (kind.starts_with(filter) && kind.as_bytes().get(filter.len()) == Some(&b'.'))
}

/// `types` as asked, each checked: a type the server emits, or a group of them (`job` for
/// `job.*`); anything else would be a stream that never sends a thing.
fn known_types(types: Option<&str>) -> Result<Vec<String>, ApiError> {
    let mut out = Vec::new();
    for t in types.unwrap_or("").split(',').map(str::trim) {
        if t.is_empty() {
            continue;
        }
        let known = t == "resync" || EventKind::ALL.iter().any(|k| type_matches(k.name(), t));
        if !known {
            return Err(ApiError::bad_request(
                "invalid_query",
                format!(
                    "query `types`: {t:?} is not an event type or group of them (e.g. `job`, \
                     `machine.jog`, `status`; the list is in the README's event stream section)"
                ),
            ));
        }
        out.push(t.to_string());
    }
    Ok(out)
}

/// The event's whole SSE frame is made once per event (`BusEvent::sse`) and shared by every
/// client: with thousands of streams, a copy per client would cost more than the event.
fn to_sse(e: &BusEvent) -> Bytes {
    e.sse()
}

/// A `resync` frame (made per client: what it missed is its own).
fn resync_frame(data: &serde_json::Value) -> Bytes {
    fresa_core::events::sse_frame("resync", &data.to_string(), None)
}

/// A comment line: keeps proxies and clients from closing a quiet stream.
const KEEP_ALIVE: &[u8] = b":\n\n";

#[utoipa::path(get, path = "/events", tag = "events",
    params(Filter,
        ("Last-Event-ID" = Option<i64>, Header, description = "Resume after this persisted event id"),
        ("access_token" = Option<String>, Query, description = "The token, for browsers' EventSource (accepted here only)")),
    responses(
        (status = 200, description = "Server-Sent Events: `event: <type>`, `id: <id>` (persisted events), `data: Event` as JSON. A client that fell behind, or resumes across pruned events, first gets `event: resync` (`{\"reason\", \"missed\"|\"pruned_through\", \"after\"}`).",
            content_type = "text/event-stream", body = crate::openapi::EventDoc),
        (status = 400, description = "`invalid_header`, `invalid_query` (also a `types` entry that is no event type or group), `token_in_query`", body = crate::openapi::ErrorBody),
        (status = 404, description = "`unknown_machine`: `machine` names no machine", body = crate::openapi::ErrorBody),
        (status = 429, description = "`too_many_streams`: this token holds `max_event_streams_per_client` streams (with `Retry-After`; the connection is closed)", body = crate::openapi::ErrorBody),
        (status = 503, description = "`too_many_streams`: `max_event_streams` are open (with `Retry-After`; the connection is closed)", body = crate::openapi::ErrorBody),
    ))]
pub async fn stream(
    State(app): State<SharedApp>,
    headers: HeaderMap,
    Query(f): Query<Filter>,
    Extension(caller): Extension<Caller>,
    by_token: Option<Extension<ByToken>>,
    Extension(admission): Extension<Option<Arc<Admission>>>,
    connection: Option<Extension<crate::admission::Connection>>,
) -> Result<Response, Response> {
    let last_id = match headers.get("last-event-id") {
        Some(v) => Some(
            v.to_str()
                .ok()
                .and_then(|s| s.trim().parse::<i64>().ok())
                .ok_or_else(|| {
                    ApiError::bad_request(
                        "invalid_header",
                        "Last-Event-ID must be an integer event id",
                    )
                    .into_response()
                })?,
        ),
        None => f.after,
    };
    let types = known_types(f.types.as_deref()).map_err(IntoResponse::into_response)?;
    if let Some(id) = f.machine {
        // A typo would otherwise be a stream that stays silent forever. Unknown only when the
        // store says so: during an outage live events still flow.
        if app.machines.get(id).await.is_none() && matches!(app.store.machine(id).await, Ok(None)) {
            return Err(ApiError::not_found(
                "unknown_machine",
                format!("query `machine`: no machine with id {id}"),
            )
            .into_response());
        }
    }
    let matcher = Matcher {
        types,
        machine: f.machine,
    };
    // A stream holds its connection while it lasts, so it needs one of the stream slots,
    // which are fewer than the connections (see `admission`); freed when the body is dropped.
    // Counted per token; tokenless local callers only against the server's cap.
    let slot = match admission {
        Some(a) => Some(
            a.open_stream(by_token.map(|_| &*caller.name))
                .map_err(IntoResponse::into_response)?,
        ),
        None => None,
    };
    // From here on the connection counts under `max_event_streams`, not `max_connections`.
    if let Some(Extension(c)) = &connection {
        c.into_stream();
    }
    // Subscribe before replaying so nothing falls between the replay and the live stream.
    let mut rx = app.bus.subscribe();
    let shutdown = app.shutdown.clone();
    let store = app.store.clone();
    let keepalive = app.settings.sse_keepalive;
    let s = async_stream(move |tx| async move {
        let mut sent_up_to = last_id.unwrap_or(0);
        if let Some(after) = last_id {
            let Some((start, resynced)) = resync_if_gap(&store, after, &tx).await else {
                return;
            };
            sent_up_to = start;
            if !replay(&store, &matcher, &mut sent_up_to, &tx).await {
                return;
            }
            // A retention pass during the replay may have deleted events before the replay
            // read them: say so (at worst needlessly, if they had been sent already).
            if !resynced {
                if let Ok(pruned) = store.events_pruned_through().await {
                    if pruned > start && !send_resync(&tx, retention_gap(start, pruned)).await {
                        return;
                    }
                }
            }
        }
        loop {
            tokio::select! {
                _ = shutdown.cancelled() => return,
                // The client went away: let go of the bus now, not at the next matching event.
                _ = tx.closed() => return,
                r = rx.recv() => match r {
                    Ok(e) => {
                        if let Some(id) = e.id {
                            if id <= sent_up_to { continue; }
                            sent_up_to = id;
                        }
                        if matcher.matches(&e) && tx.send(to_sse(&e)).await.is_err() {
                            return;
                        }
                    }
                    Err(RecvError::Lagged(n)) => {
                        let ev = resync_frame(
                            &serde_json::json!({"reason": "client fell behind", "missed": n, "after": sent_up_to}),
                        );
                        if tx.send(ev).await.is_err() { return; }
                        if !replay(&store, &matcher, &mut sent_up_to, &tx).await { return; }
                    }
                    Err(RecvError::Closed) => return,
                }
            }
        }
    });
    // A comment whenever no frame came for `keepalive` (as axum's `KeepAlive` did), so proxies
    // and clients do not take a quiet stream for a dead one.
    let mut quiet = tokio::time::interval_at(tokio::time::Instant::now() + keepalive, keepalive);
    quiet.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let s = tokio_stream::StreamExt::timeout_repeating(s, quiet);
    let s = futures_util::StreamExt::map(s, move |frame| {
        let _held = &slot;
        Ok::<_, std::convert::Infallible>(frame.unwrap_or(Bytes::from_static(KEEP_ALIVE)))
    });
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, "text/event-stream"),
            (axum::http::header::CACHE_CONTROL, "no-cache"),
            // Its place is a stream's now (see `Connection::into_stream`): not reused.
            (axum::http::header::CONNECTION, "close"),
        ],
        Body::from_stream(s),
    )
        .into_response())
}

/// Sends `resync` when a replay after `after` cannot be complete, and returns where the replay
/// starts and whether `resync` was sent (None: the client went away). Two gaps: retention
/// deleted events after `after` (the client gets what remains after it), or `after` is beyond
/// every id this log has given (the store was restored from a backup: new events reuse those
/// ids, so the client starts from the log's end instead of skipping them).
async fn resync_if_gap(
    store: &fresa_core::store::Store,
    after: i64,
    tx: &Sender<Bytes>,
) -> Option<(i64, bool)> {
    let marks = async {
        Ok::<_, sqlx::Error>((
            store.events_pruned_through().await?,
            store.last_event_id().await?,
        ))
    };
    let (pruned, last) = match marks.await {
        Ok(m) => m,
        Err(e) => {
            tracing::error!(error = %e, "cannot read the event log's bounds for a replay");
            return Some((after, false));
        }
    };
    let (data, start) = if after > last {
        (
            serde_json::json!({
                "reason": "this id is newer than the event log (restored from a backup?)",
                "after": after,
                "last_event_id": last,
            }),
            last,
        )
    } else if after < pruned {
        (retention_gap(after, pruned), after)
    } else {
        return Some((after, false));
    };
    send_resync(tx, data).await.then_some((start, true))
}

fn retention_gap(after: i64, pruned: i64) -> serde_json::Value {
    serde_json::json!({
        "reason": "events after this id were deleted by retention",
        "after": after,
        "pruned_through": pruned,
    })
}

/// False if the client went away.
async fn send_resync(tx: &Sender<Bytes>, data: serde_json::Value) -> bool {
    tx.send(resync_frame(&data)).await.is_ok()
}

/// Sends persisted events after `*after`, page by page. Returns false if the client went away.
async fn replay(
    store: &fresa_core::store::Store,
    matcher: &Matcher,
    after: &mut i64,
    tx: &Sender<Bytes>,
) -> bool {
    loop {
        let page = match store.events_after(*after, 500).await {
            Ok(p) => p,
            Err(e) => {
                tracing::error!(error = %e, "event replay failed");
                return true;
            }
        };
        if page.is_empty() {
            return true;
        }
        for row in page {
            let e = BusEvent::from(row);
            *after = e.id.unwrap_or(*after);
            if matcher.matches(&e) && tx.send(to_sse(&e)).await.is_err() {
                return false;
            }
        }
    }
}

/// A stream fed by a task through a small channel: the task ends when the client disconnects
/// (send fails) or on shutdown, which ends the stream.
fn async_stream<F, Fut>(f: F) -> tokio_stream::wrappers::ReceiverStream<Bytes>
where
    F: FnOnce(Sender<Bytes>) -> Fut,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    tokio::spawn(f(tx));
    tokio_stream::wrappers::ReceiverStream::new(rx)
}
