//! The CPU side of an ingest, shared by the serving node (`POST /v1/shapes` on its own
//! admission pool) and the queue's workers (`shapeseek worker`): read the upload, choose the
//! stored original, analyse, sign, compute the re-ranking payload. Nothing here touches a
//! store; the caller gives the result an id and inserts it.

use super::admission::Cancel;
use super::config::ServerConfig;
use super::limits::stored_original;
use super::ms;
use super::problem::ApiError;
use super::state::{Timings, Upload};
use crate::index::{Engine, ShapeRecord};
use crate::mesh::read::{detect_format, read_mesh, ReadLimits};
use crate::rerank::{compute_payload, GwPayload, PayloadSpec};
use crate::signature::Signature;
use crate::spectrum::Analysis;
use crate::storage::NewShape;
use std::time::Instant;

/// An analysed upload, ready to be stored under an id ([`Prepared::into_new_shape`]).
pub struct Prepared {
    /// The record, without its id yet (and without a name when the upload gave none).
    pub record: ShapeRecord,
    /// The signature (the caller adds it to its scan).
    pub signature: Signature,
    /// Encoded signature.
    pub signature_bytes: Vec<u8>,
    /// What is stored as the original (the upload, or its canonical re-encoding).
    pub original: Vec<u8>,
    /// Encoded re-ranking payload.
    pub payload: Option<Vec<u8>>,
    /// Size of the upload when the stored original is its re-encoding.
    pub reencoded_from: Option<u64>,
    /// SHA-256 of the upload.
    pub sha256: [u8; 32],
    name_given: bool,
}

impl Prepared {
    /// The shape to insert under `id` (an upload without a name is named by its id).
    pub fn into_new_shape(mut self, id: &str) -> (NewShape, Signature, Option<u64>) {
        self.record.id = id.to_string();
        if !self.name_given {
            self.record.name = id.to_string();
        }
        (
            NewShape {
                record: self.record,
                sha256: self.sha256,
                signature: self.signature_bytes,
                original: self.original,
                payload: self.payload,
            },
            self.signature,
            self.reencoded_from,
        )
    }
}

/// Prepare + spectrum + signature (+ re-ranking payload when `with_payload`) of a parsed
/// mesh, recording the stage timings: the one path shared by ingest and search-by-upload.
pub fn analyze_and_sign(
    engine: &Engine,
    mesh: &crate::mesh::Mesh,
    t: &mut Timings,
    with_payload: bool,
    cancel: &Cancel,
) -> Result<(Analysis, Signature, Option<GwPayload>), ApiError> {
    cancel.check()?;
    let t2 = Instant::now();
    let stop = cancel.clone();
    // An interrupted analysis or signature answers 503 `request.timeout`, as a cancellation
    // does (`ApiError::status_of`).
    let interrupt = crate::error::Interrupt::new(move || stop.is_cancelled());
    let (analysis, sig) = engine.sign_interruptible(mesh, interrupt)?;
    cancel.check()?;
    t.prepare_ms = analysis.timings.prepare_ms;
    t.laplacian_ms = analysis.timings.laplacian_ms;
    t.factorization_ms = analysis.timings.factorization_ms;
    t.eigensolve_ms = analysis.timings.eigensolve_ms;
    // The signature's time: the rest (both versions' signatures, the second version's
    // preparation and spectrum when there is one).
    t.signature_ms =
        (ms(t2) - t.prepare_ms - t.laplacian_ms - t.factorization_ms - t.eigensolve_ms).max(0.0);
    cancel.check()?;
    let payload = if with_payload {
        let t3 = Instant::now();
        let p = compute_payload(&analysis, &PayloadSpec::default())?;
        t.payload_ms = ms(t3);
        Some(p)
    } else {
        None
    };
    Ok((analysis, sig, payload))
}

/// Reads and analyses an upload whose SHA-256 is `digest` under the server's limits and
/// stored-bytes policy. A refusal (unreadable mesh, limits, degenerate geometry) is an
/// [`ApiError`] with a 4xx status: the same input always fails the same way.
pub fn prepare_upload(
    engine: &Engine,
    cfg: &ServerConfig,
    limits: &ReadLimits,
    up: &Upload,
    digest: [u8; 32],
    t: &mut Timings,
    cancel: &Cancel,
) -> Result<Prepared, ApiError> {
    let t1 = Instant::now();
    let format = detect_format(&up.bytes, up.hint)?;
    let mesh = read_mesh(&up.bytes, Some(format), limits)?;
    t.read_ms = ms(t1);
    let (stored, reencoded_from) = stored_original(cfg, &up.bytes, &mesh, format)?;
    let area = mesh.area();
    let (analysis, sig, payload) = analyze_and_sign(engine, &mesh, t, true, cancel)?;
    let record = ShapeRecord {
        name: up.name.clone().unwrap_or_default(),
        id: String::new(),
        tags: up.tags.clone(),
        format: format.name().to_string(),
        content_type: format.mime().to_string(),
        bytes: stored.len() as u64,
        vertices: mesh.vertices.len(),
        faces: mesh.faces.len(),
        area,
        sha256: hex::encode(digest),
        created_unix_ms: crate::index::store::now_unix_ms(),
        prepare: analysis.report.clone(),
        spec_key: engine.signature_spec_key(&sig),
    };
    Ok(Prepared {
        record,
        signature_bytes: engine.encode_signature(&sig),
        signature: sig,
        original: stored.to_vec(),
        payload: payload.map(|p| p.to_bytes()),
        reencoded_from,
        sha256: digest,
        name_given: up.name.is_some(),
    })
}
