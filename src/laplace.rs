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
    assemble(n, edges, mass)
}

/// Sums per-triangle half-weights `(i, j, cot/2)` into the symmetric PSD stiffness matrix.
fn assemble(n: usize, mut edges: Vec<(u32, u32, f64)>, mass: Vec<f64>) -> crate::Result<Laplacian> {
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

/// Which discretisation of the Laplace–Beltrami operator to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LaplacianKind {
    /// Cotangent weights on the mesh as given (the paper's §4 choice; libigl's convention).
    #[default]
    Cotangent,
    /// Cotangent weights on the *intrinsic Delaunay triangulation* of the same surface
    /// (Bobenko & Springborn 2007; Fisher et al. 2007): edges are flipped intrinsically, keeping
    /// the metric, until every interior edge satisfies α + β ≤ π. All weights are then ≥ 0, the
    /// operator no longer depends on how the surface happens to be triangulated (to first
    /// order), and slivers stop dominating the spectrum. Vertices and total area are unchanged.
    IntrinsicDelaunay,
}

/// Builds the Laplacian of the requested kind.
pub fn laplacian(mesh: &Mesh, kind: LaplacianKind) -> crate::Result<Laplacian> {
    match kind {
        LaplacianKind::Cotangent => cotangent_laplacian(mesh),
        LaplacianKind::IntrinsicDelaunay => intrinsic_delaunay_laplacian(mesh).map(|(l, _)| l),
    }
}

const NONE: u32 = u32::MAX;

/// Area of a triangle from its edge lengths (Kahan's stable form of Heron's formula); 0 for an
/// invalid triple.
fn area_from_lengths(a: f64, b: f64, c: f64) -> f64 {
    let mut l = [a, b, c];
    l.sort_by(|x, y| y.total_cmp(x));
    let [a, b, c] = l;
    let p = (a + (b + c)) * (c - (a - b)) * (c + (a - b)) * (a + (b - c));
    if p > 0.0 {
        0.25 * p.sqrt()
    } else {
        0.0
    }
}

/// Intrinsic triangulation state: per halfedge `3f + i` (from corner i to corner i+1 of face f)
/// its twin and its length.
struct Intrinsic {
    faces: Vec<[u32; 3]>,
    twin: Vec<u32>,
    length: Vec<f64>,
}

impl Intrinsic {
    fn from_mesh(mesh: &Mesh) -> crate::Result<Self> {
        let n = mesh.vertices.len();
        let nf = mesh.faces.len();
        let mut length = vec![0.0; 3 * nf];
        let mut keys: Vec<(u32, u32, u32)> = Vec::with_capacity(3 * nf);
        for (f, face) in mesh.faces.iter().enumerate() {
            if face.iter().any(|&i| i as usize >= n) {
                return Err(crate::Error::InvalidArgument(format!(
                    "face {f} refers to a vertex outside 0..{n}"
                )));
            }
            for i in 0..3 {
                let (a, b) = (face[i], face[(i + 1) % 3]);
                let he = (3 * f + i) as u32;
                length[he as usize] =
                    norm(sub(mesh.vertices[a as usize], mesh.vertices[b as usize]));
                keys.push((a.min(b), a.max(b), he));
            }
        }
        // Twins: exactly two opposite halfedges on an edge. Non-manifold edges, boundary edges
        // and inconsistently oriented pairs get no twin, so they are never flipped.
        keys.sort_unstable();
        let mut twin = vec![NONE; 3 * nf];
        let mut i = 0;
        while i < keys.len() {
            let mut j = i + 1;
            while j < keys.len() && keys[j].0 == keys[i].0 && keys[j].1 == keys[i].1 {
                j += 1;
            }
            if j - i == 2 {
                let (h1, h2) = (keys[i].2 as usize, keys[i + 1].2 as usize);
                let from = |h: usize| mesh.faces[h / 3][h % 3];
                if from(h1) != from(h2) {
                    twin[h1] = h2 as u32;
                    twin[h2] = h1 as u32;
                }
            }
            i = j;
        }
        Ok(Self {
            faces: mesh.faces.clone(),
            twin,
            length,
        })
    }

    /// Cotangent of the angle opposite halfedge `he` in its face.
    fn cot_opposite(&self, he: usize) -> f64 {
        let f = he / 3;
        let i = he % 3;
        let a = self.length[he];
        let b = self.length[3 * f + (i + 1) % 3];
        let c = self.length[3 * f + (i + 2) % 3];
        let area = area_from_lengths(a, b, c);
        let lmax2 = a.max(b).max(c).powi(2);
        (b * b + c * c - a * a) / (4.0 * area.max(0.5 * DENOMINATOR_FLOOR * lmax2))
    }

    /// Whether the interior edge of `he` violates the Delaunay condition.
    fn needs_flip(&self, he: usize) -> bool {
        let t = self.twin[he];
        t != NONE && self.cot_opposite(he) + self.cot_opposite(t as usize) < -1e-12
    }

    /// Flips the edge of `he` (a→b in face (a, b, c), twin b→a in face (b, a, d)) to c–d.
    /// Returns false (and changes nothing) when the flip is not valid.
    fn flip(&mut self, he: usize) -> bool {
        let t = self.twin[he];
        if t == NONE {
            return false;
        }
        let t = t as usize;
        let (f1, i1) = (he / 3, he % 3);
        let (f2, i2) = (t / 3, t % 3);
        if f1 == f2 {
            return false;
        }
        let a = self.faces[f1][i1];
        let b = self.faces[f1][(i1 + 1) % 3];
        let c = self.faces[f1][(i1 + 2) % 3];
        let d = self.faces[f2][(i2 + 2) % 3];
        if c == d {
            return false;
        }
        // Outer halfedges and their lengths.
        let h_bc = 3 * f1 + (i1 + 1) % 3;
        let h_ca = 3 * f1 + (i1 + 2) % 3;
        let h_ad = 3 * f2 + (i2 + 1) % 3;
        let h_db = 3 * f2 + (i2 + 2) % 3;
        let (l_ab, l_bc, l_ca, l_ad, l_db) = (
            self.length[he],
            self.length[h_bc],
            self.length[h_ca],
            self.length[h_ad],
            self.length[h_db],
        );
        // Unfold both triangles into the plane: a = (0,0), b = (l_ab, 0), c above, d below.
        let place = |l_from_a: f64, l_from_b: f64, sign: f64| {
            let x = (l_ab * l_ab + l_from_a * l_from_a - l_from_b * l_from_b) / (2.0 * l_ab);
            let y2 = l_from_a * l_from_a - x * x;
            (x, sign * y2.max(0.0).sqrt())
        };
        let (cx, cy) = place(l_ca, l_bc, 1.0);
        let (dx, dy) = place(l_ad, l_db, -1.0);
        let l_cd = ((cx - dx).powi(2) + (cy - dy).powi(2)).sqrt();
        if !(l_cd.is_finite() && l_cd > 0.0)
            || area_from_lengths(l_cd, l_ca, l_ad) <= 0.0
            || area_from_lengths(l_cd, l_db, l_bc) <= 0.0
        {
            return false;
        }
        let (t_bc, t_ca, t_ad, t_db) = (
            self.twin[h_bc],
            self.twin[h_ca],
            self.twin[h_ad],
            self.twin[h_db],
        );
        // New faces: f1 = (c, a, d), f2 = (d, b, c). Halfedges in order of their corners.
        self.faces[f1] = [c, a, d];
        self.faces[f2] = [d, b, c];
        let set = |s: &mut Self, h: usize, len: f64, tw: u32| {
            s.length[h] = len;
            s.twin[h] = tw;
            if tw != NONE {
                s.twin[tw as usize] = h as u32;
            }
        };
        let (n_ca, n_ad, n_dc) = (3 * f1, 3 * f1 + 1, 3 * f1 + 2);
        let (n_db, n_bc, n_cd) = (3 * f2, 3 * f2 + 1, 3 * f2 + 2);
        set(self, n_ca, l_ca, t_ca);
        set(self, n_ad, l_ad, t_ad);
        set(self, n_db, l_db, t_db);
        set(self, n_bc, l_bc, t_bc);
        self.length[n_dc] = l_cd;
        self.length[n_cd] = l_cd;
        self.twin[n_dc] = n_cd as u32;
        self.twin[n_cd] = n_dc as u32;
        true
    }
}

/// What the intrinsic Delaunay flips did.
#[derive(Debug, Clone, Copy, Default, serde::Serialize, serde::Deserialize)]
pub struct IntrinsicStats {
    /// Number of intrinsic edge flips performed.
    pub flips: usize,
    /// Interior edges still non-Delaunay when the flip budget ran out (0 normally).
    pub remaining_non_delaunay: usize,
}

/// Cotangent Laplacian of the intrinsic Delaunay triangulation of `mesh` (see
/// [`LaplacianKind::IntrinsicDelaunay`]): the classic flip algorithm on edge lengths. Boundary,
/// non-manifold and inconsistently oriented edges are kept fixed. The mass matrix is the
/// barycentric lumping of the intrinsic triangles (same total area).
pub fn intrinsic_delaunay_laplacian(mesh: &Mesh) -> crate::Result<(Laplacian, IntrinsicStats)> {
    let n = mesh.vertices.len();
    let mut tri = Intrinsic::from_mesh(mesh)?;
    let nh = tri.length.len();
    let mut queued = vec![true; nh];
    let mut stack: Vec<usize> = (0..nh).rev().collect();
    let mut flips = 0usize;
    // The flip algorithm terminates (each flip lowers a bounded energy); the budget only guards
    // against rounding cycles.
    let budget = 50 * nh + 1000;
    while let Some(he) = stack.pop() {
        queued[he] = false;
        if flips >= budget {
            break;
        }
        if !tri.needs_flip(he) {
            continue;
        }
        let (f1, f2) = (he / 3, tri.twin[he] as usize / 3);
        if tri.flip(he) {
            flips += 1;
            for h in [3 * f1, 3 * f1 + 1, 3 * f2, 3 * f2 + 1] {
                for h in [h, tri.twin[h] as usize] {
                    if h < nh && !queued[h] {
                        queued[h] = true;
                        stack.push(h);
                    }
                }
            }
        }
    }
    let remaining_non_delaunay = (0..nh)
        .filter(|&h| (tri.twin[h] as usize) > h && tri.needs_flip(h))
        .count();
    let mut mass = vec![0.0f64; n];
    let mut edges: Vec<(u32, u32, f64)> = Vec::with_capacity(3 * tri.faces.len());
    for (f, face) in tri.faces.iter().enumerate() {
        let [l0, l1, l2] = [
            tri.length[3 * f],
            tri.length[3 * f + 1],
            tri.length[3 * f + 2],
        ];
        let area = area_from_lengths(l0, l1, l2);
        if area == 0.0 {
            continue;
        }
        for i in 0..3 {
            let he = 3 * f + i;
            let (a, b) = (face[i], face[(i + 1) % 3]);
            edges.push((a.min(b), a.max(b), 0.5 * tri.cot_opposite(he)));
        }
        for &v in face {
            mass[v as usize] += area / 3.0;
        }
    }
    Ok((
        assemble(n, edges, mass)?,
        IntrinsicStats {
            flips,
            remaining_non_delaunay,
        },
    ))
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
    fn intrinsic_delaunay_equals_cotangent_on_a_delaunay_mesh() {
        let mesh = generate::icosphere(3);
        let a = cotangent_laplacian(&mesh).unwrap();
        let (b, stats) = intrinsic_delaunay_laplacian(&mesh).unwrap();
        assert_eq!(stats.flips, 0);
        let (da, db) = (dense(&a), dense(&b));
        for i in 0..da.len() {
            for j in 0..da.len() {
                assert!((da[i][j] - db[i][j]).abs() < 1e-12, "{i},{j}");
            }
        }
    }

    #[test]
    fn intrinsic_delaunay_removes_negative_weights_and_keeps_area() {
        // A grid whose interior vertices are sheared so many triangles are obtuse.
        let mut mesh = generate::rectangle(1.0, 1.0, 12, 12);
        for (i, v) in mesh.vertices.iter_mut().enumerate() {
            if v[0] > 1e-9 && v[0] < 1.0 - 1e-9 && v[1] > 1e-9 && v[1] < 1.0 - 1e-9 {
                v[0] += 0.035 * ((i * 7919) % 13) as f64 / 13.0 - 0.0175;
                v[1] += 0.035 * ((i * 104729) % 11) as f64 / 11.0 - 0.0175;
            }
        }
        let a = cotangent_laplacian(&mesh).unwrap();
        let (b, stats) = intrinsic_delaunay_laplacian(&mesh).unwrap();
        assert!(
            a.negative_weights > 0,
            "the test mesh must start non-Delaunay"
        );
        assert!(stats.flips > 0);
        assert_eq!(stats.remaining_non_delaunay, 0);
        let off_diagonal_positive = {
            let m = b.stiffness.as_ref();
            (0..m.ncols()).all(|j| {
                m.row_idx_of_col(j)
                    .zip(m.val_of_col(j))
                    .all(|(i, v)| i == j || *v <= 1e-12)
            })
        };
        assert!(
            off_diagonal_positive,
            "all intrinsic Delaunay weights are ≥ 0"
        );
        let (sa, sb): (f64, f64) = (a.mass.iter().sum(), b.mass.iter().sum());
        assert!((sa - sb).abs() < 1e-12);
        // A flat domain stays flat: linear functions remain harmonic inside.
        let d = dense(&b);
        let u: Vec<f64> = mesh.vertices.iter().map(|p| 2.0 * p[0] - p[1]).collect();
        for (i, p) in mesh.vertices.iter().enumerate() {
            if p[0] > 1e-9 && p[0] < 1.0 - 1e-9 && p[1] > 1e-9 && p[1] < 1.0 - 1e-9 {
                let lu: f64 = (0..u.len()).map(|j| d[i][j] * u[j]).sum();
                assert!(lu.abs() < 1e-10, "vertex {i}: {lu}");
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
