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

mod corpus;

use corpus::{run_populate, run_search, unit};

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
