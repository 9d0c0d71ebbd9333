//! `shapeseek worker`: flags, then [`shapeseek::worker::run`] on a tokio runtime.

use super::CliError;
use clap::Args;
use std::path::PathBuf;

/// `shapeseek worker` flags (the rest of the configuration — limits, eigenpairs, queue
/// settings — comes from the same TOML file and `SHAPESEEK_*` variables as `serve`).
#[derive(Debug, Clone, Args)]
pub struct WorkerArgs {
    /// The PostgreSQL database the shapes go to (`postgres://…`) [env SHAPESEEK_STORE]
    #[arg(long)]
    pub store: Option<String>,
    /// The NATS JetStream server the jobs come from (`nats://HOST:PORT`) [env SHAPESEEK_QUEUE]
    #[arg(long)]
    pub queue: Option<String>,
    /// Jobs analysed at once by this process
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// TOML config file [env SHAPESEEK_CONFIG]
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Log format: text or json [env SHAPESEEK_LOG_FORMAT]
    #[arg(long)]
    pub log_format: Option<String>,
}

/// Runs the worker until SIGINT/SIGTERM.
pub fn run(a: &WorkerArgs) -> Result<(), CliError> {
    let serve = shapeseek::server::ServeArgs {
        store: a.store.clone(),
        queue: a.queue.clone(),
        config: a.config.clone(),
        log_format: a.log_format.clone(),
        ..Default::default()
    };
    let cfg = serve.to_config()?;
    if cfg.store_url().is_none() || cfg.queue_url().is_none() {
        return Err(CliError::new(
            "usage",
            "worker: --store postgres://… and --queue nats://… are required",
            64,
        ));
    }
    shapeseek::server::init_tracing(&cfg.log_format);
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| CliError::new("io", format!("cannot start the runtime: {e}"), 74))?
        .block_on(shapeseek::worker::run(shapeseek::worker::WorkerConfig {
            server: cfg,
            jobs: a.jobs,
        }))?;
    Ok(())
}
