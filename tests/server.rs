//! Integration tests of `shapeseek serve`: the real server on an ephemeral port, spoken to over
//! HTTP with a tiny blocking client (no HTTP client dependency).

use serde_json::{json, Value};
use shapeseek::index::{migrate, MigrateOutcome, SCHEMA_VERSION};
use shapeseek::mesh::generate::{bumpy_sphere, bumpy_torus, icosphere, rectangle, torus};
use shapeseek::mesh::read::Format;
use shapeseek::mesh::write::write_mesh;
use shapeseek::mesh::Mesh;
use shapeseek::server::ServerConfig;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::{Duration, Instant};

#[path = "common/multipart.rs"]
mod multipart;
use multipart::multipart;
#[path = "common/in_process.rs"]
mod in_process;
use in_process::Server;

/// Eigenpairs per shape in these tests (small meshes, fast CI).
const K: usize = in_process::EIGENPAIRS;

// ---------------------------------------------------------------- HTTP client

struct Resp {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Resp {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "not JSON ({e}): status {} body {:?}",
                self.status,
                String::from_utf8_lossy(&self.body)
            )
        })
    }
    /// Asserts an RFC 9457 problem document with `code` and returns it.
    fn problem(&self, status: u16, code: &str) -> Value {
        assert_eq!(
            self.status,
            status,
            "body: {}",
            String::from_utf8_lossy(&self.body)
        );
        assert_eq!(
            self.header("content-type"),
            Some("application/problem+json"),
            "status {status}"
        );
        let v = self.json();
        assert_eq!(v["code"], code, "{v}");
        assert_eq!(v["status"], status);
        assert!(v["detail"].as_str().is_some_and(|d| !d.is_empty()));
        v
    }
}

fn http(addr: SocketAddr, method: &str, path: &str, ctype: Option<&str>, body: &[u8]) -> Resp {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(300))).ok();
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    if let Some(c) = ctype {
        req.push_str(&format!("Content-Type: {c}\r\n"));
    }
    if !body.is_empty() || method == "POST" {
        req.push_str(&format!("Content-Length: {}\r\n", body.len()));
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).expect("write head");
    // A server may answer (413) before reading the whole body: ignore write errors then.
    let _ = s.write_all(body);
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    parse_response(&raw)
}

fn parse_response(raw: &[u8]) -> Resp {
    let split = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .unwrap_or_else(|| panic!("no header end in {:?}", String::from_utf8_lossy(raw)));
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    let (status, headers) = in_process::parse_head(&head);
    let mut body = raw[split + 4..].to_vec();
    if headers
        .iter()
        .any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"))
    {
        let mut out = Vec::new();
        let mut rest = &body[..];
        loop {
            let nl = rest.windows(2).position(|w| w == b"\r\n").unwrap();
            let n = usize::from_str_radix(std::str::from_utf8(&rest[..nl]).unwrap().trim(), 16)
                .unwrap();
            if n == 0 {
                break;
            }
            out.extend_from_slice(&rest[nl + 2..nl + 2 + n]);
            rest = &rest[nl + 2 + n + 2..];
        }
        body = out;
    }
    Resp {
        status,
        headers,
        body,
    }
}

fn get(addr: SocketAddr, path: &str) -> Resp {
    http(addr, "GET", path, None, b"")
}

/// A GET with extra header lines (`"Name: value\r\n"` each).
fn get_with(addr: SocketAddr, path: &str, headers: &str) -> Resp {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(300))).ok();
    let req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n{headers}\r\n");
    s.write_all(req.as_bytes()).expect("write head");
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    parse_response(&raw)
}

fn post_json(addr: SocketAddr, path: &str, v: &Value) -> Resp {
    http(
        addr,
        "POST",
        path,
        Some("application/json"),
        v.to_string().as_bytes(),
    )
}

// ---------------------------------------------------------------- server and meshes

/// Shutdown grace of these tests' servers: long enough for an in-flight analysis to finish on a
/// loaded machine.
const GRACE_SECS: f64 = 20.0;

fn bytes_of(mesh: &Mesh, format: Format) -> Vec<u8> {
    let mut out = Vec::new();
    write_mesh(mesh, format, &mut out).unwrap();
    out
}

fn squash(mut m: Mesh, sx: f64, sy: f64, sz: f64) -> Mesh {
    for v in &mut m.vertices {
        v[0] *= sx;
        v[1] *= sy;
        v[2] *= sz;
    }
    m
}

fn bend(mut m: Mesh, amount: f64) -> Mesh {
    for v in &mut m.vertices {
        v[2] += amount * (3.0 * v[0]).sin();
    }
    m
}

/// Three classes of small generated shapes: (class, name, mesh).
fn corpus() -> Vec<(&'static str, String, Mesh)> {
    vec![
        ("sphere", "sphere-a".into(), icosphere(2)),
        ("sphere", "sphere-b".into(), bumpy_sphere(2, 0.08)),
        (
            "sphere",
            "sphere-c".into(),
            squash(icosphere(2), 1.0, 1.1, 0.9),
        ),
        ("torus", "torus-a".into(), torus(1.0, 0.35, 20, 10)),
        ("torus", "torus-b".into(), bumpy_torus(22, 10)),
        ("torus", "torus-c".into(), torus(1.0, 0.35, 24, 12)),
        ("plane", "plane-a".into(), rectangle(1.0, 1.0, 11, 11)),
        (
            "plane",
            "plane-b".into(),
            bend(rectangle(1.0, 1.0, 12, 12), 0.1),
        ),
        ("plane", "plane-c".into(), rectangle(1.0, 1.0, 13, 13)),
    ]
}

fn ingest(addr: SocketAddr, name: &str, tags: &str, bytes: &[u8], ctype: &str) -> Resp {
    http(
        addr,
        "POST",
        &format!("/v1/shapes?name={name}&tags={tags}"),
        Some(ctype),
        bytes,
    )
}

fn wait_calibrated(addr: SocketAddr, n: u64) -> Value {
    let t = Instant::now();
    loop {
        let v = get(addr, "/v1/index").json();
        if v["shapes"] == n && v["calibrated_on"] == n {
            return v;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "never calibrated: {v}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn ingest_corpus(addr: SocketAddr) -> Vec<(String, &'static str, String, Vec<u8>)> {
    let mut out = Vec::new();
    for (class, name, mesh) in corpus() {
        let b = bytes_of(&mesh, Format::Obj);
        let r = ingest(addr, &name, class, &b, "model/obj");
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        out.push((r.json()["id"].as_str().unwrap().to_string(), class, name, b));
    }
    wait_calibrated(addr, out.len() as u64);
    out
}

// ---------------------------------------------------------------- tests

#[test]
fn ingest_every_format_read_back_list_delete() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let a = s.addr;
    assert_eq!(get(a, "/healthz").status, 200);
    assert_eq!(get(a, "/readyz").status, 200);

    let mesh = bumpy_sphere(2, 0.05);
    let mut ids = Vec::new();
    for (i, (format, ctype)) in [
        (Format::Obj, "model/obj"),
        (Format::Ply, "application/ply"),
        (Format::Off, "application/octet-stream"),
        (Format::Stl, "model/stl"),
        (Format::Glb, "model/gltf-binary"),
    ]
    .into_iter()
    .enumerate()
    {
        let b = bytes_of(&mesh, format);
        let r = ingest(a, &format!("s{i}"), "fmt,sphere", &b, ctype);
        assert_eq!(
            r.status,
            201,
            "{format}: {}",
            String::from_utf8_lossy(&r.body)
        );
        let v = r.json();
        assert_eq!(v["created"], true);
        assert_eq!(v["shape"]["format"], format.name());
        assert_eq!(v["shape"]["vertices"], mesh.vertices.len());
        assert!(v["timings"]["eigensolve_ms"].as_f64().unwrap() >= 0.0);
        assert_eq!(v["shape"]["prepare"]["components"], 1);
        let id = v["id"].as_str().unwrap().to_string();
        assert_eq!(
            r.header("location"),
            Some(format!("/v1/shapes/{id}").as_str())
        );
        // Original bytes back, as application/octet-stream (the record names the format).
        let m = get(a, &format!("/v1/shapes/{id}/mesh"));
        assert_eq!(m.status, 200);
        assert_eq!(m.body, b);
        assert_eq!(m.header("content-type"), Some("application/octet-stream"));
        // With ?format=, the mesh as the server read it, in any format: the same surface
        // whatever was uploaded (the web page reads every stored shape as PLY).
        for to in Format::ALL {
            let m = get(a, &format!("/v1/shapes/{id}/mesh?format={to}"));
            assert_eq!(
                m.status,
                200,
                "{format} as {to}: {}",
                String::from_utf8_lossy(&m.body)
            );
            assert_eq!(m.header("content-type"), Some("application/octet-stream"));
            let disposition = format!("attachment; filename=\"{id}.{to}\"");
            assert_eq!(m.header("content-disposition"), Some(disposition.as_str()));
            let back = shapeseek::mesh::read::read_mesh(&m.body, Some(to), &Default::default())
                .unwrap_or_else(|e| panic!("{format} as {to}: {e}"));
            assert_eq!(back.faces.len(), mesh.faces.len(), "{format} as {to}");
            let rel = (back.area() - mesh.area()).abs() / mesh.area();
            assert!(
                rel < 1e-6,
                "{format} as {to}: area {} vs {}",
                back.area(),
                mesh.area()
            );
            // Revalidation: the same ETag is answered 304 without a body.
            let tag = m.header("etag").expect("an ETag").to_string();
            let again = get_with(
                a,
                &format!("/v1/shapes/{id}/mesh?format={}", to.name().to_uppercase()),
                &format!("If-None-Match: {tag}\r\n"),
            );
            assert_eq!(again.status, 304, "{format} as {to}");
            assert!(again.body.is_empty());
            assert_eq!(again.header("etag"), Some(tag.as_str()));
            // A weak form of the tag matches too (RFC 9110); another format's does not.
            let weak = format!("If-None-Match: \"x\", W/{tag}\r\n");
            let path = format!("/v1/shapes/{id}/mesh?format={to}");
            assert_eq!(get_with(a, &path, &weak).status, 304);
            let other = if to == Format::Ply { "stl" } else { "ply" };
            let path = format!("/v1/shapes/{id}/mesh?format={other}");
            let r = get_with(a, &path, &format!("If-None-Match: {tag}\r\n"));
            assert_eq!(r.status, 200, "{format} as {other} with the tag of {to}");
        }
        let tag = m.header("etag").expect("the original's ETag").to_string();
        let again = get_with(
            a,
            &format!("/v1/shapes/{id}/mesh"),
            &format!("If-None-Match: {tag}\r\n"),
        );
        assert_eq!(again.status, 304);
        ids.push((id, b));
    }
    // Idempotent: the same bytes again → 200, same id, nothing new.
    let r = ingest(a, "again", "", &ids[0].1, "model/obj");
    assert_eq!(r.status, 200);
    assert_eq!(r.json()["id"], ids[0].0.as_str());
    assert_eq!(r.json()["created"], false);

    // Multipart with metadata; format from the file name.
    let b = bytes_of(&icosphere(2), Format::Off);
    let (ct, body) = multipart(&[
        ("file", Some("ball.off"), None, &b),
        (
            "metadata",
            None,
            Some("application/json"),
            br#"{"name":"ball","tags":["mp","sphere"]}"#,
        ),
    ]);
    let r = http(a, "POST", "/v1/shapes", Some(&ct), &body);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let mp_id = r.json()["id"].as_str().unwrap().to_string();
    let rec = get(a, &format!("/v1/shapes/{mp_id}")).json();
    assert_eq!(rec["name"], "ball");
    assert_eq!(rec["tags"], json!(["mp", "sphere"]));
    assert_eq!(rec["format"], "off");

    // Signature as JSON: the default spec's channels.
    let sig = get(a, &format!("/v1/shapes/{mp_id}/signature"));
    assert_eq!(sig.status, 200);
    let sig = sig.json();
    let default_channels = shapeseek::presets::default_config()
        .signature
        .channel_names();
    let names: Vec<String> = sig["signature"]["channels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(names, default_channels);

    // Paging: limit 2 over 6 shapes, in ingest order, no duplicates.
    let mut seen = Vec::new();
    let mut cursor: Option<String> = None;
    loop {
        let path = match &cursor {
            Some(c) => format!("/v1/shapes?limit=2&cursor={c}"),
            None => "/v1/shapes?limit=2".to_string(),
        };
        let page = get(a, &path).json();
        let items = page["items"].as_array().unwrap();
        assert!(items.len() <= 2);
        seen.extend(items.iter().map(|i| i["id"].as_str().unwrap().to_string()));
        match page["next_cursor"].as_str() {
            Some(c) => cursor = Some(c.to_string()),
            None => break,
        }
    }
    let mut expected: Vec<String> = ids.iter().map(|(i, _)| i.clone()).collect();
    expected.push(mp_id.clone());
    assert_eq!(seen, expected);
    // Tag filter.
    let page = get(a, "/v1/shapes?tag=mp").json();
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    assert_eq!(page["items"][0]["id"], mp_id.as_str());
    // A filter no stored tag could be is refused as the same tag in an upload is (a NUL
    // reached PostgreSQL and came back as 500).
    for bad in ["%00", "", "a%0Ab", &"x".repeat(65)] {
        get(a, &format!("/v1/shapes?tag={bad}")).problem(400, "request.invalid");
    }

    // Delete: 204, then gone everywhere; the same bytes can be ingested anew.
    let (id0, b0) = &ids[0];
    assert_eq!(
        http(a, "DELETE", &format!("/v1/shapes/{id0}"), None, b"").status,
        204
    );
    get(a, &format!("/v1/shapes/{id0}")).problem(404, "shape.not_found");
    get(a, &format!("/v1/shapes/{id0}/mesh")).problem(404, "shape.not_found");
    get(a, &format!("/v1/shapes/{id0}/signature")).problem(404, "shape.not_found");
    http(a, "DELETE", &format!("/v1/shapes/{id0}"), None, b"").problem(404, "shape.not_found");
    post_json(a, "/v1/search", &json!({"id": id0})).problem(404, "shape.not_found");
    let r = ingest(a, "back", "", b0, "model/obj");
    assert_eq!(r.status, 201);
    assert_ne!(r.json()["id"], id0.as_str());

    let metrics = String::from_utf8(get(a, "/metrics").body).unwrap();
    for name in [
        "shapeseek_http_requests_total",
        "shapeseek_http_request_duration_seconds_bucket",
        "shapeseek_ingest_stage_seconds_bucket",
        "shapeseek_queue_depth",
        "shapeseek_index_shapes",
    ] {
        assert!(metrics.contains(name), "{name} missing from /metrics");
    }
    let spec = get(a, "/openapi.yaml");
    assert_eq!(spec.status, 200);
    assert!(String::from_utf8_lossy(&spec.body).contains("/v1/search"));
    s.stop();
}

#[test]
fn search_by_id_and_by_upload_finds_the_same_class() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let a = s.addr;
    let shapes = ingest_corpus(a);
    let class_of = |id: &str| shapes.iter().find(|s| s.0 == id).unwrap().1;

    // By id: the two best hits are the other members of the class.
    let mut agree = 0;
    for (id, class, _, _) in &shapes {
        let r = post_json(a, "/v1/search", &json!({"id": id, "top_k": 2}));
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let v = r.json();
        let hits = v["hits"].as_array().unwrap();
        assert_eq!(hits.len(), 2);
        assert_eq!(hits[0]["rank"], 1);
        assert!(hits[0]["score"].as_f64().unwrap() <= hits[1]["score"].as_f64().unwrap());
        assert!(
            hits.iter().all(|h| h["id"] != id.as_str()),
            "query itself excluded"
        );
        assert!(hits
            .iter()
            .all(|h| h["calibration_epoch"] == v["calibration_epoch"]));
        agree += hits
            .iter()
            .filter(|h| class_of(h["id"].as_str().unwrap()) == *class)
            .count();
    }
    assert!(
        agree >= 16,
        "same-class hits among the best 2: {agree} of 18"
    );

    // By upload of a new variant (raw and multipart): best hit of the same class.
    let query = bytes_of(
        &squash(torus(1.0, 0.35, 18, 9), 1.05, 1.0, 1.0),
        Format::Ply,
    );
    let r = http(
        a,
        "POST",
        "/v1/search?top_k=3",
        Some("application/ply"),
        &query,
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let v = r.json();
    assert_eq!(
        class_of(v["hits"][0]["id"].as_str().unwrap()),
        "torus",
        "{v}"
    );
    assert!(v["timings"]["analysis"]["eigensolve_ms"].is_number());

    let query = bytes_of(&bend(rectangle(1.0, 1.0, 10, 10), 0.05), Format::Stl);
    let (ct, body) = multipart(&[
        ("file", Some("q.stl"), Some("model/stl"), &query),
        (
            "query",
            None,
            Some("application/json"),
            json!({"top_k": 3, "rerank": [{"stage": "exact", "shortlist": 6, "spec": {"dissimilarity": "emd"}}]})
                .to_string()
                .as_bytes(),
        ),
    ]);
    let r = http(a, "POST", "/v1/search", Some(&ct), &body);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let v = r.json();
    assert_eq!(v["stages"], json!(["scan", "exact"]));
    assert_eq!(
        class_of(v["hits"][0]["id"].as_str().unwrap()),
        "plane",
        "{v}"
    );
    for h in v["hits"].as_array().unwrap() {
        let st = h["stage_scores"].as_array().unwrap();
        assert_eq!(st.len(), 2);
        assert_eq!(st[1], h["score"]);
    }
    // Nothing was stored by searching.
    assert_eq!(get(a, "/v1/index").json()["shapes"], 9);

    // Tag filter and spec overrides.
    let sphere = &shapes[0].0;
    let v = post_json(
        a,
        "/v1/search",
        &json!({"id": sphere, "top_k": 10, "tags": ["torus"], "spec": {"aggregation": "max"}}),
    )
    .json();
    assert_eq!(v["hits"].as_array().unwrap().len(), 3);
    assert!(v["hits"]
        .as_array()
        .unwrap()
        .iter()
        .all(|h| class_of(h["id"].as_str().unwrap()) == "torus"));
    assert_eq!(v["spec"]["aggregation"], "max");
    assert_eq!(v["candidates"], 3);
    post_json(
        a,
        "/v1/search",
        &json!({"id": sphere, "spec": {"channels": ["nope"]}}),
    )
    .problem(400, "request.invalid");
    post_json(
        a,
        "/v1/search",
        &json!({"id": sphere, "rerank": [{"stage": "sgw"}]}),
    )
    .problem(400, "request.invalid");
    post_json(a, "/v1/search", &json!({"id": sphere, "top_k": 0})).problem(400, "request.invalid");
    s.stop();
}

fn max_sig_diff(a: &shapeseek::signature::Signature, b: &shapeseek::signature::Signature) -> f64 {
    use shapeseek::signature::ChannelValues;
    let mut m: f64 = 0.0;
    assert_eq!(a.channels.len(), b.channels.len());
    for (x, y) in a.channels.iter().zip(&b.channels) {
        match (&x.values, &y.values) {
            (ChannelValues::Distribution(p), ChannelValues::Distribution(q)) => {
                m = m.max((p.mass - q.mass).abs());
                for (u, v) in p.quantiles.iter().zip(&q.quantiles) {
                    m = m.max((u - v).abs());
                }
            }
            (ChannelValues::Vector(p), ChannelValues::Vector(q)) => {
                for (u, v) in p.iter().zip(q) {
                    m = m.max((u - v).abs());
                }
            }
            _ => return f64::INFINITY,
        }
    }
    // The second cut versions, when there are any.
    match (&a.alternate, &b.alternate) {
        (Some(x), Some(y)) => m.max(max_sig_diff(x, y)),
        (None, None) => m,
        _ => f64::INFINITY,
    }
}

/// The server's ranking equals the library's (what `eval` does): `calibrate` over all stored
/// signatures, the corpus encoding, `Query::score`, sort ascending.
#[test]
fn ranking_equals_library_ranking() {
    use shapeseek::presets::default_config;
    use shapeseek::ranking::{calibrate_with, QuerySpec};
    use shapeseek::search::{Corpus, Encoded, Layout, Query};
    use shapeseek::signature::Signature;

    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let a = s.addr;
    let shapes = ingest_corpus(a);
    let cfg = default_config();

    // The eval path: signatures computed here from the same bytes with the same options.
    let mut opts = shapeseek::spectrum::AnalyzeOptions::default();
    opts.eigen.k = K;
    let sigs: Vec<Signature> = shapes
        .iter()
        .map(|(.., bytes)| {
            let mesh = shapeseek::mesh::read::read_mesh(bytes, None, &Default::default()).unwrap();
            shapeseek::signature::sign(&mesh, &cfg.signature, &opts)
                .unwrap()
                .1
        })
        .collect();
    assert!(
        sigs.iter().any(|s| s.alternate.is_some()),
        "the corpus has a shape with a second cut version"
    );
    // The served JSON agrees (up to JSON float parsing); the stored bytes are checked exactly
    // below, after the server stopped.
    for ((id, ..), local) in shapes.iter().zip(&sigs) {
        let served: Signature = serde_json::from_value(
            get(a, &format!("/v1/shapes/{id}/signature")).json()["signature"].clone(),
        )
        .unwrap();
        assert!(
            max_sig_diff(&served, local) <= 1e-12,
            "signature of {id} differs"
        );
    }

    let refs: Vec<&Signature> = sigs.iter().collect();
    let cal = calibrate_with(&refs, &cfg.signature, 0, &cfg.calibration);
    let layout = Layout::of(&cal);
    let rows: Vec<Encoded> = sigs
        .iter()
        .map(|s| Encoded::from_signature(s, &cal, &layout))
        .collect();
    let corpus = Corpus::build(layout, &rows);
    let score = |i: usize, j: usize, spec: &QuerySpec| {
        let l = corpus.layout();
        Query::new(spec, l).score(l, corpus.shape(i), corpus.shape(j))
    };
    let specs: Vec<(QuerySpec, Value)> = vec![
        (cfg.query.clone(), json!(null)),
        (
            QuerySpec {
                aggregation: shapeseek::signature::Aggregation::Max,
                dissimilarity: shapeseek::ranking::Dissimilarity::Emd,
                ..cfg.query.clone()
            },
            json!({"aggregation": "max", "dissimilarity": "emd"}),
        ),
    ];
    for (spec, overrides) in &specs {
        for (qi, (qid, ..)) in shapes.iter().enumerate() {
            let mut expected: Vec<(f64, usize)> =
                (0..shapes.len()).map(|j| (score(qi, j, spec), j)).collect();
            expected.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
            let mut req =
                json!({"id": qid, "top_k": shapes.len(), "include_self": true, "rerank": []});
            if !overrides.is_null() {
                req["spec"] = overrides.clone();
            }
            let v = post_json(a, "/v1/search", &req).json();
            let got: Vec<(f64, String)> = v["hits"]
                .as_array()
                .unwrap()
                .iter()
                .map(|h| {
                    (
                        h["score"].as_f64().unwrap(),
                        h["id"].as_str().unwrap().to_string(),
                    )
                })
                .collect();
            assert_eq!(got.len(), expected.len());
            for ((gs, gid), (es, ej)) in got.iter().zip(&expected) {
                assert_eq!(gid, &shapes[*ej].0, "order differs for query {qid}: {v}");
                assert!((gs - es).abs() <= 1e-12 * es.abs().max(1.0), "{gs} vs {es}");
            }
        }
    }
    // The default search (no `rerank` field) re-ranks by reciprocal neighbourhoods: the
    // library's stage on the library's first-stage scores between the query and every other
    // shape (the default shortlist holds them all).
    let stage = shapeseek::rerank::ReciprocalStage::default();
    assert!(stage.shortlist >= shapes.len());
    for (qi, (qid, ..)) in shapes.iter().enumerate() {
        let mut first: Vec<(f64, usize)> = (0..shapes.len())
            .filter(|&j| j != qi)
            .map(|j| (score(qi, j, &cfg.query), j))
            .collect();
        first.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        let items: Vec<usize> = std::iter::once(qi)
            .chain(first.iter().map(|x| x.1))
            .collect();
        let m = items.len();
        let mut d = vec![0.0; m * m];
        for (x, &i) in items.iter().enumerate() {
            for (y, &j) in items.iter().enumerate() {
                if x != y {
                    d[x * m + y] = score(i, j, &cfg.query);
                }
            }
        }
        let expected = shapeseek::rerank::reciprocal::rerank(&d, m, &stage);
        let v = post_json(a, "/v1/search", &json!({"id": qid, "top_k": shapes.len()})).json();
        assert_eq!(v["stages"], json!(["scan", "reciprocal"]));
        let hits = v["hits"].as_array().unwrap();
        assert_eq!(hits.len(), expected.len());
        for (h, &(c, es)) in hits.iter().zip(&expected) {
            assert_eq!(h["id"], json!(shapes[items[c + 1]].0), "query {qid}: {v}");
            let gs = h["score"].as_f64().unwrap();
            assert!((gs - es).abs() <= 1e-12, "{gs} vs {es}");
            assert_eq!(h["stage_scores"].as_array().unwrap().len(), 2);
        }
    }
    s.stop();
    let store = shapeseek::index::Store::open(dir.path()).unwrap();
    for ((id, ..), local) in shapes.iter().zip(&sigs) {
        let stored = Signature::from_bytes(&store.signature(id).unwrap().unwrap()).unwrap();
        assert_eq!(
            &stored, local,
            "stored signature of {id} differs from the library's"
        );
    }
}

/// The spectral Gromov–Wasserstein stage re-orders the scan's shortlist by the library's GW
/// score between payloads computed here from the same bytes (by id and by upload), and bad
/// stage options are refused.
#[test]
fn spectral_gw_stage_equals_library_scores() {
    use shapeseek::rerank::{compute_payload, gw_score, GwOptions, GwPayload, PayloadSpec};
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let a = s.addr;
    let shapes = ingest_corpus(a);
    let mut base = shapeseek::spectrum::AnalyzeOptions::default();
    base.eigen.k = K;
    // The server's payloads come from the analysis of the default spec's preparation
    // (smoothing, capping, handle cutting).
    let opts = shapeseek::presets::default_config()
        .signature
        .analysis_options(&base);
    let payloads: Vec<GwPayload> = shapes
        .iter()
        .map(|(.., bytes)| {
            let mesh = shapeseek::mesh::read::read_mesh(bytes, None, &Default::default()).unwrap();
            let analysis = shapeseek::spectrum::analyze(&mesh, &opts).unwrap();
            compute_payload(&analysis, &PayloadSpec::default()).unwrap()
        })
        .collect();
    let at = |id: &str| shapes.iter().position(|s| s.0 == id).unwrap();
    let ids = |v: &Value| -> Vec<String> {
        let mut out: Vec<String> = v["hits"]
            .as_array()
            .unwrap()
            .iter()
            .map(|h| h["id"].as_str().unwrap().to_string())
            .collect();
        out.sort();
        out
    };
    let stage = json!([{"stage": "spectral_gw", "shortlist": 4}]);
    for (qi, (qid, ..)) in shapes.iter().enumerate() {
        let scan = post_json(
            a,
            "/v1/search",
            &json!({"id": qid, "top_k": 4, "rerank": []}),
        )
        .json();
        let r = post_json(
            a,
            "/v1/search",
            &json!({"id": qid, "top_k": 4, "rerank": stage}),
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let v = r.json();
        assert_eq!(v["stages"], json!(["scan", "spectral_gw"]));
        assert_eq!(
            ids(&v),
            ids(&scan),
            "the stage re-orders the shortlist only"
        );
        let mut last = f64::NEG_INFINITY;
        for h in v["hits"].as_array().unwrap() {
            let expected = gw_score(
                &payloads[qi],
                &payloads[at(h["id"].as_str().unwrap())],
                &GwOptions::default(),
            );
            let got = h["score"].as_f64().unwrap();
            assert!(
                (got - expected).abs() <= 1e-12 * expected.abs().max(1e-300),
                "GW score {got} vs library {expected}"
            );
            assert_eq!(h["stage_scores"].as_array().unwrap().len(), 2);
            assert!(got >= last, "hits sorted by the GW score");
            last = got;
        }
    }

    // By upload (multipart): the payload computed from the upload equals the stored one, so
    // the answer equals the by-id search that keeps the query itself.
    let (qid, _, _, qbytes) = &shapes[4];
    let by_id = post_json(
        a,
        "/v1/search",
        &json!({"id": qid, "top_k": 3, "include_self": true, "rerank": stage}),
    )
    .json();
    let (ct, body) = multipart(&[
        ("file", Some("q.obj"), Some("model/obj"), qbytes),
        (
            "query",
            None,
            Some("application/json"),
            json!({"top_k": 3, "rerank": stage}).to_string().as_bytes(),
        ),
    ]);
    let r = http(a, "POST", "/v1/search", Some(&ct), &body);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["hits"], by_id["hits"]);

    for bad in [
        json!({"stage": "spectral_gw", "shortlist": 0}),
        json!({"stage": "spectral_gw", "shortlist": 201}),
        json!({"stage": "spectral_gw", "eps_rel": 2.0}),
        json!({"stage": "spectral_gw", "outer_iterations": 0}),
        json!({"stage": "spectral_gw", "blend": 1.5}),
        json!({"stage": "spectral_gw", "samples": 10}),
        json!({"stage": "reciprocal", "shortlist": 0}),
        json!({"stage": "reciprocal", "shortlist": 1001}),
        json!({"stage": "reciprocal", "neighbourhoods": []}),
        json!({"stage": "reciprocal", "neighbourhoods": [0, 8]}),
        json!({"stage": "reciprocal", "expansion": 0}),
        json!({"stage": "reciprocal", "original_weight": -0.1}),
        json!({"stage": "reciprocal", "k": 8}),
    ] {
        post_json(a, "/v1/search", &json!({"id": qid, "rerank": [bad]}))
            .problem(400, "request.invalid");
    }
    // Stages chain in either order (the reciprocal stage re-takes the scan lock after GW);
    // each re-orders the previous stage's list.
    for (stages, names) in [
        (
            json!([{"stage": "reciprocal"}, {"stage": "spectral_gw", "shortlist": 3}]),
            json!(["scan", "reciprocal", "spectral_gw"]),
        ),
        (
            json!([{"stage": "spectral_gw", "shortlist": 4}, {"stage": "reciprocal"}]),
            json!(["scan", "spectral_gw", "reciprocal"]),
        ),
    ] {
        let r = post_json(
            a,
            "/v1/search",
            &json!({"id": qid, "top_k": 3, "rerank": stages}),
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let v = r.json();
        assert_eq!(v["stages"], names);
        assert_eq!(v["hits"].as_array().unwrap().len(), 3);
        for h in v["hits"].as_array().unwrap() {
            assert_eq!(h["stage_scores"].as_array().unwrap().len(), 3);
        }
    }
    s.stop();
}

#[test]
fn concurrent_ingest_and_search() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.queue_capacity = 64);
    let a = s.addr;
    let seed = ingest(
        a,
        "seed",
        "",
        &bytes_of(&icosphere(2), Format::Obj),
        "model/obj",
    );
    let seed_id = seed.json()["id"].as_str().unwrap().to_string();
    let writers: Vec<_> = (0..6)
        .map(|i| {
            std::thread::spawn(move || {
                let m = squash(
                    bumpy_sphere(2, 0.02 * (i + 1) as f64),
                    1.0 + 0.05 * i as f64,
                    1.0,
                    1.0,
                );
                let r = ingest(
                    a,
                    &format!("w{i}"),
                    "",
                    &bytes_of(&m, Format::Obj),
                    "model/obj",
                );
                assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
                r.json()["id"].as_str().unwrap().to_string()
            })
        })
        .collect();
    let readers: Vec<_> = (0..2)
        .map(|_| {
            let seed_id = seed_id.clone();
            std::thread::spawn(move || {
                for _ in 0..15 {
                    let r = post_json(a, "/v1/search", &json!({"id": seed_id, "top_k": 3}));
                    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
                    assert!(r.json()["hits"].as_array().unwrap().len() <= 3);
                    std::thread::sleep(Duration::from_millis(5));
                }
            })
        })
        .collect();
    let mut ids: Vec<String> = writers.into_iter().map(|w| w.join().unwrap()).collect();
    readers.into_iter().for_each(|r| r.join().unwrap());
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), 6);
    wait_calibrated(a, 7);
    let v = post_json(a, "/v1/search", &json!({"id": seed_id, "top_k": 10})).json();
    assert_eq!(v["hits"].as_array().unwrap().len(), 6);
    s.stop();
}

#[test]
fn restart_keeps_shapes_and_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let shapes = ingest_corpus(s.addr);
    let before = get(s.addr, "/v1/index").json();
    let e = migrate(dir.path()).unwrap_err().to_string();
    assert!(e.contains("in use"), "migrate while serving: {e}");
    let hits_before = post_json(
        s.addr,
        "/v1/search",
        &json!({"id": shapes[0].0, "top_k": 4}),
    )
    .json()["hits"]
        .clone();
    s.stop();

    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let a = s.addr;
    let after = get(a, "/v1/index").json();
    assert_eq!(after["shapes"], 9);
    assert_eq!(
        after["calibration_epoch"], before["calibration_epoch"],
        "calibration persisted"
    );
    for (id, _, name, bytes) in &shapes {
        assert_eq!(
            get(a, &format!("/v1/shapes/{id}")).json()["name"],
            name.as_str()
        );
        assert_eq!(&get(a, &format!("/v1/shapes/{id}/mesh")).body, bytes);
        // Idempotency survives the restart.
        assert_eq!(ingest(a, "x", "", bytes, "model/obj").status, 200);
    }
    let hits_after =
        post_json(a, "/v1/search", &json!({"id": shapes[0].0, "top_k": 4})).json()["hits"].clone();
    assert_eq!(hits_before, hits_after);
    s.stop();
}

/// A mesh above `analysis_vertex_budget` is analysed simplified to it (`decimated` in its
/// preparation report) and stored as sent; a search by its upload finds it first; a mesh within
/// the budget is analysed whole; the budget is in `/v1/index`; one below the least is refused.
#[test]
fn a_mesh_above_the_vertex_budget_is_analysed_simplified_and_stored_as_sent() {
    let bad = ServerConfig {
        analysis_vertex_budget: 999,
        ..Default::default()
    };
    let e = bad.validate().expect_err("a budget under 1000").to_string();
    assert!(e.contains("analysis_vertex_budget"), "{e}");

    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.analysis_vertex_budget = 1500);
    let a = s.addr;
    assert_eq!(
        get(a, "/v1/index").json()["signature_spec"]["vertex_budget"],
        1500
    );
    let big = bumpy_torus(80, 40);
    assert_eq!(big.vertices.len(), 3200);
    let bytes = bytes_of(&big, Format::Off);
    let r = ingest(a, "big", "", &bytes, "application/off");
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let v = r.json();
    let shape = &v["shape"];
    let d = &shape["prepare"]["decimated"];
    assert_eq!(
        (d["budget"].as_u64(), d["vertices_before"].as_u64()),
        (Some(1500), Some(3200)),
        "{v}"
    );
    let after = d["vertices_after"].as_u64().unwrap();
    assert!((1350..=1500).contains(&after), "{v}");
    assert_eq!(shape["prepare"]["vertices_in"], 3200);
    assert_eq!(shape["prepare"]["vertices_out"].as_u64(), Some(after));
    assert_eq!(shape["vertices"], 3200, "the record describes the original");
    let id = shape["id"].as_str().unwrap().to_string();
    assert_eq!(get(a, &format!("/v1/shapes/{id}/mesh")).body, bytes);
    assert_eq!(
        get(a, &format!("/v1/shapes/{id}")).json()["prepare"]["decimated"],
        *d
    );

    let small = bytes_of(&icosphere(3), Format::Off);
    let r = ingest(a, "small", "", &small, "application/off").json();
    assert!(r["shape"]["prepare"].get("decimated").is_none(), "{r}");

    // The same torus, sent again as another file (rotated vertex order): found first.
    let mut turned = big.clone();
    turned.vertices.rotate_left(7);
    for f in &mut turned.faces {
        *f = f.map(|i| (i + 3200 - 7) % 3200);
    }
    let r = http(
        a,
        "POST",
        "/v1/search?top_k=2",
        Some("application/off"),
        &bytes_of(&turned, Format::Off),
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["hits"][0]["id"], id.as_str());
    s.stop();
}

/// First-stage scores (`rerank: []`) of `id`'s search against the `n` nearest other shapes,
/// by name.
fn scan_scores(addr: SocketAddr, id: &str, n: usize) -> Vec<(String, u64)> {
    let r = post_json(
        addr,
        "/v1/search",
        &json!({"id": id, "top_k": n, "rerank": []}),
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let mut v: Vec<(String, u64)> = r.json()["hits"]
        .as_array()
        .unwrap()
        .iter()
        .map(|h| {
            (
                h["name"].as_str().unwrap().to_string(),
                h["score"].as_f64().unwrap().to_bits(),
            )
        })
        .collect();
    v.sort();
    v
}

/// A stored calibration made with other calibration options than the default's (here the
/// paper's 95th-percentile window, as an index calibrated before the default's 0.90) is not
/// scanned with: the restart recalibrates under the default's options and stores that.
#[test]
fn a_calibration_with_another_window_percentile_is_recomputed_at_start() {
    fn percentiles(v: &mut Value, set: Option<f64>, seen: &mut Vec<f64>) {
        match v {
            Value::Object(m) => {
                for (k, x) in m.iter_mut() {
                    if k == "percentile" {
                        seen.push(x.as_f64().unwrap());
                        if let Some(p) = set {
                            *x = json!(p);
                        }
                    } else {
                        percentiles(x, set, seen);
                    }
                }
            }
            Value::Array(a) => a.iter_mut().for_each(|x| percentiles(x, set, seen)),
            _ => {}
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let shapes = ingest_corpus(s.addr);
    let before = get(s.addr, "/v1/index").json();
    s.stop();
    {
        let store = shapeseek::index::Store::open(dir.path()).unwrap();
        let mut doc: Value =
            serde_json::from_slice(&store.calibration().unwrap().unwrap()).unwrap();
        let mut seen = Vec::new();
        percentiles(&mut doc, Some(0.95), &mut seen);
        assert_eq!(
            seen,
            vec![shapeseek::presets::DEFAULT_WINDOW_PERCENTILE],
            "the server calibrates with the default's window"
        );
        store
            .set_calibration(&serde_json::to_vec(&doc).unwrap())
            .unwrap();
    }
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let after = get(s.addr, "/v1/index").json();
    assert_eq!(after["shapes"], 9);
    assert!(
        after["calibration_epoch"].as_u64() > before["calibration_epoch"].as_u64(),
        "recalibrated at start: {before} → {after}"
    );
    let hits = post_json(
        s.addr,
        "/v1/search",
        &json!({"id": shapes[0].0, "top_k": 4}),
    );
    assert_eq!(hits.status, 200);
    s.stop();
    let store = shapeseek::index::Store::open(dir.path()).unwrap();
    let mut doc: Value = serde_json::from_slice(&store.calibration().unwrap().unwrap()).unwrap();
    let mut seen = Vec::new();
    percentiles(&mut doc, None, &mut seen);
    assert_eq!(seen, vec![shapeseek::presets::DEFAULT_WINDOW_PERCENTILE]);
}

/// Above `calibration_sample` shapes the calibration is computed on that many: the shapes
/// with the smallest content hashes, exactly as a server holding only those computes it; the
/// corpus loads again under it bit for bit, and a load that must recalibrate (stale
/// signatures) samples the same way.
#[test]
fn calibration_above_the_sample_size_uses_the_smallest_content_hashes() {
    let dir = tempfile::tempdir().unwrap();
    let sampled = |c: &mut ServerConfig| {
        c.calibration_sample = 4;
        c.recalibrate_fraction = 0.0;
    };
    let s = Server::start(dir.path(), GRACE_SECS, sampled);
    let shapes = ingest_corpus(s.addr);
    let info = get(s.addr, "/v1/index").json();
    assert_eq!(info["calibrated_on"], 9, "{info}");
    assert_eq!(info["calibration_shapes"], 4, "{info}");
    assert_eq!(info["left_out"], 0, "{info}");
    // The sample: the 4 smallest SHA-256s, in upload order (= id order).
    let mut by_hash: Vec<(String, usize)> = shapes
        .iter()
        .enumerate()
        .map(|(i, (id, ..))| {
            let rec = get(s.addr, &format!("/v1/shapes/{id}")).json();
            (rec["sha256"].as_str().unwrap().to_string(), i)
        })
        .collect();
    by_hash.sort();
    let mut members: Vec<usize> = by_hash[..4].iter().map(|(_, i)| *i).collect();
    members.sort();
    let probe = &shapes[members[0]];
    let whole = scan_scores(s.addr, &probe.0, 9);
    s.stop();

    // A server holding only the members calibrates on all of them: the same windows, so the
    // same first-stage scores between members, bit for bit.
    let only = tempfile::tempdir().unwrap();
    let b = Server::start(only.path(), GRACE_SECS, |c| c.recalibrate_fraction = 0.0);
    let mut probe_b = String::new();
    for &i in &members {
        let (_, class, name, bytes) = &shapes[i];
        let r = ingest(b.addr, name, class, bytes, "model/obj");
        assert_eq!(r.status, 201);
        if i == members[0] {
            probe_b = r.json()["id"].as_str().unwrap().to_string();
        }
    }
    let info_b = wait_calibrated(b.addr, 4);
    assert_eq!(info_b["calibration_shapes"], 4);
    let subset = scan_scores(b.addr, &probe_b, 4);
    let names: Vec<&str> = members.iter().map(|&i| shapes[i].2.as_str()).collect();
    let whole_members: Vec<(String, u64)> = whole
        .iter()
        .filter(|(n, _)| names.contains(&n.as_str()))
        .cloned()
        .collect();
    assert_eq!(
        whole_members, subset,
        "sampled calibration = the members' own"
    );
    b.stop();

    // Restart under the stored calibration: the same scores (shapes encoded as they are read).
    let s = Server::start(dir.path(), GRACE_SECS, sampled);
    assert_eq!(scan_scores(s.addr, &probe.0, 9), whole);
    let epoch = get(s.addr, "/v1/index").json()["calibration_epoch"].clone();
    s.stop();

    // Other eigenpairs: every signature is recomputed at load, then a new calibration is
    // computed on the sample and every shape encoded again from the store.
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        sampled(c);
        c.eigenpairs = K + 4;
    });
    let info = get(s.addr, "/v1/index").json();
    assert_eq!(info["shapes"], 9, "{info}");
    assert_eq!(info["calibrated_on"], 9, "{info}");
    assert_eq!(info["calibration_shapes"], 4, "{info}");
    assert!(
        info["calibration_epoch"].as_u64() > epoch.as_u64(),
        "{info}"
    );
    assert_eq!(
        scan_scores(s.addr, &probe.0, 9).len(),
        8,
        "every other shape"
    );
    s.stop();
}

#[test]
fn bad_input_is_problem_json() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.max_body_bytes = 200_000;
        c.max_vertices = 500;
    });
    let a = s.addr;
    ingest(
        a,
        "x",
        "",
        b"\x00\x01\x02 definitely not a mesh",
        "application/octet-stream",
    )
    .problem(415, "mesh.format");
    ingest(
        a,
        "x",
        "",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
        "model/obj",
    )
    .problem(422, "mesh.parse");
    ingest(a, "x", "", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "model/obj").problem(422, "mesh.empty");
    ingest(a, "x", "", b"", "model/obj").problem(422, "mesh.empty");
    ingest(
        a,
        "x",
        "",
        b"OFF\n3 1 0\n0 0 0\n1 0 0\nnan 1 0\n3 0 1 2\n",
        "application/off",
    )
    .problem(422, "mesh.non_finite");
    // Limits.
    let big = bytes_of(&icosphere(4), Format::Obj); // 2562 vertices, > 200 kB
    assert!(big.len() > 200_000);
    ingest(a, "x", "", &big, "model/obj").problem(413, "limit.bytes");
    let many = bytes_of(&icosphere(3), Format::Ply); // 642 vertices, small binary file
    assert!(many.len() < 200_000);
    ingest(a, "x", "", &many, "application/ply").problem(413, "limit.vertices");
    // Request errors.
    http(
        a,
        "POST",
        "/v1/shapes?format=xyz",
        Some("model/obj"),
        b"v 0 0 0",
    )
    .problem(400, "request.invalid");
    http(
        a,
        "POST",
        "/v1/shapes?name=",
        Some("model/obj"),
        b"v 0 0 0\n",
    )
    .problem(400, "request.invalid");
    http(
        a,
        "POST",
        "/v1/search",
        Some("application/json"),
        b"{not json",
    )
    .problem(400, "request.invalid");
    post_json(a, "/v1/search", &json!({"top_k": 3})).problem(400, "request.invalid");
    post_json(a, "/v1/search", &json!({"id": "x", "unknown": 1})).problem(400, "request.invalid");
    post_json(a, "/v1/search", &json!({"id": "0000000000000099"})).problem(404, "shape.not_found");
    let (ct, body) = multipart(&[("metadata", None, None, b"{}")]);
    http(a, "POST", "/v1/shapes", Some(&ct), &body).problem(400, "request.invalid");
    let (ct, body) = multipart(&[
        (
            "file",
            Some("a.obj"),
            None,
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        ),
        ("metadata", None, None, b"{\"nme\":1}"),
    ]);
    http(a, "POST", "/v1/shapes", Some(&ct), &body).problem(400, "request.invalid");
    http(
        a,
        "POST",
        "/v1/shapes",
        Some("multipart/form-data"),
        b"garbage",
    )
    .problem(400, "request.invalid");
    get(a, "/v1/shapes?limit=abc").problem(400, "request.invalid");
    get(a, "/v1/shapes?limit=0").problem(400, "request.invalid");
    // A misspelt query parameter is refused with the names accepted (`?tags=` on the listing
    // was ignored, and every shape listed as if it had matched the filter).
    for (method, path) in [
        ("GET", "/v1/shapes?tags=chair"),
        ("POST", "/v1/shapes?tag=chair"),
        ("POST", "/v1/search?topk=3"),
        ("GET", "/v1/shapes/0000000000000001/mesh?as=ply"),
    ] {
        let p =
            http(a, method, path, Some("model/obj"), b"v 0 0 0\n").problem(400, "request.invalid");
        let detail = p["detail"].as_str().unwrap_or_default();
        assert!(detail.contains("unknown field"), "{path}: {detail}");
        // "expected one of `a`, `b`", or "expected `format`" where one name is accepted.
        let accepted = if path.contains("/mesh") {
            "expected `format`"
        } else {
            "expected one of"
        };
        assert!(detail.contains(accepted), "{path}: {detail}");
    }
    // A format the mesh route cannot write is refused before the shape is looked up.
    let p = get(a, "/v1/shapes/0000000000000001/mesh?format=fbx").problem(400, "request.invalid");
    assert!(p["detail"].as_str().unwrap_or_default().contains("fbx"));
    get(a, "/nope").problem(404, "route.not_found");
    http(a, "PUT", "/v1/search", None, b"").problem(405, "request.method_not_allowed");
    // Nothing was stored, and the server still answers.
    assert_eq!(get(a, "/v1/index").json()["shapes"], 0);
    assert_eq!(get(a, "/healthz").status, 200);
    s.stop();
}

#[test]
fn conversions_wait_their_turn_and_leave_the_queue_to_searches() {
    // One worker and no queue: a search is refused whenever other work holds the lane. A page
    // asks for two dozen conversions at once; they must neither be refused nor refuse searches.
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.workers = 1;
        c.queue_capacity = 0;
    });
    let a = s.addr;
    let r = ingest(
        a,
        "big",
        "",
        &bytes_of(&icosphere(5), Format::Obj),
        "model/obj",
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let threads: Vec<_> = (0..12)
        .map(|_| {
            let (id, stop) = (id.clone(), stop.clone());
            std::thread::spawn(move || {
                let mut statuses = Vec::new();
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    statuses.push(get(a, &format!("/v1/shapes/{id}/mesh?format=obj")).status);
                }
                statuses
            })
        })
        .collect();
    let mut searches = Vec::new();
    for _ in 0..20 {
        let r = post_json(
            a,
            "/v1/search",
            &serde_json::json!({"id": id, "rerank": []}),
        );
        searches.push(r.status);
        std::thread::sleep(Duration::from_millis(20));
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let conversions: Vec<u16> = threads
        .into_iter()
        .flat_map(|t| t.join().unwrap())
        .collect();
    assert!(searches.iter().all(|&c| c == 200), "searches: {searches:?}");
    assert!(conversions.len() >= 12);
    assert!(
        conversions.iter().all(|&c| c == 200),
        "conversions: {} of {} not 200",
        conversions.iter().filter(|&&c| c != 200).count(),
        conversions.len()
    );
    s.stop();
}

#[test]
fn full_queue_answers_503_with_retry_after() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| {
        c.workers = 1;
        c.queue_capacity = 0;
        c.retry_after_secs = 7;
    });
    let a = s.addr;
    let threads: Vec<_> = (0..4)
        .map(|i| {
            std::thread::spawn(move || {
                let m = squash(icosphere(3), 1.0 + 0.1 * i as f64, 1.0, 1.0);
                ingest(a, "q", "", &bytes_of(&m, Format::Obj), "model/obj")
            })
        })
        .collect();
    let resps: Vec<Resp> = threads.into_iter().map(|t| t.join().unwrap()).collect();
    let ok = resps.iter().filter(|r| r.status == 201).count();
    let busy: Vec<&Resp> = resps.iter().filter(|r| r.status == 503).collect();
    assert!(ok >= 1, "one ingest ran");
    assert!(
        !busy.is_empty(),
        "statuses: {:?}",
        resps.iter().map(|r| r.status).collect::<Vec<_>>()
    );
    for b in busy {
        b.problem(503, "server.busy");
        assert_eq!(b.header("retry-after"), Some("7"));
    }
    assert_eq!(ok + resps.iter().filter(|r| r.status == 503).count(), 4);
    s.stop();
}

#[test]
fn schema_versions_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("idx");
    // No index there: refused, nothing created.
    let e = migrate(&data).unwrap_err().to_string();
    assert!(e.contains("nothing to migrate"), "{e}");
    assert!(!data.exists());
    drop(shapeseek::index::Store::open(&data).unwrap());
    assert_eq!(
        migrate(&data).unwrap(),
        MigrateOutcome::UpToDate(SCHEMA_VERSION)
    );
    // A newer version: serve and migrate refuse, and leave it as it was.
    shapeseek::index::migrate::stamp_version(&data, SCHEMA_VERSION + 1).unwrap();
    let e = migrate(&data).unwrap_err().to_string();
    assert!(e.contains("newer"), "{e}");
    let e = shapeseek::index::Store::open(&data)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("newer"), "{e}");
    // An older version without an upgrade path: refused, pointing at migrate / no path.
    shapeseek::index::migrate::stamp_version(&data, 0).unwrap();
    let e = shapeseek::index::Store::open(&data)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("shapeseek migrate"), "{e}");
    let e = migrate(&data).unwrap_err().to_string();
    assert!(e.contains("no upgrade path"), "{e}");
    // Nothing was backed up when nothing could be done.
    assert!(!data.join(shapeseek::index::migrate::BACKUPS_DIR).exists());
}

/// The child process's address from its JSON log ("listening" line).
fn child_addr(stdout: &mut impl std::io::BufRead) -> SocketAddr {
    let mut line = String::new();
    loop {
        line.clear();
        assert!(
            stdout.read_line(&mut line).unwrap() > 0,
            "server exited before listening"
        );
        if let Some(i) = line.find("\"addr\":\"") {
            let rest = &line[i + 8..];
            return rest[..rest.find('"').unwrap()].parse().unwrap();
        }
    }
}

fn spawn_child(data: &Path) -> (std::process::Child, SocketAddr) {
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_shapeseek"))
        .args([
            "serve",
            "--addr",
            "127.0.0.1:0",
            "--log-format",
            "json",
            "--data",
        ])
        .arg(data)
        .env("SHAPESEEK_EIGENPAIRS", K.to_string())
        .env("SHAPESEEK_WORKERS", "2")
        .env("RUST_LOG", "info")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut out = std::io::BufReader::new(child.stdout.take().unwrap());
    let addr = child_addr(&mut out);
    // Keep draining the log so the child never blocks on a full pipe.
    std::thread::spawn(move || {
        let mut sink = Vec::new();
        let _ = out.read_to_end(&mut sink);
    });
    (child, addr)
}

/// SIGKILL while ingests are in flight: after a restart every acknowledged shape is there,
/// whole (record, original, signature, hash entry), and nothing half-written is.
#[test]
fn sigkill_during_ingest_leaves_a_consistent_index() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::{Arc, Mutex};
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let acked = Arc::new(Mutex::new(Vec::<(String, Vec<u8>)>::new()));
    let cut = Arc::new(AtomicUsize::new(0)); // requests sent whose answer never came
    for round in 0..3 {
        let (mut child, a) = spawn_child(&data);
        let start = acked.lock().unwrap().len();
        let workers: Vec<_> = (0..3)
            .map(|w| {
                let (acked, cut) = (acked.clone(), cut.clone());
                std::thread::spawn(move || {
                    for i in 0..60 {
                        let m = squash(
                            icosphere(2),
                            1.0 + 0.01 * i as f64,
                            1.0 + 0.013 * w as f64,
                            1.0 + 0.017 * round as f64,
                        );
                        let b = bytes_of(&m, Format::Obj);
                        let Ok(mut s) = TcpStream::connect(a) else {
                            return;
                        };
                        let head = format!(
                            "POST /v1/shapes HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: model/obj\r\nContent-Length: {}\r\n\r\n",
                            b.len()
                        );
                        let mut raw = Vec::new();
                        let sent = s.write_all(head.as_bytes()).and_then(|_| s.write_all(&b));
                        if sent.is_err() || s.read_to_end(&mut raw).is_err() || raw.is_empty() {
                            cut.fetch_add(1, Ordering::Relaxed); // killed mid-request
                            return;
                        }
                        let r = parse_response(&raw);
                        if r.status == 201 {
                            let id = r.json()["id"].as_str().unwrap().to_string();
                            acked.lock().unwrap().push((id, b));
                        }
                    }
                })
            })
            .collect();
        // Kill once a few more shapes were acknowledged (the others are still ingesting).
        let t = Instant::now();
        while acked.lock().unwrap().len() < start + 3 && t.elapsed() < Duration::from_secs(120) {
            std::thread::sleep(Duration::from_millis(2));
        }
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        workers.into_iter().for_each(|w| w.join().unwrap());
    }
    let acked = acked.lock().unwrap().clone();
    assert!(acked.len() >= 9, "only {} acknowledged", acked.len());

    let (mut child, a) = spawn_child(&data);
    for (id, bytes) in &acked {
        let r = get(a, &format!("/v1/shapes/{id}"));
        assert_eq!(r.status, 200, "acknowledged shape {id} lost");
        assert_eq!(&get(a, &format!("/v1/shapes/{id}/mesh")).body, bytes);
        assert_eq!(get(a, &format!("/v1/shapes/{id}/signature")).status, 200);
        let again = http(a, "POST", "/v1/shapes", Some("model/obj"), bytes);
        assert_eq!(again.status, 200);
        assert_eq!(again.json()["id"], id.as_str());
    }
    // Every listed shape is whole.
    let page = get(a, "/v1/shapes?limit=1000").json();
    let items = page["items"].as_array().unwrap();
    assert!(items.len() >= acked.len());
    for it in items {
        let id = it["id"].as_str().unwrap();
        assert_eq!(
            get(a, &format!("/v1/shapes/{id}/mesh")).status,
            200,
            "{id} without its mesh"
        );
        assert_eq!(
            get(a, &format!("/v1/shapes/{id}/signature")).status,
            200,
            "{id} without its signature"
        );
        let gw =
            json!({"id": id, "top_k": 1, "rerank": [{"stage": "spectral_gw", "shortlist": 1}]});
        assert_eq!(
            post_json(a, "/v1/search", &gw).status,
            200,
            "{id} without its re-ranking payload"
        );
    }
    let info = get(a, "/v1/index").json();
    assert_eq!(info["shapes"].as_u64().unwrap() as usize, items.len());
    eprintln!(
        "sigkill: 3 kills, {} acknowledged, {} cut mid-request, {} stored after restart",
        acked.len(),
        cut.load(Ordering::Relaxed),
        items.len()
    );
    // Graceful stop via SIGTERM.
    let _ = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    let status = child.wait().unwrap();
    assert!(status.success(), "SIGTERM exit: {status}");
}

/// A delete answered 204 is durable: SIGKILL right after the answer, and the shape stays
/// deleted after the restart (sled's own background flush would come only later).
#[test]
fn sigkill_right_after_a_delete_keeps_the_shape_deleted() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (mut child, a) = spawn_child(&data);
    let mut ids = Vec::new();
    for i in 0..4 {
        let m = squash(icosphere(2), 1.0 + 0.05 * i as f64, 1.0, 1.0);
        let r = http(
            a,
            "POST",
            "/v1/shapes",
            Some("model/obj"),
            &bytes_of(&m, Format::Obj),
        );
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        ids.push(r.json()["id"].as_str().unwrap().to_string());
    }
    child.kill().unwrap();
    child.wait().unwrap();
    // Three rounds: delete one shape, SIGKILL as soon as the answer is read.
    for id in &ids[..3] {
        let (mut child, a) = spawn_child(&data);
        let r = http(a, "DELETE", &format!("/v1/shapes/{id}"), None, b"");
        assert_eq!(r.status, 204, "{}", String::from_utf8_lossy(&r.body));
        child.kill().unwrap();
        child.wait().unwrap();
    }
    let (mut child, a) = spawn_child(&data);
    for id in &ids[..3] {
        assert_eq!(
            get(a, &format!("/v1/shapes/{id}")).status,
            404,
            "deleted shape {id} is back after SIGKILL"
        );
    }
    assert_eq!(get(a, &format!("/v1/shapes/{}", ids[3])).status, 200);
    assert_eq!(get(a, "/v1/index").json()["shapes"], 1);
    child.kill().unwrap();
    child.wait().unwrap();
}

/// The shared mini benchmark (3 classes × 8 shapes), when present.
#[test]
fn mini_benchmark_nearest_neighbours() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/bench/mini");
    let manifest = root.join("manifest.csv");
    if !manifest.exists() {
        println!(
            "SKIPPED mini_benchmark_nearest_neighbours: {} not found",
            manifest.display()
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let a = s.addr;
    let text = std::fs::read_to_string(&manifest).unwrap();
    let mut shapes = Vec::new();
    for line in text.lines().skip(1) {
        let cols: Vec<&str> = line.split(',').collect();
        let (id, path, class) = (cols[0], cols[1], cols[2]);
        let bytes = std::fs::read(root.join(path)).unwrap();
        let r = ingest(a, id, class, &bytes, "model/obj");
        assert_eq!(r.status, 201, "{id}: {}", String::from_utf8_lossy(&r.body));
        shapes.push((
            r.json()["id"].as_str().unwrap().to_string(),
            class.to_string(),
        ));
    }
    // 24 after 23 is within the 10% recalibration band: any calibration will do here.
    assert_eq!(get(a, "/v1/index").json()["shapes"], shapes.len());
    let class_of = |id: &str| {
        shapes
            .iter()
            .find(|s| s.0 == id)
            .map(|s| s.1.clone())
            .unwrap()
    };
    let mut nn = 0;
    for (id, class) in &shapes {
        let v = post_json(a, "/v1/search", &json!({"id": id, "top_k": 1})).json();
        if class_of(v["hits"][0]["id"].as_str().unwrap()) == *class {
            nn += 1;
        }
    }
    println!(
        "mini benchmark: nearest neighbour of the same class for {nn} of {}",
        shapes.len()
    );
    // Chance is about 7/23; the product default must do clearly better.
    assert!(
        nn * 2 > shapes.len(),
        "nearest neighbour same class only {nn} of {}",
        shapes.len()
    );
    s.stop();
}

/// The OpenAPI enums of the query spec are the library's serialisations.
#[test]
fn openapi_enums_match_the_library() {
    let yaml =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("api/openapi.yaml"))
            .unwrap();
    let ser = |v: Value| v.as_str().unwrap().to_string();
    let d: Vec<String> = shapeseek::ranking::Dissimilarity::all()
        .iter()
        .map(|d| ser(serde_json::to_value(d).unwrap()))
        .collect();
    use shapeseek::signature::Aggregation as A;
    let a: Vec<String> = [A::Single, A::Sum, A::Sum2, A::Max]
        .iter()
        .map(|x| ser(serde_json::to_value(x).unwrap()))
        .collect();
    assert!(
        yaml.contains(&format!("enum: [{}]", d.join(", "))),
        "Dissimilarity enum: {d:?}"
    );
    assert!(
        yaml.contains(&format!("enum: [{}]", a.join(", "))),
        "Aggregation enum: {a:?}"
    );
    assert_eq!(
        shapeseek::server::handlers::OPENAPI_YAML,
        yaml,
        "served document is the file"
    );
}

/// Defaults < TOML file < SHAPESEEK_* environment; unknown keys and bad values are refused.
#[test]
fn config_layers() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("shapeseek.toml");
    std::fs::write(
        &file,
        "addr = \"127.0.0.1:9999\"\nmax_vertices = 1234\nworkers = 3\n",
    )
    .unwrap();
    let env = vec![
        ("SHAPESEEK_WORKERS".to_string(), "5".to_string()),
        ("SHAPESEEK_DATA".to_string(), "/tmp/x".to_string()),
        (
            "SHAPESEEK_REQUEST_TIMEOUT_SECS".to_string(),
            "2.5".to_string(),
        ),
        ("OTHER".to_string(), "1".to_string()),
    ];
    let cfg = ServerConfig::load(Some(&file), env).unwrap();
    assert_eq!(cfg.addr, "127.0.0.1:9999");
    assert_eq!(cfg.max_vertices, 1234);
    assert_eq!(cfg.workers, 5);
    assert_eq!(cfg.data, Path::new("/tmp/x"));
    assert_eq!(cfg.request_timeout_secs, 2.5);
    assert_eq!(cfg.max_faces, ServerConfig::default().max_faces);
    std::fs::write(&file, "adr = \"x\"\n").unwrap();
    assert!(ServerConfig::load(Some(&file), vec![]).is_err());
    let bad = vec![("SHAPESEEK_WORKERS".to_string(), "many".to_string())];
    assert!(ServerConfig::load(None, bad).is_err());
    let bad = vec![("SHAPESEEK_LOG_FORMAT".to_string(), "xml".to_string())];
    assert!(ServerConfig::load(None, bad).is_err());
    // Too few eigenpairs for the default signature's ShapeDNA channel: refused at start, with
    // the count it needs, rather than every upload refused later.
    let few = vec![("SHAPESEEK_EIGENPAIRS".to_string(), "30".to_string())];
    let e = ServerConfig::load(None, few).unwrap_err().to_string();
    assert!(e.contains("at least 51"), "{e}");
    // sled's page cache: sled's own 1 GiB unless set, in MiB, never 0.
    assert_eq!(ServerConfig::default().sled_cache_bytes(), 1 << 30);
    let small = vec![("SHAPESEEK_SLED_CACHE_MB".to_string(), "64".to_string())];
    assert_eq!(
        ServerConfig::load(None, small).unwrap().sled_cache_bytes(),
        64 << 20
    );
    let none = vec![("SHAPESEEK_SLED_CACHE_MB".to_string(), "0".to_string())];
    let e = ServerConfig::load(None, none).unwrap_err().to_string();
    assert!(e.contains("sled_cache_mb"), "{e}");
}

/// A shutdown lets an ingest already running finish (201, and it is there after a restart).
#[test]
fn shutdown_finishes_in_flight_ingest() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.eigenpairs = 100);
    let a = s.addr;
    let bytes = bytes_of(&bumpy_sphere(4, 0.05), Format::Ply); // 2562 vertices
    let b2 = bytes.clone();
    let t = std::thread::spawn(move || http(a, "POST", "/v1/shapes", Some("application/ply"), &b2));
    let t0 = Instant::now();
    while get(a, "/v1/index").json()["queue"]["running"] != 1 {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "ingest never started"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    s.stop();
    let r = t.join().unwrap();
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.eigenpairs = 100);
    assert_eq!(get(s.addr, &format!("/v1/shapes/{id}")).status, 200);
    s.stop();
}

#[test]
fn slow_requests_time_out_as_problem_json() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.request_timeout_secs = 0.001);
    let bytes = bytes_of(&bumpy_sphere(4, 0.05), Format::Obj);
    ingest(s.addr, "slow", "", &bytes, "model/obj").problem(503, "request.timeout");
    assert_eq!(get(s.addr, "/healthz").status, 200);
    s.stop();
}

/// Changing the signature's analysis options makes stored signatures stale: they are
/// recomputed from the stored originals at the next start.
#[test]
fn stale_signatures_are_recomputed_from_originals() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let r = ingest(
        s.addr,
        "a",
        "",
        &bytes_of(&icosphere(2), Format::Obj),
        "model/obj",
    );
    let id = r.json()["id"].as_str().unwrap().to_string();
    let key_before = r.json()["shape"]["spec_key"].clone();
    s.stop();
    let s = Server::start(dir.path(), GRACE_SECS, |c| c.eigenpairs = K + 10);
    let rec = get(s.addr, &format!("/v1/shapes/{id}")).json();
    assert_ne!(rec["spec_key"], key_before);
    assert_eq!(rec["spec_key"], get(s.addr, "/v1/index").json()["spec_key"]);
    assert_eq!(
        get(s.addr, &format!("/v1/shapes/{id}/signature")).status,
        200
    );
    s.stop();
}

/// The migrations runner copies the directory first, then applies the steps and stamps the
/// version (exercised with a test step 0 → 1, since version 1 is the first real format).
#[test]
fn migrate_backs_up_then_upgrades() {
    use shapeseek::index::migrate::{migrate_with, Step};
    fn add_marker(db: &sled::Db) -> shapeseek::Result<()> {
        db.open_tree("meta")
            .and_then(|t| t.insert("migrated_by_test", &b"yes"[..]))
            .map_err(|e| shapeseek::Error::Io(std::io::Error::other(e.to_string())))?;
        Ok(())
    }
    fn version_of(dir: &Path) -> u32 {
        let db = shapeseek::index::store::open_db(&dir.join("db")).unwrap();
        shapeseek::index::store::read_schema_version(&db)
            .unwrap()
            .unwrap()
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("idx");
    drop(shapeseek::index::Store::open(&data).unwrap());
    shapeseek::index::migrate::stamp_version(&data, 0).unwrap();
    let steps = [Step {
        from: 0,
        description: "test step",
        apply: add_marker,
    }];
    let MigrateOutcome::Upgraded { from, to, backup } = migrate_with(&data, &steps, 1).unwrap()
    else {
        panic!("not upgraded")
    };
    assert_eq!((from, to), (0, 1));
    assert_eq!(
        version_of(&backup),
        0,
        "the backup is the untouched original"
    );
    assert_eq!(
        backup.parent(),
        Some(data.join(shapeseek::index::migrate::BACKUPS_DIR).as_path()),
        "the backup is kept inside the data directory"
    );
    assert_eq!(version_of(&data), 1);
    let db = shapeseek::index::store::open_db(&data.join("db")).unwrap();
    assert!(db
        .open_tree("meta")
        .unwrap()
        .get("migrated_by_test")
        .unwrap()
        .is_some());
    drop(db);
    assert_eq!(
        migrate_with(&data, &steps, 1).unwrap(),
        MigrateOutcome::UpToDate(1)
    );
}

/// The stored values of each shape, read through the store: (signature, original, payload).
type Stored = (Vec<u8>, Vec<u8>, Option<Vec<u8>>);

fn stored_values(data: &Path, ids: &[String]) -> Vec<Stored> {
    let store = shapeseek::index::Store::open(data).unwrap();
    ids.iter()
        .map(|id| {
            (
                store.signature(id).unwrap().expect("a signature"),
                store.mesh(id).unwrap().expect("an original"),
                store.payload(id).unwrap(),
            )
        })
        .collect()
}

/// Rewrites a current (version 3) index in version 2's layout: whole values in `signatures`,
/// `meshes` and `payloads` (`migrations/0002_payloads.md`), the chunked trees dropped.
fn to_version_2_layout(data: &Path, ids: &[String]) {
    let values = stored_values(data, ids);
    let db = shapeseek::index::store::open_db(&data.join("db")).unwrap();
    let (sigs, meshes, payloads) = (
        db.open_tree("signatures").unwrap(),
        db.open_tree("meshes").unwrap(),
        db.open_tree("payloads").unwrap(),
    );
    for (id, (sig, mesh, payload)) in ids.iter().zip(values) {
        sigs.insert(id.as_bytes(), sig).unwrap();
        meshes.insert(id.as_bytes(), mesh).unwrap();
        if let Some(p) = payload {
            payloads.insert(id.as_bytes(), p).unwrap();
        }
    }
    for t in ["signature_chunks", "mesh_chunks", "payload_chunks"] {
        assert!(db.drop_tree(t).unwrap(), "{t} existed");
    }
    db.open_tree("meta")
        .unwrap()
        .insert("schema_version", &2u32.to_be_bytes())
        .unwrap();
    db.flush().unwrap();
}

/// Two shapes ingested by a server into `data`; their ids.
fn two_shapes(data: &Path) -> Vec<String> {
    let s = Server::start(data, GRACE_SECS, |_| {});
    let ids = [icosphere(2), torus(1.0, 0.35, 20, 10)]
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let r = ingest(
                s.addr,
                &format!("s{i}"),
                "",
                &bytes_of(m, Format::Off),
                "model/off",
            );
            assert_eq!(r.status, 201);
            r.json()["id"].as_str().unwrap().to_string()
        })
        .collect();
    s.stop();
    ids
}

/// Version 2 → 3 stores signatures, originals and payloads in pieces: every value reads back
/// byte for byte, the old trees are gone, and the server opens the result and searches.
#[test]
fn migrate_from_version_2_chunks_the_values() {
    let dir = tempfile::tempdir().unwrap();
    let ids = two_shapes(dir.path());
    let before = stored_values(dir.path(), &ids);
    assert!(
        before.iter().all(|(s, _, p)| s.len() > 4096 && p.is_some()),
        "signatures span several pieces"
    );
    to_version_2_layout(dir.path(), &ids);
    let e = shapeseek::index::Store::open(dir.path())
        .err()
        .expect("a version-2 index is refused")
        .to_string();
    assert!(e.contains("shapeseek migrate"), "{e}");
    let MigrateOutcome::Upgraded { from, to, .. } = migrate(dir.path()).unwrap() else {
        panic!("not upgraded")
    };
    assert_eq!((from, to), (2, SCHEMA_VERSION));
    assert_eq!(stored_values(dir.path(), &ids), before);
    {
        let db = shapeseek::index::store::open_db(&dir.path().join("db")).unwrap();
        let names: Vec<String> = db
            .tree_names()
            .iter()
            .map(|n| String::from_utf8_lossy(n).into_owned())
            .collect();
        for old in ["signatures", "meshes", "payloads"] {
            assert!(!names.iter().any(|n| n == old), "{old} left: {names:?}");
        }
    }
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let v = post_json(
        s.addr,
        "/v1/search",
        &json!({"id": ids[0], "rerank": [{"stage": "spectral_gw"}]}),
    );
    assert_eq!(v.status, 200, "{}", String::from_utf8_lossy(&v.body));
    assert_eq!(v.json()["hits"].as_array().unwrap().len(), 1);
    // Deleting a shape removes every piece of it.
    assert_eq!(
        http(
            s.addr,
            "DELETE",
            &format!("/v1/shapes/{}", ids[1]),
            None,
            b""
        )
        .status,
        204
    );
    s.stop();
    let db = shapeseek::index::store::open_db(&dir.path().join("db")).unwrap();
    for t in ["signature_chunks", "mesh_chunks", "payload_chunks"] {
        let left: Vec<_> = db
            .open_tree(t)
            .unwrap()
            .scan_prefix(ids[1].as_bytes())
            .collect();
        assert!(
            left.is_empty(),
            "{t}: {} keys of the deleted shape",
            left.len()
        );
        assert!(
            !db.open_tree(t).unwrap().is_empty(),
            "{t} keeps the other shape"
        );
    }
}

/// Version 1 → 2 computes every shape's re-ranking payload from its stored original: the
/// payloads equal those written at ingest, bit for bit, and the server opens the result (after
/// version 2 → 3 too).
#[test]
fn migrate_from_version_1_computes_payloads() {
    let dir = tempfile::tempdir().unwrap();
    let shapes = two_shapes(dir.path());
    let written: Vec<Vec<u8>> = stored_values(dir.path(), &shapes)
        .into_iter()
        .map(|(_, _, p)| p.expect("payload written at ingest"))
        .collect();
    // Make it a version-1 index: version 2's layout without payloads, version 1.
    to_version_2_layout(dir.path(), &shapes);
    {
        let db = shapeseek::index::store::open_db(&dir.path().join("db")).unwrap();
        db.open_tree("payloads").unwrap().clear().unwrap();
        db.flush().unwrap();
    }
    shapeseek::index::migrate::stamp_version(dir.path(), 1).unwrap();
    let e = shapeseek::index::Store::open(dir.path())
        .err()
        .expect("a version-1 index is refused")
        .to_string();
    assert!(e.contains("shapeseek migrate"), "{e}");
    let MigrateOutcome::Upgraded { from, to, .. } = migrate(dir.path()).unwrap() else {
        panic!("not upgraded")
    };
    assert_eq!((from, to), (1, SCHEMA_VERSION));
    let store = shapeseek::index::Store::open(dir.path()).unwrap();
    for (id, before) in shapes.iter().zip(&written) {
        assert_eq!(
            store.payload(id).unwrap().as_ref(),
            Some(before),
            "payload of {id} after migration"
        );
    }
    drop(store);
    let s = Server::start(dir.path(), GRACE_SECS, |_| {});
    let v = post_json(
        s.addr,
        "/v1/search",
        &json!({"id": shapes[0], "rerank": [{"stage": "spectral_gw"}]}),
    );
    assert_eq!(v.status, 200, "{}", String::from_utf8_lossy(&v.body));
    s.stop();
}
