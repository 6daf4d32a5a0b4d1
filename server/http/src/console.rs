//! The web console's files (crate `fresa-console`) at `/` and `/assets/{file}`. They need no
//! token (they hold no data; the API calls they make carry one) but pass the same Host/Origin
//! guard as the API. Each answer has its content type, a strong ETag (304 when unchanged), and
//! `no-cache` so a new binary's files are picked up at once; gzip is the router's layer.

use crate::error::ApiError;
use axum::extract::Path;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::sync::OnceLock;

/// The page may load only its own scripts and styles and talk only to this server.
const CSP: &str = "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
                   connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'";

fn etags() -> &'static HashMap<&'static str, String> {
    static ETAGS: OnceLock<HashMap<&'static str, String>> = OnceLock::new();
    ETAGS.get_or_init(|| {
        fresa_console::ASSETS
            .iter()
            .map(|a| {
                let h = Sha256::digest(a.bytes);
                (a.name, format!("\"{}\"", hex::encode(&h[..12])))
            })
            .collect()
    })
}

#[utoipa::path(get, path = "/", tag = "console",
    responses((status = 200, description = "The web console's page (HTML); no token needed", content_type = "text/html")))]
pub async fn index(headers: HeaderMap) -> Response {
    serve("index.html", &headers)
}

#[utoipa::path(get, path = "/assets/{name}", tag = "console",
    params(("name" = String, Path, description = "an embedded file of the console", example = "app.js")),
    responses(
        (status = 200, description = "The file, with its content type and ETag"),
        (status = 304, description = "Unchanged since the ETag sent in If-None-Match"),
        (status = 404, description = "`not_found`: no such file"),
    ))]
pub async fn asset(Path(name): Path<String>, headers: HeaderMap) -> Response {
    serve(&name, &headers)
}

fn serve(name: &str, headers: &HeaderMap) -> Response {
    let (Some(asset), Some(etag)) = (fresa_console::find(name), etags().get(name)) else {
        return ApiError::not_found("not_found", format!("no console file named {name:?}"))
            .into_response();
    };
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"));
    let etag = HeaderValue::from_str(etag).unwrap_or(HeaderValue::from_static("\"\""));
    let common = [
        (header::ETAG, etag),
        (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        (
            header::CONTENT_SECURITY_POLICY,
            HeaderValue::from_static(CSP),
        ),
        (
            header::X_CONTENT_TYPE_OPTIONS,
            HeaderValue::from_static("nosniff"),
        ),
    ];
    if fresh {
        return (StatusCode::NOT_MODIFIED, common).into_response();
    }
    (
        common,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static(asset.content_type),
        )],
        asset.bytes,
    )
        .into_response()
}
