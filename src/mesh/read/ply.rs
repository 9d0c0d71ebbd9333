//! PLY reader: `ascii`, `binary_little_endian` and `binary_big_endian` 1.0.
//!
//! Hand-written rather than through `ply-rs-bw`: that crate sizes its buffers from the header's
//! element counts (a hostile `element vertex 4000000000` would allocate before reading) and its
//! errors carry neither a line nor a byte offset. This parser reads only what a mesh needs:
//! `x`, `y`, `z` of the `vertex` element (any numeric type, widened to f64) and the
//! `vertex_indices` (or `vertex_index`) list of the `face` element (any integer count and index
//! type); every other element and property is read past and ignored. Polygons are triangulated by
//! ear clipping. Errors give the 1-based line (header and ASCII body) or the 0-based byte offset
//! (binary body).

use super::triangulate::triangulate;
use super::ReadLimits;
use crate::error::{Error, Location, Result};
use crate::mesh::Mesh;

const F: &str = "PLY";

fn line_err(line: usize, msg: impl Into<String>) -> Error {
    Error::parse(F, Some(Location::Line(line)), msg)
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Ty {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Ty {
    fn parse(s: &str) -> Option<Ty> {
        Some(match s {
            "char" | "int8" => Ty::I8,
            "uchar" | "uint8" => Ty::U8,
            "short" | "int16" => Ty::I16,
            "ushort" | "uint16" => Ty::U16,
            "int" | "int32" => Ty::I32,
            "uint" | "uint32" => Ty::U32,
            "float" | "float32" => Ty::F32,
            "double" | "float64" => Ty::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Ty::I8 | Ty::U8 => 1,
            Ty::I16 | Ty::U16 => 2,
            Ty::I32 | Ty::U32 | Ty::F32 => 4,
            Ty::F64 => 8,
        }
    }

    fn is_int(self) -> bool {
        !matches!(self, Ty::F32 | Ty::F64)
    }
}

#[derive(Debug)]
enum Prop {
    Scalar(Ty, String),
    List(Ty, Ty, String),
}

impl Prop {
    fn name(&self) -> &str {
        match self {
            Prop::Scalar(_, n) | Prop::List(_, _, n) => n,
        }
    }
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Prop>,
    line: usize,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Encoding {
    Ascii,
    Le,
    Be,
}

/// The body, either as text tokens or as binary data.
enum Body<'a> {
    Ascii {
        toks: std::iter::Peekable<Box<dyn Iterator<Item = (usize, &'a str)> + 'a>>,
        last_line: usize,
        remaining_hint: usize,
    },
    Binary {
        data: &'a [u8],
        pos: usize,
        big: bool,
    },
}

impl Body<'_> {
    /// Where the next value is (ASCII: its line; at the end of the data: the last line).
    fn location(&mut self) -> Location {
        match self {
            Body::Ascii {
                toks, last_line, ..
            } => Location::Line(toks.peek().map_or(*last_line, |t| t.0)),
            Body::Binary { pos, .. } => Location::Byte(*pos),
        }
    }

    fn err(&mut self, msg: impl Into<String>) -> Error {
        Error::parse(F, Some(self.location()), msg)
    }

    /// Bytes left (binary) or an upper bound of the tokens left (ASCII).
    fn remaining(&self) -> usize {
        match self {
            Body::Ascii { remaining_hint, .. } => *remaining_hint,
            Body::Binary { data, pos, .. } => data.len().saturating_sub(*pos),
        }
    }

    fn is_binary(&self) -> bool {
        matches!(self, Body::Binary { .. })
    }

    /// Reads one value of type `ty`, widened to f64 (exact for every PLY integer type).
    fn value(&mut self, ty: Ty) -> Result<f64> {
        match self {
            Body::Ascii {
                toks, last_line, ..
            } => {
                let (l, t) = match toks.next() {
                    Some(x) => x,
                    None => {
                        return Err(line_err(
                            *last_line,
                            "unexpected end of data (counts larger than the data?)",
                        ))
                    }
                };
                *last_line = l;
                let v = if ty.is_int() {
                    t.parse::<i64>().map(|v| v as f64).ok()
                } else {
                    t.parse::<f64>().ok()
                };
                v.ok_or_else(|| line_err(l, format!("bad number {t:?}")))
            }
            Body::Binary { data, pos, big } => {
                let n = ty.size();
                let start = *pos;
                let b = data.get(start..start + n).ok_or_else(|| {
                    Error::parse(
                        F,
                        Some(Location::Byte(start)),
                        "unexpected end of data (counts larger than the data?)",
                    )
                })?;
                *pos += n;
                let mut a = [0u8; 8];
                a[..n].copy_from_slice(b);
                if *big {
                    a[..n].reverse();
                }
                Ok(match ty {
                    Ty::I8 => a[0] as i8 as f64,
                    Ty::U8 => a[0] as f64,
                    Ty::I16 => i16::from_le_bytes([a[0], a[1]]) as f64,
                    Ty::U16 => u16::from_le_bytes([a[0], a[1]]) as f64,
                    Ty::I32 => i32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
                    Ty::U32 => u32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
                    Ty::F32 => f32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
                    Ty::F64 => f64::from_le_bytes(a),
                })
            }
        }
    }

    /// Reads a list length.
    fn list_len(&mut self, ty: Ty, item: Ty) -> Result<usize> {
        let loc = self.location();
        let v = self.value(ty)?;
        if v < 0.0 || v.fract() != 0.0 {
            return Err(Error::parse(F, Some(loc), format!("bad list length {v}")));
        }
        let n = v as usize;
        // Binary: n items need n·size bytes; ASCII: n tokens (remaining() bounds the tokens).
        let need = if self.is_binary() {
            n.saturating_mul(item.size())
        } else {
            n
        };
        if need > self.remaining() {
            return Err(self.err(format!("list of {n} items runs past the end of the data")));
        }
        Ok(n)
    }

    /// Skips one property.
    fn skip(&mut self, p: &Prop) -> Result<()> {
        match p {
            Prop::Scalar(t, _) => self.skip_values(*t, 1),
            Prop::List(c, t, _) => {
                let n = self.list_len(*c, *t)?;
                self.skip_values(*t, n)
            }
        }
    }

    fn skip_values(&mut self, ty: Ty, n: usize) -> Result<()> {
        match self {
            Body::Binary { data, pos, .. } => {
                let end = pos.saturating_add(n.saturating_mul(ty.size()));
                if end > data.len() {
                    return Err(self.err("unexpected end of data"));
                }
                *pos = end;
                Ok(())
            }
            Body::Ascii { .. } => {
                for _ in 0..n {
                    self.value(ty)?;
                }
                Ok(())
            }
        }
    }
}

struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
    /// Byte offset of the body.
    body: usize,
    /// Number of header lines.
    lines: usize,
}

fn parse_header(bytes: &[u8]) -> Result<Header> {
    let mut pos = 0;
    let mut ln = 0;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        ln += 1;
        let rest = &bytes[pos..];
        let nl = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| line_err(ln, "header not terminated by end_header"))?;
        let raw = &rest[..nl];
        pos += nl + 1;
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        let line =
            std::str::from_utf8(raw).map_err(|_| line_err(ln, "header is not valid text"))?;
        let mut t = line.split_ascii_whitespace();
        let kw = t.next().unwrap_or("");
        if ln == 1 {
            if kw != "ply" {
                return Err(line_err(1, "missing \"ply\" magic"));
            }
            continue;
        }
        match kw {
            "format" => {
                let enc = match t.next() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::Le,
                    Some("binary_big_endian") => Encoding::Be,
                    other => return Err(line_err(ln, format!("unknown format {other:?}"))),
                };
                if t.next() != Some("1.0") {
                    return Err(line_err(ln, "unsupported PLY version (1.0 expected)"));
                }
                encoding = Some(enc);
            }
            "element" => {
                let name = t
                    .next()
                    .ok_or_else(|| line_err(ln, "element without a name"))?;
                let c = t
                    .next()
                    .ok_or_else(|| line_err(ln, "element without a count"))?;
                let count: u64 = c
                    .parse()
                    .map_err(|_| line_err(ln, format!("bad element count {c:?}")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count: usize::try_from(count).unwrap_or(usize::MAX),
                    props: Vec::new(),
                    line: ln,
                });
            }
            "property" => {
                let el = elements
                    .last_mut()
                    .ok_or_else(|| line_err(ln, "property before any element"))?;
                let a = t.next().unwrap_or("");
                let prop = if a == "list" {
                    let (c, i, n) = (t.next(), t.next(), t.next());
                    match (c.and_then(Ty::parse), i.and_then(Ty::parse), n) {
                        (Some(c), Some(i), Some(n)) if c.is_int() => {
                            Prop::List(c, i, n.to_string())
                        }
                        _ => return Err(line_err(ln, format!("bad list property {line:?}"))),
                    }
                } else {
                    match (Ty::parse(a), t.next()) {
                        (Some(ty), Some(n)) => Prop::Scalar(ty, n.to_string()),
                        _ => return Err(line_err(ln, format!("bad property {line:?}"))),
                    }
                };
                el.props.push(prop);
            }
            "end_header" => break,
            "comment" | "obj_info" | "" => {}
            other => return Err(line_err(ln, format!("unknown header keyword {other:?}"))),
        }
    }
    let encoding = encoding.ok_or_else(|| line_err(ln, "header has no format line"))?;
    Ok(Header {
        encoding,
        elements,
        body: pos,
        lines: ln,
    })
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh> {
    let h = parse_header(bytes)?;
    let data = &bytes[h.body..];
    // Limits from the header, before anything is allocated.
    for el in &h.elements {
        match el.name.as_str() {
            "vertex" => limits.check_vertices(el.count)?,
            "face" => limits.check_faces(el.count)?,
            _ => {}
        }
    }
    let mut body = match h.encoding {
        Encoding::Ascii => {
            let text = std::str::from_utf8(data).map_err(|e| {
                Error::parse(
                    F,
                    Some(Location::Byte(h.body + e.valid_up_to())),
                    "ASCII body is not valid UTF-8",
                )
            })?;
            let first = h.lines;
            let toks: Box<dyn Iterator<Item = (usize, &str)>> =
                Box::new(text.lines().enumerate().flat_map(move |(i, l)| {
                    l.split_ascii_whitespace().map(move |t| (first + i + 1, t))
                }));
            Body::Ascii {
                toks: toks.peekable(),
                last_line: first,
                // Every token takes at least one byte plus a separator.
                remaining_hint: data.len() / 2 + 1,
            }
        }
        enc => Body::Binary {
            data: bytes,
            pos: h.body,
            big: enc == Encoding::Be,
        },
    };

    let mut vertices: Vec<[f64; 3]> = Vec::new();
    let mut flat: Vec<u32> = Vec::new();
    let mut polys: Vec<(usize, Location)> = Vec::new();
    let mut triangles = 0usize;
    let mut have_vertices = false;
    for el in &h.elements {
        if el.count == 0 {
            continue;
        }
        if el.props.is_empty() {
            // Nothing to read, whatever the count.
            continue;
        }
        // Each instance takes at least `min` bytes (binary) or `props` tokens (ASCII): refuse
        // counts the data cannot hold before looping or allocating.
        let min = match body {
            Body::Binary { .. } => el
                .props
                .iter()
                .map(|p| match p {
                    Prop::Scalar(t, _) => t.size(),
                    Prop::List(c, _, _) => c.size(),
                })
                .sum::<usize>(),
            Body::Ascii { .. } => el.props.len(),
        };
        if el.count.saturating_mul(min) > body.remaining() {
            return Err(line_err(
                el.line,
                format!(
                    "element {:?} announces {} instances, more than the data holds",
                    el.name, el.count
                ),
            ));
        }
        match el.name.as_str() {
            "vertex" => {
                if have_vertices {
                    return Err(line_err(el.line, "second vertex element"));
                }
                have_vertices = true;
                let find = |n: &str| {
                    el.props
                        .iter()
                        .position(|p| matches!(p, Prop::Scalar(_, m) if m == n))
                };
                let (ix, iy, iz) = match (find("x"), find("y"), find("z")) {
                    (Some(x), Some(y), Some(z)) => (x, y, z),
                    _ => return Err(line_err(el.line, "vertex element lacks scalar x, y and z")),
                };
                vertices.reserve(el.count);
                for _ in 0..el.count {
                    let mut p = [0.0; 3];
                    for (k, prop) in el.props.iter().enumerate() {
                        match prop {
                            Prop::Scalar(t, _) if k == ix || k == iy || k == iz => {
                                let v = body.value(*t)?;
                                p[if k == ix {
                                    0
                                } else if k == iy {
                                    1
                                } else {
                                    2
                                }] = v;
                            }
                            _ => body.skip(prop)?,
                        }
                    }
                    vertices.push(p);
                }
            }
            "face" => {
                let li = el
                    .props
                    .iter()
                    .position(|p| {
                        matches!(p, Prop::List(..))
                            && (p.name() == "vertex_indices" || p.name() == "vertex_index")
                    })
                    .ok_or_else(|| line_err(el.line, "face element lacks a vertex_indices list"))?;
                if let Prop::List(_, it, _) = &el.props[li] {
                    if !it.is_int() {
                        return Err(line_err(el.line, "face indices must be integers"));
                    }
                }
                // Grows with the data actually read (the count is only an upper bound).
                polys.reserve(el.count.min(1 << 16));
                for _ in 0..el.count {
                    for (k, prop) in el.props.iter().enumerate() {
                        match prop {
                            Prop::List(c, it, _) if k == li => {
                                let loc = body.location();
                                let n = body.list_len(*c, *it)?;
                                if n < 3 {
                                    return Err(Error::parse(
                                        F,
                                        Some(loc),
                                        format!("face with {n} vertices (at least 3 needed)"),
                                    ));
                                }
                                limits.check_polygon(F, Some(loc), n)?;
                                triangles = triangles.saturating_add(n - 2);
                                limits.check_faces(triangles)?;
                                let start = flat.len();
                                for _ in 0..n {
                                    let loc = body.location();
                                    let v = body.value(*it)?;
                                    if !(0.0..=u32::MAX as f64).contains(&v) {
                                        return Err(Error::parse(
                                            F,
                                            Some(loc),
                                            format!("bad vertex index {v}"),
                                        ));
                                    }
                                    flat.push(v as u32);
                                }
                                polys.push((start, loc));
                            }
                            _ => body.skip(prop)?,
                        }
                    }
                }
            }
            _ => {
                for _ in 0..el.count {
                    for prop in &el.props {
                        body.skip(prop)?;
                    }
                }
            }
        }
    }
    let mut repairs = Vec::new();
    let left = match &mut body {
        Body::Binary { data, pos, .. } => data.len().saturating_sub(*pos),
        Body::Ascii { toks, .. } => toks.by_ref().count(),
    };
    if left > 0 {
        let unit = if body.is_binary() { "bytes" } else { "values" };
        let loc = match &body {
            Body::Binary { pos, .. } => Some(Location::Byte(*pos)),
            Body::Ascii { .. } => None,
        };
        limits.inconsistent(
            F,
            loc,
            format!("{left} {unit} follow the last element the header declares (ignored)"),
            &mut repairs,
        )?;
    }
    let nv = vertices.len();
    let mut faces = Vec::with_capacity(triangles);
    for (k, &(start, loc)) in polys.iter().enumerate() {
        let end = polys.get(k + 1).map_or(flat.len(), |p| p.0);
        let poly = &flat[start..end];
        if let Some(&bad) = poly.iter().find(|&&i| i as usize >= nv) {
            return Err(Error::parse(
                F,
                Some(loc),
                format!("vertex index {bad} out of range (the file has {nv} vertices)"),
            ));
        }
        triangulate(poly, &vertices, &mut faces);
    }
    let mut mesh = Mesh::new(vertices, faces);
    mesh.repairs = repairs;
    Ok(mesh)
}
