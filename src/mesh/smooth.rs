//! **Taubin smoothing**: a low-pass filter of the surface before its spectrum is computed
//! (G. Taubin, *A signal processing approach to fair surface design*, SIGGRAPH 1995).
//!
//! Each step moves every vertex twice towards the mean of its neighbours, by `λ` and then by `μ`
//! (`μ < −λ < 0`, the second move pushes back): `x ← x + λ (W x − x)`, then
//! `x ← x + μ (W x − x)`, `W` the umbrella operator (the plain mean of the neighbours). For a
//! surface frequency `k` (an eigenvalue of `I − W`) one step multiplies its component by
//! `(1 − λk)(1 − μk)`: 1 at `k = 0`, above 1 just below the pass-band frequency
//! `k_PB = 1/λ + 1/μ` (0.113 for the defaults `λ = 0.5`, `μ = −0.53`), and far below 1 at the
//! high frequencies, so noise at the scale of the edges is removed while the overall shape keeps
//! its size — plain umbrella smoothing would shrink it.
//!
//! **Boundaries.** A vertex on a boundary edge (an edge of exactly one face) moves towards the
//! mean of its neighbours *along the boundary* only, so a boundary curve is smoothed as a curve
//! and is not pulled into the surface (a hole would otherwise widen). Interior vertices use all
//! their neighbours. A vertex on a non-manifold edge (more than two faces) does not move.
//!
//! **Why here.** Normal noise of a few tenths of an edge length adds area unevenly — most where
//! the edges are short — so it changes the intrinsic geometry that every spectral descriptor
//! reads; on human figures, which differ from one another by little, it mixes them up
//! (`docs/quality.md` §25). A few steps remove it and leave the low modes of the clean shapes
//! nearly unchanged.
//!
//! The umbrella weights depend on the triangulation (they also even out the vertex spacing); it
//! is a preparation step, not an intrinsic operator.
//!
//! **How many steps.** `steps` pairs, or with [`SmoothOptions::until_settled`] more while the
//! last pair still lowered the surface's [`mesh_roughness`] (the median height of a vertex over
//! its neighbours' mean, along the normal, in mean edge lengths) by more than a given fraction:
//! the filter removes noise fast and a clean surface's own detail slowly, so a noisy shape gets
//! the pairs its noise needs and a clean one exactly `steps`.
//!
//! **Safeguard.** On irregular meshes unguarded umbrella steps turn faces over and make slivers
//! (a decimated horse, a remeshed face mask: faces of 10⁻⁴ of the mean area after 10 steps, and
//! the eigensolver then does not converge). A move that would shrink a face below
//! [`MIN_AREA_KEPT`] of its input area is taken back for that face's vertices.
//!
//! Deterministic; `O(steps · F)`, plus an `O(V + F)` roughness per pair with `until_settled`.

use super::buckets::Buckets;
use super::Mesh;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Options of [`taubin`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SmoothOptions {
    /// Number of `λ`/`μ` step pairs (1..=100).
    pub steps: usize,
    /// The smoothing factor `λ`, in `(0, 0.5]`.
    pub lambda: f64,
    /// The inflating factor `μ`, in `(−1, −λ)`, with `(1 − 2λ)(1 − 2μ) ≤ 1` (no frequency of
    /// the umbrella operator, at most 2, is amplified).
    pub mu: f64,
    /// Continue past `steps` while the filter is still removing noise ([`UntilSettled`]);
    /// absent: exactly `steps` pairs. Omitted from the JSON when absent, so a spec without it
    /// keeps its key.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub until_settled: Option<UntilSettled>,
}

/// When [`taubin`] takes more step pairs than [`SmoothOptions::steps`]: after those, another
/// pair follows while the last pair lowered the surface's [`mesh_roughness`] by more than
/// `min_reduction` of its value, up to `max_steps` pairs in all.
///
/// Why: normal noise is what the first pairs remove fast (a strongly noisy shape's roughness
/// halves in the first pair), while on a clean surface, once the first pair has passed, a pair
/// lowers it by a tenth or less — the filter then works on the shape's own detail. So the clean
/// shapes of a collection get exactly `steps` pairs, and a noisy one gets as many more as its
/// noise needs to come down to the level of its clean siblings (`docs/quality.md` §27).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct UntilSettled {
    /// At most this many step pairs in all (`steps..=100`).
    pub max_steps: usize,
    /// Another pair follows while the last one lowered the roughness by more than this fraction
    /// of it, in `(0, 1)`.
    pub min_reduction: f64,
}

impl SmoothOptions {
    /// `steps` pairs with Taubin's usual factors `λ = 0.5`, `μ = −0.53`.
    pub const fn steps(steps: usize) -> Self {
        Self {
            steps,
            lambda: 0.5,
            mu: -0.53,
            until_settled: None,
        }
    }

    /// Why these options cannot be used, if they cannot.
    pub fn validate(&self) -> Result<(), String> {
        if !(1..=100).contains(&self.steps) {
            return Err(format!("steps must be in 1..=100, got {}", self.steps));
        }
        if !(self.lambda > 0.0 && self.lambda <= 0.5) {
            return Err(format!("lambda must be in (0, 0.5], got {}", self.lambda));
        }
        if !(self.mu > -1.0 && self.mu < -self.lambda) {
            return Err(format!(
                "mu must be in (-1, -lambda) = (-1, {}), got {}",
                -self.lambda, self.mu
            ));
        }
        // The umbrella operator's frequencies reach 2: there a step multiplies by
        // (1 − 2λ)(1 − 2μ), which must not amplify.
        let top = (1.0 - 2.0 * self.lambda) * (1.0 - 2.0 * self.mu);
        if top > 1.0 {
            return Err(format!(
                "(1 - 2 lambda)(1 - 2 mu) = {top} amplifies the highest frequencies (must be ≤ 1)"
            ));
        }
        if let Some(u) = &self.until_settled {
            if !(self.steps..=100).contains(&u.max_steps) {
                return Err(format!(
                    "until_settled.max_steps must be in steps..=100 = {}..=100, got {}",
                    self.steps, u.max_steps
                ));
            }
            if !(u.min_reduction > 0.0 && u.min_reduction < 1.0) {
                return Err(format!(
                    "until_settled.min_reduction must be in (0, 1), got {}",
                    u.min_reduction
                ));
            }
        }
        Ok(())
    }
}

/// `mesh` smoothed by `opts.steps` Taubin step pairs (module docs), or more with
/// [`SmoothOptions::until_settled`]. Faces are unchanged; vertices referenced by no face do not
/// move.
pub fn taubin(mesh: &Mesh, opts: &SmoothOptions) -> Mesh {
    taubin_counted(mesh, opts).0
}

/// [`taubin`], and how many step pairs it took.
pub fn taubin_counted(mesh: &Mesh, opts: &SmoothOptions) -> (Mesh, usize) {
    let nbr = neighbours(mesh);
    let normal0: Vec<[f64; 3]> = mesh
        .faces
        .iter()
        .map(|f| face_normal(&mesh.vertices, f))
        .collect();
    let mut x = mesh.vertices.clone();
    let mut next = x.clone();
    let max_steps = opts
        .until_settled
        .map_or(opts.steps, |u| u.max_steps.max(opts.steps));
    // The roughness before the last pair, once it is needed (from the pair before `steps`).
    let mut before = None;
    let mut done = 0;
    while done < max_steps {
        if let Some(u) = &opts.until_settled {
            if done + 1 >= opts.steps {
                let now = roughness(&mesh.faces, &nbr, &x);
                // Settled: the last pair removed little (or the surface is already flat).
                let settled = |b: f64| !(b > 0.0 && (b - now) > u.min_reduction * b);
                if done >= opts.steps && before.is_some_and(settled) {
                    break;
                }
                before = Some(now);
            }
        }
        done += 1;
        for f in [opts.lambda, opts.mu] {
            for (v, out) in next.iter_mut().enumerate() {
                let ns = nbr.get(v);
                let p = x[v];
                if ns.is_empty() {
                    *out = p;
                    continue;
                }
                let mut m = [0.0; 3];
                for &u in ns {
                    let q = x[u as usize];
                    for i in 0..3 {
                        m[i] += q[i];
                    }
                }
                let inv = 1.0 / ns.len() as f64;
                for i in 0..3 {
                    out[i] = p[i] + f * (m[i] * inv - p[i]);
                }
            }
            keep_faces_valid(&mesh.faces, &normal0, &x, &mut next);
            std::mem::swap(&mut x, &mut next);
        }
    }
    let out = Mesh {
        vertices: x,
        faces: mesh.faces.clone(),
        repairs: mesh.repairs.clone(),
    };
    (out, done)
}

/// `roughness` of a mesh, with the umbrella neighbours [`taubin`] uses.
pub fn mesh_roughness(mesh: &Mesh) -> f64 {
    roughness(&mesh.faces, &neighbours(mesh), &mesh.vertices)
}

/// How rough the surface `x` is at the scale of its edges: the median, over the vertices with
/// at least three umbrella neighbours (interior vertices), of the distance from the vertex to the
/// mean of its neighbours *along the vertex normal* (area-weighted), over the mean edge length.
/// The tangential part is left out: it measures how unevenly the vertices are spaced along the
/// surface, not how far the surface strays across itself. About 0.03–0.16 on the clean shapes
/// of the benchmarks and 0.23–0.33 under normal noise of σ = 0.35–0.5 mean edge lengths
/// (`docs/quality.md` §27); 0 when no vertex qualifies.
fn roughness(faces: &[[u32; 3]], nbr: &Buckets<u32>, x: &[[f64; 3]]) -> f64 {
    let mut normal = vec![[0.0f64; 3]; x.len()];
    for f in faces {
        let n = face_normal(x, f);
        for &v in f {
            for i in 0..3 {
                normal[v as usize][i] += n[i];
            }
        }
    }
    let (mut edge_sum, mut edges) = (0.0, 0usize);
    let mut heights = Vec::with_capacity(x.len());
    for (v, p) in x.iter().enumerate() {
        let ns = nbr.get(v);
        for &u in ns {
            edge_sum += super::norm(super::sub(x[u as usize], *p));
        }
        edges += ns.len();
        let n = normal[v];
        let len = super::norm(n);
        if ns.len() < 3 || len == 0.0 {
            continue;
        }
        let mut d = [0.0; 3];
        for &u in ns {
            for i in 0..3 {
                d[i] += x[u as usize][i];
            }
        }
        let inv = 1.0 / ns.len() as f64;
        let h = (0..3).map(|i| (d[i] * inv - p[i]) * n[i]).sum::<f64>() / len;
        heights.push(h.abs());
    }
    if heights.is_empty() || edges == 0 || edge_sum == 0.0 {
        return 0.0;
    }
    let mid = heights.len() / 2;
    let (_, m, _) = heights.select_nth_unstable_by(mid, f64::total_cmp);
    *m / (edge_sum / edges as f64)
}

/// Smallest area a face may shrink to under smoothing, as a fraction of its input area.
pub const MIN_AREA_KEPT: f64 = 0.1;

/// The safeguard of a smoothing move from `prev` to `next`: a face that the move would shrink
/// below [`MIN_AREA_KEPT`] of its input area gets its vertices moved back to `prev`, until no face
/// does. On irregular meshes (decimations, remeshed boundaries) unguarded umbrella steps make
/// slivers of a ten-thousandth of the mean area, and the eigensolver then does not converge
/// (`docs/quality.md` §25). Orientation is not tested: the cotangent operator reads a triangle's
/// edge lengths only, and on a noisy surface smoothing *should* turn faces over where the noise
/// folded it (a guard against turning over, measured, kept much of the noise, §25). `prev`
/// passes the test (the input does, every accepted step does), so moving every vertex back ends
/// it. A face of zero input area keeps its vertices where they are.
fn keep_faces_valid(
    faces: &[[u32; 3]],
    normal0: &[[f64; 3]],
    prev: &[[f64; 3]],
    next: &mut [[f64; 3]],
) {
    let bad = |next: &[[f64; 3]], fi: usize| {
        let n = face_normal(next, &faces[fi]);
        let n0 = normal0[fi];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let min = MIN_AREA_KEPT * MIN_AREA_KEPT * dot(n0, n0);
        dot(n, n) < min || min == 0.0
    };
    // Each pass moves at least one vertex back for good, so this ends; in practice after a
    // pass or two (reverting a vertex changes its other faces, hence the repeat).
    loop {
        let mut reverted = false;
        for (fi, f) in faces.iter().enumerate() {
            if bad(next, fi) {
                for &v in f {
                    let v = v as usize;
                    if next[v] != prev[v] {
                        next[v] = prev[v];
                        reverted = true;
                    }
                }
            }
        }
        if !reverted {
            return;
        }
    }
}

/// The (unnormalised) normal of face `f`: twice its area, along its orientation.
fn face_normal(x: &[[f64; 3]], f: &[u32; 3]) -> [f64; 3] {
    let [a, b, c] = f.map(|i| x[i as usize]);
    super::cross(super::sub(b, a), super::sub(c, a))
}

/// Neighbour lists of the umbrella operator: an interior vertex's edge neighbours, a
/// boundary vertex's neighbours along boundary edges, none for a vertex on a non-manifold edge.
fn neighbours(mesh: &Mesh) -> Buckets<u32> {
    let n = mesh.vertices.len();
    let mut faces_of_edge: HashMap<(u32, u32), u32> = HashMap::with_capacity(mesh.faces.len() * 3);
    for f in &mesh.faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            *faces_of_edge.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    // 0: interior, 1: on a boundary edge, 2: on a non-manifold edge.
    let mut kind = vec![0u8; n];
    for (&(a, b), &c) in &faces_of_edge {
        let k = match c {
            1 => 1,
            2 => 0,
            _ => 2,
        };
        for v in [a, b] {
            kind[v as usize] = kind[v as usize].max(k);
        }
    }
    let mut edges: Vec<(u32, u32)> = Vec::with_capacity(faces_of_edge.len() * 2);
    for (&(a, b), &c) in &faces_of_edge {
        for (v, u) in [(a, b), (b, a)] {
            let used = match kind[v as usize] {
                0 => true,
                1 => c == 1,
                _ => false,
            };
            if used {
                edges.push((v, u));
            }
        }
    }
    // Sorted so that the sums run in a fixed order whatever the hash map's.
    edges.sort_unstable();
    Buckets::new(n, edges)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;

    /// A deterministic pseudo-random number in [-1, 1) for vertex `i` (the fractional part of a
    /// scaled sine).
    fn hash_unit(i: usize, freq: f64, scale: f64) -> f64 {
        2.0 * ((i as f64 * freq).sin() * scale).rem_euclid(1.0) - 1.0
    }

    /// Mean length of `x − W x` (normal and tangential parts): the high-frequency content the
    /// filter removes.
    fn umbrella_length(m: &Mesh) -> f64 {
        let nbr = neighbours(m);
        let mut sum = 0.0;
        for (v, p) in m.vertices.iter().enumerate() {
            let ns = nbr.get(v);
            let mut d = [0.0; 3];
            for &u in ns {
                for i in 0..3 {
                    d[i] += m.vertices[u as usize][i] / ns.len() as f64;
                }
            }
            sum += ((d[0] - p[0]).powi(2) + (d[1] - p[1]).powi(2) + (d[2] - p[2]).powi(2)).sqrt();
        }
        sum / m.vertices.len() as f64
    }

    #[test]
    fn removes_noise_and_keeps_the_size() {
        let sphere = generate::icosphere(4);
        let mut noisy = sphere.clone();
        for (i, v) in noisy.vertices.iter_mut().enumerate() {
            // Deterministic radial noise in [-1, 1) of 2 % of the radius.
            let h = hash_unit(i, 12.9898, 43758.5453);
            for c in v.iter_mut() {
                *c *= 1.0 + 0.02 * h;
            }
        }
        let smooth = taubin(&noisy, &SmoothOptions::steps(5));
        let (r0, r1, r2) = (
            umbrella_length(&sphere),
            umbrella_length(&noisy),
            umbrella_length(&smooth),
        );
        assert!(r1 > 2.0 * r0, "{r0} {r1}");
        assert!(
            r2 < r0 + 0.25 * (r1 - r0),
            "clean {r0}, noisy {r1}, smoothed {r2}"
        );
        // Taubin's filter keeps the size (the mean radius); umbrella smoothing alone (μ ≈ 0)
        // shrinks the sphere.
        let radius = |m: &Mesh| {
            m.vertices
                .iter()
                .map(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt())
                .sum::<f64>()
                / m.vertices.len() as f64
        };
        let unbalanced = taubin(
            &noisy,
            &SmoothOptions {
                mu: -0.0001,
                ..SmoothOptions::steps(5)
            },
        );
        let (r_noisy, r_taubin, r_plain) = (radius(&noisy), radius(&smooth), radius(&unbalanced));
        assert!(
            (r_taubin / r_noisy - 1.0).abs() < 0.001 && r_plain / r_noisy < 0.995,
            "mean radius {r_noisy}: Taubin {r_taubin}, without the inflating step {r_plain}"
        );
        assert_eq!(smooth.faces, noisy.faces);
    }

    #[test]
    fn a_plane_stays_a_plane() {
        // A flat grid stays in z = 0 (every mean of points of the plane is in it); its border is
        // smoothed as a curve (the corners round off a little), the area stays within 2 %.
        let g = generate::rectangle(2.0, 1.5, 12, 9);
        let s = taubin(&g, &SmoothOptions::steps(10));
        assert!(s.vertices.iter().all(|v| v[2] == 0.0));
        let ratio = s.area() / g.area();
        assert!((ratio - 1.0).abs() < 0.02, "area ratio {ratio}");
    }

    #[test]
    fn a_hole_is_not_widened() {
        // A unit sphere without its cap above z = 0.875: the rim moves along the rim only. Had
        // the rim vertices used all their neighbours, all of which lie below, the rim would be
        // dragged down and the hole would grow.
        let sphere = generate::icosphere(4);
        let mut holed = sphere.clone();
        holed
            .faces
            .retain(|f| f.iter().all(|&v| sphere.vertices[v as usize][2] < 0.875));
        // The rim: the vertices of the edges of one face.
        let mut count: HashMap<(u32, u32), u32> = HashMap::new();
        for f in &holed.faces {
            for k in 0..3 {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                *count.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        let mut rim: Vec<u32> = count
            .iter()
            .filter(|&(_, &c)| c == 1)
            .flat_map(|(&(a, b), _)| [a, b])
            .collect();
        rim.sort_unstable();
        rim.dedup();
        assert!(rim.len() >= 20, "{}", rim.len());
        let mean = |m: &Mesh, f: &dyn Fn(&[f64; 3]) -> f64| {
            rim.iter().map(|&v| f(&m.vertices[v as usize])).sum::<f64>() / rim.len() as f64
        };
        let s = taubin(&holed, &SmoothOptions::steps(10));
        let z = |p: &[f64; 3]| p[2];
        let r = |p: &[f64; 3]| p[0].hypot(p[1]);
        let (z0, z1) = (mean(&holed, &z), mean(&s, &z));
        let (r0, r1) = (mean(&holed, &r), mean(&s, &r));
        assert!(
            (z1 - z0).abs() < 0.005 && (r1 / r0 - 1.0).abs() < 0.01,
            "rim z {z0} -> {z1}, radius {r0} -> {r1}"
        );
        let ratio = s.area() / holed.area();
        assert!(ratio > 0.99, "area ratio {ratio}");
    }

    #[test]
    fn no_face_collapses_and_noise_still_goes() {
        // Strong noise (a third of an edge) and many steps.
        let sphere = generate::icosphere(3);
        let mut noisy = sphere.clone();
        for (i, v) in noisy.vertices.iter_mut().enumerate() {
            let (h, g) = (
                hash_unit(i, 78.233, 43758.5453),
                hash_unit(i, 12.9898, 24634.6345),
            );
            v[0] += 0.05 * h;
            v[1] += 0.05 * g;
        }
        let strong = SmoothOptions {
            mu: -0.6,
            ..SmoothOptions::steps(20)
        };
        let smallest_area_ratio = |m: &Mesh| {
            m.faces
                .iter()
                .map(|f| {
                    let (n, o) = (face_normal(&m.vertices, f), face_normal(&noisy.vertices, f));
                    ((n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
                        / (o[0] * o[0] + o[1] * o[1] + o[2] * o[2]))
                        .sqrt()
                })
                .fold(f64::INFINITY, f64::min)
        };
        let s = taubin(&noisy, &strong);
        assert!(smallest_area_ratio(&s) >= MIN_AREA_KEPT);
        // And the guarded result is still smoother than the input.
        assert!(
            umbrella_length(&s) < 0.5 * umbrella_length(&noisy),
            "{} {}",
            umbrella_length(&s),
            umbrella_length(&noisy)
        );
    }

    #[test]
    fn the_safeguard_takes_back_slivers_only() {
        let g = generate::rectangle(1.0, 1.0, 4, 4);
        let n0: Vec<[f64; 3]> = g
            .faces
            .iter()
            .map(|f| face_normal(&g.vertices, f))
            .collect();
        // Vertex 6 = (0.25, 0.25) is interior; vertex 17 = (0.5, 0.75) too.
        assert_eq!(g.vertices[6], [0.25, 0.25, 0.0]);
        assert_eq!(g.vertices[17], [0.5, 0.75, 0.0]);
        let mut next = g.vertices.clone();
        next[17] = [0.51, 0.76, 0.0]; // a small move: kept
        next[0] = [0.01, 0.0, 0.0]; // a corner sliding along its side: kept
        keep_faces_valid(&g.faces, &n0, &g.vertices, &mut next);
        assert_eq!(next[17], [0.51, 0.76, 0.0]);
        assert_eq!(next[0], [0.01, 0.0, 0.0]);
        // Onto the line through two of its neighbours: its faces there collapse to slivers.
        let mut next = g.vertices.clone();
        next[6] = [0.25, 0.5 - 1e-3, 0.0];
        keep_faces_valid(&g.faces, &n0, &g.vertices, &mut next);
        assert_eq!(next[6], g.vertices[6]);
    }

    #[test]
    fn validates_its_options() {
        assert!(SmoothOptions::steps(5).validate().is_ok());
        assert!(SmoothOptions::steps(0).validate().is_err());
        assert!(SmoothOptions::steps(101).validate().is_err());
        let bad_mu = SmoothOptions {
            mu: -0.4,
            ..SmoothOptions::steps(5)
        };
        assert!(bad_mu.validate().unwrap_err().contains("mu"));
        let bad_lambda = SmoothOptions {
            lambda: 0.6,
            mu: -0.7,
            ..SmoothOptions::steps(5)
        };
        assert!(bad_lambda.validate().unwrap_err().contains("lambda"));
        let amplifying = SmoothOptions {
            lambda: 0.1,
            mu: -0.9,
            ..SmoothOptions::steps(5)
        };
        assert!(amplifying.validate().unwrap_err().contains("amplifies"));
        assert!(SmoothOptions {
            lambda: 0.4,
            mu: -0.9,
            ..SmoothOptions::steps(5)
        }
        .validate()
        .is_ok());
    }

    /// `mesh` with every vertex moved along its radius by `sigma` times the mean edge length,
    /// times a deterministic pseudo-random number in [-1, 1).
    fn radial_noise(mesh: &Mesh, sigma: f64) -> Mesh {
        let nbr = neighbours(mesh);
        let (mut sum, mut count) = (0.0, 0usize);
        for (v, p) in mesh.vertices.iter().enumerate() {
            for &u in nbr.get(v) {
                sum += crate::mesh::norm(crate::mesh::sub(mesh.vertices[u as usize], *p));
                count += 1;
            }
        }
        let ebar = sum / count as f64;
        let mut out = mesh.clone();
        for (i, v) in out.vertices.iter_mut().enumerate() {
            let r = crate::mesh::norm(*v);
            let h = hash_unit(i, 78.233, 12345.678);
            for c in v.iter_mut() {
                *c *= 1.0 + sigma * ebar * h / r;
            }
        }
        out
    }

    #[test]
    fn roughness_tells_noise_from_a_clean_surface() {
        let sphere = generate::icosphere(4);
        let clean = mesh_roughness(&sphere);
        let noisy = mesh_roughness(&radial_noise(&sphere, 0.5));
        assert!(clean < 0.05 && noisy > 0.2, "clean {clean}, noisy {noisy}");
        // Neither the size nor the resolution changes it.
        let mut big = sphere.clone();
        big.scale(7.0);
        assert!((mesh_roughness(&big) - clean).abs() < 1e-12);
        let finer = mesh_roughness(&generate::icosphere(5));
        assert!(finer < 0.05, "{finer}");
        // A plane is not rough at all.
        assert_eq!(mesh_roughness(&generate::rectangle(2.0, 1.5, 12, 9)), 0.0);
    }

    #[test]
    fn until_settled_stops_on_a_clean_surface_and_goes_on_under_noise() {
        let until = SmoothOptions {
            until_settled: Some(UntilSettled {
                max_steps: 10,
                min_reduction: 0.15,
            }),
            ..SmoothOptions::steps(2)
        };
        // Without it: exactly `steps` pairs.
        let sphere = generate::icosphere(4);
        assert_eq!(taubin_counted(&sphere, &SmoothOptions::steps(3)).1, 3);
        // A clean surface: the filter has nothing to remove, two pairs, the same vertices as
        // plain two steps.
        let (clean, n) = taubin_counted(&sphere, &until);
        assert_eq!(n, 2);
        assert_eq!(clean, taubin(&sphere, &SmoothOptions::steps(2)));
        // Under noise: more pairs, fewer than the bound, and the result's roughness closer to
        // the clean sphere's than two pairs leave it.
        let noisy = radial_noise(&sphere, 0.5);
        let (settled, n) = taubin_counted(&noisy, &until);
        assert!((3..10).contains(&n), "{n} pairs");
        let two = taubin(&noisy, &SmoothOptions::steps(2));
        let target = mesh_roughness(&clean);
        let (r_two, r_settled) = (mesh_roughness(&two), mesh_roughness(&settled));
        assert!(
            (r_settled - target).abs() < 0.5 * (r_two - target).abs(),
            "clean after two pairs {target}, noisy after two {r_two}, after {n} {r_settled}"
        );
        // The bound holds.
        let capped = SmoothOptions {
            until_settled: Some(UntilSettled {
                max_steps: 3,
                min_reduction: 0.01,
            }),
            ..SmoothOptions::steps(2)
        };
        assert_eq!(taubin_counted(&noisy, &capped).1, 3);
    }

    #[test]
    fn validates_until_settled() {
        let with = |max_steps, min_reduction| SmoothOptions {
            until_settled: Some(UntilSettled {
                max_steps,
                min_reduction,
            }),
            ..SmoothOptions::steps(2)
        };
        assert!(with(10, 0.15).validate().is_ok());
        assert!(with(2, 0.15).validate().is_ok());
        assert!(with(1, 0.15).validate().unwrap_err().contains("max_steps"));
        assert!(with(101, 0.15)
            .validate()
            .unwrap_err()
            .contains("max_steps"));
        assert!(with(10, 0.0)
            .validate()
            .unwrap_err()
            .contains("min_reduction"));
        assert!(with(10, 1.0)
            .validate()
            .unwrap_err()
            .contains("min_reduction"));
        assert!(with(10, f64::NAN).validate().is_err());
    }
}
