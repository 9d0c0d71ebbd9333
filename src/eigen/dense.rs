//! The dense kernels of [`super`]'s eigensolver: the tall-skinny products of its block
//! Gram–Schmidt and Cholesky-QR, and the small dense factorisations (symmetric eigensolver,
//! Householder QR) at a fixed parallel degree ([`super::faer_par`]), so that their rounding does
//! not depend on the thread count.

use super::faer_par;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::evd::{
    self_adjoint_evd, self_adjoint_evd_scratch, ComputeEigenvectors, EvdError,
};
use faer::linalg::matmul::matmul;
use faer::reborrow::{Reborrow, ReborrowMut};
use faer::{Accum, Conj, Mat, MatMut, MatRef, Par};

/// Rows per task of the tall-skinny kernels below: a chunk of V (rows × basis) stays in cache.
pub(super) const ROW_CHUNK: usize = 1024;

/// `Vᵀ W` for tall-skinny V (n × c) and W (n × b), as a tree-reduction over row chunks on the
/// rayon pool. faer's general GEMM was measured at ~2.4 GFlop/s on this shape (inner dimension
/// n = 50k, outputs 200 × 16), 10× below the chunked form; the fixed split points make the
/// summation order, hence the result, deterministic.
pub(super) fn gemm_tn(v: MatRef<'_, f64>, w: MatRef<'_, f64>) -> Mat<f64> {
    let n = v.nrows();
    if n <= ROW_CHUNK {
        let mut h = Mat::<f64>::zeros(v.ncols(), w.ncols());
        matmul(h.as_mut(), Accum::Replace, v.transpose(), w, 1.0, Par::Seq);
        return h;
    }
    let half = (n / 2).div_ceil(ROW_CHUNK) * ROW_CHUNK;
    let (a, b) = rayon::join(
        || gemm_tn(v.subrows(0, half), w.subrows(0, half)),
        || gemm_tn(v.subrows(half, n - half), w.subrows(half, n - half)),
    );
    a + b
}

/// `W ← W + α V H` (`Accum::Add`) or `W ← α V H` (`Accum::Replace`) for tall-skinny V and W,
/// in parallel over row chunks (each row is computed by one task: deterministic).
pub(super) fn gemm_nn(
    w: MatMut<'_, f64>,
    accum: Accum,
    v: MatRef<'_, f64>,
    h: MatRef<'_, f64>,
    alpha: f64,
) {
    let n = w.nrows();
    if n <= ROW_CHUNK {
        matmul(w, accum, v, h, alpha, Par::Seq);
        return;
    }
    let half = (n / 2).div_ceil(ROW_CHUNK) * ROW_CHUNK;
    let (top, bottom) = w.split_at_row_mut(half);
    rayon::join(
        || gemm_nn(top, accum, v.subrows(0, half), h, alpha),
        || gemm_nn(bottom, accum, v.subrows(half, n - half), h, alpha),
    );
}

/// One sweep over row chunks: `w ← w − V h`, then returns `Vᵀ w` (the tree reduction of
/// [`gemm_tn`]), so the second Gram–Schmidt pass reads V once less.
pub(super) fn subtract_then_tn(
    v: MatRef<'_, f64>,
    w: MatMut<'_, f64>,
    h: MatRef<'_, f64>,
) -> Mat<f64> {
    let n = w.nrows();
    if n <= ROW_CHUNK {
        let mut w = w;
        matmul(w.rb_mut(), Accum::Add, v, h, -1.0, Par::Seq);
        let mut out = Mat::<f64>::zeros(v.ncols(), w.ncols());
        matmul(
            out.as_mut(),
            Accum::Replace,
            v.transpose(),
            w.rb(),
            1.0,
            Par::Seq,
        );
        return out;
    }
    let half = (n / 2).div_ceil(ROW_CHUNK) * ROW_CHUNK;
    let (top, bottom) = w.split_at_row_mut(half);
    let (a, b) = rayon::join(
        || subtract_then_tn(v.subrows(0, half), top, h),
        || subtract_then_tn(v.subrows(half, n - half), bottom, h),
    );
    a + b
}

/// Classical Gram–Schmidt twice against the orthonormal `v` in three sweeps over V (memory
/// traffic, not flops, bounds these tall-skinny products): returns the total coefficients.
pub(super) fn cgs2(v: MatRef<'_, f64>, mut w: MatMut<'_, f64>) -> Mat<f64> {
    if v.ncols() == 0 {
        return Mat::<f64>::zeros(0, w.ncols());
    }
    let h1 = gemm_tn(v, w.rb());
    let h2 = subtract_then_tn(v, w.rb_mut(), h1.as_ref());
    gemm_nn(w, Accum::Add, v, h2.as_ref(), -1.0);
    h1 + h2
}

/// `w ← w − V (Vᵀ w)`, returning `Vᵀ w`.
pub(super) fn project_out(v: MatRef<'_, f64>, w: MatMut<'_, f64>) -> Mat<f64> {
    if v.ncols() == 0 {
        return Mat::<f64>::zeros(0, w.ncols());
    }
    let h = gemm_tn(v, w.rb());
    gemm_nn(w, Accum::Add, v, h.as_ref(), -1.0);
    h
}

/// Cholesky factor `R` (upper, `G = RᵀR`) of a small SPD matrix, or `None` when a pivot is not
/// safely positive. Written out because the blocks are tiny (b ≤ 32) and the pivot test is ours.
pub(super) fn small_cholesky_upper(g: &Mat<f64>) -> Option<Mat<f64>> {
    let b = g.nrows();
    let mut r = Mat::<f64>::zeros(b, b);
    let max_diag = (0..b).map(|i| g[(i, i)]).fold(0.0, f64::max);
    for j in 0..b {
        let mut d = g[(j, j)];
        for k in 0..j {
            d -= r[(k, j)] * r[(k, j)];
        }
        if d.is_nan() || d <= 1e-20 * max_diag || max_diag <= 0.0 {
            return None;
        }
        let rjj = d.sqrt();
        r[(j, j)] = rjj;
        for i in j + 1..b {
            let mut x = g[(j, i)];
            for k in 0..j {
                x -= r[(k, j)] * r[(k, i)];
            }
            r[(j, i)] = x / rjj;
        }
    }
    Some(r)
}

/// Inverse of a small upper-triangular matrix.
pub(super) fn upper_inverse(r: &Mat<f64>) -> Mat<f64> {
    let b = r.nrows();
    let mut inv = Mat::<f64>::zeros(b, b);
    for j in 0..b {
        inv[(j, j)] = 1.0 / r[(j, j)];
        for i in (0..j).rev() {
            let mut x = 0.0;
            for k in i + 1..=j {
                x += r[(i, k)] * inv[(k, j)];
            }
            inv[(i, j)] = -x / r[(i, i)];
        }
    }
    inv
}

/// Eigenvalues (ascending) and eigenvectors of the symmetric `a` (its lower triangle), by
/// faer's dense solver at [`faer_par`] (`Mat::self_adjoint_eigen` would take the global
/// parallelism, the pool's size).
pub(super) fn symmetric_evd(
    a: MatRef<'_, f64>,
) -> std::result::Result<(Vec<f64>, Mat<f64>), EvdError> {
    let n = a.nrows();
    let mut u = Mat::<f64>::zeros(n, n);
    let mut s = faer::diag::Diag::<f64>::zeros(n);
    let par = faer_par();
    let mut mem = MemBuffer::new(self_adjoint_evd_scratch::<f64>(
        n,
        ComputeEigenvectors::Yes,
        par,
        Default::default(),
    ));
    self_adjoint_evd(
        a,
        s.as_mut(),
        Some(u.as_mut()),
        par,
        MemStack::new(&mut mem),
        Default::default(),
    )?;
    Ok(((0..n).map(|i| s[i]).collect(), u))
}

/// The thin Householder QR of the tall `w` (`m ≥ n`): `(Q, R)`, `Q` m × n with orthonormal
/// columns, `R` n × n upper triangular, by faer's kernels at [`faer_par`] (`Mat::qr` would take
/// the global parallelism).
pub(super) fn householder_qr(w: MatRef<'_, f64>) -> (Mat<f64>, Mat<f64>) {
    use faer::linalg::householder::{
        apply_block_householder_sequence_on_the_left_in_place_scratch as apply_scratch,
        apply_block_householder_sequence_on_the_left_in_place_with_conj as apply,
    };
    use faer::linalg::qr::no_pivoting::factor::{
        qr_in_place, qr_in_place_scratch, recommended_block_size,
    };
    let (m, n) = w.shape();
    debug_assert!(m >= n);
    let par = faer_par();
    let bs = recommended_block_size::<f64>(m, n);
    let mut qr = w.to_owned();
    let mut coeff = Mat::<f64>::zeros(bs, n);
    let mut mem = MemBuffer::new(qr_in_place_scratch::<f64>(
        m,
        n,
        bs,
        par,
        Default::default(),
    ));
    qr_in_place(
        qr.as_mut(),
        coeff.as_mut(),
        par,
        MemStack::new(&mut mem),
        Default::default(),
    );
    let r = Mat::<f64>::from_fn(n, n, |i, j| if i <= j { qr[(i, j)] } else { 0.0 });
    // The Householder basis: unit lower trapezoidal.
    let basis = Mat::<f64>::from_fn(m, n, |i, j| match i.cmp(&j) {
        std::cmp::Ordering::Less => 0.0,
        std::cmp::Ordering::Equal => 1.0,
        std::cmp::Ordering::Greater => qr[(i, j)],
    });
    let mut q = Mat::<f64>::identity(m, n);
    let mut mem = MemBuffer::new(apply_scratch::<f64>(m, bs, n));
    apply(
        basis.as_ref(),
        coeff.as_ref(),
        Conj::No,
        q.as_mut(),
        par,
        MemStack::new(&mut mem),
    );
    (q, r)
}

/// One Cholesky-QR pass: `w = Q R`, `Q` returned, or `None` if `w` is numerically rank
/// deficient.
pub(super) fn cholqr(w: MatRef<'_, f64>) -> Option<(Mat<f64>, Mat<f64>)> {
    let g = gemm_tn(w, w);
    let r = small_cholesky_upper(&g)?;
    let rinv = upper_inverse(&r);
    let mut q = Mat::<f64>::zeros(w.nrows(), w.ncols());
    gemm_nn(q.as_mut(), Accum::Replace, w, rinv.as_ref(), 1.0);
    Some((q, r))
}
