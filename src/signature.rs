//! Corpus-independent spectral signatures of one shape (paper §2.3–§3).
//!
//! A [`SignatureSpec`] lists *channels* (kernel × norm × scale, a scale aggregate, or a
//! baseline); [`compute_signature`] turns an [`Analysis`] (unit-area mesh + spectrum) into a
//! [`Signature`] holding, per channel, a distribution of pair distances that does **not** depend
//! on any other shape. Histograms on a corpus window are derived later
//! ([`crate::ranking::prepare_for_ranking`]).
//!
//! # Distances
//!
//! * Kernel weights `K(λ_i)` (eq. 5): heat `e^{-tλ}`, commute time `λ^{-1/2}` (eq. 19), step
//!   `1[λ < λ_c]`, or a kernel-stage aggregate over heat scales (§3.2). Zero modes
//!   (`λ ≤ 10⁻⁶ · 4π / area`, the λ_0 of each component) get weight 0 everywhere, so the
//!   constant (per component) eigenfunctions never enter a distance. Modes with
//!   `K² < 10⁻¹⁶ · max K²` are dropped (they change `d²` by less than 10⁻¹⁶ relative).
//! * **L2** (eq. 9): `d²(x,y) = Σ_{i} K(λ_i)² (φ_i(x) − φ_i(y))²`, computed for all quadrature
//!   point pairs at once as `|ψ_x|² + |ψ_y|² − 2 ψ_x·ψ_y` with `ψ = Φ diag(K)`, one GEMM per row
//!   block of the upper triangle. This equals eq. 6 with the A-weighted vertex quadrature
//!   because `Φᵀ A Φ = I` (tested to 1e-8).
//! * **L1 / L∞**: kernel rows `k(x, z) = Σ_i K(λ_i) φ_i(x) φ_i(z)` evaluated on `lp_samples`
//!   (default 500) farthest-point nodes `z` with their Voronoi areas as quadrature weights:
//!   `d(x,y) = Σ_z W_z |k(x,z) − k(y,z)|` resp. `max_z |…|`, the same nodes serving as pair
//!   points (with the near field below). O(m³): paper Table 2's H-L1 and H-L∞ only. Measured
//!   against 1 200 nodes on a 2 562-vertex shape (`lp_quadrature_error`, ignored): nL1 0.030–0.035
//!   with 300 nodes, 0.016 with 500, 0.007–0.009 with 800.
//!
//! * Not implemented: the scale-invariant kernel of eq. 21. Its log-time derivative and Fourier
//!   modulus need the kernel on a dense log-scale grid per pair, and here every shape is already
//!   normalised to unit area; the commute-time kernel gives exact scale invariance (tested).
//!
//! # Pair quadrature (eq. 10)
//!
//! F is the push-forward of `μ × μ`. [`PairQuadrature::AllVertices`] uses every ordered vertex
//! pair with weight `a_x a_y` (exact, O(n² k)). The default, [`PairQuadrature::Farthest`], uses
//! `m = 1000` **farthest-point samples** (geodesic FPS on the edge graph, started at the vertex
//! farthest from the area centroid, so the choice is rigid-motion and permutation invariant on
//! asymmetric shapes), each carrying the area of its **Voronoi cell** (every vertex is assigned
//! to its nearest sample in edge-graph distance, weights `a_i`): every ordered sample pair
//! `(i, j)` has weight `W_i W_j`, so the total mass is still `area²`. **Near field**: pairs of
//! the same or of adjacent cells (cells joined by a mesh edge) are evaluated one-sided exactly,
//! `W_i Σ_{y ∈ cell j} a_y δ(d(s_i, y))`, so that small distances are not quantised to the
//! sample spacing (≈ 7 n extra distances; the mass is unchanged).
//!
//! Measured error (nL1 of the 256-bin Parzen histograms derived from the signature against
//! binning the exact all-pairs `a_x a_y` distances directly, six heat-L2 scales, k = 100):
//!
//! | shape | own 95 % window | twice it | half of it |
//! |---|---|---|---|
//! | bumpy torus, 3 000 vertices (test `quadrature_and_sketch_errors_against_exact_all_pairs`) | ≤ 0.0069 | ≤ 0.0073 | ≤ 0.019 |
//! | bumpy torus, 10 000 vertices (test `quadrature_error_10k`, ignored: 1 min) | ≤ 0.0067 | ≤ 0.0042 | ≤ 0.018 |
//!
//! The worst case is always t = 0.016 on the half window (its distribution has a sharp peak and
//! the half window resolves small distances finely); the other scales stay ≤ 0.0124 there. A
//! corpus window differs from a shape's own, hence the half / twice columns. Sweep at 3 000
//! vertices (own / half-or-twice window, `quadrature_sweep`): 500 samples 0.015 / 0.035; 1 000
//! without near field 0.0079 / 0.0225; 1 000 with cell-mean rows 0.0090 / 0.026; 1 500 samples
//! 0.0042 / 0.014 (at 1.5–2× the time). i.i.d. sampling of 1 000 points was measured by
//! REFERENCE.md at ≈ 0.08 between two draws.
//!
//! # Stored representation
//!
//! Distances are streamed (no pair is stored) into a fine histogram of 32 768 bins on
//! `[0, bound]` (`bound` = the sum of the two largest `|ψ|`, an upper bound of every distance)
//! plus an exact atom at 0 (the diagonal pairs) and the exact smallest / largest distance. From
//! it a [`QuantileSketch`] is read: the total mass `F(∞)` and the quantile function at
//! `sketch_quantiles + 1` (default 1 025) equally spaced levels, the CDF linear between knots.
//! Any window, bin count and Parzen bandwidth can be derived from it. Measured derivation error
//! (histogram from the sketch of the exact pairs vs binning the exact pairs directly): nL1
//! **≤ 0.0008** on the shape's own window, ≤ 0.006 on half / twice it; 512 quantiles give
//! 0.0013 / 0.0086, 2 048 give 0.0006 / 0.0042. 1 025 × 8 bytes per channel.
//!
//! # Scales
//!
//! [`DEFAULT_HEAT_SCALES`] = `0.016 · 2.5^j`, j = 0..5, for **unit-area** shapes (the pipeline
//! normalises area): unit-area shapes have `λ_1 ≈ 6` (REFERENCE.md: DEV median 6.46), so `t λ_1`
//! spans ≈ 0.1 … 10, from "many eigenfunctions matter" to "φ_1 dominates", and at the smallest t
//! `e^{-t λ_100} ≈ e^{-20}`, so k = 100 eigenpairs truncate nothing. REFERENCE.md found the three
//! smallest ([`SMALL_HEAT_SCALES`]) best.
//!
//! # Complexity and time
//!
//! FPS: `O(m n)` for the farthest-vertex scans plus pruned Dijkstra runs (≈ 25 ms at n = 10⁴,
//! m = 1 000). Per L2 channel: `O(m² k_eff)` GEMM + `m²/2` histogram updates + `O(n k_eff)`
//! near field. Channels run in
//! parallel (rayon), each over row blocks; per-block histograms are merged in block order, so
//! results are bitwise deterministic whatever the thread count. Six-scale heat-L2 signature of a
//! 10 000-vertex shape with k = 100: **134 ms of CPU time** (both threads together, so ≈ 70–135 ms
//! wall on two idle cores); measured wall time on the shared 2-core machine at load average 5–10:
//! 213–330 ms median, 205–250 ms best of 10
//! (`cargo test --release --lib signature::tests::timing_10k -- --ignored --nocapture`).

use crate::bytes::{put_f64, put_f64s, put_u64, ByteReader};
use crate::mesh::{norm, sub, Mesh};
use crate::pipeline::Analysis;
use crate::{Error, Result};
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatRef, Par};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// The default diffusion times for unit-area shapes, `t_j = 0.016 · 2.5^j`, j = 0..5.
pub const DEFAULT_HEAT_SCALES: [f64; 6] = [0.016, 0.04, 0.1, 0.25, 0.625, 1.5625];

/// The three smallest default scales (`t ≤ 0.1`).
pub const SMALL_HEAT_SCALES: [f64; 3] = [0.016, 0.04, 0.1];

/// Scale aggregation functional (§3.2): single scale, sum, sum of squares, maximum.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Aggregation {
    /// The first (only) member.
    Single,
    /// `Σ_t f_t`.
    Sum,
    /// `Σ_t f_t²`.
    Sum2,
    /// `max_t f_t`.
    Max,
}

impl Aggregation {
    /// Short name used in channel and configuration names.
    pub fn label(&self) -> &'static str {
        match self {
            Aggregation::Single => "Single",
            Aggregation::Sum => "Sum",
            Aggregation::Sum2 => "Sum2",
            Aggregation::Max => "Max",
        }
    }

    /// Applies the functional to `values` in order (empty → 0).
    pub fn apply(&self, values: impl IntoIterator<Item = f64>) -> f64 {
        let mut it = values.into_iter();
        match self {
            Aggregation::Single => it.next().unwrap_or(0.0),
            Aggregation::Sum => it.sum(),
            Aggregation::Sum2 => it.map(|v| v * v).sum(),
            Aggregation::Max => it.fold(f64::NEG_INFINITY, f64::max).max(0.0),
        }
    }
}

/// Transfer function K(λ) of the diffusion kernel (eq. 5).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum Kernel {
    /// Heat kernel `K(λ) = e^{-tλ}` (§2.2).
    Heat {
        /// Diffusion time (unit-area shapes: see [`DEFAULT_HEAT_SCALES`]).
        t: f64,
    },
    /// Commute-time kernel `K(λ) = λ^{-1/2}` (eq. 19).
    CommuteTime,
    /// Band-limiting step `K(λ) = 1[λ < λ_c]`.
    Step {
        /// Cut-off eigenvalue.
        lambda_c: f64,
    },
    /// Kernel-stage aggregation of heat kernels (§3.2): `K(λ) = A_t e^{-tλ}`; for
    /// [`Aggregation::Sum2`], `K(λ) = (Σ_t e^{-2tλ})^{1/2}`, so that the L2 distance is
    /// `(Σ_t d_t²)^{1/2}`.
    HeatAggregate {
        /// Diffusion times.
        ts: Vec<f64>,
        /// Functional applied to the transfer functions.
        aggregation: Aggregation,
    },
}

/// Norm of `k(x,·) − k(y,·)` defining the diffusion distance (§3).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Norm {
    /// `L²(X)`: closed form from the eigenmap (eq. 9).
    L2,
    /// `L¹(X)`: kernel rows on area-weighted quadrature points.
    L1,
    /// `L^∞(X)`: kernel rows on quadrature points.
    LInf,
}

impl Norm {
    fn label(&self) -> &'static str {
        match self {
            Norm::L2 => "l2",
            Norm::L1 => "l1",
            Norm::LInf => "linf",
        }
    }
}

/// What one channel of a signature measures.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum ChannelKind {
    /// Distribution of the spectral distance of `kernel` under `norm` (eq. 10).
    Spectral {
        /// Transfer function.
        kernel: Kernel,
        /// Norm.
        norm: Norm,
    },
    /// Distance-stage aggregation (§3.2): distribution of `A_t d_t(x, y)` over pairs, `d_t` the
    /// heat distance at time `t` under `norm`.
    DistanceAggregate {
        /// Diffusion times.
        ts: Vec<f64>,
        /// Norm of each `d_t`.
        norm: Norm,
        /// Functional applied per pair.
        aggregation: Aggregation,
    },
    /// Distribution-stage aggregation (§3.2): the measure `Σ_t F_t` (mass `|ts| · area²`).
    DistributionSum {
        /// Diffusion times.
        ts: Vec<f64>,
        /// Norm of each `d_t`.
        norm: Norm,
    },
    /// Baseline: distribution of geodesic distances (edge-graph Dijkstra), optionally only the
    /// pairs closer than `radius`.
    Geodesic {
        /// Pairs farther apart are left out (unit-area units).
        radius: Option<f64>,
    },
    /// Baseline: Osada's D2, Euclidean distances between `samples` area-uniform surface points.
    EuclideanD2 {
        /// Number of surface points (all pairs are used).
        samples: usize,
    },
    /// Baseline: ShapeDNA, the first `count` non-zero eigenvalues (a vector, not a distribution).
    ShapeDna {
        /// Number of eigenvalues.
        count: usize,
    },
    /// Truncated distance range of another distribution channel: only its pairs closer than
    /// `radius` (unit-area units; mass beyond is left out). Calibrated and histogrammed as a
    /// channel of its own, so it gets its own window on the short range.
    Truncated {
        /// The distribution channel (not ShapeDNA, not truncated).
        channel: Box<ChannelKind>,
        /// Pairs farther apart are left out.
        radius: f64,
    },
}

/// One channel of a [`SignatureSpec`].
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ChannelSpec {
    /// What the channel measures.
    pub kind: ChannelKind,
}

fn fmt_ts(ts: &[f64]) -> String {
    ts.iter()
        .map(|t| format!("{t}"))
        .collect::<Vec<_>>()
        .join(",")
}

fn fmt_lambda_c(lc: f64) -> String {
    let m = lc / (4.0 * std::f64::consts::PI);
    if (m - m.round()).abs() < 1e-9 * m.abs().max(1.0) {
        format!("4pi*{}", m.round())
    } else {
        format!("{lc}")
    }
}

impl ChannelSpec {
    /// Heat kernel at time `t` under `norm`.
    pub fn heat(t: f64, norm: Norm) -> Self {
        Self {
            kind: ChannelKind::Spectral {
                kernel: Kernel::Heat { t },
                norm,
            },
        }
    }

    /// Commute-time kernel under the L2 norm (eq. 19).
    pub fn commute_time() -> Self {
        Self {
            kind: ChannelKind::Spectral {
                kernel: Kernel::CommuteTime,
                norm: Norm::L2,
            },
        }
    }

    /// Step kernel `1[λ < λ_c]` under the L2 norm.
    pub fn step(lambda_c: f64) -> Self {
        Self {
            kind: ChannelKind::Spectral {
                kernel: Kernel::Step { lambda_c },
                norm: Norm::L2,
            },
        }
    }

    /// The pairs of `channel` closer than `radius` ([`ChannelKind::Truncated`]).
    pub fn truncated(channel: ChannelSpec, radius: f64) -> Self {
        Self {
            kind: ChannelKind::Truncated {
                channel: Box::new(channel.kind),
                radius,
            },
        }
    }

    /// Geodesic distance distribution.
    pub fn geodesic(radius: Option<f64>) -> Self {
        Self {
            kind: ChannelKind::Geodesic { radius },
        }
    }

    /// Osada D2 with `samples` points.
    pub fn d2(samples: usize) -> Self {
        Self {
            kind: ChannelKind::EuclideanD2 { samples },
        }
    }

    /// ShapeDNA with `count` eigenvalues.
    pub fn shape_dna(count: usize) -> Self {
        Self {
            kind: ChannelKind::ShapeDna { count },
        }
    }

    /// Stable, human-readable name, e.g. `heat-l2[t=0.016]`, `ct-l2`, `step-l2[lc=4pi*10]`,
    /// `heat-l2-ksum[t=0.016,0.04]`, `heat-l2-dmax[...]`, `heat-l2-fsum[...]`, `geo`,
    /// `geo[r=0.5]`, `d2[n=2000]`, `shapedna[50]`, `heat-l2[t=0.016][r=2.44]` (truncated).
    pub fn name(&self) -> String {
        match &self.kind {
            ChannelKind::Spectral { kernel, norm } => {
                let n = norm.label();
                match kernel {
                    Kernel::Heat { t } => format!("heat-{n}[t={t}]"),
                    Kernel::CommuteTime => format!("ct-{n}"),
                    Kernel::Step { lambda_c } => {
                        format!("step-{n}[lc={}]", fmt_lambda_c(*lambda_c))
                    }
                    Kernel::HeatAggregate { ts, aggregation } => format!(
                        "heat-{n}-k{}[t={}]",
                        aggregation.label().to_lowercase(),
                        fmt_ts(ts)
                    ),
                }
            }
            ChannelKind::DistanceAggregate {
                ts,
                norm,
                aggregation,
            } => format!(
                "heat-{}-d{}[t={}]",
                norm.label(),
                aggregation.label().to_lowercase(),
                fmt_ts(ts)
            ),
            ChannelKind::DistributionSum { ts, norm } => {
                format!("heat-{}-fsum[t={}]", norm.label(), fmt_ts(ts))
            }
            ChannelKind::Geodesic { radius } => match radius {
                Some(r) => format!("geo[r={r}]"),
                None => "geo".to_string(),
            },
            ChannelKind::EuclideanD2 { samples } => format!("d2[n={samples}]"),
            ChannelKind::ShapeDna { count } => format!("shapedna[{count}]"),
            ChannelKind::Truncated { channel, radius } => {
                let inner = ChannelSpec {
                    kind: (**channel).clone(),
                };
                format!("{}[r={radius}]", inner.name())
            }
        }
    }

    /// The channel whose distances are computed (the inner channel of a truncated one).
    fn base_kind(&self) -> &ChannelKind {
        match &self.kind {
            ChannelKind::Truncated { channel, .. } => channel,
            k => k,
        }
    }
}

/// Which point pairs discretise `μ × μ` in eq. 10.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum PairQuadrature {
    /// Every ordered vertex pair (x, y), weight `a_x a_y`: exact, O(n² k).
    AllVertices,
    /// Farthest-point samples (edge-graph geodesic FPS), each carrying the area of its Voronoi
    /// cell (nearest-sample assignment of vertices, weights `a_i`).
    Farthest {
        /// Number of samples for L2 channels (clamped to n).
        samples: usize,
        /// Represent each sample by the area-weighted mean eigenmap row of its Voronoi cell
        /// instead of the sample vertex's own row.
        #[serde(default)]
        cell_means: bool,
        /// Evaluate same-cell and adjacent-cell pairs one-sided exactly (sample to every vertex
        /// of the other cell) instead of sample to sample (ignored with `cell_means`).
        #[serde(default = "yes")]
        near_field: bool,
    },
}

fn yes() -> bool {
    true
}

/// What to compute for a shape: the channels and the discretisation.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct SignatureSpec {
    /// Channels, in order.
    pub channels: Vec<ChannelSpec>,
    /// Pair quadrature of the L2 spectral channels.
    pub quadrature: PairQuadrature,
    /// Quadrature points (pairs and integration nodes) of L1 / L∞ channels (O(m³) per channel).
    pub lp_samples: usize,
    /// Geodesic sources (farthest-point samples with Voronoi weights; targets are all vertices).
    pub geodesic_sources: usize,
    /// Number of quantile intervals stored per distribution channel.
    pub sketch_quantiles: usize,
    /// Per-shape rescaling of the spectrum before kernels are evaluated
    /// ([`crate::scale`]); omitted from the JSON (and key) when `None`.
    #[serde(
        default,
        skip_serializing_if = "crate::scale::SpectrumScaling::is_none"
    )]
    pub spectrum_scaling: crate::scale::SpectrumScaling,
}

impl Default for SignatureSpec {
    fn default() -> Self {
        Self {
            channels: Vec::new(),
            quadrature: PairQuadrature::Farthest {
                samples: 1000,
                cell_means: false,
                near_field: true,
            },
            lp_samples: 500,
            geodesic_sources: 200,
            sketch_quantiles: 1024,
            spectrum_scaling: crate::scale::SpectrumScaling::None,
        }
    }
}

impl SignatureSpec {
    /// A spec with `channels` and the default discretisation.
    pub fn with_channels(channels: Vec<ChannelSpec>) -> Self {
        Self {
            channels,
            ..Self::default()
        }
    }

    /// Stable key (hex SHA-256 prefix of the canonical JSON of the spec) for caches.
    pub fn key(&self) -> String {
        let json = serde_json::to_string(self).unwrap_or_default();
        let digest = Sha256::digest(json.as_bytes());
        hex::encode(&digest[..12])
    }

    /// Channel names, in order.
    pub fn channel_names(&self) -> Vec<String> {
        self.channels.iter().map(|c| c.name()).collect()
    }

    /// The union of several specs (channels deduplicated by name, first occurrence first). The
    /// discretisation of `self` is kept.
    pub fn union(&self, others: &[&SignatureSpec]) -> SignatureSpec {
        let mut out = self.clone();
        let mut names = out.channel_names();
        for o in others {
            for c in &o.channels {
                let n = c.name();
                if !names.contains(&n) {
                    names.push(n);
                    out.channels.push(c.clone());
                }
            }
        }
        out
    }
}

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

/// Stored values of one channel.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum ChannelValues {
    /// A distance distribution.
    Distribution(QuantileSketch),
    /// A plain vector (ShapeDNA).
    Vector(Vec<f64>),
}

/// One channel of a [`Signature`].
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ChannelData {
    /// [`ChannelSpec::name`] of the channel.
    pub name: String,
    /// The values.
    pub values: ChannelValues,
}

/// The signature of one shape under one [`SignatureSpec`].
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Signature {
    /// [`SignatureSpec::key`] of the spec it was computed with.
    pub spec_key: String,
    /// One entry per channel of the spec, in order.
    pub channels: Vec<ChannelData>,
    /// Vertices of the analysed mesh.
    pub vertices: usize,
    /// Total area of the analysed mesh.
    pub area: f64,
    /// Number of pair-quadrature points actually used for L2 channels.
    pub quadrature_points: usize,
}

/// Computes the signature of an analysed shape (see the module docs for the method).
///
/// Errors: [`Error::InvalidArgument`] for an invalid spec (non-positive or non-finite scales,
/// zero samples or quantiles, more ShapeDNA eigenvalues than the spectrum has) or a spectrum that
/// does not match the mesh.
pub fn compute_signature(analysis: &Analysis, spec: &SignatureSpec) -> Result<Signature> {
    validate_spec(spec)?;
    // Scale selection by rescaling the spectrum (crate::scale).
    if !spec.spectrum_scaling.is_none() {
        let mut plain = spec.clone();
        plain.spectrum_scaling = crate::scale::SpectrumScaling::None;
        let mut sig = compute_signature(&spec.spectrum_scaling.apply(analysis), &plain)?;
        sig.spec_key = spec.key();
        return Ok(sig);
    }
    let mesh = &analysis.mesh;
    let sp = &analysis.spectrum;
    let n = mesh.vertices.len();
    if sp.eigenvectors.nrows() != n
        || sp.mass.len() != n
        || sp.eigenvalues.len() != sp.eigenvectors.ncols()
    {
        return Err(Error::InvalidArgument(format!(
            "spectrum ({} × {}, {} masses, {} eigenvalues) does not match the mesh ({n} vertices)",
            sp.eigenvectors.nrows(),
            sp.eigenvectors.ncols(),
            sp.mass.len(),
            sp.eigenvalues.len()
        )));
    }
    if n == 0 {
        return Err(Error::EmptyMesh("no vertices".into()));
    }
    let area: f64 = sp.mass.iter().sum();
    let zero_tol = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI / area;
    let nonzero: Vec<usize> = (0..sp.eigenvalues.len())
        .filter(|&i| sp.eigenvalues[i] > zero_tol)
        .collect();

    // Which quadratures are needed.
    let mut need_l2 = false;
    let mut need_lp = false;
    let mut need_geo = false;
    for c in &spec.channels {
        match c.base_kind() {
            ChannelKind::Spectral { norm, .. }
            | ChannelKind::DistanceAggregate { norm, .. }
            | ChannelKind::DistributionSum { norm, .. } => {
                if *norm == Norm::L2 {
                    need_l2 = true
                } else {
                    need_lp = true
                }
            }
            ChannelKind::Geodesic { .. } => need_geo = true,
            ChannelKind::ShapeDna { count } => {
                if *count > nonzero.len() {
                    return Err(Error::InvalidArgument(format!(
                        "ShapeDNA[{count}] needs {count} non-zero eigenvalues, the spectrum has {}",
                        nonzero.len()
                    )));
                }
            }
            ChannelKind::EuclideanD2 { .. } | ChannelKind::Truncated { .. } => {}
        }
    }
    let l2_samples = match spec.quadrature {
        PairQuadrature::AllVertices => 0,
        PairQuadrature::Farthest { samples, .. } => samples.min(n),
    };
    let (cell_means, near_field) = match spec.quadrature {
        PairQuadrature::Farthest {
            cell_means,
            near_field,
            ..
        } => (cell_means, near_field),
        PairQuadrature::AllVertices => (false, false),
    };
    let lp_samples = spec.lp_samples.min(n);
    let geo_sources = spec.geodesic_sources.min(n);
    let mut prefixes = Vec::new();
    if need_l2 && l2_samples > 0 {
        prefixes.push(l2_samples);
    }
    if need_lp {
        prefixes.push(lp_samples);
    }
    if need_geo {
        prefixes.push(geo_sources);
    }
    let graph = if !prefixes.is_empty() || need_geo {
        Some(EdgeGraph::new(mesh))
    } else {
        None
    };
    let fps = match &graph {
        Some(g) if !prefixes.is_empty() => Some(farthest_points(mesh, g, &prefixes)),
        _ => None,
    };
    let cells = |count: usize| -> Quadrature {
        let f = fps
            .as_ref()
            .expect("farthest points computed for every prefix");
        f.quadrature(count, &sp.mass)
    };
    let l2_quad = need_l2.then(|| {
        if l2_samples == 0 {
            Quadrature::all_vertices(&sp.mass)
        } else {
            cells(l2_samples)
        }
    });
    let lp_quad = need_lp.then(|| cells(lp_samples));
    let geo_quad = need_geo.then(|| cells(geo_sources));

    let phi = sp.eigenvectors.as_ref();
    let l2_rows = l2_quad.as_ref().map(|q| q.rows(phi, &sp.mass, cell_means));
    let near_field_of = |quad: &Option<Quadrature>| match (quad, &graph) {
        (Some(q), Some(g)) if near_field && !cell_means => match (&q.points, &q.owner) {
            (Some(points), Some(owner)) => Some(NearField::new(
                g,
                owner,
                points.clone(),
                &sp.eigenvectors,
                &sp.mass,
            )),
            _ => None,
        },
        _ => None,
    };
    let near = near_field_of(&l2_quad);
    let lp_near = near_field_of(&lp_quad);
    let ctx = SpectralContext {
        l2_rows,
        near,
        lp_near,
        lp_rows: lp_quad.as_ref().map(|q| q.rows(phi, &sp.mass, cell_means)),
        lp_nodes: lp_quad.as_ref().map(|q| q.point_rows(phi)),
        l2_quad,
        lp_quad,
        q: spec.sketch_quantiles,
    };
    let q = ctx.q;

    // Distinct base channels, each computed once: a truncated channel reuses the distances of
    // its full channel when both are in the spec.
    let mut bases: Vec<&ChannelKind> = Vec::new();
    for c in &spec.channels {
        if !bases.contains(&c.base_kind()) {
            bases.push(c.base_kind());
        }
    }
    let base_values: Vec<Result<ChannelValues>> = bases
        .par_iter()
        .map(|&kind| {
            Ok(match kind {
                ChannelKind::Spectral { kernel, norm } => {
                    let w = vec![transfer_weights(kernel, &sp.eigenvalues, zero_tol)];
                    spectral_channel(&w, *norm, PairMode::Single, &ctx)
                }
                ChannelKind::DistanceAggregate {
                    ts,
                    norm,
                    aggregation,
                } => {
                    let w = heat_weights(ts, &sp.eigenvalues, zero_tol);
                    spectral_channel(&w, *norm, PairMode::Aggregate(*aggregation), &ctx)
                }
                ChannelKind::DistributionSum { ts, norm } => {
                    let w = heat_weights(ts, &sp.eigenvalues, zero_tol);
                    spectral_channel(&w, *norm, PairMode::Mixture, &ctx)
                }
                ChannelKind::Geodesic { radius } => {
                    ChannelValues::Distribution(crate::baseline::geodesic_sketch(
                        mesh,
                        graph.as_ref().expect("graph built for geodesic channels"),
                        geo_quad.as_ref().expect("geodesic quadrature"),
                        &sp.mass,
                        *radius,
                        q,
                    ))
                }
                ChannelKind::EuclideanD2 { samples } => {
                    ChannelValues::Distribution(crate::baseline::d2_sketch(mesh, *samples, q))
                }
                ChannelKind::ShapeDna { count } => ChannelValues::Vector(
                    nonzero
                        .iter()
                        .take(*count)
                        .map(|&i| sp.eigenvalues[i])
                        .collect(),
                ),
                ChannelKind::Truncated { .. } => {
                    return Err(Error::InvalidArgument("nested truncated channel".into()))
                }
            })
        })
        .collect();
    let base_values = base_values.into_iter().collect::<Result<Vec<_>>>()?;
    let channels: Vec<ChannelData> = spec
        .channels
        .iter()
        .map(|c| {
            let b = bases
                .iter()
                .position(|&k| k == c.base_kind())
                .expect("every base kind listed");
            let values = match (&c.kind, &base_values[b]) {
                (ChannelKind::Truncated { radius, .. }, ChannelValues::Distribution(d)) => {
                    ChannelValues::Distribution(truncate_sketch(d, *radius))
                }
                (_, v) => v.clone(),
            };
            ChannelData {
                name: c.name(),
                values,
            }
        })
        .collect();
    Ok(Signature {
        spec_key: spec.key(),
        channels,
        vertices: n,
        area,
        quadrature_points: ctx.l2_quad.as_ref().map_or(0, |q| q.len()),
    })
}

/// Eigenvalues `λ ≤ ZERO_MODE_TOLERANCE · 4π / area` are zero modes (λ_0 of each component)
/// and get kernel weight 0.
pub const ZERO_MODE_TOLERANCE: f64 = 1e-6;

fn validate_spec(spec: &SignatureSpec) -> Result<()> {
    let bad = |m: String| Err(Error::InvalidArgument(m));
    if spec.sketch_quantiles == 0 || spec.sketch_quantiles > 1 << 20 {
        return bad(format!(
            "sketch_quantiles must be in 1..=2^20, got {}",
            spec.sketch_quantiles
        ));
    }
    if let PairQuadrature::Farthest { samples: 0, .. } = spec.quadrature {
        return bad("quadrature samples must be ≥ 1".into());
    }
    if spec.lp_samples == 0 || spec.geodesic_sources == 0 {
        return bad("lp_samples and geodesic_sources must be ≥ 1".into());
    }
    let check_t = |t: f64| t.is_finite() && t > 0.0;
    match spec.spectrum_scaling {
        crate::scale::SpectrumScaling::Lambda1 { reference } if !check_t(reference) => {
            return bad(format!(
                "spectrum_scaling: reference must be finite and > 0, got {reference}"
            ));
        }
        crate::scale::SpectrumScaling::WeylFit {
            eigenpairs: Some(m),
        } if m < 2 => {
            return bad(format!("spectrum_scaling: eigenpairs must be ≥ 2, got {m}"));
        }
        _ => {}
    }
    for c in &spec.channels {
        if let ChannelKind::Truncated { channel, radius } = &c.kind {
            if !(radius.is_finite() && *radius > 0.0)
                || matches!(
                    **channel,
                    ChannelKind::Truncated { .. } | ChannelKind::ShapeDna { .. }
                )
            {
                return bad(format!("invalid channel {}", c.name()));
            }
        }
        let ok = match c.base_kind() {
            ChannelKind::Spectral { kernel, .. } => match kernel {
                Kernel::Heat { t } => check_t(*t),
                Kernel::CommuteTime => true,
                Kernel::Step { lambda_c } => lambda_c.is_finite() && *lambda_c > 0.0,
                Kernel::HeatAggregate { ts, .. } => {
                    !ts.is_empty() && ts.iter().all(|&t| check_t(t))
                }
            },
            ChannelKind::DistanceAggregate { ts, .. } | ChannelKind::DistributionSum { ts, .. } => {
                !ts.is_empty() && ts.iter().all(|&t| check_t(t))
            }
            ChannelKind::Geodesic { radius } => radius.is_none_or(|r| r.is_finite() && r > 0.0),
            ChannelKind::EuclideanD2 { samples } => *samples >= 2 && *samples <= 100_000,
            ChannelKind::ShapeDna { count } => *count >= 1,
            ChannelKind::Truncated { .. } => false,
        };
        if !ok {
            return bad(format!("invalid channel {}", c.name()));
        }
    }
    Ok(())
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

/// `K(λ_i)` of `kernel` for every eigenvalue, 0 on zero modes.
pub fn transfer_weights(kernel: &Kernel, eigenvalues: &[f64], zero_tol: f64) -> Vec<f64> {
    eigenvalues
        .iter()
        .map(|&l| {
            if l <= zero_tol {
                return 0.0;
            }
            match kernel {
                Kernel::Heat { t } => (-t * l).exp(),
                Kernel::CommuteTime => 1.0 / l.sqrt(),
                Kernel::Step { lambda_c } => {
                    if l < *lambda_c {
                        1.0
                    } else {
                        0.0
                    }
                }
                Kernel::HeatAggregate { ts, aggregation } => match aggregation {
                    Aggregation::Sum2 => {
                        ts.iter().map(|t| (-2.0 * t * l).exp()).sum::<f64>().sqrt()
                    }
                    a => a.apply(ts.iter().map(|t| (-t * l).exp())),
                },
            }
        })
        .collect()
}

fn heat_weights(ts: &[f64], eigenvalues: &[f64], zero_tol: f64) -> Vec<Vec<f64>> {
    ts.iter()
        .map(|&t| transfer_weights(&Kernel::Heat { t }, eigenvalues, zero_tol))
        .collect()
}

/// How the per-scale distances of one pair become histogram entries.
#[derive(Clone, Copy, Debug)]
enum PairMode {
    /// One scale.
    Single,
    /// One entry `A_t d_t` (distance-stage aggregation).
    Aggregate(Aggregation),
    /// One entry per scale (distribution-stage sum).
    Mixture,
}

/// Everything the spectral channels share: quadratures, eigenmap rows, near field.
struct SpectralContext<'a> {
    l2_quad: Option<Quadrature>,
    l2_rows: Option<Mat<f64>>,
    near: Option<NearField<'a>>,
    lp_near: Option<NearField<'a>>,
    lp_quad: Option<Quadrature>,
    lp_rows: Option<Mat<f64>>,
    lp_nodes: Option<Mat<f64>>,
    q: usize,
}

fn spectral_channel(
    weights: &[Vec<f64>],
    norm: Norm,
    mode: PairMode,
    ctx: &SpectralContext<'_>,
) -> ChannelValues {
    let fine = match norm {
        Norm::L2 => {
            let quad = ctx.l2_quad.as_ref().expect("L2 quadrature");
            let rows = ctx.l2_rows.as_ref().expect("L2 rows");
            l2_pairs(
                rows.as_ref(),
                &quad.weights,
                weights,
                mode,
                ctx.near.as_ref(),
            )
        }
        Norm::L1 | Norm::LInf => {
            let quad = ctx.lp_quad.as_ref().expect("Lp quadrature");
            lp_pairs(
                ctx.lp_rows.as_ref().expect("Lp rows").as_ref(),
                ctx.lp_nodes.as_ref().expect("Lp nodes").as_ref(),
                &quad.weights,
                weights,
                norm == Norm::LInf,
                mode,
                ctx.lp_near.as_ref(),
            )
        }
    };
    ChannelValues::Distribution(fine.sketch(ctx.q))
}

/// Columns `i` with `w_i² ≥ 1e-16 · max w²` (the rest change d² by less than 1e-16 relative),
/// and the scaled embedding `rows[:, i] · w_i` restricted to them.
fn weighted_embedding(rows: MatRef<'_, f64>, w: &[f64]) -> Mat<f64> {
    let keep = kept_columns(w, rows.ncols());
    Mat::from_fn(rows.nrows(), keep.len(), |r, c| {
        rows[(r, keep[c])] * w[keep[c]]
    })
}

/// Indices `i < ncols` with `w_i ≠ 0` and `|w_i| ≥ 10⁻⁸ max |w|`.
fn kept_columns(w: &[f64], ncols: usize) -> Vec<usize> {
    let wmax = w.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
    (0..w.len().min(ncols))
        .filter(|&i| w[i] != 0.0 && w[i].abs() >= 1e-8 * wmax)
        .collect()
}

/// Row ranges of an m × m upper triangle (diagonal included) with about equal pair counts.
fn row_chunks(m: usize) -> Vec<(usize, usize)> {
    let chunks = (m / 48).clamp(1, 4096);
    let total = m * (m + 1) / 2;
    let mut out = Vec::with_capacity(chunks);
    let (mut start, mut acc) = (0usize, 0usize);
    for i in 0..m {
        acc += m - i;
        if acc * chunks >= total * (out.len() + 1) {
            out.push((start, i + 1));
            start = i + 1;
        }
    }
    if start < m {
        out.push((start, m));
    }
    out
}

/// Runs `f(r0, r1, fine)` over the row chunks of an m-point pair set, in parallel, merging the
/// per-chunk histograms in chunk order (deterministic whatever the thread count).
fn chunked_pairs<F>(m: usize, bound: f64, f: F) -> FineHistogram
where
    F: Fn(usize, usize, &mut FineHistogram) + Sync,
{
    let chunks = row_chunks(m);
    let mut total = FineHistogram::new(bound);
    for group in chunks.chunks(16) {
        let parts: Vec<FineHistogram> = group
            .par_iter()
            .map(|&(r0, r1)| {
                let mut h = FineHistogram::new(bound);
                f(r0, r1, &mut h);
                h
            })
            .collect();
        for p in &parts {
            total.merge(p);
        }
    }
    total
}

fn combine(mode: PairMode, d: &[f64], w: f64, fine: &mut FineHistogram) {
    match mode {
        PairMode::Single => fine.add(d[0], w),
        PairMode::Aggregate(a) => fine.add(a.apply(d.iter().copied()), w),
        PairMode::Mixture => {
            for &x in d {
                fine.add(x, w)
            }
        }
    }
}

fn mode_bound(mode: PairMode, per_scale: &[f64]) -> f64 {
    match mode {
        PairMode::Single => per_scale[0],
        PairMode::Aggregate(a) => a.apply(per_scale.iter().copied()),
        PairMode::Mixture => per_scale.iter().fold(0.0, |a: f64, &b| a.max(b)),
    }
}

fn diag_weight(mode: PairMode, scales: usize) -> f64 {
    match mode {
        PairMode::Mixture => scales as f64,
        _ => 1.0,
    }
}

/// Near field of a farthest-point quadrature: pairs of the same or adjacent Voronoi cells are
/// evaluated one-sided exactly, `W_i Σ_{y ∈ cell j} a_y δ(d(s_i, y))` instead of
/// `W_i W_j δ(d(s_i, s_j))`, so that small distances are not quantised to the sample spacing.
pub(crate) struct NearField<'a> {
    /// Per sample: adjacent samples (cells sharing a mesh edge) with a larger index, sorted.
    adj: Vec<Vec<u32>>,
    /// Per sample: every adjacent sample, sorted.
    nbrs: Vec<Vec<u32>>,
    /// Per sample: member vertices of its cell.
    members: Vec<Vec<u32>>,
    /// Sample vertices.
    samples: Vec<u32>,
    /// Eigenvectors at every vertex.
    phi: &'a Mat<f64>,
    /// Vertex areas.
    mass: &'a [f64],
}

impl<'a> NearField<'a> {
    fn new(
        graph: &EdgeGraph,
        owner: &[u32],
        samples: Vec<u32>,
        phi: &'a Mat<f64>,
        mass: &'a [f64],
    ) -> Self {
        let m = samples.len();
        let mut adj = vec![Vec::new(); m];
        let mut members = vec![Vec::new(); m];
        for (v, &o) in owner.iter().enumerate() {
            if (o as usize) >= m {
                continue;
            }
            members[o as usize].push(v as u32);
            for e in graph.offsets[v]..graph.offsets[v + 1] {
                let p = owner[graph.nbrs[e] as usize];
                if p > o && (p as usize) < m {
                    adj[o as usize].push(p);
                }
            }
        }
        for a in &mut adj {
            a.sort_unstable();
            a.dedup();
        }
        let mut nbrs = adj.clone();
        for (i, a) in adj.iter().enumerate() {
            for &j in a {
                nbrs[j as usize].push(i as u32);
            }
        }
        for a in &mut nbrs {
            a.sort_unstable();
        }
        Self {
            adj,
            nbrs,
            members,
            samples,
            phi,
            mass,
        }
    }
}

/// Row-major `n × kept` embedding `φ_i(v) w_i` of every vertex (the columns of
/// [`weighted_embedding`]).
fn vertex_embedding(phi: &Mat<f64>, w: &[f64]) -> (Vec<f64>, usize) {
    let keep = kept_columns(w, phi.ncols());
    let (n, k) = (phi.nrows(), keep.len());
    let mut out = vec![0.0; n * k];
    // Blocked transpose: a block of 64 output rows stays in cache while the columns are read.
    for v0 in (0..n).step_by(64) {
        let v1 = (v0 + 64).min(n);
        for (c, &i) in keep.iter().enumerate() {
            let wi = w[i];
            for (v, x) in phi.col_as_slice(i)[v0..v1].iter().enumerate() {
                out[(v0 + v) * k + c] = x * wi;
            }
        }
    }
    (out, k)
}

/// Eq. 9 distances between all quadrature points, `d² = |ψ_i|² + |ψ_j|² − 2 ψ_i·ψ_j` (GEMM per
/// row chunk), every ordered pair weighted `w_i w_j`; with a [`NearField`], same-cell and
/// adjacent-cell pairs are replaced by sample-to-vertex pairs.
fn l2_pairs(
    rows: MatRef<'_, f64>,
    pw: &[f64],
    weights: &[Vec<f64>],
    mode: PairMode,
    near: Option<&NearField<'_>>,
) -> FineHistogram {
    let m = rows.nrows();
    let psi: Vec<Mat<f64>> = weights
        .iter()
        .map(|w| weighted_embedding(rows, w))
        .collect();
    let sq: Vec<Vec<f64>> = psi
        .iter()
        .map(|p| {
            (0..m)
                .map(|i| (0..p.ncols()).map(|c| p[(i, c)] * p[(i, c)]).sum())
                .collect()
        })
        .collect();
    let full: Vec<(Vec<f64>, usize)> = match near {
        Some(nf) => weights
            .iter()
            .map(|w| vertex_embedding(nf.phi, w))
            .collect(),
        None => Vec::new(),
    };
    let top2 = |it: &mut dyn Iterator<Item = f64>| {
        let (mut a, mut b) = (0.0f64, 0.0f64);
        for v in it {
            if v > a {
                b = a;
                a = v;
            } else if v > b {
                b = v;
            }
        }
        a.sqrt() + b.sqrt()
    };
    // d(x, y) ≤ |ψ_x| + |ψ_y| ≤ the two largest norms (over every vertex with a near field).
    let per_scale: Vec<f64> = if near.is_some() {
        full.iter()
            .map(|(e, k)| top2(&mut e.chunks(*k.max(&1)).map(|r| r.iter().map(|x| x * x).sum())))
            .collect()
    } else {
        sq.iter().map(|s| top2(&mut s.iter().copied())).collect()
    };
    let bound = mode_bound(mode, &per_scale);
    let ns = psi.len();
    let dw = diag_weight(mode, ns);
    let empty: Vec<u32> = Vec::new();
    let far = chunked_pairs(m, bound, |r0, r1, fine| {
        let r = r1 - r0;
        let gs: Vec<Mat<f64>> = psi
            .iter()
            .map(|p| {
                let mut g = Mat::<f64>::zeros(m - r0, r);
                if p.ncols() > 0 {
                    matmul(
                        g.as_mut(),
                        Accum::Replace,
                        p.as_ref().subrows(r0, m - r0),
                        p.as_ref().subrows(r0, r).transpose(),
                        1.0,
                        Par::Seq,
                    );
                }
                g
            })
            .collect();
        let mut d = vec![0.0; ns];
        for ii in 0..r {
            let i = r0 + ii;
            let skip: &[u32] = near.map_or(&empty, |nf| &nf.adj[i]);
            // Far field: j > i not adjacent to i, in segments between adjacent indices.
            let mut lo = i + 1;
            for stop in skip.iter().map(|&a| a as usize).chain(std::iter::once(m)) {
                if let (PairMode::Single, [g]) = (mode, gs.as_slice()) {
                    let sq = &sq[0];
                    let (si, wi) = (sq[i], 2.0 * pw[i]);
                    let col = &g.col_as_slice(ii)[lo - r0..stop - r0];
                    for ((gij, sj), wj) in col.iter().zip(&sq[lo..stop]).zip(&pw[lo..stop]) {
                        fine.add((si + sj - 2.0 * gij).max(0.0).sqrt(), wi * wj);
                    }
                } else {
                    let cols: Vec<&[f64]> = gs.iter().map(|g| g.col_as_slice(ii)).collect();
                    for j in lo..stop {
                        for ((ds, sqs), col) in d.iter_mut().zip(&sq).zip(&cols) {
                            *ds = (sqs[i] + sqs[j] - 2.0 * col[j - r0]).max(0.0).sqrt();
                        }
                        combine(mode, &d, 2.0 * pw[i] * pw[j], fine);
                    }
                }
                lo = stop + 1;
            }
            if near.is_none() {
                fine.add_zero(pw[i] * pw[i] * dw);
            }
        }
    });
    let Some(nf) = near else {
        return far;
    };
    // Near field, cell by cell (each cell's member rows are read once): pairs (s_a, y) for
    // y in cell b and a = b or a adjacent to b, weight W_a a_y.
    let mut total = far;
    let ncell = nf.members.len();
    let groups: Vec<usize> = (0..ncell).step_by(64).collect();
    for block in groups.chunks(16) {
        let parts: Vec<FineHistogram> = block
            .par_iter()
            .map(|&b0| {
                let mut fine = FineHistogram::new(bound);
                let mut d = vec![0.0; ns];
                for b in b0..(b0 + 64).min(ncell) {
                    for &y in &nf.members[b] {
                        let y = y as usize;
                        for a in std::iter::once(b).chain(nf.nbrs[b].iter().map(|&a| a as usize)) {
                            let s = nf.samples[a] as usize;
                            for (ds, (e, k)) in d.iter_mut().zip(&full) {
                                *ds = squared_distance(
                                    &e[s * k..(s + 1) * k],
                                    &e[y * k..(y + 1) * k],
                                )
                                .sqrt();
                            }
                            combine(mode, &d, pw[a] * nf.mass[y], &mut fine);
                        }
                    }
                }
                fine
            })
            .collect();
        for p in &parts {
            total.merge(p);
        }
    }
    total
}

/// L1 / L∞ distances `‖k(x,·) − k(y,·)‖` with the kernel rows evaluated on the quadrature nodes
/// (weights `pw`, the same points as the pair set).
fn lp_pairs(
    rows: MatRef<'_, f64>,
    nodes: MatRef<'_, f64>,
    pw: &[f64],
    weights: &[Vec<f64>],
    inf: bool,
    mode: PairMode,
    near: Option<&NearField<'_>>,
) -> FineHistogram {
    let m = rows.nrows();
    let mz = nodes.nrows();
    // Kernel rows K[x][z] = Σ_i w_i φ_i(x) φ_i(z) of the points `at` (rows), as columns of an
    // mz × rows matrix.
    let kernel_rows = |at: MatRef<'_, f64>, w: &[f64]| -> Mat<f64> {
        let psi = weighted_embedding(at, w);
        let keep = kept_columns(w, at.ncols());
        let z = Mat::from_fn(mz, keep.len(), |r, c| nodes[(r, keep[c])]);
        let mut k = Mat::<f64>::zeros(mz, at.nrows());
        if !keep.is_empty() {
            matmul(
                k.as_mut(),
                Accum::Replace,
                z.as_ref(),
                psi.as_ref().transpose(),
                1.0,
                Par::Seq,
            );
        }
        k
    };
    let kr: Vec<Mat<f64>> = weights.iter().map(|w| kernel_rows(rows, w)).collect();
    // With a near field: kernel rows of every vertex.
    let kall: Vec<Mat<f64>> = match near {
        Some(nf) => weights
            .iter()
            .map(|w| kernel_rows(nf.phi.as_ref(), w))
            .collect(),
        None => Vec::new(),
    };
    let dist = |a: &[f64], b: &[f64]| -> f64 {
        if inf {
            max_abs_difference(a, b)
        } else {
            weighted_l1_distance(a, b, pw)
        }
    };
    let per_scale: Vec<f64> = kr
        .iter()
        .chain(kall.iter())
        .map(|k| {
            2.0 * (0..k.ncols())
                .map(|i| {
                    let a = k.col_as_slice(i);
                    if inf {
                        a.iter().fold(0.0f64, |acc, x| acc.max(x.abs()))
                    } else {
                        a.iter().zip(pw).map(|(x, wz)| wz * x.abs()).sum()
                    }
                })
                .fold(0.0f64, f64::max)
        })
        .collect();
    let ns = kr.len();
    let per_scale: Vec<f64> = (0..ns)
        .map(|s| {
            per_scale[s].max(if kall.is_empty() {
                0.0
            } else {
                per_scale[ns + s]
            })
        })
        .collect();
    let bound = mode_bound(mode, &per_scale);
    let dw = diag_weight(mode, ns);
    let empty: Vec<u32> = Vec::new();
    chunked_pairs(m, bound, |r0, r1, fine| {
        let mut d = vec![0.0; ns];
        for i in r0..r1 {
            let skip: &[u32] = near.map_or(&empty, |nf| &nf.adj[i]);
            let mut lo = i + 1;
            for stop in skip.iter().map(|&a| a as usize).chain(std::iter::once(m)) {
                for j in lo..stop {
                    for (ds, k) in d.iter_mut().zip(&kr) {
                        *ds = dist(k.col_as_slice(i), k.col_as_slice(j));
                    }
                    combine(mode, &d, 2.0 * pw[i] * pw[j], fine);
                }
                lo = stop + 1;
            }
            match near {
                None => fine.add_zero(pw[i] * pw[i] * dw),
                Some(nf) => {
                    let mut one_sided = |a: usize, b: usize, fine: &mut FineHistogram| {
                        for &y in &nf.members[b] {
                            for ((ds, k), ka) in d.iter_mut().zip(&kr).zip(&kall) {
                                *ds = dist(k.col_as_slice(a), ka.col_as_slice(y as usize));
                            }
                            combine(mode, &d, pw[a] * nf.mass[y as usize], fine);
                        }
                    };
                    one_sided(i, i, fine);
                    for &j in skip {
                        one_sided(i, j as usize, fine);
                        one_sided(j as usize, i, fine);
                    }
                }
            }
        }
    })
}

/// `Σ (a_i − b_i)²` with four independent accumulators (fixed order: deterministic).
#[inline]
fn squared_distance(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            let t = x[l] - y[l];
            acc[l] += t * t;
        }
    }
    let mut tail = 0.0;
    for (x, y) in ra.iter().zip(rb) {
        tail += (x - y) * (x - y);
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// `Σ w_i |a_i − b_i|` with four independent accumulators (fixed order: deterministic).
#[inline]
fn weighted_l1_distance(a: &[f64], b: &[f64], w: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb, cw) = (a.chunks_exact(4), b.chunks_exact(4), w.chunks_exact(4));
    let (ra, rb, rw) = (ca.remainder(), cb.remainder(), cw.remainder());
    for ((x, y), z) in ca.zip(cb).zip(cw) {
        for l in 0..4 {
            acc[l] += z[l] * (x[l] - y[l]).abs();
        }
    }
    let mut tail = 0.0;
    for ((x, y), z) in ra.iter().zip(rb).zip(rw) {
        tail += z * (x - y).abs();
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// `max |a_i − b_i|`.
#[inline]
fn max_abs_difference(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            acc[l] = acc[l].max((x[l] - y[l]).abs());
        }
    }
    let mut m = acc[0].max(acc[1]).max(acc[2].max(acc[3]));
    for (x, y) in ra.iter().zip(rb) {
        m = m.max((x - y).abs());
    }
    m
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

/// The undirected edge graph of a mesh (CSR, Euclidean edge lengths).
#[derive(Clone, Debug)]
pub(crate) struct EdgeGraph {
    pub(crate) offsets: Vec<usize>,
    pub(crate) nbrs: Vec<u32>,
    pub(crate) lens: Vec<f64>,
}

impl EdgeGraph {
    pub(crate) fn new(mesh: &Mesh) -> Self {
        let n = mesh.vertices.len();
        let mut e: Vec<(u32, u32)> = Vec::with_capacity(mesh.faces.len() * 6);
        for f in &mesh.faces {
            for k in 0..3 {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                if a != b && (a as usize) < n && (b as usize) < n {
                    e.push((a, b));
                    e.push((b, a));
                }
            }
        }
        e.sort_unstable();
        e.dedup();
        let mut offsets = vec![0usize; n + 1];
        for &(a, _) in &e {
            offsets[a as usize + 1] += 1;
        }
        for i in 0..n {
            offsets[i + 1] += offsets[i];
        }
        let nbrs: Vec<u32> = e.iter().map(|&(_, b)| b).collect();
        let lens = e
            .iter()
            .map(|&(a, b)| norm(sub(mesh.vertices[a as usize], mesh.vertices[b as usize])))
            .collect();
        Self {
            offsets,
            nbrs,
            lens,
        }
    }

    /// Dijkstra from `src`, lowering `dist` only where the new distance is strictly smaller
    /// (with `owner` set to `id` there): run with `dist = ∞` for a full single-source run, or
    /// repeatedly for an incremental multi-source (Voronoi) run.
    pub(crate) fn relax_from(
        &self,
        src: usize,
        dist: &mut [f64],
        owner: &mut [u32],
        id: u32,
        heap: &mut BinaryHeap<Reverse<(u64, u32)>>,
    ) {
        heap.clear();
        dist[src] = 0.0;
        owner[src] = id;
        heap.push(Reverse((0f64.to_bits(), src as u32)));
        while let Some(Reverse((db, v))) = heap.pop() {
            let d = f64::from_bits(db);
            let v = v as usize;
            if d > dist[v] {
                continue;
            }
            for e in self.offsets[v]..self.offsets[v + 1] {
                let u = self.nbrs[e] as usize;
                let nd = d + self.lens[e];
                if nd < dist[u] {
                    dist[u] = nd;
                    owner[u] = id;
                    heap.push(Reverse((nd.to_bits(), u as u32)));
                }
            }
        }
    }
}

/// Farthest-point samples (edge-graph geodesic FPS) and their Voronoi assignments at the
/// requested prefix sizes.
pub(crate) struct FarthestPoints {
    pub(crate) samples: Vec<u32>,
    /// (prefix size, owner of every vertex among the first `prefix` samples).
    owners: Vec<(usize, Vec<u32>)>,
}

/// Point set with weights: either sample vertices with their Voronoi-cell areas, or all
/// vertices with their areas.
pub(crate) struct Quadrature {
    /// Sample vertices (`None`: all vertices).
    points: Option<Vec<u32>>,
    /// Owner (cell) of every vertex, for cell means.
    owner: Option<Vec<u32>>,
    /// Weight of each point (sums to the area).
    pub(crate) weights: Vec<f64>,
}

impl Quadrature {
    fn all_vertices(mass: &[f64]) -> Self {
        Self {
            points: None,
            owner: None,
            weights: mass.to_vec(),
        }
    }

    fn len(&self) -> usize {
        self.weights.len()
    }

    /// Eigenmap rows at the points themselves.
    fn point_rows(&self, phi: MatRef<'_, f64>) -> Mat<f64> {
        match &self.points {
            None => phi.to_owned(),
            Some(p) => Mat::from_fn(p.len(), phi.ncols(), |r, c| phi[(p[r] as usize, c)]),
        }
    }

    /// Sample vertex indices (all vertices when the quadrature is exact).
    pub(crate) fn point_indices(&self) -> Vec<u32> {
        match &self.points {
            Some(p) => p.clone(),
            None => (0..self.weights.len() as u32).collect(),
        }
    }

    /// Representative eigenmap rows of the pair points: the sample vertices' rows, or (with
    /// `cell_means`) the area-weighted mean row of each Voronoi cell.
    fn rows(&self, phi: MatRef<'_, f64>, mass: &[f64], cell_means: bool) -> Mat<f64> {
        match (&self.owner, cell_means) {
            (Some(owner), true) => {
                let m = self.weights.len();
                let k = phi.ncols();
                let mut out = Mat::<f64>::zeros(m, k);
                for c in 0..k {
                    let col = phi.col(c);
                    let o = out.col_as_slice_mut(c);
                    for (v, &ow) in owner.iter().enumerate() {
                        if (ow as usize) < m {
                            o[ow as usize] += mass[v] * col[v];
                        }
                    }
                    for (x, w) in o.iter_mut().zip(&self.weights) {
                        if *w > 0.0 {
                            *x /= w;
                        }
                    }
                }
                out
            }
            _ => self.point_rows(phi),
        }
    }
}

impl FarthestPoints {
    pub(crate) fn quadrature(&self, count: usize, mass: &[f64]) -> Quadrature {
        let (size, owner) = self
            .owners
            .iter()
            .find(|(s, _)| *s >= count)
            .or_else(|| self.owners.last())
            .expect("at least one prefix");
        let size = (*size).min(self.samples.len());
        let mut weights = vec![0.0; size];
        for (v, &o) in owner.iter().enumerate() {
            if (o as usize) < size {
                weights[o as usize] += mass[v];
            }
        }
        Quadrature {
            points: Some(self.samples[..size].to_vec()),
            owner: Some(owner.clone()),
            weights,
        }
    }
}

/// Geodesic farthest-point sampling on the edge graph. The first sample is the vertex farthest
/// (Euclidean) from the area-weighted centroid; each next one is the vertex farthest (graph
/// distance) from all previous samples (lowest index on exact ties; vertices of components
/// without a sample are at distance ∞, so every component gets one early). Vertex owners are
/// snapshotted when the sample count reaches each of `prefixes`.
pub(crate) fn farthest_points(
    mesh: &Mesh,
    graph: &EdgeGraph,
    prefixes: &[usize],
) -> FarthestPoints {
    let n = mesh.vertices.len();
    let mut wanted: Vec<usize> = prefixes.iter().map(|&p| p.clamp(1, n)).collect();
    wanted.sort_unstable();
    wanted.dedup();
    let total = *wanted.last().unwrap_or(&1);
    // Area-weighted centroid (vertex areas from the faces).
    let mut c = [0.0; 3];
    let mut asum = 0.0;
    for f in &mesh.faces {
        let a = crate::mesh::triangle_area(mesh, f);
        for &v in f {
            let p = mesh.vertices[v as usize];
            for k in 0..3 {
                c[k] += a * p[k];
            }
        }
        asum += 3.0 * a;
    }
    if asum > 0.0 {
        for x in &mut c {
            *x /= asum;
        }
    }
    let mut start = 0usize;
    let mut best = -1.0;
    for (i, p) in mesh.vertices.iter().enumerate() {
        let d = norm(sub(*p, c));
        if d > best {
            best = d;
            start = i;
        }
    }
    let mut dist = vec![f64::INFINITY; n];
    let mut owner = vec![u32::MAX; n];
    let mut heap = BinaryHeap::new();
    let mut samples = Vec::with_capacity(total);
    let mut owners = Vec::with_capacity(wanted.len());
    let mut next = start;
    while samples.len() < total {
        let id = samples.len() as u32;
        samples.push(next as u32);
        graph.relax_from(next, &mut dist, &mut owner, id, &mut heap);
        if wanted.contains(&samples.len()) {
            owners.push((samples.len(), owner.clone()));
        }
        // Farthest vertex from the current samples.
        let mut far = 0usize;
        let mut fd = -1.0;
        for (i, &d) in dist.iter().enumerate() {
            if d > fd {
                fd = d;
                far = i;
            }
        }
        if fd <= 0.0 {
            break;
        }
        next = far;
    }
    if owners.last().map(|(s, _)| *s) != Some(samples.len()) {
        owners.push((samples.len(), owner));
    }
    FarthestPoints { samples, owners }
}

const MAGIC: &[u8; 4] = b"SSG1";

impl Signature {
    /// Compact binary encoding (little endian, exact f64), see [`Signature::from_bytes`].
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut w = Vec::with_capacity(64 + self.channels.len() * 4200);
        w.extend_from_slice(MAGIC);
        put_str(&mut w, &self.spec_key);
        put_u64(&mut w, self.vertices as u64);
        put_f64(&mut w, self.area);
        put_u64(&mut w, self.quadrature_points as u64);
        put_u64(&mut w, self.channels.len() as u64);
        for c in &self.channels {
            put_str(&mut w, &c.name);
            match &c.values {
                ChannelValues::Distribution(s) => {
                    w.push(0);
                    put_f64(&mut w, s.mass);
                    put_f64_array(&mut w, &s.quantiles);
                }
                ChannelValues::Vector(v) => {
                    w.push(1);
                    put_f64_array(&mut w, v);
                }
            }
        }
        w
    }

    /// Decodes [`Signature::to_bytes`]; malformed input is an [`Error::InvalidArgument`].
    pub fn from_bytes(b: &[u8]) -> Result<Self> {
        let mut r = Reader(ByteReader::new(b));
        if r.take(4)? != MAGIC {
            return Err(Error::InvalidArgument("signature: bad magic".into()));
        }
        let spec_key = r.string()?;
        let vertices = r.u64()? as usize;
        let area = r.f64()?;
        let quadrature_points = r.u64()? as usize;
        let nch = r.u64()? as usize;
        if nch > b.len() {
            return Err(Error::InvalidArgument(
                "signature: bad channel count".into(),
            ));
        }
        let mut channels = Vec::with_capacity(nch);
        for _ in 0..nch {
            let name = r.string()?;
            let tag = r.take(1)?[0];
            let values = match tag {
                0 => {
                    let mass = r.f64()?;
                    let quantiles = r.f64s()?;
                    ChannelValues::Distribution(QuantileSketch { mass, quantiles })
                }
                1 => ChannelValues::Vector(r.f64s()?),
                _ => return Err(Error::InvalidArgument("signature: bad channel tag".into())),
            };
            channels.push(ChannelData { name, values });
        }
        if !r.0.at_end() {
            return Err(Error::InvalidArgument("signature: trailing bytes".into()));
        }
        Ok(Signature {
            spec_key,
            channels,
            vertices,
            area,
            quadrature_points,
        })
    }

    /// The channel called `name`, if any.
    pub fn channel(&self, name: &str) -> Option<&ChannelData> {
        self.channels.iter().find(|c| c.name == name)
    }
}

fn put_str(w: &mut Vec<u8>, s: &str) {
    put_u64(w, s.len() as u64);
    w.extend_from_slice(s.as_bytes());
}

/// A length-prefixed `f64` array.
fn put_f64_array(w: &mut Vec<u8>, v: &[f64]) {
    put_u64(w, v.len() as u64);
    put_f64s(w, v);
}

/// [`ByteReader`] with this format's errors.
struct Reader<'a>(ByteReader<'a>);

fn truncated() -> Error {
    Error::InvalidArgument("signature: truncated".into())
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        self.0.take(n).ok_or_else(truncated)
    }
    fn u64(&mut self) -> Result<u64> {
        self.0.u64().ok_or_else(truncated)
    }
    fn f64(&mut self) -> Result<f64> {
        self.0.f64().ok_or_else(truncated)
    }
    fn string(&mut self) -> Result<String> {
        let n = self.u64()? as usize;
        let s = self.take(n)?;
        String::from_utf8(s.to_vec())
            .map_err(|_| Error::InvalidArgument("signature: bad utf-8".into()))
    }
    /// A length-prefixed `f64` array.
    fn f64s(&mut self) -> Result<Vec<f64>> {
        let n = self.u64()? as usize;
        self.0.f64s(n).ok_or_else(truncated)
    }
}

#[cfg(test)]
#[path = "signature_tests.rs"]
mod tests;
