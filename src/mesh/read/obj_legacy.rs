//! The previous, hand-written Wavefront OBJ reader, compiled for tests only: `obj` must read every
//! file to the same mesh (see its tests).
//!
//! Hand-written rather than through `tobj`, on purpose: `tobj` re-indexes the positions of each
//! model/group separately (so a body split into groups comes out disconnected, which breaks the
//! Laplacian, and the vertex order changes), stores f32 unless a crate feature is switched on
//! (OBJ coordinates would not round-trip), and its errors carry no line number. Only the
//! geometry statements matter here: `v x y z [w | r g b]` and `f i[/t[/n]] ...` with 1-based or
//! negative (relative) indices. Everything else (`vt`, `vn`, `o`, `g`, `s`, `usemtl`, `mtllib`,
//! `l`, `p`, free-form statements, materials) is ignored; all objects and groups share one
//! global vertex list, as the OBJ specification says, so they are merged with their
//! connectivity intact. Polygons are triangulated by ear clipping. Vertices keep file order
//! (unreferenced ones included).

use super::text::{float, lines};
use super::triangulate::triangulate;
use super::ReadLimits;
use crate::error::{Error, Location, Result};
use crate::mesh::Mesh;

const F: &str = "OBJ";

fn err(line: usize, msg: impl Into<String>) -> Error {
    Error::parse(F, Some(Location::Line(line)), msg)
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh> {
    let mut vertices: Vec<[f64; 3]> = Vec::new();
    // Polygons: flat resolved 0-based indices (as i64, checked at the end), their start offsets
    // and source lines.
    let mut flat: Vec<i64> = Vec::new();
    let mut polys: Vec<(usize, usize)> = Vec::new(); // (start in flat, line)
    let mut triangles = 0usize;
    for item in lines(F, bytes) {
        let (ln, line) = item?;
        let line = line.split('#').next().unwrap_or("");
        let mut toks = line.split_ascii_whitespace();
        match toks.next() {
            Some("v") => {
                let mut p = [0.0; 3];
                for c in &mut p {
                    let t = toks
                        .next()
                        .ok_or_else(|| err(ln, "vertex with fewer than 3 coordinates"))?;
                    *c = float(F, ln, t)?;
                }
                limits.check_vertices(vertices.len() + 1)?;
                vertices.push(p);
            }
            Some("f") => {
                let start = flat.len();
                for t in toks {
                    let first = t.split('/').next().unwrap_or("");
                    let i: i64 = first
                        .parse()
                        .map_err(|_| err(ln, format!("bad vertex index {t:?}")))?;
                    let resolved = match i {
                        0 => return Err(err(ln, "vertex index 0 (OBJ indices start at 1)")),
                        i if i < 0 => vertices.len() as i64 + i,
                        i => i - 1,
                    };
                    if resolved < 0 {
                        return Err(err(
                            ln,
                            format!("relative index {i} reaches before the first vertex"),
                        ));
                    }
                    flat.push(resolved);
                }
                let n = flat.len() - start;
                if n < 3 {
                    return Err(err(
                        ln,
                        format!("face with {n} vertices (at least 3 needed)"),
                    ));
                }
                triangles = triangles.saturating_add(n - 2);
                limits.check_faces(triangles)?;
                polys.push((start, ln));
            }
            _ => {}
        }
    }
    let nv = vertices.len();
    let mut faces = Vec::with_capacity(triangles);
    let mut poly: Vec<u32> = Vec::new();
    for (k, &(start, ln)) in polys.iter().enumerate() {
        let end = polys.get(k + 1).map_or(flat.len(), |p| p.0);
        poly.clear();
        for &i in &flat[start..end] {
            if i as u64 >= nv as u64 {
                return Err(err(
                    ln,
                    format!(
                        "vertex index {} out of range (the file has {nv} vertices)",
                        i + 1
                    ),
                ));
            }
            poly.push(i as u32);
        }
        triangulate(&poly, &vertices, &mut faces);
    }
    Ok(Mesh::new(vertices, faces))
}
