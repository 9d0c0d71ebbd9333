//! A store for tests that fails on demand: every call goes to the wrapped store except those
//! switched to fail, which answer [`Error::Storage`] (a database that went away, a full disk).

use super::{
    Backend, CalibrationLock, InsertOutcome, LockHolder, NewShape, Page, ShapeRecord, ShapeStore,
    StoredCalibration,
};
use crate::{Error, Result};
use async_trait::async_trait;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// A test's hook, called with a shape's id.
pub(crate) type IdHook = Arc<dyn Fn(&str) + Send + Sync>;

/// The wrapped store and the switches.
pub(crate) struct Faulty {
    inner: Arc<dyn ShapeStore>,
    /// Calibration commits fail (the lock is released, nothing written).
    pub fail_commits: Arc<AtomicBool>,
    /// Calibration commits tried, failed or not.
    pub commits_tried: Arc<AtomicUsize>,
    /// Reads of a shape's signature (`signature`) fail.
    pub fail_signature_reads: AtomicBool,
    /// Called on every read of a shape's signature (`signature`), before it.
    pub on_signature_read: Mutex<Option<Arc<dyn Fn() + Send + Sync>>>,
    /// Called with the id after each insert that stored a new shape, before it returns.
    pub after_insert: Mutex<Option<IdHook>>,
    /// An insert that stored a new shape answers an error all the same (a flush that failed
    /// after the commit, a commit whose acknowledgement was lost).
    pub fail_after_insert: AtomicBool,
    /// Called after each page of `list` was read, before it returns.
    pub after_list: Mutex<Option<Arc<dyn Fn() + Send + Sync>>>,
    /// Reads of a page of signatures (`scan_signatures`) fail.
    pub fail_scans: AtomicBool,
    /// Pages of `scan_signatures` hold at most this many (0: no cap): short pages before the
    /// end, as a backend may return.
    pub page_cap: AtomicUsize,
    /// The originals of these shapes read as damaged on disk ([`Error::Corrupt`]).
    pub corrupt_originals: Mutex<std::collections::HashSet<String>>,
}

impl Faulty {
    pub(crate) fn new(inner: Arc<dyn ShapeStore>) -> Faulty {
        Faulty {
            inner,
            fail_commits: Arc::new(AtomicBool::new(false)),
            commits_tried: Arc::new(AtomicUsize::new(0)),
            fail_signature_reads: AtomicBool::new(false),
            fail_scans: AtomicBool::new(false),
            on_signature_read: Mutex::new(None),
            after_insert: Mutex::new(None),
            fail_after_insert: AtomicBool::new(false),
            after_list: Mutex::new(None),
            page_cap: AtomicUsize::new(0),
            corrupt_originals: Mutex::default(),
        }
    }

    fn injected(what: &str) -> Error {
        Error::Storage(format!("injected failure: {what}"))
    }

    fn wrap(&self, lock: CalibrationLock) -> CalibrationLock {
        CalibrationLock::new(
            lock.current.clone(),
            Box::new(Holder {
                inner: lock,
                fail: self.fail_commits.clone(),
                tried: self.commits_tried.clone(),
            }),
        )
    }
}

struct Holder {
    inner: CalibrationLock,
    fail: Arc<AtomicBool>,
    tried: Arc<AtomicUsize>,
}

#[async_trait]
impl LockHolder for Holder {
    async fn commit(self: Box<Self>, cal: &StoredCalibration) -> Result<()> {
        self.tried.fetch_add(1, Ordering::SeqCst);
        if self.fail.load(Ordering::SeqCst) {
            self.inner.release().await?;
            return Err(Faulty::injected("calibration commit"));
        }
        self.inner.inner.commit(cal).await
    }

    async fn release(self: Box<Self>) -> Result<()> {
        self.inner.release().await
    }
}

#[async_trait]
impl ShapeStore for Faulty {
    fn backend(&self) -> Backend {
        self.inner.backend()
    }
    async fn schema_version(&self) -> Result<u32> {
        self.inner.schema_version().await
    }
    async fn new_id(&self) -> Result<String> {
        self.inner.new_id().await
    }
    async fn insert(&self, shape: NewShape) -> Result<InsertOutcome> {
        let out = self.inner.insert(shape).await?;
        if let InsertOutcome::Inserted(id) = &out {
            let hook = self.after_insert.lock().unwrap().clone();
            if let Some(f) = hook {
                f(id);
            }
            if self.fail_after_insert.load(Ordering::SeqCst) {
                return Err(Faulty::injected("insert (stored all the same)"));
            }
        }
        Ok(out)
    }
    async fn id_for_hash(&self, sha256: &[u8; 32]) -> Result<Option<String>> {
        self.inner.id_for_hash(sha256).await
    }
    async fn delete(&self, id: &str) -> Result<bool> {
        self.inner.delete(id).await
    }
    async fn get(&self, id: &str) -> Result<Option<ShapeRecord>> {
        self.inner.get(id).await
    }
    async fn list(&self, after: Option<&str>, tag: Option<&str>, limit: usize) -> Result<Page> {
        let page = self.inner.list(after, tag, limit).await?;
        let hook = self.after_list.lock().unwrap().clone();
        if let Some(f) = hook {
            f();
        }
        Ok(page)
    }
    async fn signature(&self, id: &str) -> Result<Option<Vec<u8>>> {
        // Called outside the switch's lock: reads in parallel stay parallel.
        let hook = self.on_signature_read.lock().unwrap().clone();
        if let Some(f) = hook {
            f();
        }
        if self.fail_signature_reads.load(Ordering::SeqCst) {
            return Err(Faulty::injected("signature read"));
        }
        self.inner.signature(id).await
    }
    async fn mesh(&self, id: &str) -> Result<Option<Vec<u8>>> {
        if self.corrupt_originals.lock().unwrap().contains(id) {
            return Err(Error::corrupt("original", Some(id), "injected damage"));
        }
        self.inner.mesh(id).await
    }
    async fn payload(&self, id: &str) -> Result<Option<Vec<u8>>> {
        self.inner.payload(id).await
    }
    async fn replace_signature(
        &self,
        record: &ShapeRecord,
        signature: &[u8],
        payload: Option<&[u8]>,
    ) -> Result<bool> {
        self.inner
            .replace_signature(record, signature, payload)
            .await
    }
    async fn scan_signatures(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<(ShapeRecord, Vec<u8>)>> {
        if self.fail_scans.load(Ordering::SeqCst) {
            return Err(Faulty::injected("page of signatures"));
        }
        let limit = match self.page_cap.load(Ordering::SeqCst) {
            0 => limit,
            cap => limit.min(cap),
        };
        self.inner.scan_signatures(after, limit).await
    }
    async fn count(&self) -> Result<u64> {
        self.inner.count().await
    }
    async fn size_on_disk(&self) -> Result<u64> {
        self.inner.size_on_disk().await
    }
    async fn calibration(&self) -> Result<Option<StoredCalibration>> {
        self.inner.calibration().await
    }
    async fn lock_calibration(&self) -> Result<CalibrationLock> {
        Ok(self.wrap(self.inner.lock_calibration().await?))
    }
    async fn try_lock_calibration(&self) -> Result<Option<CalibrationLock>> {
        Ok(self
            .inner
            .try_lock_calibration()
            .await?
            .map(|l| self.wrap(l)))
    }
    async fn meta_get(&self, key: &str) -> Result<Option<Vec<u8>>> {
        self.inner.meta_get(key).await
    }
    async fn meta_set(&self, key: &str, value: &[u8]) -> Result<()> {
        self.inner.meta_set(key, value).await
    }
    async fn flush(&self) -> Result<()> {
        self.inner.flush().await
    }
}
