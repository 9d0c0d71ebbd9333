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

/// What [`App::caught_up`] found.
enum CaughtUp {
    /// The scan holds a newer epoch: nothing to install.
    Newer,
    /// No shape added since the snapshot: its corpus as it was.
    Same(Corpus),
    /// The scan's ids of now and the corpus re-keyed to them.
    Rekeyed(Vec<String>, Corpus),
}

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
                    let read: crate::Result<Vec<Option<(usize, Signature)>>> = snapshot
                        .par_iter()
                        .enumerate()
                        .map(|(i, id)| Ok(self.read_signature(id)?.map(|s| (i, s))))
                        .collect();
                    let sigs: Vec<(usize, Signature)> = match read {
                        Ok(v) => v.into_iter().flatten().collect(),
                        Err(e) => return self.give_up(lock, &e),
                    };
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
                    let sample = match self.stored_sample() {
                        Ok(s) => s,
                        Err(e) => return self.give_up(lock, &e),
                    };
                    let on = sample.offered();
                    let cal = {
                        let sigs = sample.into_signatures();
                        let refs: Vec<&Signature> = sigs.iter().map(|(_, s)| s).collect();
                        Arc::new(self.engine.calibrate(&refs, epoch))
                    };
                    let encoded = match self.reencoded(&snapshot, &cal) {
                        Ok(e) => e,
                        Err(e) => return self.give_up(lock, &e),
                    };
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

    /// A recalibration given up because the store could not be read (`e`, logged): the lock
    /// released, nothing committed or installed; the next change (or reconciliation) tries
    /// again. True, as [`App::recalibrate_loop`] answers when it yields.
    fn give_up(&self, lock: crate::storage::CalibrationLock, e: &crate::Error) -> bool {
        tracing::error!(error = %e, "could not read the store; recalibration given up");
        if let Err(e) = self.block(lock.release()) {
            tracing::warn!(error = %e, "releasing the calibration lock");
        }
        true
    }

    /// The shapes `ids` encoded under `cal` from their stored signatures, each read, encoded
    /// and dropped in turn (absent when gone or undecodable); an error when the store could not
    /// be read (a shape made absent by a passing fault would stay unsearchable).
    fn reencoded(&self, ids: &[String], cal: &Calibration) -> crate::Result<Vec<Encoded>> {
        let layout = Layout::of(cal);
        ids.par_iter()
            .map(|id| self.encode_stored(id, cal, &layout))
            .collect()
    }

    /// Installs `cal` (computed on `on` shapes): every held shape re-encoded from its stored
    /// signature. Blocking, CPU-bound. Nothing changes when the store could not be read
    /// (logged; the caller's next reconciliation or search tries again).
    pub(super) fn install(&self, cal: Arc<Calibration>, on: usize) {
        let snapshot = self.scan.read().unwrap_or_else(|p| p.into_inner()).ids();
        let encoded = match self.reencoded(&snapshot, &cal) {
            Ok(e) => e,
            Err(e) => {
                tracing::error!(error = %e, "could not read the store; calibration not installed");
                return;
            }
        };
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
    /// first may end last. False when skipped, or when the store could not be read for the
    /// shapes added since the snapshot (logged; a later change or reconciliation tries again).
    fn install_built(
        &self,
        cal: Arc<Calibration>,
        on: usize,
        snapshot: &[String],
        corpus: Corpus,
    ) -> bool {
        let epoch = self.engine.calibration_epoch(&cal);
        let (now, corpus) = match self.caught_up(&cal, snapshot, corpus) {
            Ok(CaughtUp::Newer) => return false,
            Ok(CaughtUp::Same(corpus)) => (None, corpus),
            Ok(CaughtUp::Rekeyed(now, corpus)) => (Some(now), corpus),
            Err(e) => {
                tracing::error!(error = %e, epoch, "could not read the store; calibration not installed");
                return false;
            }
        };
        let snapshot = now.as_deref().unwrap_or(snapshot);
        let mut scan = self.scan.write().unwrap_or_else(|p| p.into_inner());
        if self.holds_newer(&scan, epoch) {
            return false;
        }
        scan.install_calibration(cal, on, snapshot, corpus, &mut |id, cal, layout| {
            self.encode_stored(id, cal, layout).unwrap_or_else(|e| {
                tracing::error!(id, error = %e, "could not read a stored signature");
                Encoded::absent(layout)
            })
        });
        drop(scan);
        self.update_gauges();
        true
    }

    /// True (logged) when `scan` holds a calibration newer than `epoch`.
    fn holds_newer(&self, scan: &crate::index::ScanIndex, epoch: u64) -> bool {
        let held = scan.calibration().map(|c| self.engine.calibration_epoch(c));
        let newer = held.is_some_and(|h| h > epoch);
        if newer {
            tracing::info!(
                epoch,
                held,
                "a newer calibration was installed meanwhile; skipped"
            );
        }
        newer
    }

    /// `corpus` (the encoding of `snapshot` under `cal`) brought up to the scan's ids of now,
    /// with those ids ([`CaughtUp`]): the shapes added since (the inserts during a
    /// recalibration) are read from the store and encoded here, before [`App::install_built`]
    /// takes the scan's write lock, under which every search waits. Under it only the rows are
    /// copied, and only the shapes added in between are read (one store round trip each on
    /// PostgreSQL). An error when the store could not be read (a shape made absent by a
    /// passing fault would stay unsearchable until the next calibration).
    fn caught_up(
        &self,
        cal: &Calibration,
        snapshot: &[String],
        corpus: Corpus,
    ) -> crate::Result<CaughtUp> {
        let now = {
            let scan = self.scan.read().unwrap_or_else(|p| p.into_inner());
            if self.holds_newer(&scan, self.engine.calibration_epoch(cal)) {
                return Ok(CaughtUp::Newer);
            }
            let added = (0..scan.len()).any(|i| {
                snapshot
                    .binary_search_by(|s| s.as_str().cmp(scan.id(i)))
                    .is_err()
            });
            if !added {
                // Deletions only: leaving rows out under the lock reads nothing.
                return Ok(CaughtUp::Same(corpus));
            }
            scan.ids()
        };
        let layout = corpus.layout().clone();
        let added: Vec<&String> = now
            .iter()
            .filter(|id| snapshot.binary_search(id).is_err())
            .collect();
        let fresh: Vec<Encoded> = added
            .par_iter()
            .map(|id| self.encode_stored(id, cal, &layout))
            .collect::<crate::Result<_>>()?;
        let mut fresh = fresh.into_iter();
        let corpus = crate::index::scan::rekey(
            &corpus,
            snapshot,
            now.iter().map(String::as_str),
            &mut |_| fresh.next().expect("one per added id, in order"),
        );
        Ok(CaughtUp::Rekeyed(now, corpus))
    }

    /// `id`'s stored signature encoded under `cal` (absent when the shape is gone or its
    /// signature does not decode); an error when the store could not be read.
    fn encode_stored(
        &self,
        id: &str,
        cal: &Calibration,
        layout: &Layout,
    ) -> crate::Result<Encoded> {
        Ok(match self.read_signature(id)? {
            Some(s) => Encoded::from_signature(&s, cal, layout),
            None => Encoded::absent(layout),
        })
    }

    /// The calibration sample of every stored shape (`src/server/sample.rs`): the records
    /// listed page by page, then the members' signatures read. A sharded node learns the whole
    /// corpus's size here too. An error when the store could not be read: a sample of part of
    /// the corpus would be committed for every node.
    fn stored_sample(&self) -> crate::Result<Sample> {
        let mut sample = Sample::new(self.cfg.calibration_sample);
        let mut after: Option<String> = None;
        loop {
            let page = self.block(self.store.list(after.as_deref(), None, LIST_PAGE))?;
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
        self.fill_sample(&mut sample)?;
        Ok(sample)
    }

    /// Reads the signatures of `sample`'s members; an error when the store could not be read
    /// (a calibration on the members that could be read would not be the sample's).
    pub(super) fn fill_sample(&self, sample: &mut Sample) -> crate::Result<()> {
        let failed = std::sync::Mutex::new(None);
        sample.fill(|id| match self.read_signature(id) {
            Ok(s) => s,
            Err(e) => {
                *failed.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                None
            }
        });
        match failed.into_inner().unwrap_or_else(|p| p.into_inner()) {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// The stored signature of `id`: `None` when the shape is gone, or its signature does not
    /// decode (logged); an error when the store could not be read.
    pub(super) fn read_signature(&self, id: &str) -> crate::Result<Option<Signature>> {
        Ok(match self.block(self.store.signature(id))? {
            Some(b) => match self.engine.decode_signature(&b) {
                Ok(s) => Some(s),
                Err(e) => {
                    tracing::error!(id, error = %e, "unreadable stored signature");
                    None
                }
            },
            None => None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::test_support::{
        ingest, meshes, node, runtime, served_epoch, wait_idle, OnFaulty,
    };

    /// A recalibration whose commit fails installs nothing: the node keeps ranking with the
    /// stored epoch (an epoch only it held would match no peer, and another node's later
    /// commit of the same number would be another calibration). The next change commits and
    /// installs one.
    #[test]
    fn a_calibration_that_could_not_be_committed_is_not_installed() {
        let n = OnFaulty::start(3, |_| {});
        let (app, rt, faulty) = (&n.app, &n.rt, &n.faulty);
        let meshes = meshes();
        let stored = || n.stored();
        let before = stored();
        assert_eq!(served_epoch(app), before.epoch);
        assert_eq!(before.calibrated_on, 3);

        // Two more shapes move the corpus past `recalibrate_fraction`: the recalibration runs
        // and its commit fails.
        faulty.fail_commits.store(true, Ordering::SeqCst);
        let tried = faulty.commits_tried.load(Ordering::SeqCst);
        for (i, m) in meshes[3..5].iter().enumerate() {
            ingest(app, rt, m, &format!("t{i}"));
            wait_idle(app);
        }
        assert!(
            faulty.commits_tried.load(Ordering::SeqCst) > tried,
            "a commit was tried"
        );
        assert_eq!(stored().epoch, before.epoch, "nothing committed");
        assert_eq!(served_epoch(app), before.epoch, "nothing installed");
        assert_eq!(app.scan.read().unwrap().calibrated_on(), 3);
        assert!(app.needs_recalibration(), "still due");

        // The store works again: the next change recalibrates, commits and installs.
        faulty.fail_commits.store(false, Ordering::SeqCst);
        ingest(app, rt, &meshes[5], "u");
        wait_idle(app);
        let after = stored();
        assert!(after.epoch > before.epoch);
        assert_eq!(after.calibrated_on, 6);
        assert_eq!(served_epoch(app), after.epoch);
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
            .map(|id| app.read_signature(id).unwrap().unwrap())
            .collect();
        let refs: Vec<&Signature> = sigs.iter().collect();
        let older = Arc::new(app.engine.calibrate(&refs, held - 1));
        app.install(older, sigs.len());
        assert_eq!(served_epoch(&app), held, "the newer epoch stays");
        let newer = Arc::new(app.engine.calibrate(&refs, held + 1));
        app.install(newer, sigs.len());
        assert_eq!(served_epoch(&app), held + 1, "a newer one is installed");
    }

    /// A recalibration that cannot read the store (signature reads fail) gives up: nothing
    /// committed, nothing installed, no shape made absent; once the store reads again the
    /// next change recalibrates. On both paths: every held shape's signature read, and a
    /// sample of the store (here 2 shapes).
    #[test]
    fn a_recalibration_that_cannot_read_the_store_changes_nothing() {
        for cap in [None, Some(2)] {
            let n = OnFaulty::start(3, |c| {
                if let Some(cap) = cap {
                    c.calibration_sample = cap;
                }
            });
            let (app, rt, faulty) = (&n.app, &n.rt, &n.faulty);
            let meshes = meshes();
            let stored = || n.stored();
            let before = stored();
            let rows = |n: usize| -> Vec<Encoded> {
                let s = app.scan.read().unwrap();
                (0..n).map(|at| s.corpus().encoded(at)).collect()
            };
            let held = rows(3);

            faulty.fail_signature_reads.store(true, Ordering::SeqCst);
            for (i, m) in meshes[3..5].iter().enumerate() {
                ingest(app, rt, m, &format!("t{i}"));
                wait_idle(app);
            }
            assert_eq!(stored().epoch, before.epoch, "{cap:?}: nothing committed");
            assert_eq!(
                served_epoch(app),
                before.epoch,
                "{cap:?}: nothing installed"
            );
            assert!(
                rows(3) == held,
                "{cap:?}: the held shapes keep their encodings"
            );
            assert!(app.needs_recalibration(), "{cap:?}: still due");

            faulty.fail_signature_reads.store(false, Ordering::SeqCst);
            ingest(app, rt, &meshes[5], "u");
            wait_idle(app);
            let after = stored();
            assert!(after.epoch > before.epoch, "{cap:?}");
            assert_eq!(after.calibrated_on, 6, "{cap:?}");
            assert_eq!(served_epoch(app), after.epoch, "{cap:?}");
        }
    }

    /// An install whose snapshot is older than the scan (shapes were added during the
    /// recalibration) reads the added shapes' signatures before it takes the scan's write
    /// lock: none while every search waits on it. It installs what an install from a fresh
    /// snapshot would.
    #[test]
    fn an_install_reads_the_shapes_added_since_its_snapshot_outside_the_write_lock() {
        use std::sync::atomic::AtomicUsize;
        let n = OnFaulty::start(3, |_| {});
        let (app, rt, faulty) = (&n.app, &n.rt, &n.faulty);
        for (i, m) in meshes()[3..].iter().enumerate() {
            ingest(app, rt, m, &format!("t{i}"));
            wait_idle(app);
        }
        let (cal, on, ids, rows) = {
            let s = app.scan.read().unwrap();
            let rows: Vec<Encoded> = (0..s.len()).map(|at| s.corpus().encoded(at)).collect();
            (
                s.calibration().unwrap().clone(),
                s.calibrated_on(),
                s.ids(),
                rows,
            )
        };
        assert_eq!(ids.len(), 6);
        // The encoding, under the held calibration, of a snapshot of every other shape.
        let snapshot: Vec<String> = ids.iter().step_by(2).cloned().collect();
        let corpus = Corpus::build(Layout::of(&cal), &app.reencoded(&snapshot, &cal).unwrap());

        let rows_now = || {
            let s = app.scan.read().unwrap();
            (0..s.len())
                .map(|at| s.corpus().encoded(at))
                .collect::<Vec<_>>()
        };
        // A store that cannot be read: nothing installed (an added shape made absent would stay
        // unsearchable until the next calibration).
        faulty.fail_signature_reads.store(true, Ordering::SeqCst);
        assert!(!app.install_built(cal.clone(), on, &snapshot, corpus.clone()));
        faulty.fail_signature_reads.store(false, Ordering::SeqCst);
        assert!(rows_now() == rows, "the rows as they were");

        let (reads, locked) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
        let (scan, r, l) = (app.scan.clone(), reads.clone(), locked.clone());
        *faulty.on_signature_read.lock().unwrap() = Some(Arc::new(move || {
            r.fetch_add(1, Ordering::SeqCst);
            // The only writer here is the install itself.
            if scan.try_read().is_err() {
                l.fetch_add(1, Ordering::SeqCst);
            }
        }));
        assert!(app.install_built(cal, on, &snapshot, corpus));
        *faulty.on_signature_read.lock().unwrap() = None;
        assert_eq!(reads.load(Ordering::SeqCst), 3, "the 3 shapes added since");
        assert_eq!(
            locked.load(Ordering::SeqCst),
            0,
            "signatures read under the scan's write lock"
        );
        assert_eq!(app.scan.read().unwrap().ids(), ids);
        assert!(rows_now() == rows);
    }

    /// A stored calibration newer than the node's is installed once however many callers ask
    /// at the same time (searches that met a shard at that epoch, the change feed, the
    /// reconciliation): the others find it installed. A caller with a deadline stops waiting
    /// at it while the install goes on.
    #[test]
    fn a_newer_stored_calibration_is_installed_once_and_waited_for_until_the_deadline() {
        use std::sync::atomic::AtomicUsize;
        use std::time::{Duration, Instant};
        let n = OnFaulty::start(3, |_| {});
        let (app, rt, faulty) = (&n.app, &n.rt, &n.faulty);
        let held = app.scan.read().unwrap().len();
        // The node's calibration committed again as the next epoch.
        let commit_next = || {
            let lock = rt.block_on(n.store.lock_calibration()).unwrap();
            let next = lock.next_epoch();
            let mut cal = (**app.scan.read().unwrap().calibration().unwrap()).clone();
            cal.epoch = next;
            let json = serde_json::to_vec(&cal).unwrap();
            rt.block_on(lock.commit_as(next, held as u64, json))
                .unwrap();
            next
        };
        let reads = Arc::new(AtomicUsize::new(0));
        let pause = Arc::new(AtomicUsize::new(0)); // ms slept per signature read
        let (r, p) = (reads.clone(), pause.clone());
        *faulty.on_signature_read.lock().unwrap() = Some(Arc::new(move || {
            r.fetch_add(1, Ordering::SeqCst);
            std::thread::sleep(Duration::from_millis(p.load(Ordering::SeqCst) as u64));
        }));

        let epoch = commit_next();
        rt.block_on(async {
            let asks: Vec<_> = (0..4).map(|_| app.adopt_stored_calibration()).collect();
            for r in futures_util::future::join_all(asks).await {
                r.unwrap();
            }
        });
        assert_eq!(app.epoch(), epoch);
        assert_eq!(
            reads.load(Ordering::SeqCst),
            held,
            "each held shape read once: one install for 4 callers"
        );

        // Every read now takes a second: the install takes at least two (3 reads, 2 threads).
        pause.store(1000, Ordering::SeqCst);
        let epoch = commit_next();
        let t = Instant::now();
        rt.block_on(app.adopt_until(Instant::now() + Duration::from_millis(50)))
            .unwrap();
        let waited = t.elapsed();
        assert!(
            waited < Duration::from_secs(1),
            "waited {waited:?} past a 50 ms deadline"
        );
        while app.epoch() != epoch {
            assert!(t.elapsed() < Duration::from_secs(30), "the install went on");
            std::thread::sleep(Duration::from_millis(20));
        }
        *faulty.on_signature_read.lock().unwrap() = None;
    }
}
