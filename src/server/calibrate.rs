//! Recalibration: when the corpus size moved by more than `recalibrate_fraction` since the
//! last calibration, a background task on the heavy lane's threads computes a new one and
//! installs it while searches go on.
//!
//! The epoch is assigned under the store's calibration lock (`try_lock_calibration`): when the
//! lock is held elsewhere (another node of a cluster), this node does nothing and the other's
//! epoch arrives through the store. Under the lock, a stored calibration newer than this
//! node's that still fits the corpus is installed as it is instead of computing another, so a
//! cluster computes each epoch once and every node ranks with the same calibration. The epoch
//! written is the stored one + 1, or this node's + 1 when that is larger (the provisional
//! calibration a first shape gets in memory counts as epoch 1 and is never stored).
//!
//! A calibration is installed only once it is committed: one the store refused (a lost
//! connection, a full disk) is dropped and the scan keeps the one it has until the next change
//! tries again. An install never replaces a newer epoch (installs run concurrently on a
//! cluster node, and one that began first may end last).
//!
//! Above `calibration_sample` shapes (or on a shard node) the calibration is computed on the
//! sample of `src/server/sample.rs` and every held shape re-encoded from its stored signature
//! one at a time, so a recalibration never holds more than that many signatures.

use super::load::moved;
use super::ms;
use super::sample::Sample;
use super::state::App;
use crate::queue::Change;
use crate::ranking::Calibration;
use crate::search::corpus::{Corpus, Encoded, Layout};
use crate::signature::Signature;
use rayon::prelude::*;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

/// Records per page when the stored shapes are listed for the calibration sample.
const LIST_PAGE: usize = 1000;

impl App {
    /// True when the index size moved by more than the configured fraction since the last
    /// calibration.
    pub(super) fn needs_recalibration(&self) -> bool {
        self.calibration_due(&self.scan.read().unwrap_or_else(|p| p.into_inner()))
    }

    /// After an insert or delete: gauges, and a background recalibration when the index size
    /// moved by more than the configured fraction (searches go on meanwhile).
    pub(super) fn after_change(self: &Arc<Self>) {
        self.update_gauges();
        if self.needs_recalibration() {
            self.clone().calibrate_in_background(false);
        }
    }

    /// Starts the recalibration loop unless it runs already; `provisional`: the scan's
    /// calibration was made in memory from its first shape and must be replaced by the
    /// store's (or a committed one) whatever the corpus size.
    pub(super) fn calibrate_in_background(self: Arc<Self>, provisional: bool) {
        if self.recalibrating.swap(true, Ordering::AcqRel) {
            return;
        }
        // Recalibration is CPU work no request waits for: it runs on the heavy lane's
        // threads, not beside cheap searches.
        tokio::task::spawn_blocking(move || {
            self.admission
                .on_heavy_pool(|| self.recalibrate_until_settled(provisional))
        });
    }

    /// Runs [`App::recalibrate_loop`] until the calibration fits the corpus, or until the
    /// lock is held elsewhere (that node's epoch arrives through the store; a cluster node's
    /// reconciliation tries again later) or the store refused the commit (the next change
    /// tries again).
    fn recalibrate_until_settled(&self, provisional: bool) {
        let mut provisional = provisional;
        loop {
            let yielded = self.recalibrate_loop(provisional);
            provisional = false;
            self.recalibrating.store(false, Ordering::Release);
            // A write that came between the last check and the reset saw the flag set and left
            // the work to this loop: check once more.
            if yielded
                || !self.needs_recalibration()
                || self.recalibrating.swap(true, Ordering::AcqRel)
            {
                return;
            }
        }
    }

    /// Recalibrates while the corpus moved; true when it stopped because the lock was held
    /// elsewhere or could not be taken, or the new calibration could not be committed.
    fn recalibrate_loop(&self, mut provisional: bool) -> bool {
        loop {
            let (n, local_epoch) = {
                let s = self.scan.read().unwrap_or_else(|p| p.into_inner());
                if !provisional && !self.calibration_due(&s) {
                    return false;
                }
                // The whole corpus: the store's for a sharded node (`src/server/shard.rs`).
                let n = self.corpus_size(&s);
                if n == 0 {
                    return false;
                }
                (
                    n,
                    s.calibration()
                        .map(|c| self.engine.calibration_epoch(c))
                        .unwrap_or(0),
                )
            };
            let lock = match self.block(self.store.try_lock_calibration()) {
                Ok(Some(lock)) => lock,
                Ok(None) => {
                    tracing::debug!("recalibration lock held elsewhere; skipped");
                    return true;
                }
                Err(e) => {
                    tracing::error!(error = %e, "could not take the calibration lock");
                    return true;
                }
            };
            // A newer stored calibration that still fits: install it instead of computing.
            let adopt = lock.current().and_then(|c| {
                let fits = !moved(c.calibrated_on as usize, n, self.cfg.recalibrate_fraction);
                let newer = c.epoch > local_epoch || (provisional && c.epoch >= local_epoch);
                if !(fits && newer) {
                    return None;
                }
                self.engine
                    .stored_calibration(&c.json)
                    .map(|cal| (cal, c.calibrated_on as usize))
            });
            provisional = false;
            if let Some((cal, on)) = adopt {
                if let Err(e) = self.block(lock.release()) {
                    tracing::warn!(error = %e, "releasing the calibration lock");
                }
                self.install(Arc::new(cal), on);
                continue;
            }
            let epoch = lock.next_epoch().max(local_epoch + 1);
            let t = Instant::now();
            let snapshot = self.scan.read().unwrap_or_else(|p| p.into_inner()).ids();
            let cap = self.cfg.calibration_sample;
            let (cal, on, encoded) =
                if self.shard().is_none() && (cap == 0 || snapshot.len() <= cap) {
                    // Every held shape: their signatures (not kept in memory) read from the store,
                    // outside the lock, once for the calibration and its encoding.
                    let sigs: Vec<(usize, Signature)> = snapshot
                        .par_iter()
                        .enumerate()
                        .filter_map(|(i, id)| self.stored_signature(id).map(|s| (i, s)))
                        .collect();
                    let cal = {
                        let refs: Vec<&Signature> = sigs.iter().map(|(_, s)| s).collect();
                        Arc::new(self.engine.calibrate(&refs, epoch))
                    };
                    let layout = Layout::of(&cal);
                    let mut encoded: Vec<Encoded> = vec![Encoded::absent(&layout); snapshot.len()];
                    let done: Vec<(usize, Encoded)> = sigs
                        .par_iter()
                        .map(|(i, s)| (*i, Encoded::from_signature(s, &cal, &layout)))
                        .collect();
                    drop(sigs);
                    for (i, e) in done {
                        encoded[i] = e;
                    }
                    (cal, snapshot.len(), encoded)
                } else {
                    // A large corpus, or a shard of one: the calibration sample of every stored
                    // shape (`src/server/sample.rs`), then each held shape re-encoded from its
                    // stored signature, one at a time.
                    let sample = self.stored_sample();
                    let on = sample.offered();
                    let cal = {
                        let sigs = sample.into_signatures();
                        let refs: Vec<&Signature> = sigs.iter().map(|(_, s)| s).collect();
                        Arc::new(self.engine.calibrate(&refs, epoch))
                    };
                    let encoded = self.reencoded(&snapshot, &cal);
                    (cal, on, encoded)
                };
            let layout = Layout::of(&cal);
            let corpus = Corpus::build(layout, &encoded);
            drop(encoded);
            if let Err(e) = self.commit_calibration(lock, epoch, on, &cal) {
                // Not installed: an epoch the store does not hold would be this node's alone
                // (its shards' peers could never match it, and a later commit of the same
                // epoch by another node would carry another calibration). The scan keeps the
                // calibration it has; the next change (or reconciliation) tries again.
                tracing::error!(
                    error = %e,
                    epoch,
                    "could not persist the calibration; kept the current one"
                );
                return true;
            }
            if let Some(bus) = self.cluster().map(|c| c.bus.clone()) {
                self.rt.spawn(async move {
                    if let Err(e) = bus.announce(&Change::Calibration { epoch }).await {
                        tracing::warn!(error = %e, "could not announce the calibration");
                    }
                });
            }
            if !self.install_built(cal, on, &snapshot, corpus) {
                continue;
            }
            tracing::info!(epoch, shapes = on, ms = ms(t), "recalibrated");
        }
    }

    /// The shapes `ids` encoded under `cal` from their stored signatures, each read, encoded
    /// and dropped in turn (absent when missing or unreadable).
    fn reencoded(&self, ids: &[String], cal: &Calibration) -> Vec<Encoded> {
        let layout = Layout::of(cal);
        ids.par_iter()
            .map(|id| match self.stored_signature(id) {
                Some(s) => Encoded::from_signature(&s, cal, &layout),
                None => Encoded::absent(&layout),
            })
            .collect()
    }

    /// Installs `cal` (computed on `on` shapes): every held shape re-encoded from its stored
    /// signature. Blocking, CPU-bound.
    pub(super) fn install(&self, cal: Arc<Calibration>, on: usize) {
        let snapshot = self.scan.read().unwrap_or_else(|p| p.into_inner()).ids();
        let encoded = self.reencoded(&snapshot, &cal);
        let corpus = Corpus::build(Layout::of(&cal), &encoded);
        drop(encoded);
        let epoch = self.engine.calibration_epoch(&cal);
        if self.install_built(cal, on, &snapshot, corpus) {
            tracing::info!(epoch, shapes = on, "installed the stored calibration");
        }
    }

    /// Installs `cal` with `corpus` (its encoding of `snapshot`), unless the scan holds a
    /// newer epoch by now: installs run concurrently (the replica's reconciliation, a
    /// coordinator that saw a newer epoch, this node's own recalibration), and one that began
    /// first may end last. False when skipped.
    fn install_built(
        &self,
        cal: Arc<Calibration>,
        on: usize,
        snapshot: &[String],
        corpus: Corpus,
    ) -> bool {
        let mut scan = self.scan.write().unwrap_or_else(|p| p.into_inner());
        let epoch = self.engine.calibration_epoch(&cal);
        if let Some(held) = scan.calibration().map(|c| self.engine.calibration_epoch(c)) {
            if held > epoch {
                tracing::info!(
                    epoch,
                    held,
                    "a newer calibration was installed meanwhile; skipped"
                );
                return false;
            }
        }
        scan.install_calibration(cal, on, snapshot, corpus, &mut |id, cal, layout| match self
            .stored_signature(id)
        {
            Some(s) => Encoded::from_signature(&s, cal, layout),
            None => Encoded::absent(layout),
        });
        drop(scan);
        self.update_gauges();
        true
    }

    /// The calibration sample of every stored shape (`src/server/sample.rs`): the records
    /// listed page by page, then the members' signatures read. A sharded node learns the whole
    /// corpus's size here too.
    fn stored_sample(&self) -> Sample {
        let mut sample = Sample::new(self.cfg.calibration_sample);
        let mut after: Option<String> = None;
        loop {
            let page = match self.block(self.store.list(after.as_deref(), None, LIST_PAGE)) {
                Ok(p) => p,
                Err(e) => {
                    tracing::error!(error = %e, "could not list the stored shapes");
                    break;
                }
            };
            for r in &page.records {
                sample.offer_id(&r.sha256, &r.id);
            }
            after = page.records.last().map(|r| r.id.clone());
            if !page.more || after.is_none() {
                break;
            }
        }
        if let Some(sh) = self.shard() {
            sh.set_total(sample.offered());
        }
        sample.fill(|id| self.stored_signature(id));
        sample
    }

    /// The stored signature of `id` (`None`, logged, when it is missing or unreadable).
    pub(super) fn stored_signature(&self, id: &str) -> Option<Signature> {
        match self.block(self.store.signature(id)) {
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::test_support::{ingest, meshes, node, runtime, served_epoch, wait_idle};
    use crate::storage::faulty::Faulty;
    use crate::storage::ShapeStore;

    /// A recalibration whose commit fails installs nothing: the node keeps ranking with the
    /// stored epoch (an epoch only it held would match no peer, and another node's later
    /// commit of the same number would be another calibration). The next change commits and
    /// installs one.
    #[test]
    fn a_calibration_that_could_not_be_committed_is_not_installed() {
        let dir = tempfile::tempdir().unwrap();
        let rt = runtime();
        let faulty = Arc::new(Faulty::new(crate::server::test_support::sled_store(
            dir.path(),
            &rt,
        )));
        let store: Arc<dyn ShapeStore> = faulty.clone();
        let app = Arc::new(node(dir.path(), &store, &rt));
        let meshes = meshes();
        for (i, m) in meshes[..3].iter().enumerate() {
            ingest(&app, &rt, m, &format!("s{i}"));
            wait_idle(&app);
        }
        let stored = || app.block(store.calibration()).unwrap().unwrap();
        let before = stored();
        assert_eq!(served_epoch(&app), before.epoch);
        assert_eq!(before.calibrated_on, 3);

        // Two more shapes move the corpus past `recalibrate_fraction`: the recalibration runs
        // and its commit fails.
        faulty.fail_commits.store(true, Ordering::SeqCst);
        let tried = faulty.commits_tried.load(Ordering::SeqCst);
        for (i, m) in meshes[3..5].iter().enumerate() {
            ingest(&app, &rt, m, &format!("t{i}"));
            wait_idle(&app);
        }
        assert!(
            faulty.commits_tried.load(Ordering::SeqCst) > tried,
            "a commit was tried"
        );
        assert_eq!(stored().epoch, before.epoch, "nothing committed");
        assert_eq!(served_epoch(&app), before.epoch, "nothing installed");
        assert_eq!(app.scan.read().unwrap().calibrated_on(), 3);
        assert!(app.needs_recalibration(), "still due");

        // The store works again: the next change recalibrates, commits and installs.
        faulty.fail_commits.store(false, Ordering::SeqCst);
        ingest(&app, &rt, &meshes[5], "u");
        wait_idle(&app);
        let after = stored();
        assert!(after.epoch > before.epoch);
        assert_eq!(after.calibrated_on, 6);
        assert_eq!(served_epoch(&app), after.epoch);
        assert!(!app.needs_recalibration());
    }

    /// An install that began under an older epoch and ends after a newer one was installed
    /// (installs run concurrently on a cluster node) leaves the newer one in place.
    #[test]
    fn an_older_calibration_never_replaces_a_newer_one() {
        let dir = tempfile::tempdir().unwrap();
        let rt = runtime();
        let store = crate::server::test_support::sled_store(dir.path(), &rt);
        let app = Arc::new(node(dir.path(), &store, &rt));
        for (i, m) in meshes().iter().enumerate() {
            ingest(&app, &rt, m, &format!("s{i}"));
            wait_idle(&app);
        }
        let held = served_epoch(&app);
        assert!(held > 1);
        let sigs: Vec<Signature> = app
            .scan
            .read()
            .unwrap()
            .ids()
            .iter()
            .map(|id| app.stored_signature(id).unwrap())
            .collect();
        let refs: Vec<&Signature> = sigs.iter().collect();
        let older = Arc::new(app.engine.calibrate(&refs, held - 1));
        app.install(older, sigs.len());
        assert_eq!(served_epoch(&app), held, "the newer epoch stays");
        let newer = Arc::new(app.engine.calibrate(&refs, held + 1));
        app.install(newer, sigs.len());
        assert_eq!(served_epoch(&app), held + 1, "a newer one is installed");
    }
}
