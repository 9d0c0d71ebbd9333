//! Opening the server's state on a store of either backend: the specs are recorded, stale
//! signatures are recomputed from the stored originals, the calibration is kept or recomputed
//! under the store's calibration lock, and the in-memory scan is built.
//!
//! The work here is CPU-bound and runs on a blocking thread; store calls are bridged with
//! [`App::block`] (the store's futures run on the server's tokio runtime).

use super::admission::{Admission, AdmissionConfig};
use super::config::ServerConfig;
use super::metrics as m;
use super::sample::Sample;
use super::state::App;
use crate::index::{Engine, ScanIndex, ShapeRecord};
use crate::mesh::read::{read_mesh, Format, ReadLimits};
use crate::ranking::Calibration;
use crate::rerank::{compute_payload, PayloadSpec};
use crate::search::corpus::{Encoded, Layout};
use crate::signature::Signature;
use crate::storage::{CalibrationLock, ShapeStore};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, RwLock};

/// Signatures read from the store per page while loading.
const LOAD_PAGE: usize = 256;

/// One loaded shape: id, name, tags.
type Meta = (String, String, Vec<String>);

/// What [`App::load_signatures`] read.
struct Loaded {
    /// This node's shapes, in id order.
    rows: Vec<Meta>,
    /// The scan of every row, built while reading under the stored calibration of epoch
    /// `encoded_under` (none when there was no stored calibration).
    scan: Option<ScanIndex>,
    encoded_under: Option<u64>,
    /// The shapes the calibration would be computed on (the whole corpus's sample).
    sample: Sample,
    /// Signatures recomputed for the current spec.
    recomputed: usize,
    /// Shapes whose signature had to be recomputed and could not be ([`App::recompute`]).
    left_out: usize,
}

/// A stored original read as a mesh: its record's `format` is the hint, and no upload limit
/// applies (the bytes passed them when stored). Recomputation and format conversions start here.
pub(super) fn read_original(format: &str, bytes: &[u8]) -> crate::Result<crate::mesh::Mesh> {
    read_mesh(
        bytes,
        Format::from_extension(format),
        &ReadLimits::unlimited(),
    )
}

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
            heavy_borrow: cfg.heavy_borrow,
            borrow_quiet: super::admission::BORROW_QUIET,
            retry_after: cfg.retry_after_secs,
            request_timeout: std::time::Duration::from_secs_f64(cfg.request_timeout_secs),
        })?;
        let shard = cfg.shard_spec().map(super::shard::Sharding::new);
        let conversions = Arc::new(tokio::sync::Semaphore::new(cfg.effective_workers().max(1)));
        let downloads = super::limits::ResponseBudget::new(cfg.max_inflight_response_bytes);
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
            adopting: Arc::new(tokio::sync::Mutex::new(())),
            writes: Arc::default(),
            metrics: m::handle(),
            cluster: None,
            conversions,
            downloads,
            left_out: Arc::default(),
        };
        app.record_specs()?;
        let loaded = app.load_signatures()?;
        let scan = app.calibrated_scan(loaded)?;
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

    /// Reads every stored signature once, page by page: a stale or unreadable one is recomputed
    /// from the stored original and written back; each of this node's shapes is encoded under
    /// the stored calibration seen before reading (if any), appended to the scan being built,
    /// and its signature dropped, except those the calibration sample keeps
    /// ([`super::sample`]). So a load holds the scan itself plus a page of encodings and at most
    /// `calibration_sample` signatures: neither every signature nor every shape's encoding
    /// beside the scan built from them.
    fn load_signatures(&self) -> crate::Result<Loaded> {
        use rayon::prelude::*;
        let spec_key = self.engine.spec_key();
        let seen = self.stored_calibration(self.block(self.store.calibration())?.as_ref());
        let layout = seen.as_ref().map(|(cal, _, _)| Layout::of(cal));
        // The usual restart: the stored calibration fits the corpus. Then the sample is only
        // listed (its signatures read later should a recomputed signature force a new
        // calibration after all), and the load holds nothing but the encodings.
        let (expect_fit, scan) = match &seen {
            Some((cal, on, _)) => {
                let count = self.block(self.store.count())? as usize;
                // Room for this node's part of the store (a shard's is about its share; the
                // scan grows past a reservation as any vector does).
                let part = self
                    .shard()
                    .map_or(count, |sh| count / sh.spec.count.max(1) as usize);
                let scan = ScanIndex::with_capacity(cal.clone(), *on, part);
                (
                    !moved(*on, count, self.cfg.recalibrate_fraction),
                    Some(scan),
                )
            }
            None => (false, None),
        };
        let mut l = Loaded {
            rows: Vec::new(),
            scan,
            encoded_under: seen.as_ref().map(|(_, _, epoch)| *epoch),
            sample: Sample::new(self.cfg.calibration_sample),
            recomputed: 0,
            left_out: 0,
        };
        let mut after: Option<String> = None;
        let mut total = 0usize;
        loop {
            let page = self.block(self.store.scan_signatures(after.as_deref(), LOAD_PAGE))?;
            // The end is an empty page: a page may be short before it (a record whose
            // signature is missing is left out of it).
            let Some(last) = page.last().map(|(r, _)| r.id.clone()) else {
                break;
            };
            after = Some(last);
            total += page.len();
            let mut own: Vec<(ShapeRecord, Signature)> = Vec::with_capacity(page.len());
            for (rec, bytes) in page {
                // A sharded node decodes (and refreshes) its own shard's signatures only, and
                // the others' that enter the calibration sample.
                if self.shard().is_some_and(|sh| !sh.spec.holds(&rec.id)) {
                    if expect_fit {
                        l.sample.offer_id(&rec.sha256, &rec.id);
                        continue;
                    }
                    l.sample.offer(&rec.sha256, &rec.id, || {
                        self.engine
                            .decode_signature(&bytes)
                            .ok()
                            .filter(|s| self.engine.signature_spec_key(s) == spec_key)
                    });
                    continue;
                }
                let sig = match self.current_signature(&rec, &bytes, &spec_key) {
                    Some(s) => s,
                    None => {
                        let Some(sig) = self.recompute(rec.clone())? else {
                            l.left_out += 1;
                            continue;
                        };
                        l.recomputed += 1;
                        sig
                    }
                };
                own.push((rec, sig));
            }
            if let (Some((cal, _, _)), Some(layout), Some(scan)) = (&seen, &layout, &mut l.scan) {
                let encoded: Vec<Encoded> = own
                    .par_iter()
                    .map(|(_, sig)| Encoded::from_signature(sig, cal, layout))
                    .collect();
                for ((rec, _), e) in own.iter().zip(&encoded) {
                    scan.push_encoded(&rec.id, &rec.name, &rec.tags, e);
                }
            }
            for (rec, sig) in own {
                if expect_fit {
                    l.sample.offer_id(&rec.sha256, &rec.id);
                } else {
                    l.sample.offer(&rec.sha256, &rec.id, || Some(sig));
                }
                l.rows.push((rec.id, rec.name, rec.tags));
            }
        }
        if l.recomputed > 0 {
            tracing::info!(
                recomputed = l.recomputed,
                "signatures recomputed for the current spec"
            );
        }
        if l.left_out > 0 {
            tracing::warn!(
                left_out = l.left_out,
                "stored shapes left out of the index: their signatures could not be recomputed \
                 (each logged above); the next start tries again"
            );
        }
        if let Some(sh) = self.shard() {
            sh.set_total(total);
        }
        Ok(l)
    }

    /// A stored calibration as (calibration, shapes it was computed on, epoch); `None` when
    /// there is none, it does not parse, or the configuration calibrates otherwise
    /// ([`crate::index::Engine::stored_calibration`]).
    fn stored_calibration(
        &self,
        stored: Option<&crate::storage::StoredCalibration>,
    ) -> Option<(Arc<Calibration>, usize, u64)> {
        let s = stored?;
        self.engine
            .stored_calibration(&s.json)
            .map(|c| (Arc::new(c), s.calibrated_on as usize, s.epoch))
    }

    /// The stored signature `bytes` of `rec` when it was computed under this node's spec,
    /// `spec_key` = [`Engine::spec_key`] (the record's key and the signature's own); `None` when
    /// it is stale or unreadable (logged), to be recomputed ([`App::recompute`]).
    pub(super) fn current_signature(
        &self,
        rec: &ShapeRecord,
        bytes: &[u8],
        spec_key: &str,
    ) -> Option<Signature> {
        match self.engine.decode_signature(bytes) {
            Ok(s) if rec.spec_key == spec_key && self.engine.signature_spec_key(&s) == spec_key => {
                Some(s)
            }
            Ok(_) => None,
            Err(e) => {
                tracing::warn!(id = %rec.id, error = %e, "unreadable signature; recomputing");
                None
            }
        }
    }

    /// Recomputes the signature and payload of `rec` from its stored original (derivable data)
    /// and stores them. `None` (logged as an error) when that shape cannot be recomputed: its
    /// original is missing or damaged on disk, or it no longer passes the analysis under this
    /// spec (a release whose preparation refuses what an earlier one accepted). The record and
    /// its original stay stored, left out of the scan, and the id is remembered so that nothing
    /// tries it again (a cluster node's reconciliation, an upload of the same bytes) until the
    /// next start. One such shape never stops a node from serving the others. A store that
    /// fails otherwise is an error. Blocking (store calls through [`App::block`]).
    pub(super) fn recompute(&self, mut rec: ShapeRecord) -> crate::Result<Option<Signature>> {
        if self.is_left_out(&rec.id) {
            return Ok(None);
        }
        let skipped = |why: &str, e: &dyn std::fmt::Display| {
            tracing::error!(
                id = %rec.id,
                error = %e,
                "{why}; the shape stays stored but is left out of the index until the next start"
            );
            self.left_out
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(rec.id.clone());
            Ok(None)
        };
        let orig = match self.block(self.store.mesh(&rec.id)) {
            Ok(Some(o)) => o,
            Ok(None) => return skipped("no original mesh to recompute from", &"missing"),
            Err(e @ crate::Error::Corrupt { .. }) => {
                return skipped("the original mesh is damaged on disk", &e)
            }
            Err(e) => return Err(e),
        };
        let analysed = read_original(&rec.format, &orig).and_then(|m| self.engine.sign(&m));
        let (analysis, sig) = match analysed {
            Ok(a) => a,
            Err(e) => return skipped("the original mesh cannot be analysed under this spec", &e),
        };
        rec.spec_key = self.engine.spec_key();
        // The payload depends on the same analysis (eigenpairs): refresh it too.
        let payload = match compute_payload(&analysis, &PayloadSpec::default()) {
            Ok(p) => p.to_bytes(),
            Err(e) => return skipped("the re-ranking payload cannot be computed", &e),
        };
        self.block(self.store.replace_signature(
            &rec,
            &self.engine.encode_signature(&sig),
            Some(&payload),
        ))?;
        Ok(Some(sig))
    }

    /// True when `id` could not be recomputed since this node started ([`App::recompute`]).
    pub(super) fn is_left_out(&self, id: &str) -> bool {
        self.left_out
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .contains(id)
    }

    /// The scan over the loaded shapes with the stored calibration when it still fits (nothing
    /// recomputed, the size has not moved past `recalibrate_fraction`), else a new one computed
    /// on the calibration sample and committed as the next epoch, under the store's lock.
    fn calibrated_scan(&self, l: Loaded) -> crate::Result<ScanIndex> {
        // The whole corpus's size: a sharded node's rows are its shard's.
        let n = self.shard().map_or(l.rows.len(), |sh| sh.total());
        if n == 0 {
            return Ok(ScanIndex::default());
        }
        let lock = self.block(self.store.lock_calibration())?;
        match self.stored_calibration(lock.current()) {
            Some((cal, on, epoch))
                if l.recomputed == 0 && !moved(on, n, self.cfg.recalibrate_fraction) =>
            {
                self.block(lock.release())?;
                match l.scan {
                    Some(scan)
                        if l.encoded_under == Some(epoch)
                            && scan.calibrated_on() == on
                            && scan.len() == l.rows.len() =>
                    {
                        Ok(scan)
                    }
                    scan => {
                        // Another node recalibrated while this one read.
                        drop(scan);
                        self.encode_rows(cal, on, l.rows)
                    }
                }
            }
            _ => {
                // Encoded under a calibration that is about to be replaced.
                drop(l.scan);
                let whole = l.sample.is_whole() && self.shard().is_none();
                let mut sample = l.sample;
                self.fill_sample(&mut sample)?;
                let sigs = sample.into_signatures();
                let epoch = lock.next_epoch();
                let cal = {
                    let refs: Vec<&Signature> = sigs.iter().map(|(_, s)| s).collect();
                    self.engine.calibrate(&refs, epoch)
                };
                self.commit_calibration(lock, epoch, n, &cal)?;
                let cal = Arc::new(cal);
                let same = sigs.len() == l.rows.len()
                    && sigs.iter().zip(&l.rows).all(|((a, _), (b, _, _))| a == b);
                if whole && same {
                    // The sample is every shape of this node: encode from it.
                    let rows = l
                        .rows
                        .into_iter()
                        .zip(sigs)
                        .map(|((id, name, tags), (_, sig))| (id, name, tags, sig))
                        .collect();
                    Ok(ScanIndex::build(cal, n, rows))
                } else {
                    drop(sigs);
                    self.encode_rows(cal, n, l.rows)
                }
            }
        }
    }

    /// The scan over `rows` (in id order) under `cal`, their signatures read again from the
    /// store page by page (a row whose signature is gone or unreadable is left out; the
    /// replica's reconciliation settles it). A store that cannot be read fails the load with
    /// its error: a scan of the rows read so far would serve a part of the corpus as the whole.
    fn encode_rows(
        &self,
        cal: Arc<Calibration>,
        on: usize,
        rows: Vec<Meta>,
    ) -> crate::Result<ScanIndex> {
        use rayon::prelude::*;
        let layout = Layout::of(&cal);
        let mut scan = ScanIndex::with_capacity(cal.clone(), on, rows.len());
        let mut rows = rows.into_iter().peekable();
        let mut after: Option<String> = None;
        while rows.peek().is_some() {
            let page = self.block(self.store.scan_signatures(after.as_deref(), LOAD_PAGE))?;
            let Some(last) = page.last().map(|(r, _)| r.id.clone()) else {
                break; // the end (see `load_signatures`)
            };
            after = Some(last);
            let mut wanted: Vec<(Meta, Vec<u8>)> = Vec::new();
            for (rec, bytes) in page {
                while rows.peek().is_some_and(|r| r.0 < rec.id) {
                    rows.next(); // deleted since the first read
                }
                if rows.peek().is_some_and(|r| r.0 == rec.id) {
                    wanted.push((rows.next().expect("peeked"), bytes));
                }
            }
            let encoded: Vec<Option<Encoded>> = wanted
                .par_iter()
                .map(|(_, bytes)| {
                    self.engine
                        .decode_signature(bytes)
                        .ok()
                        .map(|s| Encoded::from_signature(&s, &cal, &layout))
                })
                .collect();
            for ((id, name, tags), e) in wanted.iter().map(|(m, _)| m).zip(encoded) {
                match e {
                    Some(e) => scan.push_encoded(id, name, tags, &e),
                    None => tracing::error!(id, "unreadable stored signature; left out"),
                }
            }
        }
        Ok(scan)
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::test_support::{
        ingest, meshes, node, node_with, runtime, sled_store, wait_idle, OnFaulty,
    };

    /// Every row of `scan` as (id, encoding), in scan order.
    fn encodings(scan: &ScanIndex) -> Vec<(String, Encoded)> {
        (0..scan.len())
            .map(|at| (scan.id(at).to_string(), scan.corpus().encoded(at)))
            .collect()
    }

    /// The calibration epoch of `app`'s scan and its rows' encodings.
    fn served(app: &App) -> (u64, Vec<(String, Encoded)>) {
        let scan = app.scan.read().unwrap();
        let epoch = app.engine.calibration_epoch(scan.calibration().unwrap());
        (epoch, encodings(&scan))
    }

    /// A node reads the stored signatures under one calibration; before it takes the
    /// calibration lock, another node commits a newer one that still fits the corpus. The
    /// scan built while reading is under the old calibration: the node must not serve it but
    /// encode every shape again under the newer one, exactly as a node that starts afterwards.
    #[test]
    fn a_calibration_committed_while_loading_replaces_the_scan_built_under_the_old_one() {
        let dir = tempfile::tempdir().unwrap();
        let rt = runtime();
        let store = sled_store(dir.path(), &rt);
        let first = Arc::new(node(dir.path(), &store, &rt));
        let meshes = meshes();
        for (i, m) in meshes.iter().enumerate() {
            ingest(&first, &rt, m, &format!("s{i}"));
        }
        // The background recalibration settles (it shares the store with the nodes below).
        wait_idle(&first);
        assert!(!first.needs_recalibration());
        drop(first);

        // A node started now takes the usual restart's path: the scan built while reading.
        let reader = node(dir.path(), &store, &rt);
        let (old_epoch, before) = served(&reader);
        assert_eq!(before.len(), meshes.len());

        // The same node loads again, and another node commits a calibration between its read
        // and its lock: computed on half of the shapes, stored as calibrated on all of them
        // (so it fits, and only its epoch tells it apart).
        let loaded = reader.load_signatures().unwrap();
        assert_eq!(loaded.encoded_under, Some(old_epoch));
        assert!(loaded.scan.is_some(), "the scan was built while reading");
        let half: Vec<Signature> = before[..3]
            .iter()
            .map(|(id, _)| {
                let bytes = reader.block(store.signature(id)).unwrap().unwrap();
                reader.engine.decode_signature(&bytes).unwrap()
            })
            .collect();
        let lock = reader.block(store.lock_calibration()).unwrap();
        let new_epoch = lock.next_epoch();
        assert!(new_epoch > old_epoch);
        let other = reader
            .engine
            .calibrate(&half.iter().collect::<Vec<_>>(), new_epoch);
        reader
            .commit_calibration(lock, new_epoch, meshes.len(), &other)
            .unwrap();

        let scan = reader.calibrated_scan(loaded).unwrap();
        assert_eq!(
            reader.engine.calibration_epoch(scan.calibration().unwrap()),
            new_epoch
        );
        assert_eq!(scan.calibrated_on(), meshes.len());
        let after = encodings(&scan);
        assert_ne!(
            after, before,
            "the other calibration encodes differently (else the test shows nothing)"
        );
        // A node that starts now reads the newer calibration before reading the signatures.
        let later = node(dir.path(), &store, &rt);
        assert_eq!(served(&later), (new_epoch, after));
    }

    /// The load reads the signatures a second time when the scan built while reading cannot
    /// be served (a newer calibration was committed meanwhile, or a recalibration on a sample
    /// of the corpus). A store that fails during that read fails the load with its error, on
    /// both paths, instead of serving the shapes read before the failure as the whole corpus.
    #[test]
    fn a_store_that_fails_during_the_second_read_fails_the_load() {
        use std::sync::atomic::Ordering;
        let meshes = meshes();
        let OnFaulty {
            app: first,
            store,
            faulty,
            rt,
            dir,
        } = OnFaulty::start(meshes.len(), |_| {});
        drop(first);
        let reader = node_with(dir.path(), &store, &rt, |c| c.calibration_sample = 3);
        let (epoch, rows) = served(&reader);
        assert_eq!(rows.len(), meshes.len());
        // `json` committed as the next epoch, computed on every shape.
        let commit = |json: Vec<u8>| {
            let lock = rt.block_on(store.lock_calibration()).unwrap();
            let next = lock.next_epoch();
            rt.block_on(lock.commit_as(next, meshes.len() as u64, json))
                .unwrap();
            next
        };
        let expect_failure = |loaded: Loaded, path: &str| {
            faulty.fail_scans.store(true, Ordering::SeqCst);
            let got = reader.calibrated_scan(loaded);
            faulty.fail_scans.store(false, Ordering::SeqCst);
            match got {
                Err(e) => assert!(e.to_string().contains("injected"), "{path}: {e}"),
                Ok(scan) => panic!("{path}: the load served {} of 6 shapes", scan.len()),
            }
        };

        // A newer calibration that fits, committed between the read and the lock.
        let loaded = reader.load_signatures().unwrap();
        assert_eq!(loaded.encoded_under, Some(epoch));
        let cal =
            serde_json::to_vec(&**reader.scan.read().unwrap().calibration().unwrap()).unwrap();
        assert!(commit(cal) > epoch);
        expect_failure(loaded, "newer calibration");

        // No usable calibration: one is computed on a sample of 3, then every shape encoded.
        commit(b"[]".to_vec());
        let loaded = reader.load_signatures().unwrap();
        assert_eq!(loaded.encoded_under, None);
        expect_failure(loaded, "recalibration on a sample");

        // With the store back, the same load serves every shape.
        let back = node_with(dir.path(), &store, &rt, |c| c.calibration_sample = 3);
        assert_eq!(served(&back).1.len(), meshes.len());
    }

    /// A page shorter than asked for is not the end of the corpus (a backend leaves out a
    /// record whose signature is missing): the load reads on until an empty page.
    #[test]
    fn short_pages_do_not_end_the_load() {
        use std::sync::atomic::Ordering;
        let OnFaulty {
            app: first,
            store,
            faulty,
            rt,
            dir,
        } = OnFaulty::start(meshes().len(), |_| {});
        let whole = served(&first);
        drop(first);
        faulty.page_cap.store(2, Ordering::SeqCst);
        // The stored calibration's path (the scan built while reading) ...
        let loaded = served(&node(dir.path(), &store, &rt));
        assert_eq!(loaded.1.len(), whole.1.len(), "every shape loaded");
        assert!(loaded == whole, "the same scan");
        let n = rt
            .block_on(crate::storage::for_each_signature(
                &*store,
                5,
                |_, _| Ok(()),
            ))
            .unwrap();
        assert_eq!(n, 6);
        // ... and a recalibration at load on a sample of the shapes, every shape then encoded
        // from a second read of the store.
        let lock = rt.block_on(store.lock_calibration()).unwrap();
        let epoch = lock.next_epoch();
        let json = b"[]".to_vec(); // a calibration no engine reads: recalibrate
        rt.block_on(lock.commit_as(epoch, 6, json)).unwrap();
        let again = node_with(dir.path(), &store, &rt, |c| c.calibration_sample = 3);
        let (e, rows) = served(&again);
        assert!(e > epoch);
        assert_eq!(rows.len(), 6);
    }

    /// `n` of the test meshes ingested into a sled node in a new directory: the directory and
    /// the ids in scan order (the node is closed again).
    fn stored(n: usize) -> (tempfile::TempDir, Vec<String>) {
        let dir = tempfile::tempdir().unwrap();
        let ids = {
            let rt = runtime();
            let store = sled_store(dir.path(), &rt);
            let first = Arc::new(node(dir.path(), &store, &rt));
            for (i, m) in meshes()[..n].iter().enumerate() {
                ingest(&first, &rt, m, &format!("s{i}"));
            }
            wait_idle(&first);
            served(&first).1.into_iter().map(|(id, _)| id).collect()
        };
        (dir, ids)
    }

    /// Flips one byte (at `at` of its length) of the first piece of the chunked value of `id`
    /// in `tree` (its key: the id, then the piece's index as 4 bytes).
    fn flip_first_piece(tree: &sled::Tree, id: &str, at: impl Fn(usize) -> usize) {
        let mut key = id.as_bytes().to_vec();
        key.extend_from_slice(&0u32.to_be_bytes());
        let mut piece = tree.get(&key).unwrap().expect("a first piece").to_vec();
        let i = at(piece.len());
        piece[i] ^= 0x5a;
        tree.insert(&key[..], piece).unwrap();
    }

    /// A signature damaged on disk (sled's checksum of the value fails) is recomputed from its
    /// original at the next start and stored again: the node serves every shape. Before, the
    /// load failed on that one shape and `serve` exited.
    #[test]
    fn a_signature_damaged_on_disk_is_recomputed_at_load() {
        let (dir, ids) = stored(3);
        let (whole, damaged) = (ids.len(), ids[1].clone());
        {
            let db = crate::index::store::open_db(&dir.path().join("db")).unwrap();
            let tree = db.open_tree(crate::index::store::SIGNATURE_CHUNKS).unwrap();
            flip_first_piece(&tree, &damaged, |n| n / 2);
            db.flush().unwrap();
        }
        let rt = runtime();
        let store = sled_store(dir.path(), &rt);
        let e = rt.block_on(store.signature(&damaged)).unwrap_err();
        assert!(matches!(e, crate::Error::Corrupt { .. }), "{e:?}");
        let app = node(dir.path(), &store, &rt);
        let (_, rows) = served(&app);
        assert_eq!(rows.len(), whole, "every shape served");
        let bytes = rt.block_on(store.signature(&damaged)).unwrap().unwrap();
        app.engine
            .decode_signature(&bytes)
            .expect("the recomputed signature was stored");
    }

    /// A shape whose signature must be recomputed and cannot be — its original no longer
    /// reads as a mesh, or is damaged on disk — is left out of the index (logged), and the node
    /// serves every other shape. Before, `serve` exited on it: one shape could keep a whole
    /// index offline after an upgrade.
    #[test]
    fn a_shape_that_cannot_be_recomputed_is_left_out_and_the_others_are_served() {
        let (dir, ids) = stored(4);
        assert_eq!(ids.len(), 4);
        let (unreadable, damaged) = (ids[1].clone(), ids[2].clone());
        {
            let db = crate::index::store::open_db(&dir.path().join("db")).unwrap();
            let signatures = db.open_tree(crate::index::store::SIGNATURE_CHUNKS).unwrap();
            let originals = db.open_tree(crate::index::store::MESH_CHUNKS).unwrap();
            for id in [&unreadable, &damaged] {
                // Both signatures unreadable, so both must be recomputed.
                flip_first_piece(&signatures, id, |_| 0);
            }
            // One original replaced whole (checksums intact) by bytes that are no mesh.
            originals
                .transaction(|t| {
                    crate::index::store::put_chunked(t, unreadable.as_bytes(), b"not a mesh")
                })
                .unwrap();
            // The other's first piece flipped: the store reports it damaged.
            flip_first_piece(&originals, &damaged, |_| 0);
            db.flush().unwrap();
        }
        let rt = runtime();
        let store = sled_store(dir.path(), &rt);
        let app = node(dir.path(), &store, &rt);
        let mut rows: Vec<String> = served(&app).1.into_iter().map(|(id, _)| id).collect();
        rows.sort();
        let mut others = vec![ids[0].clone(), ids[3].clone()];
        others.sort();
        assert_eq!(rows, others, "the two others served");
        assert_eq!(
            app.left_out.lock().unwrap().len(),
            2,
            "counted in GET /v1/index"
        );
        // Still stored, so a later start (or a mended original) can bring them back.
        for id in [&unreadable, &damaged] {
            assert!(rt.block_on(store.get(id)).unwrap().is_some(), "{id} kept");
        }
    }

    /// A shape left out at start is not analysed again by the same node (a cluster node's
    /// reconciliation every few seconds, an upload of the same bytes): only the next start
    /// tries again, and serves it once its original reads. Before, each reconciliation ran the
    /// failing analysis again on the heavy lane.
    #[test]
    fn a_shape_left_out_is_tried_again_at_the_next_start_only() {
        let (dir, ids) = stored(3);
        let left = ids[1].clone();
        {
            // Its signature of another spec (as after an upgrade): to be recomputed.
            let db = crate::index::store::open_db(&dir.path().join("db")).unwrap();
            let shapes = db.open_tree("shapes").unwrap();
            let mut rec: ShapeRecord =
                serde_json::from_slice(&shapes.get(left.as_bytes()).unwrap().unwrap()).unwrap();
            rec.spec_key = "an earlier spec".into();
            shapes
                .insert(left.as_bytes(), serde_json::to_vec(&rec).unwrap())
                .unwrap();
            db.flush().unwrap();
        }
        {
            let rt = runtime();
            let faulty = Arc::new(crate::storage::faulty::Faulty::new(sled_store(
                dir.path(),
                &rt,
            )));
            faulty
                .corrupt_originals
                .lock()
                .unwrap()
                .insert(left.clone());
            let store: Arc<dyn ShapeStore> = faulty.clone();
            let app = Arc::new(node(dir.path(), &store, &rt));
            assert_eq!(served(&app).1.len(), 2);
            assert!(app.is_left_out(&left));
            // The original reads again; the node that left the shape out does not try it.
            faulty.corrupt_originals.lock().unwrap().clear();
            rt.block_on(app.apply_insert(&left)).unwrap();
            let rows: Vec<String> = served(&app).1.into_iter().map(|(id, _)| id).collect();
            assert_eq!(rows.len(), 2, "not analysed again before the next start");
            assert!(!rows.contains(&left));
        }
        let rt = runtime();
        let store = sled_store(dir.path(), &rt);
        let app = node(dir.path(), &store, &rt);
        let rows: Vec<String> = served(&app).1.into_iter().map(|(id, _)| id).collect();
        assert_eq!(rows.len(), 3, "the next start recomputed it");
        assert!(rows.contains(&left));
    }
}
