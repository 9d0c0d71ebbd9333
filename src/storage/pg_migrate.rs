//! The PostgreSQL migrations runner: versioned SQL files in `migrations/postgres/`, compiled
//! into the binary, applied in order, each in one transaction that also records its version in
//! the table `schema_version`.
//!
//! * [`migrate`] applies the missing files (what `shapeseek migrate --store postgres://…` runs).
//!   Every transaction first takes a transaction-scoped advisory lock, so two nodes migrating at
//!   once apply each file once; a failing file rolls back whole and leaves the previous version.
//! * [`check`] is what opening a store runs: the database must be at exactly
//!   [`PG_SCHEMA_VERSION`]. Older: "run `shapeseek migrate --store …`". Newer: refused (a newer
//!   build wrote it). An empty database (no `schema_version`) must be migrated first; tables of
//!   ours without `schema_version` are refused as unknown.
//!
//! Writing the next version: add `migrations/postgres/000N_<what>.sql` and one entry to
//! [`MIGRATIONS`]; never edit a file that has been released.

use crate::index::store::storage_err;
use crate::{Error, Result};
use tokio_postgres::Client;

/// One versioned SQL file.
#[derive(Debug, Clone, Copy)]
pub struct Migration {
    /// The version the database is at once this file is applied (1, 2, ...).
    pub version: u32,
    /// File name under `migrations/postgres/`.
    pub name: &'static str,
    /// Its SQL.
    pub sql: &'static str,
}

/// Every migration of this build, in order (`version` = position + 1).
pub const MIGRATIONS: &[Migration] = &[
    Migration {
        version: 1,
        name: "0001_initial.sql",
        sql: include_str!("../../migrations/postgres/0001_initial.sql"),
    },
    Migration {
        version: 2,
        name: "0002_jobs.sql",
        sql: include_str!("../../migrations/postgres/0002_jobs.sql"),
    },
];

/// The schema version this build reads and writes.
pub const PG_SCHEMA_VERSION: u32 = MIGRATIONS.len() as u32;

/// Key of the advisory lock migrations run under (an arbitrary constant: "shapeseek" in ASCII).
const MIGRATION_LOCK: i64 = 0x7368_6170_6573_6565;

/// What [`migrate`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MigrateReport {
    /// Version found before (0: empty database).
    pub from: u32,
    /// Version now.
    pub to: u32,
    /// Files applied, in order.
    pub applied: Vec<&'static str>,
}

/// The error of a failed statement: what was being done and the server's message
/// ([`describe`]).
pub(crate) fn pg(what: &str) -> impl Fn(tokio_postgres::Error) -> Error + '_ {
    move |e| {
        let message = format!("postgres: {what}: {}", describe(&e));
        if transient(&e) {
            Error::StorageUnavailable(message)
        } else {
            storage_err(message)
        }
    }
}

/// True when the statement failed because the database could not be reached or put it off,
/// so that the same request may succeed later (503, not 500): the connection closed, or an I/O
/// error of the network's kind (refused, reset, aborted, broken, timed out, unreachable), or
/// the server answered with a connection exception (SQLSTATE class 08 but 08P01, a protocol
/// violation), a shutdown or start-up in progress (57P01–57P03), too many connections (53300),
/// a serialization failure or a deadlock (40001, 40P01). Not: a host name that does not
/// resolve, a value too large to send, a failed login — the same request would fail again.
pub(crate) fn transient(e: &tokio_postgres::Error) -> bool {
    use std::io::ErrorKind as K;
    match e.code() {
        Some(state) => {
            let code = state.code();
            (code.starts_with("08") && code != "08P01")
                || matches!(
                    code,
                    "57P01" | "57P02" | "57P03" | "53300" | "40001" | "40P01"
                )
        }
        None => {
            e.is_closed()
                || std::error::Error::source(e)
                    .and_then(|s| s.downcast_ref::<std::io::Error>())
                    .is_some_and(|io| {
                        matches!(
                            io.kind(),
                            K::ConnectionRefused
                                | K::ConnectionReset
                                | K::ConnectionAborted
                                | K::NotConnected
                                | K::BrokenPipe
                                | K::TimedOut
                                | K::UnexpectedEof
                                | K::HostUnreachable
                                | K::NetworkUnreachable
                                | K::NetworkDown
                        )
                    })
        }
    }
}

/// The server's message of a database error, else the driver's.
pub(crate) fn describe(e: &tokio_postgres::Error) -> String {
    match e.as_db_error() {
        Some(db) => format!("{} ({})", db.message(), db.code().code()),
        None => e.to_string(),
    }
}

/// A statement from the connection's cache, prepared on first use: on a pooled connection or
/// inside its transaction.
pub(crate) trait Prepared {
    /// The cached statement of `sql`.
    async fn prepared(&self, sql: &str) -> Result<tokio_postgres::Statement>;
}

impl<C: deadpool_postgres::GenericClient> Prepared for C {
    async fn prepared(&self, sql: &str) -> Result<tokio_postgres::Statement> {
        self.prepare_cached(sql).await.map_err(pg("preparing"))
    }
}

/// The version recorded in the database (`None`: no `schema_version` table).
pub async fn current_version(client: &Client) -> Result<Option<u32>> {
    let row = client
        .query_one("SELECT to_regclass('schema_version') IS NOT NULL", &[])
        .await
        .map_err(pg("reading the schema version"))?;
    if !row.get::<_, bool>(0) {
        return Ok(None);
    }
    let row = client
        .query_one("SELECT coalesce(max(version), 0) FROM schema_version", &[])
        .await
        .map_err(pg("reading the schema version"))?;
    let v: i32 = row.get(0);
    Ok(Some(v.max(0) as u32))
}

/// True when the database holds a table of ours (a `shapes` table).
async fn has_our_tables(client: &Client) -> Result<bool> {
    let row = client
        .query_one("SELECT to_regclass('shapes') IS NOT NULL", &[])
        .await
        .map_err(pg("inspecting the database"))?;
    Ok(row.get(0))
}

fn newer_error(found: u32, build: u32) -> Error {
    Error::InvalidArgument(format!(
        "PostgreSQL store has schema version {found}, newer than this build's {build}: \
         refusing to use it (use a newer shapeseek)"
    ))
}

/// Checks the database is at exactly `target` (see the module docs); `target` is
/// [`PG_SCHEMA_VERSION`] outside tests.
pub async fn check(client: &Client, target: u32) -> Result<()> {
    match current_version(client).await? {
        Some(v) if v == target => Ok(()),
        Some(v) if v > target => Err(newer_error(v, target)),
        Some(v) => Err(Error::InvalidArgument(format!(
            "PostgreSQL store has schema version {v}, this build uses {target}: run \
             `shapeseek migrate --store <url>` first"
        ))),
        None if has_our_tables(client).await? => Err(Error::InvalidArgument(
            "PostgreSQL database has a `shapes` table but no `schema_version`: unknown \
             format, refusing"
                .into(),
        )),
        None => Err(Error::InvalidArgument(
            "PostgreSQL database has no shapeseek schema: run `shapeseek migrate --store <url>` \
             first"
                .into(),
        )),
    }
}

/// Applies every migration of [`MIGRATIONS`] the database lacks.
pub async fn migrate(client: &mut Client) -> Result<MigrateReport> {
    migrate_with(client, MIGRATIONS).await
}

/// [`migrate`] with an explicit list (the runner itself; tests use their own lists).
pub async fn migrate_with(client: &mut Client, migrations: &[Migration]) -> Result<MigrateReport> {
    for (i, m) in migrations.iter().enumerate() {
        if m.version as usize != i + 1 {
            return Err(Error::InvalidArgument(format!(
                "migration {} has version {}, expected {}",
                m.name,
                m.version,
                i + 1
            )));
        }
    }
    let target = migrations.len() as u32;
    let from = match current_version(client).await? {
        Some(v) => v,
        None if has_our_tables(client).await? => {
            return Err(Error::InvalidArgument(
                "PostgreSQL database has a `shapes` table but no `schema_version`: unknown \
                 format, refusing to migrate it"
                    .into(),
            ))
        }
        None => 0,
    };
    if from > target {
        return Err(newer_error(from, target));
    }
    let mut applied = Vec::new();
    for m in migrations {
        let tx = client
            .transaction()
            .await
            .map_err(pg("starting a migration"))?;
        tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK])
            .await
            .map_err(pg("taking the migration lock"))?;
        tx.batch_execute(
            "CREATE TABLE IF NOT EXISTS schema_version (
                 version    integer     PRIMARY KEY,
                 name       text        NOT NULL,
                 applied_at timestamptz NOT NULL DEFAULT now())",
        )
        .await
        .map_err(pg("creating schema_version"))?;
        // Re-read under the lock: another node may have applied it meanwhile.
        let now: i32 = tx
            .query_one("SELECT coalesce(max(version), 0) FROM schema_version", &[])
            .await
            .map_err(pg("reading the schema version"))?
            .get(0);
        let now = now.max(0) as u32;
        if now > target {
            return Err(newer_error(now, target));
        }
        if now >= m.version {
            continue;
        }
        tx.batch_execute(m.sql)
            .await
            .map_err(|e| storage_err(format!("postgres: applying {}: {}", m.name, describe(&e))))?;
        tx.execute(
            "INSERT INTO schema_version (version, name) VALUES ($1, $2)",
            &[&(m.version as i32), &m.name],
        )
        .await
        .map_err(pg("recording the schema version"))?;
        tx.commit().await.map_err(|e| {
            storage_err(format!("postgres: committing {}: {}", m.name, describe(&e)))
        })?;
        applied.push(m.name);
    }
    Ok(MigrateReport {
        from,
        to: target,
        applied,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn migrations_are_numbered_in_order_and_named_after_their_version() {
        for (i, m) in MIGRATIONS.iter().enumerate() {
            assert_eq!(m.version as usize, i + 1);
            assert!(
                m.name.starts_with(&format!("{:04}_", m.version)),
                "{}",
                m.name
            );
            assert!(m.sql.contains("CREATE"), "{} looks empty", m.name);
        }
        assert_eq!(PG_SCHEMA_VERSION as usize, MIGRATIONS.len());
    }
}
