//! The malformed-input corpus as generated tests: every format × every failure class, each with
//! the error code it must give after reading and preparing (`read_mesh` then `prepare` with the
//! default options), plus the issue-11 findings reproduced one by one, and proptest generators
//! over every reader (no panic, a known code, bounded allocation).
//!
//! Nothing here is a data file: every input is generated from a small `Spec`.

use base64::Engine;
use proptest::prelude::*;
use shapeseek::mesh::prepare::{prepare, PrepareOptions, PrepareReport};
use shapeseek::mesh::read::{read_mesh, Format, ReadLimits};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

// ------------------------------------------------------------------ allocation accounting

/// Counts the bytes live and the peak per thread, so a test can bound what one read allocates.
struct Counting;

thread_local! {
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(l) };
        if !p.is_null() {
            let _ = LIVE.try_with(|c| {
                let v = c.get() + l.size();
                c.set(v);
                let _ = PEAK.try_with(|p| p.set(p.get().max(v)));
            });
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) };
        let _ = LIVE.try_with(|c| c.set(c.get().saturating_sub(l.size())));
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Peak bytes allocated (above what was live before) by `f` on this thread.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    let out = f();
    (out, PEAK.with(Cell::get) - base)
}

// ------------------------------------------------------------------ generated files

/// A mesh as a file would declare it.
#[derive(Clone, Debug)]
struct Spec {
    v: Vec<[f64; 3]>,
    /// Polygons, 0-based indices (may be out of range or negative on purpose).
    f: Vec<Vec<i64>>,
    /// Declared vertex / face counts (OFF, PLY; STL uses `nf`; glTF uses `nf` × 3 indices).
    nv: u64,
    nf: u64,
    /// Extra data after what is declared (one more face / triangle / buffer bytes).
    trailing: bool,
}

impl Spec {
    fn new(v: Vec<[f64; 3]>, f: Vec<Vec<i64>>) -> Self {
        let (nv, nf) = (v.len() as u64, f.len() as u64);
        Spec {
            v,
            f,
            nv,
            nf,
            trailing: false,
        }
    }

    fn sphere() -> Self {
        let m = shapeseek::mesh::generate::icosphere(1);
        Spec::new(
            m.vertices,
            m.faces
                .iter()
                .map(|f| f.iter().map(|&i| i as i64).collect())
                .collect(),
        )
    }

    fn triangles(&self) -> Vec<[i64; 3]> {
        self.f
            .iter()
            .flat_map(|p| (1..p.len().saturating_sub(1)).map(move |k| [p[0], p[k], p[k + 1]]))
            .collect()
    }

    fn pos(&self, i: i64) -> [f64; 3] {
        self.v.get(i as usize).copied().unwrap_or([0.0; 3])
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Fmt {
    Obj,
    Off,
    PlyAscii,
    PlyBinary,
    StlAscii,
    StlBinary,
    Gltf,
    Glb,
}

const FMTS: [Fmt; 8] = [
    Fmt::Obj,
    Fmt::Off,
    Fmt::PlyAscii,
    Fmt::PlyBinary,
    Fmt::StlAscii,
    Fmt::StlBinary,
    Fmt::Gltf,
    Fmt::Glb,
];

impl Fmt {
    fn hint(self) -> Format {
        match self {
            Fmt::Obj => Format::Obj,
            Fmt::Off => Format::Off,
            Fmt::PlyAscii | Fmt::PlyBinary => Format::Ply,
            Fmt::StlAscii | Fmt::StlBinary => Format::Stl,
            Fmt::Gltf => Format::Gltf,
            Fmt::Glb => Format::Glb,
        }
    }
    fn binary(self) -> bool {
        matches!(self, Fmt::PlyBinary | Fmt::StlBinary | Fmt::Glb)
    }
}

fn num(x: f64) -> String {
    format!("{x:?}")
}

fn emit(fmt: Fmt, s: &Spec) -> Vec<u8> {
    let mut o = String::new();
    match fmt {
        Fmt::Obj => {
            for p in &s.v {
                o += &format!("v {} {} {}\n", num(p[0]), num(p[1]), num(p[2]));
            }
            for f in &s.f {
                o.push('f');
                for &i in f {
                    o += &format!(" {}", if i < 0 { i } else { i + 1 });
                }
                o.push('\n');
            }
            o.into_bytes()
        }
        Fmt::Off => {
            o += &format!("OFF\n{} {} 0\n", s.nv, s.nf);
            for p in &s.v {
                o += &format!("{} {} {}\n", num(p[0]), num(p[1]), num(p[2]));
            }
            for f in &s.f {
                o += &f.len().to_string();
                for &i in f {
                    o += &format!(" {i}");
                }
                o.push('\n');
            }
            if s.trailing {
                o += "3 0 1 2\n";
            }
            o.into_bytes()
        }
        Fmt::PlyAscii | Fmt::PlyBinary => {
            let enc = if fmt == Fmt::PlyAscii {
                "ascii"
            } else {
                "binary_little_endian"
            };
            o += &format!(
                "ply\nformat {enc} 1.0\nelement vertex {}\nproperty double x\nproperty double y\n\
                 property double z\nelement face {}\nproperty list int int vertex_indices\nend_header\n",
                s.nv, s.nf
            );
            let mut b = o.into_bytes();
            let mut faces = s.f.clone();
            if s.trailing {
                faces.push(vec![0, 1, 2]);
            }
            if fmt == Fmt::PlyAscii {
                let mut t = String::new();
                for p in &s.v {
                    t += &format!("{} {} {}\n", num(p[0]), num(p[1]), num(p[2]));
                }
                for f in &faces {
                    t += &f.len().to_string();
                    for &i in f {
                        t += &format!(" {i}");
                    }
                    t.push('\n');
                }
                b.extend(t.into_bytes());
            } else {
                for p in &s.v {
                    for c in p {
                        b.extend(c.to_le_bytes());
                    }
                }
                for f in &faces {
                    b.extend((f.len() as i32).to_le_bytes());
                    for &i in f {
                        b.extend((i as i32).to_le_bytes());
                    }
                }
            }
            b
        }
        Fmt::StlAscii => {
            o += "solid t\n";
            for t in s.triangles() {
                o += "facet normal 0 0 0\nouter loop\n";
                for i in t {
                    let p = s.pos(i);
                    o += &format!("vertex {} {} {}\n", num(p[0]), num(p[1]), num(p[2]));
                }
                o += "endloop\nendfacet\n";
            }
            o += "endsolid t\n";
            o.into_bytes()
        }
        Fmt::StlBinary => {
            let mut tris = s.triangles();
            let declared = if s.nf == s.f.len() as u64 {
                tris.len() as u64
            } else {
                s.nf
            };
            if s.trailing {
                tris.push(tris.first().copied().unwrap_or([0, 0, 0]));
            }
            let mut b = vec![b' '; 80];
            b.extend((declared as u32).to_le_bytes());
            for t in tris {
                b.extend([0u8; 12]);
                for i in t {
                    for c in s.pos(i) {
                        b.extend((c as f32).to_le_bytes());
                    }
                }
                b.extend([0u8; 2]);
            }
            b
        }
        Fmt::Gltf | Fmt::Glb => gltf(fmt == Fmt::Glb, s, "2.0", 0),
    }
}

/// glTF / GLB of `s` (triangles, u32 indices). `nf` sets the declared index count (`3 nf`),
/// `trailing` adds 8 buffer bytes beyond `byteLength`, `extra_indices` adds indices to the
/// declared count.
fn gltf(glb: bool, s: &Spec, version: &str, extra_indices: usize) -> Vec<u8> {
    let tris = s.triangles();
    let mut buf = Vec::new();
    for p in &s.v {
        for c in p {
            buf.extend((*c as f32).to_le_bytes());
        }
    }
    let pos_len = buf.len();
    for t in &tris {
        for &i in t {
            buf.extend((i as u32).to_le_bytes());
        }
    }
    for _ in 0..extra_indices {
        buf.extend(0u32.to_le_bytes());
    }
    let idx_len = buf.len() - pos_len;
    let declared_len = buf.len();
    let idx_count = if s.nf == s.f.len() as u64 {
        3 * tris.len() + extra_indices
    } else {
        3 * s.nf as usize
    };
    if s.trailing {
        buf.extend([0u8; 8]);
    }
    let mut buffer = serde_json::json!({ "byteLength": declared_len });
    if !glb {
        buffer["uri"] = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&buf)
        )
        .into();
    }
    let doc = serde_json::json!({
        "asset": { "version": version },
        "scene": 0, "scenes": [ { "nodes": [0] } ], "nodes": [ { "mesh": 0 } ],
        "meshes": [ { "primitives": [ { "attributes": { "POSITION": 0 }, "indices": 1 } ] } ],
        "accessors": [
            { "bufferView": 0, "componentType": 5126, "count": s.nv, "type": "VEC3",
              "min": [0, 0, 0], "max": [0, 0, 0] },
            { "bufferView": 1, "componentType": 5125, "count": idx_count, "type": "SCALAR" }
        ],
        "bufferViews": [
            { "buffer": 0, "byteOffset": 0, "byteLength": pos_len },
            { "buffer": 0, "byteOffset": pos_len, "byteLength": idx_len }
        ],
        "buffers": [buffer]
    });
    let mut json = serde_json::to_vec(&doc).unwrap();
    if !glb {
        return json;
    }
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    while buf.len() % 4 != 0 {
        buf.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + buf.len();
    let mut b = b"glTF".to_vec();
    b.extend(2u32.to_le_bytes());
    b.extend((total as u32).to_le_bytes());
    b.extend((json.len() as u32).to_le_bytes());
    b.extend(b"JSON");
    b.extend(json);
    b.extend((buf.len() as u32).to_le_bytes());
    b.extend(b"BIN\0");
    b.extend(buf);
    b
}

fn strict() -> ReadLimits {
    ReadLimits::default()
}

fn lenient() -> ReadLimits {
    ReadLimits {
        lenient: true,
        ..ReadLimits::default()
    }
}

/// Reads and prepares; the code of the first error, or the report.
fn ingest(bytes: &[u8], hint: Format, limits: &ReadLimits) -> Result<PrepareReport, String> {
    let mesh = read_mesh(bytes, Some(hint), limits).map_err(|e| e.code().to_string())?;
    prepare(&mesh, &PrepareOptions::default())
        .map(|(_, r)| r)
        .map_err(|e| e.code().to_string())
}

// ------------------------------------------------------------------ failure classes

/// Every failure class: its name, and for each format the malformed bytes and expected code
/// (`None` where the class does not exist in that format, e.g. declared counts in OBJ).
/// One corpus entry: failure class, and the bytes with the expected code (`None`: the class does
/// not apply to the format).
type Case = (&'static str, Option<(Vec<u8>, &'static str)>);

fn corpus(fmt: Fmt) -> Vec<Case> {
    let base = Spec::sphere();
    let has_counts = !matches!(fmt, Fmt::Obj | Fmt::StlAscii);
    let has_indices = !matches!(fmt, Fmt::StlAscii | Fmt::StlBinary);
    let polygons = matches!(fmt, Fmt::Obj | Fmt::Off | Fmt::PlyAscii | Fmt::PlyBinary);
    let mut out = Vec::new();

    out.push(("valid", Some((emit(fmt, &base), "ok"))));

    // Truncation: binary and glTF lose their last 3 bytes, ASCII STL half its text, the other
    // text formats the last corner of their last face.
    let full = emit(fmt, &base);
    let cut = if fmt.binary() || fmt == Fmt::Gltf {
        full[..full.len() - 3].to_vec()
    } else if fmt == Fmt::StlAscii {
        full[..full.len() / 2].to_vec()
    } else {
        let trimmed = &full[..full.len() - 1];
        let sp = trimmed.iter().rposition(|&b| b == b' ').unwrap();
        full[..sp].to_vec()
    };
    out.push(("truncated", Some((cut, "mesh.parse"))));

    // Declared counts larger than the data.
    out.push((
        "count_above_data",
        has_counts.then(|| {
            let mut s = base.clone();
            s.nf += 1;
            (emit(fmt, &s), "mesh.parse")
        }),
    ));
    // Declared counts smaller than the data: refused, not repaired silently.
    out.push((
        "count_below_data",
        has_counts.then(|| {
            let mut s = base.clone();
            s.trailing = true;
            (emit(fmt, &s), "mesh.inconsistent")
        }),
    ));
    let gl = matches!(fmt, Fmt::Gltf | Fmt::Glb);
    out.push((
        "index_count_not_multiple_of_3",
        gl.then(|| (gltf(fmt == Fmt::Glb, &base, "2.0", 2), "mesh.inconsistent")),
    ));
    out.push((
        "asset_version_1",
        gl.then(|| (gltf(fmt == Fmt::Glb, &base, "1.0", 0), "mesh.inconsistent")),
    ));
    out.push((
        "index_out_of_range",
        has_indices.then(|| {
            let mut s = base.clone();
            s.f[5][1] = s.v.len() as i64 + 7;
            (emit(fmt, &s), "mesh.parse")
        }),
    ));
    out.push((
        "negative_index",
        (has_indices && !gl).then(|| {
            let mut s = base.clone();
            s.f[5][1] = -(s.v.len() as i64) - 5;
            (emit(fmt, &s), "mesh.parse")
        }),
    ));
    out.push(("non_finite", {
        let mut s = base.clone();
        s.v[3][1] = f64::NAN;
        s.v[4][2] = f64::INFINITY;
        Some((emit(fmt, &s), "mesh.non_finite"))
    }));
    out.push((
        "huge_declared_vertices",
        (has_counts && fmt != Fmt::StlBinary).then(|| {
            let mut s = base.clone();
            s.nv = 4_000_000_000;
            (emit(fmt, &s), "limit.vertices")
        }),
    ));
    out.push((
        "huge_declared_faces",
        (has_counts && !gl).then(|| {
            let mut s = base.clone();
            s.nf = 4_000_000_000;
            (emit(fmt, &s), "limit.faces")
        }),
    ));
    out.push((
        "huge_polygon",
        polygons.then(|| {
            let n = 2000;
            let v: Vec<[f64; 3]> = (0..n)
                .map(|k| {
                    let a = k as f64 * std::f64::consts::TAU / n as f64;
                    [a.cos(), a.sin(), 0.0]
                })
                .collect();
            let s = Spec::new(v, vec![(0..n as i64).collect()]);
            (emit(fmt, &s), "limit.polygon_vertices")
        }),
    ));
    let tri = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    out.push((
        "one_triangle",
        Some((
            emit(fmt, &Spec::new(tri.clone(), vec![vec![0, 1, 2]])),
            "mesh.too_few_faces",
        )),
    ));
    out.push((
        "identical_triangles",
        Some((
            emit(fmt, &Spec::new(tri.clone(), vec![vec![0, 1, 2]; 500])),
            "mesh.too_few_faces",
        )),
    ));
    out.push(("scattered_triangles", {
        let mut v = Vec::new();
        let mut f = Vec::new();
        for k in 0..600 {
            let x = 3.0 * k as f64;
            v.extend([[x, 0.0, 0.0], [x + 1.0, 0.0, 0.0], [x, 1.0, 0.0]]);
            f.push(vec![3 * k, 3 * k + 1, 3 * k + 2]);
        }
        Some((emit(fmt, &Spec::new(v, f)), "mesh.area_kept"))
    }));
    out.push(("zero_area", {
        let v = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [3.0, 0.0, 0.0],
        ];
        let s = Spec::new(v, vec![vec![0, 1, 2], vec![1, 2, 3]]);
        Some((emit(fmt, &s), "mesh.empty"))
    }));
    out.push((
        "no_faces",
        (fmt != Fmt::StlBinary && fmt != Fmt::StlAscii).then(|| {
            let mut s = base.clone();
            s.f.clear();
            s.nf = 0;
            // glTF with an empty index accessor: no triangles.
            (emit(fmt, &s), "mesh.empty")
        }),
    ));
    out
}

#[test]
fn malformed_corpus_every_format_every_class() {
    let mut checked = 0;
    let mut table = String::new();
    for fmt in FMTS {
        for (class, case) in corpus(fmt) {
            let Some((bytes, want)) = case else {
                table += &format!("{fmt:?}/{class}: n/a\n");
                continue;
            };
            let got = match ingest(&bytes, fmt.hint(), &strict()) {
                Ok(_) => "ok".to_string(),
                Err(c) => c,
            };
            assert_eq!(got, want, "{fmt:?}/{class}");
            checked += 1;
        }
    }
    eprintln!("{checked} malformed cases checked\n{table}");
    assert!(checked >= 100, "{checked}");
}

/// The lenient read keeps the old behaviour for every count-below-data case, and says so.
#[test]
fn lenient_reads_repair_and_report() {
    let base = Spec::sphere();
    let mut cases: Vec<(Fmt, Vec<u8>)> = Vec::new();
    for fmt in [
        Fmt::Off,
        Fmt::PlyAscii,
        Fmt::PlyBinary,
        Fmt::StlBinary,
        Fmt::Gltf,
        Fmt::Glb,
    ] {
        let mut s = base.clone();
        s.trailing = true;
        cases.push((fmt, emit(fmt, &s)));
    }
    for glb in [false, true] {
        let f = if glb { Fmt::Glb } else { Fmt::Gltf };
        cases.push((f, gltf(glb, &base, "2.0", 2)));
        cases.push((f, gltf(glb, &base, "1.0", 0)));
    }
    for (fmt, bytes) in cases {
        assert_eq!(
            ingest(&bytes, fmt.hint(), &strict()).unwrap_err(),
            "mesh.inconsistent",
            "{fmt:?}"
        );
        let r = ingest(&bytes, fmt.hint(), &lenient()).unwrap();
        assert_eq!(r.read_repairs.len(), 1, "{fmt:?}: {:?}", r.read_repairs);
        assert_eq!(r.faces_out, 80, "{fmt:?}");
        let json = serde_json::to_value(&r).unwrap();
        assert!(json["read_repairs"].is_array(), "{fmt:?}");
    }
    // Nothing repaired: the field is absent.
    let r = ingest(&emit(Fmt::Off, &base), Format::Off, &lenient()).unwrap();
    assert!(r.read_repairs.is_empty());
    assert!(serde_json::to_value(&r)
        .unwrap()
        .get("read_repairs")
        .is_none());
}

// ------------------------------------------------------------------ issue 11, one by one

#[test]
fn issue11_one_triangle_is_refused() {
    let s = Spec::new(
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        vec![vec![0, 1, 2]],
    );
    assert_eq!(
        ingest(&emit(Fmt::Obj, &s), Format::Obj, &strict()).unwrap_err(),
        "mesh.too_few_faces"
    );
}

#[test]
fn issue11_600_disconnected_triangles_are_refused() {
    let (bytes, want) = corpus(Fmt::Obj)
        .into_iter()
        .find(|c| c.0 == "scattered_triangles")
        .and_then(|c| c.1)
        .unwrap();
    assert_eq!(ingest(&bytes, Format::Obj, &strict()).unwrap_err(), want);
}

#[test]
fn issue11_500_identical_stl_triangles_are_refused() {
    let s = Spec::new(
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        vec![vec![0, 1, 2]; 500],
    );
    assert_eq!(
        ingest(&emit(Fmt::StlBinary, &s), Format::Stl, &strict()).unwrap_err(),
        "mesh.too_few_faces"
    );
}

#[test]
fn issue11_ply_of_a_4mb_comment_and_one_triangle_is_refused() {
    let mut b = b"ply\nformat ascii 1.0\ncomment ".to_vec();
    b.extend(std::iter::repeat_n(b'x', 4 << 20));
    b.extend(
        b"\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
    );
    assert_eq!(
        ingest(&b, Format::Ply, &strict()).unwrap_err(),
        "mesh.too_few_faces"
    );
}

#[test]
fn issue11_a_20000_gon_is_refused_quickly() {
    let n = 20_000;
    let v: Vec<[f64; 3]> = (0..n)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / n as f64;
            [a.cos(), a.sin(), 0.0]
        })
        .collect();
    let bytes = emit(Fmt::Obj, &Spec::new(v, vec![(0..n as i64).collect()]));
    assert!(bytes.len() > 300_000, "{}", bytes.len());
    let t = std::time::Instant::now();
    assert_eq!(
        ingest(&bytes, Format::Obj, &strict()).unwrap_err(),
        "limit.polygon_vertices"
    );
    assert!(t.elapsed().as_secs_f64() < 1.0, "{:?}", t.elapsed());
}

#[test]
fn issue11_stl_declaring_7_triangles_holding_8_is_refused() {
    let mut s = Spec::sphere();
    s.f.truncate(7);
    s.nf = 7;
    s.trailing = true;
    let b = emit(Fmt::StlBinary, &s);
    assert_eq!(b.len(), 84 + 50 * 8);
    let e = read_mesh(&b, Some(Format::Stl), &strict()).unwrap_err();
    assert_eq!(e.code(), "mesh.inconsistent", "{e}");
    assert!(e.to_string().contains("7 triangles"), "{e}");
}

#[test]
fn issue11_gltf_byte_length_shorter_than_its_data_is_refused() {
    let mut s = Spec::sphere();
    s.trailing = true;
    for glb in [false, true] {
        let e = read_mesh(&gltf(glb, &s, "2.0", 0), None, &strict()).unwrap_err();
        assert_eq!(e.code(), "mesh.inconsistent", "{e}");
    }
}

#[test]
fn issue11_gltf_index_count_not_a_multiple_of_3_is_refused() {
    let e = read_mesh(&gltf(false, &Spec::sphere(), "2.0", 1), None, &strict()).unwrap_err();
    assert_eq!(e.code(), "mesh.inconsistent", "{e}");
}

#[test]
fn issue11_gltf_asset_version_1_is_refused() {
    let e = read_mesh(&gltf(false, &Spec::sphere(), "1.0", 0), None, &strict()).unwrap_err();
    assert_eq!(e.code(), "mesh.inconsistent", "{e}");
    assert!(e.to_string().contains("1.0"), "{e}");
}

// ------------------------------------------------------------------ generators

/// Codes a reader may return on hostile input (anything else, or a panic, is a bug).
const READ_CODES: [&str; 8] = [
    "mesh.parse",
    "mesh.format",
    "mesh.inconsistent",
    "mesh.external_reference",
    "limit.bytes",
    "limit.vertices",
    "limit.faces",
    "limit.polygon_vertices",
];

fn coord() -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => -10.0f64..10.0,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(1e308),
        1 => Just(-0.0),
    ]
}

fn spec() -> impl Strategy<Value = Spec> {
    (
        prop::collection::vec([coord(), coord(), coord()], 0..12),
        prop::collection::vec(prop::collection::vec(-14i64..16, 0..7), 0..10),
        prop_oneof![4 => Just(0i64), 1 => -2i64..3, 1 => Just(4_000_000_000i64)],
        prop_oneof![4 => Just(0i64), 1 => -2i64..3, 1 => Just(4_000_000_000i64)],
        any::<bool>(),
    )
        .prop_map(|(v, f, dv, df, trailing)| {
            let nv = (v.len() as i64 + dv).max(0) as u64;
            let nf = (f.len() as i64 + df).max(0) as u64;
            Spec {
                v,
                f,
                nv,
                nf,
                trailing,
            }
        })
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: std::env::var("MALFORMED_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(64),
        ..ProptestConfig::default()
    })]

    /// Every reader, on generated files with wrong counts, indices, non-finite values, trailing
    /// data and truncation: no panic, a known code, and at most 64 bytes allocated per input
    /// byte (plus 1 MiB) — never sized by a declared count.
    #[test]
    fn generated_files_never_panic_and_allocate_boundedly(
        s in spec(),
        fmt in prop::sample::select(FMTS.to_vec()),
        cut in prop::option::of(0.0f64..1.0),
        lenient_read in any::<bool>(),
    ) {
        let mut bytes = emit(fmt, &s);
        if let Some(c) = cut {
            bytes.truncate((bytes.len() as f64 * c) as usize);
        }
        let limits = ReadLimits { lenient: lenient_read, ..ReadLimits::default() };
        let (res, peak) = peak_of(|| read_mesh(&bytes, Some(fmt.hint()), &limits));
        if let Err(e) = &res {
            prop_assert!(READ_CODES.contains(&e.code()), "{fmt:?}: {e}");
        }
        prop_assert!(peak <= 64 * bytes.len() + (1 << 20), "{fmt:?}: {peak} bytes for {}", bytes.len());
        if let Ok(m) = res {
            // Preparation of whatever was read never panics either.
            let _ = prepare(&m, &PrepareOptions::default());
        }
    }
}
