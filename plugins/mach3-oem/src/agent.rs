//! The agent: serves the protocol of `protocol.rs` on TCP and makes every Mach3 call on ONE
//! thread (the COM single-threaded apartment on Windows), from a queue where urgent batches go
//! first and each batch has a deadline. A connection that jogged with `JogOn` gets `JogOff` on
//! those axes when it goes away or goes quiet (watchdog), or when Mach3 stops answering.

use crate::mach3::{Call, ErrorKind, Mach3, Mach3Error};
use crate::protocol::{self, Auth, CallResult, Hello, Request, Response, Welcome};
use std::collections::{BTreeSet, VecDeque};
use std::io::{BufReader, BufWriter, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// Builds the Mach3 link on the Mach3 thread itself (COM objects must stay on their thread).
pub type Mach3Factory = Box<dyn FnOnce() -> Box<dyn Mach3> + Send>;

#[derive(Debug, Clone)]
pub struct AgentConfig {
    pub secret: String,
    /// Longest wait for one Mach3 call.
    pub call_timeout: Duration,
    /// A connection silent this long is closed (and its jogs ended). Clients poll faster.
    pub watchdog: Duration,
    /// Where `write_program` stores programs for `LoadFile`.
    pub program_dir: PathBuf,
}

struct Job {
    calls: Vec<Call>,
    /// Dropped unrun if the requester gave up waiting; `None` for safety calls (JogOff).
    deadline: Option<Instant>,
    reply: mpsc::Sender<Vec<CallResult>>,
}

#[derive(Default)]
struct Queue {
    jobs: Mutex<VecDeque<Job>>,
    ready: Condvar,
}

impl Queue {
    fn push(&self, job: Job, urgent: bool) {
        let mut q = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
        if urgent {
            q.push_front(job);
        } else {
            q.push_back(job);
        }
        self.ready.notify_one();
    }

    fn pop(&self) -> Job {
        let mut q = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if let Some(j) = q.pop_front() {
                return j;
            }
            q = self.ready.wait(q).unwrap_or_else(|e| e.into_inner());
        }
    }
}

pub struct Agent {
    listener: TcpListener,
    cfg: Arc<AgentConfig>,
    queue: Arc<Queue>,
}

fn log(message: &str) {
    eprintln!("{AGENT}: {message}", AGENT = protocol::AGENT_NAME);
}

impl Agent {
    /// Binds `addr` and starts the Mach3 thread.
    pub fn bind(addr: &str, cfg: AgentConfig, factory: Mach3Factory) -> std::io::Result<Agent> {
        std::fs::create_dir_all(&cfg.program_dir)?;
        let listener = TcpListener::bind(addr)?;
        let queue = Arc::new(Queue::default());
        let q = Arc::clone(&queue);
        std::thread::Builder::new()
            .name("mach3".into())
            .spawn(move || mach3_thread(factory, &q))?;
        Ok(Agent {
            listener,
            cfg: Arc::new(cfg),
            queue,
        })
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// Accepts connections forever, one thread each.
    pub fn serve(self) {
        for stream in self.listener.incoming() {
            let stream = match stream {
                Ok(s) => s,
                Err(e) => {
                    log(&format!("accept failed: {e}"));
                    continue;
                }
            };
            let conn = Connection {
                cfg: Arc::clone(&self.cfg),
                queue: Arc::clone(&self.queue),
                jogged: BTreeSet::new(),
            };
            let spawned = std::thread::Builder::new()
                .name("agent connection".into())
                .spawn(move || conn.run(stream));
            if let Err(e) = spawned {
                log(&format!("cannot start a connection thread: {e}"));
            }
        }
    }
}

fn mach3_thread(factory: Mach3Factory, queue: &Queue) {
    let mut mach3 = factory();
    loop {
        let job = queue.pop();
        if job.deadline.is_some_and(|d| Instant::now() >= d) {
            continue; // its requester already answered "timeout"
        }
        let results = job
            .calls
            .iter()
            .map(|c| match c.apply(mach3.as_mut()) {
                Ok(v) => CallResult::Ok(v),
                Err(e) => CallResult::Err(e),
            })
            .collect();
        let _ = job.reply.send(results);
    }
}

struct Connection {
    cfg: Arc<AgentConfig>,
    queue: Arc<Queue>,
    /// Axes this connection started with `JogOn` and has not stopped.
    jogged: BTreeSet<i16>,
}

impl Connection {
    fn run(mut self, stream: TcpStream) {
        let peer = stream
            .peer_addr()
            .map(|a| a.to_string())
            .unwrap_or_else(|_| "?".into());
        match self.serve(stream) {
            Ok(()) => log(&format!("{peer}: disconnected")),
            Err(e) => log(&format!("{peer}: connection ended: {e}")),
        }
        self.stop_jogs("the connection ended");
    }

    fn serve(&mut self, stream: TcpStream) -> std::io::Result<()> {
        stream.set_read_timeout(Some(self.cfg.watchdog))?;
        stream.set_write_timeout(Some(self.cfg.call_timeout))?;
        stream.set_nodelay(true)?;
        let mut reader = BufReader::new(stream.try_clone()?);
        let mut writer = BufWriter::new(stream);
        let nonce = protocol::new_nonce();
        protocol::write_frame(
            &mut writer,
            &Hello {
                agent: protocol::AGENT_NAME.into(),
                protocol: protocol::PROTOCOL_VERSION,
                nonce: nonce.clone(),
                features: protocol::FEATURES.iter().map(|f| f.to_string()).collect(),
            },
        )?;
        let mut buf = Vec::new();
        if !protocol::read_frame(&mut reader, &mut buf)? {
            return Ok(());
        }
        let refuse = match serde_json::from_slice::<Auth>(&buf) {
            Err(e) => Some(protocol::protocol_error(format!(
                "expected {{\"protocol\":1,\"auth\":...}}: {e}"
            ))),
            Ok(a) if a.protocol != protocol::PROTOCOL_VERSION => {
                Some(protocol::protocol_error(format!(
                    "this agent speaks protocol {}, the client {}",
                    protocol::PROTOCOL_VERSION,
                    a.protocol
                )))
            }
            Ok(a) if !protocol::verify(&self.cfg.secret, &nonce, &a.auth) => Some(Mach3Error::new(
                ErrorKind::Auth,
                "wrong secret: check the `secret` in the server's machine config",
            )),
            Ok(_) => None,
        };
        let welcome = Welcome {
            ok: refuse.is_none(),
            error: refuse.clone(),
        };
        protocol::write_frame(&mut writer, &welcome)?;
        if let Some(e) = refuse {
            return Err(std::io::Error::other(format!("handshake refused: {e}")));
        }
        while protocol::read_frame(&mut reader, &mut buf)? {
            let response = match serde_json::from_slice::<Request>(&buf) {
                Ok(req) => Response {
                    id: Some(req.id),
                    results: self.handle(req),
                    error: None,
                },
                Err(e) => {
                    let excerpt = protocol::frame_excerpt(&buf);
                    log(&format!("malformed request skipped: {e}: {excerpt}"));
                    let id = serde_json::from_slice::<serde_json::Value>(&buf)
                        .ok()
                        .and_then(|v| v["id"].as_u64());
                    Response {
                        id,
                        results: Vec::new(),
                        error: Some(protocol::protocol_error(format!(
                            "malformed request ({e}): {excerpt}"
                        ))),
                    }
                }
            };
            protocol::write_frame(&mut writer, &response)?;
        }
        Ok(())
    }

    /// Runs a request: consecutive Mach3 calls as one job, `write_program` here.
    fn handle(&mut self, req: Request) -> Vec<CallResult> {
        let mut results = Vec::with_capacity(req.calls.len());
        let mut pending: Vec<Call> = Vec::new();
        for call in req.calls {
            if let Call::WriteProgram { .. } = call {
                let batch = std::mem::take(&mut pending);
                results.extend(self.mach3(batch, req.urgent));
                results.push(match write_program(&self.cfg.program_dir, &call) {
                    Ok(v) => CallResult::Ok(v),
                    Err(e) => CallResult::Err(e),
                });
            } else {
                pending.push(call);
            }
        }
        results.extend(self.mach3(pending, req.urgent));
        results
    }

    fn mach3(&mut self, calls: Vec<Call>, urgent: bool) -> Vec<CallResult> {
        if calls.is_empty() {
            return Vec::new();
        }
        let results = submit(&self.queue, &self.cfg, calls.clone(), urgent, true);
        let mut lost = false;
        for (call, result) in calls.iter().zip(&results) {
            match (call, result) {
                (Call::JogOn { axis, .. }, CallResult::Ok(_)) => {
                    self.jogged.insert(*axis);
                }
                (Call::JogOff { axis }, CallResult::Ok(_)) => {
                    self.jogged.remove(axis);
                }
                (_, CallResult::Err(e))
                    if matches!(
                        e.kind,
                        ErrorKind::NotRunning | ErrorKind::Timeout | ErrorKind::Com
                    ) =>
                {
                    lost = true
                }
                _ => {}
            }
        }
        if lost {
            self.stop_jogs("Mach3 stopped answering");
        }
        results
    }

    /// Best effort `JogOff` on every axis this connection jogged.
    fn stop_jogs(&mut self, why: &str) {
        if self.jogged.is_empty() {
            return;
        }
        let calls: Vec<Call> = self
            .jogged
            .iter()
            .map(|&axis| Call::JogOff { axis })
            .collect();
        log(&format!("{why}: JogOff on axes {:?}", self.jogged));
        self.jogged.clear();
        for r in submit(&self.queue, &self.cfg, calls, true, false) {
            if let CallResult::Err(e) = r {
                log(&format!("JogOff failed: {e}"));
            }
        }
    }
}

/// Queues `calls` as one job and waits for the results, at most `call_timeout` per call.
fn submit(
    queue: &Queue,
    cfg: &AgentConfig,
    calls: Vec<Call>,
    urgent: bool,
    expires: bool,
) -> Vec<CallResult> {
    let n = calls.len();
    let wait = cfg.call_timeout * u32::try_from(n.max(1)).unwrap_or(u32::MAX);
    let (tx, rx) = mpsc::channel();
    queue.push(
        Job {
            calls,
            deadline: expires.then(|| Instant::now() + wait),
            reply: tx,
        },
        urgent,
    );
    match rx.recv_timeout(wait) {
        Ok(r) => r,
        Err(_) => {
            let e = Mach3Error::new(
                ErrorKind::Timeout,
                format!("Mach3 did not answer within {wait:?} (busy or hung?)"),
            );
            vec![CallResult::Err(e); n]
        }
    }
}

/// A program name the agent accepts: a plain file name, no path.
fn valid_program_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
}

fn write_program(dir: &Path, call: &Call) -> Result<serde_json::Value, Mach3Error> {
    let Call::WriteProgram {
        name,
        data,
        first,
        last,
    } = call
    else {
        return Err(Mach3Error::invalid("not a write_program call"));
    };
    if !valid_program_name(name) {
        return Err(Mach3Error::invalid(format!(
            "program name {name:?}: use 1-64 of A-Z a-z 0-9 . _ - (not starting with .)"
        )));
    }
    let io = |what: &str, e: std::io::Error| Mach3Error::new(ErrorKind::Io, format!("{what}: {e}"));
    let part = dir.join(format!("{name}.part"));
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .write(true)
        .append(!first)
        .truncate(*first)
        .open(&part)
        .map_err(|e| io(&format!("cannot open {}", part.display()), e))?;
    file.write_all(data.as_bytes())
        .map_err(|e| io(&format!("cannot write {}", part.display()), e))?;
    if !last {
        return Ok(serde_json::Value::Null);
    }
    file.sync_all()
        .map_err(|e| io(&format!("cannot flush {}", part.display()), e))?;
    drop(file);
    let done = dir.join(name);
    std::fs::rename(&part, &done)
        .map_err(|e| io(&format!("cannot rename to {}", done.display()), e))?;
    let full = std::path::absolute(&done).unwrap_or(done);
    Ok(serde_json::Value::String(
        full.to_string_lossy().into_owned(),
    ))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    #[test]
    fn program_names_are_plain_file_names() {
        for ok in ["fresa-run-12.nc", "a", "x_y.tap"] {
            assert!(valid_program_name(ok), "{ok}");
        }
        for bad in ["", "../x", "a/b", "a\\b", ".hidden", "c:x", &"x".repeat(65)] {
            assert!(!valid_program_name(bad), "{bad}");
        }
    }
}
