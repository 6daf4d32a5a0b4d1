//! Machines' tool tables (G41/G42 `D`, G43): checked here, kept by the store, read by the
//! upload check (`jobs`) and handed to the backend with each program. Every change is an audit
//! event, `machine.tools`.

use crate::app::App;
use crate::error::{Error, Result};
use crate::events::EventKind;
use crate::store::ToolRow;
use serde_json::json;

/// Highest tool number (LinuxCNC's tool tables go to 99999 too).
pub const MAX_TOOL: i64 = 99_999;
/// Most tools in one table.
pub const MAX_TOOLS: usize = 1000;
/// Largest |diameter| (mm): no milling cutter is a metre wide.
const MAX_DIAMETER_MM: f64 = 1000.0;
/// Largest |length offset| (mm).
const MAX_LENGTH_MM: f64 = 10_000.0;
const MAX_DESCRIPTION: usize = 200;

/// Checks one tool; `field` prefixes the field names in messages (`tools[2].`).
fn check(field: &str, t: &ToolRow) -> Result<()> {
    let bad = |name: &str, why: String| {
        Err(Error::invalid(
            "invalid_field",
            format!("field `{field}{name}`: {why}"),
        ))
    };
    if !(1..=MAX_TOOL).contains(&t.tool) {
        return bad(
            "tool",
            format!("{} is not a tool number (1..={MAX_TOOL})", t.tool),
        );
    }
    if !t.diameter_mm.is_finite() || t.diameter_mm.abs() > MAX_DIAMETER_MM {
        return bad(
            "diameter_mm",
            format!("must be a finite number of mm, at most {MAX_DIAMETER_MM} either way"),
        );
    }
    if !t.length_mm.is_finite() || t.length_mm.abs() > MAX_LENGTH_MM {
        return bad(
            "length_mm",
            format!("must be a finite number of mm, at most {MAX_LENGTH_MM} either way"),
        );
    }
    if t.description.chars().count() > MAX_DESCRIPTION
        || t.description.chars().any(char::is_control)
    {
        return bad(
            "description",
            format!("at most {MAX_DESCRIPTION} characters, no control characters"),
        );
    }
    Ok(())
}

async fn known_machine(app: &App, machine_id: i64) -> Result<()> {
    match app.store.machine(machine_id).await? {
        Some(_) => Ok(()),
        None => Err(Error::not_found(
            "unknown_machine",
            format!("no machine with id {machine_id}"),
        )),
    }
}

/// The machine's table, by tool number.
pub async fn list(app: &App, machine_id: i64) -> Result<Vec<ToolRow>> {
    known_machine(app, machine_id).await?;
    Ok(app.store.tools(machine_id).await?)
}

/// The machine's table as the interpreter takes it (empty for an unknown machine).
pub async fn gcode_table(app: &App, machine_id: i64) -> Result<fresa_gcode::ToolTable> {
    Ok(ToolRow::to_gcode(&app.store.tools(machine_id).await?))
}

/// Replaces the whole table.
pub async fn replace(
    app: &App,
    machine_id: i64,
    mut tools: Vec<ToolRow>,
    actor: &str,
) -> Result<Vec<ToolRow>> {
    known_machine(app, machine_id).await?;
    if tools.len() > MAX_TOOLS {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `tools`: at most {MAX_TOOLS} tools"),
        ));
    }
    for (i, t) in tools.iter().enumerate() {
        check(&format!("tools[{i}]."), t)?;
    }
    tools.sort_by_key(|t| t.tool);
    if let Some(w) = tools.windows(2).find(|w| w[0].tool == w[1].tool) {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `tools`: tool {} is listed twice", w[0].tool),
        ));
    }
    app.store.replace_tools(machine_id, &tools).await?;
    app.bus
        .record_or_log(
            EventKind::MachineTools,
            Some(machine_id),
            Some(actor),
            json!({"replaced": true, "tools": tools}),
        )
        .await;
    Ok(tools)
}

/// Adds or replaces one tool.
pub async fn set(app: &App, machine_id: i64, tool: ToolRow, actor: &str) -> Result<ToolRow> {
    known_machine(app, machine_id).await?;
    check("", &tool)?;
    let existing = app.store.tools(machine_id).await?;
    if existing.len() >= MAX_TOOLS && !existing.iter().any(|t| t.tool == tool.tool) {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `tool`: the table already has {MAX_TOOLS} tools"),
        ));
    }
    app.store.upsert_tool(machine_id, &tool).await?;
    app.bus
        .record_or_log(
            EventKind::MachineTools,
            Some(machine_id),
            Some(actor),
            json!({"set": tool}),
        )
        .await;
    Ok(tool)
}

/// Removes one tool.
pub async fn delete(app: &App, machine_id: i64, tool: i64, actor: &str) -> Result<()> {
    known_machine(app, machine_id).await?;
    if !app.store.delete_tool(machine_id, tool).await? {
        return Err(Error::not_found(
            "unknown_tool",
            format!("machine {machine_id} has no tool {tool}"),
        ));
    }
    app.bus
        .record_or_log(
            EventKind::MachineTools,
            Some(machine_id),
            Some(actor),
            json!({"deleted": tool}),
        )
        .await;
    Ok(())
}
