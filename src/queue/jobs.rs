//! The `jobs` table (`migrations/postgres/0002_jobs.sql`): ingest jobs of the work queue,
//! kept in the same PostgreSQL database as the shapes. Every statement is parameterised.

use crate::index::store::{now_unix_ms, storage_err};
use crate::storage::pg_migrate::{pg, Prepared};
use crate::storage::postgres::key;
use crate::storage::{format_id, PgStore};
use crate::{Error, Result};
use serde::Serialize;

/// Where a job is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// Stored, waiting for (or being analysed by) a worker.
    Pending,
    /// The shape is stored (`shape_id`).
    Done,
    /// A dead letter: the input was refused, or failed `max_deliver` times.
    Failed,
}

impl JobState {
    fn parse(s: &str) -> Result<JobState> {
        match s {
            "pending" => Ok(JobState::Pending),
            "done" => Ok(JobState::Done),
            "failed" => Ok(JobState::Failed),
            other => Err(storage_err(format!(
                "postgres: unknown job state {other:?}"
            ))),
        }
    }
}

/// The error a failed job ended with.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct DeadLetter {
    /// The HTTP status the refusal maps to (4xx: the input; 5xx: retries exhausted).
    pub status: u16,
    /// Stable error code (`mesh.parse`, `limit.vertices`, ...).
    pub code: String,
    /// Message.
    pub message: String,
}

/// A job as `GET /v1/jobs/{id}` shows it.
#[derive(Debug, Clone, Serialize)]
pub struct Job {
    /// Job id (the shape is stored under it, unless the same bytes were stored before).
    pub id: String,
    /// State.
    pub state: JobState,
    /// Deliveries a worker started.
    pub attempts: u32,
    /// The stored shape, once done.
    pub shape_id: Option<String>,
    /// The dead letter, once failed.
    pub error: Option<DeadLetter>,
    /// When the job was created (Unix ms).
    pub created_unix_ms: u64,
    /// Last change (Unix ms).
    pub updated_unix_ms: u64,
}

/// What a worker needs to run a job.
#[derive(Debug, Clone)]
pub struct JobInput {
    /// Job id.
    pub id: String,
    /// SHA-256 of the upload.
    pub sha256: [u8; 32],
    /// Display name, if given.
    pub name: Option<String>,
    /// Tags.
    pub tags: Vec<String>,
    /// Format hint of the upload.
    pub format_hint: Option<String>,
    /// The upload (`None` once done).
    pub upload: Option<Vec<u8>>,
    /// State when claimed.
    pub state: JobState,
    /// Attempts including this one.
    pub attempts: u32,
}

/// What [`JobStore::enqueue`] found or made.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Enqueued {
    /// Job id.
    pub id: String,
    /// True when this call created the job (or reset a job whose retries were exhausted).
    pub created: bool,
    /// Its state now.
    pub state: JobState,
}

/// The job table on a [`PgStore`]'s pool.
#[derive(Clone)]
pub struct JobStore {
    pg: PgStore,
}

fn now() -> i64 {
    i64::try_from(now_unix_ms()).unwrap_or(i64::MAX)
}

impl JobStore {
    /// The job table of the database `pg` is connected to.
    pub fn new(pg: PgStore) -> JobStore {
        JobStore { pg }
    }

    /// Stores an upload as a pending job in one committed row, or finds the job of the same
    /// bytes. A job that failed for a server-side reason (5xx: retries exhausted) is reset to
    /// pending (`created`: true); one whose input was refused (4xx) stays failed.
    pub async fn enqueue(
        &self,
        sha256: &[u8; 32],
        name: Option<&str>,
        tags: &[String],
        format_hint: Option<&str>,
        upload: &[u8],
    ) -> Result<Enqueued> {
        let c = self.pg.client().await?;
        let sha: &[u8] = sha256;
        let t = now();
        for _ in 0..5 {
            let ins = c
                .prepared(
                    "INSERT INTO jobs (id, sha256, name, tags, format_hint, upload, state, \
                     created_unix_ms, updated_unix_ms) \
                     VALUES (nextval('shape_id_seq'), $1, $2, $3, $4, $5, 'pending', $6, $6) \
                     ON CONFLICT (sha256) DO NOTHING RETURNING id",
                )
                .await?;
            if let Some(row) = c
                .query_opt(&ins, &[&sha, &name, &tags, &format_hint, &upload, &t])
                .await
                .map_err(pg("storing a job"))?
            {
                return Ok(Enqueued {
                    id: format_id(row.get::<_, i64>(0) as u64),
                    created: true,
                    state: JobState::Pending,
                });
            }
            // The same bytes have a job. Reset it when its retries ran out on a server fault.
            let reset = c
                .prepared(
                    "UPDATE jobs SET state = 'pending', attempts = 0, upload = $2, \
                     error_status = NULL, error_code = NULL, error_message = NULL, \
                     updated_unix_ms = $3 \
                     WHERE sha256 = $1 AND state = 'failed' AND error_status >= 500 RETURNING id",
                )
                .await?;
            if let Some(row) = c
                .query_opt(&reset, &[&sha, &upload, &t])
                .await
                .map_err(pg("resetting a job"))?
            {
                return Ok(Enqueued {
                    id: format_id(row.get::<_, i64>(0) as u64),
                    created: true,
                    state: JobState::Pending,
                });
            }
            let sel = c
                .prepared("SELECT id, state FROM jobs WHERE sha256 = $1")
                .await?;
            if let Some(row) = c
                .query_opt(&sel, &[&sha])
                .await
                .map_err(pg("reading a job"))?
            {
                return Ok(Enqueued {
                    id: format_id(row.get::<_, i64>(0) as u64),
                    created: false,
                    state: JobState::parse(row.get(1))?,
                });
            }
            // Deleted (with its shape) between the statements: try again.
        }
        Err(storage_err(
            "postgres: a job kept vanishing while being stored",
        ))
    }

    /// A job, `None` when unknown (or malformed id).
    pub async fn get(&self, id: &str) -> Result<Option<Job>> {
        let Some(k) = key(id) else {
            return Ok(None);
        };
        let c = self.pg.client().await?;
        let st = c
            .prepared(
                "SELECT state, attempts, shape_id, error_status, error_code, error_message, \
                 created_unix_ms, updated_unix_ms FROM jobs WHERE id = $1",
            )
            .await?;
        let Some(row) = c.query_opt(&st, &[&k]).await.map_err(pg("reading a job"))? else {
            return Ok(None);
        };
        let status: Option<i32> = row.get(3);
        let error = match (status, row.get::<_, Option<String>>(4)) {
            (Some(s), Some(code)) => Some(DeadLetter {
                status: u16::try_from(s).unwrap_or(500),
                code,
                message: row.get::<_, Option<String>>(5).unwrap_or_default(),
            }),
            _ => None,
        };
        Ok(Some(Job {
            id: id.to_string(),
            state: JobState::parse(row.get(0))?,
            attempts: u32::try_from(row.get::<_, i32>(1)).unwrap_or(0),
            shape_id: row
                .get::<_, Option<i64>>(2)
                .map(|s| format_id(s.max(0) as u64)),
            error,
            created_unix_ms: row.get::<_, i64>(6).max(0) as u64,
            updated_unix_ms: row.get::<_, i64>(7).max(0) as u64,
        }))
    }

    /// Counts a delivery and returns the job's input; `None` when the job is unknown (deleted
    /// with its shape, or a malformed id).
    pub async fn claim(&self, id: &str) -> Result<Option<JobInput>> {
        let Some(k) = key(id) else {
            return Ok(None);
        };
        let c = self.pg.client().await?;
        let st = c
            .prepared(
                "UPDATE jobs SET attempts = attempts + 1, updated_unix_ms = $2 WHERE id = $1 \
                 RETURNING sha256, name, tags, format_hint, upload, state, attempts",
            )
            .await?;
        let Some(row) = c
            .query_opt(&st, &[&k, &now()])
            .await
            .map_err(pg("claiming a job"))?
        else {
            return Ok(None);
        };
        let sha: Vec<u8> = row.get(0);
        let sha256: [u8; 32] = sha
            .try_into()
            .map_err(|_| storage_err("postgres: a job's sha256 is not 32 bytes"))?;
        Ok(Some(JobInput {
            id: id.to_string(),
            sha256,
            name: row.get(1),
            tags: row.get(2),
            format_hint: row.get(3),
            upload: row.get(4),
            state: JobState::parse(row.get(5))?,
            attempts: u32::try_from(row.get::<_, i32>(6)).unwrap_or(0),
        }))
    }

    /// Marks a job done with its stored shape (and drops the upload: the stored original is
    /// in `meshes`). False when the job is gone.
    pub async fn complete(&self, id: &str, shape_id: &str) -> Result<bool> {
        let (Some(k), Some(s)) = (key(id), key(shape_id)) else {
            return Err(Error::InvalidArgument(format!(
                "job {id:?} / shape {shape_id:?}: expected ids"
            )));
        };
        let c = self.pg.client().await?;
        let st = c
            .prepared(
                "UPDATE jobs SET state = 'done', shape_id = $2, upload = NULL, \
                 updated_unix_ms = $3 WHERE id = $1",
            )
            .await?;
        let n = c
            .execute(&st, &[&k, &s, &now()])
            .await
            .map_err(pg("completing a job"))?;
        Ok(n == 1)
    }

    /// Records a dead letter on a pending job. False when it is gone or no longer pending.
    pub async fn fail(&self, id: &str, dead: &DeadLetter) -> Result<bool> {
        let Some(k) = key(id) else {
            return Ok(false);
        };
        let c = self.pg.client().await?;
        let st = c
            .prepared(
                "UPDATE jobs SET state = 'failed', error_status = $2, error_code = $3, \
                 error_message = $4, updated_unix_ms = $5 WHERE id = $1 AND state = 'pending'",
            )
            .await?;
        let n = c
            .execute(
                &st,
                &[
                    &k,
                    &i32::from(dead.status),
                    &dead.code,
                    &dead.message,
                    &now(),
                ],
            )
            .await
            .map_err(pg("failing a job"))?;
        Ok(n == 1)
    }

    /// Ids of jobs pending without any change for `older_than_ms` (republished by workers).
    pub async fn stale_pending(&self, older_than_ms: u64, limit: i64) -> Result<Vec<String>> {
        let cutoff = now().saturating_sub(i64::try_from(older_than_ms).unwrap_or(i64::MAX));
        let c = self.pg.client().await?;
        let st = c
            .prepared(
                "SELECT id FROM jobs WHERE state = 'pending' AND updated_unix_ms < $1 \
                 ORDER BY id LIMIT $2",
            )
            .await?;
        let rows = c
            .query(&st, &[&cutoff, &limit])
            .await
            .map_err(pg("listing stale jobs"))?;
        Ok(rows
            .iter()
            .map(|r| format_id(r.get::<_, i64>(0).max(0) as u64))
            .collect())
    }

    /// Marks a job as just seen (so [`JobStore::stale_pending`] does not return it at once).
    pub async fn touch(&self, id: &str) -> Result<()> {
        let Some(k) = key(id) else {
            return Ok(());
        };
        let c = self.pg.client().await?;
        let st = c
            .prepared("UPDATE jobs SET updated_unix_ms = $2 WHERE id = $1")
            .await?;
        c.execute(&st, &[&k, &now()])
            .await
            .map_err(pg("touching a job"))?;
        Ok(())
    }
}
