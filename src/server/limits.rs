//! Admission of request bodies, and the bound on the bytes stored per shape (the CPU work of a
//! request is admitted by [`super::admission`]).

use super::problem::ApiError;
use crate::mesh::read::Format;
use std::sync::Arc;
use tokio::sync::Semaphore;

/// The bytes kept as a shape's original: the upload when its size is within
/// `max(stored_bytes_floor, stored_bytes_per_element × (vertices + faces))`, else (policy
/// `reencode`) the mesh as read, written again in the same format, with the upload's size
/// returned alongside, or (policy `refuse`) 413 `limit.stored_bytes`. Padding, comments,
/// unused buffers and textures are not kept.
pub fn stored_original(
    cfg: &super::config::ServerConfig,
    upload: &axum::body::Bytes,
    mesh: &crate::mesh::Mesh,
    format: Format,
) -> Result<(axum::body::Bytes, Option<u64>), ApiError> {
    let elements = mesh.vertices.len() + mesh.faces.len();
    let cap = cfg
        .stored_bytes_floor
        .max(cfg.stored_bytes_per_element.saturating_mul(elements));
    if upload.len() <= cap {
        return Ok((upload.clone(), None));
    }
    metrics::counter!("shapeseek_originals_over_cap_total").increment(1);
    if cfg.oversized_original == "refuse" {
        return Err(ApiError::new(
            axum::http::StatusCode::PAYLOAD_TOO_LARGE,
            "limit.stored_bytes",
            format!(
                "the upload has {} bytes for {} vertices and {} faces; at most {cap} bytes \
                 are stored for this geometry (stored_bytes_per_element = {}, \
                 stored_bytes_floor = {})",
                upload.len(),
                mesh.vertices.len(),
                mesh.faces.len(),
                cfg.stored_bytes_per_element,
                cfg.stored_bytes_floor
            ),
        ));
    }
    let mut out = Vec::new();
    crate::mesh::write::write_mesh(mesh, format, &mut out)?;
    Ok((out.into(), Some(upload.len() as u64)))
}

/// Admission of request bodies: a size check on the announced `Content-Length` before any
/// byte is read, a budget of body bytes held in memory over all requests, and a deadline for
/// reading a body.
///
/// The body is read here, whole, under the budget and the deadline, and handed to the handler
/// as a complete buffer; the budget is released when the response is ready. So the memory held
/// by bodies is bounded by `max_inflight_body_bytes` whatever the number of connections, and a
/// client trickling its body holds a connection for at most `body_read_timeout`. An announced
/// size over the limit is refused with 413 before hyper sends `100 Continue` (it sends it only
/// when the body is first read).
///
/// A body takes from the budget what has arrived of it (in steps of [`RESERVE_STEP`]), not
/// what it announces or could grow to: when a chunked body reserved the largest body up front
/// and an announced one its `Content-Length`, four clients that each sent a few bytes of a
/// chunked upload and then one every few seconds held the whole budget, and every POST (a
/// 40-byte search too) was refused with 503 for as long as they kept it up. A body that cannot
/// take the next step is answered 503 `server.busy` then (the budget is full of bytes that
/// did arrive).
///
/// A `multipart/form-data` body takes its size from the budget a second time once it has
/// arrived (as far as the budget's total allows): its parts are parsed by copying (multer
/// buffers the stream, and a part's bytes are collected again), so it is held about twice
/// while the handler reads it, where a raw body is held once.
pub struct BodyGate {
    /// Largest body, bytes.
    pub max_body_bytes: usize,
    /// Time to read a whole body.
    pub read_timeout: std::time::Duration,
    /// `Retry-After` seconds of a 503.
    pub retry_after: u64,
    /// Budget in KiB (a semaphore takes at most `u32::MAX` permits at once).
    budget_kib: Arc<Semaphore>,
    /// The budget's whole size in KiB.
    total_kib: u32,
}

impl BodyGate {
    /// A gate admitting bodies up to `max_body_bytes`, `max_inflight_bytes` in all.
    pub fn new(
        max_body_bytes: usize,
        max_inflight_bytes: usize,
        read_timeout: std::time::Duration,
        retry_after: u64,
    ) -> Self {
        Self {
            max_body_bytes,
            read_timeout,
            retry_after,
            budget_kib: Arc::new(Semaphore::new(kib(max_inflight_bytes) as usize)),
            total_kib: kib(max_inflight_bytes),
        }
    }

    /// KiB of the budget free now.
    pub fn available_kib(&self) -> usize {
        self.budget_kib.available_permits()
    }
}

/// The bytes of downloads held in memory at once (stored originals, format conversions), over
/// all connections: a download reserves its size before its original is read from the store
/// (the size is in the record) or once its conversion is written, waiting for room (the
/// request's deadline ends the wait: 503 `request.timeout`). The reservation travels with the
/// response's body ([`Reserved::body`]), so it ends when hyper has taken the last byte (it then
/// holds one frame's worth at most) or the connection closed, not when the handler returns.
/// (Before, every download read its whole original with no bound: forty clients that asked for
/// a 13 MB original and read nothing held about 1 GiB until they left.) A download larger than
/// the whole budget takes all of it.
pub struct ResponseBudget {
    /// Budget in KiB.
    kib: Arc<Semaphore>,
    total_kib: u32,
}

/// Room reserved in a [`ResponseBudget`].
pub struct Reserved(tokio::sync::OwnedSemaphorePermit);

/// A download's bytes with their reservation: freed together once the last of them has been
/// taken by hyper (or the response dropped with its connection).
struct Held {
    data: Vec<u8>,
    _room: tokio::sync::OwnedSemaphorePermit,
}

impl AsRef<[u8]> for Held {
    fn as_ref(&self) -> &[u8] {
        &self.data
    }
}

/// The body of a download: its bytes handed out in [`DOWNLOAD_FRAME`] pieces, each a view of
/// the held buffer. hyper copies a frame into its own write buffer (the connection's IO is not
/// vectored) and asks for the next only once that has room; given the whole buffer as one
/// frame, it copied all of it and dropped ours at once, so a reservation in the frame was
/// given back while hyper still held every byte. In pieces, the buffer and its reservation
/// stay with the body until its last piece, and hyper holds one piece at most. Its exact size
/// gives the answer its `Content-Length`.
struct Download {
    rest: axum::body::Bytes,
}

/// Bytes per frame of a [`Download`].
const DOWNLOAD_FRAME: usize = 64 * 1024;

impl hyper::body::Body for Download {
    type Data = axum::body::Bytes;
    type Error = std::convert::Infallible;

    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        _cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<hyper::body::Frame<Self::Data>, Self::Error>>> {
        if self.rest.is_empty() {
            return std::task::Poll::Ready(None);
        }
        let n = self.rest.len().min(DOWNLOAD_FRAME);
        let piece = self.rest.split_to(n);
        std::task::Poll::Ready(Some(Ok(hyper::body::Frame::data(piece))))
    }

    fn is_end_stream(&self) -> bool {
        self.rest.is_empty()
    }

    fn size_hint(&self) -> hyper::body::SizeHint {
        hyper::body::SizeHint::with_exact(self.rest.len() as u64)
    }
}

impl ResponseBudget {
    /// A budget of `bytes`.
    pub fn new(bytes: usize) -> Self {
        Self {
            kib: Arc::new(Semaphore::new(kib(bytes) as usize)),
            total_kib: kib(bytes),
        }
    }

    /// Waits for room for `bytes` (at most the whole budget).
    pub async fn reserve(&self, bytes: usize) -> Reserved {
        let want = kib(bytes).min(self.total_kib);
        if self.kib.available_permits() < want as usize {
            metrics::counter!("shapeseek_downloads_waited_total").increment(1);
        }
        let permit = self
            .kib
            .clone()
            .acquire_many_owned(want)
            .await
            .expect("the budget's semaphore is never closed");
        Reserved(permit)
    }
}

impl Reserved {
    /// `data` as a response body holding this reservation until its last byte is taken.
    pub fn body(self, data: Vec<u8>) -> axum::body::Body {
        axum::body::Body::new(Download {
            rest: axum::body::Bytes::from_owner(Held {
                data,
                _room: self.0,
            }),
        })
    }
}

/// The steps in which a body takes from the budget as it arrives.
pub const RESERVE_STEP: usize = 64 * 1024;

fn kib(bytes: usize) -> u32 {
    bytes.div_ceil(1024).min(u32::MAX as usize) as u32
}

/// The body layer (see [`BodyGate`]).
pub async fn admit_body(
    axum::extract::State(gate): axum::extract::State<Arc<BodyGate>>,
    req: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    use axum::http::{header, StatusCode};
    use axum::response::IntoResponse;
    let close = |e: ApiError| {
        let mut r = e.into_response();
        r.headers_mut().insert(
            header::CONNECTION,
            axum::http::HeaderValue::from_static("close"),
        );
        r
    };
    let declared = match req.headers().get(header::CONTENT_LENGTH) {
        None => None,
        Some(v) => match v.to_str().ok().and_then(|s| s.trim().parse::<u64>().ok()) {
            Some(n) => Some(n),
            None => return close(ApiError::invalid("Content-Length is not a number")),
        },
    };
    let chunked = req.headers().contains_key(header::TRANSFER_ENCODING);
    if declared.is_none() && !chunked {
        return next.run(req).await;
    }
    if let Some(n) = declared {
        if n > gate.max_body_bytes as u64 {
            return close(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "limit.bytes",
                format!(
                    "the request body announces {n} bytes; the limit is {} bytes",
                    gate.max_body_bytes
                ),
            ));
        }
        if n == 0 {
            return next.run(req).await;
        }
    }
    let busy = || {
        metrics::counter!("shapeseek_bodies_refused_total").increment(1);
        let mut e = ApiError::busy(gate.retry_after);
        e.detail = "too many request bodies in flight; retry later".into();
        e
    };
    let first = declared
        .map_or(gate.max_body_bytes, |n| n as usize)
        .min(RESERVE_STEP);
    let Ok(mut permit) = gate.budget_kib.clone().try_acquire_many_owned(kib(first)) else {
        return busy().into_response();
    };
    let (parts, body) = req.into_parts();
    let read = tokio::time::timeout(
        gate.read_timeout,
        read_whole(
            body,
            gate.max_body_bytes,
            declared.map(|n| n as usize),
            &gate.budget_kib,
            &mut permit,
        ),
    )
    .await;
    let bytes = match read {
        Ok(Ok(b)) => b,
        Ok(Err(BodyReadError::Busy)) => return close(busy()),
        Ok(Err(BodyReadError::TooBig)) => {
            return close(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "limit.bytes",
                format!("the request body exceeds {} bytes", gate.max_body_bytes),
            ))
        }
        Ok(Err(BodyReadError::Read(e))) => {
            return close(ApiError::invalid(format!(
                "the request body could not be read: {e}"
            )))
        }
        Err(_) => {
            return close(ApiError::new(
                StatusCode::REQUEST_TIMEOUT,
                "request.body_timeout",
                format!(
                    "the request body was not received within {:.0} s",
                    gate.read_timeout.as_secs_f64()
                ),
            ))
        }
    };
    if is_multipart(&parts.headers) {
        // Held about twice while its parts are parsed (see [`BodyGate`]); never more than the
        // whole budget, or a body near its size could not be admitted at all.
        let held = permit.num_permits() as u32;
        let extra = kib(bytes.len()).min(gate.total_kib.saturating_sub(held));
        match gate.budget_kib.clone().try_acquire_many_owned(extra) {
            Ok(more) => permit.merge(more),
            Err(_) => return close(busy()),
        }
    }
    let resp = next
        .run(axum::extract::Request::from_parts(
            parts,
            axum::body::Body::from(bytes),
        ))
        .await;
    drop(permit);
    resp
}

/// Whether the body is `multipart/form-data` (the handlers then read its parts).
pub(super) fn is_multipart(headers: &axum::http::HeaderMap) -> bool {
    headers
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|c| {
            c.trim_start()
                .to_ascii_lowercase()
                .starts_with("multipart/form-data")
        })
}

/// Why [`read_whole`] stopped.
enum BodyReadError {
    /// More than the limit arrived.
    TooBig,
    /// The connection failed or the body was malformed (e.g. shorter than announced).
    Read(axum::Error),
    /// The budget had no room for the bytes that arrived.
    Busy,
}

/// Reads a whole body into one buffer, sized up front to its announced length, so that the
/// memory a body holds is what the budget reserved for it: collecting the frames first and
/// concatenating them afterwards (`axum::body::to_bytes`) holds each body twice at the moment
/// it completes — with four 60 MiB uploads finishing together, 240 MiB over the budget
/// (`scripts/memory-test.sh`, glTF peaks of 476–493 MiB against the 448 MiB bound). Each frame
/// is copied in and dropped as it arrives. (The buffer's pages become resident as they are
/// written.) `permit` grows from `budget` by [`RESERVE_STEP`]s to cover what has arrived.
async fn read_whole(
    mut body: axum::body::Body,
    limit: usize,
    declared: Option<usize>,
    budget: &Arc<Semaphore>,
    permit: &mut tokio::sync::OwnedSemaphorePermit,
) -> Result<axum::body::Bytes, BodyReadError> {
    use http_body_util::BodyExt;
    let mut buf: Vec<u8> = Vec::with_capacity(declared.unwrap_or(0).min(limit));
    while let Some(frame) = body.frame().await {
        let frame = frame.map_err(BodyReadError::Read)?;
        if let Ok(data) = frame.into_data() {
            let len = buf.len() + data.len();
            if len > limit {
                return Err(BodyReadError::TooBig);
            }
            let held = permit.num_permits() as u32;
            if kib(len) > held {
                let want = kib(len.next_multiple_of(RESERVE_STEP).min(limit)).max(kib(len));
                let more = budget
                    .clone()
                    .try_acquire_many_owned(want - held)
                    .map_err(|_| BodyReadError::Busy)?;
                permit.merge(more);
            }
            buf.extend_from_slice(&data);
        }
    }
    Ok(buf.into())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(chunks: usize, size: usize) -> axum::body::Body {
        let frames = (0..chunks)
            .map(move |_| Ok::<_, std::io::Error>(axum::body::Bytes::from(vec![b'#'; size])));
        axum::body::Body::from_stream(futures_util::stream::iter(frames))
    }

    /// A body holds from the budget what has arrived of it, rounded up to a step, and is
    /// refused once the budget has no room for the next step; the permit is back when dropped.
    #[tokio::test]
    async fn a_body_takes_from_the_budget_as_it_arrives() {
        let budget = Arc::new(Semaphore::new(kib(4 * RESERVE_STEP) as usize));
        let mut permit = budget.clone().try_acquire_many_owned(1).unwrap();
        let got = read_whole(body(10, 10_000), 1 << 20, None, &budget, &mut permit)
            .await
            .ok()
            .unwrap();
        assert_eq!(got.len(), 100_000);
        // 100 000 bytes: two steps of 64 KiB held, two free.
        assert_eq!(permit.num_permits(), kib(2 * RESERVE_STEP) as usize);
        assert_eq!(budget.available_permits(), kib(2 * RESERVE_STEP) as usize);
        // Another body of 3 steps' bytes does not fit in what is left.
        let mut other = budget.clone().try_acquire_many_owned(1).unwrap();
        let r = read_whole(body(20, 10_000), 1 << 20, None, &budget, &mut other).await;
        assert!(matches!(r, Err(BodyReadError::Busy)));
        drop(other);
        drop(permit);
        assert_eq!(budget.available_permits(), kib(4 * RESERVE_STEP) as usize);
    }

    /// What the budget has free while a handler runs: a raw body holds its size, a multipart
    /// one twice its size (its parsing copies it), at most the whole budget.
    #[tokio::test]
    async fn a_multipart_body_counts_twice_while_it_is_handled() {
        use tower::ServiceExt;
        let free_during = |gate: Arc<BodyGate>, ctype: &'static str, len: usize| async move {
            let seen = gate.clone();
            let app = axum::Router::new()
                .route(
                    "/",
                    axum::routing::post(move || async move { seen.available_kib().to_string() }),
                )
                .layer(axum::middleware::from_fn_with_state(gate, admit_body));
            let req = axum::http::Request::post("/")
                .header("content-type", ctype)
                .header("content-length", len)
                .body(axum::body::Body::from(vec![b'#'; len]))
                .unwrap();
            let resp = app.oneshot(req).await.unwrap();
            let status = resp.status().as_u16();
            let body = axum::body::to_bytes(resp.into_body(), 1 << 20)
                .await
                .unwrap();
            (status, String::from_utf8_lossy(&body).into_owned())
        };
        let gate = || {
            Arc::new(BodyGate::new(
                512 << 10,
                1 << 20,
                std::time::Duration::from_secs(5),
                1,
            ))
        };
        let body = 2 * RESERVE_STEP; // 128 KiB
        assert_eq!(
            free_during(gate(), "model/obj", body).await,
            (200, "896".into())
        );
        assert_eq!(
            free_during(gate(), "multipart/form-data; boundary=x", body).await,
            (200, "768".into())
        );
        // A body of 512 KiB in a budget of 640 KiB: the second count stops at the total.
        let tight = Arc::new(BodyGate::new(
            512 << 10,
            640 << 10,
            std::time::Duration::from_secs(5),
            1,
        ));
        assert_eq!(
            free_during(tight, "Multipart/Form-Data; boundary=x", 512 << 10).await,
            (200, "0".into())
        );
    }
}
