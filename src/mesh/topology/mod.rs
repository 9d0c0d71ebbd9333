//! Surface topology of a prepared triangle mesh, short homology loops, and **handle cutting**
//! (topological noise removal): handles made by a short tube between two parts of a shape that
//! touch in space (a hand welded to a thigh by a scanner or a mesh fusion) are found and cut, while
//! genuine handles (a torus, a mug handle, a ring of joined arms) are left alone.
//!
//! # What is computed
//!
//! * [`surface_stats`]: vertices, edges, faces, connected components `c`, boundary loops `b`,
//!   Euler characteristic `χ = V − E + F` and, for an orientable manifold, the genus
//!   `g = (2c − χ − b) / 2` (summed over the components).
//! * [`short_homology_basis`]: `2g` loops of the mesh graph that generate the first homology
//!   group (over Z₂) of the surface **with every boundary loop capped** (so boundary curves are
//!   never reported as handles, only the handles themselves), greedily chosen short.
//! * [`cut_handles`]: repeatedly takes the shortest basis loop that qualifies as a *bridge*
//!   (see below), cuts the mesh along it (every vertex of the loop is duplicated, the faces on
//!   one side get the copies; optionally the faces touching the cut are removed so that the two
//!   new boundary curves do not coincide in space), and recomputes, until no loop qualifies or
//!   the surface has genus 0. Returns the cleaned mesh and a [`HandleCutReport`].
//!
//! # Method
//!
//! **Homology classes** (Z₂ "annotations", Erickson & Whittlesey 2005, §3; Dey, Fan & Wang
//! 2013, annotations): a spanning forest `T` of the primal graph, a spanning forest `C` of the dual
//! graph among the edges not in `T` (tree–cotree decomposition, Eppstein 2003), the capped
//! boundary loops being one extra dual node each. The `2g` edges in neither are the generators:
//! edge `xᵢ` gets the annotation bit `i`, tree edges `0`, and each cotree edge the XOR of the
//! other edges of its dual child (leaves first), so the XOR of the annotations around every face
//! (and every capped boundary) is 0. The class of any cycle is then the XOR of its edges'
//! annotations, a `2g`-bit vector.
//!
//! **Short loops** (greedy shortest homology basis, Erickson & Whittlesey 2005, *Greedy optimal
//! homotopy and homology generators*, SODA): for a root `r`, the shortest-path tree of `r`
//! (Dijkstra on edge lengths) and an edge `uv` not in it define the loop `σ(r, uv)` = tree path
//! `r → u`, edge `uv`, tree path `v → r`; stripped of the common prefix of the two tree paths
//! (it cancels in homology), it is a simple cycle through the paths' last common vertex, of
//! length `d(u) + |uv| + d(v) − 2 d(lca)`. E–W show that the shortest basis is the greedy choice
//! (by increasing length, keeping a loop when its class is independent of the classes kept)
//! among the `σ(r, e)` over **all** roots; that is `O(n² log n)`. Here the roots are bounded:
//! `roots` farthest-point samples (each Dijkstra also gives the next sample), then, for each loop
//! of that first basis, `refine_roots` vertices spread along it, and the greedy choice is made
//! again over all candidates. A basis loop through a root is found exactly; through any other
//! vertex, within the stripped stem. Cost `O((roots + refine_roots · 2g) · E log E)` per basis,
//! with `2g ≤ 128` (genus above 64 is refused).
//!
//! **Bridges.** A weld is a *short neck*: a tube whose circumference `L` (the tunnel loop) is
//! small compared with the shape (`L / √area`), and whose length is small compared with its
//! circumference, flaring into the body within about a tube radius on both sides. A genuine
//! handle is a long tube (a mug handle, an arm) or a ring (a torus), along which the loop stays
//! short. Both are measured on the loop `γ`: `L / √A`, and the **neck aspect** `(s₊ + s₋) / L`,
//! where on each side of the cut `s±` is the geodesic distance from `γ` at which the area swept
//! since `γ` first exceeds `growth · L · s` (a tube keeps area `≈ L · s`; a surface that flares
//! exceeds it), or the whole side when it never does (a ring). The **side aspect**
//! `min(s₊, s₋) / L` asks only that one side flare: a limb welded to the body (a hand to a thigh)
//! is a tube on the limb's side but opens into the body within a tube radius on the other, while
//! a genuine handle (a mug's, joined arms, a ring) runs for more than its circumference on both.
//! A loop is cut when `L / √A ≤ max_loop_rel` and (`aspect ≤ max_neck_aspect` or
//! `side aspect ≤ max_side_aspect`), or when `L / √A ≤ free_loop_rel` whatever its aspects; the
//! thresholds are options (their defaults and how they were chosen are in `docs/quality.md`,
//! "Handle cutting" and §13).
//!
//! **Stubs.** Cutting a weld at its tunnel loop leaves the two halves of its tube as stubs on
//! the parts it joined. On each side, the stub ends at the first distance from `γ` where the
//! level curves around it have grown to 1.5 `L` (a tube keeps them at about `L`; where it opens
//! into a surface they lengthen at once). With `stub_aspect > 0`, a side whose stub is at most
//! `stub_aspect · L` long is removed with the cut, up to that point: the cut then leaves a hole
//! where the weld began instead of a protruding stub. A side whose level curves never lengthen
//! (a limb, a ring) is never removed.
//!
//! Everything is deterministic (no randomness; ties broken by indices). Requires a manifold mesh
//! (every edge in at most two faces): [`TopologyError::NonManifoldEdge`] otherwise. A loop through
//! a boundary vertex, or one whose two sides cannot be told apart (a one-sided loop of a
//! non-orientable surface), is never cut.

use super::buckets::Buckets;
use super::{cross, norm, sub, Mesh};
use serde::{Deserialize, Serialize};
use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

/// Why a topology computation was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TopologyError {
    /// A face refers to a vertex that does not exist.
    #[error("face {face} refers to vertex {vertex}, but the mesh has {vertices} vertices")]
    BadIndex {
        /// Face index.
        face: usize,
        /// Offending vertex index.
        vertex: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// A face repeats a vertex.
    #[error("face {0} is degenerate (repeated vertex)")]
    DegenerateFace(usize),
    /// An edge has more than two incident faces.
    #[error("edge ({0}, {1}) has more than two incident faces")]
    NonManifoldEdge(u32, u32),
    /// The capped surface has more handles than the Z₂ classes can hold (genus > 64).
    #[error("genus {0} is above the supported 64")]
    GenusTooLarge(usize),
    /// An option is out of range.
    #[error("invalid option: {0}")]
    InvalidOption(String),
}

impl From<TopologyError> for crate::Error {
    fn from(e: TopologyError) -> Self {
        crate::Error::InvalidArgument(e.to_string())
    }
}

/// Counts and derived invariants of a triangle mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SurfaceStats {
    /// Vertices referenced by at least one face.
    pub vertices: usize,
    /// Distinct edges.
    pub edges: usize,
    /// Faces.
    pub faces: usize,
    /// Connected components (faces sharing an edge or a vertex).
    pub components: usize,
    /// Closed boundary curves (cycles of edges with one incident face).
    pub boundary_loops: usize,
    /// `V − E + F`.
    pub euler_characteristic: i64,
    /// `(2c − χ − b) / 2` summed over components: the number of handles of an orientable
    /// surface (`None` when `2c − χ − b` is odd or negative: non-orientable or not a surface).
    pub genus: Option<usize>,
}

/// One loop of a homology basis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HomologyLoop {
    /// Vertices of the simple cycle, in order (the last connects to the first).
    pub vertices: Vec<u32>,
    /// Length (sum of edge lengths).
    pub length: f64,
}

/// Options of [`cut_handles`]. Missing fields deserialize to their defaults.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct HandleCutOptions {
    /// A loop qualifies only when `length / sqrt(area) ≤ max_loop_rel`.
    pub max_loop_rel: f64,
    /// A loop (within `max_loop_rel`) qualifies when its neck aspect (module docs) is
    /// `≤ max_neck_aspect`, or its side aspect passes `max_side_aspect`, or it is shorter than
    /// `free_loop_rel`.
    pub max_neck_aspect: f64,
    /// A loop (within `max_loop_rel`) also qualifies when its **side aspect** `min(s₊, s₋) / L`
    /// is `≤ max_side_aspect`: the surface flares within that much of `L` on at least one side
    /// (module docs). 0 (the default) turns the test off: only the two-sided test. Omitted from
    /// the JSON at 0, so the key of a spec without it is unchanged.
    #[serde(skip_serializing_if = "is_zero")]
    pub max_side_aspect: f64,
    /// When a loop is cut (and `remove_band` is set), each side whose stub (the tube up to
    /// where the surface opens, module docs "Stubs") is at most `stub_aspect · L` long is
    /// removed too.
    /// 0 (the default) keeps both sides whole. Omitted from the JSON at 0.
    #[serde(skip_serializing_if = "is_zero")]
    pub stub_aspect: f64,
    /// A loop with `length / sqrt(area) ≤ free_loop_rel` qualifies whatever its neck aspect
    /// (default 0: none). Two tiers: loops this short are cut as welds, longer ones up to
    /// `max_loop_rel` only when they are also short necks (`docs/quality.md` §9 for the values).
    pub free_loop_rel: f64,
    /// Area growth factor that ends a neck (module docs); `> 1`.
    pub growth: f64,
    /// Farthest-point roots of the first basis (≥ 1).
    pub roots: usize,
    /// Extra roots per loop of the first basis, spread along it.
    pub refine_roots: usize,
    /// At most this many cuts.
    pub max_cuts: usize,
    /// Remove the faces that touch the cut (both sides), so that the two new boundary curves are
    /// one ring apart instead of coincident (a file writer/reader that welds coincident vertices
    /// would otherwise undo the cut).
    pub remove_band: bool,
}

impl HandleCutOptions {
    /// Checks the options: `growth > 1` and finite, every threshold `≥ 0` (not NaN).
    ///
    /// # Errors
    /// [`TopologyError::InvalidOption`] naming the values.
    pub fn validate(&self) -> Result<(), TopologyError> {
        let valid = self.growth > 1.0
            && self.growth.is_finite()
            && self.max_loop_rel >= 0.0
            && self.max_neck_aspect >= 0.0
            && self.max_side_aspect >= 0.0
            && self.stub_aspect >= 0.0
            && self.free_loop_rel >= 0.0;
        if valid {
            Ok(())
        } else {
            Err(TopologyError::InvalidOption(format!(
                "growth must be > 1 and the thresholds >= 0, got growth {}, max_loop_rel {}, \
                 max_neck_aspect {}, max_side_aspect {}, stub_aspect {}, free_loop_rel {}",
                self.growth,
                self.max_loop_rel,
                self.max_neck_aspect,
                self.max_side_aspect,
                self.stub_aspect,
                self.free_loop_rel
            )))
        }
    }
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl Default for HandleCutOptions {
    fn default() -> Self {
        Self {
            max_loop_rel: 0.5,
            max_neck_aspect: 1.5,
            max_side_aspect: 0.0,
            stub_aspect: 0.0,
            free_loop_rel: 0.0,
            growth: 2.0,
            roots: 8,
            refine_roots: 3,
            max_cuts: 16,
            remove_band: true,
        }
    }
}

/// A basis loop examined by [`cut_handles`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LoopReport {
    /// Cut round (0 = on the input mesh).
    pub round: usize,
    /// Length in mesh units.
    pub length: f64,
    /// `length / sqrt(area)` (area of the mesh of that round).
    pub length_rel: f64,
    /// Neck aspect `(s₊ + s₋) / length` (module docs); `None` when not measured (the loop touches
    /// the boundary or is one-sided).
    pub neck_aspect: Option<f64>,
    /// Side aspect `min(s₊, s₋) / length`; `None` when not measured.
    pub side_aspect: Option<f64>,
    /// Shortest distance between the two sides of the cut over the rest of the surface, relative
    /// to `length` (the handle this loop goes around, seen from the loop); `None` when not measured.
    pub handle_rel: Option<f64>,
    /// Number of vertices of the loop.
    pub vertices: usize,
    /// Whether this loop was cut.
    pub cut: bool,
}

/// What [`cut_handles`] found and did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HandleCutReport {
    /// Invariants of the input.
    pub before: SurfaceStats,
    /// Invariants of the output.
    pub after: SurfaceStats,
    /// Every loop examined, in order (each round lists the basis loops by increasing length up
    /// to and including the one cut).
    pub loops: Vec<LoopReport>,
    /// Number of cuts made.
    pub cuts: usize,
    /// Output area over input area.
    pub area_kept: f64,
}

// ---------------------------------------------------------------------------------------------
// Connectivity

const NONE: u32 = u32::MAX;

/// Edge-based connectivity of a manifold triangle mesh.
struct Topo {
    n: usize,
    /// Edges as (low, high) vertex pairs.
    edges: Vec<[u32; 2]>,
    /// The (one or two) faces of each edge; `NONE` when absent.
    edge_faces: Vec<[u32; 2]>,
    /// The three edges of each face (edge `k` is opposite vertex `k`... not assumed: just the
    /// three edges).
    face_edges: Vec<[u32; 3]>,
    /// Vertex → (neighbour, edge).
    adj: Buckets<(u32, u32)>,
    /// Edge lengths.
    len: Vec<f64>,
}

impl Topo {
    fn build(mesh: &Mesh) -> Result<Self, TopologyError> {
        let n = mesh.vertices.len();
        let mut map: HashMap<(u32, u32), u32> = HashMap::with_capacity(mesh.faces.len() * 2);
        let mut edges: Vec<[u32; 2]> = Vec::with_capacity(mesh.faces.len() * 3 / 2 + 4);
        let mut edge_faces: Vec<[u32; 2]> = Vec::with_capacity(edges.capacity());
        let mut face_edges = Vec::with_capacity(mesh.faces.len());
        for (fi, f) in mesh.faces.iter().enumerate() {
            for &v in f {
                if v as usize >= n {
                    return Err(TopologyError::BadIndex {
                        face: fi,
                        vertex: v,
                        vertices: n,
                    });
                }
            }
            if f[0] == f[1] || f[1] == f[2] || f[0] == f[2] {
                return Err(TopologyError::DegenerateFace(fi));
            }
            let mut fe = [0u32; 3];
            for k in 0..3 {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                let key = (a.min(b), a.max(b));
                let id = *map.entry(key).or_insert_with(|| {
                    edges.push([key.0, key.1]);
                    edge_faces.push([NONE, NONE]);
                    (edges.len() - 1) as u32
                });
                let ef = &mut edge_faces[id as usize];
                if ef[0] == NONE {
                    ef[0] = fi as u32;
                } else if ef[1] == NONE {
                    ef[1] = fi as u32;
                } else {
                    return Err(TopologyError::NonManifoldEdge(key.0, key.1));
                }
                fe[k] = id;
            }
            face_edges.push(fe);
        }
        let adj = Buckets::new(
            n,
            edges
                .iter()
                .enumerate()
                .flat_map(|(id, e)| [(e[0], (e[1], id as u32)), (e[1], (e[0], id as u32))]),
        );
        let len = edges
            .iter()
            .map(|e| {
                norm(sub(
                    mesh.vertices[e[0] as usize],
                    mesh.vertices[e[1] as usize],
                ))
            })
            .collect();
        Ok(Self {
            n,
            edges,
            edge_faces,
            face_edges,
            adj,
            len,
        })
    }

    fn nbrs(&self, v: u32) -> &[(u32, u32)] {
        self.adj.get(v as usize)
    }

    fn is_boundary_edge(&self, e: usize) -> bool {
        self.edge_faces[e][1] == NONE
    }

    /// Boundary loops: each boundary edge gets the id of its loop (`NONE` for interior edges).
    /// Loops are the connected components of the boundary-edge graph (a chain through a
    /// non-manifold vertex joins them; prepared meshes have none).
    fn boundary_loops(&self) -> (Vec<u32>, usize) {
        let mut id = vec![NONE; self.edges.len()];
        let mut count = 0usize;
        let mut stack = Vec::new();
        for e0 in 0..self.edges.len() {
            if !self.is_boundary_edge(e0) || id[e0] != NONE {
                continue;
            }
            id[e0] = count as u32;
            stack.push(e0);
            while let Some(e) = stack.pop() {
                for &v in &self.edges[e] {
                    for &(_, e2) in self.nbrs(v) {
                        let e2 = e2 as usize;
                        if self.is_boundary_edge(e2) && id[e2] == NONE {
                            id[e2] = count as u32;
                            stack.push(e2);
                        }
                    }
                }
            }
            count += 1;
        }
        (id, count)
    }

    fn boundary_vertex_flags(&self) -> Vec<bool> {
        let mut b = vec![false; self.n];
        for (e, v) in self.edges.iter().enumerate() {
            if self.is_boundary_edge(e) {
                b[v[0] as usize] = true;
                b[v[1] as usize] = true;
            }
        }
        b
    }
}

/// A Dijkstra heap entry `(distance, vertex)`, ordered as a min-heap on distance (ties by vertex
/// index) in a `BinaryHeap`; shared with [`crate::mesh::weld`].
#[derive(PartialEq)]
pub(crate) struct HeapItem(pub(crate) f64, pub(crate) u32);
impl Eq for HeapItem {}
impl PartialOrd for HeapItem {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for HeapItem {
    fn cmp(&self, other: &Self) -> Ordering {
        // Min-heap on distance, ties by vertex index.
        other
            .0
            .total_cmp(&self.0)
            .then_with(|| other.1.cmp(&self.1))
    }
}

/// Multi-source Dijkstra: distances and parent edges (`NONE` at sources / unreached).
fn dijkstra(t: &Topo, sources: &[u32]) -> (Vec<f64>, Vec<u32>) {
    let mut dist = vec![f64::INFINITY; t.n];
    let mut parent = vec![NONE; t.n];
    let mut heap = BinaryHeap::new();
    for &s in sources {
        dist[s as usize] = 0.0;
        heap.push(HeapItem(0.0, s));
    }
    while let Some(HeapItem(d, v)) = heap.pop() {
        if d > dist[v as usize] {
            continue;
        }
        for &(w, e) in t.nbrs(v) {
            let nd = d + t.len[e as usize];
            if nd < dist[w as usize] {
                dist[w as usize] = nd;
                parent[w as usize] = e;
                heap.push(HeapItem(nd, w));
            }
        }
    }
    (dist, parent)
}

fn other(t: &Topo, e: u32, v: u32) -> u32 {
    let [a, b] = t.edges[e as usize];
    if a == v {
        b
    } else {
        a
    }
}

/// Connected components over faces sharing a vertex; returns the number of components that have
/// at least one face and, per vertex, its component (`NONE` for unreferenced vertices).
fn components(mesh: &Mesh, t: &Topo) -> (usize, Vec<u32>) {
    let mut used = vec![false; t.n];
    for f in &mesh.faces {
        for &v in f {
            used[v as usize] = true;
        }
    }
    let mut comp = vec![NONE; t.n];
    let mut c = 0u32;
    let mut stack = Vec::new();
    for s in 0..t.n {
        if !used[s] || comp[s] != NONE {
            continue;
        }
        comp[s] = c;
        stack.push(s as u32);
        while let Some(v) = stack.pop() {
            for &(w, _) in t.nbrs(v) {
                if comp[w as usize] == NONE {
                    comp[w as usize] = c;
                    stack.push(w);
                }
            }
        }
        c += 1;
    }
    (c as usize, comp)
}

fn stats_of(mesh: &Mesh, t: &Topo) -> SurfaceStats {
    let (c, _) = components(mesh, t);
    let (_, b) = t.boundary_loops();
    let mut used = vec![false; t.n];
    for f in &mesh.faces {
        for &v in f {
            used[v as usize] = true;
        }
    }
    let v = used.iter().filter(|&&u| u).count();
    let chi = v as i64 - t.edges.len() as i64 + mesh.faces.len() as i64;
    let twice = 2 * c as i64 - chi - b as i64;
    let genus = (twice >= 0 && twice % 2 == 0).then_some((twice / 2) as usize);
    SurfaceStats {
        vertices: v,
        edges: t.edges.len(),
        faces: mesh.faces.len(),
        components: c,
        boundary_loops: b,
        euler_characteristic: chi,
        genus,
    }
}

/// Vertices, edges, faces, components, boundary loops, Euler characteristic and genus.
///
/// # Errors
/// [`TopologyError`] for a bad index, a degenerate face or a non-manifold edge.
pub fn surface_stats(mesh: &Mesh) -> Result<SurfaceStats, TopologyError> {
    let t = Topo::build(mesh)?;
    Ok(stats_of(mesh, &t))
}

mod cut;
mod homology;

pub(crate) use cut::compact;
pub use cut::{cut_handles, cut_handles_with_map};
pub use homology::short_homology_basis;

#[cfg(test)]
mod tests {
    use super::homology::annotations;
    use super::*;
    use crate::mesh::generate;

    #[test]
    fn annotations_vanish_on_faces() {
        let m = generate::torus(2.0, 0.5, 16, 10);
        let t = Topo::build(&m).unwrap();
        let (ann, rank) = annotations(&m, &t).unwrap();
        assert_eq!(rank, 2);
        for fe in &t.face_edges {
            assert_eq!(
                ann[fe[0] as usize] ^ ann[fe[1] as usize] ^ ann[fe[2] as usize],
                0
            );
        }
    }

    #[test]
    fn torus_basis_lengths() {
        // R = 2, r = 0.5: meridian ≈ 2π·0.5 = 3.14 (polygon: 10·2·0.5·sin(π/10) = 3.09),
        // shortest longitude = inner equator 2π·1.5 ≈ 9.42.
        let m = generate::torus(2.0, 0.5, 40, 10);
        let b = short_homology_basis(&m, 8, 3).unwrap();
        assert_eq!(b.len(), 2);
        assert!((b[0].length - 3.09).abs() < 0.05, "{}", b[0].length);
        assert!(b[1].length > 9.0 && b[1].length < 9.6, "{}", b[1].length);
    }
}
