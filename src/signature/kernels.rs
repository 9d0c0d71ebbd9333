//! Kernel transfer weights `K(λ_i)` and the diffusion distances between quadrature points (L2 by
//! GEMM, L1 / L∞ on kernel rows), streamed into fine histograms.

use super::distributions::FineHistogram;
use super::sampling::NearField;
use super::spec::{Aggregation, Kernel};
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatRef, Par};
use rayon::prelude::*;

/// The heat kernel signature `h(x, t) = Σ_k exp(−λ_k t) φ_k(x)²` of every vertex (the diagonal
/// of the paper's heat kernel, §2.2) over every eigenpair given, the zero mode included;
/// eigenvalues below 0 by rounding count as 0. Used by
/// [`ChannelKind::HeatQuantiles`](crate::signature::ChannelKind::HeatQuantiles) and by
/// `examples/hks_dump`.
pub fn heat_kernel_signature(phi: MatRef<'_, f64>, eigenvalues: &[f64], t: f64) -> Vec<f64> {
    let decay: Vec<f64> = eigenvalues
        .iter()
        .map(|l| (-l.max(0.0) * t).exp())
        .collect();
    (0..phi.nrows())
        .map(|x| {
            decay
                .iter()
                .enumerate()
                .map(|(k, e)| e * phi[(x, k)].powi(2))
                .sum()
        })
        .collect()
}

/// `K(λ_i)` of `kernel` for every eigenvalue, 0 on zero modes.
pub fn transfer_weights(kernel: &Kernel, eigenvalues: &[f64], zero_tol: f64) -> Vec<f64> {
    eigenvalues
        .iter()
        .map(|&l| {
            if l <= zero_tol {
                return 0.0;
            }
            match kernel {
                Kernel::Heat { t } => (-t * l).exp(),
                Kernel::CommuteTime => 1.0 / l.sqrt(),
                Kernel::Step { lambda_c } => {
                    if l < *lambda_c {
                        1.0
                    } else {
                        0.0
                    }
                }
                Kernel::HeatAggregate { ts, aggregation } => match aggregation {
                    Aggregation::Sum2 => {
                        ts.iter().map(|t| (-2.0 * t * l).exp()).sum::<f64>().sqrt()
                    }
                    a => a.apply(ts.iter().map(|t| (-t * l).exp())),
                },
            }
        })
        .collect()
}

pub(crate) fn heat_weights(ts: &[f64], eigenvalues: &[f64], zero_tol: f64) -> Vec<Vec<f64>> {
    ts.iter()
        .map(|&t| transfer_weights(&Kernel::Heat { t }, eigenvalues, zero_tol))
        .collect()
}

/// How the per-scale distances of one pair become histogram entries.
#[derive(Clone, Copy, Debug)]
pub(crate) enum PairMode {
    /// One scale.
    Single,
    /// One entry `A_t d_t` (distance-stage aggregation).
    Aggregate(Aggregation),
    /// One entry per scale (distribution-stage sum).
    Mixture,
}

/// Columns `i` with `w_i² ≥ 1e-16 · max w²` (the rest change d² by less than 1e-16 relative),
/// and the scaled embedding `rows[:, i] · w_i` restricted to them.
pub(crate) fn weighted_embedding(rows: MatRef<'_, f64>, w: &[f64]) -> Mat<f64> {
    let keep = kept_columns(w, rows.ncols());
    Mat::from_fn(rows.nrows(), keep.len(), |r, c| {
        rows[(r, keep[c])] * w[keep[c]]
    })
}

/// Indices `i < ncols` with `w_i ≠ 0` and `|w_i| ≥ 10⁻⁸ max |w|`.
pub(crate) fn kept_columns(w: &[f64], ncols: usize) -> Vec<usize> {
    let wmax = w.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
    (0..w.len().min(ncols))
        .filter(|&i| w[i] != 0.0 && w[i].abs() >= 1e-8 * wmax)
        .collect()
}

/// Row ranges of an m × m upper triangle (diagonal included) with about equal pair counts.
pub(crate) fn row_chunks(m: usize) -> Vec<(usize, usize)> {
    let chunks = (m / 48).clamp(1, 4096);
    let total = m * (m + 1) / 2;
    let mut out = Vec::with_capacity(chunks);
    let (mut start, mut acc) = (0usize, 0usize);
    for i in 0..m {
        acc += m - i;
        if acc * chunks >= total * (out.len() + 1) {
            out.push((start, i + 1));
            start = i + 1;
        }
    }
    if start < m {
        out.push((start, m));
    }
    out
}

/// Runs `f(r0, r1, fine)` over the row chunks of an m-point pair set, in parallel, merging the
/// per-chunk histograms in chunk order (deterministic whatever the thread count).
pub(crate) fn chunked_pairs<F>(m: usize, bound: f64, f: F) -> FineHistogram
where
    F: Fn(usize, usize, &mut FineHistogram) + Sync,
{
    let chunks = row_chunks(m);
    let mut total = FineHistogram::new(bound);
    for group in chunks.chunks(16) {
        let parts: Vec<FineHistogram> = group
            .par_iter()
            .map(|&(r0, r1)| {
                let mut h = FineHistogram::new(bound);
                f(r0, r1, &mut h);
                h
            })
            .collect();
        for p in &parts {
            total.merge(p);
        }
    }
    total
}

pub(crate) fn combine(mode: PairMode, d: &[f64], w: f64, fine: &mut FineHistogram) {
    match mode {
        PairMode::Single => fine.add(d[0], w),
        PairMode::Aggregate(a) => fine.add(a.apply(d.iter().copied()), w),
        PairMode::Mixture => {
            for &x in d {
                fine.add(x, w)
            }
        }
    }
}

pub(crate) fn mode_bound(mode: PairMode, per_scale: &[f64]) -> f64 {
    match mode {
        PairMode::Single => per_scale[0],
        PairMode::Aggregate(a) => a.apply(per_scale.iter().copied()),
        PairMode::Mixture => per_scale.iter().fold(0.0, |a: f64, &b| a.max(b)),
    }
}

pub(crate) fn diag_weight(mode: PairMode, scales: usize) -> f64 {
    match mode {
        PairMode::Mixture => scales as f64,
        _ => 1.0,
    }
}

/// Row-major `n × kept` embedding `φ_i(v) w_i` of every vertex (the columns of
/// [`weighted_embedding`]).
pub(crate) fn vertex_embedding(phi: &Mat<f64>, w: &[f64]) -> (Vec<f64>, usize) {
    let keep = kept_columns(w, phi.ncols());
    let (n, k) = (phi.nrows(), keep.len());
    let mut out = vec![0.0; n * k];
    // Blocked transpose: a block of 64 output rows stays in cache while the columns are read.
    for v0 in (0..n).step_by(64) {
        let v1 = (v0 + 64).min(n);
        for (c, &i) in keep.iter().enumerate() {
            let wi = w[i];
            for (v, x) in phi.col_as_slice(i)[v0..v1].iter().enumerate() {
                out[(v0 + v) * k + c] = x * wi;
            }
        }
    }
    (out, k)
}

/// Eq. 9 distances between all quadrature points, `d² = |ψ_i|² + |ψ_j|² − 2 ψ_i·ψ_j` (GEMM per
/// row chunk), every ordered pair weighted `w_i w_j`; with a [`NearField`], same-cell and
/// adjacent-cell pairs are replaced by sample-to-vertex pairs.
pub(crate) fn l2_pairs(
    rows: MatRef<'_, f64>,
    pw: &[f64],
    weights: &[Vec<f64>],
    mode: PairMode,
    near: Option<&NearField<'_>>,
) -> FineHistogram {
    let m = rows.nrows();
    let psi: Vec<Mat<f64>> = weights
        .iter()
        .map(|w| weighted_embedding(rows, w))
        .collect();
    let sq: Vec<Vec<f64>> = psi
        .iter()
        .map(|p| {
            (0..m)
                .map(|i| (0..p.ncols()).map(|c| p[(i, c)] * p[(i, c)]).sum())
                .collect()
        })
        .collect();
    let full: Vec<(Vec<f64>, usize)> = match near {
        Some(nf) => weights
            .iter()
            .map(|w| vertex_embedding(nf.phi, w))
            .collect(),
        None => Vec::new(),
    };
    let top2 = |it: &mut dyn Iterator<Item = f64>| {
        let (mut a, mut b) = (0.0f64, 0.0f64);
        for v in it {
            if v > a {
                b = a;
                a = v;
            } else if v > b {
                b = v;
            }
        }
        a.sqrt() + b.sqrt()
    };
    // d(x, y) ≤ |ψ_x| + |ψ_y| ≤ the two largest norms (over every vertex with a near field).
    let per_scale: Vec<f64> = if near.is_some() {
        full.iter()
            .map(|(e, k)| top2(&mut e.chunks(*k.max(&1)).map(|r| r.iter().map(|x| x * x).sum())))
            .collect()
    } else {
        sq.iter().map(|s| top2(&mut s.iter().copied())).collect()
    };
    let bound = mode_bound(mode, &per_scale);
    let ns = psi.len();
    let dw = diag_weight(mode, ns);
    let empty: Vec<u32> = Vec::new();
    let far = chunked_pairs(m, bound, |r0, r1, fine| {
        let r = r1 - r0;
        let gs: Vec<Mat<f64>> = psi
            .iter()
            .map(|p| {
                let mut g = Mat::<f64>::zeros(m - r0, r);
                if p.ncols() > 0 {
                    matmul(
                        g.as_mut(),
                        Accum::Replace,
                        p.as_ref().subrows(r0, m - r0),
                        p.as_ref().subrows(r0, r).transpose(),
                        1.0,
                        Par::Seq,
                    );
                }
                g
            })
            .collect();
        let mut d = vec![0.0; ns];
        for ii in 0..r {
            let i = r0 + ii;
            let skip: &[u32] = near.map_or(&empty, |nf| &nf.adj[i]);
            // Far field: j > i not adjacent to i, in segments between adjacent indices.
            let mut lo = i + 1;
            for stop in skip.iter().map(|&a| a as usize).chain(std::iter::once(m)) {
                if let (PairMode::Single, [g]) = (mode, gs.as_slice()) {
                    let sq = &sq[0];
                    let (si, wi) = (sq[i], 2.0 * pw[i]);
                    let col = &g.col_as_slice(ii)[lo - r0..stop - r0];
                    for ((gij, sj), wj) in col.iter().zip(&sq[lo..stop]).zip(&pw[lo..stop]) {
                        fine.add((si + sj - 2.0 * gij).max(0.0).sqrt(), wi * wj);
                    }
                } else {
                    let cols: Vec<&[f64]> = gs.iter().map(|g| g.col_as_slice(ii)).collect();
                    for j in lo..stop {
                        for ((ds, sqs), col) in d.iter_mut().zip(&sq).zip(&cols) {
                            *ds = (sqs[i] + sqs[j] - 2.0 * col[j - r0]).max(0.0).sqrt();
                        }
                        combine(mode, &d, 2.0 * pw[i] * pw[j], fine);
                    }
                }
                lo = stop + 1;
            }
            if near.is_none() {
                fine.add_zero(pw[i] * pw[i] * dw);
            }
        }
    });
    let Some(nf) = near else {
        return far;
    };
    // Near field, cell by cell (each cell's member rows are read once): pairs (s_a, y) for
    // y in cell b and a = b or a adjacent to b, weight W_a a_y.
    let mut total = far;
    let ncell = nf.members.len();
    let groups: Vec<usize> = (0..ncell).step_by(64).collect();
    for block in groups.chunks(16) {
        let parts: Vec<FineHistogram> = block
            .par_iter()
            .map(|&b0| {
                let mut fine = FineHistogram::new(bound);
                let mut d = vec![0.0; ns];
                for b in b0..(b0 + 64).min(ncell) {
                    for &y in &nf.members[b] {
                        let y = y as usize;
                        for a in std::iter::once(b).chain(nf.nbrs[b].iter().map(|&a| a as usize)) {
                            let s = nf.samples[a] as usize;
                            for (ds, (e, k)) in d.iter_mut().zip(&full) {
                                *ds = squared_distance(
                                    &e[s * k..(s + 1) * k],
                                    &e[y * k..(y + 1) * k],
                                )
                                .sqrt();
                            }
                            combine(mode, &d, pw[a] * nf.mass[y], &mut fine);
                        }
                    }
                }
                fine
            })
            .collect();
        for p in &parts {
            total.merge(p);
        }
    }
    total
}

/// L1 / L∞ distances `‖k(x,·) − k(y,·)‖` with the kernel rows evaluated on the quadrature nodes
/// (weights `pw`, the same points as the pair set).
pub(crate) fn lp_pairs(
    rows: MatRef<'_, f64>,
    nodes: MatRef<'_, f64>,
    pw: &[f64],
    weights: &[Vec<f64>],
    inf: bool,
    mode: PairMode,
    near: Option<&NearField<'_>>,
) -> FineHistogram {
    let m = rows.nrows();
    let mz = nodes.nrows();
    // Kernel rows K[x][z] = Σ_i w_i φ_i(x) φ_i(z) of the points `at` (rows), as columns of an
    // mz × rows matrix.
    let kernel_rows = |at: MatRef<'_, f64>, w: &[f64]| -> Mat<f64> {
        let psi = weighted_embedding(at, w);
        let keep = kept_columns(w, at.ncols());
        let z = Mat::from_fn(mz, keep.len(), |r, c| nodes[(r, keep[c])]);
        let mut k = Mat::<f64>::zeros(mz, at.nrows());
        if !keep.is_empty() {
            matmul(
                k.as_mut(),
                Accum::Replace,
                z.as_ref(),
                psi.as_ref().transpose(),
                1.0,
                Par::Seq,
            );
        }
        k
    };
    let kr: Vec<Mat<f64>> = weights.iter().map(|w| kernel_rows(rows, w)).collect();
    // With a near field: kernel rows of every vertex.
    let kall: Vec<Mat<f64>> = match near {
        Some(nf) => weights
            .iter()
            .map(|w| kernel_rows(nf.phi.as_ref(), w))
            .collect(),
        None => Vec::new(),
    };
    let dist = |a: &[f64], b: &[f64]| -> f64 {
        if inf {
            max_abs_difference(a, b)
        } else {
            weighted_l1_distance(a, b, pw)
        }
    };
    let per_scale: Vec<f64> = kr
        .iter()
        .chain(kall.iter())
        .map(|k| {
            2.0 * (0..k.ncols())
                .map(|i| {
                    let a = k.col_as_slice(i);
                    if inf {
                        a.iter().fold(0.0f64, |acc, x| acc.max(x.abs()))
                    } else {
                        a.iter().zip(pw).map(|(x, wz)| wz * x.abs()).sum()
                    }
                })
                .fold(0.0f64, f64::max)
        })
        .collect();
    let ns = kr.len();
    let per_scale: Vec<f64> = (0..ns)
        .map(|s| {
            per_scale[s].max(if kall.is_empty() {
                0.0
            } else {
                per_scale[ns + s]
            })
        })
        .collect();
    let bound = mode_bound(mode, &per_scale);
    let dw = diag_weight(mode, ns);
    let empty: Vec<u32> = Vec::new();
    chunked_pairs(m, bound, |r0, r1, fine| {
        let mut d = vec![0.0; ns];
        for i in r0..r1 {
            let skip: &[u32] = near.map_or(&empty, |nf| &nf.adj[i]);
            let mut lo = i + 1;
            for stop in skip.iter().map(|&a| a as usize).chain(std::iter::once(m)) {
                for j in lo..stop {
                    for (ds, k) in d.iter_mut().zip(&kr) {
                        *ds = dist(k.col_as_slice(i), k.col_as_slice(j));
                    }
                    combine(mode, &d, 2.0 * pw[i] * pw[j], fine);
                }
                lo = stop + 1;
            }
            match near {
                None => fine.add_zero(pw[i] * pw[i] * dw),
                Some(nf) => {
                    let mut one_sided = |a: usize, b: usize, fine: &mut FineHistogram| {
                        for &y in &nf.members[b] {
                            for ((ds, k), ka) in d.iter_mut().zip(&kr).zip(&kall) {
                                *ds = dist(k.col_as_slice(a), ka.col_as_slice(y as usize));
                            }
                            combine(mode, &d, pw[a] * nf.mass[y as usize], fine);
                        }
                    };
                    one_sided(i, i, fine);
                    for &j in skip {
                        one_sided(i, j as usize, fine);
                        one_sided(j as usize, i, fine);
                    }
                }
            }
        }
    })
}

/// `Σ (a_i − b_i)²` with four independent accumulators (fixed order: deterministic).
#[inline]
pub(crate) fn squared_distance(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            let t = x[l] - y[l];
            acc[l] += t * t;
        }
    }
    let mut tail = 0.0;
    for (x, y) in ra.iter().zip(rb) {
        tail += (x - y) * (x - y);
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// `Σ w_i |a_i − b_i|` with four independent accumulators (fixed order: deterministic).
#[inline]
pub(crate) fn weighted_l1_distance(a: &[f64], b: &[f64], w: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb, cw) = (a.chunks_exact(4), b.chunks_exact(4), w.chunks_exact(4));
    let (ra, rb, rw) = (ca.remainder(), cb.remainder(), cw.remainder());
    for ((x, y), z) in ca.zip(cb).zip(cw) {
        for l in 0..4 {
            acc[l] += z[l] * (x[l] - y[l]).abs();
        }
    }
    let mut tail = 0.0;
    for ((x, y), z) in ra.iter().zip(rb).zip(rw) {
        tail += z * (x - y).abs();
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// `max |a_i − b_i|`.
#[inline]
pub(crate) fn max_abs_difference(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            acc[l] = acc[l].max((x[l] - y[l]).abs());
        }
    }
    let mut m = acc[0].max(acc[1]).max(acc[2].max(acc[3]));
    for (x, y) in ra.iter().zip(rb) {
        m = m.max((x - y).abs());
    }
    m
}
