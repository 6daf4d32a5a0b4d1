//! A machine's tracker (issue 28, part 2): the one writer of its state changes
//! (`machine_states`) and its maintenance counters. It reads what the machine publishes (the
//! status the task publishes, `unresponsive` from the lanes, and the current run) and changes
//! nothing the task owns.
//!
//! It wakes on every published status and run change and at least once a [`TICK`]. Time is
//! attributed to what the previous sample showed (spindle on, moving), so a counter is exact to
//! the publication of the machine's status changes. State changes are written as they are seen;
//! counters every [`PERSIST_INTERVAL`] and at shutdown ([`Records::flush`]), each only upwards
//! (`Store::raise_counters`), so a kill -9 loses at most the last interval and nothing ever goes
//! backwards. While the database is unreachable both wait in memory (state changes up to
//! [`MAX_PENDING_STATES`], oldest dropped first).

use super::Machine;
use crate::events::{EventBus, EventKind};
use crate::records::{counter_value, util_state, MaintenanceItem};
use crate::store::{now_ms, CountersRow, MarkRow, Store};
use fresa_plugin_api::contract::{io, IoValue, MachineState, MachineStatus};
use serde::Serialize;
use serde_json::json;
use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The longest the tracker sleeps without a status change (it notices `unresponsive` and
/// keeps counting a spindle that runs with nothing else changing).
pub const TICK: Duration = Duration::from_secs(1);
/// How often counters are written while they change.
pub const PERSIST_INTERVAL: Duration = Duration::from_secs(5);
/// State changes kept in memory while the database is unreachable.
pub const MAX_PENDING_STATES: usize = 1024;

/// Counters in memory (ms and mm as floats: samples are a few ms apart, rounding each would
/// lose time).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Totals {
    spindle_ms: f64,
    motion_ms: f64,
    distance: [f64; 4],
    jobs: f64,
}

impl Totals {
    fn row(&self) -> CountersRow {
        CountersRow {
            spindle_ms: self.spindle_ms as i64,
            motion_ms: self.motion_ms as i64,
            distance_x: self.distance[0],
            distance_y: self.distance[1],
            distance_z: self.distance[2],
            distance_a: self.distance[3],
            jobs: self.jobs as i64,
        }
    }
    fn from_row(r: &CountersRow) -> Totals {
        Totals {
            spindle_ms: r.spindle_ms as f64,
            motion_ms: r.motion_ms as f64,
            distance: [r.distance_x, r.distance_y, r.distance_z, r.distance_a],
            jobs: r.jobs as f64,
        }
    }
    fn plus(&self, o: &Totals) -> Totals {
        let mut t = *self;
        t.spindle_ms += o.spindle_ms;
        t.motion_ms += o.motion_ms;
        for (d, e) in t.distance.iter_mut().zip(o.distance) {
            *d += e;
        }
        t.jobs += o.jobs;
        t
    }
}

#[derive(Default)]
struct Live {
    /// What the store held when the tracker read it (`None` until it could).
    base: Option<Totals>,
    /// Counted since.
    delta: Totals,
    items: Vec<MaintenanceItem>,
    marks: BTreeMap<String, MarkRow>,
    /// State changes not yet in the store.
    pending_states: VecDeque<(&'static str, i64)>,
    state: Option<&'static str>,
    /// Seconds in each state since this process started (for `/metrics`).
    state_seconds: BTreeMap<&'static str, f64>,
    /// Set at shutdown: no more writes.
    closed: bool,
}

/// One maintenance interval as `GET /machines/{id}/counters` shows it.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct MaintenanceView {
    pub name: String,
    /// `spindle_hours`, `motion_hours` or `jobs`.
    pub counter: String,
    pub every: f64,
    /// The counter's value when it was last done (0: never).
    pub done_value: f64,
    /// How much of the interval has passed.
    pub since_done: f64,
    pub due: bool,
    pub done_at: Option<i64>,
    pub done_by: Option<String>,
}

/// A machine's counters (`GET /machines/{id}/counters`).
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CountersView {
    pub machine: i64,
    pub spindle_hours: f64,
    pub motion_hours: f64,
    /// Distance travelled per axis (mm; degrees for A).
    #[schema(value_type = Object)]
    pub distance_mm: serde_json::Value,
    pub jobs: i64,
    /// The state the machine is in now, as utilisation counts it.
    pub state: Option<String>,
    pub maintenance: Vec<MaintenanceView>,
    /// False until the stored counters were read (the database was unreachable since start):
    /// the values are then only what was counted since.
    pub loaded: bool,
}

/// The tracker's shared state, held by the machine's handle.
#[derive(Default)]
pub struct Records {
    live: Mutex<Live>,
}

impl Records {
    fn lock(&self) -> std::sync::MutexGuard<'_, Live> {
        // A panic elsewhere while holding it leaves plain numbers behind: still usable.
        self.live.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn totals(live: &Live) -> Totals {
        live.base.unwrap_or_default().plus(&live.delta)
    }

    pub fn view(&self, machine: i64) -> CountersView {
        let live = self.lock();
        let t = Self::totals(&live);
        let row = t.row();
        let maintenance = live
            .items
            .iter()
            .map(|item| maintenance_view(item, &row, live.marks.get(&item.name)))
            .collect();
        CountersView {
            machine,
            // Whole ms, as stored: what is shown is never more than a restart reads back.
            spindle_hours: row.spindle_ms as f64 / 3_600_000.0,
            motion_hours: row.motion_ms as f64 / 3_600_000.0,
            distance_mm: json!({"x": t.distance[0], "y": t.distance[1], "z": t.distance[2], "a": t.distance[3]}),
            jobs: row.jobs,
            state: live.state.map(str::to_string),
            maintenance,
            loaded: live.base.is_some(),
        }
    }

    /// Seconds in each utilisation state since this process started.
    pub fn state_seconds(&self) -> BTreeMap<&'static str, f64> {
        self.lock().state_seconds.clone()
    }

    /// Shutdown: the counters as they are now and an `offline` state change are written (the
    /// machine is not driven until the next start), and the tracker writes nothing after.
    pub async fn flush(&self, machine: i64, store: &Store) {
        let (row, states) = {
            let mut live = self.lock();
            if live.closed {
                return;
            }
            live.closed = true;
            let now = now_ms();
            if live.state != Some("offline") {
                push_state(&mut live, "offline", now);
            }
            let row = live.base.map(|b| b.plus(&live.delta).row());
            (row, std::mem::take(&mut live.pending_states))
        };
        for (state, since) in states {
            if let Err(e) = store.insert_machine_state(machine, state, since).await {
                tracing::warn!(machine, error = %e, "could not record the machine's state at shutdown");
                break;
            }
        }
        if let Some(row) = row {
            if let Err(e) = store.raise_counters(machine, &row).await {
                tracing::warn!(machine, error = %e, "could not store the maintenance counters at shutdown");
            }
        }
    }
}

fn maintenance_view(
    item: &MaintenanceItem,
    row: &CountersRow,
    mark: Option<&MarkRow>,
) -> MaintenanceView {
    let (counter, every) = item.interval();
    let done_value = mark.map_or(0.0, |m| m.done_value);
    let since_done = (counter_value(counter, row) - done_value).max(0.0);
    MaintenanceView {
        name: item.name.clone(),
        counter: counter.to_string(),
        every,
        done_value,
        since_done,
        due: since_done >= every,
        done_at: mark.and_then(|m| m.done_at),
        done_by: mark.and_then(|m| m.done_by.clone()),
    }
}

fn push_state(live: &mut Live, state: &'static str, since: i64) {
    live.state = Some(state);
    if live.pending_states.len() >= MAX_PENDING_STATES {
        live.pending_states.pop_front();
        tracing::warn!("machine state changes waiting for the database: the oldest was dropped");
    }
    live.pending_states.push_back((state, since));
}

/// What one look at the machine showed.
struct Sample {
    at: Instant,
    state: MachineState,
    spindle_on: bool,
    position: [f64; 4],
}

fn sample(status: &MachineStatus) -> Sample {
    let spindle_on = match status.outputs.get(io::SPINDLE) {
        Some(Some(IoValue::On(on))) => *on,
        _ => matches!(
            status.outputs.get(io::SPINDLE_RPM),
            Some(Some(IoValue::Number(rpm))) if *rpm > 0.0
        ),
    };
    let p = &status.machine_position;
    Sample {
        at: Instant::now(),
        state: status.state,
        spindle_on,
        position: [p.x, p.y, p.z, p.a],
    }
}

impl Machine {
    /// Shutdown: see [`Records::flush`].
    pub async fn flush_records(&self, store: &Store) {
        self.records.flush(self.id, store).await;
    }

    /// Seconds in each utilisation state since this process started (for `/metrics`).
    pub fn state_seconds(&self) -> BTreeMap<&'static str, f64> {
        self.records.state_seconds()
    }

    /// The machine's counters and maintenance intervals, as the tracker has them now.
    pub fn counters(&self) -> CountersView {
        self.records.view(self.id)
    }

    /// Marks the maintenance interval `name` done by `actor`: it starts again from the counter's
    /// value now; audited as `machine.maintenance_done`.
    pub async fn maintenance_done(
        &self,
        store: &Store,
        name: &str,
        actor: &str,
    ) -> crate::error::Result<MaintenanceView> {
        let (item, row, loaded) = {
            let live = self.records.lock();
            let item = live.items.iter().find(|i| i.name == name).cloned();
            (item, Records::totals(&live).row(), live.base.is_some())
        };
        let Some(item) = item else {
            return Err(crate::error::Error::not_found(
                "unknown_maintenance",
                format!(
                    "machine {} has no maintenance interval named {name:?}",
                    self.id
                ),
            ));
        };
        if !loaded {
            return Err(crate::error::Error::new(
                crate::error::ErrorKind::Unavailable,
                "database_unavailable",
                "the machine's counters have not been read from the database yet",
            ));
        }
        let value = item.value(&row);
        store
            .health()
            .guard(store.maintenance_done(self.id, name, value, actor))
            .await?;
        let mark = MarkRow {
            name: name.to_string(),
            done_value: value,
            due_raised: 0,
            done_at: Some(now_ms()),
            done_by: Some(actor.to_string()),
        };
        self.records
            .lock()
            .marks
            .insert(name.to_string(), mark.clone());
        let (counter, every) = item.interval();
        self.bus
            .record_or_log(
                EventKind::MachineMaintenanceDone,
                Some(self.id),
                Some(actor),
                json!({"name": name, "counter": counter, "every": every, "value": value}),
            )
            .await;
        Ok(maintenance_view(&item, &row, Some(&mark)))
    }
}

/// The tracker's task: runs as long as the machine's task.
pub(super) async fn track(machine: Arc<Machine>, store: Store, bus: EventBus) {
    let mut status = machine.status.clone();
    let mut run = machine.run.clone();
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut prev: Option<Sample> = None;
    let mut last_run = run.borrow().as_ref().map(|r| r.run_id);
    let mut last_persist = Instant::now();
    let mut dirty = false;
    let id = machine.id;
    loop {
        tokio::select! {
            _ = status.changed() => {}
            _ = run.changed() => {}
            _ = tick.tick() => {}
        }
        if machine.tx.is_closed() {
            return;
        }
        let now = sample(&machine.status());
        let wall = now_ms();
        let current_run = run.borrow_and_update().as_ref().map(|r| r.run_id);
        status.borrow_and_update();
        {
            let mut live = machine.records.lock();
            if live.closed {
                return;
            }
            if let Some(p) = &prev {
                let dt = now.at.duration_since(p.at).as_secs_f64() * 1000.0;
                if p.spindle_on {
                    live.delta.spindle_ms += dt;
                    dirty = true;
                }
                if matches!(
                    p.state,
                    MachineState::Running | MachineState::Jogging | MachineState::Homing
                ) {
                    live.delta.motion_ms += dt;
                    dirty = true;
                }
                // A position across a lost link (offline, unresponsive) is no travel.
                let known = |s: MachineState| {
                    !matches!(s, MachineState::Offline | MachineState::Unresponsive)
                };
                if known(p.state) && known(now.state) {
                    for (i, d) in live.delta.distance.iter_mut().enumerate() {
                        let step = (now.position[i] - p.position[i]).abs();
                        if step.is_finite() && step > 0.0 {
                            *d += step;
                            dirty = true;
                        }
                    }
                }
                if let Some(s) = live.state {
                    *live.state_seconds.entry(s).or_default() += dt / 1000.0;
                }
            }
            if last_run.is_some() && current_run != last_run {
                live.delta.jobs += 1.0;
                dirty = true;
            }
            let state = util_state(now.state);
            if live.state != Some(state) {
                push_state(&mut live, state, wall);
            }
        }
        last_run = current_run;
        prev = Some(now);
        write_states(&machine, &store).await;
        if machine.records.lock().base.is_none() {
            load(&machine, &store).await;
        }
        if dirty && last_persist.elapsed() >= PERSIST_INTERVAL {
            let row = {
                let live = machine.records.lock();
                live.base.map(|b| b.plus(&live.delta).row())
            };
            if let Some(row) = row {
                if store
                    .health()
                    .guard(store.raise_counters(id, &row))
                    .await
                    .is_ok()
                {
                    dirty = false;
                    last_persist = Instant::now();
                }
            }
        }
        check_maintenance(&machine, &store, &bus).await;
    }
}

/// Writes the state changes waiting, in order; stops at the first failure.
async fn write_states(machine: &Machine, store: &Store) {
    loop {
        let next = machine.records.lock().pending_states.front().copied();
        let Some((state, since)) = next else { return };
        if let Err(e) = store
            .health()
            .guard(store.insert_machine_state(machine.id, state, since))
            .await
        {
            tracing::debug!(machine = machine.id, error = %e, "machine state change kept until the database answers");
            return;
        }
        machine.records.lock().pending_states.pop_front();
    }
}

/// Reads the stored counters, intervals and marks (once, when the database answers).
async fn load(machine: &Machine, store: &Store) {
    let health = store.health();
    let read = async {
        let counters = health.guard(store.counters(machine.id)).await?;
        let items = health.guard(store.machine_maintenance(machine.id)).await?;
        let marks = health.guard(store.maintenance_marks(machine.id)).await?;
        Ok::<_, crate::error::Error>((counters, items, marks))
    }
    .await;
    match read {
        Ok((counters, items, marks)) => {
            let items: Vec<MaintenanceItem> = items
                .and_then(|t| serde_json::from_str(&t).ok())
                .unwrap_or_default();
            let mut live = machine.records.lock();
            live.base = Some(counters.as_ref().map(Totals::from_row).unwrap_or_default());
            live.items = items;
            live.marks = marks.into_iter().map(|m| (m.name.clone(), m)).collect();
        }
        Err(e) => {
            tracing::debug!(machine = machine.id, error = %e, "maintenance counters not read yet")
        }
    }
}

/// Raises `machine.maintenance_due` for each interval that came due and was not raised yet.
/// The store's mark is set first (compare-and-set): once per crossing, also across restarts
/// and nodes.
async fn check_maintenance(machine: &Machine, store: &Store, bus: &EventBus) {
    let due: Vec<(MaintenanceItem, f64, f64)> = {
        let mut live = machine.records.lock();
        if live.base.is_none() {
            return;
        }
        let row = Records::totals(&live).row();
        let mut due = Vec::new();
        let items = live.items.clone();
        for item in items {
            let mark = live.marks.entry(item.name.clone()).or_insert(MarkRow {
                name: item.name.clone(),
                done_value: 0.0,
                due_raised: 0,
                done_at: None,
                done_by: None,
            });
            let value = item.value(&row);
            let (_, every) = item.interval();
            if mark.due_raised == 0 && value - mark.done_value >= every {
                mark.due_raised = 1;
                due.push((item, value, value - mark.done_value));
            }
        }
        due
    };
    for (item, value, since_done) in due {
        match store
            .health()
            .guard(store.raise_maintenance_due(machine.id, &item.name))
            .await
        {
            Ok(true) => {
                let (counter, every) = item.interval();
                bus.record_or_log(
                    EventKind::MachineMaintenanceDue,
                    Some(machine.id),
                    None,
                    json!({"name": item.name, "counter": counter, "every": every,
                           "value": value, "since_done": since_done}),
                )
                .await;
            }
            Ok(false) => {}
            Err(_) => {
                // Tried again on the next look.
                if let Some(m) = machine.records.lock().marks.get_mut(&item.name) {
                    m.due_raised = 0;
                }
            }
        }
    }
}
