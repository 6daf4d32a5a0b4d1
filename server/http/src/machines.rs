use super::auth::Caller;
use super::error::{ApiError, Json, Path};
use axum::extract::State;
use axum::http::StatusCode;
use axum::Extension;
use fresa_core::machine::{limits, Machine};
use fresa_core::SharedApp;
use fresa_plugin_api::contract::{Axis, AxisValues, Command, MachineStatus, WorkOffset};
use serde::Deserialize;
use serde_json::{json, Value};
use std::sync::Arc;

async fn machine(app: &SharedApp, id: i64) -> Result<Arc<Machine>, ApiError> {
    app.machines
        .get(id)
        .await
        .ok_or_else(|| ApiError::not_found("unknown_machine", format!("no machine with id {id}")))
}

fn machine_json(m: &Machine) -> Value {
    let row = m.row();
    let status = m.status();
    json!({"id": row.id, "name": row.name, "backend": row.backend, "config": row.config_json(),
           "max_jog_mm": row.max_jog_mm, "max_feed_mm_min": row.max_feed_mm_min,
           "state": status.state, "reason": status.reason, "created_at": row.created_at})
}

pub async fn list(State(app): State<SharedApp>) -> Json<Vec<Value>> {
    Json(
        app.machines
            .all()
            .await
            .iter()
            .map(|m| machine_json(m))
            .collect(),
    )
}

pub async fn get_one(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    Ok(Json(machine_json(&m)))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewMachine {
    name: String,
    backend: String,
    #[serde(default)]
    config: Option<Value>,
    #[serde(default)]
    max_jog_mm: Option<f64>,
    #[serde(default)]
    max_feed_mm_min: Option<f64>,
}

pub async fn create(
    State(app): State<SharedApp>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<NewMachine>,
) -> Result<(StatusCode, Json<Value>), ApiError> {
    let name = fresa_core::Error::required_name(&req.name)?;
    let mut config = req.config.unwrap_or_else(|| json!({}));
    if !config.is_object() {
        return Err(ApiError::unprocessable(
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
    let Some(lib) = app.plugins.get(&req.backend) else {
        return Err(ApiError::unprocessable(
            "unknown_backend",
            format!(
                "field `backend`: no plugin named {:?} is loaded (loaded: {})",
                req.backend,
                app.plugins.names().join(", ")
            ),
        ));
    };
    if app.store.machine_by_name(name).await?.is_some() {
        return Err(ApiError::conflict(
            "name_taken",
            format!("a machine named {name:?} already exists"),
        ));
    }
    limits::confine_backend_files(&mut config, &app.settings.data_dir)?;
    // The plugin judges the config before anything is stored; that instance is the one kept.
    let backend = Machine::prepare(lib, config.clone()).await.map_err(|e| {
        ApiError::unprocessable(
            "invalid_config",
            format!("field `config` rejected by {}: {e}", req.backend),
        )
    })?;
    let id = app
        .store
        .insert_machine(name, &req.backend, &config, max_jog, max_feed)
        .await
        .map_err(|e| fresa_core::Error::insert_failed(e, "machine", name))?;
    let row = app
        .store
        .machine(id)
        .await?
        .ok_or_else(|| ApiError::internal("machine vanished"))?;
    let m = Machine::start(
        row,
        Ok(backend),
        app.store.clone(),
        app.bus.clone(),
        &app.machine_options(),
    )
    .await;
    app.machines.insert(m).await;
    app.bus
        .record_or_log(
            "machine.created",
            Some(id),
            Some(&caller.name),
            json!({"id": id, "name": name, "backend": req.backend}),
        )
        .await;
    Ok((StatusCode::CREATED, Json(json!({"id": id}))))
}

pub async fn status(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    Ok(Json(status_json(&m, m.status())))
}

fn status_json(m: &Machine, s: MachineStatus) -> Value {
    let mut v = json!(s);
    let job = m.run().map(|r| r.progress_json());
    if let Some(o) = v.as_object_mut() {
        o.insert("machine".into(), json!(m.id));
        o.insert("job".into(), job.unwrap_or(Value::Null));
    }
    v
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JogReq {
    axis: Axis,
    distance: f64,
    #[serde(default)]
    feed: Option<f64>,
}

pub async fn jog(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<JogReq>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    m.jog(req.axis, req.distance, req.feed, &caller.name)
        .await?;
    Ok(Json(json!({"ok": true})))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MdiReq {
    line: String,
}

pub async fn mdi(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<MdiReq>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    m.mdi(&req.line, &caller.name).await?;
    Ok(Json(json!({"ok": true})))
}

pub async fn command(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    Json(raw): Json<Value>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    let cmd: Command = serde_json::from_value(raw.clone())
        .map_err(|e| ApiError::unprocessable("invalid_command", format!("{e} (commands: cycle_start, feed_hold, resume, stop, reset, home, zero, go_to_zero, select_offset, set_output, toggle_output)")))?;
    // Like every other body: a field the command does not have is an error, not ignored (a
    // misspelt `axis` must not zero every axis).
    let known = serde_json::to_value(cmd).unwrap_or_default();
    if let (Some(given), Some(known)) = (raw.as_object(), known.as_object()) {
        if let Some(extra) = given.keys().find(|k| !known.contains_key(*k)) {
            return Err(ApiError::unprocessable(
                "invalid_command",
                format!(
                    "unknown field `{extra}` for command {:?} (its fields: {})",
                    known["command"].as_str().unwrap_or_default(),
                    known.keys().cloned().collect::<Vec<_>>().join(", ")
                ),
            ));
        }
    }
    let answer = m.command(cmd, &caller.name).await?;
    Ok(Json(json!({"ok": true, "result": answer})))
}

pub async fn offsets(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    let offsets = app.store.offsets(id).await?;
    let map: serde_json::Map<String, Value> = offsets
        .iter()
        .map(|(o, v)| (o.name().to_string(), json!(v)))
        .collect();
    Ok(Json(
        json!({"active": m.row().active_offset, "offsets": map}),
    ))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OffsetReq {
    x: Option<f64>,
    y: Option<f64>,
    z: Option<f64>,
    a: Option<f64>,
}

pub async fn set_offset(
    State(app): State<SharedApp>,
    Path((id, name)): Path<(i64, String)>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<OffsetReq>,
) -> Result<Json<Value>, ApiError> {
    let m = machine(&app, id).await?;
    let offset = WorkOffset::parse(&name).ok_or_else(|| {
        ApiError::not_found(
            "unknown_offset",
            format!("{name:?} is not a work offset (G54..G59)"),
        )
    })?;
    let current = app
        .store
        .offsets(id)
        .await?
        .into_iter()
        .find(|(o, _)| *o == offset)
        .map(|(_, v)| v)
        .unwrap_or_default();
    let mut values = current;
    for (axis, v) in [
        (Axis::X, req.x),
        (Axis::Y, req.y),
        (Axis::Z, req.z),
        (Axis::A, req.a),
    ] {
        if let Some(v) = v {
            if !v.is_finite() {
                return Err(ApiError::unprocessable(
                    "invalid_field",
                    format!(
                        "field `{}` must be a finite number",
                        axis.letter().to_ascii_lowercase()
                    ),
                ));
            }
            values.set(axis, v);
        }
    }
    m.set_offset(offset, values, &caller.name).await?;
    Ok(Json(json!({"offset": offset, "values": values})))
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct PartZeroReq {
    /// Machine coordinates of the part zero; the current machine position when absent.
    #[serde(default)]
    position: Option<AxisValues>,
    #[serde(default)]
    source: Option<String>,
    #[serde(default)]
    note: Option<String>,
}

pub async fn record_part_zero(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
    Extension(caller): Extension<Caller>,
    body: axum::body::Bytes,
) -> Result<(StatusCode, Json<Value>), ApiError> {
    let m = machine(&app, id).await?;
    // The body is optional: an empty POST records the current position.
    let req: PartZeroReq = if body.iter().all(u8::is_ascii_whitespace) {
        PartZeroReq::default()
    } else {
        serde_json::from_slice(&body)
            .map_err(|e| ApiError::bad_request("invalid_json", format!("part zero: {e}")))?
    };
    let at = match req.position {
        Some(p) => p,
        None => m.refresh_status().await?.machine_position,
    };
    let source = req.source.unwrap_or_else(|| "api".into());
    let row = app
        .store
        .insert_part_zero(id, at, &source, &caller.name, req.note.as_deref())
        .await?;
    app.bus
        .record_or_log(
            "machine.part_zero",
            Some(id),
            Some(&caller.name),
            json!(row),
        )
        .await;
    Ok((StatusCode::CREATED, Json(json!(row))))
}

pub async fn part_zeros(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<Json<Value>, ApiError> {
    machine(&app, id).await?;
    Ok(Json(json!(app.store.part_zeros(id).await?)))
}

/// `GET /machines/{id}/as-program`: the controller program the backend generates (robot
/// backends), as a download.
pub async fn as_program(
    State(app): State<SharedApp>,
    Path(id): Path<i64>,
) -> Result<axum::response::Response, ApiError> {
    artifact(&app, id, "as-program").await
}

async fn artifact(
    app: &SharedApp,
    id: i64,
    name: &str,
) -> Result<axum::response::Response, ApiError> {
    use axum::response::IntoResponse;
    let m = machine(app, id).await?;
    let backend = m.row().backend;
    let answer = m.artifact(name).await?;
    let body = answer["body"]
        .as_str()
        .ok_or_else(|| {
            ApiError::internal(format!("backend {backend} answered {name} without a body"))
        })?
        .to_string();
    let content_type = answer["content_type"]
        .as_str()
        .unwrap_or("application/octet-stream")
        .to_string();
    let file_name = answer["file_name"]
        .as_str()
        .unwrap_or(name)
        .replace('"', "");
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, content_type),
            (
                axum::http::header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{file_name}\""),
            ),
        ],
        body,
    )
        .into_response())
}
