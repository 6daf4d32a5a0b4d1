//! `GET /api/v1/events`: Server-Sent Events. Persisted events carry their id and are replayed
//! after `Last-Event-ID`; transient ones (status, progress) are live only. A client that falls
//! behind gets an explicit `resync` event, then the persisted events it missed; so does one
//! whose `Last-Event-ID` is older than what retention has deleted, then what remains.

use super::error::{ApiError, Query};
use crate::admission::Admission;
use crate::auth::Caller;
use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::HeaderMap;
use axum::response::{IntoResponse, Response};
use axum::Extension;
use fresa_core::events::{BusEvent, EventKind};
use fresa_core::SharedApp;
use serde::Deserialize;
use std::collections::VecDeque;
use std::sync::Arc;
use tokio::sync::broadcast::error::RecvError;

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

#[utoipa::path(get, path = "/api/v1/events", tag = "events",
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
        if !app.machines.is_local(id) && matches!(app.store.machine(id).await, Ok(None)) {
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
            a.open_stream(caller.by_token.then_some(&*caller.name))
                .map_err(IntoResponse::into_response)?,
        ),
        None => None,
    };
    // From here on the connection counts under `max_event_streams`, not `max_connections`.
    if let Some(Extension(c)) = &connection {
        c.into_stream();
    }
    let feed = Feed {
        // Subscribed before the replay, so nothing falls between the replay and the live bus.
        rx: app.bus.subscribe(),
        store: app.store.clone(),
        matcher,
        sent_up_to: last_id.unwrap_or(0),
        ready: VecDeque::new(),
        resume: last_id.map(Resume::Asked),
    };
    let keepalive = app.settings.sse_keepalive;
    // The stream is polled by the connection's own task: no task and channel per stream, and
    // shutdown is one registration for the stream's life rather than one per event.
    let s = futures_util::stream::unfold(feed, |mut feed| async move {
        feed.next().await.map(|frame| (frame, feed))
    });
    let s = futures_util::StreamExt::take_until(s, app.shutdown.clone().cancelled_owned());
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

/// Where a stream that asked to resume (`Last-Event-ID`) stands before it goes live.
enum Resume {
    /// Resume after this id: first check it against the log's bounds.
    Asked(i64),
    /// Replaying from the log (after a resume or a lag); `Some(start)`: once done, say so if
    /// a retention pass deleted events after `start` meanwhile.
    Replaying(Option<i64>),
}

/// One client's events: a replay from the log where asked or needed, then the live bus.
struct Feed {
    rx: tokio::sync::broadcast::Receiver<Arc<BusEvent>>,
    store: fresa_core::store::Store,
    matcher: Matcher,
    sent_up_to: i64,
    /// Frames to send before anything else: a `resync` and a page of the replay (at most
    /// [`REPLAY_PAGE`] events, so a replay holds one page in memory at a time).
    ready: VecDeque<Bytes>,
    resume: Option<Resume>,
}

/// Events read from the log per replay query.
const REPLAY_PAGE: i64 = 500;

impl Feed {
    /// The next frame; `None` once the bus is closed.
    async fn next(&mut self) -> Option<Bytes> {
        loop {
            if let Some(frame) = self.ready.pop_front() {
                return Some(frame);
            }
            match self.resume.take() {
                Some(Resume::Asked(after)) => self.check_gap(after).await,
                Some(Resume::Replaying(start)) => self.replay_page(start).await,
                None => {}
            }
            if !self.ready.is_empty() || self.resume.is_some() {
                continue;
            }
            match self.rx.recv().await {
                Ok(e) => {
                    if let Some(id) = e.id {
                        if id <= self.sent_up_to {
                            continue;
                        }
                        self.sent_up_to = id;
                    }
                    if self.matcher.matches(&e) {
                        return Some(to_sse(&e));
                    }
                }
                Err(RecvError::Lagged(n)) => {
                    self.ready.push_back(resync_frame(&serde_json::json!({
                        "reason": "client fell behind", "missed": n, "after": self.sent_up_to,
                    })));
                    self.resume = Some(Resume::Replaying(None));
                }
                Err(RecvError::Closed) => return None,
            }
        }
    }

    /// Queues `resync` when a replay after `after` cannot be complete, then the replay. Two
    /// gaps: retention deleted events after `after` (the client gets what remains after it),
    /// or `after` is beyond every id this log has given (the store was restored from a backup:
    /// new events reuse those ids, so the client starts from the log's end instead of skipping
    /// them).
    async fn check_gap(&mut self, after: i64) {
        let marks = async {
            Ok::<_, sqlx::Error>((
                self.store.events_pruned_through().await?,
                self.store.last_event_id().await?,
            ))
        };
        let (pruned, last) = match marks.await {
            Ok(m) => m,
            Err(e) => {
                tracing::error!(error = %e, "cannot read the event log's bounds for a replay");
                self.resume = Some(Resume::Replaying(Some(after)));
                return;
            }
        };
        if after > last {
            self.ready.push_back(resync_frame(&serde_json::json!({
                "reason": "this id is newer than the event log (restored from a backup?)",
                "after": after,
                "last_event_id": last,
            })));
            self.sent_up_to = last;
            self.resume = Some(Resume::Replaying(None));
        } else if after < pruned {
            self.ready
                .push_back(resync_frame(&retention_gap(after, pruned)));
            self.resume = Some(Resume::Replaying(None));
        } else {
            // A retention pass during the replay may delete events before the replay reads
            // them: checked once it is done.
            self.resume = Some(Resume::Replaying(Some(after)));
        }
    }

    /// One page of persisted events after `sent_up_to`; the replay goes on while pages come.
    async fn replay_page(&mut self, start: Option<i64>) {
        let page = match self.store.events_after(self.sent_up_to, REPLAY_PAGE).await {
            Ok(p) => p,
            Err(e) => {
                tracing::error!(error = %e, "event replay failed");
                return;
            }
        };
        if page.is_empty() {
            if let Some(start) = start {
                if let Ok(pruned) = self.store.events_pruned_through().await {
                    if pruned > start {
                        self.ready
                            .push_back(resync_frame(&retention_gap(start, pruned)));
                    }
                }
            }
            return;
        }
        for row in page {
            let e = BusEvent::from(row);
            self.sent_up_to = e.id.unwrap_or(self.sent_up_to);
            if self.matcher.matches(&e) {
                self.ready.push_back(to_sse(&e));
            }
        }
        self.resume = Some(Resume::Replaying(start));
    }
}

fn retention_gap(after: i64, pruned: i64) -> serde_json::Value {
    serde_json::json!({
        "reason": "events after this id were deleted by retention",
        "after": after,
        "pruned_through": pruned,
    })
}
