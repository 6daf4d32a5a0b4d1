//! Tokens and roles. On a loopback-only bind no token is needed (the machine's own users are
//! trusted); on any other bind every request needs one. A token given anyway is always checked.

use super::error::ApiError;
use axum::extract::{Request, State};
use axum::http::{Method, StatusCode};
use axum::middleware::Next;
use axum::response::Response;
use fresa_core::SharedApp;
use sha2::{Digest, Sha256};

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Role {
    Viewer,
    Operator,
    Admin,
}

impl Role {
    pub fn name(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }

    pub fn parse(s: &str) -> Option<Role> {
        match s {
            "viewer" => Some(Role::Viewer),
            "operator" => Some(Role::Operator),
            "admin" => Some(Role::Admin),
            _ => None,
        }
    }
}

/// Who is calling: stored in request extensions for handlers (audit) to read.
#[derive(Debug, Clone)]
pub struct Caller {
    pub name: String,
    pub role: Role,
}

pub fn hash_token(secret: &str) -> String {
    hex::encode(Sha256::digest(secret.as_bytes()))
}

pub fn new_secret() -> String {
    let bytes: [u8; 24] = rand::random();
    format!("fresa_{}", hex::encode(bytes))
}

/// The role a request needs: reading is for viewers, moving machines and jobs for operators,
/// configuring machines and plugins for admins.
fn required_role(method: &Method, path: &str) -> Role {
    if method == Method::GET || method == Method::HEAD {
        return Role::Viewer;
    }
    if path == "/api/v1/machines" || path.starts_with("/api/v1/pendants") && method != Method::PATCH
    {
        return Role::Admin;
    }
    Role::Operator
}

fn bearer(req: &Request) -> Option<String> {
    if let Some(v) = req.headers().get(axum::http::header::AUTHORIZATION) {
        return v
            .to_str()
            .ok()
            .and_then(|s| s.strip_prefix("Bearer "))
            .map(|s| s.trim().to_string());
    }
    // EventSource cannot set headers, so SSE clients may pass ?access_token=.
    req.uri().query().and_then(|q| {
        q.split('&')
            .find_map(|kv| kv.strip_prefix("access_token=").map(str::to_string))
    })
}

pub async fn middleware(
    State(app): State<SharedApp>,
    mut req: Request,
    next: Next,
) -> Result<Response, ApiError> {
    let caller =
        match bearer(&req) {
            Some(secret) => match app.store.token_by_hash(&hash_token(&secret)).await? {
                Some(t) => Caller {
                    name: t.name,
                    role: Role::parse(&t.role).unwrap_or(Role::Viewer),
                },
                None => {
                    return Err(ApiError::new(
                        StatusCode::UNAUTHORIZED,
                        "invalid_token",
                        "the API token is not valid",
                    ))
                }
            },
            None if app.auth_required => return Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "token_required",
                "this server is reachable from the network: send `Authorization: Bearer <token>` \
                 (create one with `fresa token create`)",
            )),
            None => Caller {
                name: "local".into(),
                role: Role::Admin,
            },
        };
    // This middleware runs inside `nest("/api/v1", ..)`, which strips the prefix from the URI:
    // judge the full path, as `required_role` expects.
    let path = req
        .extensions()
        .get::<axum::extract::OriginalUri>()
        .map(|u| u.path().to_string())
        .unwrap_or_else(|| req.uri().path().to_string());
    let need = required_role(req.method(), &path);
    if caller.role < need {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "forbidden",
            format!(
                "token {:?} has role {}; this request needs {}",
                caller.name,
                caller.role.name(),
                need.name()
            ),
        ));
    }
    req.extensions_mut().insert(caller);
    Ok(next.run(req).await)
}
