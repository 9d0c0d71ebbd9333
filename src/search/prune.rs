//! Exact top-k over a [`Corpus`] by filter-and-refine.
//!
//! Scoring a candidate exactly reads all its counts (`bins` per channel). The corpus also keeps
//! every histogram's sums over groups of [`GROUP_BINS`] bins, from which a **lower bound** of
//! each of the nine dissimilarities follows (the GEMINI scheme of Faloutsos et al. 1994, with
//! a bound specific to each dissimilarity). The bounds of every candidate are computed in one
//! pass over the group sums; candidates are then scored exactly in order of increasing bound,
//! and the scan stops as soon as the `k`-th best exact score is below every remaining bound.
//!
//! The result is **exactly** the head of [`rank_all`] restricted to the kept candidates: the
//! same scores bit for bit (the exact score is [`Query::score`]) and the same order (score by
//! `f64::total_cmp`, ties by position). Candidates whose bound ties the `k`-th score are always
//! scored, so ties are resolved as the full ranking resolves them.
//!
//! # The bounds
//!
//! For a group `g` of `w` bins write `X_g = Σ_{b∈g} x_b` (the counts `a`, `b`; `T` their total,
//! `M` the masses, `h` the bin width):
//!
//! | dissimilarity | lower bound | why |
//! |---|---|---|
//! | nL1 | `Σ_g |A_g − B_g| / T` | triangle inequality (integers: exact) |
//! | nL2 | `(Σ_g (A_g − B_g)²/w / T² / h)^{1/2}` | Cauchy–Schwarz: `(Σ_{b∈g} x_b)² ≤ w Σ x_b²` |
//! | EMD | `Σ_g |ΣA_{≤g} − ΣB_{≤g}| / T · h` | the running sums at the groups' last bins are a subset of the terms |
//! | L1 | `Σ_g |M_a A_g − M_b B_g| / T` | triangle inequality |
//! | L2 | `(Σ_g (M_a A_g − M_b B_g)²/w / T² / h)^{1/2}` | Cauchy–Schwarz |
//! | L∞ | `max_g |M_a A_g − M_b B_g| / w / T / h` | a group's mean is at most its max |
//! | KL | `Σ_g (P_g − Q_g)(ln(P_g + wε) − ln(Q_g + wε))` | `(x − y)(ln x − ln y)` is the perspective of a convex function, hence subadditive |
//! | Bhattacharyya | `−ln clamp(Σ_g (A_g B_g)^{1/2} / T)` | Cauchy–Schwarz |
//! | χ² | `2 Σ_g (A_g − B_g)² / (A_g + B_g) / T` | Sedrakyan: `(Σ x)² / Σ y ≤ Σ x² / y` |
//!
//! Every aggregation (single, sum, sum of squares, max) is non-decreasing in each non-negative
//! argument, so aggregating the channel bounds bounds the aggregated score. A channel the
//! bounds cannot use (a vector channel, a channel absent from the query or the candidate)
//! contributes 0. Each bound is finally lowered by a relative 10⁻⁹ and an absolute 10⁻¹² so
//! that rounding can never make it exceed the exact score.

use super::corpus::{Corpus, ShapeRef, Slot, GROUP_BINS, TOTAL};
use super::score::Query;
use crate::ranking::{Dissimilarity, BHATTACHARYYA_FLOOR, KL_EPSILON};
use rayon::prelude::*;
use std::cmp::Ordering;

/// The smallest first batch of exactly scored candidates (it doubles after each batch).
const FIRST_BATCH: usize = 256;

/// Scores `query` against every shape of `corpus` (in parallel): `(position, score)` sorted by
/// increasing score, ties by position.
pub fn rank_all(corpus: &Corpus, q: &Query, query: ShapeRef<'_>) -> Vec<(usize, f64)> {
    let layout = corpus.layout();
    let mut out: Vec<(usize, f64)> = (0..corpus.len())
        .into_par_iter()
        .map(|i| (i, q.score(layout, query, corpus.shape(i))))
        .collect();
    out.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    out
}

/// The `k` best shapes of `corpus` for `query` among positions passing `keep`: `(position,
/// score)`, best first, equal to the first `k` entries of [`rank_all`] filtered by `keep`;
/// also returns how many candidates were scored exactly.
pub fn top_k(
    corpus: &Corpus,
    q: &Query,
    query: ShapeRef<'_>,
    k: usize,
    keep: &(dyn Fn(usize) -> bool + Sync),
) -> (Vec<(usize, f64)>, usize) {
    search(corpus, q, query, k, keep, FIRST_BATCH.max(4 * k))
}

/// The filter-and-refine loop; `first_batch` candidates (by bound) are scored first, then
/// twice as many per round until the bounds exceed the `k`-th score.
pub(crate) fn search(
    corpus: &Corpus,
    q: &Query,
    query: ShapeRef<'_>,
    k: usize,
    keep: &(dyn Fn(usize) -> bool + Sync),
    first_batch: usize,
) -> (Vec<(usize, f64)>, usize) {
    if k == 0 || corpus.is_empty() {
        return (Vec::new(), 0);
    }
    let layout = corpus.layout();
    let bounder = Bounder::new(corpus, q, query);
    let mut bounds: Vec<(f64, u32)> = (0..corpus.len())
        .into_par_iter()
        .with_min_len(4096)
        .filter(|&i| keep(i))
        .map(|i| (bounder.bound(i), i as u32))
        .collect();
    let by_bound =
        |a: &(f64, u32), b: &(f64, u32)| -> Ordering { a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)) };
    let mut best: Vec<(usize, f64)> = Vec::with_capacity(2 * k);
    let mut scored = 0;
    let mut rest: &mut [(f64, u32)] = &mut bounds;
    let mut batch = first_batch.max(1);
    while !rest.is_empty() {
        let take = batch.min(rest.len());
        if take < rest.len() {
            rest.select_nth_unstable_by(take - 1, by_bound);
        }
        let (head, tail) = rest.split_at_mut(take);
        // Every candidate left in `tail` has a bound ≥ every bound in `head`.
        let cutoff = kth(&best, k);
        let todo: Vec<usize> = head
            .iter()
            .filter(|&&(b, _)| b <= cutoff)
            .map(|&(_, i)| i as usize)
            .collect();
        if todo.is_empty() {
            break;
        }
        scored += todo.len();
        let mut new: Vec<(usize, f64)> = todo
            .par_iter()
            .with_min_len(64)
            .map(|&i| (i, q.score(layout, query, corpus.shape(i))))
            .collect();
        best.append(&mut new);
        best.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        best.truncate(k);
        // Candidates bounded above the new k-th score can never enter: drop them now, so that
        // the next selection runs over the few that remain.
        let cutoff = kth(&best, k);
        rest = keep_at_most(tail, cutoff);
        batch = batch.saturating_mul(2);
    }
    (best, scored)
}

/// The `k`-th best score so far (∞ while fewer than `k`, or when it is NaN).
fn kth(best: &[(usize, f64)], k: usize) -> f64 {
    match best.get(k - 1) {
        Some(&(_, s)) if !s.is_nan() => s,
        _ => f64::INFINITY,
    }
}

/// Moves the entries with bound ≤ `cutoff` to the front and returns them.
fn keep_at_most(v: &mut [(f64, u32)], cutoff: f64) -> &mut [(f64, u32)] {
    if cutoff == f64::INFINITY {
        return v;
    }
    let mut n = 0;
    for i in 0..v.len() {
        if v[i].0 <= cutoff {
            v.swap(n, i);
            n += 1;
        }
    }
    &mut v[..n]
}

/// One compared channel of the query: histogram slot, its group sums and mass, bin width.
struct QueryChannel {
    slot: usize,
    groups: Vec<u16>,
    mass: f64,
    h: f64,
}

/// The query's side of the bounds.
pub(crate) struct Bounder<'a> {
    corpus: &'a Corpus,
    q: &'a Query,
    /// Per compared channel, `None` when it cannot be bounded (bound 0).
    channels: Vec<Option<QueryChannel>>,
    /// Group sums per shape (histogram channels × groups).
    stride: usize,
}

impl<'a> Bounder<'a> {
    pub(crate) fn new(corpus: &'a Corpus, q: &'a Query, query: ShapeRef<'_>) -> Bounder<'a> {
        let l = corpus.layout();
        let channels = q
            .channels
            .iter()
            .map(|c| {
                let c = (*c)?;
                match l.slots[c] {
                    Slot::Histogram(k) if query.present[c] => Some(QueryChannel {
                        slot: k,
                        groups: query.groups[k * l.groups..(k + 1) * l.groups].to_vec(),
                        mass: query.mass[k],
                        h: l.bin_width[k],
                    }),
                    _ => None,
                }
            })
            .collect();
        Bounder {
            corpus,
            q,
            channels,
            stride: l.histograms() * l.groups,
        }
    }

    /// A lower bound of the exact score of candidate `i`. A candidate lacking a compared
    /// channel scores ∞, so its (zero) group sums may enter the bound: no presence check.
    pub(crate) fn bound(&self, i: usize) -> f64 {
        let l = self.corpus.layout();
        let gs = l.groups;
        let row = &self.corpus.all_groups()[i * self.stride..(i + 1) * self.stride];
        let d = self.q.dissimilarity;
        let b = self
            .q
            .aggregation
            .apply(self.channels.iter().map(|ch| match ch {
                Some(qc) => {
                    let g = &row[qc.slot * gs..(qc.slot + 1) * gs];
                    if d == Dissimilarity::NL1 {
                        // The common case, as one integer loop.
                        let s: u32 = qc
                            .groups
                            .iter()
                            .zip(g)
                            .map(|(&x, &y)| (x as i32 - y as i32).unsigned_abs())
                            .sum();
                        s as f64 / TOTAL as f64
                    } else {
                        let v = channel_bound(
                            d,
                            &qc.groups,
                            qc.mass,
                            g,
                            self.corpus.mass_of(i, qc.slot),
                            qc.h,
                            l.bins,
                        );
                        if v.is_nan() {
                            0.0
                        } else {
                            v
                        }
                    }
                }
                None => 0.0,
            }));
        with_margin(b)
    }
}

/// Lowers a bound by a relative 10⁻⁹ and an absolute 10⁻¹²; NaN and negative values become 0.
pub(crate) fn with_margin(b: f64) -> f64 {
    if b.is_nan() || b <= 0.0 {
        0.0
    } else {
        (b * (1.0 - 1e-9) - 1e-12).max(0.0)
    }
}

/// Lower bound of dissimilarity `d` from the group sums `a` (query, mass `ma`) and `b`
/// (candidate, mass `mb`), bin width `h`, `bins` bins (see the module docs).
pub(crate) fn channel_bound(
    d: Dissimilarity,
    a: &[u16],
    ma: f64,
    b: &[u16],
    mb: f64,
    h: f64,
    bins: usize,
) -> f64 {
    let t = TOTAL as f64;
    let w = |g: usize| GROUP_BINS.min(bins - g * GROUP_BINS) as f64;
    let pairs = || a.iter().zip(b).map(|(&x, &y)| (x as i64, y as i64));
    let (fa, fb) = (ma / t, mb / t);
    let dens = || {
        a.iter()
            .zip(b)
            .map(move |(&x, &y)| (fa * x as f64 - fb * y as f64).abs())
    };
    match d {
        Dissimilarity::NL1 => pairs().map(|(x, y)| (x - y).unsigned_abs()).sum::<u64>() as f64 / t,
        Dissimilarity::NL2 => {
            if h > 0.0 {
                let s: f64 = pairs()
                    .enumerate()
                    .map(|(g, (x, y))| ((x - y) * (x - y)) as f64 / w(g))
                    .sum();
                (s / (t * t) / h).sqrt()
            } else {
                0.0
            }
        }
        Dissimilarity::Emd => {
            let (mut ca, mut cb, mut s) = (0i64, 0i64, 0u64);
            for (x, y) in pairs() {
                ca += x;
                cb += y;
                s += (ca - cb).unsigned_abs();
            }
            s as f64 / t * h
        }
        Dissimilarity::L1 => dens().sum(),
        Dissimilarity::L2 => {
            if h > 0.0 {
                (dens().enumerate().map(|(g, v)| v * v / w(g)).sum::<f64>() / h).sqrt()
            } else {
                0.0
            }
        }
        Dissimilarity::LInf => {
            if h > 0.0 {
                dens()
                    .enumerate()
                    .map(|(g, v)| v / w(g))
                    .fold(0.0, f64::max)
                    / h
            } else {
                0.0
            }
        }
        Dissimilarity::KL => pairs()
            .enumerate()
            .map(|(g, (x, y))| {
                let e = w(g) * KL_EPSILON;
                let (p, q) = (x as f64 / t, y as f64 / t);
                (p - q) * ((p + e).ln() - (q + e).ln())
            })
            .sum::<f64>()
            .max(0.0),
        Dissimilarity::Bhattacharyya => {
            let bc = pairs().map(|(x, y)| ((x * y) as f64).sqrt()).sum::<f64>() / t;
            -(bc.clamp(BHATTACHARYYA_FLOOR, 1.0)).ln()
        }
        Dissimilarity::Chi2 => {
            2.0 * pairs()
                .map(|(x, y)| {
                    if x + y > 0 {
                        ((x - y) * (x - y)) as f64 / (x + y) as f64
                    } else {
                        0.0
                    }
                })
                .sum::<f64>()
                / t
        }
    }
}
