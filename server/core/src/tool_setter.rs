//! The tool length setter (issue 25): a fixed switch at a known machine position
//! (`run_settings`' `tool_setter`). Measuring a tool goes up to the setter's Z, across to it,
//! probes down (through [`Machine::probe`]: bounded, gated, stopped when its caller goes away)
//! and back up, then stores the tool's length in the machine's tool table.
//!
//! Convention: a tool's length is how much lower its tip reaches than the reference tool's
//! (`tool_setter.reference_tool`, whose length is 0): the machine Z at which it tripped the
//! setter minus the Z at which the reference tool did. A longer tool trips higher up, so its
//! length is positive; it is what G43 adds to the machine Z for the same tip position.
//!
//! During a tool-change hold for this tool (and with G43 not in force) the work offset's Z is
//! moved by the new tool's length minus the old one's, so the new tip reads the same Z at the
//! same height as the old one did: Z is zeroed again without touching the part, recorded like
//! a touch-off (`machine.touch_off` with `source: tool_setter`, before and after). With G43 in
//! force the backend is given the new table instead, and the new length applies at cycle
//! start. Every measure is recorded as `machine.tool_measured`.

use crate::app::App;
use crate::error::{Error, Result};
use crate::events::EventKind;
use crate::machine::probing::ProbeAsk;
use crate::machine::Machine;
use crate::store::{ToolRow, ToolSetter};
use fresa_plugin_api::contract::{
    Axis, AxisValues, MachineState, ProbeUntil, ProgramTool, WorkOffset,
};
use serde::Serialize;
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;
use utoipa::ToSchema;

/// How long the moves to and from the setter may take to end before the answer says so.
const SETTLE: Duration = Duration::from_secs(120);

/// The work offset's Z moved for a new tool during a tool change.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct Rezero {
    pub offset: WorkOffset,
    /// The tool that was in before the change, and its length in the table.
    pub from_tool: u32,
    pub from_length_mm: f64,
    pub before: AxisValues,
    pub after: AxisValues,
}

/// What a measure did (`POST /machines/{id}/tools/{n}/measure`).
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct MeasureReport {
    pub tool: i64,
    /// Machine Z where the tool tripped the setter.
    pub trip_z: f64,
    /// Machine Z where the reference tool tripped it (this one's, when it is the reference).
    pub reference_z: f64,
    /// The length stored: `trip_z - reference_z`.
    pub length_mm: f64,
    /// The length the table had before, if it had the tool.
    pub previous_length_mm: Option<f64>,
    /// During a tool change for this tool without G43: the work offset's Z moved for it.
    pub rezero: Option<Rezero>,
    /// Why a tool change's Z was not moved, when it was not (G43 in force: the new length
    /// applies at cycle start; the old tool's length unknown).
    pub note: Option<String>,
    /// Machine position once back up at the setter's Z.
    pub position: AxisValues,
}

fn conflict(code: &'static str, m: String) -> Error {
    Error::conflict(code, m)
}

/// Jogs `axis` by `distance` in pieces of at most `max_jog_mm`, all queued (the backend runs
/// them in order), as part of the operation that took the gate's `ticket`.
async fn jog_by(
    m: &Machine,
    axis: Axis,
    distance: f64,
    max_jog_mm: f64,
    actor: &str,
    ticket: u64,
) -> Result<()> {
    let mut left = distance;
    while left.abs() > 1e-9 {
        let step = left.clamp(-max_jog_mm, max_jog_mm);
        m.jog_ticketed(axis, step, None, actor, ticket).await?;
        left -= step;
    }
    Ok(())
}

/// Waits until the jogs sent so far have ended.
async fn settled(m: &Machine) -> Result<()> {
    let mut watch = m.subscribe_status();
    m.sync().await;
    let still = watch.wait_for(|s| s.state != MachineState::Jogging);
    let ended = matches!(tokio::time::timeout(SETTLE, still).await, Ok(Ok(_)));
    if ended {
        return Ok(());
    }
    Err(conflict(
        "machine_moving",
        format!("the move to or from the tool setter had not ended after {SETTLE:?}"),
    ))
}

/// Goes up to the setter's Z (at the current X Y), across to it, and down to its Z if the
/// machine was higher: the Z is never lowered while X and Y move.
async fn go_to_setter(
    m: &Machine,
    setter: &ToolSetter,
    max_jog_mm: f64,
    actor: &str,
    ticket: u64,
) -> Result<()> {
    let at = m.status().machine_position;
    if at.z < setter.z {
        jog_by(m, Axis::Z, setter.z - at.z, max_jog_mm, actor, ticket).await?;
    }
    jog_by(m, Axis::X, setter.x - at.x, max_jog_mm, actor, ticket).await?;
    jog_by(m, Axis::Y, setter.y - at.y, max_jog_mm, actor, ticket).await?;
    if at.z > setter.z {
        jog_by(m, Axis::Z, setter.z - at.z, max_jog_mm, actor, ticket).await?;
    }
    settled(m).await
}

/// Measures tool `tool` on the machine's tool setter (the tool in the spindle is taken to be
/// it) and stores its length; see the module's description.
pub async fn measure(app: &App, machine_id: i64, tool: i64, actor: &str) -> Result<MeasureReport> {
    let m: Arc<Machine> = app.machines.get(machine_id).ok_or_else(|| {
        Error::not_found(
            "unknown_machine",
            format!("no machine with id {machine_id}"),
        )
    })?;
    if !(1..=crate::tools::MAX_TOOL).contains(&tool) {
        return Err(Error::invalid(
            "invalid_field",
            format!(
                "tool {tool} is not a tool number (1..={})",
                crate::tools::MAX_TOOL
            ),
        ));
    }
    let (settings, reference) = app.store.run_settings(machine_id).await?;
    let Some(setter) = settings.tool_setter else {
        return Err(conflict(
            "no_tool_setter",
            format!(
                "machine {machine_id} has no tool setter: set `tool_setter` in its run settings \
                 (PUT /api/v1/machines/{machine_id}/run-settings)"
            ),
        ));
    };
    let is_reference = tool == setter.reference_tool;
    if !is_reference && reference.is_none() {
        return Err(conflict(
            "reference_not_measured",
            format!(
                "tool lengths are measured from the reference tool T{r}: measure T{r} first",
                r = setter.reference_tool
            ),
        ));
    }
    let status = m.status();
    let hold = status
        .hold
        .clone()
        .filter(|_| crate::machine::holds::in_tool_change(&status));
    if m.run().is_some() && hold.is_none() {
        return Err(conflict(
            "machine_busy",
            format!(
                "machine {machine_id} runs a job: a tool is measured while the machine is idle \
                 or held for a tool change"
            ),
        ));
    }
    let table = app.store.tools(machine_id).await?;
    let row = table.iter().find(|t| t.tool == tool).cloned();
    let max_jog_mm = m.row().max_jog_mm;
    // One ticket for the whole measure: a stop at any point cancels what is left of it.
    let ticket = m.gate().ticket();
    go_to_setter(&m, &setter, max_jog_mm, actor, ticket).await?;
    // With the measure's ticket: a stop during the approach also cancels the probe.
    let probed = m
        .probe_ticketed(
            ProbeAsk {
                axis: Axis::Z,
                positive: false,
                distance: setter.distance_mm,
                feed: setter.feed_mm_min,
                until: ProbeUntil::Contact,
            },
            actor,
            ticket,
        )
        .await?;
    // Back up to the setter's Z, tripped or not.
    let down = m.status().machine_position.z;
    jog_by(&m, Axis::Z, setter.z - down, max_jog_mm, actor, ticket).await?;
    settled(&m).await?;
    let Some(trip) = probed.trip else {
        return Err(Error::invalid(
            "probe_not_tripped",
            format!(
                "the tool ran {} mm down from Z {} without tripping the setter; nothing was \
                 stored (is the tool in, and the setter at X {} Y {}?)",
                setter.distance_mm, setter.z, setter.x, setter.y
            ),
        ));
    };
    let reference_z = if is_reference {
        app.store
            .health()
            .guard(app.store.set_setter_reference(machine_id, trip.z))
            .await?;
        trip.z
    } else {
        reference.unwrap_or(trip.z)
    };
    let length = trip.z - reference_z;
    let stored = ToolRow {
        tool,
        diameter_mm: row.as_ref().map_or(0.0, |r| r.diameter_mm),
        length_mm: length,
        description: row
            .as_ref()
            .map(|r| r.description.clone())
            .unwrap_or_default(),
    };
    crate::tools::set(app, machine_id, stored, actor).await?;
    let (rezero, note) = match hold.and_then(|h| h.tool_change) {
        Some(tc) if i64::from(tc.to) == tool => {
            if tc.length_compensation {
                tell_backend(app, &m, actor).await;
                (
                    None,
                    Some(format!(
                        "G43 is in force: T{tool}'s length {length:.4} mm applies at cycle start"
                    )),
                )
            } else {
                rezero(app, &m, &table, &setter, tc.from, length, actor).await?
            }
        }
        _ => (None, None),
    };
    let report = MeasureReport {
        tool,
        trip_z: trip.z,
        reference_z,
        length_mm: length,
        previous_length_mm: row.map(|r| r.length_mm),
        rezero,
        note,
        position: m.status().machine_position,
    };
    app.bus
        .record_or_log(
            EventKind::MachineToolMeasured,
            Some(machine_id),
            Some(actor),
            json!(report),
        )
        .await;
    Ok(report)
}

/// The backend's copy of the tool table, for the run in progress (G43).
async fn tell_backend(app: &App, m: &Machine, actor: &str) {
    let tools = match app.store.tools(m.id).await {
        Ok(t) => t,
        Err(e) => {
            tracing::error!(machine = m.id, error = %e, "could not read the tool table");
            return;
        }
    };
    let tools = tools
        .iter()
        .filter_map(|t| {
            Some(ProgramTool {
                tool: u32::try_from(t.tool).ok()?,
                diameter_mm: t.diameter_mm,
                length_mm: t.length_mm,
            })
        })
        .collect();
    if let Err(e) = m.set_tools(tools, actor).await {
        tracing::warn!(machine = m.id, error = %e, "the backend did not take the new tool table");
    }
}

/// Moves the active work offset's Z by the new tool's length minus the old one's (the old
/// one's from the table before this measure; the reference tool's is 0).
async fn rezero(
    app: &App,
    m: &Machine,
    table: &[ToolRow],
    setter: &ToolSetter,
    from: Option<u32>,
    length: f64,
    actor: &str,
) -> Result<(Option<Rezero>, Option<String>)> {
    let Some(from) = from else {
        return Ok((
            None,
            Some("the tool that was in before is not known: Z was not moved".to_string()),
        ));
    };
    let from_length = match table.iter().find(|t| t.tool == i64::from(from)) {
        Some(t) => t.length_mm,
        None if i64::from(from) == setter.reference_tool => 0.0,
        None => {
            return Ok((
                None,
                Some(format!(
                    "T{from} (the tool that was in) has no length in the tool table: Z was \
                     not moved; measure it too, or touch off"
                )),
            ))
        }
    };
    let status = m.status();
    let offset = status.active_offset;
    let before = app
        .store
        .offsets(m.id)
        .await?
        .into_iter()
        .find(|(o, _)| *o == offset)
        .map(|(_, v)| v)
        .unwrap_or_default();
    let mut after = before;
    after.z = before.z + (length - from_length);
    m.set_offset(offset, after, actor).await.map_err(|e| {
        Error::new(
            e.kind,
            e.code,
            format!(
                "the length was stored, but Z could not be zeroed for the new tool: {}",
                e.message
            ),
        )
    })?;
    app.bus
        .record_or_log(
            EventKind::MachineTouchOff,
            Some(m.id),
            Some(actor),
            json!({
                "axis": Axis::Z, "offset": offset, "before": before, "after": after,
                "source": "tool_setter", "from_tool": from, "from_length_mm": from_length,
                "length_mm": length,
            }),
        )
        .await;
    Ok((
        Some(Rezero {
            offset,
            from_tool: from,
            from_length_mm: from_length,
            before,
            after,
        }),
        None,
    ))
}
