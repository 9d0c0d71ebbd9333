//! Topology and handle cutting (`shapeseek::mesh::topology`) on shapes built in code: genus of
//! closed surfaces, genuine handles that must survive (a torus, a mug handle on a sphere, a thick
//! ring of varying section) and welded necks that must be cut (a short tube between the two tips
//! of a bent, C-shaped body; the same with a genuine handle on the body).

use shapeseek::mesh::generate::{icosphere, torus};
use shapeseek::mesh::topology::{
    cut_handles, short_homology_basis, surface_stats, HandleCutOptions,
};
use shapeseek::mesh::Mesh;
use std::f64::consts::PI;

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}
fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = norm(a);
    [a[0] / n, a[1] / n, a[2] / n]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn add(a: [f64; 3], b: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

/// Removes every face with a vertex closer than `radius` to `centre` and returns the vertices
/// of the new hole's boundary, ordered by angle around `axis` in the frame `(u, axis × u)`.
fn drill(mesh: &mut Mesh, centre: [f64; 3], radius: f64, axis: [f64; 3], u: [f64; 3]) -> Vec<u32> {
    let inside: Vec<bool> = mesh
        .vertices
        .iter()
        .map(|&p| norm(sub(p, centre)) < radius)
        .collect();
    let before = mesh.faces.len();
    mesh.faces
        .retain(|f| !f.iter().any(|&v| inside[v as usize]));
    assert!(mesh.faces.len() < before, "nothing drilled");
    // Rim: kept vertices that shared a face with a removed vertex.
    let mut rim: Vec<u32> = Vec::new();
    for (i, p) in mesh.vertices.iter().enumerate() {
        if !inside[i] && norm(sub(*p, centre)) < radius * 1.9 {
            rim.push(i as u32);
        }
    }
    // Keep only vertices on a boundary edge.
    let mut count = std::collections::HashMap::new();
    for f in &mesh.faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            *count.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    let mut on_boundary = std::collections::HashSet::new();
    for (&(a, b), &c) in &count {
        if c == 1 {
            on_boundary.insert(a);
            on_boundary.insert(b);
        }
    }
    rim.retain(|v| on_boundary.contains(v));
    let v = cross(axis, u);
    let angle = |i: u32| {
        let d = sub(mesh.vertices[i as usize], centre);
        dot(d, v).atan2(dot(d, u))
    };
    rim.sort_by(|&a, &b| angle(a).total_cmp(&angle(b)));
    rim
}

/// Triangulates the band between two closed loops ordered in the same rotational sense.
fn zip(faces: &mut Vec<[u32; 3]>, p: &[u32], q: &[u32]) {
    let (np, nq) = (p.len(), q.len());
    let (mut i, mut j) = (0, 0);
    while i < np || j < nq {
        if j >= nq || (i < np && (i + 1) as f64 / np as f64 <= (j + 1) as f64 / nq as f64) {
            faces.push([p[i % np], p[(i + 1) % np], q[j % nq]]);
            i += 1;
        } else {
            faces.push([p[i % np], q[(j + 1) % nq], q[j % nq]]);
            j += 1;
        }
    }
}

/// A tube through the given centre points (`rings.len() ≥ 1`), ring `k` of `m` points of radius
/// `radii[k]` in the frame `(u_k, v_k)`, joining hole `a` (at the first ring) to hole `b` (at the
/// last).
fn tube(
    mesh: &mut Mesh,
    a: &[u32],
    b: &[u32],
    centres: &[[f64; 3]],
    frames: &[([f64; 3], [f64; 3])],
    radii: &[f64],
    m: usize,
) {
    let mut prev = a.to_vec();
    for ((c, (u, v)), &r) in centres.iter().zip(frames).zip(radii) {
        let start = mesh.vertices.len() as u32;
        for k in 0..m {
            let t = 2.0 * PI * k as f64 / m as f64;
            let p = add(add(*c, *u, r * t.cos()), *v, r * t.sin());
            mesh.vertices.push(p);
        }
        let ring: Vec<u32> = (start..start + m as u32).collect();
        zip(&mut mesh.faces, &prev, &ring);
        prev = ring;
    }
    zip(&mut mesh.faces, &prev, b);
}

fn sphere(subdiv: u32) -> Mesh {
    icosphere(subdiv)
}

/// A unit sphere with a mug-like handle: a tube of radius `r` along an arc in the xz-plane that
/// leaves the sphere at polar angles ±`half` from +x and bulges out to `reach`.
fn mug(r: f64, half: f64, reach: f64) -> Mesh {
    handle_on_sphere(r, r, half, reach)
}

/// A limb welded to the body: the handle of [`mug`] with radius `r` leaves the sphere at one end
/// as a limb, and its tip meets the sphere at the other end through a short neck of radius
/// `weld` (its last two rings), as a hand welded to a thigh. Seen from the neck, the surface
/// flares into the body at once on one side and runs along the limb on the other.
fn limb_welded_to_body(r: f64, weld: f64, half: f64, reach: f64) -> Mesh {
    handle_on_sphere(r, weld, half, reach)
}

/// A unit sphere with a handle along an arc in the xz-plane that leaves the sphere at polar
/// angles ±`half` from +x and bulges out to `reach`: a tube of radius `r` whose last two rings
/// (and the hole they meet) have radius `end`.
fn handle_on_sphere(r: f64, end: f64, half: f64, reach: f64) -> Mesh {
    let mut m = sphere(4);
    let p1 = [half.cos(), 0.0, half.sin()];
    let p2 = [half.cos(), 0.0, -half.sin()];
    let y = [0.0, 1.0, 0.0];
    // Arc centre on the x-axis through p1, p2 and [reach, 0, 0].
    let x0 = (reach * reach - 1.0) / (2.0 * (reach - half.cos()));
    let c0 = [x0, 0.0, 0.0];
    let rad = reach - x0;
    let phi1 = (p1[2]).atan2(p1[0] - x0);
    let radial = |phi: f64| [phi.cos(), 0.0, phi.sin()];
    // Holes: axis = arc tangent at the end, frame u = radial of the arc.
    let h1 = drill(&mut m, p1, r * 1.05, cross(radial(phi1), y), radial(phi1));
    let h2 = drill(
        &mut m,
        p2,
        end * 1.05,
        cross(radial(-phi1), y),
        radial(-phi1),
    );
    let n = 40;
    let mut centres = Vec::new();
    let mut frames = Vec::new();
    let mut radii = Vec::new();
    for k in 1..n {
        // from phi1 down to -phi1 through 0 (the far side of the arc, at `reach`).
        let phi = phi1 - 2.0 * phi1 * k as f64 / n as f64;
        centres.push(add(c0, radial(phi), rad));
        frames.push((radial(phi), y));
        radii.push(if k + 2 >= n { end } else { r });
    }
    tube(&mut m, &h1, &h2, &centres, &frames, &radii, 16);
    m
}

/// A torus whose tube radius varies from `r_min` to `r_max` around the ring ("arms and joined
/// hands": a genuine, thick ring with a thinnest place).
fn thick_ring(r_min: f64, r_max: f64) -> Mesh {
    let mut m = torus(1.0, 1.0, 96, 24);
    let (nu, nv) = (96, 24);
    for (idx, p) in m.vertices.iter_mut().enumerate() {
        let (i, j) = (idx / nv, idx % nv);
        let u = 2.0 * PI * i as f64 / nu as f64;
        let w = 2.0 * PI * j as f64 / nv as f64;
        let minor = r_min + (r_max - r_min) * 0.5 * (1.0 - u.cos());
        let rr = 1.2 + minor * w.cos();
        *p = [rr * u.cos(), rr * u.sin(), minor * w.sin()];
    }
    m
}

fn genus(m: &Mesh) -> usize {
    surface_stats(m).unwrap().genus.expect("orientable")
}

#[test]
fn genus_of_sphere_torus_and_two_handled_sphere() {
    assert_eq!(genus(&sphere(3)), 0);
    assert_eq!(genus(&torus(2.0, 0.5, 30, 12)), 1);
    let s = surface_stats(&torus(2.0, 0.5, 30, 12)).unwrap();
    assert_eq!(
        (s.euler_characteristic, s.boundary_loops, s.components),
        (0, 0, 1)
    );
    let m = mug(0.15, 0.6, 1.8);
    assert_eq!(genus(&m), 1);
    // Double torus: a sphere with two handles.
    let mut two = sphere(4);
    let y = [0.0, 1.0, 0.0];
    let z = [0.0, 0.0, 1.0];
    let x = [1.0, 0.0, 0.0];
    for (sgn, axis) in [(1.0, x), (-1.0, x)] {
        let p1 = unit([sgn * 0.8, 0.0, 0.6]);
        let p2 = unit([sgn * 0.8, 0.0, -0.6]);
        let h1 = drill(&mut two, p1, 0.16, z, axis);
        let h2 = drill(&mut two, p2, 0.16, z, axis);
        let mut centres = Vec::new();
        let mut frames = Vec::new();
        for k in 1..10 {
            let t = k as f64 / 10.0;
            let c = add(
                add(p1, sub(p2, p1), t),
                [sgn, 0.0, 0.0],
                0.8 * (PI * t).sin(),
            );
            centres.push(c);
            frames.push((axis, cross(z, axis)));
        }
        tube(&mut two, &h1, &h2, &centres, &frames, &[0.15; 9], 16);
        let _ = y;
    }
    assert_eq!(genus(&two), 2);
    // A disc (boundary, genus 0).
    let d = shapeseek::mesh::generate::rectangle(1.0, 1.0, 6, 6);
    let s = surface_stats(&d).unwrap();
    assert_eq!(
        (s.genus, s.boundary_loops, s.euler_characteristic),
        (Some(0), 1, 1)
    );
}

#[test]
fn torus_homology_basis_is_meridian_then_inner_equator() {
    let m = torus(2.0, 0.5, 60, 16);
    let b = short_homology_basis(&m, 8, 3).unwrap();
    assert_eq!(b.len(), 2);
    let meridian = 16.0 * 2.0 * 0.5 * (PI / 16.0).sin();
    assert!(
        (b[0].length - meridian).abs() < 1e-6 * meridian,
        "{}",
        b[0].length
    );
    let inner = 60.0 * 2.0 * 1.5 * (PI / 60.0).sin();
    assert!(
        b[1].length >= inner - 1e-9 && b[1].length < inner * 1.02,
        "{}",
        b[1].length
    );
}

#[test]
fn genuine_handles_survive() {
    let opts = HandleCutOptions::default();
    for (name, m) in [
        ("torus", torus(3.0, 0.5, 90, 16)),
        ("mug", mug(0.15, 0.6, 1.8)),
        ("thick ring", thick_ring(0.22, 0.4)),
    ] {
        let (out, rep) = cut_handles(&m, &opts).unwrap();
        assert_eq!(rep.cuts, 0, "{name}: {rep:?}");
        assert_eq!(rep.after.genus, Some(1), "{name}");
        assert_eq!(out, m, "{name}: mesh changed");
        // Its short loop was examined and judged a long tube / ring.
        let l = &rep.loops[0];
        assert!(
            l.neck_aspect.unwrap() > opts.max_neck_aspect,
            "{name}: {l:?}"
        );
    }
}

#[test]
fn bad_input_is_refused() {
    let m = Mesh::new(vec![[0.0; 3]; 3], vec![[0, 1, 5]]);
    assert!(surface_stats(&m).is_err());
    let m = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 1.0, 1.0],
        ],
        vec![[0, 1, 2], [0, 1, 3], [0, 1, 4]],
    );
    assert!(matches!(
        surface_stats(&m),
        Err(shapeseek::mesh::topology::TopologyError::NonManifoldEdge(
            0, 1
        ))
    ));
    let opts = HandleCutOptions {
        growth: 1.0,
        ..Default::default()
    };
    assert!(cut_handles(&torus(2.0, 0.5, 10, 6), &opts).is_err());
}

/// A C-shaped body welded shut: a ring of radius 1 around the z-axis whose tube (radius
/// `thick`) ends at both tips of a gap of `gap` radians in hemispherical caps, and a short thin
/// tube of radius `weld` across the gap joining the two caps' poles. Topologically a torus;
/// geometrically the bench's weld: two parts far apart along the surface (the tips, ≈ 2π apart)
/// joined by a short tube that flares into the body within a tube radius on both sides.
fn welded_c(thick: f64, weld: f64, gap: f64, nu: usize, nv: usize) -> Mesh {
    let mut m = torus(1.0, 1.0, nu, nv);
    let half = 0.5 * gap;
    for (idx, p) in m.vertices.iter_mut().enumerate() {
        let (i, j) = (idx / nv, idx % nv);
        let u = 2.0 * PI * i as f64 / nu as f64;
        let w = 2.0 * PI * j as f64 / nv as f64;
        // Arc distance from the nearer tip of the C (negative inside the gap, centred on u = 0).
        let a = u.min(2.0 * PI - u);
        let d = a - half;
        let cap = if d <= 0.0 {
            0.0
        } else if d < thick {
            (thick * thick - (thick - d) * (thick - d)).sqrt()
        } else {
            thick
        };
        let minor = cap.max(weld);
        let rr = 1.0 + minor * w.cos();
        *p = [rr * u.cos(), rr * u.sin(), minor * w.sin()];
    }
    m
}

#[test]
fn welded_neck_is_cut_and_deterministic() {
    use shapeseek::mesh::prepare::{prepare, PrepareOptions};
    let m = welded_c(0.25, 0.06, 0.12, 360, 24);
    assert_eq!(genus(&m), 1);
    for opts in [
        shapeseek::presets::DEFAULT_HANDLE_CUT,
        HandleCutOptions::default(),
        HandleCutOptions {
            max_neck_aspect: 1e9,
            max_loop_rel: 0.2,
            ..Default::default()
        },
    ] {
        let (out, rep) = cut_handles(&m, &opts).unwrap();
        assert_eq!(rep.cuts, 1, "{rep:?}");
        assert_eq!(rep.after.genus, Some(0), "{rep:?}");
        assert_eq!(genus(&out), 0);
        assert!(rep.area_kept > 0.97 && rep.area_kept < 1.0, "{rep:?}");
        // The loop cut goes around the weld tube (circumference 2π·0.06 ≈ 0.377), not the body.
        let l = rep.loops.iter().find(|l| l.cut).unwrap();
        assert!(
            (l.length - 2.0 * PI * 0.06).abs() < 0.05,
            "cut loop length {}",
            l.length
        );
        // Deterministic: the same input gives the same output, bit for bit.
        let (again, rep2) = cut_handles(&m, &opts).unwrap();
        assert_eq!(again, out);
        assert_eq!(rep2, rep);
        // Through preparation: one cut, genus 0, unit area, > 97 % of the area kept, and the
        // vertex map points every kept input vertex at the same position (up to normalisation).
        let popts = PrepareOptions {
            cut_handles: Some(opts.clone()),
            normalize_area: false,
            ..PrepareOptions::default()
        };
        let (p, r, map) = shapeseek::mesh::prepare::prepare_with_map(&m, &popts).expect("prepared");
        let hc = r.handle_cut.clone().expect("summary");
        assert_eq!(
            (hc.cuts, hc.genus_before, hc.genus_after),
            (1, Some(1), Some(0))
        );
        assert!(hc.area_kept > 0.97, "{hc:?}");
        assert_eq!(genus(&p), 0);
        assert_eq!(r.vertices_out, p.vertices.len());
        let mut kept = 0;
        for (i, o) in map.iter().enumerate() {
            if let Some(o) = o {
                assert_eq!(p.vertices[*o as usize], m.vertices[i]);
                kept += 1;
            }
        }
        assert!(kept > m.vertices.len() - 3 * 24, "{kept}");
        let (p2, r2) = prepare(&m, &popts).unwrap();
        assert_eq!((p2, r2.handle_cut.map(|h| h.cuts)), (p, Some(1)));
    }
}

#[test]
fn capping_and_cutting_together_count_the_dropped_vertices_once() {
    use shapeseek::mesh::prepare::{prepare, PrepareOptions};
    let (nu, nv) = (360, 24);
    let mut m = welded_c(0.25, 0.06, 0.12, nu, nv);
    // A hole opposite the weld: the faces around one vertex of the body's outer equator.
    let centre = ((nu / 2) * nv) as u32;
    m.faces.retain(|f| !f.contains(&centre));
    let cut_only = PrepareOptions {
        cut_handles: Some(shapeseek::presets::DEFAULT_HANDLE_CUT),
        normalize_area: false,
        ..PrepareOptions::default()
    };
    let both = PrepareOptions {
        cap_boundaries: Some(shapeseek::presets::DEFAULT_CAP),
        ..cut_only.clone()
    };
    let (_, open) = prepare(&m, &cut_only).unwrap();
    let (p, capped) = prepare(&m, &both).unwrap();
    assert_eq!(capped.capped.map(|c| c.loops), Some(1), "{capped:?}");
    assert_eq!(open.handle_cut.as_ref().map(|h| h.cuts), Some(1));
    assert_eq!(capped.handle_cut.as_ref().map(|h| h.cuts), Some(1));
    // The vertices dropped are the hole's centre and the cut's band, with or without the cap
    // (the caps' vertices were once subtracted from the count, which wrapped around).
    assert_eq!(capped.unreferenced_vertices, open.unreferenced_vertices);
    assert!(
        (1..3 * nv).contains(&capped.unreferenced_vertices),
        "{capped:?}"
    );
    assert_eq!(capped.vertices_out, p.vertices.len());
}

#[test]
fn genuine_handles_survive_preparation_with_cutting() {
    use shapeseek::mesh::prepare::{prepare, PrepareOptions};
    for opts in [
        shapeseek::presets::DEFAULT_HANDLE_CUT,
        HandleCutOptions::default(),
        HandleCutOptions {
            max_neck_aspect: 1e9,
            max_loop_rel: 0.2,
            ..Default::default()
        },
    ] {
        for (name, m) in [
            ("torus", torus(3.0, 0.5, 90, 16)),
            ("mug", mug(0.15, 0.6, 1.8)),
            ("thick ring", thick_ring(0.22, 0.4)),
            ("joined arms", mug(0.08, 0.6, 1.8)),
        ] {
            if name == "joined arms" && opts.max_loop_rel == 0.2 {
                continue; // the length-only rule cuts them (see the test below)
            }
            let plain = prepare(&m, &PrepareOptions::default()).unwrap();
            let with = prepare(
                &m,
                &PrepareOptions {
                    cut_handles: Some(opts.clone()),
                    ..PrepareOptions::default()
                },
            )
            .unwrap();
            assert_eq!(with.0, plain.0, "{name}: mesh changed");
            let hc = with.1.handle_cut.expect("summary");
            assert_eq!((hc.cuts, hc.genus_after), (0, Some(1)), "{name}");
            assert!(plain.1.handle_cut.is_none());
        }
    }
}

#[test]
fn preparation_options_without_cutting_serialise_as_before() {
    use shapeseek::mesh::prepare::PrepareOptions;
    let j = serde_json::to_value(PrepareOptions::default()).unwrap();
    assert!(j.get("cut_handles").is_none(), "{j}");
    let o: PrepareOptions = serde_json::from_str(r#"{"cut_handles": {}}"#).unwrap();
    assert_eq!(o.cut_handles, Some(HandleCutOptions::default()));
    let bad = PrepareOptions {
        cut_handles: Some(HandleCutOptions {
            remove_band: false,
            ..Default::default()
        }),
        ..PrepareOptions::default()
    };
    assert!(shapeseek::mesh::prepare::prepare(&torus(2.0, 0.5, 20, 8), &bad).is_err());
}

/// The product default's rule (`presets::DEFAULT_HANDLE_CUT`: `L/√A ≤ 0.5` and neck aspect
/// `≤ 3`) keeps every genuine handle, including arms joined into a ring on a body (a thin, long
/// handle on a sphere: `L/√A` ≈ 0.13, as short as the bench's welds, aspect ≈ 5.4), which a
/// length-only rule (`free_loop_rel` 0.2) cuts: the test fails for a rule without the neck test.
///
/// Each shape's second basis loop runs through the handle and across the body, `L/√A` 0.61–2.08;
/// the shortest is the short joined arms' (0.607, neck aspect 2.71 ≤ 3), which the rule would cut
/// if its length bound reached it. The bound 0.65, the protocol's choice of `docs/quality.md` §30,
/// does: it was not adopted for this reason (§31).
#[test]
fn default_rule_keeps_joined_arms_that_a_length_rule_cuts() {
    let arms = mug(0.08, 0.6, 1.8);
    assert_eq!(genus(&arms), 1);
    let default = shapeseek::presets::DEFAULT_HANDLE_CUT;
    for (name, m) in [
        ("torus", torus(3.0, 0.5, 90, 16)),
        ("mug", mug(0.15, 0.6, 1.8)),
        ("thick ring", thick_ring(0.22, 0.4)),
        ("joined arms", arms.clone()),
        ("short mug", mug(0.15, 0.4, 1.4)),
        ("short joined arms", mug(0.08, 0.4, 1.4)),
    ] {
        let (out, rep) = cut_handles(&m, &default).unwrap();
        assert_eq!(rep.cuts, 0, "{name}: {rep:?}");
        assert_eq!(out, m, "{name}");
        let l = &rep.loops[0];
        assert!(
            l.neck_aspect.unwrap() > default.max_neck_aspect,
            "{name}: {l:?}"
        );
        assert!(
            l.side_aspect.unwrap() > default.max_side_aspect,
            "{name}: {l:?}"
        );
    }
    let length_only = HandleCutOptions {
        free_loop_rel: 0.2,
        ..default
    };
    let (_, rep) = cut_handles(&arms, &length_only).unwrap();
    assert_eq!((rep.cuts, rep.after.genus), (1, Some(0)), "{rep:?}");
    assert!(rep.loops[0].length_rel < 0.2, "{:?}", rep.loops[0]);
    let longer = HandleCutOptions {
        max_loop_rel: 0.65,
        ..default
    };
    let (_, rep) = cut_handles(&mug(0.08, 0.4, 1.4), &longer).unwrap();
    assert_eq!(rep.cuts, 1, "{rep:?}");
    let through_body = &rep.loops[1];
    assert!(
        through_body.cut
            && through_body.length_rel > default.max_loop_rel
            && through_body.neck_aspect.unwrap() <= default.max_neck_aspect,
        "{through_body:?}"
    );
}

/// A limb welded to the body (a hand to a thigh): seen from the weld's neck, the body side
/// flares at once and the limb side is a tube, so its neck aspect `(s₊ + s₋)/L` is that of a
/// genuine handle (> 3) but its side aspect `min(s₊, s₋)/L` is not. The default's side test cuts
/// it, at the neck; the two-sided test alone leaves it (the test fails without the side test).
#[test]
fn a_limb_welded_to_the_body_is_cut_by_the_side_test() {
    let m = limb_welded_to_body(0.1, 0.06, 0.6, 1.8);
    assert_eq!(genus(&m), 1);
    let default = shapeseek::presets::DEFAULT_HANDLE_CUT;
    let (out, rep) = cut_handles(&m, &default).unwrap();
    assert_eq!((rep.cuts, rep.after.genus), (1, Some(0)), "{rep:?}");
    assert_eq!(genus(&out), 0);
    let l = &rep.loops[0];
    assert!(l.cut, "{l:?}");
    assert!(l.neck_aspect.unwrap() > default.max_neck_aspect, "{l:?}");
    assert!(l.side_aspect.unwrap() <= default.max_side_aspect, "{l:?}");
    // The neck's circumference (16-gon of radius 0.06: 0.3766), not the limb's (0.1: 0.628).
    assert!((l.length - 0.3766).abs() < 0.05, "{l:?}");
    assert!(rep.area_kept > 0.97 && rep.area_kept < 1.0, "{rep:?}");
    let two_sided = HandleCutOptions {
        max_side_aspect: 0.0,
        ..default
    };
    let (same, rep) = cut_handles(&m, &two_sided).unwrap();
    assert_eq!(rep.cuts, 0, "{rep:?}");
    assert_eq!(same, m);
    // Through preparation with the default's cutting: one cut, genus 1 -> 0.
    let prepared = shapeseek::mesh::prepare::prepare(
        &m,
        &shapeseek::mesh::prepare::PrepareOptions {
            cut_handles: Some(default),
            ..Default::default()
        },
    )
    .unwrap();
    let hc = prepared.1.handle_cut.expect("summary");
    assert_eq!(
        (hc.cuts, hc.genus_before, hc.genus_after),
        (1, Some(1), Some(0))
    );
}

/// Side aspects of the genuine handles: every one runs for more than its circumference on both
/// sides (`min(s₊, s₋)/L` ≥ 1.1), the welds of the tests do not (≤ 0.7).
#[test]
fn side_aspects_of_genuine_handles_and_welds() {
    let measure = HandleCutOptions {
        max_loop_rel: 1e9,
        max_neck_aspect: 0.0,
        max_side_aspect: 0.0,
        max_cuts: 1,
        ..Default::default()
    };
    let side = |m: &Mesh| {
        let (_, rep) = cut_handles(m, &measure).unwrap();
        rep.loops[0].side_aspect.expect("measured")
    };
    for (name, m, lo, hi) in [
        ("torus", torus(3.0, 0.5, 90, 16), 2.5, 3.1),
        ("mug", mug(0.15, 0.6, 1.8), 1.1, 1.2),
        ("thick ring", thick_ring(0.22, 0.4), 2.4, 2.9),
        ("joined arms", mug(0.08, 0.6, 1.8), 1.4, 1.6),
        ("short mug", mug(0.15, 0.4, 1.4), 1.7, 2.1),
        ("short joined arms", mug(0.08, 0.4, 1.4), 2.1, 2.6),
        ("welded C", welded_c(0.25, 0.06, 0.12, 360, 24), 0.5, 0.7),
        (
            "limb welded to body",
            limb_welded_to_body(0.1, 0.06, 0.6, 1.8),
            0.0,
            0.3,
        ),
    ] {
        let s = side(&m);
        assert!(
            s >= lo && s <= hi,
            "{name}: side aspect {s} not in [{lo}, {hi}]"
        );
    }
}

/// `max_side_aspect` is omitted from the JSON at 0 (its "off" value), so a spec that does not use
/// the side test keeps its key; the default's (0.9) is written and read back; a negative or NaN
/// threshold is refused.
#[test]
fn side_threshold_serialises_only_when_set() {
    let off = serde_json::to_string(&HandleCutOptions::default()).unwrap();
    assert!(!off.contains("max_side_aspect"), "{off}");
    let default = shapeseek::presets::DEFAULT_HANDLE_CUT;
    let json = serde_json::to_string(&default).unwrap();
    assert!(json.contains("\"max_side_aspect\":0.9"), "{json}");
    let back: HandleCutOptions = serde_json::from_str(&json).unwrap();
    assert_eq!(back, default);
    let old: HandleCutOptions =
        serde_json::from_str(r#"{"max_loop_rel": 0.5, "max_neck_aspect": 3}"#).unwrap();
    assert_eq!(old.max_side_aspect, 0.0);
    for bad in [-0.1, f64::NAN] {
        let o = HandleCutOptions {
            max_side_aspect: bad,
            ..default
        };
        assert!(o.validate().is_err(), "{bad}");
        assert!(cut_handles(&torus(2.0, 0.5, 20, 8), &o).is_err(), "{bad}");
    }
}

/// `stub_aspect`: cutting the welded C's neck with it removes the two halves of the weld tube
/// (every kept vertex lies outside the gap the tube spans) and no more than a thin ring of the
/// caps beyond; without it the tube halves stay. The limb welded to the body loses its short
/// stub on the body's side, never the limb (which does not open within `L`). Off (0) by default
/// and omitted from the JSON then; negative or NaN refused.
#[test]
fn stubs_of_a_cut_weld_are_removed_up_to_where_the_surface_opens() {
    let m = welded_c(0.25, 0.06, 0.12, 360, 24);
    let angle = |p: &[f64; 3]| p[1].atan2(p[0]).abs();
    let keep = shapeseek::presets::DEFAULT_HANDLE_CUT;
    let stubs = HandleCutOptions {
        stub_aspect: 1.0,
        ..keep.clone()
    };
    let (kept, rk) = cut_handles(&m, &keep).unwrap();
    let (out, rs) = cut_handles(&m, &stubs).unwrap();
    assert_eq!((rk.cuts, rs.cuts), (1, 1));
    assert_eq!((genus(&kept), genus(&out)), (0, 0));
    // Kept: the tube's rings inside the gap (half-width 0.06 rad) stay on both sides.
    assert!(kept.vertices.iter().any(|p| angle(p) < 0.04), "tube kept");
    // Removed: the tube up to its last ring (at 3°, 0.052 rad; the gap's edge, 0.06 rad, falls
    // between it and the caps' first ring), and at most a thin ring of the caps beyond.
    let nearest = out.vertices.iter().map(angle).fold(f64::INFINITY, f64::min);
    assert!(
        nearest > 0.05 && nearest < 0.16,
        "nearest kept angle {nearest}"
    );
    assert!(
        rs.area_kept < rk.area_kept && rs.area_kept > 0.97,
        "{rs:?} {rk:?}"
    );
    // The limb: only the stub on the body's side goes; the limb stays.
    let limb = limb_welded_to_body(0.1, 0.06, 0.6, 1.8);
    let (_, rl) = cut_handles(&limb, &stubs).unwrap();
    assert_eq!(rl.cuts, 1);
    assert!(rl.area_kept > 0.97, "{rl:?}");
    // Serialisation and validation.
    let json = serde_json::to_string(&keep).unwrap();
    assert!(!json.contains("stub_aspect"), "{json}");
    let json = serde_json::to_string(&stubs).unwrap();
    assert!(json.contains("\"stub_aspect\":1.0"), "{json}");
    assert_eq!(
        serde_json::from_str::<HandleCutOptions>(&json).unwrap(),
        stubs
    );
    for bad in [-0.1, f64::NAN] {
        let o = HandleCutOptions {
            stub_aspect: bad,
            ..keep.clone()
        };
        assert!(o.validate().is_err(), "{bad}");
    }
}

/// The default's second cut ([`shapeseek::presets::DEFAULT_ALTERNATE_CUT`]) takes the genuine
/// handles its first cut keeps, so every such shape is signed twice
/// ([`shapeseek::signature::sign`]): the first version uncut (the mesh of the first rule's
/// preparation), the second cut, smaller, with the same channels and spec key; a genus-0 shape
/// and a cut weld have one version. Both survive the binary encoding.
#[test]
fn genuine_handles_get_a_second_version_cut_by_the_alternate_rule() {
    use shapeseek::mesh::prepare::{prepare, PrepareOptions};
    use shapeseek::presets::{DEFAULT_ALTERNATE_CUT, DEFAULT_HANDLE_CUT};
    use shapeseek::signature::{sign, ChannelSpec, Norm, PairQuadrature, Signature, SignatureSpec};
    use shapeseek::spectrum::AnalyzeOptions;
    let mut spec = SignatureSpec::with_channels(vec![ChannelSpec::heat(0.04, Norm::L2)]);
    spec.quadrature = PairQuadrature::Farthest {
        samples: 150,
        cell_means: false,
        near_field: true,
    };
    spec.sketch_quantiles = 64;
    spec.cut_handles = Some(DEFAULT_HANDLE_CUT);
    spec.alternate_cut = Some(DEFAULT_ALTERNATE_CUT);
    let mut base = AnalyzeOptions::default();
    base.eigen.k = 20;
    for (name, m, second) in [
        ("mug", mug(0.15, 0.6, 1.8), true),
        ("joined arms", mug(0.08, 0.6, 1.8), true),
        ("thick ring", thick_ring(0.22, 0.4), true),
        ("sphere", sphere(3), false),
        ("welded C", welded_c(0.25, 0.06, 0.12, 360, 24), false),
    ] {
        let (first, sig) = sign(&m, &spec, &base).unwrap();
        let cut_first = prepare(
            &m,
            &PrepareOptions {
                cut_handles: Some(DEFAULT_HANDLE_CUT),
                ..PrepareOptions::default()
            },
        )
        .unwrap();
        assert_eq!(first.mesh, cut_first.0, "{name}: first version");
        assert_eq!(sig.spec_key, spec.key());
        assert_eq!(sig.alternate.is_some(), second, "{name}");
        if let Some(alt) = &sig.alternate {
            assert_eq!(alt.spec_key, sig.spec_key, "{name}");
            assert_eq!(alt.alternate, None, "{name}");
            assert_eq!(
                alt.channels.iter().map(|c| &c.name).collect::<Vec<_>>(),
                sig.channels.iter().map(|c| &c.name).collect::<Vec<_>>()
            );
            assert!(alt.channels != sig.channels, "{name}: same distributions");
            assert!(alt.vertices < sig.vertices, "{name}: the band is removed");
        }
        assert_eq!(
            Signature::from_bytes(&sig.to_bytes()).unwrap(),
            sig,
            "{name}"
        );
    }
}
