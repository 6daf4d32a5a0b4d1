//! Machines' run settings (issues 25 and 26): the optional stop switch (M1), what M6 does (hold,
//! ignore, refuse), where tools are changed, and the tool length setter. Checked here, kept by
//! the store (`store::run_settings`), read by the machine's task when it loads a program and by
//! the tool setter. Every change is an audit event, `machine.run_settings`.

use crate::app::App;
use crate::error::{Error, Result};
use crate::events::EventKind;
use crate::store::{JobRow, MachineRow, MachineXyz, RunSettings, ToolChangePolicy};
use serde::Serialize;
use serde_json::json;
use utoipa::ToSchema;

/// A machine's run settings as the API shows them: [`RunSettings`] and the setter's reference.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct RunSettingsView {
    /// M1 holds the run when on.
    pub optional_stop: bool,
    /// What M6 does: `hold`, `ignore`, `refuse`.
    pub tool_change: ToolChangePolicy,
    /// Where tools are changed (machine coordinates), or null.
    pub tool_change_position: Option<MachineXyz>,
    /// The tool length setter, or null.
    pub tool_setter: Option<crate::store::ToolSetter>,
    /// Machine Z at which the reference tool tripped the setter (tool lengths are measured
    /// from it); null until it is measured, and again after the setter is moved.
    pub tool_setter_reference_z: Option<f64>,
}

impl RunSettingsView {
    fn new(s: RunSettings, reference: Option<f64>) -> RunSettingsView {
        RunSettingsView {
            optional_stop: s.optional_stop,
            tool_change: s.tool_change,
            tool_change_position: s.tool_change_position,
            tool_setter: s.tool_setter,
            tool_setter_reference_z: reference,
        }
    }
}

async fn machine_row(app: &App, machine_id: i64) -> Result<MachineRow> {
    app.store.machine(machine_id).await?.ok_or_else(|| {
        Error::not_found(
            "unknown_machine",
            format!("no machine with id {machine_id}"),
        )
    })
}

/// The machine's settings (the defaults until changed).
pub async fn get(app: &App, machine_id: i64) -> Result<RunSettingsView> {
    machine_row(app, machine_id).await?;
    let (settings, reference) = app.store.run_settings(machine_id).await?;
    Ok(RunSettingsView::new(settings, reference))
}

fn position(field: &str, p: &MachineXyz) -> Result<()> {
    for (axis, v) in [("x", p.x), ("y", p.y), ("z", p.z)] {
        if !v.is_finite() || v.abs() > fresa_plugin_api::kit::MAX_COORDINATE_MM {
            return Err(Error::invalid(
                "invalid_field",
                format!("field `{field}.{axis}`: {v} is not a machine position in mm"),
            ));
        }
    }
    Ok(())
}

/// What is wrong with `s` on machine `row`, if anything. Positions are checked against the
/// machine's travel by its backend when a program is loaded (the change position) or the
/// setter probes.
fn check(s: &RunSettings, row: &MachineRow) -> Result<()> {
    if let Some(p) = &s.tool_change_position {
        position("tool_change_position", p)?;
    }
    if let Some(t) = &s.tool_setter {
        position(
            "tool_setter",
            &MachineXyz {
                x: t.x,
                y: t.y,
                z: t.z,
            },
        )?;
        if !(t.distance_mm.is_finite() && t.distance_mm > 0.0 && t.distance_mm <= row.max_jog_mm) {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `tool_setter.distance_mm`: {} must be more than 0 and at most {} mm \
                     (the machine's `max_jog_mm`)",
                    t.distance_mm, row.max_jog_mm
                ),
            ));
        }
        if !(t.feed_mm_min.is_finite()
            && t.feed_mm_min > 0.0
            && t.feed_mm_min <= row.max_probe_feed_mm_min)
        {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `tool_setter.feed_mm_min`: {} must be more than 0 and at most {} \
                     mm/min (the machine's `max_probe_feed_mm_min`)",
                    t.feed_mm_min, row.max_probe_feed_mm_min
                ),
            ));
        }
        if !(1..=crate::tools::MAX_TOOL).contains(&t.reference_tool) {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `tool_setter.reference_tool`: {} is not a tool number (1..={})",
                    t.reference_tool,
                    crate::tools::MAX_TOOL
                ),
            ));
        }
    }
    Ok(())
}

/// Replaces the machine's settings. The reference tool's trip is kept while the setter stays
/// where it was (same X, Y, Z) and forgotten when it moves.
pub async fn put(
    app: &App,
    machine_id: i64,
    settings: RunSettings,
    actor: &str,
) -> Result<RunSettingsView> {
    let row = machine_row(app, machine_id).await?;
    check(&settings, &row)?;
    app.store.health().check()?;
    let (before, _) = app.store.run_settings(machine_id).await?;
    let place = |s: &RunSettings| s.tool_setter.map(|t| (t.x, t.y, t.z, t.reference_tool));
    let keep = place(&before).is_some() && place(&before) == place(&settings);
    app.store
        .health()
        .guard(app.store.set_run_settings(machine_id, &settings, keep))
        .await?;
    app.bus
        .record_or_log(
            EventKind::MachineRunSettings,
            Some(machine_id),
            Some(actor),
            json!(settings),
        )
        .await;
    get(app, machine_id).await
}

/// Changes the settings named in `changes` (a JSON object; `null` clears a position or the
/// setter), keeping the others.
pub async fn patch(
    app: &App,
    machine_id: i64,
    changes: &serde_json::Value,
    actor: &str,
) -> Result<RunSettingsView> {
    let serde_json::Value::Object(changes) = changes else {
        return Err(Error::invalid(
            "invalid_field",
            "the body must be a JSON object of the settings to change, e.g. {\"optional_stop\": true}",
        ));
    };
    machine_row(app, machine_id).await?;
    let (current, _) = app.store.run_settings(machine_id).await?;
    let mut merged = json!(current);
    for (k, v) in changes {
        merged[k] = v.clone();
    }
    let settings: RunSettings = serde_json::from_value(merged)
        .map_err(|e| Error::invalid("invalid_field", format!("run settings: {e}")))?;
    put(app, machine_id, settings, actor).await
}

/// A job whose program changes tools (M6) is refused on a machine whose policy is `refuse`,
/// naming the first M6 line (from the upload's analysis; a job analysed before lines were
/// recorded is refused naming its tools).
pub async fn check_start(app: &App, job: &JobRow) -> Result<()> {
    let (settings, _) = app
        .store
        .health()
        .guard(app.store.run_settings(job.machine_id))
        .await?;
    if settings.tool_change != ToolChangePolicy::Refuse {
        return Ok(());
    }
    let analysis: serde_json::Value = job
        .analysis
        .as_deref()
        .and_then(|a| serde_json::from_str(a).ok())
        .unwrap_or_default();
    let line = analysis["first_tool_change_line"].as_u64();
    let tools = analysis["tools"].as_array().filter(|t| !t.is_empty());
    let why = match (line, tools) {
        (Some(line), _) => format!("line {line} changes tools (M6)"),
        (None, Some(tools)) => format!(
            "the program changes tools (M6 with {}; upload it again to have the line named)",
            tools
                .iter()
                .map(|t| format!("T{t}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        (None, None) => return Ok(()),
    };
    Err(Error::conflict(
        "tool_change_refused",
        format!(
            "job {}: {why}, and machine {}'s tool-change policy is `refuse` (set it to `hold` \
             in its run settings to change tools by hand)",
            job.id, job.machine_id
        ),
    ))
}
