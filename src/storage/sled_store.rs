//! The sled backend of [`ShapeStore`]: the existing [`crate::index::Store`] (schema version 2,
//! `migrations/0001_initial.md`, `0002_payloads.md`), adapted through its public methods only,
//! every call on tokio's blocking pool. The on-disk format is unchanged.
//!
//! Calibration is kept where the server keeps it today, `meta/calibration` as
//! `{"calibrated_on": n, "epoch": e, "calibration": <engine JSON>}`: the same document the
//! server reads (it ignores the extra `epoch`); a document written without `epoch` takes it from
//! `calibration.epoch` (the engine's own field). The calibration lock is a mutex shared by every
//! clone of one [`SledStorage`]; sled's directory lock keeps other processes out, so that is the
//! whole of the exclusion a sled index needs.

use super::{
    check_meta_key, join_err, parse_cursor, parse_id, Backend, CalibrationLock, InsertOutcome,
    LockHolder, NewShape, Page, ShapeStore, StoredCalibration,
};
use crate::index::store::{storage_err, Inserted, ShapeRecord, Store, SCHEMA_VERSION};
use crate::{Error, Result};
use async_trait::async_trait;
use std::path::Path;
use std::sync::Arc;

/// The embedded sled store behind the [`ShapeStore`] seam.
#[derive(Clone)]
pub struct SledStorage {
    store: Store,
    cal_lock: Arc<tokio::sync::Mutex<()>>,
}

impl SledStorage {
    /// Opens (or creates) the index in `dir` ([`Store::open`]: a new index is stamped with the
    /// build's schema version, an older or newer one is refused). Blocking.
    pub fn open(dir: &Path) -> Result<SledStorage> {
        SledStorage::open_with_cache(dir, crate::index::store::DEFAULT_CACHE_BYTES)
    }

    /// [`SledStorage::open`] with a page cache of `cache_bytes` ([`Store::open_with_cache`]).
    pub fn open_with_cache(dir: &Path, cache_bytes: u64) -> Result<SledStorage> {
        Ok(SledStorage::from_store(Store::open_with_cache(
            dir,
            cache_bytes,
        )?))
    }

    /// Wraps an open store.
    pub fn from_store(store: Store) -> SledStorage {
        SledStorage {
            store,
            cal_lock: Arc::new(tokio::sync::Mutex::new(())),
        }
    }

    /// The wrapped store.
    pub fn store(&self) -> &Store {
        &self.store
    }

    /// Runs `f` on the store: on the blocking pool, or on the calling thread when that is a
    /// blocking thread already ([`super::on_blocking_thread`]).
    async fn run<T, F>(&self, f: F) -> Result<T>
    where
        T: Send + 'static,
        F: FnOnce(&Store) -> Result<T> + Send + 'static,
    {
        let store = self.store.clone();
        blocking(move || f(&store)).await
    }

    /// Runs `f` on the shape `id` names; a string that is no id names none (as PostgreSQL's
    /// `key`), and `f` is not run: sled's keys are raw bytes, and an id followed by four more
    /// bytes is the key of one of its pieces (read as the head of a value, it was "corrupt").
    async fn on_id<T, F>(&self, id: &str, absent: T, f: F) -> Result<T>
    where
        T: Send + 'static,
        F: FnOnce(&Store, &str) -> Result<T> + Send + 'static,
    {
        if parse_id(id).is_none() {
            return Ok(absent);
        }
        let id = id.to_string();
        self.run(move |s| f(s, &id)).await
    }

    async fn read_calibration(&self) -> Result<Option<StoredCalibration>> {
        let raw = self.run(|s| s.calibration()).await?;
        raw.map(|b| decode_calibration(&b)).transpose()
    }

    fn lock_from(&self, guard: tokio::sync::OwnedMutexGuard<()>) -> SledLock {
        SledLock {
            store: self.store.clone(),
            _guard: guard,
        }
    }
}

/// The stored calibration document of the sled `meta` tree. The engine's JSON is taken back
/// verbatim from a document [`encode_calibration`] wrote (its layout is fixed, the engine JSON
/// last); from any other document (the server's own, today) it is re-serialised from the parsed
/// value, which keeps every number exactly (`float_roundtrip`) but not necessarily key order.
fn decode_calibration(bytes: &[u8]) -> Result<StoredCalibration> {
    let corrupt = |what: String| {
        storage_err(format!(
            "stored calibration is unreadable (meta/calibration): {what}"
        ))
    };
    let doc: serde_json::Value =
        serde_json::from_slice(bytes).map_err(|e| corrupt(e.to_string()))?;
    let calibrated_on = doc
        .get("calibrated_on")
        .and_then(|v| v.as_u64())
        .ok_or_else(|| corrupt("no calibrated_on".into()))?;
    let inner = doc
        .get("calibration")
        .ok_or_else(|| corrupt("no calibration".into()))?;
    let epoch = doc
        .get("epoch")
        .or_else(|| inner.get("epoch"))
        .and_then(|v| v.as_u64())
        .ok_or_else(|| corrupt("no epoch".into()))?;
    let prefix = document_prefix(calibrated_on, epoch);
    let verbatim = bytes
        .strip_prefix(prefix.as_bytes())
        .and_then(|rest| rest.strip_suffix(b"}"))
        .filter(|raw| {
            serde_json::from_slice::<serde_json::Value>(raw)
                .ok()
                .as_ref()
                == Some(inner)
        });
    let json = match verbatim {
        Some(raw) => raw.to_vec(),
        None => serde_json::to_vec(inner).map_err(|e| corrupt(e.to_string()))?,
    };
    Ok(StoredCalibration {
        epoch,
        calibrated_on,
        json,
    })
}

fn document_prefix(calibrated_on: u64, epoch: u64) -> String {
    format!("{{\"calibrated_on\":{calibrated_on},\"epoch\":{epoch},\"calibration\":")
}

/// `{"calibrated_on": n, "epoch": e, "calibration": <engine JSON verbatim>}`: the document the
/// server reads today (it ignores `epoch`), readable back byte for byte by [`decode_calibration`].
fn encode_calibration(cal: &StoredCalibration) -> Result<Vec<u8>> {
    let mut doc = document_prefix(cal.calibrated_on, cal.epoch).into_bytes();
    doc.extend_from_slice(&cal.json);
    doc.push(b'}');
    Ok(doc)
}

struct SledLock {
    store: Store,
    _guard: tokio::sync::OwnedMutexGuard<()>,
}

/// Runs the blocking `f` inline on a thread that may block ([`super::on_blocking_thread`]),
/// else on tokio's blocking pool.
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T> + Send + 'static) -> Result<T> {
    if super::may_block() {
        f()
    } else {
        tokio::task::spawn_blocking(f).await.map_err(join_err)?
    }
}

#[async_trait]
impl LockHolder for SledLock {
    async fn commit(self: Box<Self>, cal: &StoredCalibration) -> Result<()> {
        let doc = encode_calibration(cal)?;
        let store = self.store.clone();
        blocking(move || store.set_calibration(&doc)).await?;
        // The guard is released here, after the write is flushed.
        drop(self);
        Ok(())
    }

    async fn release(self: Box<Self>) -> Result<()> {
        Ok(())
    }
}

#[async_trait]
impl ShapeStore for SledStorage {
    fn backend(&self) -> Backend {
        Backend::Sled
    }

    async fn schema_version(&self) -> Result<u32> {
        // `Store::open` admits exactly this version.
        Ok(SCHEMA_VERSION)
    }

    async fn new_id(&self) -> Result<String> {
        self.run(|s| s.new_id()).await
    }

    async fn insert(&self, shape: NewShape) -> Result<InsertOutcome> {
        if shape.record.sha256 != hex::encode(shape.sha256) || parse_id(&shape.record.id).is_none()
        {
            return Err(Error::InvalidArgument(
                "new shape: record.sha256 must be the hex of sha256 and record.id an id".into(),
            ));
        }
        self.run(move |s| {
            Ok(
                match s.insert(
                    &shape.record,
                    &shape.sha256,
                    &shape.signature,
                    &shape.original,
                    shape.payload.as_deref(),
                )? {
                    Inserted::New(id) => InsertOutcome::Inserted(id),
                    Inserted::Existing(id) => InsertOutcome::AlreadyPresent(id),
                },
            )
        })
        .await
    }

    async fn id_for_hash(&self, sha256: &[u8; 32]) -> Result<Option<String>> {
        let h = *sha256;
        self.run(move |s| s.id_for_hash(&h)).await
    }

    async fn delete(&self, id: &str) -> Result<bool> {
        self.on_id(id, false, |s, id| s.delete(id)).await
    }

    async fn get(&self, id: &str) -> Result<Option<ShapeRecord>> {
        self.on_id(id, None, |s, id| s.get(id)).await
    }

    async fn list(&self, after: Option<&str>, tag: Option<&str>, limit: usize) -> Result<Page> {
        parse_cursor(after)?;
        let (after, tag) = (after.map(str::to_string), tag.map(str::to_string));
        let (records, more) = self
            .run(move |s| s.list(after.as_deref(), tag.as_deref(), limit))
            .await?;
        Ok(Page { records, more })
    }

    async fn signature(&self, id: &str) -> Result<Option<Vec<u8>>> {
        self.on_id(id, None, |s, id| s.signature(id)).await
    }

    async fn mesh(&self, id: &str) -> Result<Option<Vec<u8>>> {
        self.on_id(id, None, |s, id| s.mesh(id)).await
    }

    async fn payload(&self, id: &str) -> Result<Option<Vec<u8>>> {
        self.on_id(id, None, |s, id| s.payload(id)).await
    }

    /// Not one transaction on sled (the public `Store` API has none covering payload and
    /// signature): the payload is written first, then record and signature together. A crash
    /// in between leaves the stale signature, so the next start recomputes both; a stale
    /// signature never sits beside a fresh payload it was not computed with.
    async fn replace_signature(
        &self,
        record: &ShapeRecord,
        signature: &[u8],
        payload: Option<&[u8]>,
    ) -> Result<bool> {
        let (rec, sig, pay) = (
            record.clone(),
            signature.to_vec(),
            payload.map(<[u8]>::to_vec),
        );
        self.run(move |s| s.replace_signature(&rec, &sig, pay.as_deref()))
            .await
    }

    async fn scan_signatures(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<(ShapeRecord, Vec<u8>)>> {
        parse_cursor(after)?;
        let after = after.map(str::to_string);
        self.run(move |s| {
            let (records, _) = s.list(after.as_deref(), None, limit)?;
            let mut out = Vec::with_capacity(records.len());
            for rec in records {
                // A shape deleted between the two reads is simply not part of the page; a
                // record without its signature (damage) is left out and said so. A signature
                // whose checksum fails (damage on disk) comes with no bytes, which decode as
                // no signature: a load recomputes it from the original and stores it again,
                // as it does a signature of another spec, instead of failing on one shape.
                match s.signature(&rec.id) {
                    Ok(Some(sig)) => out.push((rec, sig)),
                    Ok(None) if s.get(&rec.id)?.is_some() => {
                        tracing::error!(id = %rec.id, "stored shape without its signature; left out");
                    }
                    Ok(None) => {}
                    Err(e @ Error::Corrupt { .. }) => {
                        tracing::error!(id = %rec.id, error = %e, "damaged signature; passed on as unreadable");
                        out.push((rec, Vec::new()));
                    }
                    Err(e) => return Err(e),
                }
            }
            Ok(out)
        })
        .await
    }

    async fn count(&self) -> Result<u64> {
        self.run(|s| Ok(s.len() as u64)).await
    }

    async fn size_on_disk(&self) -> Result<u64> {
        self.run(|s| Ok(s.size_on_disk())).await
    }

    async fn calibration(&self) -> Result<Option<StoredCalibration>> {
        self.read_calibration().await
    }

    async fn lock_calibration(&self) -> Result<CalibrationLock> {
        let guard = self.cal_lock.clone().lock_owned().await;
        let current = self.read_calibration().await?;
        Ok(CalibrationLock::new(
            current,
            Box::new(self.lock_from(guard)),
        ))
    }

    async fn try_lock_calibration(&self) -> Result<Option<CalibrationLock>> {
        let Ok(guard) = self.cal_lock.clone().try_lock_owned() else {
            return Ok(None);
        };
        let current = self.read_calibration().await?;
        Ok(Some(CalibrationLock::new(
            current,
            Box::new(self.lock_from(guard)),
        )))
    }

    async fn meta_get(&self, key: &str) -> Result<Option<Vec<u8>>> {
        check_meta_key(key)?;
        let key = key.to_string();
        self.run(move |s| s.meta_get(&key)).await
    }

    async fn meta_set(&self, key: &str, value: &[u8]) -> Result<()> {
        check_meta_key(key)?;
        let (key, value) = (key.to_string(), value.to_vec());
        self.run(move |s| s.meta_set(&key, &value)).await
    }

    async fn flush(&self) -> Result<()> {
        self.run(|s| s.flush()).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_document_round_trips_and_reads_the_servers_format() {
        let cal = StoredCalibration {
            epoch: 7,
            calibrated_on: 120,
            json: br#"{"epoch":7,"w":[0.1,2.5e-17]}"#.to_vec(),
        };
        let doc = encode_calibration(&cal).unwrap();
        assert_eq!(decode_calibration(&doc).unwrap(), cal);
        // The document the server writes today: no top-level epoch.
        let server = br#"{"calibrated_on":3,"calibration":{"epoch":4,"x":1}}"#;
        let got = decode_calibration(server).unwrap();
        assert_eq!((got.epoch, got.calibrated_on), (4, 3));
        assert_eq!(got.json, br#"{"epoch":4,"x":1}"#.to_vec());
        // The server's document reads back as what the server deserialises.
        #[derive(serde::Deserialize)]
        struct ServerDoc {
            calibrated_on: usize,
            calibration: serde_json::Value,
        }
        let back: ServerDoc = serde_json::from_slice(&doc).unwrap();
        assert_eq!(back.calibrated_on, 120);
        assert_eq!(
            back.calibration,
            serde_json::from_slice::<serde_json::Value>(&cal.json).unwrap()
        );
        assert!(decode_calibration(b"{").is_err());
    }
}
