use super::auth::Caller;
use super::error::{ApiError, Json, Path};
use crate::machines::Created;
use crate::openapi::ErrorBody;
use axum::extract::State;
use axum::http::StatusCode;
use axum::Extension;
use fresa_core::events::EventKind;
use fresa_core::pendants as core;
use fresa_core::store::MacroAction;
use fresa_core::SharedApp;
use serde::Deserialize;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use utoipa::ToSchema;

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewPendant {
    name: String,
    /// `host:port` (default port 8001), an IP or DNS name.
    address: String,
    /// The machine to bind it to.
    #[serde(default)]
    machine: Option<i64>,
    /// `firmware` (default) or `document`.
    #[serde(default)]
    dialect: Option<String>,
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    config: Option<Value>,
    /// `M1`..`M4` to an action (`{"type": "command"|"jog"|"toggle"|"mdi", ...}`) or null.
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    macros: Option<BTreeMap<String, Option<Value>>>,
}

/// A pendant and its link.
#[derive(ToSchema)]
#[allow(dead_code)] // describes `fresa_core::pendants::pendant_json`
pub struct Pendant {
    id: i64,
    name: String,
    address: String,
    dialect: String,
    machine: Option<i64>,
    connected: bool,
    #[schema(value_type = Object)]
    config: Value,
    /// `M1`..`M4` to their action (or null).
    #[schema(value_type = Object)]
    macros: Value,
    /// False when the transport plugin is not loaded; `reason` says why.
    available: bool,
    reason: Option<String>,
    created_at: i64,
}

/// `{"M1": action|null, ...}` -> slots; names the bad key or action.
fn parse_macros(
    m: &BTreeMap<String, Option<Value>>,
) -> Result<Vec<(u8, Option<MacroAction>)>, ApiError> {
    let mut out = Vec::new();
    for (k, v) in m {
        let slot = match k.as_str() {
            "M1" => 1,
            "M2" => 2,
            "M3" => 3,
            "M4" => 4,
            other => {
                return Err(ApiError::unprocessable(
                    "invalid_field",
                    format!("field `macros`: {other:?} is not a macro key (M1, M2, M3, M4)"),
                ))
            }
        };
        let action = match v {
            None | Some(Value::Null) => None,
            Some(v) => Some(
                serde_json::from_value::<MacroAction>(v.clone()).map_err(|e| {
                    ApiError::unprocessable(
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
                return Err(ApiError::unprocessable(
                    "invalid_field",
                    format!("field `macros.{k}.distance` must be a non-zero number"),
                ));
            }
            Some(MacroAction::Mdi { line }) => {
                fresa_core::machine::limits::check_mdi_line(line).map_err(|e| {
                    ApiError::unprocessable(
                        "invalid_field",
                        format!("field `macros.{k}.line`: {e}"),
                    )
                })?;
            }
            _ => {}
        }
        out.push((slot, action));
    }
    Ok(out)
}

async fn check_machine(app: &SharedApp, machine: Option<i64>) -> Result<(), ApiError> {
    if let Some(id) = machine {
        if app.machines.get(id).await.is_none() {
            // A pendant's keys go to its machine's task on this node: both must be here.
            if let Some(row) = app.store.machine(id).await? {
                return Err(ApiError::unprocessable(
                    "machine_on_other_node",
                    format!(
                        "field `machine`: machine {id} is driven by node {}; a pendant drives \
                         machines of its own node ({})",
                        row.node.as_deref().unwrap_or("?"),
                        app.settings.node.name
                    ),
                ));
            }
            return Err(ApiError::unprocessable(
                "unknown_machine",
                format!("field `machine`: no machine with id {id}"),
            ));
        }
    }
    Ok(())
}

#[utoipa::path(post, path = "/pendants", tag = "pendants",
    request_body(content = NewPendant, example = json!({"name": "bench-1", "address": "127.0.0.1:8001", "dialect": "firmware"})),
    responses(
        (status = 201, description = "Created; the server connects to it", body = Created),
        (status = 409, description = "`name_taken`", body = ErrorBody),
        (status = 422, description = "`invalid_field`, `invalid_name`, `unknown_machine`, `machine_on_other_node`", body = ErrorBody),
    ))]
pub async fn create(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<NewPendant>,
) -> Result<(StatusCode, Json<Created>), ApiError> {
    let name = fresa_core::Error::required_name(&req.name)?;
    let (host, port) = split_address(&req.address);
    if host.is_empty() || port == 0 {
        return Err(ApiError::unprocessable(
            "invalid_field",
            format!("field `address`: {:?} is not host:port (e.g. 192.168.1.40:8001 or MPG000001.local)", req.address),
        ));
    }
    let dialect = req.dialect.unwrap_or_else(|| "firmware".into());
    if !matches!(dialect.as_str(), "firmware" | "document") {
        return Err(ApiError::unprocessable(
            "invalid_field",
            format!("field `dialect`: {dialect:?} is not firmware or document"),
        ));
    }
    let config = req.config.unwrap_or_else(|| json!({}));
    if !config.is_object() {
        return Err(ApiError::unprocessable(
            "invalid_field",
            "field `config` must be a JSON object",
        ));
    }
    if let Some(v) = config.get("stop_program_on_lost") {
        if !v.is_boolean() {
            return Err(ApiError::unprocessable(
                "invalid_field",
                "field `config.stop_program_on_lost` must be true or false",
            ));
        }
    }
    check_machine(&app, req.machine).await?;
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
        .map_err(|e| fresa_core::Error::insert_failed(e, "pendant", name))?;
    let row = app
        .store
        .pendant(id)
        .await?
        .ok_or_else(|| ApiError::internal("pendant vanished"))?;
    // The transport judges its config before the pendant is kept; that instance is the one used.
    let created = match core::create_instance(&app, &row).await {
        Ok(c) => c,
        Err(e) => {
            let _ = app.store.delete_pendant(id).await;
            return Err(ApiError::unprocessable(
                "invalid_config",
                format!("field `config` rejected by {}: {e}", core::TRANSPORT_PLUGIN),
            ));
        }
    };
    core::attach(&app, row, Ok(created)).await;
    app.bus
        .record_or_log(
            EventKind::PendantCreated,
            req.machine,
            Some(&caller.name),
            json!({"pendant": id, "name": name, "address": req.address, "machine": req.machine}),
        )
        .await;
    Ok((StatusCode::CREATED, Json(Created { id })))
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
    use super::split_address;

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
}

#[utoipa::path(get, path = "/pendants", tag = "pendants",
    responses((status = 200, description = "Every pendant", body = [Pendant])))]
pub async fn list(State(app): State<SharedApp>) -> Json<Vec<Value>> {
    Json(
        app.pendants
            .all()
            .await
            .iter()
            .map(|p| core::pendant_json(p))
            .collect(),
    )
}

async fn pendant(app: &SharedApp, id: i64) -> Result<std::sync::Arc<core::Pendant>, ApiError> {
    app.pendants
        .get(id)
        .await
        .ok_or_else(|| ApiError::not_found("unknown_pendant", format!("no pendant with id {id}")))
}

#[utoipa::path(get, path = "/pendants/{id}", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    responses(
        (status = 200, description = "The pendant", body = Pendant),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
    ))]
pub async fn get_one(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    let p = pendant(&app, id).await?;
    Ok(Json(core::pendant_json(&p)))
}

/// `null` and absent differ for `machine`: absent keeps the binding, `null` unbinds.
fn double_option<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Option<i64>>, D::Error> {
    Option::<i64>::deserialize(d).map(Some)
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PatchPendant {
    /// Bind to this machine; `null` unbinds; absent keeps the binding.
    #[serde(default, deserialize_with = "double_option")]
    #[schema(value_type = Option<i64>)]
    machine: Option<Option<i64>>,
    /// `M1`..`M4` to an action or null (see `NewPendant.macros`).
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    macros: Option<BTreeMap<String, Option<Value>>>,
}

#[utoipa::path(patch, path = "/pendants/{id}", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    request_body(content = PatchPendant, example = json!({"machine": null})),
    responses(
        (status = 200, description = "The pendant as now bound", body = Pendant),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
        (status = 422, description = "`invalid_field`, `unknown_machine`, `machine_on_other_node`", body = ErrorBody),
    ))]
pub async fn patch(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<PatchPendant>,
) -> Result<Json<Value>, ApiError> {
    let p = pendant(&app, id).await?;
    let macros = match &req.macros {
        Some(m) => parse_macros(m)?,
        None => Vec::new(),
    };
    if let Some(machine) = req.machine {
        check_machine(&app, machine).await?;
        app.store.set_pendant_machine(id, machine).await?;
        p.set_machine(machine);
        app.bus
            .record_or_log(
                EventKind::PendantBound,
                machine,
                Some(&caller.name),
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
                Some(&caller.name),
                json!({"pendant": id, "key": format!("M{slot}"), "action": action}),
            )
            .await;
        p.set_macro(slot, action);
    }
    Ok(Json(core::pendant_json(&p)))
}

#[utoipa::path(delete, path = "/pendants/{id}", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    responses(
        (status = 204, description = "Removed; its link is closed"),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
    ))]
pub async fn delete(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
) -> Result<StatusCode, ApiError> {
    pendant(&app, id).await?;
    app.pendants.remove(id).await;
    app.store.delete_pendant(id).await?;
    app.bus
        .record_or_log(
            EventKind::PendantDeleted,
            None,
            Some(&caller.name),
            json!({"pendant": id}),
        )
        .await;
    Ok(StatusCode::NO_CONTENT)
}

#[utoipa::path(get, path = "/pendants/discovered", tag = "pendants",
    responses((status = 200, description = "Pendants announced on the LAN by mDNS (`MPGnnnnnn`, `_http._tcp`)", body = Object)))]
pub async fn discovered(State(app): State<SharedApp>) -> Result<Json<Value>, ApiError> {
    Ok(Json(core::discovered(&app).await?))
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PendantNodeReq {
    /// The node whose network the pendant is on now (its `node_name`).
    node: String,
}

/// Moves a pendant to another node (it was carried to another hall): that node opens its link
/// within a heartbeat and this one closes it. The machine binding is kept only if that machine
/// is driven by the new node.
#[utoipa::path(put, path = "/pendants/{id}/node", tag = "pendants",
    params(("id" = i64, Path, description = "pendant id", example = 1)),
    request_body(content = PendantNodeReq, example = json!({"node": "hall-2"})),
    responses(
        (status = 200, description = "Moved: `{\"pendant\", \"node\", \"machine\"}`", body = Object),
        (status = 404, description = "`unknown_pendant`", body = ErrorBody),
        (status = 422, description = "`invalid_field`", body = ErrorBody),
    ))]
pub async fn set_node(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<PendantNodeReq>,
) -> Result<Json<Value>, ApiError> {
    crate::machines::check_node_name(&req.node)?;
    let before = app.store.pendant(id).await?.ok_or_else(|| {
        ApiError::not_found("unknown_pendant", format!("no pendant with id {id}"))
    })?;
    app.store.set_pendant_node(id, &req.node).await?;
    let after = app.store.pendant(id).await?.ok_or_else(|| {
        ApiError::not_found("unknown_pendant", format!("no pendant with id {id}"))
    })?;
    if let Some(p) = app.pendants.get(id).await {
        p.set_machine(after.machine_id);
    }
    let body =
        json!({"pendant": id, "from": before.node, "node": req.node, "machine": after.machine_id});
    app.bus
        .record_or_log(
            EventKind::PendantNode,
            before.machine_id,
            Some(&caller.name),
            body.clone(),
        )
        .await;
    Ok(Json(body))
}
