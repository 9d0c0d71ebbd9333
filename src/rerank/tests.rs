use super::*;
use crate::mesh::{generate, Mesh};
use crate::spectrum::{analyze, AnalyzeOptions};
use faer::Mat;

/// Deterministic pseudo-random numbers in [0, 1) (SplitMix64).
fn rng(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed;
    move || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Euclidean distance matrix of `m` random points in the box `[0,1]×[0,1]×[0,h]` and random
/// weights summing to 1.
fn random_space(m: usize, h: f64, seed: u64) -> (Mat<f64>, Vec<f64>) {
    let mut r = rng(seed);
    let pts: Vec<[f64; 3]> = (0..m).map(|_| [r(), r(), h * r()]).collect();
    let c = Mat::from_fn(m, m, |i, j| {
        let d: f64 = (0..3).map(|k| (pts[i][k] - pts[j][k]).powi(2)).sum();
        d.sqrt()
    });
    let mut w: Vec<f64> = (0..m).map(|_| 0.5 + r()).collect();
    let s: f64 = w.iter().sum();
    w.iter_mut().for_each(|x| *x /= s);
    (c, w)
}

/// Sharp regularisation for the metric-space tests (ε = 0.003 × mean product cost).
fn sharp() -> GwOptions {
    GwOptions {
        eps_rel: 0.003,
        ..GwOptions::default()
    }
}

fn gw(c1: &Mat<f64>, p: &[f64], c2: &Mat<f64>, q: &[f64]) -> f64 {
    entropic_gw(&[c1.as_ref()], p, &[c2.as_ref()], q, &sharp()).value
}

#[test]
fn gw_of_a_space_with_itself_is_minimal_and_gw_is_symmetric() {
    let (x, p) = random_space(60, 1.0, 1);
    let (y, q) = random_space(50, 1.0, 2);
    let (z, r) = random_space(70, 0.2, 3);
    let xx = gw(&x, &p, &x, &p);
    let xy = gw(&x, &p, &y, &q);
    let yx = gw(&y, &q, &x, &p);
    let xz = gw(&x, &p, &z, &r);
    // Scale of the energy: E under the product measure.
    let mut prod = 0.0;
    for i in 0..60 {
        for k in 0..60 {
            for j in 0..60 {
                for l in 0..60 {
                    prod += (x[(i, k)] - x[(j, l)]).powi(2) * p[i] * p[k] * p[j] * p[l];
                }
            }
        }
    }
    assert!(
        xx < 0.02 * prod,
        "GW(X,X) = {xx}, product-measure energy {prod}"
    );
    assert!(
        xx < xy && xx < xz,
        "GW(X,X) = {xx}, GW(X,Y) = {xy}, GW(X,Z) = {xz}"
    );
    // Two draws from the same distribution are closer than a flat box.
    assert!(xy < xz, "GW(X,Y) = {xy} vs GW(X,Z) = {xz}");
    // The solver in either order: equal to a relative 1e-3.
    assert!(
        (xy - yx).abs() <= 1e-3 * xy,
        "GW(X,Y) = {xy}, GW(Y,X) = {yx}"
    );
    // The transport plan of X with itself concentrates on the diagonal.
    let res = entropic_gw(&[x.as_ref()], &p, &[x.as_ref()], &p, &sharp());
    let diag: f64 = (0..60).map(|i| res.plan[(i, i)]).sum();
    assert!(diag > 0.8, "diagonal mass {diag}");
    // Marginals of the returned plan.
    for i in 0..60 {
        let row: f64 = (0..60).map(|j| res.plan[(i, j)]).sum();
        assert!((row - p[i]).abs() < 1e-4, "row {i}: {row} vs {}", p[i]);
    }
}

#[test]
fn gw_is_invariant_to_a_permutation_of_samples() {
    let (x, p) = random_space(50, 1.0, 11);
    let (y, q) = random_space(40, 0.7, 12);
    let mut r = rng(99);
    let mut perm: Vec<usize> = (0..40).collect();
    for i in (1..40).rev() {
        let j = (r() * (i + 1) as f64) as usize;
        perm.swap(i, j);
    }
    let yp = Mat::from_fn(40, 40, |i, j| y[(perm[i], perm[j])]);
    let qp: Vec<f64> = perm.iter().map(|&i| q[i]).collect();
    let a = gw(&x, &p, &y, &q);
    let b = gw(&x, &p, &yp, &qp);
    assert!((a - b).abs() <= 1e-9 * a, "{a} vs {b}");
    assert!(perm.iter().enumerate().any(|(i, &j)| i != j));
}

fn payload_of(mesh: &Mesh, spec: &PayloadSpec) -> GwPayload {
    let mut opts = AnalyzeOptions::default();
    opts.eigen.k = 40;
    let a = analyze(mesh, &opts).expect("analysis");
    compute_payload(&a, spec).expect("payload")
}

/// The rectangle rolled onto a cylinder of radius `radius` along x (an isometric bending).
fn rolled(mut m: Mesh, radius: f64) -> Mesh {
    for v in &mut m.vertices {
        let a = v[0] / radius;
        *v = [radius * a.sin(), v[1], radius * (1.0 - a.cos())];
    }
    m
}

fn small_spec() -> PayloadSpec {
    PayloadSpec {
        samples: 80,
        times: vec![0.04],
        ..PayloadSpec::default()
    }
}

#[test]
fn gw_separates_different_generated_shapes_from_poses_and_remeshes() {
    let spec = small_spec();
    let o = GwOptions::default();
    // Remeshes of one surface vs another surface.
    let t1 = payload_of(&generate::bumpy_torus(48, 20), &spec);
    let t2 = payload_of(&generate::bumpy_torus(64, 26), &spec);
    let s = payload_of(&generate::bumpy_sphere(3, 0.3), &spec);
    let same = gw_score(&t1, &t2, &o);
    let diff = gw_score(&t1, &s, &o);
    assert!(same < 0.5 * diff, "remesh {same} vs different {diff}");
    // An isometric bending of a rectangle vs a rectangle of another aspect ratio.
    let flat = payload_of(&generate::rectangle(2.0, 1.0, 40, 20), &spec);
    let bent = payload_of(&rolled(generate::rectangle(2.0, 1.0, 40, 20), 0.8), &spec);
    let long = payload_of(&generate::rectangle(4.0, 0.5, 60, 8), &spec);
    let pose = gw_score(&flat, &bent, &o);
    let other = gw_score(&flat, &long, &o);
    assert!(pose < 0.5 * other, "pose {pose} vs different {other}");
    // Symmetric bit for bit.
    assert_eq!(gw_score(&t1, &s, &o), gw_score(&s, &t1, &o));
}

#[test]
fn payload_round_trip_and_malformed_input() {
    let spec = PayloadSpec {
        samples: 30,
        times: vec![0.02, 0.1],
        metric: GwMetric::HeatKernel,
        time_rule: TimeRule::Lambda1,
    };
    let p = payload_of(&generate::bumpy_sphere(2, 0.3), &spec);
    assert_eq!(p.samples, 30);
    assert_eq!(p.upper.len(), 2);
    assert!((p.weights.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    assert!((p.times[0] * p.lambda1 - 0.02).abs() < 1e-12);
    let b = p.to_bytes();
    assert_eq!(GwPayload::from_bytes(&b).unwrap(), p);
    let json = serde_json::to_string(&p).unwrap();
    let back: GwPayload = serde_json::from_str(&json).unwrap();
    assert_eq!(back.upper, p.upper);
    assert_eq!(back.spec_key, p.spec_key);
    assert!(GwPayload::from_bytes(&b[..b.len() - 1]).is_err());
    let mut bad = b.clone();
    bad[0] = b'X';
    assert!(GwPayload::from_bytes(&bad).is_err());
    // The dense matrix is symmetric with the stored diagonal.
    let m = p.matrix(1);
    assert_eq!(m[(3, 7)], m[(7, 3)]);
    assert_eq!(m[(5, 5)], p.diagonal[1][5] as f64);
    // Stage (de)serialisation in the configuration form; invalid values are refused.
    use crate::search::Stage;
    let st = Stage::SpectralGw(SgwStage::default());
    let j = serde_json::to_string(&st).unwrap();
    assert_eq!(serde_json::from_str::<Stage>(&j).unwrap(), st);
    let d = Stage::Reciprocal(ReciprocalStage::default());
    assert_eq!(d.label(), "recip:200");
    let j = serde_json::to_string(&d).unwrap();
    assert_eq!(serde_json::from_str::<Stage>(&j).unwrap(), d);
    for bad in [
        r#"{"kind":"reciprocal","shortlist":100,"neighbourhoods":[],"expansion":4,"original_weight":0.1}"#,
        r#"{"kind":"reciprocal","shortlist":0,"neighbourhoods":[8],"expansion":4,"original_weight":0.1}"#,
        r#"{"kind":"reciprocal","shortlist":10,"neighbourhoods":[8],"expansion":4,"original_weight":2.0}"#,
        r#"{"kind":"none"}"#,
    ] {
        assert!(serde_json::from_str::<Stage>(bad).is_err(), "{bad}");
    }
}

#[test]
fn rerank_reorders_a_shortlist_deterministically() {
    let spec = small_spec();
    let q = payload_of(&generate::bumpy_torus(48, 20), &spec);
    let near = payload_of(&generate::bumpy_torus(60, 24), &spec);
    let far1 = payload_of(&generate::bumpy_sphere(3, 0.3), &spec);
    let far2 = payload_of(&generate::rectangle(2.0, 1.0, 30, 15), &spec);
    // First stage put the true match last.
    let cands = vec![
        Candidate {
            id: "sphere",
            score: 0.1,
            payload: Some(&far1),
        },
        Candidate {
            id: "plate",
            score: 0.2,
            payload: Some(&far2),
        },
        Candidate {
            id: "none",
            score: 0.25,
            payload: None,
        },
        Candidate {
            id: "torus",
            score: 0.3,
            payload: Some(&near),
        },
    ];
    let stage = SgwStage {
        shortlist: 4,
        payload: spec,
        ..SgwStage::default()
    };
    let a = rerank_gw(&stage, &q, &cands);
    let b = rerank_gw(&stage, &q, &cands);
    assert_eq!(a, b);
    assert_eq!(a[0].0, "torus");
    assert_eq!(a.last().unwrap().0, "none");
    assert!(a.windows(2).all(|w| w[0].1 <= w[1].1));
    // Rank blend with weight 1 is the first-stage order.
    let blend = SgwStage {
        shortlist: 4,
        payload: small_spec(),
        fusion: Fusion::RankBlend { weight: 1.0 },
        ..SgwStage::default()
    };
    let c = rerank_gw(&blend, &q, &cands);
    assert_eq!(
        c.iter().map(|x| x.0).collect::<Vec<_>>(),
        ["sphere", "plate", "torus", "none"]
    );
}

/// Cost per candidate at 200 and 300 samples (`--ignored --nocapture`).
#[test]
#[ignore]
fn gw_cost_per_candidate() {
    for m in [100usize, 200, 300] {
        let (x, p) = random_space(m, 1.0, 5);
        let (y, q) = random_space(m, 0.8, 6);
        let mut times = Vec::new();
        let mut last = None;
        for _ in 0..5 {
            let t = std::time::Instant::now();
            let r = entropic_gw(&[x.as_ref()], &p, &[y.as_ref()], &q, &GwOptions::default());
            times.push(t.elapsed().as_secs_f64() * 1e3);
            last = Some(r);
        }
        times.sort_by(f64::total_cmp);
        let r = last.unwrap();
        println!(
            "m = {m}: median {:.1} ms (min {:.1}), outer {}, sinkhorn {}",
            times[2], times[0], r.outer_iterations, r.sinkhorn_iterations
        );
    }
}

#[test]
#[ignore]
fn gw_diagnostics() {
    let (x, p) = random_space(60, 1.0, 1);
    let (y, q) = random_space(50, 1.0, 2);
    for eps in [0.03, 0.01, 0.003, 0.001] {
        for outer in [5usize, 10, 30] {
            let o = GwOptions {
                eps_rel: eps,
                outer_iterations: outer,
                ..GwOptions::default()
            };
            let r = entropic_gw(&[x.as_ref()], &p, &[x.as_ref()], &p, &o);
            let s = entropic_gw(&[x.as_ref()], &p, &[y.as_ref()], &q, &o);
            let diag: f64 = (0..60).map(|i| r.plan[(i, i)]).sum();
            println!(
                "eps {eps} outer {outer}: xx {:.5} diag {diag:.3} xy {:.5} its {} {}",
                r.value, s.value, r.outer_iterations, r.sinkhorn_iterations
            );
        }
    }
}

/// Latency of one search of a 10 000-shape index: first-stage scan (`search::rank_all`, default
/// configuration) + SGW re-ranking of the top 50 (`--ignored --nocapture`).
#[test]
#[ignore]
fn search_latency_10k_with_rerank() {
    use crate::presets::default_config;
    use crate::ranking::calibrate;
    use crate::search::{rank_all, Corpus, Encoded, Layout, Query};
    use crate::signature::compute_signature;
    let cfg = default_config();
    let mut opts = AnalyzeOptions::default();
    opts.eigen.k = 100;
    let meshes = [
        generate::bumpy_torus(60, 30),
        generate::bumpy_torus(70, 28),
        generate::bumpy_sphere(4, 0.3),
        generate::bumpy_sphere(4, 0.2),
    ];
    let spec = PayloadSpec::default();
    let mut sigs = Vec::new();
    let mut pays = Vec::new();
    for m in &meshes {
        let a = analyze(m, &opts).unwrap();
        sigs.push(compute_signature(&a, &cfg.signature).unwrap());
        pays.push(compute_payload(&a, &spec).unwrap());
    }
    let cal = calibrate(&sigs.iter().collect::<Vec<_>>(), &cfg.signature, 1);
    let layout = Layout::of(&cal);
    let rows: Vec<Encoded> = (0..10_000)
        .map(|i| Encoded::from_signature(&sigs[i % 4], &cal, &layout))
        .collect();
    let corpus = Corpus::build(layout, &rows);
    let query = Query::new(&cfg.query, corpus.layout());
    let stage = if std::env::var("SGW_K20").is_ok() {
        SgwStage::default()
    } else {
        SgwStage {
            shortlist: 50,
            ..SgwStage::default()
        }
    };
    let mut scan = Vec::new();
    let mut rr = Vec::new();
    for q in 0..5 {
        let t = std::time::Instant::now();
        let hits = rank_all(&corpus, &query, corpus.shape(q));
        scan.push(t.elapsed().as_secs_f64() * 1e3);
        let cands: Vec<Candidate<'_, usize>> = hits
            .iter()
            .take(stage.shortlist)
            .map(|&(i, s)| Candidate {
                id: i,
                score: s,
                payload: Some(&pays[i % 4]),
            })
            .collect();
        let t = std::time::Instant::now();
        let out = rerank_gw(&stage, &pays[q % 4], &cands);
        rr.push(t.elapsed().as_secs_f64() * 1e3);
        assert_eq!(out.len(), stage.shortlist);
    }
    scan.sort_by(f64::total_cmp);
    rr.sort_by(f64::total_cmp);
    println!(
        "10k scan: median {:.1} ms (min {:.1}); rerank top {} (m = {}, t = {:?}): median {:.0} ms (min {:.0}); threads {}",
        scan[2], scan[0], stage.shortlist, spec.samples, spec.times, rr[2], rr[0], rayon::current_num_threads()
    );
}

/// From the product measure a symmetric shape's own copy can score above other shapes; with
/// anchored starts every shape's copy scores lowest, at the entropic floor.
#[test]
fn a_symmetric_shapes_own_copy_scores_lowest_with_anchored_starts() {
    let spec = PayloadSpec::default();
    let shapes = [
        generate::torus(1.0, 0.35, 60, 24),
        generate::torus(1.0, 0.35, 48, 20),
        generate::torus(1.0, 0.45, 48, 20),
        generate::bumpy_torus(48, 20),
        generate::icosphere(3),
        generate::bumpy_sphere(3, 0.1),
        generate::rectangle(2.0, 1.0, 40, 20),
    ];
    let ps: Vec<_> = shapes.iter().map(|m| payload_of(m, &spec)).collect();
    let product = GwOptions::default();
    let anchored = GwOptions {
        anchored_starts: true,
        ..GwOptions::default()
    };
    // The failure the anchored starts mend: from the product start, the finer torus's own copy
    // scores above the bumpy torus.
    let (own, other) = (
        gw_score(&ps[0], &ps[0], &product),
        gw_score(&ps[0], &ps[3], &product),
    );
    println!("product start: the torus with itself {own:.4}, with the bumpy torus {other:.4}");
    assert!(own > other, "{own} vs {other}");
    for (i, a) in ps.iter().enumerate() {
        let own = gw_score(a, a, &anchored);
        let nearest = ps
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .map(|(_, b)| gw_score(a, b, &anchored))
            .fold(f64::INFINITY, f64::min);
        assert!(own < 0.1, "shape {i}: own copy {own}");
        assert!(
            own < nearest,
            "shape {i}: own copy {own}, nearest other {nearest}"
        );
    }
}
