//! Wavefront OBJ reader, parsing through the [`tobj`] crate (as the design card asks).
//!
//! Only the geometry statements matter here: `v x y z [w | r g b]` and `f i[/t[/n]] ...` with
//! 1-based or negative (relative) position indices. Everything else (`vt`, `vn`, `s`, `usemtl`,
//! `mtllib`, `l`, `p`, free-form statements, materials) is ignored; all objects and groups share
//! one global vertex list, as the OBJ specification says, so they are merged with their
//! connectivity intact. Polygons are triangulated by the project's ear clipping
//! ([`super::triangulate`]), not by `tobj`'s fan.
//!
//! # What `tobj` does not give, and how this reader makes up for it
//!
//! The bytes reach `tobj::load_obj_buf` through a line filter (`Filter`, a [`BufRead`]) that
//! sees every line before `tobj` does:
//!
//! * **Line numbers.** `tobj`'s [`tobj::LoadError`] is a bare kind (`PositionParseError`,
//!   `FaceParseError`, ...). The filter hands over one line at a time and knows which line `tobj`
//!   is parsing, so every error names its 1-based line, as before. Invalid UTF-8 (which `tobj`
//!   reports as a `ReadError`) is detected by the filter and named too.
//! * **Limits before allocation.** `tobj` grows its arrays without bound. The filter counts
//!   vertices and triangles (after triangulation: `n − 2` per `n`-gon) as the lines stream by and
//!   fails with [`Error::Limit`] before `tobj` stores the line that exceeds a limit; polygons
//!   with more corners than [`ReadLimits::max_polygon_vertices`] are refused
//!   ([`Error::Polygon`]).
//! * **Index checks.** `tobj` turns index `0` and relative indices reaching before the first
//!   vertex into a wrapped `usize` and then an anonymous out-of-bounds error at the end of the
//!   object; the filter resolves each position index itself (relative indices against the
//!   vertices read so far, exactly as `tobj` and the specification do) and reports the line.
//!   It passes the resolved absolute index to `tobj`, without the texture/normal parts that this
//!   reader ignores (so a missing `vt`/`vn` is not an error, as before).
//! * **Comments after statements** (`v 1 2 3 # corner`) make `tobj` read `#` as a `w` value; the
//!   filter strips everything from `#` on. `v` lines are handed over with their three
//!   coordinates only: `tobj` would divide by a fourth (`w`) value, which the previous reader
//!   (and most tools) ignore. `l` and `p` statements are not handed over (`tobj` would read an
//!   `l a b c` as a triangle).
//! * **One vertex list.** `tobj` re-indexes the positions of each model (`o`/`g`) separately, in
//!   order of first use, and drops positions no face uses. The filter keeps the absolute index
//!   of every face corner in file order; walking `tobj`'s models in order next to that list maps
//!   each model-local index back to its file index, which merges the models (positions shared
//!   between objects become one vertex again) and restores the file order of the vertices.
//!   The positions themselves (the floats) are `tobj`'s, parsed as `f64` (feature `use_f64`).
//! * **Forward references across objects.** `tobj` resolves a model's faces when the model
//!   ends, so a face may not use a vertex defined after the end of its object or group (the
//!   previous reader allowed it); the filter refuses that at the `o`/`g` line with the face's
//!   line number rather than letting `tobj` fail anonymously.
//!
//! The result is the mesh the previous hand-written reader produced, minus the vertices no face
//! uses (the preparation step dropped those anyway): same coordinates bit for bit, same vertex
//! order, same triangles in the same order. `obj_legacy` (compiled for tests only) is that
//! reader, kept to prove it on every OBJ of the test corpus and the shared benchmark.

use super::triangulate::triangulate;
use super::ReadLimits;
use crate::error::{Error, Location, Result};
use crate::mesh::Mesh;
use std::io::{BufRead, Read, Write};

const F: &str = "OBJ";

fn err(line: usize, msg: impl Into<String>) -> Error {
    Error::parse(F, Some(Location::Line(line)), msg)
}

/// True if the first statement of the text (ignoring blank and `#` lines) is an OBJ keyword.
pub(crate) fn looks_like_obj(head: &[u8]) -> bool {
    const KEYWORDS: [&str; 12] = [
        "v", "vt", "vn", "vp", "f", "o", "g", "s", "l", "p", "mtllib", "usemtl",
    ];
    let text = String::from_utf8_lossy(head);
    for line in text.lines() {
        let t = line.trim();
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        let kw = t.split_ascii_whitespace().next().unwrap_or("");
        return KEYWORDS.contains(&kw) && t.len() > kw.len();
    }
    false
}

/// One face as seen by the filter: where its corners start in `Filter::corners`, its line.
#[derive(Clone, Copy)]
struct FaceRec {
    start: usize,
    line: usize,
}

/// The line filter between the input bytes and `tobj` (see the module docs).
struct Filter<'a> {
    src: &'a [u8],
    pos: usize,
    /// 1-based number of the last line read from `src`.
    line: usize,
    /// The line handed to `tobj` (rewritten), and how much of it `tobj` consumed.
    out: Vec<u8>,
    out_pos: usize,
    /// The first error found (`tobj` then sees an I/O error and stops).
    error: Option<Error>,
    limits: &'a ReadLimits,
    /// `v` statements so far.
    vertices: usize,
    /// Absolute 0-based position index of every face corner, in file order.
    corners: Vec<u32>,
    faces: Vec<FaceRec>,
    /// Index into `faces` of the first face of the current `tobj` model.
    model_start: usize,
    triangles: usize,
}

impl<'a> Filter<'a> {
    fn new(src: &'a [u8], limits: &'a ReadLimits) -> Self {
        Filter {
            src,
            pos: 0,
            line: 0,
            out: Vec::with_capacity(256),
            out_pos: 0,
            error: None,
            limits,
            vertices: 0,
            corners: Vec::new(),
            faces: Vec::new(),
            model_start: 0,
            triangles: 0,
        }
    }

    /// Reads source lines until one produces output for `tobj` (or the end); false at the end.
    fn refill(&mut self) -> Result<bool> {
        self.out.clear();
        self.out_pos = 0;
        while self.pos < self.src.len() {
            let rest = &self.src[self.pos..];
            let (raw, next) = match rest.iter().position(|&b| b == b'\n') {
                Some(i) => (&rest[..i], self.pos + i + 1),
                None => (rest, self.src.len()),
            };
            self.pos = next;
            self.line += 1;
            let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
            let text = std::str::from_utf8(raw).map_err(|_| err(self.line, "invalid UTF-8"))?;
            self.statement(text)?;
            if !self.out.is_empty() {
                return Ok(true);
            }
        }
        // End of input: every face must refer to an existing vertex.
        self.check_model_end("the file")?;
        Ok(false)
    }

    /// Checks that the faces of the `tobj` model that ends here use defined vertices only.
    fn check_model_end(&mut self, what: &str) -> Result<()> {
        let nv = self.vertices;
        for k in self.model_start..self.faces.len() {
            let f = self.faces[k];
            let end = self
                .faces
                .get(k + 1)
                .map_or(self.corners.len(), |g| g.start);
            if let Some(&i) = self.corners[f.start..end]
                .iter()
                .find(|&&i| i as usize >= nv)
            {
                let msg = if what == "the file" {
                    format!(
                        "vertex index {} out of range (the file has {nv} vertices)",
                        i as u64 + 1
                    )
                } else {
                    format!(
                        "vertex index {} is not defined before the end of its object or group \
                         ({what}; {nv} vertices so far)",
                        i as u64 + 1
                    )
                };
                return Err(err(f.line, msg));
            }
        }
        self.model_start = self.faces.len();
        Ok(())
    }

    /// Translates one statement into what `tobj` is given (possibly nothing).
    fn statement(&mut self, text: &str) -> Result<()> {
        let ln = self.line;
        let text = text.split('#').next().unwrap_or("");
        let mut toks = text.split_ascii_whitespace();
        match toks.next() {
            Some("v") => {
                self.limits.check_vertices(self.vertices + 1)?;
                self.out.push(b'v');
                for _ in 0..3 {
                    let t = toks
                        .next()
                        .ok_or_else(|| err(ln, "vertex with fewer than 3 coordinates"))?;
                    self.out.push(b' ');
                    self.out.extend_from_slice(t.as_bytes());
                }
                self.out.push(b'\n');
                self.vertices += 1;
            }
            Some("f") => {
                let start = self.corners.len();
                self.out.push(b'f');
                for t in toks {
                    let first = t.split('/').next().unwrap_or("");
                    let i: i64 = first
                        .parse()
                        .map_err(|_| err(ln, format!("bad vertex index {t:?}")))?;
                    let resolved = match i {
                        0 => return Err(err(ln, "vertex index 0 (OBJ indices start at 1)")),
                        i if i < 0 => self.vertices as i64 + i,
                        i => i - 1,
                    };
                    if resolved < 0 {
                        return Err(err(
                            ln,
                            format!("relative index {i} reaches before the first vertex"),
                        ));
                    }
                    let resolved = u32::try_from(resolved).map_err(|_| {
                        err(
                            ln,
                            format!("vertex index {i} out of range (indices are 32-bit)"),
                        )
                    })?;
                    self.corners.push(resolved);
                    // Writing to a Vec cannot fail.
                    let _ = write!(self.out, " {}", resolved as u64 + 1);
                }
                let n = self.corners.len() - start;
                if n < 3 {
                    return Err(err(
                        ln,
                        format!("face with {n} vertices (at least 3 needed)"),
                    ));
                }
                self.limits.check_polygon(F, Some(Location::Line(ln)), n)?;
                self.triangles = self.triangles.saturating_add(n - 2);
                self.limits.check_faces(self.triangles)?;
                self.out.push(b'\n');
                self.faces.push(FaceRec { start, line: ln });
            }
            Some(kw @ ("o" | "g")) => {
                // `tobj` starts a new model here if the current one has faces.
                if self.model_start < self.faces.len() {
                    self.check_model_end(&format!("`{kw}` at line {ln}"))?;
                }
                self.out.extend_from_slice(kw.as_bytes());
                for t in toks {
                    self.out.push(b' ');
                    self.out.extend_from_slice(t.as_bytes());
                }
                self.out.push(b'\n');
            }
            _ => {}
        }
        Ok(())
    }

    fn fail(&mut self, e: Error) -> std::io::Error {
        let msg = e.to_string();
        self.error.get_or_insert(e);
        std::io::Error::other(msg)
    }
}

impl Read for Filter<'_> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let avail = self.fill_buf()?;
        let n = avail.len().min(buf.len());
        buf[..n].copy_from_slice(&avail[..n]);
        self.consume(n);
        Ok(n)
    }
}

impl BufRead for Filter<'_> {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        if self.error.is_some() {
            return Err(std::io::Error::other("stopped after an error"));
        }
        if self.out_pos >= self.out.len() {
            match self.refill() {
                Ok(_) => {}
                Err(e) => return Err(self.fail(e)),
            }
        }
        Ok(&self.out[self.out_pos..])
    }

    fn consume(&mut self, amt: usize) {
        self.out_pos = (self.out_pos + amt).min(self.out.len());
    }
}

/// A `tobj` error kind as a message (what `tobj` parses: positions and faces).
fn tobj_message(e: tobj::LoadError) -> String {
    match e {
        tobj::LoadError::PositionParseError => "bad number in vertex".into(),
        tobj::LoadError::FaceParseError => "bad face".into(),
        other => format!("tobj: {other}"),
    }
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh> {
    let mut filter = Filter::new(bytes, limits);
    let opts = tobj::LoadOptions {
        single_index: false,
        triangulate: false,
        ignore_points: false,
        ignore_lines: false,
    };
    let loaded = tobj::load_obj_buf(&mut filter, &opts, |_| Err(tobj::LoadError::OpenFileFailed));
    let models = match loaded {
        Ok((models, _materials)) => models,
        Err(e) => {
            return Err(match filter.error.take() {
                Some(mine) => mine,
                None => err(filter.line.max(1), tobj_message(e)),
            })
        }
    };
    if let Some(e) = filter.error.take() {
        return Err(e);
    }
    let Filter {
        vertices: nv,
        corners,
        faces: recs,
        triangles,
        ..
    } = filter;

    // Merge the models: model-local index -> absolute file index, through the corner list.
    let mut positions = vec![[0.0f64; 3]; nv];
    let mut used = vec![false; nv];
    let mut corner = 0usize;
    let mut face = 0usize;
    for model in &models {
        let m = &model.mesh;
        let arity = |k: usize| m.face_arities.get(k).map_or(3, |&a| a as usize);
        let nfaces = if m.face_arities.is_empty() {
            m.indices.len() / 3
        } else {
            m.face_arities.len()
        };
        let mut at = 0usize;
        for k in 0..nfaces {
            let n = arity(k);
            let rec = recs.get(face).copied();
            let expected = recs
                .get(face + 1)
                .map_or(corners.len(), |g| g.start)
                .saturating_sub(rec.map_or(corners.len(), |r| r.start));
            if rec.is_none() || n != expected || at + n > m.indices.len() {
                return Err(err(
                    rec.map_or(1, |r| r.line),
                    "internal: tobj's faces do not match the file's",
                ));
            }
            for &local in &m.indices[at..at + n] {
                let g = corners[corner] as usize;
                let l = local as usize;
                let p = m
                    .positions
                    .get(3 * l..3 * l + 3)
                    .ok_or_else(|| err(rec.map_or(1, |r| r.line), "internal: tobj index"))?;
                positions[g] = [p[0], p[1], p[2]];
                used[g] = true;
                corner += 1;
            }
            at += n;
            face += 1;
        }
    }
    if face != recs.len() {
        return Err(err(
            recs.get(face).map_or(1, |r| r.line),
            "internal: tobj returned fewer faces than the file has",
        ));
    }

    // Triangulate in file order on absolute indices (as the previous reader did), then drop the
    // vertices no face uses, keeping the file order of the others.
    let mut tri = Vec::with_capacity(triangles);
    for (k, r) in recs.iter().enumerate() {
        let end = recs.get(k + 1).map_or(corners.len(), |g| g.start);
        triangulate(&corners[r.start..end], &positions, &mut tri);
    }
    let mut new_index = vec![u32::MAX; nv];
    let mut vertices = Vec::with_capacity(used.iter().filter(|&&u| u).count());
    for (g, &u) in used.iter().enumerate() {
        if u {
            new_index[g] = vertices.len() as u32;
            vertices.push(positions[g]);
        }
    }
    let faces = tri
        .into_iter()
        .map(|f| f.map(|i| new_index[i as usize]))
        .collect();
    Ok(Mesh::new(vertices, faces))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lim() -> ReadLimits {
        ReadLimits::default()
    }

    /// The previous reader's mesh with the vertices no face uses removed (file order kept).
    fn legacy_compacted(bytes: &[u8]) -> Result<Mesh> {
        let m = super::super::obj_legacy::read(bytes, &lim())?;
        let mut used = vec![false; m.vertices.len()];
        for f in &m.faces {
            for &i in f {
                used[i as usize] = true;
            }
        }
        let mut map = vec![u32::MAX; m.vertices.len()];
        let mut v = Vec::new();
        for (i, &u) in used.iter().enumerate() {
            if u {
                map[i] = v.len() as u32;
                v.push(m.vertices[i]);
            }
        }
        let f = m.faces.iter().map(|f| f.map(|i| map[i as usize])).collect();
        Ok(Mesh::new(v, f))
    }

    fn bits(m: &Mesh) -> Vec<[u64; 3]> {
        m.vertices.iter().map(|v| v.map(f64::to_bits)).collect()
    }

    fn assert_same(bytes: &[u8], what: &str) {
        let old = legacy_compacted(bytes);
        let new = read(bytes, &lim());
        match (old, new) {
            (Ok(o), Ok(n)) => {
                assert_eq!(bits(&o), bits(&n), "{what}: vertices differ");
                assert_eq!(o.faces, n.faces, "{what}: faces differ");
            }
            (Err(o), Err(n)) => {
                assert_eq!(o.code(), n.code(), "{what}: {o} vs {n}");
            }
            (o, n) => panic!("{what}: old {o:?} vs new {n:?}"),
        }
    }

    #[test]
    fn obj_tobj_matches_the_previous_reader_on_small_cases() {
        let cases: [&[u8]; 9] = [
            b"# test\nmtllib nothing.mtl\no a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n\
f -3/1/1 -2/1/1 -1/1/1\ng b\nusemtl red\nv 1 1 0\nf 2//1 4//1 3//1\no c\ns 1\nf -1 -3 -2\nl 1 2\n",
            b"v 2 1 0\nv 1 1 0\nv 1 2 0\nv 0 2 0\nv 0 0 0\nv 2 0 0\nf 1 2 3 4 5 6\n",
            b"v 0 0 0 # c\nv 1 0 0 0.5\nv 0 1 0 1 0 0\nv 9 9 9\nf 1 2 3\n",
            b"v 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nv 1 1 0\r\nf 1 2 4 3\r\n",
            b"o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\no b\nv 5 5 5\nv 6 5 5\nf 1 4 5\n",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
            b"v 0 0 0\nv 1 x 0\nv 0 1 0\nf 1 2 3\n",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
            b"v nan 0 0\nv inf 0 0\nv 0 1 0\nf 3 2 1\n",
        ];
        for (k, c) in cases.iter().enumerate() {
            assert_same(c, &format!("case {k}"));
        }
    }

    #[test]
    fn obj_errors_keep_their_line() {
        let cases: [(&[u8], usize); 6] = [
            (b"v 0 0 0\nv 1 x 0\nv 0 1 0\nf 1 2 3\n", 2),
            (b"v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 9\n", 5),
            (b"v 0 0 0\nv 1 0 0\nf -3 -2 -1\n", 3),
            (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3q\n", 4),
            (b"v 0 0 0\n\xff\xfe\n", 2),
            // Forward reference across an object boundary: refused at the face's line.
            (
                b"o a\nv 0 0 0\nv 1 0 0\nf 1 2 3\no b\nv 0 1 0\nf 1 2 3\n",
                4,
            ),
        ];
        for (bytes, line) in cases {
            let e = read(bytes, &lim()).unwrap_err();
            assert_eq!(e.code(), "mesh.parse", "{e}");
            assert!(e.to_string().contains(&format!("line {line}")), "{e}");
        }
    }

    /// Every OBJ the test corpus writes and every OBJ of the shared benchmark (skipped, visibly,
    /// where absent) reads to the same mesh with both readers, bit for bit.
    #[test]
    fn obj_tobj_matches_the_previous_reader_on_the_corpus_and_benchmark() {
        use crate::mesh::generate::{icosphere, torus};
        let mut n = 0;
        for m in [torus(1.0, 0.3, 24, 12), icosphere(2), icosphere(0)] {
            let mut b = Vec::new();
            crate::mesh::write::write_obj(&m, &mut b).unwrap();
            assert_same(&b, "generated");
            n += 1;
        }
        for set in ["mini", "dev"] {
            let dir = std::path::Path::new("/work/shared/bench")
                .join(set)
                .join("meshes");
            let Ok(entries) = std::fs::read_dir(&dir) else {
                eprintln!("SKIPPED: {} not found", dir.display());
                continue;
            };
            let mut paths: Vec<_> = entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "obj"))
                .collect();
            paths.sort();
            for p in paths {
                let bytes = std::fs::read(&p).unwrap();
                assert_same(&bytes, &p.display().to_string());
                n += 1;
            }
        }
        eprintln!("compared {n} OBJ files");
    }
}
