//! `fresa serve`: bind, start, notify systemd, serve until SIGTERM/Ctrl-C (or, as a Windows
//! service, the service manager's stop), shut down cleanly.
//!
//! Shutdown order: motion first. On the signal every machine's gate closes (no new motion),
//! active runs become `interrupted` (resumable) and each backend is told to stop, on its urgent
//! lane, bounded. Only then do open connections get a bounded grace period to finish; whatever
//! is still open after it is dropped. So a slow client cannot keep a machine cutting, and the
//! process always exits well inside systemd's `TimeoutStopSec` (20 s in the shipped unit).

use axum::body::Body;
use fresa_core::config::Settings;
use fresa_core::App;
use fresa_http::admission::{Admission, ConnectionSlot};
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::TokioIo;
use std::collections::BTreeMap;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

/// At most this long for the backends to confirm they stopped.
const STOP_MOTION_LIMIT: Duration = Duration::from_secs(5);

/// Serves until `shutdown` completes, then stops motion and drains. `ready` is called once the
/// server answers requests (bound, migrated, plugins loaded), with the address it listens on.
pub async fn run(
    settings: Settings,
    shutdown: impl std::future::Future<Output = ()>,
    ready: impl FnOnce(std::net::SocketAddr),
) -> Result<(), Box<dyn std::error::Error>> {
    if let Some(f) = &settings.config_file {
        tracing::info!(file = %f.display(), "config file read");
    }
    tracing::info!(data_dir = %settings.data_dir.display(), "data directory");
    for w in &settings.warnings {
        tracing::warn!("config: {w}");
    }
    let listener =
        bind(settings.listen).map_err(|e| format!("cannot listen on {}: {e}", settings.listen))?;
    let bound = listener.local_addr()?;
    let admission = fresa_http::admission::Admission::new(&settings.edges);
    // The routing table needs nothing from the store: built while the store opens (see
    // `fresa_http::Routes`).
    let routes = tokio::task::spawn_blocking({
        let admission = admission.clone();
        move || {
            let routes = fresa_http::routes(Some(admission), after_describing_the_api);
            release_thread_garbage();
            routes
        }
    });
    // A stop while starting ends the start at once: a database that does not answer holds it
    // for the pool's timeout (10 s), and the signal, heard from the first moment, must not wait
    // for that. Nothing has moved yet; once the machines exist, motion is stopped first.
    tokio::pin!(shutdown);
    let app = tokio::select! {
        app = App::start(settings) => app?,
        () = &mut shutdown => {
            tracing::info!("stopped while starting");
            return Ok(());
        }
    };
    let limit = STOP_MOTION_LIMIT.min(app.settings.plugin_call_timeout);
    let finished = tokio::select! {
        finished = async {
            let heartbeat = fresa_core::nodes::start(&app, bound).await?;
            let routes = routes
                .await
                .map_err(|e| format!("building the HTTP routes failed (a bug): {e}"))?;
            Ok::<_, Box<dyn std::error::Error + Send + Sync>>((heartbeat, routes))
        } => Some(finished),
        () = &mut shutdown => None,
    };
    let (heartbeat, routes) = match finished {
        Some(Ok(finished)) => finished,
        // Stopped, or the node could not register, or the routes could not be built: the
        // machines exist now, so their backends are told to stop before the process ends.
        not_started => {
            tracing::info!("the start did not finish: stopping all motion");
            app.stop_motion(limit).await;
            app.stop_rest(limit).await;
            return match not_started {
                Some(Err(e)) => Err(e as Box<dyn std::error::Error>),
                _ => Ok(()),
            };
        }
    };
    let router = fresa_http::service(app.clone(), admission.clone(), routes);
    let integrations = fresa_integrations::start(app.clone());
    // This exact phrase is what scripts and tests wait for.
    tracing::info!("listening on http://{bound}");
    if !app.settings.loopback_only() {
        tracing::info!("not loopback-only: every request needs an API token");
    }
    systemd::ready();
    systemd::spawn_watchdog(app.clone());
    // Streams hold connections outside `max_connections` (see `admission::Connection`).
    warn_if_too_few_files(app.settings.max_connections + app.settings.edges.max_event_streams);
    let drain = tokio_util::sync::CancellationToken::new();
    let limits = ConnLimits::from(&app.settings);
    let mut server = tokio::spawn(accept_loop(
        listener,
        router,
        admission,
        limits,
        drain.clone(),
    ));
    ready(bound);
    // The start is done: the code only it ran need not stay mapped (see `resident`).
    #[cfg(target_os = "linux")]
    tokio::task::spawn_blocking(|| {
        crate::resident::unmap_pages_used_once("start", crate::resident::Files::All);
    });
    tokio::select! {
        () = &mut shutdown => {}
        r = &mut server => {
            // The server ended on its own (an accept loop error): still stop motion.
            tracing::error!(result = ?r, "HTTP server ended");
        }
    }
    systemd::stopping();
    // First: it could otherwise start a machine moved here while motion is being stopped.
    heartbeat.stop().await;
    tracing::info!("shutting down: stopping all motion");
    app.stop_motion(limit).await;
    let grace = app.settings.shutdown_grace;
    tracing::info!("motion stopped");
    tracing::info!("draining connections for at most {grace:?}");
    drain.cancel();
    app.stop_rest(limit).await;
    // Shutdown was signalled by `stop_rest`: the MQTT bridge says it is going offline.
    integrations.join(Duration::from_secs(2)).await;
    // The accept loop ends once every connection has closed (or is aborted here).
    if !server.is_finished() && tokio::time::timeout(grace, &mut server).await.is_err() {
        tracing::warn!("connections still open after {grace:?}; closing them");
        server.abort();
    }
    tracing::info!("stopped");
    Ok(())
}

/// systemd's `Type=notify` readiness and watchdog (Linux; nothing elsewhere).
#[cfg(unix)]
mod systemd {
    use std::time::Duration;

    pub fn ready() {
        let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Ready]);
    }

    pub fn stopping() {
        let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    }

    /// Pings the watchdog only while the database answers, so a wedged store gets us restarted.
    pub fn spawn_watchdog(app: fresa_core::SharedApp) {
        let mut usec = 0u64;
        if !sd_notify::watchdog_enabled(false, &mut usec) || usec == 0 {
            return;
        }
        let period = Duration::from_micros(usec / 2);
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            loop {
                tick.tick().await;
                match tokio::time::timeout(period, app.store.ping()).await {
                    Ok(Ok(())) => {
                        let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
                    }
                    _ => tracing::error!("database did not answer; withholding the watchdog ping"),
                }
            }
        });
    }
}

#[cfg(not(unix))]
mod systemd {
    pub fn ready() {}
    pub fn stopping() {}
    pub fn spawn_watchdog(_app: fresa_core::SharedApp) {}
}

/// Console use: SIGTERM, Ctrl-C or SIGHUP (Linux); Ctrl-C, Ctrl-Break or closing the console
/// window (Windows). SIGHUP (the terminal or SSH session that started the server went away)
/// used to end the process by its default action, without stopping motion (a Mach3 PC goes on
/// cutting); it now takes the same path as SIGTERM, unless it was ignored when the server
/// started (`nohup`), which then still holds.
///
/// The listeners are registered when this is called (inside the runtime), not when the future
/// is first polled: `run` polls it only once the server answers, and a SIGTERM sent right
/// after the first answer (a service manager's stop, a script's `kill`) either found no
/// handler and killed the process without stopping motion, or landed between tokio's handler
/// and its first listener and was lost, leaving the server running.
pub fn wait_for_signal() -> impl std::future::Future<Output = ()> {
    #[cfg(unix)]
    let (first, second, third) = {
        use tokio::signal::unix::{signal, SignalKind};
        (
            signal(SignalKind::interrupt()).ok(),
            signal(SignalKind::terminate()).ok(),
            (!hangup_ignored())
                .then(|| signal(SignalKind::hangup()).ok())
                .flatten(),
        )
    };
    #[cfg(windows)]
    let (first, second, third) = {
        use tokio::signal::windows;
        // Windows gives a closing console about 5 s: enough to stop motion, not to drain.
        (
            windows::ctrl_c().ok(),
            windows::ctrl_break().ok(),
            windows::ctrl_close().ok(),
        )
    };
    async move {
        // A listener that could not be registered never fires; the others still do.
        macro_rules! recv {
            ($s:expr) => {
                async {
                    match $s {
                        Some(mut s) => {
                            s.recv().await;
                        }
                        None => std::future::pending::<()>().await,
                    }
                }
            };
        }
        #[cfg(unix)]
        let signal = tokio::select! {
            _ = recv!(first) => "SIGINT",
            _ = recv!(second) => "SIGTERM",
            _ = recv!(third) => "SIGHUP",
        };
        #[cfg(windows)]
        let signal = tokio::select! {
            _ = recv!(first) => "Ctrl-C",
            _ = recv!(second) => "Ctrl-Break",
            _ = recv!(third) => "console closed",
        };
        #[cfg(any(unix, windows))]
        tracing::info!(signal, "stop requested");
        #[cfg(not(any(unix, windows)))]
        std::future::pending::<()>().await
    }
}

/// Whether SIGHUP is ignored (inherited from `nohup` or a parent that chose so).
#[cfg(unix)]
fn hangup_ignored() -> bool {
    // SAFETY: reads this process's disposition of one signal (no new action is given) into a
    // zeroed `sigaction`, a plain C struct.
    unsafe {
        let mut old: libc::sigaction = std::mem::zeroed();
        libc::sigaction(libc::SIGHUP, std::ptr::null(), &mut old) == 0
            && old.sa_sigaction == libc::SIG_IGN
    }
}

/// Connections the kernel queues for us while we are at `max_connections` (the default, 128, is
/// soon full; past it new clients' SYNs are dropped and they retry only after seconds).
const LISTEN_BACKLOG: u32 = 1024;

/// Gives the calling thread's freed pages back to the system, where the daemon's allocator keeps
/// them (mimalloc on Linux, see `alloc`); the system allocators elsewhere need nothing.
fn release_thread_garbage() {
    #[cfg(all(target_os = "linux", feature = "mimalloc"))]
    crate::alloc::release_thread_garbage();
}

/// Run on the thread that described the API for the OpenAPI document's first request, once the
/// document is serialised. Describing builds the routing table again, as only the start does
/// otherwise: its garbage goes back to the system and its code need not stay mapped. Only the
/// binary's: machines may be moving by now, and a plugin's loop must not fault its code back in.
fn after_describing_the_api() {
    release_thread_garbage();
    #[cfg(target_os = "linux")]
    crate::resident::unmap_pages_used_once("describing the API", crate::resident::Files::Binary);
}

fn bind(addr: std::net::SocketAddr) -> io::Result<TcpListener> {
    let socket = if addr.is_ipv4() {
        tokio::net::TcpSocket::new_v4()?
    } else {
        tokio::net::TcpSocket::new_v6()?
    };
    // As `TcpListener::bind` does: a restart may bind while old connections are in TIME_WAIT.
    #[cfg(unix)]
    socket.set_reuseaddr(true)?;
    socket.bind(addr)?;
    socket.listen(LISTEN_BACKLOG)
}

/// Descriptors the server needs besides client connections (database, plugins, pendants, ...).
const OTHER_FILES: u64 = 128;

/// Says so at start-up when `max_connections` and `max_event_streams` (given added up) cannot
/// all be open under the process's soft limit on open files: the caps would then not prevent
/// EMFILE.
fn warn_if_too_few_files(max_connections: usize) {
    #[cfg(target_os = "linux")]
    {
        let Ok(limits) = std::fs::read_to_string("/proc/self/limits") else {
            return;
        };
        let soft = limits
            .lines()
            .find(|l| l.starts_with("Max open files"))
            .and_then(|l| l.split_whitespace().nth(3))
            .and_then(|v| v.parse::<u64>().ok());
        if let Some(soft) = soft {
            if max_connections as u64 + OTHER_FILES > soft {
                tracing::warn!(
                    "max_connections plus max_event_streams = {max_connections} plus about \
                     {OTHER_FILES} other files exceeds the open-file limit of {soft}: raise \
                     LimitNOFILE (ulimit -n) or lower max_connections or max_event_streams"
                );
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (max_connections, OTHER_FILES);
}

/// The connection settings the accept loop needs.
#[derive(Debug, Clone, Copy)]
struct ConnLimits {
    header_read_timeout: Duration,
    idle_timeout: Duration,
    max_connections: usize,
    max_event_streams: usize,
}

impl From<&Settings> for ConnLimits {
    fn from(s: &Settings) -> Self {
        ConnLimits {
            header_read_timeout: s.header_read_timeout,
            idle_timeout: s.idle_timeout,
            max_connections: s.max_connections,
            max_event_streams: s.edges.max_event_streams,
        }
    }
}

/// Accepts connections until `drain` is cancelled, then waits for the open ones to finish.
///
/// Each connection holds a permit. At the cap a new client is still accepted (one at a time),
/// and the connection that has been open longest with no request in progress (one that sends
/// nothing, half a head, or sits idle between requests) is closed to make room for it; while
/// every connection has a request in progress (event streams are capped below the cap, see
/// `fresa_http::admission`), further clients wait in the kernel's listen backlog (costing us no
/// file descriptor). So a slowloris flood cannot keep a stop out for a whole header read or
/// idle timeout: a new client's head usually arrives with it, long before the flood has closed
/// every connection older than it.
async fn accept_loop(
    listener: TcpListener,
    router: fresa_http::Service,
    admission: Arc<Admission>,
    limits: ConnLimits,
    drain: CancellationToken,
) {
    let max = limits.max_connections;
    let permits = Arc::new(Semaphore::new(max));
    // The places of connections that carry an event stream (`admission::Connection`).
    let stream_places = limits.max_event_streams;
    let streams = Arc::new(Semaphore::new(stream_places));
    let lingering = Arc::new(Semaphore::new(MAX_LINGERING_REFUSALS));
    // HTTP/1 only, with hyper's own HTTP/1 connection: hyper-util's `auto` would first wait for
    // a 24-byte HTTP/2 preface (a wait the header read timeout does not cover), and even with
    // `http1_only` it wraps every connection and read in its version sniffing.
    // No header read timeout of hyper's: it arms a timer for every request head (a boxed sleep
    // put into and taken out of the timer wheel, and an extra read after each response: about
    // 1,200 instructions of a 14,500-instruction status poll). The head check below enforces
    // `header_read_timeout` from the connections' counters instead.
    let mut builder = http1::Builder::new();
    builder.header_read_timeout(None::<Duration>);
    let builder = Arc::new(builder);
    let mut errors = AcceptErrors::default();
    let mut permit: Option<OwnedSemaphorePermit> = None;
    // Under a flood every closed connection frees one permit that is taken again at once; the
    // cap only counts as cleared once a tenth of it is free, so the log says it once each way.
    let clear_at = (max / 10).max(1);
    let mut at_cap = false;
    let open = OpenConnections::default();
    // Ends with this loop, also if the loop is aborted at the end of the shutdown grace.
    let _idle_checks = tokio_util::task::AbortOnDropHandle::new(tokio::spawn(
        open.clone().close_idle_every(limits.idle_timeout),
    ));
    let _head_checks = tokio_util::task::AbortOnDropHandle::new(tokio::spawn(
        open.clone()
            .close_slow_heads_every(limits.header_read_timeout),
    ));
    let start = |stream: TcpStream, peer, (permit, slot)| {
        let _ = stream.set_nodelay(true);
        tokio::spawn(serve_connection(
            builder.clone(),
            stream,
            router.clone(),
            (
                fresa_http::admission::Connection::new(peer, permit, streams.clone()),
                slot,
                open.register(),
            ),
        ));
    };
    loop {
        if at_cap && permits.available_permits() + usize::from(permit.is_some()) >= clear_at {
            at_cap = false;
            tracing::info!("connection limit cleared: accepting connections again");
        }
        let free = match permit.take() {
            Some(p) => Ok(p),
            None => permits.clone().try_acquire_owned(),
        };
        let Ok(p) = free else {
            if !at_cap {
                at_cap = true;
                tracing::warn!(
                    "connection limit reached: {max} connections open (max_connections); \
                     a new one takes the place of the oldest with no request in progress, \
                     or waits in the listen backlog"
                );
            }
            let accepted = tokio::select! {
                p = permits.clone().acquire_owned() => {
                    // The semaphore is never closed, so this is always a permit.
                    let Ok(p) = p else { break };
                    permit = Some(p);
                    continue;
                }
                r = listener.accept() => r,
                _ = drain.cancelled() => break,
            };
            let (stream, peer) = match accepted {
                Ok(a) => a,
                Err(e) => {
                    if !accept_failed(&e, &mut errors, &drain).await {
                        break;
                    }
                    continue;
                }
            };
            let slot = match admission.open_connection(peer.ip()) {
                Ok(slot) => slot,
                Err(answer) => {
                    refuse(stream, answer, &lingering);
                    continue;
                }
            };
            // Room for it: that connection's permit comes back once its task has ended.
            if open.close_oldest_quiet() {
                admission.count_closed_at_cap();
            }
            let p = tokio::select! {
                p = permits.clone().acquire_owned() => p,
                _ = drain.cancelled() => break,
            };
            let Ok(p) = p else { break };
            start(stream, peer, (p, slot));
            continue;
        };
        let accepted = tokio::select! {
            r = listener.accept() => r,
            _ = drain.cancelled() => break,
            // Wakes now and then while at the cap, to say so once it has cleared.
            _ = tokio::time::sleep(Duration::from_secs(1)), if at_cap => {
                permit = Some(p);
                continue;
            }
        };
        match accepted {
            Ok((stream, peer)) => match admission.open_connection(peer.ip()) {
                Ok(slot) => start(stream, peer, (p, slot)),
                Err(answer) => {
                    // Its permit goes straight back: a refusal holds no connection slot.
                    permit = Some(p);
                    refuse(stream, answer, &lingering);
                }
            },
            Err(e) => {
                permit = Some(p);
                if !accept_failed(&e, &mut errors, &drain).await {
                    break;
                }
            }
        }
    }
    // New connections are refused from here on; the open ones finish what they are answering.
    drop(listener);
    open.drain();
    drop(permit);
    // Every open connection holds a permit, of one cap or the other: all of them back means
    // all closed.
    let _ = permits.acquire_many(max as u32).await;
    let _ = streams.acquire_many(stream_places as u32).await;
}

/// Refused connections (`max_connections_per_client`) being answered at once; beyond it a
/// refused connection is closed without an answer.
const MAX_LINGERING_REFUSALS: usize = 32;
/// How long a refused connection is kept to deliver its answer.
const REFUSAL_LINGER: Duration = Duration::from_secs(1);

/// Answers a connection refused before its request was read, then closes it: the answer is
/// written, our side shut, and what the client sends read away (briefly) so that closing does
/// not reset the connection before the client has read the answer.
fn refuse(stream: TcpStream, answer: Vec<u8>, lingering: &Arc<Semaphore>) {
    let Ok(permit) = lingering.clone().try_acquire_owned() else {
        return;
    };
    tokio::spawn(async move {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let _permit = permit;
        let mut stream = stream;
        let _ = tokio::time::timeout(REFUSAL_LINGER, async {
            stream.write_all(&answer).await?;
            stream.shutdown().await?;
            let mut buf = [0u8; 1024];
            while stream.read(&mut buf).await? > 0 {}
            Ok::<_, io::Error>(())
        })
        .await;
    });
}

/// Logs an accept error and backs off if accepting again at once would fail again; false if
/// the server is draining.
async fn accept_failed(
    e: &io::Error,
    errors: &mut AcceptErrors,
    drain: &CancellationToken,
) -> bool {
    errors.log(e);
    // Out of descriptors or memory: accepting again at once would fail again and spin; give
    // the open connections a moment to close. A connection that died in the backlog is not our
    // problem, so carry on at once.
    if matches!(
        e.kind(),
        io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::Interrupted
    ) {
        return true;
    }
    tokio::select! {
        _ = tokio::time::sleep(ACCEPT_BACKOFF) => true,
        _ = drain.cancelled() => false,
    }
}

/// How long to wait before accepting again after an accept error such as EMFILE.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);

/// Logs accept errors at most once a second, counting the ones it left out.
#[derive(Default)]
struct AcceptErrors {
    last: Option<Instant>,
    suppressed: u64,
}

impl AcceptErrors {
    fn log(&mut self, e: &io::Error) {
        let now = Instant::now();
        if self
            .last
            .is_some_and(|t| now.duration_since(t) < Duration::from_secs(1))
        {
            self.suppressed += 1;
            return;
        }
        let more = std::mem::take(&mut self.suppressed);
        if more > 0 {
            tracing::error!("accept error: {e} ({more} more in the last second)");
        } else {
            tracing::error!("accept error: {e}");
        }
        self.last = Some(now);
    }
}

/// Serves one connection until it ends or the accept loop orders it to: drain (finish the
/// request in progress, then close) or close now (at the cap, or idle: see
/// [`OpenConnections::close_idle`], or no request head in time:
/// [`OpenConnections::close_slow_heads`]).
async fn serve_connection(
    builder: Arc<http1::Builder>,
    stream: TcpStream,
    router: fresa_http::Service,
    held: (
        fresa_http::admission::Connection,
        ConnectionSlot,
        OpenConnection,
    ),
) {
    // Held until the connection ends: its place, its address's count, its entry in the list.
    let (connection, _slot, me) = held;
    let io = TokioIo::new(Tracked {
        inner: stream,
        activity: me.activity.clone(),
    });
    let in_flight = me.activity.clone();
    let service = hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
        let router = router.clone();
        let guard = InFlight::enter(in_flight.clone());
        let connection = connection.clone();
        async move {
            let mut req = req.map(axum::body::Body::new);
            // Who is calling, for the per-address limits, and the connection's place under the
            // caps (see `fresa_http::admission`).
            req.extensions_mut().insert(connection);
            let resp = tower::ServiceExt::oneshot(router, req).await?;
            Ok::<_, std::convert::Infallible>(resp.map(|inner| CountedBody {
                inner,
                _guard: guard,
            }))
        }
    });
    let conn = builder.serve_connection(io, service);
    tokio::pin!(conn);
    // The orders are read with an atomic load on each wake, where a `select!` over a drain
    // token, a close token and an idle timer polled all three on every wake (about a twentieth
    // of a status poll's instructions).
    let mut draining = false;
    std::future::poll_fn(|cx| {
        // Registered before the orders are read, so an order given in between still wakes us.
        me.orders.task.register(cx.waker());
        if me.orders.given(Orders::CLOSE) {
            tracing::debug!("closing a connection (idle, or making room at the connection cap)");
            return Poll::Ready(());
        }
        if !draining && me.orders.given(Orders::DRAIN) {
            draining = true;
            conn.as_mut().graceful_shutdown();
        }
        std::future::Future::poll(conn.as_mut(), cx).map(|r| {
            if let Err(e) = r {
                tracing::debug!("connection ended: {e}");
            }
        })
    })
    .await;
}

/// What the accept loop tells a connection's task; read by its task on every wake.
#[derive(Default)]
struct Orders {
    given: AtomicU8,
    task: futures_util::task::AtomicWaker,
}

impl Orders {
    /// Finish the request in progress, then close.
    const DRAIN: u8 = 1;
    /// Close now.
    const CLOSE: u8 = 2;

    fn give(&self, order: u8) {
        self.given.fetch_or(order, Ordering::Release);
        self.task.wake();
    }

    fn given(&self, order: u8) -> bool {
        self.given.load(Ordering::Acquire) & order != 0
    }
}

/// The open connections in the order they were accepted, so that at the cap the oldest with no
/// request in progress can be closed to make room, idle ones closed, and all of them drained.
#[derive(Clone, Default)]
struct OpenConnections(Arc<Mutex<OpenList>>);

#[derive(Default)]
struct OpenList {
    next: u64,
    conns: BTreeMap<u64, Open>,
    /// Set once the server drains: a connection registered after that is told at once.
    draining: bool,
}

/// One connection as the list sees it.
struct Open {
    activity: Arc<Activity>,
    orders: Arc<Orders>,
    /// Its byte counter at the last idle check; `None` before its first one.
    seen: Option<u64>,
    /// Since when it has waited for a request's head, as the head checks saw it: its count of
    /// requests begun then, and the time. `None` while a request is in progress.
    head_wait: Option<(u64, Instant)>,
}

impl OpenConnections {
    fn list(&self) -> std::sync::MutexGuard<'_, OpenList> {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn register(&self) -> OpenConnection {
        let activity = Arc::new(Activity::new());
        let orders = Arc::new(Orders::default());
        let mut list = self.list();
        if list.draining {
            orders.give(Orders::DRAIN);
        }
        let id = list.next;
        list.next += 1;
        list.conns.insert(
            id,
            Open {
                activity: activity.clone(),
                orders: orders.clone(),
                seen: None,
                // The first head is due from connecting.
                head_wait: Some((0, Instant::now())),
            },
        );
        OpenConnection {
            id,
            open: self.clone(),
            activity,
            orders,
        }
    }

    /// Closes the connection open longest that has no request in progress (it sent nothing,
    /// half a head, or sits between requests); false if every one has a request in progress.
    fn close_oldest_quiet(&self) -> bool {
        let mut list = self.list();
        let oldest = list
            .conns
            .iter()
            .find(|(_, open)| !open.activity.in_flight())
            .map(|(id, _)| *id);
        match oldest.and_then(|id| list.conns.remove(&id)) {
            Some(open) => {
                open.orders.give(Orders::CLOSE);
                true
            }
            None => false,
        }
    }

    /// One idle check, run every idle period: closes each connection with no request in
    /// progress whose bytes have not moved since the last check. A connection is checked first
    /// one check after it opened, so it is closed between one and two periods after it went
    /// quiet (no clock read per request: bytes moving only bump a counter).
    fn close_idle(&self) {
        let mut list = self.list();
        list.conns.retain(|_, open| {
            let now = open.activity.moves();
            let idle = open.seen == Some(now) && !open.activity.in_flight();
            open.seen = Some(now);
            if idle {
                open.orders.give(Orders::CLOSE);
            }
            !idle
        });
    }

    /// One head check: closes each connection that has waited `timeout` or more for a
    /// request's head: no request in progress and none begun since it connected or its last
    /// response ended (a head sent a byte at a time does not reset it, unlike the idle check).
    /// The wait counts from connecting, or from the first check that saw the previous request
    /// done; with a check every quarter of `timeout` (see [`Self::close_slow_heads_every`]) a
    /// connection is closed between `timeout` and 1.25 x `timeout` after its wait began.
    fn close_slow_heads(&self, timeout: Duration, now: Instant) {
        let mut list = self.list();
        let before = list.conns.len();
        list.conns.retain(|_, open| {
            let (begun, in_flight) = open.activity.requests();
            if in_flight {
                open.head_wait = None;
                return true;
            }
            match open.head_wait {
                Some((seen, since)) if seen == begun => {
                    if now.saturating_duration_since(since) >= timeout {
                        open.orders.give(Orders::CLOSE);
                        return false;
                    }
                }
                _ => open.head_wait = Some((begun, now)),
            }
            true
        });
        let closed = before - list.conns.len();
        if closed > 0 {
            tracing::debug!(
                "closing {closed} connection(s): no request head within header_read_timeout"
            );
        }
    }

    /// Runs [`Self::close_slow_heads`] every quarter of `timeout` until dropped (aborted).
    async fn close_slow_heads_every(self, timeout: Duration) {
        let period = (timeout / 4).max(Duration::from_millis(10));
        every(period, || self.close_slow_heads(timeout, Instant::now())).await
    }

    /// Runs [`Self::close_idle`] every `idle` until dropped (aborted).
    async fn close_idle_every(self, idle: Duration) {
        every(idle, || self.close_idle()).await
    }

    /// Tells every open connection, and any registered from now on, to drain.
    fn drain(&self) {
        let mut list = self.list();
        list.draining = true;
        for open in list.conns.values() {
            open.orders.give(Orders::DRAIN);
        }
    }
}

/// Calls `check` every `period`, the first time one period from now, until dropped (aborted).
async fn every(period: Duration, mut check: impl FnMut()) {
    let mut tick = tokio::time::interval_at(Instant::now() + period, period);
    // After a stall the default (Burst) would run missed checks back to back, and an idle
    // check's second run would close connections whose bytes moved just before its first:
    // each check must come a whole period after the one before.
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        check();
    }
}

/// One connection's entry in [`OpenConnections`], removed when the connection's task ends.
struct OpenConnection {
    id: u64,
    open: OpenConnections,
    activity: Arc<Activity>,
    orders: Arc<Orders>,
}

impl Drop for OpenConnection {
    fn drop(&mut self) {
        self.open.list().conns.remove(&self.id);
    }
}

/// Whether a connection moved bytes, and how many of its requests are being answered. Bytes
/// moving only bump a counter (no clock read per read or write: this is on every request's
/// path); the idle check ([`OpenConnections::close_idle`]) compares it across one idle period.
struct Activity {
    moves: AtomicU64,
    /// Requests whose head arrived, and those whose response is done: in progress is the
    /// difference. Two counts rather than one in-progress count, so the head check also sees
    /// that a request began and ended between two of its looks.
    begun: AtomicU64,
    done: AtomicU64,
}

impl Activity {
    fn new() -> Self {
        Activity {
            moves: AtomicU64::new(0),
            begun: AtomicU64::new(0),
            done: AtomicU64::new(0),
        }
    }
    fn touch(&self) {
        self.moves.fetch_add(1, Ordering::Relaxed);
    }
    fn moves(&self) -> u64 {
        self.moves.load(Ordering::Relaxed)
    }
    fn in_flight(&self) -> bool {
        self.requests().1
    }
    /// Requests begun so far, and whether one is in progress.
    fn requests(&self) -> (u64, bool) {
        // `done` first: read after `begun`, a request ending in between would make done
        // exceed begun.
        let done = self.done.load(Ordering::Acquire);
        let begun = self.begun.load(Ordering::Acquire);
        (begun, begun != done)
    }
}

/// Counts a request as in progress from its head until its response body is dropped.
struct InFlight(Arc<Activity>);

impl InFlight {
    fn enter(a: Arc<Activity>) -> Self {
        a.begun.fetch_add(1, Ordering::Release);
        InFlight(a)
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.done.fetch_add(1, Ordering::Release);
        self.0.touch();
    }
}

/// A response body that keeps its request counted as in progress until it is done.
struct CountedBody {
    inner: Body,
    _guard: InFlight,
}

impl http_body::Body for CountedBody {
    type Data = <Body as http_body::Body>::Data;
    type Error = <Body as http_body::Body>::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }
    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }
    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// A socket that records when bytes last moved either way.
struct Tracked {
    inner: TcpStream,
    activity: Arc<Activity>,
}

impl AsyncRead for Tracked {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.inner).poll_read(cx, buf);
        if matches!(r, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.activity.touch();
        }
        r
    }
}

impl AsyncWrite for Tracked {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write(cx, buf);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.activity.touch();
        }
        r
    }
    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.activity.touch();
        }
        r
    }
    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A SIGTERM sent before the shutdown future is first polled (the server already answers
    /// then) still shuts down. Before, the process died of it, or ignored it, depending on
    /// where the signal fell.
    #[cfg(unix)]
    #[tokio::test]
    async fn a_sigterm_before_the_first_poll_is_not_lost() {
        let shutdown = wait_for_signal();
        // SAFETY: sends a signal to this process; the listener above has its handler in place.
        assert_eq!(unsafe { libc::kill(libc::getpid(), libc::SIGTERM) }, 0);
        let done = tokio::time::timeout(Duration::from_secs(30), shutdown).await;
        assert!(
            done.is_ok(),
            "the SIGTERM sent before the first poll was lost"
        );
    }

    fn closed(c: &OpenConnection) -> bool {
        c.orders.given(Orders::CLOSE)
    }

    #[test]
    fn at_the_cap_the_oldest_quiet_connection_gives_way() {
        let open = OpenConnections::default();
        let (a, b, c) = (open.register(), open.register(), open.register());
        // `a` is answering a request (an event stream, say): never closed to make room.
        let _busy = InFlight::enter(a.activity.clone());
        assert!(open.close_oldest_quiet());
        assert!(!closed(&a) && closed(&b) && !closed(&c));
        assert!(open.close_oldest_quiet());
        assert!(closed(&c));
        assert!(!open.close_oldest_quiet(), "only the busy one is left");
        drop((b, c));
        assert_eq!(open.list().conns.len(), 1);
    }

    #[test]
    fn a_connection_is_closed_after_a_whole_idle_period_without_bytes_or_requests() {
        let open = OpenConnections::default();
        let (quiet, busy, talking) = (open.register(), open.register(), open.register());
        let _busy = InFlight::enter(busy.activity.clone());
        // The first check after they opened only looks.
        open.close_idle();
        assert!(!closed(&quiet) && !closed(&busy) && !closed(&talking));
        talking.activity.touch();
        let late = open.register();
        open.close_idle();
        assert!(closed(&quiet), "no bytes and no request for a whole period");
        assert!(
            !closed(&busy),
            "a request in progress (an event stream) is not idle"
        );
        assert!(!closed(&talking), "its bytes moved");
        assert!(!closed(&late), "opened during the period");
        open.drain();
        assert!(busy.orders.given(Orders::DRAIN) && late.orders.given(Orders::DRAIN));
        assert!(
            open.register().orders.given(Orders::DRAIN),
            "one accepted while draining drains too"
        );
    }
}
