//! The sled store: trees, records, atomic writes and the schema version.
//!
//! Trees (schema version 3, see `migrations/0001_initial.md` to `0003_chunked_values.md`):
//!
//! | tree | key | value |
//! | --- | --- | --- |
//! | `meta` | `schema_version` | u32, big endian |
//! | `meta` | `calibration` | JSON of the engine's calibration (with its epoch) |
//! | `meta` | `default_query` | JSON of the default query spec |
//! | `meta` | `spec_key` | the signature spec key the stored signatures were computed with |
//! | `meta` | `created_at` | Unix milliseconds as decimal text (informational) |
//! | `shapes` | id | [`ShapeRecord`] as JSON |
//! | `signature_chunks` | id, and id + chunk | engine signature bytes, chunked (below) |
//! | `mesh_chunks` | id, and id + chunk | the original upload, byte for byte, chunked |
//! | `by_hash` | SHA-256 of the upload (32 bytes) | id |
//! | `payload_chunks` | id, and id + chunk | spectral Gromov–Wasserstein payload (`rerank::GwPayload::to_bytes`), chunked |
//!
//! **Chunked values.** A signature (≈ 80 KB with the default), a payload or an original is
//! stored as a head under the id (its length, u64, and the CRC-32 of its bytes, u32, little
//! endian) and its bytes in pieces of at most
//! [`CHUNK_BYTES`] under the id followed by the piece's number (u32, big endian), all written
//! and removed in the shape's transaction. Whole values of that size were what sled keeps in
//! memory once read, whatever its cache capacity: a node that had read 8.3 GB of signatures
//! held 8.8 GB; in pieces of 4 KB sled's cache evicts them (`docs/scale-out.md`). A value is
//! read without a transaction and checked against its head; one being replaced meanwhile is
//! read again, and after `CHUNKED_READ_ATTEMPTS` tries inside a transaction (`get_chunked`).
//!
//! sled is built from `vendor/sled`: 0.34.7 with a fix for a hang of the whole process under
//! writes that replace or delete values (`vendor/sled/PATCHES.md`).
//!
//! Errors: failures of sled itself (open, read, write, transaction, flush) and an index this build
//! cannot use as it is (another schema version, foreign data) are [`Error::Storage`]; stored bytes
//! that do not decode (a shape record, the schema version, a shape without its signature) are
//! [`Error::Corrupt`] with the shape id.
//!
//! Ids are 16 lower-case hex digits of a monotonic counter, so key order is ingest order.
//! A shape is written by one sled transaction over the five data trees, then the database is
//! flushed before the caller acknowledges it: after a crash a shape is wholly there or absent.

use crate::mesh::prepare::PrepareReport;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use sled::transaction::{ConflictableTransactionError, TransactionError, Transactional};
use std::path::{Path, PathBuf};

/// The on-disk schema version this build reads and writes.
pub const SCHEMA_VERSION: u32 = 3;

/// The largest piece of a chunked value (signatures, originals, payloads).
pub const CHUNK_BYTES: usize = 4096;

/// The trees of the chunked values (schema version 3).
pub(crate) const SIGNATURE_CHUNKS: &str = "signature_chunks";
pub(crate) const MESH_CHUNKS: &str = "mesh_chunks";
pub(crate) const PAYLOAD_CHUNKS: &str = "payload_chunks";

const KEY_SCHEMA: &[u8] = b"schema_version";
const KEY_CALIBRATION: &[u8] = b"calibration";
const KEY_DEFAULT_QUERY: &[u8] = b"default_query";
const KEY_SPEC: &[u8] = b"spec_key";
const KEY_CREATED: &[u8] = b"created_at";

/// One stored shape (the `shapes` tree value).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ShapeRecord {
    /// Id (16 hex digits).
    pub id: String,
    /// Display name.
    pub name: String,
    /// Free tags, used by filters.
    pub tags: Vec<String>,
    /// Source format name (`obj`, `glb`, ...).
    pub format: String,
    /// MIME type of the original's format (the download itself is `application/octet-stream`).
    pub content_type: String,
    /// Size of the original upload in bytes.
    pub bytes: u64,
    /// Vertex count as read.
    pub vertices: usize,
    /// Face count as read (triangles).
    pub faces: usize,
    /// Surface area as read (before normalisation).
    pub area: f64,
    /// SHA-256 of the upload, hex.
    pub sha256: String,
    /// Unix time of ingest, milliseconds.
    pub created_unix_ms: u64,
    /// What preparation found and changed.
    pub prepare: PrepareReport,
    /// Signature spec key the stored signature was computed with.
    pub spec_key: String,
}

/// One shape for [`Store::insert_batch`].
#[derive(Debug, Clone)]
pub struct BatchItem {
    /// The record.
    pub record: ShapeRecord,
    /// SHA-256 of `original`.
    pub sha256: [u8; 32],
    /// Encoded signature.
    pub signature: Vec<u8>,
    /// Original upload bytes.
    pub original: Vec<u8>,
    /// Encoded re-ranking payload, if any.
    pub payload: Option<Vec<u8>>,
}

/// The value of `key` in `tree`, copied out.
fn get_bytes(tree: &sled::Tree, key: &str) -> Result<Option<Vec<u8>>> {
    Ok(tree
        .get(key.as_bytes())
        .map_err(storage_err)?
        .map(|v| v.to_vec()))
}

/// The key of piece `i` of the chunked value of `id`.
fn chunk_key(id: &[u8], i: u32) -> Vec<u8> {
    let mut k = Vec::with_capacity(id.len() + 4);
    k.extend_from_slice(id);
    k.extend_from_slice(&i.to_be_bytes());
    k
}

/// The number of pieces of a chunked value of `len` bytes.
fn chunk_count(len: u64) -> Option<u32> {
    u32::try_from(len.div_ceil(CHUNK_BYTES as u64)).ok()
}

/// A chunked value's head: its length (u64) and the CRC-32 of its bytes (u32), little endian.
fn head_of(value: &[u8]) -> [u8; 12] {
    let mut h = [0u8; 12];
    h[..8].copy_from_slice(&(value.len() as u64).to_le_bytes());
    h[8..].copy_from_slice(&crc32fast::hash(value).to_le_bytes());
    h
}

/// The length and checksum a head records; `None` when it is not a head.
fn parse_head(head: &[u8]) -> Option<(u64, u32)> {
    let len = u64::from_le_bytes(head.get(..8)?.try_into().ok()?);
    let crc = u32::from_le_bytes(head.get(8..)?.try_into().ok()?);
    Some((len, crc))
}

/// Writes the chunked value of `id` inside a transaction, replacing any value it had.
pub(crate) fn put_chunked(
    tree: &sled::transaction::TransactionalTree,
    id: &[u8],
    value: &[u8],
) -> std::result::Result<(), ConflictableTransactionError<()>> {
    remove_chunked(tree, id)?;
    tree.insert(id, &head_of(value))?;
    for (i, piece) in value.chunks(CHUNK_BYTES).enumerate() {
        let i = u32::try_from(i).map_err(|_| ConflictableTransactionError::Abort(()))?;
        tree.insert(chunk_key(id, i), piece)?;
    }
    Ok(())
}

/// Removes the chunked value of `id` inside a transaction; false when it had none.
pub(crate) fn remove_chunked(
    tree: &sled::transaction::TransactionalTree,
    id: &[u8],
) -> std::result::Result<bool, ConflictableTransactionError<()>> {
    let Some(head) = tree.remove(id)? else {
        return Ok(false);
    };
    let n = parse_head(&head)
        .and_then(|(len, _)| chunk_count(len))
        .ok_or(ConflictableTransactionError::Abort(()))?;
    for i in 0..n {
        tree.remove(chunk_key(id, i))?;
    }
    Ok(true)
}

/// How often [`get_chunked`] reads a value without a transaction before it reads it in one.
const CHUNKED_READ_ATTEMPTS: usize = 3;

/// What is wrong with pieces read for a head of `len` bytes and checksum `crc`: `got` of the
/// `n` pieces were found, in order, and `out` holds them; `None` when they are the value.
fn chunk_problem(len: u64, crc: u32, got: u32, n: u32, out: &[u8]) -> Option<String> {
    if got < n {
        Some(format!("piece {got} of {n} missing"))
    } else if out.len() as u64 != len {
        Some(format!("{} bytes in pieces, {len} recorded", out.len()))
    } else if crc32fast::hash(out) != crc {
        Some("checksum mismatch".to_string())
    } else {
        None
    }
}

/// An empty buffer for a value whose head records `len` bytes (at most 1 GiB reserved up
/// front, so a damaged head cannot ask for more).
fn with_capacity_for(len: u64) -> Vec<u8> {
    Vec::with_capacity(usize::try_from(len).unwrap_or(0).min(1 << 30))
}

/// The length, checksum and piece count a head records, or what is wrong with it.
fn read_head(head: &[u8]) -> std::result::Result<(u64, u32, u32), String> {
    let (len, crc) = parse_head(head).ok_or_else(|| format!("{}-byte head", head.len()))?;
    let n = chunk_count(len).ok_or_else(|| format!("length {len}"))?;
    Ok((len, crc, n))
}

/// Reads the chunked value of `id` (`what` names it in errors). The head and the pieces are
/// separate reads (sled's reads outside a transaction are not a snapshot), so a replacement or
/// a delete written meanwhile is seen as pieces that do not match the head (their length or
/// checksum): then the value is read again, [`CHUNKED_READ_ATTEMPTS`] times in all, and then
/// once more inside a sled transaction, which no write interleaves with (a value rewritten
/// faster than it can be read is read that way). Pieces that do not match their head there are
/// corruption.
pub(crate) fn get_chunked(
    tree: &sled::Tree,
    id: &[u8],
    what: &'static str,
) -> Result<Option<Vec<u8>>> {
    read_chunked(tree, id, what, CHUNKED_READ_ATTEMPTS)
}

/// [`get_chunked`] with `attempts` reads outside a transaction before the one inside (the
/// tests also read with none).
fn read_chunked(
    tree: &sled::Tree,
    id: &[u8],
    what: &'static str,
    attempts: usize,
) -> Result<Option<Vec<u8>>> {
    let corrupt =
        |detail: String| Error::corrupt(what, Some(String::from_utf8_lossy(id).as_ref()), detail);
    for _ in 0..attempts {
        let Some(head) = tree.get(id).map_err(storage_err)? else {
            return Ok(None);
        };
        let (len, crc, n) = read_head(&head).map_err(corrupt)?;
        let mut out = with_capacity_for(len);
        let mut got = 0u32;
        if n > 0 {
            // One range read of the pieces, in order; it stops at a gap.
            for kv in tree.range(chunk_key(id, 0)..=chunk_key(id, n - 1)) {
                let (k, piece) = kv.map_err(storage_err)?;
                if k.len() != id.len() + 4
                    || !k.starts_with(id)
                    || k[id.len()..] != got.to_be_bytes()
                {
                    break;
                }
                out.extend_from_slice(&piece);
                got += 1;
            }
        }
        if chunk_problem(len, crc, got, n, &out).is_none() {
            return Ok(Some(out));
        }
    }
    let read: std::result::Result<Option<Vec<u8>>, TransactionError<String>> =
        tree.transaction(|t| {
            let Some(head) = t.get(id)? else {
                return Ok(None);
            };
            let (len, crc, n) = read_head(&head).map_err(ConflictableTransactionError::Abort)?;
            let mut out = with_capacity_for(len);
            let mut got = 0u32;
            while got < n {
                let Some(piece) = t.get(chunk_key(id, got))? else {
                    break;
                };
                out.extend_from_slice(&piece);
                got += 1;
            }
            match chunk_problem(len, crc, got, n, &out) {
                None => Ok(Some(out)),
                Some(problem) => Err(ConflictableTransactionError::Abort(problem)),
            }
        });
    match read {
        Ok(value) => Ok(value),
        Err(TransactionError::Abort(problem)) => Err(corrupt(problem)),
        Err(TransactionError::Storage(e)) => Err(storage_err(e)),
    }
}

/// Writes the chunked value of `id` in a transaction of its own (the chunking's tests).
#[cfg(test)]
fn put_chunked_alone(tree: &sled::Tree, id: &[u8], value: &[u8]) -> Result<()> {
    let res: std::result::Result<(), TransactionError<()>> =
        tree.transaction(|t| put_chunked(t, id, value));
    res.map_err(|e| storage_err(format!("{e:?}")))
}

/// Maps a sled (or transaction) failure to [`Error::Storage`].
pub fn storage_err(e: impl std::fmt::Display) -> Error {
    Error::Storage(format!("index: {e}"))
}

/// A stored shape record that does not decode: [`Error::Corrupt`].
fn corrupt_record(id: &[u8], e: impl std::fmt::Display) -> Error {
    Error::corrupt(
        "shape record",
        Some(String::from_utf8_lossy(id).as_ref()),
        e.to_string(),
    )
}

/// How long [`open_db`] waits for a lock that a database just closed in this process may still
/// hold.
const LOCK_PATIENCE: std::time::Duration = std::time::Duration::from_secs(2);

/// The bytes of sled's page cache when nothing else is said: sled's own default (1 GiB).
/// What sled keeps of a read tree is bounded by it, since values are stored in pieces of at
/// most 4 KB (`docs/scale-out.md`); `serve` sets it with `sled_cache_mb`.
pub const DEFAULT_CACHE_BYTES: u64 = 1 << 30;

/// Opens the sled database at `path` with sled's default cache ([`open_db_with_cache`]).
pub fn open_db(path: &Path) -> Result<sled::Db> {
    open_db_with_cache(path, DEFAULT_CACHE_BYTES)
}

/// Opens the sled database at `path` with a page cache of `cache_bytes`, with a clear message
/// when another process holds it.
///
/// sled releases its file lock only when the last of its background threads lets go of a
/// database, which can be a moment after the database was dropped: reopening right after closing
/// (as `migrate` does: it reads the version, backs up, then opens again) could be refused. A
/// refused lock is therefore retried for `LOCK_PATIENCE` before it is reported as another
/// process's.
pub fn open_db_with_cache(path: &Path, cache_bytes: u64) -> Result<sled::Db> {
    let deadline = std::time::Instant::now() + LOCK_PATIENCE;
    loop {
        let e = match sled::Config::new()
            .path(path)
            .cache_capacity(cache_bytes)
            .open()
        {
            Ok(db) => return Ok(db),
            Err(e) => e.to_string(),
        };
        if !e.contains("could not acquire lock") {
            return Err(storage_err(format!("cannot open {}: {e}", path.display())));
        }
        if std::time::Instant::now() >= deadline {
            return Err(storage_err(format!(
                "{} is in use by another process (a running `shapeseek serve`?): {e}",
                path.display()
            )));
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// Reads the schema version stored in an open database (None: an empty, new database).
pub fn read_schema_version(db: &sled::Db) -> Result<Option<u32>> {
    let meta = db.open_tree("meta").map_err(storage_err)?;
    match meta.get(KEY_SCHEMA).map_err(storage_err)? {
        None => Ok(None),
        Some(v) => {
            let b: [u8; 4] = v.as_ref().try_into().map_err(|_| {
                Error::corrupt(
                    "schema_version",
                    None,
                    format!("{} bytes, expected 4: not a shapeseek index", v.len()),
                )
            })?;
            Ok(Some(u32::from_be_bytes(b)))
        }
    }
}

/// Outcome of an insert.
#[derive(Debug, Clone, PartialEq)]
pub enum Inserted {
    /// A new shape was written with this id.
    New(String),
    /// The same bytes were stored before under this id; nothing was written.
    Existing(String),
}

/// The index store.
#[derive(Clone)]
pub struct Store {
    db: sled::Db,
    dir: PathBuf,
    meta: sled::Tree,
    shapes: sled::Tree,
    signatures: sled::Tree,
    meshes: sled::Tree,
    by_hash: sled::Tree,
    payloads: sled::Tree,
}

impl Store {
    /// Opens (or creates) the store in `dir`. A new database is stamped with
    /// [`SCHEMA_VERSION`]; an existing one must have exactly that version (older: run
    /// `shapeseek migrate`; newer or unknown: refused). sled's page cache is
    /// [`DEFAULT_CACHE_BYTES`].
    pub fn open(dir: &Path) -> Result<Store> {
        Store::open_with_cache(dir, DEFAULT_CACHE_BYTES)
    }

    /// [`Store::open`] with a page cache of `cache_bytes`.
    pub fn open_with_cache(dir: &Path, cache_bytes: u64) -> Result<Store> {
        std::fs::create_dir_all(dir)?;
        let db = open_db_with_cache(&dir.join("db"), cache_bytes)?;
        match read_schema_version(&db)? {
            Some(SCHEMA_VERSION) => {}
            None => {
                // A new index, unless data trees already have content (then it is not ours).
                for t in [
                    "shapes",
                    "signatures",
                    "meshes",
                    "by_hash",
                    "payloads",
                    SIGNATURE_CHUNKS,
                    MESH_CHUNKS,
                    PAYLOAD_CHUNKS,
                ] {
                    let tree = db.open_tree(t).map_err(storage_err)?;
                    if !tree.is_empty() {
                        return Err(Error::Storage(format!(
                            "index at {} has data but no schema_version: unknown format, refusing",
                            dir.display()
                        )));
                    }
                }
                let meta = db.open_tree("meta").map_err(storage_err)?;
                meta.insert(KEY_SCHEMA, &SCHEMA_VERSION.to_be_bytes())
                    .map_err(storage_err)?;
                meta.insert(KEY_CREATED, now_unix_ms().to_string().as_bytes())
                    .map_err(storage_err)?;
                db.flush().map_err(storage_err)?;
            }
            Some(v) if v < SCHEMA_VERSION => {
                return Err(Error::Storage(format!(
                    "index at {} has schema version {v}, this build uses {SCHEMA_VERSION}: \
                     run `shapeseek migrate --data {}` first (it backs the index up)",
                    dir.display(),
                    dir.display()
                )))
            }
            Some(v) => {
                return Err(Error::Storage(format!(
                    "index at {} has schema version {v}, newer than this build's \
                     {SCHEMA_VERSION}: refusing to open it (use a newer shapeseek)",
                    dir.display()
                )))
            }
        }
        Ok(Store {
            meta: db.open_tree("meta").map_err(storage_err)?,
            shapes: db.open_tree("shapes").map_err(storage_err)?,
            signatures: db.open_tree(SIGNATURE_CHUNKS).map_err(storage_err)?,
            meshes: db.open_tree(MESH_CHUNKS).map_err(storage_err)?,
            by_hash: db.open_tree("by_hash").map_err(storage_err)?,
            payloads: db.open_tree(PAYLOAD_CHUNKS).map_err(storage_err)?,
            dir: dir.to_path_buf(),
            db,
        })
    }

    /// Writes `key` = `value` into `tree` and flushes.
    fn put_flushed(&self, tree: &sled::Tree, key: &str, value: &[u8]) -> Result<()> {
        tree.insert(key.as_bytes(), value).map_err(storage_err)?;
        self.db.flush().map_err(storage_err)?;
        Ok(())
    }

    /// The data directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Id of the shape stored with this content hash, if any.
    pub fn id_for_hash(&self, sha256: &[u8; 32]) -> Result<Option<String>> {
        let Some(id) = self.by_hash.get(sha256).map_err(storage_err)? else {
            return Ok(None);
        };
        // Only while its shape is stored: a delete that could not decode the record left the
        // entry behind ([`Store::delete`]).
        if !self.shapes.contains_key(&id).map_err(storage_err)? {
            return Ok(None);
        }
        Ok(Some(String::from_utf8_lossy(&id).into_owned()))
    }

    /// A fresh id (monotonic, 16 hex digits).
    pub fn new_id(&self) -> Result<String> {
        Ok(format!(
            "{:016x}",
            self.db.generate_id().map_err(storage_err)?
        ))
    }

    /// Writes one shape (record, signature, original, hash entry) in one transaction, then
    /// flushes. When the hash is already present (a concurrent identical upload won), nothing
    /// is written and the existing id is returned.
    pub fn insert(
        &self,
        record: &ShapeRecord,
        sha256: &[u8; 32],
        signature: &[u8],
        original: &[u8],
        payload: Option<&[u8]>,
    ) -> Result<Inserted> {
        let out = self.write_one(record, sha256, signature, original, payload)?;
        self.db.flush().map_err(storage_err)?;
        Ok(out)
    }

    /// Bulk loading: writes every shape as [`Store::insert`] does (one transaction each) and
    /// flushes once at the end; nothing is durable before that flush.
    pub fn insert_batch(&self, items: &[BatchItem]) -> Result<Vec<Inserted>> {
        let out = items
            .iter()
            .map(|it| {
                self.write_one(
                    &it.record,
                    &it.sha256,
                    &it.signature,
                    &it.original,
                    it.payload.as_deref(),
                )
            })
            .collect::<Result<Vec<_>>>()?;
        self.db.flush().map_err(storage_err)?;
        Ok(out)
    }

    fn write_one(
        &self,
        record: &ShapeRecord,
        sha256: &[u8; 32],
        signature: &[u8],
        original: &[u8],
        payload: Option<&[u8]>,
    ) -> Result<Inserted> {
        let rec = serde_json::to_vec(record).map_err(storage_err)?;
        let id = record.id.as_bytes();
        let res: std::result::Result<Inserted, TransactionError<()>> = (
            &self.shapes,
            &self.signatures,
            &self.meshes,
            &self.by_hash,
            &self.payloads,
        )
            .transaction(|(shapes, sigs, meshes, by_hash, payloads)| {
                if let Some(existing) = by_hash.get(sha256)? {
                    // An entry whose shape is gone (a delete could not read its record to
                    // find the hash) is stale: the upload is stored anew over it.
                    if shapes.get(&existing)?.is_some() {
                        return Ok(Inserted::Existing(
                            String::from_utf8_lossy(&existing).into_owned(),
                        ));
                    }
                }
                shapes.insert(id, rec.as_slice())?;
                put_chunked(sigs, id, signature)?;
                put_chunked(meshes, id, original)?;
                by_hash.insert(&sha256[..], id)?;
                if let Some(p) = payload {
                    put_chunked(payloads, id, p)?;
                }
                Ok::<_, ConflictableTransactionError<()>>(Inserted::New(record.id.clone()))
            });
        res.map_err(|e| storage_err(format!("{e:?}")))
    }

    /// Deletes a shape from every tree in one transaction and flushes. False when absent.
    pub fn delete(&self, id: &str) -> Result<bool> {
        let key = id.as_bytes();
        let res: std::result::Result<bool, TransactionError<()>> = (
            &self.shapes,
            &self.signatures,
            &self.meshes,
            &self.by_hash,
            &self.payloads,
        )
            .transaction(|(shapes, sigs, meshes, by_hash, payloads)| {
                let Some(rec) = shapes.remove(key)? else {
                    return Ok(false);
                };
                remove_chunked(sigs, key)?;
                remove_chunked(meshes, key)?;
                remove_chunked(payloads, key)?;
                // A record that no longer decodes does not give its hash: that entry stays,
                // and lookups and inserts treat an entry without its shape as absent.
                if let Ok(r) = serde_json::from_slice::<ShapeRecord>(&rec) {
                    if let Ok(h) = hex::decode(&r.sha256) {
                        by_hash.remove(h)?;
                    }
                }
                Ok::<_, ConflictableTransactionError<()>>(true)
            });
        let deleted = res.map_err(|e| storage_err(format!("{e:?}")))?;
        if deleted {
            // Durable before the caller acknowledges it, as every other write.
            self.db.flush().map_err(storage_err)?;
        }
        Ok(deleted)
    }

    /// The stored re-ranking payload of a shape (`None`: absent or no such shape).
    pub fn payload(&self, id: &str) -> Result<Option<Vec<u8>>> {
        get_chunked(&self.payloads, id.as_bytes(), "payload")
    }

    /// The record of a shape.
    pub fn get(&self, id: &str) -> Result<Option<ShapeRecord>> {
        match self.shapes.get(id.as_bytes()).map_err(storage_err)? {
            None => Ok(None),
            Some(v) => Ok(Some(
                serde_json::from_slice(&v).map_err(|e| corrupt_record(id.as_bytes(), e))?,
            )),
        }
    }

    /// The stored signature bytes of a shape.
    pub fn signature(&self, id: &str) -> Result<Option<Vec<u8>>> {
        get_chunked(&self.signatures, id.as_bytes(), "signature")
    }

    /// Replaces the record (its spec key), signature and, when given, payload of an existing
    /// shape, in one transaction, and flushes. False (nothing written) when the shape is absent
    /// or stored with another content hash than `record.sha256`: a replacement never outlives a
    /// concurrent delete (no payload left behind) nor rewrites another upload's shape.
    pub fn replace_signature(
        &self,
        record: &ShapeRecord,
        signature: &[u8],
        payload: Option<&[u8]>,
    ) -> Result<bool> {
        let rec = serde_json::to_vec(record).map_err(storage_err)?;
        let id = record.id.as_bytes();
        let res: std::result::Result<bool, TransactionError<()>> =
            (&self.shapes, &self.signatures, &self.payloads).transaction(
                |(shapes, sigs, payloads)| {
                    let same = match shapes.get(id)? {
                        Some(v) => serde_json::from_slice::<ShapeRecord>(&v)
                            .map_err(|_| ConflictableTransactionError::Abort(()))?
                            .sha256
                            .eq_ignore_ascii_case(&record.sha256),
                        None => false,
                    };
                    if !same {
                        return Ok(false);
                    }
                    shapes.insert(id, rec.as_slice())?;
                    put_chunked(sigs, id, signature)?;
                    if let Some(p) = payload {
                        put_chunked(payloads, id, p)?;
                    }
                    Ok::<_, ConflictableTransactionError<()>>(true)
                },
            );
        let replaced = res
            .map_err(|e| storage_err(format!("replacing the signature of {}: {e:?}", record.id)))?;
        if replaced {
            self.db.flush().map_err(storage_err)?;
        }
        Ok(replaced)
    }

    /// The original upload of a shape.
    pub fn mesh(&self, id: &str) -> Result<Option<Vec<u8>>> {
        get_chunked(&self.meshes, id.as_bytes(), "original")
    }

    /// Records in id order, starting after `after` (exclusive), filtered by `tag`, at most
    /// `limit`. Returns the page and whether more records follow.
    pub fn list(
        &self,
        after: Option<&str>,
        tag: Option<&str>,
        limit: usize,
    ) -> Result<(Vec<ShapeRecord>, bool)> {
        let iter = match after {
            Some(a) => self.shapes.range::<&[u8], _>((
                std::ops::Bound::Excluded(a.as_bytes()),
                std::ops::Bound::Unbounded,
            )),
            None => self.shapes.iter(),
        };
        let mut out = Vec::new();
        for kv in iter {
            let (k, v) = kv.map_err(storage_err)?;
            let rec: ShapeRecord = serde_json::from_slice(&v).map_err(|e| corrupt_record(&k, e))?;
            if let Some(t) = tag {
                if !rec.tags.iter().any(|x| x == t) {
                    continue;
                }
            }
            if out.len() == limit {
                return Ok((out, true));
            }
            out.push(rec);
        }
        Ok((out, false))
    }

    /// Every (record, signature bytes) pair, in id order.
    pub fn all(&self) -> Result<Vec<(ShapeRecord, Vec<u8>)>> {
        let mut out = Vec::new();
        for kv in self.shapes.iter() {
            let (k, v) = kv.map_err(storage_err)?;
            let rec: ShapeRecord = serde_json::from_slice(&v).map_err(|e| corrupt_record(&k, e))?;
            let sig = get_chunked(&self.signatures, &k, "signature")?.ok_or_else(|| {
                Error::corrupt("index", Some(rec.id.as_str()), "the shape has no signature")
            })?;
            out.push((rec, sig));
        }
        Ok(out)
    }

    /// Number of stored shapes.
    pub fn len(&self) -> usize {
        self.shapes.len()
    }

    /// True when no shape is stored.
    pub fn is_empty(&self) -> bool {
        self.shapes.is_empty()
    }

    /// Bytes on disk (sled's estimate).
    pub fn size_on_disk(&self) -> u64 {
        self.db.size_on_disk().unwrap_or(0)
    }

    /// A `meta` value.
    pub fn meta_get(&self, key: &str) -> Result<Option<Vec<u8>>> {
        get_bytes(&self.meta, key)
    }

    /// Sets a `meta` value and flushes.
    pub fn meta_set(&self, key: &str, value: &[u8]) -> Result<()> {
        self.put_flushed(&self.meta, key, value)
    }

    /// Stores the calibration JSON.
    pub fn set_calibration(&self, json: &[u8]) -> Result<()> {
        self.meta
            .insert(KEY_CALIBRATION, json)
            .map_err(storage_err)?;
        self.db.flush().map_err(storage_err)?;
        Ok(())
    }

    /// The stored calibration JSON.
    pub fn calibration(&self) -> Result<Option<Vec<u8>>> {
        self.meta_get("calibration")
    }

    /// Records the default query spec and signature spec key in `meta`.
    pub fn set_specs(&self, default_query: &[u8], spec_key: &str) -> Result<()> {
        self.meta
            .insert(KEY_DEFAULT_QUERY, default_query)
            .map_err(storage_err)?;
        self.meta
            .insert(KEY_SPEC, spec_key.as_bytes())
            .map_err(storage_err)?;
        self.db.flush().map_err(storage_err)?;
        Ok(())
    }

    /// Flushes everything to disk.
    pub fn flush(&self) -> Result<()> {
        self.db.flush().map_err(storage_err)?;
        Ok(())
    }
}

/// Milliseconds since the Unix epoch.
pub fn now_unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A shape whose record no longer decodes can still be deleted, and the same upload is
    /// then stored anew. Before, the delete left the upload's hash entry pointing at the
    /// deleted id: the lookup named a shape that answers 404, and the insert answered
    /// "existing" with it, so that upload could never be stored again.
    #[test]
    fn a_shape_deleted_with_an_undecodable_record_can_be_uploaded_again() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let mesh = crate::mesh::generate::icosphere(1);
        let (_, prepare) =
            crate::mesh::prepare::prepare(&mesh, &crate::mesh::prepare::PrepareOptions::default())
                .unwrap();
        let original = b"an original".to_vec();
        let sha256 = [7u8; 32];
        let record = |id: String| ShapeRecord {
            id,
            name: "s".into(),
            tags: vec![],
            format: "obj".into(),
            content_type: "model/obj".into(),
            bytes: original.len() as u64,
            vertices: mesh.vertices.len(),
            faces: mesh.faces.len(),
            area: 1.0,
            sha256: hex::encode(sha256),
            created_unix_ms: now_unix_ms(),
            prepare: prepare.clone(),
            spec_key: "k".into(),
        };
        let first = store.new_id().unwrap();
        let put = |id: &str| {
            store
                .insert(&record(id.to_string()), &sha256, b"sig", &original, None)
                .unwrap()
        };
        assert!(matches!(put(&first), Inserted::New(ref id) if *id == first));
        store
            .shapes
            .insert(first.as_bytes(), &b"{not a record"[..])
            .unwrap();
        assert!(store.get(&first).is_err(), "the record no longer decodes");
        assert!(store.delete(&first).unwrap());
        assert_eq!(store.id_for_hash(&sha256).unwrap(), None);
        let second = store.new_id().unwrap();
        assert!(matches!(put(&second), Inserted::New(ref id) if *id == second));
        assert_eq!(store.id_for_hash(&sha256).unwrap(), Some(second.clone()));
        assert_eq!(store.get(&second).unwrap().unwrap().id, second);
        // And a stored shape is still found as before.
        let third = store.new_id().unwrap();
        assert!(matches!(put(&third), Inserted::Existing(ref id) if *id == second));
    }

    /// Chunked values of every length around a piece boundary read back byte for byte; a
    /// shorter replacement and a removal leave no piece behind; a missing piece is corruption.
    #[test]
    fn chunked_values_round_trip_and_leave_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        let db = open_db(&dir.path().join("db")).unwrap();
        let tree = db.open_tree("t").unwrap();
        let id = b"00000000000000ab";
        let put = |v: &[u8]| put_chunked_alone(&tree, id, v).unwrap();
        let value = |n: usize| -> Vec<u8> { (0..n).map(|i| (i * 31 % 251) as u8).collect() };
        for n in [
            0,
            1,
            CHUNK_BYTES - 1,
            CHUNK_BYTES,
            CHUNK_BYTES + 1,
            3 * CHUNK_BYTES,
            83_000,
        ] {
            put(&value(n));
            for attempts in [CHUNKED_READ_ATTEMPTS, 0] {
                assert_eq!(
                    read_chunked(&tree, id, "v", attempts).unwrap(),
                    Some(value(n)),
                    "{n} bytes, {attempts} reads before the transaction"
                );
            }
            let pieces = n.div_ceil(CHUNK_BYTES);
            assert_eq!(
                tree.len(),
                1 + pieces,
                "{n} bytes: the head and {pieces} pieces"
            );
        }
        // Another id's value is not touched by writes and removals of this one.
        let other = b"00000000000000ac";
        put_chunked_alone(&tree, other, &value(5000)).unwrap();
        put(&value(10));
        assert_eq!(
            tree.len(),
            2 + 3,
            "the shorter value's stale pieces are removed"
        );
        let removed: std::result::Result<bool, TransactionError<()>> =
            tree.transaction(|t| remove_chunked(t, id));
        assert!(removed.unwrap());
        for attempts in [CHUNKED_READ_ATTEMPTS, 0] {
            assert_eq!(read_chunked(&tree, id, "v", attempts).unwrap(), None);
            assert_eq!(
                read_chunked(&tree, other, "v", attempts).unwrap(),
                Some(value(5000))
            );
        }
        assert_eq!(tree.len(), 3);
        // A changed byte and a missing piece are reported, not papered over.
        let piece = tree.get(chunk_key(other, 0)).unwrap().unwrap();
        let mut bad = piece.to_vec();
        bad[17] ^= 1;
        tree.insert(chunk_key(other, 0), bad).unwrap();
        for attempts in [CHUNKED_READ_ATTEMPTS, 0] {
            let e = read_chunked(&tree, other, "signature", attempts).unwrap_err();
            assert!(matches!(e, Error::Corrupt { .. }), "{e:?}");
            assert!(e.to_string().contains("checksum mismatch"), "{e}");
        }
        tree.insert(chunk_key(other, 0), piece).unwrap();
        tree.remove(chunk_key(other, 1)).unwrap();
        for attempts in [CHUNKED_READ_ATTEMPTS, 0] {
            let e = read_chunked(&tree, other, "signature", attempts).unwrap_err();
            assert!(matches!(e, Error::Corrupt { .. }), "{e:?}");
            assert!(e.to_string().contains("piece 1 of 2 missing"), "{e}");
        }
    }

    /// A value replaced or deleted while it is read is read whole, old or new, never a mix of
    /// the two (the head and the pieces are separate reads) and never called corrupt: the
    /// reader reads until the writer has replaced it 400 times without a pause, a third of the
    /// reads in a transaction only.
    #[test]
    fn chunked_reads_never_mix_two_versions() {
        let dir = tempfile::tempdir().unwrap();
        let db = open_db(&dir.path().join("db")).unwrap();
        let tree = db.open_tree("t").unwrap();
        let id = b"00000000000000ab";
        let versions: Vec<Vec<u8>> = (0..3u8).map(|k| vec![k; 10 * CHUNK_BYTES + 7]).collect();
        put_chunked_alone(&tree, id, &versions[0]).unwrap();
        use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
        let (stop, written) = (AtomicBool::new(false), AtomicUsize::new(0));
        let (reads, gone) = std::thread::scope(|s| {
            let writer = s.spawn(|| {
                let mut k = 1usize;
                while !stop.load(Ordering::Acquire) {
                    if k % 50 == 0 {
                        let r: std::result::Result<bool, TransactionError<()>> =
                            tree.transaction(|t| remove_chunked(t, id));
                        r.unwrap();
                    }
                    put_chunked_alone(&tree, id, &versions[k % 3]).unwrap();
                    written.store(k, Ordering::Release);
                    k += 1;
                }
            });
            // Stops the writer however the reader ends (a failed assertion included).
            struct Stop<'a>(&'a AtomicBool);
            impl Drop for Stop<'_> {
                fn drop(&mut self) {
                    self.0.store(true, Ordering::Release);
                }
            }
            let stop_writer = Stop(&stop);
            let (mut reads, mut gone) = (0usize, 0usize);
            // Until both counts are reached, or the writer ended (a failed write: joined below).
            while (reads < 400 || written.load(Ordering::Acquire) < 400) && !writer.is_finished() {
                // Every third read goes straight to the transaction, the others try first.
                match read_chunked(&tree, id, "v", reads % 3 * CHUNKED_READ_ATTEMPTS).unwrap() {
                    Some(v) => assert!(versions.contains(&v), "a mix of versions"),
                    None => gone += 1,
                }
                reads += 1;
            }
            drop(stop_writer);
            writer.join().unwrap();
            (reads, gone)
        });
        let writes = written.load(Ordering::Acquire);
        eprintln!("{reads} reads during {writes} replacements, {gone} while deleted");
    }

    /// A lock released within the patience is waited for; one held longer is reported as
    /// another process's.
    #[test]
    fn a_lock_released_soon_is_waited_for() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("db");
        let held = open_db(&path).unwrap();
        let release = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(300));
            drop(held);
        });
        let t = std::time::Instant::now();
        let db = open_db(&path).expect("opened once the lock was released");
        assert!(t.elapsed() < LOCK_PATIENCE);
        release.join().unwrap();
        let t = std::time::Instant::now();
        let e = open_db(&path).expect_err("held by the open database");
        assert!(t.elapsed() >= LOCK_PATIENCE);
        assert!(e.to_string().contains("in use by another process"), "{e}");
        drop(db);
    }
}
