//! STL reader (hand-written, both encodings; `stl_io` was not used because it reports no byte
//! or line positions and sizes its buffers from the header count).
//!
//! STL stores every triangle with its own three corners. While reading, corners whose f32
//! coordinates are bitwise identical are welded into one vertex (so `-0.0` and `0.0` stay
//! distinct, as do different NaN payloads), which turns a closed STL surface back into a
//! connected mesh. Vertex order is the order of first appearance. Normals are ignored.

use super::ReadLimits;
use crate::error::{Error, Location, Result};
use crate::mesh::Mesh;
use std::collections::HashMap;

const F: &str = "STL";

/// True if `bytes` has exactly the size a binary STL with the count stored at byte 80 needs.
pub(crate) fn binary_size_matches(bytes: &[u8]) -> bool {
    match bytes.get(80..84) {
        Some(c) => {
            let n = u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as u64;
            84 + 50 * n == bytes.len() as u64
        }
        None => false,
    }
}

struct Welder<'l> {
    map: HashMap<[u32; 3], u32>,
    repairs: Vec<String>,
    vertices: Vec<[f64; 3]>,
    faces: Vec<[u32; 3]>,
    limits: &'l ReadLimits,
}

impl Welder<'_> {
    fn vertex(&mut self, p: [f32; 3]) -> Result<u32> {
        let key = p.map(f32::to_bits);
        if let Some(&i) = self.map.get(&key) {
            return Ok(i);
        }
        self.limits.check_vertices(self.vertices.len() + 1)?;
        let i = self.vertices.len() as u32;
        self.vertices.push(p.map(f64::from));
        self.map.insert(key, i);
        Ok(i)
    }

    fn triangle(&mut self, t: [[f32; 3]; 3]) -> Result<()> {
        self.limits.check_faces(self.faces.len() + 1)?;
        let f = [self.vertex(t[0])?, self.vertex(t[1])?, self.vertex(t[2])?];
        self.faces.push(f);
        Ok(())
    }
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh> {
    let trimmed = bytes
        .iter()
        .position(|c| !c.is_ascii_whitespace())
        .map_or(&bytes[..0], |s| &bytes[s..]);
    let starts_solid = trimmed.len() >= 5 && trimmed[..5].eq_ignore_ascii_case(b"solid");
    // A binary header may also begin with "solid": the exact binary size decides (an ASCII file
    // cannot match it in practice: its bytes 80..84 are text, i.e. a count above 5e8).
    // A binary file cut short may also begin with "solid": it is read as ASCII only if it is
    // text (or at least mentions a facet), so truncation is reported as such.
    let ascii = starts_solid
        && !binary_size_matches(bytes)
        && (std::str::from_utf8(bytes).is_ok()
            || super::contains(&bytes[..bytes.len().min(4096)], b"facet"));
    let mut w = Welder {
        map: HashMap::new(),
        repairs: Vec::new(),
        vertices: Vec::new(),
        faces: Vec::new(),
        limits,
    };
    if ascii {
        read_ascii(bytes, &mut w)?;
    } else {
        read_binary(bytes, &mut w)?;
    }
    let mut mesh = Mesh::new(w.vertices, w.faces);
    mesh.repairs = w.repairs;
    Ok(mesh)
}

fn read_binary(bytes: &[u8], w: &mut Welder) -> Result<()> {
    let c = bytes.get(80..84).ok_or_else(|| {
        Error::parse(
            F,
            Some(Location::Byte(bytes.len())),
            format!(
                "binary STL needs an 84-byte header, the file has {} bytes",
                bytes.len()
            ),
        )
    })?;
    let n = u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as usize;
    w.limits.check_faces(n)?;
    let need = 84u64 + 50 * n as u64;
    if (bytes.len() as u64) < need {
        return Err(Error::parse(
            F,
            Some(Location::Byte(bytes.len())),
            format!(
                "truncated binary STL: {n} triangles need {need} bytes, the file has {}",
                bytes.len()
            ),
        ));
    }
    let extra = bytes.len() as u64 - need;
    if extra > 0 {
        w.limits.inconsistent(
            F,
            Some(Location::Byte(need as usize)),
            format!(
                "binary STL declares {n} triangles ({need} bytes) but the file has {} bytes: \
                 {extra} bytes ({} whole triangles) after the last declared triangle ignored",
                bytes.len(),
                extra / 50
            ),
            &mut w.repairs,
        )?;
    }
    // Capacity is safe: the data for n triangles is present.
    w.faces.reserve(n);
    for rec in bytes[84..need as usize].chunks_exact(50) {
        let f = |k: usize| f32::from_le_bytes([rec[k], rec[k + 1], rec[k + 2], rec[k + 3]]);
        let mut t = [[0f32; 3]; 3];
        for (j, corner) in t.iter_mut().enumerate() {
            for (d, c) in corner.iter_mut().enumerate() {
                *c = f(12 + 12 * j + 4 * d);
            }
        }
        w.triangle(t)?;
    }
    Ok(())
}

struct Toks<'a, I: Iterator<Item = (usize, &'a str)>> {
    it: std::iter::Peekable<I>,
    last_line: usize,
}

impl<'a, I: Iterator<Item = (usize, &'a str)>> Toks<'a, I> {
    fn next(&mut self, what: &str) -> Result<(usize, &'a str)> {
        match self.it.next() {
            Some((l, t)) => {
                self.last_line = l;
                Ok((l, t))
            }
            None => Err(Error::parse(
                F,
                Some(Location::Line(self.last_line)),
                format!("unexpected end of file, expected {what}"),
            )),
        }
    }

    fn expect(&mut self, kw: &str) -> Result<usize> {
        let (l, t) = self.next(kw)?;
        if t.eq_ignore_ascii_case(kw) {
            Ok(l)
        } else {
            Err(Error::parse(
                F,
                Some(Location::Line(l)),
                format!("expected {kw:?}, found {t:?}"),
            ))
        }
    }

    fn num(&mut self, what: &str) -> Result<f32> {
        let (l, t) = self.next(what)?;
        t.parse::<f32>()
            .map_err(|_| Error::parse(F, Some(Location::Line(l)), format!("bad number {t:?}")))
    }

    /// Skips the remaining tokens of line `line` (solid names).
    fn skip_line(&mut self, line: usize) {
        while matches!(self.it.peek(), Some(&(l, _)) if l == line) {
            self.it.next();
        }
    }
}

fn read_ascii(bytes: &[u8], w: &mut Welder) -> Result<()> {
    let text = std::str::from_utf8(bytes).map_err(|e| {
        Error::parse(
            F,
            Some(Location::Byte(e.valid_up_to())),
            "ASCII STL is not valid UTF-8",
        )
    })?;
    let it = text
        .lines()
        .enumerate()
        .flat_map(|(i, l)| l.split_ascii_whitespace().map(move |t| (i + 1, t)));
    let mut p = Toks {
        it: it.peekable(),
        last_line: 1,
    };
    // Several solids in one file are merged.
    loop {
        let l = p.expect("solid")?;
        p.skip_line(l);
        loop {
            let (l, t) = p.next("facet or endsolid")?;
            if t.eq_ignore_ascii_case("endsolid") {
                p.skip_line(l);
                break;
            }
            if !t.eq_ignore_ascii_case("facet") {
                return Err(Error::parse(
                    F,
                    Some(Location::Line(l)),
                    format!("expected \"facet\" or \"endsolid\", found {t:?}"),
                ));
            }
            p.expect("normal")?;
            for _ in 0..3 {
                p.num("normal component")?;
            }
            p.expect("outer")?;
            p.expect("loop")?;
            let mut t = [[0f32; 3]; 3];
            for corner in &mut t {
                p.expect("vertex")?;
                for c in corner.iter_mut() {
                    *c = p.num("coordinate")?;
                }
            }
            p.expect("endloop")?;
            p.expect("endfacet")?;
            w.triangle(t)?;
        }
        if p.it.peek().is_none() {
            return Ok(());
        }
    }
}
