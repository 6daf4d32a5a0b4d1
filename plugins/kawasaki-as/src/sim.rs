//! A loopback stand-in for the Kawasaki controller running either robot program: the seed's
//! `FRESADORA` (legacy, exactly as printed) or the generated fresa-v1 program. Motion takes
//! `distance / speed * time_scale`; every executed motion and every received message is
//! appended to a JSON-lines log; faults can be injected. Used by the `kawasaki-as-sim` binary,
//! the end-to-end tests and the benchmark.

use crate::codec::{self, LegacyCmd, V1Cmd, V1Msg};
use crate::config::Protocol;
use serde_json::json;
use std::collections::VecDeque;
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::path::PathBuf;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// When an injected link drop happens relative to the motion's `done`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DropMode {
    /// The motion is executed and acknowledged, then the link drops.
    AfterDone,
    /// The motion is executed, the link drops before its `done` is sent (the lost-`done` case).
    BeforeDone,
}

#[derive(Debug, Clone)]
pub struct SimConfig {
    pub protocol: Protocol,
    /// Part zero reported on the first connection (robot base coordinates).
    pub part_zero: [f64; 3],
    /// Part zero reported on every later connection (default: the same).
    pub part_zero_after_reconnect: Option<[f64; 3]>,
    /// Multiplies motion time: 0 = instant.
    pub time_scale: f64,
    /// Delay of every reply (simulated network + controller latency); replies are pipelined.
    pub reply_delay: Duration,
    /// Close the connection after this many executed motions (counted over the sim's life),
    /// once.
    pub drop_after: Option<u64>,
    pub drop_mode: DropMode,
    /// Send a garbage message before every n-th motion's `done`.
    pub garbage_every: Option<u64>,
    /// fresa-v1 rapid speed, mm/s (the generated program's constant).
    pub rapid_mm_s: f64,
    /// fresa-v1: commands the robot can hold; more unanswered ones is a protocol violation.
    pub queue: usize,
    pub log: Option<PathBuf>,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            protocol: Protocol::Legacy,
            part_zero: [-400.0, 0.0, -30.0],
            part_zero_after_reconnect: None,
            time_scale: 0.0,
            reply_delay: Duration::ZERO,
            drop_after: None,
            drop_mode: DropMode::AfterDone,
            garbage_every: None,
            rapid_mm_s: 10.0,
            queue: 64,
            log: None,
        }
    }
}

/// What the controller remembers between connections (AS global variables).
struct Memory {
    conn: u64,
    motions: u64,
    dropped: bool,
    pos: [f64; 3],
    /// fresa-v1: run tag and the last sequence number executed for it.
    tag: String,
    last_seq: u64,
    log: Option<File>,
}

impl Memory {
    fn log(&mut self, entry: serde_json::Value) {
        if let Some(f) = &mut self.log {
            let mut line = entry.to_string();
            line.push('\n');
            // One write per entry; a failing log must not take the robot down.
            let _ = f.write_all(line.as_bytes());
        }
    }
}

/// A running simulator.
pub struct Sim {
    cfg: SimConfig,
    mem: Mutex<Memory>,
}

type Shared = Arc<Sim>;

impl Sim {
    pub fn new(cfg: SimConfig) -> std::io::Result<Shared> {
        let log = match &cfg.log {
            Some(p) => Some(OpenOptions::new().create(true).append(true).open(p)?),
            None => None,
        };
        Ok(Arc::new(Sim {
            cfg,
            mem: Mutex::new(Memory {
                conn: 0,
                motions: 0,
                dropped: false,
                pos: [0.0; 3],
                tag: String::new(),
                last_seq: 0,
                log,
            }),
        }))
    }

    fn mem(&self) -> std::sync::MutexGuard<'_, Memory> {
        self.mem.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Serves connections one at a time, for ever (the robot program restarted after each).
    pub fn serve(self: &Shared, listener: TcpListener) {
        for stream in listener.incoming() {
            let Ok(stream) = stream else { continue };
            let _ = stream.set_nodelay(true);
            let conn = {
                let mut m = self.mem();
                m.conn += 1;
                let c = m.conn;
                m.log(json!({"conn": c, "event": "connected"}));
                c
            };
            let result = match self.cfg.protocol {
                Protocol::Legacy => self.legacy(conn, stream),
                Protocol::FresaV1 => self.v1(conn, stream),
            };
            let how = match result {
                Ok(h) => h.to_string(),
                Err(e) => format!("io error: {e}"),
            };
            self.mem()
                .log(json!({"conn": conn, "event": "disconnected", "how": how}));
        }
    }

    fn part_zero(&self, conn: u64) -> [f64; 3] {
        match self.cfg.part_zero_after_reconnect {
            Some(z) if conn > 1 => z,
            _ => self.cfg.part_zero,
        }
    }

    /// Moves to `to` at `speed`, taking the scaled time; logs it. Returns whether the link
    /// must now drop (fault injection) and whether garbage is due.
    fn execute(
        &self,
        conn: u64,
        kind: &str,
        seq: Option<u64>,
        to: [f64; 3],
        speed: f64,
    ) -> (bool, bool) {
        let from = self.mem().pos;
        let dist = (0..3)
            .map(|i| (to[i] - from[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        let secs = if self.cfg.time_scale > 0.0 && speed > 0.0 {
            dist / speed * self.cfg.time_scale
        } else {
            0.0
        };
        if secs > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(secs));
        }
        let mut m = self.mem();
        m.pos = to;
        m.motions += 1;
        let n = m.motions;
        // When it ended, ms since the Unix epoch: the record a test times motions by.
        let at_ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64);
        m.log(json!({"conn": conn, "move": kind, "seq": seq, "to": to, "speed": speed, "at_ms": at_ms}));
        let drop = match self.cfg.drop_after {
            Some(k) if !m.dropped && n >= k => {
                m.dropped = true;
                m.log(json!({"conn": conn, "event": "dropping", "after_motion": n}));
                true
            }
            _ => false,
        };
        let garbage = self
            .cfg
            .garbage_every
            .is_some_and(|g| g > 0 && n.is_multiple_of(g));
        (drop, garbage)
    }

    // ------------------------------------------------------------ legacy

    /// The seed's `FRESADORA` program.
    fn legacy(&self, conn: u64, stream: TcpStream) -> std::io::Result<&'static str> {
        let replies = Replies::start(stream.try_clone()?, self.cfg.reply_delay);
        let mut reader = BufReader::new(stream.try_clone()?);
        // BASE NULL; HERE var; BASE var; LDEPART 50: the tool position is the part zero.
        self.mem().pos = [0.0; 3];
        replies.send(codec::LEGACY_WAITING.as_bytes().to_vec());
        let z = self.part_zero(conn);
        replies.send(format!("{} {} {}", z[0], z[1], z[2]).into_bytes());
        let mut started = false;
        let mut line = Vec::new();
        loop {
            line.clear();
            if reader.read_until(b'\n', &mut line)? == 0 {
                return Ok("client closed");
            }
            let text = String::from_utf8_lossy(&line).into_owned();
            if !reader.buffer().is_empty() {
                self.mem().log(json!({"conn": conn, "violation":
                    "a second message arrived before this one was answered: the robot's single receive buffer would merge them"}));
            }
            self.mem()
                .log(json!({"conn": conn, "recv": text.trim_end()}));
            let cmd = codec::parse_legacy_cmd(&text);
            if !started {
                // espera_inicio: anything but `inicio` is read and dropped.
                if cmd == LegacyCmd::Start {
                    started = true;
                    replies.send(codec::LEGACY_DONE.as_bytes().to_vec());
                }
                continue;
            }
            match cmd {
                LegacyCmd::Exit => {
                    replies.finish();
                    let _ = stream.shutdown(Shutdown::Both);
                    return Ok("EXIT");
                }
                LegacyCmd::Move { rapid, xyz } => {
                    // POINT move_pose = TRANS(xx, -1*yy, -1*zz, 0, 0, 0); SPEED 10|15 MM/S.
                    let to = [xyz[0], -xyz[1], -xyz[2]];
                    let speed = if rapid { 10.0 } else { 15.0 };
                    let kind = if rapid { "JMOVE" } else { "LMOVE" };
                    let (drop, garbage) = self.execute(conn, kind, None, to, speed);
                    if drop && self.cfg.drop_mode == DropMode::BeforeDone {
                        replies.abort();
                        let _ = stream.shutdown(Shutdown::Both);
                        return Ok("dropped before done");
                    }
                    if garbage {
                        replies.send(b"\x07#?garbage?#".to_vec());
                    }
                    replies.send(codec::LEGACY_DONE.as_bytes().to_vec());
                    if drop {
                        replies.finish();
                        let _ = stream.shutdown(Shutdown::Both);
                        return Ok("dropped after done");
                    }
                }
                LegacyCmd::Start | LegacyCmd::Unknown(_) => {
                    // The program falls through to `GOTO recv_cmd`: no answer at all.
                    self.mem().log(json!({"conn": conn, "violation":
                        format!("unknown command {:?} ignored without an answer", text.trim_end())}));
                }
            }
        }
    }

    // ------------------------------------------------------------ fresa-v1

    /// The generated fresa-v1 program: commands are read as they arrive (up to `queue`) and
    /// executed in order; every one is answered.
    fn v1(&self, conn: u64, stream: TcpStream) -> std::io::Result<&'static str> {
        let replies = Replies::start(stream.try_clone()?, self.cfg.reply_delay);
        self.mem().pos = [0.0; 3];
        replies.send(
            V1Msg::Hello {
                part_zero: self.part_zero(conn),
            }
            .encode()
            .into_bytes(),
        );
        // A reader thread plays the program's receive task: it queues what arrives.
        let (tx, rx) = mpsc::channel::<Option<String>>();
        let read_half = stream.try_clone()?;
        let reader = std::thread::spawn(move || {
            let mut r = BufReader::new(read_half);
            let mut line = Vec::new();
            loop {
                line.clear();
                match r.read_until(b'\n', &mut line) {
                    Ok(0) | Err(_) => {
                        let _ = tx.send(None);
                        return;
                    }
                    Ok(_) => {
                        if tx
                            .send(Some(String::from_utf8_lossy(&line).into_owned()))
                            .is_err()
                        {
                            return;
                        }
                    }
                }
            }
        });
        let mut speed = 5.0;
        let mut pending: VecDeque<String> = VecDeque::new();
        let mut closed = false;
        let result = loop {
            // Take everything that has arrived, then execute the oldest.
            while let Ok(msg) = if pending.is_empty() && !closed {
                rx.recv().map_err(|_| mpsc::TryRecvError::Disconnected)
            } else {
                rx.try_recv()
            } {
                match msg {
                    Some(text) => {
                        self.mem()
                            .log(json!({"conn": conn, "recv": text.trim_end()}));
                        pending.push_back(text);
                        if pending.len() > self.cfg.queue {
                            self.mem().log(json!({"conn": conn, "violation":
                                format!("{} commands queued, more than the robot's {}", pending.len(), self.cfg.queue)}));
                        }
                    }
                    None => {
                        closed = true;
                        break;
                    }
                }
            }
            if closed {
                // Link lost: the motion in progress has finished; queued commands are dropped
                // (the robot stops when its client is gone).
                break Ok("client closed");
            }
            let Some(text) = pending.pop_front() else {
                continue;
            };
            match V1Cmd::parse(&text) {
                Ok(V1Cmd::Run { tag }) => {
                    let last_seq = {
                        let mut m = self.mem();
                        if m.tag != tag {
                            m.tag = tag.clone();
                            m.last_seq = 0;
                        }
                        m.last_seq
                    };
                    replies.send(V1Msg::Run { tag, last_seq }.encode().into_bytes());
                }
                Ok(V1Cmd::Speed { seq, mm_s }) => {
                    speed = mm_s;
                    if seq > 0 {
                        self.mem().last_seq = seq;
                    }
                    replies.send(V1Msg::Done(seq).encode().into_bytes());
                }
                Ok(V1Cmd::Move { seq, rapid, to }) => {
                    let v = if rapid { self.cfg.rapid_mm_s } else { speed };
                    let kind = if rapid { "JMOVE" } else { "LMOVE" };
                    let (drop, garbage) = self.execute(conn, kind, Some(seq), to, v);
                    if seq > 0 {
                        self.mem().last_seq = seq;
                    }
                    if drop && self.cfg.drop_mode == DropMode::BeforeDone {
                        replies.abort();
                        break Ok("dropped before done");
                    }
                    if garbage {
                        replies.send(b"\x07#?garbage?#\n".to_vec());
                    }
                    replies.send(V1Msg::Done(seq).encode().into_bytes());
                    if drop {
                        replies.finish();
                        break Ok("dropped after done");
                    }
                }
                Ok(V1Cmd::Exit) => {
                    replies.send(V1Msg::Bye.encode().into_bytes());
                    replies.finish();
                    break Ok("EXIT");
                }
                Err((seq, message)) => {
                    self.mem().log(
                        json!({"conn": conn, "violation": format!("answered err: {message}")}),
                    );
                    replies.send(V1Msg::Err { seq, message }.encode().into_bytes());
                }
            }
        };
        let _ = stream.shutdown(Shutdown::Both);
        let _ = reader.join();
        result
    }
}

/// Replies leave through a writer thread, each `delay` after it was produced, so a latency
/// does not limit a pipelined throughput. Without a delay they are written at once (one
/// thread hop less per message).
struct Replies {
    direct: Option<Mutex<TcpStream>>,
    tx: Option<mpsc::Sender<(Instant, Vec<u8>)>>,
    thread: Option<std::thread::JoinHandle<()>>,
    abort: Arc<std::sync::atomic::AtomicBool>,
    delay: Duration,
}

impl Replies {
    fn start(mut stream: TcpStream, delay: Duration) -> Replies {
        let abort = Arc::new(std::sync::atomic::AtomicBool::new(false));
        if delay.is_zero() {
            return Replies {
                direct: Some(Mutex::new(stream)),
                tx: None,
                thread: None,
                abort,
                delay,
            };
        }
        let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>();
        let stop = abort.clone();
        let thread = std::thread::spawn(move || {
            for (due, bytes) in rx {
                let now = Instant::now();
                if due > now {
                    std::thread::sleep(due - now);
                }
                if stop.load(std::sync::atomic::Ordering::SeqCst) {
                    return;
                }
                // One write per message, like one TCP_SEND.
                if stream.write_all(&bytes).is_err() {
                    return;
                }
            }
        });
        Replies {
            direct: None,
            tx: Some(tx),
            thread: Some(thread),
            abort,
            delay,
        }
    }

    fn send(&self, bytes: Vec<u8>) {
        if let Some(d) = &self.direct {
            let _ = d
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .write_all(&bytes);
        } else if let Some(tx) = &self.tx {
            let _ = tx.send((Instant::now() + self.delay, bytes));
        }
    }

    /// Waits until every reply is written.
    fn finish(mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }

    /// Drops replies not yet written.
    fn abort(self) {
        self.abort.store(true, std::sync::atomic::Ordering::SeqCst);
        self.finish();
    }
}

impl Drop for Replies {
    fn drop(&mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Starts a simulator on `listener` in a background thread (for tests and the benchmark).
pub fn spawn(cfg: SimConfig, listener: TcpListener) -> std::io::Result<Shared> {
    let sim = Sim::new(cfg)?;
    let s = sim.clone();
    std::thread::spawn(move || s.serve(listener));
    Ok(sim)
}

impl Sim {
    /// Motions executed so far (over all connections).
    pub fn motions(&self) -> u64 {
        self.mem().motions
    }
}
