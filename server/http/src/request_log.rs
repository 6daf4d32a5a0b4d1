//! The request log around the whole router: every answer with a 5xx status is logged at ERROR
//! (method, URI without secrets, status, latency); with DEBUG on, each request also runs in a
//! `request` span (so a handler's own logs name it) between a "started" and a "finished" event.
//!
//! This replaces tower-http's `TraceLayer`, which built the span, classified the response and
//! wrapped its body on every request even with DEBUG off. Here the common case (DEBUG off) is a
//! clock read, two cheap clones and a status check, boxing nothing: a status request went from
//! 26,723 to 26,256 instructions, and to 25,169 once the log wrapped the router once instead of
//! each route (`crate::service`; README: Measurements). Unlike `TraceLayer`, an error inside a
//! response body after its head was sent is not logged here.

use crate::auth::redacted_uri;
use axum::extract::Request;
use axum::http::{Method, Uri};
use axum::response::Response;
use futures_util::future::{BoxFuture, Either};
use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Instant;
use tracing::Instrument;

#[derive(Clone, Copy)]
pub struct RequestLog;

impl<S> tower::Layer<S> for RequestLog {
    type Service = Logged<S>;
    fn layer(&self, inner: S) -> Logged<S> {
        Logged { inner }
    }
}

#[derive(Clone)]
pub struct Logged<S> {
    inner: S,
}

impl<S> tower::Service<Request> for Logged<S>
where
    S: tower::Service<Request, Response = Response>,
    S::Future: Send + 'static,
{
    type Response = Response;
    type Error = S::Error;
    type Future = Either<Watched<S::Future>, BoxFuture<'static, Result<Response, S::Error>>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: Request) -> Self::Future {
        let start = Instant::now();
        let (method, uri) = (req.method().clone(), req.uri().clone());
        if !tracing::enabled!(tracing::Level::DEBUG) {
            return Either::Left(Watched {
                inner: self.inner.call(req),
                seen: Some((method, uri, start)),
            });
        }
        // DEBUG on: a span per request (boxed; this is not the fast path any more).
        let span = tracing::debug_span!(
            "request",
            method = %method,
            uri = %redacted_uri(&uri),
            version = ?req.version(),
        );
        let inner = span.in_scope(|| {
            tracing::debug!("started processing request");
            self.inner.call(req)
        });
        Either::Right(Box::pin(
            async move {
                let answer = inner.await;
                if let Ok(response) = &answer {
                    finished(&method, &uri, start, response);
                }
                answer
            }
            .instrument(span),
        ))
    }
}

pin_project_lite::pin_project! {
    /// The inner future, and what to log when its answer is a server error.
    pub struct Watched<F> {
        #[pin]
        inner: F,
        seen: Option<(Method, Uri, Instant)>,
    }
}

impl<F, E> Future for Watched<F>
where
    F: Future<Output = Result<Response, E>>,
{
    type Output = F::Output;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let this = self.project();
        let answer = std::task::ready!(this.inner.poll(cx));
        if let (Ok(response), Some((method, uri, start))) = (&answer, this.seen.take()) {
            finished(&method, &uri, start, response);
        }
        Poll::Ready(answer)
    }
}

fn finished(method: &Method, uri: &Uri, start: Instant, response: &Response) {
    let status = response.status();
    // The clock is read again only for a line that is written.
    let latency_ms = || start.elapsed().as_secs_f64() * 1e3;
    if status.is_server_error() {
        let latency_ms = latency_ms();
        tracing::error!(
            %method,
            uri = %redacted_uri(uri),
            status = status.as_u16(),
            latency_ms,
            "request failed with a server error"
        );
    } else if tracing::enabled!(tracing::Level::DEBUG) {
        tracing::debug!(
            status = status.as_u16(),
            latency_ms = latency_ms(),
            "finished processing request"
        );
    }
}
