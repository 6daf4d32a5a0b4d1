//! The machine's task: the only code that changes a machine's run, its row and its published
//! status. Requests arrive on one channel, pause and cancel on an urgent one, backend events on
//! a third; queued backend events are always handled before the next request, so a request sees
//! the run as the backend last reported it. Each request is answered once what it asked for is
//! true (recorded in the store and, for motion, acknowledged by the backend).
//!
//! Pause and cancel never wait behind an ordinary message: the urgent channel is read first, and
//! while the task waits for an ordinary backend call (a program loading, an artifact being
//! generated) it serves them in between (not during a call that starts motion: that answers
//! once motion has begun, and a pause or cancel then acts on the motion). That is the one place
//! a request's handling is interleaved with another's. A start under way copes: a cancel moves
//! the stop gate, so the start is refused before it sets the machine moving; a pause while the
//! program loads holds the run before it starts (it starts on resume); run writes are
//! compare-and-set.

use super::lanes::{BackendError, Lanes};
use super::preamble::Launch;
use super::{Gate, Msg, RunView};
use crate::error::{Error, Result};
use crate::events::EventBus;
use crate::events::EventKind;
use crate::store::{JobRow, MachineRow, PartZeroRow, RunRow, RunState, Store};
use fresa_plugin_api::contract::{
    AxisValues, Command, Event, MachineState, MachineStatus, OffsetTable, OutputName, Request,
    RunAction, RunOutcome, WorkOffset,
};
use fresa_plugin_api::operation::Lane;
use serde_json::{json, Value};
use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use tokio::sync::{mpsc, watch};

pub(super) struct Task {
    pub id: i64,
    pub lanes: Option<Arc<Lanes>>,
    pub unavailable: Option<String>,
    pub store: Store,
    pub bus: EventBus,
    pub programs_dir: PathBuf,
    pub max_program_segments: u64,
    pub status: watch::Sender<MachineStatus>,
    pub row: watch::Sender<MachineRow>,
    pub run: watch::Sender<Option<RunView>>,
    pub gate: Arc<Gate>,
    /// The job of the current run, published so that pause and cancel find it while the
    /// database is unreachable.
    pub job: watch::Sender<Option<JobRow>>,
    /// The current run's row as it was launched (the store's copy is the truth while it answers);
    /// published so reads find the running job's run while the database is down.
    pub launched: watch::Sender<Option<RunRow>>,
    /// Where probing moves' ends are published (see `super::probing`).
    pub probe_ended: watch::Sender<Option<super::probing::ProbeEnd>>,
    /// Run writes not yet in the store: acknowledged lines (always, until the batch is flushed)
    /// and, while the database is unreachable, run transitions.
    pub pending: PendingWrites,
    /// The runs whose acknowledged lines are only in `pending`, recorded beside the store so a
    /// restart knows their stored line is behind.
    pub unstored: super::unstored::Marker,
    /// Pause and cancel ([`Msg::Pause`], [`Msg::Cancel`]): served before the ordinary channel,
    /// and also while an ordinary backend call is under way (see [`Task::call_raw`]). Locked by
    /// whoever listens, so a pause served inside a call does not listen again, and a call
    /// abandoned half-way gives it back by dropping its guard.
    pub urgent: Arc<tokio::sync::Mutex<mpsc::UnboundedReceiver<Msg>>>,
    /// The run whose program the backend is loading now (a pause then holds it before it
    /// starts, see [`Task::pause`]).
    pub loading: Option<i64>,
    /// A run paused while its program loaded: it was never started, so its resume starts it.
    pub held_before_start: Option<i64>,
    /// The host's part of why the machine holds (shared with the handle, see `super::holds`).
    pub holds: Arc<super::holds::HostHolds>,
}

/// What the store has not been told yet. Written acks first, then transitions in the order they
/// happened, so a run's last lines are stored before its end and nothing is written twice
/// (acks only ever raise `last_line`; a transition is a compare-and-set).
#[derive(Default)]
pub(super) struct PendingWrites {
    /// Highest acknowledged line per run.
    pub acks: BTreeMap<i64, u32>,
    pub transitions: VecDeque<PendingTransition>,
}

pub(super) struct PendingTransition {
    run_id: i64,
    from: &'static [RunState],
    to: RunState,
    message: Option<String>,
    actor: Option<String>,
}

impl PendingWrites {
    fn ack(&mut self, run: i64, line: u32) {
        let e = self.acks.entry(run).or_insert(line);
        *e = (*e).max(line);
    }
    fn is_empty(&self) -> bool {
        self.acks.is_empty() && self.transitions.is_empty()
    }
}

const ACTIVE: &[RunState] = &[RunState::Running, RunState::Paused];
const UNAVAILABLE: &str = "database_unavailable";

fn run_event(run: &RunRow) -> Value {
    json!({"job": run.job_id, "run": run.id, "state": run.state, "line": run.last_line, "message": run.message})
}

impl Task {
    pub async fn run(
        mut self,
        mut requests: mpsc::UnboundedReceiver<Msg>,
        mut events: Option<mpsc::UnboundedReceiver<Event>>,
    ) {
        let mut batch = Vec::new();
        // The store's health lives as long as the store this task holds: never closed.
        let mut health = self.store.health().subscribe();
        let mut urgent_open = true;
        loop {
            let next_events = async {
                match events.as_mut() {
                    Some(rx) => rx.recv_many(&mut batch, 1024).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                biased;
                n = next_events => {
                    if n == 0 {
                        events = None;
                        continue;
                    }
                    let drained: Vec<Event> = std::mem::take(&mut batch);
                    self.handle_events(drained).await;
                }
                msg = async {
                    if urgent_open {
                        self.urgent.lock().await.recv().await
                    } else {
                        std::future::pending().await
                    }
                } => {
                    // Closed only with the handle, which closes `requests` too.
                    let Some(msg) = msg else {
                        urgent_open = false;
                        continue;
                    };
                    self.serve(msg, &mut events).await;
                }
                msg = requests.recv() => {
                    let Some(msg) = msg else { return };
                    self.serve(msg, &mut events).await;
                }
                Ok(()) = health.changed() => {
                    if self.store.health().is_up() && !self.pending.is_empty() {
                        self.flush_pending().await;
                    }
                }
            }
        }
    }

    /// One message, after the backend events queued before it.
    async fn serve(&mut self, msg: Msg, events: &mut Option<mpsc::UnboundedReceiver<Event>>) {
        self.drain_events(events).await;
        // Writes kept during an outage land before anything the request changes.
        if !self.pending.is_empty() {
            self.flush_pending().await;
        }
        self.handle(msg).await;
    }

    async fn drain_events(&mut self, events: &mut Option<mpsc::UnboundedReceiver<Event>>) {
        let Some(rx) = events.as_mut() else { return };
        let mut pending = Vec::new();
        while let Ok(e) = rx.try_recv() {
            pending.push(e);
        }
        if !pending.is_empty() {
            self.handle_events(pending).await;
        }
    }

    pub(super) async fn handle(&mut self, msg: Msg) {
        match msg {
            Msg::Restore { reply } => {
                self.restore().await;
                let _ = reply.send(());
            }
            Msg::Call {
                request,
                actor,
                ticket,
                reply,
            } => {
                let r = self.operate(request, &actor, ticket).await;
                let _ = reply.send(r);
            }
            Msg::PartZero {
                position,
                source,
                note,
                actor,
                reply,
            } => {
                let r = self
                    .record_part_zero(position, &source, note.as_deref(), &actor)
                    .await;
                let _ = reply.send(r);
            }
            Msg::Start {
                job,
                actor,
                from_line,
                ticket,
                height_map,
                reply,
            } => {
                let r = self
                    .start(&job, &actor, from_line, ticket, height_map)
                    .await;
                let _ = reply.send(r);
            }
            Msg::Pause {
                job_id,
                actor,
                reason,
                reply,
            } => {
                let r = self.pause(job_id, &actor, reason).await;
                let _ = reply.send(r);
            }
            Msg::Resume {
                job,
                actor,
                confirm_part_zero,
                confirm_line,
                ticket,
                reply,
            } => {
                let r = self
                    .resume(&job, &actor, (confirm_part_zero, confirm_line), ticket)
                    .await;
                let _ = reply.send(r);
            }
            Msg::Cancel {
                job_id,
                actor,
                reply,
            } => {
                let r = self.cancel(job_id, &actor).await;
                let _ = reply.send(r);
            }
            Msg::Sync { reply } => {
                let _ = reply.send(());
            }
        }
    }

    // ---- backend calls ----

    pub(super) async fn call(&mut self, request: &Request) -> Result<Value> {
        Ok(self.call_raw(request).await?)
    }

    /// A call that starts motion, fenced by the gate on both sides: refused if a stop came
    /// after the request was sent, and stopped again at once if a stop reached the backend
    /// while this call was on its way (the two lanes race inside the backend). A call that
    /// timed out may have started motion nobody will answer for: it is stopped too.
    async fn motion(&mut self, ticket: u64, request: &Request) -> Result<Value> {
        self.gate.check(ticket)?;
        let answer = match self.call(request).await {
            Ok(a) => a,
            Err(e) if e.kind == crate::error::ErrorKind::Timeout => {
                self.stop_again("a motion request timed out").await;
                return Err(e);
            }
            Err(e) => return Err(e),
        };
        if let Err(e) = self.gate.check(ticket) {
            self.stop_again("a stop overtook a motion request").await;
            return Err(e);
        }
        Ok(answer)
    }

    /// Stop on the urgent lane, for motion the machine may have started behind our back.
    async fn stop_again(&mut self, why: &str) {
        tracing::warn!(machine = self.id, "{why}; stopping the machine");
        if let Err(stop) = self.call(&Request::Command(Command::Stop)).await {
            tracing::error!(machine = self.id, error = %stop, "could not stop the machine");
        }
    }

    /// Calls the backend. While an ordinary call that starts no motion is under way, pause and
    /// cancel from the urgent channel are served (their own calls take the urgent lane and do not
    /// listen again).
    /// Boxed, and declared `Send`: serving a pause calls back into here, and the compiler needs
    /// the future's type spelled out to see that the cycle is `Send`.
    fn call_raw<'a>(
        &'a mut self,
        request: &'a Request,
    ) -> std::pin::Pin<Box<dyn std::future::Future<Output = Result<Value, BackendError>> + Send + 'a>>
    {
        Box::pin(async move {
            let lanes = self.lanes.clone().ok_or_else(|| {
                BackendError::Unavailable(self.unavailable.clone().unwrap_or_default())
            })?;
            let op = request.operation();
            let listening = match op.lane {
                Lane::Ordinary if !op.starts_motion => self.urgent.clone().try_lock_owned().ok(),
                _ => None,
            };
            let Some(mut urgent) = listening else {
                return lanes.call(request).await;
            };
            let call = lanes.call(request);
            tokio::pin!(call);
            let answer = loop {
                tokio::select! {
                    biased;
                    answer = &mut call => break answer,
                    Some(msg) = urgent.recv() => self.handle(msg).await,
                }
            };
            drop(urgent);
            answer
        })
    }

    /// A generated file's refusals have their own codes: not in this configuration
    /// (`not_available`), or no such artifact.
    fn artifact_error(&self, name: &str, e: BackendError) -> Error {
        use fresa_plugin_api::host::CallError;
        let id = self.id;
        match e {
            BackendError::Call(CallError::Plugin(p)) if p.code == "not_available" => {
                Error::conflict("not_available", format!("machine {id}: {}", p.message))
            }
            BackendError::Call(CallError::Plugin(p)) => Error::not_found(
                "no_artifact",
                format!(
                    "machine {id} (backend {}) has no {name}: {}",
                    self.row.borrow().backend,
                    p.message
                ),
            ),
            other => other.into(),
        }
    }

    pub(super) async fn refresh_status(&mut self) -> Result<MachineStatus> {
        self.status_from(&Request::Status).await
    }

    /// `status` or `connect`: both answer a status, which becomes the published one.
    async fn status_from(&mut self, request: &Request) -> Result<MachineStatus> {
        let v = self.call(request).await?;
        self.publish_answer(v)
    }

    fn publish_answer(&self, v: Value) -> Result<MachineStatus> {
        let s: MachineStatus = serde_json::from_value(v).map_err(|e| {
            Error::new(
                crate::error::ErrorKind::Backend,
                "backend_error",
                format!("status has an unexpected shape: {e}"),
            )
        })?;
        self.publish_status(s.clone());
        Ok(s)
    }

    /// The one place a backend's status becomes the published one: an input or output that
    /// changed goes out as `machine.io` first (live, every change; the status stream is rate
    /// limited and would miss a short press).
    fn publish_status(&self, s: MachineStatus) {
        let changed = {
            let before = self.status.borrow();
            io_changes(&before, &s)
        };
        if let Some(changed) = changed {
            self.bus.transient(
                EventKind::MachineIo,
                Some(self.id),
                json!({"inputs": s.inputs, "outputs": s.outputs, "changed": changed}),
            );
        }
        self.status.send_replace(s);
    }

    async fn record(&self, kind: EventKind, actor: &str, data: Value) {
        self.bus
            .record_or_log(kind, Some(self.id), Some(actor), data)
            .await;
    }

    /// Brings a freshly started backend to the state the store remembers. Offsets: the store
    /// is the source of truth; it is written into the backend here, and every change made
    /// through Fresa goes to the backend first and then to the store, in the same request.
    async fn restore(&mut self) {
        if self.lanes.is_none() {
            return;
        }
        match self.status_from(&Request::Connect).await {
            Ok(_) => {}
            Err(e) => {
                tracing::warn!(machine = self.id, error = %e, "connect failed");
                self.status.send_modify(|s| {
                    s.state = MachineState::Offline;
                    s.reason = Some(e.message.clone());
                });
                return;
            }
        }
        if let Ok(offsets) = self.store.offsets(self.id).await {
            for (offset, values) in offsets {
                if let Err(e) = self.call(&Request::SetOffset { offset, values }).await {
                    tracing::warn!(machine = self.id, offset = offset.name(), error = %e, "could not restore work offset");
                }
            }
        }
        let active = self.row.borrow().active_offset.clone();
        if let Some(o) = WorkOffset::parse(&active) {
            let _ = self
                .call(&Request::Command(Command::SelectOffset { offset: o }))
                .await;
        }
        let _ = self.refresh_status().await;
    }

    // ---- immediate commands ----

    fn refuse_during_run(&self, what: &str) -> Result<()> {
        if self.run.borrow().is_some() {
            return Err(Error::conflict(
                "machine_busy",
                format!("a job is running on this machine; pause or cancel it before {what}"),
            ));
        }
        Ok(())
    }

    /// One operation, as its declared properties say (`fresa_plugin_api::operation`): no new
    /// motion or kept change without the database, nothing that a running job or a moving
    /// machine forbids, motion through the stop gate, offsets it changed stored, then its audit
    /// record.
    async fn operate(&mut self, request: Request, actor: &str, ticket: u64) -> Result<Value> {
        let op = request.operation();
        if op.needs_store {
            self.store.health().check()?;
        }
        // A tool-change hold lets the operator jog and probe (touch off, measure the new tool).
        let tool_change_motion = matches!(request, Request::Jog { .. } | Request::Probe(_))
            && super::holds::in_tool_change(&self.status.borrow());
        if op.refused_during_run && !tool_change_motion {
            self.refuse_during_run(&format!("`{}`", op.name))?;
        }
        if op.changes_offsets {
            self.refuse_while_moving(&format!("`{}` (it changes the work offsets)", op.name))
                .await?;
        }
        // Spindle and coolant belong to the program while it cuts; the operator may change them
        // once the run is held.
        if let Request::Command(Command::SetOutput { name, .. } | Command::ToggleOutput { name }) =
            request
        {
            let cutting = self
                .run
                .borrow()
                .as_ref()
                .is_some_and(|r| r.state == RunState::Running);
            if cutting && matches!(name, OutputName::Spindle | OutputName::Coolant) {
                return Err(Error::conflict(
                    "machine_busy",
                    format!(
                        "the {} cannot be switched while a job is cutting; pause the job first",
                        name.as_str()
                    ),
                ));
            }
        }
        let answer = if op.starts_motion {
            self.motion(ticket, &request).await?
        } else {
            match self.call_raw(&request).await {
                Ok(a) => a,
                Err(e) => {
                    return Err(match &request {
                        Request::GetArtifact { name } => self.artifact_error(name, e),
                        _ => e.into(),
                    })
                }
            }
        };
        // A status read is the published status from now on.
        if matches!(request, Request::Status | Request::Connect) {
            self.publish_answer(answer.clone())?;
        }
        let mut computed_offsets = None;
        if op.changes_offsets {
            match &request {
                // The values given are the ones kept.
                Request::SetOffset { offset, values } => {
                    self.store
                        .health()
                        .guard(self.store.set_offsets(self.id, &[(*offset, *values)]))
                        .await?;
                }
                // The backend computed the new offsets; persist what it now has.
                _ => {
                    computed_offsets = Some(self.persist_backend_offsets().await?);
                }
            }
        }
        if let Some(event) = op.audit {
            self.record(event.into(), actor, audit_data(&request, &answer))
                .await;
        }
        // The offsets a command computed (zero, select offset) are recorded after the command,
        // as its consequence, with its actor.
        if let Some(table) = computed_offsets {
            self.record(EventKind::MachineOffsets, actor, json!(table))
                .await;
        }
        if op.refreshes_status {
            let _ = self.refresh_status().await;
        }
        Ok(answer)
    }

    /// Reads the backend's offsets and stores them; the caller records `machine.offsets`.
    async fn persist_backend_offsets(&mut self) -> Result<OffsetTable> {
        let v = self.call(&Request::GetOffsets).await?;
        let table: OffsetTable = serde_json::from_value(v).map_err(|e| {
            Error::new(
                crate::error::ErrorKind::Backend,
                "backend_error",
                format!("offsets have an unexpected shape: {e}"),
            )
        })?;
        let health = self.store.health();
        health
            .guard(self.store.set_offsets(self.id, &table.offsets))
            .await?;
        health
            .guard(self.store.set_active_offset(self.id, table.active))
            .await?;
        self.row
            .send_modify(|r| r.active_offset = table.active.name().to_string());
        Ok(table)
    }

    /// The one check before a part zero is recorded, an axis zeroed or a work offset changed
    /// or selected: refused with 409 `machine_moving` while the machine moves (or holds a paused
    /// job), judged on a fresh status (the published one can lag the backend), or the last
    /// one when the backend cannot answer. Every path (HTTP, MQTT, pendant keys) comes here.
    async fn refuse_while_moving(&mut self, what: &str) -> Result<()> {
        let st = match self.refresh_status().await {
            Ok(s) => s,
            Err(_) => self.status.borrow().clone(),
        };
        Self::standing_still(self.id, &st, what)
    }

    fn standing_still(id: i64, st: &MachineStatus, what: &str) -> Result<()> {
        // Held for a tool change with nothing moving: offsets may change (touch-off, setter).
        let tool_change = st.state == MachineState::Paused && super::holds::in_tool_change(st);
        if st.state.is_busy() && !tool_change {
            return Err(Error::conflict(
                "machine_moving",
                format!(
                    "machine {} is {}: {what} must wait until it stands still (stop it or let \
                     the motion end first)",
                    id,
                    st.state.as_str()
                ),
            ));
        }
        Ok(())
    }

    async fn record_part_zero(
        &mut self,
        position: Option<AxisValues>,
        source: &str,
        note: Option<&str>,
        actor: &str,
    ) -> Result<PartZeroRow> {
        self.store.health().check()?;
        let what = "recording a part zero";
        let at = match position {
            Some(p) => {
                self.refuse_while_moving(what).await?;
                p
            }
            // Where it stands, as the backend says now.
            None => {
                let st = self.refresh_status().await?;
                Self::standing_still(self.id, &st, what)?;
                st.machine_position
            }
        };
        let row = self
            .store
            .health()
            .guard(
                self.store
                    .insert_part_zero(self.id, at, source, actor, note),
            )
            .await?;
        self.record(EventKind::MachinePartZero, actor, json!(row))
            .await;
        Ok(row)
    }

    // ---- runs ----

    fn publish_run(&mut self, run: Option<RunView>) {
        if run.is_none() {
            self.job.send_replace(None);
            self.launched.send_replace(None);
            self.held_before_start = None;
        }
        self.run.send_replace(run);
    }

    /// Moves a run (compare-and-set on its state) and records the change. While the database is
    /// unreachable the move is made in memory and kept pending for the store (returning the run
    /// as the task remembers it); `None` when the run is not in a state of `from`.
    async fn transition(
        &mut self,
        run_id: i64,
        from: &'static [RunState],
        to: RunState,
        message: Option<&str>,
        actor: Option<&str>,
    ) -> Result<Option<RunRow>> {
        if self.pending.is_empty() {
            let written = self
                .store
                .health()
                .guard(self.store.transition_run(run_id, from, to, message))
                .await;
            match written {
                Ok(row) => {
                    if let Some(row) = &row {
                        self.show_transition(run_id, row.state);
                        self.record_transition(row, actor).await;
                    }
                    return Ok(row);
                }
                // It may have landed before the answer was lost: the compare-and-set on
                // replay tells.
                Err(e) if e.code == UNAVAILABLE => {}
                Err(e) => return Err(e),
            }
        }
        let remembered = self.remembered_run(run_id);
        // The run's state as the store will have it once the pending writes land: a late or
        // duplicate report (the backend's end of a run just cancelled) is ignored here as the
        // compare-and-set would ignore it, so it is neither queued nor recorded twice.
        let known = self
            .pending
            .transitions
            .iter()
            .rev()
            .find(|t| t.run_id == run_id)
            .map(|t| t.to)
            .or(remembered.as_ref().map(|r| r.state));
        if let Some(state) = known {
            if !from.contains(&state) || !state.can_move_to(to) {
                return Ok(None);
            }
        }
        tracing::warn!(
            machine = self.id,
            run = run_id,
            to = to.as_str(),
            "database unreachable: run state kept in memory until it returns"
        );
        self.pending.transitions.push_back(PendingTransition {
            run_id,
            from,
            to,
            message: message.map(str::to_string),
            actor: actor.map(str::to_string),
        });
        self.show_transition(run_id, to);
        Ok(remembered.map(|mut r| {
            r.state = to;
            r.message = message.map(str::to_string);
            r.updated_at = crate::store::now_ms();
            if !to.is_active() {
                r.ended_at = Some(r.updated_at);
            }
            r
        }))
    }

    /// The current run as the task knows it (its row at launch, its state and line since), if
    /// `run_id` is the current run.
    fn remembered_run(&self, run_id: i64) -> Option<RunRow> {
        super::current_row(self.run.borrow().as_ref(), &self.launched.borrow())
            .filter(|r| r.id == run_id)
    }

    /// The published run follows a transition of the current run.
    fn show_transition(&mut self, run_id: i64, to: RunState) {
        if self
            .run
            .borrow()
            .as_ref()
            .is_some_and(|r| r.run_id == run_id)
        {
            if to.is_active() {
                self.run.send_modify(|r| {
                    if let Some(r) = r {
                        r.state = to;
                    }
                });
            } else {
                self.publish_run(None);
            }
        }
    }

    async fn record_transition(&self, row: &RunRow, actor: Option<&str>) {
        let mut data = run_event(row);
        if row.state == RunState::Paused {
            // Why: the machine's hold once it reports one, else the pause the host asked for.
            let mut st = self.status.borrow().clone();
            self.holds.explain(&mut st);
            let hold = match st.hold {
                Some(h) if st.state == MachineState::Paused => *h,
                _ => super::holds::operator_pause(
                    actor.unwrap_or("the machine"),
                    self.holds.reason().as_ref(),
                ),
            };
            data["hold"] = json!(hold);
        }
        self.bus
            .record_or_log(EventKind::JobState, Some(self.id), actor, data)
            .await;
        // Every stored end of a run passes here (also one kept through an outage): its part
        // record, written off the task (it reads the job, tools and audit log).
        if !row.state.is_active() {
            let (store, row) = (self.store.clone(), row.clone());
            tokio::spawn(async move {
                if let Err(e) = crate::records::record_part(&store, &row).await {
                    tracing::error!(run = row.id, error = %e, "could not write the part record");
                }
            });
        }
    }

    /// After the machine changed state: the run follows it between running and paused when
    /// the machine held or went on by itself (M0, M1, M6, a feed hold or cycle start from
    /// anyone), so run and machine say the same. Jogging during a tool-change hold is held.
    /// The run's pause message is the hold's.
    async fn follow_machine(&mut self) {
        let Some(run) = self.run.borrow().clone() else {
            return;
        };
        let (state, held, message) = {
            let mut st = self.status.borrow().clone();
            self.holds.explain(&mut st);
            let held = st.state == MachineState::Paused || super::holds::in_tool_change(&st);
            (st.state, held, st.hold.map(|h| h.message))
        };
        let (from_run, to_run) = match (run.state, state) {
            (RunState::Running, _) if held => (RunState::Running, RunState::Paused),
            (RunState::Paused, MachineState::Running) => (RunState::Paused, RunState::Running),
            _ => return,
        };
        if to_run == RunState::Running {
            self.holds.clear_reason();
        }
        let from_states: &'static [RunState] = if from_run == RunState::Running {
            &[RunState::Running]
        } else {
            &[RunState::Paused]
        };
        if let Err(e) = self
            .transition(run.run_id, from_states, to_run, message.as_deref(), None)
            .await
        {
            tracing::error!(machine = self.id, run = run.run_id, error = %e, "could not follow the machine's state");
        }
    }

    /// Ends a run from a backend report. Late or duplicate reports are ignored.
    async fn finish_run(&mut self, run_id: i64, to: RunState, message: Option<&str>) {
        if let Err(e) = self.transition(run_id, ACTIVE, to, message, None).await {
            tracing::error!(machine = self.id, run = run_id, error = %e, "could not record end of run");
        }
    }

    /// Writes what the store has not been told yet (see [`Task::write_pending`]), and records
    /// beside the store which runs still have acknowledged lines only in memory.
    async fn flush_pending(&mut self) {
        self.write_pending().await;
        self.unstored.show(&self.pending.acks);
    }

    /// Writes acknowledged lines, then run transitions in order. Stops at the first sign the
    /// database is unreachable and keeps the rest; the database's return (or the next request)
    /// tries again.
    async fn write_pending(&mut self) {
        let health = self.store.health().clone();
        while let Some((&run, &line)) = self.pending.acks.first_key_value() {
            match health.guard(self.store.ack_line(run, line as i64)).await {
                Ok(()) => {}
                Err(e) if e.code == UNAVAILABLE => {
                    // Progress is still shown from memory; the store catches up later.
                    for (&run, &line) in &self.pending.acks {
                        self.show_ack(run, line);
                    }
                    return;
                }
                Err(e) => {
                    tracing::error!(machine = self.id, run, line, error = %e, "could not persist acknowledged line");
                }
            }
            self.pending.acks.remove(&run);
            self.show_ack(run, line);
            // A line the backend reported as it stopped, after the run's end was stored: the
            // part record is written again with it.
            if self.run.borrow().as_ref().is_none_or(|r| r.run_id != run) {
                let store = self.store.clone();
                tokio::spawn(async move {
                    if let Ok(Some(row)) = store.run(run).await {
                        if let Err(e) = crate::records::record_part(&store, &row).await {
                            tracing::error!(run, error = %e, "could not update the part record");
                        }
                    }
                });
            }
        }
        while let Some(t) = self.pending.transitions.front() {
            let written = health
                .guard(
                    self.store
                        .transition_run(t.run_id, t.from, t.to, t.message.as_deref()),
                )
                .await;
            let (run_id, to) = (t.run_id, t.to);
            let actor = t.actor.clone();
            match written {
                Ok(Some(row)) => self.record_transition(&row, actor.as_deref()).await,
                Ok(None) => {
                    // Either it landed just before the outage cut off the answer, or the run
                    // had moved on; only the former is ours to record.
                    match health.guard(self.store.run(run_id)).await {
                        Ok(Some(row)) if row.state == to => {
                            self.record_transition(&row, actor.as_deref()).await
                        }
                        Err(e) if e.code == UNAVAILABLE => return,
                        _ => tracing::warn!(
                            machine = self.id,
                            run = run_id,
                            to = to.as_str(),
                            "a run transition kept during an outage no longer applies; dropped"
                        ),
                    }
                }
                Err(e) if e.code == UNAVAILABLE => return,
                Err(e) => {
                    tracing::error!(machine = self.id, run = run_id, error = %e, "could not record a run transition; dropped")
                }
            }
            self.pending.transitions.pop_front();
        }
    }

    fn show_ack(&self, run: i64, line: u32) {
        self.run.send_if_modified(|r| match r {
            Some(r) if r.run_id == run && r.line < line as i64 => {
                r.line = line as i64;
                true
            }
            _ => false,
        });
    }

    /// The machine's state if it is busy. The cached status can lag the backend's events, so
    /// a busy cache is checked with a fresh status before refusing.
    async fn busy_state(&mut self) -> Option<MachineState> {
        let cached = self.status.borrow().state;
        if !cached.is_busy() {
            return None;
        }
        let state = match self.refresh_status().await {
            Ok(fresh) => fresh.state,
            Err(_) => cached,
        };
        state.is_busy().then_some(state)
    }

    fn busy_with_run(&self) -> Option<Error> {
        self.run.borrow().as_ref().map(|r| {
            Error::conflict(
                "machine_busy",
                format!(
                    "machine {} is running job {} (run {}, {})",
                    self.id, r.job_id, r.run_id, r.state
                ),
            )
        })
    }

    /// Starts a new run of `job`, from `from_line` when given: planned first (see
    /// `crate::start_at`), so a start that cannot be made creates no run; with
    /// `height_map` applied by the backend.
    async fn start(
        &mut self,
        job: &JobRow,
        actor: &str,
        from_line: Option<u32>,
        ticket: u64,
        height_map: Option<super::heightmap::Applied>,
    ) -> Result<RunRow> {
        self.store.health().check()?;
        if let Some(e) = self.busy_with_run() {
            return Err(e);
        }
        if let Some(state) = self.busy_state().await {
            return Err(Error::conflict(
                "machine_busy",
                format!(
                    "machine {} is {}; wait for it to be idle",
                    self.id,
                    state.as_str()
                ),
            ));
        }
        if let Some(reason) = &self.unavailable {
            return Err(Error::conflict("machine_offline", reason.clone()));
        }
        let start_line = from_line.unwrap_or(1);
        let plan = match start_line {
            n if n > 1 => Some(self.plan_start(job, n).await?),
            _ => None,
        };
        self.gate.check(ticket)?;
        let from = from_line.map(i64::from);
        let run = match self.store.start_run_from(job.id, self.id, from).await? {
            Ok(r) => r,
            Err(busy) => {
                return Err(Error::conflict(
                    "machine_busy",
                    format!(
                        "machine {} is running job {} (run {}, {})",
                        self.id, busy.job_id, busy.id, busy.state
                    ),
                ))
            }
        };
        // The run records the height map it runs with (a resume applies it again).
        let run = match &height_map {
            Some(applied) => {
                if let Err(e) = self.store.set_run_height_map(run.id, applied.id).await {
                    let e = Error::from(e);
                    self.finish_run(run.id, RunState::Failed, Some(&e.message))
                        .await;
                    return Err(e);
                }
                RunRow {
                    height_map_id: Some(applied.id),
                    ..run
                }
            }
            None => run,
        };
        let from = Launch {
            start_line,
            plan,
            resuming: false,
        };
        let map = height_map.as_ref().map(|a| &a.map);
        self.launch(job, run, from, actor, None, ticket, map).await
    }

    /// Loads the program into the backend from `from.start_line` (with the preamble that leads
    /// there) and starts it. On failure the run is marked failed with the backend's reason (or
    /// cancelled when a stop overtook it). `height_map`: applied by the backend, which must
    /// say so (see `ProgramLoaded`).
    #[allow(clippy::too_many_arguments)]
    async fn launch(
        &mut self,
        job: &JobRow,
        run: RunRow,
        from: Launch,
        actor: &str,
        expected_part_zero: Option<AxisValues>,
        ticket: u64,
        height_map: Option<&fresa_plugin_api::heightmap::HeightMap>,
    ) -> Result<RunRow> {
        // A job uploaded on another node: its program comes from the shared store first.
        let path =
            match crate::programs::local_copy(&self.store, &self.programs_dir, &job.sha256).await {
                Ok(p) => p,
                Err(e) => {
                    self.finish_run(run.id, RunState::Failed, Some(&e.message))
                        .await;
                    return Err(e);
                }
            };
        self.job.send_replace(Some(job.clone()));
        self.launched.send_replace(Some(run.clone()));
        self.publish_run(Some(RunView {
            run_id: run.id,
            job_id: job.id,
            total_lines: job.line_count,
            state: RunState::Running,
            line: run.last_line,
            times: time_table(job),
            announced: false,
        }));
        // The store says `running` from here on, and so does the audit log, before the backend
        // can finish or fail the run (so it never shows `completed` or `failed` without it).
        self.record(EventKind::JobState, actor, run_event(&run))
            .await;
        self.run.send_modify(|v| {
            if let Some(v) = v.as_mut().filter(|v| v.run_id == run.id) {
                v.announced = true;
            }
        });
        let started = async {
            let loaded = self
                .load_from(job, &run, &path, from, expected_part_zero, height_map)
                .await;
            self.loading = None;
            loaded?;
            // A stop or cancel that arrived while the program loaded wins: nothing moves.
            self.gate.check(ticket)?;
            // Paused while it loaded: it waits for its resume to start.
            if self.held_before_start == Some(run.id) {
                return Ok(None);
            }
            self.motion(
                ticket,
                &Request::Run {
                    action: RunAction::Start,
                },
            )
            .await
            .map(Some)
        }
        .await;
        let answer = match started {
            Ok(Some(a)) => a,
            Ok(None) => return Ok(self.remembered_run(run.id).unwrap_or(run)),
            Err(e) => {
                let to = if e.code == "stopped" || e.code == "shutting_down" {
                    RunState::Cancelled
                } else {
                    RunState::Failed
                };
                self.finish_run(run.id, to, Some(&e.message)).await;
                self.publish_run(None);
                return Err(e);
            }
        };
        let health = self.store.health().clone();
        // A controller that reports its own part zero: the run keeps the one it (re)started
        // with, for the check on the next resume.
        if let Some(zero) = answer
            .get("part_zero")
            .and_then(|z| serde_json::from_value::<AxisValues>(z.clone()).ok())
        {
            // The program runs now: a database that went down meanwhile must not turn the
            // answer into a failure (only the part-zero check of a later resume is lost).
            if let Err(e) = health
                .guard(self.store.set_run_part_zero(run.id, zero))
                .await
            {
                tracing::error!(machine = self.id, run = run.id, error = %e, "could not store the run's part zero");
            }
        }
        Ok(health
            .guard(self.store.run(run.id))
            .await
            .ok()
            .flatten()
            .or_else(|| self.remembered_run(run.id))
            .unwrap_or(run))
    }

    /// The machine's run settings as a program is loaded with them: the optional stop, and how
    /// M6 holds (`refuse` holds too: a program with M6 is refused at its start, so one that
    /// gets here anyway, a resume, holds rather than runs on with the wrong tool).
    pub(super) async fn run_options(
        &self,
    ) -> Result<(bool, Option<fresa_plugin_api::contract::ToolChangeSetup>)> {
        use crate::store::ToolChangePolicy;
        let (settings, _) = self.store.run_settings(self.id).await?;
        let tool_change = match settings.tool_change {
            ToolChangePolicy::Ignore => None,
            ToolChangePolicy::Hold | ToolChangePolicy::Refuse => {
                Some(fresa_plugin_api::contract::ToolChangeSetup {
                    position: settings.tool_change_position.map(|p| AxisValues {
                        x: p.x,
                        y: p.y,
                        z: p.z,
                        a: 0.0,
                    }),
                })
            }
        };
        Ok((settings.optional_stop, tool_change))
    }

    /// The job's latest run: from the store, or, while the database is unreachable, the
    /// current run as the task remembers it (so pause and cancel still work).
    async fn latest(&self, job_id: i64) -> Result<RunRow> {
        let stored = self
            .store
            .health()
            .guard(self.store.latest_run(job_id))
            .await;
        match stored {
            Ok(run) => run.ok_or_else(|| {
                Error::conflict(
                    "not_started",
                    format!("job {job_id} has never been started"),
                )
            }),
            Err(e) if e.code == UNAVAILABLE => self
                .run
                .borrow()
                .as_ref()
                .filter(|v| v.job_id == job_id)
                .map(|v| v.run_id)
                .and_then(|run_id| self.remembered_run(run_id))
                .ok_or(e),
            Err(e) => Err(e),
        }
    }

    /// Moves a run and returns it; when the compare-and-set lost (the backend finished the run
    /// meanwhile) returns the run as it is now.
    async fn transition_or_current(
        &mut self,
        run: &RunRow,
        from: &'static [RunState],
        to: RunState,
        actor: &str,
    ) -> Result<RunRow> {
        match self.transition(run.id, from, to, None, Some(actor)).await? {
            Some(row) => Ok(row),
            None => Ok(self
                .store
                .health()
                .guard(self.store.run(run.id))
                .await
                .ok()
                .flatten()
                .or_else(|| self.remembered_run(run.id))
                .unwrap_or_else(|| run.clone())),
        }
    }

    async fn pause(
        &mut self,
        job_id: i64,
        actor: &str,
        reason: Option<(fresa_plugin_api::contract::HoldKind, String)>,
    ) -> Result<RunRow> {
        let run = self.latest(job_id).await?;
        if run.state != RunState::Running {
            return Err(Error::conflict(
                "not_running",
                format!("job {job_id} is {}, not running", run.state),
            ));
        }
        match reason {
            Some((kind, message)) => self.holds.set_reason(kind, message),
            None => self.holds.clear_reason(),
        }
        // Its program is still loading (this pause is served while the load call is under
        // way): nothing moves yet, so the run is held before it starts instead.
        if self.loading == Some(run.id) {
            self.held_before_start = Some(run.id);
        } else if let Err(e) = self
            .call(&Request::Run {
                action: RunAction::Pause,
            })
            .await
        {
            self.holds.clear_reason();
            return Err(e);
        }
        self.transition_or_current(&run, &[RunState::Running], RunState::Paused, actor)
            .await
    }

    async fn resume(
        &mut self,
        job: &JobRow,
        actor: &str,
        (confirm_part_zero, confirm_line): (bool, Option<i64>),
        ticket: u64,
    ) -> Result<RunRow> {
        self.store.health().check()?;
        let job_id = job.id;
        let run = self.latest(job_id).await?;
        match run.state {
            RunState::Paused => {
                // Held before it started: the program is loaded, so it is started now.
                let action = if self.held_before_start == Some(run.id) {
                    RunAction::Start
                } else {
                    RunAction::Resume
                };
                self.motion(ticket, &Request::Run { action }).await?;
                self.held_before_start = None;
                self.holds.clear_reason();
                self.transition_or_current(&run, &[RunState::Paused], RunState::Running, actor)
                    .await
            }
            RunState::Interrupted | RunState::Failed => {
                if let Some(e) = self.busy_with_run() {
                    return Err(e);
                }
                if let Some(state) = self.busy_state().await {
                    return Err(Error::conflict(
                        "machine_busy",
                        format!("machine {} is {}", self.id, state.as_str()),
                    ));
                }
                let run = self.confirmed_line(job, run, confirm_line, actor).await?;
                if run.last_line >= job.line_count {
                    // Everything was acknowledged before the interruption: nothing left to run.
                    return self
                        .transition_or_current(
                            &run,
                            &[RunState::Interrupted, RunState::Failed],
                            RunState::Completed,
                            actor,
                        )
                        .await;
                }
                // It goes on through the preamble of its next line, planned before the run is
                // reopened (a start there that cannot be made leaves it as it is).
                let next = u32::try_from(run.next_line()).unwrap_or(u32::MAX);
                let plan = match next {
                    n if n > 1 => Some(self.plan_start(job, n).await?),
                    _ => None,
                };
                // The height map the run started with, as it fits now (refused before the run
                // is reopened if it is gone or no longer fits).
                let applied = match run.height_map_id {
                    Some(id) => {
                        let status = self.status.borrow().clone();
                        Some(
                            super::heightmap::applied_for_job(&self.store, job, id, &status)
                                .await
                                .map_err(|e| super::heightmap::for_resume(e, run.id, id))?,
                        )
                    }
                    None => None,
                };
                self.gate.check(ticket)?;
                let from = [RunState::Interrupted, RunState::Failed];
                let reopened = match self.store.reopen_run(run.id, self.id, &from).await? {
                    Ok(r) => r,
                    // Another resume or a cancel moved it meanwhile: the run as it is now.
                    Err(now) if now.id == run.id => return Ok(now),
                    Err(busy) => {
                        return Err(Error::conflict(
                            "machine_busy",
                            format!(
                                "machine {} is running job {} (run {})",
                                self.id, busy.job_id, busy.id
                            ),
                        ))
                    }
                };
                let next = u32::try_from(reopened.next_line()).unwrap_or(u32::MAX);
                let expected = if confirm_part_zero {
                    None
                } else {
                    self.store.run_part_zero(run.id).await?
                };
                let from = Launch {
                    start_line: next,
                    plan,
                    resuming: reopened.from_line.is_none(),
                };
                let map = applied.as_ref().map(|a| &a.map);
                self.launch(job, reopened, from, actor, expected, ticket, map)
                    .await
            }
            other => Err(Error::conflict(
                "not_resumable",
                format!("job {job_id} is {other}; only paused, interrupted or failed jobs can be resumed (start it again for a new run)"),
            )),
        }
    }

    /// A run whose stored line may be behind (the server stopped while lines of it were
    /// acknowledged only in memory, `unstored_line`) goes on only from the line the operator
    /// confirms as the last one executed; a resume without it is refused with
    /// `line_unconfirmed`, as a moved part zero is with `part_zero_changed`.
    async fn confirmed_line(
        &self,
        job: &JobRow,
        run: RunRow,
        confirm_line: Option<i64>,
        actor: &str,
    ) -> Result<RunRow> {
        let Some(unstored) = run.unstored_line else {
            return match confirm_line {
                Some(n) if n != run.last_line => Err(Error::invalid(
                    "invalid_field",
                    format!(
                        "field `confirm_line`: the stored line of job {} is exact ({}); leave confirm_line out or give that line, got {n}",
                        job.id, run.last_line
                    ),
                )),
                _ => Ok(run),
            };
        };
        // Acknowledged lines were executed: the last one executed is at least the highest.
        let lowest = run.last_line.max(unstored);
        let Some(line) = confirm_line else {
            return Err(Error::conflict(
                "line_unconfirmed",
                format!(
                    "job {} may have run past its stored line {}: the server stopped while lines up to at least {unstored} were acknowledged but could not be stored (the database could not be written). Check where the machine stopped, then resume with {{\"confirm_line\": N}}, N the last line executed ({lowest} to {}; {} completes the job without motion)",
                    job.id, run.last_line, job.line_count, job.line_count
                ),
            ));
        };
        if line < lowest || line > job.line_count {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `confirm_line` must be between {lowest} (lines up to it were acknowledged) and {} (the job's last line), got {line}",
                    job.line_count
                ),
            ));
        }
        tracing::warn!(
            machine = self.id,
            run = run.id,
            stored = run.last_line,
            unstored_line = unstored,
            confirmed = line,
            actor,
            "resume from a line the operator confirmed"
        );
        self.store
            .confirm_run_line(run.id, line)
            .await?
            .ok_or_else(|| Error::internal(format!("run {} disappeared", run.id)))
    }

    async fn cancel(&mut self, job_id: i64, actor: &str) -> Result<RunRow> {
        let run = self.latest(job_id).await?;
        match run.state {
            RunState::Running | RunState::Paused => {
                // Nothing requested before the cancel sets this run moving again (a start
                // whose program is still loading is refused at its gate check).
                if self
                    .run
                    .borrow()
                    .as_ref()
                    .is_some_and(|r| r.run_id == run.id)
                {
                    self.gate.overtake();
                }
                // The backend answers only once motion has stopped; only then is the run
                // cancelled.
                self.call(&Request::Run {
                    action: RunAction::Cancel,
                })
                .await?;
                self.transition_or_current(&run, ACTIVE, RunState::Cancelled, actor)
                    .await
            }
            RunState::Interrupted | RunState::Failed => {
                self.transition_or_current(
                    &run,
                    &[RunState::Interrupted, RunState::Failed],
                    RunState::Cancelled,
                    actor,
                )
                .await
            }
            other => Err(Error::conflict(
                "not_cancellable",
                format!("job {job_id} is already {other}"),
            )),
        }
    }

    // ---- backend events ----

    /// Persists what the backend reports. Line acknowledgements are coalesced: only the highest
    /// line per run in a batch is written, in one transaction.
    /// Events arrive decoded (the sink decodes them from the plugin's bytes on its thread).
    async fn handle_events(&mut self, batch: Vec<Event>) {
        let last_status = batch.iter().rposition(|e| matches!(e, Event::Status(_)));
        let mut changed = false;
        for (i, event) in batch.into_iter().enumerate() {
            match event {
                Event::Status(s) => self.publish_status(s),
                Event::LineAcknowledged { run, line } => self.pending.ack(run, line),
                Event::StateChanged { from, to } => {
                    // A status later in this batch carries the new state together with the
                    // position that goes with it. Published alone first, the state would show
                    // e.g. `idle` at a position the machine has left, and whoever waits for
                    // idle (`status?until=idle`, a touch-off's retract) would read that.
                    if last_status.is_none_or(|j| j < i) {
                        self.status.send_modify(|s| s.state = to);
                    }
                    changed = true;
                    self.bus.transient(
                        EventKind::MachineState,
                        Some(self.id),
                        json!({"from": from, "to": to}),
                    );
                }
                Event::Alarm { message, input } => {
                    let data = match input {
                        Some(input) => json!({ "message": message, "input": input }),
                        None => json!({ "message": message }),
                    };
                    self.bus
                        .record_or_log(EventKind::MachineAlarm, Some(self.id), None, data)
                        .await;
                }
                Event::RunEnded {
                    run,
                    outcome,
                    message,
                } => {
                    // The run's last lines are stored (or kept) before its end.
                    self.flush_pending().await;
                    let to = match outcome {
                        RunOutcome::Completed => RunState::Completed,
                        RunOutcome::Failed => RunState::Failed,
                        RunOutcome::Cancelled => RunState::Cancelled,
                    };
                    self.finish_run(run, to, message.as_deref()).await;
                }
                Event::LineReport {
                    run,
                    line,
                    max_deviation_mm,
                    percent,
                    remaining_s,
                } => {
                    // Transient like job.progress: one per line is too many for the audit log.
                    let job = self
                        .run
                        .borrow()
                        .as_ref()
                        .filter(|c| c.run_id == run)
                        .map(|c| c.job_id);
                    self.bus.transient(
                        EventKind::JobLineReport,
                        Some(self.id),
                        json!({"job": job, "run": run, "line": line,
                               "max_deviation_mm": max_deviation_mm,
                               "percent": percent, "remaining_s": remaining_s}),
                    );
                }
                Event::PartZeroReported { values, run } => {
                    self.record_reported_part_zero(values, run).await;
                }
                Event::ProbeEnded {
                    id,
                    outcome,
                    trip,
                    position,
                    message,
                } => {
                    let end = super::probing::ProbeEnd {
                        id,
                        outcome,
                        trip,
                        position,
                        message,
                    };
                    self.probe_ended.send_replace(Some(end));
                }
            }
        }
        if changed {
            self.follow_machine().await;
        }
        self.flush_pending().await;
    }

    /// A controller's own part zero joins the history (source `robot`) when it differs from
    /// the latest record, so repeated reports of the same zero do not flood it.
    async fn record_reported_part_zero(&self, values: AxisValues, run: Option<i64>) {
        const SAME_MM: f64 = 1e-6;
        let health = self.store.health();
        match health.guard(self.store.latest_part_zero(self.id)).await {
            Ok(Some(last))
                if last.source == "robot"
                    && [
                        last.x - values.x,
                        last.y - values.y,
                        last.z - values.z,
                        last.a - values.a,
                    ]
                    .iter()
                    .all(|d| d.abs() <= SAME_MM) =>
            {
                return;
            }
            Ok(_) => {}
            Err(e) => {
                tracing::error!(machine = self.id, error = %e, "could not read the part-zero history");
                return;
            }
        }
        let note = run.map(|r| format!("reported by the controller at the start of run {r}"));
        match health
            .guard(
                self.store
                    .insert_part_zero(self.id, values, "robot", "robot", note.as_deref()),
            )
            .await
        {
            Ok(row) => {
                self.record(EventKind::MachinePartZero, "robot", json!(row))
                    .await
            }
            Err(e) => {
                tracing::error!(machine = self.id, error = %e, "could not store the reported part zero")
            }
        }
    }
}

/// The inputs and outputs whose value differs between two statuses (with their new value;
/// `null` for one no longer reported), or `None` when nothing changed.
fn io_changes(before: &MachineStatus, after: &MachineStatus) -> Option<Value> {
    fn diff<V: PartialEq + serde::Serialize>(
        before: &std::collections::BTreeMap<String, V>,
        after: &std::collections::BTreeMap<String, V>,
        out: &mut serde_json::Map<String, Value>,
    ) {
        for (name, v) in after {
            if before.get(name) != Some(v) {
                out.insert(name.clone(), json!(v));
            }
        }
        for name in before.keys().filter(|n| !after.contains_key(*n)) {
            out.insert(name.clone(), Value::Null);
        }
    }
    let mut out = serde_json::Map::new();
    diff(&before.inputs, &after.inputs, &mut out);
    diff(&before.outputs, &after.outputs, &mut out);
    (!out.is_empty()).then_some(Value::Object(out))
}

/// What an operation's audit event says: its fields as the API took them, and for an output
/// its new state as the backend reports it.
/// The program's time by line, from the job's stored analysis (absent in analyses stored
/// before it existed).
fn time_table(job: &JobRow) -> Option<Arc<fresa_gcode::TimeTable>> {
    #[derive(serde::Deserialize)]
    struct Times {
        time_table: fresa_gcode::TimeTable,
    }
    let a = job.analysis.as_deref()?;
    serde_json::from_str::<Times>(a)
        .ok()
        .filter(|t| !t.time_table.marks.is_empty())
        .map(|t| Arc::new(t.time_table))
}

fn audit_data(request: &Request, answer: &Value) -> Value {
    match request {
        Request::Jog {
            axis,
            distance,
            feed,
        } => json!({"axis": axis, "distance": distance, "feed": feed}),
        Request::Mdi { line } => json!({"line": line}),
        Request::Probe(p) => json!(p),
        Request::SetOffset { offset, values } => json!({"offset": offset, "values": values}),
        Request::Command(command) => {
            let mut recorded = json!(command);
            if matches!(
                command,
                Command::SetOutput { .. } | Command::ToggleOutput { .. }
            ) {
                if let Some(on) = answer.get("on").and_then(Value::as_bool) {
                    recorded["on"] = json!(on);
                }
            }
            recorded
        }
        other => json!(other),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use crate::store::NewJob;
    use fresa_plugin_api::contract::Axis;
    use tokio::sync::oneshot;

    /// A task with no backend on a SQLite store, with run `run` of a 10-line job current.
    async fn task_with_run() -> (Task, RunRow, tempfile_dir::Dir) {
        let dir = tempfile_dir::Dir::new();
        let store = Store::open(&dir.0.join("t.db")).await.unwrap();
        let m = store
            .insert_machine("m", "sim-machine", &json!({}), 50.0, 1000.0, 300.0)
            .await
            .unwrap();
        let j = store
            .insert_job(NewJob {
                name: "a",
                machine_id: m,
                sha256: "x",
                size_bytes: 1,
                line_count: 10,
                analysis: None,
                source: "http",
            })
            .await
            .unwrap();
        let run = store.start_run(j, m).await.unwrap().unwrap();
        let job = store.job(j).await.unwrap().unwrap();
        let row = store.machine(m).await.unwrap().unwrap();
        let view = RunView {
            run_id: run.id,
            job_id: j,
            total_lines: 10,
            state: run.state,
            line: 0,
            times: None,
            announced: true,
        };
        let store_health = store.health().clone();
        let task = Task {
            id: m,
            lanes: None,
            unavailable: Some("no backend in this test".into()),
            bus: EventBus::new(store.clone(), 16),
            store,
            programs_dir: dir.0.clone(),
            max_program_segments: fresa_gcode::DEFAULT_MAX_SEGMENTS,
            status: watch::channel(MachineStatus::default()).0,
            row: watch::channel(row).0,
            run: watch::channel(Some(view)).0,
            gate: Arc::new(Gate::default()),
            job: watch::channel(Some(job)).0,
            launched: watch::channel(Some(run.clone())).0,
            probe_ended: watch::channel(None).0,
            pending: PendingWrites::default(),
            unstored: super::super::unstored::Marker::start(&dir.0.join("unstored"), m),
            urgent: Arc::new(tokio::sync::Mutex::new(mpsc::unbounded_channel().1)),
            loading: None,
            held_before_start: None,
            holds: Arc::new(super::super::holds::HostHolds::new(store_health.clone())),
        };
        (task, run, dir)
    }

    mod tempfile_dir {
        pub struct Dir(pub std::path::PathBuf);
        impl Dir {
            pub fn new() -> Dir {
                let p = std::env::temp_dir().join(format!(
                    "fresa-actor-{}-{}",
                    std::process::id(),
                    rand::random::<u64>()
                ));
                std::fs::create_dir_all(&p).unwrap();
                Dir(p)
            }
        }
        impl Drop for Dir {
            fn drop(&mut self) {
                let _ = std::fs::remove_dir_all(&self.0);
            }
        }
    }

    async fn job_state_events(store: &Store) -> Vec<Value> {
        store
            .events_after(0, 100)
            .await
            .unwrap()
            .into_iter()
            .filter(|e| e.kind == "job.state")
            .map(|e| serde_json::from_str(&e.data).unwrap())
            .collect()
    }

    /// The record in `DATA_DIR/unstored` once it satisfies `pred` (its writer is asynchronous).
    async fn unstored_record(
        dir: &std::path::Path,
        what: &str,
        pred: impl Fn(&[super::super::unstored::LeftBehind]) -> bool,
    ) {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
        loop {
            let left = super::super::unstored::left_behind(dir).unwrap();
            if pred(&left) {
                return;
            }
            assert!(std::time::Instant::now() < deadline, "{what}: {left:?}");
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    }

    /// Issue 23: acknowledged lines kept in memory during an outage are recorded beside the
    /// store (so a restart knows the stored line is behind) and the record is cleared once they
    /// landed.
    #[tokio::test]
    async fn acks_the_store_cannot_take_are_recorded_beside_it_until_they_land() {
        use super::super::unstored::{LeftBehind, UnstoredRun};
        let (mut task, run, dir) = task_with_run().await;
        let unstored = dir.0.join("unstored");
        let store = task.store.clone();
        task.handle_events(vec![Event::LineAcknowledged {
            run: run.id,
            line: 2,
        }])
        .await;
        store.health().mark_down("test outage");
        task.handle_events(vec![Event::LineAcknowledged {
            run: run.id,
            line: 7,
        }])
        .await;
        unstored_record(&unstored, "line 7 recorded", |left| {
            matches!(left, [LeftBehind::Record(_, r)]
                if r.runs == [UnstoredRun { run: run.id, line: 7 }])
        })
        .await;
        assert_eq!(store.run(run.id).await.unwrap().unwrap().last_line, 2);
        store.health().mark_up();
        task.flush_pending().await;
        assert_eq!(store.run(run.id).await.unwrap().unwrap().last_line, 7);
        unstored_record(&unstored, "the record cleared", |left| left.is_empty()).await;
    }

    #[tokio::test]
    async fn acks_and_the_end_of_a_run_wait_for_the_database_and_land_once_in_order() {
        let (mut task, run, _dir) = task_with_run().await;
        let store = task.store.clone();
        store.health().mark_down("test outage");

        task.handle_events(vec![
            Event::LineAcknowledged {
                run: run.id,
                line: 3,
            },
            Event::LineAcknowledged {
                run: run.id,
                line: 5,
            },
        ])
        .await;
        // Shown from memory, not written.
        assert_eq!(task.run.borrow().as_ref().map(|v| v.line), Some(5));
        assert_eq!(store.run(run.id).await.unwrap().unwrap().last_line, 0);

        // New motion is refused while the database is down, naming it.
        let (reply, answer) = oneshot::channel();
        task.handle(Msg::Call {
            request: Request::Jog {
                axis: Axis::X,
                distance: 1.0,
                feed: None,
            },
            actor: "t".into(),
            ticket: task.gate.ticket(),
            reply,
        })
        .await;
        let refused = answer.await.unwrap().unwrap_err();
        assert_eq!(refused.code, "database_unavailable");
        assert!(refused.message.contains("t.db"), "{}", refused.message);

        task.handle_events(vec![
            Event::LineAcknowledged {
                run: run.id,
                line: 10,
            },
            Event::RunEnded {
                run: run.id,
                outcome: RunOutcome::Completed,
                message: None,
            },
        ])
        .await;
        // The machine is free in memory; the store has not heard of any of it.
        assert!(task.run.borrow().is_none());
        let stored = store.run(run.id).await.unwrap().unwrap();
        assert_eq!((stored.state, stored.last_line), (RunState::Running, 0));
        assert_eq!(task.pending.acks.get(&run.id), Some(&10));
        assert_eq!(task.pending.transitions.len(), 1);
        // A duplicate end reported during the outage is not kept twice.
        task.handle_events(vec![Event::RunEnded {
            run: run.id,
            outcome: RunOutcome::Cancelled,
            message: None,
        }])
        .await;
        assert_eq!(task.pending.transitions.len(), 1);

        store.health().mark_up();
        task.flush_pending().await;
        let stored = store.run(run.id).await.unwrap().unwrap();
        assert_eq!((stored.state, stored.last_line), (RunState::Completed, 10));
        assert!(task.pending.is_empty());
        let states = job_state_events(&store).await;
        assert_eq!(states.len(), 1, "{states:?}");
        assert_eq!(states[0]["state"], "completed");
        assert_eq!(states[0]["line"], 10);

        // Nothing is written twice: a late duplicate end is ignored.
        task.handle_events(vec![Event::RunEnded {
            run: run.id,
            outcome: RunOutcome::Completed,
            message: None,
        }])
        .await;
        assert_eq!(job_state_events(&store).await.len(), 1);
    }

    /// Issue 26: an M0 reached during a database outage holds the run too (kept in memory,
    /// stored when the database returns, with the hold's message); the hold says that going
    /// on waits for the database; cycle start from anyone makes the run `running` again.
    #[tokio::test]
    async fn the_run_follows_the_machine_into_a_hold_and_out_of_it_also_during_an_outage() {
        use fresa_plugin_api::contract::{ContinueWith, Hold, HoldKind};
        let (mut task, run, _dir) = task_with_run().await;
        let store = task.store.clone();
        store.health().mark_down("test outage");
        let hold = Hold {
            kind: HoldKind::ProgramPause,
            message: "M0 at line 3: change clamp".into(),
            line: Some(3),
            program_message: Some("change clamp".into()),
            continue_with: ContinueWith::CycleStart,
            tool_change: None,
            blocked: None,
        };
        let paused = MachineStatus {
            state: MachineState::Paused,
            hold: Some(Box::new(hold)),
            ..Default::default()
        };
        task.handle_events(vec![
            Event::Status(paused.clone()),
            Event::StateChanged {
                from: MachineState::Running,
                to: MachineState::Paused,
            },
        ])
        .await;
        assert_eq!(
            task.run.borrow().as_ref().map(|r| r.state),
            Some(RunState::Paused)
        );
        let mut shown = task.status.borrow().clone();
        task.holds.explain(&mut shown);
        let blocked = shown.hold.unwrap().blocked.unwrap();
        assert!(blocked.contains("t.db"), "{blocked}");
        // A status without a state change (a position) changes nothing.
        task.handle_events(vec![Event::Status(paused)]).await;
        assert_eq!(task.pending.transitions.len(), 1);

        store.health().mark_up();
        task.flush_pending().await;
        let stored = store.run(run.id).await.unwrap().unwrap();
        assert_eq!(stored.state, RunState::Paused);
        assert_eq!(
            stored.message.as_deref(),
            Some("M0 at line 3: change clamp")
        );
        let states = job_state_events(&store).await;
        assert_eq!(states.last().unwrap()["state"], "paused");

        task.handle_events(vec![
            Event::Status(MachineStatus {
                state: MachineState::Running,
                ..Default::default()
            }),
            Event::StateChanged {
                from: MachineState::Paused,
                to: MachineState::Running,
            },
        ])
        .await;
        let stored = store.run(run.id).await.unwrap().unwrap();
        assert_eq!((stored.state, stored.message), (RunState::Running, None));
    }

    #[tokio::test]
    async fn a_transition_that_landed_before_the_outage_cut_its_answer_is_recorded_once() {
        let (mut task, run, _dir) = task_with_run().await;
        let store = task.store.clone();
        // The store already has it (the answer was lost); the task kept it pending.
        store
            .transition_run(run.id, ACTIVE, RunState::Cancelled, None)
            .await
            .unwrap()
            .unwrap();
        task.pending.transitions.push_back(PendingTransition {
            run_id: run.id,
            from: ACTIVE,
            to: RunState::Cancelled,
            message: None,
            actor: Some("op".into()),
        });
        task.flush_pending().await;
        assert!(task.pending.is_empty());
        let states = job_state_events(&store).await;
        assert_eq!(states.len(), 1, "{states:?}");
        assert_eq!(states[0]["state"], "cancelled");
    }

    #[tokio::test]
    async fn events_recorded_during_an_outage_are_written_in_order_when_it_ends() {
        let (task, _run, _dir) = task_with_run().await;
        let store = task.store.clone();
        let bus = task.bus.clone();
        store.health().mark_down("test outage");
        bus.record_or_log(
            EventKind::MachineCommand,
            Some(1),
            Some("op"),
            json!({"n": 1}),
        )
        .await;
        bus.record_or_log(
            EventKind::MachineCommand,
            Some(1),
            Some("op"),
            json!({"n": 2}),
        )
        .await;
        assert_eq!(bus.delayed_counts(), (2, 0));
        assert!(store.events_after(0, 10).await.unwrap().is_empty());
        store.health().mark_up();
        bus.record_or_log(
            EventKind::MachineCommand,
            Some(1),
            Some("op"),
            json!({"n": 3}),
        )
        .await;
        let written: Vec<Value> = store
            .events_after(0, 10)
            .await
            .unwrap()
            .into_iter()
            .map(|e| serde_json::from_str(&e.data).unwrap())
            .collect();
        let order: Vec<i64> = written.iter().map(|d| d["n"].as_i64().unwrap()).collect();
        assert_eq!(order, [1, 2, 3]);
        assert!(written[0]["recorded_at"].is_i64());
        assert!(written[2].get("recorded_at").is_none());
        assert_eq!(bus.delayed_counts(), (0, 0));
    }
}
