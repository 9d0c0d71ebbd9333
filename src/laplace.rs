//! Discrete Laplace–Beltrami operator on a triangle mesh (paper §4, eq. 22): the cotangent
//! stiffness matrix `L` and the lumped (barycentric) mass matrix `A`, so that `Δu ≈ A⁻¹ L u`
//! and the spectrum solves `L φ = λ A φ`.
//!
//! Conventions (identical to libigl's `-cotmatrix` / `massmatrix(BARYCENTRIC)`):
//! * `w_ij = (cot α_ij + cot β_ij) / 2`, with α, β the angles opposite edge ij (a boundary edge
//!   has a single `cot/2` term); `L_ij = −w_ij`, `L_ii = Σ_j w_ij`. `L` is symmetric positive
//!   semi-definite for every triangle mesh (it is the P1 finite-element stiffness matrix), with
//!   the constants in its kernel, even when some weights are negative (obtuse triangles).
//! * `a_i = (1/3) Σ area(t)` over the triangles `t` incident to vertex `i`.
//!
//! Near-degenerate triangles: all three cotangents of a triangle share the denominator
//! `|e1 × e2| = 2·area`. It is floored at `1e-12 · ℓ²_max` (ℓ_max the longest edge of that
//! triangle), so a sliver gives large but finite weights, never NaN or ∞; since the floor scales
//! the triangle's three weights by one common factor, its contribution stays PSD. Triangles of
//! exactly zero area (all cross products zero) contribute nothing to `L` nor `A`; the
//! preparation step removes them before this point anyway.

use crate::mesh::{cross, dot, norm, sub, Mesh};
use faer::sparse::{SparseColMat, Triplet};

/// Relative floor of the doubled triangle area in the cotangent denominators.
const DENOMINATOR_FLOOR: f64 = 1e-12;

/// The discretised operator of a mesh: `L` (stiffness) and the diagonal of `A` (mass).
#[derive(Debug, Clone)]
pub struct Laplacian {
    /// Cotangent stiffness matrix, n × n, both triangles stored, duplicates summed.
    pub stiffness: SparseColMat<usize, f64>,
    /// Lumped mass `a_i` per vertex (sums to the total area).
    pub mass: Vec<f64>,
    /// Number of interior and boundary edges with a negative cotangent weight (non-Delaunay).
    pub negative_weights: usize,
}

/// Builds the cotangent Laplacian of `mesh` (see the module docs for conventions).
///
/// Indices must be in range (the preparation step guarantees it); vertices referenced by no
/// triangle get a zero row and zero mass, which makes the generalized problem singular, so callers
/// pass prepared meshes.
pub fn cotangent_laplacian(mesh: &Mesh) -> crate::Result<Laplacian> {
    let n = mesh.vertices.len();
    let mut mass = vec![0.0f64; n];
    // Per-edge weights, summed over the (one or two) triangles of each edge, keyed (min, max).
    let mut edges: Vec<(u32, u32, f64)> = Vec::with_capacity(mesh.faces.len() * 3);
    for (fi, f) in mesh.faces.iter().enumerate() {
        if f.iter().any(|&i| i as usize >= n) {
            return Err(crate::Error::InvalidArgument(format!(
                "face {fi} refers to a vertex outside 0..{n}"
            )));
        }
        let p = f.map(|i| mesh.vertices[i as usize]);
        let e = [sub(p[2], p[1]), sub(p[0], p[2]), sub(p[1], p[0])]; // e[k] is opposite vertex k
        let double_area = norm(cross(e[1], e[2]));
        if double_area == 0.0 || !double_area.is_finite() {
            continue;
        }
        let lmax2 = e.iter().map(|v| dot(*v, *v)).fold(0.0, f64::max);
        let denom = double_area.max(DENOMINATOR_FLOOR * lmax2);
        for k in 0..3 {
            // Angle at vertex k is between -e[(k+1)%3] and e[(k+2)%3]; it is opposite edge
            // (k+1, k+2).
            let a = e[(k + 1) % 3];
            let b = e[(k + 2) % 3];
            let cot = -dot(a, b) / denom;
            let (i, j) = (f[(k + 1) % 3], f[(k + 2) % 3]);
            edges.push((i.min(j), i.max(j), 0.5 * cot));
        }
        let third = double_area / 6.0;
        for &i in f {
            mass[i as usize] += third;
        }
    }
    edges.sort_unstable_by_key(|&(i, j, _)| (i, j));
    let mut triplets: Vec<Triplet<usize, usize, f64>> = Vec::with_capacity(edges.len() + n);
    let mut diag = vec![0.0f64; n];
    let mut negative_weights = 0;
    let mut idx = 0;
    while idx < edges.len() {
        let (i, j, mut w) = edges[idx];
        idx += 1;
        while idx < edges.len() && edges[idx].0 == i && edges[idx].1 == j {
            w += edges[idx].2;
            idx += 1;
        }
        if w < 0.0 {
            negative_weights += 1;
        }
        if i == j {
            continue;
        }
        let (i, j) = (i as usize, j as usize);
        triplets.push(Triplet::new(i, j, -w));
        triplets.push(Triplet::new(j, i, -w));
        diag[i] += w;
        diag[j] += w;
    }
    for (i, d) in diag.into_iter().enumerate() {
        triplets.push(Triplet::new(i, i, d));
    }
    let stiffness = SparseColMat::try_new_from_triplets(n, n, &triplets)
        .map_err(|e| crate::Error::Numerical(format!("assembling the stiffness matrix: {e:?}")))?;
    Ok(Laplacian {
        stiffness,
        mass,
        negative_weights,
    })
}

/// Writes a sparse matrix in Matrix Market coordinate format (general, real), 1-based, full
/// precision, so external tools (SciPy, MATLAB) can load exactly the same operator.
pub fn write_matrix_market(
    mat: &SparseColMat<usize, f64>,
    out: &mut impl std::io::Write,
) -> std::io::Result<()> {
    let m = mat.as_ref();
    let nnz = m.compute_nnz();
    writeln!(out, "%%MatrixMarket matrix coordinate real general")?;
    writeln!(out, "{} {} {}", m.nrows(), m.ncols(), nnz)?;
    for j in 0..m.ncols() {
        for (i, v) in m.row_idx_of_col(j).zip(m.val_of_col(j)) {
            writeln!(out, "{} {} {:e}", i + 1, j + 1, v)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;

    fn dense(l: &Laplacian) -> Vec<Vec<f64>> {
        let n = l.mass.len();
        let mut d = vec![vec![0.0; n]; n];
        let m = l.stiffness.as_ref();
        for j in 0..n {
            for (i, v) in m.row_idx_of_col(j).zip(m.val_of_col(j)) {
                d[i][j] += *v;
            }
        }
        d
    }

    #[test]
    fn equilateral_triangle_by_hand() {
        // Each angle is 60°, cot = 1/√3, single triangle: w_ij = cot/2.
        let h = 3f64.sqrt() / 2.0;
        let mesh = Mesh::new(
            vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, h, 0.0]],
            vec![[0, 1, 2]],
        );
        let l = cotangent_laplacian(&mesh).unwrap();
        let d = dense(&l);
        let w = 0.5 / 3f64.sqrt();
        for i in 0..3 {
            for j in 0..3 {
                let expect = if i == j { 2.0 * w } else { -w };
                assert!((d[i][j] - expect).abs() < 1e-14, "{i}{j}: {}", d[i][j]);
            }
        }
        let area = h / 2.0;
        for a in &l.mass {
            assert!((a - area / 3.0).abs() < 1e-15);
        }
    }

    #[test]
    fn rows_sum_to_zero_symmetric_and_area() {
        let mesh = generate::bumpy_sphere(2, 0.3);
        let l = cotangent_laplacian(&mesh).unwrap();
        let d = dense(&l);
        let n = d.len();
        for i in 0..n {
            let s: f64 = d[i].iter().sum();
            assert!(s.abs() < 1e-12, "row {i} sums to {s}");
            for j in 0..n {
                assert!((d[i][j] - d[j][i]).abs() < 1e-14);
            }
        }
        let total: f64 = l.mass.iter().sum();
        assert!((total - mesh.area()).abs() < 1e-12);
    }

    #[test]
    fn linear_functions_are_harmonic_inside_a_flat_domain() {
        // The cotangent Laplacian reproduces linear functions exactly at interior vertices.
        let mesh = generate::rectangle(2.0, 1.0, 8, 5);
        let l = cotangent_laplacian(&mesh).unwrap();
        let d = dense(&l);
        let u: Vec<f64> = mesh
            .vertices
            .iter()
            .map(|p| 3.0 * p[0] - 2.0 * p[1] + 1.0)
            .collect();
        for (i, p) in mesh.vertices.iter().enumerate() {
            let interior = p[0] > 1e-9 && p[0] < 2.0 - 1e-9 && p[1] > 1e-9 && p[1] < 1.0 - 1e-9;
            if interior {
                let lu: f64 = (0..u.len()).map(|j| d[i][j] * u[j]).sum();
                assert!(lu.abs() < 1e-12, "vertex {i}: {lu}");
            }
        }
    }

    #[test]
    fn slivers_and_obtuse_triangles_stay_finite() {
        let mesh = Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.5, 1e-17, 0.0],
                [0.5, -0.01, 0.0],
                [0.5, 2.0, 0.0],
            ],
            vec![[0, 1, 2], [0, 3, 1], [0, 2, 4], [2, 1, 4]],
        );
        let l = cotangent_laplacian(&mesh).unwrap();
        assert!(l.stiffness.as_ref().val().iter().all(|v| v.is_finite()));
        assert!(l.mass.iter().all(|v| v.is_finite() && *v >= 0.0));
        assert!(l.negative_weights > 0);
    }
}
