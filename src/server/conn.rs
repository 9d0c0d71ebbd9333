//! Connection hygiene: the accept loop of `shapeseek serve`.
//!
//! `axum::serve` accepts every connection and keeps it as long as the client wants: no timer is
//! installed, so hyper's header-read timeout never fires, and a client can hold a socket open by
//! sending nothing, half a request head or a trickle of body bytes. This loop serves HTTP/1.1
//! connections with hyper directly and adds:
//!
//! * a cap on concurrent connections ([`ConnLimits::max_connections`]); a connection over the
//!   cap is answered at once with `503 server.busy` (problem+json, `Retry-After`) and closed, so
//!   the client learns to back off instead of waiting in the kernel's backlog;
//! * a header-read timeout ([`ConnLimits::header_read_timeout`]) driven by a tokio timer: it
//!   covers a connection that sends nothing, an unfinished request head, and an idle keep-alive
//!   connection waiting for its next request (hyper restarts the timer for every request head);
//! * a send-stall timeout ([`ConnLimits::send_stall_timeout`]): a response whose client reads
//!   nothing of it (the socket's send buffer stays full) closes the connection once writes have
//!   made no progress for that long, which frees the response (hyper has no write timeout; a
//!   client could otherwise hold a large download in the server's memory for as long as TCP
//!   kept the connection);
//! * problem+json for the errors hyper answers by itself before any handler runs (400 for a
//!   head it cannot parse — control bytes in a header, a bad method —, 414 for a URI it cannot
//!   represent, 431 for too many or too large headers): hyper writes a bare status line with an
//!   empty body; [`ProblemIo`] recognises that automatic response on the way out and sends an
//!   `application/problem+json` document with a stable code instead. Every response of the
//!   router itself already is problem+json when it is an error, so a 4xx/5xx head without a
//!   `content-type` can only come from hyper's parser.
//!
//! Bodies (size announced by `Content-Length`, a budget of in-flight body bytes, a read
//! deadline) are admitted by the router's body layer (`super::limits`), where the request is
//! known.

use super::problem::ApiError;
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tower::ServiceExt;

/// Limits of the accept loop.
#[derive(Debug, Clone)]
pub struct ConnLimits {
    /// Connections served at once; more are answered 503 and closed.
    pub max_connections: usize,
    /// Time a client has to send a complete request head (also the idle time of a keep-alive
    /// connection between requests).
    pub header_read_timeout: Duration,
    /// Time a response may wait for a client that reads none of it; past it the connection
    /// is closed.
    pub send_stall_timeout: Duration,
    /// `Retry-After` seconds sent with a refused connection.
    pub retry_after_secs: u64,
}

/// Serves `router` on `listener` until `shutdown` resolves, then stops accepting and waits for
/// the open connections to finish their in-flight requests (the caller bounds that wait).
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: ConnLimits,
    shutdown: impl Future<Output = ()> + Send,
) -> io::Result<()> {
    let slots = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let graceful = GracefulShutdown::new();
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(limits.header_read_timeout)
        .keep_alive(true);
    tokio::pin!(shutdown);
    loop {
        let (stream, _peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(c) => c,
                Err(e) => {
                    // Out of file descriptors or a connection reset before accept: wait a
                    // moment instead of spinning, then go on accepting.
                    tracing::warn!(error = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            _ = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            metrics::counter!("shapeseek_connections_refused_total").increment(1);
            tokio::spawn(refuse(stream, limits.retry_after_secs));
            continue;
        };
        let service = TowerToHyperService::new(ServiceExt::<
            axum::http::Request<hyper::body::Incoming>,
        >::map_response(
            router.clone(), length_unknown
        ));
        let io = ProblemIo::new(stream, limits.send_stall_timeout);
        let conn = http.serve_connection(TokioIo::new(io), service);
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                tracing::debug!(error = %e, "connection ended with an error");
            }
            drop(slot);
        });
    }
    drop(listener);
    graceful.shutdown().await;
    Ok(())
}

/// Answers a connection over the cap with 503 problem+json and closes it.
async fn refuse(stream: TcpStream, retry_after: u64) {
    let mut err = ApiError::new(
        StatusCode::SERVICE_UNAVAILABLE,
        "server.busy",
        "too many open connections; retry later",
    );
    err.retry_after = Some(retry_after);
    let bytes = raw_problem(&err);
    let _ = tokio::time::timeout(Duration::from_secs(2), async {
        let mut sent = 0;
        while sent < bytes.len() {
            if stream.writable().await.is_err() {
                return;
            }
            match stream.try_write(&bytes[sent..]) {
                Ok(0) => return,
                Ok(n) => sent += n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => continue,
                Err(_) => return,
            }
        }
    })
    .await;
    // Dropping the stream closes it.
}

/// A whole HTTP/1.1 response (head and body) carrying `err` as problem+json, with
/// `Connection: close`.
fn raw_problem(err: &ApiError) -> Vec<u8> {
    let resp = err.clone().into_response();
    let status = resp.status();
    let mut head = format!(
        "HTTP/1.1 {} {}\r\n",
        status.as_u16(),
        status.canonical_reason().unwrap_or("Error")
    );
    let body = err.body_bytes();
    for (k, v) in resp.headers() {
        if k == axum::http::header::CONTENT_LENGTH {
            continue;
        }
        if let Ok(v) = v.to_str() {
            head.push_str(&format!("{k}: {v}\r\n"));
        }
    }
    head.push_str(&format!(
        "content-length: {}\r\nconnection: close\r\n\r\n",
        body.len()
    ));
    let mut out = head.into_bytes();
    out.extend_from_slice(&body);
    out
}

/// The problem document for one of hyper's automatic error responses (`None`: not one).
///
/// hyper answers a request head it cannot parse by itself with a bare head (`HTTP/1.1 400 Bad
/// Request`, `414 URI Too Long`, `431 Request Header Fields Too Large`), `content-length: 0` and
/// no `content-type`; it then closes the connection.
fn automatic_response_problem(head: &[u8]) -> Option<ApiError> {
    let text = std::str::from_utf8(head).ok()?;
    let status_line = text.split("\r\n").next()?;
    let code: u16 = status_line
        .strip_prefix("HTTP/1.1 ")?
        .get(..3)?
        .parse()
        .ok()?;
    if !(400..600).contains(&code) {
        return None;
    }
    let lower = text.to_ascii_lowercase();
    let end = lower.find("\r\n\r\n")?;
    if end + 4 != lower.len()
        || lower.contains("\r\ncontent-type:")
        || !lower.contains("\r\ncontent-length: 0\r\n")
    {
        return None;
    }
    let (status, code, detail) = match code {
        414 => (
            StatusCode::URI_TOO_LONG,
            "request.uri_too_long",
            "the request URI is too long",
        ),
        431 => (
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            "request.headers_too_large",
            "the request has too many or too large header fields",
        ),
        _ => (
            StatusCode::BAD_REQUEST,
            "request.malformed",
            "the request head is not valid HTTP/1.1 (method, URI, version or a header field)",
        ),
    };
    Some(ApiError::new(status, code, detail))
}

/// A TCP stream whose outgoing automatic error responses of hyper are replaced by
/// problem+json documents, and whose writes fail once they have made no progress for
/// `stall_after` (see the module docs).
pub struct ProblemIo {
    inner: TcpStream,
    /// Replacement bytes still to be written.
    pending: Vec<u8>,
    written: usize,
    /// How long a write may wait for the client to read ([`ConnLimits::send_stall_timeout`]).
    stall_after: Duration,
    /// Armed by a write or flush that could not proceed, disarmed by one that did.
    stall: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl ProblemIo {
    fn new(inner: TcpStream, stall_after: Duration) -> Self {
        Self {
            inner,
            pending: Vec::new(),
            written: 0,
            stall_after,
            stall: None,
        }
    }

    /// Passes a write's, flush's or shutdown's outcome on, and fails it once writes have
    /// waited `stall_after` without a byte accepted: hyper then drops the connection, and with
    /// it the response it was sending. The timer registers the task's waker, so a client that
    /// reads nothing (a full send buffer never wakes the task) is still noticed.
    fn watch<T>(&mut self, cx: &mut Context<'_>, p: Poll<io::Result<T>>) -> Poll<io::Result<T>> {
        if p.is_ready() {
            self.stall = None;
            return p;
        }
        let after = self.stall_after;
        let timer = self
            .stall
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(after)));
        if timer.as_mut().poll(cx).is_pending() {
            return Poll::Pending;
        }
        metrics::counter!("shapeseek_connections_stalled_total").increment(1);
        Poll::Ready(Err(io::Error::new(
            io::ErrorKind::TimedOut,
            format!(
                "the client read nothing for {:.0} s; connection closed",
                after.as_secs_f64()
            ),
        )))
    }

    /// Writes what is left of a replacement; Ready(Ok) once it is all out.
    fn drive_pending(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        while self.written < self.pending.len() {
            let n = match Pin::new(&mut self.inner).poll_write(cx, &self.pending[self.written..]) {
                Poll::Ready(Ok(n)) => n,
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Pending => return Poll::Pending,
            };
            if n == 0 {
                return Poll::Ready(Err(io::ErrorKind::WriteZero.into()));
            }
            self.written += n;
        }
        Poll::Ready(Ok(()))
    }
}

impl AsyncRead for ProblemIo {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for ProblemIo {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        if this.pending.is_empty() {
            if let Some(err) = automatic_response_problem(buf) {
                metrics::counter!("shapeseek_http_malformed_requests_total").increment(1);
                this.pending = raw_problem(&err);
                this.written = 0;
            } else {
                let p = Pin::new(&mut this.inner).poll_write(cx, buf);
                return this.watch(cx, p);
            }
        }
        // A replacement is under way: hyper's bytes are consumed (the connection closes after
        // this response), ours are written instead.
        let p = match this.drive_pending(cx) {
            Poll::Ready(Ok(())) => Poll::Ready(Ok(buf.len())),
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            Poll::Pending if this.written > 0 => Poll::Ready(Ok(buf.len())),
            Poll::Pending => Poll::Pending,
        };
        this.watch(cx, p)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let p = match this.drive_pending(cx) {
            Poll::Ready(Ok(())) => Pin::new(&mut this.inner).poll_flush(cx),
            other => other,
        };
        this.watch(cx, p)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let p = match this.drive_pending(cx) {
            Poll::Ready(Ok(())) => Pin::new(&mut this.inner).poll_shutdown(cx),
            other => other,
        };
        this.watch(cx, p)
    }

    fn is_write_vectored(&self) -> bool {
        // hyper then flattens each response head into one buffer, which is what
        // `automatic_response_problem` inspects.
        false
    }
}

/// Marks a response to `HEAD` whose length only generating the content would tell (a format
/// conversion, `GET /v1/shapes/{id}/mesh?format=`): it leaves without `Content-Length` (RFC
/// 9110 §9.3.2 allows leaving out what generating the content determines).
#[derive(Debug, Clone, Copy)]
pub struct LengthUnknown;

/// axum gives every `HEAD` answer without a length the `Content-Length: 0` of the empty body it
/// sends, which the `GET` would contradict; answers marked [`LengthUnknown`] leave without it.
/// (A body of unknown size does not avoid it: the method router's route empties the body for
/// `HEAD`, and the layered route around it then counts the empty one; tried with axum 0.8.)
fn length_unknown(mut r: axum::response::Response) -> axum::response::Response {
    if r.extensions().get::<LengthUnknown>().is_some() {
        r.headers_mut().remove(axum::http::header::CONTENT_LENGTH);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recognises_only_hypers_bare_error_heads() {
        let bare = b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-length: 0\r\ndate: Tue, 01 Dec 2026 10:00:00 GMT\r\n\r\n";
        let p = automatic_response_problem(bare).expect("bare 431");
        assert_eq!(p.status, StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE);
        assert_eq!(p.code, "request.headers_too_large");
        let bare414 = b"HTTP/1.1 414 URI Too Long\r\ncontent-length: 0\r\n\r\n";
        assert_eq!(
            automatic_response_problem(bare414).map(|p| p.code),
            Some("request.uri_too_long".to_string())
        );
        let bare400 = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\n";
        assert_eq!(
            automatic_response_problem(bare400).map(|p| p.status),
            Some(StatusCode::BAD_REQUEST)
        );
        // The router's own responses are left alone.
        let ours = b"HTTP/1.1 404 Not Found\r\ncontent-type: application/problem+json\r\ncontent-length: 0\r\n\r\n";
        assert!(automatic_response_problem(ours).is_none());
        let ok = b"HTTP/1.1 200 OK\r\ncontent-length: 0\r\n\r\n";
        assert!(automatic_response_problem(ok).is_none());
        let with_body = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\nxyz";
        assert!(automatic_response_problem(with_body).is_none());
    }

    #[test]
    fn raw_problem_is_a_complete_response() {
        let mut e = ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "server.busy", "full");
        e.retry_after = Some(3);
        let raw = String::from_utf8(raw_problem(&e)).unwrap();
        assert!(
            raw.starts_with("HTTP/1.1 503 Service Unavailable\r\n"),
            "{raw}"
        );
        let lower = raw.to_ascii_lowercase();
        assert!(lower.contains("content-type: application/problem+json\r\n"));
        assert!(lower.contains("retry-after: 3\r\n"));
        assert!(lower.contains("connection: close\r\n"));
        let (head, body) = raw.split_once("\r\n\r\n").unwrap();
        assert!(head
            .to_ascii_lowercase()
            .contains(&format!("content-length: {}", body.len())));
        let v: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!(v["code"], "server.busy");
        assert_eq!(v["status"], 503);
    }
}
