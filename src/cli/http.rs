//! A small blocking client of the shapeseek REST API (ureq, plain HTTP): requests, problem+json
//! errors as (code, detail), and `503 server.busy` retried after its `Retry-After`.

use super::CliError;
use serde_json::Value;
use std::time::Duration;

/// The largest response body read (search answers and records are small).
const MAX_RESPONSE: u64 = 64 << 20;

/// How often a `503 server.busy` or `server.not_ready` (an index loading) is retried, after its
/// `Retry-After`, before it counts as a failure.
const BUSY_RETRIES: u32 = 30;

/// A failed request: the server's problem code and detail, or the client's own.
#[derive(Debug, Clone)]
pub struct Failure {
    /// HTTP status (0 when no answer came).
    pub status: u16,
    /// Problem code (`mesh.parse`, ...) or `server.unreachable`, `http.<status>`.
    pub code: String,
    /// What went wrong.
    pub detail: String,
}

/// A server at a base URL.
pub struct Client {
    base: String,
    agent: ureq::Agent,
}

/// One answer: status and parsed JSON body.
pub struct Answer {
    /// HTTP status.
    pub status: u16,
    /// The body as JSON.
    pub json: Value,
}

impl Client {
    /// A client of the server at `url` (`http://HOST:PORT`, optionally with a path prefix).
    pub fn new(url: &str) -> Result<Client, CliError> {
        let base = url.trim_end_matches('/').to_string();
        if base.starts_with("https://") {
            return Err(CliError::usage(format!(
                "--url {url}: this build speaks plain HTTP only (the server has no TLS either); \
                 run the command where it reaches the server over http://"
            )));
        }
        if !base.starts_with("http://") || base.len() <= "http://".len() {
            return Err(CliError::usage(format!(
                "--url {url}: expected http://HOST:PORT"
            )));
        }
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_connect(Some(Duration::from_secs(10)))
            .timeout_global(Some(Duration::from_secs(600)))
            .build()
            .into();
        Ok(Client { base, agent })
    }

    /// The base URL.
    pub fn base(&self) -> &str {
        &self.base
    }

    /// Checks the server answers `/readyz` with 200; the error says how to start one.
    pub fn ready(&self) -> Result<(), CliError> {
        match self.send(|a| a.get(format!("{}/readyz", self.base)).call()) {
            Ok(_) => Ok(()),
            Err(f) if f.status == 0 => Err(self.unreachable(&f)),
            Err(f) => Err(CliError::new(
                f.code,
                format!(
                    "the server at {} is not ready (HTTP {}: {})",
                    self.base, f.status, f.detail
                ),
                69,
            )),
        }
    }

    /// Whether the server answers at all: `GET /readyz` once, within 5 s, any answer but a
    /// proxy's 502 or 504 for a backend that is gone (a busy or loading server answers 503).
    pub fn probe(&self) -> bool {
        let r = self
            .agent
            .get(format!("{}/readyz", self.base))
            .config()
            .timeout_global(Some(Duration::from_secs(5)))
            .build()
            .call();
        r.is_ok_and(|r| !matches!(r.status().as_u16(), 502 | 504))
    }

    /// The [`CliError`] of a failure that prevented any answer.
    pub fn unreachable(&self, f: &Failure) -> CliError {
        CliError::new(
            f.code.clone(),
            format!(
                "cannot reach shapeseek at {}: {} (start one with `shapeseek serve`, pass \
                 --url, or ingest straight into a data directory with --data DIR)",
                self.base, f.detail
            ),
            69,
        )
    }

    /// `POST path` with a body of the given content type and query parameters.
    pub fn post(
        &self,
        path: &str,
        query: &[(&str, String)],
        content_type: &str,
        body: &[u8],
    ) -> Result<Answer, Failure> {
        self.send(|a| {
            let mut req = a
                .post(format!("{}{path}", self.base))
                .header("content-type", content_type);
            for (k, v) in query {
                req = req.query(*k, v);
            }
            req.send(body)
        })
    }

    /// `GET path`.
    pub fn get(&self, path: &str) -> Result<Answer, Failure> {
        self.send(|a| a.get(format!("{}{path}", self.base)).call())
    }

    /// Sends a request (again after `Retry-After` while the server is busy) and reads the
    /// answer; an error status becomes a [`Failure`] with the problem's code and detail.
    fn send(
        &self,
        request: impl Fn(&ureq::Agent) -> Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> Result<Answer, Failure> {
        let mut attempt = 0;
        loop {
            let mut resp = request(&self.agent).map_err(|e| Failure {
                status: 0,
                code: "server.unreachable".into(),
                detail: transport_reason(&e),
            })?;
            let status = resp.status().as_u16();
            let retry_after = resp
                .headers()
                .get("retry-after")
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.trim().parse::<u64>().ok());
            let text = resp
                .body_mut()
                .with_config()
                .limit(MAX_RESPONSE)
                .read_to_string()
                .map_err(|e| Failure {
                    status,
                    code: "server.unreachable".into(),
                    detail: format!("reading the answer: {e}"),
                })?;
            let json: Value = serde_json::from_str(&text).unwrap_or(Value::String(text));
            if (200..300).contains(&status) {
                return Ok(Answer { status, json });
            }
            let code = json["code"]
                .as_str()
                .map(str::to_string)
                .unwrap_or_else(|| format!("http.{status}"));
            // Busy, or still loading its index (it answers 503 `server.not_ready` meanwhile):
            // wait as it says and ask again.
            let transient = code == "server.busy" || code == "server.not_ready";
            if status == 503 && transient && attempt < BUSY_RETRIES {
                attempt += 1;
                std::thread::sleep(Duration::from_secs(retry_after.unwrap_or(1).clamp(1, 30)));
                continue;
            }
            let detail = json["detail"]
                .as_str()
                .map(str::to_string)
                .unwrap_or_else(|| format!("HTTP {status}: {json}"));
            return Err(Failure {
                status,
                code,
                detail,
            });
        }
    }
}

/// A transport error in words (connection refused, timeout, ...).
fn transport_reason(e: &ureq::Error) -> String {
    match e {
        ureq::Error::Io(io) => super::io_reason(io),
        other => other.to_string(),
    }
}

/// A `multipart/form-data` body of one file part (`file`, with its file name) and one JSON part;
/// returns (content type, body).
pub fn multipart(file_name: &str, file: &[u8], json_name: &str, json: &[u8]) -> (String, Vec<u8>) {
    // A boundary that does not occur in the parts.
    let mut n: u64 = 0x5ea5_c0de;
    let boundary = loop {
        let b = format!("shapeseek-{n:016x}");
        if !contains(file, b.as_bytes()) && !contains(json, b.as_bytes()) {
            break b;
        }
        n = n.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
    };
    let safe_name: String = file_name
        .chars()
        .map(|c| if c == '"' || c.is_control() { '_' } else { c })
        .collect();
    let mut body = Vec::with_capacity(file.len() + json.len() + 512);
    body.extend_from_slice(
        format!(
            "--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"{safe_name}\"\r\nContent-Type: application/octet-stream\r\n\r\n"
        )
        .as_bytes(),
    );
    body.extend_from_slice(file);
    body.extend_from_slice(
        format!(
            "\r\n--{boundary}\r\nContent-Disposition: form-data; name=\"{json_name}\"\r\nContent-Type: application/json\r\n\r\n"
        )
        .as_bytes(),
    );
    body.extend_from_slice(json);
    body.extend_from_slice(format!("\r\n--{boundary}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={boundary}"), body)
}

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}
