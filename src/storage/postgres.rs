//! The PostgreSQL backend of [`ShapeStore`]: `tokio-postgres` behind a `deadpool-postgres` pool,
//! every statement parameterised (and prepared once per connection), schema
//! `migrations/postgres/*.sql` checked at connect ([`super::pg_migrate`]).
//!
//! | table | holds |
//! | --- | --- |
//! | `shapes` | id (bigint, shown as 16 hex digits), `sha256` (unique: the idempotency key), name, tags (GIN-indexed), spec key, the full `ShapeRecord` JSON |
//! | `meshes`, `signatures`, `payloads` | the bytes, keyed by id, `ON DELETE CASCADE` from `shapes` |
//! | `meta` | free key/value pairs (`default_query`, `spec_key`) |
//! | `calibration` | one row: epoch, count it saw, the engine's JSON; its row lock is the recalibration lock |
//! | `schema_version` | one row per applied migration |
//!
//! * Insert: one transaction — `INSERT … ON CONFLICT (sha256) DO NOTHING RETURNING id`, then the
//!   three byte tables — acknowledged after `COMMIT` returns (durable under the server's default
//!   `synchronous_commit = on`). A concurrent insert of the same bytes waits on the unique index,
//!   then finds the committed row and answers [`InsertOutcome::AlreadyPresent`].
//! * Delete: one `DELETE FROM shapes` (the cascade removes the bytes in the same statement).
//! * Calibration lock: a pooled connection holds a transaction with
//!   `SELECT … FROM calibration FOR UPDATE` (or `SKIP LOCKED` to try); committing writes the next
//!   epoch in that transaction. If the holder dies, PostgreSQL ends its session and the lock with
//!   it; a lock dropped without commit discards its connection (so no half-open transaction goes
//!   back to the pool). If the holder's host goes away without closing the connection (power
//!   lost, cut off), the server learns it from TCP only: the lock's transaction sets keepalives
//!   and a user timeout on its connection (`LOCK_BEGIN`) so that the session ends, and the lock
//!   is free, within about half a minute instead of the two hours of the system's defaults.

use super::pg_migrate::{self, describe, pg, transient, Prepared, PG_SCHEMA_VERSION};
use super::{
    check_meta_key, format_id, parse_cursor, parse_id, Backend, CalibrationLock, InsertOutcome,
    LockHolder, NewShape, Page, ShapeStore, StoredCalibration,
};
use crate::index::store::{storage_err, ShapeRecord};
use crate::{Error, Result};
use async_trait::async_trait;
use deadpool_postgres::{
    Manager, ManagerConfig, Object, Pool, PoolError, RecyclingMethod, Runtime,
};
use tokio_postgres::NoTls;

/// Pool settings.
#[derive(Debug, Clone)]
pub struct PoolOptions {
    /// Most connections open at once.
    pub max_size: usize,
}

impl Default for PoolOptions {
    fn default() -> Self {
        PoolOptions { max_size: 16 }
    }
}

/// A PostgreSQL database behind the [`ShapeStore`] seam.
#[derive(Clone)]
pub struct PgStore {
    pool: Pool,
    /// The runtime the connections' tasks run on (see [`io_runtime`]).
    io: tokio::runtime::Handle,
}

/// A runtime of its own, on one thread, for the tasks that drive the PostgreSQL connections.
///
/// A connection's socket is driven by a task spawned where it was opened. Were that the
/// server's runtime, a query awaited by a thread that holds the scan's write lock (installing
/// a calibration reads stored signatures) could wait for a runtime worker that is itself
/// blocked on that lock: a deadlock. Connections opened here need no server worker at all.
fn io_runtime() -> Result<tokio::runtime::Handle> {
    static IO: std::sync::OnceLock<tokio::runtime::Handle> = std::sync::OnceLock::new();
    if let Some(h) = IO.get() {
        return Ok(h.clone());
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| storage_err(format!("postgres: I/O runtime: {e}")))?;
    let handle = rt.handle().clone();
    std::thread::Builder::new()
        .name("shapeseek-pg-io".into())
        .spawn(move || rt.block_on(std::future::pending::<()>()))
        .map_err(|e| storage_err(format!("postgres: I/O thread: {e}")))?;
    Ok(IO.get_or_init(|| handle).clone())
}

/// The URL's settings, with two bounds where it sets none, so that a database that went away
/// answers an error (503 `storage.unavailable`) instead of holding the request's thread: an
/// attempt to connect to a host gives up after [`CONNECT_TIMEOUT`] (each host of a multi-host
/// URL in turn; the pool sets no limit of its own over them), and a statement whose bytes the
/// server no longer acknowledges (a host cut off) after [`TCP_USER_TIMEOUT`] (the system's
/// default is about a quarter of an hour of retransmissions). Neither bounds a statement the
/// server is working on.
fn parse_url(url: &str) -> Result<tokio_postgres::Config> {
    let mut cfg = url
        .parse::<tokio_postgres::Config>()
        .map_err(|e| Error::InvalidArgument(format!("PostgreSQL URL: {e}")))?;
    if cfg.get_connect_timeout().is_none() {
        cfg.connect_timeout(CONNECT_TIMEOUT);
    }
    if cfg.get_tcp_user_timeout().is_none() {
        cfg.tcp_user_timeout(TCP_USER_TIMEOUT);
    }
    Ok(cfg)
}

/// See [`parse_url`] (the URL's `connect_timeout` overrides it).
const CONNECT_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);
/// See [`parse_url`] (the URL's `tcp_user_timeout` overrides it).
const TCP_USER_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);
/// How long a request waits for a pooled connection when all are in use.
const POOL_WAIT: std::time::Duration = std::time::Duration::from_secs(30);

/// One plain connection (no pool), its connection task spawned.
async fn connect_one(url: &str) -> Result<tokio_postgres::Client> {
    let (client, conn) = parse_url(url)?
        .connect(NoTls)
        .await
        .map_err(pg("connecting"))?;
    tokio::spawn(async move {
        if let Err(e) = conn.await {
            tracing::warn!(error = %e, "postgres connection ended");
        }
    });
    Ok(client)
}

/// Applies the missing migrations to the database at `url` (`shapeseek migrate --store`).
pub async fn migrate_url(url: &str) -> Result<pg_migrate::MigrateReport> {
    let mut client = connect_one(url).await?;
    pg_migrate::migrate(&mut client).await
}

/// An id as the `bigint` key; `None` when malformed or beyond the sequence's range.
pub(crate) fn key(id: &str) -> Option<i64> {
    parse_id(id).and_then(|n| i64::try_from(n).ok())
}

fn decode_record(json: &str) -> Result<ShapeRecord> {
    serde_json::from_str(json)
        .map_err(|e| storage_err(format!("postgres: stored record is unreadable: {e}")))
}

fn encode_record(rec: &ShapeRecord) -> Result<String> {
    serde_json::to_string(rec).map_err(storage_err)
}

fn to_i64(v: u64, what: &str) -> Result<i64> {
    i64::try_from(v).map_err(|_| Error::InvalidArgument(format!("{what} {v} is out of range")))
}

impl PgStore {
    /// Connects a pool to `url` and checks the schema is this build's
    /// ([`pg_migrate::check`]: refuses an older, newer or unknown one).
    pub async fn connect(url: &str, opts: PoolOptions) -> Result<PgStore> {
        Self::connect_expecting(url, opts, PG_SCHEMA_VERSION).await
    }

    /// [`PgStore::connect`] expecting schema version `version` (tests of the refusal path).
    pub async fn connect_expecting(url: &str, opts: PoolOptions, version: u32) -> Result<PgStore> {
        let mgr = Manager::from_config(
            parse_url(url)?,
            NoTls,
            ManagerConfig {
                recycling_method: RecyclingMethod::Fast,
            },
        );
        let pool = Pool::builder(mgr)
            .max_size(opts.max_size.max(1))
            .wait_timeout(Some(POOL_WAIT))
            .runtime(Runtime::Tokio1)
            .build()
            .map_err(|e| storage_err(format!("postgres: building the pool: {e}")))?;
        let store = PgStore {
            pool,
            io: io_runtime()?,
        };
        let client = store.client().await?;
        pg_migrate::check(&client, version).await?;
        Ok(store)
    }

    /// A pooled connection (the queue's job table shares the pool).
    pub(crate) async fn client(&self) -> Result<Object> {
        // Opened (when the pool needs a new one) on the I/O runtime, so its task runs there.
        let pool = self.pool.clone();
        self.io
            .spawn(async move { pool.get().await })
            .await
            .map_err(|e| storage_err(format!("postgres: connection task: {e}")))?
            .map_err(|e| {
                let message = format!("postgres: no connection: {e}");
                match &e {
                    PoolError::Backend(b) if !transient(b) => storage_err(message),
                    PoolError::Backend(_) | PoolError::Timeout(_) | PoolError::Closed => {
                        Error::StorageUnavailable(message)
                    }
                    _ => storage_err(message),
                }
            })
    }

    /// Takes the calibration row lock on a dedicated connection; `None` when `skip` and it is
    /// held elsewhere.
    async fn lock(&self, skip: bool) -> Result<Option<CalibrationLock>> {
        let client = self.client().await?;
        let mut holder = PgLock {
            client: Some(client),
        };
        let c = holder.client.as_ref().expect("just set");
        c.batch_execute(LOCK_BEGIN)
            .await
            .map_err(pg("starting the calibration lock's transaction"))?;
        let sql = if skip {
            "SELECT epoch, calibrated_on, body::text FROM calibration WHERE singleton \
             FOR UPDATE SKIP LOCKED"
        } else {
            "SELECT epoch, calibrated_on, body::text FROM calibration WHERE singleton FOR UPDATE"
        };
        let stmt = c.prepared(sql).await?;
        let row = c
            .query_opt(&stmt, &[])
            .await
            .map_err(pg("locking the calibration"))?;
        let Some(row) = row else {
            if skip {
                holder.finish("ROLLBACK").await?;
                return Ok(None);
            }
            return Err(storage_err(
                "postgres: the calibration row is missing (schema damaged?)",
            ));
        };
        let current = calibration_from(row.get(0), row.get(1), row.get(2))?;
        Ok(Some(CalibrationLock::new(current, Box::new(holder))))
    }
}

fn calibration_from(
    epoch: i64,
    on: Option<i64>,
    body: Option<String>,
) -> Result<Option<StoredCalibration>> {
    if epoch == 0 {
        return Ok(None);
    }
    let body = body.ok_or_else(|| storage_err("postgres: calibration epoch without a body"))?;
    Ok(Some(StoredCalibration {
        epoch: epoch as u64,
        calibrated_on: on.unwrap_or(0).max(0) as u64,
        json: body.into_bytes(),
    }))
}

/// Opens the calibration lock's transaction. The row lock lives as long as the session, and a
/// session whose client's host went away without closing it (power lost, network cut) lives on
/// until TCP gives up. With the system's defaults that is two hours of idle before the first
/// keepalive probe for a holder that vanished while it computed, and Linux's 15
/// retransmissions (about a quarter of an hour) for a waiter that vanished and was then handed
/// the lock, its answer never acknowledged. For this transaction only
/// (`SET LOCAL`: the pooled connection gets its settings back at its end), the server probes
/// after 10 s idle, every 5 s, and drops the connection after 3 unanswered probes or 30 s of
/// unacknowledged data: a vanished holder's lock is free after about 25–30 s, and a live
/// holder, however long it computes, answers the probes from its kernel. The settings act on
/// TCP connections only (a Unix socket's peer is on the server's own host), and need
/// PostgreSQL 12 or later (`tcp_user_timeout`). Behind a pooler (PgBouncer) they act on the
/// pooler's connection to the server, not on the node's. A live holder cut off for longer than
/// this loses the lock too; its commit then fails, and nothing is installed from it.
/// `tests/postgres.rs` `a_calibration_lock_held_from_a_vanished_host_is_freed` cuts a holder
/// off in a network namespace and measures it.
const LOCK_BEGIN: &str = "BEGIN; \
    SET LOCAL tcp_keepalives_idle = 10; \
    SET LOCAL tcp_keepalives_interval = 5; \
    SET LOCAL tcp_keepalives_count = 3; \
    SET LOCAL tcp_user_timeout = 30000";

/// A connection inside the calibration transaction.
struct PgLock {
    client: Option<Object>,
}

impl PgLock {
    /// Ends the transaction with `sql` (`COMMIT`/`ROLLBACK`) and returns the connection to the
    /// pool; on failure the connection is discarded.
    async fn finish(&mut self, sql: &str) -> Result<()> {
        let c = self.client.as_ref().expect("held until finished");
        match c.batch_execute(sql).await {
            Ok(()) => {
                self.client = None; // back to the pool, outside any transaction
                Ok(())
            }
            Err(e) => Err(storage_err(format!("postgres: {sql}: {}", describe(&e)))),
        }
    }
}

impl Drop for PgLock {
    fn drop(&mut self) {
        if let Some(obj) = self.client.take() {
            // Still inside the transaction: close this connection (the server rolls back and
            // releases the row lock) rather than pool it.
            drop(Object::take(obj));
        }
    }
}

#[async_trait]
impl LockHolder for PgLock {
    async fn commit(mut self: Box<Self>, cal: &StoredCalibration) -> Result<()> {
        let body = std::str::from_utf8(&cal.json)
            .map_err(|e| Error::InvalidArgument(format!("calibration is not UTF-8: {e}")))?
            .to_string();
        let c = self.client.as_ref().expect("held until finished");
        let stmt = c
            .prepared(
                "UPDATE calibration SET epoch = $1, calibrated_on = $2, body = $3::text::json, \
                 updated_at = now() WHERE singleton AND epoch < $1",
            )
            .await?;
        let epoch = to_i64(cal.epoch, "epoch")?;
        let n = c
            .execute(
                &stmt,
                &[&epoch, &to_i64(cal.calibrated_on, "calibrated_on")?, &body],
            )
            .await
            .map_err(pg("writing the calibration"))?;
        if n != 1 {
            return Err(storage_err(
                "postgres: calibration epoch moved while locked (schema damaged?)",
            ));
        }
        self.finish("COMMIT").await
    }

    async fn release(mut self: Box<Self>) -> Result<()> {
        self.finish("ROLLBACK").await
    }
}

#[async_trait]
impl ShapeStore for PgStore {
    fn backend(&self) -> Backend {
        Backend::Postgres
    }

    async fn schema_version(&self) -> Result<u32> {
        let client = self.client().await?;
        pg_migrate::current_version(&client)
            .await
            .map(|v| v.unwrap_or(0))
    }

    async fn new_id(&self) -> Result<String> {
        let c = self.client().await?;
        let stmt = c.prepared("SELECT nextval('shape_id_seq')").await?;
        let n: i64 = c
            .query_one(&stmt, &[])
            .await
            .map_err(pg("allocating an id"))?
            .get(0);
        Ok(format_id(n as u64))
    }

    async fn insert(&self, shape: NewShape) -> Result<InsertOutcome> {
        let id = key(&shape.record.id);
        let (Some(id), true) = (id, shape.record.sha256 == hex::encode(shape.sha256)) else {
            return Err(Error::InvalidArgument(
                "new shape: record.sha256 must be the hex of sha256 and record.id an id".into(),
            ));
        };
        let rec = &shape.record;
        let json = encode_record(rec)?;
        let sha: &[u8] = &shape.sha256;
        let created = i64::try_from(rec.created_unix_ms).unwrap_or(i64::MAX);
        let mut c = self.client().await?;
        // A conflict with a row deleted before we could read it: try again (bounded).
        for _ in 0..5 {
            let tx = c.transaction().await.map_err(pg("BEGIN"))?;
            let ins = tx
                .prepared(
                    "INSERT INTO shapes (id, sha256, name, tags, spec_key, created_unix_ms, \
                     record) VALUES ($1, $2, $3, $4, $5, $6, $7::text::json) \
                     ON CONFLICT (sha256) DO NOTHING RETURNING id",
                )
                .await?;
            let row = tx
                .query_opt(
                    &ins,
                    &[
                        &id,
                        &sha,
                        &rec.name,
                        &rec.tags,
                        &rec.spec_key,
                        &created,
                        &json,
                    ],
                )
                .await
                .map_err(pg("inserting a shape"))?;
            if row.is_none() {
                let sel = tx
                    .prepared("SELECT id FROM shapes WHERE sha256 = $1")
                    .await?;
                let existing = tx
                    .query_opt(&sel, &[&sha])
                    .await
                    .map_err(pg("reading by hash"))?;
                tx.rollback().await.map_err(pg("ROLLBACK"))?;
                match existing {
                    Some(r) => {
                        return Ok(InsertOutcome::AlreadyPresent(format_id(
                            r.get::<_, i64>(0) as u64
                        )))
                    }
                    None => continue,
                }
            }
            for (sql, bytes) in [
                (
                    "INSERT INTO meshes (id, content) VALUES ($1, $2)",
                    Some(&shape.original),
                ),
                (
                    "INSERT INTO signatures (id, content) VALUES ($1, $2)",
                    Some(&shape.signature),
                ),
                (
                    "INSERT INTO payloads (id, content) VALUES ($1, $2)",
                    shape.payload.as_ref(),
                ),
            ] {
                if let Some(b) = bytes {
                    let stmt = tx.prepared(sql).await?;
                    tx.execute(&stmt, &[&id, &b.as_slice()])
                        .await
                        .map_err(pg("inserting shape bytes"))?;
                }
            }
            tx.commit().await.map_err(pg("COMMIT of a shape"))?;
            return Ok(InsertOutcome::Inserted(rec.id.clone()));
        }
        Err(storage_err(
            "postgres: insert kept conflicting with shapes deleted concurrently; retry",
        ))
    }

    async fn id_for_hash(&self, sha256: &[u8; 32]) -> Result<Option<String>> {
        let c = self.client().await?;
        let stmt = c
            .prepared("SELECT id FROM shapes WHERE sha256 = $1")
            .await?;
        let sha: &[u8] = sha256;
        Ok(c.query_opt(&stmt, &[&sha])
            .await
            .map_err(pg("reading by hash"))?
            .map(|r| format_id(r.get::<_, i64>(0) as u64)))
    }

    async fn delete(&self, id: &str) -> Result<bool> {
        let Some(id) = key(id) else { return Ok(false) };
        let c = self.client().await?;
        let stmt = c.prepared("DELETE FROM shapes WHERE id = $1").await?;
        Ok(c.execute(&stmt, &[&id]).await.map_err(pg("deleting"))? > 0)
    }

    async fn get(&self, id: &str) -> Result<Option<ShapeRecord>> {
        let Some(id) = key(id) else { return Ok(None) };
        let c = self.client().await?;
        let stmt = c
            .prepared("SELECT record::text FROM shapes WHERE id = $1")
            .await?;
        c.query_opt(&stmt, &[&id])
            .await
            .map_err(pg("reading a record"))?
            .map(|r| decode_record(r.get(0)))
            .transpose()
    }

    async fn list(&self, after: Option<&str>, tag: Option<&str>, limit: usize) -> Result<Page> {
        let after = parse_cursor(after)?
            .map(|n| i64::try_from(n).unwrap_or(i64::MAX))
            .unwrap_or(-1);
        let c = self.client().await?;
        let stmt = c
            .prepared(
                "SELECT record::text FROM shapes \
                 WHERE id > $1 AND ($2::text IS NULL OR tags @> ARRAY[$2::text]) \
                 ORDER BY id LIMIT $3",
            )
            .await?;
        let fetch = i64::try_from(limit).unwrap_or(i64::MAX - 1) + 1;
        let rows = c
            .query(&stmt, &[&after, &tag, &fetch])
            .await
            .map_err(pg("listing"))?;
        let more = rows.len() > limit;
        let records = rows
            .iter()
            .take(limit)
            .map(|r| decode_record(r.get(0)))
            .collect::<Result<Vec<_>>>()?;
        Ok(Page { records, more })
    }

    async fn signature(&self, id: &str) -> Result<Option<Vec<u8>>> {
        self.bytes("SELECT content FROM signatures WHERE id = $1", id)
            .await
    }

    async fn mesh(&self, id: &str) -> Result<Option<Vec<u8>>> {
        self.bytes("SELECT content FROM meshes WHERE id = $1", id)
            .await
    }

    async fn payload(&self, id: &str) -> Result<Option<Vec<u8>>> {
        self.bytes("SELECT content FROM payloads WHERE id = $1", id)
            .await
    }

    async fn replace_signature(
        &self,
        record: &ShapeRecord,
        signature: &[u8],
        payload: Option<&[u8]>,
    ) -> Result<bool> {
        let Some(id) = key(&record.id) else {
            return Ok(false);
        };
        let json = encode_record(record)?;
        let sha = hex::decode(&record.sha256)
            .map_err(|e| Error::InvalidArgument(format!("record.sha256: {e}")))?;
        let mut c = self.client().await?;
        let tx = c.transaction().await.map_err(pg("BEGIN"))?;
        // The content hash must not change: it is what the record is the record of.
        let upd = tx
            .prepared(
                "UPDATE shapes SET record = $2::text::json, spec_key = $3, name = $4, tags = $5 \
                 WHERE id = $1 AND sha256 = $6",
            )
            .await?;
        let n = tx
            .execute(
                &upd,
                &[
                    &id,
                    &json,
                    &record.spec_key,
                    &record.name,
                    &record.tags,
                    &sha,
                ],
            )
            .await
            .map_err(pg("replacing a record"))?;
        if n == 0 {
            tx.rollback().await.map_err(pg("ROLLBACK"))?;
            return Ok(false);
        }
        let sig = tx
            .prepared("UPDATE signatures SET content = $2 WHERE id = $1")
            .await?;
        tx.execute(&sig, &[&id, &signature])
            .await
            .map_err(pg("replacing a signature"))?;
        if let Some(p) = payload {
            let pay = tx
                .prepared(
                    "INSERT INTO payloads (id, content) VALUES ($1, $2) \
                     ON CONFLICT (id) DO UPDATE SET content = EXCLUDED.content",
                )
                .await?;
            tx.execute(&pay, &[&id, &p])
                .await
                .map_err(pg("replacing a payload"))?;
        }
        tx.commit().await.map_err(pg("COMMIT"))?;
        Ok(true)
    }

    async fn scan_signatures(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<(ShapeRecord, Vec<u8>)>> {
        let after = parse_cursor(after)?
            .map(|n| i64::try_from(n).unwrap_or(i64::MAX))
            .unwrap_or(-1);
        let c = self.client().await?;
        let stmt = c
            .prepared(
                "SELECT s.record::text, g.content FROM shapes s JOIN signatures g USING (id) \
                 WHERE s.id > $1 ORDER BY s.id LIMIT $2",
            )
            .await?;
        let lim = i64::try_from(limit).unwrap_or(i64::MAX);
        c.query(&stmt, &[&after, &lim])
            .await
            .map_err(pg("scanning signatures"))?
            .iter()
            .map(|r| Ok((decode_record(r.get(0))?, r.get::<_, Vec<u8>>(1))))
            .collect()
    }

    async fn count(&self) -> Result<u64> {
        let c = self.client().await?;
        let n: i64 = c
            .query_one("SELECT count(*) FROM shapes", &[])
            .await
            .map_err(pg("counting"))?
            .get(0);
        Ok(n as u64)
    }

    async fn size_on_disk(&self) -> Result<u64> {
        let c = self.client().await?;
        let n: i64 = c
            .query_one("SELECT pg_database_size(current_database())", &[])
            .await
            .map_err(pg("database size"))?
            .get(0);
        Ok(n as u64)
    }

    async fn calibration(&self) -> Result<Option<StoredCalibration>> {
        let c = self.client().await?;
        let stmt = c
            .prepared("SELECT epoch, calibrated_on, body::text FROM calibration WHERE singleton")
            .await?;
        let row = c
            .query_one(&stmt, &[])
            .await
            .map_err(pg("reading the calibration"))?;
        calibration_from(row.get(0), row.get(1), row.get(2))
    }

    async fn lock_calibration(&self) -> Result<CalibrationLock> {
        self.lock(false)
            .await?
            .ok_or_else(|| storage_err("postgres: calibration lock not granted"))
    }

    async fn try_lock_calibration(&self) -> Result<Option<CalibrationLock>> {
        self.lock(true).await
    }

    async fn meta_get(&self, key: &str) -> Result<Option<Vec<u8>>> {
        check_meta_key(key)?;
        let c = self.client().await?;
        let stmt = c.prepared("SELECT value FROM meta WHERE key = $1").await?;
        Ok(c.query_opt(&stmt, &[&key])
            .await
            .map_err(pg("reading meta"))?
            .map(|r| r.get(0)))
    }

    async fn meta_set(&self, key: &str, value: &[u8]) -> Result<()> {
        check_meta_key(key)?;
        let c = self.client().await?;
        let stmt = c
            .prepared(
                "INSERT INTO meta (key, value) VALUES ($1, $2) \
                 ON CONFLICT (key) DO UPDATE SET value = EXCLUDED.value",
            )
            .await?;
        c.execute(&stmt, &[&key, &value])
            .await
            .map_err(pg("writing meta"))?;
        Ok(())
    }
}

impl PgStore {
    async fn bytes(&self, sql: &'static str, id: &str) -> Result<Option<Vec<u8>>> {
        let Some(id) = key(id) else { return Ok(None) };
        let c = self.client().await?;
        let stmt = c.prepared(sql).await?;
        Ok(c.query_opt(&stmt, &[&id])
            .await
            .map_err(pg("reading bytes"))?
            .map(|r| r.get(0)))
    }
}
