//! The server's state and its non-HTTP operations: loading, ingest, delete, search,
//! recalibration. Handlers only translate HTTP to these calls.

use super::admission::{Admission, Cancel, Cost};
use super::config::ServerConfig;
use super::env::ServerEnv;
use super::metrics as m;
use super::ms;
use super::problem::ApiError;
use crate::index::{Engine, ScanIndex, ShapeRecord};
use crate::mesh::read::{read_mesh, Format, ReadLimits};
use crate::ranking::QuerySpec;
use crate::rerank::GwPayload;
use crate::search::corpus::Encoded;
use crate::search::{Entry, Query, Stage, StageRequest};
use crate::signature::Signature;
use crate::storage::{InsertOutcome, ShapeStore};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, RwLock};
use std::time::Instant;

/// Shared state of a running server.
pub struct App {
    /// Configuration.
    pub cfg: ServerConfig,
    /// The store (sled index or PostgreSQL, see [`crate::storage`]).
    pub store: Arc<dyn ShapeStore>,
    /// The runtime the store's futures run on (see [`App::block`]).
    pub(super) rt: tokio::runtime::Handle,
    /// Signatures and scoring.
    pub engine: Arc<Engine>,
    /// The in-memory scan structure.
    pub scan: Arc<RwLock<ScanIndex>>,
    /// Admission of CPU work (cost model, two lanes, cancellation).
    pub admission: Admission,
    /// Mesh limits applied to uploads.
    pub limits: ReadLimits,
    /// False until loaded, and again once shutting down.
    pub ready: AtomicBool,
    pub(super) recalibrating: AtomicBool,
    /// Held while a stored calibration is installed ([`App::adopt_stored_calibration`]): one
    /// install at a time, the others then find it done.
    pub(super) adopting: Arc<tokio::sync::Mutex<()>>,
    /// Held while a stored shape enters the scan, and while a delete removes one from the
    /// store and then from the scan; it holds the tombstones of shapes deleted before they
    /// entered (`src/server/writes.rs`).
    pub(super) writes: Arc<tokio::sync::Mutex<super::writes::Tombstones>>,
    /// Metrics handle.
    pub metrics: Option<metrics_exporter_prometheus::PrometheusHandle>,
    /// The work queue and change feed, when this node is one of a cluster.
    pub(super) cluster: Option<super::cluster::Cluster>,
    /// The shard this node holds (`--shard S/N`); `None`: the whole corpus.
    pub(super) shard: Option<super::shard::Sharding>,
    /// Format conversions of stored originals ([`App::convert_original`]) running at once:
    /// `workers` permits, apart from the admission lanes.
    pub(super) conversions: Arc<tokio::sync::Semaphore>,
    /// Download bytes held at once (`max_inflight_response_bytes`).
    pub(super) downloads: super::limits::ResponseBudget,
    /// Stored shapes whose signature could not be recomputed for this node's spec
    /// ([`App::recompute`]): left out of the scan, and not tried again until the next start
    /// (a cluster node's reconciliation would otherwise analyse each again every few seconds).
    pub(super) left_out: Arc<std::sync::Mutex<std::collections::HashSet<String>>>,
}

/// Per-stage milliseconds of one ingest or query analysis.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Timings {
    /// Parsing the upload.
    pub read_ms: f64,
    /// Cleaning and normalisation.
    pub prepare_ms: f64,
    /// Laplacian assembly.
    pub laplacian_ms: f64,
    /// Factorisation.
    pub factorization_ms: f64,
    /// Eigen-iteration.
    pub eigensolve_ms: f64,
    /// Signature computation.
    pub signature_ms: f64,
    /// Re-ranking payload (farthest-point samples and their diffusion distances).
    pub payload_ms: f64,
    /// Transaction + flush (ingest only).
    pub store_ms: f64,
    /// Everything, including waiting for a worker.
    pub total_ms: f64,
}

/// An upload to ingest.
pub struct Upload {
    /// The original bytes.
    pub bytes: axum::body::Bytes,
    /// Format hint (Content-Type, `?format=`, file extension).
    pub hint: Option<Format>,
    /// Display name, if given.
    pub name: Option<String>,
    /// Tags.
    pub tags: Vec<String>,
}

/// Result of an ingest.
#[derive(Debug, Serialize)]
pub struct IngestResult {
    /// Shape id.
    pub id: String,
    /// False when the same bytes were already stored (nothing was computed).
    pub created: bool,
    /// The stored record (with its preparation report).
    pub shape: ShapeRecord,
    /// Stage timings (absent when `created` is false).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timings: Option<Timings>,
    /// Size of the upload when it was far larger than its geometry and the stored original is
    /// its canonical re-encoding (`shape.bytes`); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reencoded_from_bytes: Option<u64>,
}

pub use crate::search::stage::{MAX_GW_SHORTLIST, MAX_RECIPROCAL_SHORTLIST};

/// One rerank stage of a search request (see [`StageRequest`]).
pub type RerankStage = StageRequest;

/// A search candidate between stages: its id and name (`at` of the entry is its position in
/// the scan while it is locked).
pub(super) struct Hitting {
    pub(super) id: String,
    pub(super) name: String,
}

/// A query analysed for search-by-example: signature, payload (when a stage needs it), timings.
pub type QueryAnalysis = (Signature, Option<GwPayload>, Timings);

/// The search options shared by all ways to give the query.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SearchOptions {
    /// Stored shape to search with (JSON requests only).
    #[serde(default)]
    pub id: Option<String>,
    /// Number of hits (default 10).
    #[serde(default)]
    pub top_k: Option<usize>,
    /// Query spec overrides merged over the index's default (`channels`, `dissimilarity`,
    /// `aggregation`, ...).
    #[serde(default)]
    pub spec: Option<serde_json::Value>,
    /// Only shapes having all of these tags.
    #[serde(default)]
    pub tags: Vec<String>,
    /// Rerank stages applied in order after the scan. Absent: the index's default stages (the
    /// product default re-ranks the top `max(200, top_k)` by reciprocal neighbourhoods); `[]`:
    /// the scan's ranking alone.
    #[serde(default)]
    pub rerank: Option<Vec<RerankStage>>,
    /// Keep the query shape itself among the hits (search by id; default false).
    #[serde(default)]
    pub include_self: bool,
}

/// Hits of a search that does not say `top_k` (clamped to the server's `max_top_k`).
pub const DEFAULT_TOP_K: usize = 10;

/// One search hit.
#[derive(Debug, Clone, Serialize)]
pub struct Hit {
    /// Shape id.
    pub id: String,
    /// Display name.
    pub name: String,
    /// Score of the last stage (lower = more similar).
    pub score: f64,
    /// 1-based rank.
    pub rank: usize,
    /// Calibration epoch the scores were computed under.
    pub calibration_epoch: u64,
    /// Score of each stage that scored this hit (scan first).
    pub stage_scores: Vec<f64>,
}

/// A search answer.
#[derive(Debug, Serialize)]
pub struct SearchResult {
    /// Hits, best first.
    pub hits: Vec<Hit>,
    /// Calibration epoch used.
    pub calibration_epoch: u64,
    /// Shapes considered by the scan (after tag filters).
    pub candidates: usize,
    /// The effective query spec of the scan.
    pub spec: serde_json::Value,
    /// Stage names in order (`scan`, then the rerank stages).
    pub stages: Vec<String>,
    /// Milliseconds: query analysis (uploads), scan, rerank, total.
    pub timings: SearchTimings,
}

/// Search timings.
#[derive(Debug, Default, Serialize)]
pub struct SearchTimings {
    /// Analysis and signature of an uploaded query.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub analysis: Option<Timings>,
    /// The full scan.
    pub scan_ms: f64,
    /// All rerank stages.
    pub rerank_ms: f64,
    /// End to end.
    pub total_ms: f64,
}

/// Valid tags: 1..=64 characters, at most 32 of them.
pub fn validate_tags(tags: &[String]) -> Result<(), ApiError> {
    if tags.len() > 32 {
        return Err(ApiError::invalid("at most 32 tags"));
    }
    for t in tags {
        if t.is_empty() || t.chars().count() > 64 || t.chars().any(|c| c.is_control()) {
            return Err(ApiError::invalid(format!(
                "tag {t:?}: 1 to 64 characters, no control characters"
            )));
        }
    }
    Ok(())
}

impl App {
    /// [`super::prepared::analyze_and_sign`] with this server's engine.
    fn analyze_and_sign(
        &self,
        mesh: &crate::mesh::Mesh,
        t: &mut Timings,
        with_payload: bool,
        cancel: &Cancel,
    ) -> Result<(crate::spectrum::Analysis, Signature, Option<GwPayload>), ApiError> {
        super::prepared::analyze_and_sign(&self.engine, mesh, t, with_payload, cancel)
    }

    /// Runs a store call from a blocking thread (admission work, loading, recalibration) on
    /// the server's runtime and waits for it, the sled backend's work inline on this thread
    /// ([`crate::storage::on_blocking_thread`]). Never called on an async worker thread.
    pub(super) fn block<T, E>(
        &self,
        fut: impl std::future::Future<Output = std::result::Result<T, E>>,
    ) -> std::result::Result<T, E> {
        crate::storage::on_blocking_thread(|| self.rt.block_on(fut))
    }

    /// Sets the index gauges.
    pub fn update_gauges(&self) {
        let (n, epoch) = {
            let s = self.scan.read().unwrap_or_else(|p| p.into_inner());
            (
                s.len(),
                s.calibration()
                    .map(|c| self.engine.calibration_epoch(c))
                    .unwrap_or(0),
            )
        };
        metrics::gauge!("shapeseek_index_shapes").set(n as f64);
        metrics::gauge!("shapeseek_calibration_epoch").set(epoch as f64);
        // Callable from any thread: the size is read by a task of its own.
        let store = self.store.clone();
        self.rt.spawn(async move {
            if let Ok(b) = store.size_on_disk().await {
                metrics::gauge!("shapeseek_index_bytes").set(b as f64);
            }
        });
    }

    /// The stored re-ranking payload of a shape (`None` when it has none).
    async fn read_payload(&self, id: &str) -> Result<Option<GwPayload>, ApiError> {
        match self.store.payload(id).await.map_err(ApiError::from)? {
            None => Ok(None),
            Some(b) => decode_payload(id, &b).map(Some),
        }
    }

    /// [`App::read_payload`] from a blocking thread.
    pub(super) fn stored_payload(&self, id: &str) -> Result<Option<GwPayload>, ApiError> {
        self.block(self.read_payload(id))
    }

    /// The stored payload of the query `id`, for a search whose stage compares payloads: 404
    /// when the shape is gone (a delete that has reached the store and not yet the scan),
    /// 409 `shape.no_payload` when it is stored without one.
    pub(super) async fn query_payload(&self, id: &str) -> Result<GwPayload, ApiError> {
        match self.read_payload(id).await? {
            Some(p) => Ok(p),
            None if self.store.get(id).await.map_err(ApiError::from)?.is_none() => {
                Err(ApiError::not_found(id))
            }
            None => Err(no_payload(id)),
        }
    }

    /// Current calibration epoch (0 = none yet).
    pub fn epoch(&self) -> u64 {
        let s = self.scan.read().unwrap_or_else(|p| p.into_inner());
        s.calibration()
            .map(|c| self.engine.calibration_epoch(c))
            .unwrap_or(0)
    }

    /// Ingests an upload: idempotent by SHA-256 of the bytes.
    pub async fn ingest(self: &Arc<Self>, up: Upload) -> Result<IngestResult, ApiError> {
        self.ingest_until(up, None).await
    }

    /// Ingests an upload whose request must answer by `deadline`: admitted as heavy work
    /// costing [`Cost::analysis`] of its size; stops (nothing stored) once abandoned.
    pub async fn ingest_until(
        self: &Arc<Self>,
        up: Upload,
        deadline: Option<Instant>,
    ) -> Result<IngestResult, ApiError> {
        let t0 = Instant::now();
        let digest: [u8; 32] = Sha256::digest(&up.bytes).into();
        if let Some(r) = self.existing(&digest).await? {
            self.enter_stored(&r.id).await;
            return Ok(r);
        }
        let app = self.clone();
        let cost = Cost::analysis(up.bytes.len());
        let res = self
            .admission
            .run(cost, deadline, move |c| {
                app.ingest_blocking(up, digest, t0, c)
            })
            .await?;
        if res.created {
            self.announce(crate::queue::Change::Insert { id: res.id.clone() })
                .await;
            self.after_change();
        }
        Ok(res)
    }

    /// The stored shape with this content hash, as an ingest answer (`created: false`).
    pub(super) async fn existing(
        &self,
        digest: &[u8; 32],
    ) -> Result<Option<IngestResult>, ApiError> {
        if let Some(id) = self
            .store
            .id_for_hash(digest)
            .await
            .map_err(ApiError::from)?
        {
            if let Some(rec) = self.store.get(&id).await.map_err(ApiError::from)? {
                return Ok(Some(IngestResult {
                    id,
                    created: false,
                    shape: rec,
                    timings: None,
                    reencoded_from_bytes: None,
                }));
            }
        }
        Ok(None)
    }

    /// A shape found stored by an upload of the same bytes, entered into the scan when it is
    /// not there: an insert can store a shape and still answer an error (a flush that failed
    /// after the commit, a commit whose acknowledgement was lost), and that ingest answered 500
    /// with its shape left out of the scan. A look-up when it is there. Called from async code
    /// only, never from a thread of the heavy pool (a recomputation would wait for that pool).
    /// Best effort: the answer is the stored shape's either way, a failure is logged.
    pub(super) async fn enter_stored(self: &Arc<Self>, id: &str) {
        if let Err(e) = self.apply_insert(id).await {
            tracing::warn!(id, error = %e.detail, "a stored shape could not enter the scan");
        }
    }

    fn ingest_blocking(
        &self,
        up: Upload,
        digest: [u8; 32],
        t0: Instant,
        cancel: &Cancel,
    ) -> Result<IngestResult, ApiError> {
        // A twin upload may have been stored while this one waited.
        if let Some(r) = self.block(self.existing(&digest))? {
            return Ok(r);
        }
        let mut t = Timings::default();
        let prepared = super::prepared::prepare_upload(
            &self.engine,
            &self.cfg,
            &self.limits,
            &up,
            digest,
            &mut t,
            cancel,
        )?;
        // The last point where an abandoned ingest stops: past it the shape is stored.
        cancel.check()?;
        let t3 = Instant::now();
        let id = self.block(self.store.new_id()).map_err(ApiError::from)?;
        let (shape, sig, reencoded_from) = prepared.into_new_shape(&id);
        let record = shape.record.clone();
        let outcome = self
            .block(self.store.insert(shape))
            .map_err(ApiError::from)?;
        let id = match outcome {
            InsertOutcome::AlreadyPresent(id) => {
                return self
                    .block(self.existing(&digest))?
                    .ok_or_else(|| ApiError::internal(format!("shape {id} vanished")));
            }
            InsertOutcome::Inserted(id) => id,
        };
        // Not when a delete of this id reached the store since the insert (ids are
        // sequential and can be guessed).
        self.enter_scan(&id, |scan| {
            scan.insert(&self.engine, &id, &record.name, &record.tags, &sig, 1)
        });
        t.store_ms = ms(t3);
        t.total_ms = ms(t0);
        for (stage, v) in [
            ("read", t.read_ms),
            ("prepare", t.prepare_ms),
            ("laplacian", t.laplacian_ms),
            ("factorization", t.factorization_ms),
            ("eigensolve", t.eigensolve_ms),
            ("signature", t.signature_ms),
            ("payload", t.payload_ms),
            ("store", t.store_ms),
        ] {
            m::stage(stage, v);
        }
        Ok(IngestResult {
            id,
            created: true,
            shape: record,
            timings: Some(t),
            reencoded_from_bytes: reencoded_from,
        })
    }

    /// Deletes a shape. False when absent.
    pub async fn delete(self: &Arc<Self>, id: String) -> Result<bool, ApiError> {
        let (removed, _) = self.remove_shape(&id, true).await?;
        if removed {
            self.announce(crate::queue::Change::Delete { id }).await;
            self.after_change();
        }
        Ok(removed)
    }

    /// True when a search with `opts` runs a stage that compares re-ranking payloads (the
    /// query's must then be computed with its signature).
    pub fn search_needs_payload(&self, opts: &SearchOptions) -> bool {
        match &opts.rerank {
            Some(list) => list.iter().any(StageRequest::needs_payload),
            None => self
                .engine
                .default_stages()
                .iter()
                .any(|s| s.payload_spec().is_some()),
        }
    }

    /// The effective query spec: `overrides` (a JSON object) merged over `base`.
    pub fn query_spec(
        &self,
        base: &serde_json::Value,
        overrides: Option<&serde_json::Value>,
    ) -> Result<(QuerySpec, serde_json::Value), ApiError> {
        let mut v = base.clone();
        if let Some(o) = overrides {
            let serde_json::Value::Object(o) = o else {
                return Err(ApiError::invalid("spec must be a JSON object"));
            };
            let serde_json::Value::Object(b) = &mut v else {
                return Err(ApiError::internal("default query spec is not an object"));
            };
            for (k, val) in o {
                if !b.contains_key(k) {
                    return Err(ApiError::invalid(format!(
                        "spec: unknown field {k:?} (known: {:?})",
                        b.keys().collect::<Vec<_>>()
                    )));
                }
                b.insert(k.clone(), val.clone());
            }
        }
        let q: QuerySpec = serde_json::from_value(v.clone())
            .map_err(|e| ApiError::invalid(format!("spec: {e}")))?;
        self.engine
            .validate_query(&q)
            .map_err(|e| ApiError::invalid(format!("spec: {e}")))?;
        Ok((q, v))
    }

    /// The stages of a search: the request's, validated, or the index's defaults (a default
    /// reciprocal stage re-ranks at least `top_k`).
    fn stages(
        &self,
        opts: &SearchOptions,
        top_k: usize,
        spec_json: &serde_json::Value,
    ) -> Result<Vec<Stage>, ApiError> {
        match &opts.rerank {
            Some(list) => {
                if list.len() > 8 {
                    return Err(ApiError::invalid("at most 8 rerank stages"));
                }
                let spec = |o: Option<&serde_json::Value>| {
                    self.query_spec(spec_json, o)
                        .map(|(q, _)| q)
                        .map_err(|e| crate::Error::InvalidArgument(e.detail))
                };
                list.iter()
                    .map(|st| {
                        st.resolve(top_k, self.cfg.max_top_k, &spec)
                            .map_err(|e| ApiError::invalid(invalid_detail(e)))
                    })
                    .collect()
            }
            None => Ok(self
                .engine
                .default_stages()
                .into_iter()
                .map(|st| match st {
                    Stage::Reciprocal(mut r) => {
                        r.shortlist = r.shortlist.max(top_k);
                        Stage::Reciprocal(r)
                    }
                    other => other,
                })
                .collect()),
        }
    }

    /// The stored original of `rec`, read as a mesh and written again as `to` (binary PLY,
    /// binary STL, glTF with an embedded buffer: the writers' defaults): the surface every
    /// analysis of the shape starts from, triangulated, every glTF primitive in one mesh, in a
    /// format the client chose.
    ///
    /// Conversions have a gate of their own, `workers` at once, and wait their turn until the
    /// request's deadline (then 503 `request.timeout`); the original is read from the store
    /// once its turn has come, so waiting requests hold no mesh. An abandoned conversion (the
    /// deadline passed, the client left) stops before it parses or before it writes. They
    /// stay out of the admission lanes: a page that loads two dozen views at once must not
    /// fill the queue that searches and ingests are refused by (a review found a scan-only
    /// search refused with 503 while 24 conversions queued in the cheap lane). A running
    /// conversion is counted by admission as work outside the lanes, so a heavy job does not
    /// borrow the cheap lane's cores meanwhile; each one written is counted in
    /// `shapeseek_conversions_total`. The output is answered under the download budget
    /// (`limits::ResponseBudget`), its room reserved while the conversion still holds its turn:
    /// so outputs waiting for room are at most as many as conversions run at once.
    pub async fn convert_original(
        self: &Arc<Self>,
        rec: &ShapeRecord,
        to: Format,
        deadline: Option<Instant>,
    ) -> Result<axum::body::Body, ApiError> {
        let timeout = || ApiError {
            retry_after: Some(self.cfg.retry_after_secs),
            ..ApiError::new(
                axum::http::StatusCode::SERVICE_UNAVAILABLE,
                "request.timeout",
                "the conversion did not get its turn before the request's deadline",
            )
        };
        let permit = match deadline {
            Some(d) => tokio::time::timeout_at(d.into(), self.conversions.clone().acquire_owned())
                .await
                .map_err(|_| timeout())?,
            None => self.conversions.clone().acquire_owned().await,
        }
        .map_err(ApiError::internal)?;
        let orig = self
            .store
            .mesh(&rec.id)
            .await
            .map_err(ApiError::from)?
            .ok_or_else(|| ApiError::not_found(&rec.id))?;
        // Abandoned (the deadline passed, or the client left and the request's future was
        // dropped): the conversion stops before it reads or before it writes.
        let (cancel, guard) = Cancel::for_request(deadline);
        let format = rec.format.clone();
        let counted = self.admission.outside_work();
        // The turn lives with the blocking work (an abandoned request does not free it while
        // the work runs on) and comes back with its output.
        let out = tokio::task::spawn_blocking(move || {
            let permit = permit;
            let _counted = counted;
            cancel.check()?;
            let mesh = super::load::read_original(&format, &orig).map_err(ApiError::internal)?;
            drop(orig);
            cancel.check()?;
            let mut out = Vec::new();
            crate::mesh::write::write_mesh(&mesh, to, &mut out).map_err(ApiError::internal)?;
            metrics::counter!("shapeseek_conversions_total").increment(1);
            Ok::<_, ApiError>((out, permit))
        })
        .await
        .map_err(ApiError::internal)?;
        guard.done();
        let (out, turn) = out?;
        let room = self.downloads.reserve(out.len()).await;
        drop(turn);
        Ok(room.body(out))
    }

    /// Analyses an uploaded query mesh on the pool (nothing is stored); the re-ranking
    /// payload is computed when `with_payload`.
    pub async fn analyze_query(
        self: &Arc<Self>,
        up: Upload,
        with_payload: bool,
        deadline: Option<Instant>,
    ) -> Result<QueryAnalysis, ApiError> {
        let app = self.clone();
        let t0 = Instant::now();
        self.admission
            .run(
                Cost::analysis(up.bytes.len()),
                deadline,
                move |c| -> Result<QueryAnalysis, ApiError> {
                    let mut t = Timings::default();
                    let t1 = Instant::now();
                    let mesh = read_mesh(&up.bytes, up.hint, &app.limits)?;
                    t.read_ms = ms(t1);
                    let (_, sig, payload) = app.analyze_and_sign(&mesh, &mut t, with_payload, c)?;
                    t.total_ms = ms(t0);
                    Ok((sig, payload, t))
                },
            )
            .await
    }

    /// The validated options of a search: `top_k`, the query spec (and its JSON form) and the
    /// stages. Cheap: a search by upload calls it before analysing the upload, so options that
    /// cannot be served cost no analysis.
    pub fn resolve_options(
        &self,
        opts: &SearchOptions,
    ) -> Result<(usize, QuerySpec, serde_json::Value, Vec<Stage>), ApiError> {
        // The default never exceeds the configured limit (a server with `max_top_k` below 10
        // answers its first `max_top_k` hits instead of refusing every search without `top_k`).
        let top_k = opts.top_k.unwrap_or(DEFAULT_TOP_K.min(self.cfg.max_top_k));
        if top_k == 0 || top_k > self.cfg.max_top_k {
            return Err(ApiError::invalid(format!(
                "top_k must be in 1..={}",
                self.cfg.max_top_k
            )));
        }
        validate_tags(&opts.tags)?;
        let base = serde_json::to_value(self.engine.default_query()).map_err(ApiError::internal)?;
        let (spec, spec_json) = self.query_spec(&base, opts.spec.as_ref())?;
        let stages = self.stages(opts, top_k, &spec_json)?;
        Ok((top_k, spec, spec_json, stages))
    }

    /// What both search paths (this process's index, or the shards') settle before the scan:
    /// the validated options and stages, the query as uploaded (a search by stored id has
    /// none), and what the answer reports besides its hits.
    pub(super) fn plan_search(
        &self,
        opts: &SearchOptions,
        query: Option<QueryAnalysis>,
    ) -> Result<SearchPlan, ApiError> {
        let t0 = Instant::now();
        let (top_k, spec, spec_json, stages) = self.resolve_options(opts)?;
        let (query_sig, upload_payload, analysis) = match query {
            Some((s, p, t)) => (Some(s), p, Some(t)),
            None => (None, None, None),
        };
        if query_sig.is_none() && opts.id.is_none() {
            return Err(ApiError::invalid(
                "give a stored shape id, or upload a mesh to search by example",
            ));
        }
        let stage_names = std::iter::once("scan".to_string())
            .chain(stages.iter().map(|p| p.name().to_string()))
            .collect();
        let needs_payload = stages.iter().any(|p| p.payload_spec().is_some());
        let first_k = stages
            .iter()
            .map(Stage::shortlist)
            .max()
            .unwrap_or(0)
            .max(top_k);
        Ok(SearchPlan {
            top_k,
            first_k,
            spec,
            stages,
            needs_payload,
            query_sig,
            upload_payload,
            report: SearchReport {
                spec_json,
                stage_names,
                analysis,
                t0,
            },
        })
    }

    /// Searches with a stored shape (`id`) or an analysed upload (`query_sig`).
    pub async fn search(
        self: &Arc<Self>,
        opts: SearchOptions,
        query_sig: Option<QueryAnalysis>,
        deadline: Option<Instant>,
    ) -> Result<SearchResult, ApiError> {
        let plan = self.plan_search(&opts, query_sig)?;
        if self.shard.is_some() {
            return self.sharded_search(opts, plan, deadline).await;
        }
        let SearchPlan {
            top_k,
            first_k,
            spec,
            stages,
            needs_payload,
            query_sig,
            upload_payload,
            report,
        } = plan;
        let app = self.clone();
        let n = self.scan.read().unwrap_or_else(|p| p.into_inner()).len();
        let cost = Cost::search(n, &stages);
        let (hits, epoch, candidates, scan_ms, rerank_ms) = self
            .admission
            .run(cost, deadline, move |cancel| -> Result<_, ApiError> {
                let guard = app.scan.read().unwrap_or_else(|p| p.into_inner());
                let s = &*guard;
                let Some(cal) = s.calibration().cloned() else {
                    if let Some(id) = &opts.id {
                        return Err(ApiError::not_found(id));
                    }
                    return Ok((Vec::new(), 0, 0, 0.0, 0.0));
                };
                let epoch = app.engine.calibration_epoch(&cal);
                let (query, self_at): (Encoded, Option<usize>) = match (&query_sig, &opts.id) {
                    (Some(sig), _) => (
                        Encoded::from_signature(sig, &cal, s.corpus().layout()),
                        None,
                    ),
                    (None, Some(id)) => {
                        let at = s.position(id).ok_or_else(|| ApiError::not_found(id))?;
                        (s.corpus().encoded(at), Some(at))
                    }
                    (None, None) => return Err(ApiError::internal("a search without a query")),
                };
                let query_payload = match (&upload_payload, &opts.id) {
                    _ if !needs_payload => None,
                    (Some(p), _) => Some(p.clone()),
                    (None, Some(id)) => Some(app.block(app.query_payload(id))?),
                    (None, None) => None,
                };
                let exclude = if opts.include_self { None } else { self_at };
                let filter = s.tag_filter(&opts.tags);
                let keep = |at: usize| Some(at) != exclude && s.has_tags(at, &filter);
                let candidates = (0..s.len()).filter(|&at| keep(at)).count();
                cancel.check()?;
                let t1 = Instant::now();
                let q = Query::new(&spec, s.corpus().layout());
                let list: Vec<Entry<Hitting>> = s
                    .rank(&query, &q, first_k, &keep)
                    .into_iter()
                    .map(|sc| Entry {
                        at: sc.at,
                        item: Hitting {
                            id: s.id(sc.at).to_string(),
                            name: s.name(sc.at).to_string(),
                        },
                        score: sc.score,
                        stage_scores: vec![sc.score],
                    })
                    .collect();
                let scan_ms = ms(t1);
                let t2 = Instant::now();
                let mut env = ServerEnv {
                    app: &app,
                    scan: Some(guard),
                    query,
                    epoch,
                    first: spec,
                    query_payload,
                    cancel: cancel.clone(),
                };
                let list = crate::search::run(&stages, list, &mut env)?;
                drop(env);
                let rerank_ms = ms(t2);
                Ok((
                    super::env::hits(list, top_k, epoch),
                    epoch,
                    candidates,
                    scan_ms,
                    rerank_ms,
                ))
            })
            .await?;
        Ok(report.finish(hits, epoch, candidates, scan_ms, rerank_ms))
    }
}

/// A search settled before its scan ([`App::plan_search`]).
pub(super) struct SearchPlan {
    /// Hits answered.
    pub(super) top_k: usize,
    /// How many the scan keeps: the stages' largest shortlist, at least `top_k`.
    pub(super) first_k: usize,
    /// The scan's query spec.
    pub(super) spec: QuerySpec,
    /// The re-ranking stages, in order.
    pub(super) stages: Vec<Stage>,
    /// Some stage re-ranks by payload, so the query's payload is needed.
    pub(super) needs_payload: bool,
    /// The uploaded query's signature (none for a search by stored id).
    pub(super) query_sig: Option<Signature>,
    /// The uploaded query's payload, when it was computed.
    pub(super) upload_payload: Option<GwPayload>,
    /// What the answer reports besides its hits.
    pub(super) report: SearchReport,
}

/// What a search's answer reports besides its hits and counts.
pub(super) struct SearchReport {
    spec_json: serde_json::Value,
    stage_names: Vec<String>,
    analysis: Option<Timings>,
    t0: Instant,
}

impl SearchReport {
    /// The answer, its total time measured from the plan.
    pub(super) fn finish(
        self,
        hits: Vec<Hit>,
        calibration_epoch: u64,
        candidates: usize,
        scan_ms: f64,
        rerank_ms: f64,
    ) -> SearchResult {
        SearchResult {
            hits,
            calibration_epoch,
            candidates,
            spec: self.spec_json,
            stages: self.stage_names,
            timings: SearchTimings {
                analysis: self.analysis,
                scan_ms,
                rerank_ms,
                total_ms: ms(self.t0),
            },
        }
    }

    /// The answer on an index with no calibration yet: no hits.
    pub(super) fn empty(self) -> SearchResult {
        self.finish(Vec::new(), 0, 0, 0.0, 0.0)
    }
}

/// A stored shape's re-ranking payload, decoded.
pub(super) fn decode_payload(id: &str, bytes: &[u8]) -> Result<GwPayload, ApiError> {
    GwPayload::from_bytes(bytes)
        .map_err(|e| ApiError::internal(format!("stored payload of {id} is unreadable: {e}")))
}

/// The answer when a stage needs the stored query's payload and it has none.
pub(super) fn no_payload(id: &str) -> ApiError {
    ApiError::new(
        axum::http::StatusCode::CONFLICT,
        "shape.no_payload",
        format!(
            "shape {id} has no re-ranking payload (its original could not be analysed when the \
             payloads were computed)"
        ),
    )
}

/// The message of a validation error (without the error kind's prefix).
fn invalid_detail(e: crate::Error) -> String {
    match e {
        crate::Error::InvalidArgument(m) => m,
        other => other.to_string(),
    }
}
