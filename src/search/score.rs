//! The dissimilarities of [`crate::ranking::Dissimilarity`] on the corpus encoding, and the
//! aggregated score: the one scoring function of the scan, the pruning, the re-ranking stages
//! and eval.
//!
//! With `a, b` the counts of two histograms (summing to `T` = [`TOTAL`], or all zero), `p = a/T`,
//! `M` the in-window masses, `h` the bin width and `A, B` the running sums of the counts:
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
//! Largest-remainder rounding moves every count by less than one unit, so each normalised
//! probability is off by less than `1/T` (`T = 65 535`). Hence, per channel of `bins` bins:
//! `|ΔnL1| < 2·bins/T` (0.0079 at 256 bins; the differences have random signs, so the typical
//! error is about `bins^{1/2}/T` ≈ 2.4·10⁻⁴), `|ΔEMD| < 2·bins²·h/T·½` and, for the mass-weighted
//! dissimilarities, `|ΔL1| < (M_a + M_b)·bins/T`. KL is the exception: a probability below
//! `1/(2T)` can round to 0 and `ln(p + ε)` with ε = 10⁻¹² is sensitive to that, so KL scores may
//! differ by more; their rankings are what eval checks (`docs/search.md`). The module tests
//! check the nL1, L1 and EMD bounds on random histograms.

use super::corpus::{Layout, ShapeRef, Slot, TOTAL};
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
        }
    }

    /// Aggregated dissimilarity of `a` and `b` (∞ when a compared channel is missing from
    /// either, or when nothing is compared).
    pub fn score(&self, layout: &Layout, a: ShapeRef<'_>, b: ShapeRef<'_>) -> f64 {
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
                &a.hist[r.clone()],
                a.mass[k],
                &b.hist[r],
                b.mass[k],
                layout.bin_width[k],
            )
        }
        Slot::Vector(k) => vector_dissimilarity(d, &a.vectors[k], &b.vectors[k]),
    }
}

/// Dissimilarity of two count histograms (see the module table).
pub fn histogram(d: Dissimilarity, a: &[u16], ma: f64, b: &[u16], mb: f64, h: f64) -> f64 {
    let t = TOTAL as f64;
    let pairs = || a.iter().zip(b).map(|(&x, &y)| (x as i32, y as i32));
    let (fa, fb) = (ma / t, mb / t);
    let dens = || {
        a.iter()
            .zip(b)
            .map(move |(&x, &y)| (fa * x as f64 - fb * y as f64).abs())
    };
    match d {
        Dissimilarity::NL1 => pairs().map(|(x, y)| (x - y).unsigned_abs()).sum::<u32>() as f64 / t,
        Dissimilarity::NL2 => {
            if h > 0.0 {
                let s: u64 = pairs().map(|(x, y)| ((x - y) as i64).pow(2) as u64).sum();
                (s as f64 / (t * t) / h).sqrt()
            } else {
                0.0
            }
        }
        Dissimilarity::Emd => {
            let (mut ca, mut cb, mut s) = (0i64, 0i64, 0u64);
            for (x, y) in pairs() {
                ca += x as i64;
                cb += y as i64;
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
