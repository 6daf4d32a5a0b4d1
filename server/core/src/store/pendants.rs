//! Pendants and their M1..M4 macros.

use super::{now_ms, Result, Store};
use fresa_plugin_api::contract::{Axis, Command, OutputName};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

#[derive(Debug, Clone, Serialize, sqlx::FromRow)]
pub struct PendantRow {
    pub id: i64,
    pub name: String,
    pub address: String,
    pub dialect: String,
    pub machine_id: Option<i64>,
    #[serde(skip)]
    pub config: String,
    pub created_at: i64,
    /// The node whose transport talks to it.
    pub node: Option<String>,
}

impl PendantRow {
    pub fn config_json(&self) -> Value {
        serde_json::from_str(&self.config).unwrap_or_else(|_| json!({}))
    }
}

/// What a macro key (M1..M4) does. Stored as JSON in `pendant_macros.action`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(
    tag = "type",
    rename_all = "snake_case",
    try_from = "serde_json::Map<String, Value>"
)]
pub enum MacroAction {
    /// Any immediate machine command, e.g. `{"type":"command","command":"feed_hold"}`.
    Command {
        #[serde(flatten)]
        command: Command,
    },
    /// A bounded jog, e.g. `{"type":"jog","axis":"Z","distance":5}`.
    Jog { axis: Axis, distance: f64 },
    /// Flip an output, e.g. `{"type":"toggle","output":"spindle"}` (or `coolant`, `z_lift`).
    Toggle { output: OutputName },
    /// One MDI line, e.g. `{"type":"mdi","line":"G91 G0 Z5"}`; the backend leaves the modal
    /// state as it found it.
    Mdi { line: String },
}

/// The macro kinds other than `command`, read strictly (a misspelt field is an error).
#[derive(Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
enum PlainAction {
    Jog { axis: Axis, distance: f64 },
    Toggle { output: OutputName },
    Mdi { line: String },
}

/// By hand because serde cannot flatten a command into a tagged enum and still refuse
/// unknown fields: a `command` macro is the command's own JSON (which refuses them) beside
/// `"type"`.
impl TryFrom<serde_json::Map<String, Value>> for MacroAction {
    type Error = String;
    fn try_from(mut v: serde_json::Map<String, Value>) -> std::result::Result<Self, String> {
        if v.get("type").and_then(Value::as_str) == Some("command") {
            v.remove("type");
            return serde_json::from_value::<Command>(Value::Object(v))
                .map(|command| MacroAction::Command { command })
                .map_err(|e| e.to_string());
        }
        Ok(
            match serde_json::from_value::<PlainAction>(Value::Object(v))
                .map_err(|e| e.to_string())?
            {
                PlainAction::Jog { axis, distance } => MacroAction::Jog { axis, distance },
                PlainAction::Toggle { output } => MacroAction::Toggle { output },
                PlainAction::Mdi { line } => MacroAction::Mdi { line },
            },
        )
    }
}

impl Store {
    pub async fn insert_pendant(
        &self,
        name: &str,
        address: &str,
        dialect: &str,
        machine: Option<i64>,
        config: &Value,
        macros: &[(u8, MacroAction)],
    ) -> Result<i64> {
        let mut tx = self.begin().await?;
        let now = now_ms();
        let id: i64 = sqlx::query_scalar(
            "INSERT INTO pendants (name, address, dialect, machine_id, config, created_at, node)
             VALUES ($1, $2, $3, $4, $5, $6, $7) RETURNING id",
        )
        .bind(name)
        .bind(address)
        .bind(dialect)
        .bind(machine)
        .bind(config.to_string())
        .bind(now)
        .bind(self.node())
        .fetch_one(&mut *tx)
        .await?;
        for (slot, action) in macros {
            sqlx::query("INSERT INTO pendant_macros (pendant_id, slot, action, updated_at) VALUES ($1, $2, $3, $4)")
                .bind(id)
                .bind(*slot as i64)
                .bind(json!(action).to_string())
                .bind(now)
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(id)
    }

    pub async fn list_pendants(&self) -> Result<Vec<PendantRow>> {
        sqlx::query_as("SELECT id, name, address, dialect, machine_id, config, created_at, node FROM pendants ORDER BY id")
            .fetch_all(self.pool())
            .await
    }

    pub async fn pendant(&self, id: i64) -> Result<Option<PendantRow>> {
        sqlx::query_as("SELECT id, name, address, dialect, machine_id, config, created_at, node FROM pendants WHERE id = $1")
            .bind(id)
            .fetch_optional(self.pool())
            .await
    }

    pub async fn set_pendant_machine(&self, id: i64, machine: Option<i64>) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE pendants SET machine_id = $1 WHERE id = $2")
            .bind(machine)
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    pub async fn set_pendant_address(
        &self,
        id: i64,
        address: &str,
        machine: Option<i64>,
    ) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("UPDATE pendants SET address = $1, machine_id = $2 WHERE id = $3")
            .bind(address)
            .bind(machine)
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await
    }

    /// Sets (Some) or clears (None) one macro slot.
    pub async fn set_pendant_macro(
        &self,
        id: i64,
        slot: u8,
        action: Option<&MacroAction>,
    ) -> Result<()> {
        let mut tx = self.begin().await?;
        match action {
            Some(a) => {
                sqlx::query(
                    "INSERT INTO pendant_macros (pendant_id, slot, action, updated_at) VALUES ($1, $2, $3, $4)
                     ON CONFLICT (pendant_id, slot) DO UPDATE SET action = excluded.action, updated_at = excluded.updated_at",
                )
                .bind(id)
                .bind(slot as i64)
                .bind(json!(a).to_string())
                .bind(now_ms())
                .execute(&mut *tx)
                .await?;
            }
            None => {
                sqlx::query("DELETE FROM pendant_macros WHERE pendant_id = $1 AND slot = $2")
                    .bind(id)
                    .bind(slot as i64)
                    .execute(&mut *tx)
                    .await?;
            }
        }
        tx.commit().await
    }

    pub async fn pendant_macros(&self, id: i64) -> Result<[Option<MacroAction>; 4]> {
        let rows: Vec<(i64, String)> =
            sqlx::query_as("SELECT slot, action FROM pendant_macros WHERE pendant_id = $1")
                .bind(id)
                .fetch_all(self.pool())
                .await?;
        let mut out: [Option<MacroAction>; 4] = Default::default();
        for (slot, action) in rows {
            if let (Some(cell), Ok(a)) = (
                out.get_mut((slot - 1) as usize),
                serde_json::from_str::<MacroAction>(&action),
            ) {
                *cell = Some(a);
            }
        }
        Ok(out)
    }

    pub async fn delete_pendant(&self, id: i64) -> Result<bool> {
        let mut tx = self.begin().await?;
        sqlx::query("DELETE FROM pendant_macros WHERE pendant_id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        let n = sqlx::query("DELETE FROM pendants WHERE id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        tx.commit().await?;
        Ok(n > 0)
    }
}
