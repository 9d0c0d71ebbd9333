//! glTF buffer views compressed with meshoptimizer (`EXT_meshopt_compression`, and its
//! ratified form `KHR_meshopt_compression`): what `gltfpack -cc` and
//! `gltf-transform meshopt` write.
//!
//! Such a view names, in its extension, a range of another buffer holding the encoded bytes,
//! how many elements of what stride they decode to, the codec (`ATTRIBUTES`, `TRIANGLES`,
//! `INDICES`) and a filter applied after decoding (`NONE`, `OCTAHEDRAL`, `QUATERNION`,
//! `EXPONENTIAL`, `COLOR`). The view's own buffer is then usually a *fallback* buffer that holds
//! no data at all. Each compressed view that a position or index accessor reads is decoded here,
//! once, into bytes laid out exactly as the uncompressed view would be; the glTF reader then
//! reads them as any other view.
//!
//! The decoding is meshoptimizer's own (`meshopt_decodeVertexBuffer`, `…IndexBuffer`,
//! `…IndexSequence`, `…Filter*`), through the `meshopt` crate's bindings, which the project
//! already builds for simplification (`crate::mesh::decimate`); writing the codec again would
//! only add a second one to keep right. meshoptimizer documents these decoders as safe on
//! untrusted input; what they `assert` (strides, counts) is checked here first, since a failed
//! C++ assertion would abort the process, and every count is bounded by the read limits before
//! anything is allocated.

use super::ReadLimits;
use crate::error::{Error, Result};
use std::collections::{HashMap, HashSet};

const F: &str = "glTF";
/// The two names of the extension (same bitstream; the ratified one also allows vertex codec
/// version 1 and the `COLOR` filter, both of which the decoder reads).
const NAMES: [&str; 2] = ["EXT_meshopt_compression", "KHR_meshopt_compression"];

fn perr(msg: impl Into<String>) -> Error {
    Error::parse(F, None, msg)
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

/// The meshopt extension object of a buffer or buffer view, if it has one.
fn extension(item: &serde_json::Value) -> Option<(&'static str, &serde_json::Value)> {
    let ext = item.get("extensions")?;
    NAMES.iter().find_map(|&n| ext.get(n).map(|v| (n, v)))
}

impl Meshopt {
    /// Reads the extension objects from the document's JSON (the `gltf` crate, built without
    /// its `extensions` feature, does not keep them). Errors name the view and what is wrong.
    pub(super) fn from_json(json: &[u8]) -> Result<Meshopt> {
        // Cheap refusal of the common case: no extension name in the text at all.
        if !NAMES
            .iter()
            .any(|n| json.windows(n.len()).any(|w| w == n.as_bytes()))
        {
            return Ok(Meshopt::default());
        }
        let root: serde_json::Value =
            serde_json::from_slice(json).map_err(|e| perr(format!("invalid glTF JSON: {e}")))?;
        let mut out = Meshopt::default();
        let list = |key: &str| {
            root.get(key)
                .and_then(|v| v.as_array())
                .map(Vec::as_slice)
                .unwrap_or(&[])
        };
        for (i, b) in list("buffers").iter().enumerate() {
            if let Some((_, e)) = extension(b) {
                if e.get("fallback").and_then(|f| f.as_bool()) == Some(true) {
                    out.fallback.insert(i);
                }
            }
        }
        for (i, v) in list("bufferViews").iter().enumerate() {
            let Some((name, e)) = extension(v) else {
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
            // The view's own length is that of the decoded bytes.
            let declared = v.get("byteLength").and_then(|l| l.as_u64());
            let decoded = view.count.checked_mul(view.stride);
            if declared.is_none_or(|d| Some(d) != decoded.map(|x| x as u64)) {
                return Err(perr(format!(
                    "{at}: byteLength {declared:?} is not count × byteStride ({} × {})",
                    view.count, view.stride
                )));
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

    /// Decodes buffer view `i`, its encoded bytes read from `source` (the bytes of the buffer
    /// its extension names, `buffer(index)`), into the bytes of the uncompressed view.
    pub(super) fn decode<'b>(
        &self,
        i: usize,
        buffer: impl Fn(usize) -> Option<&'b [u8]>,
        limits: &ReadLimits,
    ) -> Result<Vec<u8>> {
        let v = &self.views[&i];
        let at = format!("bufferView {i} (meshopt-compressed)");
        // Bounded before allocating: a view holds at most as many vertices (or three indices
        // per triangle) as the mesh may have.
        match v.mode {
            Mode::Attributes => limits.check_vertices(v.count)?,
            Mode::Triangles | Mode::Indices => limits.check_faces(v.count / 3)?,
        }
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
        let mut out = vec![0u8; v.count * v.stride];
        if v.count == 0 {
            return Ok(out);
        }
        // SAFETY: `out` holds exactly `count × stride` bytes, the size each decoder writes;
        // `encoded` is a live slice whose length is passed along, and meshoptimizer's decoders
        // read no further than that length on any input. The preconditions they assert
        // (vertex stride a multiple of 4 up to 256, index size 2 or 4, a triangle count that
        // is whole, filter strides) were checked by `View::check`.
        let code = unsafe {
            use meshopt::ffi;
            match v.mode {
                Mode::Attributes => ffi::meshopt_decodeVertexBuffer(
                    out.as_mut_ptr().cast(),
                    v.count,
                    v.stride,
                    encoded.as_ptr(),
                    encoded.len(),
                ),
                Mode::Triangles => ffi::meshopt_decodeIndexBuffer(
                    out.as_mut_ptr().cast(),
                    v.count,
                    v.stride,
                    encoded.as_ptr(),
                    encoded.len(),
                ),
                Mode::Indices => ffi::meshopt_decodeIndexSequence(
                    out.as_mut_ptr().cast(),
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
        // stride it requires checked by `View::check`.
        unsafe {
            use meshopt::ffi;
            let (p, n, s) = (out.as_mut_ptr().cast(), v.count, v.stride);
            match v.filter {
                Filter::None => {}
                Filter::Octahedral => ffi::meshopt_decodeFilterOct(p, n, s),
                Filter::Quaternion => ffi::meshopt_decodeFilterQuat(p, n, s),
                Filter::Exponential => ffi::meshopt_decodeFilterExp(p, n, s),
                Filter::Color => ffi::meshopt_decodeFilterColor(p, n, s),
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
