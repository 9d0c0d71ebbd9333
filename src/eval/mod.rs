//! `shapeseek eval`: the retrieval benchmark harness (bench README protocol, paper §5).
//!
//! ```text
//! shapeseek eval --manifest M [--config C] [--json OUT] [--out DIR] [--cache DIR] [--jobs N] [--k K]
//!                [--protocol standard|loco [--loco-fixed NAMES]]
//! ```
//!
//! 1. Reads the manifest ([`manifest`]); a mesh that cannot be read or analysed is reported (id,
//!    error code, message) and left out of every ranking.
//! 2. Computes each shape's analysis (prepared mesh + spectrum) and signatures once, in parallel
//!    (rayon), cached on disk ([`cache`]) under the mesh content hash, the analysis options
//!    (preparation and eigen options, `k` among them) and `SignatureSpec::key()`. Default cache
//!    directory: `$XDG_CACHE_HOME/shapeseek/eval`, else `./.cache/shapeseek-eval`.
//! 3. Calibrates the corpus windows and encodes every shape in the search corpus layout
//!    ([`crate::search::Corpus`], the layout the server scans), then, per configuration, scores
//!    every shape against every other with the search's scoring function (per-channel matrices
//!    shared by the configurations of a family), runs the configuration's stages through
//!    [`crate::search::run`] ([`rerank`]) and evaluates the rankings ([`metrics`]).
//! 4. Writes a Markdown summary to stdout, and optionally `--json OUT` and `--out DIR`
//!    (`results.md` with tables shaped like the bench REFERENCE.md, ROC / PR curves as SVG).
//!
//! With `--protocol loco` ([`EvalOptions::loco`]) the same run also performs the
//! leave-one-class-out protocol of [`loco`]: per class, the configuration with the best All mAP on
//! the other classes is chosen among the run's configurations and scored on the held-out class;
//! its report comes first.
//!
//! Configurations: without `--config`, `presets::paper_configs()` plus `presets::default_config()`.
//! `--config` takes a JSON or TOML file holding one configuration (`{name, signature, query}`), a
//! list of them, or `{configs = [...]}`; or a preset: `paper`, `default`, `all`, or a comma-separated
//! list of configuration names from the presets. Configurations whose signature specifications
//! differ only in their channel lists share one union specification, so each channel is computed
//! once per shape.

pub mod cache;
pub mod encoding_check;
pub mod loco;
pub mod manifest;
pub mod metrics;
pub mod plot;
pub mod report;
pub mod rerank;

mod configs;
mod matrices;
mod output;
mod rows;
mod shapes;

use configs::run_configs;
pub use configs::{alias_of, covers, load_configs, union_specs};
use matrices::ChannelMatrices;
use output::{markdown_report, write_curves, write_matrices};
use rerank::{apply_stage, stage_note};
use rows::select_rows;
pub(crate) use shapes::analysis_version;
use shapes::{dur, process_shape, Progress, ShapeResult, StageClock};

use crate::mesh::read::{read_mesh, Format, ReadLimits};
use crate::presets::{self, Config};
use crate::ranking::{self, QuerySpec};
use crate::search::corpus::{Corpus, Encoded, Layout};
use crate::search::{Query, Stage};
use crate::signature::{compute_signature, Signature, SignatureSpec};
use crate::spectrum::{analyze, AnalyzeOptions};
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

/// Options of [`evaluate`] (the command line's flags are in the binary's `cli::eval`).
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// Manifest CSV (`id,path,class,transform,strength,source_pose`; paths relative to it).
    pub manifest: PathBuf,
    /// Configurations: a JSON/TOML file (one config, a list, or `{configs=[...]}`), or a preset
    /// (`paper`, `default`, `all`, or comma-separated configuration names); `None`: `all`.
    pub config: Option<String>,
    /// Write the results as JSON here.
    pub json: Option<PathBuf>,
    /// Write `results.md` and ROC / PR curves (SVG) into this folder.
    pub out: Option<PathBuf>,
    /// Cache folder (`None`: [`cache::default_dir`]).
    pub cache: Option<PathBuf>,
    /// Do not read or write the cache.
    pub no_cache: bool,
    /// Worker threads (`None`: all cores).
    pub jobs: Option<usize>,
    /// Number of eigenpairs.
    pub k: usize,
    /// Reference figures to show side by side (`None`: [`find_reference`]).
    pub reference: Option<PathBuf>,
    /// No progress output.
    pub quiet: bool,
    /// Extra stage lists applied to every configuration's ranking, each evaluated as a
    /// configuration `<config>+<label>` (an empty list re-evaluates the configuration).
    pub rerank: Vec<(String, Vec<Stage>)>,
    /// Only the manifest rows of these classes.
    pub classes: Vec<String>,
    /// Keep at most this many rows of each class (a pseudo-random subset fixed by
    /// `sample_seed`).
    pub per_class: Option<usize>,
    /// Seed of `per_class`'s subset.
    pub sample_seed: u64,
    /// Laplace–Beltrami operator.
    pub laplacian: crate::laplace::LaplacianKind,
    /// Histogram window: this fraction of the pooled corpus distances for every configuration
    /// (`None`: each configuration's own, [`crate::presets::Config::calibration`]).
    pub window_percentile: Option<f64>,
    /// Keep every mesh at its own size (no unit-area normalisation).
    pub no_normalize: bool,
    /// Most vertices a shape is analysed at (a larger one is simplified first,
    /// [`crate::mesh::decimate`]); `None`: full resolution. Default: the server's,
    /// [`crate::presets::ANALYSIS_VERTEX_BUDGET`].
    pub vertex_budget: Option<usize>,
    /// Write every configuration's all-pairs dissimilarity matrix (re-ranked rows: ranks) as
    /// JSON here.
    pub matrices: Option<PathBuf>,
    /// Also run the leave-one-class-out protocol ([`loco`]) over the configurations (the
    /// candidates) and report it ([`EvalOutcome::loco`], the JSON's `loco`, `loco.md` in `out`).
    pub loco: Option<loco::LocoOptions>,
    /// Also rank every configuration on the `f64` histograms of its definition and report the
    /// difference the corpus encoding makes ([`encoding_check`]; the JSON's `encoding_check`).
    pub check_encoding: bool,
}

impl EvalOptions {
    /// Options with defaults for a manifest.
    pub fn new(manifest: impl Into<PathBuf>) -> Self {
        EvalOptions {
            manifest: manifest.into(),
            config: None,
            json: None,
            out: None,
            cache: None,
            no_cache: false,
            jobs: None,
            k: 100,
            reference: None,
            quiet: true,
            rerank: Vec::new(),
            classes: Vec::new(),
            per_class: None,
            sample_seed: 0,
            laplacian: crate::laplace::LaplacianKind::Cotangent,
            no_normalize: false,
            vertex_budget: Some(crate::presets::ANALYSIS_VERTEX_BUDGET),
            window_percentile: None,
            matrices: None,
            loco: None,
            check_encoding: false,
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
    /// The Markdown report (as written to `results.md`; with the leave-one-class-out protocol,
    /// its section first).
    pub markdown: String,
    /// The leave-one-class-out report, when [`EvalOptions::loco`] asked for it.
    pub loco: Option<loco::LocoReport>,
    /// The encoding check, when [`EvalOptions::check_encoding`] asked for it.
    pub encoding_check: Option<encoding_check::EncodingCheck>,
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

/// Finds a reference file for the manifest (see [`EvalOptions::reference`]).
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
pub fn evaluate(args: &EvalOptions) -> Result<EvalOutcome> {
    let threads = args.jobs.unwrap_or(0);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::InvalidArgument(format!("--jobs: {e}")))?;
    pool.install(|| evaluate_in_pool(args))
}

fn evaluate_in_pool(args: &EvalOptions) -> Result<EvalOutcome> {
    let t_total = Instant::now();
    if args.k < 2 {
        return Err(Error::InvalidArgument("--k must be at least 2".into()));
    }
    let manifest = select_rows(args)?;
    let rerank_stages = &args.rerank;
    let (configs, n_candidates) = run_configs(args)?;
    let (specs, group_of) = union_specs(&configs);
    // One calibration (and corpus) per signature group and calibration options.
    let mut cal_groups: Vec<(usize, ranking::CalibrationOptions)> = Vec::new();
    let cal_of: Vec<usize> = configs
        .iter()
        .zip(&group_of)
        .map(|(c, &g)| {
            let key = (g, c.calibration.clone());
            cal_groups
                .iter()
                .position(|k| *k == key)
                .unwrap_or_else(|| {
                    cal_groups.push(key);
                    cal_groups.len() - 1
                })
        })
        .collect();
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
    opts.prepare.max_vertices = args.vertex_budget;
    opts.laplacian = args.laplacian;
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
    let cals: Vec<ranking::Calibration> = cal_groups
        .iter()
        .map(|(g, copts)| {
            let sigs: Vec<&Signature> = ok
                .iter()
                .map(|&i| &shape_results[i].as_ref().unwrap()[*g])
                .collect();
            ranking::calibrate_with(&sigs, &specs[*g], 0, copts)
        })
        .collect();
    let corpora: Vec<Corpus> = cals
        .iter()
        .zip(&cal_groups)
        .map(|(cal, &(g, _))| {
            let layout = Layout::of(cal);
            let rows: Vec<Encoded> = shape_results
                .par_iter()
                .map(|r| match r {
                    Ok(s) => Encoded::from_signature(&s[g], cal, &layout),
                    Err(_) => Encoded::absent(&layout),
                })
                .collect();
            Corpus::build(layout, &rows)
        })
        .collect();
    // The f64 histograms of the definition, for `--check-encoding` only.
    let prepared: Vec<Vec<Option<ranking::Prepared>>> = if args.check_encoding {
        cals.iter()
            .zip(&cal_groups)
            .map(|(cal, &(g, _))| {
                shape_results
                    .par_iter()
                    .map(|r| {
                        r.as_ref()
                            .ok()
                            .map(|s| ranking::prepare_for_ranking(&s[g], cal))
                    })
                    .collect()
            })
            .collect()
    } else {
        Vec::new()
    };
    let calibration_histograms_s = t_cal.elapsed().as_secs_f64();
    // Re-ranking payloads, one set per distinct payload specification.
    let mut rerank_notes = String::new();
    let mut payload_sets: Vec<(String, Vec<Option<crate::rerank::GwPayload>>)> = Vec::new();
    let all_stages = rerank_stages
        .iter()
        .flat_map(|(_, st)| st)
        .chain(configs.iter().flat_map(|c| &c.rerank));
    for st in all_stages {
        if let Some(ps) = st.payload_spec() {
            let key = ps.key();
            if !payload_sets.iter().any(|(k, _)| *k == key) {
                let t = Instant::now();
                let akey = |bytes: &[u8]| {
                    let content = hash_parts(&[bytes]);
                    hash_parts(&[
                        content.as_bytes(),
                        &opts_json,
                        analysis_version().as_bytes(),
                    ])
                };
                let pl = rerank::shape_payloads(&manifest, &included, &opts, &akey, &cache, ps);
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
    let mut channel_cache: Vec<ChannelMatrices> = (0..cal_groups.len())
        .map(|_| ChannelMatrices::default())
        .collect();
    let (mut scoring_s, mut metrics_s) = (0.0, 0.0);
    let mut solved_pairs = rerank::PairCache::new();
    let mut dumped: Vec<(String, Vec<f64>)> = Vec::new();
    let mut held_in = args
        .loco
        .as_ref()
        .map(|_| loco::HeldIn::new(&classes, class_ids.len(), &included));
    let mut candidate: Vec<bool> = Vec::new();
    let mut reference_cache: Vec<encoding_check::ReferenceMatrices> = (0..prepared.len())
        .map(|_| encoding_check::ReferenceMatrices::default())
        .collect();
    let mut check_rows = Vec::new();
    for (c, cfg) in configs.iter().enumerate() {
        let g = cal_of[c];
        let corpus = &corpora[g];
        let t = Instant::now();
        let dist = channel_cache[g].aggregate(corpus, &included, &cfg.query);
        scoring_s += t.elapsed().as_secs_f64();
        let rescore = |q: usize, j: usize, spec: &QuerySpec| {
            let l = corpus.layout();
            Query::new(spec, l).score(l, corpus.shape(q), corpus.shape(j))
        };
        // The configuration's own stages, then each `--rerank` list on its result; every
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
                &rescore,
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
        if let Some(h) = held_in.as_mut() {
            let stages: Vec<&Stage> = cfg.rerank.iter().collect();
            loco::record_held_in(
                h,
                &cur,
                &stages,
                &dist,
                n,
                &payload_sets,
                &rescore,
                &mut solved_pairs,
            );
        }
        metrics_s += t.elapsed().as_secs_f64();
        if args.check_encoding {
            let t = Instant::now();
            check_rows.push(encoding_check::check_configuration(
                cfg,
                (&cur, &eval),
                &mut reference_cache[g],
                &prepared[g],
                corpus.layout(),
                &included,
                &payload_sets,
                &mut solved_pairs,
                (&classes, &transforms, &strengths),
            ));
            metrics_s += t.elapsed().as_secs_f64();
        }
        results.push(ConfigResult {
            name: cfg.name.clone(),
            eval,
            alias: alias_of(cfg),
        });
        candidate.push(
            args.loco
                .as_ref()
                .is_some_and(|l| l.is_candidate(&cfg.name, c, n_candidates)),
        );
        for (label, list) in rerank_stages {
            let name = format!("{}+{}", cfg.name, label);
            let mut d2 = cur.clone();
            for st in list {
                let (next, stats) = apply_stage(
                    st,
                    &dist,
                    &d2,
                    n,
                    &included,
                    &payload_sets,
                    &rescore,
                    &mut solved_pairs,
                );
                rerank_notes.push_str(&stage_note(&name, st, &stats, args.quiet));
                d2 = next;
            }
            let eval = metrics::evaluate(&d2, n, &classes, &transforms, &strengths, &included);
            if let Some(h) = held_in.as_mut() {
                let stages: Vec<&Stage> = cfg.rerank.iter().chain(list).collect();
                loco::record_held_in(
                    h,
                    &d2,
                    &stages,
                    &dist,
                    n,
                    &payload_sets,
                    &rescore,
                    &mut solved_pairs,
                );
            }
            if args.matrices.is_some() {
                dumped.push((name.clone(), d2.clone()));
            }
            results.push(ConfigResult {
                name,
                eval,
                alias: None,
            });
            candidate.push(
                args.loco
                    .as_ref()
                    .is_some_and(|l| l.is_candidate(&cfg.name, c, n_candidates)),
            );
        }
    }
    drop(channel_cache);
    drop(reference_cache);
    let check = args
        .check_encoding
        .then_some(encoding_check::EncodingCheck {
            tie_tolerance: encoding_check::TIE_TOLERANCE,
            accepted_points: encoding_check::ACCEPTED_POINTS,
            rows: check_rows,
        });
    let loco_report = held_in.map(|h| {
        let fixed = args
            .loco
            .as_ref()
            .map(|l| l.fixed.clone())
            .unwrap_or_default();
        h.report(&loco::RunView {
            results: &results,
            candidate: &candidate,
            fixed: &fixed,
            class_ids: &class_ids,
            classes: &classes,
            transforms: &transforms,
            strengths: &strengths,
        })
    });
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
        // A stage leaves ranks in its rows, not distances: the pooled ROC of such a
        // configuration thresholds ranks across queries, which its EER column reports.
        markdown.push_str(&format!(
            "\n## Re-ranking\n\nThe rows of a configuration with stages hold ranks, not \
             distances: its pooled ROC and EER threshold the rank a stage gave each shape \
             (the same rank cut for every query), so they are not comparable with the EER of \
             a configuration without stages. mAP and the per-query AUC are unaffected.\n\n\
             {rerank_notes}"
        ));
    }
    if let Some(ch) = &check {
        markdown.push_str(&format!("\n{}", ch.markdown()));
    }
    if let Some(r) = &loco_report {
        let section = r.markdown();
        if let Some(dir) = &args.out {
            std::fs::write(dir.join("loco.md"), &section)?;
        }
        markdown = format!("{section}\n{markdown}");
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
    let mut json_doc = report::json_document(
        &results,
        &failures,
        &serde_json::to_value(&timings).unwrap_or(Value::Null),
        extra,
    );
    if let (Some(ch), Some(o)) = (&check, json_doc.as_object_mut()) {
        o.insert(
            "encoding_check".into(),
            serde_json::to_value(ch).unwrap_or(Value::Null),
        );
    }
    if let (Some(r), Some(o)) = (&loco_report, json_doc.as_object_mut()) {
        o.insert(
            "loco".into(),
            serde_json::to_value(r).unwrap_or(Value::Null),
        );
    }
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
        loco: loco_report,
        encoding_check: check,
    })
}
