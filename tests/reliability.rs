//! Connection hygiene of `shapeseek serve`, tried as a hostile client would: raw TCP clients
//! that send nothing, half a head, a trickle of body, absurd sizes or malformed heads, and more
//! connections or body bytes than the server admits. Every answer must be a problem+json
//! document with a stable code (or a closed connection), never a hang.

use serde_json::Value;
use shapeseek::server::{start, Running, ServerConfig};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::{Duration, Instant};

struct Server {
    rt: tokio::runtime::Runtime,
    running: Option<Running>,
    addr: SocketAddr,
}

impl Server {
    fn start(data: &Path, tweak: impl FnOnce(&mut ServerConfig)) -> Server {
        let mut cfg = ServerConfig {
            data: data.to_path_buf(),
            addr: "127.0.0.1:0".into(),
            eigenpairs: 30,
            workers: 2,
            shutdown_grace_secs: 5.0,
            ..Default::default()
        };
        tweak(&mut cfg);
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let running = rt.block_on(start(cfg)).expect("server starts");
        let addr = running.addr;
        Server {
            rt,
            running: Some(running),
            addr,
        }
    }

    fn stop(mut self) {
        let r = self.running.take().unwrap();
        self.rt.block_on(r.shutdown()).expect("clean shutdown");
    }
}

fn connect(addr: SocketAddr) -> TcpStream {
    let s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s
}

/// Reads until the server closes the connection or the read timeout passes; returns the bytes
/// and whether the connection was closed by the server.
fn read_until_closed(s: &mut TcpStream) -> (Vec<u8>, bool) {
    let mut out = Vec::new();
    let mut buf = [0u8; 8192];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return (out, true),
            Ok(n) => out.extend_from_slice(&buf[..n]),
            Err(e)
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut =>
            {
                return (out, false)
            }
            Err(_) => return (out, true),
        }
    }
}

/// Reads one response head and its `content-length` body.
fn read_response(s: &mut TcpStream) -> (u16, Vec<(String, String)>, Vec<u8>) {
    let mut raw = Vec::new();
    let mut buf = [0u8; 1];
    while !raw.ends_with(b"\r\n\r\n") {
        match s.read(&mut buf) {
            Ok(1) => raw.push(buf[0]),
            _ => panic!(
                "connection ended before a response head: {:?}",
                String::from_utf8_lossy(&raw)
            ),
        }
    }
    let head = String::from_utf8_lossy(&raw).to_string();
    let mut lines = head.split("\r\n");
    let status: u16 = lines
        .next()
        .unwrap()
        .split(' ')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let len: usize = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .map(|(_, v)| v.parse().unwrap())
        .unwrap_or(0);
    let mut body = vec![0u8; len];
    s.read_exact(&mut body).expect("body");
    (status, headers, body)
}

fn header<'a>(h: &'a [(String, String)], name: &str) -> Option<&'a str> {
    h.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

/// Asserts a problem+json answer with `status` and `code`.
fn assert_problem(resp: &(u16, Vec<(String, String)>, Vec<u8>), status: u16, code: &str) {
    let (st, h, body) = resp;
    assert_eq!(*st, status, "body {:?}", String::from_utf8_lossy(body));
    assert_eq!(header(h, "content-type"), Some("application/problem+json"));
    let v: Value = serde_json::from_slice(body).expect("problem JSON");
    assert_eq!(v["code"], code, "{v}");
    assert_eq!(v["status"], status);
}

#[test]
fn silent_unfinished_and_idle_connections_are_closed() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |c| c.header_read_timeout_secs = 1.0);
    let t0 = Instant::now();
    let mut silent = connect(s.addr);
    let mut half = connect(s.addr);
    half.write_all(b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Le")
        .unwrap();
    let mut idle = connect(s.addr);
    idle.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        .unwrap();
    let ok = read_response(&mut idle);
    assert_eq!(ok.0, 200);
    for (what, c) in [
        ("silent", &mut silent),
        ("unfinished head", &mut half),
        ("idle keep-alive", &mut idle),
    ] {
        let (_, closed) = read_until_closed(c);
        assert!(
            closed,
            "{what} connection still open after {:?}",
            t0.elapsed()
        );
    }
    assert!(
        t0.elapsed() < Duration::from_secs(5),
        "closed only after {:?}",
        t0.elapsed()
    );
    s.stop();
}

#[test]
fn a_trickling_body_gets_408_problem_json() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |c| c.body_read_timeout_secs = 1.0);
    let mut c = connect(s.addr);
    c.write_all(
        b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nContent-Length: 1000\r\n\r\nv 0 0 0\n",
    )
    .unwrap();
    let t0 = Instant::now();
    let r = read_response(&mut c);
    assert_problem(&r, 408, "request.body_timeout");
    assert!(t0.elapsed() < Duration::from_secs(5));
    assert_eq!(header(&r.1, "connection"), Some("close"));
    s.stop();
}

#[test]
fn an_oversized_content_length_is_413_before_100_continue() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |_| {});
    let mut c = connect(s.addr);
    c.write_all(
        b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nExpect: 100-continue\r\nContent-Length: 99999999999\r\n\r\n",
    )
    .unwrap();
    let t0 = Instant::now();
    let r = read_response(&mut c);
    assert_problem(&r, 413, "limit.bytes");
    assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
    // Same without Expect, with some body bytes sent.
    let mut c = connect(s.addr);
    c.write_all(
        b"POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nContent-Length: 99999999999\r\n\r\nv 0 0 0\n",
    )
    .unwrap();
    assert_problem(&read_response(&mut c), 413, "limit.bytes");
    s.stop();
}

#[test]
fn connections_over_the_cap_get_503_with_retry_after() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |c| {
        c.max_connections = 4;
        c.retry_after_secs = 3;
    });
    // Four connections hold the slots (a keep-alive request each, then idle).
    let mut held: Vec<TcpStream> = (0..4)
        .map(|_| {
            let mut c = connect(s.addr);
            c.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
                .unwrap();
            assert_eq!(read_response(&mut c).0, 200);
            c
        })
        .collect();
    let mut extra = connect(s.addr);
    extra
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        .unwrap();
    let r = read_response(&mut extra);
    assert_problem(&r, 503, "server.busy");
    assert_eq!(header(&r.1, "retry-after"), Some("3"));
    // A slot freed is a slot reused.
    drop(held.pop());
    let t0 = Instant::now();
    loop {
        let mut c = connect(s.addr);
        c.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            .unwrap();
        let r = read_response(&mut c);
        if r.0 == 200 {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(5), "slot never freed");
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(held);
    s.stop();
}

#[test]
fn errors_of_the_http_layer_are_problem_json() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |_| {});
    // A URI hyper cannot represent (100 KB of query).
    let mut c = connect(s.addr);
    let long = format!(
        "GET /v1/shapes?name={} HTTP/1.1\r\nHost: x\r\n\r\n",
        "a".repeat(100_000)
    );
    c.write_all(long.as_bytes()).unwrap();
    assert_problem(&read_response(&mut c), 414, "request.uri_too_long");
    // Control bytes in a header value.
    let mut c = connect(s.addr);
    c.write_all(b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/\x01obj\r\nContent-Length: 0\r\n\r\n")
        .unwrap();
    assert_problem(&read_response(&mut c), 400, "request.malformed");
    // Too many header fields.
    let mut c = connect(s.addr);
    let mut head = String::from("GET /healthz HTTP/1.1\r\nHost: x\r\n");
    for i in 0..300 {
        head.push_str(&format!("X-Filler-{i}: {i}\r\n"));
    }
    head.push_str("\r\n");
    c.write_all(head.as_bytes()).unwrap();
    assert_problem(&read_response(&mut c), 431, "request.headers_too_large");
    // The server is still fine.
    let mut c = connect(s.addr);
    c.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .unwrap();
    assert_eq!(read_response(&mut c).0, 200);
    s.stop();
}

#[test]
fn request_ids_are_bounded_and_sanitised() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |_| {});
    let ask = |id: &str| {
        let mut c = connect(s.addr);
        c.write_all(
            format!(
                "GET /healthz HTTP/1.1\r\nHost: x\r\nX-Request-Id: {id}\r\nConnection: close\r\n\r\n"
            )
            .as_bytes(),
        )
        .unwrap();
        let (st, h, _) = read_response(&mut c);
        assert_eq!(st, 200);
        header(&h, "x-request-id").expect("an id").to_string()
    };
    assert_eq!(ask("client-42.a:b_c"), "client-42.a:b_c");
    let huge = "x".repeat(8192);
    let got = ask(&huge);
    assert_ne!(got, huge);
    assert!(got.len() <= 64, "{got}");
    let got = ask("a b<script>");
    assert!(
        got.bytes()
            .all(|c| c.is_ascii_alphanumeric() || b"-_.:".contains(&c)),
        "{got}"
    );
    s.stop();
}

#[test]
fn body_bytes_in_flight_are_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |c| {
        c.max_body_bytes = 1 << 20;
        c.max_inflight_body_bytes = 1 << 20;
        c.retry_after_secs = 4;
    });
    // One upload announces the whole budget and sends half of it.
    let mut big = connect(s.addr);
    big.write_all(
        format!(
            "POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nContent-Length: {}\r\n\r\n",
            1 << 20
        )
        .as_bytes(),
    )
    .unwrap();
    big.write_all(&vec![b'#'; 1 << 19]).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    // Another body does not fit in what is left.
    let mut c = connect(s.addr);
    c.write_all(
        b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nContent-Length: 8\r\n\r\nv 0 0 0\n",
    )
    .unwrap();
    let r = read_response(&mut c);
    assert_problem(&r, 503, "server.busy");
    assert_eq!(header(&r.1, "retry-after"), Some("4"));
    // A request without a body is not affected.
    let mut c = connect(s.addr);
    c.write_all(b"GET /v1/shapes HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .unwrap();
    assert_eq!(read_response(&mut c).0, 200);
    // Once the first upload is over (refused as a mesh: it is all comments), the budget is back.
    big.write_all(&vec![b'#'; 1 << 19]).unwrap();
    let r = read_response(&mut big);
    assert!(r.0 >= 400 && r.0 < 500, "status {}", r.0);
    let mut c = connect(s.addr);
    c.write_all(
        b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nContent-Length: 8\r\nConnection: close\r\n\r\nv 0 0 0\n",
    )
    .unwrap();
    let r = read_response(&mut c);
    assert_ne!(r.0, 503, "budget not released");
    s.stop();
}

#[test]
fn limits_that_contradict_each_other_are_refused_at_start() {
    let cfg = ServerConfig {
        max_body_bytes: 64 << 20,
        max_inflight_body_bytes: 1 << 20,
        ..Default::default()
    };
    let e = cfg.validate().expect_err("budget below one body");
    assert!(e.to_string().contains("max_inflight_body_bytes"), "{e}");
    let cfg = ServerConfig {
        header_read_timeout_secs: 0.0,
        ..Default::default()
    };
    assert!(cfg.validate().is_err());
}

#[test]
fn the_default_top_k_respects_a_small_max_top_k() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), |c| c.max_top_k = 3);
    // An empty index still answers (no hits); before, every search without `top_k` was a 400
    // when `max_top_k` < 10.
    let mut c = connect(s.addr);
    let body = br#"{"id": "0000000000000000", "rerank": []}"#;
    c.write_all(
        format!(
            "POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            body.len()
        )
        .as_bytes(),
    )
    .unwrap();
    c.write_all(body).unwrap();
    let r = read_response(&mut c);
    // The unknown id is the only complaint: 404, not a 400 about top_k.
    assert_problem(&r, 404, "shape.not_found");
    s.stop();
}
