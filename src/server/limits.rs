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
