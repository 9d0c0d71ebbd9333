//! The shared front half of every use of the library: mesh → prepared mesh → spectrum.
//!
//! The CLI, the evaluation harness and the server all call [`analyze`]; there is no second
//! implementation of these steps anywhere.

use crate::eigen::{EigenOptions, EigenStats};
use crate::laplace::LaplacianKind;
use crate::mesh::prepare::{prepare, PrepareOptions, PrepareReport};
use crate::mesh::Mesh;
use crate::spectrum::{compute_spectrum_with, Spectrum, SpectrumTimings};
use serde::{Deserialize, Serialize};
use std::time::Instant;

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
    let (spectrum, eigen_stats, st): (Spectrum, EigenStats, SpectrumTimings) =
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
