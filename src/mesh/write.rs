//! Mesh file writers: OBJ, OFF, PLY (ASCII, binary little- or big-endian), STL (ASCII or
//! binary), glTF 2.0 (`.gltf` with one embedded base64 buffer, or `.glb`).
//!
//! Precision: OBJ, OFF and PLY store f64 coordinates and round-trip exactly through the readers
//! of [`super::read`] (text uses Rust's shortest round-trip representation, binary PLY stores
//! `double`). STL and glTF store f32: coordinates are rounded to the nearest f32 (values beyond
//! the f32 range become infinite), so a round trip is exact only for f32-representable input.
//! Every writer checks that faces index existing vertices ([`Error::InvalidArgument`] otherwise).

use super::read::Format;
use super::{cross, sub, Mesh};
use crate::error::{Error, Result};
use base64::Engine;
use std::io::Write;

/// Encoding of a PLY file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PlyEncoding {
    /// `format ascii 1.0`.
    Ascii,
    /// `format binary_little_endian 1.0` (the default: compact and exact).
    #[default]
    BinaryLittleEndian,
    /// `format binary_big_endian 1.0`.
    BinaryBigEndian,
}

/// Encoding of an STL file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StlEncoding {
    /// `solid ... endsolid` text.
    Ascii,
    /// 80-byte header, u32 count, 50 bytes per triangle (the default).
    #[default]
    Binary,
}

fn check(mesh: &Mesh) -> Result<()> {
    let n = mesh.vertices.len();
    if n > u32::MAX as usize {
        return Err(Error::InvalidArgument(format!(
            "{n} vertices do not fit u32 indices"
        )));
    }
    if let Some(f) = mesh
        .faces
        .iter()
        .find(|f| f.iter().any(|&i| i as usize >= n))
    {
        return Err(Error::InvalidArgument(format!(
            "face {f:?} references a vertex out of range ({n} vertices)"
        )));
    }
    Ok(())
}

/// Writes `mesh` in `format` with the default encoding of each format (PLY binary
/// little-endian, STL binary, glTF JSON with an embedded buffer for [`Format::Gltf`]).
pub fn write_mesh(mesh: &Mesh, format: Format, w: &mut impl Write) -> Result<()> {
    match format {
        Format::Obj => write_obj(mesh, w),
        Format::Off => write_off(mesh, w),
        Format::Ply => write_ply(mesh, PlyEncoding::default(), w),
        Format::Stl => write_stl(mesh, StlEncoding::default(), w),
        Format::Gltf => write_gltf(mesh, w),
        Format::Glb => write_glb(mesh, w),
    }
}

/// Writes a Wavefront OBJ file (`v` and `f` lines, 1-based indices), coordinates exact.
pub fn write_obj(mesh: &Mesh, w: &mut impl Write) -> Result<()> {
    check(mesh)?;
    let mut w = std::io::BufWriter::new(w);
    writeln!(
        w,
        "# shapeseek: {} vertices, {} triangles",
        mesh.vertices.len(),
        mesh.faces.len()
    )?;
    for v in &mesh.vertices {
        writeln!(w, "v {:?} {:?} {:?}", v[0], v[1], v[2])?;
    }
    for f in &mesh.faces {
        writeln!(w, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1)?;
    }
    w.flush()?;
    Ok(())
}

/// Writes an OFF file (0-based indices), coordinates exact.
pub fn write_off(mesh: &Mesh, w: &mut impl Write) -> Result<()> {
    check(mesh)?;
    let mut w = std::io::BufWriter::new(w);
    writeln!(w, "OFF\n{} {} 0", mesh.vertices.len(), mesh.faces.len())?;
    for v in &mesh.vertices {
        writeln!(w, "{:?} {:?} {:?}", v[0], v[1], v[2])?;
    }
    for f in &mesh.faces {
        writeln!(w, "3 {} {} {}", f[0], f[1], f[2])?;
    }
    w.flush()?;
    Ok(())
}

/// Writes a PLY file: `vertex` with `double x, y, z`, `face` with `list uchar uint
/// vertex_indices`. Coordinates exact in every encoding.
pub fn write_ply(mesh: &Mesh, encoding: PlyEncoding, w: &mut impl Write) -> Result<()> {
    check(mesh)?;
    let mut w = std::io::BufWriter::new(w);
    let fmt = match encoding {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
        PlyEncoding::BinaryBigEndian => "binary_big_endian",
    };
    write!(
        w,
        "ply\nformat {fmt} 1.0\ncomment shapeseek\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.faces.len()
    )?;
    match encoding {
        PlyEncoding::Ascii => {
            for v in &mesh.vertices {
                writeln!(w, "{:?} {:?} {:?}", v[0], v[1], v[2])?;
            }
            for f in &mesh.faces {
                writeln!(w, "3 {} {} {}", f[0], f[1], f[2])?;
            }
        }
        PlyEncoding::BinaryLittleEndian | PlyEncoding::BinaryBigEndian => {
            let be = encoding == PlyEncoding::BinaryBigEndian;
            for v in &mesh.vertices {
                for c in v {
                    w.write_all(&if be { c.to_be_bytes() } else { c.to_le_bytes() })?;
                }
            }
            for f in &mesh.faces {
                w.write_all(&[3])?;
                for i in f {
                    w.write_all(&if be { i.to_be_bytes() } else { i.to_le_bytes() })?;
                }
            }
        }
    }
    w.flush()?;
    Ok(())
}

fn f32v(v: [f64; 3]) -> [f32; 3] {
    v.map(|c| c as f32)
}

fn unit_normal(mesh: &Mesh, f: &[u32; 3]) -> [f32; 3] {
    let [a, b, c] = f.map(|i| mesh.vertices[i as usize]);
    let n = cross(sub(b, a), sub(c, a));
    let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if l > 0.0 && l.is_finite() {
        f32v([n[0] / l, n[1] / l, n[2] / l])
    } else {
        [0.0; 3]
    }
}

/// Writes an STL file (f32 coordinates; see the module docs). Facet normals are computed from
/// the triangles. The binary header never starts with `solid`.
pub fn write_stl(mesh: &Mesh, encoding: StlEncoding, w: &mut impl Write) -> Result<()> {
    check(mesh)?;
    let mut w = std::io::BufWriter::new(w);
    match encoding {
        StlEncoding::Ascii => {
            writeln!(w, "solid shapeseek")?;
            for f in &mesh.faces {
                let n = unit_normal(mesh, f);
                writeln!(
                    w,
                    "  facet normal {:?} {:?} {:?}\n    outer loop",
                    n[0], n[1], n[2]
                )?;
                for &i in f {
                    let p = f32v(mesh.vertices[i as usize]);
                    writeln!(w, "      vertex {:?} {:?} {:?}", p[0], p[1], p[2])?;
                }
                writeln!(w, "    endloop\n  endfacet")?;
            }
            writeln!(w, "endsolid shapeseek")?;
        }
        StlEncoding::Binary => {
            let n = u32::try_from(mesh.faces.len())
                .map_err(|_| Error::InvalidArgument("too many triangles for binary STL".into()))?;
            let mut header = [b' '; 80];
            let tag = b"shapeseek binary STL";
            header[..tag.len()].copy_from_slice(tag);
            w.write_all(&header)?;
            w.write_all(&n.to_le_bytes())?;
            for f in &mesh.faces {
                let mut rec = [0u8; 50];
                let nrm = unit_normal(mesh, f);
                let corners = f.map(|i| f32v(mesh.vertices[i as usize]));
                for (k, c) in std::iter::once(nrm).chain(corners).flatten().enumerate() {
                    rec[4 * k..4 * k + 4].copy_from_slice(&c.to_le_bytes());
                }
                w.write_all(&rec)?;
            }
        }
    }
    w.flush()?;
    Ok(())
}

/// The binary buffer (positions f32 VEC3, then u32 indices) and the glTF JSON describing it.
fn gltf_parts(mesh: &Mesh, uri: Option<String>, buffer_len: usize) -> Result<serde_json::Value> {
    let nv = mesh.vertices.len();
    let pos_len = nv * 12;
    let idx_len = mesh.faces.len() * 12;
    let mut min = [f32::INFINITY; 3];
    let mut max = [f32::NEG_INFINITY; 3];
    for v in &mesh.vertices {
        let p = f32v(*v);
        if p.iter().any(|c| !c.is_finite()) {
            return Err(Error::InvalidArgument(
                "glTF cannot store non-finite coordinates".into(),
            ));
        }
        for k in 0..3 {
            min[k] = min[k].min(p[k]);
            max[k] = max[k].max(p[k]);
        }
    }
    if nv == 0 {
        min = [0.0; 3];
        max = [0.0; 3];
    }
    let mut buffer = serde_json::json!({ "byteLength": buffer_len });
    if let Some(uri) = uri {
        buffer["uri"] = uri.into();
    }
    let mut primitive = serde_json::json!({ "attributes": { "POSITION": 0 }, "mode": 4 });
    let mut accessors = vec![serde_json::json!({
        "bufferView": 0, "componentType": 5126, "count": nv, "type": "VEC3",
        "min": min, "max": max
    })];
    let mut views = vec![
        serde_json::json!({ "buffer": 0, "byteOffset": 0, "byteLength": pos_len, "target": 34962 }),
    ];
    if !mesh.faces.is_empty() {
        primitive["indices"] = 1.into();
        accessors.push(serde_json::json!({
            "bufferView": 1, "componentType": 5125, "count": mesh.faces.len() * 3, "type": "SCALAR"
        }));
        views.push(serde_json::json!({ "buffer": 0, "byteOffset": pos_len, "byteLength": idx_len, "target": 34963 }));
    }
    Ok(serde_json::json!({
        "asset": { "version": "2.0", "generator": "shapeseek" },
        "scene": 0,
        "scenes": [ { "nodes": [0] } ],
        "nodes": [ { "mesh": 0 } ],
        "meshes": [ { "primitives": [primitive] } ],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [buffer]
    }))
}

fn gltf_buffer(mesh: &Mesh) -> Vec<u8> {
    let mut buf = Vec::with_capacity(mesh.vertices.len() * 12 + mesh.faces.len() * 12);
    for v in &mesh.vertices {
        for c in f32v(*v) {
            buf.extend_from_slice(&c.to_le_bytes());
        }
    }
    for f in &mesh.faces {
        for i in f {
            buf.extend_from_slice(&i.to_le_bytes());
        }
    }
    buf
}

/// Writes a glTF 2.0 JSON file with one mesh, one node, and its buffer embedded as a base64
/// `data:` URI. Coordinates are f32; non-finite ones are refused ([`Error::InvalidArgument`]).
pub fn write_gltf(mesh: &Mesh, w: &mut impl Write) -> Result<()> {
    check(mesh)?;
    let buf = gltf_buffer(mesh);
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&buf)
    );
    let doc = gltf_parts(mesh, Some(uri), buf.len())?;
    serde_json::to_writer(&mut *w, &doc).map_err(|e| Error::Io(e.into()))?;
    w.flush()?;
    Ok(())
}

/// Writes a binary glTF 2.0 (`.glb`) file: JSON chunk plus BIN chunk, 4-byte aligned.
pub fn write_glb(mesh: &Mesh, w: &mut impl Write) -> Result<()> {
    check(mesh)?;
    let mut bin = gltf_buffer(mesh);
    let doc = gltf_parts(mesh, None, bin.len())?;
    let mut json = serde_json::to_vec(&doc).map_err(|e| Error::Io(e.into()))?;
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    let total = u32::try_from(total)
        .map_err(|_| Error::InvalidArgument("mesh too large for GLB".into()))?;
    w.write_all(b"glTF")?;
    w.write_all(&2u32.to_le_bytes())?;
    w.write_all(&total.to_le_bytes())?;
    w.write_all(&(json.len() as u32).to_le_bytes())?;
    w.write_all(b"JSON")?;
    w.write_all(&json)?;
    if !bin.is_empty() {
        w.write_all(&(bin.len() as u32).to_le_bytes())?;
        w.write_all(b"BIN\0")?;
        w.write_all(&bin)?;
    }
    w.flush()?;
    Ok(())
}
