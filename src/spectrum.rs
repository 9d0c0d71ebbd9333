//! The Laplace–Beltrami spectrum of a prepared mesh (paper §2.2, §4), and [`analyze`], the one
//! front half of every use of the library: mesh → prepared mesh ([`crate::mesh::prepare`]) →
//! Laplacian ([`crate::laplace`]) → eigenpairs ([`crate::eigen`]) → [`Spectrum`].
//!
//! The CLI, the evaluation harness and the server all call [`analyze`]; there is no second
//! implementation of these steps anywhere.

use crate::eigen::{smallest_eigenpairs, EigenOptions, EigenStats};
use crate::laplace::{laplacian, LaplacianKind};
use crate::mesh::prepare::{prepare, PrepareOptions, PrepareReport};
use crate::mesh::Mesh;
use faer::Mat;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Eigenvalues `λ ≤ ZERO_MODE_TOLERANCE · 4π / area` are zero modes (λ_0 of each component):
/// kernels give them weight 0 ([`crate::signature`]) and scale fits leave them out
/// ([`crate::scale`]).
pub const ZERO_MODE_TOLERANCE: f64 = 1e-6;

/// The k smallest eigenpairs of `L φ = λ A φ` (paper eq. 22 in matrix form), with `L` the
/// cotangent stiffness matrix and `A` the lumped (barycentric) mass of the mesh they came from.
#[derive(Debug, Clone)]
pub struct Spectrum {
    /// λ_0 ≤ λ_1 ≤ … ≤ λ_{k-1}. For a prepared (unit-area) mesh, λ_0 ≈ 0 per component.
    pub eigenvalues: Vec<f64>,
    /// n × k matrix; column i is φ_i, A-orthonormal (Φᵀ A Φ = I), sign fixed so that the entry
    /// of largest magnitude is positive (first such vertex on exact ties).
    pub eigenvectors: Mat<f64>,
    /// Diagonal of the lumped mass matrix A (vertex areas a_i; they sum to the total area).
    pub mass: Vec<f64>,
    /// Relative residual of each pair, `‖Lφ − λAφ‖₂ / ((|λ| + λ_ref) ‖Aφ‖₂)`, see [`crate::eigen`].
    pub residuals: Vec<f64>,
}

/// Wall-clock milliseconds per stage of [`compute_spectrum`].
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct SpectrumTimings {
    /// Assembling the cotangent stiffness and lumped mass.
    pub laplacian_ms: f64,
    /// Factorising `L − σA` (0 for the dense path).
    pub factorization_ms: f64,
    /// Eigen-iteration (or the dense eigensolver).
    pub eigensolve_ms: f64,
}

/// The spectrum of `mesh` as it is (callers normally pass a prepared, unit-area mesh) with the
/// cotangent Laplacian, with solver statistics and timings.
pub fn compute_spectrum(
    mesh: &Mesh,
    opts: &EigenOptions,
) -> crate::Result<(Spectrum, EigenStats, SpectrumTimings)> {
    compute_spectrum_with(mesh, LaplacianKind::Cotangent, opts)
}

/// [`compute_spectrum`] with a chosen discretisation of the operator.
pub fn compute_spectrum_with(
    mesh: &Mesh,
    kind: LaplacianKind,
    opts: &EigenOptions,
) -> crate::Result<(Spectrum, EigenStats, SpectrumTimings)> {
    let t0 = Instant::now();
    let lap = laplacian(mesh, kind)?;
    let laplacian_ms = t0.elapsed().as_secs_f64() * 1e3;
    let pairs = smallest_eigenpairs(&lap.stiffness, &lap.mass, opts)?;
    let timings = SpectrumTimings {
        laplacian_ms,
        factorization_ms: pairs.stats.factor_ms,
        eigensolve_ms: pairs.stats.iterate_ms,
    };
    Ok((
        Spectrum {
            eigenvalues: pairs.values,
            eigenvectors: pairs.vectors,
            mass: lap.mass,
            residuals: pairs.residuals,
        },
        pairs.stats,
        timings,
    ))
}

/// Options of [`analyze`].
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct AnalyzeOptions {
    /// Cleaning and normalisation.
    pub prepare: PrepareOptions,
    /// Eigensolver (number of pairs `k`, tolerance, method).
    pub eigen: EigenOptions,
    /// Discretisation of the Laplace–Beltrami operator (cotangent by default).
    pub laplacian: LaplacianKind,
}

/// Milliseconds per stage.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct StageTimings {
    /// Cleaning, components, normalisation.
    pub prepare_ms: f64,
    /// Laplacian assembly.
    pub laplacian_ms: f64,
    /// Factorisation of the shifted operator.
    pub factorization_ms: f64,
    /// Eigen-iteration.
    pub eigensolve_ms: f64,
}

/// A prepared mesh and its spectrum.
#[derive(Debug, Clone)]
pub struct Analysis {
    /// The mesh after preparation (unit area unless disabled).
    pub mesh: Mesh,
    /// What preparation found and changed.
    pub report: PrepareReport,
    /// The Laplace–Beltrami spectrum of `mesh`.
    pub spectrum: Spectrum,
    /// Solver statistics.
    pub eigen_stats: EigenStats,
    /// Time per stage.
    pub timings: StageTimings,
}

/// Prepares `mesh` and computes its spectrum.
pub fn analyze(mesh: &Mesh, opts: &AnalyzeOptions) -> crate::Result<Analysis> {
    let t0 = Instant::now();
    let (prepared, report) = prepare(mesh, &opts.prepare)?;
    let prepare_ms = t0.elapsed().as_secs_f64() * 1e3;
    analyze_prepared(prepared, report, opts, prepare_ms)
}

/// The spectrum of a mesh already prepared with `opts.prepare` ([`prepare`]'s output and
/// report, and the time it took): the second half of [`analyze`].
pub fn analyze_prepared(
    prepared: Mesh,
    report: PrepareReport,
    opts: &AnalyzeOptions,
    prepare_ms: f64,
) -> crate::Result<Analysis> {
    // The preparation is not interruptible; the next check is the eigensolve's first, after
    // the Laplacian and the factorisation.
    opts.eigen.interrupt.check("preparation")?;
    let (spectrum, eigen_stats, st) =
        compute_spectrum_with(&prepared, opts.laplacian, &opts.eigen)?;
    Ok(Analysis {
        mesh: prepared,
        report,
        spectrum,
        eigen_stats,
        timings: StageTimings {
            prepare_ms,
            laplacian_ms: st.laplacian_ms,
            factorization_ms: st.factorization_ms,
            eigensolve_ms: st.eigensolve_ms,
        },
    })
}
