//! Entropic Gromov–Wasserstein discrepancy with the square loss (Peyré, Cuturi, Solomon,
//! "Gromov–Wasserstein averaging of kernel and distance matrices", ICML 2016).
//!
//! For metric-measure spaces `(C₁, p)` (m points) and `(C₂, q)` (n points) and a coupling
//! `T ∈ Π(p, q)`, the square-loss GW energy is
//! `E(T) = Σ_{ijkl} (C₁[i,k] − C₂[j,l])² T[i,j] T[k,l] = ⟨L(T), T⟩` with the tensor product
//! computed by the decomposition trick (Prop. 1 of the paper):
//! `L(T) = c₁ 1ᵀ + 1 c₂ᵀ − 2 C₁ T C₂ᵀ`, `c₁ = (C₁ ⊙ C₁) p`, `c₂ = (C₂ ⊙ C₂) q`:
//! two m×m×n GEMMs (faer, sequential) per evaluation instead of O(m²n²).
//!
//! Iteration (Peyré et al. Alg. 1): `T₀ = p qᵀ` (the product measure: deterministic and
//! permutation-equivariant), then `T_{k+1} = Sinkhorn_ε(p, q, L(T_k))` for a few outer steps.
//!
//! **Anchored starts** ([`GwOptions::anchored_starts`]). The iteration is equivariant: from the
//! product measure, a space with a symmetry (a torus, a sphere, a left–right symmetric body)
//! keeps a coupling that mixes every symmetric image, so a shape's own copy can score above
//! another shape (a finely meshed torus with itself 1.274, with a bumpy torus 0.800; the
//! default payload; the test
//! `rerank::tests::a_symmetric_shapes_own_copy_scores_lowest_with_anchored_starts`). Two more
//! starts break the symmetry: each space's anchors are its most eccentric point and the point
//! farthest from it, and the start pairs points by their distances to the two anchors (both
//! orders of the second space's pair: either is the image of the first under some symmetry).
//! The lowest final energy of the three solves is kept (that torus with itself 0.054). With a
//! kernel payload the second anchor is the point least similar to the first.
//!
//! The Sinkhorn solver is the stabilised scaling algorithm (Schmitzer 2016): dual potentials
//! `f, g` are kept in the log domain, the kernel `exp((f_i + g_j − M_ij)/ε)` is rebuilt whenever
//! the scalings leave `[10⁻⁵⁰, 10⁵⁰]`, so small ε neither underflows nor overflows. Potentials
//! are warm-started across outer steps. The scaling updates' products `K v` and `Kᵀ u` are
//! faer's matrix–vector products, whose SIMD width is chosen at run time (AVX2 or AVX-512 where
//! the CPU has them): on dev's stored payloads they are most of a solve's time.
//!
//! ε is relative: `ε = eps_rel · (pᵀ c₁ + qᵀ c₂)` (the mean of `L` under the product measure, the
//! natural scale of the costs), so the same options fit every scale of distances.
//!
//! Several scales: `Σ_s (C₁ˢ − C₂ˢ)²` is the square loss of the product metric, so `L` and `E`
//! are sums over scales (same coupling for every scale).
//!
//! Returned value: the GW energy `E(T)` of the final plan (without the entropy term), i.e. the
//! square of the usual `2·GW₂` up to the factor; lower = more similar.

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatMut, MatRef, Par};
use serde::{Deserialize, Serialize};

/// Solver options.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default)]
pub struct GwOptions {
    /// Entropic regularisation relative to the mean cost under the product measure.
    pub eps_rel: f64,
    /// Outer (linearisation) iterations.
    pub outer_iterations: usize,
    /// Stop the outer loop when `Σ|T_{k+1} − T_k|` falls below this.
    pub outer_tolerance: f64,
    /// Maximum Sinkhorn scaling iterations per outer iteration.
    pub sinkhorn_iterations: usize,
    /// Stop Sinkhorn when the row-marginal L1 error falls below this.
    pub sinkhorn_tolerance: f64,
    /// Also start from two anchored couplings (see the module docs) and keep the lowest
    /// energy of the three solves: 2–5× the time. Off by default: on the dev benchmark it
    /// did not change retrieval (`docs/quality.md` §1c).
    pub anchored_starts: bool,
}

impl Default for GwOptions {
    fn default() -> Self {
        Self {
            eps_rel: 0.003,
            outer_iterations: 5,
            outer_tolerance: 1e-4,
            sinkhorn_iterations: 300,
            sinkhorn_tolerance: 1e-6,
            anchored_starts: false,
        }
    }
}

/// Result of [`entropic_gw`].
#[derive(Clone, Debug)]
pub struct GwResult {
    /// GW energy `⟨L(T), T⟩` of the final coupling.
    pub value: f64,
    /// The coupling (m × n).
    pub plan: Mat<f64>,
    /// Outer iterations run.
    pub outer_iterations: usize,
    /// Sinkhorn iterations run in total.
    pub sinkhorn_iterations: usize,
}

/// `L(T) = c₁ 1ᵀ + 1 c₂ᵀ − 2 Σ_s C₁ˢ T C₂ˢ` (symmetric `C₂ˢ`), written into `out`.
fn tensor(
    c1: &[MatRef<'_, f64>],
    c2: &[MatRef<'_, f64>],
    const1: &[f64],
    const2: &[f64],
    t: MatRef<'_, f64>,
    tmp: &mut Mat<f64>,
    out: &mut Mat<f64>,
) {
    let (m, n) = (t.nrows(), t.ncols());
    for j in 0..n {
        let col = out.col_as_slice_mut(j);
        for i in 0..m {
            col[i] = const1[i] + const2[j];
        }
    }
    for (a, b) in c1.iter().zip(c2) {
        // tmp = C₁ T  (m × n), out -= 2 tmp C₂.
        matmul(tmp.as_mut(), Accum::Replace, *a, t, 1.0, Par::Seq);
        matmul(out.as_mut(), Accum::Add, tmp.as_ref(), *b, -2.0, Par::Seq);
    }
}

fn frob_dot(a: MatRef<'_, f64>, b: MatRef<'_, f64>) -> f64 {
    let mut s = 0.0;
    for j in 0..a.ncols() {
        let (x, y) = (a.col(j), b.col(j));
        for i in 0..a.nrows() {
            s += x[i] * y[i];
        }
    }
    s
}

/// Stabilised Sinkhorn: returns the plan for cost `cost`, marginals `p`, `q`, regularisation
/// `eps`; `f`, `g` are the (warm-started, updated) dual potentials. Returns iterations used.
#[allow(clippy::too_many_arguments)]
fn sinkhorn(
    p: &[f64],
    q: &[f64],
    cost: MatRef<'_, f64>,
    eps: f64,
    f: &mut [f64],
    g: &mut [f64],
    iters: usize,
    tol: f64,
    plan: &mut Mat<f64>,
) -> usize {
    let (m, n) = (p.len(), q.len());
    // c-transform of the warm-started g: f_i = min_j (M_ij − g_j), so every exponent is ≤ 0
    // and every row has an entry e⁰ = 1 (no overflow, no all-zero row).
    for i in 0..m {
        f[i] = f64::INFINITY;
    }
    for j in 0..n {
        let cj = cost.col(j);
        for i in 0..m {
            f[i] = f[i].min(cj[i] - g[j]);
        }
    }
    let mut kernel = Mat::<f64>::zeros(m, n);
    let build = |kernel: &mut Mat<f64>, f: &[f64], g: &[f64]| {
        for j in 0..n {
            let col = kernel.col_as_slice_mut(j);
            let cj = cost.col(j);
            for i in 0..m {
                col[i] = ((f[i] + g[j] - cj[i]) / eps).exp();
            }
        }
    };
    build(&mut kernel, f, g);
    let mut u = vec![1.0; m];
    let mut v = vec![1.0; n];
    let mut kv = vec![0.0; m];
    // kv = K v and ktu = Kᵀ u: faer's matrix–vector products (SIMD, chosen at run time).
    let kernel_times = |kernel: &Mat<f64>, v: &[f64], kv: &mut [f64]| {
        matmul(
            MatMut::from_column_major_slice_mut(kv, m, 1),
            Accum::Replace,
            kernel.as_ref(),
            MatRef::from_column_major_slice(v, n, 1),
            1.0,
            Par::Seq,
        );
    };
    let mut ktu = vec![0.0; n];
    let mut used = 0;
    // True when `kv` already holds K v for the current K and v (after a marginal check).
    let mut kv_current = false;
    const BOUND: f64 = 1e50;
    for it in 0..iters {
        used = it + 1;
        // u = p / (K v)
        if !kv_current {
            kernel_times(&kernel, &v, &mut kv);
        }
        kv_current = false;
        for i in 0..m {
            u[i] = p[i] / kv[i].max(1e-300);
        }
        // v = q / (Kᵀ u)
        matmul(
            MatMut::from_column_major_slice_mut(&mut ktu, n, 1),
            Accum::Replace,
            kernel.transpose(),
            MatRef::from_column_major_slice(&u, m, 1),
            1.0,
            Par::Seq,
        );
        for j in 0..n {
            v[j] = q[j] / ktu[j].max(1e-300);
        }
        let blown = u
            .iter()
            .chain(v.iter())
            .any(|&x| !(1.0 / BOUND..=BOUND).contains(&x));
        if blown {
            // Absorb the scalings into the potentials and rebuild the kernel.
            for i in 0..m {
                f[i] += eps * u[i].max(1e-300).ln();
            }
            for j in 0..n {
                g[j] += eps * v[j].max(1e-300).ln();
            }
            u.iter_mut().for_each(|x| *x = 1.0);
            v.iter_mut().for_each(|x| *x = 1.0);
            build(&mut kernel, f, g);
            continue;
        }
        // Row-marginal error (columns are exact after the v update), every 10 iterations.
        if it % 10 == 9 {
            kernel_times(&kernel, &v, &mut kv);
            let err: f64 = (0..m).map(|i| (u[i] * kv[i] - p[i]).abs()).sum();
            if err < tol {
                break;
            }
            // The next iteration starts with this very product.
            kv_current = true;
        }
    }
    // Keep the potentials for the warm start of the next outer iteration.
    for i in 0..m {
        f[i] += eps * u[i].max(1e-300).ln();
    }
    for j in 0..n {
        g[j] += eps * v[j].max(1e-300).ln();
    }
    // Plan = diag(u) K diag(v) with the absorbed potentials (u = v = 1 after absorption, else
    // apply them).
    for j in 0..n {
        let src = kernel.col_as_slice(j);
        let vj = v[j];
        let dst = plan.col_as_slice_mut(j);
        for i in 0..m {
            dst[i] = u[i] * src[i] * vj;
        }
    }
    used
}

/// Entropic GW between `(C₁ˢ)_s` with weights `p` and `(C₂ˢ)_s` with weights `q` (see the
/// module docs). Every `C` must be symmetric; `p` and `q` must be non-negative with equal sums
/// (normally 1).
pub fn entropic_gw(
    c1: &[MatRef<'_, f64>],
    p: &[f64],
    c2: &[MatRef<'_, f64>],
    q: &[f64],
    opts: &GwOptions,
) -> GwResult {
    let (m, n) = (p.len(), q.len());
    assert_eq!(c1.len(), c2.len(), "same number of scales");
    assert!(c1.iter().all(|c| c.nrows() == m && c.ncols() == m));
    assert!(c2.iter().all(|c| c.nrows() == n && c.ncols() == n));
    let mut const1 = vec![0.0; m];
    let mut const2 = vec![0.0; n];
    for c in c1 {
        for k in 0..m {
            let col = c.col(k);
            for i in 0..m {
                const1[i] += col[i] * col[i] * p[k];
            }
        }
    }
    for c in c2 {
        for l in 0..n {
            let col = c.col(l);
            for j in 0..n {
                const2[j] += col[j] * col[j] * q[l];
            }
        }
    }
    let scale: f64 = p.iter().zip(&const1).map(|(a, b)| a * b).sum::<f64>()
        + q.iter().zip(&const2).map(|(a, b)| a * b).sum::<f64>();
    let eps = (opts.eps_rel * scale).max(1e-300);
    let product = Mat::from_fn(m, n, |i, j| p[i] * q[j]);
    let mut best = solve_from(c1, p, c2, q, &const1, &const2, eps, product, opts);
    if opts.anchored_starts && m >= 2 && n >= 2 {
        let (i0, i1) = anchors(c1, &const1);
        let (j0, j1) = anchors(c2, &const2);
        let orders = if j0 == j1 {
            vec![(j0, j1)]
        } else {
            vec![(j0, j1), (j1, j0)]
        };
        for (a, b) in orders {
            let (start, its) = anchored_coupling(c1, p, c2, q, (i0, i1), (a, b), opts);
            let r = solve_from(c1, p, c2, q, &const1, &const2, eps, start, opts);
            // Every Sinkhorn iteration run, the starts' own included.
            let sinkhorn_iterations = best.sinkhorn_iterations + its + r.sinkhorn_iterations;
            if r.value < best.value {
                best = r;
            }
            best.sinkhorn_iterations = sinkhorn_iterations;
        }
    }
    best
}

/// Two anchor points of a space: the most eccentric point (largest `Σ_k C[i,k]² p_k`, the
/// lowest index on ties), then the point whose entry differs most from the anchor's own,
/// `Σ_s (C[i,a] − C[a,a])²`: the farthest point for distances (`C[a,a] = 0`), the least
/// similar for a kernel (`C[a,a]` its largest value).
fn anchors(c: &[MatRef<'_, f64>], ecc: &[f64]) -> (usize, usize) {
    let argmax =
        |f: &dyn Fn(usize) -> f64| (0..ecc.len()).fold(0, |b, i| if f(i) > f(b) { i } else { b });
    let a = argmax(&|i| ecc[i]);
    let b = argmax(&|i| {
        c.iter()
            .map(|m| (m[(i, a)] - m[(a, a)]).powi(2))
            .sum::<f64>()
    });
    (a, b)
}

/// The coupling that pairs points by their distances to two anchors: Sinkhorn of the cost
/// `Σ_s (C₁ˢ[i,a₀] − C₂ˢ[j,b₀])² + (C₁ˢ[i,a₁] − C₂ˢ[j,b₁])²`, ε relative to its mean under the
/// product measure; with the Sinkhorn iterations it took.
fn anchored_coupling(
    c1: &[MatRef<'_, f64>],
    p: &[f64],
    c2: &[MatRef<'_, f64>],
    q: &[f64],
    (a0, a1): (usize, usize),
    (b0, b1): (usize, usize),
    opts: &GwOptions,
) -> (Mat<f64>, usize) {
    let (m, n) = (p.len(), q.len());
    let cost = Mat::from_fn(m, n, |i, j| {
        c1.iter()
            .zip(c2)
            .map(|(x, y)| {
                let d0 = x[(i, a0)] - y[(j, b0)];
                let d1 = x[(i, a1)] - y[(j, b1)];
                d0 * d0 + d1 * d1
            })
            .sum::<f64>()
    });
    let mut mean = 0.0;
    for j in 0..n {
        for i in 0..m {
            mean += cost[(i, j)] * p[i] * q[j];
        }
    }
    let eps = (opts.eps_rel * mean).max(1e-300);
    let mut plan = Mat::<f64>::zeros(m, n);
    let (mut f, mut g) = (vec![0.0; m], vec![0.0; n]);
    let its = sinkhorn(
        p,
        q,
        cost.as_ref(),
        eps,
        &mut f,
        &mut g,
        opts.sinkhorn_iterations,
        opts.sinkhorn_tolerance,
        &mut plan,
    );
    (plan, its)
}

/// The outer loop of [`entropic_gw`] from the coupling `plan`.
#[allow(clippy::too_many_arguments)]
fn solve_from(
    c1: &[MatRef<'_, f64>],
    p: &[f64],
    c2: &[MatRef<'_, f64>],
    q: &[f64],
    const1: &[f64],
    const2: &[f64],
    eps: f64,
    mut plan: Mat<f64>,
    opts: &GwOptions,
) -> GwResult {
    let (m, n) = (p.len(), q.len());
    let mut next = Mat::<f64>::zeros(m, n);
    let mut tmp = Mat::<f64>::zeros(m, n);
    let mut cost = Mat::<f64>::zeros(m, n);
    let mut f = vec![0.0; m];
    let mut g = vec![0.0; n];
    let mut outer = 0;
    let mut inner = 0;
    for _ in 0..opts.outer_iterations {
        outer += 1;
        tensor(c1, c2, const1, const2, plan.as_ref(), &mut tmp, &mut cost);
        inner += sinkhorn(
            p,
            q,
            cost.as_ref(),
            eps,
            &mut f,
            &mut g,
            opts.sinkhorn_iterations,
            opts.sinkhorn_tolerance,
            &mut next,
        );
        let mut change = 0.0;
        for j in 0..n {
            let (a, b) = (plan.col_as_slice(j), next.col_as_slice(j));
            for i in 0..m {
                change += (a[i] - b[i]).abs();
            }
        }
        std::mem::swap(&mut plan, &mut next);
        if change < opts.outer_tolerance {
            break;
        }
    }
    tensor(c1, c2, const1, const2, plan.as_ref(), &mut tmp, &mut cost);
    let value = frob_dot(cost.as_ref(), plan.as_ref()).max(0.0);
    GwResult {
        value,
        plan,
        outer_iterations: outer,
        sinkhorn_iterations: inner,
    }
}
