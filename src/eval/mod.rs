//! `shapeseek eval`: the retrieval benchmark harness (bench README protocol, paper §5).
//!
//! ```text
//! shapeseek eval --manifest M [--config C] [--json OUT] [--out DIR] [--cache DIR] [--jobs N] [--k K]
//! ```
//!
//! 1. Reads the manifest ([`manifest`]); a mesh that cannot be read or analysed is reported (id,
//!    error code, message) and left out of every ranking.
//! 2. Computes each shape's analysis (prepared mesh + spectrum) and signatures once, in parallel
//!    (rayon), cached on disk ([`cache`]) under the mesh content hash, the analysis options
//!    (preparation and eigen options, `k` among them) and `SignatureSpec::key()`. Default cache
//!    directory: `$XDG_CACHE_HOME/shapeseek/eval`, else `./.cache/shapeseek-eval`.
//! 3. Calibrates the corpus windows and builds the histograms, then, per configuration, scores
//!    every shape against every other and evaluates the rankings ([`metrics`]).
//! 4. Writes a Markdown summary to stdout, and optionally `--json OUT` and `--out DIR`
//!    (`results.md` with tables shaped like the bench REFERENCE.md, ROC / PR curves as SVG).
//!
//! Configurations: without `--config`, `ranking::paper_configs()` plus `ranking::default_config()`.
//! `--config` takes a JSON or TOML file holding one configuration (`{name, signature, query}`), a
//! list of them, or `{configs = [...]}`; or a preset: `paper`, `default`, `all`, or a comma-separated
//! list of configuration names from the presets. Configurations whose signature specifications
//! differ only in their channel lists share one union specification, so each channel is computed
//! once per shape.

pub mod cache;
pub mod manifest;
pub mod metrics;
pub mod plot;
pub mod report;

use crate::mesh::read::{read_mesh, Format, ReadLimits};
use crate::pipeline::{analyze, AnalyzeOptions};
use crate::ranking::{self, Config, Prepared, QuerySpec};
use crate::signature::{compute_signature, Signature, SignatureSpec};
use crate::{Error, Result};
use cache::{hash_parts, Cache};
use manifest::Manifest;
use metrics::Evaluation;
use rayon::prelude::*;
use report::{ConfigResult, Failure, Reference};
use serde_json::{json, Value};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Arguments of `shapeseek eval`.
#[derive(Debug, Clone, clap::Args)]
pub struct EvalArgs {
    /// Manifest CSV (`id,path,class,transform,strength,source_pose`; paths relative to it).
    #[arg(long)]
    pub manifest: PathBuf,
    /// Configurations: a JSON/TOML file (one config, a list, or `{configs=[...]}`), or a preset
    /// (`paper`, `default`, `all`, or comma-separated configuration names). Default: `all`
    /// (the paper's configurations and the baselines, plus the product default).
    #[arg(long)]
    pub config: Option<String>,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write `results.md` and ROC / PR curves (SVG) into this folder.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Cache folder (default `$XDG_CACHE_HOME/shapeseek/eval`, else `./.cache/shapeseek-eval`).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Do not read or write the cache.
    #[arg(long)]
    pub no_cache: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub jobs: Option<usize>,
    /// Number of eigenpairs.
    #[arg(long, default_value_t = 100)]
    pub k: usize,
    /// Reference figures to show side by side: `reference-map.json` style JSON or a REFERENCE.md.
    /// Default: `reference-map.json`, else `REFERENCE.md`, next to the manifest, else the
    /// REFERENCE.md of the parent folder when it describes this manifest's split.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Also print the per-strength mAP table of every configuration (the report has it for the
    /// configurations of REFERENCE.md's per-strength table and `default`).
    #[arg(long)]
    pub per_strength: bool,
    /// No progress output.
    #[arg(long)]
    pub quiet: bool,
    // --- Retrieval-quality options: see `crate::rerank` and docs/quality.md. ---
    /// Re-ranking stage applied to every configuration's ranking, evaluated as an extra
    /// configuration `<config>+<STAGE>` (repeatable): `sgw:K[:key=value]...`, a JSON stage or a
    /// JSON file (see `shapeseek::rerank::eval`).
    #[arg(long)]
    pub rerank: Vec<String>,
    /// Only the manifest rows of these classes (comma-separated), e.g. for a class split.
    #[arg(long, value_delimiter = ',')]
    pub classes: Vec<String>,
    /// Keep at most this many rows of each class (a pseudo-random subset, fixed by
    /// `--sample-seed`): smaller relevant sets and fewer distractors, e.g. to check that a stage
    /// does not depend on the class size.
    #[arg(long)]
    pub per_class: Option<usize>,
    /// Seed of `--per-class`'s subset.
    #[arg(long, default_value_t = 0)]
    pub sample_seed: u64,
    /// Laplace–Beltrami operator: cotangent or intrinsic-delaunay.
    #[arg(long, default_value = "cotangent")]
    pub laplacian: String,
    /// Histogram window: this fraction of the pooled corpus distances (paper: 0.95). Smaller
    /// windows keep only the short-range part of every distribution (truncated distance range).
    #[arg(long, default_value_t = 0.95)]
    pub window_percentile: f64,
    /// Keep every mesh at its own size (no unit-area normalisation): the "raw" runs that show
    /// what scaling does to each kernel (paper Table 2's Scale row).
    #[arg(long)]
    pub no_normalize: bool,
    /// Write every configuration's all-pairs dissimilarity matrix (re-ranked rows: ranks) as JSON
    /// here, with the manifest's ids, classes and transforms, for analysis outside shapeseek.
    #[arg(long)]
    pub matrices: Option<PathBuf>,
}

impl EvalArgs {
    /// Arguments with defaults for a manifest (for programmatic use and tests).
    pub fn new(manifest: impl Into<PathBuf>) -> Self {
        EvalArgs {
            manifest: manifest.into(),
            config: None,
            json: None,
            out: None,
            cache: None,
            no_cache: false,
            jobs: None,
            k: 100,
            reference: None,
            per_strength: false,
            quiet: true,
            rerank: Vec::new(),
            classes: Vec::new(),
            per_class: None,
            sample_seed: 0,
            laplacian: "cotangent".into(),
            no_normalize: false,
            window_percentile: 0.95,
            matrices: None,
        }
    }
}

/// Wall-clock and summed per-shape times of one run, in seconds.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Timings {
    /// Reading and parsing mesh files (summed over shapes).
    pub read_s: f64,
    /// Mesh preparation (summed).
    pub prepare_s: f64,
    /// Laplacian, factorisation and eigensolve (summed).
    pub eigen_s: f64,
    /// Signature computation (summed).
    pub signature_s: f64,
    /// Cache reads and writes (summed).
    pub cache_s: f64,
    /// Wall time of the per-shape phase (all of the above, in parallel).
    pub per_shape_wall_s: f64,
    /// Corpus calibration and histograms (wall).
    pub calibration_histograms_s: f64,
    /// Scoring and metrics of every configuration (wall).
    pub ranking_s: f64,
    /// Of which: all-pairs dissimilarity matrices (wall).
    pub scoring_s: f64,
    /// Of which: rankings, AP, ROC, PR and their aggregation (wall).
    pub metrics_s: f64,
    /// Configurations scored pair by pair with `ranking::score` because the per-channel
    /// matrices did not reproduce it (expected 0).
    pub direct_fallbacks: usize,
    /// Reports (wall).
    pub report_s: f64,
    /// Whole run (wall).
    pub total_s: f64,
    /// Worker threads.
    pub threads: usize,
}

/// Everything one run produced.
#[derive(Debug, Clone)]
pub struct EvalOutcome {
    /// The manifest.
    pub manifest: Manifest,
    /// Per-configuration evaluation, in configuration order.
    pub results: Vec<ConfigResult>,
    /// Shapes left out.
    pub failures: Vec<Failure>,
    /// Stage times.
    pub timings: Timings,
    /// Cache use: (hits, misses, corrupt, write errors).
    pub cache: (u64, u64, u64, u64),
    /// The JSON document (as written by `--json`).
    pub json: Value,
    /// The Markdown report (as written to `results.md`).
    pub markdown: String,
}

impl EvalOutcome {
    /// The evaluation of the configuration `name`.
    pub fn result(&self, name: &str) -> Option<&Evaluation> {
        self.results
            .iter()
            .find(|r| r.name == name)
            .map(|r| &r.eval)
    }
}

/// Runs `shapeseek eval`: evaluates, prints the Markdown summary and stage times to stdout and
/// writes the requested files.
pub fn run(args: &EvalArgs) -> Result<()> {
    let out = evaluate(args)?;
    print!("{}", out.markdown);
    if args.per_strength {
        println!(
            "\n## mAP per strength (%)\n\n{}",
            report::per_strength_table(&out.results)
        );
    }
    Ok(())
}

/// Resolves `--config`.
pub fn load_configs(spec: Option<&str>) -> Result<Vec<Config>> {
    let presets = || {
        let mut v = ranking::paper_configs();
        let d = ranking::default_config();
        if !v.iter().any(|c| c.name == d.name) {
            v.push(d);
        }
        v
    };
    let Some(spec) = spec else {
        return Ok(presets());
    };
    let path = Path::new(spec);
    if path.is_file() {
        let text = std::fs::read_to_string(path)?;
        let is_toml = path.extension().and_then(|e| e.to_str()) == Some("toml");
        let v: Value = if is_toml {
            let t: toml::Value = toml::from_str(&text)
                .map_err(|e| Error::InvalidArgument(format!("config {spec}: {e}")))?;
            serde_json::to_value(t)
                .map_err(|e| Error::InvalidArgument(format!("config {spec}: {e}")))?
        } else {
            serde_json::from_str(&text)
                .map_err(|e| Error::InvalidArgument(format!("config {spec}: {e}")))?
        };
        let items = match v {
            Value::Array(a) => a,
            Value::Object(ref o) if o.contains_key("configs") => match &o["configs"] {
                Value::Array(a) => a.clone(),
                _ => {
                    return Err(Error::InvalidArgument(format!(
                        "config {spec}: 'configs' must be a list"
                    )))
                }
            },
            other => vec![other],
        };
        let mut out = Vec::new();
        for (i, item) in items.into_iter().enumerate() {
            let c: Config = serde_json::from_value(item)
                .map_err(|e| Error::InvalidArgument(format!("config {spec}, entry {i}: {e}")))?;
            for st in &c.rerank {
                st.validate().map_err(|e| {
                    Error::InvalidArgument(format!("config {spec}, entry {i}: rerank: {e}"))
                })?;
            }
            out.push(c);
        }
        if out.is_empty() {
            return Err(Error::InvalidArgument(format!(
                "config {spec}: no configuration"
            )));
        }
        return Ok(out);
    }
    match spec {
        "all" => Ok(presets()),
        "paper" => Ok(ranking::paper_configs()),
        "default" => Ok(vec![ranking::default_config()]),
        names => {
            let all = presets();
            names
                .split(',')
                .map(|n| n.trim())
                .filter(|n| !n.is_empty())
                .map(|n| {
                    all.iter().find(|c| c.name == n).cloned().ok_or_else(|| {
                        Error::InvalidArgument(format!(
                            "--config {n}: not a file and not a preset (paper, default, all) or configuration name; known: {}",
                            all.iter().map(|c| c.name.as_str()).collect::<Vec<_>>().join(", ")
                        ))
                    })
                })
                .collect()
        }
    }
}

/// Groups of configurations sharing one signature specification: the union of their channels,
/// for specifications that are equal apart from the channel list.
pub fn union_specs(configs: &[Config]) -> (Vec<SignatureSpec>, Vec<usize>) {
    let mut specs: Vec<SignatureSpec> = Vec::new();
    let mut bases: Vec<Value> = Vec::new();
    let mut group_of = Vec::with_capacity(configs.len());
    for c in configs {
        let mut base = c.signature.clone();
        base.channels.clear();
        let bv = serde_json::to_value(&base).unwrap_or(Value::Null);
        let g = match bases.iter().position(|b| *b == bv && bv != Value::Null) {
            Some(g) => g,
            None => {
                bases.push(bv);
                specs.push(base);
                specs.len() - 1
            }
        };
        // Channels are identified by name (as queries refer to them).
        for ch in &c.signature.channels {
            let name = ch.name();
            if !specs[g].channels.iter().any(|x| x.name() == name) {
                specs[g].channels.push(ch.clone());
            }
        }
        group_of.push(g);
    }
    (specs, group_of)
}

fn dur(ns: &AtomicU64) -> f64 {
    ns.load(Ordering::Relaxed) as f64 * 1e-9
}

fn add(ns: &AtomicU64, d: Duration) {
    ns.fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
}

#[derive(Default)]
struct StageClock {
    read: AtomicU64,
    prepare: AtomicU64,
    eigen: AtomicU64,
    signature: AtomicU64,
    cache: AtomicU64,
}

/// Progress reporting: an indicatif bar on a terminal, plain periodic lines otherwise.
struct Progress {
    bar: Option<indicatif::ProgressBar>,
    plain: bool,
    total: usize,
    done: AtomicUsize,
    last: Mutex<Instant>,
    start: Instant,
}

impl Progress {
    fn new(total: usize, quiet: bool) -> Progress {
        let tty = std::io::stderr().is_terminal();
        let bar = (!quiet && tty).then(|| {
            let b = indicatif::ProgressBar::new(total as u64);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "{spinner} shapes {pos}/{len} [{bar:40}] {elapsed_precise} eta {eta} {msg}",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            b
        });
        Progress {
            bar,
            plain: !quiet && !tty,
            total,
            done: AtomicUsize::new(0),
            last: Mutex::new(Instant::now()),
            start: Instant::now(),
        }
    }

    fn tick(&self, id: &str) {
        let done = self.done.fetch_add(1, Ordering::Relaxed) + 1;
        if let Some(b) = &self.bar {
            b.set_message(id.to_string());
            b.inc(1);
        } else if self.plain {
            let mut last = self.last.lock().unwrap_or_else(|e| e.into_inner());
            if done == self.total || last.elapsed() >= Duration::from_secs(10) {
                *last = Instant::now();
                eprintln!(
                    "eval: {done}/{} shapes ({:.0} s)",
                    self.total,
                    self.start.elapsed().as_secs_f64()
                );
            }
        }
    }

    fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

/// Part of the analysis cache key besides the mesh bytes and the options: the crate version, so
/// that a new release never reuses spectra computed by an older solver.
pub(crate) const ANALYSIS_VERSION: &str = concat!("shapeseek ", env!("CARGO_PKG_VERSION"));

/// The signatures of one shape (one per union specification), or why it failed.
type ShapeResult = std::result::Result<Vec<Signature>, (String, String)>;

#[allow(clippy::too_many_arguments)]
fn process_shape(
    path: &Path,
    specs: &[SignatureSpec],
    spec_keys: &[String],
    opts: &AnalyzeOptions,
    opts_json: &[u8],
    limits: &ReadLimits,
    cache: &Cache,
    clock: &StageClock,
) -> ShapeResult {
    let fail = |e: Error| (e.code().to_string(), e.to_string());
    let t = Instant::now();
    let bytes = read_limited(path, limits).map_err(fail)?;
    add(&clock.read, t.elapsed());
    let content = hash_parts(&[&bytes]);
    let akey = hash_parts(&[content.as_bytes(), opts_json, ANALYSIS_VERSION.as_bytes()]);
    let mut sigs: Vec<Option<Signature>> = Vec::with_capacity(specs.len());
    let t = Instant::now();
    let mut index: Option<Vec<IndexEntry>> = None;
    for (spec, sk) in specs.iter().zip(spec_keys) {
        let mut sig = load_signature_checked(cache, &akey, sk);
        if sig.is_none() {
            // A cached signature of a larger specification serves as well (channels by name).
            let idx = index.get_or_insert_with(|| load_index(cache, &akey));
            sig = idx
                .iter()
                .filter(|e| &e.key != sk && covers(&e.spec, spec))
                .find_map(|e| load_signature_checked(cache, &akey, &e.key));
        }
        sigs.push(sig);
    }
    add(&clock.cache, t.elapsed());
    if sigs.iter().all(|s| s.is_some()) {
        return Ok(sigs.into_iter().map(|s| s.unwrap()).collect());
    }
    let t = Instant::now();
    let cached = cache.load_analysis(&akey);
    add(&clock.cache, t.elapsed());
    let analysis = match cached {
        Some(a) => a,
        None => {
            let t = Instant::now();
            let hint = path
                .extension()
                .and_then(|e| e.to_str())
                .and_then(Format::from_extension);
            let mesh = read_mesh(&bytes, hint, limits).map_err(fail)?;
            add(&clock.read, t.elapsed());
            let a = analyze(&mesh, opts).map_err(fail)?;
            add(
                &clock.prepare,
                Duration::from_secs_f64(a.timings.prepare_ms * 1e-3),
            );
            add(
                &clock.eigen,
                Duration::from_secs_f64(
                    (a.timings.laplacian_ms + a.timings.factorization_ms + a.timings.eigensolve_ms)
                        * 1e-3,
                ),
            );
            let t = Instant::now();
            cache.store_analysis(&akey, &a);
            add(&clock.cache, t.elapsed());
            a
        }
    };
    let mut out = Vec::with_capacity(specs.len());
    for ((spec, sk), sig) in specs.iter().zip(spec_keys).zip(sigs) {
        match sig {
            Some(s) => out.push(s),
            None => {
                let t = Instant::now();
                let s = compute_signature(&analysis, spec).map_err(fail)?;
                add(&clock.signature, t.elapsed());
                let t = Instant::now();
                cache.store_signature(
                    &hash_parts(&[akey.as_bytes(), sk.as_bytes()]),
                    &s.to_bytes(),
                );
                if cache.dir().is_some() {
                    let mut idx = index.take().unwrap_or_else(|| load_index(cache, &akey));
                    if !idx.iter().any(|e| &e.key == sk) {
                        idx.push(IndexEntry {
                            key: sk.clone(),
                            spec: spec.clone(),
                        });
                    }
                    cache.store_index(&akey, &serde_json::to_vec(&idx).expect("index serialises"));
                    index = Some(idx);
                }
                add(&clock.cache, t.elapsed());
                out.push(s);
            }
        }
    }
    Ok(out)
}

/// One cached signature specification of an analysis.
#[derive(serde::Serialize, serde::Deserialize)]
struct IndexEntry {
    key: String,
    spec: SignatureSpec,
}

fn load_index(cache: &Cache, akey: &str) -> Vec<IndexEntry> {
    cache
        .load_index(akey)
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default()
}

fn load_signature_checked(cache: &Cache, akey: &str, spec_key: &str) -> Option<Signature> {
    let key = hash_parts(&[akey.as_bytes(), spec_key.as_bytes()]);
    cache
        .load_signature(&key)
        .and_then(|b| match Signature::from_bytes(&b) {
            Ok(s) if s.spec_key == spec_key => Some(s),
            _ => {
                cache.note_undecodable();
                None
            }
        })
}

/// Does a signature computed for `big` hold every channel of `small`, computed the same way?
pub fn covers(big: &SignatureSpec, small: &SignatureSpec) -> bool {
    let base = |s: &SignatureSpec| {
        let mut b = s.clone();
        b.channels.clear();
        serde_json::to_value(&b).ok()
    };
    base(big).is_some()
        && base(big) == base(small)
        && small
            .channels
            .iter()
            .all(|c| big.channels.iter().any(|x| x == c))
}

fn read_limited(path: &Path, limits: &ReadLimits) -> Result<Vec<u8>> {
    let meta = std::fs::metadata(path)?;
    if meta.len() as u128 > limits.max_bytes as u128 {
        return Err(Error::Limit {
            kind: crate::error::LimitKind::Bytes,
            limit: limits.max_bytes,
            actual: meta.len() as usize,
        });
    }
    Ok(std::fs::read(path)?)
}

/// Finds a reference file for the manifest (see [`EvalArgs::reference`]).
pub fn find_reference(manifest_path: &Path) -> Option<PathBuf> {
    let dir = manifest_path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    for name in ["reference-map.json", "REFERENCE.md"] {
        let p = dir.join(name);
        if p.is_file() {
            return Some(p);
        }
    }
    // The bench's top-level REFERENCE.md describes `dev/manifest.csv`.
    let split = dir.file_name()?.to_str()?.to_string();
    let p = dir.parent()?.join("REFERENCE.md");
    let text = std::fs::read_to_string(&p).ok()?;
    text.contains(&format!("`{split}/manifest.csv`"))
        .then_some(p)
}

/// Runs the evaluation and writes `--json` / `--out` files; returns everything it computed.
pub fn evaluate(args: &EvalArgs) -> Result<EvalOutcome> {
    let threads = args.jobs.unwrap_or(0);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::InvalidArgument(format!("--jobs: {e}")))?;
    pool.install(|| evaluate_in_pool(args))
}

fn evaluate_in_pool(args: &EvalArgs) -> Result<EvalOutcome> {
    let t_total = Instant::now();
    if args.k < 2 {
        return Err(Error::InvalidArgument("--k must be at least 2".into()));
    }
    let mut manifest = Manifest::read(&args.manifest)?;
    if !args.classes.is_empty() {
        manifest
            .entries
            .retain(|e| args.classes.iter().any(|c| c == &e.class));
        if manifest.entries.is_empty() {
            return Err(Error::InvalidArgument(format!(
                "--classes {}: no manifest row",
                args.classes.join(",")
            )));
        }
    }
    if let Some(m) = args.per_class {
        manifest.entries =
            per_class_subset(std::mem::take(&mut manifest.entries), m, args.sample_seed);
        if manifest.entries.is_empty() {
            return Err(Error::InvalidArgument("--per-class must be ≥ 1".into()));
        }
    }
    let rerank_stages: Vec<(String, crate::rerank::RerankStage)> = args
        .rerank
        .iter()
        .map(|r| crate::rerank::eval::parse_stage(r).map(|s| (r.clone(), s)))
        .collect::<Result<_>>()?;
    let configs = load_configs(args.config.as_deref())?;
    let (specs, group_of) = union_specs(&configs);
    let spec_keys: Vec<String> = specs.iter().map(|s| s.key()).collect();
    let cache_dir = if args.no_cache {
        None
    } else {
        Some(args.cache.clone().unwrap_or_else(cache::default_dir))
    };
    let cache = Cache::new(cache_dir)?;
    let mut opts = AnalyzeOptions::default();
    opts.eigen.k = args.k;
    opts.prepare.normalize_area = !args.no_normalize;
    opts.laplacian = match args.laplacian.as_str() {
        "cotangent" => crate::laplace::LaplacianKind::Cotangent,
        "intrinsic-delaunay" => crate::laplace::LaplacianKind::IntrinsicDelaunay,
        o => {
            return Err(Error::InvalidArgument(format!(
                "--laplacian {o}: cotangent or intrinsic-delaunay"
            )))
        }
    };
    let opts_json = serde_json::to_vec(&opts).expect("options serialise");
    let limits = ReadLimits::default();
    let clock = StageClock::default();
    let n = manifest.entries.len();
    if !args.quiet {
        eprintln!(
            "eval: {n} shapes, {} configurations, {} signature specification(s) with {} channel(s), k = {}, cache {}",
            configs.len(),
            specs.len(),
            specs.iter().map(|s| s.channels.len()).sum::<usize>(),
            args.k,
            cache.dir().map(|d| d.display().to_string()).unwrap_or_else(|| "off".into())
        );
    }

    // Per-shape phase.
    let t_shapes = Instant::now();
    let progress = Progress::new(n, args.quiet);
    let shape_results: Vec<ShapeResult> = manifest
        .entries
        .par_iter()
        .map(|e| {
            // A panic in the library on one mesh is reported for that row like an error.
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                process_shape(
                    &e.resolved,
                    &specs,
                    &spec_keys,
                    &opts,
                    &opts_json,
                    &limits,
                    &cache,
                    &clock,
                )
            }))
            .unwrap_or_else(|p| {
                let msg = p
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into());
                Err((
                    "internal.panic".to_string(),
                    format!("panic while processing: {msg}"),
                ))
            });
            progress.tick(&e.id);
            r
        })
        .collect();
    progress.finish();
    let per_shape_wall_s = t_shapes.elapsed().as_secs_f64();

    let mut failures = Vec::new();
    let included: Vec<bool> = shape_results.iter().map(|r| r.is_ok()).collect();
    for (e, r) in manifest.entries.iter().zip(&shape_results) {
        if let Err((code, message)) = r {
            failures.push(Failure {
                id: e.id.clone(),
                path: e.path.clone(),
                code: code.clone(),
                message: message.clone(),
            });
        }
    }
    let ok: Vec<usize> = (0..n).filter(|&i| included[i]).collect();
    if ok.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "no shape of {} could be analysed ({} failures; first: {} {})",
            args.manifest.display(),
            failures.len(),
            failures[0].code,
            failures[0].message
        )));
    }

    // Calibration and histograms, per union specification.
    let t_cal = Instant::now();
    let prepared: Vec<Vec<Option<Prepared>>> = specs
        .iter()
        .enumerate()
        .map(|(g, spec)| {
            let sigs: Vec<&Signature> = ok
                .iter()
                .map(|&i| &shape_results[i].as_ref().unwrap()[g])
                .collect();
            let cal = ranking::calibrate_with(
                &sigs,
                spec,
                0,
                &ranking::CalibrationOptions {
                    percentile: args.window_percentile,
                    ..Default::default()
                },
            );
            shape_results
                .par_iter()
                .map(|r| {
                    r.as_ref()
                        .ok()
                        .map(|s| ranking::prepare_for_ranking(&s[g], &cal))
                })
                .collect()
        })
        .collect();
    let calibration_histograms_s = t_cal.elapsed().as_secs_f64();
    // Re-ranking payloads, one set per distinct payload specification.
    let mut rerank_notes = String::new();
    let mut payload_sets: Vec<(String, Vec<Option<crate::rerank::GwPayload>>)> = Vec::new();
    let all_stages = rerank_stages
        .iter()
        .map(|(_, st)| st)
        .chain(configs.iter().flat_map(|c| &c.rerank));
    for st in all_stages {
        if let Some(ps) = st.payload_spec() {
            let key = ps.key();
            if !payload_sets.iter().any(|(k, _)| *k == key) {
                let t = Instant::now();
                let akey = |bytes: &[u8]| {
                    let content = hash_parts(&[bytes]);
                    hash_parts(&[content.as_bytes(), &opts_json, ANALYSIS_VERSION.as_bytes()])
                };
                let pl = crate::rerank::eval::shape_payloads(
                    &manifest, &included, &opts, &akey, &cache, ps,
                );
                rerank_notes.push_str(&format!(
                    "- payload `{}` ({} samples, t = {:?}, {:?}, {:?}): {:.1} s for {} shapes (cached under `gw/`)\n",
                    key, ps.samples, ps.times, ps.metric, ps.time_rule, t.elapsed().as_secs_f64(), pl.iter().filter(|p| p.is_some()).count()
                ));
                payload_sets.push((key, pl));
            }
        }
    }

    // Ranking.
    let t_rank = Instant::now();
    let mut class_ids: Vec<String> = Vec::new();
    let classes: Vec<usize> = manifest
        .entries
        .iter()
        .map(|e| match class_ids.iter().position(|c| *c == e.class) {
            Some(p) => p,
            None => {
                class_ids.push(e.class.clone());
                class_ids.len() - 1
            }
        })
        .collect();
    let transforms: Vec<String> = manifest
        .entries
        .iter()
        .map(|e| e.transform.clone())
        .collect();
    let strengths: Vec<i64> = manifest.entries.iter().map(|e| e.strength).collect();
    let mut results = Vec::with_capacity(configs.len());
    let mut channel_cache: Vec<ChannelMatrices> = (0..specs.len())
        .map(|_| ChannelMatrices::default())
        .collect();
    let (mut scoring_s, mut metrics_s) = (0.0, 0.0);
    let mut solved_pairs = crate::rerank::eval::PairCache::new();
    let mut direct_fallbacks = 0usize;
    let mut dumped: Vec<(String, Vec<f64>)> = Vec::new();
    for (c, cfg) in configs.iter().enumerate() {
        let g = group_of[c];
        let prep = &prepared[g];
        let t = Instant::now();
        let dist = match channel_cache[g].aggregate(prep, &cfg.query) {
            Some(d) => d,
            None => {
                direct_fallbacks += 1;
                distance_matrix(prep, &cfg.query)
            }
        };
        scoring_s += t.elapsed().as_secs_f64();
        // The configuration's own stages, then each `--rerank` stage on its result; every
        // stage's shortlist comes from the current order, a reciprocal stage's mutual
        // dissimilarities from the first stage's matrix.
        let mut cur = dist.clone();
        for st in &cfg.rerank {
            let (d2, stats) = apply_stage(
                st,
                &dist,
                &cur,
                n,
                &included,
                &payload_sets,
                &mut solved_pairs,
            );
            rerank_notes.push_str(&stage_note(&cfg.name, st, &stats, args.quiet));
            cur = d2;
        }
        if args.matrices.is_some() {
            dumped.push((cfg.name.clone(), cur.clone()));
        }
        let t = Instant::now();
        let eval = metrics::evaluate(&cur, n, &classes, &transforms, &strengths, &included);
        metrics_s += t.elapsed().as_secs_f64();
        results.push(ConfigResult {
            name: cfg.name.clone(),
            eval,
            alias: alias_of(cfg),
        });
        for (label, st) in &rerank_stages {
            let (d2, stats) = apply_stage(
                st,
                &dist,
                &cur,
                n,
                &included,
                &payload_sets,
                &mut solved_pairs,
            );
            let eval = metrics::evaluate(&d2, n, &classes, &transforms, &strengths, &included);
            let name = format!("{}+{}", cfg.name, label);
            if args.matrices.is_some() {
                dumped.push((name.clone(), d2.clone()));
            }
            rerank_notes.push_str(&stage_note(&name, st, &stats, args.quiet));
            results.push(ConfigResult {
                name,
                eval,
                alias: None,
            });
        }
    }
    drop(channel_cache);
    let ranking_s = t_rank.elapsed().as_secs_f64();
    if let Some(p) = &args.matrices {
        write_matrices(p, &manifest, &included, n, &dumped)?;
    }

    // Reports.
    let t_rep = Instant::now();
    let reference_path = args
        .reference
        .clone()
        .or_else(|| find_reference(&args.manifest));
    let reference = match &reference_path {
        Some(p) => match Reference::load(p) {
            Ok(r) if !r.is_empty() => Some(r),
            Ok(_) => None,
            Err(e) => {
                if args.reference.is_some() {
                    return Err(e);
                }
                None
            }
        },
        None => None,
    };
    let mut timings = Timings {
        read_s: dur(&clock.read),
        prepare_s: dur(&clock.prepare),
        eigen_s: dur(&clock.eigen),
        signature_s: dur(&clock.signature),
        cache_s: dur(&clock.cache),
        per_shape_wall_s,
        calibration_histograms_s,
        ranking_s,
        scoring_s,
        metrics_s,
        direct_fallbacks,
        report_s: 0.0,
        total_s: 0.0,
        threads: rayon::current_num_threads(),
    };
    let cache_counts = (
        cache.stats.hits.load(Ordering::Relaxed),
        cache.stats.misses.load(Ordering::Relaxed),
        cache.stats.corrupt.load(Ordering::Relaxed),
        cache.stats.write_errors.load(Ordering::Relaxed),
    );
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir)?;
        write_curves(dir, &results)?;
    }
    timings.report_s = t_rep.elapsed().as_secs_f64();
    timings.total_s = t_total.elapsed().as_secs_f64();
    let mut markdown = markdown_report(
        args,
        &manifest,
        &results,
        &failures,
        &timings,
        cache_counts,
        reference.as_ref(),
        reference_path.as_deref(),
    );
    if !rerank_notes.is_empty() {
        markdown.push_str(&format!("\n## Re-ranking\n\n{rerank_notes}"));
    }
    if let Some(dir) = &args.out {
        std::fs::write(dir.join("results.md"), &markdown)?;
    }
    let extra = json!({
        "manifest": args.manifest.display().to_string(),
        "n_shapes": n,
        "n_ranked": ok.len(),
        "k": args.k,
        "cache": {"dir": cache.dir().map(|d| d.display().to_string()), "hits": cache_counts.0, "misses": cache_counts.1, "corrupt": cache_counts.2, "write_errors": cache_counts.3},
        "reference": reference.as_ref().map(|r| r.source.clone()),
    });
    let json_doc = report::json_document(
        &results,
        &failures,
        &serde_json::to_value(&timings).unwrap_or(Value::Null),
        extra,
    );
    if let Some(p) = &args.json {
        if let Some(parent) = p.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent)?;
        }
        let text = serde_json::to_string_pretty(&json_doc).expect("json");
        cache::write_atomic(p, text.as_bytes())?;
    }
    Ok(EvalOutcome {
        manifest,
        results,
        failures,
        timings,
        cache: cache_counts,
        json: json_doc,
        markdown,
    })
}

/// One re-ranking stage over every query row (`crate::rerank::eval::rerank_matrix`), with the
/// run's payloads for the stage's payload spec.
fn apply_stage(
    st: &crate::rerank::RerankStage,
    base: &[f64],
    cur: &[f64],
    n: usize,
    included: &[bool],
    payload_sets: &[(String, Vec<Option<crate::rerank::GwPayload>>)],
    solved_pairs: &mut crate::rerank::eval::PairCache,
) -> (Vec<f64>, crate::rerank::eval::RerankStats) {
    let none = vec![None; n];
    let payloads = st
        .payload_spec()
        .and_then(|ps| payload_sets.iter().find(|(k, _)| *k == ps.key()))
        .map(|(_, p)| p)
        .filter(|p| !p.is_empty())
        .unwrap_or(&none);
    crate::rerank::eval::rerank_matrix(base, cur, n, included, payloads, st, solved_pairs)
}

/// The report's line about one re-ranking stage (also printed unless `quiet`).
fn stage_note(
    name: &str,
    st: &crate::rerank::RerankStage,
    stats: &crate::rerank::eval::RerankStats,
    quiet: bool,
) -> String {
    let line = match st {
        crate::rerank::RerankStage::Reciprocal(_) => format!(
            "`{name}` ({}): {:.1} s wall for every query; {:.2} ms per query's shortlist (one thread)",
            st.label(),
            stats.wall_s,
            stats.per_query_ms
        ),
        _ => format!(
            "`{name}` ({}): {} newly solved pairs in {:.1} s wall; {:.2} ms CPU per GW solve; `rerank::apply` on one query's shortlist: {:.1} ms wall",
            st.label(),
            stats.pairs,
            stats.wall_s,
            stats.per_candidate_ms,
            stats.per_query_ms
        ),
    };
    if !quiet {
        eprintln!("eval: {line}");
    }
    format!("- {line}\n")
}

/// `--per-class`: per class, the `m` rows with the smallest `hash(seed, id)`, in manifest order.
fn per_class_subset(entries: Vec<manifest::Entry>, m: usize, seed: u64) -> Vec<manifest::Entry> {
    let key = |e: &manifest::Entry| hash_parts(&[seed.to_string().as_bytes(), e.id.as_bytes()]);
    let mut keep = vec![false; entries.len()];
    let mut classes: Vec<&str> = entries.iter().map(|e| e.class.as_str()).collect();
    classes.sort_unstable();
    classes.dedup();
    for c in classes {
        let mut rows: Vec<(String, usize)> = entries
            .iter()
            .enumerate()
            .filter(|(_, e)| e.class == c)
            .map(|(i, e)| (key(e), i))
            .collect();
        rows.sort();
        for (_, i) in rows.into_iter().take(m) {
            keep[i] = true;
        }
    }
    entries
        .into_iter()
        .zip(keep)
        .filter_map(|(e, k)| k.then_some(e))
        .collect()
}

/// `--matrices`: one JSON document with the manifest rows and, per configuration, its row-major
/// `n × n` dissimilarity matrix (`null` on the diagonal and for rows that were not ranked).
fn write_matrices(
    path: &Path,
    manifest: &Manifest,
    included: &[bool],
    n: usize,
    mats: &[(String, Vec<f64>)],
) -> Result<()> {
    let rows: Vec<Value> = manifest
        .entries
        .iter()
        .zip(included)
        .map(|(e, &inc)| {
            json!({"id": e.id, "class": e.class, "transform": e.transform, "strength": e.strength, "ranked": inc})
        })
        .collect();
    let matrices: serde_json::Map<String, Value> = mats
        .iter()
        .map(|(name, d)| {
            let m: Vec<Vec<Option<f64>>> = (0..n)
                .map(|i| {
                    (0..n)
                        .map(|j| {
                            let v = d[i * n + j];
                            (i != j && included[i] && included[j] && v.is_finite()).then_some(v)
                        })
                        .collect()
                })
                .collect();
            (name.clone(), json!(m))
        })
        .collect();
    let doc = json!({"shapes": rows, "matrices": matrices});
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)?;
    }
    cache::write_atomic(path, serde_json::to_string(&doc).expect("json").as_bytes())?;
    Ok(())
}

/// The name of a preset configuration that is the same method as `cfg` under another name:
/// same query, same specifications of the queried channels, same discretisation (other channels
/// of a shared family specification do not matter). Used for reference look-ups.
pub fn alias_of(cfg: &Config) -> Option<String> {
    let method = |c: &Config| {
        let chans: Vec<Option<&crate::signature::ChannelSpec>> = c
            .query
            .channels
            .iter()
            .map(|n| c.signature.channels.iter().find(|x| &x.name() == n))
            .collect();
        let mut base = c.signature.clone();
        base.channels.clear();
        (
            serde_json::to_value(&c.query).ok(),
            serde_json::to_value(&chans).ok(),
            serde_json::to_value(&base).ok(),
            serde_json::to_value(&c.rerank).ok(),
        )
    };
    let me = method(cfg);
    ranking::paper_configs()
        .into_iter()
        .find(|c| c.name != cfg.name && method(c) == me)
        .map(|c| c.name)
}

/// All-pairs per-channel dissimilarity matrices, computed once per (channel, dissimilarity) and
/// shared by every configuration of a signature family: `Heat-L2-nL1-Single[t]`, `…-Sum`,
/// `…-Sum2` and `…-Max` all reuse the same six matrices.
///
/// A configuration's matrix is then `aggregation.apply(per-channel values)` exactly as
/// `ranking::score` combines `ranking::channel_dissimilarity`; that equivalence is checked on a
/// sample of pairs against `ranking::score` itself, and a configuration where it does not hold
/// bit for bit is scored pair by pair instead.
#[derive(Default)]
struct ChannelMatrices {
    mats: std::collections::HashMap<(String, String), Vec<f64>>,
}

impl ChannelMatrices {
    fn matrix(
        &mut self,
        prep: &[Option<Prepared>],
        name: &str,
        d: ranking::Dissimilarity,
    ) -> &Vec<f64> {
        let key = (name.to_string(), format!("{d:?}"));
        self.mats.entry(key).or_insert_with(|| {
            let n = prep.len();
            let mut m = vec![f64::NAN; n * n];
            m.par_chunks_mut(n.max(1)).enumerate().for_each(|(i, row)| {
                if let Some(pi) = &prep[i] {
                    let a = pi.channel(name);
                    for (j, x) in row.iter_mut().enumerate() {
                        if i != j {
                            if let Some(pj) = &prep[j] {
                                *x = ranking::channel_dissimilarity(d, a, pj.channel(name));
                            }
                        }
                    }
                }
            });
            m
        })
    }

    /// The configuration's all-pairs matrix, or `None` when the shortcut does not reproduce
    /// `ranking::score`.
    fn aggregate(&mut self, prep: &[Option<Prepared>], q: &QuerySpec) -> Option<Vec<f64>> {
        let names: Vec<String> = match q.aggregation {
            ranking::Aggregation::Single => q.channels.iter().take(1).cloned().collect(),
            _ => q.channels.clone(),
        };
        if names.is_empty() {
            return None;
        }
        for nm in &names {
            self.matrix(prep, nm, q.dissimilarity);
        }
        let mats: Vec<&Vec<f64>> = names
            .iter()
            .map(|nm| &self.mats[&(nm.clone(), format!("{:?}", q.dissimilarity))])
            .collect();
        let n = prep.len();
        let mut out = vec![f64::NAN; n * n];
        out.par_chunks_mut(n.max(1))
            .enumerate()
            .for_each(|(i, row)| {
                if prep[i].is_none() {
                    return;
                }
                for (j, x) in row.iter_mut().enumerate() {
                    if i != j && prep[j].is_some() {
                        *x = q.aggregation.apply(mats.iter().map(|m| m[i * n + j]));
                    }
                }
            });
        // Check against the library's own score on a deterministic sample of pairs.
        let ok: Vec<usize> = (0..n).filter(|&i| prep[i].is_some()).collect();
        let m = ok.len();
        if m >= 2 {
            for s in 0..64usize.min(m * (m - 1)) {
                let i = ok[(s * 7919) % m];
                let j = ok[(s * 104_729 + 13) % m];
                if i == j {
                    continue;
                }
                let (Some(a), Some(b)) = (&prep[i], &prep[j]) else {
                    continue;
                };
                let direct = ranking::score(a, b, q);
                let ours = out[i * n + j];
                if !(direct == ours || (direct.is_nan() && ours.is_nan())) {
                    return None;
                }
            }
        }
        Some(out)
    }
}

/// All-pairs scores (row = query), NaN where a shape is missing; rows in parallel.
fn distance_matrix(prep: &[Option<Prepared>], q: &QuerySpec) -> Vec<f64> {
    let n = prep.len();
    let mut dist = vec![f64::NAN; n * n];
    dist.par_chunks_mut(n.max(1))
        .enumerate()
        .for_each(|(i, row)| {
            if let Some(pi) = &prep[i] {
                for (j, d) in row.iter_mut().enumerate() {
                    if i != j {
                        if let Some(pj) = &prep[j] {
                            *d = ranking::score(pi, pj, q);
                        }
                    }
                }
            }
        });
    dist
}

fn safe_file_name(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.=".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

fn write_curves(dir: &Path, results: &[ConfigResult]) -> Result<()> {
    let curves = dir.join("curves");
    std::fs::create_dir_all(&curves)?;
    for r in results {
        let base = safe_file_name(&r.name);
        let series = |pick: &dyn Fn(&metrics::GroupSummary) -> &Vec<(f64, f64)>| -> Vec<(String, Vec<(f64, f64)>)> {
            r.eval
                .groups
                .iter()
                .filter(|(_, s)| !pick(s).is_empty())
                .map(|(g, s)| {
                    let lab = match (s.auc, s.map) {
                        (Some(a), Some(m)) => format!("{} (AUC {:.1}, mAP {:.1})", report::group_label(g), 100.0 * a, 100.0 * m),
                        _ => report::group_label(g),
                    };
                    (lab, pick(s).clone())
                })
                .collect()
        };
        let roc = plot::line_chart(
            &format!("ROC — {}", r.name),
            "false positive rate",
            "true positive rate",
            &series(&|s| &s.mean_roc),
            true,
        );
        std::fs::write(curves.join(format!("{base}.roc.svg")), roc)?;
        let pr = plot::line_chart(
            &format!("Precision–recall — {}", r.name),
            "recall",
            "precision",
            &series(&|s| &s.mean_pr),
            false,
        );
        std::fs::write(curves.join(format!("{base}.pr.svg")), pr)?;
    }
    // All configurations on one chart, group All: the default and the five best by mAP in
    // colour, the others as grey lines; the ROC on a log false-positive axis.
    let all = |pick: &dyn Fn(&metrics::GroupSummary) -> &Vec<(f64, f64)>| -> Vec<plot::Series> {
        results
            .iter()
            .filter_map(|r| {
                r.eval.group(metrics::ALL).map(|s| plot::Series {
                    name: r.name.clone(),
                    points: pick(s).clone(),
                    score: s.map,
                })
            })
            .collect()
    };
    let default_name = ranking::default_config().name;
    let overview = |x_axis, diagonal| plot::Overview {
        default: Some(default_name.as_str()),
        best: 5,
        score_label: "mAP",
        x_axis,
        diagonal,
    };
    std::fs::write(
        dir.join("roc-all.svg"),
        plot::overview_chart(
            "Mean ROC, all queries",
            "false positive rate (log scale)",
            "true positive rate",
            &all(&|s| &s.mean_roc),
            &overview(plot::XAxis::Log { min: 0.01 }, true),
        ),
    )?;
    std::fs::write(
        dir.join("pr-all.svg"),
        plot::overview_chart(
            "Mean precision–recall, all queries",
            "recall",
            "precision",
            &all(&|s| &s.mean_pr),
            &overview(plot::XAxis::Linear, false),
        ),
    )?;
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn markdown_report(
    args: &EvalArgs,
    manifest: &Manifest,
    results: &[ConfigResult],
    failures: &[Failure],
    t: &Timings,
    cache: (u64, u64, u64, u64),
    reference: Option<&Reference>,
    reference_path: Option<&Path>,
) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let n = manifest.entries.len();
    let _ = writeln!(s, "# shapeseek eval — {}\n", args.manifest.display());
    let mut per_t = String::new();
    for tr in manifest.transforms() {
        let c = manifest
            .entries
            .iter()
            .filter(|e| e.transform == tr)
            .count();
        let _ = write!(per_t, "{} {c}, ", report::group_label(&tr));
    }
    let _ = writeln!(
        s,
        "{n} shapes ({} ranked, {} left out); queries per transform: {}. k = {}. mAP, AUC and EER in %. \
         'All w/o scale' leaves out the scale queries.\n",
        n - failures.len(),
        failures.len(),
        per_t.trim_end_matches(", "),
        args.k
    );
    if !failures.is_empty() {
        let _ = writeln!(
            s,
            "## Left out of the ranking\n\n| id | path | code | message |\n|---|---|---|---|"
        );
        for f in failures {
            let _ = writeln!(
                s,
                "| {} | {} | `{}` | {} |",
                f.id,
                f.path,
                f.code,
                f.message.replace('|', "\\|")
            );
        }
        s.push('\n');
    }
    let _ = writeln!(
        s,
        "## All configurations\n\n{}",
        report::summary_table(results, reference)
    );
    if let (Some(_), Some(p)) = (reference, reference_path) {
        let _ = writeln!(s, "Reference figures from `{}`.\n", p.display());
    }
    s.push_str(&report::reference_shaped_tables(results, reference));
    s.push_str(&report::roc_summary_table(results, reference));
    let _ = writeln!(
        s,
        "## mAP per strength (%)\n\n{}",
        report::per_strength_table(&report::per_strength_selection(results))
    );
    let _ = writeln!(s, "## Time per stage\n");
    let _ = writeln!(s, "| stage | seconds |\n|---|---|");
    for (name, v) in [
        ("read (sum over shapes)", t.read_s),
        ("prepare (sum)", t.prepare_s),
        (
            "eigen: Laplacian + factorisation + eigensolve (sum)",
            t.eigen_s,
        ),
        ("signature (sum)", t.signature_s),
        ("cache I/O (sum)", t.cache_s),
        ("per-shape phase (wall)", t.per_shape_wall_s),
        (
            "calibration + histograms (wall)",
            t.calibration_histograms_s,
        ),
        ("ranking + metrics, all configurations (wall)", t.ranking_s),
        ("  of which dissimilarity matrices", t.scoring_s),
        ("  of which AP / ROC / PR", t.metrics_s),
        ("total (wall)", t.total_s),
    ] {
        let _ = writeln!(s, "| {name} | {v:.2} |");
    }
    let _ = writeln!(
        s,
        "\n{} worker threads; cache: {} hits, {} misses, {} corrupt (recomputed), {} write errors.",
        t.threads, cache.0, cache.1, cache.2, cache.3
    );
    s
}
