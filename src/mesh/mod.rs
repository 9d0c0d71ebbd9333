//! Triangle meshes: the in-memory type, format readers/writers, generators and preparation.
//!
//! Everything here is pure and synchronous: bytes in, [`Mesh`] out. Nothing knows of HTTP or
//! storage.

pub(crate) mod buckets;
pub mod cap;
pub mod decimate;
pub mod generate;
pub mod prepare;
pub mod read;
pub mod samples;
pub mod smooth;
pub mod topology;
pub mod weld;
pub mod write;

pub use read::{detect_format, read_mesh, read_path, Format, ReadLimits};
pub use write::write_mesh;

use serde::{Deserialize, Serialize};

/// A triangle mesh: vertex positions and triangles as indices into `vertices`.
///
/// Readers produce it as found in the file (polygons triangulated, objects merged, node transforms
/// applied); [`prepare::prepare`] cleans it. Indices are `u32`: limits keep meshes far below.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<[f64; 3]>,
    /// Triangles, counter-clockwise when seen from outside where the source was consistent.
    pub faces: Vec<[u32; 3]>,
    /// What a lenient read ([`ReadLimits::lenient`]) repaired in the file (a declared count or
    /// length that disagreed with the data), one sentence each; empty otherwise. Carried into
    /// the preparation report as `read_repairs`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub repairs: Vec<String>,
}

impl Mesh {
    /// Builds a mesh from positions and triangles (no validation; see the preparation step).
    pub fn new(vertices: Vec<[f64; 3]>, faces: Vec<[u32; 3]>) -> Self {
        Self {
            vertices,
            faces,
            repairs: Vec::new(),
        }
    }

    /// Total surface area (sum of triangle areas).
    pub fn area(&self) -> f64 {
        self.faces.iter().map(|f| triangle_area(self, f)).sum()
    }

    /// Applies `p -> R p + t` (R given row-major) to every vertex.
    pub fn transform(&mut self, r: [[f64; 3]; 3], t: [f64; 3]) {
        for v in &mut self.vertices {
            let p = *v;
            for (i, row) in r.iter().enumerate() {
                v[i] = row[0] * p[0] + row[1] * p[1] + row[2] * p[2] + t[i];
            }
        }
    }

    /// Multiplies every coordinate by `s`.
    pub fn scale(&mut self, s: f64) {
        for v in &mut self.vertices {
            for c in v.iter_mut() {
                *c *= s;
            }
        }
    }
}

/// The axis-aligned bounding box `(lo, hi)` of `points` (`lo` = +∞, `hi` = −∞ when there are
/// none).
pub(crate) fn bounding_box<'a>(
    points: impl IntoIterator<Item = &'a [f64; 3]>,
) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}

/// Area of one triangle of `mesh`.
pub fn triangle_area(mesh: &Mesh, f: &[u32; 3]) -> f64 {
    face_area(&mesh.vertices, f)
}

/// [`triangle_area`] over a bare vertex array (for passes that hold vertices and faces apart).
pub(crate) fn face_area(vertices: &[[f64; 3]], f: &[u32; 3]) -> f64 {
    let [a, b, c] = f.map(|i| vertices[i as usize]);
    0.5 * norm(cross(sub(b, a), sub(c, a)))
}

#[inline]
pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}
