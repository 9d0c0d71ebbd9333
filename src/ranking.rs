//! Corpus calibration, histograms, dissimilarities (eqs. 11–16) and scale aggregation (§3.2).
//!
//! # From signatures to scores
//!
//! 1. [`calibrate`] pools the stored distributions of a corpus and picks, per channel, the
//!    window `[0, P95]` (paper §5: 95th percentile of the distances over the whole corpus). Each
//!    shape counts equally (the pooled CDF is the mean of the shapes' normalised CDFs, found by
//!    bisection on the sketches). The result is a small [`Calibration`] with an `epoch`: the
//!    index stores it, and recalibrating re-derives histograms without touching any eigenpair.
//! 2. [`prepare_for_ranking`] derives, per channel, a 256-bin histogram on that window with a
//!    Gaussian Parzen window of σ = 1 bin (= window/256), as REFERENCE.md's binned KDE: linear
//!    binning of the mass to the bin centres (mass beyond the window dropped, mass below the
//!    first / above the last centre to the end bin), convolution truncated at ±4σ with weights
//!    summing to 1, mass pushed past either end dropped. From a [`QuantileSketch`] the mass per
//!    bin is the exact integral of its piecewise-linear CDF over 16 sub-bins per bin, each placed
//!    at its centre (derivation error in [`crate::signature`]'s docs: nL1 ≤ 0.0008 on a shape's
//!    own window). A [`Prepared`] keeps the un-normalised density `f` (mass per unit distance),
//!    the normalised bin probabilities `p = f̂ h` and their cumulative sums.
//! 3. [`crate::search`] encodes the prepared histograms compactly, one layout per corpus, and
//!    compares them with a [`QuerySpec`]: a [`Dissimilarity`] per channel, then a
//!    dissimilarity-stage [`Aggregation`] over the channels (single: the first channel only;
//!    sum; sum of squares; max). Kernel-, distance- and distribution-stage aggregation are
//!    channel kinds of the signature ([`crate::signature::ChannelKind`]).
//!    [`histogram_dissimilarity`] here is the reference on `f64` histograms; the tolerance of
//!    the encoded scores against it is stated in [`crate::search::score`].
//!
//! ```no_run
//! use shapeseek::spectrum::{analyze, AnalyzeOptions};
//! use shapeseek::presets::default_config;
//! use shapeseek::ranking::calibrate;
//! use shapeseek::search::{rank_all, Corpus, Encoded, Layout, Query};
//! use shapeseek::signature::compute_signature;
//! # fn main() -> shapeseek::Result<()> {
//! # let meshes: Vec<shapeseek::mesh::Mesh> = Vec::new();
//! let cfg = default_config();
//! let sigs = meshes
//!     .iter()
//!     .map(|m| compute_signature(&analyze(m, &AnalyzeOptions::default())?, &cfg.signature))
//!     .collect::<shapeseek::Result<Vec<_>>>()?;
//! let cal = calibrate(&sigs.iter().collect::<Vec<_>>(), &cfg.signature, 1);
//! let layout = Layout::of(&cal);
//! let rows: Vec<Encoded> = sigs.iter().map(|s| Encoded::from_signature(s, &cal, &layout)).collect();
//! let corpus = Corpus::build(layout, &rows);
//! let q = Query::new(&cfg.query, corpus.layout());
//! let hits = rank_all(&corpus, &q, corpus.shape(0)); // (index, score), best first
//! # let _ = hits;
//! # Ok(())
//! # }
//! ```
//!
//! # Dissimilarities (§2.4)
//!
//! Integrals use the bin width `h`: `L1 = Σ|f−g| h`, `L2 = (Σ(f−g)² h)^{1/2}`,
//! `L∞ = max|f−g|` on un-normalised densities; `nL1 = Σ|p−q|` (in [0, 2]),
//! `nL2 = (Σ(p−q)²/h)^{1/2}` on normalised densities; symmetric KL
//! `Σ (p−q)(ln(p+ε) − ln(q+ε))` with ε = [`KL_EPSILON`] = 10⁻¹²; Bhattacharyya
//! `−ln max(Σ√(pq), 10⁻¹²)` (so at most ≈ 27.6); χ² `2Σ(p−q)²/(p+q)` with empty-empty bins
//! contributing 0; EMD `Σ|P_b − Q_b| h` with `P, Q` the cumulative sums (eq. 16). All are finite
//! on empty bins and empty histograms, zero on identical inputs and symmetric. ShapeDNA channels
//! are vectors: L1 → `Σ|a−b|`, L∞ → `max|a−b|`, anything else → Euclidean.
//!
//! Agreement with the Python reference of the bench (REFERENCE.md) is measured by
//! `shapeseek eval --manifest ../shared/bench/mini/manifest.csv` (its tables show each figure
//! beside the reference's); the figures are in `docs/search.md`.
//!
//! Scores from [`Prepared`] values of *different* calibrations are meaningless (bins differ);
//! the caller keeps one epoch per scan.
//!
//! # Complexity
//!
//! Calibration: O(S · channels · log Q · 60) for S shapes. Preparing one shape:
//! O(channels · 256 · 16 · log Q). One score: O(channels · 256).

pub use crate::signature::Aggregation;
use crate::signature::{ChannelValues, QuantileSketch, Signature, SignatureSpec};
use serde::{Deserialize, Serialize};

/// Default number of histogram bins (paper §5).
pub const DEFAULT_BINS: usize = 256;
/// Default window: this percentile of the pooled corpus distances (paper §5).
pub const DEFAULT_PERCENTILE: f64 = 0.95;
/// Added to bin probabilities inside the logarithms of the symmetric KL dissimilarity.
pub const KL_EPSILON: f64 = 1e-12;
/// Floor of the Bhattacharyya coefficient (so the dissimilarity is at most `-ln 1e-12 ≈ 27.6`).
pub const BHATTACHARYYA_FLOOR: f64 = 1e-12;
/// Sub-bins per bin used to discretise a quantile sketch before linear binning.
const SUB_BINS: usize = 16;

/// Distribution dissimilarity (§2.4).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Dissimilarity {
    /// `∫|f − g| dδ` on un-normalised densities (eq. 11, p = 1).
    L1,
    /// `(∫(f − g)² dδ)^{1/2}` on un-normalised densities (eq. 11, p = 2).
    L2,
    /// L1 on normalised densities `f̂`.
    NL1,
    /// L2 on normalised densities `f̂`.
    NL2,
    /// Symmetric Kullback–Leibler (eq. 13) on normalised bins, [`KL_EPSILON`] added.
    KL,
    /// Bhattacharyya `−ln Σ √(p q)` (eq. 14) on normalised bins.
    Bhattacharyya,
    /// `2 Σ (p − q)² / (p + q)` (eq. 15) on normalised bins (empty-empty bins contribute 0).
    Chi2,
    /// `∫|F̂ − Ĝ| dδ` (eq. 16).
    Emd,
    /// `sup |f − g|` on un-normalised densities (eq. 12).
    LInf,
}

impl Dissimilarity {
    /// Name as used in configuration names (`L1`, `L2`, `nL1`, `nL2`, `KL`, `Bhatt`, `chi2`,
    /// `EMD`, `Linf`).
    pub fn label(&self) -> &'static str {
        match self {
            Dissimilarity::L1 => "L1",
            Dissimilarity::L2 => "L2",
            Dissimilarity::NL1 => "nL1",
            Dissimilarity::NL2 => "nL2",
            Dissimilarity::KL => "KL",
            Dissimilarity::Bhattacharyya => "Bhatt",
            Dissimilarity::Chi2 => "chi2",
            Dissimilarity::Emd => "EMD",
            Dissimilarity::LInf => "Linf",
        }
    }

    /// Every dissimilarity, in the order of paper Table 1 (then L∞).
    pub fn all() -> [Dissimilarity; 9] {
        use Dissimilarity::*;
        [L1, L2, NL1, NL2, KL, Bhattacharyya, Chi2, Emd, LInf]
    }
}

/// Per-channel histogram windows derived from a corpus, stored with the index.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Calibration {
    /// Increases whenever the calibration is recomputed.
    pub epoch: u64,
    /// Key of the spec it was computed for.
    pub spec_key: String,
    /// Channel names, in the spec's order.
    pub channel_names: Vec<String>,
    /// Upper end of the window `[0, window_max]` per channel (0 for vector channels).
    pub window_max: Vec<f64>,
    /// Number of bins.
    pub bins: usize,
    /// Gaussian Parzen bandwidth (standard deviation) in bins (1.0 = window / bins).
    pub bandwidth_bins: f64,
    /// Percentile of the pooled distances that defined the windows.
    pub percentile: f64,
    /// Number of signatures that contributed.
    pub shapes: usize,
}

/// A signature's channels as histograms under one calibration: what scoring scans.
#[derive(Clone, Debug)]
pub struct Prepared {
    /// Epoch of the calibration used.
    pub epoch: u64,
    /// Channel names, in the calibration's order.
    pub names: Vec<String>,
    /// Per channel (`None` when the signature lacks it).
    pub channels: Vec<Option<PreparedChannel>>,
    /// The second cut version's histograms ([`Signature::alternate`]), if it has one.
    pub alternate: Option<Box<Prepared>>,
}

/// One prepared channel.
#[derive(Clone, Debug)]
pub enum PreparedChannel {
    /// A binned, Parzen-smoothed distribution.
    Histogram(Histogram),
    /// A vector (ShapeDNA).
    Vector(Vec<f64>),
}

/// A histogram on `[0, bins · bin_width]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Histogram {
    /// Bin width `h` (distance units).
    pub bin_width: f64,
    /// Un-normalised density `f` per bin (mass per bin / h); `Σ f h` = in-window mass.
    pub density: Vec<f64>,
    /// Normalised bin probabilities `p_b = f̂_b h` (sum 1, or all 0 when the window is empty).
    pub prob: Vec<f64>,
    /// Cumulative sums of `prob`.
    pub cdf: Vec<f64>,
    /// In-window mass `Σ f h` (the sum of the mass per bin).
    pub mass: f64,
}

/// What to rank by.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct QuerySpec {
    /// Channels (names) compared; their dissimilarities are aggregated.
    pub channels: Vec<String>,
    /// Dissimilarity of each channel.
    pub dissimilarity: Dissimilarity,
    /// Dissimilarity-stage aggregation over `channels` ([`Aggregation::Single`]: first only).
    pub aggregation: Aggregation,
    /// How much closer a pair's second versions must be to count
    /// ([`crate::signature::SignatureSpec::alternate_cut`]): a pair of which either shape has a
    /// second version scores `min(D₁, f · D₂)`, `D₁` the aggregated dissimilarity of the first
    /// versions, `D₂` that of the second ones (a shape without a second version takes part
    /// with its first), `f` this margin (`≥ 1`, finite). Without second versions it changes
    /// nothing. Missing from the JSON: [`DEFAULT_ALTERNATE_MARGIN`].
    #[serde(default = "default_alternate_margin")]
    pub alternate_margin: f64,
}

/// The default's [`QuerySpec::alternate_margin`]: chosen by the leave-one-class-out protocol
/// (`docs/quality.md` §17: 1.1 without boundary capping; re-chosen with capping in §20: 1, the
/// plain smaller of the two comparisons).
pub const DEFAULT_ALTERNATE_MARGIN: f64 = 1.0;

fn default_alternate_margin() -> f64 {
    DEFAULT_ALTERNATE_MARGIN
}

impl QuerySpec {
    /// Why the spec's own values are invalid, if they are (the channels are checked against a
    /// signature spec by whoever knows it): a margin below 1 or not finite.
    pub fn validate(&self) -> Result<(), String> {
        let f = self.alternate_margin;
        if !(f.is_finite() && f >= 1.0) {
            return Err(format!("alternate_margin must be finite and >= 1, got {f}"));
        }
        Ok(())
    }
}

/// Options of [`calibrate_with`]. Missing fields deserialize to the paper's values.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default)]
pub struct CalibrationOptions {
    /// Number of bins.
    pub bins: usize,
    /// Parzen bandwidth in bins.
    pub bandwidth_bins: f64,
    /// Percentile (fraction) of pooled distances for the window.
    pub percentile: f64,
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        Self {
            bins: DEFAULT_BINS,
            bandwidth_bins: 1.0,
            percentile: DEFAULT_PERCENTILE,
        }
    }
}

impl CalibrationOptions {
    /// Whether these are the paper's values (256 bins, one-bin bandwidth, 95th percentile).
    pub fn is_paper(&self) -> bool {
        *self == Self::default()
    }

    /// Whether `cal` was computed with these options (bins, bandwidth and percentile).
    pub fn made(&self, cal: &Calibration) -> bool {
        cal.bins == self.bins.max(1)
            && cal.bandwidth_bins == self.bandwidth_bins
            && cal.percentile == self.percentile
    }

    /// Why these options cannot calibrate, if they cannot.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.percentile > 0.0 && self.percentile <= 1.0) {
            return Err(format!(
                "percentile must be in (0, 1], got {}",
                self.percentile
            ));
        }
        if !(self.bandwidth_bins >= 0.0 && self.bandwidth_bins.is_finite()) {
            return Err(format!(
                "bandwidth_bins must be ≥ 0, got {}",
                self.bandwidth_bins
            ));
        }
        if self.bins == 0 {
            return Err("bins must be ≥ 1".into());
        }
        Ok(())
    }
}

/// Calibration with the paper's defaults (256 bins, bandwidth = window/256, 95th percentile).
pub fn calibrate(signatures: &[&Signature], spec: &SignatureSpec, epoch: u64) -> Calibration {
    calibrate_with(signatures, spec, epoch, &CalibrationOptions::default())
}

/// Calibration: per channel, the `percentile` of the pooled distribution of all signatures'
/// distances, each shape weighted equally (the mixture of their normalised distributions).
/// A channel no signature has gets the window 1.0.
pub fn calibrate_with(
    signatures: &[&Signature],
    spec: &SignatureSpec,
    epoch: u64,
    opts: &CalibrationOptions,
) -> Calibration {
    let names = spec.channel_names();
    let window_max = names
        .iter()
        .map(|name| {
            let sketches: Vec<&QuantileSketch> = signatures
                .iter()
                .filter_map(|s| match s.channel(name).map(|c| &c.values) {
                    Some(ChannelValues::Distribution(q)) => Some(q),
                    _ => None,
                })
                .collect();
            let vector = signatures.iter().any(|s| {
                matches!(
                    s.channel(name).map(|c| &c.values),
                    Some(ChannelValues::Vector(_))
                )
            });
            if vector {
                0.0
            } else if sketches.is_empty() {
                1.0
            } else {
                pooled_quantile(&sketches, opts.percentile)
            }
        })
        .collect();
    Calibration {
        epoch,
        spec_key: spec.key(),
        channel_names: names,
        window_max,
        bins: opts.bins.max(1),
        bandwidth_bins: opts.bandwidth_bins,
        percentile: opts.percentile,
        shapes: signatures.len(),
    }
}

/// `x` with `mean_s F̂_s(x) = p` (bisection on the pooled piecewise-linear CDF).
fn pooled_quantile(sketches: &[&QuantileSketch], p: f64) -> f64 {
    let hi0 = sketches
        .iter()
        .filter_map(|s| s.quantiles.last().copied())
        .fold(0.0f64, f64::max);
    if hi0 <= 0.0 {
        return 1.0;
    }
    // The mean CDF, summed exactly in fixed point (each value to 2⁻⁵³), so that it does not
    // depend on the order of the sketches: the bisection's last steps compare it with `p` at
    // rounding level, and a cluster's nodes and shards pool the same shapes in other orders
    // than a single node (a window differing in its last bits moves a count wherever two bins'
    // remainders tie, as they do on symmetric shapes).
    const ONE: f64 = (1u64 << 53) as f64;
    let pooled = |x: f64| {
        let sum: u128 = sketches
            .iter()
            .map(|s| (sketch_cdf(s, x).clamp(0.0, 1.0) * ONE).round() as u128)
            .sum();
        (sum as f64 / ONE) / sketches.len() as f64
    };
    let (mut lo, mut hi) = (0.0, hi0);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if pooled(mid) >= p {
            hi = mid;
        } else {
            lo = mid;
        }
        if hi - lo <= 1e-15 * hi0 {
            break;
        }
    }
    if hi > 0.0 {
        hi
    } else {
        hi0
    }
}

/// Normalised CDF `F̂(x)` of a quantile sketch (linear between knots; repeated knots are atoms).
pub fn sketch_cdf(s: &QuantileSketch, x: f64) -> f64 {
    let q = &s.quantiles;
    let nq = q.len();
    if nq < 2 {
        return if nq == 1 && x >= q[0] { 1.0 } else { 0.0 };
    }
    cdf_from_count(q, x, q.partition_point(|&v| v <= x))
}

/// [`sketch_cdf`] at `x`, given `count`, the number of knots `≤ x`.
fn cdf_from_count(q: &[f64], x: f64, count: usize) -> f64 {
    let nq = q.len();
    if count == 0 {
        return 0.0;
    }
    if count >= nq {
        return 1.0;
    }
    let j = count - 1;
    let (a, b) = (q[j], q[j + 1]);
    let frac = if b > a { (x - a) / (b - a) } else { 0.0 };
    (j as f64 + frac) / (nq - 1) as f64
}

/// [`sketch_cdf`] at non-decreasing points, in one pass over the knots: the same values bit
/// for bit, without a binary search per point. A sketch whose knots are not sorted (only a
/// damaged one) is evaluated by [`sketch_cdf`] itself, point by point.
struct SketchCdfWalk<'a> {
    s: &'a QuantileSketch,
    sorted: bool,
    count: usize,
}

impl<'a> SketchCdfWalk<'a> {
    fn new(s: &'a QuantileSketch) -> Self {
        let sorted = s.quantiles.is_sorted();
        SketchCdfWalk {
            s,
            sorted,
            count: 0,
        }
    }

    /// `F̂(x)`; `x` must not be below the previous call's.
    fn at(&mut self, x: f64) -> f64 {
        let q = &self.s.quantiles;
        if !self.sorted || q.len() < 2 {
            return sketch_cdf(self.s, x);
        }
        while self.count < q.len() && q[self.count] <= x {
            self.count += 1;
        }
        cdf_from_count(q, x, self.count)
    }
}

/// Linear binning of weighted values to the centres of `bins` bins on `[0, window]` (values
/// outside the window dropped; values below the first / above the last centre go wholly to the
/// end bin), then a Gaussian Parzen window of `bandwidth_bins` bins (truncated at ±4σ, weights
/// summing to 1, mass pushed past the ends dropped). Returns mass per bin.
pub fn parzen_histogram(
    values: impl IntoIterator<Item = (f64, f64)>,
    window: f64,
    bins: usize,
    bandwidth_bins: f64,
) -> Vec<f64> {
    let mut raw = vec![0.0; bins];
    if bins == 0 || window <= 0.0 || !window.is_finite() {
        return raw;
    }
    let inv_h = bins as f64 / window;
    for (x, w) in values {
        if !(0.0..=window).contains(&x) {
            continue;
        }
        let u = x * inv_h - 0.5;
        if u <= 0.0 {
            raw[0] += w;
        } else if u >= (bins - 1) as f64 {
            raw[bins - 1] += w;
        } else {
            let i = u as usize;
            let f = u - i as f64;
            raw[i] += w * (1.0 - f);
            raw[i + 1] += w * f;
        }
    }
    gaussian_smooth(&raw, bandwidth_bins)
}

fn gaussian_smooth(raw: &[f64], sigma: f64) -> Vec<f64> {
    if sigma <= 0.0 {
        return raw.to_vec();
    }
    let r = (4.0 * sigma).ceil() as isize;
    let g: Vec<f64> = (-r..=r)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let gs: f64 = g.iter().sum();
    let n = raw.len() as isize;
    let mut out = vec![0.0; raw.len()];
    for (i, &v) in raw.iter().enumerate() {
        if v == 0.0 {
            continue;
        }
        for (kk, &gk) in g.iter().enumerate() {
            let j = i as isize + kk as isize - r;
            if j >= 0 && j < n {
                out[j as usize] += v * gk / gs;
            }
        }
    }
    out
}

/// Histogram of a quantile sketch on `[0, window]` (see [`parzen_histogram`]): the piecewise
/// linear CDF is integrated exactly over `16` sub-bins per bin, each sub-bin's mass placed at
/// its centre.
pub fn sketch_histogram(
    s: &QuantileSketch,
    window: f64,
    bins: usize,
    bandwidth_bins: f64,
) -> Histogram {
    let h = if bins > 0 { window / bins as f64 } else { 0.0 };
    let nsub = bins * SUB_BINS;
    let hs = if nsub > 0 { window / nsub as f64 } else { 0.0 };
    // Distances are ≥ 0: the first sub-bin also takes any atom at 0 (the diagonal pairs).
    let mut prev = 0.0;
    let mut cdf = SketchCdfWalk::new(s);
    let values = (0..nsub).map(|k| {
        let hi = cdf.at((k + 1) as f64 * hs);
        let m = (hi - prev) * s.mass;
        prev = hi;
        ((k as f64 + 0.5) * hs, m)
    });
    let mass_bins = parzen_histogram(values, window, bins, bandwidth_bins);
    histogram_from_mass(mass_bins, h)
}

/// Builds the derived arrays of a [`Histogram`] from mass per bin.
pub fn histogram_from_mass(mass_bins: Vec<f64>, bin_width: f64) -> Histogram {
    let total: f64 = mass_bins.iter().sum();
    let density = if bin_width > 0.0 {
        mass_bins.iter().map(|m| m / bin_width).collect()
    } else {
        vec![0.0; mass_bins.len()]
    };
    let prob: Vec<f64> = if total > 0.0 {
        mass_bins.iter().map(|m| m / total).collect()
    } else {
        vec![0.0; mass_bins.len()]
    };
    let mut acc = 0.0;
    let cdf = prob
        .iter()
        .map(|p| {
            acc += p;
            acc
        })
        .collect();
    Histogram {
        bin_width,
        density,
        prob,
        cdf,
        mass: total,
    }
}

/// Derives the histograms of `sig` under `cal` (channels matched by name), its second version's
/// too.
pub fn prepare_for_ranking(sig: &Signature, cal: &Calibration) -> Prepared {
    let channels = cal
        .channel_names
        .iter()
        .zip(&cal.window_max)
        .map(|(name, &w)| {
            sig.channel(name).map(|c| match &c.values {
                ChannelValues::Distribution(s) => {
                    PreparedChannel::Histogram(sketch_histogram(s, w, cal.bins, cal.bandwidth_bins))
                }
                ChannelValues::Vector(v) => PreparedChannel::Vector(v.clone()),
            })
        })
        .collect();
    Prepared {
        epoch: cal.epoch,
        names: cal.channel_names.clone(),
        channels,
        alternate: sig
            .alternate
            .as_deref()
            .map(|a| Box::new(prepare_for_ranking(a, cal))),
    }
}

/// Dissimilarity of two histograms of the same calibration (different bin counts → ∞).
pub fn histogram_dissimilarity(d: Dissimilarity, a: &Histogram, b: &Histogram) -> f64 {
    if a.density.len() != b.density.len() {
        return f64::INFINITY;
    }
    let h = a.bin_width;
    match d {
        Dissimilarity::L1 => {
            a.density
                .iter()
                .zip(&b.density)
                .map(|(x, y)| (x - y).abs())
                .sum::<f64>()
                * h
        }
        Dissimilarity::L2 => (a
            .density
            .iter()
            .zip(&b.density)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            * h)
            .sqrt(),
        Dissimilarity::LInf => a
            .density
            .iter()
            .zip(&b.density)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max),
        Dissimilarity::NL1 => a.prob.iter().zip(&b.prob).map(|(x, y)| (x - y).abs()).sum(),
        Dissimilarity::NL2 => {
            // p/h is the normalised density: (∫(f̂ − ĝ)²)^{1/2} = (Σ (p − q)² / h)^{1/2}.
            if h > 0.0 {
                (a.prob
                    .iter()
                    .zip(&b.prob)
                    .map(|(x, y)| (x - y) * (x - y))
                    .sum::<f64>()
                    / h)
                    .sqrt()
            } else {
                0.0
            }
        }
        Dissimilarity::KL => a
            .prob
            .iter()
            .zip(&b.prob)
            .map(|(p, q)| (p - q) * ((p + KL_EPSILON).ln() - (q + KL_EPSILON).ln()))
            .sum(),
        Dissimilarity::Bhattacharyya => {
            let bc: f64 = a
                .prob
                .iter()
                .zip(&b.prob)
                .map(|(p, q)| (p * q).sqrt())
                .sum();
            -(bc.clamp(BHATTACHARYYA_FLOOR, 1.0)).ln()
        }
        Dissimilarity::Chi2 => {
            2.0 * a
                .prob
                .iter()
                .zip(&b.prob)
                .map(|(p, q)| {
                    if p + q > 0.0 {
                        (p - q) * (p - q) / (p + q)
                    } else {
                        0.0
                    }
                })
                .sum::<f64>()
        }
        Dissimilarity::Emd => {
            a.cdf
                .iter()
                .zip(&b.cdf)
                .map(|(x, y)| (x - y).abs())
                .sum::<f64>()
                * h
        }
    }
}

/// Dissimilarity of two vectors: L1 → `Σ|a − b|`, L∞ → `max|a − b|`, every other choice the
/// Euclidean distance (ShapeDNA). Different lengths → ∞. Summed in `f64` whatever the values
/// are kept in (`f64` as computed, `f32` in the search corpus).
pub fn vector_dissimilarity<T: Copy + Into<f64>>(d: Dissimilarity, a: &[T], b: &[T]) -> f64 {
    if a.len() != b.len() {
        return f64::INFINITY;
    }
    let diffs = a.iter().zip(b).map(|(&x, &y)| (x.into() - y.into()).abs());
    match d {
        Dissimilarity::L1 | Dissimilarity::NL1 => diffs.sum(),
        Dissimilarity::LInf => diffs.fold(0.0, f64::max),
        _ => diffs.map(|v| v * v).sum::<f64>().sqrt(),
    }
}

/// Dissimilarity of two prepared channels (a missing or mismatched channel → ∞).
pub fn channel_dissimilarity(
    d: Dissimilarity,
    a: Option<&PreparedChannel>,
    b: Option<&PreparedChannel>,
) -> f64 {
    match (a, b) {
        (Some(PreparedChannel::Histogram(x)), Some(PreparedChannel::Histogram(y))) => {
            histogram_dissimilarity(d, x, y)
        }
        (Some(PreparedChannel::Vector(x)), Some(PreparedChannel::Vector(y))) => {
            vector_dissimilarity(d, x, y)
        }
        _ => f64::INFINITY,
    }
}

impl Prepared {
    /// Index of the channel called `name`.
    pub fn channel_index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// The channel called `name`.
    pub fn channel(&self, name: &str) -> Option<&PreparedChannel> {
        self.channel_index(name)
            .and_then(|i| self.channels[i].as_ref())
    }
}

/// The channels a query spec compares: the first one for [`Aggregation::Single`], else all.
pub fn compared_channels(q: &QuerySpec) -> &[String] {
    match q.aggregation {
        Aggregation::Single => &q.channels[..q.channels.len().min(1)],
        _ => &q.channels,
    }
}

#[cfg(test)]
#[path = "ranking_tests.rs"]
mod tests;
