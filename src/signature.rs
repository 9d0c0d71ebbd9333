//! Corpus-independent spectral signatures of one shape (paper §2.3–§3).
//!
//! (Skeleton: the computation is being filled in; see the module docs once complete.)

use crate::pipeline::Analysis;
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
    /// `geo[r=0.5]`, `d2[n=2000]`, `shapedna[50]`.
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
    },
}

/// What to compute for a shape: the channels and the discretisation.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct SignatureSpec {
    /// Channels, in order.
    pub channels: Vec<ChannelSpec>,
    /// Pair quadrature of the L2 spectral channels.
    pub quadrature: PairQuadrature,
    /// Quadrature points (pairs and integration points) of L1 / L∞ channels.
    pub lp_samples: usize,
    /// Geodesic sources (farthest-point samples with Voronoi weights; targets are all vertices).
    pub geodesic_sources: usize,
    /// Number of quantile intervals stored per distribution channel.
    pub sketch_quantiles: usize,
}

impl Default for SignatureSpec {
    fn default() -> Self {
        Self {
            channels: Vec::new(),
            quadrature: PairQuadrature::Farthest { samples: 1000 },
            lp_samples: 300,
            geodesic_sources: 200,
            sketch_quantiles: 512,
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

/// Computes the signature of an analysed shape.
pub fn compute_signature(analysis: &Analysis, spec: &SignatureSpec) -> Result<Signature> {
    let _ = (analysis, spec);
    Err(Error::InvalidArgument(
        "compute_signature: not implemented yet".into(),
    ))
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
                    put_f64s(&mut w, &s.quantiles);
                }
                ChannelValues::Vector(v) => {
                    w.push(1);
                    put_f64s(&mut w, v);
                }
            }
        }
        w
    }

    /// Decodes [`Signature::to_bytes`]; malformed input is an [`Error::InvalidArgument`].
    pub fn from_bytes(b: &[u8]) -> Result<Self> {
        let mut r = Reader { b, pos: 0 };
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
        if r.pos != b.len() {
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

fn put_u64(w: &mut Vec<u8>, v: u64) {
    w.extend_from_slice(&v.to_le_bytes());
}
fn put_f64(w: &mut Vec<u8>, v: f64) {
    w.extend_from_slice(&v.to_le_bytes());
}
fn put_str(w: &mut Vec<u8>, s: &str) {
    put_u64(w, s.len() as u64);
    w.extend_from_slice(s.as_bytes());
}
fn put_f64s(w: &mut Vec<u8>, v: &[f64]) {
    put_u64(w, v.len() as u64);
    for x in v {
        put_f64(w, *x);
    }
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.b.len())
            .ok_or_else(|| Error::InvalidArgument("signature: truncated".into()))?;
        let s = &self.b[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u64(&mut self) -> Result<u64> {
        let s = self.take(8)?;
        Ok(u64::from_le_bytes(s.try_into().expect("8 bytes")))
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_bits(self.u64()?))
    }
    fn string(&mut self) -> Result<String> {
        let n = self.u64()? as usize;
        let s = self.take(n)?;
        String::from_utf8(s.to_vec())
            .map_err(|_| Error::InvalidArgument("signature: bad utf-8".into()))
    }
    fn f64s(&mut self) -> Result<Vec<f64>> {
        let n = self.u64()? as usize;
        if n > self.b.len() / 8 {
            return Err(Error::InvalidArgument("signature: truncated".into()));
        }
        (0..n).map(|_| self.f64()).collect()
    }
}
