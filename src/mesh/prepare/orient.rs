//! Step 5′ of [`prepare`](super::prepare): coherent orientation. Faces are flipped so that every
//! two faces sharing an edge (an edge with exactly two faces) traverse it in opposite
//! directions.
//!
//! Why a cleaning step and not only a count: the spectrum does not depend on the orientation
//! (cotangent weights and areas are unsigned), but the steps before it read the boundary's
//! direction. A hole next to a flipped face has no directed boundary cycle, so capping skipped
//! it without counting it (`docs/quality.md` §29: a hole of `david-holes3` and one of
//! `michael-holes2`, whose source meshes, TOSCA's david and michael, carry a flipped patch of
//! about 170 faces on the head). A loop on a non-orientable patch has no directed cycle even
//! then; capping follows it without its direction ([`crate::mesh::cap::boundary_loops`]).

use super::edges::for_each_edge;
use crate::mesh::buckets::Buckets;
use crate::mesh::face_area;

/// Flips faces of `faces` (over `vertices`) so that the faces of each patch (faces connected
/// through edges with exactly two faces) are coherently oriented, and returns how many were
/// flipped. Per patch, the orientation of the larger area is kept (on an exact tie, that of
/// the patch's first face in face order), so a mesh oriented outwards but for a few faces keeps
/// its outward normals. A non-orientable patch (a Möbius strip) keeps the orientation of a
/// breadth-first traversal from its first face; the edges left inconsistent are then what the
/// topology report counts. Edges with one face or more than two are not crossed.
///
/// Deterministic; linear but for sorting each vertex's few edges ([`for_each_edge`], as the
/// topology report's edge statistics).
pub(super) fn orient_coherently(vertices: &[[f64; 3]], faces: &mut [[u32; 3]]) -> usize {
    let nf = faces.len();
    // Face adjacency through two-face edges, with the parity of the flip that makes the pair
    // coherent: 1 when both faces traverse the edge the same way.
    let mut pairs: Vec<(u32, (u32, u8))> = Vec::new();
    for_each_edge(
        vertices.len(),
        faces,
        |face, forward| (face, forward),
        |_, group| {
            if let [(_, (f, a)), (_, (g, b))] = *group {
                let p = u8::from(a == b);
                pairs.push((f, (g, p)));
                pairs.push((g, (f, p)));
            }
        },
    );
    // Neighbours in face order, so that the traversal (and, on a non-orientable patch, which
    // edges stay inconsistent) depends on the face order alone, not on the vertex numbering.
    let mut adjacent = Buckets::new(nf, pairs);
    for f in 0..nf {
        adjacent.get_mut(f).sort_unstable();
    }
    // Breadth-first per patch, in face order: flip[f] relative to the patch's first face.
    let mut flip: Vec<Option<u8>> = vec![None; nf];
    let mut flipped = 0;
    let mut patch: Vec<u32> = Vec::new();
    for seed in 0..nf {
        if flip[seed].is_some() {
            continue;
        }
        flip[seed] = Some(0);
        patch.clear();
        patch.push(seed as u32);
        let mut head = 0;
        while head < patch.len() {
            let f = patch[head] as usize;
            head += 1;
            let pf = flip[f].unwrap_or(0);
            for &(g, p) in adjacent.get(f) {
                if flip[g as usize].is_none() {
                    flip[g as usize] = Some(pf ^ p);
                    patch.push(g);
                }
            }
        }
        let (mut keep, mut other) = (0.0, 0.0);
        for &f in &patch {
            if flip[f as usize] == Some(0) {
                keep += face_area(vertices, &faces[f as usize]);
            } else {
                other += face_area(vertices, &faces[f as usize]);
            }
        }
        let turn = if other > keep { 0 } else { 1 };
        for &f in &patch {
            if flip[f as usize] == Some(turn) {
                faces[f as usize].swap(1, 2);
                flipped += 1;
            }
        }
    }
    flipped
}
