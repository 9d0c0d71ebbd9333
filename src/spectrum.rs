//! The Laplace–Beltrami spectrum of a prepared mesh (paper §2.2, §4).

use faer::Mat;

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
