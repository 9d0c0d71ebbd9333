//! Tests of the `shapeseek` binary's collection commands and error messages: `ingest` (into a
//! data directory and into a live server), `search`, `migrate` and `spectrum`, driven as a
//! user would, through the built executable.

use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_shapeseek");

struct Out {
    code: i32,
    stdout: String,
    stderr: String,
}

impl Out {
    fn json(&self) -> Value {
        serde_json::from_str(self.stdout.trim()).unwrap_or_else(|e| {
            panic!("stdout is not JSON ({e}): {}\n{}", self.stdout, self.stderr)
        })
    }
}

fn run(args: &[&str]) -> Out {
    let o = Command::new(BIN)
        .args(args)
        .env_remove("SHAPESEEK_URL")
        .env_remove("SHAPESEEK_DATA")
        .output()
        .expect("run shapeseek");
    Out {
        code: o.status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&o.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
    }
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// `count` distinct generated meshes (bumpy tori of about `size` vertices) in `dir`.
fn meshes(dir: &Path, count: usize, size: usize) -> Vec<PathBuf> {
    let o = run(&[
        "bench",
        "meshes",
        "--out",
        s(dir),
        "--count",
        &count.to_string(),
        "--size",
        &size.to_string(),
    ]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    assert_eq!(v.len(), count);
    v
}

/// `GET path` on 127.0.0.1:`port`: the status and body, `None` when nothing answers.
fn get(port: u16, path: &str) -> Option<(u16, String)> {
    request(port, "GET", path)
}

/// A request without a body on 127.0.0.1:`port`: the status and the whole response (head and
/// body, read until the server closes), `None` when nothing answers.
fn request(port: u16, method: &str, path: &str) -> Option<(u16, String)> {
    use std::io::{Read, Write};
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    c.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    c.write_all(
        format!("{method} {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").as_bytes(),
    )
    .ok()?;
    let mut raw = Vec::new();
    c.read_to_end(&mut raw).ok()?;
    let raw = String::from_utf8_lossy(&raw).into_owned();
    let code = raw.split(' ').nth(1)?.parse().ok()?;
    Some((code, raw))
}

/// The value of header `name` (lower case) in a raw response.
fn header<'a>(raw: &'a str, name: &str) -> Option<&'a str> {
    let head = raw.split("\r\n\r\n").next()?;
    head.lines().skip(1).find_map(|l| {
        let (k, v) = l.split_once(':')?;
        k.eq_ignore_ascii_case(name).then(|| v.trim())
    })
}

/// A running `shapeseek serve` on a free port of 127.0.0.1.
struct Server {
    child: Child,
    url: String,
}

impl Server {
    fn start(data: &Path) -> Server {
        Server::start_with(data, &[])
    }

    /// A server with these environment variables (`SHAPESEEK_*` settings).
    fn start_with(data: &Path, env: &[(&str, &str)]) -> Server {
        let port = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let mut child = Command::new(BIN)
            .args(["serve", "--addr", &format!("127.0.0.1:{port}"), "--data"])
            .arg(data)
            .env("SHAPESEEK_LOG_FORMAT", "text")
            .env("RUST_LOG", "warn")
            .envs(env.iter().copied())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start shapeseek serve");
        let url = format!("http://127.0.0.1:{port}");
        let t0 = Instant::now();
        loop {
            // Ready, not only listening: the port answers 503 while the index loads.
            if get(port, "/readyz").is_some_and(|(code, _)| code == 200) {
                break;
            }
            if let Ok(Some(status)) = child.try_wait() {
                let mut err = String::new();
                if let Some(e) = child.stderr.take() {
                    for l in BufReader::new(e).lines().map_while(Result::ok) {
                        err.push_str(&l);
                        err.push('\n');
                    }
                }
                panic!("serve exited with {status}: {err}");
            }
            assert!(
                t0.elapsed() < Duration::from_secs(60),
                "server did not start"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        Server { child, url }
    }

    fn stop(mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(30) {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// (sha256 → (name, tags, signature bytes)) of every stored shape.
fn index_contents(
    data: &Path,
) -> std::collections::BTreeMap<String, (String, Vec<String>, Vec<u8>)> {
    let store = shapeseek::index::Store::open(data).unwrap();
    store
        .all()
        .unwrap()
        .into_iter()
        .map(|(rec, sig)| (rec.sha256, (rec.name, rec.tags, sig)))
        .collect()
}

#[test]
fn ingest_into_a_data_dir_resumes_and_lists_failures() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("meshes");
    let files = meshes(&dir, 5, 500);
    // A sub-folder with one more mesh (found recursively), a broken file and a non-mesh file.
    let sub = dir.join("sub");
    std::fs::create_dir(&sub).unwrap();
    std::fs::copy(&files[0], sub.join("again.off")).unwrap();
    std::fs::write(sub.join("broken.obj"), "v 0 0 0\nv 1 0 0\nf 1 2 7\n").unwrap();
    std::fs::write(sub.join("notes.txt"), "not a mesh").unwrap();
    let missing = tmp.path().join("no-such.off");
    let data = tmp.path().join("data");

    let o = run(&[
        "ingest",
        "--data",
        s(&data),
        "--tag",
        "batch1",
        "--json",
        s(&dir),
        s(&missing),
    ]);
    assert_eq!(o.code, 1, "some inputs failed: {}\n{}", o.stdout, o.stderr);
    let v = o.json();
    assert_eq!(v["created"], 5, "{v}");
    assert_eq!(v["existing"], 1, "the copy has the same bytes: {v}");
    let failed = v["failed"].as_array().unwrap();
    assert_eq!(failed.len(), 2, "{v}");
    let broken = failed
        .iter()
        .find(|f| f["path"].as_str().unwrap().ends_with("broken.obj"))
        .expect("broken.obj listed");
    assert_eq!(broken["code"], "mesh.parse", "{broken}");
    assert!(!broken["detail"].as_str().unwrap().is_empty());
    let gone = failed
        .iter()
        .find(|f| f["path"] == s(&missing))
        .expect("the missing path listed");
    assert_eq!(gone["code"], "io");
    assert!(
        gone["detail"].as_str().unwrap().contains("No such file"),
        "{gone}"
    );
    // The text summary names the same failures.
    let o = run(&["ingest", "--data", s(&data), s(&dir)]);
    assert_eq!(o.code, 1);
    assert!(
        o.stdout.contains("0 new, 6 already stored, 1 failed"),
        "{}",
        o.stdout
    );
    assert!(o.stdout.contains("broken.obj") && o.stdout.contains("mesh.parse"));

    // Resumable: everything stored is skipped by content hash.
    let o = run(&[
        "ingest",
        "--data",
        s(&data),
        "--json",
        s(&files[1]),
        s(&files[2]),
    ]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = o.json();
    assert_eq!(
        (v["created"].as_u64(), v["existing"].as_u64()),
        (Some(0), Some(2))
    );

    let stored = index_contents(&data);
    assert_eq!(stored.len(), 5);
    for (name, tags, _) in stored.values() {
        // The copy races its original (same bytes): whichever is stored first names the shape.
        assert!(
            name.starts_with("torus-") || name == "again",
            "named after the file: {name}"
        );
        assert_eq!(tags, &vec!["batch1".to_string()]);
    }
}

#[test]
fn ingest_to_a_server_and_search() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("meshes");
    let files = meshes(&dir, 6, 500);
    // A manifest over the same files: names from `id`, tags from the other columns (one with
    // a comma: the server split it in two, and `--data` did not).
    let mut csv = String::from("id,path,class,transform,pose\n");
    for (i, f) in files.iter().enumerate() {
        let class = if i % 2 == 0 { "even" } else { "odd" };
        let pose = if i == 0 { "\"sitting, arms up\"" } else { "" };
        csv.push_str(&format!(
            "shape-{i},meshes/{},{class},null,{pose}\n",
            f.file_name().unwrap().to_string_lossy()
        ));
    }
    csv.push_str("shape-x,meshes/missing.off,odd,null,\n");
    let manifest = tmp.path().join("manifest.csv");
    std::fs::write(&manifest, csv).unwrap();

    let server_data = tmp.path().join("server-data");
    let server = Server::start(&server_data);
    let url = server.url.clone();
    let o = run(&[
        "ingest",
        "--url",
        &url,
        "--jobs",
        "3",
        "--json",
        s(&manifest),
    ]);
    assert_eq!(o.code, 1, "{}\n{}", o.stdout, o.stderr);
    let v = o.json();
    assert_eq!(v["created"], 6, "{v}");
    let failed = v["failed"].as_array().unwrap();
    assert_eq!(failed.len(), 1, "{v}");
    assert!(failed[0]["path"].as_str().unwrap().ends_with("missing.off"));
    assert_eq!(failed[0]["code"], "io");

    // Again: all already stored (the server answers 200 for known bytes).
    let o = run(&["ingest", "--url", &url, s(&dir)]);
    assert_eq!(o.code, 0, "{}\n{}", o.stdout, o.stderr);
    assert!(
        o.stdout.contains("0 new, 6 already stored, 0 failed"),
        "{}",
        o.stdout
    );

    // Search with a file: a table whose first hit is that shape (same bytes, score 0).
    let o = run(&["search", "--url", &url, "--top-k", "3", s(&files[3])]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let lines: Vec<&str> = o.stdout.lines().collect();
    assert!(
        lines[0].contains("3 hit(s) among 6 candidate(s)"),
        "{}",
        o.stdout
    );
    let head: Vec<&str> = lines[1].split_whitespace().collect();
    assert_eq!(
        head,
        ["rank", "score", "name", "id", "tags"],
        "{}",
        o.stdout
    );
    let first: Vec<&str> = lines[2].split_whitespace().collect();
    assert_eq!(first[0], "1");
    assert_eq!(first[2], "shape-3", "{}", o.stdout);
    assert!(
        lines[2].contains("class=odd, transform=null"),
        "{}",
        o.stdout
    );
    assert_eq!(lines.len(), 5, "{}", o.stdout);

    // By id, JSON, with a tag filter and no re-ranking.
    let o = run(&["search", "--url", &url, "--json", s(&files[0])]);
    let id = o.json()["hits"][0]["id"].as_str().unwrap().to_string();
    let o = run(&[
        "search",
        "--url",
        &url,
        "--id",
        &id,
        "--tag",
        "class=even",
        "--rerank",
        "[]",
        "--json",
    ]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = o.json();
    assert_eq!(v["stages"], serde_json::json!(["scan"]));
    let hits = v["hits"].as_array().unwrap();
    assert_eq!(hits.len(), 2, "the other two even shapes: {v}");
    assert!(hits.iter().all(|h| h["id"] != id.as_str()));

    // Server errors keep their problem code; file errors name the file.
    let o = run(&["search", "--url", &url, "--id", "ffffffffffffffff"]);
    assert_eq!(o.code, 65);
    assert!(o.stderr.contains("[shape.not_found]"), "{}", o.stderr);
    let broken = tmp.path().join("broken.obj");
    std::fs::write(&broken, "v 0 0 0\nf 1 2 3\n").unwrap();
    let o = run(&["search", "--url", &url, s(&broken)]);
    assert_ne!(o.code, 0);
    assert!(
        o.stderr.contains(s(&broken)) && o.stderr.contains("[mesh."),
        "{}",
        o.stderr
    );
    let o = run(&["search", "--url", &url, "--rerank", "{oops", s(&files[0])]);
    assert_eq!(o.code, 65);
    assert!(o.stderr.contains("--rerank"), "{}", o.stderr);
    server.stop();

    // In process into a data directory: the same index as the server built.
    let local = tmp.path().join("local-data");
    let o = run(&["ingest", "--data", s(&local), "--quiet", s(&manifest)]);
    assert_eq!(o.code, 1, "{}", o.stderr);
    let stored = index_contents(&server_data);
    assert!(
        stored
            .values()
            .any(|(_, tags, _)| tags.contains(&"pose=sitting, arms up".to_string())),
        "{:?}",
        stored.values().map(|(_, tags, _)| tags).collect::<Vec<_>>()
    );
    assert_eq!(index_contents(&local), stored);
}

/// Through a server, a file over its `max_body_bytes` is listed as `limit.bytes` without being
/// sent (the server cut the connection mid-send and the file was listed as "cannot reach");
/// a server that stops answering ends the run with status 69 and a count of the files not
/// sent (every remaining file was tried, and listed as a failure of its own).
#[test]
fn ingest_to_a_server_checks_its_body_limit_and_stops_when_it_is_gone() {
    let tmp = tempfile::tempdir().unwrap();
    let small = meshes(&tmp.path().join("small"), 3, 300);
    let big = meshes(&tmp.path().join("big"), 1, 20_000);
    let limit = 200_000;
    assert!(std::fs::metadata(&big[0]).unwrap().len() > limit);
    assert!(small
        .iter()
        .all(|f| std::fs::metadata(f).unwrap().len() < limit / 2));
    let data = tmp.path().join("data");
    let server = Server::start_with(&data, &[("SHAPESEEK_MAX_BODY_BYTES", "200000")]);
    let mut args = vec!["ingest", "--url", &server.url, "--json", "--jobs", "1"];
    args.extend(small.iter().chain(&big).map(|p| s(p)));
    let o = run(&args);
    assert_eq!(o.code, 1, "{}\n{}", o.stdout, o.stderr);
    let v = o.json();
    assert_eq!(v["created"], 3, "{v}");
    let failed = v["failed"].as_array().unwrap();
    assert_eq!(failed.len(), 1, "{v}");
    assert_eq!(failed[0]["path"], s(&big[0]), "{v}");
    assert_eq!(failed[0]["code"], "limit.bytes", "{v}");
    let detail = failed[0]["detail"].as_str().unwrap();
    assert!(
        detail.contains("takes up to 200000 bytes") && !detail.contains("  "),
        "{v}"
    );
    assert_eq!(v["not_sent"], 0, "{v}");
    server.stop();

    // A server that answers its first requests, then is gone.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let fake = std::thread::spawn(move || {
        use std::io::{Read, Write};
        let answers = [
            "{\"status\":\"ready\",\"shapes\":0}",
            "{\"shapes\":0}",
            "{\"id\":\"0000000000000001\"}",
        ];
        // Accepts with a deadline: a client that makes fewer requests fails the test's
        // assertions instead of hanging it.
        listener.set_nonblocking(true).unwrap();
        let t0 = Instant::now();
        for (i, body) in answers.iter().enumerate() {
            let accepted = loop {
                match listener.accept() {
                    Ok((c, _)) => break Some(c),
                    Err(_) if t0.elapsed() < Duration::from_secs(60) => {
                        std::thread::sleep(Duration::from_millis(10))
                    }
                    Err(_) => break None,
                }
            };
            let Some(mut c) = accepted else { return };
            c.set_nonblocking(false).unwrap();
            let mut buf = vec![0u8; 1 << 16];
            let mut got = Vec::new();
            // Read the head and, for the upload, its whole body.
            loop {
                let n = c.read(&mut buf).unwrap();
                got.extend_from_slice(&buf[..n]);
                let text = String::from_utf8_lossy(&got).to_string();
                if let Some(end) = text.find("\r\n\r\n") {
                    let len: usize = text
                        .lines()
                        .find_map(|l| {
                            l.to_ascii_lowercase()
                                .strip_prefix("content-length:")
                                .map(|v| v.trim().parse().unwrap())
                        })
                        .unwrap_or(0);
                    if got.len() >= end + 4 + len {
                        break;
                    }
                }
                if n == 0 {
                    break;
                }
            }
            let status = if i == 2 { "201 Created" } else { "200 OK" };
            let _ = write!(
                c,
                "HTTP/1.1 {status}\r\ncontent-type: application/json\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
                body.len()
            );
        }
        // Gone: the listener closes, every connection is refused.
    });
    let many = meshes(&tmp.path().join("many"), 6, 300);
    let mut args = vec!["ingest", "--url", &url, "--json", "--jobs", "1"];
    args.extend(many.iter().map(|p| s(p)));
    let o = run(&args);
    fake.join().unwrap();
    assert_eq!(o.code, 69, "{}\n{}", o.stdout, o.stderr);
    let v = o.json();
    assert_eq!(v["created"], 1, "{v}");
    assert_eq!(v["failed"].as_array().unwrap().len(), 1, "{v}");
    assert_eq!(v["not_sent"], 4, "{v}");
    assert!(
        o.stderr
            .contains("stopped answering: 4 of 6 files were not sent"),
        "{}",
        o.stderr
    );
}

#[test]
fn ingest_reports_an_unreachable_server_and_bad_arguments() {
    let tmp = tempfile::tempdir().unwrap();
    let files = meshes(&tmp.path().join("m"), 2, 300);
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("http://127.0.0.1:{port}");
    let o = run(&["ingest", "--url", &url, s(&files[0])]);
    assert_eq!(o.code, 69, "{}", o.stderr);
    assert!(
        o.stderr
            .contains(&format!("cannot reach shapeseek at {url}")),
        "{}",
        o.stderr
    );
    let o = run(&["search", "--url", &url, s(&files[0])]);
    assert_eq!(o.code, 69, "{}", o.stderr);
    let o = run(&[
        "ingest",
        "--data",
        s(&tmp.path().join("d")),
        "--name",
        "x",
        s(&files[0]),
        s(&files[1]),
    ]);
    assert_eq!(o.code, 65);
    assert!(o.stderr.contains("--name names one shape"), "{}", o.stderr);
}

/// Small faults an outside review of the command line found, each once a panic, a silent
/// success, a misleading error or minutes of silence.
#[test]
fn usage_faults_are_refused_plainly() {
    let tmp = tempfile::tempdir().unwrap();
    // Output into a pipe that is already closed: no panic (it was `failed printing to
    // stdout: Broken pipe`, exit 101); the command ends by SIGPIPE as `… | head` expects.
    let mut child = Command::new(BIN)
        .args(["spectrum", "--generate", "icosphere:2", "--k", "20"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_ne!(o.status.code(), Some(101), "{stderr}");
    // Zero eigenpairs (it printed one).
    let o = run(&["spectrum", "--generate", "icosphere:1", "--k", "0"]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("--k 0"), "{}", o.stderr);
    // Nothing to ingest (it reported "0 new, 0 already stored, 0 failed" and exit 0).
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let o = run(&["ingest", "--data", s(&tmp.path().join("d0")), s(&empty)]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("no mesh files found in"), "{}", o.stderr);
    // An exported SHAPESEEK_URL does not make `--data` a conflict (it was a usage error).
    let files = meshes(&tmp.path().join("m"), 1, 300);
    let o = Command::new(BIN)
        .args([
            "ingest",
            "--quiet",
            "--data",
            s(&tmp.path().join("d1")),
            s(&files[0]),
        ])
        .env("SHAPESEEK_URL", "http://127.0.0.1:9")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // A search with no query names both ways of giving one (it named `<FILE>` alone), and
    // refuses both at once.
    let o = run(&["search"]);
    assert_eq!(o.code, 2, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("<FILE|--id <ID>>"), "{}", o.stderr);
    let o = run(&["search", "x.obj", "--id", "0000000000000001"]);
    assert_eq!(o.code, 2, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("cannot be used with"), "{}", o.stderr);
    // A benchmark over zero shapes (it panicked on a remainder by zero).
    let o = run(&["bench", "search", "--sizes", "0"]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    // A worker count no machine has (it started threads for minutes, silently).
    let o = run(&[
        "serve",
        "--data",
        s(&tmp.path().join("d2")),
        "--workers",
        "100000",
    ]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("workers must be in"), "{}", o.stderr);
    // A taken port names the address (it said only "Address already in use"), and an
    // address without a port is a usage error (it was an I/O one, 74).
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let o = run(&[
        "serve",
        "--data",
        s(&tmp.path().join("d3")),
        "--addr",
        &addr,
    ]);
    assert_eq!(o.code, 74, "{}{}", o.stdout, o.stderr);
    assert!(
        o.stderr.contains(&format!("cannot listen on {addr}")),
        "{}",
        o.stderr
    );
    let o = run(&[
        "serve",
        "--data",
        s(&tmp.path().join("d4")),
        "--addr",
        "127.0.0.1",
    ]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("is not HOST:PORT"), "{}", o.stderr);
    // Output paths that cannot be written are refused before the evaluation, naming the path
    // (`--out` a file: it evaluated every shape, then said `File exists (os error 17)`).
    let manifest = tmp.path().join("manifest.csv");
    std::fs::write(&manifest, "id,path,class,transform,strength,source_pose\n").unwrap();
    let o = run(&[
        "eval",
        "--manifest",
        s(&manifest),
        "--out",
        s(&manifest),
        "--no-cache",
    ]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    assert!(
        o.stderr.contains(&format!(
            "--out {}: exists and is not a folder",
            s(&manifest)
        )),
        "{}",
        o.stderr
    );
    let o = run(&[
        "eval",
        "--manifest",
        s(&manifest),
        "--json",
        s(tmp.path()),
        "--no-cache",
    ]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("is a folder"), "{}", o.stderr);
}

/// `ingest --data` analyses as `serve` on that directory would: the config file and the
/// `SHAPESEEK_*` variables apply (it took the defaults, so under a server run with other
/// eigenpairs every stored signature was recomputed at the ingest's start, then back by the
/// next `serve`), but not the cluster's (`SHAPESEEK_STORE`, `_QUEUE`, `_SHARD`).
#[test]
fn ingest_into_a_data_dir_takes_the_servers_configuration() {
    let tmp = tempfile::tempdir().unwrap();
    let files = meshes(&tmp.path().join("m"), 2, 300);
    let keys = |data: &Path| -> Vec<String> {
        let store = shapeseek::index::Store::open(data).unwrap();
        store
            .all()
            .unwrap()
            .into_iter()
            .map(|(rec, _)| rec.spec_key)
            .collect()
    };
    let d = tmp.path().join("env");
    let o = Command::new(BIN)
        .args(["ingest", "--quiet", "--data", s(&d), s(&files[0])])
        .env("SHAPESEEK_EIGENPAIRS", "60")
        // A cluster node's settings exported in the same shell do not apply to a data
        // directory (a shard without a store made the configuration invalid).
        .env("SHAPESEEK_SHARD", "0/2")
        .env("SHAPESEEK_QUEUE", "nats://127.0.0.1:1")
        .env_remove("SHAPESEEK_STORE")
        .env_remove("SHAPESEEK_CONFIG")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let k = keys(&d);
    assert!(k.len() == 1 && k[0].ends_with("-k60"), "{k:?}");
    let d = tmp.path().join("file");
    let cfg = tmp.path().join("server.toml");
    std::fs::write(&cfg, "eigenpairs = 64\n").unwrap();
    let o = Command::new(BIN)
        .args([
            "ingest",
            "--quiet",
            "--data",
            s(&d),
            "--config",
            s(&cfg),
            s(&files[1]),
        ])
        .env_remove("SHAPESEEK_EIGENPAIRS")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let k = keys(&d);
    assert!(k.len() == 1 && k[0].ends_with("-k64"), "{k:?}");
}

/// While the index loads (here: every stored signature recomputed for other eigenpairs), the
/// port answers: `/healthz` 200 and `/readyz` 503 `server.not_ready` with `Retry-After`. Before,
/// the port was bound and nothing answered until the load ended (a health check hung 8 s on
/// 30 shapes).
#[test]
fn a_loading_server_answers_health_checks() {
    let tmp = tempfile::tempdir().unwrap();
    let files = meshes(&tmp.path().join("m"), 12, 3000);
    let data = tmp.path().join("d");
    let mut args = vec!["ingest", "--quiet", "--data", s(&data)];
    args.extend(files.iter().map(|f| s(f)));
    let o = run(&args);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut child = Command::new(BIN)
        .args([
            "serve",
            "--addr",
            &format!("127.0.0.1:{port}"),
            "--data",
            s(&data),
        ])
        .env("SHAPESEEK_EIGENPAIRS", "70")
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let (mut loading, mut page, mut ready) = (None, None, false);
    while t0.elapsed() < Duration::from_secs(120) && !ready {
        if let (Some((h, _)), Some((r, body))) = (get(port, "/healthz"), get(port, "/readyz")) {
            if r == 503 && loading.is_none() {
                loading = Some((h, body));
                // The viewer too (before: the 503's JSON where the page should be).
                page = get(port, "/");
            }
            ready = r == 200;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = child.kill();
    let _ = child.wait();
    assert!(ready, "never ready");
    let (h, body) = loading.expect("no answer while the index loaded");
    assert_eq!(h, 200);
    assert!(
        body.contains("server.not_ready") && body.to_lowercase().contains("retry-after"),
        "{body}"
    );
    let (code, page) = page.expect("the page answered while the index loaded");
    assert_eq!(code, 200, "{}", &page[..page.len().min(400)]);
    assert!(
        page.to_lowercase().contains("content-type: text/html"),
        "{}",
        &page[..page.len().min(400)]
    );
}

#[test]
fn file_errors_name_their_path() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("nope.obj");
    let o = run(&["spectrum", s(&missing)]);
    assert_eq!(o.code, 74);
    assert!(
        o.stderr.contains(&format!(
            "cannot read {}: No such file or directory",
            s(&missing)
        )),
        "{}",
        o.stderr
    );
    let bad = tmp.path().join("bad.off");
    std::fs::write(&bad, "OFF\n3 1 0\n0 0 0\n1 0 0\n").unwrap();
    let o = run(&["spectrum", s(&bad)]);
    assert_eq!(o.code, 65);
    assert!(
        o.stderr.contains(&format!("{}: OFF", s(&bad))),
        "{}",
        o.stderr
    );
    let o = run(&["search", "--url", "http://127.0.0.1:9", s(&missing)]);
    assert_eq!(o.code, 74);
    assert!(o.stderr.contains(s(&missing)), "{}", o.stderr);
}

#[test]
fn spectrum_refuses_more_eigenpairs_than_vertices() {
    // icosphere:1 has 42 vertices.
    let o = run(&["spectrum", "--generate", "icosphere:1", "--k", "1000"]);
    assert_eq!(o.code, 65, "{}{}", o.stdout, o.stderr);
    assert!(
        o.stderr.contains("42 vertices") && o.stderr.contains("at most 42 eigenpairs"),
        "{}",
        o.stderr
    );
    let o = run(&[
        "spectrum",
        "--generate",
        "icosphere:1",
        "--k",
        "42",
        "--json",
    ]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(o.json()["k"], 42);
}

#[test]
fn migrate_refuses_a_directory_without_an_index() {
    let tmp = tempfile::tempdir().unwrap();
    let typo = tmp.path().join("typo");
    let o = run(&["migrate", "--data", s(&typo)]);
    assert_eq!(o.code, 65, "{}", o.stdout);
    assert!(
        o.stderr.contains(s(&typo)) && o.stderr.contains("nothing to migrate"),
        "{}",
        o.stderr
    );
    assert!(!typo.exists(), "nothing was created");
    // An existing folder that is not an index is left as it was.
    let other = tmp.path().join("photos");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("a.jpg"), "x").unwrap();
    let o = run(&["migrate", "--data", s(&other)]);
    assert_eq!(o.code, 65);
    assert!(
        o.stderr.contains("not a shapeseek data directory"),
        "{}",
        o.stderr
    );
    assert_eq!(std::fs::read_dir(&other).unwrap().count(), 1);
}

/// Makes the index in `data` a version-1 index (no payloads), as `tests/server.rs` does.
fn make_version_1(data: &Path) {
    let db = sled::open(data.join("db")).unwrap();
    db.open_tree("payloads").unwrap().clear().unwrap();
    db.flush().unwrap();
    drop(db);
    shapeseek::index::migrate::stamp_version(data, 1).unwrap();
}

#[test]
fn migrate_keeps_its_backup_inside_the_data_directory() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("m");
    meshes(&dir, 2, 400);
    let data = tmp.path().join("data");
    let o = run(&["ingest", "--data", s(&data), s(&dir)]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    make_version_1(&data);
    let o = run(&["ingest", "--data", s(&data), s(&dir)]);
    assert_ne!(o.code, 0);
    assert!(o.stderr.contains("shapeseek migrate"), "{}", o.stderr);

    let o = run(&["migrate", "--data", s(&data)]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    let backup = o
        .stdout
        .trim()
        .rsplit_once("backup at ")
        .map(|(_, b)| PathBuf::from(b))
        .unwrap_or_else(|| panic!("no backup path: {}", o.stdout));
    assert_eq!(
        backup.parent(),
        Some(data.join("backups").as_path()),
        "{}",
        o.stdout
    );
    assert!(
        backup
            .file_name()
            .unwrap()
            .to_string_lossy()
            .ends_with("-v1"),
        "{}",
        backup.display()
    );
    let db = sled::open(backup.join("db")).unwrap();
    assert_eq!(
        shapeseek::index::store::read_schema_version(&db).unwrap(),
        Some(1),
        "the backup is the version-1 original"
    );
    assert_eq!(db.open_tree("shapes").unwrap().len(), 2);
    drop(db);
    // The upgraded index opens with its backup inside, and keeps its shapes.
    let o = run(&["ingest", "--data", s(&data), "--json", s(&dir)]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(o.json()["existing"], 2);
    let o = run(&["migrate", "--data", s(&data)]);
    assert!(o.stdout.contains("up to date"), "{}", o.stdout);
}

#[test]
fn an_unwritable_data_directory_is_named_with_a_hint() {
    let tmp = tempfile::tempdir().unwrap();
    // A data directory below a regular file can never be created.
    let file = tmp.path().join("file");
    std::fs::write(&file, "x").unwrap();
    let below = file.join("data");
    let o = run(&["serve", "--addr", "127.0.0.1:0", "--data", s(&below)]);
    assert_eq!(o.code, 74, "{}", o.stderr);
    assert!(
        o.stderr
            .contains(&format!("data directory {} is not writable", s(&below))),
        "{}",
        o.stderr
    );
    // Permissions: a directory the process may not write. Root may write anywhere, so as root
    // the server is run as `nobody` (setpriv); without setpriv that half is skipped.
    let locked = tmp.path().join("locked");
    std::fs::create_dir(&locked).unwrap();
    let is_root = Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false);
    let out = if is_root {
        if Command::new("setpriv").arg("--version").output().is_err() {
            println!("SKIPPED: running as root without setpriv; the permission case is not run");
            return;
        }
        // `nobody` must reach the binary and the directory; the directory stays root's, 0755.
        make_traversable(Path::new(BIN));
        make_traversable(&locked);
        Command::new("setpriv")
            .args(["--reuid=65534", "--regid=65534", "--clear-groups", BIN])
            .args(["serve", "--addr", "127.0.0.1:0", "--data", s(&locked)])
            .output()
            .unwrap()
    } else {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&locked, std::fs::Permissions::from_mode(0o555)).unwrap();
        Command::new(BIN)
            .args(["serve", "--addr", "127.0.0.1:0", "--data", s(&locked)])
            .output()
            .unwrap()
    };
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(74), "{err}");
    assert!(
        err.contains(&format!("data directory {} is not writable", s(&locked))),
        "{err}"
    );
    assert!(err.contains("Permission denied"), "{err}");
    assert!(err.contains("chown -R 10001:10001"), "{err}");
}

/// Lets other users traverse every ancestor of `p` (tests only: the temporary directory and
/// the target directory).
fn make_traversable(p: &Path) {
    use std::os::unix::fs::PermissionsExt;
    for a in p.ancestors().skip(1) {
        if let Ok(m) = std::fs::metadata(a) {
            let mode = m.permissions().mode();
            if mode & 0o001 == 0 {
                let _ = std::fs::set_permissions(a, std::fs::Permissions::from_mode(mode | 0o001));
            }
        }
    }
}

/// `eval` over a manifest with a row that cannot be analysed: the figures are over the other
/// shapes, stderr names the row, and the exit status is 1 (it was 0, and a script comparing
/// figures could not tell a run over fewer shapes).
#[test]
fn eval_that_leaves_shapes_out_says_so_and_exits_1() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("samples");
    let o = run(&["samples", "--out", s(&dir)]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let manifest = dir.join("manifest.csv");
    let o = run(&["eval", "--manifest", s(&manifest), "--no-cache"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.contains("0 left out"), "{}", o.stdout);

    std::fs::write(dir.join("broken.obj"), "v 0 0 0\nv 1 0 0\nf 1 2 7\n").unwrap();
    let mut csv = std::fs::read_to_string(&manifest).unwrap();
    let first_class = csv
        .lines()
        .nth(1)
        .unwrap()
        .split(',')
        .nth(2)
        .unwrap()
        .to_string();
    csv.push_str(&format!("broken,broken.obj,{first_class},noise,1,0\n"));
    std::fs::write(&manifest, csv).unwrap();
    let o = run(&["eval", "--manifest", s(&manifest), "--no-cache"]);
    assert_eq!(o.code, 1, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.contains("1 left out"), "{}", o.stdout);
    assert!(
        o.stdout.contains("| All"),
        "the figures are printed: {}",
        o.stdout
    );
    assert!(
        o.stderr.contains("1 of 31 shapes could not be analysed")
            && o.stderr.contains("broken.obj [mesh.parse]"),
        "{}",
        o.stderr
    );
}

#[test]
fn head_on_a_stored_mesh_answers_its_headers_without_converting() {
    // A separate process, so that its /metrics counts only this test's conversions.
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("meshes");
    meshes(&dir, 1, 2000);
    let server = Server::start(&tmp.path().join("data"));
    let port: u16 = server.url.rsplit(':').next().unwrap().parse().unwrap();
    let o = run(&["ingest", "--url", &server.url, s(&dir)]);
    assert_eq!(o.code, 0, "{}\n{}", o.stdout, o.stderr);
    let (code, raw) = get(port, "/v1/shapes").unwrap();
    assert_eq!(code, 200);
    let body: Value = serde_json::from_str(raw.split("\r\n\r\n").nth(1).unwrap()).unwrap();
    let rec = &body["items"][0];
    let id = rec["id"].as_str().unwrap();
    let conversions = || {
        let (_, m) = get(port, "/metrics").unwrap();
        m.lines()
            .find(|l| l.starts_with("shapeseek_conversions_total"))
            .map_or(0, |l| l.rsplit(' ').next().unwrap().parse::<u64>().unwrap())
    };

    // The original: its length from the record, its tag, no body.
    let (code, head) = request(port, "HEAD", &format!("/v1/shapes/{id}/mesh")).unwrap();
    assert_eq!(code, 200, "{head}");
    let (_, full) = get(port, &format!("/v1/shapes/{id}/mesh")).unwrap();
    assert_eq!(header(&head, "etag"), header(&full, "etag"));
    assert_eq!(
        header(&head, "content-length"),
        Some(rec["bytes"].to_string().as_str())
    );
    assert_eq!(
        header(&head, "content-length"),
        header(&full, "content-length")
    );
    assert!(head.ends_with("\r\n\r\n"), "a body after HEAD: {head}");
    // Every format: the conversion's tag and disposition, no length (only writing it would
    // tell), no body, and nothing converted.
    for f in ["obj", "off", "ply", "stl", "gltf", "glb"] {
        let path = format!("/v1/shapes/{id}/mesh?format={f}");
        let (code, head) = request(port, "HEAD", &path).unwrap();
        assert_eq!(code, 200, "{f}: {head}");
        assert!(head.ends_with("\r\n\r\n"), "{f}: a body after HEAD: {head}");
        assert_eq!(header(&head, "content-length"), None, "{f}: {head}");
        assert_eq!(header(&head, "transfer-encoding"), None, "{f}: {head}");
        let disposition = format!("attachment; filename=\"{id}.{f}\"");
        assert_eq!(
            header(&head, "content-disposition"),
            Some(disposition.as_str())
        );
        assert!(
            header(&head, "etag").is_some_and(|t| t.contains(&format!("-{f}-"))),
            "{f}: {head}"
        );
    }
    assert_eq!(conversions(), 0, "a HEAD converted");
    // A GET converts, once, under the tag HEAD gave.
    let path = format!("/v1/shapes/{id}/mesh?format=ply");
    let (_, head) = request(port, "HEAD", &path).unwrap();
    let (code, full) = get(port, &path).unwrap();
    assert_eq!(code, 200);
    assert_eq!(header(&head, "etag"), header(&full, "etag"));
    assert!(header(&full, "content-length").is_some());
    assert_eq!(conversions(), 1);
    // An unknown id or format is refused as by GET.
    let (code, _) = request(port, "HEAD", "/v1/shapes/00000000000000ff/mesh").unwrap();
    assert_eq!(code, 404);
    let (code, _) = request(port, "HEAD", &format!("/v1/shapes/{id}/mesh?format=x3d")).unwrap();
    assert_eq!(code, 400);
    server.stop();
}

/// A client that asks for a large original and reads none of it. Its connection is closed once
/// the server's writes have waited `send_stall_timeout_secs`, which frees the response, and the
/// bytes of downloads held at once stay within `max_inflight_response_bytes`: a second download
/// of the same original waits for the first's room and is then served whole. (Before, the
/// silent client kept its connection and the original's memory for as long as TCP kept the
/// connection, and downloads had no bound: forty such clients of a 13 MB original held about 1 GiB.)
#[test]
fn a_client_that_reads_nothing_of_a_download_is_cut_off_and_downloads_are_bounded() {
    use std::io::{Read, Write};
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("meshes");
    let file = meshes(&dir, 1, 500).remove(0);
    // The mesh with 12 MB of comment lines, kept whole as its original (the floor allows it).
    let mut bytes = std::fs::read(&file).unwrap();
    let line = format!("# {}\n", "p".repeat(97));
    while bytes.len() < 12 << 20 {
        bytes.extend_from_slice(line.as_bytes());
    }
    std::fs::write(&file, &bytes).unwrap();
    let server = Server::start_with(
        &tmp.path().join("data"),
        &[
            ("SHAPESEEK_MAX_BODY_BYTES", "16777216"),
            ("SHAPESEEK_STORED_BYTES_FLOOR", "16777216"),
            ("SHAPESEEK_MAX_INFLIGHT_RESPONSE_BYTES", "16777216"),
            ("SHAPESEEK_SEND_STALL_TIMEOUT_SECS", "2"),
        ],
    );
    let port: u16 = server.url.rsplit(':').next().unwrap().parse().unwrap();
    let o = run(&["ingest", "--url", &server.url, s(&dir)]);
    assert_eq!(o.code, 0, "{}\n{}", o.stdout, o.stderr);
    let (_, raw) = get(port, "/v1/shapes").unwrap();
    let body: Value = serde_json::from_str(raw.split("\r\n\r\n").nth(1).unwrap()).unwrap();
    let id = body["items"][0]["id"].as_str().unwrap().to_string();
    assert_eq!(body["items"][0]["bytes"].as_u64(), Some(bytes.len() as u64));
    let counter = |name: &str| {
        let (_, m) = get(port, "/metrics").unwrap();
        m.lines()
            .find(|l| l.starts_with(name))
            .map_or(0, |l| l.rsplit(' ').next().unwrap().parse::<u64>().unwrap())
    };

    // The silent client: a 4 KiB receive buffer, set before it connects.
    let silent = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
    silent.set_recv_buffer_size(4096).unwrap();
    silent
        .connect(&std::net::SocketAddr::from(([127, 0, 0, 1], port)).into())
        .unwrap();
    let mut silent: std::net::TcpStream = silent.into();
    let t0 = Instant::now();
    silent
        .write_all(format!("GET /v1/shapes/{id}/mesh HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes())
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    // A second download of the same original: the first holds 12 of the 16 MiB.
    let (code, full) = {
        let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
        c.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        c.write_all(
            format!("GET /v1/shapes/{id}/mesh HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
                .as_bytes(),
        )
        .unwrap();
        let mut raw = Vec::new();
        c.read_to_end(&mut raw).unwrap();
        let head_end = raw.windows(4).position(|w| w == b"\r\n\r\n").unwrap() + 4;
        let head = String::from_utf8_lossy(&raw[..head_end]).into_owned();
        let code: u16 = head.split(' ').nth(1).unwrap().parse().unwrap();
        (code, raw[head_end..].to_vec())
    };
    let waited = t0.elapsed();
    assert_eq!(code, 200);
    assert!(full == bytes, "the second download is the original, whole");
    assert!(
        waited >= Duration::from_millis(1500),
        "the second download did not wait for room ({waited:?})"
    );
    assert!(counter("shapeseek_downloads_waited_total") >= 1);
    assert_eq!(counter("shapeseek_connections_stalled_total"), 1);
    // The silent client's connection was closed: it gets what was in flight, then the end.
    silent
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut got = Vec::new();
    let end = silent.read_to_end(&mut got);
    assert!(
        got.len() < bytes.len(),
        "the silent client was sent the whole original ({} bytes; {end:?})",
        got.len()
    );
    server.stop();
}
