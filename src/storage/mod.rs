//! The storage seam: where shapes, original meshes, signatures, re-ranking payloads,
//! calibration and the schema version are kept, behind one trait with two backends.
//!
//! * [`sled_store::SledStorage`] — the embedded default: adapts [`crate::index::Store`] (a sled
//!   directory) through its public methods.
//! * [`postgres::PgStore`] — PostgreSQL as the system of record for a set of stateless nodes
//!   (issue 12), with versioned SQL migrations in `migrations/postgres/` applied by
//!   [`pg_migrate`].
//!
//! # Why an async, object-safe trait
//!
//! The PostgreSQL driver is asynchronous and the server already runs on tokio, so the trait is
//! async: a PostgreSQL call parks a task instead of a thread while it waits on the network and on
//! the commit's fsync. sled is synchronous and its writes flush to disk, so the sled backend runs
//! each call under [`tokio::task::spawn_blocking`]; the cost (one hop to the blocking pool) is
//! small against a flush, and a caller that is itself a blocking thread (the server's heavy
//! work and recalibration, inside [`on_blocking_thread`]) runs the call inline instead. The
//! backend is chosen at run time from the command line (`--data DIR` or
//! `--store postgres://…`), so the server holds an `Arc<dyn ShapeStore>`: the trait must be
//! dyn-compatible, which `async fn` in traits is not; `async_trait` boxes each future (one
//! allocation per call, nothing against a storage round trip). Methods take owned or borrowed
//! plain data and return owned bytes, so neither backend's types leak through the seam.
//!
//! # Guarantees, identical for both backends (tested by `tests/postgres.rs` on both)
//!
//! * [`ShapeStore::insert`] writes the record, the original mesh, the signature, the payload and
//!   the content-hash entry in **one transaction** and returns only after it is durable (sled:
//!   flushed; PostgreSQL: committed with the server's `synchronous_commit`). It is idempotent by
//!   the SHA-256 of the upload: when the hash is already stored — including by a concurrent
//!   insert of the same bytes — nothing is written and [`InsertOutcome::AlreadyPresent`] names
//!   the stored id.
//! * [`ShapeStore::delete`] removes every piece of a shape atomically.
//! * Ids are 16 lower-case hex digits of a monotonic counter ([`ShapeStore::new_id`]: sled's
//!   `generate_id`, a PostgreSQL sequence), so id order is allocation order. Listing and
//!   [`ShapeStore::scan_signatures`] page by id (keyset cursors, nothing held between pages).
//!   Ids are allocated before the transaction that uses them commits, so two concurrent ingests
//!   may become visible out of id order; a consumer that follows new shapes by cursor must allow
//!   for that (the change feed of issue 12 carries ids explicitly, see `docs/scale-out.md`).
//! * The calibration is written only through a [`CalibrationLock`]: one holder at a time (sled:
//!   an in-process mutex, sled's directory lock already excludes other processes; PostgreSQL: a
//!   row lock `SELECT … FOR UPDATE` on the one calibration row, held by a transaction and
//!   released by the database if the holder dies). The epoch is assigned under the lock
//!   (previous + 1), so epochs are global and increase by one per recalibration.
//! * Schema versions: each backend refuses, with a message that says what to do, to open data
//!   whose schema is older (migrate first) or newer (use a newer build) than this build's.

#[cfg(test)]
pub(crate) mod faulty;
pub mod pg_migrate;
pub mod postgres;
pub mod sled_store;

use crate::index::store::ShapeRecord;
use crate::{Error, Result};
use async_trait::async_trait;

thread_local! {
    static MAY_BLOCK: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` with this thread marked as one that may block: the sled backend's calls made
/// inside it (through a runtime's `block_on`) run inline instead of on tokio's blocking pool.
///
/// Why: a thread that tokio's blocking pool starts inherits the scheduling priority of the
/// thread that asked for it. The server's heavy work runs at a lower priority
/// (`ServerConfig::heavy_nice`); a store call it made from there started low-priority blocking
/// threads, which the pool then also gave to cheap searches, so that under a load of ingests a
/// cheap search could run at the heavy work's priority.
pub fn on_blocking_thread<T>(f: impl FnOnce() -> T) -> T {
    struct Reset(bool);
    impl Drop for Reset {
        fn drop(&mut self) {
            MAY_BLOCK.with(|c| c.set(self.0));
        }
    }
    let _reset = Reset(MAY_BLOCK.with(|c| c.replace(true)));
    f()
}

/// Whether this thread is inside [`on_blocking_thread`].
pub(crate) fn may_block() -> bool {
    MAY_BLOCK.with(|c| c.get())
}

pub use postgres::PgStore;
pub use sled_store::SledStorage;

/// One shape to store: everything [`ShapeStore::insert`] writes in its transaction.
#[derive(Debug, Clone)]
pub struct NewShape {
    /// The record; its `id` comes from [`ShapeStore::new_id`] and `sha256` is the hex of
    /// [`NewShape::sha256`].
    pub record: ShapeRecord,
    /// SHA-256 of `original` (the idempotency key).
    pub sha256: [u8; 32],
    /// Encoded signature.
    pub signature: Vec<u8>,
    /// The original upload, byte for byte.
    pub original: Vec<u8>,
    /// Encoded re-ranking payload, if any.
    pub payload: Option<Vec<u8>>,
}

/// What [`ShapeStore::insert`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum InsertOutcome {
    /// The shape was written (durably) under this id.
    Inserted(String),
    /// The same bytes are stored under this id; nothing was written.
    AlreadyPresent(String),
}

impl InsertOutcome {
    /// The id the content is stored under, either way.
    pub fn id(&self) -> &str {
        match self {
            InsertOutcome::Inserted(id) | InsertOutcome::AlreadyPresent(id) => id,
        }
    }
}

/// One page of [`ShapeStore::list`].
#[derive(Debug, Clone, PartialEq)]
pub struct Page {
    /// Records in id order.
    pub records: Vec<ShapeRecord>,
    /// True when more matching records follow the last one.
    pub more: bool,
}

/// The stored calibration: the engine's calibration as JSON, the epoch it was written under
/// and the number of shapes it was computed on.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredCalibration {
    /// 1 for the first calibration, +1 for each recalibration.
    pub epoch: u64,
    /// How many shapes the calibration saw.
    pub calibrated_on: u64,
    /// The engine's calibration, JSON (kept byte for byte as given).
    pub json: Vec<u8>,
}

/// Which backend a store is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// The embedded sled directory.
    Sled,
    /// A PostgreSQL database.
    Postgres,
}

/// The storage seam (see the module docs for the guarantees every implementation keeps).
#[async_trait]
pub trait ShapeStore: Send + Sync {
    /// Which backend this is.
    fn backend(&self) -> Backend;

    /// The schema version of the open data (equal to the build's: opening checks it).
    async fn schema_version(&self) -> Result<u32>;

    /// A fresh id: 16 lower-case hex digits of a monotonic counter.
    async fn new_id(&self) -> Result<String>;

    /// Writes one shape in one transaction, durable before it returns; idempotent by
    /// `shape.sha256` (see [`InsertOutcome`]).
    async fn insert(&self, shape: NewShape) -> Result<InsertOutcome>;

    /// The id stored under this content hash, if any.
    async fn id_for_hash(&self, sha256: &[u8; 32]) -> Result<Option<String>>;

    /// Deletes every piece of a shape in one transaction. False when absent.
    async fn delete(&self, id: &str) -> Result<bool>;

    /// The record of a shape.
    async fn get(&self, id: &str) -> Result<Option<ShapeRecord>>;

    /// Records in id order after `after` (exclusive; an id this store returned, else
    /// [`Error::InvalidArgument`]), carrying `tag` when given, at most `limit`.
    async fn list(&self, after: Option<&str>, tag: Option<&str>, limit: usize) -> Result<Page>;

    /// The stored signature bytes of a shape.
    async fn signature(&self, id: &str) -> Result<Option<Vec<u8>>>;

    /// The original upload of a shape.
    async fn mesh(&self, id: &str) -> Result<Option<Vec<u8>>>;

    /// The re-ranking payload of a shape (`None`: no such shape, or stored without one).
    async fn payload(&self, id: &str) -> Result<Option<Vec<u8>>>;

    /// Replaces the record (its spec key), signature and, when given, payload of an existing
    /// shape whose signature was computed with another spec, together. False (nothing written)
    /// when the shape is absent or stored with another content hash than `record.sha256`.
    async fn replace_signature(
        &self,
        record: &ShapeRecord,
        signature: &[u8],
        payload: Option<&[u8]>,
    ) -> Result<bool>;

    /// (record, signature) pairs in id order after `after` (exclusive), at most `limit`: page
    /// through the whole corpus (loading, recalibration) without holding it all, see
    /// [`for_each_signature`]. A page may be shorter than `limit` before the end (a record
    /// whose signature is missing is left out, logged); the end is an empty page. A signature
    /// found damaged (sled's checksums) comes as no bytes, which decode as no signature.
    async fn scan_signatures(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<(ShapeRecord, Vec<u8>)>>;

    /// Number of stored shapes.
    async fn count(&self) -> Result<u64>;

    /// Bytes the data takes on disk (backend's own estimate).
    async fn size_on_disk(&self) -> Result<u64>;

    /// The stored calibration, if any.
    async fn calibration(&self) -> Result<Option<StoredCalibration>>;

    /// Waits for, then takes, the calibration lock.
    async fn lock_calibration(&self) -> Result<CalibrationLock>;

    /// Takes the calibration lock when nobody holds it, else `None` at once.
    async fn try_lock_calibration(&self) -> Result<Option<CalibrationLock>>;

    /// A free `meta` value (`default_query`, `spec_key`, ...).
    async fn meta_get(&self, key: &str) -> Result<Option<Vec<u8>>>;

    /// Sets a free `meta` value, durably. `schema_version` and `calibration` are reserved.
    async fn meta_set(&self, key: &str, value: &[u8]) -> Result<()>;

    /// Makes everything written so far durable. Every write above already is when it returns;
    /// this is the shutdown's last word (sled: one more flush; PostgreSQL: nothing to do).
    async fn flush(&self) -> Result<()> {
        Ok(())
    }
}

/// Calls `f` on every (record, signature) pair in id order, `batch` at a time.
pub async fn for_each_signature<F>(store: &dyn ShapeStore, batch: usize, mut f: F) -> Result<u64>
where
    F: FnMut(ShapeRecord, Vec<u8>) -> Result<()> + Send,
{
    let mut after: Option<String> = None;
    let mut n = 0u64;
    loop {
        let page = store
            .scan_signatures(after.as_deref(), batch.max(1))
            .await?;
        // The end is an empty page (see `ShapeStore::scan_signatures`).
        let Some(last) = page.last().map(|(r, _)| r.id.clone()) else {
            return Ok(n);
        };
        for (rec, sig) in page {
            f(rec, sig)?;
            n += 1;
        }
        after = Some(last);
    }
}

/// The held calibration lock (see [`ShapeStore::lock_calibration`]): read the current
/// calibration, compute the next one with [`CalibrationLock::next_epoch`], then
/// [`CalibrationLock::commit`] it. Dropping it without committing releases it and changes
/// nothing.
pub struct CalibrationLock {
    current: Option<StoredCalibration>,
    inner: Box<dyn LockHolder>,
}

impl std::fmt::Debug for CalibrationLock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CalibrationLock")
            .field("current", &self.current)
            .finish_non_exhaustive()
    }
}

/// Backend side of a [`CalibrationLock`].
#[async_trait]
pub(crate) trait LockHolder: Send {
    /// Writes `cal` and releases the lock.
    async fn commit(self: Box<Self>, cal: &StoredCalibration) -> Result<()>;
    /// Releases the lock without writing.
    async fn release(self: Box<Self>) -> Result<()>;
}

impl CalibrationLock {
    pub(crate) fn new(current: Option<StoredCalibration>, inner: Box<dyn LockHolder>) -> Self {
        CalibrationLock { current, inner }
    }

    /// The calibration stored when the lock was taken (nobody can change it while held).
    pub fn current(&self) -> Option<&StoredCalibration> {
        self.current.as_ref()
    }

    /// The epoch [`CalibrationLock::commit`] will write: the current one + 1 (1 when none).
    pub fn next_epoch(&self) -> u64 {
        self.current.as_ref().map(|c| c.epoch).unwrap_or(0) + 1
    }

    /// Stores `json` (the engine's calibration, valid JSON) as epoch
    /// [`CalibrationLock::next_epoch`], computed on `calibrated_on` shapes, durably, and
    /// releases the lock.
    pub async fn commit(self, calibrated_on: u64, json: Vec<u8>) -> Result<StoredCalibration> {
        let epoch = self.next_epoch();
        self.commit_as(epoch, calibrated_on, json).await
    }

    /// [`CalibrationLock::commit`] as `epoch`, which must be at least
    /// [`CalibrationLock::next_epoch`] (epochs only grow; a server whose in-memory scan holds a
    /// provisional epoch that was never stored skips past it).
    pub async fn commit_as(
        self,
        epoch: u64,
        calibrated_on: u64,
        json: Vec<u8>,
    ) -> Result<StoredCalibration> {
        if epoch < self.next_epoch() {
            return Err(Error::InvalidArgument(format!(
                "calibration epoch {epoch} is not after the stored {}",
                self.next_epoch() - 1
            )));
        }
        serde_json::from_slice::<serde::de::IgnoredAny>(&json)
            .map_err(|e| Error::InvalidArgument(format!("calibration is not valid JSON: {e}")))?;
        let cal = StoredCalibration {
            epoch,
            calibrated_on,
            json,
        };
        self.inner.commit(&cal).await?;
        Ok(cal)
    }

    /// Releases the lock without writing anything.
    pub async fn release(self) -> Result<()> {
        self.inner.release().await
    }
}

/// Keys of `meta` that only the store itself writes.
pub(crate) const RESERVED_META: [&str; 2] = ["schema_version", "calibration"];

pub(crate) fn check_meta_key(key: &str) -> Result<()> {
    if RESERVED_META.contains(&key) || key.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "meta key {key:?} is reserved or empty"
        )));
    }
    Ok(())
}

/// Parses an id (16 lower-case hex digits) into its counter value; `None` when malformed.
pub fn parse_id(id: &str) -> Option<u64> {
    if id.len() != 16 || !id.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
        return None;
    }
    u64::from_str_radix(id, 16).ok()
}

/// Formats a counter value as an id.
pub fn format_id(n: u64) -> String {
    format!("{n:016x}")
}

/// Checks a listing cursor: it must be an id.
pub(crate) fn parse_cursor(after: Option<&str>) -> Result<Option<u64>> {
    after
        .map(|a| {
            parse_id(a).ok_or_else(|| {
                Error::InvalidArgument(format!(
                    "cursor {a:?}: expected an id (16 lower-case hex digits)"
                ))
            })
        })
        .transpose()
}

/// True for a `postgres://` or `postgresql://` URL.
pub fn is_postgres_url(target: &str) -> bool {
    target.starts_with("postgres://") || target.starts_with("postgresql://")
}

/// Opens the store named by `target`: a `postgres://` or `postgresql://` URL opens
/// [`PgStore`] (checking its schema version), anything else is a sled data directory.
pub async fn open(target: &str) -> Result<std::sync::Arc<dyn ShapeStore>> {
    if is_postgres_url(target) {
        Ok(std::sync::Arc::new(
            PgStore::connect(target, postgres::PoolOptions::default()).await?,
        ))
    } else {
        open_dir(std::path::PathBuf::from(target)).await
    }
}

/// Opens (or creates) the sled index in the data directory `dir`, with sled's default page
/// cache.
pub async fn open_dir(dir: std::path::PathBuf) -> Result<std::sync::Arc<dyn ShapeStore>> {
    open_dir_with_cache(dir, crate::index::store::DEFAULT_CACHE_BYTES).await
}

/// [`open_dir`] with a page cache of `cache_bytes`.
pub async fn open_dir_with_cache(
    dir: std::path::PathBuf,
    cache_bytes: u64,
) -> Result<std::sync::Arc<dyn ShapeStore>> {
    let s = tokio::task::spawn_blocking(move || SledStorage::open_with_cache(&dir, cache_bytes))
        .await
        .map_err(join_err)??;
    Ok(std::sync::Arc::new(s))
}

pub(crate) fn join_err(e: tokio::task::JoinError) -> Error {
    crate::index::store::storage_err(format!("storage task failed: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip_and_reject_malformed() {
        assert_eq!(format_id(0x2a), "000000000000002a");
        assert_eq!(parse_id("000000000000002a"), Some(0x2a));
        assert_eq!(parse_id(&format_id(u64::MAX)), Some(u64::MAX));
        for bad in [
            "",
            "2a",
            "000000000000002A",
            "000000000000002g",
            "0000000000000002a",
        ] {
            assert_eq!(parse_id(bad), None, "{bad}");
        }
        assert!(parse_cursor(Some("nope")).is_err());
        assert_eq!(parse_cursor(None).unwrap(), None);
    }

    #[test]
    fn reserved_meta_keys_are_refused() {
        assert!(check_meta_key("calibration").is_err());
        assert!(check_meta_key("schema_version").is_err());
        assert!(check_meta_key("").is_err());
        assert!(check_meta_key("spec_key").is_ok());
    }

    /// The mark holds inside, nests, and is cleared after, also after a panic.
    #[test]
    fn the_blocking_mark_is_scoped() {
        assert!(!may_block());
        on_blocking_thread(|| {
            assert!(may_block());
            on_blocking_thread(|| assert!(may_block()));
            assert!(may_block());
        });
        assert!(!may_block());
        let r = std::panic::catch_unwind(|| on_blocking_thread(|| panic!("inside")));
        assert!(r.is_err());
        assert!(!may_block());
    }
}
