//! Cross-site and DNS-rebinding protection, on every bind. A browser lets any web page send
//! simple requests (a POST with `text/plain`) to a loopback server, which trusts loopback callers
//! without a token; and a DNS-rebinding page reaches it under a name of its own. So:
//!
//! * `Host` must name this server: an IP literal of the listen address (any IP literal when
//!   bound to every address), `localhost`, or a name listed in `allowed_hosts`; there must be
//!   exactly one, and an absolute-form target's authority must name this server too and agree
//!   with it;
//! * a state-changing request (not GET/HEAD/OPTIONS) that carries an `Origin` other than the
//!   server's own, or one listed in `cors_origins`, is refused, and so is one a browser marks
//!   `Sec-Fetch-Site: cross-site`. Requests without these headers (curl, scripts, the CLI) are
//!   not browsers' and pass.
//!
//! CORS stays deny-by-default: only origins in `cors_origins` get CORS headers (see `router`).
//! The guard wraps the whole router once (`fresa_http::service`).

use crate::error::ApiError;
use axum::extract::Request;
use axum::http::{header, HeaderMap, Method, StatusCode, Uri};
use axum::response::Response;
use fresa_core::config::Settings;
use std::net::IpAddr;

/// The guard as a plain tower layer (it runs on every request, so it boxes nothing).
#[derive(Clone)]
pub struct Guard(pub std::sync::Arc<Settings>);

impl<S> tower::Layer<S> for Guard {
    type Service = Guarded<S>;
    fn layer(&self, inner: S) -> Guarded<S> {
        let ip = self.0.listen.ip();
        Guarded {
            settings: self.0.clone(),
            listen_name: match ip {
                IpAddr::V4(v4) => v4.to_string(),
                IpAddr::V6(v6) => format!("[{v6}]"),
            }
            .into(),
            inner,
        }
    }
}

#[derive(Clone)]
pub struct Guarded<S> {
    settings: std::sync::Arc<Settings>,
    /// The listen address's IP as a `Host` header writes it (`127.0.0.1`, `[::1]`): the name
    /// nearly every request carries, recognised without parsing it as an address.
    listen_name: std::sync::Arc<str>,
    inner: S,
}

impl<S> tower::Service<Request> for Guarded<S>
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
        match admit(
            &self.settings,
            &self.listen_name,
            req.method(),
            req.uri(),
            req.headers(),
        ) {
            Ok(()) => Either::Left(self.inner.call(req)),
            Err(e) => Either::Right(std::future::ready(Ok(e.into_response()))),
        }
    }
}

/// Longest request target (path and query) answered; longer ones get a JSON 414 here (beyond
/// hyper's own buffer limit hyper answers itself, without a body).
pub const MAX_URI_BYTES: usize = 8192;

/// Everything the guard checks, in order; the `Host` header is looked up once.
fn admit(
    settings: &Settings,
    listen_name: &str,
    method: &Method,
    uri: &Uri,
    headers: &HeaderMap,
) -> Result<(), ApiError> {
    uri_length(uri)?;
    let host = one_host(settings, uri, headers)?;
    if !(names_listen_address(host, listen_name) || host_allowed(settings, host)) {
        return Err(host_not_allowed(host));
    }
    if matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS) {
        return Ok(());
    }
    same_site(settings, method, headers, host)
}

fn uri_length(uri: &Uri) -> Result<(), ApiError> {
    let len = uri.path_and_query().map_or(0, |p| p.as_str().len());
    if len > MAX_URI_BYTES {
        return Err(ApiError::new(
            StatusCode::URI_TOO_LONG,
            "uri_too_long",
            format!("the request target is {len} bytes; at most {MAX_URI_BYTES} are accepted"),
        ));
    }
    Ok(())
}

/// Exactly one `Host`, as text, and (for an absolute-form target, `GET http://name/...`) a
/// target authority that names this server and agrees with it: a proxy or cache in between may
/// route by either, so both must be checked and be the same name. A request without `Host` is
/// refused whatever its method: HTTP/1.1 requires one (RFC 9112 3.2), every client we know sends
/// it (browsers, curl, reqwest and so the CLI), and without it there is no name to check.
/// Gives the `Host` header's text.
fn one_host<'h>(
    settings: &Settings,
    uri: &Uri,
    headers: &'h HeaderMap,
) -> Result<&'h str, ApiError> {
    let mut hosts = headers.get_all(header::HOST).iter();
    let host = hosts.next();
    let more = hosts.count();
    if more > 0 {
        return Err(ApiError::bad_request(
            "duplicate_host",
            format!(
                "the request has {} Host headers; exactly one is accepted",
                more + 1
            ),
        ));
    }
    let Some(host) = host else {
        return Err(ApiError::bad_request(
            "host_required",
            "the request has no Host header (HTTP/1.1 requires one): it must name this server",
        ));
    };
    let Ok(host) = host.to_str() else {
        return Err(ApiError::bad_request(
            "invalid_host",
            "the Host header is not plain text",
        ));
    };
    if let Some(authority) = uri.authority().map(|a| a.as_str()) {
        if !host_allowed(settings, authority) {
            return Err(host_not_allowed(authority));
        }
        if !authority.eq_ignore_ascii_case(host.trim()) {
            return Err(ApiError::bad_request(
                "host_mismatch",
                format!("the request target names {authority:?} but Host says {host:?}; they must agree"),
            ));
        }
    }
    Ok(host)
}

fn host_not_allowed(host: &str) -> ApiError {
    ApiError::new(
        StatusCode::FORBIDDEN,
        "host_not_allowed",
        format!(
            "Host {host:?} does not name this server; add it to `allowed_hosts` in the config if it does"
        ),
    )
}

/// A state-changing request comes from this server's own pages, an allowed origin, or no
/// browser at all.
fn same_site(
    settings: &Settings,
    method: &Method,
    headers: &HeaderMap,
    host: &str,
) -> Result<(), ApiError> {
    if let Some(origin) = headers.get(header::ORIGIN) {
        let origin = origin.to_str().unwrap_or("(not text)");
        if !origin_allowed(settings, origin, host) {
            return Err(ApiError::new(
                StatusCode::FORBIDDEN,
                "cross_origin",
                format!(
                    "a {method} from origin {origin:?} is refused: only this server's own pages, or origins listed in `cors_origins`, may change anything"
                ),
            ));
        }
        return Ok(());
    }
    if headers
        .get("sec-fetch-site")
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.eq_ignore_ascii_case("cross-site"))
    {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "cross_origin",
            format!("a cross-site {method} is refused"),
        ));
    }
    Ok(())
}

/// Splits `name[:port]` / `[v6]:port`.
fn host_name(host: &str) -> &str {
    let host = host.trim();
    if let Some(rest) = host.strip_prefix('[') {
        return rest.split(']').next().unwrap_or("");
    }
    match host.rsplit_once(':') {
        Some((name, port)) if port.bytes().all(|b| b.is_ascii_digit()) && !name.contains(':') => {
            name
        }
        _ => host,
    }
}

/// `host` is the listen address's IP (`listen_name`), with or without a port: one of the names
/// [`host_allowed`] admits (the port is not checked there either), told by comparing bytes.
fn names_listen_address(host: &str, listen_name: &str) -> bool {
    host.strip_prefix(listen_name).is_some_and(|rest| {
        rest.is_empty()
            || rest
                .strip_prefix(':')
                .is_some_and(|port| !port.is_empty() && port.bytes().all(|b| b.is_ascii_digit()))
    })
}

fn host_allowed(settings: &Settings, host: &str) -> bool {
    let name = host_name(host);
    if settings
        .allowed_hosts
        .iter()
        .any(|a| a.eq_ignore_ascii_case(host.trim()) || a.eq_ignore_ascii_case(name))
    {
        return true;
    }
    if name.eq_ignore_ascii_case("localhost") {
        return true;
    }
    // An IP literal cannot be rebound by DNS: it is this server if it is the listen address,
    // a loopback one, or any address when the server listens on all of them.
    match name.parse::<IpAddr>() {
        Ok(ip) => {
            let listen = settings.listen.ip();
            ip.is_loopback() || listen.is_unspecified() || ip == listen
        }
        Err(_) => false,
    }
}

fn origin_allowed(settings: &Settings, origin: &str, host: &str) -> bool {
    let origin = origin.trim_end_matches('/');
    if settings
        .cors_origins
        .iter()
        .any(|o| o.trim_end_matches('/').eq_ignore_ascii_case(origin))
    {
        return true;
    }
    // Same origin: the page was served by this server, under the name the request uses.
    ["http://", "https://"].iter().any(|scheme| {
        origin
            .strip_prefix(scheme)
            .is_some_and(|rest| rest.eq_ignore_ascii_case(host.trim()))
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn settings(listen: &str, allowed: &[&str], cors: &[&str]) -> Settings {
        let mut s = Settings::resolve(fresa_core::config::Overrides {
            data_dir: Some(std::env::temp_dir()),
            listen: Some(listen.into()),
            ..Default::default()
        })
        .unwrap();
        s.allowed_hosts = allowed.iter().map(|a| a.to_string()).collect();
        s.cors_origins = cors.iter().map(|a| a.to_string()).collect();
        s
    }

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, v.parse().unwrap());
        }
        h
    }

    #[test]
    fn hosts() {
        let s = settings("127.0.0.1:7878", &["fresa.shop.lan"], &[]);
        for ok in [
            "127.0.0.1:7878",
            "localhost:7878",
            "[::1]:7878",
            "FRESA.shop.lan:80",
            "fresa.shop.lan",
        ] {
            assert!(host_allowed(&s, ok), "{ok}");
        }
        for bad in [
            "evil.example",
            "evil.example:7878",
            "192.168.1.5:7878",
            "localhost.evil.example",
        ] {
            assert!(!host_allowed(&s, bad), "{bad}");
        }
        let any = settings("0.0.0.0:7878", &[], &[]);
        assert!(host_allowed(&any, "192.168.1.5:7878"));
        assert!(!host_allowed(&any, "evil.example:7878"));
    }

    /// The byte comparison for the listen address admits only what `host_allowed` admits, and
    /// the usual forms of it.
    #[test]
    fn the_listen_address_is_recognised_without_parsing() {
        let s = settings("127.0.0.1:7878", &[], &[]);
        for (host, fast) in [
            ("127.0.0.1:7878", true),
            ("127.0.0.1", true),
            ("127.0.0.1:80", true),
            ("127.0.0.1:", false),
            ("127.0.0.1:78a", false),
            ("127.0.0.1.evil.example", false),
            ("127.0.0.1.evil.example:7878", false),
            ("127.0.0.10:7878", false),
            (" 127.0.0.1:7878", false),
        ] {
            assert_eq!(names_listen_address(host, "127.0.0.1"), fast, "{host}");
            if fast {
                assert!(host_allowed(&s, host), "{host}");
            }
        }
        assert!(names_listen_address("[::1]:7878", "[::1]"));
        assert!(!names_listen_address("[::1]x", "[::1]"));
        assert!(!host_allowed(&s, "127.0.0.1.evil.example"));
    }

    #[test]
    fn one_host_agreeing_with_an_absolute_target() {
        let s = settings("127.0.0.1:7878", &[], &[]);
        let uri = |u: &str| u.parse::<Uri>().unwrap();
        let code =
            |u: &str, h: &HeaderMap| one_host(&s, &uri(u), h).map(|_| ()).map_err(|e| e.code);
        let own = headers(&[("host", "127.0.0.1:7878")]);
        assert_eq!(code("/api/v1/machines", &own), Ok(()));
        assert_eq!(code("http://127.0.0.1:7878/api/v1/machines", &own), Ok(()));
        assert_eq!(
            code("http://evil.example/api/v1/machines", &own),
            Err("host_not_allowed")
        );
        assert_eq!(
            code("http://localhost:7878/api/v1/machines", &own),
            Err("host_mismatch")
        );
        assert_eq!(code("/", &HeaderMap::new()), Err("host_required"));
        let mut two = own.clone();
        two.append("host", "evil.example".parse().unwrap());
        assert_eq!(code("/", &two), Err("duplicate_host"));
        let mut binary = HeaderMap::new();
        binary.insert(
            "host",
            axum::http::HeaderValue::from_bytes(b"h\xffst").unwrap(),
        );
        assert_eq!(code("/", &binary), Err("invalid_host"));
    }

    #[test]
    fn origins_on_state_changing_requests() {
        let s = settings("127.0.0.1:7878", &[], &["http://tablet.lan:8080"]);
        let post = Method::POST;
        let h = |o: &str| headers(&[("host", "127.0.0.1:7878"), ("origin", o)]);
        let check =
            |m: &Method, h: &HeaderMap| admit(&s, "127.0.0.1", m, &Uri::from_static("/"), h);
        assert!(check(&post, &h("http://127.0.0.1:7878")).is_ok());
        assert!(check(&post, &h("http://tablet.lan:8080")).is_ok());
        assert_eq!(
            check(&post, &h("http://evil.example")).unwrap_err().code,
            "cross_origin"
        );
        assert_eq!(check(&post, &h("null")).unwrap_err().code, "cross_origin");
        assert!(check(&Method::GET, &h("http://evil.example")).is_ok());
        let fetch = headers(&[("host", "127.0.0.1:7878"), ("sec-fetch-site", "cross-site")]);
        assert_eq!(check(&post, &fetch).unwrap_err().code, "cross_origin");
        assert!(check(&post, &headers(&[("host", "127.0.0.1:7878")])).is_ok());
        let rebound = headers(&[("host", "evil.example:7878")]);
        assert_eq!(
            check(&Method::GET, &rebound).unwrap_err().code,
            "host_not_allowed"
        );
    }
}
