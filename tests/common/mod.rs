//! Helpers shared by the integration tests of the spectral core (`tests/spectrum.rs`,
//! `tests/eigen.rs`, `tests/reference_eigenvalues.rs`). Include with `mod common;`.
//!
//! Every test binary compiles this module on its own and uses a part of it, hence the
//! `dead_code` allowance.
#![allow(dead_code)]

use faer::sparse::{SparseColMat, Triplet};
use faer::Mat;
use shapeseek::eigen::{EigenOptions, Method};
use shapeseek::spectrum::AnalyzeOptions;
use std::f64::consts::PI;
use std::path::PathBuf;

/// Analysis options with `k` eigenpairs and the given solver, everything else default.
pub fn analyze_opts(k: usize, method: Method) -> AnalyzeOptions {
    AnalyzeOptions {
        eigen: EigenOptions {
            k,
            method,
            ..Default::default()
        },
        ..Default::default()
    }
}

/// Unit-area sphere (radius `1/√(4π)`): the `i`-th eigenvalue `4π l(l+1)` with `l = ⌊√i⌋`
/// (eigenvalue `l(l+1)/r²` with multiplicity `2l+1`).
pub fn unit_area_sphere_eigenvalue(i: usize) -> f64 {
    let l = (i as f64).sqrt().floor();
    4.0 * PI * l * (l + 1.0)
}

/// The benchmark folder `shared/bench/<name>`: `$SHAPESEEK_BENCH_DIR/<name>` when that variable
/// is set, else the first `shared/bench/<name>` found beside the crate or one of its ancestors
/// (a clone in `/work/main` and a worktree in `/work/wt/x` both find `/work/shared`). `None`
/// when absent: the caller prints `SKIPPED:` and returns.
pub fn bench_dir(name: &str) -> Option<PathBuf> {
    if let Some(d) = std::env::var_os("SHAPESEEK_BENCH_DIR") {
        let p = PathBuf::from(d).join(name);
        return p.is_dir().then_some(p);
    }
    let manifest = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    manifest
        .ancestors()
        .map(|a| a.join("shared").join("bench").join(name))
        .find(|p| p.is_dir())
}

/// A symmetric sparse matrix (full storage, as [`shapeseek::laplace`] builds it) from the
/// upper-triangle entries `(i, j, v)` with `i ≤ j`; duplicates are summed.
pub fn symmetric(n: usize, upper: &[(usize, usize, f64)]) -> SparseColMat<usize, f64> {
    let mut t = Vec::with_capacity(2 * upper.len());
    for &(i, j, v) in upper {
        assert!(
            i <= j && j < n,
            "entry ({i}, {j}) outside the upper triangle of {n}"
        );
        t.push(Triplet::new(i, j, v));
        if i != j {
            t.push(Triplet::new(j, i, v));
        }
    }
    SparseColMat::try_new_from_triplets(n, n, &t).expect("valid triplets")
}

/// The graph Laplacian of a weighted graph on `n` vertices: `L_ii = Σ_j w_ij`, `L_ij = −w_ij`.
pub fn graph_laplacian(n: usize, edges: &[(usize, usize, f64)]) -> SparseColMat<usize, f64> {
    let mut diag = vec![0.0; n];
    let mut upper = Vec::with_capacity(edges.len() + n);
    for &(i, j, w) in edges {
        let (a, b) = (i.min(j), i.max(j));
        upper.push((a, b, -w));
        diag[a] += w;
        diag[b] += w;
    }
    upper.extend(diag.into_iter().enumerate().map(|(i, d)| (i, i, d)));
    symmetric(n, &upper)
}

/// Unit-weight path `0 − 1 − … − (n−1)`: eigenvalues `4 sin²(π j / 2n)`, `j = 0..n` (simple).
pub fn path_edges(n: usize) -> Vec<(usize, usize, f64)> {
    (0..n - 1).map(|i| (i, i + 1, 1.0)).collect()
}

/// The eigenvalues of [`path_edges`], ascending.
pub fn path_eigenvalues(n: usize) -> Vec<f64> {
    (0..n)
        .map(|j| 4.0 * (PI * j as f64 / (2.0 * n as f64)).sin().powi(2))
        .collect()
}

/// Unit-weight cycle of `n` vertices: eigenvalues `4 sin²(π j / n)`, `j = 0..n`; every
/// non-zero value except `j = n/2` (even `n`) is double.
pub fn cycle_edges(n: usize) -> Vec<(usize, usize, f64)> {
    (0..n).map(|i| (i, (i + 1) % n, 1.0)).collect()
}

/// The eigenvalues of [`cycle_edges`], ascending.
pub fn cycle_eigenvalues(n: usize) -> Vec<f64> {
    let mut v: Vec<f64> = (0..n)
        .map(|j| 4.0 * (PI * j as f64 / n as f64).sin().powi(2))
        .collect();
    v.sort_by(f64::total_cmp);
    v
}

/// `D^{1/2} L D^{1/2}` for a diagonal `D = diag(d)`: the generalized problem
/// `(D^{1/2} L D^{1/2}) φ = λ D φ` has exactly the eigenvalues of `L φ = λ φ`
/// (`φ = D^{-1/2} ψ`), so a non-uniform mass keeps an analytic spectrum.
pub fn congruent(l: &SparseColMat<usize, f64>, d: &[f64]) -> SparseColMat<usize, f64> {
    let n = d.len();
    let lr = l.as_ref();
    let mut t = Vec::with_capacity(lr.compute_nnz());
    for j in 0..n {
        for (i, v) in lr.row_idx_of_col(j).zip(lr.val_of_col(j)) {
            t.push(Triplet::new(i, j, d[i].sqrt() * v * d[j].sqrt()));
        }
    }
    SparseColMat::try_new_from_triplets(n, n, &t).expect("valid triplets")
}

/// A deterministic mass vector in `[0.5, 1.5)` (fractional parts of multiples of the golden
/// ratio).
pub fn uneven_mass(n: usize) -> Vec<f64> {
    let g = 0.618_033_988_749_894_9;
    (0..n)
        .map(|i| 0.5 + ((i as f64 + 1.0) * g).fract())
        .collect()
}

/// `max |Φᵀ A Φ − I|` for `A = diag(mass)`.
pub fn a_orthonormality_error(phi: &Mat<f64>, mass: &[f64]) -> f64 {
    let k = phi.ncols();
    let mut worst: f64 = 0.0;
    for a in 0..k {
        for b in a..k {
            let dot: f64 = (0..phi.nrows())
                .map(|v| phi[(v, a)] * mass[v] * phi[(v, b)])
                .sum();
            let target = if a == b { 1.0 } else { 0.0 };
            worst = worst.max((dot - target).abs());
        }
    }
    worst
}

/// Largest relative difference `|a_i − b_i| / max(|b_i|, floor)`.
pub fn max_relative_error(a: &[f64], b: &[f64], floor: f64) -> f64 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() / y.abs().max(floor))
        .fold(0.0, f64::max)
}
