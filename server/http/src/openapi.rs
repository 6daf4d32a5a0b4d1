//! The OpenAPI 3.1 description, built together with the router.
//!
//! Every route is registered through `utoipa_axum::routes!(handler)`, which takes the method and
//! path from the handler's `#[utoipa::path(...)]` annotation and adds the handler to the router
//! *and* its operation to the description: a route cannot be served without being described.
//! [`needs`] then wraps it with the role check and writes the same role into the description
//! (`x-fresa-role`, the security requirement, 401/403 answers), so the role is stated once, next
//! to the route. `tests/clients/openapi.rs` checks the served document against the running server.

use crate::auth::{self, Role};
use axum::response::IntoResponse;
use axum::Extension;
use fresa_core::SharedApp;
use serde::Serialize;
use std::sync::Arc;
use utoipa::openapi::path::{Operation, PathItem};
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityRequirement, SecurityScheme};
use utoipa::openapi::{ContentBuilder, Ref, ResponseBuilder};
use utoipa::ToSchema;

/// What `utoipa_axum::routes!` returns: schemas, the described paths and the axum method router.
pub type Routes = utoipa_axum::router::UtoipaMethodRouter<SharedApp>;

/// The top of the document; operations and their schemas are added by the router.
#[derive(utoipa::OpenApi)]
#[openapi(
    info(
        title = "Fresa HTTP API",
        description = "Shop-floor motion control: machines, jobs, pendants, webhooks and the \
                       event stream. Each operation's `x-fresa-role` is the role its token needs \
                       (`viewer` < `operator` < `admin`); a server bound to loopback only needs \
                       no token (every local caller is `admin`). Errors are `ErrorBody` with a \
                       stable `code`; each operation lists the codes it answers with.",
        license(name = "MIT OR Apache-2.0")
    ),
    components(schemas(ErrorBody, EventDoc)),
    modifiers(&BearerScheme)
)]
pub struct ApiDoc;

struct BearerScheme;

impl utoipa::Modify for BearerScheme {
    fn modify(&self, doc: &mut utoipa::openapi::OpenApi) {
        let components = doc.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(
                HttpBuilder::new()
                    .scheme(HttpAuthScheme::Bearer)
                    .description(Some(
                        "`Authorization: Bearer <token>` (create one with `fresa token create`). \
                         Not needed when the server listens on loopback only.",
                    ))
                    .build(),
            ),
        );
    }
}

/// Every error answer: a stable code and a message naming the field, value or G-code line.
#[derive(Serialize, ToSchema)]
#[schema(example = json!({"code": "unknown_machine", "message": "no machine with id 7"}))]
pub struct ErrorBody {
    /// Stable, machine-readable: `unknown_machine`, `invalid_field`, `forbidden`, ...
    pub code: String,
    pub message: String,
}

/// One Server-Sent Event's `data` (its `event:` field is `type`, its `id:` field is `id`).
/// Persisted (audit) types: `job.created`, `job.state`, `machine.created`, `machine.command`,
/// `machine.jog`, `machine.jog_cancel`, `machine.mdi`, `machine.offsets`, `machine.part_zero`, `machine.alarm`,
/// `machine.tools`, `machine.run_settings`, `machine.tool_measured`, `pendant.*`, `webhook.created`,
/// `webhook.deleted`, `height_map.ended`, `height_map.deleted`, `queue.*` (job queues),
/// `machine.maintenance_due`, `machine.maintenance_done`. Live only (no `id`): `status` (same
/// schema as `GET /machines/{id}/status`), `job.progress` (`job`, `run`, `line`, `total_lines`,
/// `percent`), `job.line_report`, `machine.state`, `height_map.progress` (`map`, `done`,
/// `total`, `i`, `j`, `x`, `y`, `z`). Control: `resync`.
#[derive(Serialize, ToSchema)]
#[schema(as = Event)]
pub struct EventDoc {
    /// Present on persisted events only; resume after it with `Last-Event-ID`.
    pub id: Option<i64>,
    #[serde(rename = "type")]
    pub kind: String,
    pub machine: Option<i64>,
    /// Who caused it: a token name, `local`, `pendant:<id>`, `http`.
    pub actor: Option<String>,
    /// Milliseconds since the Unix epoch.
    pub time: i64,
    #[schema(value_type = Object)]
    pub data: serde_json::Value,
}

/// `needs(role, routes!(handler))`: the route answers only callers with at least `role`, and
/// its description says so.
pub fn needs(role: Role, (schemas, mut paths, method_router): Routes) -> Routes {
    for item in paths.paths.values_mut() {
        for op in operations(item) {
            describe_role(op, Some(role));
        }
    }
    (schemas, paths, auth::needs(role, method_router))
}

/// A route anyone who can reach the server may call (no token): `/healthz`, the description.
pub fn public((schemas, mut paths, method_router): Routes) -> Routes {
    for item in paths.paths.values_mut() {
        for op in operations(item) {
            describe_role(op, None);
        }
    }
    (schemas, paths, method_router)
}

pub(crate) fn operations(item: &mut PathItem) -> impl Iterator<Item = &mut Operation> {
    [
        item.get.as_mut(),
        item.put.as_mut(),
        item.post.as_mut(),
        item.delete.as_mut(),
        item.patch.as_mut(),
        item.head.as_mut(),
        item.options.as_mut(),
        item.trace.as_mut(),
    ]
    .into_iter()
    .flatten()
}

fn describe_role(op: &mut Operation, role: Option<Role>) {
    // Handlers are named per module (`machines::list`, `jobs::list`): the tag makes the
    // operation id unique, as OpenAPI requires.
    if let (Some(tag), Some(id)) = (
        op.tags.as_ref().and_then(|t| t.first()),
        op.operation_id.as_ref(),
    ) {
        op.operation_id = Some(format!("{tag}_{id}"));
    }
    let name = role.map_or("none", Role::name);
    op.extensions
        .get_or_insert_with(Default::default)
        .insert("x-fresa-role".into(), serde_json::json!(name));
    let note = match role {
        Some(r) => format!(
            "Role: `{}` (no token needed on a loopback-only server).",
            r.name()
        ),
        None => "No token needed.".to_string(),
    };
    op.description = Some(match op.description.take() {
        Some(d) if !d.is_empty() => format!("{d}\n\n{note}"),
        _ => note,
    });
    let Some(role) = role else {
        op.security = Some(vec![SecurityRequirement::default()]);
        return;
    };
    // The empty requirement: a loopback-only server takes requests without a token.
    op.security = Some(vec![
        SecurityRequirement::new("bearer", Vec::<String>::new()),
        SecurityRequirement::default(),
    ]);
    let error = |what: &str| {
        ResponseBuilder::new()
            .description(what)
            .content(
                "application/json",
                ContentBuilder::new()
                    .schema(Some(Ref::from_schema_name("ErrorBody")))
                    .build(),
            )
            .build()
    };
    op.responses.responses.insert(
        "401".into(),
        error("`token_required` (no token on a networked server) or `invalid_token`").into(),
    );
    if role > Role::Viewer {
        op.responses.responses.insert(
            "403".into(),
            error(&format!(
                "`forbidden`: the token's role is below `{}`",
                role.name()
            ))
            .into(),
        );
    }
}

/// The description, made on its first request and kept: made at start-up it cost about 1 ms of
/// every start and 270 KB of memory that most servers never serve.
#[derive(Clone)]
pub struct Document {
    json: Arc<tokio::sync::OnceCell<axum::body::Bytes>>,
    /// Called on the describing thread once only the served bytes are left. Describing builds
    /// the whole routing table and its operations again (several MiB, all freed at once), with
    /// code that nothing but the start runs: the daemon gives back the allocator's freed pages
    /// (1.4 MiB more private memory for as long as the server runs otherwise) and unmaps that
    /// code (about 3 MiB of the binary).
    after_describing: fn(),
}

impl Document {
    pub fn new(after_describing: fn()) -> Self {
        Document {
            json: Arc::default(),
            after_describing,
        }
    }

    /// Describes the API: the document exactly as long as it is (the serialiser's buffer has
    /// grown by doubling), then `after_describing`.
    fn describe(&self) -> axum::body::Bytes {
        let json = crate::openapi_document().into_boxed_str();
        (self.after_describing)();
        axum::body::Bytes::from(json.into_boxed_bytes())
    }
}

/// This server's OpenAPI 3.1 description. Public like `/healthz`: it is the same for every Fresa
/// of this version and holds nothing about this server's machines or jobs, and client generators
/// fetch it without credentials.
#[utoipa::path(
    get,
    path = "/api/v1/openapi.json",
    tag = "system",
    responses((status = 200, description = "The OpenAPI 3.1 document", content_type = "application/json", body = Object))
)]
pub async fn openapi_json(
    Extension(document): Extension<Document>,
) -> Result<impl IntoResponse, crate::error::ApiError> {
    // Described again from the same routes the server was built from: 4-9 ms of CPU, once,
    // on a blocking thread, not on a runtime worker whose other tasks (a pendant's poll, a
    // STOP) would wait for it. Concurrent first requests wait for the one description.
    let json = document
        .json
        .get_or_try_init(|| async {
            let describing = document.clone();
            tokio::task::spawn_blocking(move || describing.describe()).await
        })
        .await
        .map_err(|e| {
            crate::error::ApiError::internal(format!("describing the API failed (a bug): {e}"))
        })?
        .clone();
    Ok((
        [(axum::http::header::CONTENT_TYPE, "application/json")],
        json,
    ))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use std::sync::Mutex;
    use std::thread::ThreadId;

    /// The threads the release hook ran on.
    static RELEASED_ON: Mutex<Vec<ThreadId>> = Mutex::new(Vec::new());

    fn record_release() {
        RELEASED_ON
            .lock()
            .unwrap()
            .push(std::thread::current().id());
    }

    async fn served(document: &Document) -> axum::body::Bytes {
        let answer = openapi_json(Extension(document.clone()))
            .await
            .map_err(|_| "describing failed")
            .unwrap()
            .into_response();
        axum::body::to_bytes(answer.into_body(), usize::MAX)
            .await
            .unwrap()
    }

    /// First requests at once describe the API once: the hook that gives back what describing
    /// used runs once, on that blocking thread (not on the runtime's), and every answer is the
    /// whole document.
    #[tokio::test]
    async fn what_describing_used_is_given_back_once_on_the_describing_thread() {
        let document = Document::new(record_release);
        let answers = tokio::join!(
            served(&document),
            served(&document),
            served(&document),
            served(&document)
        );
        let later = served(&document).await;
        let expected = crate::openapi_document();
        for answer in [answers.0, answers.1, answers.2, answers.3, later] {
            assert_eq!(answer, expected.as_bytes());
        }
        let released_on = RELEASED_ON.lock().unwrap().clone();
        assert_eq!(released_on.len(), 1, "released {released_on:?}");
        assert_ne!(released_on[0], std::thread::current().id());
    }
}
