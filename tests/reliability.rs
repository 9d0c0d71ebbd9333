//! Connection hygiene of `shapeseek serve`, tried as a hostile client would: raw TCP clients
//! that send nothing, half a head, a trickle of body, absurd sizes or malformed heads, and more
//! connections or body bytes than the server admits. Every answer must be a problem+json
//! document with a stable code (or a closed connection), never a hang.

use serde_json::Value;
use shapeseek::server::ServerConfig;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

/// The tests of this file run one at a time: two of them measure latency and the process's CPU
/// time, which other tests' servers in the same process would disturb.
fn serial() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|p| p.into_inner())
}

#[path = "common/in_process.rs"]
mod in_process;
use in_process::Server;

/// Shutdown grace of these tests' servers: short, since hostile clients may hold connections
/// open until it runs out.
const GRACE_SECS: f64 = 5.0;

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
    let (status, headers) = in_process::parse_head(&head);
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
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.header_read_timeout_secs = 1.0);
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
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.body_read_timeout_secs = 1.0);
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
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
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
fn a_chunked_body_is_read_whole_up_to_the_limit_and_refused_past_it() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.max_body_bytes = 4096);
    let chunked = |parts: &[&[u8]]| {
        let mut req = b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/off\r\n\
Transfer-Encoding: chunked\r\n\r\n"
            .to_vec();
        for p in parts {
            req.extend_from_slice(format!("{:x}\r\n", p.len()).as_bytes());
            req.extend_from_slice(p);
            req.extend_from_slice(b"\r\n");
        }
        req.extend_from_slice(b"0\r\n\r\n");
        req
    };
    // A tetrahedron in three chunks: read whole, then refused as too small a mesh (not 413).
    let tet: &[&[u8]] = &[
        b"OFF\n4 4 0\n0 0 0\n1 0 0\n",
        b"0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n",
        b"3 0 3 2\n3 1 2 3\n",
    ];
    let mut c = connect(s.addr);
    c.write_all(&chunked(tet)).unwrap();
    let r = read_response(&mut c);
    assert_ne!(r.0, 413, "{}", String::from_utf8_lossy(&r.2));
    assert!(
        r.0 == 201 || r.0 == 422,
        "{} {}",
        r.0,
        String::from_utf8_lossy(&r.2)
    );
    // 5 000 bytes in chunks of 1 000 without a Content-Length: 413 once past 4 096.
    let big = vec![b'#'; 1000];
    let parts: Vec<&[u8]> = (0..5).map(|_| big.as_slice()).collect();
    let mut c = connect(s.addr);
    c.write_all(&chunked(&parts)).unwrap();
    assert_problem(&read_response(&mut c), 413, "limit.bytes");
    s.stop();
}

#[test]
fn connections_over_the_cap_get_503_with_retry_after() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
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
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
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
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
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

/// Bodies take from the budget what has arrived of them: one upload that announced the largest
/// body and sent half of it, and four chunked uploads trickling a few bytes, leave room for
/// other bodies (before: the first held its announced size from its first byte, and each
/// chunked one the largest body's, so with a budget of two largest bodies every other POST was
/// refused with 503 while they lasted). A body
/// that cannot take the next step is refused mid-way (`limits` unit tests).
#[test]
fn body_bytes_in_flight_are_bounded_by_what_arrived() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.max_body_bytes = 1 << 20;
        c.max_inflight_body_bytes = 2 << 20;
        c.retry_after_secs = 4;
    });
    // One upload announces the largest body and sends half of it.
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
    // Four chunked uploads send a chunk of two bytes, and no more.
    let trickles: Vec<_> = (0..4)
        .map(|_| {
            let mut t = connect(s.addr);
            t.write_all(
                b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n2\r\n# \r\n",
            )
            .unwrap();
            t
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    // Other bodies are read and answered (this one is not a mesh: a 4xx, not 503).
    for _ in 0..3 {
        let mut c = connect(s.addr);
        c.write_all(
            b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\nContent-Length: 8\r\nConnection: close\r\n\r\nv 0 0 0\n",
        )
        .unwrap();
        let r = read_response(&mut c);
        assert!(
            r.0 >= 400 && r.0 < 500,
            "status {}: {}",
            r.0,
            String::from_utf8_lossy(&r.2)
        );
    }
    // A request without a body is not affected.
    let mut c = connect(s.addr);
    c.write_all(b"GET /v1/shapes HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .unwrap();
    assert_eq!(read_response(&mut c).0, 200);
    // The first upload completes (refused as a mesh: it is all comments).
    big.write_all(&vec![b'#'; 1 << 19]).unwrap();
    let r = read_response(&mut big);
    assert!(r.0 >= 400 && r.0 < 500, "status {}", r.0);
    drop(trickles);
    s.stop();
}

#[test]
fn limits_that_contradict_each_other_are_refused_at_start() {
    let _serial = serial();
    let cfg = ServerConfig {
        max_body_bytes: 64 << 20,
        max_inflight_body_bytes: 1 << 20,
        ..Default::default()
    };
    let e = cfg.validate().expect_err("budget below one body");
    assert!(e.to_string().contains("max_inflight_body_bytes"), "{e}");
    let cfg = ServerConfig {
        max_body_bytes: 64 << 20,
        max_inflight_response_bytes: 1 << 20,
        ..Default::default()
    };
    let e = cfg
        .validate()
        .expect_err("download budget below one original");
    assert!(e.to_string().contains("max_inflight_response_bytes"), "{e}");
    for bad in [
        ServerConfig {
            header_read_timeout_secs: 0.0,
            ..Default::default()
        },
        ServerConfig {
            send_stall_timeout_secs: 0.0,
            ..Default::default()
        },
    ] {
        assert!(bad.validate().is_err());
    }
}

#[test]
fn the_default_top_k_respects_a_small_max_top_k() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.max_top_k = 3);
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

// ------------------------------------------------------------------ CPU admission, overload

use shapeseek::mesh::generate::{bumpy_sphere, icosphere, torus};
use shapeseek::mesh::read::Format;
use shapeseek::mesh::write::write_mesh;
use shapeseek::mesh::Mesh;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

type Resp = (u16, Vec<(String, String)>, Vec<u8>);

/// One request on its own connection (`Connection: close`).
fn request(addr: SocketAddr, method: &str, path: &str, ctype: &str, body: &[u8]) -> Resp {
    let mut c = TcpStream::connect(addr).expect("connect");
    c.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    c.write_all(
        format!(
            "{method} {path} HTTP/1.1\r\nHost: x\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            body.len()
        )
        .as_bytes(),
    )
    .unwrap();
    let _ = c.write_all(body);
    read_response(&mut c)
}

fn json_of(r: &Resp) -> Value {
    serde_json::from_slice(&r.2).unwrap_or_else(|e| {
        panic!(
            "not JSON ({e}): {} {:?}",
            r.0,
            String::from_utf8_lossy(&r.2)
        )
    })
}

fn search(addr: SocketAddr, body: &Value) -> Resp {
    request(
        addr,
        "POST",
        "/v1/search",
        "application/json",
        body.to_string().as_bytes(),
    )
}

fn index_info(addr: SocketAddr) -> Value {
    json_of(&request(addr, "GET", "/v1/index", "text/plain", b""))
}

fn obj(m: &Mesh) -> Vec<u8> {
    let mut out = Vec::new();
    write_mesh(m, Format::Obj, &mut out).unwrap();
    out
}

/// A distinct small shape per `i` (162 to 200 vertices; 40 proportions, then shifted).
fn shape(i: usize) -> Mesh {
    let mut m = match i % 3 {
        0 => icosphere(2),
        1 => bumpy_sphere(2, 0.05 + 0.01 * (i % 7) as f64),
        _ => torus(1.0, 0.3 + 0.01 * (i % 5) as f64, 20, 10),
    };
    let s = 1.0 + 0.013 * (i % 40) as f64;
    for v in &mut m.vertices {
        v[0] *= s;
        v[1] += 1e-3 * (i / 40) as f64;
        v[2] /= s;
    }
    m
}

/// Ingests `n` shapes; returns their ids once all are searchable (index calibrated).
fn ingest_corpus(addr: SocketAddr, n: usize) -> Vec<String> {
    let ids: Vec<String> = (0..n)
        .map(|i| {
            let r = request(addr, "POST", "/v1/shapes", "model/obj", &obj(&shape(i)));
            assert_eq!(r.0, 201, "{:?}", String::from_utf8_lossy(&r.2));
            json_of(&r)["id"].as_str().unwrap().to_string()
        })
        .collect();
    let t = Instant::now();
    loop {
        let v = index_info(addr);
        if v["shapes"] == n && v["calibrated_on"].as_u64().unwrap() > 0 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "never calibrated");
        std::thread::sleep(Duration::from_millis(20));
    }
    ids
}

/// Nearest-rank percentile of milliseconds.
fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((p * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1]
}

/// How long until the heavy lane runs nothing; fails past `within`.
fn heavy_lane_empties(addr: SocketAddr, within: Duration) -> Duration {
    let t = Instant::now();
    while index_info(addr)["queue"]["heavy"]["running"] != 0 {
        assert!(
            t.elapsed() < within,
            "the heavy lane still runs {:?} after the timeout",
            t.elapsed()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    t.elapsed()
}

/// CPU time (user + system) of this process so far, seconds: the server runs in it.
fn process_cpu_secs() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap();
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let f: Vec<&str> = rest.split(' ').collect();
    // Fields 14 and 15 of stat(5) (utime, stime), counted from the state field (3).
    let ticks: f64 = f[11].parse::<f64>().unwrap() + f[12].parse::<f64>().unwrap();
    ticks / 100.0
}

/// A 5xx must be a 503 with `Retry-After` (`server.busy` or `request.timeout`).
fn assert_acceptable(r: &Resp, what: &str) {
    if r.0 >= 500 {
        assert_eq!(r.0, 503, "{what}: {:?}", String::from_utf8_lossy(&r.2));
        assert!(
            header(&r.1, "retry-after").is_some(),
            "{what}: 503 without Retry-After: {:?}",
            String::from_utf8_lossy(&r.2)
        );
        let code = json_of(r)["code"].as_str().unwrap().to_string();
        assert!(
            code == "server.busy" || code == "request.timeout",
            "{what}: {code}"
        );
    }
}

fn gw_search(id: &str, outer: usize) -> Value {
    serde_json::json!({
        "id": id,
        "rerank": [{"stage": "spectral_gw", "shortlist": 200, "outer_iterations": outer, "eps_rel": 0.001}]
    })
}

/// Finding 1: searches bypassed the bounded pool (`workers = 1, queue_capacity = 1`: 15 491
/// searches, 0 `server.busy`). Now an expensive search is admitted like an ingest.
#[test]
fn searches_are_admitted_through_the_bounded_lanes() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.workers = 1;
        c.queue_capacity = 1;
        c.retry_after_secs = 5;
    });
    let ids = ingest_corpus(s.addr, 12);
    let addr = s.addr;
    let threads: Vec<_> = (0..6)
        .map(|i| {
            let id = ids[i].clone();
            std::thread::spawn(move || search(addr, &gw_search(&id, 20)))
        })
        .collect();
    let resps: Vec<Resp> = threads.into_iter().map(|t| t.join().unwrap()).collect();
    let busy: Vec<&Resp> = resps.iter().filter(|r| r.0 == 503).collect();
    let ok = resps.iter().filter(|r| r.0 == 200).count();
    assert!(
        ok >= 1,
        "{:?}",
        resps.iter().map(|r| r.0).collect::<Vec<_>>()
    );
    assert!(
        busy.len() >= 3,
        "one runs, one waits, the rest are refused: {:?}",
        resps.iter().map(|r| r.0).collect::<Vec<_>>()
    );
    for b in busy {
        assert_problem(b, 503, "server.busy");
        assert_eq!(header(&b.1, "retry-after"), Some("5"));
    }
    assert!(
        index_info(addr)["queue"]["heavy"]["refused"]
            .as_u64()
            .unwrap()
            >= 3
    );
    s.stop();
}

/// Finding 1: timed-out searches kept burning CPU for 3.7 s after the last response, and the
/// timeout carried no `Retry-After`. Now an abandoned search (deadline passed, or the client
/// closed its connection) stops within one GW candidate.
#[test]
fn abandoned_searches_stop_their_work() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.request_timeout_secs = 1.0;
        c.retry_after_secs = 2;
        // One heavy thread whatever the machine's cores, so that the search below takes as
        // long on a many-core machine.
        c.workers = 2;
        c.heavy_borrow = false;
    });
    let ids = ingest_corpus(s.addr, 200);
    let addr = s.addr;
    // Alone, this search must outlast the 1 s timeout: 199 candidates, 20 outer iterations on
    // one thread took 4.7 s without a timeout (47 candidates on both cores took 0.5 s once the
    // solver's products used SIMD; 23, before that, 0.95 s).
    let t0 = Instant::now();
    let r = search(addr, &gw_search(&ids[0], 20));
    assert_problem(&r, 503, "request.timeout");
    assert_eq!(header(&r.1, "retry-after"), Some("2"));
    let answered = t0.elapsed();
    // The job stops: the heavy lane is empty within a candidate's time (+ polling).
    let stopped_after = heavy_lane_empties(addr, Duration::from_millis(1500));
    // And the process is idle: CPU time over the next second.
    let cpu0 = process_cpu_secs();
    let w0 = Instant::now();
    std::thread::sleep(Duration::from_secs(1));
    let idle_cpu = process_cpu_secs() - cpu0;
    let window = w0.elapsed().as_secs_f64();
    assert!(
        idle_cpu < 0.2 * window,
        "{idle_cpu:.2} s of CPU in {window:.2} s after the timeout"
    );
    let info = index_info(addr);
    assert!(info["queue"]["cancelled"].as_u64().unwrap() >= 1, "{info}");
    assert!(
        info["queue"]["gw_candidates_skipped"].as_u64().unwrap() >= 1,
        "{info}"
    );
    // A client that hangs up: its search stops too.
    let before = info["queue"]["cancelled"].as_u64().unwrap();
    let body = gw_search(&ids[1], 20).to_string();
    let mut c = connect(addr);
    c.write_all(
        format!(
            "POST /v1/search HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        )
        .as_bytes(),
    )
    .unwrap();
    let t2 = Instant::now();
    while index_info(addr)["queue"]["heavy"]["running"] != 1 {
        assert!(
            t2.elapsed() < Duration::from_secs(5),
            "search never started"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    drop(c);
    let t3 = Instant::now();
    while index_info(addr)["queue"]["cancelled"].as_u64().unwrap() == before {
        assert!(
            t3.elapsed() < Duration::from_millis(900),
            "the search of a client that left was not stopped"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    eprintln!(
        "timeout answered after {answered:?}; job stopped {stopped_after:?} later; \
         {idle_cpu:.3} s CPU in the next {window:.2} s; hang-up stopped after {:?}",
        t3.elapsed()
    );
    s.stop();
}

/// An abandoned upload stops its analysis: the eigensolve checks the request's token before
/// each block of operator applications (before, an upload whose analysis outlasted the timeout
/// held the heavy lane — one thread on 2 cores — until its spectrum was done).
#[test]
fn abandoned_uploads_stop_their_analysis() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.request_timeout_secs = 1.0;
        c.retry_after_secs = 2;
    });
    // 163 842 vertices: its analysis alone takes many seconds.
    let big = obj(&bumpy_sphere(7, 0.05));
    let t0 = Instant::now();
    let r = request(s.addr, "POST", "/v1/shapes", "model/obj", &big);
    assert_problem(&r, 503, "request.timeout");
    assert_eq!(header(&r.1, "retry-after"), Some("2"));
    let answered = t0.elapsed();
    let stopped_after = heavy_lane_empties(s.addr, Duration::from_secs(3));
    let info = index_info(s.addr);
    assert_eq!(info["shapes"], 0, "{info}");
    assert!(info["queue"]["cancelled"].as_u64().unwrap() >= 1, "{info}");
    // The lane is free: a small upload is analysed at once.
    let r = request(s.addr, "POST", "/v1/shapes", "model/obj", &obj(&shape(0)));
    assert_eq!(r.0, 201, "{:?}", String::from_utf8_lossy(&r.2));
    eprintln!("timeout answered after {answered:?}; analysis stopped {stopped_after:?} later");
    s.stop();
}

/// The overload mix of the review: expensive GW searches, cheap scan-only searches and
/// ingests at once. Every answer is a success or a 503 with `Retry-After`, and the cheap
/// searches' p99 stays within 5× their p99 measured idle on the same server just before.
#[test]
fn cheap_searches_keep_their_latency_under_an_overload_mix() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.request_timeout_secs = 6.0;
        c.queue_capacity = 6;
        c.retry_after_secs = 1;
    });
    let ids = ingest_corpus(s.addr, 32);
    let addr = s.addr;
    let cheap = |i: usize| serde_json::json!({"id": ids[i % ids.len()], "rerank": []});
    let timed = |body: &Value| {
        let t = Instant::now();
        let r = search(addr, body);
        (t.elapsed().as_secs_f64() * 1e3, r)
    };
    // Idle.
    for i in 0..20 {
        assert_eq!(timed(&cheap(i)).1 .0, 200);
    }
    let mut idle: Vec<f64> = (0..1000)
        .map(|i| {
            let (ms, r) = timed(&cheap(i));
            assert_eq!(r.0, 200);
            ms
        })
        .collect();
    let idle_p50 = percentile(&mut idle, 0.5);
    let idle_p99 = percentile(&mut idle, 0.99);
    // Overload: 6 GW searchers, 2 ingesters, 1 cheap searcher, for 12 s.
    let stop = Arc::new(AtomicBool::new(false));
    let mut load = Vec::new();
    for g in 0..6 {
        let (stop, id) = (stop.clone(), ids[g].clone());
        load.push(std::thread::spawn(move || {
            let mut out = Vec::new();
            while !stop.load(Ordering::Relaxed) {
                let r = search(addr, &gw_search(&id, 5));
                if r.0 == 503 {
                    // Back off as told, but no longer than the test runs.
                    std::thread::sleep(Duration::from_millis(200));
                }
                out.push(("gw", r));
            }
            out
        }));
    }
    for w in 0..2 {
        let stop = stop.clone();
        load.push(std::thread::spawn(move || {
            let mut out = Vec::new();
            let mut i = 1000 + w * 1000;
            while !stop.load(Ordering::Relaxed) {
                let r = request(addr, "POST", "/v1/shapes", "model/obj", &obj(&shape(i)));
                if r.0 == 503 {
                    std::thread::sleep(Duration::from_millis(200));
                } else {
                    i += 1;
                }
                out.push(("ingest", r));
            }
            out
        }));
    }
    std::thread::sleep(Duration::from_millis(500));
    let t_load = Instant::now();
    let mut loaded = Vec::new();
    let mut cheap_resps = Vec::new();
    let mut i = 0;
    while t_load.elapsed() < Duration::from_secs(12) {
        let (ms, r) = timed(&cheap(i));
        i += 1;
        loaded.push(ms);
        cheap_resps.push(("cheap", r));
    }
    stop.store(true, Ordering::Relaxed);
    let mut all = cheap_resps;
    for t in load {
        all.extend(t.join().unwrap());
    }
    let count = |kind: &str, st: u16| all.iter().filter(|(k, r)| *k == kind && r.0 == st).count();
    for (what, r) in &all {
        assert_acceptable(r, what);
        assert!(
            matches!(r.0, 200 | 201 | 503),
            "{what}: {} {:?}",
            r.0,
            String::from_utf8_lossy(&r.2)
        );
    }
    let load_p50 = percentile(&mut loaded, 0.5);
    let load_p99 = percentile(&mut loaded, 0.99);
    let info = index_info(addr);
    eprintln!(
        "idle cheap: n={} p50 {idle_p50:.2} ms p99 {idle_p99:.2} ms | loaded cheap: n={} p50 \
         {load_p50:.2} ms p99 {load_p99:.2} ms ({:.1}×) | gw 200/503: {}/{} | ingest 201/503: \
         {}/{} | cheap 503: {} | queue {}",
        idle.len(),
        loaded.len(),
        load_p99 / idle_p99,
        count("gw", 200),
        count("gw", 503),
        count("ingest", 201),
        count("ingest", 503),
        count("cheap", 503),
        info["queue"]
    );
    assert_eq!(count("cheap", 503), 0, "a cheap search was refused");
    assert!(count("gw", 200) >= 3, "expensive searches made no progress");
    assert!(count("ingest", 201) >= 2, "ingests made no progress");
    assert!(
        load_p99 <= 5.0 * idle_p99,
        "cheap-search p99 {load_p99:.2} ms under load vs {idle_p99:.2} ms idle"
    );
    s.stop();
}

/// Finding 3 (quality of what is stored): a glTF holding a small mesh and megabytes of
/// padding was stored whole. Now the stored original is bounded by the geometry: re-encoded
/// (default) or refused.
#[test]
fn padding_is_not_stored() {
    let _serial = serial();
    let mesh = icosphere(2);
    let mut gltf = Vec::new();
    write_mesh(&mesh, Format::Gltf, &mut gltf).unwrap();
    // 4 MiB of JSON whitespace before the closing brace.
    let end = gltf.iter().rposition(|&b| b == b'}').unwrap();
    let mut padded = gltf[..end].to_vec();
    padded.extend(std::iter::repeat_n(b' ', 4 << 20));
    padded.extend_from_slice(&gltf[end..]);
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let r = request(s.addr, "POST", "/v1/shapes", "model/gltf+json", &padded);
    assert_eq!(r.0, 201, "{:?}", String::from_utf8_lossy(&r.2));
    let v = json_of(&r);
    let stored = v["shape"]["bytes"].as_u64().unwrap();
    assert_eq!(v["reencoded_from_bytes"], padded.len() as u64);
    assert!(stored < 256 << 10, "stored {stored} bytes");
    let id = v["id"].as_str().unwrap();
    let m = request(
        s.addr,
        "GET",
        &format!("/v1/shapes/{id}/mesh"),
        "text/plain",
        b"",
    );
    assert_eq!(m.0, 200);
    assert_eq!(m.2.len() as u64, stored);
    let back = shapeseek::mesh::read::read_mesh(
        &m.2,
        Some(Format::Gltf),
        &shapeseek::mesh::read::ReadLimits::default(),
    )
    .expect("the stored re-encoding reads back");
    assert_eq!(back.vertices.len(), mesh.vertices.len());
    assert_eq!(back.faces.len(), mesh.faces.len());
    // An upload within the cap is stored as sent.
    let r = request(s.addr, "POST", "/v1/shapes", "model/obj", &obj(&shape(4)));
    assert_eq!(r.0, 201);
    assert!(json_of(&r).get("reencoded_from_bytes").is_none());
    s.stop();
    // Policy `refuse`: 413 with its own code.
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.oversized_original = "refuse".into()
    });
    let r = request(s.addr, "POST", "/v1/shapes", "model/gltf+json", &padded);
    assert_problem(&r, 413, "limit.stored_bytes");
    s.stop();
}

/// Finding 6: a search by upload ran the whole mesh analysis before rejecting its options.
/// Now the options are checked first: an upload that is not even a mesh, with an impossible
/// rerank stage, is refused for its options (400), not for its bytes.
#[test]
fn upload_search_options_are_checked_before_the_analysis() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let query = br#"{"rerank": [{"stage": "spectral_gw", "shortlist": 100000}]}"#;
    let boundary = "b0undary";
    let mut body = Vec::new();
    for (name, ctype, data) in [
        (
            "file",
            "application/octet-stream",
            &b"not a mesh at all"[..],
        ),
        ("query", "application/json", &query[..]),
    ] {
        body.extend_from_slice(
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{name}\"\r\nContent-Type: {ctype}\r\n\r\n"
            )
            .as_bytes(),
        );
        body.extend_from_slice(data);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    let r = request(
        s.addr,
        "POST",
        "/v1/search",
        &format!("multipart/form-data; boundary={boundary}"),
        &body,
    );
    assert_problem(&r, 400, "request.invalid");
    assert!(
        json_of(&r)["detail"]
            .as_str()
            .unwrap()
            .contains("shortlist"),
        "{}",
        json_of(&r)
    );
    s.stop();
}
