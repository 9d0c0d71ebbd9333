//! glTF buffer views compressed with meshoptimizer (`EXT_meshopt_compression`, and its
//! ratified form `KHR_meshopt_compression`): what `gltfpack -c`/`-cc` and
//! `gltf-transform meshopt` write.
//!
//! Such a view names, in its extension, a range of another buffer holding the encoded bytes,
//! how many elements of what stride they decode to, the codec (`ATTRIBUTES`, `TRIANGLES`,
//! `INDICES`) and a filter applied after decoding (`NONE`, `OCTAHEDRAL`, `QUATERNION`,
//! `EXPONENTIAL`, `COLOR`). The view's own buffer is then usually a *fallback* buffer that holds
//! no data at all. The glTF reader decodes a compressed view when a primitive it reads needs
//! it (a position or index accessor), once, into bytes laid out exactly as the uncompressed
//! view would be, and then reads them as any other view.
//!
//! The decoding is meshoptimizer's own (`meshopt_decodeVertexBuffer`, `…IndexBuffer`,
//! `…IndexSequence`, `…Filter*`), through the `meshopt` crate's bindings, which the project
//! already builds for simplification (`crate::mesh::decimate`); writing the codec again would
//! only add a second one to keep right. meshoptimizer documents these decoders as safe on
//! untrusted input given valid parameters; what they `assert` (strides, counts, filter strides)
//! is checked here first: the C++ is built with `NDEBUG`, so a violated precondition would not
//! even abort but corrupt memory. The codec compresses constant data by orders of magnitude, so
//! a small file could ask for gigabytes: every view is bounded by the read limits, and all the
//! views of one read together by [`decoded_budget`], before anything is allocated.

use super::ReadLimits;
use crate::error::{Error, Result};
use serde::Deserialize;
use std::collections::{HashMap, HashSet};

const F: &str = "glTF";
/// The two names of the extension (same bitstream; the ratified one also allows vertex codec
/// version 1 and the `COLOR` filter, both of which the decoder reads).
const NAMES: [&str; 2] = ["EXT_meshopt_compression", "KHR_meshopt_compression"];
/// Decoded bytes allowed per vertex and per triangle of the read limits ([`decoded_budget`]):
/// a position stream of up to 64 bytes per vertex (float positions take 12, gltfpack's
/// quantized ones 8; interleaved streams with normals and texture coordinates 32–48), and three
/// 4-byte indices per triangle.
const BYTES_PER_VERTEX: usize = 64;
const BYTES_PER_TRIANGLE: usize = 12;

fn perr(msg: impl Into<String>) -> Error {
    Error::parse(F, None, msg)
}

/// The most bytes the compressed views of one read may decode to: what a mesh within `limits`
/// needs ([`BYTES_PER_VERTEX`] per vertex, [`BYTES_PER_TRIANGLE`] per triangle).
pub(super) fn decoded_budget(limits: &ReadLimits) -> usize {
    limits
        .max_vertices
        .saturating_mul(BYTES_PER_VERTEX)
        .saturating_add(limits.max_faces.saturating_mul(BYTES_PER_TRIANGLE))
}

/// The codec of a compressed view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Attributes,
    Triangles,
    Indices,
}

/// The filter applied to decoded `ATTRIBUTES` data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Filter {
    None,
    Octahedral,
    Quaternion,
    Exponential,
    Color,
}

/// One compressed buffer view, as its extension declares it.
#[derive(Debug, Clone)]
struct View {
    buffer: usize,
    offset: usize,
    length: usize,
    stride: usize,
    count: usize,
    mode: Mode,
    filter: Filter,
}

/// The compressed views and fallback buffers of a document.
#[derive(Debug, Default)]
pub(super) struct Meshopt {
    views: HashMap<usize, View>,
    fallback: HashSet<usize>,
}

/// A compressed view's decoded bytes, in `u32` storage: the index decoders and the filters
/// write 2- and 4-byte values through aligned pointers.
#[derive(Debug)]
pub(super) struct Decoded {
    words: Vec<u32>,
    len: usize,
}

impl Decoded {
    pub(super) fn bytes(&self) -> &[u8] {
        &bytemuck::cast_slice(&self.words)[..self.len]
    }
}

/// What the reader needs of the document: only the buffers' and buffer views' extensions
/// (serde skips everything else without keeping it).
#[derive(Deserialize)]
struct Doc {
    #[serde(default)]
    buffers: Vec<Item>,
    #[serde(default, rename = "bufferViews")]
    buffer_views: Vec<Item>,
}

/// A buffer or buffer view: its length and stride, and its extensions by name.
#[derive(Deserialize)]
struct Item {
    #[serde(rename = "byteLength")]
    byte_length: Option<serde_json::Value>,
    #[serde(rename = "byteStride")]
    byte_stride: Option<serde_json::Value>,
    #[serde(default)]
    extensions: HashMap<String, serde_json::Value>,
}

impl Item {
    /// The meshopt extension object, under either name.
    fn extension(&self) -> Option<(&'static str, &serde_json::Value)> {
        NAMES
            .iter()
            .find_map(|&n| self.extensions.get(n).map(|v| (n, v)))
    }
}

/// `object[key]` as a non-negative integer that fits a `usize`, or `default` when absent.
fn size_field(
    o: &serde_json::Map<String, serde_json::Value>,
    key: &str,
    default: Option<usize>,
    at: &str,
) -> Result<usize> {
    match o.get(key) {
        None => default.ok_or_else(|| perr(format!("{at}: `{key}` is required"))),
        Some(v) => v
            .as_u64()
            .and_then(|x| usize::try_from(x).ok())
            .ok_or_else(|| perr(format!("{at}: `{key}` must be a non-negative integer"))),
    }
}

impl Meshopt {
    /// Reads the extension objects from the document's JSON (the `gltf` crate, built without
    /// its `extensions` feature, does not keep them). Errors name the view and what is wrong.
    pub(super) fn from_json(json: &[u8]) -> Result<Meshopt> {
        // The common case: no extension name in the text at all.
        if !NAMES
            .iter()
            .any(|n| json.windows(n.len()).any(|w| w == n.as_bytes()))
        {
            return Ok(Meshopt::default());
        }
        let doc: Doc =
            serde_json::from_slice(json).map_err(|e| perr(format!("invalid glTF JSON: {e}")))?;
        let mut out = Meshopt::default();
        for (i, b) in doc.buffers.iter().enumerate() {
            if let Some((_, e)) = b.extension() {
                if e.get("fallback").and_then(|f| f.as_bool()) == Some(true) {
                    out.fallback.insert(i);
                }
            }
        }
        for (i, v) in doc.buffer_views.iter().enumerate() {
            let Some((name, e)) = v.extension() else {
                continue;
            };
            let at = format!("bufferView {i} ({name})");
            let o = e
                .as_object()
                .ok_or_else(|| perr(format!("{at}: the extension must be an object")))?;
            let text = |key: &str, default: &'static str| -> Result<String> {
                match o.get(key) {
                    None => Ok(default.to_string()),
                    Some(s) => s
                        .as_str()
                        .map(str::to_string)
                        .ok_or_else(|| perr(format!("{at}: `{key}` must be a string"))),
                }
            };
            let mode = match text("mode", "")?.as_str() {
                "ATTRIBUTES" => Mode::Attributes,
                "TRIANGLES" => Mode::Triangles,
                "INDICES" => Mode::Indices,
                m => {
                    return Err(perr(format!(
                        "{at}: mode {m:?} (ATTRIBUTES, TRIANGLES or INDICES expected)"
                    )))
                }
            };
            let filter = match text("filter", "NONE")?.as_str() {
                "NONE" => Filter::None,
                "OCTAHEDRAL" => Filter::Octahedral,
                "QUATERNION" => Filter::Quaternion,
                "EXPONENTIAL" => Filter::Exponential,
                "COLOR" => Filter::Color,
                f => return Err(perr(format!("{at}: unknown filter {f:?}"))),
            };
            let view = View {
                buffer: size_field(o, "buffer", None, &at)?,
                offset: size_field(o, "byteOffset", Some(0), &at)?,
                length: size_field(o, "byteLength", None, &at)?,
                stride: size_field(o, "byteStride", None, &at)?,
                count: size_field(o, "count", None, &at)?,
                mode,
                filter,
            };
            view.check(&at)?;
            // The view's own length is that of the decoded bytes, and its own stride (when it
            // has one) the extension's.
            let declared = v.byte_length.as_ref().and_then(|l| l.as_u64());
            let decoded = view.count.checked_mul(view.stride);
            if declared.is_none_or(|d| Some(d) != decoded.map(|x| x as u64)) {
                return Err(perr(format!(
                    "{at}: byteLength {declared:?} is not count × byteStride ({} × {})",
                    view.count, view.stride
                )));
            }
            if let Some(s) = &v.byte_stride {
                if s.as_u64() != Some(view.stride as u64) {
                    return Err(perr(format!(
                        "{at}: the view's byteStride {s} is not the extension's {}",
                        view.stride
                    )));
                }
            }
            out.views.insert(i, view);
        }
        Ok(out)
    }

    /// True when buffer `i` is a fallback: it holds no data of its own, only compressed views
    /// refer to it.
    pub(super) fn is_fallback(&self, i: usize) -> bool {
        self.fallback.contains(&i)
    }

    /// True when buffer view `i` is compressed.
    pub(super) fn is_compressed(&self, i: usize) -> bool {
        self.views.contains_key(&i)
    }

    /// Checks that an accessor of `elem`-byte elements read as indices (`index`) or positions
    /// may read compressed view `i`: index codecs hold indices of exactly their stride, and
    /// positions come from the attribute codec.
    pub(super) fn check_accessor(&self, i: usize, index: bool, elem: usize) -> Result<()> {
        let Some(v) = self.views.get(&i) else {
            return Ok(());
        };
        match (v.mode, index) {
            (Mode::Attributes, _) => Ok(()),
            (_, true) if elem == v.stride => Ok(()),
            (_, true) => Err(perr(format!(
                "bufferView {i} (meshopt-compressed): indices of {elem} bytes over a view of \
                 {}-byte indices",
                v.stride
            ))),
            (_, false) => Err(perr(format!(
                "bufferView {i} (meshopt-compressed): positions read from a view of mode {:?}",
                v.mode
            ))),
        }
    }

    /// The bytes compressed view `i` decodes to, charged against `budget` (bytes left for the
    /// read's decoded views) before anything is allocated.
    pub(super) fn decoded_size(
        &self,
        i: usize,
        limits: &ReadLimits,
        budget: usize,
    ) -> Result<usize> {
        let v = &self.views[&i];
        // A view holds at most as many vertices (or three indices per triangle) as the mesh
        // may have.
        match v.mode {
            Mode::Attributes => limits.check_vertices(v.count)?,
            Mode::Triangles | Mode::Indices => limits.check_faces(v.count / 3)?,
        }
        let size = v.count * v.stride; // checked against the view's length in `from_json`
        if size > budget {
            return Err(perr(format!(
                "bufferView {i} (meshopt-compressed) decodes to {size} bytes, past what is left \
                 of the {} bytes the read limits allow the file's compressed views together \
                 ({BYTES_PER_VERTEX} per vertex, {BYTES_PER_TRIANGLE} per triangle)",
                decoded_budget(limits)
            )));
        }
        Ok(size)
    }

    /// Decodes buffer view `i`, its encoded bytes read from `buffer(index)` (the bytes of the
    /// buffer its extension names), into the bytes of the uncompressed view. Call
    /// [`Meshopt::decoded_size`] first.
    pub(super) fn decode<'b>(
        &self,
        i: usize,
        buffer: impl Fn(usize) -> Option<&'b [u8]>,
    ) -> Result<Decoded> {
        let v = &self.views[&i];
        let at = format!("bufferView {i} (meshopt-compressed)");
        if self.is_fallback(v.buffer) {
            return Err(perr(format!(
                "{at}: its data is in buffer {}, a fallback buffer without data",
                v.buffer
            )));
        }
        let data = buffer(v.buffer)
            .ok_or_else(|| perr(format!("{at}: buffer {} does not exist", v.buffer)))?;
        let encoded = v
            .offset
            .checked_add(v.length)
            .and_then(|end| data.get(v.offset..end))
            .ok_or_else(|| {
                perr(format!(
                    "{at}: bytes {}..{} lie outside buffer {} ({} bytes)",
                    v.offset,
                    v.offset.saturating_add(v.length),
                    v.buffer,
                    data.len()
                ))
            })?;
        let len = v.count * v.stride;
        let mut out = Decoded {
            words: vec![0u32; len.div_ceil(4)],
            len,
        };
        if v.count == 0 {
            return Ok(out);
        }
        let dest: &mut [u8] = bytemuck::cast_slice_mut(&mut out.words);
        let dest = dest.as_mut_ptr().cast();
        // SAFETY: `dest` points to at least `count × stride` writable bytes, aligned to 4, the
        // size each decoder writes and the alignment of the 2- and 4-byte values it writes;
        // `encoded` is a live slice whose length is passed along, and meshoptimizer's decoders
        // read no further than that length on any input. Their preconditions (vertex stride a
        // multiple of 4 up to 256, index size 2 or 4, a whole number of triangles) were checked
        // by `View::check`.
        let code = unsafe {
            use meshopt::ffi;
            match v.mode {
                Mode::Attributes => ffi::meshopt_decodeVertexBuffer(
                    dest,
                    v.count,
                    v.stride,
                    encoded.as_ptr(),
                    encoded.len(),
                ),
                Mode::Triangles => ffi::meshopt_decodeIndexBuffer(
                    dest,
                    v.count,
                    v.stride,
                    encoded.as_ptr(),
                    encoded.len(),
                ),
                Mode::Indices => ffi::meshopt_decodeIndexSequence(
                    dest,
                    v.count,
                    v.stride,
                    encoded.as_ptr(),
                    encoded.len(),
                ),
            }
        };
        if code != 0 {
            return Err(perr(format!(
                "{at}: the compressed data does not decode (meshoptimizer error {code})"
            )));
        }
        // SAFETY: as above; each filter rewrites the `count × stride` bytes in place, with the
        // stride it requires (4 or 8, 8, a multiple of 4) checked by `View::check`.
        unsafe {
            use meshopt::ffi;
            let (n, s) = (v.count, v.stride);
            match v.filter {
                Filter::None => {}
                Filter::Octahedral => ffi::meshopt_decodeFilterOct(dest, n, s),
                Filter::Quaternion => ffi::meshopt_decodeFilterQuat(dest, n, s),
                Filter::Exponential => ffi::meshopt_decodeFilterExp(dest, n, s),
                Filter::Color => ffi::meshopt_decodeFilterColor(dest, n, s),
            }
        }
        Ok(out)
    }
}

impl View {
    /// The extension's rules on strides, counts and filters (which are also the decoders'
    /// preconditions).
    fn check(&self, at: &str) -> Result<()> {
        let s = self.stride;
        let ok_stride = match self.mode {
            Mode::Attributes => s > 0 && s <= 256 && s % 4 == 0,
            Mode::Triangles | Mode::Indices => s == 2 || s == 4,
        };
        if !ok_stride {
            return Err(perr(format!(
                "{at}: byteStride {s} for mode {:?} (ATTRIBUTES: a multiple of 4 up to 256; \
                 TRIANGLES and INDICES: 2 or 4)",
                self.mode
            )));
        }
        if self.mode == Mode::Triangles && self.count % 3 != 0 {
            return Err(perr(format!(
                "{at}: {} indices in TRIANGLES mode, not a multiple of 3",
                self.count
            )));
        }
        let ok_filter = match self.filter {
            Filter::None => true,
            _ if self.mode != Mode::Attributes => false,
            Filter::Octahedral | Filter::Color => s == 4 || s == 8,
            Filter::Quaternion => s == 8,
            Filter::Exponential => true,
        };
        if !ok_filter {
            return Err(perr(format!(
                "{at}: filter {:?} does not apply to mode {:?} with byteStride {s}",
                self.filter, self.mode
            )));
        }
        Ok(())
    }
}
