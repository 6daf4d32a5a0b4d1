//! Setting the workshop up: creating machines and pendants, moving them between nodes, and
//! recording part zeros. Each function checks its input, changes the store and the live state
//! together and records the audit event, so HTTP (and any other front end) only parses the
//! request and shows the answer. Errors carry the API's codes.

use crate::app::{App, SharedApp};
use crate::error::{Error, Result};
use crate::events::EventKind;
pub use crate::machine::limits::OverrideLimits;
use crate::machine::{limits, Machine};
use crate::pendants;
use crate::store::{MacroAction, PartZeroRow, PendantRow};
use fresa_plugin_api::contract::AxisValues;
use serde_json::{json, Value};
use std::collections::BTreeMap;

/// A machine to create (`POST /machines`).
pub struct NewMachine {
    pub name: String,
    /// A loaded backend plugin.
    pub backend: String,
    /// The backend's settings (default `{}`); it judges them before anything is stored.
    pub config: Option<Value>,
    /// Longest jog accepted, mm (default 50).
    pub max_jog_mm: Option<f64>,
    /// Fastest jog feed accepted, mm/min (default 5000).
    pub max_feed_mm_min: Option<f64>,
    /// Fastest probing feed accepted, mm/min (default 300).
    pub max_probe_feed_mm_min: Option<f64>,
    /// The overrides an operator may set (default feed 10-200 %, spindle 50-150 %, rapid
    /// 25-100 %).
    pub override_limits: Option<limits::OverrideLimits>,
    /// The machine Z (machine coordinates, mm) a start at a line goes up to at least before
    /// it moves across (default: none, see `crate::start_at`).
    pub safe_z_mm: Option<f64>,
    /// Maintenance intervals (default none), e.g. `[{"name": "lubricate",
    /// "every_spindle_hours": 40}]`: each raises `machine.maintenance_due` once it comes due.
    pub maintenance: Option<Vec<crate::records::MaintenanceItem>>,
}

/// Creates a machine: checks the fields, lets the backend judge its config (the instance it
/// judged with is the one kept, so a real controller is not connected twice), stores the row,
/// starts the machine's task and records `machine.created`. Returns the new id.
pub async fn create_machine(app: &App, req: NewMachine, actor: &str) -> Result<i64> {
    let name = Error::required_name(&req.name)?;
    let mut config = req.config.unwrap_or_else(|| json!({}));
    if !config.is_object() {
        return Err(Error::invalid(
            "invalid_field",
            "field `config` must be a JSON object",
        ));
    }
    let max_jog = limits::check_configured(
        "max_jog_mm",
        req.max_jog_mm.unwrap_or(50.0),
        limits::MAX_JOG_MM,
    )?;
    let max_feed = limits::check_configured(
        "max_feed_mm_min",
        req.max_feed_mm_min.unwrap_or(5000.0),
        limits::MAX_FEED_MM_MIN,
    )?;
    let max_probe_feed = limits::check_configured(
        "max_probe_feed_mm_min",
        req.max_probe_feed_mm_min
            .unwrap_or(limits::DEFAULT_PROBE_FEED_MM_MIN),
        limits::MAX_PROBE_FEED_MM_MIN,
    )?;
    let override_limits = req.override_limits.unwrap_or_default();
    override_limits.check_configured()?;
    if let Some(z) = req
        .safe_z_mm
        .filter(|z| !(z.is_finite() && z.abs() <= fresa_gcode::MAX_COORDINATE_MM))
    {
        return Err(Error::invalid(
            "invalid_field",
            format!(
                "field `safe_z_mm` must be a machine Z within ±{} mm, got {z}",
                fresa_gcode::MAX_COORDINATE_MM
            ),
        ));
    }
    let maintenance = req.maintenance.unwrap_or_default();
    crate::records::MaintenanceItem::check_all(&maintenance)?;
    let Some(lib) = app.plugins.get(&req.backend) else {
        return Err(Error::invalid(
            "unknown_backend",
            format!(
                "field `backend`: no plugin named {:?} is loaded (loaded: {})",
                req.backend,
                app.plugins.names().join(", ")
            ),
        ));
    };
    if app.store.machine_by_name(name).await?.is_some() {
        return Err(Error::conflict(
            "name_taken",
            format!("a machine named {name:?} already exists"),
        ));
    }
    limits::confine_backend_files(&mut config, &app.settings.data_dir)?;
    let backend = Machine::prepare(lib, config.clone()).await.map_err(|e| {
        Error::invalid(
            "invalid_config",
            format!("field `config` rejected by {}: {e}", req.backend),
        )
    })?;
    let id = app
        .store
        .insert_machine_with(
            name,
            &req.backend,
            &config,
            [max_jog, max_feed, max_probe_feed],
            &override_limits,
        )
        .await
        .map_err(|e| Error::insert_failed(e, "machine", name))?;
    if req.safe_z_mm.is_some() {
        app.store.set_machine_safe_z(id, req.safe_z_mm).await?;
    }
    if !maintenance.is_empty() {
        let text = serde_json::to_string(&maintenance)
            .map_err(|e| Error::internal(format!("maintenance: {e}")))?;
        app.store.set_machine_maintenance(id, &text).await?;
    }
    let row = app
        .store
        .machine(id)
        .await?
        .ok_or_else(|| Error::internal("machine vanished"))?;
    let m = Machine::start(
        row,
        Ok(backend),
        app.store.clone(),
        app.bus.clone(),
        &app.machine_options(),
    )
    .await;
    app.machines.insert(m);
    app.bus
        .record_or_log(
            EventKind::MachineCreated,
            Some(id),
            Some(actor),
            json!({"id": id, "name": name, "backend": req.backend}),
        )
        .await;
    Ok(id)
}

/// A `node` field: a name a node could have (it need not have started yet).
pub fn check_node_name(node: &str) -> Result<()> {
    if crate::config::NodeSettings::valid_name(node) {
        return Ok(());
    }
    Err(Error::invalid(
        "invalid_field",
        format!("node: {node:?} is not a node name (1 to 63 letters, digits, '-', '_' or '.')"),
    ))
}

/// Moves a machine (and the pendants bound to it) to another node, the hardware having moved:
/// that node starts driving it within a heartbeat and this one lets go. Refused with
/// `machine_busy` while a run is active (the run belongs to the process driving it). Records
/// `machine.node`.
pub async fn set_machine_node(app: &App, id: i64, node: &str, actor: &str) -> Result<()> {
    check_node_name(node)?;
    let before =
        app.store.machine(id).await?.ok_or_else(|| {
            Error::not_found("unknown_machine", format!("no machine with id {id}"))
        })?;
    if !app.store.set_machine_node(id, node).await? {
        return Err(Error::conflict(
            "machine_busy",
            format!(
                "machine {id} has an active run; finish or cancel it before moving the machine"
            ),
        ));
    }
    app.bus
        .record_or_log(
            EventKind::MachineNode,
            Some(id),
            Some(actor),
            json!({"from": before.node, "to": node}),
        )
        .await;
    Ok(())
}

/// A part zero to record: at `position` (machine coordinates), or where the machine stands.
#[derive(Default)]
pub struct PartZero {
    pub position: Option<AxisValues>,
    /// Who found it (default `api`).
    pub source: Option<String>,
    pub note: Option<String>,
}

/// Records a part zero on machine `m` (`machine.part_zero`); refused with `machine_moving`
/// while it moves or holds a paused job, and while the database is down.
pub async fn record_part_zero(m: &Machine, req: PartZero, actor: &str) -> Result<PartZeroRow> {
    let source = req.source.unwrap_or_else(|| "api".into());
    m.record_part_zero(req.position, &source, req.note.as_deref(), actor)
        .await
}

/// A pendant to create (`POST /pendants`).
pub struct NewPendant {
    pub name: String,
    /// `host:port` (default port 8001), an IP or DNS name.
    pub address: String,
    /// The machine to bind it to (one of this node's).
    pub machine: Option<i64>,
    /// `firmware` (default) or `document`.
    pub dialect: Option<String>,
    pub config: Option<Value>,
    /// `M1`..`M4` to an action or null.
    pub macros: Option<BTreeMap<String, Option<Value>>>,
}

use crate::machine::probing::MAX_TOUCH_PLATE_MM;

/// Creates a pendant: checks the fields, stores the row and its macros, lets the transport
/// plugin judge its config (the instance it judged with is the one used; a refused config
/// leaves no row), starts its tasks and records `pendant.created`. Returns the new id.
pub async fn create_pendant(app: &SharedApp, req: NewPendant, actor: &str) -> Result<i64> {
    let name = Error::required_name(&req.name)?;
    let (host, port) = split_address(&req.address);
    if host.is_empty() || port == 0 {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `address`: {:?} is not host:port (e.g. 192.168.1.40:8001 or MPG000001.local)", req.address),
        ));
    }
    let dialect = req.dialect.unwrap_or_else(|| "firmware".into());
    if !matches!(dialect.as_str(), "firmware" | "document") {
        return Err(Error::invalid(
            "invalid_field",
            format!("field `dialect`: {dialect:?} is not firmware or document"),
        ));
    }
    let config = req.config.unwrap_or_else(|| json!({}));
    if !config.is_object() {
        return Err(Error::invalid(
            "invalid_field",
            "field `config` must be a JSON object",
        ));
    }
    if let Some(v) = config.get("stop_program_on_lost") {
        if !v.is_boolean() {
            return Err(Error::invalid(
                "invalid_field",
                "field `config.stop_program_on_lost` must be true or false",
            ));
        }
    }
    if let Some(v) = config.get("touch_plate_mm") {
        if !v
            .as_f64()
            .is_some_and(|mm| mm > 0.0 && mm <= MAX_TOUCH_PLATE_MM)
        {
            return Err(Error::invalid(
                "invalid_field",
                format!(
                    "field `config.touch_plate_mm`: {v} is not a touch plate's thickness in mm \
                     (more than 0, at most {MAX_TOUCH_PLATE_MM})"
                ),
            ));
        }
    }
    check_pendant_machine(app, req.machine).await?;
    let macros: Vec<(u8, MacroAction)> = match &req.macros {
        Some(m) => parse_macros(m)?
            .into_iter()
            .filter_map(|(s, a)| a.map(|a| (s, a)))
            .collect(),
        None => Vec::new(),
    };
    let id = app
        .store
        .insert_pendant(
            name,
            req.address.trim(),
            &dialect,
            req.machine,
            &config,
            &macros,
        )
        .await
        .map_err(|e| Error::insert_failed(e, "pendant", name))?;
    let row = app
        .store
        .pendant(id)
        .await?
        .ok_or_else(|| Error::internal("pendant vanished"))?;
    let created = match pendants::create_instance(app, &row).await {
        Ok(c) => c,
        Err(e) => {
            let _ = app.store.delete_pendant(id).await;
            return Err(Error::invalid(
                "invalid_config",
                format!(
                    "field `config` rejected by {}: {e}",
                    pendants::TRANSPORT_PLUGIN
                ),
            ));
        }
    };
    pendants::attach(app, row, Ok(created)).await;
    app.bus
        .record_or_log(
            EventKind::PendantCreated,
            req.machine,
            Some(actor),
            json!({"pendant": id, "name": name, "address": req.address, "machine": req.machine}),
        )
        .await;
    Ok(id)
}

/// Moves a pendant to another node (it was carried to another hall): that node opens its link
/// within a heartbeat and this one closes it. The machine binding is kept only if that machine
/// is driven by the new node. Records `pendant.node`, whose data is also the answer:
/// `{"pendant", "from", "node", "machine"}`.
pub async fn set_pendant_node(app: &App, id: i64, node: &str, actor: &str) -> Result<Value> {
    check_node_name(node)?;
    let unknown = || Error::not_found("unknown_pendant", format!("no pendant with id {id}"));
    let before: PendantRow = app.store.pendant(id).await?.ok_or_else(unknown)?;
    app.store.set_pendant_node(id, node).await?;
    let after = app.store.pendant(id).await?.ok_or_else(unknown)?;
    if let Some(p) = app.pendants.get(id).await {
        p.set_machine(app, after.machine_id).await;
    }
    let body =
        json!({"pendant": id, "from": before.node, "node": node, "machine": after.machine_id});
    app.bus
        .record_or_log(
            EventKind::PendantNode,
            before.machine_id,
            Some(actor),
            body.clone(),
        )
        .await;
    Ok(body)
}

/// Changes a live pendant: binds it to `machine` (`Some(None)` unbinds; `pendant.bound`) and
/// sets the given macro keys (`pendant.macro` each). Every macro is checked before anything
/// changes.
pub async fn change_pendant(
    app: &App,
    p: &pendants::Pendant,
    machine: Option<Option<i64>>,
    macros: Option<&BTreeMap<String, Option<Value>>>,
    actor: &str,
) -> Result<()> {
    let id = p.id;
    let macros = match macros {
        Some(m) => parse_macros(m)?,
        None => Vec::new(),
    };
    if let Some(machine) = machine {
        check_pendant_machine(app, machine).await?;
        app.store.set_pendant_machine(id, machine).await?;
        p.set_machine(app, machine).await;
        app.bus
            .record_or_log(
                EventKind::PendantBound,
                machine,
                Some(actor),
                json!({"pendant": id, "machine": machine}),
            )
            .await;
    }
    for (slot, action) in macros {
        app.store
            .set_pendant_macro(id, slot, action.as_ref())
            .await?;
        app.bus
            .record_or_log(
                EventKind::PendantMacro,
                p.row().machine_id,
                Some(actor),
                json!({"pendant": id, "key": format!("M{slot}"), "action": action}),
            )
            .await;
        p.set_macro(slot, action);
    }
    Ok(())
}

/// Removes pendant `id`: its link is closed, its row deleted, `pendant.deleted` recorded.
pub async fn delete_pendant(app: &App, id: i64, actor: &str) -> Result<()> {
    app.pendants.remove(id).await;
    app.store.delete_pendant(id).await?;
    app.bus
        .record_or_log(
            EventKind::PendantDeleted,
            None,
            Some(actor),
            json!({"pendant": id}),
        )
        .await;
    Ok(())
}

/// A pendant's `machine` field: a machine this node drives (a pendant's keys go to its
/// machine's task on this node, so both must be here).
pub async fn check_pendant_machine(app: &App, machine: Option<i64>) -> Result<()> {
    if let Some(id) = machine {
        if !app.machines.is_local(id) {
            if let Some(row) = app.store.machine(id).await? {
                return Err(Error::invalid(
                    "machine_on_other_node",
                    format!(
                        "field `machine`: machine {id} is driven by node {}; a pendant drives \
                         machines of its own node ({})",
                        row.node.as_deref().unwrap_or("?"),
                        app.settings.node.name
                    ),
                ));
            }
            return Err(Error::invalid(
                "unknown_machine",
                format!("field `machine`: no machine with id {id}"),
            ));
        }
    }
    Ok(())
}

/// `{"M1": action|null, ...}` -> slots; names the bad key or action.
pub fn parse_macros(m: &BTreeMap<String, Option<Value>>) -> Result<Vec<(u8, Option<MacroAction>)>> {
    let mut out = Vec::new();
    for (k, v) in m {
        let slot = match k.as_str() {
            "M1" => 1,
            "M2" => 2,
            "M3" => 3,
            "M4" => 4,
            other => {
                return Err(Error::invalid(
                    "invalid_field",
                    format!("field `macros`: {other:?} is not a macro key (M1, M2, M3, M4)"),
                ))
            }
        };
        let action = match v {
            None | Some(Value::Null) => None,
            Some(v) => Some(
                serde_json::from_value::<MacroAction>(v.clone()).map_err(|e| {
                    Error::invalid(
                        "invalid_field",
                        format!("field `macros.{k}`: {e} (types: command, jog, toggle, mdi)"),
                    )
                })?,
            ),
        };
        match &action {
            Some(MacroAction::Jog { distance, .. })
                if !distance.is_finite() || *distance == 0.0 =>
            {
                return Err(Error::invalid(
                    "invalid_field",
                    format!("field `macros.{k}.distance` must be a non-zero number"),
                ));
            }
            Some(MacroAction::Mdi { line }) => {
                limits::check_mdi_line(line).map_err(|e| {
                    Error::invalid("invalid_field", format!("field `macros.{k}.line`: {e}"))
                })?;
            }
            _ => {}
        }
        out.push((slot, action));
    }
    Ok(out)
}

/// Same rule as the transport plugin: `host:port`, or `host` for port 8001; the host must be an
/// IP address or a DNS name (`MPG000001.local`). Anything else gives an empty host.
fn split_address(address: &str) -> (String, u16) {
    let a = address.trim();
    if let Ok(sa) = a.parse::<std::net::SocketAddr>() {
        return (sa.ip().to_string(), sa.port());
    }
    if let Ok(ip) = a.parse::<std::net::IpAddr>() {
        return (ip.to_string(), 8001);
    }
    let (host, port) = match a.rsplit_once(':') {
        Some((h, p)) => (h, p.parse().unwrap_or(0)),
        None => (a, 8001),
    };
    if is_dns_name(host) {
        (host.to_string(), port)
    } else {
        (String::new(), port)
    }
}

/// RFC 1123 host name: dot-separated labels of letters, digits and inner hyphens.
fn is_dns_name(host: &str) -> bool {
    let host = host.strip_suffix('.').unwrap_or(host);
    !host.is_empty()
        && host.len() <= 253
        && host.split('.').all(|label| {
            !label.is_empty()
                && label.len() <= 63
                && !label.starts_with('-')
                && !label.ends_with('-')
                && label
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-')
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pendant_addresses_are_parsed() {
        assert_eq!(
            split_address("192.168.1.40:8001"),
            ("192.168.1.40".into(), 8001)
        );
        assert_eq!(
            split_address("MPG000001.local"),
            ("MPG000001.local".into(), 8001)
        );
        assert_eq!(split_address("[::1]:9000"), ("::1".into(), 9000));
        assert_eq!(split_address("fe80::1"), ("fe80::1".into(), 8001));
        for bad in ["::::", "a b:1", "-x.local", "x..y", "host:", "", "é.local"] {
            let (host, port) = split_address(bad);
            assert!(
                host.is_empty() || port == 0,
                "{bad:?} accepted as {host}:{port}"
            );
        }
    }

    #[test]
    fn macros_name_the_bad_key_or_action() {
        let parse = |v: Value| {
            let m: BTreeMap<String, Option<Value>> = serde_json::from_value(v).unwrap_or_default();
            parse_macros(&m)
        };
        let ok = parse(json!({"M1": {"type": "jog", "axis": "Z", "distance": 5.0}, "M2": null}));
        assert!(ok.is_ok_and(|m| m.len() == 2 && m[1].1.is_none()));
        for (bad, names) in [
            (json!({"M5": null}), "\"M5\""),
            (
                json!({"M1": {"type": "jog", "axis": "Z", "distance": 0.0}}),
                "macros.M1.distance",
            ),
            (
                json!({"M2": {"type": "mdi", "line": " "}}),
                "macros.M2.line",
            ),
            (json!({"M3": {"type": "fly"}}), "macros.M3"),
        ] {
            let e = parse(bad).err().map(|e| (e.code, e.message));
            assert!(
                e.as_ref()
                    .is_some_and(|(c, m)| *c == "invalid_field" && m.contains(names)),
                "{e:?} should name {names}"
            );
        }
    }
}
