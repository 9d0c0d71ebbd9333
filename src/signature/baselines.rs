//! Baselines that are not spectral distance distributions but sit behind the same ranking
//! interface: the geodesic distance distribution (paper Table 2, "Geo") and Osada's D2.
//! ShapeDNA (the eigenvalue vector) needs no code beyond [`super::compute`].
//!
//! * **Geodesic**: exact shortest paths on the *edge graph* (Dijkstra, Euclidean edge lengths)
//!   from the farthest-point sources of the shared quadrature (weights: their Voronoi-cell
//!   areas) to every vertex (weights `a_y`). Edge-graph paths are polylines along mesh edges, so
//!   they *overestimate* the surface geodesic distance; the bias is systematic (similar on every
//!   shape of similar triangulation quality) and is not corrected (measured in
//!   `docs/signature.md`, bounded by the test `baselines_on_the_sphere`).
//! * **D2** (Osada et al. 2002): `samples` points uniform on the surface (triangle by area, then
//!   uniform barycentric), all unordered pairs, Euclidean distances, equal weights. The random
//!   generator is seeded with a hash of the mesh content, so a shape always gets the same
//!   signature (a vertex permutation changes the seed: D2 is then equal only statistically).

use super::distributions::{FineHistogram, QuantileSketch};
use super::sampling::{EdgeGraph, Quadrature};
use crate::mesh::{norm, sub, triangle_area, Mesh};
use rayon::prelude::*;
use sha2::{Digest, Sha256};
use std::collections::BinaryHeap;

/// Distribution of edge-graph geodesic distances from the quadrature sources to all vertices,
/// pairs (s, y) weighted `W_s a_y`, optionally only pairs closer than `radius`. Vertices not
/// reachable from a source (another component) are left out of that source's pairs.
pub(crate) fn geodesic_sketch(
    mesh: &Mesh,
    graph: &EdgeGraph,
    quad: &Quadrature,
    mass: &[f64],
    radius: Option<f64>,
    q: usize,
) -> QuantileSketch {
    let n = mesh.vertices.len();
    let sources = quad.point_indices();
    let dists: Vec<Vec<f64>> = sources
        .par_iter()
        .map(|&s| {
            let mut dist = vec![f64::INFINITY; n];
            let mut owner = vec![0u32; n];
            let mut heap = BinaryHeap::new();
            graph.relax_from(s as usize, &mut dist, &mut owner, 0, &mut heap);
            dist
        })
        .collect();
    let cap = radius.unwrap_or(f64::INFINITY);
    let bound = dists
        .iter()
        .flat_map(|d| d.iter())
        .filter(|d| d.is_finite() && **d <= cap)
        .fold(0.0f64, |a, &b| a.max(b));
    let mut fine = FineHistogram::new(bound);
    for (d, &ws) in dists.iter().zip(&quad.weights) {
        for (y, &g) in d.iter().enumerate() {
            if g.is_finite() && g <= cap {
                fine.add(g, ws * mass[y]);
            }
        }
    }
    fine.sketch(q)
}

/// A small deterministic generator (SplitMix64).
pub(crate) struct SplitMix64(pub(crate) u64);

impl SplitMix64 {
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub(crate) fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// Seed derived from the mesh content (SHA-256 of coordinates and indices).
pub fn mesh_seed(mesh: &Mesh) -> u64 {
    let mut h = Sha256::new();
    for v in &mesh.vertices {
        for c in v {
            h.update(c.to_le_bytes());
        }
    }
    for f in &mesh.faces {
        for i in f {
            h.update(i.to_le_bytes());
        }
    }
    let d = h.finalize();
    u64::from_le_bytes(d[..8].try_into().expect("8 bytes"))
}

/// `count` points uniform on the surface, from a generator seeded with [`mesh_seed`].
pub fn area_uniform_points(mesh: &Mesh, count: usize) -> Vec<[f64; 3]> {
    let mut cdf = Vec::with_capacity(mesh.faces.len());
    let mut acc = 0.0;
    for f in &mesh.faces {
        acc += triangle_area(mesh, f);
        cdf.push(acc);
    }
    if acc <= 0.0 || mesh.faces.is_empty() {
        return Vec::new();
    }
    let mut rng = SplitMix64(mesh_seed(mesh));
    (0..count)
        .map(|_| {
            let u = rng.next_f64() * acc;
            let fi = cdf.partition_point(|&c| c <= u).min(mesh.faces.len() - 1);
            let [a, b, c] = mesh.faces[fi].map(|i| mesh.vertices[i as usize]);
            let r1 = rng.next_f64().sqrt();
            let r2 = rng.next_f64();
            let (wa, wb, wc) = (1.0 - r1, r1 * (1.0 - r2), r1 * r2);
            [
                wa * a[0] + wb * b[0] + wc * c[0],
                wa * a[1] + wb * b[1] + wc * c[1],
                wa * a[2] + wb * b[2] + wc * c[2],
            ]
        })
        .collect()
}

/// Osada D2: Euclidean distances of all unordered pairs of `samples` area-uniform points, each
/// pair weighted `2 (area / samples)²` (ordered pairs, diagonal left out).
pub(crate) fn d2_sketch(mesh: &Mesh, samples: usize, q: usize) -> QuantileSketch {
    let pts = area_uniform_points(mesh, samples);
    let area = mesh.area();
    let m = pts.len();
    let w = 2.0 * (area / m.max(1) as f64).powi(2);
    let (lo, hi) = crate::mesh::bounding_box(&pts);
    let bound = if m > 0 { norm(sub(hi, lo)) } else { 1.0 };
    let chunk = 64;
    let parts: Vec<FineHistogram> = (0..m.div_ceil(chunk))
        .into_par_iter()
        .map(|c| {
            let mut fine = FineHistogram::new(bound);
            for i in c * chunk..((c + 1) * chunk).min(m) {
                for j in (i + 1)..m {
                    fine.add(norm(sub(pts[i], pts[j])), w);
                }
            }
            fine
        })
        .collect();
    let mut fine = FineHistogram::new(bound);
    for p in &parts {
        fine.merge(p);
    }
    fine.sketch(q)
}
