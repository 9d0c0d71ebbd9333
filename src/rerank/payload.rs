//! Per-shape payload of the spectral Gromov–Wasserstein re-ranking: a few hundred
//! farthest-point samples with their Voronoi areas (the measure) and the spectral distance
//! matrices between them at one or a few scales. Computed once per shape from its
//! [`Analysis`] and stored next to the signature (eval cache, index).
//!
//! * Samples: the same geodesic farthest-point sampling and Voronoi cells as the signature's
//!   pair quadrature ([`crate::signature`]): rigid-motion and vertex-permutation invariant.
//!   Weights are the cell areas divided by the total area (a probability measure).
//! * Matrices: the diffusion distance `d_t(x,y)² = Σ_{i≥1} e^{−2tλ_i}(φ_i(x) − φ_i(y))²`
//!   ([`GwMetric::Diffusion`]) or the heat kernel `k_t(x,y) = Σ_i e^{−tλ_i} φ_i(x)φ_i(y)`
//!   ([`GwMetric::HeatKernel`], Mémoli's spectral GW), both on the unit-area shape, with times
//!   either absolute or relative to the shape's own first non-zero eigenvalue
//!   ([`TimeRule::Lambda1`]: `t = τ / λ₁`).
//! * Storage: per scale the strict upper triangle as `f32` (`m(m−1)/2` values; the diagonal of
//!   a distance matrix is 0, the heat-kernel diagonal is stored separately). At m = 200 and one
//!   scale: 80 KB per shape.

use crate::bytes::{put_f32s, put_f64, put_f64s, put_u64, ByteReader};
use crate::signature::{farthest_points, EdgeGraph, ZERO_MODE_TOLERANCE};
use crate::spectrum::Analysis;
use crate::{Error, Result};
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, Par};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// Which spectral matrix compares samples.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum GwMetric {
    /// Diffusion (heat-L2) distance, eq. 9 with `K = e^{−tλ}`.
    Diffusion,
    /// Heat kernel values `k_t(x, y)` (not a metric; Mémoli's spectral GW compares kernels).
    HeatKernel,
}

/// How the payload's times relate to the shape.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum TimeRule {
    /// `t` as given (unit-area shapes: the same meaning as the signature's heat scales).
    Absolute,
    /// `t = τ / λ₁` with `λ₁` the shape's first non-zero eigenvalue.
    Lambda1,
}

/// What to store per shape.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct PayloadSpec {
    /// Farthest-point samples (clamped to the vertex count).
    pub samples: usize,
    /// Times (or `τ` for [`TimeRule::Lambda1`]), one matrix each.
    pub times: Vec<f64>,
    /// Distance or kernel.
    pub metric: GwMetric,
    /// Interpretation of `times`.
    pub time_rule: TimeRule,
}

impl Default for PayloadSpec {
    fn default() -> Self {
        Self {
            samples: 100,
            times: vec![0.016, 0.04, 0.1],
            metric: GwMetric::Diffusion,
            time_rule: TimeRule::Absolute,
        }
    }
}

impl PayloadSpec {
    /// Stable key (hex SHA-256 prefix of the canonical JSON) for caches.
    pub fn key(&self) -> String {
        let json = serde_json::to_string(self).unwrap_or_default();
        hex::encode(&Sha256::digest(json.as_bytes())[..12])
    }
}

/// The stored per-shape data.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct GwPayload {
    /// [`PayloadSpec::key`] it was computed with.
    pub spec_key: String,
    /// Number of samples `m`.
    pub samples: usize,
    /// Sample weights (Voronoi areas / total area; sum 1).
    pub weights: Vec<f64>,
    /// Per scale: the strict upper triangle, row-major (`(0,1), (0,2), …, (1,2), …`).
    pub upper: Vec<Vec<f32>>,
    /// Per scale: the diagonal (zeros for distances).
    pub diagonal: Vec<Vec<f32>>,
    /// Times actually used (after [`TimeRule`]).
    pub times: Vec<f64>,
    /// First non-zero eigenvalue of the shape.
    pub lambda1: f64,
}

const MAGIC: &[u8; 4] = b"SGW1";

impl GwPayload {
    /// The dense symmetric matrix of scale `s` (f64).
    pub fn matrix(&self, s: usize) -> Mat<f64> {
        let m = self.samples;
        let up = &self.upper[s];
        let dg = &self.diagonal[s];
        let mut out = Mat::<f64>::zeros(m, m);
        let mut k = 0;
        for i in 0..m {
            out[(i, i)] = dg[i] as f64;
            for j in i + 1..m {
                let v = up[k] as f64;
                out[(i, j)] = v;
                out[(j, i)] = v;
                k += 1;
            }
        }
        out
    }

    /// Every scale's dense matrix.
    pub fn matrices(&self) -> Vec<Mat<f64>> {
        (0..self.upper.len()).map(|s| self.matrix(s)).collect()
    }

    /// Compact binary encoding (little endian).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut w = Vec::with_capacity(64 + self.upper.iter().map(|u| u.len() * 4).sum::<usize>());
        w.extend_from_slice(MAGIC);
        put_u64(&mut w, self.spec_key.len() as u64);
        w.extend_from_slice(self.spec_key.as_bytes());
        put_u64(&mut w, self.samples as u64);
        put_f64(&mut w, self.lambda1);
        put_u64(&mut w, self.weights.len() as u64);
        put_f64s(&mut w, &self.weights);
        put_u64(&mut w, self.times.len() as u64);
        put_f64s(&mut w, &self.times);
        put_u64(&mut w, self.upper.len() as u64);
        for (u, d) in self.upper.iter().zip(&self.diagonal) {
            put_u64(&mut w, u.len() as u64);
            put_f32s(&mut w, u);
            put_u64(&mut w, d.len() as u64);
            put_f32s(&mut w, d);
        }
        w
    }

    /// Decodes [`GwPayload::to_bytes`]; malformed input (a stored payload damaged or of another
    /// format) is an [`Error::Corrupt`] of `what = "gw payload"`.
    pub fn from_bytes(b: &[u8]) -> Result<Self> {
        let mut r = ByteReader::new(b);
        if r.take(4).ok_or_else(bad)? != MAGIC {
            return Err(Error::corrupt("gw payload", None, "bad magic"));
        }
        let len = r.u64().ok_or_else(bad)? as usize;
        if len > 1 << 10 {
            return Err(bad());
        }
        let spec_key =
            String::from_utf8(r.take(len).ok_or_else(bad)?.to_vec()).map_err(|_| bad())?;
        let samples = r.u64().ok_or_else(bad)? as usize;
        let lambda1 = r.f64().ok_or_else(bad)?;
        let nw = r.u64().ok_or_else(bad)? as usize;
        let weights = r.f64s(nw).ok_or_else(bad)?;
        let nt = r.u64().ok_or_else(bad)? as usize;
        let times = r.f64s(nt).ok_or_else(bad)?;
        let ns = r.u64().ok_or_else(bad)? as usize;
        if ns > 64 {
            return Err(bad());
        }
        let mut upper = Vec::with_capacity(ns);
        let mut diagonal = Vec::with_capacity(ns);
        for _ in 0..ns {
            let nu = r.u64().ok_or_else(bad)? as usize;
            upper.push(r.f32s(nu).ok_or_else(bad)?);
            let nd = r.u64().ok_or_else(bad)? as usize;
            diagonal.push(r.f32s(nd).ok_or_else(bad)?);
        }
        if !r.at_end()
            || weights.len() != samples
            || upper
                .iter()
                .any(|u| u.len() != samples * samples.saturating_sub(1) / 2)
            || diagonal.iter().any(|d| d.len() != samples)
        {
            return Err(bad());
        }
        Ok(GwPayload {
            spec_key,
            samples,
            weights,
            upper,
            diagonal,
            times,
            lambda1,
        })
    }
}

fn bad() -> Error {
    Error::corrupt("gw payload", None, "truncated or malformed")
}

/// Computes the payload of an analysed (unit-area) shape.
///
/// Errors: [`Error::InvalidArgument`] for an empty time list, a non-positive or non-finite time,
/// zero samples, or a spectrum without a non-zero eigenvalue.
pub fn compute_payload(analysis: &Analysis, spec: &PayloadSpec) -> Result<GwPayload> {
    if spec.samples == 0 || spec.times.is_empty() {
        return Err(Error::InvalidArgument(
            "gw payload: need ≥ 1 sample and ≥ 1 time".into(),
        ));
    }
    if spec.times.iter().any(|t| !(t.is_finite() && *t > 0.0)) {
        return Err(Error::InvalidArgument(
            "gw payload: times must be positive and finite".into(),
        ));
    }
    let mesh = &analysis.mesh;
    let sp = &analysis.spectrum;
    let n = mesh.vertices.len();
    if n == 0 || sp.eigenvectors.nrows() != n || sp.mass.len() != n {
        return Err(Error::InvalidArgument(
            "gw payload: spectrum does not match the mesh".into(),
        ));
    }
    let area: f64 = sp.mass.iter().sum();
    let zero_tol = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI / area;
    let lambda1 = sp
        .eigenvalues
        .iter()
        .copied()
        .find(|&l| l > zero_tol)
        .ok_or_else(|| Error::InvalidArgument("gw payload: no non-zero eigenvalue".into()))?;
    let m = spec.samples.min(n);
    let graph = EdgeGraph::new(mesh);
    let fps = farthest_points(mesh, &graph, &[m]);
    let quad = fps.quadrature(m, &sp.mass);
    let pts = quad.point_indices();
    let m = pts.len();
    let wsum: f64 = quad.weights.iter().sum();
    let weights: Vec<f64> = quad.weights.iter().map(|w| w / wsum).collect();
    let times: Vec<f64> = spec
        .times
        .iter()
        .map(|&t| match spec.time_rule {
            TimeRule::Absolute => t,
            TimeRule::Lambda1 => t / lambda1,
        })
        .collect();
    let k = sp.eigenvalues.len();
    let mut upper = Vec::with_capacity(times.len());
    let mut diagonal = Vec::with_capacity(times.len());
    for &t in &times {
        // ψ = Φ_S diag(K), K = e^{−tλ} (zero modes: 0 for distances, kept for the kernel).
        let kw: Vec<f64> = sp
            .eigenvalues
            .iter()
            .map(|&l| {
                if l <= zero_tol {
                    if spec.metric == GwMetric::HeatKernel {
                        1.0
                    } else {
                        0.0
                    }
                } else {
                    (-t * l).exp()
                }
            })
            .collect();
        // Gram: G = Φ_S diag(K^a) Φ_Sᵀ with a = 2 for distances (|ψ|² terms), 1 for the kernel.
        let pw = if spec.metric == GwMetric::HeatKernel {
            0.5
        } else {
            1.0
        };
        let psi = Mat::from_fn(m, k, |r, c| {
            sp.eigenvectors[(pts[r] as usize, c)] * kw[c].powf(pw)
        });
        let mut gram = Mat::<f64>::zeros(m, m);
        matmul(
            gram.as_mut(),
            Accum::Replace,
            psi.as_ref(),
            psi.as_ref().transpose(),
            1.0,
            Par::Seq,
        );
        let mut up = Vec::with_capacity(m * m.saturating_sub(1) / 2);
        let mut dg = Vec::with_capacity(m);
        for i in 0..m {
            match spec.metric {
                GwMetric::Diffusion => dg.push(0.0f32),
                GwMetric::HeatKernel => dg.push(gram[(i, i)] as f32),
            }
            for j in i + 1..m {
                let v = match spec.metric {
                    GwMetric::Diffusion => (gram[(i, i)] + gram[(j, j)] - 2.0 * gram[(i, j)])
                        .max(0.0)
                        .sqrt(),
                    GwMetric::HeatKernel => gram[(i, j)],
                };
                up.push(v as f32);
            }
        }
        upper.push(up);
        diagonal.push(dg);
    }
    Ok(GwPayload {
        spec_key: spec.key(),
        samples: m,
        weights,
        upper,
        diagonal,
        times,
        lambda1,
    })
}
