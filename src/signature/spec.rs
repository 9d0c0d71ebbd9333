//! What to compute for a shape: channels (kernel × norm × scale, scale aggregates, baselines),
//! the pair quadrature and the sketch resolution, with their validation and stable names/keys.

use crate::mesh::cap::CapOptions;
use crate::mesh::smooth::SmoothOptions;
use crate::mesh::topology::HandleCutOptions;
use crate::scale::SpectrumScaling;
use crate::spectrum::AnalyzeOptions;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

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

fn unit_weight() -> f64 {
    1.0
}

fn is_unit_weight(w: &f64) -> bool {
    *w == 1.0
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
    /// Baseline: ShapeDNA, the first `count` non-zero eigenvalues (a vector, not a distribution),
    /// each multiplied by `weight`.
    ShapeDna {
        /// Number of eigenvalues.
        count: usize,
        /// Factor applied to every eigenvalue (1 unless set; omitted from the JSON, the key and
        /// the name when 1). A vector channel's dissimilarity is in the eigenvalues' units (L1:
        /// `Σ|λ − λ'|`), so in a [`Aggregation::Sum`] with histogram channels (nL1, at most 2
        /// each) this factor is the vector channel's weight.
        #[serde(default = "unit_weight", skip_serializing_if = "is_unit_weight")]
        weight: f64,
    },
    /// The distribution of the heat kernel signature over the surface (Sun, Ovsjanikov, Guibas
    /// 2009: `h(x, t) = Σ_k exp(−λ_k t) φ_k(x)²`, the diagonal of the paper's heat kernel
    /// `h_t(x, y)` of §2.2), as a vector: per time `t` of `ts`, the `quantiles` area-weighted
    /// quantiles, at `(i + ½) / quantiles`, of `log(A h(x, t) / Σ_k exp(−λ_k t))` (`A` the
    /// area: the ratio has area-weighted mean 1), each multiplied by `weight / quantiles`.
    /// Its L1 dissimilarity is then `weight` times the sum over the times of the 1-Wasserstein
    /// distances of the two distributions (evaluated by the quantiles' mean absolute difference).
    /// A pointwise quantity, not a pair distance: at small times it reflects how much of the
    /// surface lies on thin parts (limbs, their girth), which the distance distributions of
    /// the other channels summarise poorly (`docs/quality.md` §35).
    HeatQuantiles {
        /// Diffusion times.
        ts: Vec<f64>,
        /// Quantiles per time (1 … 1024).
        quantiles: usize,
        /// Factor applied to every value (the channel's weight in a sum with other channels).
        weight: f64,
    },
    /// Scale-invariant heat kernel of eq. 21, `k̂ = F⁻¹|F(∂_τ log k_τ)|` on a log-time grid
    /// read at one lag, under `norm` over area-normalised quadrature nodes
    /// ([`crate::signature::scale_invariant`]): the distribution is unchanged by a uniform
    /// scaling of the shape, without unit-area normalisation.
    ScaleInvariant {
        /// Smallest log-time `τ = log t` of the grid.
        tau_min: f64,
        /// Largest log-time.
        tau_max: f64,
        /// Grid samples `T` (8 … 1024).
        steps: usize,
        /// Grid lag at which the inverse transform is read (0 … T−1; 0 = the mean modulus).
        lag: usize,
        /// Regularisation of `1/k` in the log-derivative, relative to `1/area`
        /// ([`crate::signature::scale_invariant::SI_EPSILON`] in
        /// [`ChannelSpec::scale_invariant`]). Required in JSON: a default would let a stored
        /// spec written with another value be read as this one (and its cached signature reused).
        epsilon: f64,
        /// Norm of `k̂(x,·) − k̂(y,·)` (L1 / L2 / L∞ over the `lp_samples` nodes).
        norm: Norm,
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

    /// The scale-invariant kernel of eq. 21 under `norm`, on the default window
    /// [`crate::signature::scale_invariant::SI_DEFAULT_WINDOW`], lag 0.
    pub fn scale_invariant(norm: Norm) -> Self {
        let (tau_min, tau_max, steps) = super::scale_invariant::SI_DEFAULT_WINDOW;
        Self {
            kind: ChannelKind::ScaleInvariant {
                tau_min,
                tau_max,
                steps,
                lag: 0,
                epsilon: super::scale_invariant::SI_EPSILON,
                norm,
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

    /// The heat kernel signature's distribution at times `ts` as `quantiles` quantiles each,
    /// weighted by `weight` ([`ChannelKind::HeatQuantiles`]).
    pub fn heat_quantiles(ts: &[f64], quantiles: usize, weight: f64) -> Self {
        Self {
            kind: ChannelKind::HeatQuantiles {
                ts: ts.to_vec(),
                quantiles,
                weight,
            },
        }
    }

    /// ShapeDNA with `count` eigenvalues.
    pub fn shape_dna(count: usize) -> Self {
        Self::weighted_shape_dna(count, 1.0)
    }

    /// ShapeDNA of `count` eigenvalues, each multiplied by `weight` (the channel's weight in a
    /// sum with histogram channels).
    pub fn weighted_shape_dna(count: usize, weight: f64) -> Self {
        Self {
            kind: ChannelKind::ShapeDna { count, weight },
        }
    }

    /// Stable, human-readable name, e.g. `heat-l2[t=0.016]`, `ct-l2`, `step-l2[lc=4pi*10]`,
    /// `heat-l2-ksum[t=0.016,0.04]`, `heat-l2-dmax[...]`, `heat-l2-fsum[...]`, `geo`,
    /// `geo[r=0.5]`, `d2[n=2000]`, `shapedna[50]`, `heat-l2[t=0.016][r=2.44]` (truncated),
    /// `si-heat-l2[tau=-14..5,n=128,lag=0,eps=1]` (eq. 21).
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
            ChannelKind::ScaleInvariant {
                tau_min,
                tau_max,
                steps,
                lag,
                epsilon,
                norm,
            } => format!(
                "si-heat-{}[tau={tau_min}..{tau_max},n={steps},lag={lag},eps={epsilon}]",
                norm.label()
            ),
            ChannelKind::EuclideanD2 { samples } => format!("d2[n={samples}]"),
            ChannelKind::ShapeDna { count, weight } if *weight == 1.0 => {
                format!("shapedna[{count}]")
            }
            ChannelKind::ShapeDna { count, weight } => format!("shapedna[{count}][w={weight}]"),
            ChannelKind::HeatQuantiles {
                ts,
                quantiles,
                weight,
            } => format!("hks-q[t={}][n={quantiles}][w={weight}]", fmt_ts(ts)),
            ChannelKind::Truncated { channel, radius } => {
                let inner = ChannelSpec {
                    kind: (**channel).clone(),
                };
                format!("{}[r={radius}]", inner.name())
            }
        }
    }

    /// The channel whose distances are computed (the inner channel of a truncated one).
    pub(crate) fn base_kind(&self) -> &ChannelKind {
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
    #[serde(default, skip_serializing_if = "SpectrumScaling::is_none")]
    pub spectrum_scaling: SpectrumScaling,
    /// Handle cutting before the spectrum (topological noise removal,
    /// [`crate::mesh::topology::cut_handles`]): the signature is computed on the shape with its
    /// short welded handles cut. It is a preparation step, applied by whoever analyses the shape
    /// for this spec ([`SignatureSpec::analysis_options`]: eval, the server); the signature code
    /// itself reads the analysis it is given. Omitted from the JSON (and key) when `None`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cut_handles: Option<HandleCutOptions>,
    /// A second handle cut (`docs/quality.md` §16–§17): every shape whose mesh this cut leaves
    /// different from [`SignatureSpec::cut_handles`]'s also gets the same channels computed on
    /// that second version ([`Signature::alternate`](crate::signature::Signature::alternate)),
    /// and the first stage scores a pair by the smaller of its two versions' dissimilarities
    /// (the second multiplied by
    /// [`QuerySpec::alternate_margin`](crate::ranking::QuerySpec::alternate_margin),
    /// [`crate::search::Query::score`]). The default cuts every short loop here, genuine handles
    /// included, while its first cut keeps those that look genuine: a weld the first rule must
    /// leave is compared cut, a genuine handle keeps its uncut comparison. Omitted from the
    /// JSON (and key) when `None`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alternate_cut: Option<HandleCutOptions>,
    /// Boundary capping before the spectrum ([`crate::mesh::cap`], `docs/quality.md` §19):
    /// every boundary loop of the shape not longer than [`CapOptions::max_length`] (holes, the
    /// rim of a part cut away; not an open surface's own long border) is closed by a cap before
    /// handle cutting, for both versions. A preparation step like
    /// [`SignatureSpec::cut_handles`] ([`SignatureSpec::analysis_options`]). Omitted from the
    /// JSON (and key) when `None`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cap_boundaries: Option<CapOptions>,
    /// Taubin smoothing before the spectrum ([`crate::mesh::smooth`], `docs/quality.md` §25):
    /// noise at the scale of the edges is filtered out before capping and handle cutting, for
    /// both versions. A preparation step like [`SignatureSpec::cut_handles`]
    /// ([`SignatureSpec::analysis_options`]). Omitted from the JSON (and key) when `None`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smooth: Option<SmoothOptions>,
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
            spectrum_scaling: SpectrumScaling::None,
            cut_handles: None,
            alternate_cut: None,
            cap_boundaries: None,
            smooth: None,
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

    /// Stable key for caches and stored signatures: the hex SHA-256 prefix of the canonical JSON
    /// of the spec, followed by [`crate::revision_tag`] (nothing at revision 0, `+r<N>` after),
    /// so that a signature computed by an older revision of the code has another key
    /// ([`Signature::spec_key`](crate::signature::Signature::spec_key)) and is recomputed.
    pub fn key(&self) -> String {
        let json = serde_json::to_string(self).unwrap_or_default();
        let digest = Sha256::digest(json.as_bytes());
        format!("{}{}", hex::encode(&digest[..12]), crate::revision_tag())
    }

    /// Whether this spec asks for a preparation of its own (smoothing, capping, handle
    /// cutting), so that its shapes cannot share the analysis of a spec without one.
    pub fn has_own_preparation(&self) -> bool {
        self.cut_handles.is_some() || self.cap_boundaries.is_some() || self.smooth.is_some()
    }

    /// The analysis options a shape must be analysed with for this spec: `base` with this
    /// spec's smoothing, boundary capping and handle cutting, when it has them (otherwise `base`
    /// unchanged).
    pub fn analysis_options(&self, base: &AnalyzeOptions) -> AnalyzeOptions {
        let o = match &self.cut_handles {
            Some(c) => with_cut(base, c),
            None => base.clone(),
        };
        self.with_shared_preparation(o)
    }

    /// The analysis options of the second version ([`SignatureSpec::alternate_cut`]): `base`
    /// with the spec's smoothing and capping and the alternate cut in place of the first; `None`
    /// without an alternate cut.
    pub fn alternate_analysis_options(&self, base: &AnalyzeOptions) -> Option<AnalyzeOptions> {
        self.alternate_cut
            .as_ref()
            .map(|c| self.with_shared_preparation(with_cut(base, c)))
    }

    /// `o` with the preparation steps both versions share: smoothing and capping.
    fn with_shared_preparation(&self, mut o: AnalyzeOptions) -> AnalyzeOptions {
        if self.cap_boundaries.is_some() {
            o.prepare.cap_boundaries = self.cap_boundaries;
        }
        if self.smooth.is_some() {
            o.prepare.smooth = self.smooth;
        }
        o
    }

    /// The fewest eigenpairs an analysis needs for this spec: one more than the longest
    /// ShapeDNA channel (the zero mode of a connected shape comes first), else 2. A spectrum
    /// with fewer is refused when the signature is computed; a server checks its configured
    /// count against its default at start.
    pub fn min_eigenpairs(&self) -> usize {
        self.channels
            .iter()
            .map(|c| match c.base_kind() {
                ChannelKind::ShapeDna { count, .. } => count + 1,
                _ => 2,
            })
            .max()
            .unwrap_or(2)
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

/// `base` with `cut` as its preparation's handle cutting.
fn with_cut(base: &AnalyzeOptions, cut: &HandleCutOptions) -> AnalyzeOptions {
    let mut o = base.clone();
    o.prepare.cut_handles = Some(cut.clone());
    o
}

pub(crate) fn validate_spec(spec: &SignatureSpec) -> Result<()> {
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
    for (what, c) in [
        ("cut_handles", &spec.cut_handles),
        ("alternate_cut", &spec.alternate_cut),
    ] {
        if let Some(c) = c {
            if !c.remove_band {
                return bad(format!("{what}.remove_band must be true in a spec"));
            }
            if let Err(e) = c.validate() {
                return bad(format!("{what}: {e}"));
            }
        }
    }
    if let Some(Err(e)) = spec.cap_boundaries.map(|c| c.validate()) {
        return bad(format!("cap_boundaries: {e}"));
    }
    if let Some(Err(e)) = spec.smooth.map(|c| c.validate()) {
        return bad(format!("smooth: {e}"));
    }
    let check_t = |t: f64| t.is_finite() && t > 0.0;
    match spec.spectrum_scaling {
        SpectrumScaling::Lambda1 { reference } if !check_t(reference) => {
            return bad(format!(
                "spectrum_scaling: reference must be finite and > 0, got {reference}"
            ));
        }
        SpectrumScaling::WeylFit {
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
                    ChannelKind::Truncated { .. }
                        | ChannelKind::ShapeDna { .. }
                        | ChannelKind::HeatQuantiles { .. }
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
            ChannelKind::ScaleInvariant {
                tau_min,
                tau_max,
                steps,
                lag,
                epsilon,
                ..
            } => {
                epsilon.is_finite()
                    && *epsilon > 0.0
                    && tau_min.is_finite()
                    && tau_max.is_finite()
                    && tau_min < tau_max
                    && *tau_max <= 50.0
                    && (8..=1024).contains(steps)
                    && lag < steps
            }
            ChannelKind::EuclideanD2 { samples } => *samples >= 2 && *samples <= 100_000,
            ChannelKind::ShapeDna { count, weight } => {
                *count >= 1 && weight.is_finite() && *weight > 0.0
            }
            ChannelKind::HeatQuantiles {
                ts,
                quantiles,
                weight,
            } => {
                !ts.is_empty()
                    && ts.iter().all(|&t| check_t(t))
                    && (1..=1024).contains(quantiles)
                    && weight.is_finite()
                    && *weight > 0.0
            }
            ChannelKind::Truncated { .. } => false,
        };
        if !ok {
            return bad(format!("invalid channel {}", c.name()));
        }
    }
    Ok(())
}
