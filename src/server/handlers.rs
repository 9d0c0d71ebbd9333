//! HTTP handlers: translate requests to [`App`] calls and results to JSON.

use super::cluster::Queued;
use super::limits::is_multipart;
use super::problem::ApiError;
use super::state::{validate_tags, App, SearchOptions, Upload};
use crate::mesh::read::Format;
use axum::body::Bytes;
use axum::extract::{FromRequest, Multipart, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Deserialize;
use std::sync::atomic::Ordering;
use std::sync::Arc;

type AppState = State<Arc<App>>;

/// Query parameters of `POST /v1/shapes`. A parameter of another name is refused (400) with
/// the names accepted, as for every query below: `?tag=` here, or `?tags=` on the listing,
/// used to be ignored, and the request did something else than asked.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IngestParams {
    /// Format name or MIME type (overrides Content-Type as a hint; content still wins).
    pub format: Option<String>,
    /// Display name.
    pub name: Option<String>,
    /// Comma-separated tags.
    pub tags: Option<String>,
    /// `false`: with a work queue, answer 202 with the job once it is queued instead of waiting
    /// for the shape (without a queue the shape is stored before the answer either way).
    pub wait: Option<bool>,
}

/// Query parameters of `POST /v1/search` (unknown names refused).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SearchParams {
    /// Format name or MIME type.
    pub format: Option<String>,
    /// Number of hits.
    pub top_k: Option<usize>,
    /// Comma-separated tags every hit must have.
    pub tags: Option<String>,
}

/// Multipart `metadata` part of an ingest.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct Metadata {
    #[serde(default)]
    name: Option<String>,
    #[serde(default)]
    tags: Vec<String>,
}

fn split_tags(s: Option<&str>) -> Vec<String> {
    s.map(|s| {
        s.split(',')
            .map(|t| t.trim().to_string())
            .filter(|t| !t.is_empty())
            .collect()
    })
    .unwrap_or_default()
}

fn format_param(s: Option<&str>) -> Result<Option<Format>, ApiError> {
    match s {
        None | Some("") => Ok(None),
        Some(f) => f.parse::<Format>().map(Some).map_err(|_| {
            ApiError::invalid(format!(
                "format {f:?}: expected obj, gltf, glb, ply, off, stl or a mesh MIME type"
            ))
        }),
    }
}

fn content_type(headers: &HeaderMap) -> Option<String> {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|s| s.to_ascii_lowercase())
}

fn is_json(headers: &HeaderMap) -> bool {
    content_type(headers).is_some_and(|c| {
        let e = c.split(';').next().unwrap_or("").trim().to_string();
        e == "application/json" || e.ends_with("+json") && !e.starts_with("model/")
    })
}

fn check_name(name: &Option<String>) -> Result<(), ApiError> {
    if let Some(n) = name {
        if n.is_empty() || n.chars().count() > 256 || n.chars().any(|c| c.is_control()) {
            return Err(ApiError::invalid(
                "name: 1 to 256 characters, no control characters",
            ));
        }
    }
    Ok(())
}

async fn read_raw(
    app: &Arc<App>,
    req: Request,
    hint: Option<Format>,
) -> Result<(Bytes, Option<Format>), ApiError> {
    let hint = hint.or_else(|| content_type(req.headers()).and_then(|c| Format::from_mime(&c)));
    let body = Bytes::from_request(req, app).await.map_err(|e| {
        ApiError::new(
            e.status(),
            super::problem::code_for_status(e.status()),
            e.body_text(),
        )
    })?;
    if body.is_empty() {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "mesh.empty",
            "empty request body: send the mesh file",
        ));
    }
    Ok((body, hint))
}

/// Reads a multipart body: the `file` part and the named JSON part.
async fn read_multipart(
    app: &Arc<App>,
    req: Request,
    json_part: &str,
) -> Result<(Bytes, Option<Format>, Option<Bytes>), ApiError> {
    let mut mp = Multipart::from_request(req, app).await.map_err(|e| {
        ApiError::new(
            e.status(),
            super::problem::code_for_status(e.status()),
            e.body_text(),
        )
    })?;
    let mut file = None;
    let mut json = None;
    let mp_err = |e: axum::extract::multipart::MultipartError| {
        ApiError::new(
            e.status(),
            super::problem::code_for_status(e.status()),
            e.body_text(),
        )
    };
    while let Some(field) = mp.next_field().await.map_err(mp_err)? {
        let name = field.name().unwrap_or("").to_string();
        if name == "file" {
            let hint = field
                .content_type()
                .and_then(Format::from_mime)
                .or_else(|| {
                    field
                        .file_name()
                        .and_then(|f| f.rsplit_once('.'))
                        .and_then(|(_, ext)| Format::from_extension(ext))
                });
            let bytes = field.bytes().await.map_err(mp_err)?;
            file = Some((bytes, hint));
        } else if name == json_part {
            json = Some(field.bytes().await.map_err(mp_err)?);
        } else {
            return Err(ApiError::invalid(format!(
                "multipart: unexpected part {name:?} (expected \"file\" and \"{json_part}\")"
            )));
        }
    }
    let (bytes, hint) =
        file.ok_or_else(|| ApiError::invalid("multipart: missing the \"file\" part"))?;
    if bytes.is_empty() {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "mesh.empty",
            "the \"file\" part is empty",
        ));
    }
    Ok((bytes, hint, json))
}

/// `POST /v1/shapes`.
pub async fn ingest(
    State(app): AppState,
    Query(params): Query<IngestParams>,
    req: Request,
) -> Result<Response, ApiError> {
    let format = format_param(params.format.as_deref())?;
    let deadline = super::router::deadline_of(&req);
    let up = if is_multipart(req.headers()) {
        let (bytes, hint, meta) = read_multipart(&app, req, "metadata").await?;
        let meta: Metadata = match meta {
            Some(b) => serde_json::from_slice(&b)
                .map_err(|e| ApiError::invalid(format!("metadata: {e}")))?,
            None => Metadata::default(),
        };
        Upload {
            bytes,
            hint: format.or(hint),
            name: meta.name.or(params.name),
            tags: if meta.tags.is_empty() {
                split_tags(params.tags.as_deref())
            } else {
                meta.tags
            },
        }
    } else {
        let (bytes, hint) = read_raw(&app, req, format).await?;
        Upload {
            bytes,
            hint,
            name: params.name,
            tags: split_tags(params.tags.as_deref()),
        }
    };
    check_name(&up.name)?;
    validate_tags(&up.tags)?;
    let res = if app.cluster().is_some() {
        match app
            .queued_ingest(up, params.wait.unwrap_or(true), deadline)
            .await?
        {
            Queued::Stored(r) => *r,
            Queued::Accepted(job) => return Ok(job_response(StatusCode::ACCEPTED, job)),
        }
    } else {
        app.ingest_until(up, deadline).await?
    };
    let status = if res.created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    let location = format!("/v1/shapes/{}", res.id);
    let mut resp = (status, Json(res)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        resp.headers_mut().insert(header::LOCATION, v);
    }
    Ok(resp)
}

/// A job as JSON with its `Location` (`/v1/jobs/{id}`).
fn job_response(status: StatusCode, job: crate::queue::Job) -> Response {
    let location = format!("/v1/jobs/{}", job.id);
    let mut body = serde_json::to_value(&job).unwrap_or_default();
    if let serde_json::Value::Object(m) = &mut body {
        m.insert("link".into(), serde_json::Value::String(location.clone()));
    }
    let mut resp = (status, Json(body)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        resp.headers_mut().insert(header::LOCATION, v);
    }
    resp
}

/// `GET /v1/jobs/{id}`: an ingest job of the work queue (404 without a queue).
pub async fn get_job(State(app): AppState, Path(id): Path<String>) -> Result<Response, ApiError> {
    let not_found = || {
        ApiError::new(
            StatusCode::NOT_FOUND,
            "job.not_found",
            format!("no job with id {id:?}"),
        )
    };
    let Some(cl) = app.cluster() else {
        return Err(not_found());
    };
    match cl.jobs.get(&id).await? {
        Some(job) => Ok(job_response(StatusCode::OK, job)),
        None => Err(not_found()),
    }
}

/// Query parameters of `GET /v1/shapes` (unknown names refused).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListParams {
    /// Page size, 1..=1000 (default 50).
    pub limit: Option<usize>,
    /// `next_cursor` of the previous page.
    pub cursor: Option<String>,
    /// Only shapes with this tag (a valid tag: 1 to 64 characters, no control characters).
    pub tag: Option<String>,
}

/// `GET /v1/shapes`.
pub async fn list(State(app): AppState, Query(p): Query<ListParams>) -> Result<Response, ApiError> {
    let limit = p.limit.unwrap_or(50);
    if !(1..=1000).contains(&limit) {
        return Err(ApiError::invalid("limit must be in 1..=1000"));
    }
    if let Some(tag) = &p.tag {
        validate_tags(std::slice::from_ref(tag))?;
    }
    let page = app
        .store
        .list(p.cursor.as_deref(), p.tag.as_deref(), limit)
        .await
        .map_err(ApiError::from)?;
    let (items, more) = (page.records, page.more);
    let next = if more {
        items.last().map(|r| r.id.clone())
    } else {
        None
    };
    Ok(Json(serde_json::json!({ "items": items, "next_cursor": next })).into_response())
}

/// `GET /v1/shapes/{id}`.
pub async fn get_shape(State(app): AppState, Path(id): Path<String>) -> Result<Response, ApiError> {
    match app.store.get(&id).await.map_err(ApiError::from)? {
        Some(rec) => Ok(Json(rec).into_response()),
        None => Err(ApiError::not_found(&id)),
    }
}

/// `DELETE /v1/shapes/{id}`.
pub async fn delete_shape(
    State(app): AppState,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    if app.delete(id.clone()).await? {
        Ok(StatusCode::NO_CONTENT.into_response())
    } else {
        Err(ApiError::not_found(&id))
    }
}

/// Query parameters of `GET /v1/shapes/{id}/mesh` (unknown names refused).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshParams {
    /// A format name: the mesh as the server read it, written in that format, instead of the
    /// original bytes.
    pub format: Option<String>,
}

/// `GET /v1/shapes/{id}/mesh`: the original upload, or with `?format=` the mesh read from it
/// written in that format (a client then needs one reader whatever was uploaded; the web page
/// asks for binary PLY).
///
/// `HEAD` answers the headers a GET would send without reading the original or converting it:
/// the original's `Content-Length` is in its record; a conversion's length is known only once
/// it is written, so a `HEAD` with `?format=` sends none (RFC 9110 §9.3.2 allows leaving out
/// what only generating the content determines).
pub async fn get_mesh(
    State(app): AppState,
    Path(id): Path<String>,
    Query(params): Query<MeshParams>,
    req: Request,
) -> Result<Response, ApiError> {
    let to = match params.format.as_deref() {
        None | Some("") => None,
        Some(f) => Some(
            Format::ALL
                .into_iter()
                .find(|x| x.name().eq_ignore_ascii_case(f))
                .ok_or_else(|| {
                    ApiError::invalid(format!(
                        "format {f:?}: expected one of obj, gltf, glb, ply, off, stl"
                    ))
                })?,
        ),
    };
    let rec = app
        .store
        .get(&id)
        .await
        .map_err(ApiError::from)?
        .ok_or_else(|| ApiError::not_found(&id))?;
    // An id's stored original is never replaced and an id is never reused, so the upload's
    // SHA-256 in the record names the bytes for good; a conversion also depends on the readers
    // and writers, so its tag adds the format and the fingerprint of the sources this binary
    // was built from. A client that has the tag is answered 304 without the store being read
    // or anything converted.
    let etag = match to {
        None => format!("\"{}\"", rec.sha256),
        Some(to) => format!(
            "\"{}-{}-{}\"",
            rec.sha256,
            to.name(),
            env!("SHAPESEEK_SOURCE_FINGERPRINT")
        ),
    };
    let fresh = super::if_none_match(req.headers(), &etag);
    let ext: &str = match to {
        Some(to) => to.name(),
        None => &rec.format,
    };
    let mut resp = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else if req.method() == axum::http::Method::HEAD {
        let mut r = StatusCode::OK.into_response();
        match to {
            None => {
                r.headers_mut()
                    .insert(header::CONTENT_LENGTH, HeaderValue::from(rec.bytes));
            }
            // axum gives a HEAD answer the `Content-Length: 0` of its empty body, which GET
            // contradicts; the connection's service drops it for answers marked so.
            Some(_) => {
                r.extensions_mut().insert(super::conn::LengthUnknown);
            }
        }
        r
    } else {
        // Held under the download budget until the last byte has left (`limits::ResponseBudget`).
        let body = match to {
            None => {
                let room = app.downloads.reserve(rec.bytes as usize).await;
                let bytes = app
                    .store
                    .mesh(&id)
                    .await
                    .map_err(ApiError::from)?
                    .ok_or_else(|| ApiError::not_found(&id))?;
                room.body(bytes)
            }
            Some(to) => {
                let deadline = super::router::deadline_of(&req);
                app.convert_original(&rec, to, deadline).await?
            }
        };
        body.into_response()
    };
    // Always octet-stream (the record's `format`/`content_type` name the original's format): a
    // format type such as `model/gltf+json` would make clients parse the download as JSON.
    let h = resp.headers_mut();
    if !fresh {
        h.insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/octet-stream"),
        );
    }
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"{}.{ext}\"", rec.id)) {
        h.insert(header::CONTENT_DISPOSITION, v);
    }
    Ok(resp)
}

/// `GET /v1/shapes/{id}/signature`: the distributions as JSON.
pub async fn get_signature(
    State(app): AppState,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let bytes = app
        .store
        .signature(&id)
        .await
        .map_err(ApiError::from)?
        .ok_or_else(|| ApiError::not_found(&id))?;
    let sig = app
        .engine
        .decode_signature(&bytes)
        .map_err(ApiError::internal)?;
    Ok(Json(serde_json::json!({
        "id": id,
        "spec_key": app.engine.signature_spec_key(&sig),
        "signature": app.engine.signature_json(&sig),
    }))
    .into_response())
}

/// `POST /v1/search`: JSON (by id), multipart (`file` + `query` JSON) or a raw mesh body.
pub async fn search(
    State(app): AppState,
    Query(params): Query<SearchParams>,
    req: Request,
) -> Result<Response, ApiError> {
    let headers = req.headers().clone();
    let deadline = super::router::deadline_of(&req);
    let res = if is_json(&headers) {
        let Json(opts) = Json::<SearchOptions>::from_request(req, &app)
            .await
            .map_err(|e| {
                ApiError::new(
                    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
                        e.status()
                    } else {
                        StatusCode::BAD_REQUEST
                    },
                    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
                        "limit.bytes"
                    } else {
                        "request.invalid"
                    },
                    e.body_text(),
                )
            })?;
        if opts.id.is_none() {
            return Err(ApiError::invalid(
                "a JSON search needs \"id\"; to search by example upload the mesh (raw body or multipart)",
            ));
        }
        app.search(opts, None, deadline).await?
    } else {
        // Search by example: a multipart file (+ optional `query` JSON part) or a raw body.
        let (bytes, hint, opts) = if is_multipart(&headers) {
            let (bytes, hint, query) = read_multipart(&app, req, "query").await?;
            let opts: SearchOptions = match query {
                Some(b) => serde_json::from_slice(&b)
                    .map_err(|e| ApiError::invalid(format!("query: {e}")))?,
                None => SearchOptions::default(),
            };
            if opts.id.is_some() {
                return Err(ApiError::invalid(
                    "give either an uploaded file or an id, not both",
                ));
            }
            let hint = format_param(params.format.as_deref())?.or(hint);
            (bytes, hint, opts)
        } else {
            let format = format_param(params.format.as_deref())?;
            let (bytes, hint) = read_raw(&app, req, format).await?;
            let opts = SearchOptions {
                top_k: params.top_k,
                tags: split_tags(params.tags.as_deref()),
                ..Default::default()
            };
            (bytes, hint, opts)
        };
        // Every option is validated before the expensive analysis of the upload.
        app.resolve_options(&opts)?;
        let q = app
            .analyze_query(
                Upload {
                    bytes,
                    hint,
                    name: None,
                    tags: Vec::new(),
                },
                app.search_needs_payload(&opts),
                deadline,
            )
            .await?;
        app.search(opts, Some(q), deadline).await?
    };
    Ok(Json(res).into_response())
}

/// `GET /v1/index`: size, calibration, specs, queue.
pub async fn index_info(State(app): AppState) -> Result<Response, ApiError> {
    let (n, on, epoch, sampled) = {
        let s = app.scan.read().unwrap_or_else(|p| p.into_inner());
        (
            s.len(),
            s.calibrated_on(),
            s.calibration()
                .map(|c| app.engine.calibration_epoch(c))
                .unwrap_or(0),
            s.calibration().map_or(0, |c| c.shapes),
        )
    };
    let mut v = serde_json::json!({
        "shapes": n,
        "calibration_epoch": epoch,
        "calibrated_on": on,
        "calibration_shapes": sampled,
        // Stored shapes this node could not recompute for its spec (`src/server/load.rs`).
        "left_out": app.left_out.lock().unwrap_or_else(|p| p.into_inner()).len(),
        "schema_version": app.store.schema_version().await.map_err(ApiError::from)?,
        "engine": app.engine.name(),
        "spec_key": app.engine.spec_key(),
        "signature_spec": app.engine.spec_json(),
        "default_query": serde_json::to_value(app.engine.default_query()).map_err(ApiError::internal)?,
        "size_on_disk": app.store.size_on_disk().await.map_err(ApiError::from)?,
        "queue": queue_stats(&app),
        // What an upload may be: a client checks a file against these before sending it (a
        // body over `max_body_bytes` is cut off mid-send, which a client sees as a broken
        // connection, not as the 413 the server answers).
        "limits": {
            "max_body_bytes": app.cfg.max_body_bytes,
            "max_vertices": app.cfg.max_vertices,
            "max_faces": app.cfg.max_faces,
        },
    });
    if let Some(sh) = app.shard() {
        // A sharded node: `shapes` are its shard's, `calibrated_on` counts the whole corpus.
        v["shard"] = serde_json::json!({
            "index": sh.spec.index,
            "count": sh.spec.count,
            "corpus_shapes": sh.total(),
        });
    }
    Ok(Json(v).into_response())
}

/// The `queue` object of `GET /v1/index`: totals (as before the lanes existed) and per lane.
fn queue_stats(app: &App) -> serde_json::Value {
    let (cheap, heavy) = app.admission.stats();
    let lane = |l: &super::admission::LaneStats| {
        serde_json::json!({
            "queued": l.queued.load(Ordering::Relaxed),
            "running": l.running.load(Ordering::Relaxed),
            "queued_units": l.queued_units.load(Ordering::Relaxed),
            "running_units": l.running_units.load(Ordering::Relaxed),
            "refused": l.refused.load(Ordering::Relaxed),
        })
    };
    serde_json::json!({
        "queued": cheap.queued.load(Ordering::Relaxed) + heavy.queued.load(Ordering::Relaxed),
        "running": cheap.running.load(Ordering::Relaxed) + heavy.running.load(Ordering::Relaxed),
        "workers": app.cfg.effective_workers(),
        "capacity": app.cfg.queue_capacity,
        "heavy_threads": app.admission.heavy_threads(),
        "borrow_threads": app.admission.borrow_threads(),
        "borrowed": app.admission.borrowed.load(Ordering::Relaxed),
        "cancelled": app.admission.cancelled.load(Ordering::Relaxed),
        "gw_candidates_skipped": app.admission.skipped.load(Ordering::Relaxed),
        "cheap": lane(cheap),
        "heavy": lane(heavy),
    })
}

/// `GET /healthz`: the process answers.
pub async fn healthz() -> Response {
    Json(serde_json::json!({"status": "ok"})).into_response()
}

/// `GET /readyz`: loaded and not shutting down.
pub async fn readyz(State(app): AppState) -> Result<Response, ApiError> {
    if app.ready.load(Ordering::Acquire) {
        // The scan's count, not the store's: sled counts a tree by walking it, and a probe
        // every few seconds walked every stored shape. The store's only while the scan is
        // locked for writing (a probe does not wait behind an install).
        let counted = app.scan.try_read().ok().map(|s| app.corpus_size(&s));
        let shapes = match counted {
            Some(n) => n as u64,
            None => app.store.count().await.map_err(ApiError::from)?,
        };
        Ok(Json(serde_json::json!({"status": "ready", "shapes": shapes})).into_response())
    } else {
        Err(ApiError::not_ready(
            "not ready (starting or shutting down)",
            app.cfg.retry_after_secs,
        ))
    }
}

/// `GET /metrics`: Prometheus text format.
pub async fn metrics(State(app): AppState) -> Response {
    let (cheap, heavy) = app.admission.stats();
    let q = cheap.queued.load(Ordering::Relaxed) + heavy.queued.load(Ordering::Relaxed);
    let r = cheap.running.load(Ordering::Relaxed) + heavy.running.load(Ordering::Relaxed);
    ::metrics::gauge!("shapeseek_queue_depth").set(q as f64);
    ::metrics::gauge!("shapeseek_jobs_running").set(r as f64);
    app.update_gauges();
    let body = app.metrics.as_ref().map(|h| h.render()).unwrap_or_default();
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        body,
    )
        .into_response()
}

/// The OpenAPI document (`api/openapi.yaml`, compiled in).
pub const OPENAPI_YAML: &str = include_str!("../../api/openapi.yaml");

/// `GET /openapi.yaml`: `application/yaml`, or `text/plain` when the `Accept` header names
/// `text/plain` (or `text/*`) but not `application/yaml` (both are declared in the document).
pub async fn openapi(headers: HeaderMap) -> Response {
    let accept = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let names = |t: &str| {
        accept
            .split(',')
            .any(|r| r.split(';').next().unwrap_or("").trim() == t)
    };
    let ct = if !names("application/yaml") && (names("text/plain") || names("text/*")) {
        "text/plain; charset=utf-8"
    } else {
        "application/yaml"
    };
    ([(header::CONTENT_TYPE, ct)], OPENAPI_YAML).into_response()
}
