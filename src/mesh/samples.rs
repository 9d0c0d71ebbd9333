//! A small labelled set of sample shapes, generated in code, for the demo and the viewer: a fresh
//! clone can ingest and search something meaningful without any benchmark data.
//!
//! Six classes of distinct shapes, five members each:
//!
//! | class | how it is built |
//! | --- | --- |
//! | `ring` | a tube around a closed curve of fixed length (circle, ellipse, wavy, saddle) |
//! | `blob` | [`generate::bumpy_sphere`], bent and twisted |
//! | `worm` | a tapered tube along an open curve of fixed length, curled differently |
//! | `star` | a ball with five two-segment arms, bent up and down at the root and the joint |
//! | `quadruped` | body, four two-segment legs, neck, head and tail |
//! | `biped` | torso, head, two arms and two legs, each of two segments |
//!
//! The tube and limb shapes are the zero level set of a smooth union of tapered capsules
//! ("skeleton" shapes; poses move the joints, so they are nearly isometric deformations),
//! polygonised by marching tetrahedra on a regular grid (one closed, connected, consistently
//! oriented surface; shared edge points are shared vertices) and smoothed by a few Taubin steps.
//!
//! The members of a class are, in order: `null` (pose 0), `isometry` 1 and 2 (poses 1 and 2),
//! `remesh` (pose 3 on a coarser grid with another offset, or another subdivision level) and
//! `noise` (pose 4 with every vertex moved randomly by 0.3% of the bounding-box diagonal). Every
//! member is also rotated, scaled and moved rigidly, and the files cycle through OBJ, PLY, OFF,
//! STL, GLB and glTF. Everything is deterministic: the same build writes the same bytes.

use super::read::Format;
use super::{generate, write::write_mesh, Mesh};
use crate::error::Result;
use std::collections::HashMap;
use std::f64::consts::PI;
use std::path::Path;

/// The classes, in the order [`samples`] generates them.
pub const CLASSES: [&str; 6] = ["ring", "blob", "worm", "star", "quadruped", "biped"];

/// The members of each class: (transform, strength), as in the benchmark manifests.
pub const MEMBERS: [(&str, u32); 5] = [
    ("null", 0),
    ("isometry", 1),
    ("isometry", 2),
    ("remesh", 1),
    ("noise", 1),
];

const FORMATS: [Format; 6] = [
    Format::Obj,
    Format::Ply,
    Format::Off,
    Format::Stl,
    Format::Glb,
    Format::Gltf,
];

/// One generated sample.
#[derive(Debug, Clone)]
pub struct Sample {
    /// File stem and display name, `<class>-<transform><strength>` (`ring-null`, `worm-iso2`).
    pub id: String,
    /// Its class.
    pub class: &'static str,
    /// `null`, `isometry`, `remesh` or `noise`.
    pub transform: &'static str,
    /// 0 for `null`, else the pose number or 1.
    pub strength: u32,
    /// The pose of its class (0..=4; for the manifest's `source_pose`).
    pub pose: usize,
    /// File format it is written in.
    pub format: Format,
    /// The mesh (already moved rigidly).
    pub mesh: Mesh,
}

/// Grid cells along the longest side of a skeleton shape's bounding box (the `remesh` member
/// uses [`REMESH_CELLS`]).
const CELLS: f64 = 44.0;
const REMESH_CELLS: f64 = 34.0;

/// Generates every sample (6 classes × 5 members = 30 meshes of 600–16 000 vertices).
pub fn samples() -> Vec<Sample> {
    let mut out = Vec::with_capacity(CLASSES.len() * MEMBERS.len());
    for (ci, &class) in CLASSES.iter().enumerate() {
        for (mi, &(transform, strength)) in MEMBERS.iter().enumerate() {
            let pose = mi; // members use poses 0..=4
            let remesh = transform == "remesh";
            let mut mesh = class_mesh(class, pose, remesh);
            let mut rng = Rng::new(0x5EED_0000 + (ci * 16 + mi) as u64);
            if transform == "noise" {
                add_noise(&mut mesh, 0.003, &mut rng);
            }
            rigid_motion(&mut mesh, &mut rng);
            let (id, strength) = match transform {
                "null" => (format!("{class}-null"), 0),
                "isometry" => (format!("{class}-iso{pose}"), pose as u32),
                t => (format!("{class}-{t}"), strength),
            };
            out.push(Sample {
                id,
                class,
                transform,
                strength,
                pose,
                format: FORMATS[(ci * MEMBERS.len() + mi) % FORMATS.len()],
                mesh,
            });
        }
    }
    out
}

/// Writes [`samples`] into `dir` (created if needed): one file per sample named
/// `<id>.<format>` and a `manifest.csv` with the benchmark manifest's columns
/// (`id,path,class,transform,strength,source_pose`), so `eval --manifest` reads it too.
/// Returns the samples written.
pub fn write_samples(dir: &Path) -> Result<Vec<Sample>> {
    std::fs::create_dir_all(dir)?;
    let all = samples();
    let mut manifest = String::from("id,path,class,transform,strength,source_pose\n");
    for s in &all {
        let file = format!("{}.{}", s.id, s.format.name());
        let mut bytes = Vec::new();
        write_mesh(&s.mesh, s.format, &mut bytes)?;
        std::fs::write(dir.join(&file), bytes)?;
        manifest.push_str(&format!(
            "{},{},{},{},{},{}-pose{}\n",
            s.id, file, s.class, s.transform, s.strength, s.class, s.pose
        ));
    }
    std::fs::write(dir.join("manifest.csv"), manifest)?;
    Ok(all)
}

/// The mesh of `class` in pose `pose` (0..=4), before the rigid motion and noise.
pub fn class_mesh(class: &str, pose: usize, remesh: bool) -> Mesh {
    let cells = if remesh { REMESH_CELLS } else { CELLS };
    let offset = if remesh { 0.37 } else { 0.0 };
    match class {
        "blob" => blob(pose, remesh),
        other => {
            let bones = match other {
                "ring" => ring(pose),
                "worm" => worm(pose),
                "star" => star(pose),
                "quadruped" => quadruped(pose),
                _ => biped(pose),
            };
            skeleton_mesh(&bones, 0.06, cells, offset)
        }
    }
}

/// A pose parameter in [-1, 1]: 0 for pose 0, else a fixed pseudo-random pattern per (pose, j).
fn wiggle(pose: usize, j: usize) -> f64 {
    if pose == 0 {
        0.0
    } else {
        (1.9 * pose as f64 + 1.3 * j as f64 + 0.4 * (pose * j) as f64).sin()
    }
}

// ---- skeleton shapes --------------------------------------------------------------------------

/// A tapered capsule: segment `a`–`b` with radius `ra` at `a`, `rb` at `b`.
#[derive(Debug, Clone, Copy)]
struct Bone {
    a: [f64; 3],
    b: [f64; 3],
    ra: f64,
    rb: f64,
}

fn bone(a: [f64; 3], b: [f64; 3], ra: f64, rb: f64) -> Bone {
    Bone { a, b, ra, rb }
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn mul(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    if n > 0.0 {
        mul(a, 1.0 / n)
    } else {
        a
    }
}

/// Rotates `v` about the unit `axis` by `angle` (Rodrigues).
fn rotate(v: [f64; 3], axis: [f64; 3], angle: f64) -> [f64; 3] {
    let (s, c) = angle.sin_cos();
    add(
        add(mul(v, c), mul(cross(axis, v), s)),
        mul(axis, dot(axis, v) * (1.0 - c)),
    )
}

/// A chain of bones from `root`, starting along `dir`; before segment `i` the direction turns
/// by `angles[i]` about `axis`. Radii taper linearly from `r0` to `r1`.
fn limb(
    root: [f64; 3],
    dir: [f64; 3],
    axis: [f64; 3],
    lengths: &[f64],
    angles: &[f64],
    r0: f64,
    r1: f64,
) -> Vec<Bone> {
    let axis = unit(axis);
    let mut d = unit(dir);
    let mut p = root;
    let n = lengths.len();
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        d = rotate(d, axis, angles.get(i).copied().unwrap_or(0.0));
        let q = add(p, mul(d, lengths[i]));
        let ra = r0 + (r1 - r0) * i as f64 / n as f64;
        let rb = r0 + (r1 - r0) * (i + 1) as f64 / n as f64;
        out.push(bone(p, q, ra, rb));
        p = q;
    }
    out
}

fn ring(pose: usize) -> Vec<Bone> {
    // A closed curve: circle plus an ellipse term, a three-lobe term and an out-of-plane saddle,
    // each weighted by the pose; resampled to a fixed length by scaling.
    let (a2, a3, z2) = match pose {
        0 => (0.0, 0.0, 0.0),
        1 => (0.25, 0.0, 0.0),
        2 => (0.0, 0.12, 0.0),
        3 => (0.0, 0.0, 0.35),
        _ => (0.15, 0.06, 0.2),
    };
    let m = 48;
    let pts: Vec<[f64; 3]> = (0..m)
        .map(|i| {
            let t = 2.0 * PI * i as f64 / m as f64;
            let r = 1.0 + a2 * (2.0 * t).cos() + a3 * (3.0 * t).cos();
            [r * t.cos(), r * t.sin(), z2 * (2.0 * t).sin()]
        })
        .collect();
    let len: f64 = (0..m)
        .map(|i| {
            let d = sub(pts[(i + 1) % m], pts[i]);
            dot(d, d).sqrt()
        })
        .sum();
    let s = 2.0 * PI / len;
    (0..m)
        .map(|i| bone(mul(pts[i], s), mul(pts[(i + 1) % m], s), 0.3, 0.3))
        .collect()
}

fn worm(pose: usize) -> Vec<Bone> {
    let n = 10;
    let lengths = vec![0.32; n];
    // Curl about z with a pose-dependent wave; a little out of plane for poses 3 and 4.
    let angles: Vec<f64> = (0..n)
        .map(|i| {
            if i == 0 {
                0.0
            } else {
                0.18 + 0.35 * wiggle(pose, i) * (i as f64 * 0.7 + pose as f64).cos()
            }
        })
        .collect();
    let tilt = if pose >= 3 { 0.25 } else { 0.0 };
    let mut bones = limb(
        [0.0; 3],
        [1.0, 0.0, 0.0],
        [0.0, tilt, 1.0],
        &lengths,
        &angles,
        0.2,
        0.1,
    );
    // A round head at the start.
    bones.push(bone([0.0; 3], [-0.12, 0.0, 0.0], 0.22, 0.2));
    bones
}

fn star(pose: usize) -> Vec<Bone> {
    let mut bones = vec![bone([0.0, 0.0, -0.1], [0.0, 0.0, 0.1], 0.42, 0.42)];
    for k in 0..5 {
        let th = 2.0 * PI * k as f64 / 5.0;
        let dir = [th.cos(), th.sin(), 0.0];
        let axis = [-th.sin(), th.cos(), 0.0]; // bending up/down
        let a0 = 0.45 * wiggle(pose, 2 * k);
        let a1 = 0.6 * wiggle(pose, 2 * k + 1);
        bones.extend(limb(
            mul(dir, 0.3),
            dir,
            axis,
            &[0.55, 0.5],
            &[a0, a1],
            0.2,
            0.1,
        ));
    }
    bones
}

fn quadruped(pose: usize) -> Vec<Bone> {
    let mut b = vec![bone([-0.8, 0.0, 0.0], [0.8, 0.0, 0.05], 0.32, 0.3)];
    // Legs: hips/shoulders at x = ±0.6, y = ±0.2, pointing down, swinging about y.
    for (k, &(x, y)) in [(0.6, 0.2), (0.6, -0.2), (-0.6, 0.2), (-0.6, -0.2)]
        .iter()
        .enumerate()
    {
        let swing = 0.45 * wiggle(pose, k);
        let knee = -0.5 * wiggle(pose, k + 4).abs() * if x > 0.0 { 1.0 } else { -1.0 };
        b.extend(limb(
            [x, y, -0.1],
            [0.0, 0.0, -1.0],
            [0.0, 1.0, 0.0],
            &[0.42, 0.4],
            &[swing, knee],
            0.13,
            0.1,
        ));
    }
    // Neck and head.
    let neck = 0.35 * wiggle(pose, 9);
    let nb = limb(
        [0.8, 0.0, 0.1],
        [0.6, 0.0, 0.8],
        [0.0, 1.0, 0.0],
        &[0.45],
        &[neck],
        0.17,
        0.15,
    );
    let top = nb[0].b;
    let head_dir = rotate([1.0, 0.0, -0.2], [0.0, 1.0, 0.0], neck);
    b.extend(nb);
    b.push(bone(top, add(top, mul(unit(head_dir), 0.3)), 0.2, 0.13));
    // Tail.
    b.extend(limb(
        [-0.8, 0.0, 0.05],
        [-0.8, 0.0, 0.6],
        [0.2 * wiggle(pose, 11), 1.0, 0.0],
        &[0.35, 0.35],
        &[0.5 * wiggle(pose, 10), 0.5 * wiggle(pose, 12)],
        0.1,
        0.08,
    ));
    b
}

fn biped(pose: usize) -> Vec<Bone> {
    let mut b = vec![
        bone([0.0, 0.0, 0.0], [0.0, 0.0, 0.85], 0.27, 0.3),
        bone([0.0, 0.0, 0.9], [0.0, 0.0, 1.12], 0.11, 0.11),
    ];
    // Head.
    let nod = 0.25 * wiggle(pose, 8);
    let hd = rotate([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], nod);
    b.push(bone(
        add([0.0, 0.0, 1.12], mul(hd, 0.12)),
        add([0.0, 0.0, 1.12], mul(hd, 0.3)),
        0.2,
        0.18,
    ));
    // Arms from the shoulders, raised sideways (kept away from the torso), elbows bent.
    for (k, side) in [1.0f64, -1.0].iter().enumerate() {
        let raise = 0.9 + 0.4 * wiggle(pose, k);
        let dir = [side * raise.sin(), 0.0, -raise.cos()];
        let elbow = 0.6 * wiggle(pose, k + 2);
        b.extend(limb(
            [side * 0.3, 0.0, 0.78],
            dir,
            [0.0, 1.0, 0.3 * wiggle(pose, k + 6)],
            &[0.42, 0.38],
            &[0.0, elbow],
            0.1,
            0.08,
        ));
    }
    // Legs from the hips, swinging forward/back, knees bent.
    for (k, side) in [1.0f64, -1.0].iter().enumerate() {
        let swing = 0.4 * wiggle(pose, k + 4);
        let knee = -0.55 * wiggle(pose, k + 10).abs();
        b.extend(limb(
            [side * 0.15, 0.0, -0.05],
            [side * 0.15, 0.0, -1.0],
            [1.0, 0.0, 0.0],
            &[0.5, 0.48],
            &[swing, knee],
            0.14,
            0.1,
        ));
    }
    b
}

/// Signed distance (approximate, negative inside) to a tapered capsule.
fn bone_sdf(p: [f64; 3], bn: &Bone) -> f64 {
    let ab = sub(bn.b, bn.a);
    let l2 = dot(ab, ab);
    let t = if l2 > 0.0 {
        (dot(sub(p, bn.a), ab) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let c = add(bn.a, mul(ab, t));
    let d = sub(p, c);
    dot(d, d).sqrt() - (bn.ra + (bn.rb - bn.ra) * t)
}

/// Polynomial smooth minimum (blend radius `k`).
fn smin(a: f64, b: f64, k: f64) -> f64 {
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b + (a - b) * h - k * h * (1.0 - h)
}

fn skeleton_mesh(bones: &[Bone], blend: f64, cells: f64, offset: f64) -> Mesh {
    let rmax = bones.iter().map(|b| b.ra.max(b.rb)).fold(0.0, f64::max);
    let (mut lo, mut hi) = super::bounding_box(bones.iter().flat_map(|b| [&b.a, &b.b]));
    let longest = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max) + 2.0 * rmax;
    let h = longest / cells;
    for k in 0..3 {
        lo[k] -= rmax + 2.0 * h + offset * h;
        hi[k] += rmax + 2.0 * h;
    }
    let f = |p: [f64; 3]| {
        bones
            .iter()
            .map(|b| bone_sdf(p, b))
            .reduce(|a, d| smin(a, d, blend))
            .unwrap_or(1.0)
    };
    let mesh = marching_tetrahedra(&f, lo, hi, h);
    taubin(&mesh, 6, 0.5, -0.53)
}

/// Polygonises the zero level set of `f` (negative inside) on the grid of spacing `h` from `lo`
/// to at least `hi`: each cube is split into the six tetrahedra of its 0–7 diagonal (the same
/// split in every cube, so neighbouring cubes agree on their shared faces), each tetrahedron
/// yields 0, 1 or 2 triangles, oriented with the outside (f ≥ 0) in front.
fn marching_tetrahedra(f: &dyn Fn([f64; 3]) -> f64, lo: [f64; 3], hi: [f64; 3], h: f64) -> Mesh {
    let n: Vec<usize> = (0..3)
        .map(|k| ((hi[k] - lo[k]) / h).ceil() as usize + 1)
        .collect();
    let (nx, ny, nz) = (n[0], n[1], n[2]);
    let idx = |i: usize, j: usize, k: usize| (k * ny + j) * nx + i;
    let pos = |i: usize, j: usize, k: usize| {
        [
            lo[0] + i as f64 * h,
            lo[1] + j as f64 * h,
            lo[2] + k as f64 * h,
        ]
    };
    let mut val = vec![0.0; nx * ny * nz];
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                val[idx(i, j, k)] = f(pos(i, j, k));
            }
        }
    }
    // The six tetrahedra of a cube: paths 0 → e_a → e_a + e_b → 7 over the axis orders.
    const PERMS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut vertices: Vec<[f64; 3]> = Vec::new();
    let mut faces: Vec<[u32; 3]> = Vec::new();
    let mut edge_vertex: HashMap<(usize, usize), u32> = HashMap::new();
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let corner = |c: usize| (i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
                for perm in PERMS {
                    let c1 = 1 << perm[0];
                    let c2 = c1 | (1 << perm[1]);
                    let tet = [0usize, c1, c2, 7];
                    let g: [usize; 4] = tet.map(|c| {
                        let (a, b, d) = corner(c);
                        idx(a, b, d)
                    });
                    let p: [[f64; 3]; 4] = tet.map(|c| {
                        let (a, b, d) = corner(c);
                        pos(a, b, d)
                    });
                    let s: [f64; 4] = g.map(|gi| val[gi]);
                    let inside: Vec<usize> = (0..4).filter(|&t| s[t] < 0.0).collect();
                    let outside: Vec<usize> = (0..4).filter(|&t| s[t] >= 0.0).collect();
                    if inside.is_empty() || outside.is_empty() {
                        continue;
                    }
                    let mut ev = |a: usize, b: usize| -> u32 {
                        // a inside, b outside.
                        let key = (g[a].min(g[b]), g[a].max(g[b]));
                        *edge_vertex.entry(key).or_insert_with(|| {
                            let t = (s[a] / (s[a] - s[b])).clamp(0.02, 0.98);
                            vertices.push(add(p[a], mul(sub(p[b], p[a]), t)));
                            (vertices.len() - 1) as u32
                        })
                    };
                    let tris: Vec<[u32; 3]> = match (inside.len(), outside.len()) {
                        (1, 3) => {
                            let a = inside[0];
                            vec![[ev(a, outside[0]), ev(a, outside[1]), ev(a, outside[2])]]
                        }
                        (3, 1) => {
                            let b = outside[0];
                            vec![[ev(inside[0], b), ev(inside[1], b), ev(inside[2], b)]]
                        }
                        _ => {
                            let (a, b) = (inside[0], inside[1]);
                            let (c, d) = (outside[0], outside[1]);
                            let (ac, ad, bd, bc) = (ev(a, c), ev(a, d), ev(b, d), ev(b, c));
                            vec![[ac, ad, bd], [ac, bd, bc]]
                        }
                    };
                    // Orient: the normal points from the inside corners to the outside ones.
                    let cin = centroid(inside.iter().map(|&t| p[t]));
                    let cout = centroid(outside.iter().map(|&t| p[t]));
                    let out_dir = sub(cout, cin);
                    for mut t in tris {
                        let [x, y, z] = t.map(|v| vertices[v as usize]);
                        if dot(cross(sub(y, x), sub(z, x)), out_dir) < 0.0 {
                            t.swap(1, 2);
                        }
                        faces.push(t);
                    }
                }
            }
        }
    }
    Mesh::new(vertices, faces)
}

fn centroid(pts: impl Iterator<Item = [f64; 3]>) -> [f64; 3] {
    let mut c = [0.0; 3];
    let mut n = 0.0;
    for p in pts {
        c = add(c, p);
        n += 1.0;
    }
    mul(c, 1.0 / n)
}

/// Taubin smoothing (`steps` pairs of umbrella steps with factors `lambda` and `mu`): smooths
/// the grid's staircase and evens the triangles without shrinking the shape.
fn taubin(mesh: &Mesh, steps: usize, lambda: f64, mu: f64) -> Mesh {
    let n = mesh.vertices.len();
    let mut nbr: Vec<Vec<u32>> = vec![Vec::new(); n];
    for f in &mesh.faces {
        for e in 0..3 {
            let (a, b) = (f[e] as usize, f[(e + 1) % 3]);
            if !nbr[a].contains(&b) {
                nbr[a].push(b);
                nbr[b as usize].push(f[e]);
            }
        }
    }
    let mut v = mesh.vertices.clone();
    for _ in 0..steps {
        for factor in [lambda, mu] {
            let next: Vec<[f64; 3]> = (0..n)
                .map(|i| {
                    if nbr[i].is_empty() {
                        return v[i];
                    }
                    let avg = centroid(nbr[i].iter().map(|&j| v[j as usize]));
                    add(v[i], mul(sub(avg, v[i]), factor))
                })
                .collect();
            v = next;
        }
    }
    Mesh::new(v, mesh.faces.clone())
}

// ---- the parametric class ---------------------------------------------------------------------

fn blob(pose: usize, remesh: bool) -> Mesh {
    let mut m = generate::bumpy_sphere(if remesh { 3 } else { 4 }, 0.3);
    // Bend about y by an angle proportional to x, then twist about x.
    let bend = 0.35 * wiggle(pose, 0);
    let twist = 0.5 * wiggle(pose, 1);
    for v in &mut m.vertices {
        let [x, y, z] = *v;
        let a = twist * x;
        let (y, z) = (y * a.cos() - z * a.sin(), y * a.sin() + z * a.cos());
        // Bend about an axis parallel to y at z = 1/bend: x runs along an arc.
        *v = if bend.abs() > 1e-12 {
            let r = 1.0 / bend;
            let th = bend * x;
            [th.sin() * (r - z), y, r - th.cos() * (r - z)]
        } else {
            [x, y, z]
        };
    }
    m
}

// ---- randomness and rigid motions -------------------------------------------------------------

/// xorshift64*: a tiny deterministic generator (no dependency, same numbers everywhere).
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Self(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let x = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D);
        (x >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in [-1, 1).
    fn signed(&mut self) -> f64 {
        2.0 * self.next_f64() - 1.0
    }
}

fn add_noise(mesh: &mut Mesh, fraction: f64, rng: &mut Rng) {
    let (lo, hi) = super::bounding_box(&mesh.vertices);
    let diag = dot(sub(hi, lo), sub(hi, lo)).sqrt();
    for v in &mut mesh.vertices {
        for c in v.iter_mut() {
            *c += fraction * diag * rng.signed();
        }
    }
}

fn rigid_motion(mesh: &mut Mesh, rng: &mut Rng) {
    let axis = unit([rng.signed(), rng.signed(), rng.signed() + 0.1]);
    let angle = PI * rng.signed();
    let r: Vec<[f64; 3]> = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        .iter()
        .map(|&e| rotate(e, axis, angle))
        .collect();
    // Columns are the images of the basis vectors; Mesh::transform takes rows.
    let rows = [
        [r[0][0], r[1][0], r[2][0]],
        [r[0][1], r[1][1], r[2][1]],
        [r[0][2], r[1][2], r[2][2]],
    ];
    let scale = 2f64.powf(rng.signed());
    mesh.scale(scale);
    mesh.transform(rows, [rng.signed(), rng.signed(), rng.signed()]);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::prepare::{prepare, PrepareOptions};
    use crate::mesh::read::{read_mesh, ReadLimits};
    use std::collections::HashMap;

    /// Every edge is shared by exactly two faces with opposite directions (closed, oriented).
    fn closed_and_oriented(m: &Mesh) -> Result<(), String> {
        let mut dir: HashMap<(u32, u32), i32> = HashMap::new();
        for f in &m.faces {
            for e in 0..3 {
                let (a, b) = (f[e], f[(e + 1) % 3]);
                *dir.entry((a, b)).or_default() += 1;
            }
        }
        for (&(a, b), &c) in &dir {
            if c != 1 || dir.get(&(b, a)).copied() != Some(1) {
                return Err(format!(
                    "edge {a}-{b}: {c} times, reverse {:?}",
                    dir.get(&(b, a))
                ));
            }
        }
        Ok(())
    }

    #[test]
    fn every_class_is_one_closed_oriented_surface() {
        for class in CLASSES {
            for (pose, remesh) in [(0, false), (2, false), (3, true)] {
                let m = class_mesh(class, pose, remesh);
                let (p, r) = prepare(&m, &PrepareOptions::default()).unwrap();
                assert_eq!(r.components, 1, "{class} pose {pose}: {r:?}");
                assert_eq!(r.boundary_loops, 0, "{class} pose {pose}");
                assert_eq!(r.nonmanifold_edges, 0, "{class} pose {pose}");
                assert_eq!(r.inconsistent_orientation_edges, 0, "{class} pose {pose}");
                let genus_0 = class != "ring";
                assert_eq!(
                    r.euler_characteristic,
                    if genus_0 { 2 } else { 0 },
                    "{class} pose {pose}"
                );
                assert!(
                    (1000..20_000).contains(&p.vertices.len()) || (class == "blob" && remesh),
                    "{class} pose {pose}: {} vertices",
                    p.vertices.len()
                );
                closed_and_oriented(&m).unwrap_or_else(|e| panic!("{class} pose {pose}: {e}"));
                // Outward orientation: positive signed volume.
                let vol: f64 = m
                    .faces
                    .iter()
                    .map(|f| {
                        let [a, b, c] = f.map(|i| m.vertices[i as usize]);
                        dot(a, cross(b, c)) / 6.0
                    })
                    .sum();
                assert!(vol > 0.0, "{class} pose {pose}: volume {vol}");
            }
        }
    }

    #[test]
    fn poses_differ_and_generation_is_deterministic() {
        let a = samples();
        let b = samples();
        assert_eq!(a.len(), CLASSES.len() * MEMBERS.len());
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(x.id, y.id);
            assert_eq!(x.mesh, y.mesh);
        }
        let ids: std::collections::HashSet<_> = a.iter().map(|s| s.id.clone()).collect();
        assert_eq!(ids.len(), a.len(), "ids are unique");
        for class in CLASSES {
            let p0 = class_mesh(class, 0, false);
            let p1 = class_mesh(class, 1, false);
            assert_ne!(
                p0.vertices, p1.vertices,
                "{class}: pose 1 differs from pose 0"
            );
        }
        let formats: std::collections::HashSet<_> = a.iter().map(|s| s.format).collect();
        assert_eq!(formats.len(), 6, "all six formats are used");
    }

    #[test]
    fn written_files_read_back_with_the_manifest() {
        let dir = tempfile::tempdir().unwrap();
        let all = write_samples(dir.path()).unwrap();
        let manifest = std::fs::read_to_string(dir.path().join("manifest.csv")).unwrap();
        let lines: Vec<&str> = manifest.lines().collect();
        assert_eq!(lines[0], "id,path,class,transform,strength,source_pose");
        assert_eq!(lines.len(), all.len() + 1);
        for (s, line) in all.iter().zip(&lines[1..]) {
            let cols: Vec<&str> = line.split(',').collect();
            assert_eq!(cols[0], s.id);
            assert_eq!(cols[2], s.class);
            let bytes = std::fs::read(dir.path().join(cols[1])).unwrap();
            let m = read_mesh(&bytes, Some(s.format), &ReadLimits::default()).unwrap();
            assert_eq!(m.faces.len(), s.mesh.faces.len(), "{}", s.id);
        }
    }
}
