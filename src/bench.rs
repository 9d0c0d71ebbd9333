//! `shapeseek bench spectrum`: time the whole spectrum (Laplacian + factorisation + eigensolve)
//! on generated meshes of several sizes, with peak memory, and — where Python with SciPy is
//! installed — the ratio to `scipy.sparse.linalg.eigsh` in shift-invert mode on the very same
//! matrices (exported from Rust as Matrix Market files), measured in the same run.
//!
//! Each case runs in a child process of this binary so its peak resident memory (VmHWM) is its
//! own.

use clap::{Args, Subcommand};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use shapeseek::eigen::{smallest_eigenpairs, EigenOptions};
use shapeseek::laplace::{cotangent_laplacian, write_matrix_market};
use shapeseek::mesh::generate;
use shapeseek::mesh::prepare::{prepare, PrepareOptions};
use shapeseek::search::{Encoded, Layout};
use shapeseek::signature::{Signature, SignatureSpec};
use shapeseek::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

#[derive(Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    what: BenchWhat,
}

#[derive(Subcommand)]
enum BenchWhat {
    /// Spectrum of generated bumpy tori (no symmetry) of the given sizes.
    Spectrum(SpectrumBench),
    /// Signature computation from a computed spectrum (six-scale heat L2 and other channels).
    Signature(SignatureBench),
    /// First-stage search latency and resident memory per shape over N stored shapes (the
    /// server's scan index, without HTTP),
    /// with the full ranking measured in the same run as the reference.
    Search(SearchBench),
    /// Writes N synthetic shapes into a server data directory (for HTTP load tests).
    Populate(PopulateBench),
    /// Writes generated meshes of a given size (for ingest load tests).
    Meshes(MeshesBench),
}

#[derive(Args)]
struct SearchBench {
    /// Stored signatures (synthetic, see `bench populate`).
    #[arg(long, value_delimiter = ',', default_value = "1000,100000")]
    sizes: Vec<usize>,
    /// Queries per size (p50 and p99 are reported).
    #[arg(long, default_value_t = 50)]
    queries: usize,
    /// Hits per query.
    #[arg(long, default_value_t = 10)]
    top_k: usize,
    /// Dissimilarity instead of the default configuration's (API names: `n_l1`, `emd`, `l2`,
    /// `chi2`, ...).
    #[arg(long)]
    dissimilarity: Option<String>,
    /// Spread of the synthetic copies' distance scale factors (see `bench populate`).
    #[arg(long, default_value_t = 0.05)]
    spread: f64,
    /// Query with shapes that are not stored: base shapes with every distance scaled by this
    /// factor (outside `1 ± spread`, their nearest stored neighbours are far: a harder case
    /// for the bounds). Default: stored shapes, themselves left out.
    #[arg(long)]
    query_scale: Option<f64>,
    /// Distinct synthetic signatures encoded from their sketches (a multiple of 24 is used);
    /// larger indexes repeat these rows, each copy with a few counts moved by one unit to a
    /// neighbouring bin (deterministic), since encoding a sketch costs about a millisecond.
    #[arg(long, default_value_t = 100_000)]
    distinct: usize,
    /// Queries whose pruned top-k is compared with the full ranking (every candidate scored);
    /// default: every query up to 100 000 stored shapes, else 3.
    #[arg(long)]
    verify: Option<usize>,
}

#[derive(Args)]
struct PopulateBench {
    /// Server data directory (created; shapes are added to what it holds).
    #[arg(long, required_unless_present = "store", conflicts_with = "store")]
    data: Option<PathBuf>,
    /// A migrated PostgreSQL database (`postgres://…`) to add the shapes to instead (8
    /// concurrent single-shape transactions through the store's own `insert`).
    #[arg(long)]
    store: Option<String>,
    /// Number of synthetic shapes: copies of 24 generated shapes' signatures, each copy's
    /// distances scaled by its own factor in [0.95, 1.05]; the stored original of each is a
    /// 12-vertex OBJ with a unique comment (tagged `synthetic`).
    #[arg(long, default_value_t = 100_000)]
    count: usize,
    /// Also store a re-ranking payload per shape (one of the 24 base shapes' payloads, about
    /// 60 KB each), so that spectral-GW stages have work to do.
    #[arg(long)]
    payloads: bool,
}

#[derive(Args)]
struct MeshesBench {
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
    /// Number of meshes (distinct bumpy tori).
    #[arg(long, default_value_t = 20)]
    count: usize,
    /// Approximate vertex count of each.
    #[arg(long, default_value_t = 10_000)]
    size: usize,
}

#[derive(Args)]
struct SignatureBench {
    /// Approximate vertex count of the generated shape.
    #[arg(long, default_value_t = 10000)]
    size: usize,
    /// Eigenpairs of the spectrum the signatures are computed from.
    #[arg(long, default_value_t = 100)]
    k: usize,
    /// Repetitions per signature spec (the median is reported).
    #[arg(long, default_value_t = 5)]
    repeat: usize,
}

#[derive(Args)]
struct SpectrumBench {
    /// Approximate vertex counts.
    #[arg(long, value_delimiter = ',', default_value = "10000,50000,200000")]
    sizes: Vec<usize>,
    /// Numbers of eigenpairs.
    #[arg(long, value_delimiter = ',', default_value = "100,200")]
    ks: Vec<usize>,
    /// Skip the SciPy comparison even when SciPy is installed.
    #[arg(long)]
    no_scipy: bool,
    /// Python interpreter used for the SciPy comparison.
    #[arg(long, default_value = "python3")]
    python: String,
    /// ARPACK `tol` given to eigsh (0 = machine precision, SciPy's default).
    #[arg(long, default_value_t = 0.0)]
    scipy_tol: f64,
    /// Write a JSON summary here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Internal: run one case `SIZE:K` in this process and print its JSON.
    #[arg(long, hide = true)]
    single: Option<String>,
    /// Internal: where the single case exports its matrices.
    #[arg(long, hide = true)]
    export: Option<PathBuf>,
}

#[derive(Debug, Serialize, Deserialize)]
struct CaseResult {
    vertices: usize,
    k: usize,
    prepare_s: f64,
    laplacian_s: f64,
    factorization_s: f64,
    eigensolve_s: f64,
    total_s: f64,
    peak_mib: f64,
    max_residual: f64,
    restarts: usize,
    solves: usize,
    shift: f64,
    scipy: Option<ScipyResult>,
}

#[derive(Debug, Serialize, Deserialize)]
struct ScipyResult {
    seconds: f64,
    peak_mib: f64,
    max_residual: f64,
    max_rel_diff: f64,
}

pub fn run(args: &BenchArgs) -> Result<()> {
    match &args.what {
        BenchWhat::Spectrum(b) => match &b.single {
            Some(case) => run_single(case, b.export.as_deref()),
            None => run_all(b),
        },
        BenchWhat::Signature(b) => run_signature(b),
        BenchWhat::Search(b) => run_search(b),
        BenchWhat::Populate(b) => run_populate(b),
        BenchWhat::Meshes(b) => run_meshes(b),
    }
}

/// Torus grid `nu × nv ≈ size` with aspect 5:4.
fn grid(size: usize) -> (usize, usize) {
    let nu = ((size as f64 * 1.25).sqrt().round() as usize).max(3);
    (nu, (size / nu).max(3))
}

fn peak_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<f64>().ok())
            })
        })
        .map(|kib| kib / 1024.0)
        .unwrap_or(f64::NAN)
}

fn run_single(case: &str, export: Option<&Path>) -> Result<()> {
    let bad = || Error::InvalidArgument(format!("--single wants SIZE:K, got {case:?}"));
    let (size, k) = case.split_once(':').ok_or_else(bad)?;
    let size: usize = size.parse().map_err(|_| bad())?;
    let k: usize = k.parse().map_err(|_| bad())?;
    let (nu, nv) = grid(size);
    let raw = generate::bumpy_torus(nu, nv);
    let tp = Instant::now();
    let (mesh, _) = prepare(&raw, &PrepareOptions::default())?;
    let prepare_s = tp.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let lap = cotangent_laplacian(&mesh)?;
    let laplacian_s = t0.elapsed().as_secs_f64();
    let pairs = smallest_eigenpairs(
        &lap.stiffness,
        &lap.mass,
        &EigenOptions {
            k,
            ..Default::default()
        },
    )?;
    let total_s = t0.elapsed().as_secs_f64();
    let result = CaseResult {
        vertices: mesh.vertices.len(),
        k,
        prepare_s,
        laplacian_s,
        factorization_s: pairs.stats.factor_ms / 1e3,
        eigensolve_s: pairs.stats.iterate_ms / 1e3,
        total_s,
        peak_mib: peak_mib(),
        max_residual: shapeseek::eigen::max_or_nan(&pairs.residuals),
        restarts: pairs.stats.restarts,
        solves: pairs.stats.operator_applications,
        shift: pairs.stats.shift,
        scipy: None,
    };
    if let Some(dir) = export {
        std::fs::create_dir_all(dir)?;
        let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("L.mtx"))?);
        write_matrix_market(&lap.stiffness, &mut f)?;
        f.flush()?;
        let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("mass.txt"))?);
        for a in &lap.mass {
            writeln!(f, "{a:e}")?;
        }
        f.flush()?;
        let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("ours.txt"))?);
        for v in &pairs.values {
            writeln!(f, "{v:e}")?;
        }
        f.flush()?;
    }
    println!(
        "{}",
        serde_json::to_string(&result).map_err(|e| Error::Numerical(e.to_string()))?
    );
    Ok(())
}

const SCIPY_SCRIPT: &str = r#"
import json, resource, sys, time
import numpy as np, scipy.io, scipy.sparse as sp, scipy.sparse.linalg as sla
d, k, sigma, tol = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
L = scipy.io.mmread(d + "/L.mtx").tocsc()
a = np.loadtxt(d + "/mass.txt")
ours = np.loadtxt(d + "/ours.txt")
A = sp.diags(a).tocsc()
t = time.perf_counter()
vals, vecs = sla.eigsh(L, k=k, M=A, sigma=sigma, which="LM", tol=tol)
dt = time.perf_counter() - t
order = np.argsort(vals); vals = vals[order]; vecs = vecs[:, order]
lam_ref = 4 * np.pi / a.sum()
R = L @ vecs - (A @ vecs) * vals
res = np.linalg.norm(R, axis=0) / ((np.abs(vals) + lam_ref) * np.linalg.norm(A @ vecs, axis=0))
rel = np.abs(vals[1:] - ours[1:]) / np.abs(vals[1:])
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print(json.dumps({"seconds": dt, "peak_mib": peak, "max_residual": float(res.max()), "max_rel_diff": float(rel.max())}))
"#;

fn scipy_available(python: &str) -> bool {
    Command::new(python)
        .args(["-c", "import scipy, numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

fn run_all(b: &SpectrumBench) -> Result<()> {
    let exe = std::env::current_exe()?;
    let use_scipy = !b.no_scipy && scipy_available(&b.python);
    if !use_scipy && !b.no_scipy {
        eprintln!(
            "note: {} with scipy not found: no SciPy comparison (pip install scipy)",
            b.python
        );
    }
    let tmp = std::env::temp_dir().join(format!("shapeseek-bench-{}", std::process::id()));
    let script = tmp.join("eigsh.py");
    std::fs::create_dir_all(&tmp)?;
    std::fs::write(&script, SCIPY_SCRIPT)?;
    println!(
        "{:>8} {:>4} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8} {:>7} {:>9} {:>9} {:>7} {:>9}",
        "vertices",
        "k",
        "prep s",
        "lapl s",
        "factor s",
        "eigen s",
        "total s",
        "peak MiB",
        "max res",
        "solves",
        "scipy s",
        "scipy MiB",
        "ratio",
        "max |Δλ|"
    );
    let mut results = Vec::new();
    for &size in &b.sizes {
        for &k in &b.ks {
            let dir = tmp.join(format!("{size}-{k}"));
            let mut cmd = Command::new(&exe);
            cmd.args(["bench", "spectrum", "--single", &format!("{size}:{k}")]);
            if use_scipy {
                cmd.arg("--export").arg(&dir);
            }
            let out = cmd.output()?;
            if !out.status.success() {
                return Err(Error::Numerical(format!(
                    "case {size}:{k} failed: {}",
                    String::from_utf8_lossy(&out.stderr)
                )));
            }
            let mut r: CaseResult = serde_json::from_slice(&out.stdout)
                .map_err(|e| Error::Numerical(format!("case {size}:{k}: bad output: {e}")))?;
            if use_scipy {
                let o = Command::new(&b.python)
                    .arg(&script)
                    .arg(&dir)
                    .arg(k.to_string())
                    .arg(r.shift.to_string())
                    .arg(b.scipy_tol.to_string())
                    .env("OMP_NUM_THREADS", "1")
                    .output()?;
                if o.status.success() {
                    r.scipy = serde_json::from_slice(&o.stdout).ok();
                } else {
                    eprintln!(
                        "scipy case {size}:{k} failed: {}",
                        String::from_utf8_lossy(&o.stderr)
                    );
                }
                let _ = std::fs::remove_dir_all(&dir);
            }
            let (ss, sm, ratio, diff) = match &r.scipy {
                Some(s) => (
                    format!("{:.2}", s.seconds),
                    format!("{:.0}", s.peak_mib),
                    format!("{:.2}x", s.seconds / r.total_s),
                    format!("{:.1e}", s.max_rel_diff),
                ),
                None => ("-".into(), "-".into(), "-".into(), "-".into()),
            };
            println!(
                "{:>8} {:>4} {:>9.3} {:>9.3} {:>9.3} {:>9.3} {:>9.3} {:>9.0} {:>8.1e} {:>7} {:>9} {:>9} {:>7} {:>9}",
                r.vertices, r.k, r.prepare_s, r.laplacian_s, r.factorization_s, r.eigensolve_s, r.total_s, r.peak_mib, r.max_residual, r.solves, ss, sm, ratio, diff
            );
            results.push(r);
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    println!("total = Laplacian + factorisation + eigensolve (prep = cleaning + normalisation, not in total); ratio = SciPy eigsh seconds / shapeseek total, same matrices, same k, same shift; max |Δλ| = largest relative difference of λ1..λk-1.");
    if let Some(path) = &b.json {
        std::fs::write(
            path,
            serde_json::to_vec_pretty(&results).map_err(|e| Error::Numerical(e.to_string()))?,
        )?;
    }
    Ok(())
}

/// Wall and process CPU time of a closure, in milliseconds.
fn timed<T>(f: impl FnOnce() -> T) -> (T, f64, f64) {
    let cpu = || {
        // utime + stime of this process from /proc/self/stat, in clock ticks of 10 ms (Linux).
        std::fs::read_to_string("/proc/self/stat")
            .ok()
            .and_then(|s| {
                let rest = s.rsplit_once(')')?.1.split_whitespace().collect::<Vec<_>>();
                let ut: f64 = rest.get(11)?.parse().ok()?;
                let st: f64 = rest.get(12)?.parse().ok()?;
                Some((ut + st) * 10.0)
            })
            .unwrap_or(f64::NAN)
    };
    let (c0, t0) = (cpu(), Instant::now());
    let out = f();
    (out, t0.elapsed().as_secs_f64() * 1e3, cpu() - c0)
}

fn run_signature(b: &SignatureBench) -> Result<()> {
    use shapeseek::signature::{compute_signature, ChannelSpec, Norm, SignatureSpec};
    use shapeseek::spectrum::{analyze, AnalyzeOptions};
    let (nu, nv) = grid(b.size);
    let mesh = generate::bumpy_torus(nu, nv);
    let opts = AnalyzeOptions {
        eigen: EigenOptions {
            k: b.k,
            ..Default::default()
        },
        ..Default::default()
    };
    let (analysis, wall, cpu) = timed(|| analyze(&mesh, &opts));
    let analysis = analysis?;
    println!(
        "shape: {} vertices, k = {}; prepare + spectrum {wall:.0} ms wall ({cpu:.0} ms CPU)",
        analysis.mesh.vertices.len(),
        b.k
    );
    let heat6: Vec<ChannelSpec> = [0.016, 0.04, 0.1, 0.25, 0.625, 1.5625]
        .iter()
        .map(|&t| ChannelSpec::heat(t, Norm::L2))
        .collect();
    let specs = vec![
        (
            "six-scale heat L2 (default quadrature)",
            SignatureSpec::with_channels(heat6),
        ),
        (
            "commute time + step + ShapeDNA + D2 + geodesic",
            SignatureSpec::with_channels(vec![
                ChannelSpec::commute_time(),
                ChannelSpec::step(4.0 * std::f64::consts::PI * 10.0),
                ChannelSpec::shape_dna(50),
                ChannelSpec::d2(2000),
                ChannelSpec::geodesic(None),
            ]),
        ),
        (
            "heat L1 + L∞ at t = 0.1",
            SignatureSpec::with_channels(vec![
                ChannelSpec::heat(0.1, Norm::L1),
                ChannelSpec::heat(0.1, Norm::LInf),
            ]),
        ),
    ];
    println!(
        "{:<48} {:>12} {:>12} {:>12}",
        "signature spec", "median ms", "min ms", "CPU ms"
    );
    for (name, spec) in &specs {
        let mut walls = Vec::new();
        let mut cpus = Vec::new();
        for _ in 0..b.repeat.max(1) {
            let (sig, wall, cpu) = timed(|| compute_signature(&analysis, spec));
            sig?;
            walls.push(wall);
            cpus.push(cpu);
        }
        walls.sort_by(f64::total_cmp);
        cpus.sort_by(f64::total_cmp);
        println!(
            "{name:<48} {:>12.1} {:>12.1} {:>12.1}",
            walls[walls.len() / 2],
            walls[0],
            cpus[cpus.len() / 2]
        );
    }
    Ok(())
}

/// Base shapes of the synthetic index: bumpy spheres and bumpy tori, each stretched by its own
/// anisotropic factors (which changes its intrinsic geometry, hence its signature).
const SYNTHETIC_BASES: usize = 24;

/// A deterministic uniform number in [0, 1) for `i` (SplitMix64).
fn unit(i: u64) -> f64 {
    let mut z = i.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

/// The 24 base shapes' signatures under `spec` (and their re-ranking payloads when asked).
fn synthetic_bases(
    spec: &SignatureSpec,
    payloads: bool,
) -> Result<Vec<(Signature, Option<shapeseek::rerank::GwPayload>)>> {
    use shapeseek::rerank::{compute_payload, PayloadSpec};
    use shapeseek::signature::sign;
    use shapeseek::spectrum::AnalyzeOptions;
    (0..SYNTHETIC_BASES)
        .into_par_iter()
        .map(|j| {
            let mut m = if j % 2 == 0 {
                generate::bumpy_sphere(3, 0.1 + 0.02 * j as f64)
            } else {
                generate::bumpy_torus(36 + 2 * j, 18)
            };
            let s = [
                1.0 + 0.06 * (j % 5) as f64,
                1.0,
                1.0 - 0.05 * (j % 3) as f64,
            ];
            for v in &mut m.vertices {
                *v = [v[0] * s[0], v[1] * s[1], v[2] * s[2]];
            }
            // As the server signs (both cut versions when the spec has an alternate cut: the
            // bumpy tori are genuine handles, which the default's second cut takes).
            let (a, sig) = sign(&m, spec, &AnalyzeOptions::default())?;
            let p = if payloads {
                Some(compute_payload(&a, &PayloadSpec::default())?)
            } else {
                None
            };
            Ok((sig, p))
        })
        .collect()
}

/// Synthetic signature `i` from the bases: base `i % 24` with every distance scaled by a
/// factor in [1 − spread, 1 + spread] (copies `0..24` are the bases themselves). With the
/// default spread 0.05 a query has a few thousand same-base neighbours at 10⁵ shapes, most of
/// them close; a wider spread makes neighbours farther apart (more exact scores per query).
fn synthetic_signature(
    bases: &[(Signature, Option<shapeseek::rerank::GwPayload>)],
    i: usize,
    spread: f64,
) -> Signature {
    let sig = &bases[i % bases.len()].0;
    if i < bases.len() {
        return sig.clone();
    }
    scaled(sig, 1.0 + spread * (2.0 * unit(i as u64) - 1.0))
}

/// `sig` with every distance multiplied by `f` and every eigenvalue (ShapeDNA) by `f⁻²`, as the
/// shape scaled by `f` would have them (its second cut version's too).
fn scaled(sig: &Signature, f: f64) -> Signature {
    use shapeseek::signature::ChannelValues;
    let mut sig = sig.clone();
    for c in &mut sig.channels {
        match &mut c.values {
            ChannelValues::Distribution(q) => q.quantiles.iter_mut().for_each(|x| *x *= f),
            ChannelValues::Vector(v) => v.iter_mut().for_each(|x| *x /= f * f),
        }
    }
    sig.alternate = sig.alternate.map(|a| Box::new(scaled(&a, f)));
    sig
}

/// Resident set size of this process (VmRSS), in bytes.
fn rss_bytes() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmRSS:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<f64>().ok())
            })
        })
        .map(|kib| kib * 1024.0)
        .unwrap_or(f64::NAN)
}

/// Copy `c ≥ 1` of an encoded row: up to four counts moved by one unit to the next bin of
/// the same channel (positions from `i`), group sums recomputed; its second version likewise.
fn perturbed(e: &Encoded, layout: &Layout, i: usize) -> Encoded {
    let mut e = e.clone();
    let bins = layout.bins;
    for k in 0..layout.histograms() {
        for r in 0..4u64 {
            let j = (unit(i as u64 * 131 + k as u64 * 17 + r) * (bins - 1) as f64) as usize;
            let at = k * bins + j;
            if e.hist[at] > 0 && e.hist[at + 1] < u16::MAX {
                e.hist[at] -= 1;
                e.hist[at + 1] += 1;
            }
        }
    }
    e.fill_groups(layout);
    // The second version, moved the same way (copies do not share one exactly).
    e.alt = e.alt.map(|a| Box::new(perturbed(&a, layout, i)));
    e
}

fn run_search(b: &SearchBench) -> Result<()> {
    use shapeseek::index::ScanIndex;
    use shapeseek::presets::default_config;
    use shapeseek::ranking::calibrate_with;
    use shapeseek::search::{rank_all, top_k, Query};
    use std::sync::Arc;
    let mut cfg = default_config();
    if let Some(d) = &b.dissimilarity {
        cfg.query.dissimilarity = serde_json::from_value(serde_json::Value::String(d.clone()))
            .map_err(|e| Error::InvalidArgument(format!("--dissimilarity {d}: {e}")))?;
    }
    let bases = synthetic_bases(&cfg.signature, false)?;
    println!(
        "config `{}` ({:?}), top {}, {} queries per size, rayon threads {}; reference = the \
         full ranking (every candidate scored, sorted) on the verified queries; memory = \
         resident set growth while the index (corpus + ids, names, tags) was built, and the \
         index's own heap bytes, per shape",
        cfg.name,
        cfg.query.dissimilarity,
        b.top_k,
        b.queries,
        rayon::current_num_threads()
    );
    println!(
        "{:>10} {:>9} {:>9} {:>9} {:>12} {:>10} {:>9} {:>9} {:>11} {:>11}",
        "stored",
        "p50 ms",
        "p99 ms",
        "max ms",
        "scored (mean)",
        "full p50",
        "speed-up",
        "verified",
        "RSS B/shape",
        "heap B/shape"
    );
    for &n in &b.sizes {
        let distinct = b.distinct.max(SYNTHETIC_BASES) / SYNTHETIC_BASES * SYNTHETIC_BASES;
        let d = distinct.min(n);
        // Calibration on (up to) the distinct signatures, then dropped: the index keeps none.
        let sigs: Vec<Signature> = (0..d)
            .into_par_iter()
            .map(|i| synthetic_signature(&bases, i, b.spread))
            .collect();
        let cal = Arc::new(calibrate_with(
            &sigs.iter().collect::<Vec<_>>(),
            &cfg.signature,
            1,
            &cfg.calibration,
        ));
        let layout = Layout::of(&cal);
        let rows: Vec<Encoded> = sigs
            .par_iter()
            .map(|s| Encoded::from_signature(s, &cal, &layout))
            .collect();
        drop(sigs);
        let rss0 = rss_bytes();
        let mut index = ScanIndex::with_capacity(cal.clone(), n, n);
        let tags = |i: usize| {
            vec![
                "synthetic".to_string(),
                format!("base{}", i % SYNTHETIC_BASES),
            ]
        };
        for i in 0..n {
            let id = format!("{i:016x}");
            let name = format!("synthetic-{i:07}");
            if i < d {
                index.push_encoded(&id, &name, &tags(i), &rows[i]);
            } else {
                index.push_encoded(&id, &name, &tags(i), &perturbed(&rows[i % d], &layout, i));
            }
        }
        let rss = (rss_bytes() - rss0) / n as f64;
        let heap = index.heap_bytes() as f64 / n as f64;
        let corpus = index.corpus();
        let q = Query::new(&cfg.query, corpus.layout());
        let queries: Vec<usize> = (0..b.queries.max(1))
            .map(|q| (unit(1_000_000 + q as u64) * n as f64) as usize % n)
            .collect();
        let verify = b
            .verify
            .unwrap_or(if n <= 100_000 { queries.len() } else { 3 });
        let (mut times, mut full, mut scored) = (Vec::new(), Vec::new(), 0usize);
        for (qi, &qpos) in queries.iter().enumerate() {
            let outside = b.query_scale.map(|f| {
                Encoded::from_signature(&scaled(&bases[qpos % bases.len()].0, f), &cal, &layout)
            });
            let (query, skip) = match &outside {
                Some(p) => (p.clone(), usize::MAX),
                None => (corpus.encoded(qpos), qpos),
            };
            let t = Instant::now();
            let (hits, count) = top_k(corpus, &q, query.view(), b.top_k, &|i| i != skip);
            times.push(t.elapsed().as_secs_f64() * 1e3);
            scored += count;
            if qi < verify {
                let t = Instant::now();
                let all = rank_all(corpus, &q, query.view());
                full.push(t.elapsed().as_secs_f64() * 1e3);
                let head: Vec<(usize, f64)> = all
                    .into_iter()
                    .filter(|&(i, _)| i != skip)
                    .take(b.top_k)
                    .collect();
                if head != hits {
                    return Err(Error::InvalidArgument(format!(
                        "pruned top-k differs from the full ranking for query {qpos}"
                    )));
                }
            }
        }
        times.sort_by(f64::total_cmp);
        full.sort_by(f64::total_cmp);
        let pct = |v: &[f64], p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        let full50 = if full.is_empty() {
            f64::NAN
        } else {
            pct(&full, 0.5)
        };
        println!(
            "{n:>10} {:>9.2} {:>9.2} {:>9.2} {:>12.0} {:>10.2} {:>8.1}x {:>9} {:>11.0} {:>11.0}",
            pct(&times, 0.5),
            pct(&times, 0.99),
            times[times.len() - 1],
            scored as f64 / queries.len() as f64,
            full50,
            full50 / pct(&times, 0.5),
            full.len(),
            rss,
            heap
        );
    }
    Ok(())
}

/// What every synthetic shape shares: the base signatures and payloads, the tiny original.
struct Synthetic {
    engine: shapeseek::index::Engine,
    bases: Vec<(Signature, Option<shapeseek::rerank::GwPayload>)>,
    payloads: Vec<Option<Vec<u8>>>,
    obj: Vec<u8>,
    vertices: usize,
    faces: usize,
    area: f64,
    report: shapeseek::mesh::prepare::PrepareReport,
}

impl Synthetic {
    fn new(payloads: bool) -> Result<Synthetic> {
        use shapeseek::mesh::write::write_obj;
        let engine = shapeseek::index::Engine::new();
        let bases = synthetic_bases(&engine.config.signature, payloads)?;
        let payloads = bases
            .iter()
            .map(|(_, p)| p.as_ref().map(|p| p.to_bytes()))
            .collect();
        let tiny = generate::icosphere(0);
        let (_, report) = prepare(&tiny, &PrepareOptions::default())?;
        let mut obj = Vec::new();
        write_obj(&tiny, &mut obj)?;
        Ok(Synthetic {
            engine,
            bases,
            payloads,
            obj,
            vertices: tiny.vertices.len(),
            faces: tiny.faces.len(),
            area: tiny.area(),
            report,
        })
    }

    /// Synthetic shape `i` under the id `id`.
    fn shape(&self, i: usize, id: String) -> shapeseek::storage::NewShape {
        use sha2::{Digest, Sha256};
        use shapeseek::index::store::{now_unix_ms, ShapeRecord};
        let sig = &synthetic_signature(&self.bases, i, 0.05);
        let mut original = format!("# shapeseek synthetic shape {i}\n").into_bytes();
        original.extend_from_slice(&self.obj);
        let sha256: [u8; 32] = Sha256::digest(&original).into();
        shapeseek::storage::NewShape {
            record: ShapeRecord {
                name: format!("synthetic-{i:06}"),
                tags: vec!["synthetic".into(), format!("base{}", i % SYNTHETIC_BASES)],
                id,
                format: "obj".into(),
                content_type: "model/obj".into(),
                bytes: original.len() as u64,
                vertices: self.vertices,
                faces: self.faces,
                area: self.area,
                sha256: hex::encode(sha256),
                created_unix_ms: now_unix_ms(),
                prepare: self.report.clone(),
                spec_key: self.engine.spec_key(),
            },
            sha256,
            signature: self.engine.encode_signature(sig),
            original,
            // With `--payloads`, a base shape's payload, else none (a spectral-GW stage then
            // ranks these after shapes that have one). The payload's base is decoupled from
            // the signature's (`i / 24` vs `i % 24`), so that a shortlist of same-signature
            // shapes holds different payloads: identical metric spaces would make the GW
            // solves unrealistically cheap.
            payload: self.payloads[(i / SYNTHETIC_BASES) % SYNTHETIC_BASES].clone(),
        }
    }
}

fn run_populate(b: &PopulateBench) -> Result<()> {
    use shapeseek::index::store::{BatchItem, Store};
    let t0 = Instant::now();
    let syn = Synthetic::new(b.payloads)?;
    if let Some(url) = &b.store {
        return populate_store(b, url, syn, t0);
    }
    let data = b.data.as_ref().expect("--data or --store");
    let store = Store::open(data)?;
    let mut written = 0usize;
    while written < b.count {
        let chunk = (b.count - written).min(5000);
        let mut items = Vec::with_capacity(chunk);
        for i in written..written + chunk {
            let s = syn.shape(i, store.new_id()?);
            items.push(BatchItem {
                record: s.record,
                sha256: s.sha256,
                signature: s.signature,
                original: s.original,
                payload: s.payload,
            });
        }
        store.insert_batch(&items)?;
        written += items.len();
        eprint!("\rwritten {written}/{}", b.count);
    }
    eprintln!();
    println!(
        "{} synthetic shapes written to {} in {:.1} s ({} shapes now)",
        b.count,
        data.display(),
        t0.elapsed().as_secs_f64(),
        store.len()
    );
    Ok(())
}

/// `bench populate --store postgres://…`: the same shapes through [`shapeseek::storage`]'s
/// `insert`, 8 at a time.
fn populate_store(b: &PopulateBench, url: &str, syn: Synthetic, t0: Instant) -> Result<()> {
    const WRITERS: usize = 8;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let count = b.count;
    let n = rt.block_on(async move {
        let store = shapeseek::storage::open(url).await?;
        let syn = std::sync::Arc::new(syn);
        let done = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let tasks: Vec<_> = (0..WRITERS)
            .map(|w| {
                let (store, syn, done) = (store.clone(), syn.clone(), done.clone());
                tokio::spawn(async move {
                    for i in (w..count).step_by(WRITERS) {
                        let id = store.new_id().await?;
                        let shape = syn.shape(i, id);
                        store.insert(shape).await?;
                        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                        if d % 1000 == 0 {
                            eprint!("\rwritten {d}/{count}");
                        }
                    }
                    Ok::<(), Error>(())
                })
            })
            .collect();
        for t in tasks {
            t.await
                .map_err(|e| Error::Io(std::io::Error::other(e.to_string())))??;
        }
        store.count().await
    })?;
    eprintln!();
    println!(
        "{count} synthetic shapes written to {url} in {:.1} s ({n} shapes now)",
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

fn run_meshes(b: &MeshesBench) -> Result<()> {
    use shapeseek::mesh::write::write_off;
    std::fs::create_dir_all(&b.out)?;
    let (nu, nv) = grid(b.size);
    for i in 0..b.count {
        let mut m = generate::bumpy_torus(nu, nv);
        let s = 1.0 + 0.3 * unit(i as u64);
        for v in &mut m.vertices {
            v[2] *= s;
        }
        let path = b.out.join(format!("torus-{i:03}.off"));
        let mut f = std::io::BufWriter::new(std::fs::File::create(&path)?);
        write_off(&m, &mut f)?;
        f.flush()?;
    }
    println!(
        "{} meshes of {} vertices written to {}",
        b.count,
        nu * nv,
        b.out.display()
    );
    Ok(())
}
