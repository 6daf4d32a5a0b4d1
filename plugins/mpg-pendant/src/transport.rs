//! The link to one pendant: the server side is the TCP client. Connect, say hello, send
//! heartbeats, answer polls from the status cache, reconnect with capped exponential backoff,
//! and declare the pendant lost when it closes the link or stays silent too long.

use crate::codec::{Decoded, Decoder, Dialect, Frame, Info, FRAME_LEN};
use fresa_plugin_api::contract::{Axis, AxisValues, PendantEvent, PendantJob};
use fresa_plugin_api::quiet::Quiet;
use serde::Deserialize;
use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// The pendants' TCP port.
pub const DEFAULT_PORT: u16 = 8001;

/// Per-pendant transport settings (the plugin instance's JSON config).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// `host:port` or `host` (port 8001). `MPG000001.local` names are resolved by mDNS.
    pub address: String,
    #[serde(default)]
    pub dialect: Dialect,
    /// Only used to label log lines.
    #[serde(default)]
    pub pendant: Option<i64>,
    #[serde(default = "default_heartbeat")]
    pub heartbeat_ms: u64,
    #[serde(default = "default_lost")]
    pub lost_after_ms: u64,
    #[serde(default = "default_backoff_initial")]
    pub backoff_initial_ms: u64,
    #[serde(default = "default_backoff_max")]
    pub backoff_max_ms: u64,
    #[serde(default = "default_connect_timeout")]
    pub connect_timeout_ms: u64,
    /// An upload with no data for this long is abandoned.
    #[serde(default = "default_upload_idle")]
    pub upload_idle_ms: u64,
    #[serde(default = "default_max_upload")]
    pub max_upload_bytes: u64,
    /// The link's thread asks for nice `LINK_NICE` (see there).
    #[serde(default = "default_raise_priority")]
    pub raise_priority: bool,
}

/// The nice value a link's thread asks for when `raise_priority` is on. The thread answers the
/// pendant's polls from the status cache and passes its keys on (STOP among them); it sleeps
/// in between and does little work per frame. At normal priority, measured with 100 pendants
/// beside busy machines on 2 cores, a poll's answer waited up to a scheduler slice behind
/// other work (p99 0.4-1.4 ms); at nice -5 to -20 the p99 was 0.11-0.14 ms. -10 leaves the
/// parallel port's step loop (-20) ahead of it.
pub const LINK_NICE: i32 = -10;

fn default_raise_priority() -> bool {
    true
}

fn default_heartbeat() -> u64 {
    1000
}
fn default_lost() -> u64 {
    3000
}
fn default_backoff_initial() -> u64 {
    100
}
fn default_backoff_max() -> u64 {
    5000
}
fn default_connect_timeout() -> u64 {
    1000
}
fn default_upload_idle() -> u64 {
    5000
}
fn default_max_upload() -> u64 {
    64 << 20
}

impl Config {
    pub fn check(&self) -> Result<(), String> {
        if self.address.trim().is_empty() {
            return Err("field `address` must not be empty".into());
        }
        for (name, v) in [
            ("heartbeat_ms", self.heartbeat_ms),
            ("lost_after_ms", self.lost_after_ms),
            ("backoff_initial_ms", self.backoff_initial_ms),
            ("backoff_max_ms", self.backoff_max_ms),
            ("connect_timeout_ms", self.connect_timeout_ms),
            ("upload_idle_ms", self.upload_idle_ms),
        ] {
            if v == 0 {
                return Err(format!("field `{name}` must be at least 1"));
            }
        }
        Ok(())
    }

    /// Host and port of `address`, with the default port when none is given.
    pub fn host_port(&self) -> (String, u16) {
        split_host_port(&self.address)
    }
}

pub fn split_host_port(address: &str) -> (String, u16) {
    let a = address.trim();
    if let Ok(sa) = a.parse::<SocketAddr>() {
        return (sa.ip().to_string(), sa.port());
    }
    match a.rsplit_once(':') {
        Some((h, p)) if !h.contains(':') => match p.parse() {
            Ok(port) => (h.to_string(), port),
            Err(_) => (a.to_string(), DEFAULT_PORT),
        },
        _ => (a.trim_matches(['[', ']']).to_string(), DEFAULT_PORT),
    }
}

pub type EmitFn = Box<dyn Fn(&PendantEvent) + Send + Sync>;
pub type LogFn = Box<dyn Fn(u32, &str) + Send + Sync>;

struct Cache {
    positions: [u8; FRAME_LEN],
    progress: [u8; FRAME_LEN],
}

struct Shared {
    cfg: Config,
    stop: AtomicBool,
    cache: Mutex<Cache>,
    /// Write half of the live connection; every write goes through it, so frames never interleave.
    link: Mutex<Option<TcpStream>>,
    connected: AtomicBool,
    /// Upload waiting for the core's confirmation.
    awaiting: AtomicU64,
    wake: (Mutex<()>, Condvar),
    emit: EmitFn,
    log: LogFn,
    /// Warnings that can come once per frame or per status push (a clamped LCD field,
    /// garbage on the link) are logged once, then at most once a minute with a count.
    quiet: Quiet,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Shared {
    fn info(&self, msg: &str) {
        (self.log)(fresa_plugin_api::abi::LOG_INFO, &self.label(msg))
    }
    fn warn(&self, msg: &str) {
        (self.log)(fresa_plugin_api::abi::LOG_WARN, &self.label(msg))
    }
    /// A warning that may repeat per frame: rate-limited per `kind`.
    fn warn_quiet(&self, kind: &str, msg: impl FnOnce() -> String) {
        if let Some(line) = self.quiet.admit(kind, msg) {
            self.warn(&line);
        }
    }
    fn label(&self, msg: &str) -> String {
        match self.cfg.pendant {
            Some(id) => format!("pendant {id} ({}): {msg}", self.cfg.address),
            None => format!("pendant {}: {msg}", self.cfg.address),
        }
    }

    /// Writes one frame on the live link. False when there is none or the write failed.
    fn send(&self, frame: &[u8; FRAME_LEN]) -> bool {
        let mut link = lock(&self.link);
        match link.as_mut() {
            Some(s) => match s.write_all(frame) {
                Ok(()) => true,
                Err(e) => {
                    self.warn(&format!("write failed: {e}"));
                    let _ = s.shutdown(Shutdown::Both);
                    *link = None;
                    false
                }
            },
            None => false,
        }
    }

    /// Sleeps up to `d`, waking early on shutdown.
    fn pause(&self, d: Duration) {
        let (m, cv) = &self.wake;
        let guard = lock(m);
        if self.stop.load(Ordering::Relaxed) {
            return;
        }
        let _ = cv.wait_timeout(guard, d);
    }
}

/// A running link to one pendant. Dropping it closes the link and joins its thread.
pub struct Transport {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl Transport {
    pub fn start(cfg: Config, emit: EmitFn, log: LogFn) -> Result<Transport, String> {
        cfg.check()?;
        let shared = Arc::new(Shared {
            cfg,
            stop: AtomicBool::new(false),
            cache: Mutex::new(Cache {
                positions: Frame::Positions(AxisValues::default()).encode(),
                progress: Frame::Progress(PendantJob::default()).encode(),
            }),
            link: Mutex::new(None),
            connected: AtomicBool::new(false),
            awaiting: AtomicU64::new(0),
            wake: (Mutex::new(()), Condvar::new()),
            emit,
            log,
            quiet: Quiet::per_minute(),
        });
        let s = shared.clone();
        let thread = std::thread::Builder::new()
            .name("mpg-pendant".into())
            .spawn(move || run(&s))
            .map_err(|e| format!("cannot start the pendant thread: {e}"))?;
        Ok(Transport {
            shared,
            thread: Some(thread),
        })
    }

    pub fn connected(&self) -> bool {
        self.shared.connected.load(Ordering::Relaxed)
    }

    pub fn address(&self) -> &str {
        &self.shared.cfg.address
    }

    /// Replaces the status cache the pendant's polls are answered from. A status line (why
    /// the machine holds) rides in the N52 answer, after the job's fields.
    pub fn set_status(
        &self,
        position: AxisValues,
        job: Option<PendantJob>,
        status_line: Option<String>,
    ) {
        let (pos, n1) = Frame::Positions(position).encode_checked();
        let job = job.unwrap_or_default();
        let (prog, n2) = match status_line.filter(|s| !s.is_empty()) {
            Some(status) => Frame::ProgressWithStatus { job, status }.encode_checked(),
            None => Frame::Progress(job).encode_checked(),
        };
        {
            let mut c = lock(&self.shared.cache);
            c.positions = pos;
            c.progress = prog;
        }
        // Pushed up to 20 times a second, and the elapsed time in an N52 note changes every
        // second: rate-limited per frame type, not per text.
        if let Some(n) = n1 {
            self.shared.warn_quiet("n51-clamp", || n);
        }
        if let Some(n) = n2 {
            self.shared.warn_quiet("n52-clamp", || n);
        }
    }

    /// Sends N53 for `upload` if it is the one waiting and the link is up.
    pub fn confirm_upload(&self, upload: u64) -> bool {
        if upload == 0
            || self
                .shared
                .awaiting
                .compare_exchange(upload, 0, Ordering::SeqCst, Ordering::SeqCst)
                .is_err()
        {
            return false;
        }
        self.shared.send(&Frame::UploadConfirmed.encode())
    }
}

impl Drop for Transport {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(s) = lock(&self.shared.link).as_ref() {
            let _ = s.shutdown(Shutdown::Both);
        }
        {
            let _g = lock(&self.shared.wake.0);
            self.shared.wake.1.notify_all();
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn resolve(cfg: &Config) -> Result<Vec<SocketAddr>, String> {
    let (host, port) = cfg.host_port();
    let mut addrs: Vec<SocketAddr> = (host.as_str(), port)
        .to_socket_addrs()
        .map(|a| a.collect())
        .unwrap_or_default();
    if addrs.is_empty() && host.to_ascii_lowercase().ends_with(".local") {
        addrs = crate::discovery::resolve_mdns(
            &host,
            port,
            Duration::from_millis(cfg.connect_timeout_ms.max(500)),
        )?;
    }
    if addrs.is_empty() {
        return Err(format!("cannot resolve {host:?}"));
    }
    Ok(addrs)
}

fn connect(cfg: &Config) -> Result<TcpStream, String> {
    // Re-resolved on every attempt: a pendant that rejoined Wi-Fi may have a new address.
    let addrs = resolve(cfg)?;
    let timeout = Duration::from_millis(cfg.connect_timeout_ms);
    let mut last = String::new();
    for a in addrs {
        match TcpStream::connect_timeout(&a, timeout) {
            Ok(s) => return Ok(s),
            Err(e) => last = format!("{a}: {e}"),
        }
    }
    Err(last)
}

/// Asks for `LINK_NICE` for the calling (link) thread, saying in the log what it got.
fn raise_priority(s: &Shared) {
    if !s.cfg.raise_priority {
        return;
    }
    match fresa_plugin_api::priority::set_thread_nice(LINK_NICE) {
        Ok(()) => s.info(&format!(
            "the link's thread runs at nice {LINK_NICE}{AS_ON_THIS_OS}, so polls and keys are \
             answered ahead of other work"
        )),
        Err(e) => s.warn(&format!(
            "the link's thread could NOT take nice {LINK_NICE} ({e}); on a busy PC polls and \
             keys may wait milliseconds behind other work.{ALLOW_IT}"
        )),
    }
}

/// What `LINK_NICE` becomes where there are no nice values (`set_thread_nice`'s mapping).
#[cfg(windows)]
const AS_ON_THIS_OS: &str = " (on Windows: above normal priority)";
#[cfg(not(windows))]
const AS_ON_THIS_OS: &str = "";

/// How an admin lets a link's thread raise its priority.
#[cfg(target_os = "linux")]
const ALLOW_IT: &str = " Grant CAP_SYS_NICE (e.g. `setcap cap_sys_nice+ep fresa`) or allow it \
     with RLIMIT_NICE (systemd: `LimitNICE=-10`)";
#[cfg(not(target_os = "linux"))]
const ALLOW_IT: &str = "";

fn run(s: &Shared) {
    raise_priority(s);
    let initial = Duration::from_millis(s.cfg.backoff_initial_ms);
    let max = Duration::from_millis(s.cfg.backoff_max_ms.max(s.cfg.backoff_initial_ms));
    let mut backoff = initial;
    let mut failures = 0u32;
    while !s.stop.load(Ordering::Relaxed) {
        match connect(&s.cfg) {
            Ok(stream) => {
                backoff = initial;
                failures = 0;
                match session(s, stream) {
                    _ if s.stop.load(Ordering::Relaxed) => break,
                    Ok(reason) => {
                        s.warn(&format!("lost: {reason}"));
                        (s.emit)(&PendantEvent::Lost { reason });
                    }
                    // Never got as far as `connected`: nothing to report as lost.
                    Err(e) => s.info(&format!("connection failed at setup: {e}")),
                }
            }
            Err(e) => {
                failures += 1;
                // Log the 1st, 2nd, 4th, 8th... failure: an absent pendant is normal.
                if failures.is_power_of_two() {
                    s.info(&format!("cannot connect ({failures} tries): {e}"));
                }
            }
        }
        s.pause(backoff);
        backoff = (backoff * 2).min(max);
    }
}

/// The published firmware counts lines in an 8-bit variable: files with more lines than this
/// are re-sent from the start forever, without N03FIN.
pub const FIRMWARE_MAX_LINES: u64 = 255;

struct Upload {
    declared_lines: u64,
    lines: Vec<String>,
    /// Lines that arrived, kept or not.
    received: u64,
    bytes: u64,
    problem: Option<String>,
    /// The core has already been told this upload failed (the rest of it is discarded).
    reported: bool,
    last_data: Instant,
}

impl Upload {
    fn new(declared_lines: u64) -> Upload {
        Upload {
            declared_lines,
            lines: Vec::new(),
            received: 0,
            bytes: 0,
            problem: None,
            reported: false,
            last_data: Instant::now(),
        }
    }

    /// Names the firmware's line limit when the declared count is over it.
    fn firmware_limit_note(&self) -> String {
        if self.declared_lines > FIRMWARE_MAX_LINES {
            format!(
                "; the pendant firmware's 8-bit line counter cannot send files over \
                 {FIRMWARE_MAX_LINES} lines (this one declared {}): it re-sends the first lines \
                 forever and never sends N03FIN, so split the file",
                self.declared_lines
            )
        } else {
            String::new()
        }
    }
}

/// Serves one connection until it ends; returns why it ended (Err: it ended before the pendant
/// was reported connected).
fn session(s: &Shared, mut stream: TcpStream) -> Result<String, String> {
    let cfg = &s.cfg;
    let _ = stream.set_nodelay(true);
    let heartbeat = Duration::from_millis(cfg.heartbeat_ms);
    let lost_after = Duration::from_millis(cfg.lost_after_ms);
    let tick = (heartbeat / 4)
        .min(lost_after / 4)
        .clamp(Duration::from_millis(5), Duration::from_millis(50));
    if let Err(e) = stream.set_read_timeout(Some(tick)) {
        return Err(format!("cannot set a read timeout: {e}"));
    }
    match stream.try_clone() {
        Ok(w) => *lock(&s.link) = Some(w),
        Err(e) => return Err(format!("cannot share the socket: {e}")),
    }
    let peer = stream
        .peer_addr()
        .map(|a| a.to_string())
        .unwrap_or_else(|_| cfg.address.clone());
    if !s.send(&Frame::Hello(cfg.dialect).encode()) {
        *lock(&s.link) = None;
        return Err("could not send the hello frame".into());
    }
    s.connected.store(true, Ordering::Relaxed);
    s.info(&format!("connected to {peer}"));
    (s.emit)(&PendantEvent::Connected { address: peer });
    let mut decoder = Decoder::new();
    let mut upload: Option<Upload> = None;
    let mut next_upload_id = 1u64;
    let mut counter = 0u32;
    let mut last_rx = Instant::now();
    let mut next_hb = Instant::now() + heartbeat;
    let mut buf = vec![0u8; 64 * 1024];
    let reason = loop {
        if s.stop.load(Ordering::Relaxed) {
            break "shutting down".to_string();
        }
        match stream.read(&mut buf) {
            Ok(0) => break "the pendant closed the connection".to_string(),
            Ok(n) => {
                last_rx = Instant::now();
                decoder.push(&buf[..n]);
                let mut wheel = WheelRun::default();
                while let Some(d) = decoder.pop() {
                    // Consecutive wheel frames of one read become one event with their exact
                    // sum: a flood costs one emit per read, not one per frame.
                    if let Decoded::Frame(Frame::Jog { step, axis, count }) = d {
                        if let Some(full) = wheel.add(axis, step, count) {
                            emit_jog(s, full);
                        }
                        continue;
                    }
                    if let Some(run) = wheel.take() {
                        emit_jog(s, run);
                    }
                    handle(s, d, &mut upload, &mut next_upload_id);
                }
                if let Some(run) = wheel.take() {
                    emit_jog(s, run);
                }
            }
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(e) if e.kind() == ErrorKind::Interrupted => continue,
            Err(e) => break format!("read failed: {e}"),
        }
        let now = Instant::now();
        if now >= next_hb {
            counter = counter.wrapping_add(1) % 10_000_000;
            s.send(
                &Frame::Heartbeat {
                    dialect: cfg.dialect,
                    counter,
                }
                .encode(),
            );
            next_hb = now + heartbeat;
        }
        if lock(&s.link).is_none() {
            break "write failed".to_string();
        }
        if now.duration_since(last_rx) > lost_after {
            break format!("silent for more than {} ms", cfg.lost_after_ms);
        }
        if let Some(u) = &upload {
            if now.duration_since(u.last_data) > Duration::from_millis(cfg.upload_idle_ms) {
                decoder.abort_upload();
                if !u.reported {
                    (s.emit)(&PendantEvent::UploadFailed {
                        reason: format!(
                            "no upload data and no N03FIN for {} ms after {} of {} lines; upload \
                             abandoned{}",
                            cfg.upload_idle_ms,
                            u.received,
                            u.declared_lines,
                            u.firmware_limit_note()
                        ),
                    });
                }
                upload = None;
            }
        }
    };
    s.connected.store(false, Ordering::Relaxed);
    s.awaiting.store(0, Ordering::SeqCst);
    if let Some(l) = lock(&s.link).take() {
        let _ = l.shutdown(Shutdown::Both);
    }
    if upload.as_ref().is_some_and(|u| !u.reported) {
        (s.emit)(&PendantEvent::UploadFailed {
            reason: format!("connection ended during the upload: {reason}"),
        });
    }
    Ok(reason)
}

fn handle(s: &Shared, d: Decoded, upload: &mut Option<Upload>, next_id: &mut u64) {
    match d {
        Decoded::Frame(Frame::Request(info)) => {
            let frame = {
                let c = lock(&s.cache);
                match info {
                    Info::Positions => c.positions,
                    Info::Job => c.progress,
                }
            };
            s.send(&frame);
        }
        Decoded::Frame(Frame::Jog { step, axis, count }) => emit_jog(s, (axis, step, count)),
        Decoded::Frame(Frame::Key(key)) => (s.emit)(&PendantEvent::Key { key }),
        Decoded::Frame(Frame::UploadStart { lines }) => {
            // A new START replaces an upload that never finished.
            s.info(&format!("upload started: {lines} lines declared"));
            *upload = Some(Upload::new(u64::from(lines)));
        }
        Decoded::Line(bytes) => {
            let Some(u) = upload.as_mut() else { return };
            u.last_data = Instant::now();
            u.received += 1;
            if u.problem.is_some() {
                return;
            }
            if u.received > u.declared_lines {
                // Bounded: nothing more is kept; the rest of the upload is discarded until a
                // frame, N03FIN or the idle time-out ends raw-line mode.
                u.lines = Vec::new();
                let reason = format!(
                    "the pendant sent more lines than the {} its N03START declared; upload \
                     rejected{}",
                    u.declared_lines,
                    u.firmware_limit_note()
                );
                s.warn(&reason);
                u.problem = Some(reason.clone());
                u.reported = true;
                (s.emit)(&PendantEvent::UploadFailed { reason });
                return;
            }
            u.bytes += bytes.len() as u64;
            if u.bytes > s.cfg.max_upload_bytes {
                u.problem = Some(format!(
                    "upload is larger than {} bytes",
                    s.cfg.max_upload_bytes
                ));
                return;
            }
            match String::from_utf8(bytes) {
                Ok(line) => u.lines.push(line),
                Err(e) => {
                    u.problem = Some(format!(
                        "line {} is not text: {e} (bytes {:?})",
                        u.lines.len() + 1,
                        String::from_utf8_lossy(e.as_bytes())
                    ))
                }
            }
        }
        Decoded::Frame(Frame::UploadEnd { chars }) => {
            let Some(u) = upload.take() else {
                s.warn_quiet("fin-without-start", || {
                    "N03FIN without N03START; ignored".into()
                });
                return;
            };
            if u.reported {
                s.info("N03FIN of an upload already rejected; ignored");
                return;
            }
            match u.problem {
                Some(reason) => (s.emit)(&PendantEvent::UploadFailed { reason }),
                None => {
                    let id = *next_id;
                    *next_id += 1;
                    s.awaiting.store(id, Ordering::SeqCst);
                    s.info(&format!(
                        "upload received: {} lines, {} characters",
                        u.lines.len(),
                        u.bytes
                    ));
                    (s.emit)(&PendantEvent::Upload {
                        upload: id,
                        lines: u.lines,
                        declared_lines: u.declared_lines,
                        declared_chars: chars,
                    });
                }
            }
        }
        Decoded::UploadAborted { reason } => match upload.take() {
            Some(u) if u.reported => s.info(&format!("rejected upload ended: {reason}")),
            Some(u) => {
                let reason = format!(
                    "upload aborted after {} of {} lines: {reason}",
                    u.received, u.declared_lines
                );
                s.warn(&reason);
                (s.emit)(&PendantEvent::UploadFailed { reason });
            }
            None => (s.emit)(&PendantEvent::UploadFailed { reason }),
        },
        Decoded::Skipped { bytes, reason } => s.warn_quiet("skipped", || {
            let shown: String = String::from_utf8_lossy(&bytes).chars().take(120).collect();
            format!(
                "skipped {} bytes that are not a valid frame ({reason}): {shown:?}",
                bytes.len()
            )
        }),
        Decoded::Frame(other) => s.warn_quiet("unexpected-frame", || {
            format!("unexpected frame from a pendant: {other:?}; ignored")
        }),
    }
}

/// Wheel frames of one read not emitted yet: axis, step and the sum of their detent counts.
#[derive(Default)]
struct WheelRun(Option<(Axis, f64, i32)>);

impl WheelRun {
    /// Adds one frame; answers the run to emit first when this frame cannot join it (another
    /// axis or step, or a sum that would not fit the event's count).
    fn add(&mut self, axis: Axis, step: f64, count: i32) -> Option<(Axis, f64, i32)> {
        if let Some((a, st, sum)) = &mut self.0 {
            if *a == axis && *st == step {
                if let Some(total) = sum.checked_add(count) {
                    *sum = total;
                    return None;
                }
            }
        }
        self.0.replace((axis, step, count))
    }

    fn take(&mut self) -> Option<(Axis, f64, i32)> {
        self.0.take()
    }
}

fn emit_jog(s: &Shared, (axis, step, count): (Axis, f64, i32)) {
    // Turns that cancel out within one read move nothing.
    if count != 0 {
        (s.emit)(&PendantEvent::Jog { axis, count, step });
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    #[test]
    fn a_run_of_wheel_frames_keeps_its_exact_sum_and_breaks_on_another_axis_or_step() {
        let mut w = WheelRun::default();
        assert_eq!(w.add(Axis::X, 0.01, 1), None);
        assert_eq!(w.add(Axis::X, 0.01, 9999), None);
        assert_eq!(w.add(Axis::X, 0.01, -3), None);
        assert_eq!(w.add(Axis::Y, 0.01, 2), Some((Axis::X, 0.01, 9997)));
        assert_eq!(w.add(Axis::Y, 0.1, 2), Some((Axis::Y, 0.01, 2)));
        assert_eq!(w.add(Axis::Y, 0.1, i32::MAX), Some((Axis::Y, 0.1, 2)));
        // A sum that would overflow the count starts a new run instead of wrapping.
        assert_eq!(w.add(Axis::Y, 0.1, 1), Some((Axis::Y, 0.1, i32::MAX)));
        assert_eq!(w.take(), Some((Axis::Y, 0.1, 1)));
        assert_eq!(w.take(), None);
    }

    /// Starts a link (`config` with `address` added) to a local listener from the calling
    /// thread; returns the link's priority log line (if any) and its thread's nice value as
    /// the kernel reports it once connected, read on that thread by the log sink.
    #[cfg(target_os = "linux")]
    fn link_priority(mut config: serde_json::Value) -> (Option<String>, i32) {
        use std::sync::mpsc;
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        config["address"] = listener.local_addr().unwrap().to_string().into();
        let cfg: Config = serde_json::from_value(config).unwrap();
        let (tx, rx) = mpsc::channel();
        let tx = Mutex::new(tx);
        let log: LogFn = Box::new(move |_, line| {
            if line.contains("nice") || line.contains("connected to") {
                let nice = fresa_plugin_api::priority::thread_nice().unwrap();
                let _ = lock(&tx).send((line.to_string(), nice));
            }
        });
        let link = Transport::start(cfg, Box::new(|_| {}), log).unwrap();
        let mut priority = None;
        let nice = loop {
            let (line, nice) = rx.recv_timeout(Duration::from_secs(30)).unwrap();
            if line.contains("connected to") {
                break nice;
            }
            priority = Some(line);
        };
        drop(link);
        (priority, nice)
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_links_thread_answers_polls_at_nice_minus_10_and_only_that_thread() {
        let own = fresa_plugin_api::priority::thread_nice().unwrap();
        let (line, nice) = link_priority(serde_json::json!({}));
        let line = line.expect("a log line about the link's priority");
        assert!(
            !line.contains("could NOT"),
            "this test needs CAP_SYS_NICE (run it as root, as tests/run does): {line}"
        );
        assert!(line.contains("nice -10"), "{line}");
        assert_eq!(nice, LINK_NICE);
        assert_eq!(fresa_plugin_api::priority::thread_nice(), Some(own));
        // Turned off in the config: no change, no line.
        assert_eq!(
            link_priority(serde_json::json!({"raise_priority": false})),
            (None, own)
        );
    }

    /// The calling thread gives up `CAP_SYS_NICE` (capabilities are per thread; threads it
    /// starts inherit its set).
    #[cfg(target_os = "linux")]
    fn without_cap_sys_nice() {
        #[repr(C)]
        struct Header {
            version: u32,
            pid: i32,
        }
        #[repr(C)]
        #[derive(Clone, Copy, Default)]
        struct Data {
            effective: u32,
            permitted: u32,
            inheritable: u32,
        }
        const VERSION_3: u32 = 0x2008_0522;
        const CAP_SYS_NICE: u32 = 23;
        let mut header = Header {
            version: VERSION_3,
            pid: 0,
        };
        let mut data = [Data::default(); 2];
        // SAFETY: capget/capset with a v3 header and the two data blocks v3 reads and writes.
        unsafe {
            assert_eq!(
                libc::syscall(libc::SYS_capget, &mut header, data.as_mut_ptr()),
                0
            );
            data[0].effective &= !(1 << CAP_SYS_NICE);
            assert_eq!(
                libc::syscall(libc::SYS_capset, &mut header, data.as_ptr()),
                0
            );
        }
    }

    /// Without `CAP_SYS_NICE`, as under the systemd unit's dynamic user when the unit's
    /// `LimitNICE` is taken out: refused, with a warning that says how to allow it. (That
    /// `RLIMIT_NICE` allows it is the kernel's documented rule, `20 - limit`; raising the hard
    /// limit to show it needs `CAP_SYS_RESOURCE`, which this test cannot count on.)
    #[cfg(target_os = "linux")]
    #[test]
    fn without_cap_sys_nice_a_link_keeps_its_priority_and_warns_how_to_allow_it() {
        let own = fresa_plugin_api::priority::thread_nice().unwrap();
        // SAFETY: getrlimit/setrlimit with a valid, initialised struct. The soft limit goes to
        // 0 (no lowering without the capability; the default), the hard one stays.
        unsafe {
            let mut limit = std::mem::zeroed::<libc::rlimit>();
            assert_eq!(libc::getrlimit(libc::RLIMIT_NICE, &mut limit), 0);
            limit.rlim_cur = 0;
            assert_eq!(libc::setrlimit(libc::RLIMIT_NICE, &limit), 0);
        }
        let (line, nice) = std::thread::spawn(|| {
            without_cap_sys_nice();
            link_priority(serde_json::json!({}))
        })
        .join()
        .unwrap();
        let line = line.expect("a warning about the link's priority");
        for part in ["could NOT take nice -10", "CAP_SYS_NICE", "LimitNICE=-10"] {
            assert!(line.contains(part), "{part:?} missing: {line}");
        }
        assert_eq!(nice, own, "the thread keeps its priority");
    }
}
