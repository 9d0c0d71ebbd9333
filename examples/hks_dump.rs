//! Per-vertex heat kernel signatures of every shape of a manifest, prepared and analysed as the
//! default spec prepares its first version (smoothing, capping, handle cutting, unit area), for
//! offline prototypes (`scripts/analysis/hks_chamfer.py`, partial matching, `docs/quality.md`
//! §33; `scripts/analysis/hks_distribution.py`, the signature's distribution, §35):
//!
//! ```text
//! cargo run --release --example hks_dump -- MANIFEST OUT_DIR
//! ```
//!
//! Writes `OUT_DIR/<id>.f32` (little-endian `f32`: the `n × 32` values `h(x, t) = Σ_k
//! exp(−λ_k t) φ_k(x)²` at 32 times log-spaced over [0.005, 1], vertex-major, then the `n`
//! vertex masses) and `OUT_DIR/index.json` (`times`, and per id `n` and the eigenvalues).
use rayon::prelude::*;
use shapeseek::mesh::{read_path, ReadLimits};
use shapeseek::signature::kernels::heat_kernel_signature;
use shapeseek::spectrum::{analyze, AnalyzeOptions};
use std::path::Path;

const TIMES: usize = 32;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

type Res<T> = Result<T, Box<dyn std::error::Error + Send + Sync>>;

fn run() -> Res<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 3 {
        return Err("usage: hks_dump MANIFEST OUT_DIR".into());
    }
    let manifest = Path::new(&args[1]);
    let out = Path::new(&args[2]);
    std::fs::create_dir_all(out)?;
    let base = manifest.parent().unwrap_or(Path::new("."));
    let text = std::fs::read_to_string(manifest)?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().ok_or("empty manifest")?.split(',').collect();
    let col = |n: &str| {
        header
            .iter()
            .position(|h| *h == n)
            .ok_or(format!("no column {n}"))
    };
    let (ci, cp) = (col("id")?, col("path")?);
    let rows: Vec<(String, String)> = lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[ci].to_string(), f[cp].to_string())
        })
        .collect();
    let spec = shapeseek::presets::default_config().signature;
    let opts = spec.analysis_options(&AnalyzeOptions::default());
    let times: Vec<f64> = (0..TIMES)
        .map(|i| 0.005 * 200f64.powf(i as f64 / (TIMES - 1) as f64))
        .collect();
    let shapes = rows
        .par_iter()
        .map(|(id, p)| -> Res<(String, serde_json::Value)> {
            let mesh = read_path(base.join(p), &ReadLimits::default())?;
            let sp = analyze(&mesh, &opts)?.spectrum;
            let n = sp.eigenvectors.nrows();
            let per_time: Vec<Vec<f64>> = times
                .iter()
                .map(|&t| heat_kernel_signature(sp.eigenvectors.as_ref(), &sp.eigenvalues, t))
                .collect();
            let mut bytes = Vec::with_capacity(4 * n * (TIMES + 1));
            for i in 0..n {
                for h in &per_time {
                    bytes.extend_from_slice(&(h[i] as f32).to_le_bytes());
                }
            }
            for &m in &sp.mass {
                bytes.extend_from_slice(&(m as f32).to_le_bytes());
            }
            std::fs::write(out.join(format!("{id}.f32")), bytes)?;
            eprintln!("{id}: {n} vertices");
            Ok((
                id.clone(),
                serde_json::json!({"n": n, "eigenvalues": sp.eigenvalues}),
            ))
        })
        .collect::<Res<Vec<_>>>()?;
    let shapes: serde_json::Map<String, serde_json::Value> = shapes.into_iter().collect();
    let index = serde_json::json!({"times": times, "shapes": shapes});
    std::fs::write(out.join("index.json"), serde_json::to_vec(&index)?)?;
    Ok(())
}
