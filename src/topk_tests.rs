//! Tests of [`crate::topk`] (`cargo test --release --lib topk`).

use super::*;
use crate::ranking::{histogram_dissimilarity, histogram_from_mass, rank};
use proptest::prelude::*;

fn hist(mass: &[f64], width: f64) -> Histogram {
    histogram_from_mass(mass.to_vec(), width)
}

fn prepared(names: &[&str], channels: Vec<Option<PreparedChannel>>) -> Prepared {
    Prepared {
        epoch: 1,
        names: names.iter().map(|s| s.to_string()).collect(),
        channels,
    }
}

fn sums(h: &Histogram) -> [Vec<f64>; 3] {
    let layout = Layout {
        names: vec!["a".into()],
        bins: h.density.len(),
        groups: h.density.len().div_ceil(GROUP_BINS),
    };
    group_sums(h, &layout).unwrap()
}

fn widths(bins: usize) -> Vec<f64> {
    let layout = Layout {
        names: vec!["a".into()],
        bins,
        groups: bins.div_ceil(GROUP_BINS),
    };
    (0..layout.groups).map(|g| layout.width(g)).collect()
}

fn spec(channels: &[&str], d: Dissimilarity, a: Aggregation) -> QuerySpec {
    QuerySpec {
        channels: channels.iter().map(|s| s.to_string()).collect(),
        dissimilarity: d,
        aggregation: a,
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

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    /// Every bound of the module table is below the exact dissimilarity, for all nine.
    #[test]
    fn bound_never_exceeds_exact(
        (a, b) in (1usize..70).prop_flat_map(|n| (masses(n), masses(n))),
        width in prop_oneof![Just(1e-4), 1e-3..2.0f64],
    ) {
        let ha = hist(&a, width);
        let hb = hist(&b, width);
        let sb = sums(&hb);
        for d in Dissimilarity::all() {
            let exact = histogram_dissimilarity(d, &ha, &hb);
            let bound = with_margin(channel_bound(
                d,
                &sums(&ha),
                [&sb[0], &sb[1], &sb[2]],
                width,
                &widths(a.len()),
            ));
            prop_assert!(bound >= 0.0);
            prop_assert!(bound <= exact, "{d:?}: bound {bound} > exact {exact}");
        }
    }

    /// The pruned top-k equals the head of the full ranking filtered by `keep`, bit for bit,
    /// with ties (duplicated shapes), filters, and every dissimilarity and aggregation.
    #[test]
    fn top_k_equals_full_ranking(
        base in prop::collection::vec((masses(20), masses(20)), 1..12),
        picks in prop::collection::vec(0usize..1000, 1..80),
        drop in prop::collection::vec(any::<bool>(), 80),
        k in 1usize..30,
        d in 0usize..9,
        agg in 0usize..4,
        query in 0usize..1000,
        first_batch in 1usize..6,
    ) {
        let shapes: Vec<Prepared> = base
            .iter()
            .map(|(x, y)| {
                prepared(
                    &["t1", "t2"],
                    vec![
                        Some(PreparedChannel::Histogram(hist(x, 0.05))),
                        Some(PreparedChannel::Histogram(hist(y, 0.05))),
                    ],
                )
            })
            .collect();
        let candidates: Vec<Prepared> = picks.iter().map(|&i| shapes[i % shapes.len()].clone()).collect();
        let table = BoundTable::build(&candidates);
        let q = spec(&["t2", "t1"], Dissimilarity::all()[d], AGGREGATIONS[agg]);
        let query = &shapes[query % shapes.len()];
        let keep = |i: usize| !drop[i];
        let expected: Vec<(usize, f64)> = rank(query, &candidates, &q)
            .into_iter()
            .filter(|&(i, _)| keep(i))
            .take(k)
            .collect();
        let (got, _) = table.search(query, &candidates, &q, k, &keep, first_batch);
        prop_assert_eq!(got.len(), expected.len());
        for (g, e) in got.iter().zip(&expected) {
            prop_assert_eq!(g.0, e.0);
            prop_assert_eq!(g.1.to_bits(), e.1.to_bits());
        }
    }
}

/// Shapes the table cannot bound (other channel layout, a missing channel, a vector channel,
/// another bin count) are still ranked exactly.
#[test]
fn unbounded_candidates_are_ranked_exactly() {
    let h = |m: &[f64]| Some(PreparedChannel::Histogram(hist(m, 0.1)));
    let base = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0];
    let shifted = [9.0, 8.0, 7.0, 6.0, 5.0, 4.0, 3.0, 2.0, 1.0];
    let candidates = vec![
        prepared(&["a", "b"], vec![h(&shifted), h(&shifted)]),
        prepared(&["b", "a"], vec![h(&base), h(&base)]), // other layout
        prepared(&["a", "b"], vec![h(&base), None]),     // missing channel → ∞
        prepared(
            &["a", "b"],
            vec![h(&base), Some(PreparedChannel::Vector(vec![1.0]))],
        ),
        prepared(&["a", "b"], vec![h(&base[..5]), h(&base)]), // other bin count → ∞
        prepared(&["a", "b"], vec![h(&base), h(&base)]),
    ];
    let table = BoundTable::build(&candidates);
    let query = prepared(&["a", "b"], vec![h(&base), h(&base)]);
    for d in Dissimilarity::all() {
        for agg in AGGREGATIONS {
            let q = spec(&["a", "b"], d, agg);
            let expected: Vec<(usize, f64)> = rank(&query, &candidates, &q);
            for k in 1..=candidates.len() {
                let (got, _) = table.search(&query, &candidates, &q, k, &|_| true, 1);
                assert_eq!(got, expected[..k].to_vec(), "{d:?} {agg:?} k={k}");
            }
        }
    }
}

/// Inserting, replacing and removing keep the table equal to one built from scratch.
#[test]
fn edits_match_a_rebuilt_table() {
    let h = |s: f64| {
        Some(PreparedChannel::Histogram(hist(
            &(0..20)
                .map(|i| (i as f64 * s).sin().abs())
                .collect::<Vec<_>>(),
            0.1,
        )))
    };
    let p = |s: f64| prepared(&["a"], vec![h(s)]);
    let vector = prepared(&["a"], vec![Some(PreparedChannel::Vector(vec![1.0, 2.0]))]);
    // A table that starts with no histogram at all gets its layout from the first one.
    let mut arr = vec![vector.clone()];
    let mut t = BoundTable::build(&arr);
    for (at, s) in [(1, 0.3), (0, 0.5), (1, 0.7), (3, 0.9)] {
        arr.insert(at, p(s));
        t.insert(at, &p(s));
    }
    arr[2] = p(1.1);
    t.replace(2, &p(1.1));
    arr.remove(0);
    t.remove(0);
    let rebuilt = BoundTable::build(&arr);
    assert_eq!(t.len(), arr.len());
    assert_eq!(t.layout, rebuilt.layout);
    assert_eq!(t.valid, rebuilt.valid);
    assert_eq!(t.density, rebuilt.density);
    assert_eq!(t.prob, rebuilt.prob);
    assert_eq!(t.cdf, rebuilt.cdf);
}

/// On clustered data the scan scores only a fraction of the candidates exactly.
#[test]
fn clustered_candidates_are_pruned() {
    let bump = |c: f64, s: f64| -> Vec<f64> {
        (0..256)
            .map(|i| (-((i as f64 - c) / s).powi(2)).exp())
            .collect()
    };
    let candidates: Vec<Prepared> = (0..4000)
        .map(|i| {
            let c = 20.0 + (i % 200) as f64;
            prepared(
                &["a"],
                vec![Some(PreparedChannel::Histogram(hist(&bump(c, 8.0), 0.01)))],
            )
        })
        .collect();
    let table = BoundTable::build(&candidates);
    let q = spec(&["a"], Dissimilarity::NL1, Aggregation::Sum);
    let (got, scored) = table.top_k_counted(&candidates[57], &candidates, &q, 10, &|_| true);
    let expected: Vec<(usize, f64)> = rank(&candidates[57], &candidates, &q)[..10].to_vec();
    assert_eq!(got, expected);
    assert!(scored < 1000, "scored {scored} of 4000");
}
