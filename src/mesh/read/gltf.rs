//! glTF 2.0 reader: `.gltf` JSON whose buffers are embedded as base64 `data:` URIs, and `.glb`.
//!
//! The JSON is parsed and validated by the `gltf` crate (without its `import` feature); the GLB
//! container and the buffers are resolved here, by hand: the GLB header and chunk lengths are
//! checked against the file (errors give byte offsets), buffers are the GLB `BIN` chunk or a
//! base64 `data:` URI, and any other URI (file path, http...) is refused with
//! [`Error::ExternalReference`] (images are never loaded, so their URIs do not matter).
//!
//! Geometry: every `TRIANGLES`, `TRIANGLE_STRIP` and `TRIANGLE_FAN` primitive of the meshes
//! reachable from the default scene (else scene 0, else every root node), indexed or not, with
//! the node transforms (matrix or TRS, composed down the hierarchy) applied in f64 and the
//! winding flipped under mirroring transforms. `POINTS`/`LINES*` primitives are skipped. Positions
//! are `VEC3` of `FLOAT`, or of `BYTE`, `UNSIGNED_BYTE`, `SHORT` or `UNSIGNED_SHORT` (plain or
//! normalized, as `KHR_mesh_quantization` allows); indices `u8`/`u16`/`u32`; byte strides
//! honoured; sparse accessors and accessors without a buffer view are refused. A mesh instanced
//! by several nodes is added once per instance.
//!
//! Required extensions: those that change only how a surface looks (materials, textures,
//! lights), animation (`KHR_animation_pointer`), XMP metadata and `KHR_mesh_quantization` are
//! read past (the `gltf` crate's `allow_empty_texture` lets a texture whose image is only in an
//! extension pass its validator); meshopt-compressed buffer views (`EXT_meshopt_compression`,
//! `KHR_meshopt_compression`: `gltfpack -cc`, `gltf-transform meshopt`) are decoded
//! ([`super::gltf_meshopt`]); any other (Draco compression, GPU instancing) is refused with its
//! name, since the bytes of the geometry may then mean something else.
//!
//! Declared lengths must agree with the data (else `mesh.inconsistent`, unless the read is
//! lenient, which keeps the old behaviour and notes the repair): `asset.version` must be 2.x; a
//! `data:` buffer must decode to exactly its `byteLength` and a GLB `BIN` chunk may exceed it
//! only by the ≤ 3 bytes of alignment padding; a `TRIANGLES` primitive's index (or, unindexed,
//! position) count must be a multiple of 3 (lenient: the trailing indices are ignored).
//! Positions are f32 (or dequantized to f32) in glTF: they are widened exactly to f64.

use super::gltf_meshopt::{Decoded, Meshopt};
use super::ReadLimits;
use crate::error::{Error, Location, Result};
use crate::mesh::Mesh;
use base64::Engine;
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;
use std::collections::HashMap;

const F: &str = "glTF";
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;
/// Bound on the node hierarchy depth (guards against cycles).
const MAX_DEPTH: usize = 256;
/// Bound on node visits plus the primitives walked on them (guards against exponential fan-out
/// of shared children: each visit of a node walks every primitive of its mesh, so a small file
/// of shared children over a mesh of many primitives would otherwise be hours of work).
const MAX_VISITS: usize = 1 << 20;

fn perr(msg: impl Into<String>) -> Error {
    Error::parse(F, None, msg)
}

fn berr(at: usize, msg: impl Into<String>) -> Error {
    Error::parse(F, Some(Location::Byte(at)), msg)
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    b.get(at..at + 4)
        .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
}

/// Splits a GLB file into its JSON chunk and optional BIN chunk, checking every length.
fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>)> {
    if bytes.len() < 12 {
        return Err(berr(bytes.len(), "GLB header truncated (12 bytes needed)"));
    }
    let version = u32_at(bytes, 4).unwrap_or(0);
    if version != 2 {
        return Err(berr(
            4,
            format!("unsupported GLB version {version} (2 expected)"),
        ));
    }
    let length = u32_at(bytes, 8).unwrap_or(0) as usize;
    if length != bytes.len() {
        return Err(berr(
            8,
            format!(
                "GLB length field says {length} bytes, the file has {}",
                bytes.len()
            ),
        ));
    }
    let mut json = None;
    let mut bin = None;
    let mut at = 12;
    while at < bytes.len() {
        let (len, ty) = match (u32_at(bytes, at), u32_at(bytes, at + 4)) {
            (Some(l), Some(t)) => (l as usize, t),
            _ => return Err(berr(at, "GLB chunk header truncated")),
        };
        let start = at + 8;
        let data = start
            .checked_add(len)
            .and_then(|end| bytes.get(start..end))
            .ok_or_else(|| {
                berr(
                    at,
                    format!("GLB chunk of {len} bytes runs past the end of the file"),
                )
            })?;
        match ty {
            CHUNK_JSON if json.is_none() && at == 12 => json = Some(data),
            CHUNK_BIN if bin.is_none() && json.is_some() => bin = Some(data),
            CHUNK_JSON | CHUNK_BIN => return Err(berr(at, "misplaced or repeated GLB chunk")),
            _ => {} // unknown chunk types are skipped, as the specification requires
        }
        // Chunks are 4-byte aligned.
        at = start + len.div_ceil(4) * 4;
    }
    let json = json.ok_or_else(|| berr(12, "GLB has no JSON chunk"))?;
    Ok((json, bin))
}

fn decode_data_uri(uri: &str, index: usize) -> Result<Vec<u8>> {
    let (meta, payload) = uri
        .split_once(',')
        .ok_or_else(|| perr(format!("buffer {index}: malformed data URI")))?;
    if !meta.ends_with(";base64") {
        return Err(perr(format!("buffer {index}: data URI is not base64")));
    }
    base64::engine::general_purpose::STANDARD
        .decode(payload.trim())
        .map_err(|e| perr(format!("buffer {index}: bad base64: {e}")))
}

type Mat = [[f64; 4]; 4]; // column-major, m[col][row]

fn mul(a: &Mat, b: &Mat) -> Mat {
    let mut m = [[0.0; 4]; 4];
    for (c, col) in m.iter_mut().enumerate() {
        for (r, v) in col.iter_mut().enumerate() {
            *v = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    m
}

fn apply(m: &Mat, p: [f32; 3]) -> [f64; 3] {
    let [x, y, z] = p.map(f64::from);
    let mut out = [0.0; 3];
    for (r, o) in out.iter_mut().enumerate() {
        *o = m[0][r] * x + m[1][r] * y + m[2][r] * z + m[3][r];
    }
    out
}

fn det3(m: &Mat) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[2][1] * m[1][2])
        - m[1][0] * (m[0][1] * m[2][2] - m[2][1] * m[0][2])
        + m[2][0] * (m[0][1] * m[1][2] - m[1][1] * m[0][2])
}

const IDENTITY: Mat = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// Where the reader takes the bytes of a buffer view from.
struct Sources<'b> {
    /// Each buffer's data URI decoded (empty for the BIN chunk and for fallback buffers).
    buffers: Vec<Vec<u8>>,
    /// The GLB `BIN` chunk.
    bin: Option<&'b [u8]>,
    /// The meshopt-compressed views and fallback buffers.
    meshopt: Meshopt,
    /// Each buffer's source (the BIN chunk or a URI), by buffer index.
    sources: Vec<gltf::buffer::Source<'b>>,
    /// Compressed views decoded, by view index.
    decoded: HashMap<usize, Decoded>,
    /// Bytes the compressed views still to be decoded may take
    /// ([`super::gltf_meshopt::decoded_budget`]).
    budget_left: usize,
}

impl<'b> Sources<'b> {
    /// The bytes of buffer `i`: its decoded data URI, or the BIN chunk.
    fn buffer(&self, i: usize) -> Result<&[u8]> {
        match self.sources.get(i) {
            Some(gltf::buffer::Source::Bin) => self
                .bin
                .ok_or_else(|| perr(format!("buffer {i}: no GLB BIN chunk"))),
            Some(gltf::buffer::Source::Uri(_)) => self
                .buffers
                .get(i)
                .map(Vec::as_slice)
                .ok_or_else(|| perr(format!("buffer {i} missing"))),
            None => Err(perr(format!("buffer {i} missing"))),
        }
    }

    /// Decodes the compressed view `acc` reads, if it has one that is not decoded yet (a
    /// primitive's position accessor, `index` false, or index accessor), charged against what
    /// is left of the read's budget of decoded bytes.
    fn decode_view_of(
        &mut self,
        acc: &gltf::Accessor,
        index: bool,
        limits: &ReadLimits,
    ) -> Result<()> {
        let Some(view) = acc.view() else {
            return Ok(()); // refused by accessor_bytes
        };
        let i = view.index();
        if !self.meshopt.is_compressed(i) {
            return Ok(());
        }
        self.meshopt.check_accessor(i, index, acc.size())?;
        if self.decoded.contains_key(&i) {
            return Ok(());
        }
        let size = self.meshopt.decoded_size(i, limits, self.budget_left)?;
        let data = self.meshopt.decode(i, |b| self.buffer(b).ok())?;
        self.budget_left -= size;
        self.decoded.insert(i, data);
        Ok(())
    }
}

/// The bytes of an accessor's elements: `(data, first element offset, stride)`, all checked.
fn accessor_bytes<'s>(
    acc: &gltf::Accessor,
    src: &'s Sources,
    what: &str,
) -> Result<(&'s [u8], usize, usize)> {
    let name = format!("{what} accessor {}", acc.index());
    if acc.sparse().is_some() {
        return Err(perr(format!("{name}: sparse accessors are not supported")));
    }
    let view = acc.view().ok_or_else(|| {
        perr(format!(
            "{name}: accessors without a bufferView are not supported"
        ))
    })?;
    let buffer = view.buffer();
    // A compressed view's bytes are its decoded data, from their start.
    let (data, view_offset): (&[u8], usize) = match src.decoded.get(&view.index()) {
        Some(d) => (d.bytes(), 0),
        None if src.meshopt.is_fallback(buffer.index()) => {
            return Err(perr(format!(
                "{name}: bufferView {} reads buffer {}, a meshopt fallback buffer without data",
                view.index(),
                buffer.index()
            )))
        }
        None => (src.buffer(buffer.index())?, view.offset()),
    };
    let elem = acc.size();
    let stride = view.stride().unwrap_or(elem);
    if stride < elem {
        return Err(perr(format!(
            "{name}: byteStride {stride} smaller than the element size {elem}"
        )));
    }
    let view_end = view_offset
        .checked_add(view.length())
        .filter(|&e| e <= data.len())
        .ok_or_else(|| {
            perr(format!(
                "bufferView {} lies outside its buffer",
                view.index()
            ))
        })?;
    let start = view_offset.saturating_add(acc.offset());
    let count = acc.count();
    if count > 0 {
        let need = (count - 1)
            .checked_mul(stride)
            .and_then(|x| x.checked_add(elem))
            .and_then(|x| x.checked_add(start));
        if need.is_none_or(|end| end > view_end) {
            return Err(perr(format!(
                "{name}: {count} elements do not fit in bufferView {}",
                view.index()
            )));
        }
    }
    Ok((data, start, stride))
}

fn read_positions(acc: &gltf::Accessor, src: &Sources) -> Result<Vec<[f32; 3]>> {
    let dt = acc.data_type();
    if acc.dimensions() != Dimensions::Vec3 || dt == DataType::U32 {
        return Err(perr(format!(
            "POSITION accessor {} must be VEC3 of FLOAT (or, quantized, of BYTE, UNSIGNED_BYTE, \
             SHORT or UNSIGNED_SHORT)",
            acc.index()
        )));
    }
    let (data, start, stride) = accessor_bytes(acc, src, "POSITION")?;
    // KHR_mesh_quantization: integer components, as integers or normalized (signed ones
    // clamped at -1); the node transforms that exporters add to dequantize are applied later.
    let normalized = acc.normalized();
    let width = dt.size();
    let c = |o: usize| -> f32 {
        let (v, scale) = match dt {
            DataType::F32 => {
                return f32::from_le_bytes([data[o], data[o + 1], data[o + 2], data[o + 3]])
            }
            DataType::I8 => (data[o] as i8 as f32, 127.0),
            DataType::U8 => (data[o] as f32, 255.0),
            DataType::I16 => (i16::from_le_bytes([data[o], data[o + 1]]) as f32, 32767.0),
            _ => (u16::from_le_bytes([data[o], data[o + 1]]) as f32, 65535.0),
        };
        if normalized {
            (v / scale).max(-1.0)
        } else {
            v
        }
    };
    // Bounds were checked by accessor_bytes; count is bounded by the data size.
    Ok((0..acc.count())
        .map(|i| {
            let o = start + i * stride;
            [c(o), c(o + width), c(o + 2 * width)]
        })
        .collect())
}

/// Whether a required glTF extension leaves a file's geometry readable here: after its vendor
/// prefix its name says it changes only how the surface looks (`materials_`, `texture_`,
/// `lights_`), or it is `KHR_animation_pointer` or `KHR_xmp_json_ld` (animation, XMP
/// metadata), none of which is read; or it is `KHR_mesh_quantization`, whose integer positions
/// [`read_positions`] reads, or meshopt compression, whose views [`Sources::decode_view_of`]
/// decodes. Anything else (Draco compression, GPU instancing, levels of detail, structural
/// metadata) may change what the bytes of the geometry mean.
fn leaves_geometry_readable(ext: &str) -> bool {
    let looks = ext.split_once('_').is_some_and(|(_, name)| {
        ["materials_", "texture_", "lights_"]
            .iter()
            .any(|p| name.starts_with(p))
    });
    looks
        || matches!(
            ext,
            "KHR_mesh_quantization"
                | "KHR_animation_pointer"
                | "KHR_xmp_json_ld"
                | "EXT_meshopt_compression"
                | "KHR_meshopt_compression"
        )
}

fn read_indices(acc: &gltf::Accessor, src: &Sources) -> Result<Vec<u32>> {
    if acc.dimensions() != Dimensions::Scalar {
        return Err(perr(format!(
            "index accessor {} must be SCALAR",
            acc.index()
        )));
    }
    let dt = acc.data_type();
    if !matches!(dt, DataType::U8 | DataType::U16 | DataType::U32) {
        return Err(perr(format!(
            "index accessor {} has component type {dt:?} (u8, u16 or u32 expected)",
            acc.index()
        )));
    }
    let (data, start, stride) = accessor_bytes(acc, src, "index")?;
    Ok((0..acc.count())
        .map(|i| {
            let o = start + i * stride;
            match dt {
                DataType::U8 => data[o] as u32,
                DataType::U16 => u16::from_le_bytes([data[o], data[o + 1]]) as u32,
                _ => u32::from_le_bytes([data[o], data[o + 1], data[o + 2], data[o + 3]]),
            }
        })
        .collect())
}

/// Deserializes and validates the glTF JSON.
///
/// gltf-json 1.4.1's validator indexes `root.accessors[...]` with the `POSITION` attribute before
/// checking that index (a panic on hostile input, found by the fuzz test), so attribute indices
/// are checked here first; the validator itself then checks every other reference.
///
/// The bounds (`min`/`max`) that the specification requires on `POSITION` accessors are unused
/// here and often missing in exported files: missing or malformed ones are filled with zeros
/// instead of failing validation.
fn parse_document(json: &[u8]) -> Result<gltf::Document> {
    let mut root: gltf::json::Root = gltf::json::deserialize::from_slice(json)
        .map_err(|e| perr(format!("invalid glTF JSON: {e}")))?;
    // Required extensions that leave the geometry readable are no obstacle (the validator
    // refuses every one it was not built with). Any other leaves it unreadable, most often
    // compressed buffers (Draco, meshopt): said plainly, before the validator's list of every
    // accessor without data that it causes.
    root.extensions_required
        .retain(|e| !leaves_geometry_readable(e));
    if let Some(ext) = root
        .extensions_required
        .iter()
        .find(|e| !gltf::json::extensions::ENABLED_EXTENSIONS.contains(&e.as_str()))
    {
        let what = match ext.as_str() {
            "KHR_draco_mesh_compression" => " (Draco-compressed geometry)",
            _ => "",
        };
        // `gltf-transform copy` writes Draco-compressed files uncompressed (checked with
        // @gltf-transform/cli 4.5.1).
        let how = if what.is_empty() {
            "export the mesh without it"
        } else {
            "decompress it first, for example with `npx @gltf-transform/cli copy in.glb out.glb`"
        };
        return Err(perr(format!(
            "the file requires the glTF extension {ext}{what}, which shapeseek does not read; \
             {how}"
        )));
    }
    let n_acc = root.accessors.len();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let targets = prim
                .targets
                .iter()
                .flatten()
                .flat_map(|t| [t.positions, t.normals, t.tangents].into_iter().flatten());
            let bad = prim
                .attributes
                .values()
                .copied()
                .chain(prim.indices)
                .chain(targets)
                .find(|i| i.value() >= n_acc);
            if let Some(i) = bad {
                return Err(perr(format!(
                    "mesh {m} primitive {p}: accessor {} does not exist ({n_acc} accessors)",
                    i.value()
                )));
            }
        }
    }
    let positions: Vec<usize> = root
        .meshes
        .iter()
        .flat_map(|m| m.primitives.iter())
        .filter_map(|p| {
            p.attributes.get(&gltf::json::validation::Checked::Valid(
                gltf::Semantic::Positions,
            ))
        })
        .map(|i| i.value())
        .collect();
    for i in positions {
        if let Some(acc) = root.accessors.get_mut(i) {
            for bound in [&mut acc.min, &mut acc.max] {
                let ok = bound
                    .as_ref()
                    .and_then(|v| v.as_array())
                    .is_some_and(|a| a.len() == 3 && a.iter().all(|x| x.is_number()));
                if !ok {
                    *bound = Some(gltf::json::Value::from(vec![0.0f32; 3]));
                }
            }
        }
    }
    gltf::Document::from_json(root).map_err(|e| perr(format!("invalid glTF document: {e}")))
}

pub(crate) fn read(bytes: &[u8], limits: &ReadLimits) -> Result<Mesh> {
    let (json, bin) = if bytes.starts_with(b"glTF") {
        split_glb(bytes)?
    } else {
        (bytes, None)
    };
    let doc = parse_document(json)?;
    let meshopt = Meshopt::from_json(json)?;
    let mut repairs = Vec::new();
    let version = doc.as_json().asset.version.clone();
    if version.split('.').next() != Some("2") {
        limits.inconsistent(
            F,
            None,
            format!("asset.version is {version:?}; this reader reads glTF 2.x"),
            &mut repairs,
        )?;
    }

    // Resolve the buffers (BIN chunk or embedded data URI; anything else is refused).
    let mut buffers: Vec<Vec<u8>> = Vec::new();
    for b in doc.buffers() {
        if meshopt.is_fallback(b.index()) {
            // No data of its own: only compressed views refer to it (their bytes are elsewhere).
            buffers.push(Vec::new());
            continue;
        }
        let data = match b.source() {
            gltf::buffer::Source::Bin => {
                let bin = bin.ok_or_else(|| {
                    perr(format!(
                        "buffer {} has no URI and there is no GLB BIN chunk",
                        b.index()
                    ))
                })?;
                if bin.len() < b.length() {
                    return Err(perr(format!(
                        "buffer {}: byteLength {} exceeds the BIN chunk ({} bytes)",
                        b.index(),
                        b.length(),
                        bin.len()
                    )));
                }
                if bin.len() > b.length() + 3 {
                    limits.inconsistent(
                        F,
                        None,
                        format!(
                            "buffer {}: byteLength {} is shorter than the BIN chunk ({} bytes; \
                             at most 3 bytes of padding allowed)",
                            b.index(),
                            b.length(),
                            bin.len()
                        ),
                        &mut repairs,
                    )?;
                }
                Vec::new() // read from `bin` directly
            }
            gltf::buffer::Source::Uri(uri) if uri.trim_start().starts_with("data:") => {
                let d = decode_data_uri(uri, b.index())?;
                if d.len() < b.length() {
                    return Err(perr(format!(
                        "buffer {}: byteLength {} exceeds the decoded data ({} bytes)",
                        b.index(),
                        b.length(),
                        d.len()
                    )));
                }
                if d.len() > b.length() {
                    limits.inconsistent(
                        F,
                        None,
                        format!(
                            "buffer {}: byteLength {} is shorter than its data ({} bytes)",
                            b.index(),
                            b.length(),
                            d.len()
                        ),
                        &mut repairs,
                    )?;
                }
                d
            }
            gltf::buffer::Source::Uri(uri) => {
                return Err(Error::ExternalReference(format!(
                    "buffer {} refers to {uri:?}; a glTF whose data is in other files cannot \
                     be read alone: pack it as one .glb (for example `npx @gltf-transform/cli \
                     copy scene.gltf scene.glb`) or embed its buffers",
                    b.index()
                )))
            }
        };
        buffers.push(data);
    }
    let mut src = Sources {
        buffers,
        bin,
        meshopt,
        sources: doc.buffers().map(|b| b.source()).collect(),
        decoded: HashMap::new(),
        budget_left: super::gltf_meshopt::decoded_budget(limits),
    };

    let roots: Vec<gltf::Node> = match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(scene) => scene.nodes().collect(),
        None => {
            let mut is_child = vec![false; doc.nodes().len()];
            for n in doc.nodes() {
                for c in n.children() {
                    if let Some(x) = is_child.get_mut(c.index()) {
                        *x = true;
                    }
                }
            }
            doc.nodes().filter(|n| !is_child[n.index()]).collect()
        }
    };

    let mut vertices: Vec<[f64; 3]> = Vec::new();
    let mut faces: Vec<[u32; 3]> = Vec::new();
    let mut stack: Vec<(gltf::Node, Mat, usize)> =
        roots.into_iter().rev().map(|n| (n, IDENTITY, 0)).collect();
    let mut visits = 0usize;
    while let Some((node, parent, depth)) = stack.pop() {
        visits += 1;
        if visits > MAX_VISITS {
            return Err(perr(format!(
                "more than {MAX_VISITS} node visits (shared children or cycle)"
            )));
        }
        if depth > MAX_DEPTH {
            return Err(perr(format!(
                "node hierarchy deeper than {MAX_DEPTH} (cycle at node {}?)",
                node.index()
            )));
        }
        let local = node.transform().matrix().map(|c| c.map(f64::from));
        let world = mul(&parent, &local);
        for c in node.children().collect::<Vec<_>>().into_iter().rev() {
            stack.push((c, world, depth + 1));
        }
        let Some(mesh) = node.mesh() else { continue };
        visits = visits.saturating_add(mesh.primitives().len());
        if visits > MAX_VISITS {
            return Err(perr(format!(
                "more than {MAX_VISITS} node and primitive visits (shared children over a mesh \
                 of {} primitives)",
                mesh.primitives().len()
            )));
        }
        let flip = det3(&world) < 0.0;
        for prim in mesh.primitives() {
            let mode = prim.mode();
            if !matches!(
                mode,
                Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
            ) {
                continue;
            }
            let Some(pos_acc) = prim.get(&gltf::Semantic::Positions) else {
                continue;
            };
            let np = pos_acc.count();
            limits.check_vertices(vertices.len().saturating_add(np))?;
            let n_idx = prim.indices().map_or(np, |a| a.count());
            if matches!(mode, Mode::Triangles) && n_idx % 3 != 0 {
                limits.inconsistent(
                    F,
                    None,
                    format!(
                        "mesh {} primitive {}: {n_idx} {} in TRIANGLES mode, not a multiple of 3 \
                         (the last {} ignored)",
                        mesh.index(),
                        prim.index(),
                        if prim.indices().is_some() {
                            "indices"
                        } else {
                            "positions"
                        },
                        n_idx % 3
                    ),
                    &mut repairs,
                )?;
            }
            let n_tri = match mode {
                Mode::Triangles => n_idx / 3,
                _ => n_idx.saturating_sub(2),
            };
            limits.check_faces(faces.len().saturating_add(n_tri))?;
            // Compressed views are decoded here, once the running counts are known to be
            // within the limits, and only for primitives the scene draws.
            src.decode_view_of(&pos_acc, false, limits)?;
            if let Some(acc) = prim.indices() {
                src.decode_view_of(&acc, true, limits)?;
            }
            let positions = read_positions(&pos_acc, &src)?;
            let indices: Vec<u32> = match prim.indices() {
                Some(acc) => {
                    let idx = read_indices(&acc, &src)?;
                    if let Some(&bad) = idx.iter().find(|&&i| i as usize >= np) {
                        return Err(perr(format!(
                            "mesh {} primitive {}: index {bad} out of range ({np} positions)",
                            mesh.index(),
                            prim.index()
                        )));
                    }
                    idx
                }
                None => (0..np as u32).collect(),
            };
            let base = vertices.len() as u32;
            vertices.extend(positions.iter().map(|&p| apply(&world, p)));
            let mut push = |a: u32, b: u32, c: u32| {
                let t = if flip { [a, c, b] } else { [a, b, c] };
                faces.push(t.map(|i| base + i));
            };
            match mode {
                Mode::Triangles => {
                    for t in indices.chunks_exact(3) {
                        push(t[0], t[1], t[2]);
                    }
                }
                Mode::TriangleStrip => {
                    for i in 0..indices.len().saturating_sub(2) {
                        if i % 2 == 0 {
                            push(indices[i], indices[i + 1], indices[i + 2]);
                        } else {
                            push(indices[i + 1], indices[i], indices[i + 2]);
                        }
                    }
                }
                _ => {
                    for i in 1..indices.len().saturating_sub(1) {
                        push(indices[0], indices[i], indices[i + 1]);
                    }
                }
            }
        }
    }
    let mut mesh = Mesh::new(vertices, faces);
    mesh.repairs = repairs;
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(ty: &[u8; 4], data: &[u8]) -> Vec<u8> {
        let mut c = (data.len() as u32).to_le_bytes().to_vec();
        c.extend_from_slice(ty);
        c.extend_from_slice(data);
        c
    }

    fn glb(chunks: &[Vec<u8>]) -> Vec<u8> {
        let body: Vec<u8> = chunks.concat();
        let mut g = b"glTF".to_vec();
        g.extend(2u32.to_le_bytes());
        g.extend(((12 + body.len()) as u32).to_le_bytes());
        g.extend(body);
        g
    }

    #[test]
    fn glb_chunks_unknown_ones_skipped() {
        let g = glb(&[
            chunk(b"JSON", b"{}  "),
            chunk(b"BIN\0", &[1, 2, 3, 4]),
            chunk(b"XTRA", &[9; 8]),
        ]);
        let (json, bin) = split_glb(&g).unwrap();
        assert_eq!(json, b"{}  ");
        assert_eq!(bin, Some(&[1u8, 2, 3, 4][..]));
    }

    #[test]
    fn glb_chunk_errors_have_offsets() {
        let g = glb(&[chunk(b"BIN\0", &[0; 4])]);
        assert!(matches!(
            split_glb(&g),
            Err(Error::Parse {
                location: Some(Location::Byte(12)),
                ..
            })
        ));
        let g = glb(&[chunk(b"JSON", b"{}  "), chunk(b"JSON", b"{}  ")]);
        assert!(matches!(
            split_glb(&g),
            Err(Error::Parse {
                location: Some(Location::Byte(24)),
                ..
            })
        ));
        let mut g = glb(&[chunk(b"JSON", b"{}  ")]);
        g.extend([0, 0, 0]); // dangling partial chunk header
        let n = g.len() as u32;
        g[8..12].copy_from_slice(&n.to_le_bytes());
        assert!(matches!(
            split_glb(&g),
            Err(Error::Parse {
                location: Some(Location::Byte(24)),
                ..
            })
        ));
    }

    #[test]
    fn a_required_compression_extension_is_named() {
        // A Draco-compressed tetrahedron as an exporter writes it: accessors without data, the
        // geometry in the primitive's extension.
        let doc = |ext: &str| {
            format!(
                r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["{ext}"],
                "extensionsRequired":["{ext}"],
                "buffers":[{{"byteLength":4}}],"bufferViews":[{{"buffer":0,"byteLength":4}}],
                "accessors":[{{"componentType":5126,"count":4,"type":"VEC3",
                  "min":[0,0,0],"max":[1,1,1]}},{{"componentType":5123,"count":12,"type":"SCALAR"}}],
                "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1,
                  "extensions":{{"{ext}":{{"bufferView":0,"attributes":{{"POSITION":0}}}}}}}}]}}]}}"#
            )
        };
        let err = |ext: &str| match parse_document(doc(ext).as_bytes()) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("{ext}: read"),
        };
        let e = err("KHR_draco_mesh_compression");
        assert!(
            e.contains("requires the glTF extension KHR_draco_mesh_compression (Draco-compressed"),
            "{e}"
        );
        assert!(!e.contains("Missing data"), "{e}");
        assert!(e.contains("decompress it first"), "{e}");
        let e = err("EXT_mesh_gpu_instancing");
        assert!(
            e.contains("extension EXT_mesh_gpu_instancing, which shapeseek"),
            "{e}"
        );
        assert!(e.contains("export the mesh without it"), "{e}");
        // Ones that leave the geometry readable are no obstacle (the validator refused each).
        for ext in [
            "KHR_materials_unlit",
            "KHR_materials_variants",
            "KHR_texture_transform",
            "KHR_texture_basisu",
            "KHR_lights_punctual",
            "KHR_mesh_quantization",
        ] {
            // The same document with its accessors' data where an uncompressed file has it.
            let plain =
                doc(ext).replace(r#"{"componentType""#, r#"{"bufferView":0,"componentType""#);
            assert!(plain.contains(r#""bufferView":0,"componentType":5123"#));
            let read = parse_document(plain.as_bytes());
            assert!(read.is_ok(), "{ext}: {:?}", read.err());
        }
        // A KTX2 texture, as gltfpack -tc writes it: the image only in the extension, so the
        // texture has no `source` of its own (the validator's `allow_empty_texture`).
        let mut v: serde_json::Value = serde_json::from_str(
            &doc("KHR_texture_basisu")
                .replace(r#"{"componentType""#, r#"{"bufferView":0,"componentType""#),
        )
        .unwrap();
        v["images"] = serde_json::json!([{"uri": "textures/skin.ktx2", "mimeType": "image/ktx2"}]);
        v["textures"] = serde_json::json!([{"extensions": {"KHR_texture_basisu": {"source": 0}}}]);
        v["materials"] =
            serde_json::json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
        v["meshes"][0]["primitives"][0]["material"] = 0.into();
        let read = parse_document(v.to_string().as_bytes());
        assert!(read.is_ok(), "a KTX2 texture: {:?}", read.err());
        // Names matched after the vendor prefix only.
        assert!(!leaves_geometry_readable("EXT_mesh_texture_displacement"));
        assert!(leaves_geometry_readable(
            "ADOBE_materials_thin_transparency"
        ));
    }

    /// A GLB of one tetrahedron whose positions are `comps` (four vertices × 3) stored as
    /// `component_type` (4-byte-aligned stride), under a node with `node` as its JSON
    /// transform, requiring `KHR_mesh_quantization`.
    fn quantized_glb(component_type: u32, normalized: bool, comps: &[i64], node: &str) -> Vec<u8> {
        let width: usize = match component_type {
            5120 | 5121 => 1,
            5122 | 5123 => 2,
            _ => 4,
        };
        let stride = (3 * width).div_ceil(4) * 4;
        let mut bin = Vec::new();
        for v in comps.chunks(3) {
            let mut elem = Vec::new();
            for &c in v {
                match width {
                    1 => elem.push(c as u8),
                    2 => elem.extend((c as u16).to_le_bytes()),
                    _ => elem.extend((c as f32).to_le_bytes()),
                }
            }
            elem.resize(stride, 0);
            bin.extend(elem);
        }
        let pos_len = bin.len();
        for i in [0u16, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3] {
            bin.extend(i.to_le_bytes());
        }
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["KHR_mesh_quantization"],
            "extensionsRequired":["KHR_mesh_quantization"],
            "buffers":[{{"byteLength":{}}}],
            "bufferViews":[{{"buffer":0,"byteLength":{pos_len},"byteStride":{stride}}},
              {{"buffer":0,"byteOffset":{pos_len},"byteLength":24}}],
            "accessors":[{{"bufferView":0,"componentType":{component_type},"normalized":{normalized},
              "count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,1]}},
              {{"bufferView":1,"componentType":5123,"count":12,"type":"SCALAR"}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
            "nodes":[{{"mesh":0,{node}}}],"scenes":[{{"nodes":[0]}}],"scene":0}}"#,
            bin.len()
        );
        let mut json = json.into_bytes();
        json.resize(json.len().div_ceil(4) * 4, b' ');
        bin.resize(bin.len().div_ceil(4) * 4, 0);
        glb(&[chunk(b"JSON", &json), chunk(b"BIN\0", &bin)])
    }

    #[test]
    fn quantized_positions_are_dequantized_and_transformed() {
        let limits = ReadLimits::default();
        let corners = [
            [1.0, 0.0, 0.0],
            [3.0, 0.0, 0.0],
            [1.0, 2.0, 0.0],
            [1.0, 0.0, 2.0],
        ];
        // Normalized UNSIGNED_SHORT under the node's dequantizing scale and offset (as
        // gltfpack writes): 65535 is 1.
        let q = 65535;
        let comps = [0, 0, 0, q, 0, 0, 0, q, 0, 0, 0, q];
        let node = r#""scale":[2,2,2],"translation":[1,0,0]"#;
        let m = read(&quantized_glb(5123, true, &comps, node), &limits).unwrap();
        assert_eq!(m.vertices, corners);
        assert_eq!(m.faces.len(), 4);
        // Normalized BYTE: 127 is 1, and -128 is clamped to -1.
        let comps = [0, 0, 0, 127, 0, 0, 0, 127, -128, 0, 0, 127];
        let m = read(&quantized_glb(5120, true, &comps, r#""name":"n""#), &limits).unwrap();
        assert_eq!(m.vertices[1], [1.0, 0.0, 0.0]);
        assert_eq!(m.vertices[2], [0.0, 1.0, -1.0]);
        // Plain SHORT and UNSIGNED_BYTE: the integers themselves.
        let comps = [0, 0, 0, 2, 0, 0, 0, 2, 0, 0, 0, 2];
        let half = r#""scale":[0.5,0.5,0.5]"#;
        for ty in [5122, 5121] {
            let m = read(&quantized_glb(ty, false, &comps, half), &limits).unwrap();
            assert_eq!(m.vertices[3], [0.0, 0.0, 1.0], "component type {ty}");
        }
        // The same surface as FLOAT.
        let comps = [1, 0, 0, 3, 0, 0, 1, 2, 0, 1, 0, 2];
        let m = read(
            &quantized_glb(5126, false, &comps, r#""name":"f""#),
            &limits,
        )
        .unwrap();
        assert_eq!(m.vertices, corners);
    }

    #[test]
    fn matrices_compose_column_major() {
        let t: Mat = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [1.0, 2.0, 3.0, 1.0],
        ];
        let s: Mat = [
            [2.0, 0.0, 0.0, 0.0],
            [0.0, 2.0, 0.0, 0.0],
            [0.0, 0.0, 2.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        // Scale first, then translate.
        assert_eq!(apply(&mul(&t, &s), [1.0, 1.0, 1.0]), [3.0, 4.0, 5.0]);
        assert_eq!(apply(&mul(&s, &t), [1.0, 1.0, 1.0]), [4.0, 6.0, 8.0]);
        assert!(det3(&s) > 0.0);
    }

    /// `b` padded with `byte` to a multiple of 4 bytes (GLB chunks: spaces after JSON, zeros
    /// after binary data).
    fn pad4(mut b: Vec<u8>, byte: u8) -> Vec<u8> {
        while b.len() % 4 != 0 {
            b.push(byte);
        }
        b
    }

    /// A GLB of one primitive whose positions (`stride` bytes each, `vertices` encoded, `filter`
    /// named) and indices (`index_size` bytes each, `indices` encoded, `mode` named) are
    /// meshopt-compressed in the BIN chunk, under extension `ext`, their views in a fallback
    /// buffer; `component` is the positions' component type.
    fn meshopt_glb(
        ext: &str,
        (vertices, count, stride, component, filter): (&[u8], usize, usize, u32, &str),
        (indices, n_idx, index_size, mode): (&[u8], usize, usize, &str),
    ) -> Vec<u8> {
        let vbytes = pad4(vertices.to_vec(), 0);
        let ibytes = pad4(indices.to_vec(), 0);
        let (voff, ioff) = (0, vbytes.len());
        let bin = [vbytes, ibytes].concat();
        let decoded_v = count * stride;
        let decoded_i = n_idx * index_size;
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},
            "extensionsUsed":["{ext}"],"extensionsRequired":["{ext}"],
            "buffers":[{{"byteLength":{bl}}},
                       {{"byteLength":{fl},"extensions":{{"{ext}":{{"fallback":true}}}}}}],
            "bufferViews":[
              {{"buffer":1,"byteOffset":0,"byteLength":{decoded_v},"byteStride":{stride},
                "extensions":{{"{ext}":{{"buffer":0,"byteOffset":{voff},"byteLength":{vl},
                  "byteStride":{stride},"count":{count},"mode":"ATTRIBUTES","filter":"{filter}"}}}}}},
              {{"buffer":1,"byteOffset":{decoded_v},"byteLength":{decoded_i},
                "extensions":{{"{ext}":{{"buffer":0,"byteOffset":{ioff},"byteLength":{il},
                  "byteStride":{index_size},"count":{n_idx},"mode":"{mode}"}}}}}}],
            "accessors":[
              {{"bufferView":0,"componentType":{component},"count":{count},"type":"VEC3",
                "min":[-1,-1,-1],"max":[1,1,1]}},
              {{"bufferView":1,"componentType":{ict},"count":{n_idx},"type":"SCALAR"}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
            "nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],"scene":0}}"#,
            bl = bin.len(),
            fl = decoded_v + decoded_i,
            vl = vertices.len(),
            il = indices.len(),
            ict = if index_size == 2 { 5123 } else { 5125 },
        );
        glb(&[
            chunk(b"JSON", &pad4(json.into_bytes(), b' ')),
            chunk(b"BIN\0", &bin),
        ])
    }

    /// An icosphere of `subdivisions`, its positions as f32 and its indices flat.
    fn sphere_arrays(subdivisions: u32) -> (Mesh, Vec<[f32; 3]>, Vec<u32>) {
        let sphere = crate::mesh::generate::icosphere(subdivisions);
        let positions = sphere
            .vertices
            .iter()
            .map(|p| p.map(|x| x as f32))
            .collect();
        let flat = sphere.faces.iter().flatten().copied().collect();
        (sphere, positions, flat)
    }

    /// `g` (a GLB) with its JSON changed by `f`.
    fn edit_glb(g: &[u8], f: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
        let (json, bin) = split_glb(g).unwrap();
        let mut doc: serde_json::Value = serde_json::from_slice(json).unwrap();
        f(&mut doc);
        glb(&[
            chunk(b"JSON", &pad4(doc.to_string().into_bytes(), b' ')),
            chunk(b"BIN\0", bin.unwrap()),
        ])
    }

    /// A meshopt-compressed file (gltfpack's `-cc`, `gltf-transform meshopt`) reads as the same
    /// mesh uncompressed: float positions with u32 indices in `TRIANGLES` mode, and positions
    /// through the `EXPONENTIAL` filter with u16 indices in `INDICES` mode under the extension's
    /// ratified name. Before, both were refused ("requires the glTF extension …").
    #[test]
    fn a_meshopt_compressed_file_reads_as_the_uncompressed_mesh() {
        let (sphere, positions, flat) = sphere_arrays(2);
        let n = positions.len();
        // The index codec may rotate a triangle's corners (never its winding).
        let rotated = |t: &[u32; 3]| {
            let k = (0..3).min_by_key(|&k| t[k]).unwrap();
            [t[k], t[(k + 1) % 3], t[(k + 2) % 3]]
        };
        let expect = |m: &Mesh, tol: f64| {
            let got: Vec<[u32; 3]> = m.faces.iter().map(rotated).collect();
            let want: Vec<[u32; 3]> = sphere.faces.iter().map(rotated).collect();
            assert_eq!(got, want);
            assert_eq!(m.vertices.len(), n);
            for (a, b) in m.vertices.iter().zip(&positions) {
                for k in 0..3 {
                    assert!((a[k] - b[k] as f64).abs() <= tol, "{a:?} vs {b:?}");
                }
            }
        };

        let v = meshopt::encode_vertex_buffer(&positions).unwrap();
        let i = meshopt::encode_index_buffer(&flat, n).unwrap();
        let g = meshopt_glb(
            "EXT_meshopt_compression",
            (&v, n, 12, 5126, "NONE"),
            (&i, flat.len(), 4, "TRIANGLES"),
        );
        expect(&read(&g, &ReadLimits::default()).unwrap(), 0.0);

        // 24-bit mantissas: within 2^-23 of the largest coordinate (1).
        let mut exp = vec![0u32; n * 3];
        let flat16: Vec<u16> = flat.iter().map(|&x| x as u16).collect();
        let mut seq = vec![0u8; flat16.len() * 4 + 64];
        // SAFETY: `exp` holds `n` elements of 12 bytes and `positions` `n × 3` floats, as the
        // filter reads and writes; `seq` is as large as meshoptimizer's bound for 2-byte
        // indices (the bound is below 4 bytes per index plus its header).
        let written = unsafe {
            use meshopt::ffi;
            ffi::meshopt_encodeFilterExp(
                exp.as_mut_ptr().cast(),
                n,
                12,
                24,
                positions.as_ptr().cast(),
                ffi::meshopt_EncodeExpMode_meshopt_EncodeExpSeparate,
            );
            assert!(ffi::meshopt_encodeIndexSequenceBound(flat16.len(), n) <= seq.len());
            ffi::meshopt_encodeIndexSequence(seq.as_mut_ptr(), seq.len(), flat.as_ptr(), flat.len())
        };
        seq.truncate(written);
        assert!(written > 0);
        let raw: Vec<[u32; 3]> = exp.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
        let v = meshopt::encode_vertex_buffer(&raw).unwrap();
        let g = meshopt_glb(
            "KHR_meshopt_compression",
            (&v, n, 12, 5126, "EXPONENTIAL"),
            (&seq, flat.len(), 2, "INDICES"),
        );
        expect(
            &read(&g, &ReadLimits::default()).unwrap(),
            1.0 / (1u64 << 22) as f64,
        );
    }

    /// What is wrong with a compressed view is said plainly, and never reaches a decoder with
    /// parameters it does not take: a damaged stream, a stride the codec cannot have, a filter
    /// on the wrong stride, a view over more vertices than the limit, views that together
    /// decode past the read's budget (a small file asking for gigabytes), indices of another
    /// size than the view's, a parent stride that is not the extension's, a view of the
    /// fallback buffer read as data.
    #[test]
    fn a_bad_meshopt_view_is_refused_plainly() {
        let (_, positions, flat) = sphere_arrays(1);
        let n = positions.len();
        let v = meshopt::encode_vertex_buffer(&positions).unwrap();
        let i = meshopt::encode_index_buffer(&flat, n).unwrap();
        let ext = "EXT_meshopt_compression";
        let err = |g: Vec<u8>, limits: &ReadLimits| match read(&g, limits) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("read"),
        };
        let ok = ReadLimits::default();

        let mut damaged = v.clone();
        damaged[0] = 0x7f; // the header byte: an unknown codec version
        let e = err(
            meshopt_glb(
                ext,
                (&damaged, n, 12, 5126, "NONE"),
                (&i, flat.len(), 4, "TRIANGLES"),
            ),
            &ok,
        );
        assert!(
            e.contains("bufferView 0 (meshopt-compressed): the compressed data does not decode"),
            "{e}"
        );

        let e = err(
            meshopt_glb(
                ext,
                (&v, n * 2, 6, 5126, "NONE"),
                (&i, flat.len(), 4, "TRIANGLES"),
            ),
            &ok,
        );
        assert!(e.contains("byteStride 6 for mode Attributes"), "{e}");

        let e = err(
            meshopt_glb(
                ext,
                (&v, n, 12, 5126, "QUATERNION"),
                (&i, flat.len(), 4, "TRIANGLES"),
            ),
            &ok,
        );
        assert!(e.contains("filter Quaternion does not apply"), "{e}");

        let packed = meshopt_glb(
            ext,
            (&v, n, 12, 5126, "NONE"),
            (&i, flat.len(), 4, "TRIANGLES"),
        );
        // One triangle read from a view of more vertices than the limit: refused before the
        // view is decoded (the running count, 3, is within it).
        let one_triangle = edit_glb(&packed, |doc| {
            doc["accessors"][0]["count"] = 3.into();
            doc["meshes"][0]["primitives"][0]
                .as_object_mut()
                .unwrap()
                .remove("indices");
        });
        let small = ReadLimits {
            max_vertices: n - 1,
            ..ReadLimits::default()
        };
        let e = err(one_triangle.clone(), &small);
        assert!(
            e.contains(&format!("too many vertices: {n} > limit {}", n - 1)),
            "{e}"
        );
        assert!(read(&one_triangle, &ok).is_ok());

        // Ten triangles, each read from its own copy of the view over the same encoded bytes:
        // each view is within the limits, together they decode to 120 n bytes, past the
        // budget of 64 n + 12 × 10 (before: all ten decoded).
        let ten = edit_glb(&packed, |doc| {
            let view = doc["bufferViews"][0].clone();
            let mut prims = Vec::new();
            for k in 0..10 {
                let at = doc["bufferViews"].as_array().unwrap().len();
                doc["bufferViews"]
                    .as_array_mut()
                    .unwrap()
                    .push(view.clone());
                let acc = doc["accessors"].as_array().unwrap().len();
                doc["accessors"]
                    .as_array_mut()
                    .unwrap()
                    .push(serde_json::json!({
                        "bufferView": at, "componentType": 5126, "count": 3, "type": "VEC3",
                        "min": [-1, -1, -1], "max": [1, 1, 1], "byteOffset": 12 * k
                    }));
                prims.push(serde_json::json!({"attributes": {"POSITION": acc}}));
            }
            doc["meshes"][0]["primitives"] = prims.into();
        });
        let tight = ReadLimits {
            max_vertices: n,
            max_faces: 10,
            ..ReadLimits::default()
        };
        let e = err(ten.clone(), &tight);
        assert!(e.contains("past what is left of the"), "{e}");
        assert_eq!(read(&ten, &ok).unwrap().faces.len(), 10);

        // Indices read with another size than the view's.
        let e = err(
            edit_glb(&packed, |doc| {
                doc["accessors"][1]["componentType"] = 5123.into()
            }),
            &ok,
        );
        assert!(
            e.contains("indices of 2 bytes over a view of 4-byte indices"),
            "{e}"
        );

        // A parent stride that is not the extension's.
        let e = err(
            edit_glb(&packed, |doc| {
                doc["bufferViews"][0]["byteStride"] = 16.into()
            }),
            &ok,
        );
        assert!(
            e.contains("the view's byteStride 16 is not the extension's 12"),
            "{e}"
        );

        // The index view without its extension: it reads the fallback buffer itself.
        let g = edit_glb(&packed, |doc| {
            doc["bufferViews"][1]
                .as_object_mut()
                .unwrap()
                .remove("extensions")
                .unwrap();
        });
        let e = err(g, &ok);
        assert!(e.contains("a meshopt fallback buffer without data"), "{e}");
    }
}
