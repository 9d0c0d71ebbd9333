//! Exact top-k over a [`Corpus`] by filter-and-refine.
//!
//! Scoring a candidate exactly reads all its counts (`bins` per channel). The corpus also keeps
//! every histogram's sums over [`GROUPS`](super::corpus::GROUPS) groups of adjacent bins, from
//! which a **lower bound** of each of the nine dissimilarities follows (the GEMINI scheme of
//! Faloutsos et al. 1994, with a bound specific to each dissimilarity). The bounds of every
//! candidate are computed in one pass over the group sums (two for a query with a second cut
//! version, below); candidates are then scored exactly in order of increasing bound, and the scan
//! stops as soon as the `k`-th best exact score is below every remaining bound.
//!
//! The result is **exactly** the head of [`rank_all`] restricted to the kept candidates: the
//! same scores bit for bit (the exact score is [`Query::score`]) and the same order (score by
//! `f64::total_cmp`, ties by position). Candidates whose bound ties the `k`-th score are always
//! scored, so ties are resolved as the full ranking resolves them.
//!
//! # The bounds
//!
//! For a group `g` of `w` bins write `X_g = Σ_{b∈g} x_b` (the counts `a`, `b` brought to the
//! corpus's common scale, exact integers: see [`super::corpus`]; `T` their total, `M` the masses,
//! `h` the bin width):
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
//! A **vector channel** (ShapeDNA's eigenvalues) is bounded the same way from the sums of its
//! values over [`VECTOR_GROUPS`] groups (`vector_bound`: L1 and nL1 `Σ_g |A_g − B_g|`, L∞
//! `max_g |A_g − B_g| / w_g`, the Euclidean distance `(Σ_g (A_g − B_g)²/w_g)^{1/2}`, each gap
//! lowered by an allowance for the sums' `f32` rounding). Without it a query whose eigenvalues
//! are far from every stored shape's (a shape uploaded at another scale) would bound nothing
//! and score most of the corpus exactly (`bench search --query-scale 1.3` at 10⁶: 835 391
//! candidates scored per query, 1.24 s; with it 4 746, 43 ms).
//!
//! Every aggregation (single, sum, sum of squares, max) is non-decreasing in each non-negative
//! argument, so aggregating the channel bounds bounds the aggregated score. A channel absent
//! from the query contributes 0 (a candidate lacking a compared channel scores ∞). Each bound
//! is finally lowered by a relative 10⁻⁹ and an absolute 10⁻¹² so that rounding can never make
//! it exceed the exact score.
//!
//! **Second cut versions** ([`Query::score`] = `min(D₁, f · D₂)` for a pair of which either
//! shape has one): the bound is `min(B₁, f · B₂)`, `B₁` the first versions' bound and `B₂` that
//! of the second pair — the query's second version (or its first) against the candidate's
//! first version, in a second pass over the group sums when the query has a second version, or
//! against the candidate's second version for a candidate that has one (the shapes whose short
//! loops the first cut leaves). Second versions are kept in position order, so those of a chunk
//! of positions are consecutive rows: under nL1 their bounds are the same integer loop over
//! those rows as the first versions' (one pass over the group sums of every version).

use super::corpus::{
    total_at, vector_group_width, Corpus, Layout, ShapeRef, Slot, VersionRef, MAX_SHIFT,
    VECTOR_GROUPS,
};
use super::score::Query;
use crate::ranking::{Dissimilarity, BHATTACHARYYA_FLOOR, KL_EPSILON};
use crate::signature::Aggregation;
use rayon::prelude::*;
use std::cmp::Ordering;
use std::collections::BinaryHeap;

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
    search(
        corpus,
        q,
        query,
        k,
        keep,
        FIRST_BATCH.max(k.saturating_mul(4)),
    )
}

/// The filter-and-refine loop.
///
/// 1. One parallel pass over the group sums computes every kept candidate's bound (into one
///    `f64` per position; NaN for a position `keep` rejects) and, per worker, the `first_batch`
///    candidates of smallest bound (a bounded max-heap: most candidates are rejected by one
///    comparison). The heaps merged give the `first_batch` smallest bounds overall.
/// 2. Those are scored exactly; the `k`-th best score `τ` is a valid cut-off: a candidate
///    bounded above `τ` can never enter. A second parallel pass collects the candidates with a
///    bound `≤ τ` that were not scored yet.
/// 3. They are scored in batches of increasing bound (doubling), `τ` tightening after each
///    batch, until every remaining bound exceeds `τ`.
pub(crate) fn search(
    corpus: &Corpus,
    q: &Query,
    query: ShapeRef<'_>,
    k: usize,
    keep: &(dyn Fn(usize) -> bool + Sync),
    first_batch: usize,
) -> (Vec<(usize, f64)>, usize) {
    // More than the corpus holds is the whole corpus (a shard request may name any `k`; the
    // buffers below are sized by it).
    let k = k.min(corpus.len());
    if k == 0 {
        return (Vec::new(), 0);
    }
    let bounder = Bounder::new(corpus, q, query);
    let first_batch = first_batch.max(k).max(1);
    let mut bounds = vec![f64::INFINITY; corpus.len()];
    // Pass 1: every bound, and the `first_batch` smallest of each worker.
    let heaps: Vec<BinaryHeap<Cand>> = bounds
        .par_chunks_mut(CHUNK)
        .enumerate()
        .fold(BinaryHeap::new, |mut heap, (c, chunk)| {
            let base = c * CHUNK;
            bounder.fill(base, chunk, keep);
            for (j, &b) in chunk.iter().enumerate() {
                if b.is_nan() {
                    continue; // not kept
                }
                let cand = Cand(b, (base + j) as u32);
                if heap.len() < first_batch {
                    heap.push(cand);
                } else if cand < *heap.peek().expect("non-empty") {
                    heap.pop();
                    heap.push(cand);
                }
            }
            heap
        })
        .collect();
    let mut head: Vec<Cand> = heaps.into_iter().flatten().collect();
    head.sort_unstable();
    head.truncate(first_batch);
    let mut best: Vec<(usize, f64)> = Vec::with_capacity(2 * k);
    let mut scored = 0;
    score_into(corpus, q, query, &head, &mut best, k, &mut scored);
    // Pass 2: the candidates that can still enter, not yet scored (none when every kept
    // candidate was in the head). `NaN` (not kept) fails `b <= cutoff`.
    let cutoff = kth(&best, k);
    let mut rest: Vec<Cand> = match head.last() {
        Some(&last) if head.len() == first_batch => bounds
            .par_iter()
            .enumerate()
            .with_min_len(CHUNK)
            .filter(|&(i, &b)| b <= cutoff && Cand(b, i as u32) > last)
            .map(|(i, &b)| Cand(b, i as u32))
            .collect(),
        _ => Vec::new(),
    };
    let mut rest: &mut [Cand] = &mut rest;
    let mut batch = first_batch.saturating_mul(2);
    while !rest.is_empty() {
        let cutoff = kth(&best, k);
        rest = keep_at_most(rest, cutoff);
        if rest.is_empty() {
            break;
        }
        let take = batch.min(rest.len());
        if take < rest.len() {
            rest.select_nth_unstable(take - 1);
        }
        let (now, tail) = rest.split_at_mut(take);
        // Every candidate left in `tail` has a bound ≥ every bound in `now`.
        score_into(corpus, q, query, now, &mut best, k, &mut scored);
        rest = tail;
        batch = batch.saturating_mul(2);
    }
    (best, scored)
}

/// Positions per work item of the bound pass.
const CHUNK: usize = 4096;

/// A candidate: its bound and position, ordered by bound (`total_cmp`), ties by position.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Cand(f64, u32);
impl Eq for Cand {}
impl PartialOrd for Cand {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Cand {
    fn cmp(&self, other: &Self) -> Ordering {
        self.0.total_cmp(&other.0).then(self.1.cmp(&other.1))
    }
}

/// Scores the candidates of `todo` whose bound is at most the current `k`-th score, merges
/// them into `best` (kept sorted, at most `k`), and counts them in `scored`.
fn score_into(
    corpus: &Corpus,
    q: &Query,
    query: ShapeRef<'_>,
    todo: &[Cand],
    best: &mut Vec<(usize, f64)>,
    k: usize,
    scored: &mut usize,
) {
    let cutoff = kth(best, k);
    let todo: Vec<usize> = todo
        .iter()
        .filter(|c| c.0 <= cutoff)
        .map(|c| c.1 as usize)
        .collect();
    if todo.is_empty() {
        return;
    }
    *scored += todo.len();
    let layout = corpus.layout();
    let mut new: Vec<(usize, f64)> = todo
        .par_iter()
        .with_min_len(64)
        .map(|&i| (i, q.score(layout, query, corpus.shape(i))))
        .collect();
    best.append(&mut new);
    best.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    best.truncate(k);
}

/// The `k`-th best score so far (∞ while fewer than `k`, or when it is NaN).
fn kth(best: &[(usize, f64)], k: usize) -> f64 {
    match best.get(k - 1) {
        Some(&(_, s)) if !s.is_nan() => s,
        _ => f64::INFINITY,
    }
}

/// Moves the entries with bound ≤ `cutoff` to the front and returns them.
fn keep_at_most(v: &mut [Cand], cutoff: f64) -> &mut [Cand] {
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

/// One compared channel of the query, as the bounds read it.
enum QueryChannel {
    /// Histogram slot, its group sums and mass, bin width.
    Histogram {
        slot: usize,
        groups: Vec<u32>,
        mass: f64,
        h: f64,
    },
    /// Vector slot, its group sums, the vector's length.
    Vector {
        slot: usize,
        groups: [f32; VECTOR_GROUPS],
        len: usize,
    },
}

/// nL1 under a sum (or a single channel), every compared histogram channel at most once: the
/// query's group sums over the whole row and the ranges of the row that are compared, so that
/// the histograms' bound is one integer loop per range, `Σ_j |q_j − c_j| / T_max`, plus the
/// compared vector channels' bounds (offset in the row of vector group sums, query's sums).
struct Nl1Row {
    row: Vec<u32>,
    ranges: Vec<std::ops::Range<usize>>,
    vectors: Vec<(usize, [f32; VECTOR_GROUPS])>,
}

/// The query's side of the bounds.
pub(crate) struct Bounder<'a> {
    corpus: &'a Corpus,
    q: &'a Query,
    /// Per compared channel, `None` when it cannot be bounded (bound 0).
    channels: Vec<Option<QueryChannel>>,
    /// Group sums per shape (histogram channels × groups).
    stride: usize,
    /// Vector group sums per shape (vector channels × [`VECTOR_GROUPS`]).
    vstride: usize,
    /// The nL1 fast path, where it applies.
    nl1_row: Option<Nl1Row>,
    /// The bounds of the query's second version, if it has one.
    second: Option<Box<Bounder<'a>>>,
}

impl<'a> Bounder<'a> {
    pub(crate) fn new(corpus: &'a Corpus, q: &'a Query, query: ShapeRef<'_>) -> Bounder<'a> {
        let l = corpus.layout();
        let channels: Vec<Option<QueryChannel>> = q
            .channels
            .iter()
            .map(|c| {
                let c = (*c)?;
                if !query.present[c] {
                    return None;
                }
                Some(match l.slots[c] {
                    Slot::Histogram(k) => QueryChannel::Histogram {
                        slot: k,
                        groups: query.groups[k * l.groups..(k + 1) * l.groups].to_vec(),
                        mass: query.mass[k],
                        h: l.bin_width[k],
                    },
                    Slot::Vector(k) => QueryChannel::Vector {
                        slot: k,
                        groups: query.vgroups[k * VECTOR_GROUPS..(k + 1) * VECTOR_GROUPS]
                            .try_into()
                            .expect("VECTOR_GROUPS sums per vector channel"),
                        len: query.vectors[k].len(),
                    },
                })
            })
            .collect();
        let stride = l.histograms() * l.groups;
        let summed: Option<Vec<&Option<QueryChannel>>> = match q.aggregation {
            Aggregation::Sum => Some(channels.iter().collect()),
            Aggregation::Single => Some(channels.iter().take(1).collect()),
            _ => None,
        };
        let nl1_row = match summed {
            // A row sums within `u32`: entries below 2^24 (scale 2^MAX_SHIFT ≤ 2^8), ≤ 255 of them.
            // A layout of vector channels only (no group sums) takes the general path.
            Some(used) if q.dissimilarity == Dissimilarity::NL1 && (1..=255).contains(&stride) => {
                let mut row = vec![0u32; stride];
                let (mut slots, mut vectors) = (Vec::new(), Vec::new());
                for qc in used.into_iter().flatten() {
                    match qc {
                        QueryChannel::Histogram { slot, groups, .. } => {
                            row[slot * l.groups..(slot + 1) * l.groups].copy_from_slice(groups);
                            slots.push(*slot);
                        }
                        // A vector channel compared twice counts twice, as in the sum.
                        QueryChannel::Vector { slot, groups, .. } => {
                            vectors.push((slot * VECTOR_GROUPS, *groups))
                        }
                    }
                }
                slots.sort_unstable();
                let n = slots.len();
                slots.dedup();
                (slots.len() == n).then(|| {
                    let mut ranges: Vec<std::ops::Range<usize>> = Vec::new();
                    for k in slots {
                        let r = k * l.groups..(k + 1) * l.groups;
                        match ranges.last_mut() {
                            Some(last) if last.end == r.start => last.end = r.end,
                            _ => ranges.push(r),
                        }
                    }
                    Nl1Row {
                        row,
                        ranges,
                        vectors,
                    }
                })
            }
            _ => None,
        };
        Bounder {
            corpus,
            q,
            channels,
            stride,
            vstride: l.vectors() * VECTOR_GROUPS,
            nl1_row,
            second: query
                .alt
                .map(|_| Box::new(Bounder::new(corpus, q, query.second()))),
        }
    }

    /// Writes the bound of every position `base + j` into `out[j]`, or NaN where `keep`
    /// rejects the position (second versions: module docs).
    pub(crate) fn fill(&self, base: usize, out: &mut [f64], keep: &(dyn Fn(usize) -> bool + Sync)) {
        self.fill_first(base, out, keep);
        let f = self.q.alternate_margin;
        // A candidate with a second version: its second pair is (the query's second version, or
        // its first, against the candidate's second), bounded from the candidate's own group
        // sums; kept with its first pair's bound before the query's second version is applied.
        let query_second = self.second.as_deref().unwrap_or(self);
        let with_alt: Vec<(usize, f64)> = match &query_second.nl1_row {
            // The common case: one loop over the second versions' contiguous rows.
            Some(nl1) => {
                let (at, rows, vrows) = self.corpus.alt_groups_in(base..base + out.len());
                let mut second = vec![0.0; at.len()];
                let rows = GroupRows {
                    groups: rows,
                    stride: self.stride,
                    vgroups: vrows,
                    vstride: self.vstride,
                };
                nl1_rows(&rows, nl1, 0, &mut second, &|_| true);
                at.into_iter()
                    .zip(second)
                    .filter(|&(i, _)| !out[i - base].is_nan())
                    .map(|(i, second)| (i, out[i - base].min(f * second)))
                    .collect()
            }
            None => self
                .corpus
                .alts_in(base..base + out.len())
                .filter(|&i| !out[i - base].is_nan())
                .map(|i| {
                    let alt = self.corpus.alt(i).expect("listed with a second version");
                    let second = query_second.bound_against(alt);
                    (i, out[i - base].min(f * second))
                })
                .collect(),
        };
        if let Some(second) = &self.second {
            let mut other = vec![0.0; out.len()];
            second.fill_first(base, &mut other, keep);
            for (o, b) in out.iter_mut().zip(other) {
                *o = o.min(f * b); // NaN (not kept) stays NaN
            }
        }
        for (i, b) in with_alt {
            out[i - base] = b;
        }
    }

    /// [`Bounder::fill`] of this version of the query against the candidates' first versions.
    fn fill_first(&self, base: usize, out: &mut [f64], keep: &(dyn Fn(usize) -> bool + Sync)) {
        match &self.nl1_row {
            Some(nl1) => {
                let end = base + out.len();
                let rows = GroupRows {
                    groups: &self.corpus.all_groups()[base * self.stride..end * self.stride],
                    stride: self.stride,
                    vgroups: &self.corpus.all_vgroups()[base * self.vstride..end * self.vstride],
                    vstride: self.vstride,
                };
                nl1_rows(&rows, nl1, base, out, keep);
            }
            None => {
                for (j, o) in out.iter_mut().enumerate() {
                    *o = if keep(base + j) {
                        self.first_bound(base + j)
                    } else {
                        f64::NAN
                    };
                }
            }
        }
    }

    /// A lower bound of the first versions' score `D₁` of candidate `i`. A candidate lacking a
    /// compared channel scores ∞, so its (zero) group sums may enter the bound: no presence
    /// check.
    fn first_bound(&self, i: usize) -> f64 {
        let row = &self.corpus.all_groups()[i * self.stride..(i + 1) * self.stride];
        let vrow = &self.corpus.all_vgroups()[i * self.vstride..(i + 1) * self.vstride];
        self.bound_of(row, vrow, |k| self.corpus.mass_of(i, k))
    }

    /// A lower bound of the score of this version of the query against the shape version `c`
    /// (a candidate's second version), from `c`'s own group sums.
    fn bound_against(&self, c: VersionRef<'_>) -> f64 {
        self.bound_of(c.groups, c.vgroups, |k| c.mass[k])
    }

    /// The bound against a shape whose group sums are `row` (`[histogram channel][group]`) and
    /// `vrow` (`[vector channel][group]`) and whose in-window mass of histogram slot `k` is
    /// `mass(k)`.
    fn bound_of(&self, row: &[u32], vrow: &[f32], mass: impl Fn(usize) -> f64) -> f64 {
        let l = self.corpus.layout();
        let gs = l.groups;
        let d = self.q.dissimilarity;
        let b = self
            .q
            .aggregation
            .apply(self.channels.iter().map(|ch| match ch {
                Some(QueryChannel::Histogram {
                    slot,
                    groups,
                    mass: m,
                    h,
                }) => {
                    let g = &row[slot * gs..(slot + 1) * gs];
                    let v = channel_bound(d, groups, *m, g, mass(*slot), *h, l);
                    if v.is_nan() {
                        0.0
                    } else {
                        v
                    }
                }
                Some(QueryChannel::Vector { slot, groups, len }) => {
                    let g = &vrow[slot * VECTOR_GROUPS..(slot + 1) * VECTOR_GROUPS];
                    vector_bound(d, groups, g, *len)
                }
                None => 0.0,
            }));
        with_margin(b)
    }
}

/// Consecutive rows of group sums and vector group sums.
struct GroupRows<'r> {
    groups: &'r [u32],
    stride: usize,
    vgroups: &'r [f32],
    vstride: usize,
}

/// [`fill_nl1`] with AVX2 where the CPU has it (runtime dispatch).
fn nl1_rows(
    rows: &GroupRows<'_>,
    nl1: &Nl1Row,
    base: usize,
    out: &mut [f64],
    keep: &(dyn Fn(usize) -> bool + Sync),
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { fill_nl1_avx2(rows, nl1, base, out, keep) };
        return;
    }
    fill_nl1(rows, nl1, base, out, keep);
}

/// The nL1 bound of every row of `rows` over the compared ranges and vector channels of `nl1`,
/// as [`Bounder::fill`] writes it. Inlined into [`fill_nl1_avx2`] so that the same loop is
/// compiled once for the baseline CPU and once with AVX2.
#[inline(always)]
fn fill_nl1(
    rows: &GroupRows<'_>,
    nl1: &Nl1Row,
    base: usize,
    out: &mut [f64],
    keep: &(dyn Fn(usize) -> bool + Sync),
) {
    let t = total_at(MAX_SHIFT);
    for (j, (o, row)) in out
        .iter_mut()
        .zip(rows.groups.chunks_exact(rows.stride))
        .enumerate()
    {
        *o = if keep(base + j) {
            let mut s = 0u32;
            for r in &nl1.ranges {
                s += row[r.clone()]
                    .iter()
                    .zip(&nl1.row[r.clone()])
                    .map(|(&c, &x)| c.abs_diff(x))
                    .sum::<u32>();
            }
            let mut b = s as f64 / t;
            for (at, q) in &nl1.vectors {
                let at = j * rows.vstride + at;
                b += vector_l1_bound(q, &rows.vgroups[at..at + VECTOR_GROUPS]);
            }
            with_margin(b)
        } else {
            f64::NAN
        };
    }
}

/// [`fill_nl1`] compiled for AVX2 (runtime dispatch in [`nl1_rows`]).
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fill_nl1_avx2(
    rows: &GroupRows<'_>,
    nl1: &Nl1Row,
    base: usize,
    out: &mut [f64],
    keep: &(dyn Fn(usize) -> bool + Sync),
) {
    fill_nl1(rows, nl1, base, out, keep)
}

/// Relative allowance for the rounding of a stored vector group sum (see [`vector_bound`]).
const VECTOR_ROUNDING: f64 = 1.0 / (1u64 << 22) as f64;

/// Per group of two vectors' group sums `a`, `b`: `|A − B|` less the allowance for their
/// rounding (never negative; 0 where a sum is NaN).
#[inline(always)]
fn vector_group_gaps<'x>(a: &'x [f32], b: &'x [f32]) -> impl Iterator<Item = f64> + 'x {
    a.iter().zip(b).map(|(&x, &y)| {
        let (x, y) = (x as f64, y as f64);
        let gap = (x - y).abs() - VECTOR_ROUNDING * (x.abs() + y.abs());
        // Not `f64::max`: this form vectorises (NaN fails the comparison).
        if gap > 0.0 {
            gap
        } else {
            0.0
        }
    })
}

// The pairwise sum below halves the groups down to one.
const _: () = assert!(VECTOR_GROUPS.is_power_of_two());

/// [`vector_bound`] under L1 and nL1: the sum of the gaps (pairwise, which vectorises).
#[inline(always)]
fn vector_l1_bound(a: &[f32], b: &[f32]) -> f64 {
    let mut g = [0.0; VECTOR_GROUPS];
    for (g, v) in g.iter_mut().zip(vector_group_gaps(a, b)) {
        *g = v;
    }
    let mut half = VECTOR_GROUPS / 2;
    while half > 0 {
        for i in 0..half {
            g[i] += g[i + half];
        }
        half /= 2;
    }
    g[0]
}

/// Lower bound of the vector dissimilarity `d` ([`crate::ranking::vector_dissimilarity`]) of
/// two vectors of `n` values from their [`VECTOR_GROUPS`] group sums `a`, `b` (groups of
/// `w_g` values, [`super::corpus::vector_group_width`]). Per group the gap `|A_g − B_g|` is a
/// lower bound of `Σ_{i∈g} |a_i − b_i|` (triangle inequality); a stored sum is within
/// `2^-23 |A_g|` of the exact sum of the group's `f32` values (a sum whose `f64` accumulation
/// could be off by more is stored as NaN and bounds nothing), so each gap is lowered by
/// `2^-22 (|A_g| + |B_g|)`. Then L1 and nL1: `Σ_g gap`; L∞: `max_g gap / w_g` (a group's mean
/// is at most its max); every other choice (Euclidean): `(Σ_g gap² / w_g)^{1/2}`
/// (Cauchy–Schwarz). Vectors of different lengths score ∞, so any value bounds them.
pub(crate) fn vector_bound(d: Dissimilarity, a: &[f32], b: &[f32], n: usize) -> f64 {
    let w = vector_group_width(n);
    let widths = (0..VECTOR_GROUPS).map(|g| w.min(n.saturating_sub(g * w)));
    match d {
        Dissimilarity::L1 | Dissimilarity::NL1 => vector_l1_bound(a, b),
        Dissimilarity::LInf => vector_group_gaps(a, b)
            .zip(widths)
            .filter(|&(_, w)| w > 0)
            .map(|(v, w)| v / w as f64)
            .fold(0.0, f64::max),
        _ => vector_group_gaps(a, b)
            .zip(widths)
            .filter(|&(_, w)| w > 0)
            .map(|(v, w)| v * v / w as f64)
            .sum::<f64>()
            .sqrt(),
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
/// (candidate, mass `mb`), bin width `h`, the bins and groups of `layout` (see the module docs).
pub(crate) fn channel_bound(
    d: Dissimilarity,
    a: &[u32],
    ma: f64,
    b: &[u32],
    mb: f64,
    h: f64,
    layout: &Layout,
) -> f64 {
    let t = total_at(MAX_SHIFT);
    let w = |g: usize| layout.group_width(g) as f64;
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
                    .map(|(g, (x, y))| ((x - y) as f64).powi(2) / w(g))
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
            let bc = pairs()
                .map(|(x, y)| (x as f64 * y as f64).sqrt())
                .sum::<f64>()
                / t;
            -(bc.clamp(BHATTACHARYYA_FLOOR, 1.0)).ln()
        }
        Dissimilarity::Chi2 => {
            2.0 * pairs()
                .map(|(x, y)| {
                    if x + y > 0 {
                        ((x - y) as f64).powi(2) / (x + y) as f64
                    } else {
                        0.0
                    }
                })
                .sum::<f64>()
                / t
        }
    }
}
