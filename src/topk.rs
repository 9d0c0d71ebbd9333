//! Exact top-k ranking over many prepared shapes by filter-and-refine.
//!
//! A first-stage search scores the query against every stored shape (paper §4: the aggregated
//! dissimilarity of the distance distributions) and keeps the `k` best. Scoring a candidate
//! exactly reads its full histograms (`bins` values per channel, scattered allocations), which
//! makes a brute-force scan of 10⁵ shapes memory-bound. This module keeps, contiguously, the
//! sums of every channel's histogram over groups of [`GROUP_BINS`] consecutive bins and derives
//! from them a **lower bound** of each of the nine dissimilarities (the GEMINI
//! filter-and-refine scheme of Faloutsos et al. 1994, with bounds specific to each
//! dissimilarity). Candidates are then scored exactly in order of increasing bound, and the
//! scan stops as soon as the `k`-th best exact score is below every remaining bound.
//!
//! The result is **exactly** the head of [`crate::ranking::rank`] restricted to the kept
//! candidates: same scores bit for bit (the exact score is [`crate::ranking::rank`]'s
//! computation) and the same order (score by `f64::total_cmp`, ties by position). Candidates
//! whose bound ties the `k`-th score are always scored, so ties are resolved as the full
//! ranking resolves them.
//!
//! Why by hand: this is a small structure specific to our histograms and dissimilarities; no
//! crate offers lower-bounding for Parzen-histogram dissimilarities.
//!
//! # The bounds
//!
//! For a group `g` of `w` bins write `X_g = Σ_{b∈g} x_b`. With `p, q` the normalised bin
//! probabilities, `f, g` the densities, `C, D` the cumulative sums and `h` the bin width:
//!
//! | dissimilarity | lower bound | why |
//! |---|---|---|
//! | L1 | `h Σ_g |F_g − G_g|` | triangle inequality |
//! | L2 | `(h Σ_g (F_g − G_g)² / w)^{1/2}` | Cauchy–Schwarz: `(Σ_{b∈g} x_b)² ≤ w Σ x_b²` |
//! | L∞ | `max_g |F_g − G_g| / w` | the mean of `|x_b|` over a group is at most its max |
//! | nL1 | `Σ_g |P_g − Q_g|` | triangle inequality |
//! | nL2 | `(Σ_g (P_g − Q_g)² / (w h))^{1/2}` | Cauchy–Schwarz |
//! | KL (symmetric) | `Σ_g (P_g − Q_g)(ln(P_g + wε) − ln(Q_g + wε))` | `(x − y)(ln x − ln y)` is the perspective of the convex `(u − 1) ln u`, hence subadditive (data processing) |
//! | Bhattacharyya | `−ln clamp(Σ_g (P_g Q_g)^{1/2})` | Cauchy–Schwarz: `Σ_{b∈g} (p_b q_b)^{1/2} ≤ (P_g Q_g)^{1/2}` |
//! | χ² | `2 Σ_g (P_g − Q_g)² / (P_g + Q_g)` | Sedrakyan: `(Σ x)² / Σ y ≤ Σ x² / y` |
//! | EMD | `h Σ_g |ΣC_g − ΣD_g|` | triangle inequality on the cumulative sums |
//!
//! Every aggregation of the dissimilarity stage (single, sum, sum of squares, max) is
//! non-decreasing in each non-negative argument, so aggregating the channel bounds bounds the
//! aggregated score. A channel the table cannot bound (a vector channel, a missing channel, a
//! different bin count or channel layout) contributes 0, which is always a valid bound. Each
//! bound is finally lowered by a relative 10⁻⁹ and an absolute 10⁻¹² so that the rounding of
//! the group sums can never make it exceed the exact score.

use crate::ranking::{
    self, Dissimilarity, Histogram, Prepared, PreparedChannel, QuerySpec, BHATTACHARYYA_FLOOR,
    KL_EPSILON,
};
use crate::signature::Aggregation;
use rayon::prelude::*;
use std::cmp::Ordering;

/// Histogram bins summed into one group of the bound table.
pub const GROUP_BINS: usize = 8;

/// The smallest first batch of exactly scored candidates (it doubles after each batch).
const FIRST_BATCH: usize = 256;

/// Group sums of every stored shape's histograms, contiguous, in the order of the prepared
/// array it was built from (kept in step by [`BoundTable::insert`], [`BoundTable::replace`],
/// [`BoundTable::remove`]).
#[derive(Clone, Debug, Default)]
pub struct BoundTable {
    /// Channel layout (names) every bounded shape shares; `None` until a shape with at least
    /// one histogram channel is added.
    layout: Option<Layout>,
    /// Number of shapes.
    len: usize,
    /// Per shape and channel: whether the group sums are valid (a histogram of `bins` bins).
    valid: Vec<bool>,
    /// Group sums of the densities, `[shape][channel][group]`.
    density: Vec<f64>,
    /// Group sums of the normalised probabilities.
    prob: Vec<f64>,
    /// Group sums of the cumulative probabilities.
    cdf: Vec<f64>,
}

#[derive(Clone, Debug, PartialEq)]
struct Layout {
    names: Vec<String>,
    bins: usize,
    groups: usize,
}

impl Layout {
    fn of(p: &Prepared) -> Option<Layout> {
        let bins = p.channels.iter().find_map(|c| match c {
            Some(PreparedChannel::Histogram(h)) => Some(h.density.len()),
            _ => None,
        })?;
        Some(Layout {
            names: p.names.clone(),
            bins,
            groups: bins.div_ceil(GROUP_BINS),
        })
    }

    fn stride(&self) -> usize {
        self.names.len() * self.groups
    }

    /// Bins in group `g`.
    fn width(&self, g: usize) -> f64 {
        (GROUP_BINS.min(self.bins - g * GROUP_BINS)) as f64
    }
}

/// Group sums of one histogram (`None` when it does not have `bins` bins).
fn group_sums(h: &Histogram, layout: &Layout) -> Option<[Vec<f64>; 3]> {
    if h.density.len() != layout.bins || h.prob.len() != layout.bins || h.cdf.len() != layout.bins {
        return None;
    }
    let sums = |v: &[f64]| -> Vec<f64> { v.chunks(GROUP_BINS).map(|c| c.iter().sum()).collect() };
    Some([sums(&h.density), sums(&h.prob), sums(&h.cdf)])
}

/// One shape's rows: (valid per channel, density, prob, cdf group sums).
type Rows = (Vec<bool>, Vec<f64>, Vec<f64>, Vec<f64>);

fn rows_of(p: &Prepared, layout: &Layout) -> Rows {
    let nch = layout.names.len();
    let mut rows = (
        vec![false; nch],
        vec![0.0; layout.stride()],
        vec![0.0; layout.stride()],
        vec![0.0; layout.stride()],
    );
    if p.names != layout.names {
        return rows;
    }
    for (c, ch) in p.channels.iter().enumerate() {
        let Some(PreparedChannel::Histogram(h)) = ch else {
            continue;
        };
        let Some([d, pr, cd]) = group_sums(h, layout) else {
            continue;
        };
        let r = c * layout.groups..(c + 1) * layout.groups;
        rows.0[c] = true;
        rows.1[r.clone()].copy_from_slice(&d);
        rows.2[r.clone()].copy_from_slice(&pr);
        rows.3[r].copy_from_slice(&cd);
    }
    rows
}

impl BoundTable {
    /// The table of `prepared` (in order).
    pub fn build(prepared: &[Prepared]) -> Self {
        let mut t = Self {
            layout: prepared.iter().find_map(Layout::of),
            ..Self::default()
        };
        let Some(layout) = t.layout.clone() else {
            t.len = prepared.len();
            return t;
        };
        let rows: Vec<Rows> = prepared.par_iter().map(|p| rows_of(p, &layout)).collect();
        for r in rows {
            t.valid.extend(r.0);
            t.density.extend(r.1);
            t.prob.extend(r.2);
            t.cdf.extend(r.3);
        }
        t.len = prepared.len();
        t
    }

    /// Number of shapes.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Inserts the group sums of `p` at position `at` (shifting the following shapes).
    pub fn insert(&mut self, at: usize, p: &Prepared) {
        assert!(at <= self.len, "insert position {at} > len {}", self.len);
        if self.layout.is_none() {
            self.layout = Layout::of(p);
            if let Some(l) = &self.layout {
                // Shapes added before any histogram existed have no valid sums.
                let n = self.len;
                self.valid = vec![false; n * l.names.len()];
                self.density = vec![0.0; n * l.stride()];
                self.prob = self.density.clone();
                self.cdf = self.density.clone();
            }
        }
        self.len += 1;
        let Some(layout) = &self.layout else {
            return;
        };
        let (v, d, pr, cd) = rows_of(p, layout);
        let nch = layout.names.len();
        let s = layout.stride();
        self.valid.splice(at * nch..at * nch, v);
        self.density.splice(at * s..at * s, d);
        self.prob.splice(at * s..at * s, pr);
        self.cdf.splice(at * s..at * s, cd);
    }

    /// Replaces the group sums at position `at`.
    pub fn replace(&mut self, at: usize, p: &Prepared) {
        assert!(at < self.len, "replace position {at} >= len {}", self.len);
        let Some(layout) = &self.layout else {
            // No layout yet: `p` may bring the first one.
            self.remove(at);
            self.insert(at, p);
            return;
        };
        let (v, d, pr, cd) = rows_of(p, layout);
        let nch = layout.names.len();
        let s = layout.stride();
        self.valid[at * nch..(at + 1) * nch].copy_from_slice(&v);
        self.density[at * s..(at + 1) * s].copy_from_slice(&d);
        self.prob[at * s..(at + 1) * s].copy_from_slice(&pr);
        self.cdf[at * s..(at + 1) * s].copy_from_slice(&cd);
    }

    /// Removes position `at`.
    pub fn remove(&mut self, at: usize) {
        assert!(at < self.len, "remove position {at} >= len {}", self.len);
        self.len -= 1;
        let Some(layout) = &self.layout else {
            return;
        };
        let nch = layout.names.len();
        let s = layout.stride();
        self.valid.drain(at * nch..(at + 1) * nch);
        self.density.drain(at * s..(at + 1) * s);
        self.prob.drain(at * s..(at + 1) * s);
        self.cdf.drain(at * s..(at + 1) * s);
    }

    /// The `k` best of `candidates` (which must be the array the table was built from) for
    /// `query` under `q`, among positions passing `keep`: `(position, score)`, best first,
    /// equal to the first `k` entries of [`ranking::rank`] filtered by `keep`.
    pub fn top_k(
        &self,
        query: &Prepared,
        candidates: &[Prepared],
        q: &QuerySpec,
        k: usize,
        keep: &(dyn Fn(usize) -> bool + Sync),
    ) -> Vec<(usize, f64)> {
        self.top_k_counted(query, candidates, q, k, keep).0
    }

    /// [`BoundTable::top_k`], also returning how many candidates were scored exactly.
    pub fn top_k_counted(
        &self,
        query: &Prepared,
        candidates: &[Prepared],
        q: &QuerySpec,
        k: usize,
        keep: &(dyn Fn(usize) -> bool + Sync),
    ) -> (Vec<(usize, f64)>, usize) {
        self.search(query, candidates, q, k, keep, FIRST_BATCH.max(4 * k))
    }

    /// The filter-and-refine loop; `first_batch` candidates (by bound) are scored first, then
    /// twice as many per round until the bounds exceed the `k`-th score.
    fn search(
        &self,
        query: &Prepared,
        candidates: &[Prepared],
        q: &QuerySpec,
        k: usize,
        keep: &(dyn Fn(usize) -> bool + Sync),
        first_batch: usize,
    ) -> (Vec<(usize, f64)>, usize) {
        if k == 0 || candidates.is_empty() {
            return (Vec::new(), 0);
        }
        let exact = ranking::Scorer::new(query, q);
        let bounder = match (&self.layout, self.len == candidates.len()) {
            (Some(layout), true) => QueryBounds::new(query, q, layout),
            _ => None,
        };
        let Some(bounder) = bounder else {
            // Nothing to bound with: the full ranking.
            let all: Vec<(usize, f64)> = ranking::rank(query, candidates, q)
                .into_iter()
                .filter(|&(i, _)| keep(i))
                .take(k)
                .collect();
            return (all, candidates.len());
        };
        let mut bounds: Vec<(f64, usize)> = (0..candidates.len())
            .into_par_iter()
            .filter(|&i| keep(i))
            .map(|i| (bounder.bound(self, i), i))
            .collect();
        let by_bound = |a: &(f64, usize), b: &(f64, usize)| -> Ordering {
            a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
        };
        let mut best: Vec<(usize, f64)> = Vec::with_capacity(2 * k);
        let mut scored = 0;
        let mut rest: &mut [(f64, usize)] = &mut bounds;
        let mut batch = first_batch.max(1);
        while !rest.is_empty() {
            let take = batch.min(rest.len());
            if take < rest.len() {
                rest.select_nth_unstable_by(take - 1, by_bound);
            }
            let (head, tail) = rest.split_at_mut(take);
            // Every candidate left after `head` has a bound ≥ every bound in `head`.
            let cutoff = match best.get(k - 1) {
                Some(&(_, s)) if !s.is_nan() => s,
                _ => f64::INFINITY,
            };
            let todo: Vec<usize> = head
                .iter()
                .filter(|&&(b, _)| b <= cutoff)
                .map(|&(_, i)| i)
                .collect();
            if todo.is_empty() {
                break;
            }
            scored += todo.len();
            let mut new: Vec<(usize, f64)> = todo
                .par_iter()
                .map(|&i| (i, exact.score(&candidates[i])))
                .collect();
            best.append(&mut new);
            best.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
            best.truncate(k);
            rest = tail;
            batch = batch.saturating_mul(2);
        }
        (best, scored)
    }
}

/// One compared channel of the query: its index in the layout, its group sums
/// `[density, prob, cdf]` and its bin width.
type QueryChannel = (usize, [Vec<f64>; 3], f64);

/// The query's side of the bounds: its group sums for the channels the spec compares.
struct QueryBounds {
    d: Dissimilarity,
    aggregation: Aggregation,
    /// Per compared channel, `None` when the query cannot be bounded on it (bound 0).
    channels: Vec<Option<QueryChannel>>,
    groups: usize,
    nch: usize,
    widths: Vec<f64>,
}

impl QueryBounds {
    fn new(query: &Prepared, q: &QuerySpec, layout: &Layout) -> Option<Self> {
        if query.names != layout.names {
            return None;
        }
        let names = ranking::compared_channels(q);
        if names.is_empty() {
            return None;
        }
        let channels = names
            .iter()
            .map(|n| {
                let c = layout.names.iter().position(|x| x == n)?;
                match &query.channels[c] {
                    Some(PreparedChannel::Histogram(h)) => {
                        group_sums(h, layout).map(|s| (c, s, h.bin_width))
                    }
                    _ => None,
                }
            })
            .collect();
        Some(Self {
            d: q.dissimilarity,
            aggregation: q.aggregation,
            channels,
            groups: layout.groups,
            nch: layout.names.len(),
            widths: (0..layout.groups).map(|g| layout.width(g)).collect(),
        })
    }

    /// A lower bound of the exact score of candidate `i`.
    fn bound(&self, t: &BoundTable, i: usize) -> f64 {
        let b = self.aggregation.apply(self.channels.iter().map(|ch| {
            let Some((c, sums, h)) = ch else {
                return 0.0;
            };
            if !t.valid[i * self.nch + c] {
                return 0.0;
            }
            let at = (i * self.nch + c) * self.groups;
            let r = at..at + self.groups;
            let v = channel_bound(
                self.d,
                sums,
                [&t.density[r.clone()], &t.prob[r.clone()], &t.cdf[r]],
                *h,
                &self.widths,
            );
            if v.is_nan() {
                0.0
            } else {
                v
            }
        }));
        with_margin(b)
    }
}

/// Lowers a bound by a relative 10⁻⁹ and an absolute 10⁻¹² (rounding of the group sums); NaN
/// and negative values become 0.
fn with_margin(b: f64) -> f64 {
    if b.is_nan() || b <= 0.0 {
        0.0
    } else {
        (b * (1.0 - 1e-9) - 1e-12).max(0.0)
    }
}

/// Lower bound of dissimilarity `d` from group sums `a` (query) and `b` (candidate):
/// `[density, prob, cdf]`, bin width `h`, bins per group `w` (see the module docs).
fn channel_bound(d: Dissimilarity, a: &[Vec<f64>; 3], b: [&[f64]; 3], h: f64, w: &[f64]) -> f64 {
    let pairs = |k: usize| a[k].iter().zip(b[k]).zip(w).map(|((x, y), w)| (*x, *y, *w));
    match d {
        Dissimilarity::L1 => pairs(0).map(|(x, y, _)| (x - y).abs()).sum::<f64>() * h,
        Dissimilarity::L2 => (pairs(0).map(|(x, y, w)| (x - y) * (x - y) / w).sum::<f64>() * h)
            .max(0.0)
            .sqrt(),
        Dissimilarity::LInf => pairs(0)
            .map(|(x, y, w)| (x - y).abs() / w)
            .fold(0.0, f64::max),
        Dissimilarity::NL1 => pairs(1).map(|(x, y, _)| (x - y).abs()).sum(),
        Dissimilarity::NL2 => {
            if h > 0.0 {
                (pairs(1).map(|(x, y, w)| (x - y) * (x - y) / w).sum::<f64>() / h).sqrt()
            } else {
                0.0
            }
        }
        Dissimilarity::KL => pairs(1)
            .map(|(x, y, w)| {
                let e = w * KL_EPSILON;
                (x - y) * ((x + e).ln() - (y + e).ln())
            })
            .sum::<f64>()
            .max(0.0),
        Dissimilarity::Bhattacharyya => {
            let bc: f64 = pairs(1).map(|(x, y, _)| (x * y).max(0.0).sqrt()).sum();
            -(bc.clamp(BHATTACHARYYA_FLOOR, 1.0)).ln()
        }
        Dissimilarity::Chi2 => {
            2.0 * pairs(1)
                .map(|(x, y, _)| {
                    if x + y > 0.0 {
                        (x - y) * (x - y) / (x + y)
                    } else {
                        0.0
                    }
                })
                .sum::<f64>()
        }
        Dissimilarity::Emd => pairs(2).map(|(x, y, _)| (x - y).abs()).sum::<f64>() * h,
    }
}

#[cfg(test)]
#[path = "topk_tests.rs"]
mod tests;
