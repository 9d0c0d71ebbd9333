//! The scale-invariant heat kernel of eq. 21 and the distances it defines.
//!
//! Uniform scaling by `α` maps `λ_i ↦ α⁻² λ_i` and `φ_i ↦ α⁻¹ φ_i` (eq. 17), so on the log-time
//! axis `τ = log t` the heat kernel obeys `k'_τ = α⁻² k_{τ+β}`, `β = −2 log α`. The paper
//! (eq. 21, after Bronstein & Kokkinos' scale-invariant HKS) removes the factor with the
//! log-derivative and the shift with the Fourier modulus:
//!
//! ```text
//! k̂_τ(x, y) = F⁻¹( | F( ∂/∂τ log k_τ(x, y) ) | )          (eq. 21)
//! ```
//!
//! # Discretisation
//!
//! * **Grid.** `τ_j = τ_min + j Δ`, `j = 0 … T−1`, `Δ = (τ_max − τ_min)/(T − 1)`. The kernel
//!   uses every eigenpair, zero modes included (`k_τ → 1/area > 0` as `t → ∞`), with
//!   `e^{−max(λ,0) t}` weights.
//! * **Log-derivative**, exact rather than a finite difference:
//!   `s_j = ∂_τ log k = t ∂_t k / k` with `t ∂_t k = −Σ_i t λ_i e^{−λ_i t} φ_i(x) φ_i(y)`.
//!   A truncated eigen-expansion is not positive everywhere (far pairs at small `t`), so `1/k`
//!   is regularised as `k / (k² + ε²)` with `ε = epsilon/area` (spec field, default
//!   [`SI_EPSILON`]): `k`, `t ∂_t k` and
//!   `ε` all scale by `α⁻²`, so `s` stays exactly scale covariant (`s'_j = s(τ_j + β)`), and
//!   where `|k| ≫ ε` it is the log-derivative itself.
//! * **Modulus and inverse transform.** `S_ω = Σ_j s_j e^{−2πi ωj/T}` (a plain DFT, T is small),
//!   and `k̂ = (1/T) Σ_ω |S_ω| cos(2π ω ℓ / T)` at the lag `ℓ` of the spec (lag 0: the mean
//!   modulus). `|S_ω|` is unchanged by a *circular* shift of `s`; a shift by `β` on the finite
//!   grid is circular up to the samples that leave the window, which is why the window must be
//!   wide enough for `s` to be negligible at both ends for every scale of interest (`s → 0`
//!   exponentially in `τ` both for `t λ_1 ≫ 1` and, with a truncated spectrum, for
//!   `t λ_k ≪ 1`).
//! * **Distances.** `d(x, y) = ‖k̂(x, ·) − k̂(y, ·)‖` over the L1 / L∞ quadrature nodes (the
//!   `lp_samples` farthest-point samples with their Voronoi areas), with the measure divided by
//!   the total area so that it does not grow with `α²`; every ordered pair of nodes `(x, y)` has
//!   weight `W_x W_y / area²` (total mass 1: the distribution itself, not only its shape, is
//!   scale invariant). No near field (the kernel rows of every vertex over the whole τ grid
//!   would cost `n m T k`).
//!
//! Scale invariance is then exact up to (a) the eigensolver's tolerance, (b) the window edges
//! and (c) the interpolation of a shift by a non-integer number of grid steps (none when
//! `β/Δ` is an integer); the farthest-point samples and Voronoi cells of a uniformly scaled
//! mesh are the same vertices (edge-graph distances scale uniformly).
//!
//! Cost per shape: `2T` products of `m × k` by `k × m` (T = 128, m = 500, k = 100: ≈ 6·10⁹
//! multiply-adds) plus `m² (T/2 + 1) T` for the transforms and `m³/2` for the distances —
//! seconds per shape, which is why it is not among the configurations every `eval` runs.

use super::distributions::FineHistogram;
use super::kernels::{chunked_pairs, max_abs_difference, squared_distance, weighted_l1_distance};
use super::spec::Norm;
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatRef, Par};
use rayon::prelude::*;

/// Default regularisation of `1/k` in the log-derivative, relative to `1/area` (the kernel's
/// limit as `t → ∞`): `ε = SI_EPSILON / area`.
///
/// Why 1: a small `ε` keeps the exact log-derivative where a truncated kernel crosses zero, and
/// the resulting spikes in `s(τ)` are not resolved by the τ grid, so a scale factor that is not
/// a whole number of grid steps moves the distribution by several percent. Measured on a bumpy
/// sphere (k = 40, 150 nodes, factors 2 and 1/2, 128 samples): relative quantile change 9e-2 /
/// 2.4e-1 at ε = 10⁻³, 1.2e-2 at 10⁻¹, 1.7e-3 / 6.8e-4 at 1, 4e-5 at 10, against 0.19–0.20 (ε = 1)
/// for a different shape (a torus). ε = 1/area is the kernel's own large-time value: where
/// `|k| ≫ 1/area` (nearby points, short times) `s` is the log-derivative, elsewhere it is damped
/// towards `t ∂_t k · area`; ε = 10 would damp everything into the second regime.
pub const SI_EPSILON: f64 = 1.0;

/// Default log-time window and grid of [`super::ChannelSpec::scale_invariant`]: `τ ∈ [−14, 5]`,
/// 128 samples (Δ ≈ 0.15; 64 samples measured 5–8× less invariant for factors 2 and 1/2). For unit-area shapes `tλ_1` reaches ≈ 10³ at `τ = 5` and
/// `tλ_100` ≈ 10⁻³ at `τ = −14`, so the window holds the whole transition of `s` with room for
/// a scale factor of about 1/4 … 4 either way (`|β| ≤ 2.8`).
pub const SI_DEFAULT_WINDOW: (f64, f64, usize) = (-14.0, 5.0, 128);

/// The log-time grid `τ_j` of a window.
pub fn tau_grid(tau_min: f64, tau_max: f64, steps: usize) -> Vec<f64> {
    let d = (tau_max - tau_min) / (steps.max(2) - 1) as f64;
    (0..steps).map(|j| tau_min + j as f64 * d).collect()
}

/// Eq. 21 on one series: `k_j` and `t ∂_t k` at the grid's times, `eps` the regularisation;
/// returns `k̂` at lag `lag`. `cos` / `sin` are the DFT tables of [`dft_tables`].
pub fn si_transform(
    k: &[f64],
    tdk: &[f64],
    eps: f64,
    lag: usize,
    tables: &(Vec<f64>, Vec<f64>),
) -> f64 {
    let t_len = k.len();
    let e2 = eps * eps;
    let s: Vec<f64> = k
        .iter()
        .zip(tdk)
        .map(|(&k, &d)| d * k / (k * k + e2))
        .collect();
    si_from_log_derivative(&s, lag, tables, t_len)
}

/// `(1/T) Σ_ω |S_ω| cos(2π ω lag / T)` for the DFT `S` of the real series `s`.
fn si_from_log_derivative(
    s: &[f64],
    lag: usize,
    (cos, sin): &(Vec<f64>, Vec<f64>),
    t_len: usize,
) -> f64 {
    let half = t_len / 2;
    let mut acc = 0.0;
    for w in 0..=half {
        let (mut re, mut im) = (0.0, 0.0);
        let row = w * t_len;
        for (j, &x) in s.iter().enumerate() {
            re += x * cos[row + j];
            im -= x * sin[row + j];
        }
        let modulus = (re * re + im * im).sqrt();
        // |S_ω| = |S_{T−ω}| for a real series: the bins 1 … ⌈T/2⌉−1 stand for two.
        let mult = if w == 0 || (t_len % 2 == 0 && w == half) {
            1.0
        } else {
            2.0
        };
        let phase = 2.0 * std::f64::consts::PI * (w * lag % t_len) as f64 / t_len as f64;
        acc += mult * modulus * phase.cos();
    }
    acc / t_len as f64
}

/// `cos(2π ω j / T)`, `sin(…)` for `ω = 0 … T/2`, `j = 0 … T−1` (row-major by ω).
pub fn dft_tables(t_len: usize) -> (Vec<f64>, Vec<f64>) {
    let half = t_len / 2;
    let mut c = Vec::with_capacity((half + 1) * t_len);
    let mut s = Vec::with_capacity((half + 1) * t_len);
    for w in 0..=half {
        for j in 0..t_len {
            let a = 2.0 * std::f64::consts::PI * ((w * j) % t_len) as f64 / t_len as f64;
            c.push(a.cos());
            s.push(a.sin());
        }
    }
    (c, s)
}

/// `k̂(x, z)` for the points `x` (rows of `points`, eigenmap rows) against the nodes `z` (rows
/// of `nodes`): an `m_nodes × m_points` matrix (column = point).
#[allow(clippy::too_many_arguments)]
pub(crate) fn si_kernel_rows(
    points: MatRef<'_, f64>,
    nodes: MatRef<'_, f64>,
    eigenvalues: &[f64],
    area: f64,
    taus: &[f64],
    lag: usize,
    epsilon: f64,
) -> Mat<f64> {
    let (mp, mz, k) = (
        points.nrows(),
        nodes.nrows(),
        eigenvalues.len().min(points.ncols()),
    );
    let t_len = taus.len();
    let tables = dft_tables(t_len);
    let eps = epsilon / area;
    let lam: Vec<f64> = eigenvalues[..k].iter().map(|&l| l.max(0.0)).collect();
    let nodes_k = nodes.subcols(0, k);
    const BLOCK: usize = 16;
    let blocks: Vec<usize> = (0..mp).step_by(BLOCK).collect();
    let cols: Vec<Vec<f64>> = blocks
        .par_iter()
        .flat_map_iter(|&p0| {
            let p1 = (p0 + BLOCK).min(mp);
            let b = p1 - p0;
            // series[j] = (k_j, t∂_t k_j) as mz × b matrices.
            let series: Vec<(Mat<f64>, Mat<f64>)> = taus
                .iter()
                .map(|&tau| {
                    let t = tau.exp();
                    let wk = Mat::from_fn(b, k, |r, c| points[(p0 + r, c)] * (-t * lam[c]).exp());
                    let wd = Mat::from_fn(b, k, |r, c| {
                        -t * lam[c] * points[(p0 + r, c)] * (-t * lam[c]).exp()
                    });
                    let mut kv = Mat::<f64>::zeros(mz, b);
                    let mut dv = Mat::<f64>::zeros(mz, b);
                    matmul(
                        kv.as_mut(),
                        Accum::Replace,
                        nodes_k,
                        wk.as_ref().transpose(),
                        1.0,
                        Par::Seq,
                    );
                    matmul(
                        dv.as_mut(),
                        Accum::Replace,
                        nodes_k,
                        wd.as_ref().transpose(),
                        1.0,
                        Par::Seq,
                    );
                    (kv, dv)
                })
                .collect();
            let mut kser = vec![0.0; t_len];
            let mut dser = vec![0.0; t_len];
            (0..b)
                .map(|c| {
                    (0..mz)
                        .map(|z| {
                            for (j, (kv, dv)) in series.iter().enumerate() {
                                kser[j] = kv[(z, c)];
                                dser[j] = dv[(z, c)];
                            }
                            si_transform(&kser, &dser, eps, lag, &tables)
                        })
                        .collect::<Vec<f64>>()
                })
                .collect::<Vec<_>>()
        })
        .collect();
    Mat::from_fn(mz, mp, |z, p| cols[p][z])
}

/// The distribution of `‖k̂(x,·) − k̂(y,·)‖` over ordered pairs of quadrature points (weights
/// `pw`, which are also the node weights), measure and pair weights divided by the total area.
pub(crate) fn si_pairs(kr: &Mat<f64>, pw: &[f64], area: f64, norm: Norm) -> FineHistogram {
    let m = kr.ncols();
    let nw: Vec<f64> = pw.iter().map(|w| w / area).collect();
    // L2: rows scaled by √w, so that the plain squared distance is the weighted one.
    let sqrt_w: Vec<f64> = nw.iter().map(|w| w.sqrt()).collect();
    let scaled: Option<Mat<f64>> =
        (norm == Norm::L2).then(|| Mat::from_fn(kr.nrows(), m, |z, p| kr[(z, p)] * sqrt_w[z]));
    let rows = scaled.as_ref().unwrap_or(kr);
    let dist = |a: &[f64], b: &[f64]| -> f64 {
        match norm {
            Norm::L1 => weighted_l1_distance(a, b, &nw),
            Norm::LInf => max_abs_difference(a, b),
            Norm::L2 => squared_distance(a, b).sqrt(),
        }
    };
    // ‖a − b‖ ≤ ‖a‖ + ‖b‖ ≤ twice the largest row norm.
    let zero = vec![0.0; kr.nrows()];
    let bound = 2.0
        * (0..m)
            .map(|i| dist(rows.col_as_slice(i), &zero))
            .fold(0.0f64, f64::max);
    chunked_pairs(m, bound.max(f64::MIN_POSITIVE), |r0, r1, fine| {
        for i in r0..r1 {
            for j in i + 1..m {
                fine.add(
                    dist(rows.col_as_slice(i), rows.col_as_slice(j)),
                    2.0 * nw[i] * nw[j],
                );
            }
            fine.add_zero(nw[i] * nw[i]);
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;
    use crate::signature::{compute_signature, ChannelSpec, ChannelValues, SignatureSpec};
    use crate::spectrum::{analyze, AnalyzeOptions};

    /// A kernel series of a two-mode "shape" and the same shape scaled by α = e^{−βΔ… }: the
    /// transform agrees when the shift is a whole number of grid steps and `s` vanishes at the
    /// window's ends.
    #[test]
    fn transform_is_invariant_under_a_grid_shift() {
        let (lo, hi, n) = (-12.0, 6.0, 64);
        let taus = tau_grid(lo, hi, n);
        let d = taus[1] - taus[0];
        let tables = dft_tables(n);
        // Modes: (λ, φ(x)φ(y)), area 1: the zero mode contributes 1.
        let modes = [(0.0, 1.0), (6.0, 0.8), (20.0, -0.5), (300.0, 0.3)];
        let series = |alpha: f64| -> (Vec<f64>, Vec<f64>) {
            // Scaled: λ/α², φφ/α² (eq. 17); area α², so ε scales with it.
            let k: Vec<f64> = taus
                .iter()
                .map(|&tau| {
                    let t = tau.exp();
                    modes
                        .iter()
                        .map(|&(l, p)| p / (alpha * alpha) * (-t * l / (alpha * alpha)).exp())
                        .sum()
                })
                .collect();
            let dk: Vec<f64> = taus
                .iter()
                .map(|&tau| {
                    let t = tau.exp();
                    modes
                        .iter()
                        .map(|&(l, p)| {
                            let l = l / (alpha * alpha);
                            -t * l * p / (alpha * alpha) * (-t * l).exp()
                        })
                        .sum()
                })
                .collect();
            (k, dk)
        };
        // α with β = −2 log α = 3Δ: a shift of exactly three samples.
        let alpha = (-1.5 * d).exp();
        let (k0, d0) = series(1.0);
        let (k1, d1) = series(alpha);
        for lag in [0, 1, 3] {
            let a = si_transform(&k0, &d0, SI_EPSILON, lag, &tables);
            let b = si_transform(&k1, &d1, SI_EPSILON / (alpha * alpha), lag, &tables);
            // s at the window's first and last three samples bounds what the shift moves
            // across the window edge; each of those samples changes every |S_ω| by at most
            // its own size, so |Δk̂| ≤ Σ_ω 2|s_edge| / T ≤ 2 · 3 · max|s_edge|.
            let s = |k: &[f64], dk: &[f64], j: usize| {
                let e = SI_EPSILON * SI_EPSILON;
                (dk[j] * k[j] / (k[j] * k[j] + e)).abs()
            };
            let edge = (0..3)
                .chain(n - 3..n)
                .map(|j| s(&k0, &d0, j).max(s(&k1, &d1, j)))
                .fold(0.0f64, f64::max);
            let tol = 6.0 * edge + 1e-12;
            assert!(
                (a - b).abs() <= tol,
                "lag {lag}: {a} vs {b}, tolerance {tol}"
            );
            assert!(a.abs() > 1e-3, "a non-trivial value ({a})");
        }
        // Not a tautology: the plain (unscaled) kernel sum changes by α⁻².
        assert!((k0[30] - k1[30]).abs() > 1e-3);
    }

    /// The channel's spec round-trips through serde (JSON, as stored in configurations and
    /// keys) and its signature through the binary codec; invalid parameters are refused.
    #[test]
    fn spec_and_signature_round_trip() {
        let ch = ChannelSpec::scale_invariant(Norm::L1);
        assert_eq!(ch.name(), "si-heat-l1[tau=-14..5,n=128,lag=0,eps=1]");
        let spec = SignatureSpec {
            lp_samples: 60,
            ..SignatureSpec::with_channels(vec![
                ch.clone(),
                ChannelSpec::truncated(ChannelSpec::scale_invariant(Norm::L2), 5.0),
            ])
        };
        let json = serde_json::to_string(&spec).expect("json");
        let back: SignatureSpec = serde_json::from_str(&json).expect("parse");
        assert_eq!(back, spec);
        assert_eq!(back.key(), spec.key());
        let a =
            analyze(&generate::bumpy_sphere(2, 0.2), &AnalyzeOptions::default()).expect("analysis");
        let sig = compute_signature(&a, &spec).expect("signature");
        assert_eq!(
            sig.channels[1].name,
            "si-heat-l2[tau=-14..5,n=128,lag=0,eps=1][r=5]"
        );
        let bytes = sig.to_bytes();
        let decoded = crate::signature::Signature::from_bytes(&bytes).expect("decode");
        assert_eq!(decoded, sig);
        for bad in [
            (0.0, 0.0, 64, 0),
            (-1.0, 1.0, 4, 0),
            (-1.0, 1.0, 16, 16),
            (f64::NAN, 1.0, 16, 0),
        ] {
            let mut c = ch.clone();
            c.kind = crate::signature::ChannelKind::ScaleInvariant {
                tau_min: bad.0,
                tau_max: bad.1,
                steps: bad.2,
                lag: bad.3,
                epsilon: SI_EPSILON,
                norm: Norm::L2,
            };
            let s = SignatureSpec::with_channels(vec![c]);
            assert!(compute_signature(&a, &s).is_err(), "{bad:?} accepted");
        }
    }

    fn quantiles(sig: &crate::signature::Signature, c: usize) -> Vec<f64> {
        match &sig.channels[c].values {
            ChannelValues::Distribution(s) => {
                let mut q = s.quantiles.clone();
                q.push(s.mass);
                q
            }
            ChannelValues::Vector(v) => v.clone(),
        }
    }

    /// Eq. 21 on a mesh and on the same mesh scaled by α = e^{3Δ/2}… without unit-area
    /// normalisation: the scale-invariant channel's distribution agrees within the tolerance
    /// derived below, the heat channel's does not.
    #[test]
    fn channel_is_scale_invariant_without_normalisation() {
        let base = generate::bumpy_sphere(3, 0.2);
        let mut opts = AnalyzeOptions::default();
        opts.prepare.normalize_area = false;
        opts.eigen.k = 40;
        let (lo, hi, steps) = SI_DEFAULT_WINDOW;
        let d = (hi - lo) / (steps - 1) as f64;
        let spec = SignatureSpec {
            lp_samples: 150,
            ..SignatureSpec::with_channels(vec![
                ChannelSpec::scale_invariant(Norm::L2),
                ChannelSpec::scale_invariant(Norm::L1),
                ChannelSpec::heat(0.04, Norm::L1),
            ])
        };
        let sig = |alpha: f64| {
            let mut m = base.clone();
            m.scale(alpha);
            let a = analyze(&m, &opts).expect("analysis");
            compute_signature(&a, &spec).expect("signature")
        };
        // β = −2 log α = −4Δ (a shift of four grid steps; α ≈ 1.35).
        let alpha = (2.0 * d).exp();
        let (s0, s1) = (sig(1.0), sig(alpha));
        assert!(
            (s1.area / s0.area - alpha * alpha).abs() < 1e-9,
            "not normalised"
        );
        // Tolerance: the discrete eigenproblem scales exactly (cotangent weights are scale
        // free, the mass matrix scales by α²), up to the eigensolver's residual (< 1e-8
        // relative), and the samples are the same vertices. The transform's error is then the
        // edge term of the test above, which for every kernel series here is below 1e-6 of k̂
        // (s decays like e^{-tλ_1} at τ = 5 and like tλ_k at τ = −14); quantiles are read from a
        // 32 768-bin histogram on [0, bound] whose bound moves with k̂, so each quantile may move
        // by up to two fine bins: 2/32768 ≈ 6e-5 of the bound, i.e. ≈ 1.2e-4 of a quantile near
        // the median. 1e-3 relative covers both with margin.
        // Control: another shape (a torus) at the original size is far from the sphere in the
        // same measure, so the tolerance does not hide everything.
        let torus = {
            let a = analyze(&generate::bumpy_torus(40, 16), &opts).expect("analysis");
            compute_signature(&a, &spec).expect("signature")
        };
        let rel = |a: &[f64], b: &[f64]| {
            let scale = a.iter().fold(0.0f64, |m, &x| m.max(x.abs()));
            a.iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs() / scale)
                .fold(0.0f64, f64::max)
        };
        for c in 0..2 {
            let (q0, q1) = (quantiles(&s0, c), quantiles(&s1, c));
            let worst = rel(&q0, &q1);
            let other = rel(&q0, &quantiles(&torus, c));
            println!(
                "{}: median {:.4e}, max {:.4e}; relative change under scaling {worst:.2e}, to a torus {other:.2e}",
                s0.channels[c].name,
                q0[q0.len() / 2],
                q0[q0.len() - 2],
            );
            assert!(
                worst < 1e-3,
                "channel {}: relative change {worst}",
                s0.channels[c].name
            );
            assert!(
                other > 3e-2,
                "channel {}: torus only {other} away",
                s0.channels[c].name
            );
            assert!(
                q0[q0.len() / 2] > 1e-3 * q0[q0.len() - 2],
                "degenerate distribution"
            );
        }
        // A factor that is not a whole number of grid steps (α = 2 and 1/2: β/Δ = ∓9.3): the
        // shift is then only as exact as the sampling of s(τ) resolves it. Not derived: measured
        // 1.7e-3 / 6.8e-4 (L2), 4.8e-4 / 4.5e-4 (L1); the bound 1e-2 is a regression guard, still
        // well below the distance to the torus.
        for alpha in [2.0, 0.5] {
            let s2 = sig(alpha);
            for c in 0..2 {
                let r = rel(&quantiles(&s0, c), &quantiles(&s2, c));
                println!(
                    "α = {alpha}, {}: relative change {r:.2e}",
                    s0.channels[c].name
                );
                assert!(r < 1e-2, "α = {alpha}, channel {c}: {r}");
            }
        }
        // The plain heat channel is not scale invariant without normalisation.
        let (h0, h1) = (quantiles(&s0, 2), quantiles(&s1, 2));
        let scale = h0.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
        let moved = h0
            .iter()
            .zip(&h1)
            .map(|(a, b)| (a - b).abs() / scale)
            .fold(0.0f64, f64::max);
        assert!(moved > 1e-2, "heat channel moved only {moved}");
    }
}
