//! **Welding**: deterministic topological noise. Pairs of points that are close in space but far
//! apart along the surface are joined by a short tube, each tube adding one handle (genus + 1),
//! the way the `topology` and `isometry+topology` shapes of the benchmark were made
//! (`bench/README.md`, "How the shapes were made", row `topology`: *pairs of points close in
//! space but far along the surface (more than 0.2 geodesic diameter and more than 3x their gap
//! apart) are brought together (smooth local pull closing up to 60% of the gap), a small
//! geodesic disc is cut around each and the two boundary loops are joined by a short tube of
//! triangles*; strength levels 1..4 = (bridges, disc radius) = (1, 1.5 ē), (2, 2 ē),
//! (3, 2.5 ē), (4, 3 ē), ē the mean edge length). [`weld`] rebuilds that construction; it is not
//! the benchmark's own code, so the contacts it chooses differ from the benchmark's.
//!
//! # Construction
//!
//! Surface distances are Dijkstra distances on the edge graph (an upper bound of the geodesic
//! distance, enough to tell "far along the surface" from "near"); `r = disc_radius_edges · ē`.
//!
//! 1. **Contacts.** Every vertex `p` (every k-th above [`MAX_SAMPLES`] vertices, offset by the
//!    seed) is paired with the vertices `q` of its component within `max_gap_edges · ē` (a
//!    uniform grid) whose surfaces *face each other through the outside*: with outward normals
//!    (the sign of the enclosed volume tells outward from inward) and `d̂` the unit vector from
//!    `p` to `q`, `n_p · d̂ ≥ 0.3`, `−n_q · d̂ ≥ 0.3` and `n_p · n_q ≤ −0.3`. A pair is a
//!    candidate when its surface distance exceeds `min_geodesic_rel ×` the geodesic diameter of
//!    the component (double-sweep Dijkstra), `min_gap_ratio ×` the gap `|p − q|` and
//!    `2 r + separation_edges · ē` (a Dijkstra from `p` stopped at the largest bound).
//! 2. **Choice.** Candidates are taken greedily by increasing gap, rounded down to half an edge
//!    length, ties broken by a seeded hash of the pair (splitmix64): different seeds choose
//!    different contacts among nearly equal ones. A candidate is skipped when an endpoint lies
//!    within `2 r + separation_edges · ē` of an endpoint already chosen, when a disc shares a
//!    vertex with a disc already chosen, or when a disc or its rim does not qualify (3.).
//! 3. **Discs.** The disc of `p` is every face with a vertex at surface distance `< r`. It must
//!    be a topological disc (Euler characteristic 1) bounded by one simple cycle (the *rim*), away
//!    from the mesh boundary and from inconsistently oriented edges. Seen along the axis `d̂`,
//!    the rim must wind exactly once around the axis, in the sense that makes the tube face
//!    outwards (this checks the orientation geometrically), turning backwards by at most 0.15
//!    turn in total; its angles about the axis (running maximum) parametrise it.
//! 4. **Pull.** Vertex `v` near `p` moves by `w · pull/2 · (q − p)`, `w = 1` within `r` of `p`,
//!    then `1 − smoothstep` down to 0 at `r + gap + 2 ē`; likewise near `q`, so the gap
//!    closes by `pull`. Where pulls overlap, the weighted displacements are summed and divided
//!    by the sum of the weights when it exceeds 1.
//! 5. **Tube.** The discs are removed (their interior vertices disappear) and the rims `A` (of
//!    `p`) and `B` (of `q`) are joined: `A` is walked against the direction in which its
//!    remaining faces traverse it and `B` along it, so that every rim edge ends up in two faces
//!    traversing it in opposite directions (the tube is oriented like the rest of the surface).
//!    Up to 6 rings (about one per ē of the longest rim-to-rim distance) are interpolated, the
//!    vertex count going from `|A|` to `|B|`: the ring point at angle `t` lies on the cubic
//!    Hermite curve from `A(t)` to `B(t)` with both tangents along the axis (the tube leaves the
//!    rims along the axis), drawn in radially to a neck of 0.6 of the rims' radius at the
//!    middle. Consecutive rings are zipped by angle into `|lower| + |upper|` triangles. Kept
//!    input vertices keep their relative order; new ones are appended.
//!
//! Each bridge removes two discs (Euler characteristic − 2) and adds an annulus glued along two
//! circles (± 0): the genus rises by one per bridge; components and boundary loops do not
//! change. The result is checked with [`surface_stats`] (manifold, same components and boundary
//! loops, genus + bridges made) and for degenerate faces; a failed check is an error. The pull
//! stops short of the contact, so no new vertex lands on an old one and an OBJ round trip through
//! `prepare` (which welds exactly coincident vertices) keeps the handles (checked by the tests and
//! the `weld_bench` example, not by [`weld`]). The tube is not checked against intersecting the
//! rest of the surface: on thin limbs a disc wraps around the limb and the tube can cut through
//! neighbouring faces (the surface stays a valid manifold; intrinsic descriptors are unaffected).
//!
//! Everything is deterministic for a given seed. The input must be a manifold triangle mesh
//! (every edge in at most two faces, no repeated vertex in a face).

use super::topology::{compact, surface_stats, SurfaceStats, TopologyError};
use super::{cross, dot, norm, sub, Mesh};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, HashSet};

mod graph;
mod tubes;

use graph::{components_and_diameters, Graph, Scratch};
use tubes::{angle_params, tube, Bridge};

/// Most bridges one call may make.
pub const MAX_BRIDGES: usize = 64;
/// Above this many vertices, only every k-th vertex is tried as a contact endpoint `p`.
pub const MAX_SAMPLES: usize = 8000;

/// Smallest gap (in mean edge lengths) of a contact: the tube must have a length.
const MIN_GAP_EDGES: f64 = 0.1;
/// Width of the gap bins of the greedy choice, in mean edge lengths.
const GAP_BIN_EDGES: f64 = 0.5;
/// Facing tests of a contact (module docs, step 1).
const FACING: f64 = 0.3;
/// At most this many interpolated rings in a tube.
const MAX_RINGS: usize = 6;
/// Largest total backward turning of a disc's rim about the bridge axis, in turns.
const MAX_BACKTURN: f64 = 0.15;
/// Radius of a tube's middle ring relative to its rims (the tube narrows to a neck).
const NECK: f64 = 0.6;

/// Why [`weld`] refused or failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WeldError {
    /// An option is out of range.
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// The input is not a manifold triangle mesh (bad index, repeated vertex, an edge in more
    /// than two faces).
    #[error(transparent)]
    Topology(#[from] TopologyError),
    /// The input has no usable geometry (no face, or zero mean edge length).
    #[error("cannot weld: {0}")]
    Degenerate(String),
    /// The welded mesh failed its final check (a bug; the message says which).
    #[error("welded mesh failed its check: {0}")]
    Check(String),
}

impl From<WeldError> for crate::Error {
    fn from(e: WeldError) -> Self {
        crate::Error::InvalidArgument(e.to_string())
    }
}

/// Options of [`weld`]. Missing fields deserialize to their defaults.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct WeldOptions {
    /// Bridges (handles) to make, at most [`MAX_BRIDGES`] (default 1). Fewer are made when the
    /// shape has too few suitable contacts; 0 returns the input unchanged.
    pub bridges: usize,
    /// Geodesic radius of each cut disc in mean edge lengths (default 1.5; the benchmark uses
    /// 1.5, 2, 2.5, 3 for levels 1..4). Finite, `> 0`.
    pub disc_radius_edges: f64,
    /// Fraction of the gap closed by the pull (default 0.6), in `[0, 0.9]`.
    pub pull: f64,
    /// Smallest surface distance of a contact relative to the geodesic diameter (default 0.2).
    /// Finite, `≥ 0`.
    pub min_geodesic_rel: f64,
    /// Smallest surface distance of a contact relative to its gap (default 3). Finite, `≥ 0`.
    pub min_gap_ratio: f64,
    /// Largest gap of a contact in mean edge lengths (default 20). Finite, `> 0`.
    pub max_gap_edges: f64,
    /// Surface distance kept between the discs of two bridges, in mean edge lengths: endpoints
    /// of different bridges are more than `2 r + separation_edges · ē` apart (default 4).
    /// Finite, `≥ 0`.
    pub separation_edges: f64,
    /// Seed of the tie-break among contacts of nearly equal gap (default 0).
    pub seed: u64,
}

impl Default for WeldOptions {
    fn default() -> Self {
        Self {
            bridges: 1,
            disc_radius_edges: 1.5,
            pull: 0.6,
            min_geodesic_rel: 0.2,
            min_gap_ratio: 3.0,
            max_gap_edges: 20.0,
            separation_edges: 4.0,
            seed: 0,
        }
    }
}

/// One bridge made by [`weld`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BridgeReport {
    /// Contact endpoint (vertex index of the input; removed with its disc).
    pub a: u32,
    /// The other endpoint (vertex index of the input).
    pub b: u32,
    /// Euclidean gap `|a − b|` before the pull, in mesh units.
    pub gap: f64,
    /// The gap in mean edge lengths.
    pub gap_edges: f64,
    /// Surface (Dijkstra) distance between `a` and `b` in the input.
    pub geodesic: f64,
    /// `geodesic` over the geodesic diameter of the component.
    pub geodesic_rel: f64,
    /// `|a − b|` after the pull.
    pub pulled_gap: f64,
    /// Vertices of the boundary loop of the disc around `a`.
    pub loop_a: usize,
    /// Vertices of the boundary loop of the disc around `b`.
    pub loop_b: usize,
    /// Interpolated rings of the tube (0: the two loops are zipped directly).
    pub rings: usize,
    /// Triangles of the tube. The tubes' triangles are the last ones of the output, bridge
    /// after bridge; the kept input faces come first, in their input order.
    pub tube_faces: usize,
}

/// What [`weld`] found and did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WeldReport {
    /// Bridges asked for.
    pub requested: usize,
    /// Bridges made (`bridges.len()`).
    pub made: usize,
    /// Candidate contacts that passed the distance and facing tests.
    pub candidates: usize,
    /// Mean edge length ē of the input.
    pub mean_edge: f64,
    /// Largest geodesic diameter over the components (double-sweep Dijkstra).
    pub geodesic_diameter: f64,
    /// The bridges, in the order they were chosen.
    pub bridges: Vec<BridgeReport>,
    /// Invariants of the input.
    pub before: SurfaceStats,
    /// Invariants of the output.
    pub after: SurfaceStats,
}

/// Welds up to `opts.bridges` short tubes between surface points that touch in space (module
/// docs). Returns the welded mesh and a report; with no bridge made, the mesh is returned
/// unchanged.
///
/// # Errors
/// [`WeldError::InvalidOption`] for an option out of range, [`WeldError::Topology`] for a
/// non-manifold input, [`WeldError::Degenerate`] for an input without geometry and
/// [`WeldError::Check`] if the result fails its final check.
pub fn weld(mesh: &Mesh, opts: &WeldOptions) -> Result<(Mesh, WeldReport), WeldError> {
    validate(opts)?;
    let before = surface_stats(mesh)?;
    if mesh.faces.is_empty() {
        return Err(WeldError::Degenerate("the mesh has no faces".into()));
    }
    let g = Graph::build(mesh);
    if !(g.mean_edge > 0.0 && g.mean_edge.is_finite()) {
        return Err(WeldError::Degenerate(
            "mean edge length is not positive".into(),
        ));
    }
    let e = g.mean_edge;
    let r = opts.disc_radius_edges * e;
    let sep = 2.0 * r + opts.separation_edges * e;
    let mut scratch = Scratch::new(g.n);
    let (comp, diam) = components_and_diameters(&g, &mut scratch);
    let mut report = WeldReport {
        requested: opts.bridges,
        made: 0,
        candidates: 0,
        mean_edge: e,
        geodesic_diameter: diam.iter().copied().fold(0.0, f64::max),
        bridges: Vec::new(),
        before,
        after: before,
    };
    if opts.bridges == 0 {
        return Ok((mesh.clone(), report));
    }

    // 1. Candidates.
    let cands = candidates(mesh, &g, &comp, &diam, opts, sep, &mut scratch);
    report.candidates = cands.len();

    // 2.–3. Greedy choice with disc validation.
    let mut blocked = vec![false; g.n];
    let mut in_disc = vec![false; g.n];
    let mut chosen: Vec<Bridge> = Vec::new();
    for c in cands {
        if chosen.len() == opts.bridges {
            break;
        }
        if blocked[c.p as usize] || blocked[c.q as usize] {
            continue;
        }
        let Some(da) = disc(mesh, &g, c.p, r, &mut scratch) else {
            continue;
        };
        let Some(db) = disc(mesh, &g, c.q, r, &mut scratch) else {
            continue;
        };
        let (pp, qq) = (mesh.vertices[c.p as usize], mesh.vertices[c.q as usize]);
        let axis = sub(qq, pp).map(|x| x / c.gap);
        let p_ring: Vec<u32> = da.cycle.iter().rev().copied().collect();
        let (Some(pa), Some(qa)) = (
            angle_params(&mesh.vertices, &p_ring, pp, axis, g.orient),
            angle_params(&mesh.vertices, &db.cycle, qq, axis, g.orient),
        ) else {
            continue;
        };
        let (va, vb) = (da.region_vertices(mesh), db.region_vertices(mesh));
        if va.iter().chain(&vb).any(|&v| in_disc[v as usize]) || va.iter().any(|v| vb.contains(v)) {
            continue;
        }
        for &v in va.iter().chain(&vb) {
            in_disc[v as usize] = true;
        }
        scratch.run(&g, &[c.p, c.q], sep);
        for &v in &scratch.touched {
            if scratch.dist[v as usize] <= sep {
                blocked[v as usize] = true;
            }
        }
        chosen.push(Bridge {
            c,
            faces: [da.faces, db.faces],
            rings: [pa, qa],
        });
    }
    if chosen.is_empty() {
        return Ok((mesh.clone(), report));
    }

    // 4. Pull.
    let mut pos = mesh.vertices.clone();
    let mut disp = vec![[0.0f64; 3]; g.n];
    let mut wsum = vec![0.0f64; g.n];
    for Bridge { c, .. } in &chosen {
        let width = c.gap + 2.0 * e;
        let d = sub(mesh.vertices[c.q as usize], mesh.vertices[c.p as usize]);
        for (src, sign) in [(c.p, 1.0), (c.q, -1.0)] {
            scratch.run(&g, &[src], r + width);
            let k = sign * 0.5 * opts.pull;
            for &v in &scratch.touched {
                let dv = scratch.dist[v as usize];
                let t = ((dv - r) / width).clamp(0.0, 1.0);
                let w = 1.0 - t * t * (3.0 - 2.0 * t);
                if w > 0.0 {
                    wsum[v as usize] += w;
                    for i in 0..3 {
                        disp[v as usize][i] += w * k * d[i];
                    }
                }
            }
        }
    }
    for v in 0..g.n {
        let s = wsum[v].max(1.0);
        for i in 0..3 {
            pos[v][i] += disp[v][i] / s;
        }
    }

    // 5. Discs out, tubes in.
    let mut removed = vec![false; mesh.faces.len()];
    let mut faces: Vec<[u32; 3]> = Vec::new();
    for b in &chosen {
        for &f in b.faces.iter().flatten() {
            removed[f as usize] = true;
        }
    }
    for Bridge { c, rings, .. } in &chosen {
        let [(pr, fp), (qr, fq)] = rings;
        let d = sub(mesh.vertices[c.q as usize], mesh.vertices[c.p as usize]);
        let axis = d.map(|x| x / c.gap);
        let centre = pos[c.p as usize];
        let before_tube = faces.len();
        let n_rings = tube(&mut pos, (pr, fp), (qr, fq), axis, centre, e, &mut faces);
        let geo = {
            scratch.run(&g, &[c.p], f64::INFINITY);
            scratch.dist[c.q as usize]
        };
        let dm = diam[comp[c.p as usize] as usize];
        report.bridges.push(BridgeReport {
            a: c.p,
            b: c.q,
            gap: c.gap,
            gap_edges: c.gap / e,
            geodesic: geo,
            geodesic_rel: if dm > 0.0 { geo / dm } else { 0.0 },
            pulled_gap: norm(sub(pos[c.q as usize], pos[c.p as usize])),
            loop_a: pr.len(),
            loop_b: qr.len(),
            rings: n_rings,
            tube_faces: faces.len() - before_tube,
        });
    }
    report.made = report.bridges.len();
    let kept = mesh
        .faces
        .iter()
        .zip(&removed)
        .filter(|(_, &r)| !r)
        .map(|(f, _)| *f);
    let all: Vec<[u32; 3]> = kept.chain(faces).collect();
    let (mut out, _) = compact(&pos, all);
    out.repairs = mesh.repairs.clone();

    // Final check.
    let after = surface_stats(&out).map_err(|e| WeldError::Check(e.to_string()))?;
    let want_genus = before.genus.map(|g| g + report.made);
    if after.components != before.components
        || after.boundary_loops != before.boundary_loops
        || (before.genus.is_some() && after.genus != want_genus)
    {
        return Err(WeldError::Check(format!(
            "expected {} component(s), {} boundary loop(s), genus {:?}; got {}, {}, {:?}",
            before.components,
            before.boundary_loops,
            want_genus,
            after.components,
            after.boundary_loops,
            after.genus
        )));
    }
    let mean_area = out.area() / out.faces.len() as f64;
    if let Some(fi) = (0..out.faces.len())
        .find(|&fi| super::triangle_area(&out, &out.faces[fi]) <= 1e-10 * mean_area)
    {
        return Err(WeldError::Check(format!("face {fi} is degenerate")));
    }
    report.after = after;
    Ok((out, report))
}

fn validate(o: &WeldOptions) -> Result<(), WeldError> {
    let positive = [
        ("disc_radius_edges", o.disc_radius_edges),
        ("max_gap_edges", o.max_gap_edges),
    ];
    let non_negative = [
        ("min_geodesic_rel", o.min_geodesic_rel),
        ("min_gap_ratio", o.min_gap_ratio),
        ("separation_edges", o.separation_edges),
    ];
    let too_many = o.bridges > MAX_BRIDGES;
    let bad = (too_many.then(|| format!("bridges = {} > {MAX_BRIDGES}", o.bridges)))
        .into_iter()
        .chain(
            positive
                .iter()
                .filter(|(_, v)| !(v.is_finite() && *v > 0.0))
                .map(|(n, v)| format!("{n} = {v} must be finite and > 0")),
        )
        .chain(
            non_negative
                .iter()
                .filter(|(_, v)| !(v.is_finite() && *v >= 0.0))
                .map(|(n, v)| format!("{n} = {v} must be finite and >= 0")),
        )
        .chain(
            (!(0.0..=0.9).contains(&o.pull))
                .then(|| format!("pull = {} must be in [0, 0.9]", o.pull)),
        )
        .next();
    bad.map_or(Ok(()), |m| Err(WeldError::InvalidOption(m)))
}

// ---------------------------------------------------------------------------------------------
// Contacts

struct Cand {
    p: u32,
    q: u32,
    gap: f64,
    key: (u64, u64),
}

fn splitmix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// Candidate contacts, sorted in the order of the greedy choice.
fn candidates(
    mesh: &Mesh,
    g: &Graph,
    comp: &[u32],
    diam: &[f64],
    opts: &WeldOptions,
    sep: f64,
    s: &mut Scratch,
) -> Vec<Cand> {
    let e = g.mean_edge;
    let (max_gap, min_gap) = (opts.max_gap_edges * e, MIN_GAP_EDGES * e);
    let pts = &mesh.vertices;
    let cell = |p: [f64; 3]| p.map(|x| (x / max_gap).floor() as i64);
    let mut grid: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
    let usable = |v: usize| g.used[v] && norm(g.normal[v]) > 0.5;
    for v in 0..g.n {
        if usable(v) {
            grid.entry(cell(pts[v])).or_default().push(v as u32);
        }
    }
    let used_count = g.used.iter().filter(|&&u| u).count();
    let stride = used_count.div_ceil(MAX_SAMPLES).max(1);
    let offset = (opts.seed % stride as u64) as usize;
    let mut out = Vec::new();
    let mut near: Vec<(u32, f64)> = Vec::new();
    for p in 0..g.n {
        if !usable(p) || (p + offset) % stride != 0 {
            continue;
        }
        let (pp, np) = (pts[p], g.normal[p]);
        let c = cell(pp);
        near.clear();
        for o in 0..27i64 {
            let key = [c[0] + o % 3 - 1, c[1] + o / 3 % 3 - 1, c[2] + o / 9 - 1];
            for &q in grid.get(&key).map_or(&[][..], Vec::as_slice) {
                let qu = q as usize;
                let d = sub(pts[qu], pp);
                let gap = norm(d);
                if comp[qu] != comp[p] || qu == p || !(gap >= min_gap && gap <= max_gap) {
                    continue;
                }
                let nq = g.normal[qu];
                if dot(np, d) >= FACING * gap
                    && -dot(nq, d) >= FACING * gap
                    && dot(np, nq) <= -FACING
                {
                    near.push((q, gap));
                }
            }
        }
        if near.is_empty() {
            continue;
        }
        let base = (opts.min_geodesic_rel * diam[comp[p] as usize]).max(sep);
        let need = |gap: f64| base.max(opts.min_gap_ratio * gap);
        let limit = near.iter().map(|&(_, gap)| need(gap)).fold(0.0, f64::max);
        s.run(g, &[p as u32], limit);
        for &(q, gap) in &near {
            // Each unordered pair once: from its smaller endpoint when both are sampled.
            if (q as usize) < p && (q as usize + offset) % stride == 0 {
                continue;
            }
            if s.dist[q as usize] > need(gap) {
                let (a, b) = (p as u32, q);
                let (lo, hi) = (a.min(b) as u64, a.max(b) as u64);
                let tie = splitmix64(opts.seed ^ splitmix64((lo << 32) | hi));
                let bin = (gap / (GAP_BIN_EDGES * e)).floor() as u64;
                out.push(Cand {
                    p: a,
                    q: b,
                    gap,
                    key: (bin, tie),
                });
            }
        }
    }
    out.sort_by(|x, y| x.key.cmp(&y.key).then(x.p.cmp(&y.p)).then(x.q.cmp(&y.q)));
    out
}

// ---------------------------------------------------------------------------------------------
// Discs

/// A geodesic disc to cut: its faces and its boundary cycle, in the direction in which the
/// remaining faces traverse it.
struct Disc {
    faces: Vec<u32>,
    cycle: Vec<u32>,
}

impl Disc {
    fn region_vertices(&self, mesh: &Mesh) -> Vec<u32> {
        let mut v: Vec<u32> = self
            .faces
            .iter()
            .flat_map(|&f| mesh.faces[f as usize])
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    }
}

/// The disc of radius `r` around `centre` (module docs, step 3), or `None` when it is not a
/// disc bounded by one simple cycle away from the mesh boundary.
fn disc(mesh: &Mesh, g: &Graph, centre: u32, r: f64, s: &mut Scratch) -> Option<Disc> {
    s.run(g, &[centre], r);
    let inner: Vec<u32> = s
        .touched
        .iter()
        .copied()
        .filter(|&v| s.dist[v as usize] < r)
        .collect();
    if inner.iter().any(|&v| g.avoid[v as usize]) {
        return None;
    }
    let mut faces: Vec<u32> = inner.iter().flat_map(|&v| g.faces_of(v)).copied().collect();
    faces.sort_unstable();
    faces.dedup();
    let is_removed = |f: u32| faces.binary_search(&f).is_ok();
    let mut next: HashMap<u32, u32> = HashMap::new();
    let mut edges: HashSet<(u32, u32)> = HashSet::new();
    let mut verts: HashSet<u32> = HashSet::new();
    for &f in &faces {
        let t = mesh.faces[f as usize];
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            verts.insert(a);
            edges.insert((a.min(b), a.max(b)));
            let twin = *g.half.get(&(b, a))?;
            if !is_removed(twin) && next.insert(b, a).is_some() {
                return None; // the boundary passes twice through b
            }
        }
    }
    if verts.len() as i64 - edges.len() as i64 + faces.len() as i64 != 1 || next.len() < 3 {
        return None;
    }
    let start = *next.keys().min()?;
    let mut cycle = vec![start];
    let mut v = next[&start];
    while v != start {
        if cycle.len() > next.len() || g.avoid[v as usize] {
            return None;
        }
        cycle.push(v);
        v = *next.get(&v)?;
    }
    if cycle.len() != next.len() || g.avoid[start as usize] {
        return None;
    }
    Some(Disc { faces, cycle })
}
