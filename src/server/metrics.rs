//! Prometheus metrics: one process-wide recorder, rendered by `GET /metrics`.
//!
//! Names: `shapeseek_http_requests_total{method,route,status}`,
//! `shapeseek_http_request_duration_seconds{method,route}` (histogram),
//! `shapeseek_ingest_stage_seconds{stage}` (histogram: read, prepare, laplacian, factorization,
//! eigensolve, signature, store), `shapeseek_queue_depth`, `shapeseek_jobs_running`,
//! `shapeseek_index_shapes`, `shapeseek_index_bytes`, `shapeseek_calibration_epoch`,
//! `shapeseek_search_candidates_total`.

use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};
use std::sync::OnceLock;

static HANDLE: OnceLock<Option<PrometheusHandle>> = OnceLock::new();

/// The process-wide recorder's handle (installed on first use; None if another recorder was
/// installed by the embedding program).
pub fn handle() -> Option<PrometheusHandle> {
    HANDLE
        .get_or_init(|| {
            let buckets = [
                0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
                60.0,
            ];
            let builder = PrometheusBuilder::new()
                .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), &buckets)
                .ok()?;
            let recorder = builder.build_recorder();
            let handle = recorder.handle();
            metrics::set_global_recorder(recorder).ok()?;
            describe();
            Some(handle)
        })
        .clone()
}

fn describe() {
    metrics::describe_counter!(
        "shapeseek_http_requests_total",
        "HTTP requests by route and status"
    );
    metrics::describe_histogram!(
        "shapeseek_http_request_duration_seconds",
        metrics::Unit::Seconds,
        "HTTP request latency"
    );
    metrics::describe_histogram!(
        "shapeseek_ingest_stage_seconds",
        metrics::Unit::Seconds,
        "time per ingest stage"
    );
    metrics::describe_gauge!(
        "shapeseek_queue_depth",
        "analysis jobs waiting for a worker"
    );
    metrics::describe_gauge!("shapeseek_jobs_running", "analysis jobs running");
    metrics::describe_gauge!("shapeseek_index_shapes", "shapes in the index");
    metrics::describe_gauge!(
        "shapeseek_index_bytes",
        "index size on disk (sled estimate)"
    );
    metrics::describe_gauge!("shapeseek_calibration_epoch", "current calibration epoch");
    metrics::describe_counter!(
        "shapeseek_conversions_total",
        "stored originals written in another format (GET /v1/shapes/{id}/mesh?format=), counted once written"
    );
}

/// Records one ingest stage duration.
pub fn stage(stage: &'static str, ms: f64) {
    metrics::histogram!("shapeseek_ingest_stage_seconds", "stage" => stage).record(ms / 1e3);
}
