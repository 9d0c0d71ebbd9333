//! `shapeseek serve`: the REST service on the embedded sled index.
//!
//! Endpoints (contract: `api/openapi.yaml`, served at `/openapi.yaml`):
//!
//! | method | path | what |
//! | --- | --- | --- |
//! | POST | `/v1/shapes` | ingest (raw body or multipart `file` + `metadata`); 201, or 200 for known bytes |
//! | GET | `/v1/shapes` | list, `?limit&cursor&tag` |
//! | GET, DELETE | `/v1/shapes/{id}` | record / delete |
//! | GET | `/v1/shapes/{id}/mesh` | original bytes (`application/octet-stream`); `?format=` the mesh read from them, written in that format |
//! | GET | `/v1/shapes/{id}/signature` | the signature's distributions as JSON |
//! | POST | `/v1/search` | by id (JSON), by upload (raw or multipart `file` + `query`), rerank stages |
//! | GET | `/v1/index` | size, calibration epoch, specs, queue |
//! | GET | `/healthz`, `/readyz`, `/metrics`, `/openapi.yaml` | operations |
//!
//! Connections are served by [`conn::serve`] (a connection cap, a header-read timeout,
//! problem+json for hyper's own error answers). Layers (outside in): request-id sanitiser →
//! request id → trace → metrics → panic → problem+json catch-all → body
//! admission ([`limits::admit_body`]: announced size, in-flight byte budget taken as bytes
//! arrive, read deadline) →
//! body limit → per-request timeout (on `/v1`, 503 `request.timeout` + `Retry-After`) →
//! handlers. Every CPU job (ingest, the analysis of an uploaded query, a search with its rerank
//! stages) is admitted by [`admission::Admission`] with an estimated cost: cheap and heavy
//! lanes, heavy work on its own lower-priority thread pool, 503 `server.busy` + `Retry-After`
//! when a lane is full, and a cancellation token that stops the work of an abandoned request. Configuration: [`ServerConfig`] (defaults <
//! TOML file < `SHAPESEEK_*` environment < flags).

pub mod admission;
mod calibrate;
pub mod cluster;
pub mod config;
pub mod conn;
pub mod env;
pub mod handlers;
pub mod limits;
mod load;
pub mod metrics;
pub mod prepared;
pub mod problem;
pub mod router;
mod sample;
pub mod shard;
pub mod state;
#[cfg(test)]
mod state_tests;
#[cfg(test)]
mod test_support;
pub mod web;
mod writes;

pub use config::{MigrateArgs, ServeArgs, ServerConfig};
pub use router::{start, start_with, Running};

use crate::Result;

/// Runs the server with the product engine until SIGINT/SIGTERM, then shuts down gracefully:
/// stops accepting, lets in-flight requests finish for `shutdown_grace_secs`, abandons the rest
/// (a shape is acknowledged only after its write was flushed, so an abandoned one is simply
/// absent), flushes the index.
pub async fn serve(cfg: ServerConfig) -> Result<()> {
    init_tracing(&cfg.log_format);
    let running = start(cfg).await?;
    tracing::info!(addr = %running.addr, "listening");
    shutdown_signal().await;
    tracing::info!("shutdown signal received; draining");
    running.shutdown().await
}

/// Milliseconds since `t`.
pub(crate) fn ms(t: std::time::Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// True when a request's `If-None-Match` names `etag` (a strong tag in quotes) or `*`: the
/// weak comparison of RFC 9110 (a `W/` prefix ignored), over every such header line.
pub(crate) fn if_none_match(headers: &axum::http::HeaderMap, etag: &str) -> bool {
    headers
        .get_all(axum::http::header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(|t| t.trim())
        .any(|t| t == "*" || t.strip_prefix("W/").unwrap_or(t) == etag)
}

/// Installs a tracing subscriber (RUST_LOG or `info`), text or JSON. No-op if one is set.
pub fn init_tracing(format: &str) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stdout());
    let _ = if format == "json" {
        tracing_subscriber::fmt()
            .json()
            .with_env_filter(filter)
            .try_init()
    } else {
        tracing_subscriber::fmt()
            .with_ansi(ansi)
            .with_env_filter(filter)
            .try_init()
    };
}

/// Resolves on SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}
