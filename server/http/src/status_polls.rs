//! The hottest request, a status poll (`GET /api/v1/machines/{id}/status`, no query), answered
//! in front of the router: matching the route, decoding its path parameter and inserting it in
//! the request's extensions cost a poll about a tenth of its instructions (README: Measurements,
//! "Status reads"). Only the routing is skipped: this layer sits inside the guard, the request
//! log, CORS and the [`Gate`](crate::Gate) (authentication, forwarding), as the route does; the
//! route needs a viewer, which every caller the gate lets through is (`auth::needs`); and the
//! answer is the route's own, the machine's shared status bytes (`Machine::status_json`).
//! Anything else goes to the router, which answers as before: a query (`until`, a token), an id
//! that is not plain digits, a machine this node does not drive, a status that fails.

use axum::extract::Request;
use axum::http::{header, HeaderValue, Method};
use axum::response::{IntoResponse, Response};
use fresa_core::SharedApp;
use futures_util::future::Either;
use std::convert::Infallible;
use std::future::Ready;
use std::task::{Context, Poll};

#[derive(Clone)]
pub struct StatusPolls<S> {
    app: SharedApp,
    inner: S,
}

impl<S> StatusPolls<S> {
    pub(crate) fn new(app: SharedApp, inner: S) -> StatusPolls<S> {
        StatusPolls { app, inner }
    }

    fn answer(&self, req: &Request) -> Option<Response> {
        let machine = self.app.machines.get(polled_machine(req)?)?;
        let json = machine.status_json().ok()?;
        Some(
            (
                [(
                    header::CONTENT_TYPE,
                    HeaderValue::from_static("application/json"),
                )],
                json,
            )
                .into_response(),
        )
    }
}

/// The machine a plain status poll asks for; `None` for every other request.
fn polled_machine(req: &Request) -> Option<i64> {
    if req.method() != Method::GET || req.uri().query().is_some() {
        return None;
    }
    let id = req
        .uri()
        .path()
        .strip_prefix("/api/v1/machines/")?
        .strip_suffix("/status")?;
    // At most 18 digits: always an i64, and no sign, blank or percent-escape for `parse` to
    // read differently from the router's `Path<i64>`.
    if id.is_empty() || id.len() > 18 || !id.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    id.parse().ok()
}

impl<S> tower::Service<Request> for StatusPolls<S>
where
    S: tower::Service<Request, Response = Response, Error = Infallible>,
{
    type Response = Response;
    type Error = Infallible;
    type Future = Either<Ready<Result<Response, Infallible>>, S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: Request) -> Self::Future {
        match self.answer(&req) {
            Some(answer) => Either::Left(std::future::ready(Ok(answer))),
            None => Either::Right(self.inner.call(req)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::polled_machine;
    use axum::body::Body;
    use axum::extract::Request;

    fn polled(method: &str, uri: &str) -> Option<i64> {
        let req = Request::builder()
            .method(method)
            .uri(uri)
            .body(Body::empty())
            .ok()?;
        polled_machine(&req)
    }

    #[test]
    fn only_a_plain_status_poll_skips_the_router() {
        assert_eq!(polled("GET", "/api/v1/machines/1/status"), Some(1));
        assert_eq!(polled("GET", "/api/v1/machines/42/status"), Some(42));
        for (method, uri) in [
            ("HEAD", "/api/v1/machines/1/status"),
            ("POST", "/api/v1/machines/1/status"),
            ("GET", "/api/v1/machines/1/status?until=idle"),
            ("GET", "/api/v1/machines/1/status?access_token=fresa_x"),
            ("GET", "/api/v1/machines/1/status/"),
            ("GET", "/api/v1/machines//status"),
            ("GET", "/api/v1/machines/-1/status"),
            ("GET", "/api/v1/machines/+1/status"),
            ("GET", "/api/v1/machines/%31/status"),
            ("GET", "/api/v1/machines/1/2/status"),
            ("GET", "/api/v1/machines/1/statusx"),
            ("GET", "/api/v1/machines/1"),
            ("GET", "/api/v2/machines/1/status"),
            ("GET", "/api/v1/machines/9223372036854775807/status"),
        ] {
            assert_eq!(polled(method, uri), None, "{method} {uri}");
        }
    }
}
