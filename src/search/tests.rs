//! Tests of [`crate::search`] (`cargo test --release --lib search`).

use super::corpus::{quantise, total_at, Slot, GROUPS, TOTAL, VECTOR_GROUPS};
use super::prune::{channel_bound, search, vector_bound, with_margin, Bounder};
use super::score::{histogram, Counts};
use super::*;
use crate::ranking::{
    histogram_dissimilarity, histogram_from_mass, vector_dissimilarity, Calibration, Dissimilarity,
    Histogram, Prepared, PreparedChannel, QuerySpec,
};
use crate::signature::Aggregation;
use proptest::prelude::*;

fn hist(mass: &[f64], width: f64) -> Histogram {
    histogram_from_mass(mass.to_vec(), width)
}

fn layout(names: &[&str], bins: usize, window: f64) -> Layout {
    Layout::of(&calibration(names, bins, window))
}

fn calibration(names: &[&str], bins: usize, window: f64) -> Calibration {
    Calibration {
        epoch: 1,
        spec_key: String::new(),
        channel_names: names.iter().map(|s| s.to_string()).collect(),
        window_max: vec![window; names.len()],
        bins,
        bandwidth_bins: 1.0,
        percentile: 0.95,
        shapes: 0,
    }
}

/// Two histogram channels `t1`, `t2` of 70 bins and a vector channel `v`.
fn mixed_layout() -> Layout {
    Layout::of(&Calibration {
        window_max: vec![3.5, 3.5, 0.0],
        ..calibration(&["t1", "t2", "v"], 70, 3.5)
    })
}

/// A shape of [`mixed_layout`].
fn mixed(t1: &[f64], t2: &[f64], v: Vec<f64>, l: &Layout) -> Encoded {
    Encoded::from_prepared(
        &prepared(
            &["t1", "t2", "v"],
            vec![
                Some(PreparedChannel::Histogram(hist(t1, 0.05))),
                Some(PreparedChannel::Histogram(hist(t2, 0.05))),
                Some(PreparedChannel::Vector(v)),
            ],
        ),
        l,
    )
}

/// Vector values: positive and increasing (as eigenvalues), or of both signs over many
/// magnitudes (sums that cancel).
fn vector_values(n: usize) -> impl Strategy<Value = Vec<f64>> {
    prop_oneof![
        prop::collection::vec(0.0..10.0f64, n).prop_map(|v| v
            .iter()
            .scan(0.0, |acc, x| {
                *acc += x;
                Some(*acc)
            })
            .collect()),
        prop::collection::vec(
            prop_oneof![Just(0.0), -1.0..1.0f64, -1e6..1e6f64, Just(1e-30)],
            n
        ),
    ]
}

fn prepared(names: &[&str], channels: Vec<Option<PreparedChannel>>) -> Prepared {
    Prepared {
        epoch: 1,
        names: names.iter().map(|s| s.to_string()).collect(),
        channels,
        alternate: None,
    }
}

fn spec(channels: &[&str], d: Dissimilarity, a: Aggregation) -> QuerySpec {
    QuerySpec {
        channels: channels.iter().map(|s| s.to_string()).collect(),
        dissimilarity: d,
        aggregation: a,
        alternate_margin: crate::ranking::DEFAULT_ALTERNATE_MARGIN,
    }
}

const AGGREGATIONS: [Aggregation; 4] = [
    Aggregation::Single,
    Aggregation::Sum,
    Aggregation::Sum2,
    Aggregation::Max,
];

/// Masses with many exact zeros (empty bins are where KL, χ² and Bhattacharyya are delicate).
fn masses(bins: usize) -> impl Strategy<Value = Vec<f64>> {
    prop::collection::vec(
        prop_oneof![Just(0.0), 0.0..1.0f64, 0.0..1e-6f64, 1.0..100.0f64],
        bins,
    )
}

/// The first histogram channel of `e`.
fn counts(e: &Encoded) -> Counts<'_> {
    Counts {
        counts: &e.hist,
        shift: e.shift[0],
        mass: e.mass[0],
    }
}

/// The layout of [`encode`]'s histograms.
fn single(bins: usize, width: f64) -> Layout {
    layout(&["a"], bins, width * bins as f64)
}

/// One encoded single-channel histogram and its group sums.
fn encode(mass: &[f64], width: f64) -> Encoded {
    let l = single(mass.len(), width);
    let p = prepared(
        &["a"],
        vec![Some(PreparedChannel::Histogram(hist(mass, width)))],
    );
    Encoded::from_prepared(&p, &l)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    /// Quantised counts sum to `T_s` (or are all zero), move by less than `2·bins` units in
    /// all, keep every positive probability positive and every zero zero, and the exponent is
    /// the largest that fits.
    #[test]
    fn quantisation_is_exact_in_sum(m in (1usize..300).prop_flat_map(masses)) {
        let h = hist(&m, 1.0);
        let mut out = vec![0u16; m.len()];
        let s = quantise(&h.prob, &mut out);
        let sum: u64 = out.iter().map(|&x| x as u64).sum();
        let total: f64 = m.iter().sum();
        if total > 0.0 {
            let t = total_at(s);
            prop_assert_eq!(sum as f64, t);
            let moved: f64 = out.iter().zip(&h.prob).map(|(&c, &p)| (c as f64 - p * t).abs()).sum();
            prop_assert!(moved < 2.0 * m.len() as f64, "moved {moved}");
            for (&c, &p) in out.iter().zip(&h.prob) {
                prop_assert_eq!(c > 0, p > 0.0);
            }
            let max_p = h.prob.iter().cloned().fold(0.0, f64::max);
            prop_assert!(s == super::corpus::MAX_SHIFT || max_p * total_at(s + 1) + 2.0 > u16::MAX as f64);
        } else {
            prop_assert_eq!(sum, 0);
            prop_assert_eq!(s, 0);
        }
    }

    /// Every bound is below the exact dissimilarity of the same counts, for all nine.
    #[test]
    fn bound_never_exceeds_exact(
        (a, b) in (1usize..200).prop_flat_map(|n| (masses(n), masses(n))),
        width in prop_oneof![Just(1e-4), 1e-3..2.0f64],
    ) {
        let (ea, eb) = (encode(&a, width), encode(&b, width));
        for d in Dissimilarity::all() {
            let exact = histogram(d, counts(&ea), counts(&eb), width);
            let bound = with_margin(channel_bound(
                d, &ea.groups, ea.mass[0], &eb.groups, eb.mass[0], width, &single(a.len(), width),
            ));
            prop_assert!(bound >= 0.0);
            prop_assert!(bound <= exact, "{d:?}: bound {bound} > exact {exact}");
        }
    }

    /// Every vector bound (from the stored `f32` group sums) is below the exact vector
    /// dissimilarity of the stored `f32` values, for all nine, with sums that cancel.
    #[test]
    fn vector_bound_never_exceeds_exact(
        (a, b) in (1usize..70).prop_flat_map(|n| (vector_values(n), vector_values(n))),
        near in any::<bool>(),
    ) {
        let l = mixed_layout();
        let t = vec![1.0; 70];
        // `near`: b is a within a relative 10⁻⁶ (gaps close to the rounding allowance).
        let b: Vec<f64> = if near {
            a.iter().zip(&b).map(|(x, y)| x * (1.0 + 1e-6 * y.signum())).collect()
        } else {
            b
        };
        let (ea, eb) = (mixed(&t, &t, a.clone(), &l), mixed(&t, &t, b, &l));
        prop_assert_eq!(ea.vgroups.len(), VECTOR_GROUPS);
        for d in Dissimilarity::all() {
            let exact = vector_dissimilarity(d, &ea.vectors[0], &eb.vectors[0]);
            let bound = with_margin(vector_bound(d, &ea.vgroups, &eb.vgroups, a.len()));
            prop_assert!(bound >= 0.0);
            prop_assert!(bound <= exact, "{d:?}: bound {bound} > exact {exact}");
        }
    }

    /// The stated tolerance against the `f64` histograms holds for nL1, L1 and EMD.
    #[test]
    fn scores_within_the_stated_tolerance(
        (a, b) in (1usize..300).prop_flat_map(|n| (masses(n), masses(n))),
        width in 1e-3..2.0f64,
    ) {
        let n = a.len() as f64;
        let t = TOTAL as f64;
        let (ha, hb) = (hist(&a, width), hist(&b, width));
        let (ea, eb) = (encode(&a, width), encode(&b, width));
        let q = |d| histogram(d, counts(&ea), counts(&eb), width);
        let f = |d| histogram_dissimilarity(d, &ha, &hb);
        let tol = 1e-9 * (1.0 + f(Dissimilarity::L1));
        prop_assert!((q(Dissimilarity::NL1) - f(Dissimilarity::NL1)).abs() <= 4.0 * n / t + 1e-12);
        prop_assert!((q(Dissimilarity::Emd) - f(Dissimilarity::Emd)).abs() <= 4.0 * n * n * width / t + 1e-12);
        prop_assert!(
            (q(Dissimilarity::L1) - f(Dissimilarity::L1)).abs()
                <= 2.0 * (ea.mass[0] + eb.mass[0]) * n / t + tol
        );
    }

    /// The pruned top-k equals the head of the full ranking filtered by `keep`, bit for bit,
    /// with ties (duplicated shapes), filters, every dissimilarity and aggregation, a vector
    /// channel, and second cut versions on the query, on candidates, or on both.
    #[test]
    fn top_k_equals_full_ranking(
        base in prop::collection::vec((masses(70), masses(70), vector_values(9)), 1..12),
        alts in prop::collection::vec(0usize..24, 12),
        margin in 1.0f64..1.5,
        picks in prop::collection::vec(0usize..1000, 1..80),
        drop in prop::collection::vec(any::<bool>(), 80),
        k in 1usize..30,
        d in 0usize..9,
        agg in 0usize..4,
        query in 0usize..1000,
        first_batch in 1usize..6,
    ) {
        let l = mixed_layout();
        let shapes: Vec<Encoded> = base
            .iter()
            .map(|(x, y, v)| mixed(x, y, v.clone(), &l))
            .collect();
        // Some shapes (those whose draw names another shape) get that shape's first version as
        // their second one.
        let shapes: Vec<Encoded> = shapes
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let mut e = e.clone();
                if alts[i] < shapes.len() && alts[i] != i {
                    e.alt = Some(Box::new(shapes[alts[i]].clone()));
                }
                e
            })
            .collect();
        let rows: Vec<Encoded> = picks.iter().map(|&i| shapes[i % shapes.len()].clone()).collect();
        let corpus = Corpus::build(l, &rows);
        let q = Query::new(
            &QuerySpec {
                alternate_margin: margin,
                ..spec(&["t2", "v", "t1"], Dissimilarity::all()[d], AGGREGATIONS[agg])
            },
            corpus.layout(),
        );
        let query = &shapes[query % shapes.len()];
        let keep = |i: usize| !drop[i];
        let expected: Vec<(usize, f64)> = rank_all(&corpus, &q, query.view())
            .into_iter()
            .filter(|&(i, _)| keep(i))
            .take(k)
            .collect();
        let (got, _) = search(&corpus, &q, query.view(), k, &keep, first_batch);
        prop_assert_eq!(got.len(), expected.len());
        for (g, e) in got.iter().zip(&expected) {
            prop_assert_eq!(g.0, e.0);
            prop_assert_eq!(g.1.to_bits(), e.1.to_bits());
        }
    }
}

/// The bounds are tight where they can be: with each histogram in one bin of a different
/// group, nL1, L1, χ² and Bhattacharyya bounds equal the exact scores, so a bound raised by any
/// factor above 1 (a loosened proof) fails `bound_never_exceeds_exact` on such inputs.
#[test]
fn a_raised_bound_fails() {
    let mut a = vec![0.0; 64];
    let mut b = vec![0.0; 64];
    a[3] = 2.0;
    b[40] = 1.0;
    let (ea, eb) = (encode(&a, 0.1), encode(&b, 0.1));
    for d in [
        Dissimilarity::NL1,
        Dissimilarity::L1,
        Dissimilarity::Chi2,
        Dissimilarity::Bhattacharyya,
    ] {
        let exact = histogram(d, counts(&ea), counts(&eb), 0.1);
        let bound = channel_bound(
            d,
            &ea.groups,
            ea.mass[0],
            &eb.groups,
            eb.mass[0],
            0.1,
            &single(64, 0.1),
        );
        assert_eq!(bound, exact, "{d:?}");
        assert!(with_margin(bound) <= exact);
        assert!(bound * 1.001 > exact, "{d:?}: a raised bound would pass");
    }
}

/// Shapes the bounds cannot use (a missing channel, a vector channel) are still ranked exactly.
#[test]
fn unbounded_candidates_are_ranked_exactly() {
    let mut cal_layout = layout(&["a", "b", "v"], 9, 0.9);
    cal_layout.slots[2] = Slot::Vector(0);
    cal_layout.bin_width.pop();
    let l = cal_layout;
    let h = |m: &[f64]| Some(PreparedChannel::Histogram(hist(m, 0.1)));
    let v = |x: f64| Some(PreparedChannel::Vector(vec![x, 1.0]));
    let base = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0];
    let shifted = [9.0, 8.0, 7.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0];
    let rows: Vec<Encoded> = [
        prepared(&["a", "b", "v"], vec![h(&shifted), h(&shifted), v(1.0)]),
        prepared(&["a", "b", "v"], vec![h(&base), None, v(2.0)]), // missing channel → ∞
        prepared(&["a", "b", "v"], vec![h(&base), h(&base), None]),
        prepared(&["a", "b", "v"], vec![h(&base[..5]), h(&base), v(0.0)]), // other bin count
        prepared(&["a", "b", "v"], vec![h(&base), h(&base), v(3.0)]),
    ]
    .iter()
    .map(|p| Encoded::from_prepared(p, &l))
    .collect();
    let corpus = Corpus::build(l.clone(), &rows);
    let query = Encoded::from_prepared(
        &prepared(&["a", "b", "v"], vec![h(&base), h(&base), v(1.5)]),
        &l,
    );
    for chans in [&["a", "b"][..], &["a", "v"], &["v", "b"]] {
        for d in Dissimilarity::all() {
            for agg in AGGREGATIONS {
                let q = Query::new(&spec(chans, d, agg), corpus.layout());
                let expected = rank_all(&corpus, &q, query.view());
                for k in 1..=rows.len() {
                    let (got, _) = search(&corpus, &q, query.view(), k, &|_| true, 1);
                    assert_eq!(got, expected[..k].to_vec(), "{chans:?} {d:?} {agg:?} k={k}");
                }
            }
        }
    }
}

/// A pair scores the smaller of its first versions' dissimilarity and the margin times its
/// second versions' (a shape without a second version takes part with its first); without
/// second versions on either side the score is the first versions'.
#[test]
fn second_versions_score_the_smaller_comparison() {
    let l = layout(&["a"], 8, 0.8);
    let e = |m: &[f64]| {
        Encoded::from_prepared(
            &prepared(&["a"], vec![Some(PreparedChannel::Histogram(hist(m, 0.1)))]),
            &l,
        )
    };
    let far = e(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    let near = e(&[0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
    let target = e(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
    let with_alt = |first: &Encoded, second: &Encoded| {
        let mut x = first.clone();
        x.alt = Some(Box::new(second.clone()));
        x
    };
    for f in [1.0, 1.1, 3.0] {
        let q = Query::new(
            &QuerySpec {
                alternate_margin: f,
                ..spec(&["a"], Dissimilarity::NL1, Aggregation::Single)
            },
            &l,
        );
        let d = |a: &Encoded, b: &Encoded| q.score_versions(&l, a.view(), b.view());
        let (d_far, d_near) = (d(&far, &target), d(&near, &target));
        assert!(d_near < d_far && d_far == 2.0, "{d_near} {d_far}");
        // No second version: the first versions' score.
        assert_eq!(q.score(&l, far.view(), target.view()), d_far);
        // A second version on either side (the other side takes part with its first).
        let x = with_alt(&far, &near);
        let expected = d_far.min(f * d_near);
        assert_eq!(q.score(&l, x.view(), target.view()), expected);
        assert_eq!(q.score(&l, target.view(), x.view()), expected);
        // On both sides: the second versions are compared with each other.
        let y = with_alt(&target, &near);
        assert_eq!(q.score(&l, x.view(), y.view()), d_far.min(0.0));
        // A second version farther away changes nothing.
        let z = with_alt(&near, &far);
        assert_eq!(q.score(&l, z.view(), target.view()), d_near);
    }
}

/// Inserting, replacing and removing keep the corpus equal to one built from scratch.
#[test]
fn edits_match_a_rebuilt_corpus() {
    let l = mixed_layout();
    let p = |s: f64| {
        let m = (0..70)
            .map(|i| (i as f64 * s).sin().abs())
            .collect::<Vec<_>>();
        let v = (0..9).map(|i| i as f64 * s).collect();
        mixed(&m, &m, v, &l)
    };
    let mut arr = vec![Encoded::absent(&l)];
    let mut c = Corpus::build(l.clone(), &arr);
    for (at, s) in [(1, 0.3), (0, 0.5), (1, 0.7), (3, 0.9)] {
        arr.insert(at, p(s));
        c.insert(at, &p(s));
    }
    let mut with_alt = p(1.1);
    with_alt.alt = Some(Box::new(p(1.3)));
    arr[2] = with_alt.clone();
    c.replace(2, &with_alt);
    arr.insert(1, with_alt.clone());
    c.insert(1, &with_alt);
    arr.remove(0);
    c.remove(0);
    // Random edits, half of the shapes with a second version: every kind of replacement
    // (a second version added, removed, replaced) and edits before and after such shapes.
    let mut r = 7u64;
    let mut next = |n: usize| {
        r = r
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (r >> 33) as usize % n
    };
    for step in 0..300 {
        let mut e = p(0.05 * (step % 40) as f64 + 0.2);
        if next(2) == 0 {
            e.alt = Some(Box::new(p(0.03 * (step % 50) as f64 + 0.1)));
        }
        match next(4) {
            0 | 1 => {
                let at = next(arr.len() + 1);
                arr.insert(at, e.clone());
                c.insert(at, &e);
            }
            2 if !arr.is_empty() => {
                let at = next(arr.len());
                arr[at] = e.clone();
                c.replace(at, &e);
            }
            _ if arr.len() > 1 => {
                let at = next(arr.len());
                arr.remove(at);
                c.remove(at);
            }
            _ => {}
        }
    }
    assert!(arr.iter().filter(|e| e.alt.is_some()).count() > 3);
    let rebuilt = Corpus::build(l, &arr);
    assert_eq!(c.len(), arr.len());
    for i in 0..arr.len() {
        assert_eq!(c.encoded(i), rebuilt.encoded(i));
        assert_eq!(c.encoded(i), arr[i]);
    }
}

/// The nL1 bounds of the fast loops (over the first versions' rows and over the second
/// versions' contiguous rows, histograms and vector) equal the per-channel bounds of the module
/// docs, for candidates with and without a second version, queries with and without one,
/// across several chunks.
#[test]
fn nl1_bounds_of_second_versions() {
    let l = mixed_layout();
    let p = |s: f64| {
        let m = |c: f64| {
            (0..70)
                .map(|i| ((i as f64 * s + c).sin() + 1.0).powi(3))
                .collect::<Vec<_>>()
        };
        let v = (1..=20).map(|i| (i as f64 * (1.0 + s)).powf(1.1)).collect();
        mixed(&m(0.0), &m(1.0), v, &l)
    };
    let with_alt = |s: f64, t: f64| {
        let mut e = p(s);
        e.alt = Some(Box::new(p(t)));
        e
    };
    let shapes: Vec<Encoded> = (0..9000)
        .map(|i| {
            let s = 0.01 * (i % 97) as f64 + 0.05;
            if i % 3 == 0 {
                p(s)
            } else {
                with_alt(s, 0.013 * (i % 89) as f64 + 0.07)
            }
        })
        .collect();
    let corpus = Corpus::build(l.clone(), &shapes);
    let q = Query::new(
        &spec(&["t2", "v", "t1"], Dissimilarity::NL1, Aggregation::Sum),
        corpus.layout(),
    );
    let f = q.alternate_margin;
    let g = l.groups;
    let pair = |a: VersionRef<'_>, b: VersionRef<'_>| {
        let hist: f64 = (0..2)
            .map(|k| {
                let r = k * g..(k + 1) * g;
                channel_bound(
                    Dissimilarity::NL1,
                    &a.groups[r.clone()],
                    a.mass[k],
                    &b.groups[r],
                    b.mass[k],
                    l.bin_width[k],
                    &l,
                )
            })
            .sum();
        with_margin(hist + vector_bound(Dissimilarity::NL1, a.vgroups, b.vgroups, 20))
    };
    let keep = |i: usize| i % 7 != 0;
    for query in [p(0.4), with_alt(0.4, 0.9)] {
        let qv = query.view();
        let bounder = Bounder::new(&corpus, &q, qv);
        let mut got = vec![0.0; corpus.len()];
        for (c, chunk) in got.chunks_mut(4096).enumerate() {
            bounder.fill(c * 4096, chunk, &keep);
        }
        let mut second_smaller = 0;
        for (i, &b) in got.iter().enumerate() {
            if !keep(i) {
                assert!(b.is_nan(), "position {i} is not kept");
                continue;
            }
            let cand = corpus.shape(i);
            let first = pair(qv.first, cand.first);
            let second = match (cand.alt, qv.alt) {
                (Some(alt), _) => pair(qv.second().first, alt),
                (None, Some(qalt)) => pair(qalt, cand.first),
                (None, None) => f64::INFINITY,
            };
            let want = first.min(f * second);
            second_smaller += usize::from(f * second < first);
            assert!(
                (b - want).abs() <= 1e-12 * want.max(1e-3),
                "position {i}: {b} against {want}"
            );
        }
        assert!(second_smaller > 100, "{second_smaller} second pairs bound");
    }
}

/// Where the vector channel makes most of the score (a query whose eigenvalues are far from
/// every stored shape's, as a shape uploaded at another scale), its bound keeps the scan
/// pruning: without it every candidate's bound would be below the `k`-th score.
#[test]
fn vector_channels_are_bounded() {
    let l = mixed_layout();
    let flat = vec![1.0; 70];
    let eig = |s: f64| (1..=50).map(|i| s * i as f64).collect::<Vec<f64>>();
    let rows: Vec<Encoded> = (0..4000)
        .map(|i| mixed(&flat, &flat, eig(1.0 + 0.001 * i as f64), &l))
        .collect();
    let corpus = Corpus::build(l.clone(), &rows);
    let q = Query::new(
        &spec(&["t1", "t2", "v"], Dissimilarity::NL1, Aggregation::Sum),
        corpus.layout(),
    );
    let query = mixed(&flat, &flat, eig(0.5), &l);
    let (got, scored) = top_k(&corpus, &q, query.view(), 10, &|_| true);
    let expected: Vec<(usize, f64)> = rank_all(&corpus, &q, query.view())[..10].to_vec();
    assert_eq!(got, expected);
    assert_eq!(got[0].0, 0);
    assert!(scored <= 256, "scored {scored} of 4000");
    // A layout of the vector channel alone (no group sums of histograms), every dissimilarity.
    let only = Layout::of(&Calibration {
        window_max: vec![0.0],
        ..calibration(&["v"], 70, 3.5)
    });
    let vector = |s: f64| {
        let p = prepared(&["v"], vec![Some(PreparedChannel::Vector(eig(s)))]);
        Encoded::from_prepared(&p, &only)
    };
    let rows: Vec<Encoded> = (0..4000).map(|i| vector(1.0 + 0.001 * i as f64)).collect();
    let corpus = Corpus::build(only.clone(), &rows);
    for d in Dissimilarity::all() {
        let q = Query::new(&spec(&["v"], d, Aggregation::Sum), corpus.layout());
        let query = vector(0.5);
        let (got, scored) = top_k(&corpus, &q, query.view(), 10, &|_| true);
        let expected: Vec<(usize, f64)> = rank_all(&corpus, &q, query.view())[..10].to_vec();
        assert_eq!(got, expected, "{d:?}");
        assert!(scored <= 256, "{d:?}: scored {scored} of 4000");
    }
}

/// A group whose values cancel (2^40 and −2^40 beside a small value) has an `f64` sum that
/// is off by more than the rounding allowance: it is stored as NaN and bounds nothing, where
/// its sum would have bounded 128 times the exact dissimilarity.
#[test]
fn cancelling_vector_groups_bound_nothing() {
    let l = mixed_layout();
    let t = vec![1.0; 70];
    let v = |f: f64| {
        let mut v = vec![0.0; 24];
        v[0] = 2f64.powi(40);
        v[1] = 2f64.powi(-13) * f;
        v[2] = -(2f64.powi(40));
        v
    };
    let (a, b) = (
        mixed(&t, &t, v(1.0 + 2f64.powi(-7)), &l),
        mixed(&t, &t, v(1.0 - 2f64.powi(-7)), &l),
    );
    assert!(a.vgroups[0].is_nan() && b.vgroups[0].is_nan());
    assert_eq!(a.vgroups[1], 0.0);
    for d in Dissimilarity::all() {
        let exact = vector_dissimilarity(d, &a.vectors[0], &b.vectors[0]);
        assert!(exact > 0.0);
        assert_eq!(vector_bound(d, &a.vgroups, &b.vgroups, 24), 0.0, "{d:?}");
    }
}

/// On clustered data the scan scores only a fraction of the candidates exactly.
#[test]
fn clustered_candidates_are_pruned() {
    let bump = |c: f64, s: f64| -> Vec<f64> {
        (0..256)
            .map(|i| (-((i as f64 - c) / s).powi(2)).exp())
            .collect()
    };
    let l = layout(&["a"], 256, 2.56);
    let rows: Vec<Encoded> = (0..4000)
        .map(|i| {
            let c = 20.0 + (i % 200) as f64;
            Encoded::from_prepared(
                &prepared(
                    &["a"],
                    vec![Some(PreparedChannel::Histogram(hist(&bump(c, 8.0), 0.01)))],
                ),
                &l,
            )
        })
        .collect();
    let corpus = Corpus::build(l, &rows);
    let q = Query::new(
        &spec(&["a"], Dissimilarity::NL1, Aggregation::Sum),
        corpus.layout(),
    );
    let (got, scored) = top_k(&corpus, &q, corpus.shape(57), 10, &|_| true);
    let expected: Vec<(usize, f64)> = rank_all(&corpus, &q, corpus.shape(57))[..10].to_vec();
    assert_eq!(got, expected);
    assert!(scored < 1000, "scored {scored} of 4000");
    assert_eq!((corpus.layout().group_bins, GROUPS), (32, 8));
}

/// A `k` past the corpus size (a shard request names any `k`) asks for every kept candidate,
/// no more: nothing is reserved for candidates that cannot exist.
#[test]
fn k_past_the_corpus_size_ranks_every_kept_candidate() {
    let l = layout(&["a"], 64, 0.64);
    let rows: Vec<Encoded> = (0..40)
        .map(|i| {
            let m: Vec<f64> = (0..64).map(|b| 1.0 + ((b * (i + 1)) % 7) as f64).collect();
            Encoded::from_prepared(
                &prepared(
                    &["a"],
                    vec![Some(PreparedChannel::Histogram(hist(&m, 0.01)))],
                ),
                &l,
            )
        })
        .collect();
    let corpus = Corpus::build(l, &rows);
    let q = Query::new(
        &spec(&["a"], Dissimilarity::NL1, Aggregation::Sum),
        corpus.layout(),
    );
    let all = rank_all(&corpus, &q, corpus.shape(3));
    for k in [40, 41, 1 << 40, usize::MAX / 2, usize::MAX] {
        let (got, _) = top_k(&corpus, &q, corpus.shape(3), k, &|_| true);
        assert_eq!(got, all, "k = {k}");
        let (odd, _) = top_k(&corpus, &q, corpus.shape(3), k, &|at| at % 2 == 1);
        assert_eq!(odd.len(), 20, "k = {k}");
    }
}

/// Stages in the configuration form read what they wrote; `none` entries of a list are
/// skipped; the request form resolves defaults and refuses out-of-range values.
#[test]
fn stage_forms() {
    let list: Vec<Stage> = stage::deserialize_list(&mut serde_json::Deserializer::from_str(
        r#"[{"kind": "none"}, {"kind": "reciprocal", "shortlist": 50, "neighbourhoods": [8], "expansion": 4, "original_weight": 0.1}]"#,
    ))
    .unwrap();
    assert_eq!(list.len(), 1);
    assert_eq!(list[0].shortlist(), 50);
    let back: Stage = serde_json::from_value(serde_json::to_value(&list[0]).unwrap()).unwrap();
    assert_eq!(back, list[0]);
    let q = spec(&["a"], Dissimilarity::NL1, Aggregation::Sum);
    let resolve = |v: serde_json::Value| {
        let r: StageRequest = serde_json::from_value(v).unwrap();
        r.resolve(10, 100, &|_| Ok(q.clone()))
    };
    assert_eq!(
        resolve(serde_json::json!({"stage": "exact"})).unwrap(),
        Stage::Exact {
            shortlist: 40,
            query: q.clone()
        }
    );
    assert_eq!(
        resolve(serde_json::json!({"stage": "reciprocal"}))
            .unwrap()
            .shortlist(),
        200
    );
    // The exact stage's default (4 × top_k) is clamped to the bound: top_k 30 asks for no
    // shortlist, so it is not refused for 120 (it was: "rerank shortlist must be in 1..=100").
    let exact: StageRequest =
        serde_json::from_value(serde_json::json!({"stage": "exact"})).unwrap();
    assert_eq!(
        exact
            .resolve(30, 100, &|_| Ok(q.clone()))
            .unwrap()
            .shortlist(),
        100
    );
    // The GW stage's anchored starts: off unless asked for.
    for (v, want) in [
        (serde_json::json!({"stage": "spectral_gw"}), false),
        (
            serde_json::json!({"stage": "spectral_gw", "anchored_starts": true}),
            true,
        ),
    ] {
        match resolve(v).unwrap() {
            Stage::SpectralGw(g) => assert_eq!(g.gw.anchored_starts, want),
            other => panic!("{other:?}"),
        }
    }
    for bad in [
        serde_json::json!({"stage": "exact", "shortlist": 101}),
        serde_json::json!({"stage": "spectral_gw", "shortlist": 201}),
        serde_json::json!({"stage": "spectral_gw", "eps_rel": 2.0}),
        serde_json::json!({"stage": "reciprocal", "expansion": 0}),
        serde_json::json!({"stage": "reciprocal", "shortlist": 1001}),
    ] {
        assert!(resolve(bad.clone()).is_err(), "{bad}");
    }
    // A margin below 1 (or not finite) on an exact stage's query is refused.
    for f in [0.5, -1.0, f64::INFINITY, f64::NAN] {
        let query = QuerySpec {
            alternate_margin: f,
            ..q.clone()
        };
        assert!(
            Stage::new(Stage::Exact {
                shortlist: 10,
                query
            })
            .is_err(),
            "{f}"
        );
    }
}

/// The layout check covers the second version: one of another layout (or with a second
/// version of its own) does not fit, so a query from another node is refused, not indexed out
/// of bounds.
#[test]
fn a_second_version_must_fit_the_layout() {
    let l = layout(&["a", "b"], 8, 0.8);
    let other = layout(&["a"], 8, 0.8);
    let mut e = Encoded::absent(&l);
    assert!(l.fits(&e));
    e.alt = Some(Box::new(Encoded::absent(&l)));
    assert!(l.fits(&e));
    e.alt = Some(Box::new(Encoded::absent(&other)));
    assert!(!l.fits(&e));
    let mut nested = Encoded::absent(&l);
    nested.alt = Some(Box::new(Encoded::absent(&l)));
    e.alt = Some(Box::new(nested));
    assert!(!l.fits(&e));
}
