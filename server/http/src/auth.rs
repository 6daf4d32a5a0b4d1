//! Tokens and roles. On a loopback-only bind no token is needed (the machine's own users are
//! trusted); on any other bind every request needs one. A token given anyway is always checked.

use super::error::ApiError;
use crate::admission::Admission;
use crate::middleware::{Fast, Middleware, Next};
use axum::extract::Request;
use axum::http::{HeaderName, Method, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::MethodRouter;
use fresa_core::store::TokenHash;
use fresa_core::SharedApp;
use futures_util::future::BoxFuture;
use sha2::{Digest, Sha256};
use std::sync::Arc;

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
    /// Shared: the local caller's name is made once, not per request.
    pub name: Arc<str>,
    pub role: Role,
    /// Whether a token (or a node's secret) names this caller, rather than it being a tokenless
    /// local caller: the event stream counts its streams against that name. A field rather
    /// than an extension of its own: each extension past the request's third costs a rehash.
    pub by_token: bool,
}

pub fn new_secret() -> String {
    let bytes: [u8; 24] = rand::random();
    format!("fresa_{}", hex::encode(bytes))
}

/// The token of a request. `?access_token=` is accepted on `GET /api/v1/events` only, because
/// a browser's EventSource cannot send headers; anywhere else a secret in the URL (which ends up
/// in logs, proxies and browser history) is refused.
fn bearer(req: &Request) -> Result<Option<&str>, ApiError> {
    if let Some(v) = req.headers().get(axum::http::header::AUTHORIZATION) {
        return Ok(v.to_str().ok().and_then(bearer_token));
    }
    let Some(token) = query_token(req.uri()) else {
        return Ok(None);
    };
    // Authentication runs before routing (`crate::Gate`): the URI is the client's, unchanged.
    if req.method() == axum::http::Method::GET && req.uri().path() == "/api/v1/events" {
        Ok(Some(token))
    } else {
        Err(ApiError::bad_request(
            "token_in_query",
            "`access_token` in the URL is accepted only on GET /api/v1/events; send `Authorization: Bearer <token>`",
        ))
    }
}

/// The token of an `Authorization: Bearer <token>` value; the scheme is case-insensitive
/// (RFC 9110 11.1), so `bearer` and `BEARER` are the same. Other schemes carry no token.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.trim().split_once(' ')?;
    scheme
        .eq_ignore_ascii_case("bearer")
        .then(|| token.trim_start_matches(' ').trim_end())
}

fn query_token(uri: &axum::http::Uri) -> Option<&str> {
    uri.query()
        .and_then(|q| q.split('&').find_map(|kv| kv.strip_prefix("access_token=")))
}

/// The URI as it may be logged: the value of any `access_token` replaced.
pub fn redacted_uri(uri: &axum::http::Uri) -> String {
    match uri.query() {
        Some(q) if q.contains("access_token=") => {
            let q: Vec<String> = q
                .split('&')
                .map(|kv| {
                    if kv.starts_with("access_token=") {
                        "access_token=REDACTED".to_string()
                    } else {
                        kv.to_string()
                    }
                })
                .collect();
            format!("{}?{}", uri.path(), q.join("&"))
        }
        _ => uri.to_string(),
    }
}

// ---- requests forwarded by another node of the same store (see `forward`) ----

/// The node secret, proving a request comes from a node of the same store. A `HeaderName`,
/// not text: authentication asks for it on every request, and a name given as text is parsed
/// and validated at each lookup.
pub static NODE_TOKEN: HeaderName = HeaderName::from_static("x-fresa-node-token");
/// The forwarding node's name.
pub const FORWARDED_BY: &str = "x-fresa-forwarded-by";
/// The original caller's token name and role, vouched for by the node secret.
pub const CALLER_NAME: &str = "x-fresa-caller";
pub const CALLER_ROLE: &str = "x-fresa-caller-role";
/// On a forwarded answer: the node that carried the request out.
pub const ANSWERED_BY: &str = "x-fresa-node";

/// Set by the auth layer on a request another node forwarded.
#[derive(Debug, Clone)]
pub struct ForwardedBy(pub String);

/// A request another node forwarded: the node secret vouches for the caller it names (that node
/// checked the caller's token). `None`: not a forwarded request.
fn forwarded_caller(app: &SharedApp, req: &Request) -> Option<Result<(Caller, String), ApiError>> {
    let given = req.headers().get(&NODE_TOKEN)?;
    // Compared as digests: the time taken says nothing about the secret.
    let valid = Sha256::digest(given.as_bytes()) == Sha256::digest(app.node_secret.as_bytes());
    let header = |name: &str| {
        req.headers()
            .get(name)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
    };
    let role = header(CALLER_ROLE).as_deref().and_then(Role::parse);
    Some(match (valid, role) {
        (true, Some(role)) => Ok((
            Caller {
                name: header(CALLER_NAME).map_or_else(|| Arc::from("node"), Arc::from),
                role,
                by_token: true,
            },
            header(FORWARDED_BY).unwrap_or_default(),
        )),
        _ => Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "invalid_node_token",
            "forwarded request refused: the node token or the caller role is not valid              (nodes of one store share the secret in its `cluster` table)",
        )),
    })
}

/// Says who is calling before any route runs (see [`Caller`]); a plain [`Middleware`] so the
/// common case (a tokenless caller on a loopback-only server) costs no allocation.
#[derive(Clone)]
pub struct Authenticate {
    app: SharedApp,
    /// Wrong secrets are counted and limited per address (see `admission`).
    admission: Option<Arc<Admission>>,
    /// The caller of a tokenless request where none is needed, made once.
    local: Caller,
}

impl Authenticate {
    pub fn new(app: SharedApp, admission: Option<Arc<Admission>>) -> Authenticate {
        Authenticate {
            app,
            admission,
            local: Caller {
                name: Arc::from("local"),
                role: Role::Admin,
                by_token: false,
            },
        }
    }
}

impl Middleware for Authenticate {
    fn fast(&self, mut req: Request) -> Fast {
        // One pass over the few names a poll carries, where two lookups hashed them (about
        // 230 instructions of a status poll); a request holds at most hyper's 100 headers.
        let token_given = req
            .headers()
            .keys()
            .any(|name| name == axum::http::header::AUTHORIZATION || name == NODE_TOKEN)
            || req
                .uri()
                .query()
                .is_some_and(|q| q.contains("access_token="));
        if token_given {
            return match self.recently_accepted(&req) {
                Some(caller) => {
                    req.extensions_mut().insert(caller);
                    Fast::Pass(req)
                }
                None => Fast::Slow(req),
            };
        }
        if self.app.auth_required {
            return Fast::Slow(req);
        }
        req.extensions_mut().insert(self.local.clone());
        Fast::Pass(req)
    }

    fn slow(self, req: Request, next: impl Next) -> BoxFuture<'static, Response> {
        Box::pin(async move {
            match self.check(req).await {
                Ok(req) => next.run(req).await,
                Err(refused) => refused,
            }
        })
    }
}

/// How long a read may go on trusting the database's "this token is valid": a status poll with a
/// token would otherwise wait for a database round trip on every request (11,300 status reads a
/// second instead of 65,000; README: Measurements). Anything that changes state always asks the
/// database, so a revoked token is refused at once there, and on reads at most this much later.
pub const READ_TOKEN_RECHECK_MS: i64 = 1_000;

impl Authenticate {
    /// The caller of a read (GET, HEAD) whose token the database accepted within
    /// [`READ_TOKEN_RECHECK_MS`]; `None` sends the request to [`Self::check`], which asks the
    /// database (and refuses a rate-limited address, a node's request or a bad token).
    fn recently_accepted(&self, req: &Request) -> Option<Caller> {
        if !matches!(*req.method(), Method::GET | Method::HEAD)
            || req.headers().contains_key(&NODE_TOKEN)
        {
            return None;
        }
        if let Some(a) = &self.admission {
            if !a.no_failed_tokens(crate::admission::peer(req)) {
                return None;
            }
        }
        let hash = TokenHash::of(bearer(req).ok()??);
        let token = self
            .app
            .store
            .token_accepted_within(hash.as_str(), READ_TOKEN_RECHECK_MS)?;
        Some(caller_of(token))
    }

    /// The request with its [`Caller`] (and [`ForwardedBy`]) set, or the refusal.
    async fn check(&self, mut req: Request) -> Result<Request, Response> {
        let app = &self.app;
        let peer = crate::admission::peer(&req);
        let may_check = || match &self.admission {
            Some(a) => a.may_check_token(peer),
            None => Ok(()),
        };
        let failed = |e: ApiError| {
            if let Some(a) = &self.admission {
                a.token_failed(peer, e.code);
            }
            e.into_response()
        };
        if req.headers().contains_key(&NODE_TOKEN) {
            may_check().map_err(IntoResponse::into_response)?;
        }
        if let Some(forwarded) = forwarded_caller(app, &req) {
            let (caller, node) = forwarded.map_err(failed)?;
            req.extensions_mut().insert(caller);
            req.extensions_mut().insert(ForwardedBy(node));
            return Ok(req);
        }
        let hash = bearer(&req)
            .map_err(IntoResponse::into_response)?
            .map(TokenHash::of);
        let caller = match hash {
            Some(hash) => {
                may_check().map_err(IntoResponse::into_response)?;
                let found = app
                    .store
                    .token_by_hash(hash.as_str())
                    .await
                    .map_err(|e| ApiError::from(e).into_response())?;
                match found {
                    Some(t) => caller_of(t),
                    None => {
                        return Err(failed(ApiError::new(
                            StatusCode::UNAUTHORIZED,
                            "invalid_token",
                            "the API token is not valid",
                        )))
                    }
                }
            }
            None if app.auth_required => return Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "token_required",
                "this server is reachable from the network: send `Authorization: Bearer <token>` \
                     (create one with `fresa token create`)",
            )
            .into_response()),
            None => self.local.clone(),
        };
        req.extensions_mut().insert(caller);
        Ok(req)
    }
}

fn caller_of(token: fresa_core::store::TokenRow) -> Caller {
    Caller {
        name: token.name,
        role: Role::parse(&token.role).unwrap_or(Role::Viewer),
        by_token: true,
    }
}

/// A route's handler that needs at least `role`; the role is declared where the route is
/// (see `router`), and checked after [`middleware`] has said who is calling. A plain tower layer
/// rather than `from_fn`: it runs on every request, so it boxes nothing.
pub fn needs(role: Role, handler: MethodRouter<SharedApp>) -> MethodRouter<SharedApp> {
    if role == Role::Viewer {
        // Every caller the auth middleware lets through is at least a viewer: a check would
        // only cost the hottest routes (status polls) a boxed layer per request.
        return handler;
    }
    handler.route_layer(RequireRole(role))
}

#[derive(Clone, Copy)]
pub struct RequireRole(Role);

impl<S> tower::Layer<S> for RequireRole {
    type Service = RoleCheck<S>;
    fn layer(&self, inner: S) -> RoleCheck<S> {
        RoleCheck {
            role: self.0,
            inner,
        }
    }
}

#[derive(Clone)]
pub struct RoleCheck<S> {
    role: Role,
    inner: S,
}

impl<S> tower::Service<Request> for RoleCheck<S>
where
    S: tower::Service<Request, Response = Response>,
{
    type Response = Response;
    type Error = S::Error;
    type Future =
        futures_util::future::Either<S::Future, std::future::Ready<Result<Response, S::Error>>>;

    fn poll_ready(
        &mut self,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: Request) -> Self::Future {
        use axum::response::IntoResponse;
        use futures_util::future::Either;
        let refusal = match req.extensions().get::<Caller>() {
            Some(c) if c.role >= self.role => None,
            Some(c) => Some(ApiError::new(
                StatusCode::FORBIDDEN,
                "forbidden",
                format!(
                    "token {:?} has role {}; this request needs {}",
                    c.name,
                    c.role.name(),
                    self.role.name()
                ),
            )),
            None => Some(ApiError::internal(
                "route has no caller: auth layer missing",
            )),
        };
        match refusal {
            None => Either::Left(self.inner.call(req)),
            Some(e) => Either::Right(std::future::ready(Ok(e.into_response()))),
        }
    }
}
