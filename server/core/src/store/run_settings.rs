//! Each machine's run settings (issues 25 and 26): the optional stop switch, what M6 does, where
//! tools are changed, and the tool length setter. Kept as one checked JSON object per machine
//! (absent: the defaults), plus the reference tool's trip on the setter.

use super::{now_ms, Result, Store};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// What a program's M6 does on a machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ToolChangePolicy {
    /// The run holds for a manual tool change (the default).
    #[default]
    Hold,
    /// M6 passes: the run goes on with the tool that is in.
    Ignore,
    /// A program with M6 is refused at start, naming its line.
    Refuse,
}

impl ToolChangePolicy {
    pub fn as_str(self) -> &'static str {
        match self {
            ToolChangePolicy::Hold => "hold",
            ToolChangePolicy::Ignore => "ignore",
            ToolChangePolicy::Refuse => "refuse",
        }
    }
}

/// A machine position, mm (machine coordinates).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MachineXyz {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// A fixed tool length setter: a switch the tool is lowered onto, at a known machine position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ToolSetter {
    /// Machine X and Y of the setter's button.
    pub x: f64,
    pub y: f64,
    /// Machine Z to probe down from: clear of the setter with the longest tool. The machine
    /// goes up to it first (at its X Y), across, and back up to it after the probe.
    pub z: f64,
    /// How far down from `z` to probe at most, mm (at most the machine's `max_jog_mm`).
    pub distance_mm: f64,
    /// Probing feed, mm/min (at most the machine's `max_probe_feed_mm_min`).
    pub feed_mm_min: f64,
    /// The tool whose length is 0: every other tool's length is measured from it (its trip
    /// on the setter). Measure it first.
    pub reference_tool: i64,
}

/// A machine's run settings (`GET/PUT /api/v1/machines/{id}/run-settings`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RunSettings {
    /// The optional stop switch: on, M1 holds the run like M0; off, M1 is passed over.
    #[serde(default)]
    pub optional_stop: bool,
    /// What M6 does: `hold` (default), `ignore`, `refuse`.
    #[serde(default)]
    pub tool_change: ToolChangePolicy,
    /// Where the machine goes for a manual tool change (Z first); null: it stays where M6
    /// found it.
    #[serde(default)]
    pub tool_change_position: Option<MachineXyz>,
    /// The tool length setter; null: none.
    #[serde(default)]
    pub tool_setter: Option<ToolSetter>,
}

impl Store {
    // ---- run settings ----

    /// The machine's settings (the defaults when it has none stored) and the reference tool's
    /// trip Z on the setter, if measured. A stored object that no longer parses is reported.
    pub async fn run_settings(&self, machine_id: i64) -> Result<(RunSettings, Option<f64>)> {
        let row: Option<(String, Option<f64>)> = sqlx::query_as(
            "SELECT settings, setter_reference_z FROM machine_run_settings WHERE machine_id = $1",
        )
        .bind(machine_id)
        .fetch_optional(&self.pool)
        .await?;
        let Some((text, reference)) = row else {
            return Ok((RunSettings::default(), None));
        };
        let settings = serde_json::from_str(&text).map_err(|e| sqlx::Error::Decode(e.into()))?;
        Ok((settings, reference))
    }

    /// Replaces the settings; the reference trip is kept unless `keep_reference` is false.
    pub async fn set_run_settings(
        &self,
        machine_id: i64,
        settings: &RunSettings,
        keep_reference: bool,
    ) -> Result<()> {
        let text = serde_json::to_string(settings).map_err(|e| sqlx::Error::Encode(e.into()))?;
        let mut tx = self.begin().await?;
        sqlx::query(
            "INSERT INTO machine_run_settings (machine_id, settings, setter_reference_z, updated_at)
             VALUES ($1, $2, NULL, $3)
             ON CONFLICT (machine_id) DO UPDATE SET settings = excluded.settings,
             updated_at = excluded.updated_at,
             setter_reference_z = CASE WHEN $4 THEN machine_run_settings.setter_reference_z
                                  ELSE NULL END",
        )
        .bind(machine_id)
        .bind(text)
        .bind(now_ms())
        .bind(keep_reference)
        .execute(&mut *tx)
        .await?;
        tx.commit().await
    }

    /// Records the reference tool's trip Z on the setter (the settings must exist).
    pub async fn set_setter_reference(&self, machine_id: i64, z: f64) -> Result<bool> {
        let mut tx = self.begin().await?;
        let done = sqlx::query(
            "UPDATE machine_run_settings SET setter_reference_z = $1, updated_at = $2
             WHERE machine_id = $3",
        )
        .bind(z)
        .bind(now_ms())
        .bind(machine_id)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(done.rows_affected() > 0)
    }
}
