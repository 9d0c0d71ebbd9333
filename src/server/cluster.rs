//! A serving node of a cluster (`serve --store postgres://… --queue nats://…`): uploads become
//! jobs of the work queue (see [`crate::queue`]), and the in-memory scan is a replica of the
//! store kept current by the change feed plus a periodic reconciliation.
//!
//! * Ingest: stored already → 200 at once; else the upload is committed as a job and
//!   published. With `?wait=false` the answer is 202 with `/v1/jobs/{id}`; otherwise the node
//!   waits (until the request's deadline) for the job to end, applies the stored shape to its
//!   own scan, and answers 201/200 as a single node does — the shape is then stored and
//!   searchable here. A job that failed answers its dead letter's status and code. When the
//!   deadline passes first, 503 `request.timeout`: the job goes on and a retry of the same
//!   bytes finds it.
//! * Replica: every change announced on the feed is applied from the store (insert: record
//!   and signature read back; delete; calibration: the stored epoch installed). A node that
//!   starts builds its scan from the store ([`App::load`]), subscribes to the feed and
//!   reconciles once before it says it is ready (what changed while it loaded is in its scan
//!   by then); every `reconcile` interval it compares its ids and epoch with the store's and
//!   repairs what a lost message left out, so a node that missed messages converges without
//!   them.
//! * Calibration: computed by one node under the store's lock; a node that finds, under the
//!   lock, a stored epoch newer than its own that still fits the corpus installs it instead of
//!   computing (`src/server/calibrate.rs`), so all nodes rank with the same calibration at the
//!   same epoch.

use super::problem::ApiError;
use super::state::{App, IngestResult, Upload};
use crate::queue::{Bus, Change, Job, JobState, JobStore};
use sha2::{Digest, Sha256};
use std::collections::HashSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The queue side of a serving node.
pub struct Cluster {
    /// The job table.
    pub jobs: JobStore,
    /// NATS.
    pub bus: Bus,
    /// Woken by every insert on the change feed: uploads waiting for their job read it then
    /// (and, should a message be lost, after a growing back-off), not every few milliseconds.
    pub inserted: tokio::sync::Notify,
}

impl Cluster {
    /// Connects to the queue at `url` for a node whose store is PostgreSQL (the job table
    /// lives in the same database; it gets a small pool of its own).
    pub async fn connect(cfg: &super::config::ServerConfig, url: &str) -> crate::Result<Cluster> {
        let Some(url_pg) = cfg.store_url() else {
            return Err(crate::Error::InvalidArgument(
                "a queue needs a PostgreSQL store".into(),
            ));
        };
        let pg = crate::storage::PgStore::connect(
            url_pg,
            crate::storage::postgres::PoolOptions { max_size: 4 },
        )
        .await?;
        Ok(Cluster {
            jobs: JobStore::new(pg),
            bus: Bus::connect(url, cfg.queue_options()).await?,
            inserted: tokio::sync::Notify::new(),
        })
    }
}

/// What a queued ingest answers.
pub enum Queued {
    /// The shape is stored and in this node's scan.
    Stored(Box<IngestResult>),
    /// The job is accepted (`?wait=false`).
    Accepted(Job),
}

/// A waiting ingest reads its job on every insert announced on the change feed, and at the
/// latest after this back-off, which starts at `POLL_MIN` and doubles up to `POLL_MAX`.
const POLL_MIN: Duration = Duration::from_millis(20);
const POLL_MAX: Duration = Duration::from_millis(500);

impl App {
    /// The cluster side, when this node runs with a queue.
    pub fn cluster(&self) -> Option<&Cluster> {
        self.cluster.as_ref()
    }

    /// Ingest through the work queue (see the module docs).
    pub async fn queued_ingest(
        self: &Arc<Self>,
        up: Upload,
        wait: bool,
        deadline: Option<Instant>,
    ) -> Result<Queued, ApiError> {
        let Some(cl) = self.cluster() else {
            return Err(ApiError::internal("queued ingest without a queue"));
        };
        let digest: [u8; 32] = Sha256::digest(&up.bytes).into();
        if let Some(r) = self.existing(&digest).await? {
            self.enter_stored(&r.id).await;
            return Ok(Queued::Stored(Box::new(r)));
        }
        let hint = up.hint.map(|f| f.name().to_string());
        let job = cl
            .jobs
            .enqueue(
                &digest,
                up.name.as_deref(),
                &up.tags,
                hint.as_deref(),
                &up.bytes,
            )
            .await?;
        if job.state == JobState::Pending {
            // A twin's or a retry's republish is dropped by the stream's duplicate window;
            // after it, the workers complete a done job at once.
            let dedupe = if job.created {
                format!("{}-{}", job.id, crate::index::store::now_unix_ms())
            } else {
                job.id.clone()
            };
            cl.bus.publish_job(&job.id, &dedupe).await?;
            tracing::debug!(id = job.id, "job published");
        }
        if !wait {
            let view = cl
                .jobs
                .get(&job.id)
                .await?
                .ok_or_else(|| ApiError::internal(format!("job {} vanished", job.id)))?;
            return Ok(Queued::Accepted(view));
        }
        let until = deadline.unwrap_or_else(|| {
            Instant::now() + Duration::from_secs_f64(self.cfg.request_timeout_secs)
        });
        let mut backoff = POLL_MIN;
        loop {
            // Registered before the job is read, so an insert announced meanwhile still wakes.
            let inserted = cl.inserted.notified();
            tokio::pin!(inserted);
            inserted.as_mut().enable();
            let view = cl.jobs.get(&job.id).await?;
            match view {
                Some(Job {
                    state: JobState::Done,
                    shape_id: Some(sid),
                    ..
                }) => {
                    self.apply_insert(&sid).await?;
                    let rec = self
                        .store
                        .get(&sid)
                        .await?
                        .ok_or_else(|| ApiError::not_found(&sid))?;
                    return Ok(Queued::Stored(Box::new(IngestResult {
                        id: sid,
                        created: job.created,
                        shape: rec,
                        timings: None,
                        reencoded_from_bytes: None,
                    })));
                }
                Some(Job {
                    state: JobState::Failed,
                    error: Some(dead),
                    ..
                }) => {
                    let status = axum::http::StatusCode::from_u16(dead.status)
                        .unwrap_or(axum::http::StatusCode::INTERNAL_SERVER_ERROR);
                    return Err(ApiError::new(status, dead.code, dead.message));
                }
                Some(_) => {}
                // Deleted (with its shape) while we waited.
                None => return Err(ApiError::not_found(&job.id)),
            }
            if Instant::now() >= until {
                return Err(ApiError {
                    retry_after: Some(self.cfg.retry_after_secs),
                    ..ApiError::new(
                        axum::http::StatusCode::SERVICE_UNAVAILABLE,
                        "request.timeout",
                        format!(
                            "job {} is still pending; retry the upload or read /v1/jobs/{}",
                            job.id, job.id
                        ),
                    )
                });
            }
            let left = until.saturating_duration_since(Instant::now());
            tokio::select! {
                _ = &mut inserted => {}
                _ = tokio::time::sleep(backoff.min(left)) => backoff = (backoff * 2).min(POLL_MAX),
            }
        }
    }

    /// Applies a stored shape to this node's scan (no-op when it is there already).
    pub(super) async fn apply_insert(self: &Arc<Self>, id: &str) -> Result<(), ApiError> {
        if self.foreign_change(id).await? {
            return Ok(()); // another shard's (src/server/shard.rs)
        }
        if self.is_left_out(id) {
            return Ok(()); // could not be recomputed since this node started (logged then)
        }
        if self
            .scan
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .position(id)
            .is_some()
        {
            return Ok(());
        }
        let (Some(rec), Some(bytes)) = (self.store.get(id).await?, self.store.signature(id).await?)
        else {
            return Ok(()); // deleted meanwhile
        };
        let app = self.clone();
        let id = id.to_string();
        let first = tokio::task::spawn_blocking(move || -> Option<bool> {
            // A signature stored by a node or worker of another spec (a release with another
            // default during a rolling upgrade) is never mixed into this scan: it is
            // recomputed from the stored original, as at start-up, and stored for this spec.
            let sig = match app.current_signature(&rec, &bytes, &app.engine.spec_key()) {
                Some(s) => s,
                None => {
                    tracing::info!(
                        id = %id,
                        stored = %rec.spec_key,
                        current = %app.engine.spec_key(),
                        "signature of another spec; recomputing"
                    );
                    // A shape that cannot be recomputed is left out of this scan (logged, and
                    // not tried again until the next start) without holding up the others; a
                    // store that fails is logged here and tried again by the next
                    // reconciliation.
                    match app.admission.on_heavy_pool(|| app.recompute(rec.clone())) {
                        Ok(Some(s)) => s,
                        Ok(None) => return None, // left out (logged by `recompute`)
                        Err(e) => {
                            tracing::error!(id = %id, error = %e, "could not recompute; skipped");
                            return None;
                        }
                    }
                }
            };
            // Not when its delete was applied since it was read (`src/server/writes.rs`).
            let mut first = false;
            let entered = app.enter_scan(&id, |scan| {
                first = scan.calibration().is_none();
                scan.insert(&app.engine, &id, &rec.name, &rec.tags, &sig, 1);
            });
            entered.then_some(first)
        })
        .await
        .map_err(ApiError::internal)?;
        let Some(first) = first else {
            return Ok(());
        };
        if first {
            // A provisional calibration on one shape: replaced by the store's epoch (or a new
            // one committed under the lock) so every node ranks with the same.
            self.clone().calibrate_in_background(true);
        } else {
            self.after_change();
        }
        Ok(())
    }

    /// Applies a deletion to this node's scan.
    async fn apply_delete(self: &Arc<Self>, id: &str) -> Result<(), ApiError> {
        if self.foreign_change(id).await? {
            return Ok(());
        }
        let (_, removed) = self.remove_shape(id, false).await?;
        if removed {
            self.after_change();
        }
        Ok(())
    }

    /// Announces a committed change (logged, not fatal: reconciliation repairs a lost one).
    pub(super) async fn announce(&self, change: Change) {
        if let Some(cl) = self.cluster() {
            if let Err(e) = cl.bus.announce(&change).await {
                tracing::warn!(error = %e, ?change, "could not announce a change");
            }
        }
    }

    /// Installs the stored calibration when its epoch is newer than this node's.
    pub(super) async fn adopt_stored_calibration(self: &Arc<Self>) -> Result<(), ApiError> {
        let Some(stored) = self.store.calibration().await? else {
            return Ok(());
        };
        if stored.epoch <= self.epoch() {
            return Ok(());
        }
        // A calibration committed by a node of another spec (its channels, windows or
        // options) cannot encode this node's signatures: it keeps its own until one of its
        // spec is committed.
        let Some(cal) = self.engine.stored_calibration(&stored.json) else {
            tracing::warn!(
                epoch = stored.epoch,
                own = self.epoch(),
                "the stored calibration was made for another spec; not installed"
            );
            return Ok(());
        };
        // One install at a time: concurrent callers (searches that met a shard at a newer
        // epoch, the change feed, the reconciliation) would each re-encode every held shape. A
        // caller that waited finds the epoch installed; one that stops waiting (a deadline)
        // holds no thread meanwhile. The install owns the guard to its end.
        let one = self.adopting.clone().lock_owned().await;
        if stored.epoch <= self.epoch() {
            return Ok(());
        }
        let app = self.clone();
        tokio::task::spawn_blocking(move || {
            let _one = one;
            app.admission.on_heavy_pool(|| {
                app.install(Arc::new(cal), stored.calibrated_on as usize);
            })
        })
        .await
        .map_err(ApiError::internal)?;
        Ok(())
    }

    /// [`App::adopt_stored_calibration`] waited for until `until` at the latest (a request's
    /// deadline): the install goes on in the background when the deadline comes first.
    pub(super) async fn adopt_until(self: &Arc<Self>, until: Instant) -> Result<(), ApiError> {
        match tokio::time::timeout_at(until.into(), self.adopt_stored_calibration()).await {
            Ok(r) => r,
            Err(_) => Ok(()),
        }
    }

    /// Brings the scan to the store's ids and epoch.
    ///
    /// The scan is read before the store is listed. A shape enters the scan only after it is
    /// stored, and a deleted id is never stored again, so a shape held then and absent from the
    /// later listing was deleted, and a stored shape missing from the scan is inserted (a
    /// no-op when it entered meanwhile). Read the other way round, a shape stored during the
    /// listing and entered into the scan before the read (an ingest on this node, right before
    /// its 201) looked deleted, and was taken out of the scan until the change feed's insert or
    /// the next reconciliation.
    pub(super) async fn reconcile(self: &Arc<Self>) -> Result<(), ApiError> {
        let held: HashSet<String> = self
            .scan
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .ids()
            .into_iter()
            .collect();
        let mut stored: HashSet<String> = HashSet::new();
        let mut after: Option<String> = None;
        loop {
            let page = self.store.list(after.as_deref(), None, 1000).await?;
            after = page.records.last().map(|r| r.id.clone());
            stored.extend(page.records.into_iter().map(|r| r.id));
            if !page.more {
                break;
            }
        }
        if let Some(sh) = self.shard() {
            sh.set_total(stored.len());
            stored.retain(|id| sh.spec.holds(id));
        }
        let mut missing: Vec<&String> = stored.difference(&held).collect();
        missing.sort();
        for id in missing {
            self.apply_insert(id).await?;
        }
        for id in held.difference(&stored) {
            self.apply_delete(id).await?;
        }
        self.adopt_stored_calibration().await?;
        // A recalibration that yielded to another node's lock is tried again here.
        if self.needs_recalibration() {
            self.clone().calibrate_in_background(false);
        }
        Ok(())
    }

    /// Follows the change feed and reconciles every `every`. It subscribes first and
    /// reconciles once before it returns, so that a change made while the node loaded (before
    /// it listened) is in the scan before the node says it is ready (`router::start_with`).
    pub(super) async fn start_replica(self: &Arc<Self>, every: Duration) {
        let Some(cl) = self.cluster() else {
            return;
        };
        let mut sub = match cl.bus.changes().await {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::error!(error = %e, "no change feed; reconciling only");
                None
            }
        };
        if let Err(e) = self.reconcile().await {
            tracing::warn!(error = %e.detail, "the first reconciliation failed; tried again every interval");
        }
        let app = self.clone();
        tokio::spawn(async move {
            use futures_util::StreamExt;
            let mut tick = tokio::time::interval_at(tokio::time::Instant::now() + every, every);
            loop {
                let msg = async {
                    match sub.as_mut() {
                        Some(s) => s.next().await,
                        None => std::future::pending().await,
                    }
                };
                tokio::select! {
                    m = msg => {
                        let Some(m) = m else {
                            tracing::warn!("change feed ended; reconciling only");
                            sub = None;
                            continue;
                        };
                        let res = match serde_json::from_slice::<Change>(&m.payload) {
                            Ok(Change::Insert { id }) => {
                                // The job is marked done before its shape is announced.
                                if let Some(cl) = app.cluster() {
                                    cl.inserted.notify_waiters();
                                }
                                app.apply_insert(&id).await
                            }
                            Ok(Change::Delete { id }) => app.apply_delete(&id).await,
                            Ok(Change::Calibration { .. }) => app.adopt_stored_calibration().await,
                            Err(e) => {
                                tracing::warn!(error = %e, "unreadable change message");
                                Ok(())
                            }
                        };
                        if let Err(e) = res {
                            tracing::warn!(error = %e.detail, "applying a change failed; the next reconciliation repairs it");
                        }
                    }
                    _ = tick.tick() => {
                        if let Err(e) = app.reconcile().await {
                            tracing::warn!(error = %e.detail, "reconciliation failed");
                        }
                    }
                }
            }
        });
    }
}
