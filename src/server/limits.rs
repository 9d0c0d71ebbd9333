//! The bounded CPU pool: analysis and signature jobs run on blocking threads, at most
//! `workers` at once, with at most `queue_capacity` more waiting; past that a request gets
//! 503 `server.busy` with `Retry-After` at once instead of piling up.

use super::problem::ApiError;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use tokio::sync::Semaphore;

/// Counts of the pool, for `/metrics` and `/v1/index`.
#[derive(Debug, Default)]
pub struct PoolStats {
    /// Jobs waiting for a worker.
    pub queued: AtomicUsize,
    /// Jobs running.
    pub running: AtomicUsize,
}

/// A bounded pool of blocking CPU work.
#[derive(Clone)]
pub struct WorkPool {
    admit: Arc<Semaphore>,
    run: Arc<Semaphore>,
    retry_after: u64,
    /// Live counts.
    pub stats: Arc<PoolStats>,
}

impl WorkPool {
    /// `workers` jobs at once, `queue` more waiting.
    pub fn new(workers: usize, queue: usize, retry_after: u64) -> Self {
        let workers = workers.max(1);
        Self {
            admit: Arc::new(Semaphore::new(workers + queue)),
            run: Arc::new(Semaphore::new(workers)),
            retry_after,
            stats: Arc::new(PoolStats::default()),
        }
    }

    /// Runs `job` on a blocking thread once a worker is free; 503 at once when the queue is
    /// full. If the request is dropped (client gone, timeout, shutdown) while queued, the job
    /// never starts; once started it runs to completion.
    pub async fn run<T, F>(&self, job: F) -> Result<T, ApiError>
    where
        T: Send + 'static,
        F: FnOnce() -> T + Send + 'static,
    {
        let admit = self
            .admit
            .clone()
            .try_acquire_owned()
            .map_err(|_| ApiError::busy(self.retry_after))?;
        self.stats.queued.fetch_add(1, Ordering::Relaxed);
        let queued = QueuedGuard(self.stats.clone());
        let permit = self
            .run
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| ApiError::busy(self.retry_after))?;
        drop(queued);
        let stats = self.stats.clone();
        stats.running.fetch_add(1, Ordering::Relaxed);
        let handle = tokio::task::spawn_blocking(move || {
            let out = job();
            stats.running.fetch_sub(1, Ordering::Relaxed);
            drop(permit);
            drop(admit);
            out
        });
        handle
            .await
            .map_err(|e| ApiError::internal(format!("analysis job failed: {e}")))
    }
}

struct QueuedGuard(Arc<PoolStats>);

impl Drop for QueuedGuard {
    fn drop(&mut self) {
        self.0.queued.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Admission of request bodies: a size check on the announced `Content-Length` before any
/// byte is read, a budget of body bytes held in memory over all requests, and a deadline for
/// reading a body.
///
/// The body is read here, whole, under the budget and the deadline, and handed to the handler
/// as a complete buffer; the budget is released when the response is ready. So the memory held
/// by bodies is bounded by `max_inflight_body_bytes` whatever the number of connections, and a
/// client trickling its body holds a connection for at most `body_read_timeout`. An announced
/// size over the limit is refused with 413 before hyper sends `100 Continue` (it sends it only
/// when the body is first read).
pub struct BodyGate {
    /// Largest body, bytes.
    pub max_body_bytes: usize,
    /// Time to read a whole body.
    pub read_timeout: std::time::Duration,
    /// `Retry-After` seconds of a 503.
    pub retry_after: u64,
    /// Budget in KiB (a semaphore takes at most `u32::MAX` permits at once).
    budget_kib: Arc<Semaphore>,
}

impl BodyGate {
    /// A gate admitting bodies up to `max_body_bytes`, `max_inflight_bytes` in all.
    pub fn new(
        max_body_bytes: usize,
        max_inflight_bytes: usize,
        read_timeout: std::time::Duration,
        retry_after: u64,
    ) -> Self {
        Self {
            max_body_bytes,
            read_timeout,
            retry_after,
            budget_kib: Arc::new(Semaphore::new(kib(max_inflight_bytes) as usize)),
        }
    }

    /// KiB of the budget free now.
    pub fn available_kib(&self) -> usize {
        self.budget_kib.available_permits()
    }
}

fn kib(bytes: usize) -> u32 {
    bytes.div_ceil(1024).min(u32::MAX as usize) as u32
}

/// The body layer (see [`BodyGate`]).
pub async fn admit_body(
    axum::extract::State(gate): axum::extract::State<Arc<BodyGate>>,
    req: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    use axum::http::{header, StatusCode};
    use axum::response::IntoResponse;
    let close = |e: ApiError| {
        let mut r = e.into_response();
        r.headers_mut().insert(
            header::CONNECTION,
            axum::http::HeaderValue::from_static("close"),
        );
        r
    };
    let declared = match req.headers().get(header::CONTENT_LENGTH) {
        None => None,
        Some(v) => match v.to_str().ok().and_then(|s| s.trim().parse::<u64>().ok()) {
            Some(n) => Some(n),
            None => return close(ApiError::invalid("Content-Length is not a number")),
        },
    };
    let chunked = req.headers().contains_key(header::TRANSFER_ENCODING);
    if declared.is_none() && !chunked {
        return next.run(req).await;
    }
    if let Some(n) = declared {
        if n > gate.max_body_bytes as u64 {
            return close(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "limit.bytes",
                format!(
                    "the request body announces {n} bytes; the limit is {} bytes",
                    gate.max_body_bytes
                ),
            ));
        }
        if n == 0 {
            return next.run(req).await;
        }
    }
    let reserve = declared.map_or(gate.max_body_bytes, |n| n as usize);
    let Ok(permit) = gate.budget_kib.clone().try_acquire_many_owned(kib(reserve)) else {
        metrics::counter!("shapeseek_bodies_refused_total").increment(1);
        let mut e = ApiError::busy(gate.retry_after);
        e.detail = "too many request bodies in flight; retry later".into();
        return e.into_response();
    };
    let (parts, body) = req.into_parts();
    let read = tokio::time::timeout(
        gate.read_timeout,
        axum::body::to_bytes(body, gate.max_body_bytes),
    )
    .await;
    let bytes = match read {
        Ok(Ok(b)) => b,
        Ok(Err(e)) => {
            let too_big = std::error::Error::source(&e)
                .is_some_and(|s| s.is::<http_body_util::LengthLimitError>());
            return close(if too_big {
                ApiError::new(
                    StatusCode::PAYLOAD_TOO_LARGE,
                    "limit.bytes",
                    format!("the request body exceeds {} bytes", gate.max_body_bytes),
                )
            } else {
                ApiError::invalid(format!("the request body could not be read: {e}"))
            });
        }
        Err(_) => {
            return close(ApiError::new(
                StatusCode::REQUEST_TIMEOUT,
                "request.body_timeout",
                format!(
                    "the request body was not received within {:.0} s",
                    gate.read_timeout.as_secs_f64()
                ),
            ))
        }
    };
    let resp = next
        .run(axum::extract::Request::from_parts(
            parts,
            axum::body::Body::from(bytes),
        ))
        .await;
    drop(permit);
    resp
}
