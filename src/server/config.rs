//! Server configuration: one struct, from defaults, a TOML file, `SHAPESEEK_*` environment
//! variables and command-line flags (later sources win).

use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Everything `shapeseek serve` can be told. Every field is also a TOML key of the config file
/// and an environment variable `SHAPESEEK_<KEY IN UPPER CASE>` (e.g. `SHAPESEEK_MAX_VERTICES`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// Data directory (the sled index lives in `<data>/db`); used when `store` is empty.
    pub data: PathBuf,
    /// MiB of sled's page cache for the sled index in `data` (sled's default, 1024). What the
    /// node keeps of the stored values it reads (signatures at start and recalibration, payloads
    /// for re-ranking stages, originals) is bounded by it; the scan's own memory is not.
    pub sled_cache_mb: u64,
    /// A PostgreSQL URL (`postgres://…`) to keep the shapes in instead of the sled index in
    /// `data` (empty: the sled index). The database must be migrated (`shapeseek migrate
    /// --store URL`).
    pub store: String,
    /// A NATS URL (`nats://HOST:PORT`, JetStream enabled): uploads become jobs of the work
    /// queue, analysed by `shapeseek worker`s, and the scan follows the change feed. Needs a
    /// PostgreSQL `store`. Empty: ingest in this process.
    pub queue: String,
    /// Seconds a worker may hold a job without an ack or an "in progress" before JetStream
    /// redelivers it (the queue's consumer is created with it by the first node or worker).
    pub queue_ack_wait_secs: f64,
    /// Deliveries of a job before it becomes a dead letter.
    pub queue_max_deliver: u32,
    /// Seconds between two reconciliations of a cluster node's scan with the store.
    pub reconcile_secs: f64,
    /// `S/N`: this node holds shard `S` of `N` (the shapes whose id is `S` mod `N`) and answers
    /// a search by fanning out to every shard over NATS (`docs/scale-out.md` §3). Needs a
    /// PostgreSQL `store` and a `queue`. Empty: the whole corpus.
    pub shard: String,
    /// Seconds a coordinator waits for every shard's answer (503 `search.shard_unavailable`
    /// past it).
    pub shard_timeout_secs: f64,
    /// Listen address `HOST:PORT` (port 0 picks a free one).
    pub addr: String,
    /// Largest accepted request body, bytes.
    pub max_body_bytes: usize,
    /// Largest accepted mesh, vertices (as read).
    pub max_vertices: usize,
    /// Largest accepted mesh, triangles (as read).
    pub max_faces: usize,
    /// Per-request time limit, seconds (503 `request.timeout` past it).
    pub request_timeout_secs: f64,
    /// Connections served at once; a connection over the cap gets 503 `server.busy` and is
    /// closed. Keep it below the process's open-file limit.
    pub max_connections: usize,
    /// Seconds a client has to send a complete request head; also how long an idle keep-alive
    /// connection is kept. Past it the connection is closed.
    pub header_read_timeout_secs: f64,
    /// Seconds a client has to send a whole request body once its head arrived (408
    /// `request.body_timeout` past it).
    pub body_read_timeout_secs: f64,
    /// Request body bytes held in memory at once over all connections, each body counted as
    /// it arrives (in 64 KiB steps); a body that does not fit gets 503 `server.busy`. At least
    /// `max_body_bytes`.
    pub max_inflight_body_bytes: usize,
    /// Download bytes (stored originals, format conversions) held in memory at once over all
    /// connections, each until its last byte has left; a download waits for room (until the
    /// request's deadline). At least `max_body_bytes`.
    pub max_inflight_response_bytes: usize,
    /// Seconds a response may wait for a client that reads none of it (the socket's send
    /// buffer full, no byte accepted); past it the connection is closed and what it held is
    /// freed.
    pub send_stall_timeout_secs: f64,
    /// CPU jobs (analysis + signature) run at once; 0 = number of cores.
    pub workers: usize,
    /// CPU jobs allowed to wait, per admission lane (cheap, heavy); more get 503 `server.busy`.
    pub queue_capacity: usize,
    /// Share of the workers that expensive work (analysis of uploads, GW stages, large
    /// reciprocal stages) may use, in (0, 1]; below 1 at least one worker is kept for cheap
    /// searches. See `src/server/admission.rs`.
    pub heavy_share: f64,
    /// Nice value (0..=19) of the threads running expensive work, so cheap searches get the CPU
    /// first when both want it (Linux; 0 = no change).
    pub heavy_nice: i32,
    /// Let an expensive job use every worker when it starts while no other expensive job runs
    /// and no cheap job runs, waits or finished within the last second; its threads run at nice
    /// `heavy_nice`, so cheap work arriving meanwhile takes its core back through the
    /// scheduler. No effect unless `heavy_nice` > 0 (Linux) and the heavy lane has fewer
    /// threads than there are workers.
    pub heavy_borrow: bool,
    /// Stored original bytes allowed per shape regardless of its geometry.
    pub stored_bytes_floor: usize,
    /// Stored original bytes allowed per vertex + face of the mesh read; an upload over
    /// `max(stored_bytes_floor, stored_bytes_per_element × (vertices + faces))` (padding,
    /// comments, textures) is not kept as uploaded (see `oversized_original`).
    pub stored_bytes_per_element: usize,
    /// What to do with an upload over the stored-bytes cap: `reencode` (store the mesh as
    /// read, re-encoded canonically in the same format) or `refuse` (413 `limit.stored_bytes`).
    pub oversized_original: String,
    /// `Retry-After` seconds sent with 503 `server.busy`.
    pub retry_after_secs: u64,
    /// Recalibrate when the index grew or shrank by more than this fraction since the last
    /// calibration.
    pub recalibrate_fraction: f64,
    /// Most shapes a calibration is computed on (0: all). Above it, the shapes with the
    /// smallest content hashes (see `src/server/sample.rs`): a calibration holds the whole
    /// signature (≈ 50 KB) of every shape it is computed on.
    pub calibration_sample: usize,
    /// Largest `top_k` and rerank shortlist accepted.
    pub max_top_k: usize,
    /// Seconds granted to in-flight requests after SIGINT/SIGTERM before they are abandoned.
    pub shutdown_grace_secs: f64,
    /// Log format: `text` or `json`.
    pub log_format: String,
    /// Eigenpairs computed per shape for its signature (changing it recomputes the stored
    /// signatures from the stored originals at the next start).
    pub eigenpairs: usize,
    /// Most vertices a shape is analysed at: a larger mesh is simplified to this many before
    /// its spectrum ([`crate::mesh::decimate`]); its original is stored as sent. 0: every mesh
    /// at full resolution (time and memory grow with it: 28 s and 1 GiB for one upload of
    /// 180 000 vertices). Not part of the spec key: stored signatures are not recomputed when
    /// it changes, and every node of a cluster should be given the same.
    pub analysis_vertex_budget: usize,
}

/// Most CPU workers a node may be configured with ([`ServerConfig::workers`]).
pub const MAX_WORKERS: usize = 1024;

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            data: PathBuf::from("./shapeseek-data"),
            sled_cache_mb: 1024,
            store: String::new(),
            queue: String::new(),
            queue_ack_wait_secs: 30.0,
            queue_max_deliver: 5,
            reconcile_secs: 5.0,
            shard: String::new(),
            shard_timeout_secs: 5.0,
            addr: "127.0.0.1:8080".into(),
            max_body_bytes: 64 << 20,
            max_vertices: 500_000,
            max_faces: 1_000_000,
            request_timeout_secs: 120.0,
            max_connections: 512,
            header_read_timeout_secs: 10.0,
            body_read_timeout_secs: 60.0,
            max_inflight_body_bytes: 256 << 20,
            max_inflight_response_bytes: 256 << 20,
            send_stall_timeout_secs: 30.0,
            workers: 0,
            queue_capacity: 16,
            heavy_share: 0.75,
            heavy_nice: 10,
            heavy_borrow: true,
            stored_bytes_floor: 256 << 10,
            stored_bytes_per_element: 256,
            oversized_original: "reencode".into(),
            retry_after_secs: 2,
            recalibrate_fraction: 0.1,
            calibration_sample: 10_000,
            max_top_k: 1000,
            shutdown_grace_secs: 30.0,
            log_format: "text".into(),
            eigenpairs: 100,
            analysis_vertex_budget: crate::presets::ANALYSIS_VERTEX_BUDGET,
        }
    }
}

impl ServerConfig {
    /// The product engine ([`crate::index::default_engine`]) with this configuration's
    /// eigenpairs and vertex budget: what `serve`, `worker` and `ingest --data` analyse with.
    pub fn engine(&self) -> crate::index::Engine {
        let mut engine = crate::index::default_engine();
        engine.analyze.eigen.k = self.eigenpairs;
        engine.analyze.prepare.max_vertices =
            (self.analysis_vertex_budget > 0).then_some(self.analysis_vertex_budget);
        engine
    }

    /// Defaults, then the TOML `file` (if any), then `SHAPESEEK_*` variables from `env`.
    pub fn load(
        file: Option<&std::path::Path>,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Self> {
        let mut table = match toml::Value::try_from(ServerConfig::default()) {
            Ok(toml::Value::Table(t)) => t,
            _ => {
                return Err(Error::InvalidArgument(
                    "config: cannot serialise defaults".into(),
                ))
            }
        };
        if let Some(path) = file {
            let text = std::fs::read_to_string(path).map_err(|e| {
                Error::InvalidArgument(format!("config file {}: {e}", path.display()))
            })?;
            let file_table: toml::Table = toml::from_str(&text).map_err(|e| {
                Error::InvalidArgument(format!("config file {}: {e}", path.display()))
            })?;
            for (k, v) in file_table {
                if !table.contains_key(&k) {
                    return Err(Error::InvalidArgument(format!(
                        "config file {}: unknown key {k:?}",
                        path.display()
                    )));
                }
                table.insert(k, v);
            }
        }
        for (k, v) in env {
            let Some(key) = k.strip_prefix("SHAPESEEK_") else {
                continue;
            };
            let key = key.to_ascii_lowercase();
            if key == "config" || key == "log" {
                continue;
            }
            let Some(old) = table.get(&key) else {
                continue;
            };
            let new = match old {
                toml::Value::Integer(_) => v.trim().parse::<i64>().map(toml::Value::Integer).ok(),
                toml::Value::Float(_) => v.trim().parse::<f64>().map(toml::Value::Float).ok(),
                toml::Value::Boolean(_) => v.trim().parse::<bool>().map(toml::Value::Boolean).ok(),
                _ => Some(toml::Value::String(v.clone())),
            }
            .ok_or_else(|| {
                Error::InvalidArgument(format!("environment {k}={v:?}: not a valid value"))
            })?;
            table.insert(key, new);
        }
        let cfg: ServerConfig = toml::Value::Table(table)
            .try_into()
            .map_err(|e| Error::InvalidArgument(format!("config: {e}")))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: &str| Err(Error::InvalidArgument(format!("config: {m}")));
        if self.max_body_bytes == 0 || self.max_vertices == 0 || self.max_faces == 0 {
            return bad("max_body_bytes, max_vertices and max_faces must be > 0");
        }
        // Each worker is a thread (two pools of them): 100 000 spent minutes starting threads
        // before the server listened, and said nothing.
        if self.workers > MAX_WORKERS {
            return Err(Error::InvalidArgument(format!(
                "config: workers must be in 0..={MAX_WORKERS} (0: one per core), got {}",
                self.workers
            )));
        }
        if !(self.request_timeout_secs.is_finite() && self.request_timeout_secs > 0.0) {
            return bad("request_timeout_secs must be > 0");
        }
        for (name, v) in [
            ("header_read_timeout_secs", self.header_read_timeout_secs),
            ("body_read_timeout_secs", self.body_read_timeout_secs),
            ("send_stall_timeout_secs", self.send_stall_timeout_secs),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
                return bad(&format!("{name} must be in (0, 86400]"));
            }
        }
        if !(1..=1 << 20).contains(&self.sled_cache_mb) {
            return bad("sled_cache_mb must be in 1..=1048576");
        }
        if self.max_connections == 0 {
            return bad("max_connections must be > 0");
        }
        if self.max_inflight_body_bytes < self.max_body_bytes {
            return bad(&format!(
                "max_inflight_body_bytes ({}) must be at least max_body_bytes ({}): a \
                 maximum-size upload could never be admitted",
                self.max_inflight_body_bytes, self.max_body_bytes
            ));
        }
        if self.max_inflight_response_bytes < self.max_body_bytes {
            return bad(&format!(
                "max_inflight_response_bytes ({}) must be at least max_body_bytes ({}): the \
                 largest original would take the whole budget",
                self.max_inflight_response_bytes, self.max_body_bytes
            ));
        }
        if !(self.shutdown_grace_secs.is_finite() && self.shutdown_grace_secs >= 0.0) {
            return bad("shutdown_grace_secs must be >= 0");
        }
        if !(self.recalibrate_fraction.is_finite() && self.recalibrate_fraction >= 0.0) {
            return bad("recalibrate_fraction must be >= 0");
        }
        let budget = self.analysis_vertex_budget;
        let least = crate::mesh::prepare::MIN_VERTEX_BUDGET;
        if budget != 0 && budget < least {
            return bad(&format!(
                "analysis_vertex_budget must be 0 (none) or at least {least}, got {budget}"
            ));
        }
        if !(2..=2000).contains(&self.eigenpairs) {
            return bad("eigenpairs must be in 2..=2000");
        }
        let need = crate::presets::default_config().signature.min_eigenpairs();
        if self.eigenpairs < need {
            return bad(&format!(
                "eigenpairs must be at least {need} for the default signature (its ShapeDNA \
                 channel compares the first {} non-zero eigenvalues), got {}",
                need - 1,
                self.eigenpairs
            ));
        }
        if !(self.heavy_share.is_finite() && self.heavy_share > 0.0 && self.heavy_share <= 1.0) {
            return bad("heavy_share must be in (0, 1]");
        }
        if !(0..=19).contains(&self.heavy_nice) {
            return bad("heavy_nice must be in 0..=19");
        }
        if self.stored_bytes_per_element == 0 {
            return bad("stored_bytes_per_element must be > 0");
        }
        if self.oversized_original != "reencode" && self.oversized_original != "refuse" {
            return bad("oversized_original must be \"reencode\" or \"refuse\"");
        }
        if self.max_top_k == 0 {
            return bad("max_top_k must be > 0");
        }
        if self.log_format != "text" && self.log_format != "json" {
            return bad("log_format must be \"text\" or \"json\"");
        }
        if !self.queue.is_empty() {
            if !crate::queue::is_nats_url(&self.queue) {
                return bad("queue must be a nats:// URL (or empty)");
            }
            if self.store.is_empty() {
                return bad("queue needs a PostgreSQL store (--store postgres://…)");
            }
        }
        if !self.shard.is_empty() {
            crate::queue::shard::ShardSpec::parse(&self.shard)
                .map_err(|e| Error::InvalidArgument(format!("config: {e}")))?;
            if self.store.is_empty() || self.queue.is_empty() {
                return bad(
                    "shard needs a PostgreSQL store and a NATS queue (--store postgres://… --queue nats://…)",
                );
            }
        }
        for (name, v) in [
            ("queue_ack_wait_secs", self.queue_ack_wait_secs),
            ("reconcile_secs", self.reconcile_secs),
            ("shard_timeout_secs", self.shard_timeout_secs),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
                return bad(&format!("{name} must be in (0, 86400]"));
            }
        }
        if self.queue_max_deliver == 0 {
            return bad("queue_max_deliver must be > 0");
        }
        if !self.store.is_empty() && !crate::storage::is_postgres_url(&self.store) {
            return bad("store must be a postgres:// or postgresql:// URL (or empty: the sled index in `data`)");
        }
        Ok(())
    }

    /// sled's page cache in bytes (`sled_cache_mb`).
    pub fn sled_cache_bytes(&self) -> u64 {
        self.sled_cache_mb << 20
    }

    /// The PostgreSQL URL of `store`, `None` for the sled index in `data`.
    pub fn store_url(&self) -> Option<&str> {
        (!self.store.is_empty()).then_some(self.store.as_str())
    }

    /// The NATS URL of `queue`, `None` without a queue.
    pub fn queue_url(&self) -> Option<&str> {
        (!self.queue.is_empty()).then_some(self.queue.as_str())
    }

    /// This node's shard, `None` for the whole corpus (validated by [`ServerConfig::validate`]).
    pub fn shard_spec(&self) -> Option<crate::queue::shard::ShardSpec> {
        (!self.shard.is_empty())
            .then(|| crate::queue::shard::ShardSpec::parse(&self.shard).ok())
            .flatten()
    }

    /// The work-queue settings.
    pub fn queue_options(&self) -> crate::queue::QueueOptions {
        crate::queue::QueueOptions {
            ack_wait: std::time::Duration::from_secs_f64(self.queue_ack_wait_secs),
            max_deliver: i64::from(self.queue_max_deliver),
        }
    }

    /// Worker count with 0 resolved to the number of cores.
    pub fn effective_workers(&self) -> usize {
        if self.workers == 0 {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(2)
        } else {
            self.workers
        }
    }
}

/// `shapeseek serve` flags.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ServeArgs {
    /// Data directory [default: ./shapeseek-data; env SHAPESEEK_DATA]
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Keep the shapes in this PostgreSQL database (`postgres://…`) instead of the sled index in
    /// the data directory [env SHAPESEEK_STORE]
    #[arg(long)]
    pub store: Option<String>,
    /// Hand the analysis of uploads to `shapeseek worker`s through this NATS JetStream server
    /// (`nats://HOST:PORT`; needs --store) [env SHAPESEEK_QUEUE]
    #[arg(long)]
    pub queue: Option<String>,
    /// Hold shard S of N (`S/N`, the shapes whose id is S mod N) and answer searches by fanning
    /// out to every shard over NATS (needs --store and --queue) [env SHAPESEEK_SHARD]
    #[arg(long)]
    pub shard: Option<String>,
    /// Listen address HOST:PORT [default: 127.0.0.1:8080; env SHAPESEEK_ADDR]
    #[arg(long)]
    pub addr: Option<String>,
    /// TOML config file [env SHAPESEEK_CONFIG]
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// CPU workers for analysis (0 = cores) [env SHAPESEEK_WORKERS]
    #[arg(long)]
    pub workers: Option<usize>,
    /// Log format: text or json [env SHAPESEEK_LOG_FORMAT]
    #[arg(long)]
    pub log_format: Option<String>,
}

impl ServeArgs {
    /// Defaults < config file < environment < flags.
    pub fn to_config(&self) -> Result<ServerConfig> {
        self.to_config_from(std::env::vars())
    }

    /// [`Self::to_config`] with these variables in place of the process's environment.
    pub fn to_config_from(
        &self,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<ServerConfig> {
        let file = self
            .config
            .clone()
            .or_else(|| std::env::var_os("SHAPESEEK_CONFIG").map(PathBuf::from));
        let mut cfg = ServerConfig::load(file.as_deref(), env)?;
        if let Some(d) = &self.data {
            cfg.data = d.clone();
        }
        if let Some(a) = &self.addr {
            cfg.addr = a.clone();
        }
        if let Some(s) = &self.store {
            cfg.store = s.clone();
        }
        if let Some(q) = &self.queue {
            cfg.queue = q.clone();
        }
        if let Some(s) = &self.shard {
            cfg.shard = s.clone();
        }
        if let Some(w) = self.workers {
            cfg.workers = w;
        }
        if let Some(f) = &self.log_format {
            cfg.log_format = f.clone();
        }
        cfg.validate()?;
        Ok(cfg)
    }
}

/// `shapeseek migrate` flags.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct MigrateArgs {
    /// Data directory [default: ./shapeseek-data; env SHAPESEEK_DATA]
    #[arg(long, conflicts_with = "store")]
    pub data: Option<PathBuf>,
    /// Apply the SQL migrations (`migrations/postgres/`) to this PostgreSQL database instead
    /// [env SHAPESEEK_STORE]
    #[arg(long)]
    pub store: Option<String>,
}

impl MigrateArgs {
    /// The data directory to migrate.
    pub fn data_dir(&self) -> PathBuf {
        self.data
            .clone()
            .or_else(|| std::env::var_os("SHAPESEEK_DATA").map(PathBuf::from))
            .unwrap_or_else(|| ServerConfig::default().data)
    }

    /// The PostgreSQL URL to migrate (`--store`, else `SHAPESEEK_STORE` when `--data` is not
    /// given), `None` for a sled data directory.
    pub fn store_url(&self) -> Option<String> {
        self.store.clone().or_else(|| {
            self.data
                .is_none()
                .then(|| std::env::var("SHAPESEEK_STORE").ok())
                .flatten()
                .filter(|s| !s.is_empty())
        })
    }

    /// Runs the migration and returns a line for the user.
    pub fn run(&self) -> Result<String> {
        if let Some(url) = self.store_url() {
            return migrate_postgres(&url);
        }
        let dir = self.data_dir();
        Ok(match crate::index::migrate(&dir)? {
            crate::index::MigrateOutcome::UpToDate(v) => {
                format!(
                    "index at {} is up to date (schema version {v})",
                    dir.display()
                )
            }
            crate::index::MigrateOutcome::Upgraded { from, to, backup } => format!(
                "upgraded index at {} from schema version {from} to {to}; backup at {}",
                dir.display(),
                backup.display()
            ),
        })
    }
}

/// `shapeseek migrate --store postgres://…`: applies the missing SQL migrations (refusing a
/// database whose schema is newer than this build's).
fn migrate_postgres(url: &str) -> Result<String> {
    if !crate::storage::is_postgres_url(url) {
        return Err(Error::InvalidArgument(format!(
            "--store {url:?}: expected a postgres:// or postgresql:// URL"
        )));
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let r = rt.block_on(crate::storage::postgres::migrate_url(url))?;
    Ok(if r.applied.is_empty() {
        format!("database is up to date (schema version {})", r.to)
    } else {
        format!(
            "migrated database from schema version {} to {} ({})",
            r.from,
            r.to,
            r.applied.join(", ")
        )
    })
}
