//! Router, middleware and the server lifecycle.

use super::config::ServerConfig;
use super::conn::ConnLimits;
use super::handlers as h;
use super::limits::{admit_body, BodyGate};
use super::problem::{code_for_status, ApiError, PROBLEM_JSON};
use super::state::App;
use crate::Result;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Router;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tower_http::request_id::{
    MakeRequestId, PropagateRequestIdLayer, RequestId, SetRequestIdLayer,
};
use tower_http::trace::TraceLayer;

/// Builds the router over a loaded [`App`].
pub fn router(app: Arc<App>) -> Router {
    let timeout = Duration::from_secs_f64(app.cfg.request_timeout_secs);
    let v1 = Router::new()
        .route("/v1/shapes", post(h::ingest).get(h::list))
        .route("/v1/shapes/{id}", get(h::get_shape).delete(h::delete_shape))
        .route("/v1/jobs/{id}", get(h::get_job))
        .route("/v1/shapes/{id}/mesh", get(h::get_mesh))
        .route("/v1/shapes/{id}/signature", get(h::get_signature))
        .route("/v1/search", post(h::search))
        .route("/v1/index", get(h::index_info))
        .layer(middleware::from_fn_with_state(
            (timeout, app.cfg.retry_after_secs),
            timeout_mw,
        ));
    Router::new()
        .merge(v1)
        .route("/healthz", get(h::healthz))
        .route("/readyz", get(h::readyz))
        .route("/metrics", get(h::metrics))
        .route("/openapi.yaml", get(h::openapi))
        .merge(super::web::routes())
        .fallback(fallback)
        .layer(DefaultBodyLimit::max(app.cfg.max_body_bytes))
        .layer(middleware::from_fn_with_state(
            Arc::new(BodyGate::new(
                app.cfg.max_body_bytes,
                app.cfg.max_inflight_body_bytes,
                Duration::from_secs_f64(app.cfg.body_read_timeout_secs),
                app.cfg.retry_after_secs,
            )),
            admit_body,
        ))
        .layer(middleware::map_response(problem_catch_all))
        .layer(tower_http::catch_panic::CatchPanicLayer::custom(panic_to_problem))
        .layer(middleware::from_fn(metrics_mw))
        .layer(TraceLayer::new_for_http().make_span_with(|req: &Request| {
            let rid = req
                .headers()
                .get("x-request-id")
                .and_then(|v| v.to_str().ok())
                .unwrap_or("-");
            tracing::info_span!("request", method = %req.method(), uri = %req.uri(), request_id = %rid)
        })
        .on_response(tower_http::trace::DefaultOnResponse::new().level(tracing::Level::INFO)))
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(SetRequestIdLayer::x_request_id(Counter::default()))
        .layer(middleware::map_request(drop_unsafe_request_id))
        .with_state(app)
}

#[derive(Clone, Default)]
struct Counter(Arc<AtomicU64>);

impl MakeRequestId for Counter {
    fn make_request_id<B>(&mut self, _: &axum::http::Request<B>) -> Option<RequestId> {
        let n = self.0.fetch_add(1, Ordering::Relaxed);
        HeaderValue::from_str(&format!("{:x}-{n}", std::process::id()))
            .ok()
            .map(RequestId::new)
    }
}

/// Longest client `X-Request-Id` kept (longer ones are replaced by a generated id).
pub const MAX_REQUEST_ID_LEN: usize = 64;

/// Removes a client `X-Request-Id` that is too long or has characters other than ASCII
/// letters, digits and `-_.:`, so that a generated one takes its place: ids end up in logs and
/// response headers and must not carry arbitrary bytes or sizes.
async fn drop_unsafe_request_id(mut req: Request) -> Request {
    let unsafe_id = req.headers().get_all("x-request-id").iter().any(|v| {
        let b = v.as_bytes();
        b.is_empty()
            || b.len() > MAX_REQUEST_ID_LEN
            || !b
                .iter()
                .all(|c| c.is_ascii_alphanumeric() || b"-_.:".contains(c))
    });
    if unsafe_id || req.headers().get_all("x-request-id").iter().count() > 1 {
        req.headers_mut().remove("x-request-id");
    }
    req
}

fn panic_to_problem(err: Box<dyn std::any::Any + Send + 'static>) -> Response {
    let msg = err
        .downcast_ref::<String>()
        .map(|s| s.as_str())
        .or_else(|| err.downcast_ref::<&str>().copied())
        .unwrap_or("panic");
    ApiError::internal(format!("handler panicked: {msg}")).into_response()
}

async fn fallback() -> ApiError {
    ApiError::new(StatusCode::NOT_FOUND, "route.not_found", "no such route")
}

/// The instant a request must be answered by (set by the timeout layer; CPU work of the
/// request stops once it passes, see [`super::admission::Cancel`]).
#[derive(Clone, Copy, Debug)]
pub struct Deadline(pub Instant);

/// The deadline of a request, if it runs under the timeout layer.
pub fn deadline_of(req: &Request) -> Option<Instant> {
    req.extensions().get::<Deadline>().map(|d| d.0)
}

async fn timeout_mw(
    State((t, retry_after)): State<(Duration, u64)>,
    mut req: Request,
    next: Next,
) -> Response {
    req.extensions_mut().insert(Deadline(Instant::now() + t));
    // On timeout the handler's future is dropped, which trips the cancellation token of the
    // CPU job it was waiting for. The job checks the same deadline, so under load it can see it
    // pass first and answer its own 503 `request.timeout`: every 503 leaves with `Retry-After`.
    match tokio::time::timeout(t, next.run(req)).await {
        Ok(mut r) => {
            if r.status() == StatusCode::SERVICE_UNAVAILABLE
                && !r.headers().contains_key(header::RETRY_AFTER)
            {
                r.headers_mut()
                    .insert(header::RETRY_AFTER, HeaderValue::from(retry_after));
            }
            r
        }
        Err(_) => {
            metrics::counter!("shapeseek_requests_timed_out_total").increment(1);
            let mut e = ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "request.timeout",
                format!(
                    "the request took longer than {:.1} s and was abandoned",
                    t.as_secs_f64()
                ),
            );
            e.retry_after = Some(retry_after);
            e.into_response()
        }
    }
}

/// Turns any error response that is not already problem+json (extractor rejections, 405s,
/// layers) into one, so clients only ever see one error format.
async fn problem_catch_all(resp: Response) -> Response {
    let status = resp.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return resp;
    }
    let is_problem = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with(PROBLEM_JSON));
    if is_problem {
        return resp;
    }
    let (parts, body) = resp.into_parts();
    let text = axum::body::to_bytes(body, 64 << 10)
        .await
        .map(|b| String::from_utf8_lossy(&b).trim().to_string())
        .unwrap_or_default();
    let detail = if text.is_empty() {
        status.canonical_reason().unwrap_or("error").to_string()
    } else {
        text
    };
    let mut out = ApiError::new(status, code_for_status(status), detail).into_response();
    // Keep headers such as Allow (405) and Retry-After.
    for (k, v) in parts.headers.iter() {
        if k != header::CONTENT_TYPE && k != header::CONTENT_LENGTH {
            out.headers_mut().insert(k.clone(), v.clone());
        }
    }
    out
}

/// The `method` label of the request metrics: one of the methods the API has, else `other`.
/// A client may send any token as a method (each one answered 405): as a label it would make
/// a new series per token, and `/metrics` and the server's memory grow without bound (20
/// requests with 50 000-byte methods took `/metrics` from 0.6 MB to 19.7 MB).
fn method_label(m: &axum::http::Method) -> &'static str {
    use axum::http::Method;
    match *m {
        Method::GET => "GET",
        Method::HEAD => "HEAD",
        Method::POST => "POST",
        Method::PUT => "PUT",
        Method::DELETE => "DELETE",
        Method::OPTIONS => "OPTIONS",
        Method::PATCH => "PATCH",
        _ => "other",
    }
}

async fn metrics_mw(req: Request, next: Next) -> Response {
    let start = Instant::now();
    let method = method_label(req.method());
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_string())
        .unwrap_or_else(|| "unmatched".into());
    let resp = next.run(req).await;
    let status = resp.status().as_u16().to_string();
    metrics::counter!("shapeseek_http_requests_total", "method" => method, "route" => route.clone(), "status" => status).increment(1);
    metrics::histogram!("shapeseek_http_request_duration_seconds", "method" => method, "route" => route)
        .record(start.elapsed().as_secs_f64());
    resp
}

/// Lifecycle hooks of a running app, independent of its engine type.
trait Lifecycle: Send + Sync {
    fn set_ready(&self, ready: bool);
    fn store(&self) -> Arc<dyn crate::storage::ShapeStore>;
}

impl Lifecycle for App {
    fn set_ready(&self, ready: bool) {
        self.ready.store(ready, Ordering::Release);
    }
    fn store(&self) -> Arc<dyn crate::storage::ShapeStore> {
        self.store.clone()
    }
}

/// A server started by [`start`] / [`start_with`].
pub struct Running {
    /// The bound address (useful with port 0).
    pub addr: SocketAddr,
    app: Arc<dyn Lifecycle>,
    stop: tokio::sync::oneshot::Sender<()>,
    join: tokio::task::JoinHandle<std::io::Result<()>>,
    grace: Duration,
}

impl Running {
    /// Graceful shutdown: not ready, stop accepting, wait up to the grace period for
    /// in-flight requests, abandon the rest, flush the index, release it.
    pub async fn shutdown(self) -> Result<()> {
        self.app.set_ready(false);
        let _ = self.stop.send(());
        let mut join = self.join;
        match tokio::time::timeout(self.grace, &mut join).await {
            Ok(Ok(r)) => r?,
            Ok(Err(e)) => tracing::error!(error = %e, "server task failed"),
            Err(_) => {
                tracing::warn!("grace period over; abandoning in-flight requests");
                join.abort();
                let _ = join.await;
            }
        }
        self.app.store().flush().await?;
        // Give blocking jobs that hold the index a moment to finish and drop it.
        let deadline = Instant::now() + self.grace;
        while Arc::strong_count(&self.app) > 1 && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        tracing::info!("stopped");
        Ok(())
    }
}

/// Starts the server with the product engine (see [`crate::index::default_engine`]).
pub async fn start(cfg: ServerConfig) -> Result<Running> {
    let engine = cfg.engine();
    start_with(cfg, engine).await
}

/// Binds `cfg.addr`, answers there while the index loads (on a blocking thread; `/healthz` 200,
/// else 503 `server.not_ready`), then serves the API in the background; returns once ready.
pub async fn start_with(cfg: ServerConfig, engine: crate::index::Engine) -> Result<Running> {
    cfg.validate()?;
    let grace = Duration::from_secs_f64(cfg.shutdown_grace_secs);
    let listener = tokio::net::TcpListener::bind(&cfg.addr)
        .await
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::InvalidInput => {
                crate::Error::InvalidArgument(format!("addr {:?} is not HOST:PORT ({e})", cfg.addr))
            }
            kind => crate::Error::Io(std::io::Error::new(
                kind,
                format!("cannot listen on {}: {e}", cfg.addr),
            )),
        })?;
    let addr = listener.local_addr()?;
    // The socket answers while the index loads (which can take minutes): `/healthz` 200, every
    // other path 503 `server.not_ready` with `Retry-After`. Until then the port was bound but
    // nothing answered, and a health check hung for the whole load. The loaded router takes
    // over in the same listener once the node is ready.
    let loaded: Arc<std::sync::OnceLock<Router>> = Arc::default();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let limits = ConnLimits {
        max_connections: cfg.max_connections,
        header_read_timeout: Duration::from_secs_f64(cfg.header_read_timeout_secs),
        send_stall_timeout: Duration::from_secs_f64(cfg.send_stall_timeout_secs),
        retry_after_secs: cfg.retry_after_secs,
    };
    let front = front_router(loaded.clone(), cfg.retry_after_secs);
    let join = tokio::spawn(async move {
        super::conn::serve(listener, front, limits, async move {
            let _ = stopped.await;
        })
        .await
    });
    // Not the `addr` field: scripts and tests take the log line with it (`listening`, once
    // ready) as the sign that the node serves.
    tracing::info!(bound = %addr, "loading the index (503 server.not_ready until it is loaded)");
    let started = load_and_route(cfg, engine).await;
    let app = match started {
        Ok((app, router)) => {
            let _ = loaded.set(router);
            app.ready.store(true, Ordering::Release);
            app
        }
        Err(e) => {
            let _ = stop.send(());
            let _ = tokio::time::timeout(grace, join).await;
            return Err(e);
        }
    };
    let lifecycle: Arc<dyn Lifecycle> = app;
    Ok(Running {
        addr,
        app: lifecycle,
        stop,
        join,
        grace,
    })
}

/// What the listener serves: the loaded router once there is one, else `/healthz` 200 (the
/// process is alive), the viewer's static files (the page then says the index is loading and
/// asks again; before, a browser opened during a load showed the 503's JSON) and 503
/// `server.not_ready` (with `Retry-After`) for every other request.
fn front_router(loaded: Arc<std::sync::OnceLock<Router>>, retry_after: u64) -> Router {
    use tower::ServiceExt;
    let page: Router = super::web::routes();
    Router::new().fallback(move |req: Request| {
        let (loaded, page) = (loaded.clone(), page.clone());
        async move {
            if let Some(r) = loaded.get() {
                return match r.clone().oneshot(req).await {
                    Ok(resp) => resp,
                    Err(never) => match never {},
                };
            }
            let read = matches!(
                *req.method(),
                axum::http::Method::GET | axum::http::Method::HEAD
            );
            if req.uri().path() == "/healthz" && read {
                return axum::Json(serde_json::json!({"status": "ok"})).into_response();
            }
            if read && super::web::is_page(req.uri().path()) {
                return match page.oneshot(req).await {
                    Ok(resp) => resp,
                    Err(never) => match never {},
                };
            }
            ApiError::not_ready("not ready: the index is loading", retry_after).into_response()
        }
    })
}

/// Opens the store (and the cluster), loads the index and builds its router.
async fn load_and_route(
    cfg: ServerConfig,
    engine: crate::index::Engine,
) -> Result<(Arc<App>, Router)> {
    let store = match cfg.store_url() {
        Some(url) => crate::storage::open(url).await?,
        None => {
            crate::storage::open_dir_with_cache(cfg.data.clone(), cfg.sled_cache_bytes()).await?
        }
    };
    let cluster = match cfg.queue_url() {
        Some(url) => Some(super::cluster::Cluster::connect(&cfg, url).await?),
        None => None,
    };
    let rt = tokio::runtime::Handle::current();
    let mut app = tokio::task::spawn_blocking(move || App::load(cfg, engine, store, rt))
        .await
        .map_err(|e| crate::Error::Io(std::io::Error::other(e.to_string())))??;
    app.cluster = cluster;
    let app = Arc::new(app);
    if app.cluster.is_some() {
        app.start_replica(Duration::from_secs_f64(app.cfg.reconcile_secs))
            .await;
        app.start_shard_responder().await?;
    }
    let router = router(app.clone());
    Ok((app, router))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tower::ServiceExt;

    async fn through_timeout_layer(handler_503: ApiError) -> Response {
        let app = Router::new()
            .route("/", get(move || async move { handler_503 }))
            .layer(middleware::from_fn_with_state(
                (Duration::from_secs(60), 2u64),
                timeout_mw,
            ));
        app.oneshot(
            Request::builder()
                .uri("/")
                .body(axum::body::Body::empty())
                .unwrap(),
        )
        .await
        .unwrap()
    }

    /// A job checks the request's deadline itself and, under load, can see it pass before the
    /// timeout layer fires; its own 503 `request.timeout` still leaves with `Retry-After` (seen
    /// without it in tests/reliability.rs's abandoned search on a loaded machine). A 503 that
    /// carries one keeps it.
    #[tokio::test]
    async fn every_503_leaves_with_retry_after() {
        let own = ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "request.timeout",
            "the request was abandoned",
        );
        let r = through_timeout_layer(own).await;
        assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(r.headers()[header::RETRY_AFTER], "2");
        let r = through_timeout_layer(ApiError::busy(7)).await;
        assert_eq!(r.headers()[header::RETRY_AFTER], "7");
        let r = through_timeout_layer(ApiError::new(
            StatusCode::NOT_FOUND,
            "route.not_found",
            "no such route",
        ))
        .await;
        assert!(!r.headers().contains_key(header::RETRY_AFTER));
    }

    /// Made-up methods share one label (each would otherwise be a new series).
    #[test]
    fn a_made_up_method_is_labelled_other() {
        use axum::http::Method;
        for m in ["Y0AAAA", "get", "PROPFIND"] {
            assert_eq!(
                method_label(&Method::from_bytes(m.as_bytes()).unwrap()),
                "other"
            );
        }
        assert_eq!(method_label(&Method::DELETE), "DELETE");
    }
}
