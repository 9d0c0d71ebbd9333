//! Meshes generated in code, for tests, examples and benchmarks (no data files needed).

use super::Mesh;
use std::collections::HashMap;

/// Unit-radius icosphere: the icosahedron with each triangle split into four `subdivisions`
/// times, new vertices projected onto the sphere. Vertices: 10·4^s + 2.
pub fn icosphere(subdivisions: u32) -> Mesh {
    let p = (1.0 + 5f64.sqrt()) / 2.0;
    let mut vertices: Vec<[f64; 3]> = vec![
        [-1.0, p, 0.0],
        [1.0, p, 0.0],
        [-1.0, -p, 0.0],
        [1.0, -p, 0.0],
        [0.0, -1.0, p],
        [0.0, 1.0, p],
        [0.0, -1.0, -p],
        [0.0, 1.0, -p],
        [p, 0.0, -1.0],
        [p, 0.0, 1.0],
        [-p, 0.0, -1.0],
        [-p, 0.0, 1.0],
    ];
    for v in &mut vertices {
        *v = normalize(*v);
    }
    let faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    let mut mesh = Mesh::new(vertices, faces);
    for _ in 0..subdivisions {
        mesh = midpoint_subdivide(&mesh);
        for v in &mut mesh.vertices {
            *v = normalize(*v);
        }
    }
    mesh
}

/// Splits every triangle into four at its edge midpoints (no smoothing). Shared edges share
/// their midpoint, so a closed mesh stays closed.
pub fn midpoint_subdivide(mesh: &Mesh) -> Mesh {
    let mut vertices = mesh.vertices.clone();
    let mut mid: HashMap<(u32, u32), u32> = HashMap::with_capacity(mesh.faces.len() * 2);
    let mut faces = Vec::with_capacity(mesh.faces.len() * 4);
    let mut midpoint = |a: u32, b: u32, vertices: &mut Vec<[f64; 3]>| -> u32 {
        let key = (a.min(b), a.max(b));
        *mid.entry(key).or_insert_with(|| {
            let (pa, pb) = (vertices[a as usize], vertices[b as usize]);
            vertices.push([
                0.5 * (pa[0] + pb[0]),
                0.5 * (pa[1] + pb[1]),
                0.5 * (pa[2] + pb[2]),
            ]);
            (vertices.len() - 1) as u32
        })
    };
    for &[a, b, c] in &mesh.faces {
        let ab = midpoint(a, b, &mut vertices);
        let bc = midpoint(b, c, &mut vertices);
        let ca = midpoint(c, a, &mut vertices);
        faces.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
    }
    Mesh::new(vertices, faces)
}

/// Flat `width × height` rectangle in the z = 0 plane, an `nx × ny` grid of cells, each split
/// into two triangles along alternating diagonals (so the mesh has no preferred direction).
pub fn rectangle(width: f64, height: f64, nx: usize, ny: usize) -> Mesh {
    let mut vertices = Vec::with_capacity((nx + 1) * (ny + 1));
    for j in 0..=ny {
        for i in 0..=nx {
            vertices.push([
                width * i as f64 / nx as f64,
                height * j as f64 / ny as f64,
                0.0,
            ]);
        }
    }
    let id = |i: usize, j: usize| (j * (nx + 1) + i) as u32;
    let mut faces = Vec::with_capacity(2 * nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            if (i + j) % 2 == 0 {
                faces.push([a, b, c]);
                faces.push([a, c, d]);
            } else {
                faces.push([a, b, d]);
                faces.push([b, c, d]);
            }
        }
    }
    Mesh::new(vertices, faces)
}

/// Torus with major radius `major`, minor radius `minor`, `nu × nv` quads split in two.
pub fn torus(major: f64, minor: f64, nu: usize, nv: usize) -> Mesh {
    let mut vertices = Vec::with_capacity(nu * nv);
    for i in 0..nu {
        let u = 2.0 * std::f64::consts::PI * i as f64 / nu as f64;
        for j in 0..nv {
            let v = 2.0 * std::f64::consts::PI * j as f64 / nv as f64;
            let r = major + minor * v.cos();
            vertices.push([r * u.cos(), r * u.sin(), minor * v.sin()]);
        }
    }
    let id = |i: usize, j: usize| ((i % nu) * nv + (j % nv)) as u32;
    let mut faces = Vec::with_capacity(2 * nu * nv);
    for i in 0..nu {
        for j in 0..nv {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            faces.push([a, b, c]);
            faces.push([a, c, d]);
        }
    }
    Mesh::new(vertices, faces)
}

/// A closed, non-convex "bumpy" sphere: the icosphere with radius 1 + a·Y(θ,φ) for a smooth
/// deterministic bump function; a test shape with no symmetry (distinct eigenvalues).
pub fn bumpy_sphere(subdivisions: u32, amplitude: f64) -> Mesh {
    let mut mesh = icosphere(subdivisions);
    for v in &mut mesh.vertices {
        let [x, y, z] = *v;
        let r = 1.0
            + amplitude
                * (0.6 * (3.0 * x + 0.5).sin() * (2.0 * y).cos() + 0.4 * z * z * x + 0.3 * y);
        *v = [x * r * 1.3, y * r, z * r * 0.8];
    }
    mesh
}

fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn icosphere_counts_and_area() {
        for s in 0..4 {
            let m = icosphere(s);
            assert_eq!(m.vertices.len(), 10 * 4usize.pow(s) + 2);
            assert_eq!(m.faces.len(), 20 * 4usize.pow(s));
        }
        let a = icosphere(5).area();
        assert!((a - 4.0 * std::f64::consts::PI).abs() < 0.01, "area {a}");
    }

    #[test]
    fn rectangle_and_torus_counts() {
        let r = rectangle(2.0, 1.0, 4, 3);
        assert_eq!(r.vertices.len(), 20);
        assert_eq!(r.faces.len(), 24);
        assert!((r.area() - 2.0).abs() < 1e-12);
        let t = torus(2.0, 0.5, 12, 8);
        assert_eq!(t.vertices.len(), 96);
        assert_eq!(t.faces.len(), 192);
    }
}
