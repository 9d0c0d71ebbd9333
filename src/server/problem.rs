//! Errors as `application/problem+json` (RFC 9457) with a stable machine-readable `code`.

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

    /// 500 `server.internal` (details are logged, not sent).
    pub fn internal(detail: impl std::fmt::Display) -> Self {
        tracing::error!(error = %detail, "internal error");
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "server.internal",
            "internal error (see the server log)",
        )
    }

    /// The HTTP status of a library error code.
    pub fn status_for_code(code: &str) -> StatusCode {
        match code {
            "limit.bytes" | "limit.vertices" | "limit.faces" => StatusCode::PAYLOAD_TOO_LARGE,
            "mesh.format" => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "mesh.parse"
            | "mesh.external_reference"
            | "mesh.empty"
            | "mesh.non_finite"
            | "spectrum.numerical" => StatusCode::UNPROCESSABLE_ENTITY,
            "request.invalid" => StatusCode::BAD_REQUEST,
            _ => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    fn title(&self) -> &'static str {
        self.status.canonical_reason().unwrap_or("Error")
    }
}

impl From<crate::Error> for ApiError {
    fn from(e: crate::Error) -> Self {
        let code = e.code();
        let status = Self::status_for_code(code);
        if status == StatusCode::INTERNAL_SERVER_ERROR {
            return Self::internal(e);
        }
        Self::new(status, code, e.to_string())
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
