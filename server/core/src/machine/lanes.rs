//! The two lanes every call into a backend instance travels on: an ordinary lane (everything the
//! machine's task sends, one call at a time) and an urgent lane (stop, feed hold, reset,
//! shutdown) that never waits behind it. Each lane is one dedicated OS thread, so a plugin that
//! hangs holds at most those two threads: a call that overruns its timeout marks the machine
//! unresponsive and further ordinary calls are refused at once, instead of piling up threads
//! behind the hung one. The mark clears when the hung call finally returns.

use crate::error::{Error, ErrorKind};
use fresa_plugin_api::contract::Request;
use fresa_plugin_api::host::{CallError, Instance};
use fresa_plugin_api::operation::Lane;
use serde_json::Value;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc as std_mpsc;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::oneshot;

/// Why a call into a backend failed.
#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    #[error("machine backend is not available: {0}")]
    Unavailable(String),
    #[error("machine backend is unresponsive: {0}")]
    Unresponsive(String),
    #[error("machine backend did not answer within {0:?}")]
    Timeout(Duration),
    #[error("{0}")]
    Call(#[from] CallError),
}

type Job = Box<dyn FnOnce() + Send>;

struct Worker {
    tx: std_mpsc::Sender<Job>,
    /// What the overdue call on this lane is, while one is.
    overdue: Arc<Mutex<Option<String>>>,
}

impl Worker {
    fn spawn(name: String) -> std::io::Result<Worker> {
        let (tx, rx) = std_mpsc::channel::<Job>();
        std::thread::Builder::new().name(name).spawn(move || {
            while let Ok(job) = rx.recv() {
                job();
            }
        })?;
        Ok(Worker {
            tx,
            overdue: Arc::new(Mutex::new(None)),
        })
    }

    fn overdue(&self) -> Option<String> {
        self.overdue.lock().ok().and_then(|o| o.clone())
    }
}

pub struct Lanes {
    instance: Arc<Instance>,
    ordinary: Worker,
    urgent: Worker,
    timeout: Duration,
}

impl Lanes {
    pub fn new(instance: Instance, machine_id: i64, timeout: Duration) -> std::io::Result<Lanes> {
        Ok(Lanes {
            instance: Arc::new(instance),
            ordinary: Worker::spawn(format!("machine-{machine_id}"))?,
            urgent: Worker::spawn(format!("machine-{machine_id}-urgent"))?,
            timeout,
        })
    }

    /// Why the machine is unresponsive: a call on either lane has overrun its timeout and not
    /// returned yet.
    pub fn unresponsive(&self) -> Option<String> {
        self.ordinary.overdue().or_else(|| self.urgent.overdue())
    }

    /// Calls the backend on the request's lane and waits at most the call timeout.
    pub async fn call(&self, request: &Request) -> Result<Value, BackendError> {
        let lane = request.lane();
        let worker = match lane {
            Lane::Ordinary => &self.ordinary,
            Lane::Urgent => &self.urgent,
        };
        // A hung call occupies the lane: anything queued behind it would hang too.
        if let Some(what) = worker.overdue() {
            return Err(BackendError::Unresponsive(what));
        }
        let req = request.clone();
        let (tx, rx) = oneshot::channel();
        let instance = self.instance.clone();
        let overdue = worker.overdue.clone();
        let done = Arc::new(AtomicBool::new(false));
        let job_done = done.clone();
        let job: Job = Box::new(move || {
            let result = instance.call_request(&req);
            // Done and un-marked under one lock, so the timeout below cannot mark a call that
            // has already returned.
            if let Ok(mut o) = overdue.lock() {
                job_done.store(true, Ordering::SeqCst);
                *o = None;
            }
            let _ = tx.send(result);
        });
        worker
            .tx
            .send(job)
            .map_err(|_| BackendError::Unavailable("machine lane has stopped".into()))?;
        match tokio::time::timeout(self.timeout, rx).await {
            Ok(Ok(result)) => Ok(result?),
            Ok(Err(_)) => Err(BackendError::Call(CallError::Panic(
                "the backend call was dropped".into(),
            ))),
            Err(_) => {
                let what = format!(
                    "backend call `{}` has not returned after {:?} (the plugin seems hung)",
                    request.operation().name,
                    self.timeout
                );
                if let Ok(mut o) = worker.overdue.lock() {
                    if !done.load(Ordering::SeqCst) {
                        *o = Some(what);
                    }
                }
                Err(BackendError::Timeout(self.timeout))
            }
        }
    }
}

/// A backend failure: the plugin's own rejection is the caller's problem, a missing, hung or
/// unresponsive backend is the server's.
impl From<BackendError> for Error {
    fn from(e: BackendError) -> Self {
        match e {
            BackendError::Unavailable(m) => {
                Error::new(ErrorKind::Unavailable, "machine_offline", m)
            }
            BackendError::Unresponsive(m) => {
                Error::new(ErrorKind::Unavailable, "machine_unresponsive", m)
            }
            BackendError::Timeout(d) => Error::new(
                ErrorKind::Timeout,
                "backend_timeout",
                format!("machine backend did not answer within {d:?}"),
            ),
            // The controller's part zero moved since the run started: the operator must decide.
            BackendError::Call(CallError::Plugin(p)) if p.code == "part_zero_changed" => {
                Error::conflict("part_zero_changed", p.message)
            }
            BackendError::Call(CallError::Plugin(p)) => {
                let kind = if p.code == "busy" {
                    ErrorKind::Conflict
                } else {
                    ErrorKind::Invalid
                };
                Error::new(
                    kind,
                    "backend_rejected",
                    format!("{}: {}", p.code, p.message),
                )
            }
            BackendError::Call(other) => {
                Error::new(ErrorKind::Backend, "backend_error", other.to_string())
            }
        }
    }
}
