//! Errors as `application/problem+json` (RFC 9457) with a stable machine-readable `code`.
//!
//! Library errors ([`crate::Error`]) keep their own code ([`crate::Error::code`]) and get their
//! status from [`ApiError::status_of`]: `limit.*` 413, `mesh.format` 415, `mesh.parse`,
//! `mesh.external_reference`, `mesh.empty`, `mesh.non_finite`, `spectrum.numerical`,
//! `spectrum.too_few_eigenpairs` 422, `request.invalid` 400. I/O, storage and corruption
//! failures (`io`, `storage`, `storage.corrupt`) are the server's fault: 500 `server.internal`,
//! with the library code and message in the log only. The server's own codes are
//! `shape.not_found` (404), `server.busy` (503 with `Retry-After`), `request.timeout` (503 with
//! `Retry-After`), `limit.stored_bytes` (413), `server.internal` (500),
//! those its handlers raise (`shape.no_payload`, `server.not_ready`, ...) and, for statuses the HTTP layer produced without a body ([`code_for_status`]), `route.not_found`,
//! `request.method_not_allowed`, `limit.bytes`, `request.unsupported_media_type`,
//! `request.timeout`, `server.unavailable`, `server.internal` and `request.invalid`.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

/// The media type of every error body.
pub const PROBLEM_JSON: &str = "application/problem+json";

/// An HTTP error: status, stable code, human detail.
#[derive(Debug, Clone)]
pub struct ApiError {
    /// HTTP status.
    pub status: StatusCode,
    /// Stable code (`mesh.parse`, `shape.not_found`, ...).
    pub code: String,
    /// What went wrong, for humans.
    pub detail: String,
    /// Seconds for a `Retry-After` header.
    pub retry_after: Option<u64>,
}

#[derive(Serialize)]
struct ProblemBody<'a> {
    #[serde(rename = "type")]
    ty: String,
    title: &'a str,
    status: u16,
    detail: &'a str,
    code: &'a str,
}

impl ApiError {
    /// A new error.
    pub fn new(status: StatusCode, code: impl Into<String>, detail: impl Into<String>) -> Self {
        Self {
            status,
            code: code.into(),
            detail: detail.into(),
            retry_after: None,
        }
    }

    /// The problem+json document of this error.
    pub fn body_bytes(&self) -> Vec<u8> {
        let body = ProblemBody {
            ty: format!("urn:shapeseek:problem:{}", self.code),
            title: self.title(),
            status: self.status.as_u16(),
            detail: &self.detail,
            code: &self.code,
        };
        serde_json::to_vec(&body).unwrap_or_else(|_| b"{}".to_vec())
    }

    /// 400 `request.invalid`.
    pub fn invalid(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, "request.invalid", detail)
    }

    /// 404 `shape.not_found`.
    pub fn not_found(id: &str) -> Self {
        Self::new(
            StatusCode::NOT_FOUND,
            "shape.not_found",
            format!("no shape with id {id:?}"),
        )
    }

    /// 503 `server.busy` with `Retry-After`.
    pub fn busy(retry_after: u64) -> Self {
        Self {
            retry_after: Some(retry_after),
            ..Self::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "server.busy",
                "the analysis queue is full; retry later",
            )
        }
    }

    /// 503 `server.not_ready` with `Retry-After` (loading its index, or shutting down).
    pub fn not_ready(detail: &str, retry_after: u64) -> Self {
        Self {
            retry_after: Some(retry_after),
            ..Self::new(StatusCode::SERVICE_UNAVAILABLE, "server.not_ready", detail)
        }
    }

    /// 500 `server.internal` (details are logged, not sent).
    pub fn internal(detail: impl std::fmt::Display) -> Self {
        tracing::error!(error = %detail, "internal error");
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "server.internal",
            "internal error (see the server log)",
        )
    }

    /// The HTTP status and the public code of a library error; `None` for a server-side fault
    /// (answered as 500 `server.internal`, details logged, not sent).
    ///
    /// One exhaustive `match` without a catch-all: a new [`crate::Error`] variant does not
    /// compile until it is mapped here.
    pub fn status_of(e: &crate::Error) -> Option<(StatusCode, &'static str)> {
        use crate::error::LimitKind;
        use crate::Error as E;
        let status = match e {
            E::Limit {
                kind: LimitKind::Bytes | LimitKind::Vertices | LimitKind::Faces,
                ..
            }
            | E::PolygonTooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            E::UnknownFormat(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            E::Parse { .. }
            | E::ExternalReference(_)
            | E::EmptyMesh(_)
            | E::NonFinite { .. }
            | E::Numerical(_)
            | E::TooFewEigenpairs { .. }
            | E::Inconsistent { .. }
            | E::Degenerate { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            E::InvalidArgument(_) => StatusCode::BAD_REQUEST,
            E::Queue(_) | E::StorageUnavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            // Only a request's cancellation token interrupts: its answer is the timeout's.
            E::Interrupted(_) => return Some((StatusCode::SERVICE_UNAVAILABLE, "request.timeout")),
            E::Io(_) | E::Storage(_) | E::Corrupt { .. } => return None,
        };
        Some((status, e.code()))
    }

    fn title(&self) -> &'static str {
        self.status.canonical_reason().unwrap_or("Error")
    }
}

impl From<crate::Error> for ApiError {
    fn from(e: crate::Error) -> Self {
        if let crate::Error::StorageUnavailable(why) = &e {
            // The database's own words (its host, its message) go to the log only.
            tracing::warn!(error = %why, "storage unavailable");
            return Self::new(
                StatusCode::SERVICE_UNAVAILABLE,
                e.code(),
                "the index's database cannot be reached or put the request off; retry later",
            );
        }
        match Self::status_of(&e) {
            Some((status, code)) => Self::new(status, code, e.to_string()),
            None => Self::internal(format_args!("[{}] {e}", e.code())),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let bytes = self.body_bytes();
        let mut resp = (self.status, bytes).into_response();
        resp.headers_mut()
            .insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        if let Some(s) = self.retry_after {
            if let Ok(v) = HeaderValue::from_str(&s.to_string()) {
                resp.headers_mut().insert(header::RETRY_AFTER, v);
            }
        }
        resp
    }
}

/// A code for a status that reached the client without a problem body (extractor rejections,
/// unknown routes, methods, layers): the catch-all middleware uses it.
pub fn code_for_status(status: StatusCode) -> &'static str {
    match status {
        StatusCode::NOT_FOUND => "route.not_found",
        StatusCode::METHOD_NOT_ALLOWED => "request.method_not_allowed",
        StatusCode::PAYLOAD_TOO_LARGE => "limit.bytes",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "request.unsupported_media_type",
        StatusCode::REQUEST_TIMEOUT => "request.timeout",
        StatusCode::SERVICE_UNAVAILABLE => "server.unavailable",
        s if s.is_server_error() => "server.internal",
        _ => "request.invalid",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::LimitKind;
    use crate::Error;

    /// Every problem code the server's sources spell out is in the API description's list of
    /// stable codes (eleven were missing from it until this test; the client's own
    /// `server.unreachable` never comes from a server).
    #[test]
    fn every_code_the_sources_name_is_listed_in_the_api_description() {
        let api = include_str!("../../api/openapi.yaml");
        let listed = &api[..api.find("servers:").expect("the description's end")];
        let prefixes = [
            "mesh", "spectrum", "limit", "shape", "request", "route", "server", "job", "queue",
            "search",
        ];
        let mut missing = std::collections::BTreeSet::new();
        let mut dirs = vec![std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("src")];
        let mut seen = 0;
        while let Some(d) = dirs.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    if !p.ends_with("cli") {
                        dirs.push(p);
                    }
                    continue;
                }
                let text = std::fs::read_to_string(&p).unwrap();
                for lit in text.split('"').skip(1).step_by(2) {
                    let Some((pre, rest)) = lit.split_once('.') else {
                        continue;
                    };
                    let word = |c: char| c.is_ascii_lowercase() || c == '_';
                    if prefixes.contains(&pre) && !rest.is_empty() && rest.chars().all(word) {
                        seen += 1;
                        if !listed.contains(&format!("`{lit}`")) {
                            missing.insert(lit.to_string());
                        }
                    }
                }
            }
        }
        assert!(
            seen > 30,
            "only {seen} codes found: is the scan reading the sources?"
        );
        assert!(missing.is_empty(), "not in api/openapi.yaml: {missing:?}");
    }

    /// The public status and code of every library error kind (the codes are a contract).
    #[test]
    fn every_error_kind_has_its_status_and_code() {
        let limit = |kind| Error::Limit {
            kind,
            limit: 1,
            actual: 2,
        };
        let cases: Vec<(Error, u16, &str)> = vec![
            (Error::parse("OBJ", None, "x"), 422, "mesh.parse"),
            (Error::UnknownFormat("x".into()), 415, "mesh.format"),
            (
                Error::ExternalReference("x".into()),
                422,
                "mesh.external_reference",
            ),
            (limit(LimitKind::Bytes), 413, "limit.bytes"),
            (limit(LimitKind::Vertices), 413, "limit.vertices"),
            (limit(LimitKind::Faces), 413, "limit.faces"),
            (Error::EmptyMesh("x".into()), 422, "mesh.empty"),
            (Error::NonFinite { vertex: 0 }, 422, "mesh.non_finite"),
            (Error::Numerical("x".into()), 422, "spectrum.numerical"),
            (
                Error::TooFewEigenpairs {
                    asked: 100,
                    found: 3,
                },
                422,
                "spectrum.too_few_eigenpairs",
            ),
            (
                Error::PolygonTooLarge {
                    format: "OBJ",
                    location: None,
                    corners: 300,
                    limit: 256,
                },
                413,
                "limit.polygon_vertices",
            ),
            (
                Error::Inconsistent {
                    format: "STL",
                    location: None,
                    message: "x".into(),
                },
                422,
                "mesh.inconsistent",
            ),
            (
                Error::Degenerate {
                    kind: crate::error::DegenerateKind::TooFewFaces,
                    message: "x".into(),
                },
                422,
                "mesh.too_few_faces",
            ),
            (
                Error::Degenerate {
                    kind: crate::error::DegenerateKind::TooFewVertices,
                    message: "x".into(),
                },
                422,
                "mesh.too_few_vertices",
            ),
            (
                Error::Degenerate {
                    kind: crate::error::DegenerateKind::AreaKept,
                    message: "x".into(),
                },
                422,
                "mesh.area_kept",
            ),
            (Error::InvalidArgument("x".into()), 400, "request.invalid"),
            (
                Error::Io(std::io::Error::other("x")),
                500,
                "server.internal",
            ),
            (Error::Storage("x".into()), 500, "server.internal"),
            (
                Error::StorageUnavailable("x".into()),
                503,
                "storage.unavailable",
            ),
            (
                Error::corrupt("signature", Some("0001"), "x"),
                500,
                "server.internal",
            ),
        ];
        for (e, status, code) in cases {
            let lib = e.code();
            let a = ApiError::from(e);
            assert_eq!(
                (a.status.as_u16(), a.code.as_str()),
                (status, code),
                "{lib}"
            );
        }
    }
}
