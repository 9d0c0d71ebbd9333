//! `shapeseek ingest PATH…`: loads mesh files, folders and CSV manifests into an index — through
//! a running server (`--url`) or straight into a data directory (`--data`, in process, through
//! the server's own ingest code, so the index is the same).
//!
//! * A folder is searched recursively for `.obj .gltf .glb .ply .off .stl` files (any case),
//!   in name order; symbolic links to folders are not followed.
//! * A `.csv` file is a manifest: a header with a `path` column (relative to the manifest's
//!   folder), optionally `name` (else `id`, else the file name without extension) and `tags`
//!   (separated by `;`); other columns become `column=value` tags (all of them by default,
//!   or those named by `--tag-columns`). The benchmark manifests
//!   (`id,path,class,transform,strength,source_pose`) read as they are.
//! * Anything else is a mesh file (its extension is the format hint; the bytes decide).
//!
//! Ingest is idempotent by the SHA-256 of the bytes: a file stored before (under any name) is
//! reported as already stored and nothing is computed, so an interrupted run is resumed by
//! running it again. Every failure is listed at the end with its path, problem code and detail;
//! the exit status is 1 when anything failed.
//!
//! Through a server, a file is sent with its name and tags as a multipart upload (they arrive
//! as `--data` stores them); a file larger than the server's `max_body_bytes` is listed as
//! `limit.bytes` without being sent; an upload that breaks off is sent again while the server
//! answers, and when it has not answered for about 7 s the run stops, lists what was not sent
//! and exits with status 69. (A resent file whose first upload was stored, its answer lost,
//! counts as already stored.)

use super::http::{Client, Failure};
use super::{read_file, CliError};
use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde::Serialize;
use std::collections::HashSet;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// File extensions of the mesh formats read from folders.
pub const MESH_EXTENSIONS: [&str; 6] = ["obj", "gltf", "glb", "ply", "off", "stl"];

/// `shapeseek ingest` flags.
#[derive(Debug, Args)]
pub struct IngestArgs {
    /// Mesh files, folders (searched recursively by extension) and CSV manifests.
    #[arg(required = true, value_name = "PATH")]
    pub paths: Vec<PathBuf>,
    /// The server to send the shapes to [env: SHAPESEEK_URL] [default: http://127.0.0.1:8080].
    /// (The variable is read when `--data` is not given: an exported `SHAPESEEK_URL` does not
    /// make `--data` a conflict.)
    #[arg(long, conflicts_with = "data")]
    pub url: Option<String>,
    /// Write straight into this data directory instead (created if missing; no server may be
    /// running on it).
    #[arg(long, value_name = "DIR")]
    pub data: Option<PathBuf>,
    /// With `--data`: the TOML config file of the server that serves that directory [env
    /// SHAPESEEK_CONFIG]. Its settings and the `SHAPESEEK_*` variables apply as they do to
    /// `serve` (eigenpairs, limits, ...): shapes are analysed as that server would, and its
    /// stored signatures are not recomputed for another configuration.
    #[arg(long, value_name = "FILE", requires = "data")]
    pub config: Option<PathBuf>,
    /// Display name of the shape (a single file only; default: the manifest's `name` or `id`
    /// column, else the file name without its extension).
    #[arg(long)]
    pub name: Option<String>,
    /// A tag for every shape (repeat it, or separate tags by commas).
    #[arg(
        long = "tag",
        visible_alias = "tags",
        value_delimiter = ',',
        value_name = "TAG"
    )]
    pub tags: Vec<String>,
    /// Manifest columns that become `column=value` tags (comma-separated; default: every
    /// column but path, name, id and tags; `--tag-columns ''` for none).
    #[arg(long, value_delimiter = ',', value_name = "COLUMNS")]
    pub tag_columns: Option<Vec<String>>,
    /// Files analysed or uploaded at once.
    #[arg(long, short = 'j', default_value_t = 4)]
    pub jobs: usize,
    /// Print the summary as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// No progress bar.
    #[arg(long, short = 'q')]
    pub quiet: bool,
}

/// One shape to ingest.
#[derive(Debug, Clone)]
struct Item {
    path: PathBuf,
    name: String,
    tags: Vec<String>,
}

/// A file (or manifest row) that could not be ingested.
#[derive(Debug, Clone, Serialize)]
pub struct Failed {
    /// The file, or `MANIFEST:LINE` for a bad manifest row.
    pub path: String,
    /// Problem code (`io`, `mesh.parse`, `limit.vertices`, `manifest.row`, ...).
    pub code: String,
    /// What went wrong.
    pub detail: String,
}

/// One stored (or already present) shape.
#[derive(Debug, Clone, Serialize)]
struct Done {
    path: String,
    id: String,
    created: bool,
}

/// What a run did (`--json` prints it).
#[derive(Debug, Serialize)]
struct Summary {
    target: String,
    files: usize,
    created: usize,
    existing: usize,
    failed: Vec<Failed>,
    /// Files not sent because the server stopped answering (0 otherwise).
    not_sent: usize,
    seconds: f64,
    shapes: Vec<Done>,
}

/// The outcome of ingesting one file's bytes.
pub enum Stored {
    /// Stored now under this id.
    New(String),
    /// The same bytes were stored before under this id (nothing computed).
    Existing(String),
}

/// Where shapes go.
trait Target: Sync {
    fn ingest(
        &self,
        bytes: Vec<u8>,
        path: &Path,
        name: &str,
        tags: &[String],
    ) -> Result<Stored, Failure>;

    /// The target is gone (a server that stopped answering): no further file is sent.
    fn gone(&self) -> bool {
        false
    }
}

/// How often a file whose upload broke off is sent again while the server still answers (a
/// connection closed by a restart, or a body refused mid-send by a busy server's budget).
const RESENDS: u32 = 2;

/// After an upload broke off, the server is asked whether it is there this many times, 0, 1,
/// 2 and 4 s apart (a restarting server does not listen for a moment), before the run stops.
const PROBES: u32 = 4;

/// A running server.
struct Remote {
    client: Client,
    /// The server's `max_body_bytes` (`GET /v1/index`'s `limits`), when it says.
    max_body: Option<u64>,
    /// Set when an upload broke off and the server no longer answers.
    gone: AtomicBool,
}

impl Remote {
    fn new(client: Client) -> Remote {
        let max_body = client
            .get("/v1/index")
            .ok()
            .and_then(|a| a.json["limits"]["max_body_bytes"].as_u64());
        Remote {
            client,
            max_body,
            gone: AtomicBool::new(false),
        }
    }
}

impl Target for Remote {
    /// Sends the file as `multipart/form-data` with its name and tags in the JSON `metadata`
    /// part, so they arrive as `--data` stores them (the query string's comma-separated `tags`
    /// split a manifest tag such as `pose=sitting, arms up` in two and trimmed spaces).
    fn ingest(
        &self,
        bytes: Vec<u8>,
        path: &Path,
        name: &str,
        tags: &[String],
    ) -> Result<Stored, Failure> {
        let meta = serde_json::json!({ "name": name, "tags": tags }).to_string();
        let file_name = path
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default();
        let (ctype, body) = super::http::multipart(&file_name, &bytes, "metadata", meta.as_bytes());
        drop(bytes);
        // A body over the server's limit is not sent: the server would cut the connection
        // while it is being sent, and the failure would read as a server that cannot be reached.
        if let Some(max) = self.max_body.filter(|&m| body.len() as u64 > m) {
            return Err(Failure {
                status: 413,
                code: "limit.bytes".into(),
                detail: format!(
                    "{} bytes as an upload (the file with its name and tags): the server \
                     takes up to {max} bytes (its max_body_bytes); not sent",
                    body.len()
                ),
            });
        }
        let mut query = Vec::new();
        if let Some(f) = super::format_hint(path) {
            query.push(("format", f.name().to_string()));
        }
        let mut resends = 0;
        let a = loop {
            match self.client.post("/v1/shapes", &query, &ctype, &body) {
                // The upload broke off: a server that still answers gets it again (ingest is
                // idempotent by content); one that does not ends the run.
                Err(f) if f.status == 0 => {
                    let answers = (0..PROBES).any(|i| {
                        if i > 0 {
                            std::thread::sleep(std::time::Duration::from_secs(1 << (i - 1)));
                        }
                        self.client.probe()
                    });
                    if !answers {
                        self.gone.store(true, Ordering::Relaxed);
                        return Err(Failure {
                            detail: format!("{}; the server no longer answers", f.detail),
                            ..f
                        });
                    }
                    if resends == RESENDS {
                        return Err(f);
                    }
                    resends += 1;
                    std::thread::sleep(std::time::Duration::from_secs(resends.into()));
                }
                r => break r?,
            }
        };
        let id = a.json["id"].as_str().unwrap_or_default().to_string();
        Ok(if a.status == 201 {
            Stored::New(id)
        } else {
            Stored::Existing(id)
        })
    }

    fn gone(&self) -> bool {
        self.gone.load(Ordering::Relaxed)
    }
}

impl Target for local::Local {
    fn ingest(
        &self,
        bytes: Vec<u8>,
        path: &Path,
        name: &str,
        tags: &[String],
    ) -> Result<Stored, Failure> {
        self.ingest(bytes, super::format_hint(path), name, tags)
    }
}

/// Runs `shapeseek ingest`. `Ok(false)` when some inputs failed (they are listed).
pub fn run(args: &IngestArgs) -> Result<bool, CliError> {
    let t0 = Instant::now();
    if args.jobs == 0 || args.jobs > 256 {
        return Err(CliError::usage("--jobs must be in 1..=256"));
    }
    for t in &args.tags {
        check_tag(t).map_err(|m| CliError::usage(format!("--tag {t:?}: {m}")))?;
    }
    let (items, mut failed) = collect(args)?;
    if items.is_empty() && failed.is_empty() {
        let given: Vec<String> = args.paths.iter().map(|p| p.display().to_string()).collect();
        return Err(CliError::usage(format!(
            "no mesh files found in {} (files ending in .obj, .gltf, .glb, .ply, .off or .stl, \
             folders holding such files, or CSV manifests)",
            given.join(", ")
        )));
    }
    // Paths that could not be read count as files; bad manifest rows do not.
    let unread = failed.iter().filter(|f| !is_row(f)).count();
    if let Some(n) = &args.name {
        check_name(n).map_err(|m| CliError::usage(format!("--name {n:?}: {m}")))?;
        if items.len() + failed.len() != 1 {
            return Err(CliError::usage(format!(
                "--name names one shape, but {} files were given (names default to the file \
                 names; a manifest can carry a `name` column)",
                items.len() + failed.len()
            )));
        }
    }
    let (target, label): (Box<dyn Target>, String) = match &args.data {
        Some(dir) => {
            super::datadir::ensure_writable(dir)?;
            let l = local::Local::open(dir, args.jobs, args.config.as_deref()).map_err(|e| {
                let mut e = CliError::from(e);
                if e.message.contains("in use by another process") {
                    e.message
                        .push_str("; ingest through that server instead (--url) or stop it first");
                }
                e
            })?;
            (Box::new(l), dir.display().to_string())
        }
        None => {
            let url = args.url.clone().unwrap_or_else(|| {
                std::env::var("SHAPESEEK_URL")
                    .ok()
                    .filter(|u| !u.is_empty())
                    .unwrap_or_else(|| "http://127.0.0.1:8080".into())
            });
            let c = Client::new(&url)?;
            c.ready()?;
            let label = c.base().to_string();
            (Box::new(Remote::new(c)), label)
        }
    };

    let bar = if args.quiet || !std::io::stderr().is_terminal() {
        ProgressBar::with_draw_target(Some(items.len() as u64), ProgressDrawTarget::hidden())
    } else {
        ProgressBar::new(items.len() as u64)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} ({per_sec}, eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let next = AtomicUsize::new(0);
    let done = Mutex::new(Vec::<Done>::new());
    let errors = Mutex::new(Vec::<Failed>::new());
    let counts = [AtomicUsize::new(0), AtomicUsize::new(0)];
    std::thread::scope(|s| {
        for _ in 0..args.jobs.min(items.len()) {
            s.spawn(|| loop {
                if target.gone() {
                    break;
                }
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(item) = items.get(i) else { break };
                let shown = item.path.display().to_string();
                let name = args.name.clone().unwrap_or_else(|| item.name.clone());
                let res = read_file(&item.path)
                    .map_err(|e| Failure {
                        status: 0,
                        code: e.code,
                        detail: e.message,
                    })
                    .and_then(|bytes| target.ingest(bytes, &item.path, &name, &item.tags));
                match res {
                    Ok(stored) => {
                        let (id, created) = match stored {
                            Stored::New(id) => (id, true),
                            Stored::Existing(id) => (id, false),
                        };
                        counts[usize::from(!created)].fetch_add(1, Ordering::Relaxed);
                        lock(&done).push(Done {
                            path: shown,
                            id,
                            created,
                        });
                    }
                    Err(f) => {
                        bar.suspend(|| {
                            if !args.json {
                                eprintln!("failed: {shown}: [{}] {}", f.code, f.detail)
                            }
                        });
                        lock(&errors).push(Failed {
                            path: shown,
                            code: f.code,
                            detail: f.detail,
                        });
                    }
                }
                bar.inc(1);
            });
        }
    });
    bar.finish_and_clear();
    let mut shapes = done.into_inner().unwrap_or_else(|p| p.into_inner());
    shapes.sort_by(|a, b| a.path.cmp(&b.path));
    let errors = errors.into_inner().unwrap_or_else(|p| p.into_inner());
    let not_sent = items.len() - shapes.len() - errors.len();
    failed.extend(errors);
    failed.sort_by(|a, b| a.path.cmp(&b.path));
    let summary = Summary {
        target: label,
        files: items.len() + unread,
        created: counts[0].load(Ordering::Relaxed),
        existing: counts[1].load(Ordering::Relaxed),
        seconds: t0.elapsed().as_secs_f64(),
        failed,
        not_sent,
        shapes,
    };
    print_summary(&summary, args.json);
    if target.gone() {
        // Before, every remaining file was tried and listed as "cannot reach", and the run
        // ended with status 1 as if those files were at fault.
        return Err(CliError::new(
            "server.unreachable",
            format!(
                "the server at {} stopped answering: {not_sent} of {} files were not sent; \
                 run the same command again once it is back (files it stored are skipped)",
                summary.target,
                items.len()
            ),
            69,
        ));
    }
    Ok(summary.failed.is_empty())
}

/// A manifest-row failure (counted as a row, not a file).
fn is_row(f: &Failed) -> bool {
    f.code.starts_with("manifest.")
}

fn print_summary(s: &Summary, json: bool) {
    if json {
        println!(
            "{}",
            serde_json::to_string(s).unwrap_or_else(|_| "{}".into())
        );
        return;
    }
    let not_sent = if s.not_sent > 0 {
        format!(", {} not sent", s.not_sent)
    } else {
        String::new()
    };
    println!(
        "ingested into {}: {} new, {} already stored, {} failed{not_sent} ({:.1} s)",
        s.target,
        s.created,
        s.existing,
        s.failed.len(),
        s.seconds
    );
    if !s.failed.is_empty() {
        let w = s.failed.iter().map(|f| f.path.len()).max().unwrap_or(0);
        let c = s.failed.iter().map(|f| f.code.len()).max().unwrap_or(0);
        println!("failures:");
        for f in &s.failed {
            println!("  {:w$}  {:c$}  {}", f.path, f.code, f.detail);
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// The server's rule for names (1 to 256 characters, no control characters).
fn check_name(n: &str) -> Result<(), String> {
    if n.is_empty() || n.chars().count() > 256 || n.chars().any(char::is_control) {
        return Err("1 to 256 characters, no control characters".into());
    }
    Ok(())
}

/// The server's rule for tags (1 to 64 characters, no control characters).
fn check_tag(t: &str) -> Result<(), String> {
    if t.is_empty() || t.chars().count() > 64 || t.chars().any(char::is_control) {
        return Err("1 to 64 characters, no control characters".into());
    }
    Ok(())
}

/// Expands the arguments into items; paths that cannot be used become failures. A missing
/// argument path is a failure like a bad file (listed, exit 1), not an abort.
fn collect(args: &IngestArgs) -> Result<(Vec<Item>, Vec<Failed>), CliError> {
    let mut items = Vec::new();
    let mut failed = Vec::new();
    for p in &args.paths {
        let meta = match std::fs::metadata(p) {
            Ok(m) => m,
            Err(e) => {
                failed.push(Failed {
                    path: p.display().to_string(),
                    code: "io".into(),
                    detail: format!("cannot read: {}", super::io_reason(&e)),
                });
                continue;
            }
        };
        if meta.is_dir() {
            walk(p, args, &mut items, &mut failed);
        } else if has_extension(p, "csv") {
            manifest(p, args, &mut items, &mut failed);
        } else {
            items.push(file_item(p.clone(), args, Vec::new()));
        }
    }
    Ok((items, failed))
}

fn has_extension(p: &Path, ext: &str) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case(ext))
}

fn stem(p: &Path) -> String {
    p.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

fn file_item(path: PathBuf, args: &IngestArgs, mut tags: Vec<String>) -> Item {
    for t in &args.tags {
        if !tags.contains(t) {
            tags.push(t.clone());
        }
    }
    Item {
        name: stem(&path),
        path,
        tags,
    }
}

/// Mesh files under `dir`, recursively, in name order.
fn walk(dir: &Path, args: &IngestArgs, items: &mut Vec<Item>, failed: &mut Vec<Failed>) {
    let entries = match std::fs::read_dir(dir) {
        Ok(rd) => rd.collect::<Result<Vec<_>, _>>(),
        Err(e) => Err(e),
    };
    let mut entries = match entries {
        Ok(v) => v,
        Err(e) => {
            failed.push(Failed {
                path: dir.display().to_string(),
                code: "io".into(),
                detail: format!("cannot read the folder: {}", super::io_reason(&e)),
            });
            return;
        }
    };
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        let path = e.path();
        let Ok(ty) = e.file_type() else { continue };
        if ty.is_dir() {
            walk(&path, args, items, failed);
        } else if (ty.is_file() || (ty.is_symlink() && path.is_file()))
            && MESH_EXTENSIONS.iter().any(|x| has_extension(&path, x))
        {
            items.push(file_item(path, args, Vec::new()));
        }
    }
}

/// Rows of a CSV manifest.
fn manifest(csv_path: &Path, args: &IngestArgs, items: &mut Vec<Item>, failed: &mut Vec<Failed>) {
    let shown = csv_path.display().to_string();
    let fail = |failed: &mut Vec<Failed>, path: String, code: &str, detail: String| {
        failed.push(Failed {
            path,
            code: code.into(),
            detail,
        })
    };
    let mut rdr = match csv::ReaderBuilder::new()
        .flexible(false)
        .from_path(csv_path)
    {
        Ok(r) => r,
        Err(e) => {
            return fail(
                failed,
                shown,
                "io",
                format!("cannot read the manifest: {e}"),
            )
        }
    };
    let header: Vec<String> = match rdr.headers() {
        Ok(h) => h.iter().map(|s| s.trim().to_string()).collect(),
        Err(e) => return fail(failed, shown, "manifest.header", e.to_string()),
    };
    let col = |name: &str| header.iter().position(|h| h == name);
    let Some(path_col) = col("path") else {
        return fail(
            failed,
            shown,
            "manifest.header",
            format!("no `path` column (header: {})", header.join(",")),
        );
    };
    let (name_col, id_col, tags_col) = (col("name"), col("id"), col("tags"));
    let tag_cols: Vec<usize> = match &args.tag_columns {
        Some(list) => {
            let mut v = Vec::new();
            for c in list.iter().filter(|c| !c.is_empty()) {
                match col(c) {
                    Some(i) => v.push(i),
                    None => {
                        return fail(
                            failed,
                            shown,
                            "manifest.header",
                            format!(
                                "--tag-columns names {c:?}, which is not a column (header: {})",
                                header.join(",")
                            ),
                        )
                    }
                }
            }
            v
        }
        None => (0..header.len())
            .filter(|i| !["path", "name", "id", "tags"].contains(&header[*i].as_str()))
            .collect(),
    };
    let base = csv_path.parent().unwrap_or(Path::new("."));
    let mut seen = HashSet::new();
    for rec in rdr.records() {
        let rec = match rec {
            Ok(r) => r,
            Err(e) => {
                let line = e.position().map(|p| p.line()).unwrap_or(0);
                fail(
                    failed,
                    format!("{shown}:{line}"),
                    "manifest.row",
                    e.to_string(),
                );
                continue;
            }
        };
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        let at = format!("{shown}:{line}");
        let get = |i: Option<usize>| {
            i.and_then(|i| rec.get(i))
                .map(str::trim)
                .filter(|s| !s.is_empty())
        };
        let Some(rel) = get(Some(path_col)) else {
            fail(failed, at, "manifest.row", "empty `path`".into());
            continue;
        };
        let path = base.join(rel);
        if !seen.insert(path.clone()) {
            fail(failed, at, "manifest.row", format!("{rel} is listed twice"));
            continue;
        }
        let mut tags: Vec<String> = get(tags_col)
            .map(|t| {
                t.split(';')
                    .map(|s| s.trim().to_string())
                    .filter(|s| !s.is_empty())
                    .collect()
            })
            .unwrap_or_default();
        for &c in &tag_cols {
            if let Some(v) = get(Some(c)) {
                tags.push(format!("{}={v}", header[c]));
            }
        }
        if let Some(bad) = tags.iter().find(|t| check_tag(t).is_err()) {
            fail(
                failed,
                at,
                "manifest.row",
                format!("tag {bad:?}: 1 to 64 characters, no control characters"),
            );
            continue;
        }
        let mut item = file_item(path, args, tags);
        if let Some(n) = get(name_col).or(get(id_col)) {
            if let Err(m) = check_name(n) {
                fail(failed, at, "manifest.row", format!("name {n:?}: {m}"));
                continue;
            }
            item.name = n.to_string();
        }
        if item.tags.len() > 32 {
            fail(
                failed,
                at,
                "manifest.row",
                format!("{} tags (at most 32)", item.tags.len()),
            );
            continue;
        }
        items.push(item);
    }
}

/// In-process ingest into a data directory: the server's own load and ingest path
/// (`server::state::App`), without HTTP. The one place the CLI touches the server's state.
mod local {
    use super::super::http::Failure;
    use super::Stored;
    use shapeseek::server::state::{App, Upload};
    use shapeseek::server::ServerConfig;
    use std::path::Path;
    use std::sync::Arc;

    /// An index opened in this process.
    pub struct Local {
        app: Arc<App>,
        rt: tokio::runtime::Runtime,
    }

    impl Local {
        /// Opens (or creates) the index in `dir` with the configuration `serve --data dir`
        /// would have (the config file `config` or `SHAPESEEK_CONFIG`, then the `SHAPESEEK_*`
        /// variables), `jobs` analyses at once. Before, it took the defaults: under a server
        /// run with `SHAPESEEK_EIGENPAIRS=60` an ingest recomputed every stored signature at
        /// its start, and the next `serve` recomputed them all back.
        pub fn open(dir: &Path, jobs: usize, config: Option<&Path>) -> shapeseek::Result<Local> {
            let serve = shapeseek::server::ServeArgs {
                data: Some(dir.to_path_buf()),
                config: config.map(Path::to_path_buf),
                ..Default::default()
            };
            // This process writes the sled directory, alone: the cluster settings do not apply,
            // and an exported `SHAPESEEK_SHARD` (which needs a store and a queue) no longer
            // makes the configuration invalid.
            let env = std::env::vars().filter(|(k, _)| {
                !matches!(
                    k.as_str(),
                    "SHAPESEEK_STORE" | "SHAPESEEK_QUEUE" | "SHAPESEEK_SHARD"
                )
            });
            let defaults = ServerConfig::default();
            let cfg = ServerConfig {
                workers: jobs,
                queue_capacity: jobs,
                store: defaults.store,
                queue: defaults.queue,
                shard: defaults.shard,
                ..serve.to_config_from(env)?
            };
            let engine = cfg.engine();
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()?;
            let store = rt.block_on(shapeseek::storage::open_dir(dir.to_path_buf()))?;
            let handle = rt.handle().clone();
            let app = Arc::new(App::load(cfg, engine, store, handle)?);
            Ok(Local { app, rt })
        }

        /// Ingests one upload as `POST /v1/shapes` does.
        pub fn ingest(
            &self,
            bytes: Vec<u8>,
            hint: Option<shapeseek::mesh::Format>,
            name: &str,
            tags: &[String],
        ) -> Result<Stored, Failure> {
            let up = Upload {
                bytes: bytes.into(),
                hint,
                name: Some(name.to_string()),
                tags: tags.to_vec(),
            };
            match self.rt.block_on(self.app.ingest(up)) {
                Ok(r) if r.created => Ok(Stored::New(r.id)),
                Ok(r) => Ok(Stored::Existing(r.id)),
                Err(e) => Err(Failure {
                    status: e.status.as_u16(),
                    code: e.code,
                    detail: e.detail,
                }),
            }
        }
    }

    impl Drop for Local {
        fn drop(&mut self) {
            // Everything acknowledged was flushed; this also persists the calibration state.
            let _ = self.rt.block_on(self.app.store.flush());
        }
    }
}
