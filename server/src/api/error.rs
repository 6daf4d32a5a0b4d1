//! JSON errors: `{"code": "...", "message": "..."}` with a stable code and a message that names
//! the offending field, value or G-code line.

use crate::machines::BackendError;
use axum::extract::rejection::{JsonRejection, PathRejection, QueryRejection};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use fresa_plugin_api::host::CallError;

#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub code: &'static str,
    pub message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> Self {
        ApiError {
            status,
            code,
            message: message.into(),
        }
    }
    pub fn bad_request(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, code, m)
    }
    pub fn unprocessable(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, code, m)
    }
    pub fn not_found(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, code, m)
    }
    pub fn conflict(code: &'static str, m: impl Into<String>) -> Self {
        Self::new(StatusCode::CONFLICT, code, m)
    }
    pub fn internal(m: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", m)
    }

    /// Maps a backend failure: the plugin's own rejection is the client's problem (422), a
    /// missing or hung backend is the server's (503/504).
    pub fn from_backend(e: BackendError) -> Self {
        match e {
            BackendError::Unavailable(m) => {
                Self::new(StatusCode::SERVICE_UNAVAILABLE, "machine_offline", m)
            }
            BackendError::Timeout(d) => Self::new(
                StatusCode::GATEWAY_TIMEOUT,
                "backend_timeout",
                format!("machine backend did not answer within {d:?}"),
            ),
            // The controller's part zero moved since the run started: the operator must decide.
            BackendError::Call(CallError::Plugin(p)) if p.code == "part_zero_changed" => {
                Self::new(StatusCode::CONFLICT, "part_zero_changed", p.message)
            }
            BackendError::Call(CallError::Plugin(p)) => {
                let status = if p.code == "busy" {
                    StatusCode::CONFLICT
                } else {
                    StatusCode::UNPROCESSABLE_ENTITY
                };
                ApiError {
                    status,
                    code: "backend_rejected",
                    message: format!("{}: {}", p.code, p.message),
                }
            }
            BackendError::Call(other) => {
                Self::new(StatusCode::BAD_GATEWAY, "backend_error", other.to_string())
            }
        }
    }
}

impl From<sqlx::Error> for ApiError {
    fn from(e: sqlx::Error) -> Self {
        tracing::error!(error = %e, "database error");
        ApiError::internal(format!("database error: {e}"))
    }
}

impl ApiError {
    /// The `name` field of something being created, trimmed; empty is refused naming the field.
    pub fn required_name(name: &str) -> Result<&str, ApiError> {
        let name = name.trim();
        if name.is_empty() {
            return Err(ApiError::unprocessable(
                "invalid_field",
                "field `name` must not be empty",
            ));
        }
        Ok(name)
    }

    /// A failed insert of a named thing: a clash with an existing name is the caller's 409
    /// `name_taken`; anything else is a database error.
    pub fn insert_failed(e: sqlx::Error, what: &str, name: &str) -> ApiError {
        match e {
            sqlx::Error::Database(d) if d.is_unique_violation() => ApiError::conflict(
                "name_taken",
                format!("a {what} named {name:?} already exists"),
            ),
            other => other.into(),
        }
    }
}

impl From<JsonRejection> for ApiError {
    fn from(r: JsonRejection) -> Self {
        let status = match &r {
            JsonRejection::MissingJsonContentType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            _ => StatusCode::BAD_REQUEST,
        };
        ApiError::new(status, "invalid_json", r.body_text())
    }
}

impl From<PathRejection> for ApiError {
    fn from(r: PathRejection) -> Self {
        ApiError::bad_request("invalid_path", r.body_text())
    }
}

impl From<QueryRejection> for ApiError {
    fn from(r: QueryRejection) -> Self {
        ApiError::bad_request("invalid_query", r.body_text())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::json!({"code": self.code, "message": self.message});
        (self.status, axum::Json(body)).into_response()
    }
}

/// `Json` that reports malformed bodies as our JSON errors.
#[derive(axum::extract::FromRequest)]
#[from_request(via(axum::Json), rejection(ApiError))]
pub struct Json<T>(pub T);

impl<T: serde::Serialize> IntoResponse for Json<T> {
    fn into_response(self) -> Response {
        axum::Json(self.0).into_response()
    }
}

#[derive(axum::extract::FromRequestParts)]
#[from_request(via(axum::extract::Path), rejection(ApiError))]
pub struct Path<T>(pub T);

#[derive(axum::extract::FromRequestParts)]
#[from_request(via(axum::extract::Query), rejection(ApiError))]
pub struct Query<T>(pub T);
