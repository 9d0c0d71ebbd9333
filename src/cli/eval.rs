//! `shapeseek eval`: its flags, and the `--rerank` grammar.
//!
//! `--rerank STAGE` re-ranks each query's top `K` of every configuration and evaluates the
//! result as an extra configuration named `<config>+<STAGE>`. STAGE syntax: `none`, a JSON
//! object / JSON file holding a stage in the configuration form (`{"kind": "reciprocal", …}`,
//! see [`shapeseek::search::stage`]), or the short form `sgw:K[:key=value]…` with keys `m`
//! (samples, default 100), `t` (comma-separated times, default 0.016,0.04,0.1), `metric`
//! (`dist` | `kernel`), `rule` (`abs` | `lambda1`: `t = τ/λ₁`), `eps` (relative ε, default
//! 0.003), `outer` (outer iterations, default 5), `anchors` (1: also solve from two anchored
//! starts, default 0), `blend` (weight `w` of the first-stage rank in a rank blend; absent: GW
//! alone); or `recip:K[:key=value]…` with keys `k`
//! (comma-separated neighbourhood sizes, default 8,16,32), `expand` (default 4) and `lambda`
//! (default 0.1).

use clap::Args;
use shapeseek::eval::loco::LocoOptions;
use shapeseek::eval::{evaluate, report, EvalOptions};
use shapeseek::laplace::LaplacianKind;
use shapeseek::rerank::{Fusion, GwMetric, ReciprocalStage, SgwStage, TimeRule};
use shapeseek::search::Stage;
use shapeseek::{Error, Result};
use std::path::PathBuf;

/// Arguments of `shapeseek eval`.
#[derive(Debug, Clone, Args)]
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
    /// Entries are keyed on the mesh bytes, the options and the sources this binary was built
    /// from: another build (or version) recomputes instead of reading them.
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
    /// Re-ranking stage applied to every configuration's ranking, evaluated as an extra
    /// configuration `<config>+<STAGE>` (repeatable): `sgw:K[:key=value]...`,
    /// `recip:K[:key=value]...`, a JSON stage or a JSON file (see the module docs).
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
    /// Histogram window: this fraction of the pooled corpus distances, for every configuration
    /// of the run. Without it each configuration uses its own: the paper's 0.95, `default`'s
    /// 0.90. Smaller windows keep only the short-range part of every distribution.
    #[arg(long)]
    pub window_percentile: Option<f64>,
    /// Keep every mesh at its own size (no unit-area normalisation): the "raw" runs that show
    /// what scaling does to each kernel (paper Table 2's Scale row).
    #[arg(long)]
    pub no_normalize: bool,
    /// Most vertices a shape is analysed at: a larger mesh is simplified to this many before
    /// its spectrum, as the server does (`analysis_vertex_budget`). 0: full resolution.
    #[arg(long, default_value_t = shapeseek::presets::ANALYSIS_VERTEX_BUDGET)]
    pub vertex_budget: usize,
    /// Write every configuration's all-pairs dissimilarity matrix (re-ranked rows: ranks) as JSON
    /// here, with the manifest's ids, classes and transforms, for analysis outside shapeseek.
    #[arg(long)]
    pub matrices: Option<PathBuf>,
    /// Evaluation protocol: `standard` (every shape queries all others) or `loco`
    /// (leave-one-class-out: per class, the configuration with the best All mAP on the other
    /// classes is chosen among `--config`'s configurations and scored on the held-out class;
    /// the section comes first in the report, `loco.md` in `--out`, `loco` in `--json`).
    #[arg(long, default_value = "standard")]
    pub protocol: String,
    /// With `--protocol loco`: configurations reported per fold without selection
    /// (comma-separated names; added to the run when `--config` lacks them).
    #[arg(long, value_delimiter = ',', default_value = "default")]
    pub loco_fixed: Vec<String>,
    /// With `--protocol loco`: the fixed configurations are never candidates (e.g. `--config
    /// paper --loco-exclude-fixed`: what the protocol picks among the paper's methods alone).
    #[arg(long)]
    pub loco_exclude_fixed: bool,
    /// Also rank every configuration on the f64 histograms of its definition and report, per
    /// configuration, the difference the search's compact corpus encoding makes (ties at
    /// rounding level merged; section "Encoding check", `encoding_check` in `--json`).
    #[arg(long)]
    pub check_encoding: bool,
}

impl EvalArgs {
    /// The library's options.
    pub fn options(&self) -> Result<EvalOptions> {
        let laplacian = match self.laplacian.as_str() {
            "cotangent" => LaplacianKind::Cotangent,
            "intrinsic-delaunay" => LaplacianKind::IntrinsicDelaunay,
            o => {
                return Err(Error::InvalidArgument(format!(
                    "--laplacian {o}: cotangent or intrinsic-delaunay"
                )))
            }
        };
        let least = shapeseek::mesh::prepare::MIN_VERTEX_BUDGET;
        if self.vertex_budget != 0 && self.vertex_budget < least {
            return Err(Error::InvalidArgument(format!(
                "--vertex-budget {}: 0 (none) or at least {least}",
                self.vertex_budget
            )));
        }
        let loco = match self.protocol.as_str() {
            "standard" => None,
            "loco" | "leave-one-class-out" => Some(LocoOptions {
                fixed: self.loco_fixed.clone(),
                exclude_fixed: self.loco_exclude_fixed,
            }),
            o => {
                return Err(Error::InvalidArgument(format!(
                    "--protocol {o}: standard or loco"
                )))
            }
        };
        Ok(EvalOptions {
            manifest: self.manifest.clone(),
            config: self.config.clone(),
            json: self.json.clone(),
            out: self.out.clone(),
            cache: self.cache.clone(),
            no_cache: self.no_cache,
            jobs: self.jobs,
            k: self.k,
            reference: self.reference.clone(),
            quiet: self.quiet,
            rerank: self
                .rerank
                .iter()
                .map(|r| parse_stage(r).map(|s| (r.clone(), s)))
                .collect::<Result<_>>()?,
            classes: self.classes.clone(),
            per_class: self.per_class,
            sample_seed: self.sample_seed,
            laplacian,
            window_percentile: self.window_percentile,
            no_normalize: self.no_normalize,
            vertex_budget: (self.vertex_budget > 0).then_some(self.vertex_budget),
            matrices: self.matrices.clone(),
            loco,
            check_encoding: self.check_encoding,
        })
    }
}

/// Runs `shapeseek eval`: evaluates, prints the Markdown summary and stage times to stdout and
/// writes the requested files. `Ok(false)` when shapes had to be left out: the figures are
/// over the others, the report lists them, stderr says so and the exit status is 1 (it was 0,
/// and a script comparing figures could not tell a run over fewer shapes).
pub fn run(args: &EvalArgs) -> Result<bool> {
    let opts = args.options()?;
    check_outputs(args)?;
    let out = evaluate(&opts)?;
    print!("{}", out.markdown);
    if args.per_strength {
        println!(
            "\n## mAP per strength (%)\n\n{}",
            report::per_strength_table(&out.results)
        );
    }
    if let Some(first) = out.failures.first() {
        eprintln!(
            "eval: {} of {} shapes could not be analysed and are left out of every figure \
             (listed under \"Left out of the ranking\"; first: {} [{}] {})",
            out.failures.len(),
            out.manifest.entries.len(),
            first.path,
            first.code,
            first.message
        );
    }
    Ok(out.failures.is_empty())
}

/// Refuses, before any work, output paths that cannot be written: a folder (`--out`,
/// `--cache`) that is a file, a file (`--json`, `--matrices`) that is a folder, or a parent
/// folder that cannot be created. (They were found only after the whole evaluation, hours on
/// a large manifest without a cache, with an error that named no path.)
fn check_outputs(args: &EvalArgs) -> Result<()> {
    let bad = |flag: &str, p: &std::path::Path, why: &str| {
        Err(Error::InvalidArgument(format!(
            "{flag} {}: {why}",
            p.display()
        )))
    };
    for (flag, dir) in [("--out", &args.out), ("--cache", &args.cache)] {
        if let Some(d) = dir {
            if d.exists() && !d.is_dir() {
                return bad(flag, d, "exists and is not a folder");
            }
            if let Err(e) = std::fs::create_dir_all(d) {
                return bad(flag, d, &format!("cannot create it ({e})"));
            }
        }
    }
    for (flag, file) in [("--json", &args.json), ("--matrices", &args.matrices)] {
        if let Some(f) = file {
            if f.is_dir() {
                return bad(flag, f, "is a folder; give a file name");
            }
            if let Some(parent) = f.parent().filter(|p| !p.as_os_str().is_empty()) {
                if let Err(e) = std::fs::create_dir_all(parent) {
                    return bad(flag, f, &format!("cannot create its folder ({e})"));
                }
            }
        }
    }
    Ok(())
}

/// Parses a `--rerank` value (see the module docs): the stages it names (none for `none`),
/// validated.
pub fn parse_stage(s: &str) -> Result<Vec<Stage>> {
    let bad = |m: String| Error::InvalidArgument(format!("--rerank {s}: {m}"));
    let t = s.trim();
    if t == "none" {
        return Ok(Vec::new());
    }
    let json = |text: &str| -> Result<Vec<Stage>> {
        let st: Stage = serde_json::from_str(text).map_err(|e| bad(e.to_string()))?;
        Ok(vec![st])
    };
    if t.starts_with('{') {
        return json(t);
    }
    let p = std::path::Path::new(t);
    if p.is_file() {
        return json(&std::fs::read_to_string(p)?);
    }
    let mut parts = t.split(':');
    let kind = parts.next();
    if kind == Some("recip") {
        let st = parse_reciprocal(parts).map_err(bad)?;
        return Ok(vec![Stage::new(st).map_err(|e| bad(e.to_string()))?]);
    }
    if kind != Some("sgw") {
        return Err(bad(
            "expected none, a JSON stage, sgw:K[:key=value]... or recip:K[:key=value]...".into(),
        ));
    }
    let k: usize = parts
        .next()
        .ok_or_else(|| bad("missing K".into()))?
        .parse()
        .map_err(|_| bad("K must be an integer".into()))?;
    let mut st = SgwStage {
        shortlist: k,
        ..SgwStage::default()
    };
    for kv in parts {
        let (key, val) = kv
            .split_once('=')
            .ok_or_else(|| bad(format!("'{kv}' is not key=value")))?;
        let num = |v: &str| {
            v.parse::<f64>()
                .map_err(|_| bad(format!("{key}: not a number")))
        };
        match key {
            "m" => st.payload.samples = num(val)? as usize,
            "t" => st.payload.times = val.split(',').map(num).collect::<Result<Vec<_>>>()?,
            "metric" => {
                st.payload.metric = match val {
                    "dist" | "diffusion" => GwMetric::Diffusion,
                    "kernel" | "heat" => GwMetric::HeatKernel,
                    _ => return Err(bad(format!("metric {val}"))),
                }
            }
            "rule" => {
                st.payload.time_rule = match val {
                    "abs" | "absolute" => TimeRule::Absolute,
                    "lambda1" => TimeRule::Lambda1,
                    _ => return Err(bad(format!("rule {val}"))),
                }
            }
            "eps" => st.gw.eps_rel = num(val)?,
            "outer" => st.gw.outer_iterations = num(val)? as usize,
            "anchors" => st.gw.anchored_starts = num(val)? != 0.0,
            "blend" => st.fusion = Fusion::RankBlend { weight: num(val)? },
            _ => return Err(bad(format!("unknown key {key}"))),
        }
    }
    Ok(vec![
        Stage::new(Stage::SpectralGw(st)).map_err(|e| bad(e.to_string()))?
    ])
}

/// `recip:K[:k=a,b,..][:expand=e][:lambda=l]` after the `recip` word.
fn parse_reciprocal<'a>(
    mut parts: impl Iterator<Item = &'a str>,
) -> std::result::Result<Stage, String> {
    let mut st = ReciprocalStage {
        shortlist: parts
            .next()
            .ok_or("missing K")?
            .parse()
            .map_err(|_| "K must be an integer")?,
        ..ReciprocalStage::default()
    };
    for kv in parts {
        let (key, val) = kv
            .split_once('=')
            .ok_or_else(|| format!("'{kv}' is not key=value"))?;
        let int = |v: &str| {
            v.parse::<usize>()
                .map_err(|_| format!("{key}: not an integer"))
        };
        match key {
            "k" => st.neighbourhoods = val.split(',').map(int).collect::<Result<_, _>>()?,
            "expand" => st.expansion = int(val)?,
            "lambda" => {
                st.original_weight = val.parse().map_err(|_| format!("{key}: not a number"))?
            }
            _ => return Err(format!("unknown key {key}")),
        }
    }
    Ok(Stage::Reciprocal(st))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grammar() {
        assert!(parse_stage("none").unwrap().is_empty());
        let s = parse_stage("sgw:50:eps=0.01:blend=0.5").unwrap();
        match &s[..] {
            [Stage::SpectralGw(g)] => {
                assert_eq!(g.shortlist, 50);
                assert_eq!(g.gw.eps_rel, 0.01);
                assert!(!g.gw.anchored_starts);
                assert_eq!(g.fusion, Fusion::RankBlend { weight: 0.5 });
            }
            other => panic!("{other:?}"),
        }
        match &parse_stage("sgw:20:anchors=1").unwrap()[..] {
            [Stage::SpectralGw(g)] => assert!(g.gw.anchored_starts),
            other => panic!("{other:?}"),
        }
        let r = parse_stage("recip:100:k=4,8:expand=2:lambda=0.3").unwrap();
        assert_eq!(r[0].label(), "recip:100:k=4,8:expand=2:lambda=0.3");
        let j = parse_stage(r#"{"kind": "reciprocal", "shortlist": 30, "neighbourhoods": [8], "expansion": 4, "original_weight": 0.1}"#).unwrap();
        assert_eq!(j[0].shortlist(), 30);
        for bad in [
            "sgw",
            "sgw:x",
            "recip:0",
            "recip:10:k=0",
            "sgw:10:eps=5",
            "foo:1",
            r#"{"kind": "none"}"#,
        ] {
            assert!(parse_stage(bad).is_err(), "{bad}");
        }
    }
}
