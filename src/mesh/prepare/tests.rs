//! Unit tests of `mesh::prepare` (kept apart to hold `prepare/mod.rs` small).
use super::edges::count_boundary_loops;
use super::welding::lex_less;
use super::*;
use crate::mesh::generate;

fn raw() -> PrepareOptions {
    PrepareOptions {
        normalize_area: false,
        ..PrepareOptions::default()
    }
}

#[test]
fn prepare_options_default_from_empty_json() {
    let o: PrepareOptions = serde_json::from_str("{}").unwrap();
    assert_eq!(o, PrepareOptions::default());
    assert_eq!(o.weld_tolerance, None);
    assert_eq!(o.components, ComponentPolicy::Largest);
    assert!(o.normalize_area);
    assert_eq!(o.degenerate_area_ratio, 1e-14);
    let o: PrepareOptions = serde_json::from_str(r#"{"components":"all"}"#).unwrap();
    assert_eq!(o.components, ComponentPolicy::All);
}

#[test]
fn prepare_rejects_bad_options() {
    let m = generate::icosphere(0);
    for bad in [
        PrepareOptions {
            weld_tolerance: Some(-1.0),
            ..raw()
        },
        PrepareOptions {
            weld_tolerance: Some(f64::NAN),
            ..raw()
        },
        PrepareOptions {
            degenerate_area_ratio: f64::INFINITY,
            ..raw()
        },
    ] {
        assert_eq!(prepare(&m, &bad).unwrap_err().code(), "request.invalid");
    }
}

#[test]
fn prepare_weld_exact_treats_negative_zero_as_zero() {
    let v = vec![[0.0, 1.0, 2.0], [-0.0, 1.0, 2.0], [0.0, 1.0, 2.0 + 1e-15]];
    let (c, _) = weld_exact(&v);
    assert_eq!(c, vec![0, 0, 2]);
}

#[test]
fn prepare_weld_tolerance_is_transitive_and_order_free() {
    // A chain 0 - 1 - 2 with steps below the tolerance, 3 far away.
    let v = vec![
        [0.0, 0.0, 0.0],
        [10.0, 0.0, 0.0],
        [0.6, 0.0, 0.0],
        [0.3, 0.0, 0.0],
    ];
    // bbox diagonal 10: eps 0.04 → 0.4 absolute.
    let (c, s) = weld_tolerance(&v, 0.04);
    assert_eq!(c, vec![0, 1, 0, 0]);
    assert_eq!(s[0], 0); // lexicographically smallest member
    let (c, _) = weld_tolerance(&v, 0.02); // 0.2 absolute: nothing merges
    assert_eq!(c, vec![0, 1, 2, 3]);
}

#[test]
fn prepare_weld_tolerance_matches_brute_force() {
    // Jittered points: many pairs near the tolerance, in every direction across cells.
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    for (npts, eps) in [(400, 0.02), (400, 0.05), (300, 0.1), (50, 0.0001)] {
        let v: Vec<[f64; 3]> = (0..npts)
            .map(|_| [rnd(), rnd() * 0.5, rnd() * 2.0])
            .collect();
        let (c, s) = weld_tolerance(&v, eps);
        let d = {
            let (lo, hi) = v.iter().fold(
                ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
                |(lo, hi), p| {
                    (
                        [0, 1, 2].map(|k| lo[k].min(p[k])),
                        [0, 1, 2].map(|k| hi[k].max(p[k])),
                    )
                },
            );
            eps * norm(sub(hi, lo))
        };
        let mut uf = UnionFind::new(npts);
        for i in 0..npts {
            for j in i + 1..npts {
                if norm(sub(v[i], v[j])) <= d {
                    uf.union(i as u32, j as u32);
                }
            }
        }
        let expected: Vec<u32> = (0..npts as u32).map(|i| uf.find(i)).collect();
        assert_eq!(c, expected, "eps {eps}");
        let merged = c
            .iter()
            .enumerate()
            .filter(|&(i, &r)| r as usize != i)
            .count();
        assert!(
            eps < 0.001 || merged > 20,
            "eps {eps}: only {merged} merged"
        );
        for (i, &r) in c.iter().enumerate() {
            assert!(!lex_less(v[i], v[s[r as usize] as usize]));
        }
    }
}

#[test]
fn prepare_loops_of_a_bowtie_boundary() {
    // Two triangles sharing only vertex 0: one boundary per triangle around the pinch.
    let e = [(0, 1), (1, 2), (2, 0), (0, 3), (3, 4), (4, 0)];
    assert_eq!(count_boundary_loops(5, &e), 2);
    // Theta graph (two vertices joined by three paths): one cycle and one open chain.
    let e = [(0, 2), (2, 1), (0, 3), (3, 1), (0, 4), (4, 1)];
    assert_eq!(count_boundary_loops(5, &e), 2);
    assert_eq!(count_boundary_loops(3, &[]), 0);
}

#[test]
fn prepare_edge_statistics_of_a_rectangle() {
    let r = generate::rectangle(1.0, 1.0, 3, 2);
    let t = analyse_edges(r.vertices.len(), &r.faces);
    assert_eq!(t.boundary_edges, 2 * (3 + 2));
    assert_eq!(t.boundary_loops, 1);
    assert_eq!(t.nonmanifold_edges, 0);
    assert_eq!(t.inconsistent, 0);
    // V - E + F = 1 for a disc.
    assert_eq!(12 - t.edges as i64 + 12, 1);
}

#[test]
fn prepare_duplicate_faces_any_orientation() {
    let f = [[0, 1, 2], [2, 1, 0], [1, 2, 0], [0, 1, 3]];
    assert_eq!(duplicate_faces(4, &f), vec![false, true, true, false]);
}
