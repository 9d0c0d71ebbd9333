//! Boundary capping: every boundary loop of a mesh is closed by a triangulated cap, so that a
//! shape with parts cut away or holes punched in it has a closed surface again before its
//! spectrum is computed (`docs/quality.md` §19).
//!
//! # Why
//!
//! A plane cut or a hole leaves a boundary on which the Laplace–Beltrami eigenfunctions obey
//! the Neumann condition; the pair distances near it, and the whole distance distribution of
//! a shape that lost a limb's end, move away from those of the complete shape. A cap restores
//! a closed surface of the same genus with an area close to the missing one for small holes,
//! and turns a cut-off limb into a stump — which is how the same limb looks on every shape of
//! the character that was cut at about the same place, and much closer to the uncut limb than
//! an open tube. Shapes with a boundary of their own (a face mask, an open mesh from a scanner)
//! are capped the same way on every version, so comparisons among them stay consistent.
//!
//! # The cap
//!
//! For a loop of `m` vertices `p_0 … p_{m−1}` (in the direction the mesh's faces traverse its
//! edges), parametrised by arc length `u ∈ [0, 1)` from `p_0`, its vertex centroid `c`, its
//! length `L` and the area `A` it encloses (half its Newell vector's length):
//! `R = max(1, round(m / 2π))` rings; ring `r` (`1 ≤ r < R`) has
//! `k_r = max(3, round(m s_r))` vertices at `c + s_r (p(j/k_r) − c) + sqrt(1 − s_r²) h`,
//! `j = 0 … k_r − 1`: the loop shrunk towards `c` and resampled uniformly in arc length,
//! lifted into a dome of height `|h| = dome_height · ρ` ([`CapOptions::dome_height`];
//! `ρ = sqrt(A / π)`, the radius of a disc as large as what the loop encloses) along the
//! loop's outward normal (minus its Newell vector, since the cap runs against the loop). The
//! shrink factors `s_r = cos θ_r` put the rings at equal steps of arc length along the
//! meridian `(cos θ, (ρ / ρ_L) · dome_height · sin θ)`, `ρ_L = L / 2π`, so each band is about
//! as high as the loop's edges are long. Two successive rings are stitched by advancing along
//! whichever ring's next parameter is smaller, and the innermost ring is joined by a fan to a
//! vertex at `c + h`. Then Lawson's edge flips run inside the cap (an edge of two cap triangles
//! flips while its opposite angles sum to more than π, never joining two loop vertices, never
//! folding a triangle over), which replaces the thin triangles a jagged loop leaves in the
//! first band — a short edge, a vertex where the loop turns back — by the better pair across
//! the same quadrilateral. A loop of three vertices gets one flat triangle. The cap's
//! triangles are oriented against the loop, so an oriented mesh stays oriented, and a
//! closed-up manifold mesh has every edge in exactly two faces.
//!
//! Why the area and not the length sets the dome (`docs/quality.md` §28): noise lengthens a
//! loop without enlarging what it encloses (the face's mouth 0.72 → 0.90 √A at σ = 0.5 ē), and
//! a slit is long but encloses little, so a dome from the length grew with the noise and
//! stood as a balloon over a slit. Until §28 the rings were at equal steps of `s` with a
//! dome of height `dome_height · ρ_L`, and the sliver guard below left 90 loops of 772
//! open over 606 benchmark shapes — whole rims of cut-away parts among them, and the same
//! loop capped on one shape of a character and open on the next; it leaves 53 now (mostly a
//! 3-vertex crack of the horse, and the face's mouth on 3 of its 36 shapes).
//!
//! Two loops are left open: one longer than [`CapOptions::max_length`] `· sqrt(area)` (the
//! own border of an open surface), and one whose cap would still hold a triangle with an
//! angle below [`MIN_CAP_ANGLE_DEG`] (a crack: such slivers make the cotangent Laplacian
//! ill-conditioned). Both are counted in [`CapStats`].
//!
//! # The caps' size is bounded
//!
//! A cap as above has about `m² / 4π` vertices: as many as the mesh has around a hole of
//! ordinary size (at most 0.63 of the mesh's vertices on `bench/dev`, `face-cut2`), but a loop
//! sampled much more finely than the rest of the mesh — a cup of 4 001 vertices whose rim has
//! 2 000 — got 361 409 (this module's test, before the bound), and a rim of 8 000 vertices
//! several GB and over a minute of edge flips (an outside review's upload).
//! So the caps of one mesh add at most [`cap_budget`] vertices (as many as the mesh has, at
//! least [`MIN_CAP_BUDGET`]). A loop whose cap would not fit what is left of it gets a
//! coarser cap of the same dome: `R f` rings of `max(3, round(m s_r f))` vertices, `f` the
//! largest factor (from `sqrt(budget / size)` down by tenths) that fits, the first band then
//! joining the loop's `m` vertices to about `m s_1 f` ([`CapStats::loops_coarsened`]). Below
//! `f = 1/64` its first band could only be slivers, and the loop is left open.
//!
//! Loops are read off the directed boundary half-edges (edges with one incident face). A
//! vertex where two loops touch (a "bow tie") is visited once per loop. A loop along a
//! non-orientable patch, whose faces do not all traverse it one way round, has no directed
//! cycle: its edges are then followed without their direction and the loop is listed the way
//! most of them point (`docs/quality.md` §29; `prepare` orients every orientable mesh first).
//! Edges with more than two faces are not boundary edges and are never capped; a walk that
//! cannot close (a non-manifold boundary) is left open.
//!
//! Written here: capping is a few dozen lines on the crate's own [`Mesh`], and no maintained
//! Rust crate offers hole filling on an indexed triangle mesh without a geometry kernel of
//! its own.

use super::{cross, dot, norm, sub, Mesh};
use std::collections::{HashMap, HashSet};

/// What [`cap_boundaries`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct CapStats {
    /// Boundary loops capped.
    pub loops: usize,
    /// Vertices added (ring vertices and centres).
    pub vertices_added: usize,
    /// Faces added.
    pub faces_added: usize,
    /// Loops left open because they are longer than [`CapOptions::max_length`].
    #[serde(default)]
    pub loops_too_long: usize,
    /// Loops left open because their cap would have had a triangle with an angle below
    /// [`MIN_CAP_ANGLE_DEG`] (a crack or a slit, e.g. lips almost closed: such slivers make the
    /// cotangent Laplacian ill-conditioned), or would not fit the mesh's [`cap_budget`] even
    /// made coarser (module docs).
    #[serde(default)]
    pub loops_left_open: usize,
    /// Loops capped, counted in [`loops`](Self::loops), with a coarser cap than the module
    /// docs' design because that one would not have fitted the mesh's [`cap_budget`]. Left out
    /// of the JSON when 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub loops_coarsened: usize,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Least number of vertices the caps of one mesh may add ([`cap_budget`]).
pub const MIN_CAP_BUDGET: usize = 1024;

/// Most vertices the caps of a mesh of `vertices` vertices add together: as many as the mesh
/// has, and at least [`MIN_CAP_BUDGET`] (module docs).
pub fn cap_budget(vertices: usize) -> usize {
    vertices.max(MIN_CAP_BUDGET)
}

/// The coarsest cap built ([`cap_boundaries`]): ring sizes and ring count at least this
/// fraction of the design's.
const MIN_COARSENING: f64 = 1.0 / 64.0;

/// Which loops [`cap_boundaries`] closes.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CapOptions {
    /// Longest loop capped, over `sqrt(area)` of the mesh: holes and the rims of cut-away
    /// parts are short (on bench/dev ≤ 2.0 — a fifth of a character cut away by a plane —,
    /// a mouth ≤ 2.0), the own border of an open surface is long (the face mask's ≥ 4.2) and
    /// stays open. `f64::INFINITY` is not representable in JSON: use a large value to cap
    /// every loop.
    pub max_length: f64,
    /// Height of the cap's dome over the radius `ρ = sqrt(A / π)` of its loop, `A` the area the
    /// loop encloses (module docs; until `docs/quality.md` §28, `ρ = length / 2π`), in
    /// `[0, 2]`; 0 is a flat cap. Missing from the JSON: [`DOME_HEIGHT`], and omitted from it
    /// at that value, so the keys of specs written without it are unchanged.
    #[serde(
        default = "default_dome_height",
        skip_serializing_if = "is_default_dome_height"
    )]
    pub dome_height: f64,
}

fn default_dome_height() -> f64 {
    DOME_HEIGHT
}

fn is_default_dome_height(h: &f64) -> bool {
    *h == DOME_HEIGHT
}

impl CapOptions {
    /// Why these options cannot be used, if they cannot.
    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..=2.0).contains(&self.dome_height) {
            return Err(format!(
                "dome_height must be in [0, 2], got {}",
                self.dome_height
            ));
        }
        if self.max_length.is_finite() && self.max_length > 0.0 {
            Ok(())
        } else {
            Err(format!(
                "max_length must be finite and > 0, got {}",
                self.max_length
            ))
        }
    }
}

/// Smallest angle (degrees) a cap triangle may have; a loop whose cap would have a smaller one
/// is left open ([`CapStats::loops_left_open`]).
pub const MIN_CAP_ANGLE_DEG: f64 = 1.0;

/// [`CapOptions::dome_height`] of options that do not name one (the height capping was
/// introduced with, so specs stored before the field keep their meaning; `default` uses 1,
/// `docs/quality.md` §20).
pub const DOME_HEIGHT: f64 = 0.5;

/// The boundary loops of `faces` over `n` vertices: each loop lists its vertices in the
/// direction the faces traverse its edges. A loop along a non-orientable patch, whose faces do
/// not all traverse it one way round, is followed as an undirected cycle and listed in the
/// direction most of its edges are traversed (`docs/quality.md` §29). Boundary chains that
/// cannot be closed (next to a non-manifold edge) are omitted.
pub fn boundary_loops(n: usize, faces: &[[u32; 3]]) -> Vec<Vec<u32>> {
    let mut count: HashMap<(u32, u32), u32> = HashMap::with_capacity(faces.len() * 3);
    for f in faces {
        for (a, b) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
            *count.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    // Directed boundary half-edges, by tail vertex, in face order (deterministic).
    let mut next: Vec<Vec<u32>> = vec![Vec::new(); n];
    let mut tails: Vec<u32> = Vec::new();
    for f in faces {
        for (a, b) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
            if count[&(a.min(b), a.max(b))] == 1 {
                if next[a as usize].is_empty() {
                    tails.push(a);
                }
                next[a as usize].push(b);
            }
        }
    }
    let mut used: HashMap<(u32, u32), ()> = HashMap::new();
    let mut loops = Vec::new();
    for &a in &tails {
        for idx in 0..next[a as usize].len() {
            let b = next[a as usize][idx];
            if used.contains_key(&(a, b)) {
                continue;
            }
            used.insert((a, b), ());
            let mut lp = vec![a];
            let mut cur = b;
            let mut closed = true;
            while cur != a {
                lp.push(cur);
                match next[cur as usize]
                    .iter()
                    .find(|&&x| !used.contains_key(&(cur, x)))
                {
                    Some(&x) => {
                        used.insert((cur, x), ());
                        cur = x;
                    }
                    None => {
                        closed = false;
                        break;
                    }
                }
                if lp.len() > n {
                    closed = false;
                    break;
                }
            }
            if closed && lp.len() >= 3 {
                loops.push(lp);
            }
        }
    }
    // The boundary edges no directed cycle took, followed without their direction.
    let mut taken: HashSet<(u32, u32)> = HashSet::new();
    for lp in &loops {
        for (k, &a) in lp.iter().enumerate() {
            let b = lp[(k + 1) % lp.len()];
            taken.insert((a.min(b), a.max(b)));
        }
    }
    let mut rest: Vec<(u32, u32)> = Vec::new();
    for &a in &tails {
        for &b in &next[a as usize] {
            if !taken.contains(&(a.min(b), a.max(b))) {
                rest.push((a, b));
            }
        }
    }
    if !rest.is_empty() {
        loops.extend(undirected_cycles(&rest));
    }
    loops
}

/// Closed cycles through the directed boundary edges `edges`, followed without regard to their
/// direction (each edge once), each listed in the direction most of its edges point; chains
/// that do not close are dropped.
fn undirected_cycles(edges: &[(u32, u32)]) -> Vec<Vec<u32>> {
    let mut at: HashMap<u32, Vec<usize>> = HashMap::new();
    for (i, &(a, b)) in edges.iter().enumerate() {
        at.entry(a).or_default().push(i);
        at.entry(b).or_default().push(i);
    }
    let mut used = vec![false; edges.len()];
    let mut out = Vec::new();
    for first in 0..edges.len() {
        if used[first] {
            continue;
        }
        used[first] = true;
        let (start, mut cur) = edges[first];
        let mut lp = vec![start];
        let mut forward = 1i64;
        let mut closed = false;
        while let Some(&e) = at[&cur].iter().find(|&&e| !used[e]) {
            used[e] = true;
            lp.push(cur);
            let (a, b) = edges[e];
            let other = if a == cur { b } else { a };
            forward += if a == cur { 1 } else { -1 };
            cur = other;
            if cur == start {
                closed = true;
                break;
            }
        }
        if closed && lp.len() >= 3 {
            if forward < 0 {
                lp[1..].reverse();
            }
            out.push(lp);
        }
    }
    out
}

/// `mesh` with every boundary loop not longer than `opts.max_length · sqrt(area)` closed by a
/// cap (module docs). The input's vertices and faces keep their indices and order; cap
/// vertices and faces are appended.
pub fn cap_boundaries(mesh: &Mesh, opts: &CapOptions) -> (Mesh, CapStats) {
    let loops = boundary_loops(mesh.vertices.len(), &mesh.faces);
    let max_len = opts.max_length * mesh.area().sqrt();
    let mut vertices = mesh.vertices.clone();
    let mut faces = mesh.faces.clone();
    let mut stats = CapStats::default();
    let min_angle = MIN_CAP_ANGLE_DEG.to_radians();
    let budget = cap_budget(mesh.vertices.len());
    for lp in &loops {
        if loop_length(&mesh.vertices, lp) > max_len {
            stats.loops_too_long += 1;
            continue;
        }
        let (v0, f0) = (vertices.len(), faces.len());
        let left = budget - stats.vertices_added;
        let built = cap_loop(&mut vertices, &mut faces, lp, opts.dome_height, left);
        if built != Built::No {
            delaunay_flips(&vertices, &mut faces[f0..], v0 as u32);
        }
        let ok = built != Built::No
            && faces[f0..]
                .iter()
                .all(|f| smallest_angle(&vertices, f) >= min_angle);
        if ok {
            stats.loops += 1;
            stats.loops_coarsened += usize::from(built == Built::Coarser);
            stats.vertices_added += vertices.len() - v0;
            stats.faces_added += faces.len() - f0;
        } else {
            vertices.truncate(v0);
            faces.truncate(f0);
            stats.loops_left_open += 1;
        }
    }
    (Mesh::new(vertices, faces), stats)
}

/// The length of the closed polygon `lp` over `vertices`.
fn loop_length(vertices: &[[f64; 3]], lp: &[u32]) -> f64 {
    (0..lp.len())
        .map(|i| {
            dist(
                vertices[lp[i] as usize],
                vertices[lp[(i + 1) % lp.len()] as usize],
            )
        })
        .sum()
}

/// What [`cap_loop`] appended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Built {
    /// Nothing: the loop has no length, or no cap of it fits the budget.
    No,
    /// The cap of the module docs.
    AsDesigned,
    /// A coarser cap of the same dome, to fit the budget.
    Coarser,
}

/// Appends the cap of `lp` (module docs) with at most `budget` vertices.
fn cap_loop(
    vertices: &mut Vec<[f64; 3]>,
    faces: &mut Vec<[u32; 3]>,
    lp: &[u32],
    dome_height: f64,
    budget: usize,
) -> Built {
    let m = lp.len();
    let p: Vec<[f64; 3]> = lp.iter().map(|&i| vertices[i as usize]).collect();
    // A triangle's orientation against the loop: the loop runs a→b, the cap b→a.
    let push = |faces: &mut Vec<[u32; 3]>, a: u32, b: u32, c: u32| faces.push([b, a, c]);
    if m == 3 {
        push(faces, lp[0], lp[1], lp[2]);
        return Built::AsDesigned;
    }
    let seg: Vec<f64> = (0..m).map(|i| dist(p[i], p[(i + 1) % m])).collect();
    let total: f64 = seg.iter().sum();
    if !(total > 0.0 && total.is_finite()) {
        return Built::No;
    }
    // Arc-length parameter of each loop vertex.
    let mut u = Vec::with_capacity(m);
    let mut acc = 0.0;
    for s in &seg {
        u.push(acc / total);
        acc += s;
    }
    let mut c = [0.0; 3];
    for q in &p {
        for k in 0..3 {
            c[k] += q[k] / m as f64;
        }
    }
    let at = |t: f64| -> [f64; 3] {
        // The point of the loop at parameter t ∈ [0, 1).
        let i = match u.partition_point(|&x| x <= t) {
            0 => 0,
            k => k - 1,
        };
        let (t0, t1) = (u[i], if i + 1 < m { u[i + 1] } else { 1.0 });
        let w = if t1 > t0 { (t - t0) / (t1 - t0) } else { 0.0 };
        let (a, b) = (p[i], p[(i + 1) % m]);
        [
            a[0] + w * (b[0] - a[0]),
            a[1] + w * (b[1] - a[1]),
            a[2] + w * (b[2] - a[2]),
        ]
    };
    // The dome: lifted along the loop's outward normal (minus its Newell vector: the cap runs
    // against the loop) by `dome_height · ρ · sqrt(1 − s²)` at shrink factor `s`, ρ the radius
    // of a circle as long as the loop. A slit's shrunk copies are slits; lifted, the bands
    // between them are not slivers.
    let mut newell = [0.0; 3];
    for i in 0..m {
        let (a, b) = (p[i], p[(i + 1) % m]);
        newell[0] += (a[1] - b[1]) * (a[2] + b[2]);
        newell[1] += (a[2] - b[2]) * (a[0] + b[0]);
        newell[2] += (a[0] - b[0]) * (a[1] + b[1]);
    }
    // The dome's height: `dome_height` times the radius of a disc as large as the area the
    // loop encloses (half the Newell vector's length), not the radius of a circle as long as
    // the loop: noise lengthens a loop without enlarging what it encloses, and a slit is
    // long and encloses little.
    let rho_len = total / std::f64::consts::TAU;
    let nn = norm(newell);
    let rho = (nn / 2.0 / std::f64::consts::PI).sqrt();
    let lift = if nn > 1e-12 * rho_len * rho_len {
        newell.map(|x| -x / nn * dome_height * rho)
    } else {
        [0.0; 3]
    };
    let lifted = |q: [f64; 3], s: f64| -> [f64; 3] {
        let h = (1.0 - s * s).max(0.0).sqrt();
        [
            c[0] + s * (q[0] - c[0]) + h * lift[0],
            c[1] + s * (q[1] - c[1]) + h * lift[1],
            c[2] + s * (q[2] - c[2]) + h * lift[2],
        ]
    };
    let rings = ((m as f64) / std::f64::consts::TAU).round().max(1.0) as usize;
    // The meridian's aspect: the dome's height over the loop's own radius.
    let aspect = dome_height * rho / rho_len;
    // The rings' shrink factors and sizes for `rings` rings of `f` times the design's sizes;
    // the cap then adds the sizes' sum plus its centre.
    let plan = |rings: usize, f: f64| -> (Vec<f64>, Vec<usize>) {
        let shrink = meridian_shrinks(rings, aspect);
        let sizes = shrink[1..]
            .iter()
            .map(|&s| ((m as f64 * s * f).round() as usize).max(3))
            .collect();
        (shrink, sizes)
    };
    let added = |sizes: &[usize]| sizes.iter().sum::<usize>() + 1;
    let (mut shrink, mut sizes) = plan(rings, 1.0);
    let mut built = Built::AsDesigned;
    if added(&sizes) > budget {
        built = Built::Coarser;
        let mut f = (budget as f64 / added(&sizes) as f64).sqrt();
        loop {
            if f < MIN_COARSENING {
                return Built::No;
            }
            let r = ((rings as f64 * f).round() as usize).max(1);
            (shrink, sizes) = plan(r, f);
            if added(&sizes) <= budget {
                break;
            }
            f *= 0.9;
        }
    }
    let mut outer: Vec<u32> = lp.to_vec();
    let mut outer_u: Vec<f64> = u.clone();
    for (&s, &k) in shrink[1..].iter().zip(&sizes) {
        let first = vertices.len() as u32;
        let inner_u: Vec<f64> = (0..k).map(|j| j as f64 / k as f64).collect();
        for &t in &inner_u {
            vertices.push(lifted(at(t), s));
        }
        let inner: Vec<u32> = (0..k as u32).map(|j| first + j).collect();
        stitch(faces, &outer, &outer_u, &inner, &inner_u, push);
        outer = inner;
        outer_u = inner_u;
    }
    let centre = vertices.len() as u32;
    vertices.push(lifted(c, 0.0));
    let n = outer.len();
    for i in 0..n {
        push(faces, outer[i], outer[(i + 1) % n], centre);
    }
    built
}

/// The shrink factors `s_r` of rings `r = 0 … rings − 1` (ring 0 is the loop, `s = 1`): the
/// rings stand at equal steps of arc length along the dome's meridian, the quarter ellipse
/// `(s, h) = (cos θ, aspect · sin θ)` (a table of 256 angles, linear between them), `aspect`
/// being the dome's height over the loop's radius. A flat cap gets `s_r = 1 − r/rings` (to
/// 10⁻⁵); a hemisphere gets equal steps of `θ`. (Equal steps of `s` on a dome make the band
/// next to the loop steep and tall — its triangles about `sqrt(2R)` times as high as the
/// loop's edges are long — with slivers where the loop has a short edge or turns back,
/// `docs/quality.md` §28.)
fn meridian_shrinks(rings: usize, aspect: f64) -> Vec<f64> {
    const STEPS: usize = 256;
    let theta = |i: usize| i as f64 / STEPS as f64 * std::f64::consts::FRAC_PI_2;
    // Cumulative arc length of the meridian at STEPS + 1 angles.
    let mut arc = Vec::with_capacity(STEPS + 1);
    arc.push(0.0);
    for i in 1..=STEPS {
        let (a, b) = (theta(i - 1), theta(i));
        let step = (a.cos() - b.cos()).hypot(aspect * (b.sin() - a.sin()));
        arc.push(arc[i - 1] + step);
    }
    let total = arc[STEPS];
    let mut shrink = vec![1.0];
    shrink.extend((1..rings).map(|r| {
        let target = r as f64 / rings as f64 * total;
        let i = arc.partition_point(|&x| x < target).clamp(1, STEPS);
        let w = if arc[i] > arc[i - 1] {
            (target - arc[i - 1]) / (arc[i] - arc[i - 1])
        } else {
            0.0
        };
        (theta(i - 1) + w * (theta(i) - theta(i - 1))).cos()
    }));
    shrink
}

/// Lawson's edge flips on the faces `faces[first..]` (one cap): an edge shared by two of them
/// is flipped while the two angles opposite it sum to more than π (the Delaunay criterion),
/// unless the new edge would join two vertices below `first_vertex` (the loop's own, whose
/// edge may exist in the mesh) or exist already, or a new triangle would fold over (its normal
/// against the pair's). Flips never add or move a vertex, so the cap's surface keeps its
/// vertices; they only replace long, thin triangles by the better-shaped pair across the same
/// quadrilateral. Passes go on until one flips nothing (at most `4 · faces` passes).
fn delaunay_flips(vertices: &[[f64; 3]], faces: &mut [[u32; 3]], first_vertex: u32) {
    let n = faces.len();
    for _ in 0..4 * n.max(1) {
        let mut edge_faces: HashMap<(u32, u32), Vec<usize>> = HashMap::with_capacity(3 * n);
        for (fi, f) in faces.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                edge_faces.entry((a.min(b), a.max(b))).or_default().push(fi);
            }
        }
        let mut touched = vec![false; n];
        let mut created = HashSet::new();
        let mut flipped = 0usize;
        let mut edges: Vec<(u32, u32)> = edge_faces
            .iter()
            .filter(|(_, fs)| fs.len() == 2)
            .map(|(&e, _)| e)
            .collect();
        edges.sort_unstable(); // deterministic order
        for (a, b) in edges {
            let (f1, f2) = (edge_faces[&(a, b)][0], edge_faces[&(a, b)][1]);
            if touched[f1] || touched[f2] {
                continue;
            }
            let (t1, t2) = (faces[f1], faces[f2]);
            let opposite = |t: [u32; 3]| *t.iter().find(|&&v| v != a && v != b).unwrap();
            let (c1, c2) = (opposite(t1), opposite(t2));
            if c1 == c2
                || (c1 < first_vertex && c2 < first_vertex)
                || edge_faces.contains_key(&(c1.min(c2), c1.max(c2)))
                || created.contains(&(c1.min(c2), c1.max(c2)))
            {
                continue;
            }
            let at = |v: u32| vertices[v as usize];
            // A degenerate corner counts as flat (π): such a pair is always flipped.
            let angle =
                |apex: u32| angle_at(at(apex), at(a), at(b)).unwrap_or(std::f64::consts::PI);
            if angle(c1) + angle(c2) <= std::f64::consts::PI + 1e-12 {
                continue;
            }
            // t1 traverses the shared edge as x → y (and t2 as y → x): the new pair
            // (c1, x, c2) and (c2, y, c1) keeps the orientation.
            let k = (0..3)
                .find(|&k| t1[k] != c1 && t1[(k + 1) % 3] != c1)
                .unwrap();
            let (x, y) = (t1[k], t1[(k + 1) % 3]);
            let new1 = [c1, x, c2];
            let new2 = [c2, y, c1];
            let normal = |t: [u32; 3]| cross(sub(at(t[1]), at(t[0])), sub(at(t[2]), at(t[0])));
            let (n1, n2) = (normal(t1), normal(t2));
            let old = [n1[0] + n2[0], n1[1] + n2[1], n1[2] + n2[2]];
            if dot(normal(new1), old) <= 0.0 || dot(normal(new2), old) <= 0.0 {
                continue;
            }
            faces[f1] = new1;
            faces[f2] = new2;
            touched[f1] = true;
            touched[f2] = true;
            created.insert((c1.min(c2), c1.max(c2)));
            flipped += 1;
        }
        if flipped == 0 {
            return;
        }
    }
}

/// Triangulates the band between two closed rings, both running in the loop's direction with
/// parameters starting at 0: advance along the ring whose next parameter comes first.
fn stitch(
    faces: &mut Vec<[u32; 3]>,
    outer: &[u32],
    outer_u: &[f64],
    inner: &[u32],
    inner_u: &[f64],
    push: impl Fn(&mut Vec<[u32; 3]>, u32, u32, u32),
) {
    let (na, nb) = (outer.len(), inner.len());
    let (mut i, mut j) = (0, 0);
    while i < na || j < nb {
        let next_a = if i + 1 < na { outer_u[i + 1] } else { 1.0 };
        let next_b = if j + 1 < nb { inner_u[j + 1] } else { 1.0 };
        if i < na && (j >= nb || next_a <= next_b) {
            push(faces, outer[i], outer[(i + 1) % na], inner[j % nb]);
            i += 1;
        } else {
            push(faces, outer[i % na], inner[(j + 1) % nb], inner[j]);
            j += 1;
        }
    }
}

/// The smallest interior angle of triangle `f` (radians; 0 for a degenerate one).
fn smallest_angle(vertices: &[[f64; 3]], f: &[u32; 3]) -> f64 {
    let p = f.map(|i| vertices[i as usize]);
    (0..3)
        .map(|k| angle_at(p[k], p[(k + 1) % 3], p[(k + 2) % 3]).unwrap_or(0.0))
        .fold(f64::INFINITY, f64::min)
}

/// The angle at `apex` between the directions to `b` and `c` (radians); `None` when either
/// is at the apex.
fn angle_at(apex: [f64; 3], b: [f64; 3], c: [f64; 3]) -> Option<f64> {
    let (lb, lc) = (dist(apex, b), dist(apex, c));
    if lb == 0.0 || lc == 0.0 {
        return None;
    }
    Some(
        (dot(sub(b, apex), sub(c, apex)) / (lb * lc))
            .clamp(-1.0, 1.0)
            .acos(),
    )
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    norm(sub(a, b))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;

    const ALL: CapOptions = CapOptions {
        max_length: 1e9,
        dome_height: DOME_HEIGHT,
    };

    /// Every edge in exactly two faces, traversed in opposite directions.
    fn closed_and_oriented(m: &Mesh) -> bool {
        let mut dir: HashMap<(u32, u32), i32> = HashMap::new();
        let mut cnt: HashMap<(u32, u32), u32> = HashMap::new();
        for f in &m.faces {
            for (a, b) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
                *dir.entry((a.min(b), a.max(b))).or_insert(0) += if a < b { 1 } else { -1 };
                *cnt.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        cnt.values().all(|&c| c == 2) && dir.values().all(|&d| d == 0)
    }

    fn euler(m: &Mesh) -> i64 {
        let mut e = std::collections::HashSet::new();
        for f in &m.faces {
            for (a, b) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
                e.insert((a.min(b), a.max(b)));
            }
        }
        m.vertices.len() as i64 - e.len() as i64 + m.faces.len() as i64
    }

    /// A sphere with the faces above `z > h` removed (a plane cut).
    fn cut_sphere(h: f64) -> Mesh {
        let s = generate::icosphere(4);
        let faces = s
            .faces
            .iter()
            .copied()
            .filter(|f| f.iter().all(|&i| s.vertices[i as usize][2] <= h))
            .collect();
        Mesh::new(s.vertices, faces)
    }

    #[test]
    fn a_cut_sphere_is_closed_into_an_oriented_sphere() {
        let m = cut_sphere(0.5);
        assert_eq!(boundary_loops(m.vertices.len(), &m.faces).len(), 1);
        let (c, st) = cap_boundaries(&m, &ALL);
        assert_eq!(st.loops, 1);
        assert!(closed_and_oriented(&c));
        // Unreferenced vertices of the cut part stay in the vertex list; count only used ones.
        let used: std::collections::HashSet<u32> = c.faces.iter().flatten().copied().collect();
        let mut e = std::collections::HashSet::new();
        for f in &c.faces {
            for (a, b) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
                e.insert((a.min(b), a.max(b)));
            }
        }
        assert_eq!(used.len() as i64 - e.len() as i64 + c.faces.len() as i64, 2);
        // The cap of a near-planar circular cut is about half an oblate spheroid over the
        // loop: semi-axes r (the loop's mean distance from the axis) and DOME_HEIGHT · r,
        // bulging outwards (+z here: the sphere's faces are oriented outwards).
        let lp = &boundary_loops(m.vertices.len(), &m.faces)[0];
        let r = lp
            .iter()
            .map(|&i| m.vertices[i as usize])
            .map(|v| (v[0] * v[0] + v[1] * v[1]).sqrt())
            .sum::<f64>()
            / lp.len() as f64;
        let e = (1.0 - DOME_HEIGHT * DOME_HEIGHT).sqrt();
        let half_spheroid = std::f64::consts::PI * r * r * (1.0 + (1.0 - e * e) / e * e.atanh());
        let cap_area = c.area() - m.area();
        assert!(
            (cap_area - half_spheroid).abs() < 0.06 * half_spheroid,
            "{cap_area} vs {half_spheroid}"
        );
        let loop_z = m.vertices[lp[0] as usize][2];
        let top = c.vertices.last().unwrap()[2];
        assert!(top > loop_z + 0.4 * r, "{top} vs {loop_z}");
        // No sliver: the smallest angle of a cap triangle is not tiny.
        let min_angle = c.faces[m.faces.len()..]
            .iter()
            .map(|f| smallest_angle(&c.vertices, f))
            .fold(f64::INFINITY, f64::min);
        assert!(min_angle > 10f64.to_radians(), "{}", min_angle.to_degrees());
    }

    /// A plane cut whose rim has one very short edge (a vertex moved to within 3 % of an edge
    /// of its neighbour), as the rims of real cuts do: the cap is built, closed and oriented,
    /// with no triangle under [`MIN_CAP_ANGLE_DEG`]. (Before the meridian rings and the flips,
    /// this loop was left open: the band next to the loop had a sliver on the short edge.)
    #[test]
    fn a_rim_with_a_very_short_edge_is_capped_without_slivers() {
        let mut m = cut_sphere(0.5);
        let lp = boundary_loops(m.vertices.len(), &m.faces)[0].clone();
        let (a, b) = (lp[0] as usize, lp[1] as usize);
        let (pa, pb) = (m.vertices[a], m.vertices[b]);
        m.vertices[a] = [0, 1, 2].map(|k| pb[k] + 0.03 * (pa[k] - pb[k]));
        let (c, st) = cap_boundaries(
            &m,
            &CapOptions {
                dome_height: 1.0,
                ..ALL
            },
        );
        assert_eq!((st.loops, st.loops_left_open), (1, 0), "{st:?}");
        assert!(closed_and_oriented(&c));
        let min_angle = c.faces[m.faces.len()..]
            .iter()
            .map(|f| smallest_angle(&c.vertices, f))
            .fold(f64::INFINITY, f64::min);
        assert!(
            min_angle >= MIN_CAP_ANGLE_DEG.to_radians(),
            "{}",
            min_angle.to_degrees()
        );
    }

    #[test]
    fn meridian_rings_are_even_along_the_dome() {
        // Flat: equal steps of s. Hemisphere: equal steps of the angle.
        let flat = meridian_shrinks(4, 0.0);
        for (r, s) in flat.iter().enumerate() {
            assert!((s - (1.0 - r as f64 / 4.0)).abs() < 1e-5, "{flat:?}");
        }
        let half = meridian_shrinks(4, 1.0);
        for (r, s) in half.iter().enumerate() {
            let th = r as f64 / 4.0 * std::f64::consts::FRAC_PI_2;
            assert!((s - th.cos()).abs() < 1e-6, "{half:?}");
        }
        assert_eq!(meridian_shrinks(1, 1.0), vec![1.0]);
    }

    #[test]
    fn the_dome_height_sets_the_caps_apex_and_is_validated() {
        let m = cut_sphere(0.5);
        let lp = &boundary_loops(m.vertices.len(), &m.faces)[0];
        // The radius of a disc as large as the (horizontal) loop encloses.
        let rho = (enclosed_xy(&m, lp) / std::f64::consts::PI).sqrt();
        // The loop's vertex centroid, over which the cap's centre vertex stands.
        let loop_z = lp.iter().map(|&i| m.vertices[i as usize][2]).sum::<f64>() / lp.len() as f64;
        for h in [0.0, 0.25, 1.0] {
            let opts = CapOptions {
                dome_height: h,
                ..ALL
            };
            assert_eq!(opts.validate(), Ok(()));
            let (c, st) = cap_boundaries(&m, &opts);
            assert_eq!(st.loops, 1);
            assert!(closed_and_oriented(&c));
            // The apex (the centre vertex, appended last) stands h·ρ above that centroid.
            let apex = c.vertices.last().unwrap()[2] - loop_z;
            assert!((apex - h * rho).abs() < 1e-9 + 0.01 * rho, "h {h}: {apex}");
        }
        for bad in [-0.1, 2.5, f64::NAN] {
            let opts = CapOptions {
                dome_height: bad,
                ..ALL
            };
            assert!(opts.validate().is_err(), "{bad}");
        }
        // The default height is left out of the JSON (spec keys unchanged), others kept.
        assert_eq!(
            serde_json::to_string(&ALL).unwrap(),
            r#"{"max_length":1000000000.0}"#
        );
        let back: CapOptions = serde_json::from_str(r#"{"max_length":2.5}"#).unwrap();
        assert_eq!(back.dome_height, DOME_HEIGHT);
        let with = CapOptions {
            dome_height: 1.0,
            ..ALL
        };
        assert!(serde_json::to_string(&with)
            .unwrap()
            .contains("dome_height"));
    }

    /// The area a loop encloses in the xy-plane (shoelace).
    fn enclosed_xy(m: &Mesh, lp: &[u32]) -> f64 {
        let p = |i: usize| m.vertices[lp[i % lp.len()] as usize];
        (0..lp.len())
            .map(|i| p(i)[0] * p(i + 1)[1] - p(i + 1)[0] * p(i)[1])
            .sum::<f64>()
            .abs()
            / 2.0
    }

    /// Noise across the loop lengthens it without enlarging what it encloses: the dome keeps
    /// its height (a dome from the loop's length grew with it, here by more than a fifth).
    #[test]
    fn noise_on_the_rim_does_not_raise_the_dome() {
        let clean = cut_sphere(0.5);
        let lp = boundary_loops(clean.vertices.len(), &clean.faces)[0].clone();
        let mut noisy = clean.clone();
        for (k, &i) in lp.iter().enumerate() {
            noisy.vertices[i as usize][2] += if k % 2 == 0 { 0.03 } else { -0.03 };
        }
        let (l0, l1) = (
            loop_length(&clean.vertices, &lp),
            loop_length(&noisy.vertices, &lp),
        );
        assert!(l1 > 1.2 * l0, "{l0} {l1}");
        let opts = CapOptions {
            dome_height: 1.0,
            ..ALL
        };
        let apex = |m: &Mesh| {
            let (c, st) = cap_boundaries(m, &opts);
            assert_eq!(st.loops, 1);
            let z = lp.iter().map(|&i| m.vertices[i as usize][2]).sum::<f64>() / lp.len() as f64;
            c.vertices.last().unwrap()[2] - z
        };
        let (a0, a1) = (apex(&clean), apex(&noisy));
        assert!((a1 - a0).abs() < 0.01 * a0, "{a0} {a1}");
    }

    #[test]
    fn closed_meshes_are_unchanged_and_a_torus_keeps_its_genus() {
        let t = generate::torus(1.0, 0.4, 32, 16);
        let (c, st) = cap_boundaries(&t, &ALL);
        assert_eq!(st, CapStats::default());
        assert_eq!(c.faces, t.faces);
        // A torus with a hole in it: capped back to Euler characteristic 0.
        let faces: Vec<[u32; 3]> = t.faces[2..].to_vec();
        let holed = Mesh::new(t.vertices.clone(), faces);
        let (c, st) = cap_boundaries(&holed, &ALL);
        assert_eq!(st.loops, 1);
        assert!(closed_and_oriented(&c));
        assert_eq!(euler(&c), 0);
    }

    #[test]
    fn several_loops_and_a_triangle_hole() {
        // A sphere cut at both poles, and one triangle removed elsewhere.
        let s = generate::icosphere(4);
        let mut faces: Vec<[u32; 3]> = s
            .faces
            .iter()
            .copied()
            .filter(|f| f.iter().all(|&i| s.vertices[i as usize][2].abs() <= 0.6))
            .collect();
        let k = faces.len() / 2;
        faces.remove(k);
        let m = Mesh::new(s.vertices, faces);
        assert_eq!(boundary_loops(m.vertices.len(), &m.faces).len(), 3);
        let (c, st) = cap_boundaries(&m, &ALL);
        assert_eq!(st.loops, 3);
        assert!(closed_and_oriented(&c));
        // Only the loops not longer than max_length · sqrt(area) are capped: the two polar
        // rims are ≈ 2π · 0.8 / sqrt(area) ≈ 1.6 long, the one-triangle hole ≈ 0.03.
        let (_, short) = cap_boundaries(
            &m,
            &CapOptions {
                max_length: 1.0,
                ..ALL
            },
        );
        assert_eq!((short.loops, short.loops_too_long), (1, 2));
        // Capping is idempotent: nothing is left to cap.
        let (_, again) = cap_boundaries(&c, &ALL);
        assert_eq!(again, CapStats::default());
    }

    #[test]
    fn a_rim_whose_faces_disagree_on_its_direction_is_still_found_and_capped() {
        // A hole (the faces around vertex 0), then one face on its rim wound the other way,
        // as on a non-orientable patch: no directed cycle runs round the rim.
        let s = generate::icosphere(3);
        let ring: Vec<u32> = (0..s.vertices.len() as u32)
            .filter(|&v| v != 0 && s.faces.iter().any(|f| f.contains(&0) && f.contains(&v)))
            .collect();
        let mut faces: Vec<[u32; 3]> = s
            .faces
            .iter()
            .copied()
            .filter(|f| !f.contains(&0))
            .collect();
        let oriented = boundary_loops(s.vertices.len(), &faces);
        assert_eq!(oriented.len(), 1);
        let rim = faces
            .iter()
            .position(|f| f.iter().filter(|v| ring.contains(v)).count() == 2)
            .unwrap();
        faces[rim].swap(0, 1);
        let loops = boundary_loops(s.vertices.len(), &faces);
        assert_eq!(loops.len(), 1);
        let mut got = loops[0].clone();
        got.sort_unstable();
        assert_eq!(got, ring);
        // Listed the way most of its edges are traversed: as the oriented rim, up to rotation.
        let lp = &loops[0];
        let k = lp.iter().position(|&v| v == oriented[0][0]).unwrap();
        let rotated: Vec<u32> = (0..lp.len()).map(|i| lp[(k + i) % lp.len()]).collect();
        assert_eq!(rotated, oriented[0]);
        let (c, st) = cap_boundaries(&Mesh::new(s.vertices.clone(), faces), &ALL);
        assert_eq!((st.loops, st.loops_left_open), (1, 0));
        assert!(boundary_loops(c.vertices.len(), &c.faces).is_empty());
    }

    /// A cup: a tube of radius 1 and height 1 closed at the bottom by a fan, whose open rim
    /// has `m` vertices and whose side is one row of thin triangles: `2m + 1` vertices, the
    /// rim sampled far more finely than the rest.
    fn cup(m: u32) -> Mesh {
        let ring = |z: f64| {
            (0..m).map(move |i| {
                let a = i as f64 / m as f64 * std::f64::consts::TAU;
                [a.cos(), a.sin(), z]
            })
        };
        let mut v: Vec<[f64; 3]> = ring(1.0).chain(ring(0.0)).collect();
        v.push([0.0, 0.0, 0.0]);
        let (top, bottom, centre) = (|i: u32| i % m, |i: u32| m + i % m, 2 * m);
        let mut f = Vec::new();
        for i in 0..m {
            // Outward normals: the side faces outwards, the bottom downwards.
            f.push([bottom(i), bottom(i + 1), top(i + 1)]);
            f.push([bottom(i), top(i + 1), top(i)]);
            f.push([centre, bottom(i + 1), bottom(i)]);
        }
        Mesh::new(v, f)
    }

    /// The design's cap of a rim of `m` vertices has about `m² / 4π`: for a cup of 4 001
    /// vertices whose rim has 2 000, 361 409 vertices before the budget (this test's failure
    /// then; the review's upload of such a cup took 23.7 s and 2 GB in the server). Now the
    /// caps add at most [`cap_budget`] vertices, here with a coarser cap that still closes the
    /// cup without slivers; a rim as finely sampled as the rest keeps the design's cap.
    #[test]
    fn a_finely_sampled_rim_gets_a_coarser_cap_within_the_budget() {
        let m = cup(2000);
        let n = m.vertices.len();
        let (c, st) = cap_boundaries(&m, &ALL);
        assert_eq!(
            (st.loops, st.loops_coarsened, st.loops_left_open),
            (1, 1, 0),
            "{st:?}"
        );
        assert!(st.vertices_added <= cap_budget(n), "{st:?}");
        assert!(st.vertices_added > cap_budget(n) / 2, "{st:?}");
        assert!(closed_and_oriented(&c));
        let min_angle = c.faces[m.faces.len()..]
            .iter()
            .map(|f| smallest_angle(&c.vertices, f))
            .fold(f64::INFINITY, f64::min);
        assert!(min_angle >= MIN_CAP_ANGLE_DEG.to_radians());
        // Still a dome over the rim: its apex half the rim's radius above it (DOME_HEIGHT).
        let apex = c.vertices.last().unwrap()[2];
        assert!((apex - (1.0 + DOME_HEIGHT)).abs() < 0.01, "{apex}");
        // A small cup's rim is within the budget and gets the design's cap.
        let (_, small) = cap_boundaries(&cup(60), &ALL);
        assert_eq!((small.loops, small.loops_coarsened), (1, 0), "{small:?}");
        // No cap at all fits a budget that is a sliver's worth: the loop stays open.
        let tight = cup(4000);
        let mut v = tight.vertices.clone();
        let mut f = tight.faces.clone();
        let lp = &boundary_loops(v.len(), &f)[0];
        assert_eq!(cap_loop(&mut v, &mut f, lp, DOME_HEIGHT, 20), Built::No);
        assert_eq!(
            (v.len(), f.len()),
            (tight.vertices.len(), tight.faces.len())
        );
    }

    #[test]
    fn a_crack_or_a_slit_is_left_open() {
        // A strip of two rows of quads whose middle row is removed except at its ends: the
        // hole between the rows is a slit of width 1e-3 of its length.
        let (nx, w) = (20u32, 1e-3);
        let mut v = Vec::new();
        for y in [0.0, 1.0, 1.0 + w, 2.0 + w] {
            for i in 0..=nx {
                v.push([i as f64 / nx as f64 * 20.0, y, 0.0]);
            }
        }
        let id = |row: u32, i: u32| row * (nx + 1) + i;
        let mut f = Vec::new();
        for (r0, r1) in [(0, 1), (2, 3)] {
            for i in 0..nx {
                f.push([id(r0, i), id(r0, i + 1), id(r1, i + 1)]);
                f.push([id(r0, i), id(r1, i + 1), id(r1, i)]);
            }
        }
        for i in [0, nx - 1] {
            f.push([id(1, i), id(1, i + 1), id(2, i + 1)]);
            f.push([id(1, i), id(2, i + 1), id(2, i)]);
        }
        let m = Mesh::new(v, f);
        let (c, st) = cap_boundaries(&m, &ALL);
        // Both loops (the slit and the long, thin outer border, 20 × 2) would get sliver
        // triangles: both stay open and the mesh is unchanged.
        assert_eq!(st.loops_left_open, 2, "{st:?}");
        assert_eq!(st.loops, 0, "{st:?}");
        assert_eq!(c.faces, m.faces);
        assert_eq!(c.vertices.len(), m.vertices.len());
    }
}
