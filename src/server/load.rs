//! Opening the server's state on a store of either backend: the specs are recorded, stale
//! signatures are recomputed from the stored originals, the calibration is kept or recomputed
//! under the store's calibration lock, and the in-memory scan is built.
//!
//! The work here is CPU-bound and runs on a blocking thread; store calls are bridged with
//! [`App::block`] (the store's futures run on the server's tokio runtime).

use super::admission::{Admission, AdmissionConfig};
use super::config::ServerConfig;
use super::metrics as m;
use super::state::App;
use crate::index::{Engine, ScanIndex, ShapeRecord};
use crate::mesh::read::{read_mesh, Format, ReadLimits};
use crate::ranking::Calibration;
use crate::rerank::{compute_payload, PayloadSpec};
use crate::signature::Signature;
use crate::spectrum::analyze;
use crate::storage::{CalibrationLock, ShapeStore};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, RwLock};

/// Signatures read from the store per page while loading.
const LOAD_PAGE: usize = 256;

/// One loaded shape: id, name, tags, signature.
type Row = (String, String, Vec<String>, Signature);

impl App {
    /// Opens the state on `store`: records the specs, recomputes stale signatures, calibrates
    /// if needed (under the store's calibration lock), builds the scan. Blocking: call it on a
    /// blocking thread; `rt` runs the store's futures.
    pub fn load(
        cfg: ServerConfig,
        engine: Engine,
        store: Arc<dyn ShapeStore>,
        rt: tokio::runtime::Handle,
    ) -> crate::Result<Self> {
        let engine = Arc::new(engine);
        let limits = ReadLimits {
            max_bytes: cfg.max_body_bytes,
            max_vertices: cfg.max_vertices,
            max_faces: cfg.max_faces,
            ..ReadLimits::default()
        };
        let admission = Admission::new(&AdmissionConfig {
            workers: cfg.effective_workers(),
            heavy_share: cfg.heavy_share,
            queue_capacity: cfg.queue_capacity,
            heavy_nice: cfg.heavy_nice,
            retry_after: cfg.retry_after_secs,
            request_timeout: std::time::Duration::from_secs_f64(cfg.request_timeout_secs),
        })?;
        let shard = cfg.shard_spec().map(super::shard::Sharding::new);
        let app = App {
            shard,
            admission,
            cfg,
            store,
            rt,
            engine,
            scan: Arc::new(RwLock::new(ScanIndex::default())),
            limits,
            ready: AtomicBool::new(false),
            recalibrating: AtomicBool::new(false),
            metrics: m::handle(),
            cluster: None,
        };
        app.record_specs()?;
        let (shapes, recomputed) = app.load_signatures()?;
        let scan = app.calibrated_scan(shapes, recomputed)?;
        *app.scan.write().unwrap_or_else(|p| p.into_inner()) = scan;
        app.update_gauges();
        Ok(app)
    }

    /// Stores the default query and the signature spec key (what the data was computed with).
    fn record_specs(&self) -> crate::Result<()> {
        let default_query = serde_json::to_vec(&self.engine.default_query())
            .map_err(|e| crate::Error::InvalidArgument(format!("default query: {e}")))?;
        self.block(self.store.meta_set("default_query", &default_query))?;
        self.block(
            self.store
                .meta_set("spec_key", self.engine.spec_key().as_bytes()),
        )
    }

    /// Every stored signature, decoded; a stale or unreadable one is recomputed from the stored
    /// original and written back. Returns the rows and how many were recomputed.
    fn load_signatures(&self) -> crate::Result<(Vec<Row>, usize)> {
        let spec_key = self.engine.spec_key();
        let mut shapes = Vec::new();
        let mut recomputed = 0usize;
        let mut after: Option<String> = None;
        let mut total = 0usize;
        loop {
            let page = self.block(self.store.scan_signatures(after.as_deref(), LOAD_PAGE))?;
            let full = page.len() >= LOAD_PAGE;
            after = page.last().map(|(r, _)| r.id.clone());
            total += page.len();
            for (rec, bytes) in page {
                // A sharded node decodes (and refreshes) its own shard's signatures only.
                if self.shard().is_some_and(|sh| !sh.spec.holds(&rec.id)) {
                    continue;
                }
                let sig = match self.engine.decode_signature(&bytes) {
                    Ok(s)
                        if rec.spec_key == spec_key
                            && self.engine.signature_spec_key(&s) == spec_key =>
                    {
                        s
                    }
                    stale => {
                        if let Err(e) = &stale {
                            tracing::warn!(id = %rec.id, error = %e, "unreadable signature; recomputing");
                        }
                        let Some(sig) = self.recompute(rec.clone())? else {
                            continue;
                        };
                        recomputed += 1;
                        sig
                    }
                };
                shapes.push((rec.id, rec.name, rec.tags, sig));
            }
            if !full {
                break;
            }
        }
        if recomputed > 0 {
            tracing::info!(recomputed, "signatures recomputed for the current spec");
        }
        if let Some(sh) = self.shard() {
            sh.set_total(total);
        }
        Ok((shapes, recomputed))
    }

    /// Recomputes the signature and payload of `rec` from its stored original (derivable data)
    /// and stores them; `None` (logged) when the original is missing.
    fn recompute(&self, mut rec: ShapeRecord) -> crate::Result<Option<Signature>> {
        let Some(orig) = self.block(self.store.mesh(&rec.id))? else {
            tracing::error!(id = %rec.id, "no original mesh to recompute from; skipped");
            return Ok(None);
        };
        let hint = Format::from_extension(&rec.format);
        let mesh = read_mesh(&orig, hint, &ReadLimits::unlimited())?;
        let analysis = analyze(&mesh, &self.engine.analyze_options())?;
        let sig = self.engine.compute(&analysis)?;
        rec.spec_key = self.engine.spec_key();
        // The payload depends on the same analysis (eigenpairs): refresh it too.
        let payload = compute_payload(&analysis, &PayloadSpec::default())?.to_bytes();
        self.block(self.store.replace_signature(
            &rec,
            &self.engine.encode_signature(&sig),
            Some(&payload),
        ))?;
        Ok(Some(sig))
    }

    /// The scan over `shapes` with the stored calibration when it still fits (nothing
    /// recomputed, the size has not moved past `recalibrate_fraction`), else a new one computed
    /// and committed as the next epoch, all under the store's calibration lock.
    fn calibrated_scan(&self, shapes: Vec<Row>, recomputed: usize) -> crate::Result<ScanIndex> {
        // The whole corpus's size: a sharded node's `shapes` are its shard's.
        let n = self.shard().map_or(shapes.len(), |sh| sh.total());
        if n == 0 {
            return Ok(ScanIndex::default());
        }
        let lock = self.block(self.store.lock_calibration())?;
        let stored = lock.current().and_then(|s| {
            serde_json::from_slice::<Calibration>(&s.json)
                .ok()
                .map(|c| (c, s.calibrated_on as usize))
        });
        let (cal, on) = match stored {
            Some((cal, on)) if recomputed == 0 && !moved(on, n, self.cfg.recalibrate_fraction) => {
                self.block(lock.release())?;
                (cal, on)
            }
            _ => {
                // A sharded node calibrates on every stored signature (read again, page by
                // page: `src/server/shard.rs`), as a single node holding them all would.
                let pool: Option<Vec<Signature>> = self.shard().map(|_| self.corpus_signatures());
                let sigs: Vec<&Signature> = match &pool {
                    Some(p) => p.iter().collect(),
                    None => shapes.iter().map(|s| &s.3).collect(),
                };
                let epoch = lock.next_epoch();
                let cal = self.engine.calibrate(&sigs, epoch);
                let on = sigs.len();
                drop(sigs);
                drop(pool);
                self.commit_calibration(lock, epoch, on, &cal)?;
                (cal, on)
            }
        };
        Ok(ScanIndex::build(Arc::new(cal), on, shapes))
    }

    /// Writes `cal` (computed on `on` shapes) as `epoch` (at least the lock's next), durably.
    pub(super) fn commit_calibration(
        &self,
        lock: CalibrationLock,
        epoch: u64,
        on: usize,
        cal: &Calibration,
    ) -> crate::Result<()> {
        let json = serde_json::to_vec(cal)
            .map_err(|e| crate::Error::InvalidArgument(format!("calibration: {e}")))?;
        self.block(lock.commit_as(epoch, on as u64, json))
            .map(|_| ())
    }
}

/// True when the corpus size `n` moved by more than `fraction` from `calibrated_on`.
pub(super) fn moved(calibrated_on: usize, n: usize, fraction: f64) -> bool {
    (n as f64 - calibrated_on as f64).abs() > fraction * (calibrated_on as f64).max(1.0)
}
