//! `shapeseek worker`: pulls ingest jobs from the JetStream work queue, analyses them with
//! the same code as a serving node ([`crate::server::prepared`]), stores the shapes in
//! PostgreSQL and acks (see [`crate::queue`] for the whole protocol).
//!
//! `jobs` analysis slots: a job is pulled only when a slot is free, and holds it from its claim
//! to the end of its analysis; its insert, completion and ack then run beside the next job's
//! analysis (so a slot's core is not idle while PostgreSQL commits — the same overlap a serving
//! node's heavy lane has with its inserts). Each job:
//!
//! 1. claim the job (counts the attempt); unknown (deleted) or no longer pending → ack;
//!    claimed more than `max_deliver` times → dead letter (503 `job.retries_exhausted`), ack:
//!    JetStream's delivery count bounds the deliveries of one message, but a job whose worker
//!    died on it (no nak, no term) is republished by the sweep below as a new message, and
//!    its count starts again;
//! 2. the same bytes stored already → mark done, announce, ack (a redelivery after a worker
//!    died between the insert and the ack ends here);
//! 3. analyse on a blocking thread, stopped at `request_timeout_secs` (the limit a serving
//!    node puts on an upload's analysis; past it a dead letter, 503 `job.timeout`: another
//!    try would take as long), sending "in progress" to JetStream
//!    and marking the job as seen in PostgreSQL every third of `ack_wait` (so the sweep does
//!    not republish a job that is being analysed); free the slot;
//! 4. insert under the job's id (idempotent by content hash), mark done, announce, ack;
//! 5. a refusal of the input (4xx) → dead letter, ack; any other failure → `nak` with a delay
//!    until the delivery count reaches `max_deliver`, then a dead letter (503) and `term`.

use crate::queue::{jobs::JobInput, Bus, Change, DeadLetter, JobState, JobStore};
use crate::server::admission::Cancel;
use crate::server::config::ServerConfig;
use crate::server::prepared::prepare_upload;
use crate::server::problem::ApiError;
use crate::server::state::{Timings, Upload};
use crate::storage::{PgStore, ShapeStore};
use crate::{Error, Result};
use async_nats::jetstream::{AckKind, Message};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// How long one pull request waits for a job before the worker asks again.
const PULL_WAIT: Duration = Duration::from_secs(5);

/// What a worker is told.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// Limits, stored-bytes policy, eigenpairs and queue settings (the serving nodes' own
    /// configuration: the same file and `SHAPESEEK_*` variables).
    pub server: ServerConfig,
    /// Jobs analysed at once by this process.
    pub jobs: usize,
}

struct Worker {
    cfg: Arc<ServerConfig>,
    engine: Arc<crate::index::Engine>,
    limits: crate::mesh::read::ReadLimits,
    store: PgStore,
    jobs: JobStore,
    bus: Bus,
}

/// Runs a worker until SIGINT/SIGTERM (a job being analysed then is not acked: JetStream
/// redelivers it to another worker).
pub async fn run(cfg: WorkerConfig) -> Result<()> {
    let (Some(store_url), Some(queue_url)) = (cfg.server.store_url(), cfg.server.queue_url())
    else {
        return Err(Error::InvalidArgument(
            "worker: --store postgres://… and --queue nats://… are required".into(),
        ));
    };
    let store = PgStore::connect(store_url, Default::default()).await?;
    let bus = Bus::connect(queue_url, cfg.server.queue_options()).await?;
    let engine = cfg.server.engine();
    let limits = crate::mesh::read::ReadLimits {
        max_bytes: cfg.server.max_body_bytes,
        max_vertices: cfg.server.max_vertices,
        max_faces: cfg.server.max_faces,
        ..Default::default()
    };
    let w = Arc::new(Worker {
        jobs: JobStore::new(store.clone()),
        cfg: Arc::new(cfg.server.clone()),
        engine: Arc::new(engine),
        limits,
        store,
        bus,
    });
    let mut tasks = tokio::task::JoinSet::new();
    let slots = Arc::new(Semaphore::new(cfg.jobs.max(1)));
    let puller = w.clone();
    tasks.spawn(async move { puller.pull_loop(slots).await });
    let sweeper = w.clone();
    tasks.spawn(async move { sweeper.sweep_loop().await });
    tracing::info!(jobs = cfg.jobs.max(1), "worker ready");
    tokio::select! {
        _ = crate::server::shutdown_signal() => {
            tracing::info!("shutdown signal received; unacked jobs will be redelivered");
            Ok(())
        }
        r = tasks.join_next() => match r {
            Some(Ok(Err(e))) => Err(e),
            Some(Err(e)) => Err(Error::Queue(format!("worker task failed: {e}"))),
            _ => Ok(()),
        },
    }
}

/// The dead letter of a job tried too often.
fn exhausted(message: String) -> DeadLetter {
    DeadLetter {
        status: 503,
        code: "job.retries_exhausted".into(),
        message,
    }
}

/// How a handled job ended.
enum Outcome {
    Ack,
    Retry(String),
}

impl Worker {
    /// Pulls a job whenever an analysis slot is free and handles it on a task of its own.
    async fn pull_loop(self: Arc<Self>, slots: Arc<Semaphore>) -> Result<()> {
        loop {
            let consumer = match self.bus.worker_consumer().await {
                Ok(c) => c,
                Err(e) => {
                    tracing::warn!(error = %e, "opening the job consumer failed; retrying");
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    continue;
                }
            };
            loop {
                let slot = slots
                    .clone()
                    .acquire_owned()
                    .await
                    .map_err(|e| Error::Queue(format!("analysis slots closed: {e}")))?;
                match Bus::next_job(&consumer, PULL_WAIT).await {
                    Ok(Some(msg)) => {
                        let w = self.clone();
                        tokio::spawn(async move { w.handle(msg, slot).await });
                    }
                    Ok(None) => {}
                    Err(e) => {
                        tracing::warn!(error = %e, "pulling a job failed; reconnecting");
                        break;
                    }
                }
            }
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
    }

    /// Republishes jobs pending far longer than `ack_wait` (a serving node that died after
    /// the commit and before the publish): no committed job is left behind.
    async fn sweep_loop(self: Arc<Self>) -> Result<()> {
        let ack_wait = self.bus.options().ack_wait;
        let stale = (ack_wait * 10).max(Duration::from_secs(60));
        loop {
            tokio::time::sleep(stale / 2).await;
            match self.jobs.stale_pending(stale.as_millis() as u64, 100).await {
                Ok(ids) => {
                    for id in ids {
                        let dedupe = format!("{id}-{}", crate::index::store::now_unix_ms());
                        if self.jobs.touch(&id).await.is_ok() {
                            if let Err(e) = self.bus.publish_job(&id, &dedupe).await {
                                tracing::warn!(error = %e, id, "republishing a stale job");
                            }
                        }
                    }
                }
                Err(e) => tracing::warn!(error = %e, "looking for stale jobs"),
            }
        }
    }

    /// Handles one delivery; `slot` is released once the analysis is over (or not needed).
    async fn handle(&self, msg: Message, slot: OwnedSemaphorePermit) {
        let delivered = msg.info().map(|i| i.delivered).unwrap_or(1);
        let id = String::from_utf8_lossy(&msg.payload).to_string();
        tracing::debug!(id, delivered, "job received");
        let outcome = match self.run_job(&id, &msg, slot).await {
            Ok(o) => o,
            Err(e) => Outcome::Retry(e.to_string()),
        };
        let ack = match outcome {
            Outcome::Ack => msg.ack().await,
            Outcome::Retry(why) if delivered >= self.bus.options().max_deliver => {
                tracing::error!(id, delivered, error = %why, "job failed on every delivery; dead letter");
                let dead = exhausted(format!("failed {delivered} times; last error: {why}"));
                if let Err(e) = self.jobs.fail(&id, &dead).await {
                    tracing::error!(error = %e, id, "could not record the dead letter");
                }
                msg.ack_with(AckKind::Term).await
            }
            Outcome::Retry(why) => {
                tracing::warn!(id, delivered, error = %why, "job failed; will be retried");
                let delay = Duration::from_millis(500 * (1 << delivered.clamp(0, 6)));
                msg.ack_with(AckKind::Nak(Some(delay))).await
            }
        };
        match ack {
            Ok(()) => tracing::debug!(id, "job acked"),
            Err(e) => tracing::warn!(error = %e, id, "ack failed; the job will be redelivered"),
        }
    }

    async fn run_job(
        &self,
        id: &str,
        msg: &Message,
        slot: OwnedSemaphorePermit,
    ) -> Result<Outcome> {
        let t0 = std::time::Instant::now();
        let Some(input) = self.jobs.claim(id).await? else {
            tracing::info!(id, "unknown job (deleted); dropped");
            return Ok(Outcome::Ack);
        };
        if input.state != JobState::Pending {
            return Ok(Outcome::Ack);
        }
        if let Some(existing) = self.store.id_for_hash(&input.sha256).await? {
            self.finish(id, &existing).await?;
            return Ok(Outcome::Ack);
        }
        let max_deliver = self.bus.options().max_deliver;
        if i64::from(input.attempts) > max_deliver {
            tracing::error!(
                id,
                attempts = input.attempts,
                "job claimed on every delivery and never finished; dead letter"
            );
            let dead = exhausted(format!(
                "claimed {} times (more than max_deliver = {max_deliver}) without finishing: its \
                 workers stopped on it",
                input.attempts
            ));
            self.jobs.fail(id, &dead).await?;
            return Ok(Outcome::Ack);
        }
        let Some(bytes) = input.upload.clone() else {
            return Err(crate::index::store::storage_err(format!(
                "pending job {id} has no upload"
            )));
        };
        let t_claim = t0.elapsed();
        let prepared = {
            let work = self.analyse(input, bytes);
            tokio::pin!(work);
            let beat = (self.bus.options().ack_wait / 3).max(Duration::from_millis(100));
            loop {
                tokio::select! {
                    r = &mut work => break r,
                    _ = tokio::time::sleep(beat) => {
                        if let Err(e) = msg.ack_with(AckKind::Progress).await {
                            tracing::warn!(error = %e, id, "progress ack failed");
                        }
                        if let Err(e) = self.jobs.touch(id).await {
                            tracing::warn!(error = %e, id, "marking the job as seen failed");
                        }
                    }
                }
            }
        };
        let prepared = match prepared {
            Ok(p) => p,
            Err(e) if e.status.is_client_error() => {
                let dead = DeadLetter {
                    status: e.status.as_u16(),
                    code: e.code.clone(),
                    message: e.detail.clone(),
                };
                tracing::info!(id, code = %e.code, "input refused; dead letter");
                self.jobs.fail(id, &dead).await?;
                return Ok(Outcome::Ack);
            }
            // The deadline: another try would take as long (a re-upload tries again).
            Err(e) if e.code == "request.timeout" => {
                let dead = DeadLetter {
                    status: 503,
                    code: "job.timeout".into(),
                    message: format!(
                        "the analysis took longer than request_timeout_secs = {} s and was stopped",
                        self.cfg.request_timeout_secs
                    ),
                };
                tracing::warn!(id, "analysis past its deadline; dead letter");
                self.jobs.fail(id, &dead).await?;
                return Ok(Outcome::Ack);
            }
            Err(e) => return Ok(Outcome::Retry(format!("{}: {}", e.code, e.detail))),
        };
        let t_analysis = t0.elapsed();
        drop(slot);
        let (shape, _, _) = prepared.into_new_shape(id);
        let outcome = self.store.insert(shape).await?;
        let t_insert = t0.elapsed();
        self.finish(id, outcome.id()).await?;
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        tracing::debug!(
            id,
            claim_ms = ms(t_claim),
            analysis_ms = ms(t_analysis - t_claim),
            insert_ms = ms(t_insert - t_analysis),
            finish_ms = ms(t0.elapsed() - t_insert),
            "job stored"
        );
        Ok(Outcome::Ack)
    }

    async fn analyse(
        &self,
        input: JobInput,
        bytes: Vec<u8>,
    ) -> std::result::Result<crate::server::prepared::Prepared, ApiError> {
        let up = Upload {
            bytes: bytes.into(),
            hint: input
                .format_hint
                .as_deref()
                .and_then(|f| f.parse::<crate::mesh::Format>().ok()),
            name: input.name.clone(),
            tags: input.tags.clone(),
        };
        let (engine, cfg, limits) = (self.engine.clone(), self.cfg.clone(), self.limits);
        let digest = input.sha256;
        let deadline = Duration::try_from_secs_f64(cfg.request_timeout_secs)
            .ok()
            .and_then(|d| std::time::Instant::now().checked_add(d))
            .map_or_else(Cancel::never, Cancel::until);
        tokio::task::spawn_blocking(move || {
            let mut t = Timings::default();
            prepare_upload(&engine, &cfg, &limits, &up, digest, &mut t, &deadline)
        })
        .await
        .map_err(ApiError::internal)?
    }

    async fn finish(&self, id: &str, shape_id: &str) -> Result<()> {
        self.jobs.complete(id, shape_id).await?;
        if let Err(e) = self
            .bus
            .announce(&Change::Insert {
                id: shape_id.to_string(),
            })
            .await
        {
            // Serving nodes reconcile with the store: a lost announcement only delays them.
            tracing::warn!(error = %e, id, "could not announce the shape");
        }
        Ok(())
    }
}
