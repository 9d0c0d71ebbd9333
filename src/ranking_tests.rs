//! Tests of [`crate::ranking`] (`cargo test --release --lib ranking`).

use super::*;
use crate::presets::{config_by_name, default_config, paper_configs};
use crate::signature::{ChannelData, ChannelSpec, Norm, PairQuadrature};

fn h(mass: &[f64], width: f64) -> Histogram {
    histogram_from_mass(mass.to_vec(), width)
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * (1.0 + a.abs().max(b.abs()))
}

/// a = [1, 0, 1, 2], b = [0, 0, 2, 2] (masses), bin width 0.5: densities [2,0,2,4], [0,0,4,4];
/// probabilities [¼,0,¼,½], [0,0,½,½].
#[test]
fn dissimilarities_by_hand() {
    let a = h(&[1.0, 0.0, 1.0, 2.0], 0.5);
    let b = h(&[0.0, 0.0, 2.0, 2.0], 0.5);
    let eps = KL_EPSILON;
    let kl =
        0.25 * ((0.25 + eps).ln() - eps.ln()) + (-0.25) * ((0.25 + eps).ln() - (0.5 + eps).ln());
    let bc: f64 = (0.25f64 * 0.5).sqrt() + 0.5;
    let expected = [
        (Dissimilarity::L1, 2.0),                                     // (2+0+2+0)·½
        (Dissimilarity::L2, 2.0),                                     // √((4+4)·½)
        (Dissimilarity::LInf, 2.0),                                   // max |f − g|
        (Dissimilarity::NL1, 0.5),                                    // ¼ + ¼
        (Dissimilarity::NL2, 0.5),                                    // √((1/16 + 1/16)/½)
        (Dissimilarity::KL, kl), // Σ (p−q)(ln p − ln q), ε added
        (Dissimilarity::Bhattacharyya, -bc.ln()), // −ln Σ √(pq)
        (Dissimilarity::Chi2, 2.0 * (0.0625 / 0.25 + 0.0625 / 0.75)), // empty-empty bin → 0
        (Dissimilarity::Emd, (0.25 + 0.25) * 0.5), // Σ |F̂ − Ĝ| h
    ];
    for (d, e) in expected {
        let v = histogram_dissimilarity(d, &a, &b);
        assert!(close(v, e), "{d:?}: {v} vs {e}");
        // Symmetric, and zero on identical inputs.
        assert!(
            close(histogram_dissimilarity(d, &b, &a), v),
            "{d:?} not symmetric"
        );
        assert_eq!(histogram_dissimilarity(d, &a, &a), 0.0, "{d:?}(a, a)");
    }
}

/// Disjoint supports and empty histograms: every dissimilarity is defined and finite.
#[test]
fn empty_bins_and_empty_histograms_are_finite() {
    let a = h(&[1.0, 0.0, 0.0], 1.0);
    let b = h(&[0.0, 0.0, 1.0], 1.0);
    let z = h(&[0.0, 0.0, 0.0], 1.0);
    for d in Dissimilarity::all() {
        for (x, y) in [(&a, &b), (&a, &z), (&z, &z)] {
            let v = histogram_dissimilarity(d, x, y);
            assert!(v.is_finite() && v >= 0.0, "{d:?}: {v}");
        }
    }
    assert!(close(
        histogram_dissimilarity(Dissimilarity::Bhattacharyya, &a, &b),
        -BHATTACHARYYA_FLOOR.ln()
    ));
    assert!(close(
        histogram_dissimilarity(Dissimilarity::NL1, &a, &b),
        2.0
    ));
    assert!(close(
        histogram_dissimilarity(Dissimilarity::Chi2, &a, &b),
        4.0
    ));
    assert!(close(
        histogram_dissimilarity(Dissimilarity::Emd, &a, &b),
        2.0
    ));
    assert!(close(
        histogram_dissimilarity(Dissimilarity::NL1, &a, &z),
        1.0
    ));
    assert_eq!(histogram_dissimilarity(Dissimilarity::L1, &z, &z), 0.0);
    // Different bin counts cannot be compared.
    assert_eq!(
        histogram_dissimilarity(Dissimilarity::L1, &a, &h(&[1.0], 1.0)),
        f64::INFINITY
    );
}

#[test]
fn vectors_by_hand() {
    let (a, b) = ([0.0, 3.0], [4.0, 0.0]);
    assert!(close(vector_dissimilarity(Dissimilarity::L2, &a, &b), 5.0));
    assert!(close(vector_dissimilarity(Dissimilarity::L1, &a, &b), 7.0));
    assert!(close(
        vector_dissimilarity(Dissimilarity::LInf, &a, &b),
        4.0
    ));
    assert_eq!(
        vector_dissimilarity(Dissimilarity::L2, &a, &[1.0]),
        f64::INFINITY
    );
}

#[test]
fn aggregation_by_hand() {
    let v = [1.0, 2.0, 3.0];
    assert_eq!(Aggregation::Single.apply(v), 1.0);
    assert_eq!(Aggregation::Sum.apply(v), 6.0);
    assert_eq!(Aggregation::Sum2.apply(v), 14.0);
    assert_eq!(Aggregation::Max.apply(v), 3.0);
    assert_eq!(Aggregation::Sum.apply([]), 0.0);

    // Two channels with nL1 0.5 and 2.0 between the shapes.
    let p = Prepared {
        epoch: 1,
        names: vec!["a".into(), "b".into()],
        channels: vec![
            Some(PreparedChannel::Histogram(h(&[1.0, 0.0, 1.0, 2.0], 0.5))),
            Some(PreparedChannel::Histogram(h(&[1.0, 0.0, 0.0, 0.0], 1.0))),
        ],
        alternate: None,
    };
    let q = Prepared {
        epoch: 1,
        names: vec!["a".into(), "b".into()],
        channels: vec![
            Some(PreparedChannel::Histogram(h(&[0.0, 0.0, 2.0, 2.0], 0.5))),
            Some(PreparedChannel::Histogram(h(&[0.0, 0.0, 1.0, 0.0], 1.0))),
        ],
        alternate: None,
    };
    // Scored on the corpus encoding (quantised to within 4·bins/T per channel).
    use crate::search::{Encoded, Layout, Query};
    let layout = Layout::of(&Calibration {
        epoch: 1,
        spec_key: String::new(),
        channel_names: vec!["a".into(), "b".into()],
        window_max: vec![2.0, 4.0],
        bins: 4,
        bandwidth_bins: 1.0,
        percentile: 0.95,
        shapes: 2,
    });
    let (p, q) = (
        Encoded::from_prepared(&p, &layout),
        Encoded::from_prepared(&q, &layout),
    );
    let score = |a: &Encoded, b: &Encoded, spec: &QuerySpec| {
        Query::new(spec, &layout).score(&layout, a.view(), b.view())
    };
    let close = |a: f64, b: f64| (a - b).abs() <= 4.0 * 8.0 / crate::search::corpus::TOTAL as f64;
    let spec = |a: Aggregation| QuerySpec {
        channels: vec!["a".into(), "b".into()],
        dissimilarity: Dissimilarity::NL1,
        aggregation: a,
        alternate_margin: crate::ranking::DEFAULT_ALTERNATE_MARGIN,
    };
    assert!(close(score(&p, &q, &spec(Aggregation::Single)), 0.5));
    assert!(close(score(&p, &q, &spec(Aggregation::Sum)), 2.5));
    assert!(close(score(&p, &q, &spec(Aggregation::Sum2)), 4.25));
    assert!(close(score(&p, &q, &spec(Aggregation::Max)), 2.0));
    assert_eq!(score(&p, &p, &spec(Aggregation::Sum)), 0.0);
    let missing = QuerySpec {
        channels: vec!["c".into()],
        ..spec(Aggregation::Single)
    };
    assert_eq!(score(&p, &q, &missing), f64::INFINITY);
}

#[test]
fn parzen_histogram_by_hand() {
    // Window [0, 4], 4 bins of width 1, centres 0.5 .. 3.5; no smoothing.
    let m = parzen_histogram(
        [(1.5, 1.0), (2.25, 2.0), (0.1, 1.0), (3.9, 1.0), (5.0, 7.0)],
        4.0,
        4,
        0.0,
    );
    // 1.5 → bin 1; 2.25 → ¾ bin 1, ¼ bin 2... (u = 1.75: ¼ to bin 1, ¾ to bin 2)
    let expected = [1.0, 1.0 + 0.5, 1.5, 1.0];
    for (x, e) in m.iter().zip(expected) {
        assert!(close(*x, e), "{m:?}");
    }
    // Smoothing with σ = 1 bin keeps interior mass and is symmetric.
    let s = parzen_histogram([(10.5, 1.0)], 21.0, 21, 1.0);
    assert!(close(s.iter().sum::<f64>(), 1.0));
    for k in 1..=4 {
        assert!(close(s[10 - k], s[10 + k]));
        assert!(close(s[10 + k] / s[10], (-((k * k) as f64) / 2.0).exp()));
    }
    assert_eq!(s[5], 0.0, "truncated at ±4σ");
}

fn uniform_sketch(hi: f64, q: usize, mass: f64) -> QuantileSketch {
    QuantileSketch {
        mass,
        quantiles: (0..=q).map(|j| hi * j as f64 / q as f64).collect(),
    }
}

#[test]
fn sketch_cdf_and_histogram() {
    let s = uniform_sketch(2.0, 8, 3.0);
    assert_eq!(sketch_cdf(&s, -1.0), 0.0);
    assert!(close(sketch_cdf(&s, 0.5), 0.25));
    assert!(close(sketch_cdf(&s, 1.3), 0.65));
    assert_eq!(sketch_cdf(&s, 2.0), 1.0);
    // An atom at 0 of mass ½ (five equal knots), then uniform on [0, 1].
    let atom = QuantileSketch {
        mass: 1.0,
        quantiles: vec![0.0, 0.0, 0.0, 0.25, 0.5, 0.75, 1.0],
    };
    assert!(close(sketch_cdf(&atom, 0.0), 2.0 / 6.0));
    // Histogram of the uniform on [0, 2] over the window [0, 1]: half the mass, flat density.
    let hist = sketch_histogram(&s, 1.0, 10, 0.0);
    let total: f64 = hist.density.iter().map(|f| f * hist.bin_width).sum();
    assert!(close(total, 1.5), "in-window mass {total}");
    for f in &hist.density {
        assert!(close(*f, 1.5), "density {f}");
    }
    assert!(close(hist.prob.iter().sum(), 1.0));
    assert!(close(*hist.cdf.last().expect("cdf"), 1.0));
}

fn sig_with(name: &str, s: QuantileSketch) -> Signature {
    Signature {
        spec_key: String::new(),
        channels: vec![ChannelData {
            name: name.into(),
            values: ChannelValues::Distribution(s),
        }],
        vertices: 0,
        area: 1.0,
        quadrature_points: 0,
        alternate: None,
    }
}

/// The windows are the same bits whatever the order of the signatures (a cluster's shards and
/// nodes pool the same shapes in other orders than a single node does).
#[test]
fn calibration_does_not_depend_on_the_order() {
    let spec = SignatureSpec::with_channels(vec![ChannelSpec::heat(0.1, Norm::L2)]);
    let name = spec.channel_names()[0].clone();
    // Uneven sketches: quantiles x_j = hi · (j/q)^e with hi and e varying per shape.
    let sigs: Vec<Signature> = (0..200)
        .map(|i| {
            let hi = 0.7 + 0.013 * ((i * 37) % 101) as f64;
            let e = 0.6 + 0.011 * ((i * 53) % 89) as f64;
            let s = QuantileSketch {
                mass: 1.0,
                quantiles: (0..=64).map(|j| hi * (j as f64 / 64.0).powf(e)).collect(),
            };
            sig_with(&name, s)
        })
        .collect();
    let forward: Vec<&Signature> = sigs.iter().collect();
    let mut shuffled = forward.clone();
    for p in [0.5, 0.9, 0.95, 0.99] {
        let opts = CalibrationOptions {
            percentile: p,
            ..Default::default()
        };
        let base = calibrate_with(&forward, &spec, 1, &opts).window_max[0];
        for round in 0..20u64 {
            // A deterministic shuffle per round.
            let n = shuffled.len();
            for i in (1..n).rev() {
                let j = ((i as u64 * 2654435761 + round * 97) % (i as u64 + 1)) as usize;
                shuffled.swap(i, j);
            }
            let w = calibrate_with(&shuffled, &spec, 1, &opts).window_max[0];
            assert_eq!(w.to_bits(), base.to_bits(), "percentile {p}, round {round}");
        }
    }
}

/// Pooled 95th percentile of uniform [0, 1] and uniform [0, 2], equally weighted:
/// (1 + x/2)/2 = 0.95 → x = 1.8.
#[test]
fn calibration_by_hand() {
    let spec = SignatureSpec::with_channels(vec![ChannelSpec::heat(0.1, Norm::L2)]);
    let name = spec.channel_names()[0].clone();
    let a = sig_with(&name, uniform_sketch(1.0, 100, 1.0));
    let b = sig_with(&name, uniform_sketch(2.0, 100, 1.0));
    let cal = calibrate(&[&a, &b], &spec, 7);
    assert_eq!(cal.epoch, 7);
    assert_eq!(cal.bins, 256);
    assert!(
        (cal.window_max[0] - 1.8).abs() < 1e-9,
        "{}",
        cal.window_max[0]
    );
    // Nothing to calibrate on: a window of 1.
    assert_eq!(calibrate(&[], &spec, 0).window_max, vec![1.0]);
    // Prepared histograms: uniform [0, 1] on [0, 1.8] has 1/1.8 of its bins filled.
    let p = prepare_for_ranking(&a, &cal);
    match p.channel(&name) {
        Some(PreparedChannel::Histogram(hh)) => {
            assert_eq!(hh.density.len(), 256);
            // In-window mass is 1 less what the Parzen window pushes below 0 from the first
            // four bins (each holding h = 1.8/256 of the mass): h Σ_k k g_k, g normalised.
            let mass: f64 = hh.density.iter().map(|f| f * hh.bin_width).sum();
            let g: Vec<f64> = (0..=4).map(|k| (-((k * k) as f64) / 2.0).exp()).collect();
            let gs = g[0] + 2.0 * g[1..].iter().sum::<f64>();
            let spill = hh.bin_width * (1..=4).map(|k| k as f64 * g[k]).sum::<f64>() / gs;
            assert!(
                (mass - (1.0 - spill)).abs() < 1e-9,
                "mass {mass}, spill {spill}"
            );
        }
        _ => panic!("missing channel"),
    }
}

#[test]
fn presets_are_consistent() {
    let configs = paper_configs();
    let mut names: Vec<&str> = configs.iter().map(|c| c.name.as_str()).collect();
    for required in [
        "Heat-L2-nL1-Single[t=0.1]",
        "Heat-L2-nL1-Sum2[t=0.016..0.1]",
        "Heat-L2-nL1-Max",
        "CT-L2-nL1",
        "Step-L2-nL1[lc=4pi*10]",
        "Step-L2-nL1[lc=4pi*30]",
        "ShapeDNA[50]-L2",
        "CT-L2-L2",
        "D2-nL1",
        "Geo-nL1",
        "Heat-L2-KL-Single[t=0.1]",
        "Heat-L2-Bhatt-Single[t=0.1]",
        "Heat-L2-chi2-Single[t=0.1]",
        "Heat-L2-EMD-Single[t=0.1]",
        "Heat-L2-nL1-Single[t=1.5625]",
        "Heat-L2-L1-Sum2[t=0.016..0.1]",
        "Heat-L1-nL1-Single[t=0.1]",
        "Heat-Linf-nL1-Single[t=0.1]",
        "Mahmoudi-Sapiro[t=0.1]",
        "DSS",
        "GPS",
        "paper-best",
        "default",
    ] {
        assert!(names.contains(&required), "missing {required}");
    }
    let n = names.len();
    names.sort_unstable();
    names.dedup();
    assert_eq!(names.len(), n, "duplicate names");
    for c in &configs {
        let chans = c.signature.channel_names();
        for q in &c.query.channels {
            assert!(chans.contains(q), "{}: channel {q} not in its spec", c.name);
        }
        assert!(!c.query.channels.is_empty());
    }
    // Families share a spec: few distinct keys.
    let mut keys: Vec<String> = configs.iter().map(|c| c.signature.key()).collect();
    keys.sort_unstable();
    keys.dedup();
    assert!(keys.len() <= 16, "{} distinct signature specs", keys.len());
    assert_eq!(config_by_name("default"), Some(default_config()));
    let ms = config_by_name("Mahmoudi-Sapiro[t=0.1]").expect("MS");
    assert_eq!(ms.query.channels, vec!["heat-l2[t=0.1]".to_string()]);
    assert_eq!(ms.query.dissimilarity, Dissimilarity::L2);
    assert!(matches!(
        default_config().signature.quadrature,
        PairQuadrature::Farthest { .. }
    ));
}

/// End to end on generated shapes: self-dissimilarity 0, symmetric scores, and a bent copy of a
/// shape ranks before a different shape.
#[test]
fn end_to_end_ranking() {
    use crate::mesh::generate;
    use crate::spectrum::{analyze, AnalyzeOptions};
    let mut opts = AnalyzeOptions::default();
    opts.eigen.k = 60;
    let sphere = generate::bumpy_sphere(3, 0.2);
    let mut bent = sphere.clone();
    for v in &mut bent.vertices {
        // A mild, nearly isometric bend: rotate about z by an angle growing with height.
        let a = 0.3 * v[2];
        let (s, c) = a.sin_cos();
        *v = [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]];
    }
    let torus = generate::bumpy_torus(60, 30);
    let cfg = default_config();
    let sigs: Vec<Signature> = [&sphere, &bent, &torus]
        .iter()
        .map(|m| {
            let a = analyze(m, &opts).expect("analysis");
            crate::signature::compute_signature(&a, &cfg.signature).expect("signature")
        })
        .collect();
    let refs: Vec<&Signature> = sigs.iter().collect();
    let cal = calibrate(&refs, &cfg.signature, 1);
    use crate::search::{rank_all, Corpus, Encoded, Layout, Query};
    let layout = Layout::of(&cal);
    let rows: Vec<Encoded> = sigs
        .iter()
        .map(|s| Encoded::from_signature(s, &cal, &layout))
        .collect();
    let corpus = Corpus::build(layout, &rows);
    let q = Query::new(&cfg.query, corpus.layout());
    let d = |i: usize, j: usize| q.score(corpus.layout(), corpus.shape(i), corpus.shape(j));
    assert_eq!(d(0, 0), 0.0);
    assert!(close(d(0, 1), d(1, 0)));
    assert!(d(0, 1) < d(0, 2), "bent {} vs torus {}", d(0, 1), d(0, 2));
    assert!(d(1, 0) < d(1, 2));
    // rank_all() agrees with score() and orders by score.
    let r = rank_all(&corpus, &q, corpus.shape(0));
    assert_eq!(r.iter().map(|x| x.0).collect::<Vec<_>>(), vec![0, 1, 2]);
    for &(i, sc) in &r {
        assert_eq!(sc, d(0, i));
    }
}

/// [`sketch_histogram`] evaluates the sketch's CDF in one pass over its knots; the result is
/// the one of a binary search per sub-bin ([`sketch_cdf`]), bit for bit, for sketches with
/// repeated knots (atoms), knots outside the window, a single knot, none, and unsorted knots.
#[test]
fn sketch_histogram_walk_matches_the_cdf_point_by_point() {
    fn reference(s: &QuantileSketch, window: f64, bins: usize, bw: f64) -> Histogram {
        let nsub = bins * SUB_BINS;
        let hs = window / nsub as f64;
        let mut prev = 0.0;
        let values = (0..nsub).map(|k| {
            let hi = sketch_cdf(s, (k + 1) as f64 * hs);
            let m = (hi - prev) * s.mass;
            prev = hi;
            ((k as f64 + 0.5) * hs, m)
        });
        histogram_from_mass(
            parzen_histogram(values, window, bins, bw),
            window / bins as f64,
        )
    }
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    for case in 0..400 {
        let nq = [0, 1, 2, 3, 17, 65, 129][case % 7];
        let mut q: Vec<f64> = (0..nq).map(|_| 3.0 * next()).collect();
        q.sort_by(f64::total_cmp);
        if nq > 4 && case % 3 == 0 {
            // atoms: runs of repeated knots
            let v = q[1];
            q[2] = v;
            q[3] = v;
        }
        if nq > 4 && case % 11 == 0 {
            q.swap(0, nq - 1); // a damaged sketch: unsorted knots
        }
        let s = QuantileSketch {
            mass: 0.5 + next(),
            quantiles: q,
        };
        let window = 0.5 + 2.5 * next();
        let bins = [1, 8, 64, 100][case % 4];
        let bw = [0.0, 0.7, 2.0][case % 3];
        let a = sketch_histogram(&s, window, bins, bw);
        let b = reference(&s, window, bins, bw);
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.density), bits(&b.density), "case {case}");
        assert_eq!(bits(&a.cdf), bits(&b.cdf), "case {case}");
        assert_eq!(a.mass.to_bits(), b.mass.to_bits(), "case {case}");
    }
}
