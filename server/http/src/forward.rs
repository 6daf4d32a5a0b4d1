//! Requests for a machine another node drives go to that node: its task, backend and hardware
//! are there. This layer runs after authentication; it forwards the request (streaming both
//! ways) with the node secret and the caller's name and role, and answers with the owner's
//! answer, so a client sees no difference. The owner checks the role again and writes the audit
//! log under the caller's name. A forwarded request is never forwarded again.
//!
//! Served here from the shared store instead: lists, `GET /machines/{id}` (status as of the
//! owner's last heartbeat), jobs and uploads (programs are in the store), `PUT
//! /machines/{id}/node`, and a remote machine's status while its node is unreachable (offline,
//! with the reason).

use crate::auth::{
    Caller, ForwardedBy, ANSWERED_BY, CALLER_NAME, CALLER_ROLE, FORWARDED_BY, NODE_TOKEN,
};
use crate::error::ApiError;
use crate::middleware::{Fast, Middleware, Next};
use axum::body::Body;
use axum::extract::Request;
use axum::http::{HeaderMap, HeaderName, Method, StatusCode};
use axum::response::{IntoResponse, Response};
use fresa_core::nodes::{Owner, RemoteNode};
use fresa_core::SharedApp;
use futures_util::future::BoxFuture;
use std::time::Duration;

#[derive(Clone)]
pub struct ForwardState {
    pub app: SharedApp,
    client: reqwest::Client,
}

impl ForwardState {
    pub fn new(app: SharedApp) -> ForwardState {
        let client = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(3))
            // Longer than any call into a backend (their own timeout answers first).
            .timeout(app.settings.plugin_call_timeout + Duration::from_secs(30))
            .redirect(reqwest::redirect::Policy::none())
            .build()
            .unwrap_or_default();
        ForwardState { app, client }
    }
}

/// What a request acts on through a machine's task, read from its path in place (no
/// allocation): every request under `/api/v1` passes here.
#[derive(Debug, PartialEq)]
enum Target {
    /// Not a machine's business (lists, jobs' reads, the store's own changes).
    None,
    Machine(i64),
    /// A job's control or start preview: the job's machine, looked up.
    Job(i64),
}

fn target(method: &Method, path: &str) -> Target {
    let path = path
        .strip_prefix("/api/v1")
        .unwrap_or(path)
        .trim_matches('/');
    // `first/id/sub[/more]`.
    let Some((first, rest)) = at_slash(path) else {
        return Target::None;
    };
    let Some((id, rest)) = at_slash(rest) else {
        return Target::None;
    };
    let (sub, more) = match at_slash(rest) {
        Some((sub, _)) => (sub, true),
        None => (rest, false),
    };
    let id = || id.parse().ok();
    match first {
        // `node` is the store's business: any node moves a machine.
        "machines" if sub != "node" => id().map_or(Target::None, Target::Machine),
        // A start preview plans from where the machine stands: its node knows.
        "jobs"
            if !more
                && ((method == Method::POST && sub != "toolpath")
                    || (method == Method::GET && sub == "start-preview")) =>
        {
            id().map_or(Target::None, Target::Job)
        }
        _ => Target::None,
    }
}

/// `s` cut at its first `/`: a plain byte loop, which on segments of a few bytes costs a third
/// of `split_once('/')`'s searcher (every status poll comes through here).
fn at_slash(s: &str) -> Option<(&str, &str)> {
    let i = s.bytes().position(|b| b == b'/')?;
    // `/` is ASCII, so both sides are whole characters.
    Some((s.get(..i)?, s.get(i + 1..)?))
}

impl Middleware for ForwardState {
    /// Not forwarded: a request another node forwarded, one no machine's task serves, and the
    /// common case, a machine this node drives (answered from memory).
    fn fast(&self, req: Request) -> Fast {
        if req.extensions().get::<ForwardedBy>().is_some() {
            return Fast::Pass(req);
        }
        match target(req.method(), req.uri().path()) {
            Target::None => Fast::Pass(req),
            Target::Machine(m) if self.app.machines.is_local(m) => Fast::Pass(req),
            Target::Machine(_) | Target::Job(_) => Fast::Slow(req),
        }
    }

    fn slow(self, req: Request, next: impl Next) -> BoxFuture<'static, Response> {
        Box::pin(self.slow_path(req, next))
    }
}

impl ForwardState {
    /// A job's machine looked up, a remote machine's owner asked, the request forwarded.
    async fn slow_path(self, req: Request, next: impl Next) -> Response {
        let machine = match target(req.method(), req.uri().path()) {
            Target::Machine(m) => m,
            // Guarded, with the running job known from memory: during a database outage a
            // pause or cancel must not wait for the pool's timeout here.
            Target::Job(job) => match fresa_core::jobs::job(&self.app, job).await {
                Ok(j) => j.machine_id,
                Err(_) => return next.run(req).await,
            },
            Target::None => return next.run(req).await,
        };
        if self.app.machines.is_local(machine) {
            return next.run(req).await;
        }
        let path = req.uri().clone();
        let node = match self.app.machine_owner(machine).await {
            Ok(Owner::Remote(node)) => node,
            Ok(Owner::Local | Owner::Unknown) => return next.run(req).await,
            Err(e) => return ApiError::from(e).into_response(),
        };
        if let Some(reason) = &node.down {
            // A status read still answers: the machine is offline, and why.
            if req.method() == Method::GET && path.path().ends_with("/status") {
                return next.run(req).await;
            }
            return unreachable(machine, reason).into_response();
        }
        forward(
            &self,
            machine,
            &node,
            req,
            path.path_and_query().map(|p| p.as_str()),
        )
        .await
        .unwrap_or_else(IntoResponse::into_response)
    }
}

fn unreachable(machine: i64, why: &str) -> ApiError {
    ApiError::new(
        StatusCode::SERVICE_UNAVAILABLE,
        "node_unreachable",
        format!("machine {machine}: {why}; nothing was sent to it"),
    )
}

/// Headers that belong to one connection, or that this node has already checked (the owner
/// must not judge the browser's origin against its own settings, nor see the client's token).
fn skipped(name: &HeaderName) -> bool {
    matches!(
        name.as_str(),
        "connection"
            | "keep-alive"
            | "proxy-connection"
            | "transfer-encoding"
            | "te"
            | "trailer"
            | "upgrade"
            | "host"
            | "content-length"
            | "authorization"
            | "cookie"
            | "origin"
            | "referer"
            | "sec-fetch-site"
            | "sec-fetch-mode"
            | "sec-fetch-dest"
    ) || name.as_str().starts_with("x-fresa-")
}

async fn forward(
    st: &ForwardState,
    machine: i64,
    node: &RemoteNode,
    req: Request,
    path_and_query: Option<&str>,
) -> Result<Response, ApiError> {
    let base = node.url.as_deref().unwrap_or_default();
    let url = format!("{base}{}", path_and_query.unwrap_or("/"));
    let caller = req
        .extensions()
        .get::<Caller>()
        .cloned()
        .ok_or_else(|| ApiError::internal("forwarding without a caller: auth layer missing"))?;
    let (parts, body) = req.into_parts();
    let mut headers = HeaderMap::new();
    for (k, v) in &parts.headers {
        if !skipped(k) {
            headers.append(k.clone(), v.clone());
        }
    }
    let mut rb = st
        .client
        .request(parts.method.clone(), &url)
        .headers(headers)
        .header(NODE_TOKEN.clone(), &st.app.node_secret)
        .header(FORWARDED_BY, &st.app.settings.node.name)
        .header(CALLER_ROLE, caller.role.name());
    // A token name is ASCII-safe by construction, but never fail a request over a header.
    if let Ok(v) = axum::http::HeaderValue::from_str(&caller.name) {
        rb = rb.header(CALLER_NAME, v);
    }
    let rb = rb.body(reqwest::Body::wrap_stream(body.into_data_stream()));
    let answer = rb.send().await.map_err(|e| {
        tracing::warn!(machine, node = %node.name, url = %url, error = %e, "forwarding failed");
        if e.is_connect() {
            return unreachable(
                machine,
                &format!("node {} at {base} could not be reached ({e})", node.name),
            );
        }
        // The request may have arrived: saying "nothing was sent" could make someone repeat a
        // motion that was carried out.
        ApiError::new(
            StatusCode::GATEWAY_TIMEOUT,
            "node_no_answer",
            format!(
                "machine {machine}: node {} at {base} took the request but its answer did not \
                 arrive ({e}); it may have been carried out: check \
                 GET /api/v1/machines/{machine}/status before repeating it",
                node.name
            ),
        )
    })?;
    let mut out = Response::builder().status(answer.status().as_u16());
    for (k, v) in answer.headers() {
        if !skipped(k) {
            out = out.header(k, v);
        }
    }
    out.header(ANSWERED_BY, &node.name)
        .body(Body::from_stream(answer.bytes_stream()))
        .map_err(|e| ApiError::internal(format!("cannot pass on node {}'s answer: {e}", node.name)))
}

/// Asks the node that drives `machine` to start a part of `job` there if it is free (`POST
/// /machines/{id}/queue/take`, as a forwarded request under the caller's name and role): for
/// a dispatch over machines of several nodes. The refusal: its code and message.
pub(crate) async fn take_remote(
    app: &SharedApp,
    machine: i64,
    node: &RemoteNode,
    job: i64,
    caller: &Caller,
) -> Result<fresa_core::queue::Started, (String, String)> {
    if let Some(reason) = &node.down {
        let e = unreachable(machine, reason);
        return Err((e.code.to_string(), e.message));
    }
    let path = format!("/api/v1/machines/{machine}/queue/take");
    let body = serde_json::json!({"job": job}).to_string();
    let mut req = Request::new(Body::from(body));
    *req.method_mut() = Method::POST;
    req.headers_mut().insert(
        axum::http::header::CONTENT_TYPE,
        axum::http::HeaderValue::from_static("application/json"),
    );
    req.extensions_mut().insert(caller.clone());
    let st = ForwardState::new(app.clone());
    let answer = forward(&st, machine, node, req, Some(&path))
        .await
        .map_err(|e| (e.code.to_string(), e.message))?;
    let status = answer.status();
    let bytes = axum::body::to_bytes(answer.into_body(), 1 << 20)
        .await
        .map_err(|e| {
            (
                "node_no_answer".to_string(),
                format!("node {}'s answer could not be read: {e}", node.name),
            )
        })?;
    let value: serde_json::Value = serde_json::from_slice(&bytes).unwrap_or_default();
    if status.is_success() {
        let field = |k: &str| value[k].as_i64();
        return match (field("job"), field("run")) {
            (Some(job), Some(run)) => Ok(fresa_core::queue::Started {
                machine,
                job,
                run,
                entry: None,
            }),
            _ => Err((
                "internal".to_string(),
                format!("node {} answered without a run: {value}", node.name),
            )),
        };
    }
    Err((
        value["code"].as_str().unwrap_or("internal").to_string(),
        value["message"]
            .as_str()
            .map(str::to_string)
            .unwrap_or_else(|| format!("node {} answered {status}", node.name)),
    ))
}

#[cfg(test)]
mod tests {
    use super::{target, Target};
    use axum::http::Method;

    #[test]
    fn the_target_is_read_from_the_path() {
        let (get, post) = (Method::GET, Method::POST);
        for (method, path, want) in [
            (&get, "/api/v1/machines/1/status", Target::Machine(1)),
            (&post, "/api/v1/machines/7/jog", Target::Machine(7)),
            (&get, "/api/v1/machines/3/offsets/G54", Target::Machine(3)),
            (&get, "/api/v1/machines/3//x", Target::Machine(3)),
            (&get, "/api/v1/machines/-2/status", Target::Machine(-2)),
            (&get, "/api/v1/machines/1/status/", Target::Machine(1)),
            (&post, "/api/v1/machines/1/node", Target::None),
            (&get, "/api/v1/machines/1", Target::None),
            (&get, "/api/v1/machines/1/", Target::None),
            (&get, "/api/v1/machines//status", Target::None),
            (&get, "/api/v1/machines/x/status", Target::None),
            (&get, "/api/v1/machines", Target::None),
            (&post, "/api/v1/jobs/5/start", Target::Job(5)),
            (&post, "/api/v1/jobs/5/toolpath", Target::None),
            (&post, "/api/v1/jobs/5/start/now", Target::None),
            (&get, "/api/v1/jobs/5/start-preview", Target::Job(5)),
            (&get, "/api/v1/jobs/5/gcode", Target::None),
            (&get, "/api/v1/queue/1/x", Target::None),
            (&get, "", Target::None),
        ] {
            assert_eq!(target(method, path), want, "{method} {path}");
        }
    }
}
