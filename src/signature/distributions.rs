//! Distributions of pair distances: the streaming fine histogram distances are accumulated in,
//! and the corpus-independent [`QuantileSketch`] read from it (and its truncation).

use serde::{Deserialize, Serialize};

/// A distribution of pair distances stored independently of any corpus: the total mass
/// `F(∞)` and the quantile function at `Q + 1` equally spaced levels.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct QuantileSketch {
    /// Total mass of the measure (`area²` for eq. 10 over all pairs).
    pub mass: f64,
    /// `quantiles[j] = F̂^{-1}(j / Q)`, j = 0..=Q; `quantiles[0]` is the smallest distance,
    /// `quantiles[Q]` the largest. Between knots the CDF is linear.
    pub quantiles: Vec<f64>,
}

/// The part of `s` below `r`: mass `F(r)`, quantiles of the restricted piecewise-linear CDF at
/// the same number of levels (empty, mass 0, when every distance is ≥ `r`).
pub fn truncate_sketch(s: &QuantileSketch, r: f64) -> QuantileSketch {
    let qs = &s.quantiles;
    let nq = qs.len().saturating_sub(1);
    if nq == 0 || qs[nq] <= r {
        return s.clone();
    }
    if qs[0] >= r {
        return QuantileSketch {
            mass: 0.0,
            quantiles: vec![r; nq + 1],
        };
    }
    // qs[j] < r < qs[j + 1] (j < nq since qs[nq] > r).
    let j = qs.partition_point(|&x| x < r) - 1;
    let frac = (r - qs[j]) / (qs[j + 1] - qs[j]);
    let p = (j as f64 + frac) / nq as f64;
    let quantiles = (0..=nq)
        .map(|i| {
            if i == nq {
                return r;
            }
            let u = p * i as f64;
            let k = (u.floor() as usize).min(nq - 1);
            let f = u - k as f64;
            qs[k] + f * (qs[k + 1] - qs[k])
        })
        .collect();
    QuantileSketch {
        mass: s.mass * p,
        quantiles,
    }
}

/// Number of bins of the fine histogram a sketch is read from.
pub(crate) const FINE_BINS: usize = 1 << 15;

/// A fine histogram on `[0, bound]` (32 768 bins) plus an atom at 0 and the exact extremes:
/// the streaming accumulator from which quantile sketches are read.
#[derive(Clone, Debug)]
pub(crate) struct FineHistogram {
    bins: Vec<f64>,
    atom0: f64,
    inv_width: f64,
    bound: f64,
    min_pos: f64,
    max: f64,
}

impl FineHistogram {
    pub(crate) fn new(bound: f64) -> Self {
        let bound = if bound.is_finite() && bound > 0.0 {
            bound
        } else {
            1.0
        };
        Self {
            bins: vec![0.0; FINE_BINS],
            atom0: 0.0,
            inv_width: FINE_BINS as f64 / bound,
            bound,
            min_pos: f64::INFINITY,
            max: 0.0,
        }
    }

    #[inline]
    pub(crate) fn add_zero(&mut self, w: f64) {
        self.atom0 += w;
    }

    #[inline]
    pub(crate) fn add(&mut self, d: f64, w: f64) {
        if d <= 0.0 {
            self.atom0 += w;
            return;
        }
        let k = ((d * self.inv_width) as usize).min(FINE_BINS - 1);
        self.bins[k] += w;
        if d < self.min_pos {
            self.min_pos = d;
        }
        if d > self.max {
            self.max = d;
        }
    }

    pub(crate) fn merge(&mut self, o: &FineHistogram) {
        for (a, b) in self.bins.iter_mut().zip(&o.bins) {
            *a += b;
        }
        self.atom0 += o.atom0;
        self.min_pos = self.min_pos.min(o.min_pos);
        self.max = self.max.max(o.max);
    }

    /// Quantile sketch with `q` intervals: the CDF is taken linear inside each fine bin (and
    /// clamped to the exact extremes).
    pub(crate) fn sketch(&self, q: usize) -> QuantileSketch {
        let total = self.atom0 + self.bins.iter().sum::<f64>();
        if total <= 0.0 {
            return QuantileSketch {
                mass: 0.0,
                quantiles: vec![0.0; q + 1],
            };
        }
        let width = self.bound / FINE_BINS as f64;
        let lo = if self.atom0 > 0.0 || !self.min_pos.is_finite() {
            0.0
        } else {
            self.min_pos
        };
        let hi = self.max.max(lo);
        let mut out = Vec::with_capacity(q + 1);
        let (mut k, mut cum) = (0usize, self.atom0);
        for j in 0..=q {
            let x = if j == 0 {
                lo
            } else if j == q {
                hi
            } else {
                let p = total * j as f64 / q as f64;
                if p <= self.atom0 {
                    0.0
                } else {
                    while k < FINE_BINS && cum + self.bins[k] < p {
                        cum += self.bins[k];
                        k += 1;
                    }
                    if k >= FINE_BINS {
                        hi
                    } else {
                        let frac = if self.bins[k] > 0.0 {
                            ((p - cum) / self.bins[k]).clamp(0.0, 1.0)
                        } else {
                            0.0
                        };
                        (k as f64 + frac) * width
                    }
                }
            };
            let prev = out.last().copied().unwrap_or(lo);
            out.push(x.clamp(prev, hi));
        }
        QuantileSketch {
            mass: total,
            quantiles: out,
        }
    }
}
