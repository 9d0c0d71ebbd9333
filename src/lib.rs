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
#[cfg(test)]
mod source_fingerprint;
pub mod spectrum;
pub mod storage;
pub mod worker;

pub use error::{Error, Result};

/// Revision of what the numerical core computes for an unchanged specification: preparation,
/// handle cutting, the eigenpairs and the signatures. Bump it with every change that moves them
/// on purpose (`tests/revision.rs` fails until it is bumped and its recorded figures updated):
/// a stored index then finds every signature stale at its next start and recomputes it from the
/// stored original (every signature carries its spec's key, which ends in [`revision_tag`]:
/// [`signature::SignatureSpec::key`]), and eval's cache no longer serves analyses or signatures
/// of the older code (its analysis key carries the tag too). Specifications, options and the
/// package version are keyed on their own; this covers the code behind them.
pub const ALGORITHM_REVISION: u32 = 2;

/// The part of spec and cache keys that names [`ALGORITHM_REVISION`]: empty for revision 0 (the
/// keys of indexes and caches made before the revision existed are unchanged), else `+r<N>`.
pub fn revision_tag() -> String {
    match ALGORITHM_REVISION {
        0 => String::new(),
        n => format!("+r{n}"),
    }
}
