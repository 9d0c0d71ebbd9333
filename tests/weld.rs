//! Welding (`shapeseek::mesh::weld`) on shapes built in code: bridges between the legs of the
//! sample biped and quadruped raise the genus by exactly the number made and leave a closed,
//! connected, consistently oriented manifold without degenerate faces; the result is
//! deterministic, survives an OBJ round trip through `prepare`, and handle cutting removes the
//! bridges again; a sphere has no contact; bad options and non-manifold input are refused.

use shapeseek::mesh::generate::icosphere;
use shapeseek::mesh::prepare::{prepare, PrepareOptions};
use shapeseek::mesh::samples::class_mesh;
use shapeseek::mesh::topology::{cut_handles, surface_stats, HandleCutOptions};
use shapeseek::mesh::weld::{weld, WeldError, WeldOptions, WeldReport};
use shapeseek::mesh::{read_mesh, triangle_area, write_mesh, Format, Mesh, ReadLimits};
use std::collections::HashSet;

fn opts(bridges: usize, disc: f64, seed: u64) -> WeldOptions {
    WeldOptions {
        bridges,
        disc_radius_edges: disc,
        seed,
        ..WeldOptions::default()
    }
}

fn signed_volume(m: &Mesh) -> f64 {
    m.faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| m.vertices[i as usize]);
            (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                + a[2] * (b[0] * c[1] - b[1] * c[0]))
                / 6.0
        })
        .sum()
}

/// Everything a welded mesh must satisfy, given its input and report.
fn check_welded(input: &Mesh, out: &Mesh, rep: &WeldReport, what: &str) {
    let before = surface_stats(input).unwrap();
    let after = surface_stats(out).unwrap_or_else(|e| panic!("{what}: not a manifold: {e}"));
    assert_eq!(rep.made, rep.bridges.len(), "{what}");
    assert!(rep.made <= rep.requested, "{what}");
    assert_eq!(
        after.genus,
        Some(before.genus.unwrap() + rep.made),
        "{what}: {before:?} -> {after:?}"
    );
    assert_eq!(after.components, 1, "{what}");
    assert_eq!(after.boundary_loops, 0, "{what}: not closed");
    assert_eq!(rep.after, after, "{what}");
    assert_eq!(rep.before, before, "{what}");
    // No degenerate face, every vertex used.
    let mean = out.area() / out.faces.len() as f64;
    for (i, f) in out.faces.iter().enumerate() {
        assert!(
            triangle_area(out, f) > 1e-6 * mean,
            "{what}: face {i} degenerate"
        );
    }
    assert_eq!(after.vertices, out.vertices.len(), "{what}: unused vertex");
    // Consistent orientation: each directed half-edge at most once (with closedness and the
    // manifold check, every edge is traversed once each way).
    let mut half = HashSet::new();
    for f in &out.faces {
        for k in 0..3 {
            assert!(
                half.insert((f[k], f[(k + 1) % 3])),
                "{what}: half-edge {:?} twice (orientation)",
                (f[k], f[(k + 1) % 3])
            );
        }
    }
    // Orientation also geometrically plausible: the enclosed volume keeps its sign and size
    // (an inside-out tube or a wild pull would change it a lot).
    let (v0, v1) = (signed_volume(input), signed_volume(out));
    assert!(
        v0 * v1 > 0.0 && (v1 / v0 - 1.0).abs() < 0.25,
        "{what}: volume {v0} -> {v1}"
    );
    // The contacts satisfy the tests of the options (defaults 3 and 0.2) and the pull closed the
    // gap by 60 % (exactly, when the pulls of different bridges do not overlap).
    for b in &rep.bridges {
        assert!(b.geodesic > 3.0 * b.gap, "{what}: {b:?}");
        assert!(b.geodesic_rel > 0.2, "{what}: {b:?}");
        assert!(
            b.pulled_gap > 0.0 && b.pulled_gap < 0.75 * b.gap,
            "{what}: {b:?}"
        );
        assert!(b.loop_a >= 3 && b.loop_b >= 3, "{what}: {b:?}");
    }
}

#[test]
fn biped_bridges_raise_genus_by_bridges_made() {
    let m = class_mesh("biped", 0, false);
    assert_eq!(surface_stats(&m).unwrap().genus, Some(0));
    for (bridges, disc) in [(1, 1.5), (2, 2.0), (3, 2.5), (4, 3.0)] {
        let (out, rep) = weld(&m, &opts(bridges, disc, 7)).unwrap();
        eprintln!(
            "biped bridges={bridges}: made {} of {} candidates, {:?}",
            rep.made, rep.candidates, rep.bridges
        );
        assert!(rep.made >= 1, "no bridge made on the biped");
        check_welded(&m, &out, &rep, &format!("biped {bridges}"));
    }
}

#[test]
fn quadruped_bridges_raise_genus_by_bridges_made() {
    for pose in [0, 1] {
        let m = class_mesh("quadruped", pose, false);
        for bridges in [1, 3, 6] {
            let (out, rep) = weld(&m, &opts(bridges, 2.0, 1)).unwrap();
            eprintln!(
                "quadruped pose {pose} bridges={bridges}: made {} of {} candidates",
                rep.made, rep.candidates
            );
            assert!(rep.made >= 1, "no bridge made on the quadruped");
            check_welded(&m, &out, &rep, &format!("quadruped {pose} {bridges}"));
        }
    }
}

#[test]
fn same_seed_same_mesh_other_seeds_may_differ() {
    let m = class_mesh("biped", 0, false);
    let o = opts(2, 2.0, 42);
    let (a, ra) = weld(&m, &o).unwrap();
    let (b, rb) = weld(&m, &o).unwrap();
    assert!(ra.made >= 1);
    assert_eq!(a, b);
    assert_eq!(ra, rb);
    // The seed is used: some other seed chooses other contacts.
    let differs = (0..16u64).any(|s| weld(&m, &opts(2, 2.0, s)).unwrap().0 != a);
    assert!(differs, "16 seeds gave the same welded mesh");
}

#[test]
fn sphere_has_no_contact_and_is_returned_unchanged() {
    let m = icosphere(3);
    for bridges in [0, 1, 5] {
        let (out, rep) = weld(&m, &opts(bridges, 2.0, 3)).unwrap();
        assert_eq!(rep.made, 0);
        assert_eq!(rep.candidates, 0);
        assert!(rep.bridges.is_empty());
        assert_eq!(out, m);
        assert_eq!(rep.before, rep.after);
    }
}

#[test]
fn invalid_options_and_inputs_are_refused() {
    let m = class_mesh("biped", 0, false);
    let bad = [
        WeldOptions {
            bridges: 65,
            ..WeldOptions::default()
        },
        WeldOptions {
            disc_radius_edges: 0.0,
            ..WeldOptions::default()
        },
        WeldOptions {
            disc_radius_edges: f64::NAN,
            ..WeldOptions::default()
        },
        WeldOptions {
            pull: 1.0,
            ..WeldOptions::default()
        },
        WeldOptions {
            pull: -0.1,
            ..WeldOptions::default()
        },
        WeldOptions {
            min_gap_ratio: f64::INFINITY,
            ..WeldOptions::default()
        },
        WeldOptions {
            min_geodesic_rel: -1.0,
            ..WeldOptions::default()
        },
        WeldOptions {
            max_gap_edges: 0.0,
            ..WeldOptions::default()
        },
        WeldOptions {
            separation_edges: -1.0,
            ..WeldOptions::default()
        },
    ];
    for o in &bad {
        match weld(&m, o) {
            Err(WeldError::InvalidOption(_)) => {}
            other => panic!("{o:?} accepted: {:?}", other.map(|r| r.1)),
        }
        let e: shapeseek::Error = weld(&m, o).unwrap_err().into();
        assert!(e.to_string().contains("invalid"), "{e}");
    }
    // Non-manifold: a fin on an edge of a tetrahedron.
    let mut t = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 1.0, 1.0],
        ],
        vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2], [0, 1, 4]],
    );
    assert!(matches!(
        weld(&t, &WeldOptions::default()),
        Err(WeldError::Topology(_))
    ));
    t.faces.pop();
    assert_eq!(weld(&t, &WeldOptions::default()).unwrap().1.made, 0);
    // Options deserialize with defaults for missing fields.
    let o: WeldOptions = serde_json::from_str(r#"{"bridges": 3, "seed": 9}"#).unwrap();
    assert_eq!(
        o,
        WeldOptions {
            bridges: 3,
            seed: 9,
            ..WeldOptions::default()
        }
    );
    assert_eq!(o.pull, 0.6);
    assert_eq!(o.min_gap_ratio, 3.0);
    assert_eq!(o.min_geodesic_rel, 0.2);
}

#[test]
fn welded_biped_survives_obj_round_trip_through_prepare() {
    let m = class_mesh("biped", 2, false);
    let (out, rep) = weld(&m, &opts(3, 2.5, 5)).unwrap();
    assert!(rep.made >= 1);
    let mut bytes = Vec::new();
    write_mesh(&out, Format::Obj, &mut bytes).unwrap();
    let back = read_mesh(&bytes, Some(Format::Obj), &ReadLimits::default()).unwrap();
    let (prepared, pr) = prepare(&back, &PrepareOptions::default()).unwrap();
    assert_eq!(pr.welded_vertices, 0);
    assert_eq!(pr.degenerate_faces, 0);
    assert_eq!(pr.duplicate_faces, 0);
    assert_eq!(prepared.faces.len(), out.faces.len());
    assert_eq!(surface_stats(&prepared).unwrap().genus, Some(rep.made));
}

#[test]
fn cutting_every_short_loop_removes_the_bridges() {
    let m = class_mesh("biped", 0, false);
    let (out, rep) = weld(&m, &opts(3, 2.0, 11)).unwrap();
    assert!(rep.made >= 1);
    assert_eq!(surface_stats(&out).unwrap().genus, Some(rep.made));
    let cut_opts: HandleCutOptions =
        serde_json::from_str(r#"{"max_loop_rel": 1e9, "max_neck_aspect": 1e9}"#).unwrap();
    let (cut, cr) = cut_handles(&out, &cut_opts).unwrap();
    assert_eq!(cr.cuts, rep.made, "{:?}", cr.loops);
    assert_eq!(surface_stats(&cut).unwrap().genus, Some(0));
}
