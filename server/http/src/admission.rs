//! Who gets in, besides the role check (issue 23): a stop or a feed hold must be answered
//! whatever else is open.
//!
//! * Event streams have their own cap, below `max_connections`: a stream holds its connection
//!   for as long as it lasts, so the connections above the stream cap are always left for short
//!   requests. One token may hold only `max_event_streams_per_client` of them. A refused stream
//!   gets 503 (server cap) or 429 (client cap) `too_many_streams` and its connection is closed,
//!   so a refusal holds no slot either.
//! * One non-loopback address may hold `max_connections_per_client` connections (the accept
//!   loop asks [`Admission::open_connection`]). Loopback is not counted: every local process and
//!   a local reverse proxy share it, so a per-address cap there would pit the operator against
//!   whatever else runs on the machine.
//! * An address that keeps presenting wrong tokens is refused for a while: a token bucket of
//!   `max_auth_failures_per_minute` per address; while it is empty, that address's requests that
//!   carry a token get 429 `too_many_auth_failures` without being looked up (so a flood costs the
//!   database nothing). Per address, so an attacker elsewhere cannot lock the operator out;
//!   requests without a token (local callers on a loopback bind) are never affected.
//!
//! Counted for `/metrics`; refusals are logged at most once a second, with a count.

use crate::error::ApiError;
use axum::extract::ConnectInfo;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use fresa_core::config::EdgeLimits;
use fresa_plugin_api::quiet::Quiet;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::net::{IpAddr, Ipv6Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// What a refused event stream is told to wait: slots free only as other clients leave.
const STREAM_RETRY_SECS: u64 = 5;
/// Addresses whose failed token attempts are remembered; beyond it (a flood from very many
/// addresses) new ones share one bucket.
const MAX_TRACKED_ADDRESSES: usize = 4096;

pub struct Admission {
    limits: EdgeLimits,
    streams: Mutex<Streams>,
    connections: Mutex<HashMap<IpAddr, usize>>,
    failures: Mutex<Failures>,
    /// Refusal and failure warnings: at most one a second of each kind, with a count.
    log: Quiet,
    counters: Counters,
}

#[derive(Default)]
struct Streams {
    open: usize,
    per_client: HashMap<String, usize>,
    at_cap: bool,
}

#[derive(Default)]
struct Failures {
    peers: HashMap<IpAddr, Bucket>,
}

impl Failures {
    /// `peer`'s bucket; once [`MAX_TRACKED_ADDRESSES`] are tracked, a new address shares the
    /// overflow bucket.
    fn bucket(&mut self, peer: IpAddr) -> Option<&mut Bucket> {
        let key = if self.peers.contains_key(&peer) || self.peers.len() < MAX_TRACKED_ADDRESSES {
            peer
        } else {
            OVERFLOW
        };
        self.peers.get_mut(&key)
    }
}

/// Failed token attempts an address may still make: refills at `per_minute` a minute.
struct Bucket {
    allowance: f64,
    at: Instant,
    /// Whether "too many failed token attempts" was logged since it last had room.
    limited_logged: bool,
}

#[derive(Default)]
struct Counters {
    streams_refused_server: AtomicU64,
    streams_refused_client: AtomicU64,
    connections_refused: AtomicU64,
    connections_closed_at_cap: AtomicU64,
    auth_failures: AtomicU64,
    auth_rate_limited: AtomicU64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A JSON error with `Retry-After`; `close` also ends the connection after it.
#[derive(Debug)]
pub struct Refusal {
    error: ApiError,
    retry_after: u64,
    close: bool,
}

fn refusal(
    status: StatusCode,
    code: &'static str,
    message: String,
    retry_after: u64,
    close: bool,
) -> Refusal {
    Refusal {
        error: ApiError::new(status, code, message),
        retry_after,
        close,
    }
}

impl IntoResponse for Refusal {
    fn into_response(self) -> Response {
        let mut r = self.error.into_response();
        r.headers_mut()
            .insert(header::RETRY_AFTER, HeaderValue::from(self.retry_after));
        if self.close {
            r.headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
        r
    }
}

/// The address a request came from (set by the accept loop), as one form per address.
pub fn peer(req: &axum::extract::Request) -> Option<IpAddr> {
    let addr = match req.extensions().get::<Connection>() {
        Some(c) => c.peer(),
        None => req.extensions().get::<ConnectInfo<SocketAddr>>()?.0,
    };
    Some(addr.ip().to_canonical())
}

/// A connection as the accept loop tells each of its requests: who is at the other end, and
/// the connection's place under `max_connections` (a semaphore permit it holds while open).
/// An event stream trades that place for one under `max_event_streams`
/// ([`Connection::into_stream`]): a stream holds its connection for as long as it lasts, so
/// counting it under `max_connections` would let streams crowd out short requests such as a
/// stop, and would tie how many streams a server may serve to how many connections it keeps.
#[derive(Clone)]
pub struct Connection(Arc<Held>);

struct Held {
    peer: SocketAddr,
    permit: Mutex<tokio::sync::OwnedSemaphorePermit>,
    streams: Arc<tokio::sync::Semaphore>,
}

impl Connection {
    /// `permit`: the connection's place under `max_connections`; `streams`: the places under
    /// `max_event_streams`, as many as that.
    pub fn new(
        peer: SocketAddr,
        permit: tokio::sync::OwnedSemaphorePermit,
        streams: Arc<tokio::sync::Semaphore>,
    ) -> Connection {
        Connection(Arc::new(Held {
            peer,
            permit: Mutex::new(permit),
            streams,
        }))
    }

    pub fn peer(&self) -> SocketAddr {
        self.0.peer
    }

    /// Gives the connection's place under `max_connections` back for a stream's place, which
    /// it holds until it closes (the stream's answer closes the connection when it ends).
    /// Called once the stream was admitted ([`Admission::open_stream`] counts the same cap),
    /// so a place is free, except for the moment between a stream's end and its connection's
    /// close: then the connection keeps its old place.
    pub fn into_stream(&self) {
        if let Ok(p) = self.0.streams.clone().try_acquire_owned() {
            *lock(&self.0.permit) = p;
        }
    }
}

impl Admission {
    pub fn new(limits: &EdgeLimits) -> Arc<Admission> {
        Arc::new(Admission {
            limits: limits.clone(),
            streams: Mutex::default(),
            connections: Mutex::default(),
            failures: Mutex::default(),
            log: Quiet::new(Duration::from_secs(1)),
            counters: Counters::default(),
        })
    }

    // ---- event streams ----

    /// A slot for one event stream of `client` (a token's name; `None`: a tokenless local
    /// caller, counted only against the server's cap), or the refusal to answer with.
    pub fn open_stream(self: &Arc<Self>, client: Option<&str>) -> Result<StreamSlot, Refusal> {
        let cap = self.limits.max_event_streams;
        let per_client = self.limits.max_event_streams_per_client;
        let mut s = lock(&self.streams);
        if s.open >= cap {
            self.counters
                .streams_refused_server
                .fetch_add(1, Ordering::Relaxed);
            if !s.at_cap {
                s.at_cap = true;
                tracing::warn!(
                    "event stream limit reached: {cap} streams open (max_event_streams); \
                     new ones get 503 too_many_streams"
                );
            }
            return Err(refusal(
                StatusCode::SERVICE_UNAVAILABLE,
                "too_many_streams",
                format!(
                    "{cap} event streams are open, the most this server keeps \
                     (max_event_streams = {cap}); retry later"
                ),
                STREAM_RETRY_SECS,
                true,
            ));
        }
        if let Some(name) = client {
            let held = s.per_client.get(name).copied().unwrap_or(0);
            if held >= per_client {
                self.counters
                    .streams_refused_client
                    .fetch_add(1, Ordering::Relaxed);
                if let Some(line) = self.log.admit("stream per client", || {
                    format!(
                        "event stream refused: token {name:?} holds {held} \
                         (max_event_streams_per_client)"
                    )
                }) {
                    tracing::warn!("{line}");
                }
                return Err(refusal(
                    StatusCode::TOO_MANY_REQUESTS,
                    "too_many_streams",
                    format!(
                        "token {name:?} already holds {held} event streams \
                         (max_event_streams_per_client = {per_client}); close one first"
                    ),
                    STREAM_RETRY_SECS,
                    true,
                ));
            }
            s.per_client.insert(name.to_string(), held + 1);
        }
        s.open += 1;
        Ok(StreamSlot {
            admission: self.clone(),
            client: client.map(str::to_string),
        })
    }

    fn close_stream(&self, client: Option<&str>) {
        let cap = self.limits.max_event_streams;
        let mut s = lock(&self.streams);
        s.open = s.open.saturating_sub(1);
        if let Some(name) = client {
            if let Some(n) = s.per_client.get_mut(name) {
                *n -= 1;
                if *n == 0 {
                    s.per_client.remove(name);
                }
            }
        }
        // Cleared once a tenth is free, so a busy cap is not logged on every close.
        if s.at_cap && s.open + (cap / 10).max(1) <= cap {
            s.at_cap = false;
            tracing::info!("event stream limit cleared: accepting event streams again");
        }
    }

    // ---- connections ----

    /// A slot for one connection from `peer`, or the canned answer to refuse it with (the
    /// request has not been read: the accept loop writes it and closes).
    pub fn open_connection(self: &Arc<Self>, peer: IpAddr) -> Result<ConnectionSlot, Vec<u8>> {
        let peer = peer.to_canonical();
        if peer.is_loopback() {
            return Ok(ConnectionSlot {
                admission: self.clone(),
                peer: None,
            });
        }
        let cap = self.limits.max_connections_per_client;
        let mut c = lock(&self.connections);
        let held = c.entry(peer).or_insert(0);
        if *held >= cap {
            drop(c);
            self.counters
                .connections_refused
                .fetch_add(1, Ordering::Relaxed);
            if let Some(line) = self.log.admit("connections per client", || {
                format!(
                    "connection from {peer} refused: it holds {cap} (max_connections_per_client)"
                )
            }) {
                tracing::warn!("{line}");
            }
            return Err(canned_refusal(
                "429 Too Many Requests",
                "too_many_connections",
                &format!(
                    "{peer} already holds {cap} connections \
                     (max_connections_per_client = {cap}); close one first"
                ),
                1,
            ));
        }
        *held += 1;
        Ok(ConnectionSlot {
            admission: self.clone(),
            peer: Some(peer),
        })
    }

    fn close_connection(&self, peer: IpAddr) {
        let mut c = lock(&self.connections);
        if let Some(n) = c.get_mut(&peer) {
            *n -= 1;
            if *n == 0 {
                c.remove(&peer);
            }
        }
    }

    /// The accept loop closed a connection with no request in progress to make room at
    /// `max_connections`.
    pub fn count_closed_at_cap(&self) {
        self.counters
            .connections_closed_at_cap
            .fetch_add(1, Ordering::Relaxed);
    }

    // ---- failed tokens ----

    fn per_second(&self) -> f64 {
        f64::from(self.limits.max_auth_failures_per_minute) / 60.0
    }

    /// Whether a token from `peer` may be checked now; else the 429 to answer with.
    pub fn may_check_token(&self, peer: Option<IpAddr>) -> Result<(), Refusal> {
        let Some(peer) = peer else { return Ok(()) };
        let per_minute = self.limits.max_auth_failures_per_minute;
        let rate = self.per_second();
        let mut f = lock(&self.failures);
        let Some(b) = f.bucket(peer) else {
            return Ok(());
        };
        b.refill(f64::from(per_minute), rate);
        if b.allowance >= 1.0 {
            b.limited_logged = false;
            return Ok(());
        }
        self.counters
            .auth_rate_limited
            .fetch_add(1, Ordering::Relaxed);
        let retry = ((1.0 - b.allowance) / rate).ceil().max(1.0) as u64;
        Err(refusal(
            StatusCode::TOO_MANY_REQUESTS,
            "too_many_auth_failures",
            format!(
                "too many failed token attempts from {peer} (max_auth_failures_per_minute = \
                 {per_minute}); its tokens are not checked for {retry} s"
            ),
            retry,
            false,
        ))
    }

    /// Whether `peer` presented no wrong token lately (it has no allowance being counted
    /// down): only then may a read skip [`Self::may_check_token`] and the database. Counts
    /// nothing, so the request that then takes the full check is counted once.
    pub fn no_failed_tokens(&self, peer: Option<IpAddr>) -> bool {
        let Some(peer) = peer else { return true };
        lock(&self.failures).bucket(peer).is_none()
    }

    /// A wrong token (or node secret) from `peer`: counted, logged without the token, and
    /// taken from the address's allowance.
    pub fn token_failed(&self, peer: Option<IpAddr>, code: &str) {
        self.counters.auth_failures.fetch_add(1, Ordering::Relaxed);
        let per_minute = self.limits.max_auth_failures_per_minute;
        let cap = f64::from(per_minute);
        let rate = self.per_second();
        let mut f = lock(&self.failures);
        let from = peer.map_or_else(|| "an unknown address".to_string(), |p| p.to_string());
        if let Some(line) = self.log.admit("token failed", || {
            format!("failed token attempt from {from}: {code}")
        }) {
            tracing::warn!("{line}");
        }
        let Some(peer) = peer else { return };
        if !f.peers.contains_key(&peer) && f.peers.len() >= MAX_TRACKED_ADDRESSES {
            // A full bucket says nothing: forget those first.
            f.peers.retain(|_, b| {
                b.refill(cap, rate);
                b.allowance < cap
            });
        }
        let key = if f.peers.contains_key(&peer) || f.peers.len() < MAX_TRACKED_ADDRESSES {
            peer
        } else {
            OVERFLOW
        };
        let b = f.peers.entry(key).or_insert_with(|| Bucket {
            allowance: cap,
            at: Instant::now(),
            limited_logged: false,
        });
        b.refill(cap, rate);
        b.allowance = (b.allowance - 1.0).max(0.0);
        if b.allowance < 1.0 && !b.limited_logged {
            b.limited_logged = true;
            tracing::warn!(
                "too many failed token attempts from {peer}: more than {per_minute} a minute \
                 (max_auth_failures_per_minute); its requests with a token get 429 \
                 too_many_auth_failures until it slows down"
            );
        }
    }

    // ---- metrics ----

    /// The Prometheus lines for `/metrics`.
    pub fn prometheus(&self) -> String {
        let c = &self.counters;
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let open = lock(&self.streams).open;
        let mut out = String::new();
        let _ = writeln!(
            out,
            "# HELP fresa_event_streams Event streams open.\n# TYPE fresa_event_streams gauge\n\
             fresa_event_streams {open}\n\
             # HELP fresa_event_streams_refused_total Event streams refused with too_many_streams, \
             at max_event_streams (limit=\"server\") or max_event_streams_per_client \
             (limit=\"client\").\n# TYPE fresa_event_streams_refused_total counter\n\
             fresa_event_streams_refused_total{{limit=\"server\"}} {}\n\
             fresa_event_streams_refused_total{{limit=\"client\"}} {}\n\
             # HELP fresa_connections_refused_total Connections refused at \
             max_connections_per_client.\n# TYPE fresa_connections_refused_total counter\n\
             fresa_connections_refused_total {}\n\
             # HELP fresa_connections_closed_at_cap_total Connections with no request in \
             progress closed to make room for a new one at max_connections.\n\
             # TYPE fresa_connections_closed_at_cap_total counter\n\
             fresa_connections_closed_at_cap_total {}\n\
             # HELP fresa_auth_failures_total Requests refused for a wrong token or node secret.\n\
             # TYPE fresa_auth_failures_total counter\nfresa_auth_failures_total {}\n\
             # HELP fresa_auth_rate_limited_total Requests with a token refused unchecked \
             (too_many_auth_failures).\n# TYPE fresa_auth_rate_limited_total counter\n\
             fresa_auth_rate_limited_total {}",
            get(&c.streams_refused_server),
            get(&c.streams_refused_client),
            get(&c.connections_refused),
            get(&c.connections_closed_at_cap),
            get(&c.auth_failures),
            get(&c.auth_rate_limited),
        );
        out
    }
}

/// The bucket new addresses share once `MAX_TRACKED_ADDRESSES` are remembered.
const OVERFLOW: IpAddr = IpAddr::V6(Ipv6Addr::UNSPECIFIED);

impl Bucket {
    fn refill(&mut self, cap: f64, per_second: f64) {
        let now = Instant::now();
        let gained = now.duration_since(self.at).as_secs_f64() * per_second;
        self.allowance = (self.allowance + gained).min(cap);
        self.at = now;
    }
}

/// A complete HTTP/1.1 answer with a JSON error, for a connection refused before its request
/// was read.
fn canned_refusal(status: &str, code: &str, message: &str, retry_after: u64) -> Vec<u8> {
    let body = serde_json::json!({"code": code, "message": message}).to_string();
    format!(
        "HTTP/1.1 {status}\r\ncontent-type: application/json\r\nretry-after: {retry_after}\r\n\
         connection: close\r\ncontent-length: {}\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
}

/// Held by an open event stream; its slot is free again when the stream is dropped.
pub struct StreamSlot {
    admission: Arc<Admission>,
    client: Option<String>,
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        self.admission.close_stream(self.client.as_deref());
    }
}

/// Held by an open connection.
pub struct ConnectionSlot {
    admission: Arc<Admission>,
    peer: Option<IpAddr>,
}

impl Drop for ConnectionSlot {
    fn drop(&mut self) {
        if let Some(p) = self.peer {
            self.admission.close_connection(p);
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn limits() -> EdgeLimits {
        EdgeLimits {
            max_event_streams: 3,
            max_event_streams_per_client: 2,
            max_connections_per_client: 2,
            max_auth_failures_per_minute: 3,
        }
    }

    fn code(r: Refusal) -> (u16, Option<String>) {
        let r = r.into_response();
        let retry = r
            .headers()
            .get(header::RETRY_AFTER)
            .map(|v| v.to_str().unwrap().to_string());
        (r.status().as_u16(), retry)
    }

    #[test]
    fn streams_have_a_server_cap_and_a_per_token_cap() {
        let a = Admission::new(&limits());
        let t1 = a.open_stream(Some("t")).unwrap();
        let _t2 = a.open_stream(Some("t")).unwrap();
        let over = a.open_stream(Some("t")).err().unwrap();
        assert_eq!(code(over), (429, Some("5".into())));
        let local = a.open_stream(None).unwrap();
        let full = a.open_stream(None).err().unwrap();
        assert_eq!(code(full).0, 503);
        drop(t1);
        let _t3 = a.open_stream(Some("t")).unwrap();
        drop(local);
        assert!(a.prometheus().contains("fresa_event_streams 2\n"));
        assert!(a
            .prometheus()
            .contains("fresa_event_streams_refused_total{limit=\"client\"} 1"));
    }

    #[test]
    fn connections_are_capped_per_address_but_not_on_loopback() {
        let a = Admission::new(&limits());
        let lan: IpAddr = "192.168.1.5".parse().unwrap();
        let c1 = a.open_connection(lan).unwrap();
        let _c2 = a.open_connection(lan).unwrap();
        let refused = String::from_utf8(a.open_connection(lan).err().unwrap()).unwrap();
        assert!(
            refused.starts_with("HTTP/1.1 429") && refused.contains("too_many_connections"),
            "{refused}"
        );
        // The IPv4-mapped form of the same address is the same client.
        let mapped: IpAddr = "::ffff:192.168.1.5".parse().unwrap();
        assert!(a.open_connection(mapped).is_err());
        drop(c1);
        let _c3 = a.open_connection(mapped).unwrap();
        let other: IpAddr = "192.168.1.6".parse().unwrap();
        let _o = a.open_connection(other).unwrap();
        let local: Vec<_> = (0..10)
            .map(|_| a.open_connection("127.0.0.1".parse().unwrap()).unwrap())
            .collect();
        assert_eq!(local.len(), 10);
    }

    #[test]
    fn failed_tokens_limit_their_address_only() {
        let a = Admission::new(&limits());
        let bad: IpAddr = "10.0.0.9".parse().unwrap();
        let good: IpAddr = "10.0.0.1".parse().unwrap();
        for _ in 0..3 {
            assert!(a.may_check_token(Some(bad)).is_ok());
            a.token_failed(Some(bad), "invalid_token");
        }
        let (status, retry) = code(a.may_check_token(Some(bad)).err().unwrap());
        assert_eq!(status, 429);
        // 3 a minute: one more every 20 s.
        let retry: u64 = retry.unwrap().parse().unwrap();
        assert!((1..=20).contains(&retry), "{retry}");
        assert!(a.may_check_token(Some(good)).is_ok());
        assert!(a.may_check_token(None).is_ok());
        // Only an address without failures may skip the check (a read's remembered token),
        // and asking counts nothing.
        assert!(!a.no_failed_tokens(Some(bad)));
        assert!(a.no_failed_tokens(Some(good)));
        assert!(a.no_failed_tokens(None));
        let m = a.prometheus();
        assert!(m.contains("fresa_auth_failures_total 3\n"), "{m}");
        assert!(m.contains("fresa_auth_rate_limited_total 1"), "{m}");
    }

    #[test]
    fn very_many_addresses_share_one_bucket_beyond_the_tracked_ones() {
        let a = Admission::new(&limits());
        for i in 0..MAX_TRACKED_ADDRESSES as u32 {
            a.token_failed(Some(IpAddr::from(i.to_be_bytes())), "invalid_token");
        }
        assert_eq!(lock(&a.failures).peers.len(), MAX_TRACKED_ADDRESSES);
        let late = |i: u32| Some(IpAddr::from((0x0a00_0000 + i).to_be_bytes()));
        for i in 0..3 {
            a.token_failed(late(i), "invalid_token");
        }
        assert!(lock(&a.failures).peers.len() <= MAX_TRACKED_ADDRESSES + 1);
        assert!(
            a.may_check_token(late(99)).is_err(),
            "the shared bucket is empty"
        );
    }
}
