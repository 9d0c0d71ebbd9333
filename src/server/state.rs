//! The server's state and its non-HTTP operations: loading, ingest, delete, search,
//! recalibration. Handlers only translate HTTP to these calls.

use super::admission::{Admission, AdmissionConfig, Cancel, Cost};
use super::config::ServerConfig;
use super::env::ServerEnv;
use super::limits::stored_original;
use super::metrics as m;
use super::problem::ApiError;
use crate::index::{Engine, Inserted, ScanIndex, ShapeRecord, Store};
use crate::mesh::read::{detect_format, read_mesh, Format, ReadLimits};
use crate::ranking::{Calibration, QuerySpec};
use crate::rerank::{compute_payload, GwPayload, PayloadSpec};
use crate::search::corpus::{Corpus, Encoded, Layout};
use crate::search::{Entry, Query, Stage, StageRequest};
use crate::signature::Signature;
use crate::spectrum::analyze;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Instant;

/// Calibration as stored in `meta` (the calibration plus the count it saw).
#[derive(Serialize, Deserialize)]
struct StoredCalibration {
    calibrated_on: usize,
    calibration: Calibration,
}

/// Shared state of a running server.
pub struct App {
    /// Configuration.
    pub cfg: ServerConfig,
    /// The sled store.
    pub store: Store,
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
    recalibrating: AtomicBool,
    /// Metrics handle.
    pub metrics: Option<metrics_exporter_prometheus::PrometheusHandle>,
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

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn storage(e: crate::Error) -> ApiError {
    ApiError::internal(e)
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
    /// Prepare + spectrum + signature (+ re-ranking payload when `with_payload`) of a parsed
    /// mesh, recording the stage timings: the one path shared by ingest and search-by-upload.
    fn analyze_and_sign(
        &self,
        mesh: &crate::mesh::Mesh,
        t: &mut Timings,
        with_payload: bool,
        cancel: &Cancel,
    ) -> Result<(crate::spectrum::Analysis, Signature, Option<GwPayload>), ApiError> {
        cancel.check()?;
        let analysis = analyze(mesh, &self.engine.analyze_options())?;
        cancel.check()?;
        t.prepare_ms = analysis.timings.prepare_ms;
        t.laplacian_ms = analysis.timings.laplacian_ms;
        t.factorization_ms = analysis.timings.factorization_ms;
        t.eigensolve_ms = analysis.timings.eigensolve_ms;
        let t2 = Instant::now();
        let sig = self.engine.compute(&analysis)?;
        t.signature_ms = ms(t2);
        cancel.check()?;
        let payload = if with_payload {
            let t3 = Instant::now();
            let p = compute_payload(&analysis, &PayloadSpec::default())?;
            t.payload_ms = ms(t3);
            Some(p)
        } else {
            None
        };
        Ok((analysis, sig, payload))
    }

    /// Opens the store, recomputes stale signatures, calibrates if needed, builds the scan.
    pub fn load(cfg: ServerConfig, engine: Engine) -> crate::Result<Self> {
        let store = Store::open(&cfg.data)?;
        let engine = Arc::new(engine);
        let limits = ReadLimits {
            max_bytes: cfg.max_body_bytes,
            max_vertices: cfg.max_vertices,
            max_faces: cfg.max_faces,
            ..ReadLimits::default()
        };
        let spec_key = engine.spec_key();
        let default_query = serde_json::to_vec(&engine.default_query())
            .map_err(|e| crate::Error::InvalidArgument(format!("default query: {e}")))?;
        store.set_specs(&default_query, &spec_key)?;

        let mut shapes = Vec::new();
        let mut recomputed = 0usize;
        for (mut rec, bytes) in store.all()? {
            let sig = match engine.decode_signature(&bytes) {
                Ok(s) if rec.spec_key == spec_key && engine.signature_spec_key(&s) == spec_key => s,
                stale => {
                    // Derivable data: recompute from the stored original.
                    if let Err(e) = &stale {
                        tracing::warn!(id = %rec.id, error = %e, "unreadable signature; recomputing");
                    }
                    let Some(orig) = store.mesh(&rec.id)? else {
                        tracing::error!(id = %rec.id, "no original mesh to recompute from; skipped");
                        continue;
                    };
                    let hint = Format::from_extension(&rec.format);
                    let mesh = read_mesh(&orig, hint, &ReadLimits::unlimited())?;
                    let analysis = analyze(&mesh, &engine.analyze_options())?;
                    let sig = engine.compute(&analysis)?;
                    rec.spec_key = spec_key.clone();
                    store.replace_signature(&rec, &engine.encode_signature(&sig))?;
                    // The payload depends on the same analysis (eigenpairs): refresh it too.
                    let payload = compute_payload(&analysis, &PayloadSpec::default())?;
                    store.set_payload(&rec.id, &payload.to_bytes())?;
                    recomputed += 1;
                    sig
                }
            };
            shapes.push((rec.id, rec.name, rec.tags, sig));
        }
        if recomputed > 0 {
            tracing::info!(recomputed, "signatures recomputed for the current spec");
        }

        let stored: Option<StoredCalibration> = store
            .calibration()?
            .and_then(|b| serde_json::from_slice(&b).ok());
        let scan = if shapes.is_empty() {
            ScanIndex::default()
        } else {
            let (cal, on) = match stored {
                Some(s)
                    if recomputed == 0
                        && !moved(s.calibrated_on, shapes.len(), cfg.recalibrate_fraction) =>
                {
                    (s.calibration, s.calibrated_on)
                }
                other => {
                    let epoch = other
                        .map(|s| engine.calibration_epoch(&s.calibration) + 1)
                        .unwrap_or(1);
                    let sigs: Vec<&Signature> = shapes.iter().map(|s| &s.3).collect();
                    let cal = engine.calibrate(&sigs, epoch);
                    let on = shapes.len();
                    store.set_calibration(&to_json(&StoredCalibration {
                        calibrated_on: on,
                        calibration: cal.clone(),
                    }))?;
                    (cal, on)
                }
            };
            ScanIndex::build(Arc::new(cal), on, shapes)
        };
        let admission = Admission::new(&AdmissionConfig {
            workers: cfg.effective_workers(),
            heavy_share: cfg.heavy_share,
            queue_capacity: cfg.queue_capacity,
            heavy_nice: cfg.heavy_nice,
            retry_after: cfg.retry_after_secs,
            request_timeout: std::time::Duration::from_secs_f64(cfg.request_timeout_secs),
        })?;
        let app = App {
            admission,
            cfg,
            store,
            engine,
            scan: Arc::new(RwLock::new(scan)),
            limits,
            ready: AtomicBool::new(false),
            recalibrating: AtomicBool::new(false),
            metrics: m::handle(),
        };
        app.update_gauges();
        Ok(app)
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
        metrics::gauge!("shapeseek_index_bytes").set(self.store.size_on_disk() as f64);
    }

    /// The stored re-ranking payload of a shape (`None` when it has none).
    pub(super) fn stored_payload(&self, id: &str) -> Result<Option<GwPayload>, ApiError> {
        match self.store.payload(id).map_err(storage)? {
            None => Ok(None),
            Some(b) => GwPayload::from_bytes(&b).map(Some).map_err(|e| {
                ApiError::internal(format!("stored payload of {id} is unreadable: {e}"))
            }),
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
        if let Some(r) = self.existing(&digest)? {
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
            self.after_change();
        }
        Ok(res)
    }

    fn existing(&self, digest: &[u8; 32]) -> Result<Option<IngestResult>, ApiError> {
        if let Some(id) = self.store.id_for_hash(digest).map_err(storage)? {
            if let Some(rec) = self.store.get(&id).map_err(storage)? {
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

    fn ingest_blocking(
        &self,
        up: Upload,
        digest: [u8; 32],
        t0: Instant,
        cancel: &Cancel,
    ) -> Result<IngestResult, ApiError> {
        // A twin upload may have been stored while this one waited.
        if let Some(r) = self.existing(&digest)? {
            return Ok(r);
        }
        let mut t = Timings::default();
        let t1 = Instant::now();
        let format = detect_format(&up.bytes, up.hint)?;
        let mesh = read_mesh(&up.bytes, Some(format), &self.limits)?;
        t.read_ms = ms(t1);
        let (stored, reencoded_from) = stored_original(&self.cfg, &up.bytes, &mesh, format)?;
        let area = mesh.area();
        let (analysis, sig, payload) = self.analyze_and_sign(&mesh, &mut t, true, cancel)?;
        let payload = payload.map(|p| p.to_bytes());
        // The last point where an abandoned ingest stops: past it the shape is stored.
        cancel.check()?;
        let t3 = Instant::now();
        let id = self.store.new_id().map_err(storage)?;
        let record = ShapeRecord {
            name: up.name.clone().unwrap_or_else(|| id.clone()),
            id,
            tags: up.tags.clone(),
            format: format.name().to_string(),
            content_type: format.mime().to_string(),
            bytes: stored.len() as u64,
            vertices: mesh.vertices.len(),
            faces: mesh.faces.len(),
            area,
            sha256: hex::encode(digest),
            created_unix_ms: crate::index::store::now_unix_ms(),
            prepare: analysis.report.clone(),
            spec_key: self.engine.signature_spec_key(&sig),
        };
        let sig_bytes = self.engine.encode_signature(&sig);
        let outcome = self
            .store
            .insert(&record, &digest, &sig_bytes, &stored, payload.as_deref())
            .map_err(storage)?;
        let id = match outcome {
            Inserted::Existing(id) => {
                return self
                    .existing(&digest)?
                    .ok_or_else(|| ApiError::internal(format!("shape {id} vanished")));
            }
            Inserted::New(id) => id,
        };
        {
            let mut scan = self.scan.write().unwrap_or_else(|p| p.into_inner());
            scan.insert(&self.engine, &id, &record.name, &record.tags, &sig, 1);
        }
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
        let app = self.clone();
        let removed = tokio::task::spawn_blocking(move || -> Result<bool, ApiError> {
            let removed = app.store.delete(&id).map_err(storage)?;
            app.scan
                .write()
                .unwrap_or_else(|p| p.into_inner())
                .remove(&id);
            Ok(removed)
        })
        .await
        .map_err(ApiError::internal)??;
        if removed {
            self.after_change();
        }
        Ok(removed)
    }

    /// True when the index size moved by more than the configured fraction since the last
    /// calibration.
    fn needs_recalibration(&self) -> bool {
        self.scan
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .needs_recalibration(self.cfg.recalibrate_fraction)
    }

    /// After an insert or delete: gauges, and a background recalibration when the index size
    /// moved by more than the configured fraction (searches go on meanwhile).
    fn after_change(self: &Arc<Self>) {
        self.update_gauges();
        if self.needs_recalibration() && !self.recalibrating.swap(true, Ordering::AcqRel) {
            let app = self.clone();
            // Recalibration is CPU work no request waits for: it runs on the heavy lane's
            // threads, not beside cheap searches.
            tokio::task::spawn_blocking(move || {
                app.admission.on_heavy_pool(|| app.recalibrate_loop())
            });
        }
    }

    fn recalibrate_loop(&self) {
        loop {
            let (snapshot, epoch) = {
                let s = self.scan.read().unwrap_or_else(|p| p.into_inner());
                if !s.needs_recalibration(self.cfg.recalibrate_fraction) {
                    break;
                }
                (
                    s.ids(),
                    s.calibration()
                        .map(|c| self.engine.calibration_epoch(c))
                        .unwrap_or(0)
                        + 1,
                )
            };
            let t = Instant::now();
            // Signatures are not kept in memory: read them from the store, outside the lock.
            let sigs: Vec<(usize, Signature)> = snapshot
                .par_iter()
                .enumerate()
                .filter_map(|(i, id)| self.stored_signature(id).map(|s| (i, s)))
                .collect();
            let refs: Vec<&Signature> = sigs.iter().map(|(_, s)| s).collect();
            let cal = Arc::new(self.engine.calibrate(&refs, epoch));
            let layout = Layout::of(&cal);
            let mut encoded: Vec<Encoded> = vec![Encoded::absent(&layout); snapshot.len()];
            let done: Vec<(usize, Encoded)> = sigs
                .par_iter()
                .map(|(i, s)| (*i, Encoded::from_signature(s, &cal, &layout)))
                .collect();
            drop(refs);
            drop(sigs);
            for (i, e) in done {
                encoded[i] = e;
            }
            let corpus = Corpus::build(layout, &encoded);
            drop(encoded);
            let on = snapshot.len();
            if let Err(e) = self.store.set_calibration(&to_json(&StoredCalibration {
                calibrated_on: on,
                calibration: (*cal).clone(),
            })) {
                tracing::error!(error = %e, "could not persist the calibration");
            }
            self.scan
                .write()
                .unwrap_or_else(|p| p.into_inner())
                .install_calibration(
                    cal,
                    on,
                    &snapshot,
                    corpus,
                    &mut |id, cal, layout| match self.stored_signature(id) {
                        Some(s) => Encoded::from_signature(&s, cal, layout),
                        None => Encoded::absent(layout),
                    },
                );
            tracing::info!(epoch, shapes = on, ms = ms(t), "recalibrated");
            self.update_gauges();
        }
        self.recalibrating.store(false, Ordering::Release);
        // A write that came between the last check and the reset saw the flag set and left the
        // work to this loop: check once more.
        if self.needs_recalibration() && !self.recalibrating.swap(true, Ordering::AcqRel) {
            self.recalibrate_loop();
        }
    }

    /// The stored signature of `id` (`None`, logged, when it is missing or unreadable).
    fn stored_signature(&self, id: &str) -> Option<Signature> {
        match self.store.signature(id) {
            Ok(Some(b)) => match self.engine.decode_signature(&b) {
                Ok(s) => Some(s),
                Err(e) => {
                    tracing::error!(id, error = %e, "unreadable stored signature");
                    None
                }
            },
            Ok(None) => None,
            Err(e) => {
                tracing::error!(id, error = %e, "could not read a stored signature");
                None
            }
        }
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

    /// Searches with a stored shape (`id`) or an analysed upload (`query_sig`).
    pub async fn search(
        self: &Arc<Self>,
        opts: SearchOptions,
        query_sig: Option<QueryAnalysis>,
        deadline: Option<Instant>,
    ) -> Result<SearchResult, ApiError> {
        let t0 = Instant::now();
        let (top_k, spec, spec_json, stages) = self.resolve_options(&opts)?;
        let (query_sig, upload_payload, analysis_t) = match query_sig {
            Some((s, p, t)) => (Some(s), p, Some(t)),
            None => (None, None, None),
        };
        if query_sig.is_none() && opts.id.is_none() {
            return Err(ApiError::invalid(
                "give a stored shape id, or upload a mesh to search by example",
            ));
        }
        let app = self.clone();
        let stage_names: Vec<String> = std::iter::once("scan".to_string())
            .chain(stages.iter().map(|p| p.name().to_string()))
            .collect();
        let needs_payload = stages.iter().any(|p| p.payload_spec().is_some());
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
                    (None, None) => return Err(ApiError::invalid("no query given")),
                };
                let query_payload = match (&upload_payload, &opts.id) {
                    _ if !needs_payload => None,
                    (Some(p), _) => Some(p.clone()),
                    (None, Some(id)) => Some(app.stored_payload(id)?.ok_or_else(|| {
                        ApiError::new(
                            axum::http::StatusCode::CONFLICT,
                            "shape.no_payload",
                            format!(
                                "shape {id} has no re-ranking payload (its original could not \
                                 be analysed when the payloads were computed)"
                            ),
                        )
                    })?),
                    (None, None) => None,
                };
                let exclude = if opts.include_self { None } else { self_at };
                let filter = s.tag_filter(&opts.tags);
                let keep = |at: usize| Some(at) != exclude && s.has_tags(at, &filter);
                let candidates = (0..s.len()).filter(|&at| keep(at)).count();
                let first_k = stages
                    .iter()
                    .map(Stage::shortlist)
                    .max()
                    .unwrap_or(0)
                    .max(top_k);
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
                    first: spec,
                    query_payload,
                    cancel: cancel.clone(),
                };
                let mut list = crate::search::run(&stages, list, &mut env)?;
                drop(env);
                let rerank_ms = ms(t2);
                list.truncate(top_k);
                let hits: Vec<Hit> = list
                    .into_iter()
                    .enumerate()
                    .map(|(r, e)| Hit {
                        id: e.item.id,
                        name: e.item.name,
                        score: e.score,
                        rank: r + 1,
                        calibration_epoch: epoch,
                        stage_scores: e.stage_scores,
                    })
                    .collect();
                Ok((hits, epoch, candidates, scan_ms, rerank_ms))
            })
            .await?;
        Ok(SearchResult {
            hits,
            calibration_epoch: epoch,
            candidates,
            spec: spec_json,
            stages: stage_names,
            timings: SearchTimings {
                analysis: analysis_t,
                scan_ms,
                rerank_ms,
                total_ms: ms(t0),
            },
        })
    }
}

/// The message of a validation error (without the error kind's prefix).
fn invalid_detail(e: crate::Error) -> String {
    match e {
        crate::Error::InvalidArgument(m) => m,
        other => other.to_string(),
    }
}

fn moved(calibrated_on: usize, n: usize, fraction: f64) -> bool {
    (n as f64 - calibrated_on as f64).abs() > fraction * (calibrated_on as f64).max(1.0)
}

fn to_json<T: Serialize>(v: &T) -> Vec<u8> {
    serde_json::to_vec(v).unwrap_or_default()
}
