//! The dissimilarities of [`crate::ranking::Dissimilarity`] on the corpus encoding, and the
//! aggregated score: the one scoring function of the scan, the pruning, the re-ranking stages
//! and eval.
//!
//! With `a, b` the counts of two histograms brought to a common scale (the larger of their
//! two exponents: both sum to `T = TOTAL · 2^s`, or are all zero; see [`super::corpus`]),
//! `p = a/T`, `M` the in-window masses, `h` the bin width and `A, B` the running sums of the
//! counts:
//!
//! | dissimilarity | computed as |
//! |---|---|
//! | nL1 | `Σ|a − b| / T` (integer sum) |
//! | nL2 | `(Σ(a − b)² / T² / h)^{1/2}` (integer sum) |
//! | EMD | `Σ|A − B| / T · h` (integer sum) |
//! | L1 | `Σ|M_a a/T − M_b b/T|` |
//! | L2 | `(Σ(M_a a/T − M_b b/T)² / h)^{1/2}` |
//! | L∞ | `max|M_a a/T − M_b b/T| / h` |
//! | KL | `Σ(p − q)(ln(p + ε) − ln(q + ε))` |
//! | Bhattacharyya | `−ln clamp(Σ(ab)^{1/2} / T)` |
//! | χ² | `2 Σ (a − b)² / (a + b) / T` (empty-empty bins contribute 0) |
//!
//! These are the formulas of [`crate::ranking::histogram_dissimilarity`] with `f = M p / h`.
//!
//! # Tolerance against the `f64` histograms
//!
//! [`super::corpus::quantise`] moves the counts of one histogram by less than `2·bins` units in
//! all, at a scale `T_s ≥ T = 65 535`. Hence, per channel of `bins` bins: `|ΔnL1| < 4·bins/T`
//! (the differences have random signs, so the typical error is about `bins^{1/2}/T_s`),
//! `|ΔEMD| < 4·bins²·h/T` and, for the mass-weighted dissimilarities,
//! `|ΔL1| < 2·(M_a + M_b)·bins/T`. KL weighs the smallest bins most: a positive probability keeps
//! at least one count, so `ln p` is off by at most `ln(1/(p·T_s))` where `p < 1/T_s` and by a
//! relative `2/(p·T_s)` elsewhere; the finer scale of spread histograms is what keeps KL
//! rankings close (`docs/search.md` has the effect on every configuration of eval). The module
//! tests check the nL1, L1 and EMD bounds on random histograms.

use super::corpus::{total_at, Layout, ShapeRef, Slot};
use crate::ranking::{
    compared_channels, vector_dissimilarity, Dissimilarity, QuerySpec, BHATTACHARYYA_FLOOR,
    KL_EPSILON,
};
use crate::signature::Aggregation;

/// A query spec resolved against a layout: the compared channels' indices.
#[derive(Clone, Debug)]
pub struct Query {
    /// Dissimilarity of every channel.
    pub dissimilarity: Dissimilarity,
    /// Aggregation over the channels.
    pub aggregation: Aggregation,
    /// Compared channels (layout index; `None`: not in the layout, scores ∞).
    pub channels: Vec<Option<usize>>,
    /// Factor on the second versions' score ([`QuerySpec::alternate_margin`]).
    pub alternate_margin: f64,
}

impl Query {
    /// Resolves `spec` (see [`compared_channels`]) in `layout`.
    pub fn new(spec: &QuerySpec, layout: &Layout) -> Query {
        Query {
            dissimilarity: spec.dissimilarity,
            aggregation: spec.aggregation,
            channels: compared_channels(spec)
                .iter()
                .map(|n| layout.channel(n))
                .collect(),
            alternate_margin: spec.alternate_margin,
        }
    }

    /// The score of `a` and `b`: their first versions' aggregated dissimilarity `D₁`
    /// ([`Query::score_versions`]); when either has a second cut version
    /// ([`crate::signature::SignatureSpec::alternate_cut`]), `min(D₁, f · D₂)` with `D₂` the
    /// dissimilarity of their second versions (a shape without one takes part with its first)
    /// and `f` the margin ([`QuerySpec::alternate_margin`]) — `docs/quality.md` §16–§17.
    pub fn score(&self, layout: &Layout, a: ShapeRef<'_>, b: ShapeRef<'_>) -> f64 {
        self.with_second(layout, a, b, self.score_versions(layout, a, b))
    }

    /// [`Query::score`] given the first versions' dissimilarity `first` (eval aggregates it
    /// from its per-channel matrices).
    pub fn with_second(
        &self,
        layout: &Layout,
        a: ShapeRef<'_>,
        b: ShapeRef<'_>,
        first: f64,
    ) -> f64 {
        if a.alt.is_none() && b.alt.is_none() {
            return first;
        }
        first.min(self.alternate_margin * self.score_versions(layout, a.second(), b.second()))
    }

    /// Aggregated dissimilarity of the two versions given (∞ when a compared channel is
    /// missing from either, or when nothing is compared); second versions are not looked at.
    pub fn score_versions(&self, layout: &Layout, a: ShapeRef<'_>, b: ShapeRef<'_>) -> f64 {
        self.aggregate(|c| channel_dissimilarity(layout, self.dissimilarity, c, a, b))
    }

    /// The aggregation of `value(c)` over the compared channels `c` (∞ for a channel not in
    /// the layout, or when nothing is compared): [`Query::score`] with the per-channel
    /// dissimilarities given (eval computes them once per channel for all pairs).
    pub fn aggregate(&self, mut value: impl FnMut(usize) -> f64) -> f64 {
        if self.channels.is_empty() {
            return f64::INFINITY;
        }
        self.aggregation
            .apply(self.channels.iter().map(|c| match c {
                Some(c) => value(*c),
                None => f64::INFINITY,
            }))
    }
}

/// Dissimilarity `d` of channel `c` of two shapes (∞ when either lacks it).
pub fn channel_dissimilarity(
    layout: &Layout,
    d: Dissimilarity,
    c: usize,
    a: ShapeRef<'_>,
    b: ShapeRef<'_>,
) -> f64 {
    if !a.present[c] || !b.present[c] {
        return f64::INFINITY;
    }
    match layout.slots[c] {
        Slot::Histogram(k) => {
            let r = k * layout.bins..(k + 1) * layout.bins;
            histogram(
                d,
                Counts {
                    counts: &a.hist[r.clone()],
                    shift: a.shift[k],
                    mass: a.mass[k],
                },
                Counts {
                    counts: &b.hist[r],
                    shift: b.shift[k],
                    mass: b.mass[k],
                },
                layout.bin_width[k],
            )
        }
        Slot::Vector(k) => vector_dissimilarity(d, &a.vectors[k], &b.vectors[k]),
    }
}

/// One quantised histogram: counts summing to `TOTAL · 2^shift` (or all zero), in-window mass.
#[derive(Clone, Copy, Debug)]
pub struct Counts<'a> {
    /// Counts per bin.
    pub counts: &'a [u16],
    /// Scale exponent.
    pub shift: u8,
    /// In-window mass `M`.
    pub mass: f64,
}

/// Dissimilarity of two count histograms (see the module table). The counts of both are
/// brought to the larger of the two scales by a shift (exact integers) where the formula is
/// integer.
pub fn histogram(d: Dissimilarity, a: Counts<'_>, b: Counts<'_>, h: f64) -> f64 {
    let top = a.shift.max(b.shift);
    let (la, lb) = ((top - a.shift) as u32, (top - b.shift) as u32);
    let t = total_at(top);
    let pairs = || {
        a.counts
            .iter()
            .zip(b.counts)
            .map(move |(&x, &y)| ((x as i64) << la, (y as i64) << lb))
    };
    let (ta, tb) = (total_at(a.shift), total_at(b.shift));
    let (fa, fb) = (a.mass / ta, b.mass / tb);
    let dens = || {
        a.counts
            .iter()
            .zip(b.counts)
            .map(move |(&x, &y)| (fa * x as f64 - fb * y as f64).abs())
    };
    match d {
        Dissimilarity::NL1 => {
            if la == 0 && lb == 0 {
                // The common case, as one 32-bit integer loop (Σ|a − b| ≤ 2 · 2^16 · bins).
                let s: u64 = a
                    .counts
                    .iter()
                    .zip(b.counts)
                    .map(|(&x, &y)| (x as i32 - y as i32).unsigned_abs() as u64)
                    .sum();
                s as f64 / t
            } else {
                pairs().map(|(x, y)| (x - y).unsigned_abs()).sum::<u64>() as f64 / t
            }
        }
        Dissimilarity::NL2 => {
            if h > 0.0 {
                let s: f64 = pairs().map(|(x, y)| ((x - y) as f64).powi(2)).sum();
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
                (dens().map(|v| v * v).sum::<f64>() / h).sqrt()
            } else {
                0.0
            }
        }
        Dissimilarity::LInf => {
            if h > 0.0 {
                dens().fold(0.0, f64::max) / h
            } else {
                0.0
            }
        }
        Dissimilarity::KL => pairs()
            .map(|(x, y)| {
                let (p, q) = (x as f64 / t, y as f64 / t);
                (p - q) * ((p + KL_EPSILON).ln() - (q + KL_EPSILON).ln())
            })
            .sum(),
        Dissimilarity::Bhattacharyya => {
            let bc = pairs()
                .map(|(x, y)| ((x as f64) * (y as f64)).sqrt())
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
