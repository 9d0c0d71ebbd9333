//! Mesh preparation: cleaning a raw triangle soup before the Laplace–Beltrami spectrum is
//! computed.
//!
//! [`prepare`] runs these steps, in this order:
//!
//! 1. **Validation.** A non-finite coordinate fails with [`Error::NonFinite`] (first offending
//!    vertex); a face index out of range fails with [`Error::InvalidArgument`]; a mesh without
//!    faces fails with [`Error::EmptyMesh`].
//! 2. **Welding** (see [`PrepareOptions::weld_tolerance`]). Every input vertex is mapped to a
//!    cluster; faces are re-indexed to cluster representatives.
//! 3. **Degenerate faces** are dropped: a face with a repeated vertex index after welding, or
//!    whose area is exactly 0 or `≤ degenerate_area_ratio × mean face area` (the mean over the
//!    faces without a repeated index). Then **exact duplicate faces** (same vertex *set*, either
//!    orientation) are dropped, keeping the first occurrence in face order. Both are counted.
//! 4. **Connected components** over faces sharing a vertex (union–find), measured by area, are
//!    kept according to [`ComponentPolicy`]; the dropped area fraction is reported.
//!    If the kept components hold less than [`PrepareOptions::min_area_kept`] of that area, the
//!    mesh is refused ([`Error::Degenerate`], code `mesh.area_kept`): a shape of which most of
//!    the surface was thrown away (600 disconnected triangles of which one is kept) is not the
//!    shape that was sent.
//! 5. **Compaction.** Vertices referenced by no kept face are dropped; the kept ones stay in the
//!    relative order of their first input index. Fewer than [`PrepareOptions::min_vertices`]
//!    vertices or [`PrepareOptions::min_faces`] triangles left is refused (`mesh.too_few_vertices`,
//!    `mesh.too_few_faces`): one triangle, or 500 copies of it, has no spectrum worth storing.
//!    5′. **Orientation.** Faces are flipped so that two faces sharing an edge traverse it in
//!    opposite directions; per patch the orientation of the larger area is kept
//!    (`reoriented_faces` counts the flips). Capping reads the boundary's direction: a hole next
//!    to a flipped face was otherwise skipped.
//!    5″. **Simplification** (optional, [`PrepareOptions::max_vertices`]): a kept surface with
//!    more vertices than the budget is simplified to it ([`crate::mesh::decimate`]) and
//!    prepared again from step 3 (`decimated` in the report).
//!    5-. **Smoothing** (optional, [`PrepareOptions::smooth`]): Taubin's low-pass filter
//!    ([`crate::mesh::smooth`]) removes noise at the scale of the edges before the steps that
//!    read the geometry; the report gives the step pairs taken (`smooth_steps`).
//!    5a. **Boundary capping** (optional, [`PrepareOptions::cap_boundaries`]): boundary loops
//!    up to a length bound closed by caps ([`crate::mesh::cap`]). 5b. **Handle cutting** (optional,
//!    [`PrepareOptions::cut_handles`]).
//! 6. **Topology report** (never an error): boundary edges and loops, non-manifold edges,
//!    inconsistently oriented edges, Euler characteristic `V − E + F`.
//! 7. **Area normalisation** (optional, default on): the area-weighted centroid of the surface is
//!    moved to the origin and coordinates are multiplied by `1/sqrt(area)`, so the total area is 1.
//!
//! Everything is deterministic and independent of the order of the input vertices (up to the
//! corresponding permutation of the output). Cost is `O(n log n)` at worst except for tolerance
//! welding, which is expected `O(n)` but quadratic in the size of a cluster of vertices that all
//! fall into neighbouring grid cells.

use super::cap::{cap_boundaries, CapOptions, CapStats};
use super::decimate::{decimate, DecimateSummary};
use super::smooth::{taubin_counted, SmoothOptions};
use super::topology::{cut_handles_with_map, HandleCutOptions};
use super::{cross, norm, sub, Mesh};
use crate::error::DegenerateKind;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

mod edges;
mod orient;
mod welding;

use edges::{analyse_edges, duplicate_faces};
use welding::{weld_exact, weld_tolerance, UnionFind};

/// Which connected components [`prepare`] keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ComponentPolicy {
    /// Keep only the component of largest surface area (the first one in face order on an exact
    /// tie).
    #[default]
    Largest,
    /// Keep every component.
    All,
}

/// Options of [`prepare`]. Missing fields deserialize to their defaults.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PrepareOptions {
    /// `None` (default): weld only *exactly* coincident vertices (bitwise-equal coordinates, with
    /// `-0.0 == 0.0`), so no two distinct points are ever merged. `Some(eps)`: additionally merge
    /// vertices whose distance is `≤ eps × d`, where `d` is the diagonal of the axis-aligned
    /// bounding box of all input vertices (so `eps` is **relative**, scale-invariant). Merging is
    /// transitive (clusters are the connected components of the "closer than" relation), found
    /// with a spatial hash grid. A cluster takes the position of its lexicographically smallest
    /// member. `eps` must be finite and `≥ 0`; `Some(0.0)` is the same as `None`.
    pub weld_tolerance: Option<f64>,
    /// Which connected components to keep (default [`ComponentPolicy::Largest`]).
    pub components: ComponentPolicy,
    /// Scale to unit total area about the area-weighted centroid, which is moved to the origin
    /// (default `true`). When `false` coordinates are left untouched.
    pub normalize_area: bool,
    /// A face is degenerate when its area is exactly 0 or `≤ degenerate_area_ratio × mean face
    /// area` (default `1e-14`). Must be finite and `≥ 0`.
    pub degenerate_area_ratio: f64,
    /// Fewest vertices the prepared mesh may have (default 4, a tetrahedron; `0` disables).
    pub min_vertices: usize,
    /// Fewest triangles the prepared mesh may have (default 4, a tetrahedron; `0` disables).
    pub min_faces: usize,
    /// Smallest fraction of the area of the non-degenerate, de-duplicated input that the kept
    /// components must hold (default `0.5`: the kept part is most of the surface; `0` disables).
    /// Only [`ComponentPolicy::Largest`] can drop area. Must be in `[0, 1]`.
    pub min_area_kept: f64,
    /// Optional **handle cutting** (topological noise removal, step 5b): short handles that
    /// qualify as welded bridges under these options are cut by
    /// [`crate::mesh::topology::cut_handles`] before the spectrum is computed. `None` (default):
    /// no cutting. Omitted from the JSON when `None`, so the options' serialisation (and every
    /// cache key derived from it) is unchanged for preparations without it; with it, every key
    /// changes and signatures are recomputed from the originals. `remove_band` must be `true`
    /// (welding would otherwise undo a bare split on the next read).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cut_handles: Option<HandleCutOptions>,
    /// Optional **boundary capping** (step 5a, [`crate::mesh::cap`]): every boundary loop of
    /// the kept surface not longer than [`CapOptions::max_length`] `· sqrt(area)` is closed by
    /// a cap before handle cutting and normalisation, so a shape with holes or a part cut away
    /// is analysed as a closed surface (the loops handle cutting opens are not capped).
    /// Default `None`; omitted from the JSON when `None`, so the keys of preparations without
    /// it are unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cap_boundaries: Option<CapOptions>,
    /// Optional **smoothing** (step 5-, [`crate::mesh::smooth::taubin`]) of the kept surface
    /// before capping, handle cutting and normalisation. Default `None`; omitted from the JSON
    /// when `None`, so the keys of preparations without it are unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smooth: Option<SmoothOptions>,
    /// Optional **vertex budget** (step 5″, [`crate::mesh::decimate`]): a kept surface with
    /// more vertices than this is simplified to at most this many (quadric edge collapses that
    /// keep its topology) before smoothing, capping, handle cutting and normalisation, so the
    /// cost of its spectrum is bounded. Default `None` (every mesh at full resolution); omitted
    /// from the JSON when `None`, so the keys of preparations without it are unchanged. Must
    /// be at least [`MIN_VERTEX_BUDGET`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_vertices: Option<usize>,
}

/// The smallest vertex budget [`PrepareOptions::max_vertices`] accepts: the signatures read
/// about 100 eigenpairs, which a few hundred vertices cannot resolve.
pub const MIN_VERTEX_BUDGET: usize = 1000;

impl Default for PrepareOptions {
    fn default() -> Self {
        Self {
            weld_tolerance: None,
            components: ComponentPolicy::Largest,
            normalize_area: true,
            degenerate_area_ratio: 1e-14,
            min_vertices: 4,
            min_faces: 4,
            min_area_kept: 0.5,
            cut_handles: None,
            cap_boundaries: None,
            smooth: None,
            max_vertices: None,
        }
    }
}

/// What the handle-cutting step (5b) of [`prepare`] did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HandleCutSummary {
    /// Genus of the compacted mesh before cutting (`None`: not an orientable surface).
    pub genus_before: Option<usize>,
    /// Genus after cutting (and after the components were selected again).
    pub genus_after: Option<usize>,
    /// Handles cut.
    pub cuts: usize,
    /// Area after cutting over area before (the removed bands and any detached component).
    pub area_kept: f64,
    /// Why the step did not run (a non-manifold edge, genus above 64); the mesh is then prepared
    /// without cutting.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
    /// Time of the step in milliseconds.
    pub ms: f64,
}

/// What [`prepare`] did and found. Counts satisfy
/// `vertices_in = vertices_out + welded_vertices + unreferenced_vertices` and
/// `faces_in = faces_out + degenerate_faces + duplicate_faces + component_faces_dropped`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PrepareReport {
    /// Number of input vertices.
    pub vertices_in: usize,
    /// Number of input faces.
    pub faces_in: usize,
    /// Number of output vertices.
    pub vertices_out: usize,
    /// Number of output faces.
    pub faces_out: usize,
    /// Input vertices merged into another vertex (input vertices minus distinct clusters).
    pub welded_vertices: usize,
    /// Faces dropped for a repeated vertex index (after welding) or a (near-)zero area.
    pub degenerate_faces: usize,
    /// Non-degenerate faces dropped because an earlier face has the same vertex set.
    pub duplicate_faces: usize,
    /// Faces dropped with a component not kept by the [`ComponentPolicy`].
    pub component_faces_dropped: usize,
    /// Welded vertices used by no output face (isolated, only in dropped faces, or in a dropped
    /// component).
    pub unreferenced_vertices: usize,
    /// Connected components (faces sharing a vertex) before the policy is applied.
    pub components: usize,
    /// Components kept.
    pub components_kept: usize,
    /// Area of the dropped components over the area of all components (0 when all are kept).
    pub dropped_area_fraction: f64,
    /// Edges with exactly one incident face.
    pub boundary_edges: usize,
    /// Boundary curves: closed boundary cycles, plus open boundary chains (these only occur
    /// next to non-manifold edges or vertices, where the decomposition is a convention).
    pub boundary_loops: usize,
    /// Edges with more than two incident faces.
    pub nonmanifold_edges: usize,
    /// Edges with exactly two incident faces that traverse it in the same direction, in the
    /// output: after step 5′ only those of a non-orientable surface (a Möbius strip).
    pub inconsistent_orientation_edges: usize,
    /// Faces flipped by step 5′ so that faces sharing an edge traverse it in opposite
    /// directions (per patch, the orientation of the larger area is kept). Absent from reports
    /// stored before the step existed (read as 0).
    #[serde(default)]
    pub reoriented_faces: usize,
    /// `V − E + F` of the output.
    pub euler_characteristic: i64,
    /// Total area of the output before normalisation.
    pub original_area: f64,
    /// Factor applied to the (centred) coordinates: `1/sqrt(original_area)` when normalising,
    /// else 1.
    pub scale_factor: f64,
    /// What a lenient read repaired in the file (see `ReadLimits::lenient`), one sentence each;
    /// absent when nothing was.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub read_repairs: Vec<String>,
    /// The handle-cutting step, when [`PrepareOptions::cut_handles`] asks for it. When handles
    /// were cut, the cleaning counts (`vertices_in` … `dropped_area_fraction`) describe the input
    /// before cutting and the rest the output; the count identities above then do not hold.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub handle_cut: Option<HandleCutSummary>,
    /// The capping step, when [`PrepareOptions::cap_boundaries`] asks for it (loops capped,
    /// vertices and faces added; the topology and output counts describe the capped mesh).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub capped: Option<CapStats>,
    /// Step pairs the smoothing took, when [`PrepareOptions::smooth`] asks for it (its `steps`,
    /// or more with `until_settled`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smooth_steps: Option<usize>,
    /// The simplification step, when the kept surface had more vertices than
    /// [`PrepareOptions::max_vertices`]. The cleaning counts (`vertices_in` …
    /// `dropped_area_fraction`) then describe the input before it and the rest the output;
    /// the vertices it removed are counted here only, so the count identities above do not
    /// hold.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decimated: Option<DecimateSummary>,
}

/// Cleans `mesh` (see the [module documentation](crate::mesh::prepare)) and reports what was done.
///
/// # Errors
/// [`Error::NonFinite`], [`Error::InvalidArgument`] (bad index or option, or an area that
/// overflows), [`Error::EmptyMesh`] (no faces, or nothing left after cleaning).
pub fn prepare(mesh: &Mesh, opts: &PrepareOptions) -> Result<(Mesh, PrepareReport)> {
    prepare_with_map(mesh, opts).map(|(m, r, _)| (m, r))
}

/// Like [`prepare`], also returning for each input vertex its index in the output mesh (`None`
/// when the vertex, or the cluster it was welded into, was dropped).
///
/// # Errors
/// As [`prepare`].
pub fn prepare_with_map(
    mesh: &Mesh,
    opts: &PrepareOptions,
) -> Result<(Mesh, PrepareReport, Vec<Option<u32>>)> {
    validate_options(opts)?;
    let n = mesh.vertices.len();
    if n > u32::MAX as usize {
        return Err(Error::InvalidArgument(format!("too many vertices: {n}")));
    }
    if let Some(i) = mesh
        .vertices
        .iter()
        .position(|v| !v.iter().all(|c| c.is_finite()))
    {
        return Err(Error::NonFinite { vertex: i });
    }
    for (fi, f) in mesh.faces.iter().enumerate() {
        if let Some(&i) = f.iter().find(|&&i| i as usize >= n) {
            return Err(Error::InvalidArgument(format!(
                "face {fi} refers to vertex {i}, but the mesh has {n} vertices"
            )));
        }
    }
    if mesh.faces.is_empty() {
        return Err(Error::EmptyMesh("the input has no faces".into()));
    }

    // 2. Welding: cluster[i] = smallest input index of i's cluster; pos[c] = cluster position.
    let (cluster, source) = match opts.weld_tolerance {
        Some(eps) if eps > 0.0 => weld_tolerance(&mesh.vertices, eps),
        _ => weld_exact(&mesh.vertices),
    };
    let clusters = cluster
        .iter()
        .enumerate()
        .filter(|&(i, &c)| c as usize == i)
        .count();
    let welded_vertices = n - clusters;
    let pos = |c: u32| mesh.vertices[source[c as usize] as usize];

    // 3. Degenerate faces.
    let mut faces: Vec<[u32; 3]> = Vec::with_capacity(mesh.faces.len());
    let mut areas: Vec<f64> = Vec::with_capacity(mesh.faces.len());
    for f in &mesh.faces {
        let w = f.map(|i| cluster[i as usize]);
        if w[0] == w[1] || w[1] == w[2] || w[0] == w[2] {
            continue;
        }
        let (a, b, c) = (pos(w[0]), pos(w[1]), pos(w[2]));
        let area = 0.5 * norm(cross(sub(b, a), sub(c, a)));
        if !area.is_finite() {
            return Err(Error::InvalidArgument(
                "face area overflows: coordinates too large".into(),
            ));
        }
        faces.push(w);
        areas.push(area);
    }
    let mut degenerate_faces = mesh.faces.len() - faces.len();
    if !faces.is_empty() {
        let mean = areas.iter().sum::<f64>() / areas.len() as f64;
        let threshold = opts.degenerate_area_ratio * mean;
        let mut k = 0;
        for j in 0..faces.len() {
            if areas[j] > 0.0 && areas[j] > threshold {
                faces[k] = faces[j];
                areas[k] = areas[j];
                k += 1;
            }
        }
        degenerate_faces += faces.len() - k;
        faces.truncate(k);
        areas.truncate(k);
    }
    if faces.is_empty() {
        return Err(Error::EmptyMesh(format!(
            "all {} faces are degenerate (repeated vertex or zero area)",
            mesh.faces.len()
        )));
    }

    // Exact duplicate faces (same vertex set).
    let dup = duplicate_faces(n, &faces);
    let duplicate_faces = dup.iter().filter(|&&d| d).count();
    if duplicate_faces > 0 {
        let mut k = 0;
        for j in 0..faces.len() {
            if !dup[j] {
                faces[k] = faces[j];
                areas[k] = areas[j];
                k += 1;
            }
        }
        faces.truncate(k);
        areas.truncate(k);
    }

    // 4. Connected components.
    let mut uf = UnionFind::new(n);
    for f in &faces {
        uf.union(f[0], f[1]);
        uf.union(f[0], f[2]);
    }
    let mut comp_of_root: Vec<usize> = vec![usize::MAX; n];
    let mut comp_area: Vec<f64> = Vec::new();
    let mut face_comp: Vec<usize> = Vec::with_capacity(faces.len());
    for (f, &a) in faces.iter().zip(&areas) {
        let r = uf.find(f[0]) as usize;
        if comp_of_root[r] == usize::MAX {
            comp_of_root[r] = comp_area.len();
            comp_area.push(0.0);
        }
        let c = comp_of_root[r];
        comp_area[c] += a;
        face_comp.push(c);
    }
    let components = comp_area.len();
    let total_area: f64 = comp_area.iter().sum();
    let (components_kept, dropped_area_fraction) = match opts.components {
        ComponentPolicy::All => (components, 0.0),
        ComponentPolicy::Largest => {
            let mut best = 0;
            for (c, &a) in comp_area.iter().enumerate() {
                if a > comp_area[best] {
                    best = c;
                }
            }
            let dropped: f64 = comp_area
                .iter()
                .enumerate()
                .filter(|&(c, _)| c != best)
                .map(|(_, a)| a)
                .sum();
            let mut k = 0;
            for j in 0..faces.len() {
                if face_comp[j] == best {
                    faces[k] = faces[j];
                    k += 1;
                }
            }
            faces.truncate(k);
            // An empty f64 sum is -0.0: report a clean 0 when nothing was dropped.
            (
                1,
                if dropped > 0.0 {
                    dropped / total_area
                } else {
                    0.0
                },
            )
        }
    };
    let component_faces_dropped =
        mesh.faces.len() - degenerate_faces - duplicate_faces - faces.len();
    let kept = 1.0 - dropped_area_fraction;
    if kept + 1e-12 < opts.min_area_kept {
        return Err(Error::Degenerate {
            kind: DegenerateKind::AreaKept,
            message: format!(
                "the largest connected component holds {:.3}% of the area (minimum {}%: \
                 {components} components)",
                100.0 * kept,
                100.0 * opts.min_area_kept
            ),
        });
    }

    // 5. Compaction, keeping the order of the smallest input index of each cluster.
    let mut new_index = vec![u32::MAX; n];
    for f in &faces {
        for &v in f {
            new_index[v as usize] = 0;
        }
    }
    let mut vertices: Vec<[f64; 3]> = Vec::new();
    for (c, slot) in new_index.iter_mut().enumerate() {
        if *slot == 0 {
            *slot = vertices.len() as u32;
            vertices.push(pos(c as u32));
        }
    }
    for f in &mut faces {
        *f = f.map(|v| new_index[v as usize]);
    }
    let map: Vec<Option<u32>> = cluster
        .iter()
        .map(|&c| Some(new_index[c as usize]).filter(|&i| i != u32::MAX))
        .collect();
    let unreferenced_vertices = clusters - vertices.len();

    if faces.len() < opts.min_faces {
        return Err(Error::Degenerate {
            kind: DegenerateKind::TooFewFaces,
            message: format!(
                "{} triangles left after preparation (minimum {}; {} degenerate, {} duplicate \
                 dropped)",
                faces.len(),
                opts.min_faces,
                degenerate_faces,
                duplicate_faces
            ),
        });
    }

    if vertices.len() < opts.min_vertices {
        return Err(Error::Degenerate {
            kind: DegenerateKind::TooFewVertices,
            message: format!(
                "{} vertices left after preparation (minimum {})",
                vertices.len(),
                opts.min_vertices
            ),
        });
    }
    // 5′. Coherent orientation: faces flip in place, so `map` holds.
    let reoriented_faces = orient::orient_coherently(&vertices, &mut faces);
    let cleaning = Cleaning {
        vertices_in: n,
        faces_in: mesh.faces.len(),
        welded_vertices,
        degenerate_faces,
        duplicate_faces,
        component_faces_dropped,
        unreferenced_vertices,
        reoriented_faces,
        components,
        components_kept,
        dropped_area_fraction,
    };
    // 5″. Simplification to the vertex budget (optional): the simplified mesh is prepared
    // again without it (what the collapses left is cleaned, then the remaining steps run), and
    // the maps are composed.
    let kept = Mesh::new(vertices, faces);
    if let Some((simple, simple_map, summary)) =
        opts.max_vertices.and_then(|budget| decimate(&kept, budget))
    {
        let inner = PrepareOptions {
            weld_tolerance: None,
            max_vertices: None,
            ..opts.clone()
        };
        let (out, mut r, map2) = prepare_with_map(&simple, &inner)?;
        cleaning.carry_into(&mut r, mesh);
        r.decimated = Some(summary);
        return Ok((out, r, compose(&map, &simple_map, &map2)));
    }
    let (mut vertices, mut faces) = (kept.vertices, kept.faces);
    // 5-. Smoothing (optional): vertices move, none is added or removed, so `map` holds.
    let mut smooth_steps = None;
    if let Some(sm) = &opts.smooth {
        let (m, done) = taubin_counted(&Mesh::new(vertices, faces), sm);
        (vertices, faces) = (m.vertices, m.faces);
        smooth_steps = Some(done);
    }
    // 5a. Boundary capping (optional): cap vertices and faces are appended, so `map` holds.
    let mut capped = None;
    if let Some(cap) = &opts.cap_boundaries {
        let (m, stats) = cap_boundaries(&Mesh::new(vertices, faces), cap);
        (vertices, faces) = (m.vertices, m.faces);
        capped = Some(stats);
    }
    // 5b. Handle cutting (optional): cut, then prepare the cut mesh again (components,
    // compaction, topology report, normalisation) and compose the maps.
    let mut handle_cut = None;
    if let Some(cut) = &opts.cut_handles {
        let t0 = std::time::Instant::now();
        let compacted = Mesh::new(vertices, faces);
        match cut_handles_with_map(&compacted, cut) {
            Ok((cut_mesh, rep, cut_map)) if rep.cuts > 0 => {
                let inner = PrepareOptions {
                    weld_tolerance: None,
                    cut_handles: None,
                    cap_boundaries: None,
                    smooth: None,
                    max_vertices: None,
                    ..opts.clone()
                };
                let (out, mut r, map2) = prepare_with_map(&cut_mesh, &inner)?;
                let genus_after = super::topology::surface_stats(&out)
                    .ok()
                    .and_then(|s| s.genus);
                r.handle_cut = Some(HandleCutSummary {
                    genus_before: rep.before.genus,
                    genus_after,
                    cuts: rep.cuts,
                    area_kept: r.original_area / compacted.area(),
                    skipped: None,
                    ms: t0.elapsed().as_secs_f64() * 1e3,
                });
                // The vertices compaction dropped (`compacted` also holds the caps' vertices)
                // are the outer pass's `unreferenced_vertices`.
                cleaning.carry_into(&mut r, mesh);
                r.capped = capped;
                r.smooth_steps = smooth_steps;
                return Ok((out, r, compose(&map, &cut_map, &map2)));
            }
            Ok((_, rep, _)) => {
                handle_cut = Some(HandleCutSummary {
                    genus_before: rep.before.genus,
                    genus_after: rep.after.genus,
                    cuts: 0,
                    area_kept: 1.0,
                    skipped: None,
                    ms: t0.elapsed().as_secs_f64() * 1e3,
                });
            }
            Err(e) => {
                handle_cut = Some(HandleCutSummary {
                    genus_before: None,
                    genus_after: None,
                    cuts: 0,
                    area_kept: 1.0,
                    skipped: Some(e.to_string()),
                    ms: t0.elapsed().as_secs_f64() * 1e3,
                });
            }
        }
        (vertices, faces) = (compacted.vertices, compacted.faces);
    }

    // 6. Topology.
    let topo = analyse_edges(vertices.len(), &faces);

    // 7. Area normalisation.
    let mut out = Mesh::new(vertices, faces);
    let original_area = out.area();
    let mut scale_factor = 1.0;
    if opts.normalize_area {
        let mut c = [0.0; 3];
        for f in &out.faces {
            let [a, b, d] = f.map(|i| out.vertices[i as usize]);
            let w = 0.5 * norm(cross(sub(b, a), sub(d, a))) / 3.0;
            for k in 0..3 {
                c[k] += w * (a[k] + b[k] + d[k]);
            }
        }
        let c = c.map(|x| x / original_area);
        scale_factor = 1.0 / original_area.sqrt();
        for v in &mut out.vertices {
            *v = [
                (v[0] - c[0]) * scale_factor,
                (v[1] - c[1]) * scale_factor,
                (v[2] - c[2]) * scale_factor,
            ];
        }
    }

    let report = PrepareReport {
        vertices_in: n,
        faces_in: mesh.faces.len(),
        vertices_out: out.vertices.len(),
        faces_out: out.faces.len(),
        welded_vertices,
        degenerate_faces,
        duplicate_faces,
        component_faces_dropped,
        unreferenced_vertices,
        components,
        components_kept,
        dropped_area_fraction,
        boundary_edges: topo.boundary_edges,
        boundary_loops: topo.boundary_loops,
        nonmanifold_edges: topo.nonmanifold_edges,
        inconsistent_orientation_edges: topo.inconsistent,
        reoriented_faces,
        euler_characteristic: out.vertices.len() as i64 - topo.edges as i64
            + out.faces.len() as i64,
        original_area,
        scale_factor,
        read_repairs: mesh.repairs.clone(),
        handle_cut,
        capped,
        smooth_steps,
        decimated: None,
    };
    Ok((out, report, map))
}

/// The cleaning counts of a pass of [`prepare_with_map`] (steps 2–5′), carried into the report
/// of the pass it runs again on a changed mesh (after simplification or handle cutting).
struct Cleaning {
    vertices_in: usize,
    faces_in: usize,
    welded_vertices: usize,
    degenerate_faces: usize,
    duplicate_faces: usize,
    component_faces_dropped: usize,
    unreferenced_vertices: usize,
    reoriented_faces: usize,
    components: usize,
    components_kept: usize,
    dropped_area_fraction: f64,
}

impl Cleaning {
    /// `r`, the inner pass's report, with the input's counts: the outer pass's sizes, welds,
    /// components and orientation; the faces and vertices both passes dropped, added up.
    fn carry_into(&self, r: &mut PrepareReport, input: &Mesh) {
        r.vertices_in = self.vertices_in;
        r.faces_in = self.faces_in;
        r.welded_vertices = self.welded_vertices;
        r.degenerate_faces += self.degenerate_faces;
        r.duplicate_faces += self.duplicate_faces;
        r.component_faces_dropped += self.component_faces_dropped;
        r.unreferenced_vertices += self.unreferenced_vertices;
        r.reoriented_faces = self.reoriented_faces;
        r.components = self.components;
        r.components_kept = self.components_kept;
        r.dropped_area_fraction = self.dropped_area_fraction;
        r.read_repairs = input.repairs.clone();
    }
}

/// The input-to-output map through two passes: the outer pass's `map`, the step between
/// (`step`: its mesh to the changed mesh) and the inner pass's `inner`.
fn compose(map: &[Option<u32>], step: &[Option<u32>], inner: &[Option<u32>]) -> Vec<Option<u32>> {
    map.iter()
        .map(|m| {
            m.and_then(|a| step[a as usize])
                .and_then(|b| inner[b as usize])
        })
        .collect()
}

fn validate_options(opts: &PrepareOptions) -> Result<()> {
    if let Some(eps) = opts.weld_tolerance {
        if !(eps.is_finite() && eps >= 0.0) {
            return Err(Error::InvalidArgument(format!(
                "weld_tolerance must be finite and >= 0, got {eps}"
            )));
        }
    }
    let a = opts.min_area_kept;
    if !(0.0..=1.0).contains(&a) {
        return Err(Error::InvalidArgument(format!(
            "min_area_kept must be in [0, 1], got {a}"
        )));
    }
    let r = opts.degenerate_area_ratio;
    if !(r.is_finite() && r >= 0.0) {
        return Err(Error::InvalidArgument(format!(
            "degenerate_area_ratio must be finite and >= 0, got {r}"
        )));
    }
    if let Some(c) = &opts.cap_boundaries {
        c.validate()
            .map_err(|e| Error::InvalidArgument(format!("cap_boundaries: {e}")))?;
    }
    if let Some(b) = opts.max_vertices {
        if b < MIN_VERTEX_BUDGET {
            return Err(Error::InvalidArgument(format!(
                "max_vertices must be at least {MIN_VERTEX_BUDGET}, got {b}"
            )));
        }
    }
    if let Some(c) = &opts.smooth {
        c.validate()
            .map_err(|e| Error::InvalidArgument(format!("smooth: {e}")))?;
    }
    if let Some(c) = &opts.cut_handles {
        if !c.remove_band {
            return Err(Error::InvalidArgument(
                "cut_handles.remove_band must be true in preparation (a bare split is undone \
                 by welding when the mesh is read again)"
                    .into(),
            ));
        }
        c.validate()
            .map_err(|e| Error::InvalidArgument(format!("cut_handles: {e}")))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests;
