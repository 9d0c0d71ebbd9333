//! [`compute_signature`]: from an analysed shape and a [`SignatureSpec`] to a [`Signature`].

use super::baselines::{d2_sketch, geodesic_sketch};
use super::distributions::{truncate_sketch, QuantileSketch};
use super::kernels::{
    heat_kernel_signature, heat_weights, l2_pairs, lp_pairs, transfer_weights, PairMode,
};
use super::sampling::{farthest_points, EdgeGraph, NearField, Quadrature};
use super::scale_invariant::{si_kernel_rows, si_pairs, tau_grid};
use super::spec::{validate_spec, ChannelKind, Norm, PairQuadrature, SignatureSpec};
use crate::error::Interrupt;
use crate::scale::SpectrumScaling;
use crate::spectrum::{Analysis, ZERO_MODE_TOLERANCE};
use crate::{Error, Result};
use faer::Mat;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

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
    /// [`ChannelSpec::name`](super::spec::ChannelSpec::name) of the channel.
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
    /// The second version ([`SignatureSpec::alternate_cut`]): the same channels computed on the
    /// shape cut by the alternate rule, present only when that cut leaves another mesh than the
    /// first ([`super::versions::sign`]). Omitted from the JSON when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alternate: Option<Box<Signature>>,
}

/// Computes the signature of an analysed shape (see the module docs for the method).
///
/// Errors: [`Error::InvalidArgument`] for an invalid spec (non-positive or non-finite scales,
/// zero samples or quantiles, more ShapeDNA eigenvalues than the spectrum has) or a spectrum that
/// does not match the mesh.
pub fn compute_signature(analysis: &Analysis, spec: &SignatureSpec) -> Result<Signature> {
    compute_signature_interruptible(analysis, spec, &Interrupt::default())
}

/// [`compute_signature`] that stops with [`Error::Interrupted`] once `interrupt` fires: it is
/// checked after the sampling (the edge graph and the farthest points, the longest step before
/// the channels) and before each channel.
pub fn compute_signature_interruptible(
    analysis: &Analysis,
    spec: &SignatureSpec,
    interrupt: &Interrupt,
) -> Result<Signature> {
    validate_spec(spec)?;
    // Scale selection by rescaling the spectrum (crate::scale).
    if !spec.spectrum_scaling.is_none() {
        let mut plain = spec.clone();
        plain.spectrum_scaling = SpectrumScaling::None;
        let mut sig = compute_signature_interruptible(
            &spec.spectrum_scaling.apply(analysis),
            &plain,
            interrupt,
        )?;
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
            ChannelKind::ScaleInvariant { .. } => need_lp = true,
            ChannelKind::Geodesic { .. } => need_geo = true,
            ChannelKind::ShapeDna { count, .. } => {
                if *count > nonzero.len() {
                    return Err(Error::InvalidArgument(format!(
                        "ShapeDNA[{count}] needs {count} non-zero eigenvalues, the spectrum has {}",
                        nonzero.len()
                    )));
                }
            }
            ChannelKind::EuclideanD2 { .. }
            | ChannelKind::Truncated { .. }
            | ChannelKind::HeatQuantiles { .. } => {}
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
    interrupt.check("signature")?;
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
            interrupt.check("signature")?;
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
                ChannelKind::ScaleInvariant {
                    tau_min,
                    tau_max,
                    steps,
                    lag,
                    epsilon,
                    norm,
                } => {
                    let quad = ctx.lp_quad.as_ref().expect("Lp quadrature");
                    let nodes = ctx.lp_nodes.as_ref().expect("Lp nodes").as_ref();
                    let taus = tau_grid(*tau_min, *tau_max, *steps);
                    let kr =
                        si_kernel_rows(nodes, nodes, &sp.eigenvalues, area, &taus, *lag, *epsilon);
                    ChannelValues::Distribution(si_pairs(&kr, &quad.weights, area, *norm).sketch(q))
                }
                ChannelKind::Geodesic { radius } => ChannelValues::Distribution(geodesic_sketch(
                    mesh,
                    graph.as_ref().expect("graph built for geodesic channels"),
                    geo_quad.as_ref().expect("geodesic quadrature"),
                    &sp.mass,
                    *radius,
                    q,
                )),
                ChannelKind::EuclideanD2 { samples } => {
                    ChannelValues::Distribution(d2_sketch(mesh, *samples, q))
                }
                ChannelKind::ShapeDna { count, weight } => ChannelValues::Vector(
                    nonzero
                        .iter()
                        .take(*count)
                        .map(|&i| weight * sp.eigenvalues[i])
                        .collect(),
                ),
                ChannelKind::HeatQuantiles {
                    ts,
                    quantiles,
                    weight,
                } => ChannelValues::Vector(heat_quantiles(
                    sp.eigenvectors.as_ref(),
                    &sp.eigenvalues,
                    &sp.mass,
                    ts,
                    *quantiles,
                    *weight,
                )),
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
        alternate: None,
    })
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

/// The values of a [`ChannelKind::HeatQuantiles`] channel: per time, the area-weighted quantiles
/// of `log(A h(x, t) / Σ_k exp(−λ_k t))` at `(i + ½) / q`, times `weight / q`.
///
/// `h(x, t)` is [`heat_kernel_signature`] over every eigenpair of the analysis. With
/// mass-orthonormal `φ`,
/// `Σ_x m_x h(x, t) = Σ_k exp(−λ_k t)`, so the ratio has area-weighted mean 1. Quantiles
/// interpolate linearly between the vertices' mid-mass cumulative positions (`m_x / 2` into
/// each vertex's share) and are clamped to the smallest and largest value at the ends.
pub(crate) fn heat_quantiles(
    phi: faer::MatRef<'_, f64>,
    eigenvalues: &[f64],
    mass: &[f64],
    ts: &[f64],
    q: usize,
    weight: f64,
) -> Vec<f64> {
    let n = phi.nrows();
    let area: f64 = mass.iter().sum();
    let mut out = Vec::with_capacity(ts.len() * q);
    for &t in ts {
        let trace: f64 = eigenvalues.iter().map(|l| (-l.max(0.0) * t).exp()).sum();
        let mut v: Vec<(f64, f64)> = heat_kernel_signature(phi, eigenvalues, t)
            .into_iter()
            .zip(mass)
            .map(|(h, &m)| ((area * h / trace).max(1e-300).ln(), m))
            .collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        // Mid-mass cumulative position of each vertex, as a fraction of the area.
        let mut pos = Vec::with_capacity(n);
        let mut acc = 0.0;
        for &(_, m) in &v {
            pos.push((acc + 0.5 * m) / area);
            acc += m;
        }
        let mut j = 0;
        for i in 0..q {
            let u = (i as f64 + 0.5) / q as f64;
            while j + 1 < n && pos[j + 1] <= u {
                j += 1;
            }
            let value = if u <= pos[0] {
                v[0].0
            } else if j + 1 >= n {
                v[n - 1].0
            } else {
                let (a, b) = (pos[j], pos[j + 1]);
                let f = if b > a { (u - a) / (b - a) } else { 0.0 };
                v[j].0 + f * (v[j + 1].0 - v[j].0)
            };
            out.push(weight / q as f64 * value);
        }
    }
    out
}
