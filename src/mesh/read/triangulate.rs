//! Polygon triangulation shared by the OBJ, OFF and PLY readers.
//!
//! Triangles and convex quads are emitted directly. Larger polygons (and quads that are not
//! convex) are projected onto the plane orthogonal to their Newell normal (the best-fit plane
//! of a planar or nearly planar polygon) and triangulated by ear clipping, which is correct for
//! any simple polygon, convex or not. Ear clipping is O(n²) per polygon: polygons with more than
//! [`MAX_EAR_CLIP`] corners fall back to a fan (correct for convex polygons only), which bounds
//! the work on hostile input. Output triangles keep the polygon's winding.

use crate::mesh::{cross, dot, sub};

/// Polygons with more corners than this are fan-triangulated (see the module docs).
///
/// Bounds hostile input: ear clipping costs at most ~n³/6 orientation tests for an n-gon, i.e.
/// ~4·10⁴ at n = 64, and the face limit bounds the number of such polygons (4 000 000 triangles
/// allow ~65 000 64-gons, a few seconds at worst). Real meshes rarely have larger concave faces.
pub const MAX_EAR_CLIP: usize = 64;

/// Triangulates the polygon `poly` (indices into `vertices`, all already checked in range) and
/// appends the triangles to `out`. Polygons with fewer than 3 corners produce nothing; a polygon
/// with n corners produces n − 2 triangles.
pub fn triangulate(poly: &[u32], vertices: &[[f64; 3]], out: &mut Vec<[u32; 3]>) {
    let n = poly.len();
    if n < 3 {
        return;
    }
    if n == 3 {
        out.push([poly[0], poly[1], poly[2]]);
        return;
    }
    if n > MAX_EAR_CLIP {
        fan(poly, out);
        return;
    }
    let p3: Vec<[f64; 3]> = poly
        .iter()
        .map(|&i| vertices.get(i as usize).copied().unwrap_or([0.0; 3]))
        .collect();
    // Newell normal.
    let mut nrm = [0.0f64; 3];
    for i in 0..n {
        let a = p3[i];
        let b = p3[(i + 1) % n];
        nrm[0] += (a[1] - b[1]) * (a[2] + b[2]);
        nrm[1] += (a[2] - b[2]) * (a[0] + b[0]);
        nrm[2] += (a[0] - b[0]) * (a[1] + b[1]);
    }
    let len = dot(nrm, nrm).sqrt();
    if len.is_nan() || len <= 0.0 || !len.is_finite() {
        // Degenerate (collinear / non-finite) polygon: nothing better than a fan.
        fan(poly, out);
        return;
    }
    let nrm = [nrm[0] / len, nrm[1] / len, nrm[2] / len];
    // Orthonormal basis (u, v) of the plane, with u × v = nrm so projected polygon is CCW.
    let helper = if nrm[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u = {
        let c = cross(helper, nrm);
        let l = dot(c, c).sqrt();
        [c[0] / l, c[1] / l, c[2] / l]
    };
    let v = cross(nrm, u);
    let origin = p3[0];
    let p2: Vec<[f64; 2]> = p3
        .iter()
        .map(|&p| {
            let d = sub(p, origin);
            [dot(d, u), dot(d, v)]
        })
        .collect();
    ear_clip(poly, &p2, out);
}

fn fan(poly: &[u32], out: &mut Vec<[u32; 3]>) {
    for i in 1..poly.len() - 1 {
        out.push([poly[0], poly[i], poly[i + 1]]);
    }
}

fn orient(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
}

/// Ear clipping of a polygon whose projection `p2` is counter-clockwise (positive area).
fn ear_clip(poly: &[u32], p2: &[[f64; 2]], out: &mut Vec<[u32; 3]>) {
    let mut idx: Vec<usize> = (0..poly.len()).collect();
    // Scale-aware tolerance for the convexity test.
    let scale = p2
        .iter()
        .fold(0.0f64, |m, p| m.max(p[0].abs()).max(p[1].abs()))
        .max(f64::MIN_POSITIVE);
    let eps = 1e-12 * scale * scale;
    while idx.len() > 3 {
        let m = idx.len();
        let mut clipped = false;
        for k in 0..m {
            let (ia, ib, ic) = (idx[(k + m - 1) % m], idx[k], idx[(k + 1) % m]);
            let (a, b, c) = (p2[ia], p2[ib], p2[ic]);
            if orient(a, b, c) <= eps {
                continue; // reflex or flat corner
            }
            let blocked = idx.iter().any(|&j| {
                if j == ia || j == ib || j == ic || p2[j] == a || p2[j] == b || p2[j] == c {
                    return false;
                }
                let p = p2[j];
                orient(a, b, p) >= 0.0 && orient(b, c, p) >= 0.0 && orient(c, a, p) >= 0.0
            });
            if !blocked {
                out.push([poly[ia], poly[ib], poly[ic]]);
                idx.remove(k);
                clipped = true;
                break;
            }
        }
        if !clipped {
            // Self-intersecting or degenerate remainder: finish with a fan so that the
            // triangle count stays n − 2.
            let rest: Vec<u32> = idx.iter().map(|&i| poly[i]).collect();
            fan(&rest, out);
            return;
        }
    }
    out.push([poly[idx[0]], poly[idx[1]], poly[idx[2]]]);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{triangle_area, Mesh};

    fn l_shape() -> (Vec<[f64; 3]>, Vec<u32>) {
        // L-shaped hexagon (area 3), starting at the corner next to the reflex vertex so that a
        // fan from the first corner would cover the notch.
        let v = vec![
            [2.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
            [1.0, 2.0, 0.0],
            [0.0, 2.0, 0.0],
            [0.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
        ];
        (v, (0..6).collect())
    }

    #[test]
    fn concave_l_shape() {
        let (v, p) = l_shape();
        let mut out = Vec::new();
        triangulate(&p, &v, &mut out);
        assert_eq!(out.len(), 4);
        let m = Mesh::new(v, out.clone());
        let total: f64 = out.iter().map(|f| triangle_area(&m, f)).sum();
        assert!((total - 3.0).abs() < 1e-12, "area {total}");
        // Same winding as the polygon (CCW seen from +z).
        for f in &out {
            let [a, b, c] = f.map(|i| m.vertices[i as usize]);
            assert!(cross(sub(b, a), sub(c, a))[2] > 0.0);
        }
        // A fan would not cover it exactly: sanity-check that the test can fail.
        let mut fan_out = Vec::new();
        fan(&p, &mut fan_out);
        let fan_area: f64 = fan_out.iter().map(|f| triangle_area(&m, f)).sum();
        assert!((fan_area - 3.0).abs() > 0.1);
    }

    #[test]
    fn clockwise_and_tilted() {
        let (v, mut p) = l_shape();
        p.reverse();
        // Tilt the plane.
        let v: Vec<[f64; 3]> = v
            .iter()
            .map(|q| [q[0], q[1] * 0.6, q[1] * 0.8 + 5.0])
            .collect();
        let mut out = Vec::new();
        triangulate(&p, &v, &mut out);
        assert_eq!(out.len(), 4);
        let m = Mesh::new(v, out.clone());
        assert!((m.area() - 3.0).abs() < 1e-9);
    }

    #[test]
    fn degenerate_does_not_panic() {
        let v = vec![
            [0.0; 3],
            [1.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [3.0, 0.0, 0.0],
            [f64::NAN; 3],
        ];
        let mut out = Vec::new();
        triangulate(&[0, 1, 2, 3, 4], &v, &mut out);
        assert_eq!(out.len(), 3);
        triangulate(&[0, 1], &v, &mut out);
        assert_eq!(out.len(), 3);
    }
}

#[cfg(test)]
mod comb_tests {
    use super::*;

    /// A comb (many reflex corners) at the size limit: correct and fast.
    #[test]
    fn comb_polygon_at_the_limit() {
        let teeth = (MAX_EAR_CLIP - 2) / 4; // 4 corners per tooth + 2 base corners
        let mut v = Vec::new();
        for t in 0..teeth {
            let x = 2.0 * t as f64;
            v.extend([
                [x, 0.0, 0.0],
                [x + 1.0, 0.0, 0.0],
                [x + 1.0, 5.0, 0.0],
                [x + 2.0, 5.0, 0.0],
            ]);
        }
        // Top-right back down and the base.
        let w = 2.0 * teeth as f64;
        v.push([w, -1.0, 0.0]);
        v.push([0.0, -1.0, 0.0]);
        // Make it a simple polygon: teeth go up from y=0 to y=5, the base spans y=-1..0.
        let poly: Vec<u32> = (0..v.len() as u32).rev().collect();
        let mut area = 0.0;
        for i in 0..v.len() {
            let (a, b) = (v[i], v[(i + 1) % v.len()]);
            area += a[0] * b[1] - b[0] * a[1];
        }
        let area = area.abs() / 2.0;
        let start = std::time::Instant::now();
        let mut out = Vec::new();
        triangulate(&poly, &v, &mut out);
        assert!(start.elapsed().as_millis() < 100);
        assert_eq!(out.len(), v.len() - 2);
        let m = crate::mesh::Mesh::new(v, out);
        assert!(
            (m.area() - area).abs() < 1e-9 * area,
            "{} vs {area}",
            m.area()
        );
    }
}
