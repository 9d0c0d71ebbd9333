//! OFF reader (hand-written): `OFF`, `COFF`, `NOFF`, `CNOFF`/`NCOFF` headers, optionally with
//! the counts on the header line, `#` comments anywhere, blank lines skipped. One vertex per
//! line (extra values such as colours or normals ignored), one face per line: `n i1 .. in`
//! followed by optional colour values (ignored). Polygons are triangulated by ear clipping.

use super::text::{float, lines};
use super::triangulate::triangulate;
use super::ReadLimits;
use crate::error::{Error, Location, Result};
use crate::mesh::Mesh;

const F: &str = "OFF";
const HEADERS: [&str; 5] = ["OFF", "COFF", "NOFF", "CNOFF", "NCOFF"];

fn err(line: usize, msg: impl Into<String>) -> Error {
    Error::parse(F, Some(Location::Line(line)), msg)
}

/// True if the first non-comment token is an OFF header keyword.
pub(crate) fn looks_like_off(head: &[u8]) -> bool {
    let text = String::from_utf8_lossy(head);
    for line in text.lines() {
        let t = line.split('#').next().unwrap_or("").trim();
        if t.is_empty() {
            continue;
        }
        let kw = t.split_ascii_whitespace().next().unwrap_or("");
        return HEADERS.contains(&kw);
    }
    false
}

fn count(ln: usize, tok: Option<&str>, what: &str) -> Result<usize> {
    let t = tok.ok_or_else(|| err(ln, format!("missing {what} count")))?;
    t.parse::<usize>()
        .map_err(|_| err(ln, format!("bad {what} count {t:?}")))
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh> {
    // Non-empty lines with comments removed.
    let mut it = lines(F, bytes).filter_map(|r| match r {
        Ok((ln, l)) => {
            let l = l.split('#').next().unwrap_or("").trim();
            (!l.is_empty()).then_some(Ok((ln, l)))
        }
        Err(e) => Some(Err(e)),
    });
    let (hl, header) = it
        .next()
        .transpose()?
        .ok_or_else(|| Error::parse(F, None, "empty file"))?;
    let mut toks = header.split_ascii_whitespace();
    let kw = toks.next().unwrap_or("");
    if !HEADERS.contains(&kw) {
        return Err(err(hl, format!("expected an OFF header, found {kw:?}")));
    }
    let rest: Vec<&str> = toks.collect();
    let (cl, counts) = if rest.is_empty() {
        let (cl, l) = it
            .next()
            .transpose()?
            .ok_or_else(|| err(hl, "missing counts line"))?;
        (cl, l.split_ascii_whitespace().collect::<Vec<_>>())
    } else {
        (hl, rest)
    };
    let nv = count(cl, counts.first().copied(), "vertex")?;
    let nf = count(cl, counts.get(1).copied(), "face")?;
    limits.check_vertices(nv)?;
    limits.check_faces(nf)?; // each face gives at least one triangle
                             // Each vertex line takes at least 6 bytes ("0 0 0\n"): cap the reservation by the input.
    let mut vertices = Vec::with_capacity(nv.min(bytes.len() / 6));
    let mut last = cl;
    for k in 0..nv {
        let (ln, l) = it
            .next()
            .transpose()?
            .ok_or_else(|| err(last, format!("file ends after {k} of {nv} vertices")))?;
        last = ln;
        let mut t = l.split_ascii_whitespace();
        let mut p = [0.0; 3];
        for c in &mut p {
            let tok = t
                .next()
                .ok_or_else(|| err(ln, "vertex with fewer than 3 coordinates"))?;
            *c = float(F, ln, tok)?;
        }
        vertices.push(p);
    }
    let mut faces = Vec::with_capacity(nf.min(bytes.len() / 8));
    let mut poly = Vec::new();
    for k in 0..nf {
        let (ln, l) = it
            .next()
            .transpose()?
            .ok_or_else(|| err(last, format!("file ends after {k} of {nf} faces")))?;
        last = ln;
        let mut t = l.split_ascii_whitespace();
        let n = count(ln, t.next(), "face vertex")?;
        if n < 3 {
            return Err(err(
                ln,
                format!("face with {n} vertices (at least 3 needed)"),
            ));
        }
        limits.check_polygon(F, Some(Location::Line(ln)), n)?;
        poly.clear();
        for _ in 0..n {
            let tok = t
                .next()
                .ok_or_else(|| err(ln, format!("face announces {n} vertices but has fewer")))?;
            let i: usize = tok
                .parse()
                .map_err(|_| err(ln, format!("bad vertex index {tok:?}")))?;
            if i >= nv {
                return Err(err(
                    ln,
                    format!("vertex index {i} out of range (the file has {nv} vertices)"),
                ));
            }
            poly.push(i as u32);
        }
        limits.check_faces(faces.len().saturating_add(n - 2))?;
        triangulate(&poly, &vertices, &mut faces);
    }
    let mut repairs = Vec::new();
    if let Some(next) = it.next() {
        let (ln, _) = next?;
        let more = 1 + it.count();
        limits.inconsistent(
            F,
            Some(Location::Line(ln)),
            format!(
                "the header declares {nv} vertices and {nf} faces, but {more} more non-empty \
                 lines follow the last face (ignored)"
            ),
            &mut repairs,
        )?;
    }
    let mut mesh = Mesh::new(vertices, faces);
    mesh.repairs = repairs;
    Ok(mesh)
}
