//! Integration tests of `shapeseek::mesh::prepare`.

use proptest::prelude::*;
use shapeseek::mesh::generate::{bumpy_sphere, icosphere, rectangle, torus};
use shapeseek::mesh::prepare::{
    prepare, prepare_with_map, ComponentPolicy, PrepareOptions, PrepareReport,
};
use shapeseek::mesh::Mesh;
use std::collections::{BTreeMap, BTreeSet};

/// The defaults without the minimums (vertex/face counts, area kept): these tests look at the
/// cleaning itself, on meshes that are deliberately tiny; the minimums have their own tests.
fn lax() -> PrepareOptions {
    PrepareOptions {
        min_vertices: 0,
        min_faces: 0,
        min_area_kept: 0.0,
        ..PrepareOptions::default()
    }
}

fn raw() -> PrepareOptions {
    PrepareOptions {
        normalize_area: false,
        ..lax()
    }
}

fn all_raw() -> PrepareOptions {
    PrepareOptions {
        components: ComponentPolicy::All,
        ..raw()
    }
}

/// Appends `b` to `a` as a separate set of vertices and faces.
fn union(a: &Mesh, b: &Mesh) -> Mesh {
    let off = a.vertices.len() as u32;
    let mut m = a.clone();
    m.vertices.extend_from_slice(&b.vertices);
    m.faces.extend(b.faces.iter().map(|f| f.map(|i| i + off)));
    m
}

/// Deterministic pseudo-random permutation of 0..n (xorshift Fisher–Yates).
fn permutation(n: usize, mut seed: u64) -> Vec<usize> {
    let mut p: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        p.swap(i, (seed % (i as u64 + 1)) as usize);
    }
    p
}

/// Vertex `i` of `m` becomes vertex `p[i]`.
fn permute(m: &Mesh, p: &[usize]) -> Mesh {
    let mut v = vec![[0.0; 3]; m.vertices.len()];
    for (i, &pi) in p.iter().enumerate() {
        v[pi] = m.vertices[i];
    }
    let f = m
        .faces
        .iter()
        .map(|f| f.map(|i| p[i as usize] as u32))
        .collect();
    Mesh::new(v, f)
}

/// Splits `m` along the plane x = 0: faces whose centroid has x > 0 get their own copies of
/// their vertices (identical coordinates with zeros negated to -0.0, moved by `offset`), as
/// exporters do along seams.
fn split_seam(m: &Mesh, offset: [f64; 3]) -> (Mesh, usize) {
    let mut out = m.clone();
    let mut copy: BTreeMap<u32, u32> = BTreeMap::new();
    for f in &mut out.faces {
        let cx: f64 = f.iter().map(|&i| m.vertices[i as usize][0]).sum();
        if cx > 0.0 {
            for i in f.iter_mut() {
                let n = out.vertices.len() as u32;
                let c = *copy.entry(*i).or_insert(n);
                if c == n {
                    let p = m.vertices[*i as usize];
                    let mut q = [0.0; 3];
                    for k in 0..3 {
                        q[k] = if p[k] == 0.0 { -0.0 } else { p[k] + offset[k] };
                    }
                    out.vertices.push(q);
                }
                *i = c;
            }
        }
    }
    let copies = copy.len();
    (out, copies)
}

fn check_counts(r: &PrepareReport) {
    assert_eq!(
        r.vertices_in,
        r.vertices_out + r.welded_vertices + r.unreferenced_vertices,
        "{r:?}"
    );
    assert_eq!(
        r.faces_in,
        r.faces_out + r.degenerate_faces + r.duplicate_faces + r.component_faces_dropped,
        "{r:?}"
    );
}

#[test]
fn icosphere_passes_through_except_scale() {
    let m = icosphere(3);
    let (out, r) = prepare(&m, &lax()).unwrap();
    check_counts(&r);
    assert_eq!(r.vertices_out, m.vertices.len());
    assert_eq!(r.faces_out, m.faces.len());
    assert_eq!(out.faces, m.faces);
    assert_eq!(
        (
            r.welded_vertices,
            r.degenerate_faces,
            r.duplicate_faces,
            r.unreferenced_vertices
        ),
        (0, 0, 0, 0)
    );
    assert_eq!((r.components, r.components_kept), (1, 1));
    assert_eq!(r.dropped_area_fraction, 0.0);
    assert_eq!((r.boundary_edges, r.boundary_loops), (0, 0));
    assert_eq!(
        (r.nonmanifold_edges, r.inconsistent_orientation_edges),
        (0, 0)
    );
    assert_eq!(r.euler_characteristic, 2);
    assert!((out.area() - 1.0).abs() < 1e-12, "{}", out.area());
    assert!((r.original_area - m.area()).abs() < 1e-12);
    assert!((r.scale_factor - 1.0 / m.area().sqrt()).abs() < 1e-15);
    // Centred: area-weighted centroid at the origin; and the shape is only scaled and shifted.
    let mut c = [0.0; 3];
    for f in &out.faces {
        let w = shapeseek::mesh::triangle_area(&out, f) / 3.0;
        for &i in f {
            for (ck, pk) in c.iter_mut().zip(out.vertices[i as usize]) {
                *ck += w * pk;
            }
        }
    }
    assert!(c.iter().all(|x| x.abs() < 1e-12), "{c:?}");
    let shift = [0, 1, 2].map(|k| m.vertices[0][k] - out.vertices[0][k] / r.scale_factor);
    for (p, q) in m.vertices.iter().zip(&out.vertices) {
        for k in 0..3 {
            assert!((q[k] / r.scale_factor + shift[k] - p[k]).abs() < 1e-12);
        }
    }
    // Without normalisation the mesh is returned unchanged.
    let (same, r) = prepare(&m, &raw()).unwrap();
    assert_eq!(same, m);
    assert_eq!(r.scale_factor, 1.0);
}

#[test]
fn torus_has_euler_zero() {
    let (out, r) = prepare(&torus(2.0, 0.5, 24, 12), &lax()).unwrap();
    assert_eq!(r.euler_characteristic, 0);
    assert_eq!((r.vertices_out, r.faces_out), (288, 576));
    assert_eq!(
        (
            r.boundary_edges,
            r.nonmanifold_edges,
            r.inconsistent_orientation_edges
        ),
        (0, 0, 0)
    );
    assert!((out.area() - 1.0).abs() < 1e-12);
}

#[test]
fn rectangle_has_one_boundary_loop() {
    let (_, r) = prepare(&rectangle(2.0, 1.0, 5, 3), &lax()).unwrap();
    assert_eq!(r.boundary_loops, 1);
    assert_eq!(r.boundary_edges, 2 * (5 + 3));
    assert_eq!(r.euler_characteristic, 1);
    assert_eq!(r.inconsistent_orientation_edges, 0);
}

#[test]
fn two_spheres_largest_keeps_the_bigger_one() {
    let big = icosphere(2);
    let mut small = icosphere(2);
    small.scale(0.5);
    small.transform(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [5.0, 0.0, 0.0],
    );
    // The small one first, so that "first component" is not the answer.
    let m = union(&small, &big);
    let (out, r, map) = prepare_with_map(&m, &raw()).unwrap();
    check_counts(&r);
    assert_eq!((r.components, r.components_kept), (2, 1));
    assert_eq!(out, big);
    let expected = small.area() / (small.area() + big.area());
    assert!(
        (r.dropped_area_fraction - expected).abs() < 1e-14,
        "{}",
        r.dropped_area_fraction
    );
    assert!((r.dropped_area_fraction - 0.2).abs() < 1e-12); // (1/2)² / (1 + (1/2)²)
    assert_eq!(r.component_faces_dropped, small.faces.len());
    assert_eq!(r.unreferenced_vertices, small.vertices.len());
    assert!(map[..small.vertices.len()].iter().all(Option::is_none));
    assert!(map[small.vertices.len()..]
        .iter()
        .enumerate()
        .all(|(i, &j)| j == Some(i as u32)));

    let (out, r) = prepare(&m, &all_raw()).unwrap();
    assert_eq!((r.components, r.components_kept), (2, 2));
    assert_eq!(r.dropped_area_fraction, 0.0);
    assert_eq!(out, m);
    assert_eq!(r.euler_characteristic, 4);
}

#[test]
fn seam_split_sphere_is_welded_back() {
    let m = icosphere(2);
    let (split, copies) = split_seam(&m, [0.0; 3]);
    assert!(copies > 10);
    // Without welding these would be two open hemispheres.
    let (out, r, map) = prepare_with_map(&split, &raw()).unwrap();
    check_counts(&r);
    assert_eq!(r.welded_vertices, copies);
    assert_eq!(r.unreferenced_vertices, 0);
    assert_eq!(
        (r.components, r.boundary_edges, r.euler_characteristic),
        (1, 0, 2)
    );
    assert_eq!(out, m);
    for (i, j) in map.iter().enumerate().skip(m.vertices.len()) {
        let j = j.expect("copy kept") as usize;
        assert_eq!(out.vertices[j], split.vertices[i]); // -0.0 == 0.0
    }
}

#[test]
fn nearby_vertices_are_welded_only_with_a_tolerance() {
    let m = rectangle(1.0, 1.0, 4, 4);
    let split = |m: &Mesh| {
        // Faces right of x = 0.5 get their own vertices, moved by 1e-9 along y.
        let mut s = m.clone();
        let mut copy: BTreeMap<u32, u32> = BTreeMap::new();
        for f in &mut s.faces {
            let cx: f64 = f.iter().map(|&i| m.vertices[i as usize][0]).sum::<f64>() / 3.0;
            if cx > 0.5 {
                for i in f.iter_mut() {
                    let n = s.vertices.len() as u32;
                    let c = *copy.entry(*i).or_insert(n);
                    if c == n {
                        let p = m.vertices[*i as usize];
                        s.vertices.push([p[0], p[1] + 1e-9, p[2]]);
                    }
                    *i = c;
                }
            }
        }
        s
    };
    let s = split(&m);
    let (out, r) = prepare(&s, &all_raw()).unwrap();
    check_counts(&r);
    assert_eq!(r.welded_vertices, 0);
    assert_eq!(r.components, 2);
    assert_eq!(r.boundary_loops, 2);
    assert_eq!(out.vertices.len(), s.vertices.len() - 10); // originals right of the seam unused

    let opts = PrepareOptions {
        weld_tolerance: Some(1e-6),
        ..all_raw()
    };
    let (out, r) = prepare(&s, &opts).unwrap();
    check_counts(&r);
    // The five seam copies, plus the ten unused originals right of the seam (each within 1e-9
    // of its copy): all welded, so nothing is left unreferenced.
    assert_eq!((r.welded_vertices, r.unreferenced_vertices), (15, 0));
    assert_eq!(
        (r.components, r.boundary_loops, r.euler_characteristic),
        (1, 1, 1)
    );
    assert_eq!(out.faces.len(), m.faces.len());
    assert_eq!(out.vertices.len(), m.vertices.len());
    assert!((out.area() - 1.0).abs() < 1e-8);
    // A tolerance far below the gap welds nothing.
    let opts = PrepareOptions {
        weld_tolerance: Some(1e-12),
        ..all_raw()
    };
    assert_eq!(prepare(&s, &opts).unwrap().1.welded_vertices, 0);
}

#[test]
fn degenerate_faces_are_dropped_and_counted() {
    let m = icosphere(1);
    let mut d = m.clone();
    let n = d.vertices.len() as u32;
    d.vertices
        .extend_from_slice(&[[3.0, 0.0, 0.0], [4.0, 0.0, 0.0], [5.0, 0.0, 0.0]]);
    d.faces.push([0, 0, 1]); // repeated index
    d.faces.push([2, 1, 1]); // repeated index
    d.faces.push([n, n + 1, n + 2]); // collinear: zero area
    d.faces.push([n, n + 2, n]); // both
    let (out, r) = prepare(&d, &raw()).unwrap();
    check_counts(&r);
    assert_eq!(r.degenerate_faces, 4);
    assert_eq!(r.unreferenced_vertices, 3);
    assert_eq!(r.components, 1);
    assert_eq!(out, m);
}

#[test]
fn degenerate_threshold_is_relative_to_the_mean_area() {
    let base = rectangle(1.0, 1.0, 2, 2); // 8 faces of area 1/8
    let with_sliver = |ratio: f64| {
        let mut m = base.clone();
        let n = m.vertices.len() as u32;
        let h = 2.0 * ratio * 0.125; // area = h / 2 ≈ ratio × mean
        m.vertices
            .extend_from_slice(&[[5.0, 0.0, 0.0], [6.0, 0.0, 0.0], [5.0, h, 0.0]]);
        m.faces.push([n, n + 1, n + 2]);
        m
    };
    let (_, r) = prepare(&with_sliver(1e-16), &all_raw()).unwrap();
    assert_eq!((r.degenerate_faces, r.components, r.faces_out), (1, 1, 8));
    let (_, r) = prepare(&with_sliver(1e-12), &all_raw()).unwrap();
    assert_eq!((r.degenerate_faces, r.components, r.faces_out), (0, 2, 9));
    // A ratio of 0 keeps every face of non-zero area.
    let opts = PrepareOptions {
        degenerate_area_ratio: 0.0,
        ..all_raw()
    };
    assert_eq!(
        prepare(&with_sliver(1e-16), &opts)
            .unwrap()
            .1
            .degenerate_faces,
        0
    );
}

#[test]
fn duplicate_faces_are_dropped_and_counted() {
    let m = icosphere(1);
    let mut d = m.clone();
    d.faces.push(m.faces[3]);
    d.faces.push([m.faces[5][2], m.faces[5][1], m.faces[5][0]]); // reversed copy
    d.faces.push([m.faces[5][1], m.faces[5][2], m.faces[5][0]]); // rotated copy
    let (out, r) = prepare(&d, &raw()).unwrap();
    check_counts(&r);
    assert_eq!((r.duplicate_faces, r.degenerate_faces), (3, 0));
    assert_eq!(out, m);
    assert_eq!(r.nonmanifold_edges, 0);
}

#[test]
fn nonmanifold_book_is_tolerated() {
    let m = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, -1.0, -1.0],
        ],
        vec![[0, 1, 2], [1, 0, 3], [0, 1, 4]],
    );
    let (out, r) = prepare(&m, &lax()).unwrap();
    check_counts(&r);
    assert_eq!(r.nonmanifold_edges, 1);
    assert_eq!(r.boundary_edges, 6);
    assert_eq!(r.faces_out, 3);
    assert_eq!(r.components, 1);
    assert_eq!(r.euler_characteristic, 5 - 7 + 3);
    // Theta-shaped boundary graph: one cycle and one open chain.
    assert_eq!(r.boundary_loops, 2);
    assert!((out.area() - 1.0).abs() < 1e-12);
}

/// `f` rotated so that its smallest index comes first (same orientation, same face).
fn canonical(f: [u32; 3]) -> [u32; 3] {
    let k = (0..3).min_by_key(|&k| f[k]).unwrap();
    [f[k], f[(k + 1) % 3], f[(k + 2) % 3]]
}

#[test]
fn a_flipped_face_is_reoriented() {
    let m = icosphere(1);
    let mut flipped = m.clone();
    flipped.faces[7].swap(0, 1);
    let (out, r) = prepare(&flipped, &raw()).unwrap();
    assert_eq!(
        (r.reoriented_faces, r.inconsistent_orientation_edges),
        (1, 0)
    );
    assert_eq!(
        (
            r.boundary_edges,
            r.nonmanifold_edges,
            r.euler_characteristic
        ),
        (0, 0, 2)
    );
    assert_eq!(out.vertices, m.vertices);
    let faces: Vec<[u32; 3]> = out.faces.iter().map(|&f| canonical(f)).collect();
    let want: Vec<[u32; 3]> = m.faces.iter().map(|&f| canonical(f)).collect();
    assert_eq!(faces, want);
    // A coherent mesh is left as it is.
    let (same, r) = prepare(&m, &raw()).unwrap();
    assert_eq!((same, r.reoriented_faces), (m, 0));
}

#[test]
fn each_patch_keeps_the_orientation_of_its_larger_area() {
    let m = icosphere(3);
    let up = |f: &[u32; 3]| f.iter().map(|&i| m.vertices[i as usize][2]).sum::<f64>() > 2.1;
    let cap = m.faces.iter().filter(|f| up(f)).count();
    assert!(cap > 20 && 4 * cap < m.faces.len(), "{cap}");
    // `m` with the faces `pick` selects wound the other way.
    let flipped = |pick: &dyn Fn(&[u32; 3]) -> bool| {
        let mut x = m.clone();
        for f in x.faces.iter_mut().filter(|f| pick(f)) {
            f.swap(0, 1);
        }
        x
    };
    // The cap flipped: it turns back, the rest keeps its outward normals. Everything but the
    // cap flipped: the cap is the smaller area, so it is the one that turns.
    let a = flipped(&up);
    let mut b = flipped(&|f: &[u32; 3]| !up(f));
    for (x, all_turned) in [(&a, false), (&b, true)] {
        let (out, r) = prepare(x, &raw()).unwrap();
        assert_eq!(
            (r.reoriented_faces, r.inconsistent_orientation_edges),
            (cap, 0)
        );
        for (o, f) in out.faces.iter().zip(&m.faces) {
            let want = if all_turned { [f[1], f[0], f[2]] } else { *f };
            assert_eq!(canonical(*o), canonical(want));
        }
    }
    // Two components (apart, so that welding keeps them apart) are oriented each on its own.
    for v in &mut b.vertices {
        v[0] += 3.0;
    }
    let two = union(&a, &b);
    let (_, r) = prepare(&two, &all_raw()).unwrap();
    assert_eq!(
        (r.reoriented_faces, r.inconsistent_orientation_edges),
        (2 * cap, 0)
    );
}

/// A Möbius strip of `n` quads (each split in two triangles), every triangle wound the same way
/// locally. It cannot be oriented: one edge is left inconsistent wherever the traversal closes.
fn moebius(n: usize) -> Mesh {
    let mut vertices = Vec::new();
    for i in 0..n {
        let u = std::f64::consts::TAU * i as f64 / n as f64;
        for s in [-0.3, 0.3] {
            let r = 1.0 + s * (u / 2.0).cos();
            vertices.push([r * u.cos(), r * u.sin(), s * (u / 2.0).sin()]);
        }
    }
    let mut faces = Vec::new();
    for i in 0..n {
        let (a, b) = (2 * i as u32, 2 * i as u32 + 1);
        // The last quad joins the first with its sides swapped.
        let (c, d) = if i + 1 < n {
            (2 * (i as u32 + 1), 2 * (i as u32 + 1) + 1)
        } else {
            (1, 0)
        };
        faces.push([a, c, b]);
        faces.push([b, c, d]);
    }
    Mesh::new(vertices, faces)
}

#[test]
fn a_moebius_strip_keeps_one_inconsistent_edge() {
    let m = moebius(40);
    let (out, r) = prepare(&m, &raw()).unwrap();
    assert_eq!(r.inconsistent_orientation_edges, 1, "{r:?}");
    assert_eq!((r.boundary_loops, r.euler_characteristic), (1, 0));
    assert_eq!(out.faces.len(), 80);
    // Deterministic, and which edge stays inconsistent does not depend on the vertex numbering.
    let (again, r2) = prepare(&m, &raw()).unwrap();
    assert_eq!((again, r2), (out, r));
    let a = prepare_with_map(&m, &raw()).unwrap();
    for seed in [1u64, 99, 12345] {
        let p = permutation(m.vertices.len(), seed);
        let b = prepare_with_map(&permute(&m, &p), &raw()).unwrap();
        assert_same_up_to_permutation(&a, &b, &p);
    }
}

#[test]
fn a_hole_next_to_a_flipped_face_is_capped() {
    let sphere = icosphere(3);
    // A hole: the faces around vertex 0.
    let mut m = sphere.clone();
    m.faces.retain(|f| !f.contains(&0));
    let opts = PrepareOptions {
        cap_boundaries: Some(shapeseek::presets::DEFAULT_CAP),
        ..raw()
    };
    let (_, r) = prepare(&m, &opts).unwrap();
    let capped = r.capped.unwrap();
    assert_eq!(
        (capped.loops, r.boundary_edges, r.reoriented_faces),
        (1, 0, 0)
    );
    // One face on the rim flipped: before orientation was made coherent the rim had no directed
    // cycle and the hole was left open without being counted.
    let rim = m.faces.iter().position(|f| {
        let n = |v: u32| {
            sphere
                .faces
                .iter()
                .any(|g| g.contains(&0) && g.contains(&v))
        };
        f.iter().filter(|&&v| n(v)).count() == 2
    });
    m.faces[rim.unwrap()].swap(0, 1);
    let (out, r) = prepare(&m, &opts).unwrap();
    let capped = r.capped.unwrap();
    assert_eq!(
        (capped.loops, capped.loops_left_open, r.boundary_edges),
        (1, 0, 0),
        "{r:?}"
    );
    assert_eq!(
        (r.reoriented_faces, r.inconsistent_orientation_edges),
        (1, 0)
    );
    assert_eq!(r.euler_characteristic, 2);
    assert!(out.faces.len() > m.faces.len());
}

#[test]
fn non_finite_and_bad_index_are_rejected() {
    let mut m = icosphere(1);
    m.vertices[7][1] = f64::NAN;
    m.vertices[9][0] = f64::INFINITY;
    let e = prepare(&m, &lax()).unwrap_err();
    assert_eq!(e.code(), "mesh.non_finite");
    assert!(
        matches!(e, shapeseek::Error::NonFinite { vertex: 7 }),
        "{e:?}"
    );

    let mut m = icosphere(1);
    let n = m.vertices.len() as u32;
    m.faces[4][2] = n;
    let e = prepare(&m, &lax()).unwrap_err();
    assert_eq!(e.code(), "request.invalid");
    assert!(e.to_string().contains("face 4"), "{e}");
}

#[test]
fn empty_and_all_degenerate_are_rejected() {
    let e = prepare(&Mesh::default(), &lax()).unwrap_err();
    assert_eq!(e.code(), "mesh.empty");
    assert!(e.to_string().contains("no faces"), "{e}");

    let m = Mesh::new(icosphere(0).vertices, vec![]);
    assert_eq!(prepare(&m, &lax()).unwrap_err().code(), "mesh.empty");

    let m = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
        ],
        vec![[0, 1, 2], [0, 0, 1], [0, 3, 1]],
    );
    let e = prepare(&m, &lax()).unwrap_err();
    assert_eq!(e.code(), "mesh.empty");
    assert!(e.to_string().contains("degenerate"), "{e}");
}

#[test]
fn unreferenced_vertices_are_dropped_in_order() {
    let m = rectangle(1.0, 2.0, 3, 3);
    // Interleave an unused vertex after every original one, and one at the front.
    let mut v = vec![[9.0, 9.0, 9.0]];
    for (i, p) in m.vertices.iter().enumerate() {
        v.push(*p);
        v.push([i as f64, -1.0, 7.0]);
    }
    let f = m.faces.iter().map(|f| f.map(|i| 2 * i + 1)).collect();
    let d = Mesh::new(v, f);
    let (out, r, map) = prepare_with_map(&d, &raw()).unwrap();
    check_counts(&r);
    assert_eq!(r.unreferenced_vertices, m.vertices.len() + 1);
    assert_eq!(out, m);
    for (i, j) in map.iter().enumerate() {
        if i % 2 == 1 {
            assert_eq!(*j, Some((i / 2) as u32));
        } else {
            assert_eq!(*j, None);
        }
    }
}

/// A messy test shape: bumpy sphere split along a seam, a small extra component, a duplicate
/// and a degenerate face, an unused vertex.
fn messy(offset: [f64; 3]) -> Mesh {
    let (mut m, _) = split_seam(&bumpy_sphere(2, 0.3), offset);
    let mut small = icosphere(1);
    small.scale(0.2);
    small.transform(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [4.0, 0.0, 0.0],
    );
    m = union(&m, &small);
    m.faces.push(m.faces[10]);
    m.faces.push([3, 3, 4]);
    m.vertices.push([1.0, 2.0, 3.0]);
    m
}

fn assert_same_up_to_permutation(
    a: &(Mesh, PrepareReport, Vec<Option<u32>>),
    b: &(Mesh, PrepareReport, Vec<Option<u32>>),
    p: &[usize],
) {
    assert_eq!(a.1, b.1); // every count and every area, bitwise
                          // sigma: output index in a -> output index in b.
    let mut sigma = vec![u32::MAX; a.0.vertices.len()];
    for (i, ja) in a.2.iter().enumerate() {
        let jb = b.2[p[i]];
        assert_eq!(ja.is_some(), jb.is_some());
        if let (Some(ja), Some(jb)) = (ja, jb) {
            assert!(sigma[*ja as usize] == u32::MAX || sigma[*ja as usize] == jb);
            sigma[*ja as usize] = jb;
        }
    }
    assert!(sigma.iter().all(|&s| s != u32::MAX));
    for (j, &s) in sigma.iter().enumerate() {
        assert_eq!(a.0.vertices[j], b.0.vertices[s as usize]);
    }
    let fa: Vec<[u32; 3]> =
        a.0.faces
            .iter()
            .map(|f| f.map(|i| sigma[i as usize]))
            .collect();
    assert_eq!(fa, b.0.faces);
}

#[test]
fn vertex_permutation_invariance() {
    for (offset, opts) in [
        ([0.0; 3], lax()),
        (
            [0.0; 3],
            PrepareOptions {
                components: ComponentPolicy::All,
                ..lax()
            },
        ),
        (
            [1e-9, -2e-9, 0.0],
            PrepareOptions {
                weld_tolerance: Some(1e-6),
                ..lax()
            },
        ),
    ] {
        let m = messy(offset);
        let a = prepare_with_map(&m, &opts).unwrap();
        assert!(a.1.welded_vertices > 0 && a.1.duplicate_faces == 1 && a.1.degenerate_faces == 1);
        assert_eq!(
            a.1.euler_characteristic,
            if a.1.components_kept == 2 { 4 } else { 2 }
        );
        for seed in [1u64, 99, 12345] {
            let p = permutation(m.vertices.len(), seed);
            let b = prepare_with_map(&permute(&m, &p), &opts).unwrap();
            assert_same_up_to_permutation(&a, &b, &p);
        }
    }
}

#[test]
fn normalisation_is_scale_and_translation_invariant() {
    let m = messy([0.0; 3]);
    let (a, ra) = prepare(&m, &lax()).unwrap();
    for (s, t) in [
        (7.3, [0.0; 3]),
        (0.013, [2.0, -5.0, 11.0]),
        (1e4, [1e3, 0.0, 0.0]),
    ] {
        let mut scaled = m.clone();
        scaled.transform([[s, 0.0, 0.0], [0.0, s, 0.0], [0.0, 0.0, s]], t);
        let (b, rb) = prepare(&scaled, &lax()).unwrap();
        assert_eq!(a.faces, b.faces);
        assert_eq!(ra.faces_out, rb.faces_out);
        assert!((rb.original_area / ra.original_area - s * s).abs() < 1e-12 * s * s);
        let worst = a
            .vertices
            .iter()
            .zip(&b.vertices)
            .flat_map(|(p, q)| (0..3).map(move |k| (p[k] - q[k]).abs()))
            .fold(0.0, f64::max);
        assert!(worst < 1e-12, "scale {s}: max difference {worst}");
    }
}

/// Independent edge statistics with ordered maps: (edges, boundary, non-manifold, inconsistent).
fn edge_stats(m: &Mesh) -> (usize, usize, usize, usize) {
    let mut e: BTreeMap<(u32, u32), Vec<bool>> = BTreeMap::new();
    for f in &m.faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            e.entry((a.min(b), a.max(b))).or_default().push(a < b);
        }
    }
    let boundary = e.values().filter(|d| d.len() == 1).count();
    let nonmanifold = e.values().filter(|d| d.len() > 2).count();
    let inconsistent = e.values().filter(|d| d.len() == 2 && d[0] == d[1]).count();
    (e.len(), boundary, nonmanifold, inconsistent)
}

/// When every boundary vertex has exactly two boundary edges, the number of boundary cycles
/// (connected components of the boundary graph, by flood fill); `None` otherwise.
fn simple_boundary_cycles(m: &Mesh) -> Option<usize> {
    let mut count: BTreeMap<(u32, u32), usize> = BTreeMap::new();
    for f in &m.faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            *count.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    let mut adj: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    for (&(a, b), _) in count.iter().filter(|(_, &c)| c == 1) {
        adj.entry(a).or_default().push(b);
        adj.entry(b).or_default().push(a);
    }
    if adj.values().any(|n| n.len() != 2) {
        return None;
    }
    let mut seen = BTreeSet::new();
    let mut cycles = 0;
    for &v in adj.keys() {
        if seen.insert(v) {
            cycles += 1;
            let mut stack = vec![v];
            while let Some(u) = stack.pop() {
                for &w in &adj[&u] {
                    if seen.insert(w) {
                        stack.push(w);
                    }
                }
            }
        }
    }
    Some(cycles)
}

fn soup() -> impl Strategy<Value = Mesh> {
    // Coordinates on a coarse grid: many exact duplicates and collinear (zero-area) triples.
    (3usize..24).prop_flat_map(|n| {
        (
            prop::collection::vec(prop::array::uniform3(-2i32..3), n),
            prop::collection::vec(prop::array::uniform3(0..n as u32), 1..40),
        )
            .prop_map(|(v, f)| {
                let v = v.iter().map(|p| p.map(|c| c as f64 * 0.5)).collect();
                Mesh::new(v, f)
            })
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn prepare_invariants_on_random_soups(
        m in soup(),
        all in any::<bool>(),
        normalize in any::<bool>(),
    ) {
        let opts = PrepareOptions {
            components: if all { ComponentPolicy::All } else { ComponentPolicy::Largest },
            normalize_area: normalize,
            ..lax()
        };
        let (out, r, map) = match prepare_with_map(&m, &opts) {
            Ok(x) => x,
            Err(e) => {
                prop_assert_eq!(e.code(), "mesh.empty");
                // Then indeed every face has a repeated position or is flat.
                for f in &m.faces {
                    prop_assert!(shapeseek::mesh::triangle_area(&m, f) == 0.0);
                }
                return Ok(());
            }
        };
        check_counts(&r);
        let nv = out.vertices.len();
        prop_assert_eq!((r.vertices_out, r.faces_out), (nv, out.faces.len()));
        prop_assert!(!out.faces.is_empty());
        let mut referenced = vec![false; nv];
        let mut sets = BTreeSet::new();
        for f in &out.faces {
            prop_assert!(f.iter().all(|&i| (i as usize) < nv));
            prop_assert!(f[0] != f[1] && f[1] != f[2] && f[0] != f[2]);
            prop_assert!(shapeseek::mesh::triangle_area(&out, f) > 0.0);
            let mut s = *f;
            s.sort_unstable();
            prop_assert!(sets.insert(s), "duplicate face {:?}", f);
            for &i in f {
                referenced[i as usize] = true;
            }
        }
        prop_assert!(referenced.iter().all(|&x| x));
        // Distinct output positions (exact welding).
        let pos: BTreeSet<[u64; 3]> =
            out.vertices.iter().map(|p| p.map(|c| (c + 0.0).to_bits())).collect();
        prop_assert_eq!(pos.len(), nv);
        if normalize {
            prop_assert!((out.area() - 1.0).abs() < 1e-12, "area {}", out.area());
        } else {
            prop_assert_eq!(r.scale_factor, 1.0);
            for (i, j) in map.iter().enumerate() {
                if let Some(j) = j {
                    prop_assert_eq!(out.vertices[*j as usize], m.vertices[i]);
                }
            }
        }
        prop_assert!(map.iter().flatten().all(|&j| (j as usize) < nv));
        let distinct_used: BTreeSet<u32> = map.iter().flatten().copied().collect();
        prop_assert_eq!(distinct_used.len(), nv);
        let (e, b, nm, inc) = edge_stats(&out);
        prop_assert_eq!(r.euler_characteristic, nv as i64 - e as i64 + out.faces.len() as i64);
        prop_assert_eq!((r.boundary_edges, r.nonmanifold_edges, r.inconsistent_orientation_edges), (b, nm, inc));
        prop_assert!(r.boundary_loops <= r.boundary_edges);
        if r.nonmanifold_edges == 0 {
            // Only closed simple cycles (no open chains), each of at least three edges.
            prop_assert!(3 * r.boundary_loops <= r.boundary_edges);
        }
        if let Some(cycles) = simple_boundary_cycles(&out) {
            prop_assert_eq!(r.boundary_loops, cycles);
        }
        prop_assert_eq!(r.boundary_edges == 0, r.boundary_loops == 0);
        prop_assert!(r.components_kept >= 1 && r.components_kept <= r.components);
        if all {
            prop_assert_eq!(r.components_kept, r.components);
            prop_assert_eq!(r.dropped_area_fraction, 0.0);
            prop_assert_eq!(r.component_faces_dropped, 0);
        } else {
            prop_assert_eq!(r.components_kept, 1);
            prop_assert!((0.0..=0.5).contains(&r.dropped_area_fraction) || r.components > 2);
            prop_assert!((0.0..1.0).contains(&r.dropped_area_fraction));
        }
    }
}

// ---------------------------------------------------------------- minimums (issue 11)

fn code(m: &Mesh, o: &PrepareOptions) -> String {
    match prepare(m, o) {
        Ok(_) => "ok".into(),
        Err(e) => e.code().into(),
    }
}

#[test]
fn minimums_have_documented_defaults() {
    let d = PrepareOptions::default();
    assert_eq!((d.min_vertices, d.min_faces, d.min_area_kept), (4, 4, 0.5));
    let o: PrepareOptions = serde_json::from_str(r#"{"min_faces": 1}"#).unwrap();
    assert_eq!((o.min_vertices, o.min_faces, o.min_area_kept), (4, 1, 0.5));
    for bad in [-0.1, 1.5, f64::NAN] {
        let o = PrepareOptions {
            min_area_kept: bad,
            ..PrepareOptions::default()
        };
        assert_eq!(code(&icosphere(1), &o), "request.invalid", "{bad}");
    }
}

#[test]
fn too_small_shapes_are_refused_with_their_own_codes() {
    let d = PrepareOptions::default();
    let tri = Mesh::new(
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        vec![[0, 1, 2]],
    );
    assert_eq!(code(&tri, &d), "mesh.too_few_faces");
    // 500 copies of it: duplicates dropped, one triangle left.
    let copies = Mesh::new(tri.vertices.clone(), vec![[0, 1, 2]; 500]);
    assert_eq!(code(&copies, &d), "mesh.too_few_faces");
    // A quad (4 vertices, 2 triangles): enough vertices, too few faces.
    let quad = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
        ],
        vec![[0, 1, 2], [0, 2, 3]],
    );
    assert_eq!(code(&quad, &d), "mesh.too_few_faces");
    // A tetrahedron is the smallest accepted shape; configurable both ways.
    let tet = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]],
    );
    assert_eq!(code(&tet, &d), "ok");
    let strict = PrepareOptions {
        min_faces: 5,
        ..PrepareOptions::default()
    };
    assert_eq!(code(&tet, &strict), "mesh.too_few_faces");
    let strict = PrepareOptions {
        min_vertices: 5,
        ..PrepareOptions::default()
    };
    assert_eq!(code(&tet, &strict), "mesh.too_few_vertices");
    assert_eq!(code(&quad, &lax()), "ok");
}

#[test]
fn most_of_the_area_must_be_kept() {
    let d = PrepareOptions::default();
    // 600 disjoint equal triangles: the largest component is 1/600 of the area.
    let mut v = Vec::new();
    let mut f = Vec::new();
    for k in 0..600u32 {
        let x = 3.0 * k as f64;
        v.extend([[x, 0.0, 0.0], [x + 1.0, 0.0, 0.0], [x, 1.0, 0.0]]);
        f.push([3 * k, 3 * k + 1, 3 * k + 2]);
    }
    let scattered = Mesh::new(v, f);
    assert_eq!(code(&scattered, &d), "mesh.area_kept");
    let e = prepare(&scattered, &d).unwrap_err().to_string();
    assert!(e.contains("0.167%") && e.contains("600 components"), "{e}");
    // Keeping every component keeps all of the area (and 600 faces).
    let all = PrepareOptions {
        components: ComponentPolicy::All,
        ..PrepareOptions::default()
    };
    assert_eq!(code(&scattered, &all), "ok");
    // Two equal spheres: exactly half kept, accepted; a sphere with a bigger twin: refused.
    let a = icosphere(1);
    let mut b = icosphere(1);
    for p in &mut b.vertices {
        p[0] += 5.0;
    }
    assert_eq!(code(&union(&a, &b), &d), "ok");
    let mut big = icosphere(1);
    for p in &mut big.vertices {
        *p = [p[0] * 1.5 + 5.0, p[1] * 1.5, p[2] * 1.5];
    }
    let mut three = union(&a, &big);
    let mut c = icosphere(1);
    for p in &mut c.vertices {
        p[0] -= 5.0;
    }
    three = union(&three, &c);
    // Areas 1 : 2.25 : 1 → the largest holds 2.25/4.25 = 53% (accepted); without it 2 equal
    // spheres of 1/3.25 each would be refused at 0.5.
    assert_eq!(code(&three, &d), "ok");
    let half = PrepareOptions {
        min_area_kept: 0.6,
        ..PrepareOptions::default()
    };
    assert_eq!(code(&three, &half), "mesh.area_kept");
}

/// The default spec's preparation caps a plane-cut sphere into a closed surface (the report
/// accounts for the cap) and leaves an open square's own long border open
/// (`docs/quality.md` §19).
#[test]
fn the_default_spec_caps_a_cut_rim_and_leaves_a_long_border_open() {
    use shapeseek::presets::default_config;
    use shapeseek::spectrum::AnalyzeOptions;
    let opts = default_config()
        .signature
        .analysis_options(&AnalyzeOptions::default())
        .prepare;
    assert!(opts.cap_boundaries.is_some());
    let s = icosphere(4);
    let faces: Vec<[u32; 3]> = s
        .faces
        .iter()
        .copied()
        .filter(|f| f.iter().all(|&i| s.vertices[i as usize][2] <= 0.6))
        .collect();
    let cut = Mesh::new(s.vertices.clone(), faces);
    let (plain, r0) = prepare(&cut, &PrepareOptions::default()).unwrap();
    assert_eq!(r0.boundary_loops, 1);
    let (m, r) = prepare(&cut, &opts).unwrap();
    let c = r.capped.expect("capping ran");
    assert_eq!((c.loops, c.loops_too_long, c.loops_left_open), (1, 0, 0));
    assert_eq!((r.boundary_edges, r.boundary_loops), (0, 0));
    assert_eq!(r.euler_characteristic, 2);
    assert_eq!(r.vertices_out, plain.vertices.len() + c.vertices_added);
    assert_eq!(m.faces.len(), plain.faces.len() + c.faces_added);
    assert_eq!(
        r.vertices_in,
        r.vertices_out - c.vertices_added + r.welded_vertices + r.unreferenced_vertices
    );
    // An open unit square: its border is 4 √A long, above the default's 2.5.
    let (_, r) = prepare(&rectangle(1.0, 1.0, 12, 12), &opts).unwrap();
    let c = r.capped.expect("capping ran");
    assert_eq!((c.loops, c.loops_too_long), (0, 1));
    assert_eq!(r.boundary_loops, 1);
}

/// Smoothing in preparation (`PrepareOptions::smooth`, `docs/quality.md` §25): the vertex map
/// and the topology are those of the unsmoothed preparation, noise along the normals is filtered
/// out, and the options are left out of the JSON when unset (keys of preparations without it
/// unchanged).
#[test]
fn smoothing_in_preparation_keeps_the_map_and_removes_noise() {
    use shapeseek::mesh::prepare::prepare_with_map;
    use shapeseek::mesh::smooth::SmoothOptions;
    let mut noisy = icosphere(4);
    for (i, p) in noisy.vertices.iter_mut().enumerate() {
        let h = 2.0 * ((i as f64 * 12.9898).sin() * 43758.5453).rem_euclid(1.0) - 1.0;
        for c in p.iter_mut() {
            *c *= 1.0 + 0.03 * h;
        }
    }
    let smooth = PrepareOptions {
        smooth: Some(SmoothOptions::steps(5)),
        ..PrepareOptions::default()
    };
    let (m0, r0, map0) = prepare_with_map(&noisy, &PrepareOptions::default()).unwrap();
    let (m1, r1, map1) = prepare_with_map(&noisy, &smooth).unwrap();
    assert_eq!(map0, map1);
    assert_eq!(m0.faces, m1.faces);
    assert_eq!(r0.euler_characteristic, r1.euler_characteristic);
    assert_ne!(m0.vertices, m1.vertices);
    // The noise added area, the smoothing took most of it away (the report's area is before
    // normalisation).
    let clean = icosphere(4).area();
    assert!(r1.original_area < r0.original_area);
    assert!((r1.original_area / clean - 1.0).abs() < 0.5 * (r0.original_area / clean - 1.0));
    // The report says how many pairs were taken, and nothing without smoothing.
    assert_eq!((r0.smooth_steps, r1.smooth_steps), (None, Some(5)));
    assert!(!serde_json::to_string(&r0).unwrap().contains("smooth"));
    let json = serde_json::to_string(&PrepareOptions::default()).unwrap();
    assert!(!json.contains("smooth"), "{json}");
    let bad = PrepareOptions {
        smooth: Some(SmoothOptions::steps(0)),
        ..PrepareOptions::default()
    };
    let e = prepare(&noisy, &bad).unwrap_err().to_string();
    assert!(e.contains("smooth: steps"), "{e}");
}
