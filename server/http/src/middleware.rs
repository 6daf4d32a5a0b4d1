//! Per-request middleware with a fast path. Every request under `/api/v1` passes authentication
//! and the forwarding check. `axum::middleware::from_fn` costs each layer two boxed futures and a
//! clone of the boxed route below it, per request, and a status poll can come a few hundred
//! thousand times a second. Here the common case (a local caller, a machine this node drives)
//! is decided without waiting and goes straight to the route; only the rest (a token to look up,
//! a request to forward) is boxed. Middlewares are chained as a pair inside one layer (each axum
//! layer is one more boxed route to clone per request).

use axum::extract::Request;
use axum::response::Response;
use futures_util::future::{BoxFuture, Either};
use std::convert::Infallible;
use std::task::{Context, Poll};

/// A middleware split into what it decides at once and what it has to wait for.
pub(crate) trait Middleware: Clone + Send + Sync + 'static {
    /// The common case, decided without waiting: [`Fast::Pass`] sends the request (with what
    /// this middleware added to it) straight on, [`Fast::Slow`] hands it back for
    /// [`Self::slow`]. [`Self::slow`] must also take a request `fast` would have passed: in a
    /// pair, the first member's `slow` runs whenever the second member's `fast` did not pass.
    fn fast(&self, req: Request) -> Fast;

    /// Everything else; `next` is what comes after this middleware. Boxed (this path is the
    /// rare one), which also keeps the compiler's `Send` check of these futures concrete.
    fn slow(self, req: Request, next: impl Next) -> BoxFuture<'static, Response>;
}

/// What [`Middleware::fast`] decided.
pub(crate) enum Fast {
    Pass(Request),
    Slow(Request),
}

/// What runs after a middleware: the route, or the rest of a pair and then the route.
pub(crate) trait Next: Send + 'static {
    fn run(self, req: Request) -> BoxFuture<'static, Response>;
}

/// `middleware`, then `next`.
struct Then<M, N> {
    middleware: M,
    next: N,
}

impl<M: Middleware, N: Next> Next for Then<M, N> {
    fn run(self, req: Request) -> BoxFuture<'static, Response> {
        match self.middleware.fast(req) {
            Fast::Pass(req) => self.next.run(req),
            Fast::Slow(req) => self.middleware.slow(req, self.next),
        }
    }
}

/// `A`, then `B`.
impl<A: Middleware, B: Middleware> Middleware for (A, B) {
    fn fast(&self, req: Request) -> Fast {
        match self.0.fast(req) {
            Fast::Pass(req) => self.1.fast(req),
            slow => slow,
        }
    }

    fn slow(self, req: Request, next: impl Next) -> BoxFuture<'static, Response> {
        let (a, b) = self;
        a.slow(
            req,
            Then {
                middleware: b,
                next,
            },
        )
    }
}

/// The tower layer of a [`Middleware`], around the whole router (`crate::service`): a request
/// pays for it once, where `Router::layer` would wrap every route.
#[derive(Clone)]
pub(crate) struct Layer<M>(pub M);

impl<M: Middleware, S> tower::Layer<S> for Layer<M> {
    type Service = Service<M, S>;
    fn layer(&self, inner: S) -> Service<M, S> {
        Service {
            middleware: self.0.clone(),
            inner,
        }
    }
}

#[derive(Clone)]
pub struct Service<M, S> {
    middleware: M,
    inner: S,
}

impl<M, S> tower::Service<Request> for Service<M, S>
where
    M: Middleware,
    S: tower::Service<Request, Response = Response, Error = Infallible> + Clone + Send + 'static,
    S::Future: Send + 'static,
{
    type Response = Response;
    type Error = Infallible;
    type Future = Either<S::Future, BoxFuture<'static, Result<Response, Infallible>>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: Request) -> Self::Future {
        match self.middleware.fast(req) {
            Fast::Pass(req) => Either::Left(self.inner.call(req)),
            Fast::Slow(req) => {
                let slow = self.middleware.clone().slow(req, Inner(self.inner.clone()));
                Either::Right(Box::pin(async move { Ok(slow.await) }))
            }
        }
    }
}

/// The service a [`Service`] wraps, as what runs after its middleware.
struct Inner<S>(S);

impl<S> Next for Inner<S>
where
    S: tower::Service<Request, Response = Response, Error = Infallible> + Send + 'static,
    S::Future: Send + 'static,
{
    fn run(self, req: Request) -> BoxFuture<'static, Response> {
        let call = tower::ServiceExt::oneshot(self.0, req);
        Box::pin(async move {
            match call.await {
                Ok(r) => r,
                Err(never) => match never {},
            }
        })
    }
}
