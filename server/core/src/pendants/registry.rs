//! The live pendants, by id: each one's row, plugin instance, macros and link state. Only the
//! data; what a pendant's input does is in the parent module.

use super::inbox::Inbox;
use crate::store::{MacroAction, PendantRow};
use fresa_plugin_api::contract::PendantEvent;
use fresa_plugin_api::host::{HostSink, Instance};
use fresa_plugin_api::quiet::Quiet;
use serde_json::Value;
use std::collections::HashMap;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex as StdMutex};
use tokio::sync::RwLock;
use tokio_util::sync::CancellationToken;

pub struct Pendant {
    pub id: i64,
    pub(super) row: StdMutex<PendantRow>,
    pub(super) instance: StdMutex<Option<Arc<Instance>>>,
    /// Why there is no instance (plugin missing, config rejected).
    pub unavailable: Option<String>,
    /// Inputs not carried out yet, and the link state (see [`Inbox`]).
    pub(super) inbox: Arc<Inbox>,
    pub(super) macros: StdMutex<[Option<MacroAction>; 4]>,
    /// Run this pendant started (Start key), for the lost-pendant policy.
    pub(super) started_run: StdMutex<Option<i64>>,
    /// The last input was a step of the firmware's "Set cero" routine (a 0.0001-step Z- wheel
    /// frame): a `ZeroZ` right after it ends the routine on the touch plate.
    pub(super) in_set_cero: AtomicBool,
    pub(super) stop: CancellationToken,
    /// Refusals and failed status pushes can repeat per wheel event or per push: rate-limited.
    pub(super) quiet: Quiet,
}

pub(super) fn lock<T>(m: &StdMutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Pendant {
    pub fn row(&self) -> PendantRow {
        lock(&self.row).clone()
    }
    /// The link, as the transport reports it (not delayed by inputs still waiting).
    pub fn connected(&self) -> bool {
        self.inbox.connected()
    }
    pub fn macros(&self) -> [Option<MacroAction>; 4] {
        lock(&self.macros).clone()
    }
    pub fn set_macro(&self, slot: u8, action: Option<MacroAction>) {
        if let Some(cell) = lock(&self.macros).get_mut(slot as usize - 1) {
            *cell = action;
        }
    }
    /// Binds the pendant to `machine` at once: motion queued for the old machine is dropped
    /// now, and inputs arriving from now on are for the new one (a key pressed right after a
    /// rebind must not wait for the status task to bind it, nor be dropped when it does).
    pub async fn set_machine(&self, app: &crate::App, machine: Option<i64>) {
        let m = match machine {
            Some(id) => app.machines.get(id),
            None => None,
        };
        lock(&self.row).machine_id = machine;
        super::bind(self, m.as_deref());
    }
    pub(super) fn actor(&self) -> String {
        format!("pendant:{}", self.id)
    }
    pub(super) fn instance(&self) -> Option<Arc<Instance>> {
        lock(&self.instance).clone()
    }
    pub(super) fn stop_program_on_lost(&self) -> bool {
        self.row().config_json()["stop_program_on_lost"].as_bool() == Some(true)
    }
    /// The touch plate's thickness (`config.touch_plate_mm`), checked when the pendant was made.
    pub(super) fn touch_plate_mm(&self) -> Option<f64> {
        self.row().config_json()["touch_plate_mm"]
            .as_f64()
            .filter(|mm| *mm > 0.0)
    }
}

#[derive(Default)]
pub struct Pendants {
    pub(super) map: RwLock<HashMap<i64, Arc<Pendant>>>,
    /// Per machine, the pendant that last started motion on it (jog, go to zero).
    pub(super) last_mover: StdMutex<HashMap<i64, i64>>,
    /// The mDNS browser, started on the first request for the discovered list.
    pub(super) discovery: tokio::sync::Mutex<Option<Arc<Instance>>>,
}

impl Pendants {
    pub async fn get(&self, id: i64) -> Option<Arc<Pendant>> {
        self.map.read().await.get(&id).cloned()
    }
    pub async fn all(&self) -> Vec<Arc<Pendant>> {
        let mut v: Vec<_> = self.map.read().await.values().cloned().collect();
        v.sort_by_key(|p| p.id);
        v
    }
    /// Stops and forgets a pendant: its link is closed.
    pub async fn remove(&self, id: i64) {
        if let Some(p) = self.map.write().await.remove(&id) {
            shut(&p).await;
        }
    }

    pub async fn stop_all(&self) {
        if let Some(d) = self.discovery.lock().await.take() {
            let _ = tokio::task::spawn_blocking(move || drop(d)).await;
        }
        let all: Vec<_> = self.map.write().await.drain().map(|(_, p)| p).collect();
        for p in all {
            shut(&p).await;
        }
    }
}

impl Pendants {
    pub(super) fn last_mover_set(&self, machine: i64, pendant: i64) {
        lock(&self.last_mover).insert(machine, pendant);
    }
    pub(super) fn last_mover_take_if(&self, machine: i64, pendant: i64) -> bool {
        let mut m = lock(&self.last_mover);
        if m.get(&machine) == Some(&pendant) {
            m.remove(&machine);
            true
        } else {
            false
        }
    }
}

pub(super) async fn shut(p: &Pendant) {
    p.stop.cancel();
    let inst = lock(&p.instance).take();
    // Dropping the instance joins the transport thread: not on the async runtime.
    if let Some(i) = inst {
        let _ = tokio::task::spawn_blocking(move || drop(i)).await;
    }
}

pub(super) struct Sink {
    pub(super) inbox: Arc<Inbox>,
    pub(super) id: i64,
    pub(super) quiet: Quiet,
}

impl Sink {
    /// Queues a decoded event at once (bounded, never blocks), or warns about one that is JSON
    /// but not a pendant event.
    fn accept(
        &self,
        decoded: std::result::Result<PendantEvent, serde_json::Error>,
        raw: &dyn Fn() -> String,
    ) {
        match decoded {
            Ok(e) => self.inbox.push(e),
            Err(e) => {
                if let Some(line) = self.quiet.admit("unknown-event", || {
                    format!("unknown pendant event {}; ignored: {e}", raw())
                }) {
                    tracing::warn!(pendant = self.id, "{line}");
                }
            }
        }
    }
}

impl HostSink for Sink {
    fn event(&self, event: Value) {
        use serde::Deserialize;
        self.accept(PendantEvent::deserialize(&event), &|| event.to_string());
    }
    /// On the plugin's thread: straight from the plugin's bytes to the contract's event.
    fn event_json(&self, bytes: &[u8]) -> std::result::Result<(), serde_json::Error> {
        let decoded = fresa_plugin_api::host::decode_event::<PendantEvent>(bytes)?;
        self.accept(decoded, &|| String::from_utf8_lossy(bytes).into_owned());
        Ok(())
    }
    fn log(&self, level: u32, message: &str) {
        use fresa_plugin_api::abi::*;
        let id = self.id;
        match level {
            LOG_ERROR => tracing::error!(pendant = id, "{message}"),
            LOG_WARN => tracing::warn!(pendant = id, "{message}"),
            LOG_INFO => tracing::info!(pendant = id, "{message}"),
            _ => tracing::debug!(pendant = id, "{message}"),
        }
    }
}
