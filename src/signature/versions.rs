//! The two cut versions of a shape ([`SignatureSpec::alternate_cut`], `docs/quality.md` §16–§17).
//!
//! A spec with an alternate cut describes each shape by up to two versions: the mesh prepared
//! with [`SignatureSpec::cut_handles`] (the first, always there) and the mesh prepared with the
//! alternate cut, kept only when it differs from the first (the alternate rule cut a loop the
//! first left, or the other way round). The alternate preparation is cheap (the cutter runs in
//! milliseconds on a genus-0 shape, which it leaves as it is); a second spectrum and signature
//! are computed only for the shapes that differ (22 of the 280 shapes of bench/dev with the
//! default's rules, all of them topology or iso+topology shapes).
//!
//! [`sign`] is the one path from a mesh to its signature used by the server (ingest, search by
//! upload, recomputation of stale signatures); eval, which caches the first analysis, calls
//! [`second_version`] with it.

use super::compute::{compute_signature_interruptible, Signature};
use super::spec::SignatureSpec;
use crate::mesh::prepare::prepare;
use crate::mesh::Mesh;
use crate::spectrum::{analyze, analyze_prepared, Analysis, AnalyzeOptions};
use crate::{Error, Result};
use std::time::Instant;

/// The analysis of the second version of `mesh`, whose first version is `first` (analysed with
/// `spec.analysis_options(base)`): `None` when the spec has no alternate cut or the alternate
/// preparation leaves the same mesh as the first, or fails (the shape then has one version,
/// as under a spec without an alternate cut; the first version's own errors are the ones
/// reported).
///
/// # Errors
/// Only [`Error::Interrupted`]: an analysis stopped by `base.eigen`'s interrupt is the
/// caller's stop, not a second version that failed.
pub fn alternate_analysis(
    mesh: &Mesh,
    first: &Analysis,
    spec: &SignatureSpec,
    base: &AnalyzeOptions,
) -> Result<Option<Analysis>> {
    let Some(opts) = spec.alternate_analysis_options(base) else {
        return Ok(None);
    };
    let t0 = Instant::now();
    let Ok((prepared, report)) = prepare(mesh, &opts.prepare) else {
        return Ok(None);
    };
    if prepared.vertices == first.mesh.vertices && prepared.faces == first.mesh.faces {
        return Ok(None);
    }
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    match analyze_prepared(prepared, report, &opts, ms) {
        Ok(second) => Ok(Some(second)),
        Err(e @ Error::Interrupted(_)) => Err(e),
        Err(_) => Ok(None),
    }
}

/// The second version's signature of `mesh` ([`alternate_analysis`], then its channels under
/// the same spec: [`compute_signature_interruptible`] reads only the channels and the
/// discretisation, so both versions carry the same spec key); `None` when the shape has one
/// version.
///
/// # Errors
/// Those of [`alternate_analysis`], and of [`compute_signature_interruptible`] on the second
/// version (under `base.eigen`'s interrupt).
pub fn second_version(
    mesh: &Mesh,
    first: &Analysis,
    spec: &SignatureSpec,
    base: &AnalyzeOptions,
) -> Result<Option<Signature>> {
    alternate_analysis(mesh, first, spec, base)?
        .map(|second| compute_signature_interruptible(&second, spec, &base.eigen.interrupt))
        .transpose()
}

/// The first version's analysis of `mesh` and its signature under `spec`, with the second
/// version attached when the spec has an alternate cut and it differs
/// ([`alternate_analysis`]); `base` holds the preparation and eigensolver options, to which the
/// spec's cuts are applied.
///
/// # Errors
/// Those of [`analyze`] and [`compute_signature_interruptible`] on the first version, and of
/// [`compute_signature_interruptible`] on the second; [`Error::Interrupted`] when
/// `base.eigen`'s interrupt fired during either version's analysis (after its preparation,
/// inside its eigensolve) or signature (after its sampling, before each channel).
pub fn sign(
    mesh: &Mesh,
    spec: &SignatureSpec,
    base: &AnalyzeOptions,
) -> Result<(Analysis, Signature)> {
    let first = analyze(mesh, &spec.analysis_options(base))?;
    let mut sig = compute_signature_interruptible(&first, spec, &base.eigen.interrupt)?;
    sig.alternate = second_version(mesh, &first, spec, base)?.map(Box::new);
    Ok((first, sig))
}
