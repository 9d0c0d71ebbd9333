//! Mesh file readers: OBJ, glTF 2.0 (`.gltf` with embedded buffers and `.glb`), PLY, OFF, STL.
//!
//! Entry points: [`read_mesh`] (bytes + optional format hint), [`read_path`] (file, hint from the
//! extension) and [`detect_format`]. Every reader returns a [`Mesh`] of triangles: polygons are
//! triangulated (ear clipping on the polygon's best-fit plane, see [`triangulate`]), objects,
//! groups and glTF primitives are merged into one mesh, glTF node transforms are applied, STL
//! vertices with bitwise-identical coordinates are welded.
//!
//! # Guarantees
//! * Malformed input yields a typed [`Error`] (never a panic): [`Error::Parse`] names the format
//!   and, where known, the 1-based line (text formats) or the 0-based byte offset (binary formats).
//! * Limits ([`ReadLimits`]) are checked as early as possible: the byte size before parsing, the
//!   vertex/face counts from headers before anything is allocated. No allocation is ever sized
//!   from an untrusted count without a cap derived from the input size.
//! * Faces referencing vertices out of range are errors.
//! * Non-finite coordinates (NaN, ±inf) are **passed through** unchanged by every reader; the
//!   preparation step is the single place that rejects them with [`Error::NonFinite`].
//! * Units are whatever the file uses; no scaling is applied (glTF node scales excepted).

mod gltf;
mod gltf_meshopt;
mod obj;
#[cfg(test)]
mod obj_legacy;
mod off;
mod ply;
mod stl;
pub mod triangulate;

use super::Mesh;
use crate::error::{Error, LimitKind, Result};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::io::Read;
use std::path::Path;
use std::str::FromStr;

/// A mesh file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// Wavefront OBJ (text).
    Obj,
    /// glTF 2.0 JSON (`.gltf`); buffers must be embedded as base64 `data:` URIs.
    Gltf,
    /// Binary glTF 2.0 (`.glb`).
    Glb,
    /// Stanford PLY (ASCII, binary little- or big-endian).
    Ply,
    /// Object File Format (`OFF`, `COFF`, `NOFF`).
    Off,
    /// STL (ASCII or binary).
    Stl,
}

impl Format {
    /// All formats, in declaration order.
    pub const ALL: [Format; 6] = [
        Format::Obj,
        Format::Gltf,
        Format::Glb,
        Format::Ply,
        Format::Off,
        Format::Stl,
    ];

    /// The canonical lower-case name, also the usual file extension (`"obj"`, `"glb"`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Format::Obj => "obj",
            Format::Gltf => "gltf",
            Format::Glb => "glb",
            Format::Ply => "ply",
            Format::Off => "off",
            Format::Stl => "stl",
        }
    }

    /// The MIME type used when serving a file of this format.
    pub fn mime(self) -> &'static str {
        match self {
            Format::Obj => "model/obj",
            Format::Gltf => "model/gltf+json",
            Format::Glb => "model/gltf-binary",
            Format::Ply => "application/ply",
            Format::Off => "application/off",
            Format::Stl => "model/stl",
        }
    }

    /// Recognises a MIME type (case-insensitive, parameters such as `; charset=...` ignored),
    /// e.g. `model/obj`, `model/gltf+json`, `model/gltf-binary`, `model/stl`, `application/sla`,
    /// `application/ply`. Generic types (`text/plain`, `application/octet-stream`) give `None`.
    pub fn from_mime(mime: &str) -> Option<Format> {
        let essence = mime
            .split(';')
            .next()
            .unwrap_or("")
            .trim()
            .to_ascii_lowercase();
        Some(match essence.as_str() {
            "model/obj" | "application/x-tgif" | "text/x-wavefront-obj" | "model/x-obj" => {
                Format::Obj
            }
            "model/gltf+json" => Format::Gltf,
            "model/gltf-binary" => Format::Glb,
            "model/stl"
            | "model/x.stl-ascii"
            | "model/x.stl-binary"
            | "application/sla"
            | "application/vnd.ms-pki.stl"
            | "application/x-stl" => Format::Stl,
            "application/ply" | "model/ply" | "application/x-ply" | "text/plain+ply" => Format::Ply,
            "application/off" | "model/off" | "application/x-off" => Format::Off,
            _ => return None,
        })
    }

    /// Recognises a file extension (with or without the dot, case-insensitive).
    pub fn from_extension(ext: &str) -> Option<Format> {
        let e = ext.trim_start_matches('.').to_ascii_lowercase();
        Some(match e.as_str() {
            "obj" => Format::Obj,
            "gltf" => Format::Gltf,
            "glb" => Format::Glb,
            "ply" => Format::Ply,
            "off" => Format::Off,
            "stl" | "stla" | "stlb" => Format::Stl,
            _ => return None,
        })
    }
}

impl fmt::Display for Format {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Format {
    type Err = Error;

    /// Accepts a name/extension (`obj`, `.glb`, `STL`...) or a MIME type (`model/gltf+json`).
    fn from_str(s: &str) -> Result<Self> {
        Format::from_extension(s)
            .or_else(|| Format::from_mime(s))
            .ok_or_else(|| {
                Error::UnknownFormat(format!(
                    "{s:?} is not a known format name, extension or MIME type"
                ))
            })
    }
}

/// Upper bounds applied while reading untrusted input, and how strictly it is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct ReadLimits {
    /// Maximum input size in bytes.
    pub max_bytes: usize,
    /// Maximum number of vertices of the resulting mesh (for STL: after welding; header counts
    /// above it are refused before reading).
    pub max_vertices: usize,
    /// Maximum number of triangles of the resulting mesh (after triangulation).
    pub max_faces: usize,
    /// Maximum number of corners of one polygon (OBJ, OFF, PLY faces; default 256). A larger
    /// polygon fails with `limit.polygon_vertices` ([`Error::PolygonTooLarge`]): it is no usable
    /// surface (ear clipping is quadratic, and a fan of thousands of slivers around one corner
    /// makes the Laplacian so ill-conditioned that the eigensolver spends seconds failing).
    pub max_polygon_vertices: usize,
    /// `false` (default): a count or length the file declares that disagrees with its data
    /// (trailing triangles after a binary STL's count, a glTF buffer longer than its
    /// `byteLength`, an index count that is not a multiple of 3, data after the last PLY element,
    /// a glTF `asset.version` other than 2.x) fails with `mesh.inconsistent`
    /// ([`Error::Inconsistent`]). `true`: read as before this check existed (the declared count
    /// wins, the rest is ignored) and list each repair in [`Mesh::repairs`], which the
    /// preparation report carries on (`read_repairs`).
    pub lenient: bool,
}

impl Default for ReadLimits {
    /// 256 MiB, 2 000 000 vertices, 4 000 000 triangles, 256 corners per polygon, strict.
    fn default() -> Self {
        ReadLimits {
            max_bytes: 256 << 20,
            max_vertices: 2_000_000,
            max_faces: 4_000_000,
            max_polygon_vertices: 256,
            lenient: false,
        }
    }
}

impl ReadLimits {
    /// No practical limit, and lenient (for trusted files: locally generated ones, and originals
    /// stored before the stricter checks, which must keep reading as they did).
    pub fn unlimited() -> Self {
        ReadLimits {
            max_bytes: usize::MAX,
            max_vertices: u32::MAX as usize,
            max_faces: usize::MAX,
            max_polygon_vertices: usize::MAX,
            lenient: true,
        }
    }

    /// Checks a polygon's corner count against [`ReadLimits::max_polygon_vertices`].
    pub(crate) fn check_polygon(
        &self,
        format: &'static str,
        location: Option<crate::error::Location>,
        corners: usize,
    ) -> Result<()> {
        if corners > self.max_polygon_vertices {
            return Err(Error::PolygonTooLarge {
                format,
                location,
                corners,
                limit: self.max_polygon_vertices,
            });
        }
        Ok(())
    }

    /// A declared count or length disagrees with the data: an error, or (lenient) a repair noted
    /// in `repairs`.
    pub(crate) fn inconsistent(
        &self,
        format: &'static str,
        location: Option<crate::error::Location>,
        message: String,
        repairs: &mut Vec<String>,
    ) -> Result<()> {
        if self.lenient {
            repairs.push(format!("{format}: {message}"));
            Ok(())
        } else {
            Err(Error::Inconsistent {
                format,
                location,
                message,
            })
        }
    }

    pub(crate) fn check_vertices(&self, n: usize) -> Result<()> {
        // Indices are u32: never more vertices than that, whatever the configuration.
        let limit = self.max_vertices.min(u32::MAX as usize);
        if n > limit {
            return Err(Error::Limit {
                kind: LimitKind::Vertices,
                limit,
                actual: n,
            });
        }
        Ok(())
    }

    pub(crate) fn check_faces(&self, n: usize) -> Result<()> {
        if n > self.max_faces {
            return Err(Error::Limit {
                kind: LimitKind::Faces,
                limit: self.max_faces,
                actual: n,
            });
        }
        Ok(())
    }

    pub(crate) fn check_bytes(&self, n: usize) -> Result<()> {
        if n > self.max_bytes {
            return Err(Error::Limit {
                kind: LimitKind::Bytes,
                limit: self.max_bytes,
                actual: n,
            });
        }
        Ok(())
    }
}

/// Reads a mesh from `bytes`.
///
/// The format is found by [`detect_format`] (magic bytes first, then `hint`). Returns the
/// triangles of the file (polygons triangulated, everything merged) with coordinates as stored
/// (STL and glTF are f32, widened exactly to f64). Errors: [`Error::Limit`] when a limit is
/// exceeded, [`Error::Parse`] on malformed input, [`Error::UnknownFormat`],
/// [`Error::ExternalReference`] for glTF files pointing outside themselves.
pub fn read_mesh(bytes: &[u8], hint: Option<Format>, limits: &ReadLimits) -> Result<Mesh> {
    limits.check_bytes(bytes.len())?;
    let bytes = skip_bom(bytes);
    let format = detect_format(bytes, hint)?;
    let mesh = match format {
        Format::Obj => obj::read(bytes, limits)?,
        Format::Gltf | Format::Glb => gltf::read(bytes, limits)?,
        Format::Ply => ply::read(bytes, limits)?,
        Format::Off => off::read(bytes, limits)?,
        Format::Stl => stl::read(bytes, limits)?,
    };
    limits.check_vertices(mesh.vertices.len())?;
    limits.check_faces(mesh.faces.len())?;
    debug_assert!(mesh
        .faces
        .iter()
        .all(|f| f.iter().all(|&i| (i as usize) < mesh.vertices.len())));
    Ok(mesh)
}

/// Reads a mesh file; the extension (if known) is the format hint. The file size is checked
/// against `limits.max_bytes` before it is read.
pub fn read_path(path: impl AsRef<Path>, limits: &ReadLimits) -> Result<Mesh> {
    let path = path.as_ref();
    let hint = path
        .extension()
        .and_then(|e| e.to_str())
        .and_then(Format::from_extension);
    let file = std::fs::File::open(path)?;
    if let Ok(meta) = file.metadata() {
        limits.check_bytes(usize::try_from(meta.len()).unwrap_or(usize::MAX))?;
    }
    let mut bytes = Vec::new();
    // Never trust the metadata alone (the file may grow): read at most one byte over the limit.
    file.take((limits.max_bytes as u64).saturating_add(1))
        .read_to_end(&mut bytes)?;
    read_mesh(&bytes, hint, limits)
}

/// Finds the format of `bytes`.
///
/// Content wins over the hint: magic bytes are checked first (`glTF` → GLB; `ply` line → PLY;
/// `OFF`/`COFF`/`NOFF` header → OFF; `solid` followed by `facet` → ASCII STL; a JSON object with
/// an `"asset"` key → glTF; a binary STL whose size is exactly 84 + 50·n; OBJ statements), then
/// the hint. [`Error::UnknownFormat`] when neither decides.
pub fn detect_format(bytes: &[u8], hint: Option<Format>) -> Result<Format> {
    if let Some(f) = sniff(skip_bom(bytes)) {
        return Ok(f);
    }
    hint.ok_or_else(|| {
        Error::UnknownFormat("content not recognised and no usable extension or format hint".into())
    })
}

/// `bytes` without a leading UTF-8 byte order mark, which some editors write before a text
/// file: every reader would otherwise see `\u{feff}` glued to the first statement (an OBJ
/// then dropped its first vertex, and every face index moved by one). A binary STL whose size
/// is exact with the three bytes is left as it is (its 80-byte header may hold anything).
fn skip_bom(bytes: &[u8]) -> &[u8] {
    match bytes.strip_prefix(b"\xEF\xBB\xBF") {
        Some(rest) if !stl::binary_size_matches(bytes) => rest,
        _ => bytes,
    }
}

fn sniff(bytes: &[u8]) -> Option<Format> {
    if bytes.starts_with(b"glTF") {
        return Some(Format::Glb);
    }
    if bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n") {
        return Some(Format::Ply);
    }
    let head = &bytes[..bytes.len().min(4096)];
    if off::looks_like_off(head) {
        return Some(Format::Off);
    }
    let trimmed = trim_start_ascii(bytes);
    if trimmed.len() >= 5 && trimmed[..5].eq_ignore_ascii_case(b"solid") && contains(head, b"facet")
    {
        return Some(Format::Stl);
    }
    if trimmed.first() == Some(&b'{') && contains(bytes, b"\"asset\"") {
        return Some(Format::Gltf);
    }
    if stl::binary_size_matches(bytes) {
        return Some(Format::Stl);
    }
    if obj::looks_like_obj(head) {
        return Some(Format::Obj);
    }
    None
}

fn trim_start_ascii(b: &[u8]) -> &[u8] {
    let start = b
        .iter()
        .position(|c| !c.is_ascii_whitespace())
        .unwrap_or(b.len());
    &b[start..]
}

pub(crate) fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

/// Text input helpers shared by the line-based readers.
pub(crate) mod text {
    use crate::error::{Error, Location, Result};

    /// Splits `bytes` into lines (`\n`, with a trailing `\r` removed), yielding `(line_no, text)`
    /// with 1-based numbers. Invalid UTF-8 is reported as a parse error of the line.
    pub(crate) fn lines<'a>(
        format: &'static str,
        bytes: &'a [u8],
    ) -> impl Iterator<Item = Result<(usize, &'a str)>> + 'a {
        bytes.split(|&b| b == b'\n').enumerate().map(move |(i, l)| {
            let l = l.strip_suffix(b"\r").unwrap_or(l);
            std::str::from_utf8(l)
                .map(|s| (i + 1, s))
                .map_err(|_| Error::parse(format, Some(Location::Line(i + 1)), "invalid UTF-8"))
        })
    }

    /// Parses a float token (Rust syntax, also `nan`/`inf`, which are passed through).
    pub(crate) fn float(format: &'static str, line: usize, tok: &str) -> Result<f64> {
        tok.parse::<f64>().map_err(|_| {
            Error::parse(
                format,
                Some(Location::Line(line)),
                format!("bad number {tok:?}"),
            )
        })
    }
}
