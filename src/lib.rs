//! shapeseek: non-rigid 3D shape retrieval with spectral shape distances
//! (M. M. Bronstein, A. M. Bronstein, "Shape recognition with spectral distances", TPAMI 2011).
//!
//! The data flow is one-way: bytes → [`mesh`] (read, prepare) → [`laplace`] (cotangent stiffness,
//! lumped mass) → [`eigen`] (k smallest generalized eigenpairs) → [`spectrum::Spectrum`]. The core
//! is pure synchronous Rust: no HTTP, no storage.

#![warn(missing_docs)]

mod bytes;
pub mod eigen;
pub mod error;
pub mod eval;
pub mod index;
pub mod laplace;
pub mod mesh;
pub mod presets;
pub mod queue;
pub mod ranking;
pub mod rerank;
pub mod scale;
pub mod search;
pub mod server;
pub mod signature;
pub mod spectrum;
pub mod storage;
pub mod worker;

pub use error::{Error, Result};
