//! The seam between the index/server and the retrieval framework (signatures and ranking).
//!
//! The server never computes a distance itself: every signature, calibration, prepared
//! histogram and score comes from an [`Engine`]. The product engine ([`super::FwEngine`]) calls
//! the framework functions `compute_signature`, `calibrate`, `prepare_for_ranking` and `score`,
//! the same calls the evaluation harness makes, so a ranking by the server equals the one of
//! `eval` for the same query spec and the same calibration.

use crate::spectrum::{Analysis, AnalyzeOptions};
use crate::Result;
use serde::de::DeserializeOwned;
use serde::Serialize;

/// Signature computation and ranking, as used by the index and the server.
pub trait Engine: Send + Sync + 'static {
    /// A per-shape signature (corpus independent).
    type Signature: Clone + Send + Sync + 'static;
    /// Corpus calibration (histogram ranges) with an epoch number.
    type Calibration: Clone + Send + Sync + Serialize + DeserializeOwned + 'static;
    /// What ranking scans: a signature derived under a calibration.
    type Prepared: Clone + Send + Sync + 'static;
    /// How two prepared signatures are compared (channels, dissimilarity, aggregation).
    type Query: Clone + Send + Sync + Serialize + DeserializeOwned + 'static;

    /// A short name for logs and `/v1/index`.
    fn name(&self) -> String;
    /// The analysis (preparation + eigenpairs) the signature needs.
    fn analyze_options(&self) -> AnalyzeOptions;
    /// A stable key of the signature spec: stored signatures with another key are stale.
    fn spec_key(&self) -> String;
    /// The signature spec as JSON (for `/v1/index`).
    fn spec_json(&self) -> serde_json::Value;
    /// Computes the signature of an analysed shape.
    fn compute(&self, analysis: &Analysis) -> Result<Self::Signature>;
    /// The spec key a signature was computed with.
    fn signature_spec_key(&self, sig: &Self::Signature) -> String;
    /// Serialises a signature for the `signatures` tree.
    fn encode_signature(&self, sig: &Self::Signature) -> Vec<u8>;
    /// Reads a stored signature back.
    fn decode_signature(&self, bytes: &[u8]) -> Result<Self::Signature>;
    /// The distributions of a signature as JSON (for `GET /v1/shapes/{id}/signature`).
    fn signature_json(&self, sig: &Self::Signature) -> serde_json::Value;
    /// Calibrates the histogram ranges on a set of signatures.
    fn calibrate(&self, sigs: &[&Self::Signature], epoch: u64) -> Self::Calibration;
    /// The epoch of a calibration.
    fn calibration_epoch(&self, cal: &Self::Calibration) -> u64;
    /// Derives what ranking scans from a signature under a calibration.
    fn prepare(&self, sig: &Self::Signature, cal: &Self::Calibration) -> Self::Prepared;
    /// The default query spec.
    fn default_query(&self) -> Self::Query;
    /// The re-ranking stages a search applies when the request names none (none by default).
    fn default_rerank(&self) -> Vec<crate::rerank::RerankStage> {
        Vec::new()
    }
    /// Checks a query spec against the signature spec (e.g. that its channels exist).
    fn validate_query(&self, q: &Self::Query) -> Result<()>;
    /// Dissimilarity of `candidate` to `query` under `spec`: lower is more similar.
    fn score(&self, query: &Self::Prepared, candidate: &Self::Prepared, spec: &Self::Query) -> f64;
    /// [`Engine::score`] of `query` against each of `candidates` (same values; an engine may
    /// resolve the query once).
    fn score_row(
        &self,
        query: &Self::Prepared,
        candidates: &[&Self::Prepared],
        spec: &Self::Query,
    ) -> Vec<f64> {
        candidates
            .iter()
            .map(|c| self.score(query, c, spec))
            .collect()
    }
    /// An accelerator over the scan's prepared array, kept in step with it by the scan index.
    type Table: ScanTable<Self::Prepared>;

    /// The `k` best of `candidates` (the array `table` was built from) among positions passing
    /// `keep`, as `(position, score)` sorted by score (`f64::total_cmp`), ties by position:
    /// the head of the full ranking by [`Engine::score`], filtered.
    fn top_k(
        &self,
        query: &Self::Prepared,
        candidates: &[Self::Prepared],
        table: &Self::Table,
        spec: &Self::Query,
        k: usize,
        keep: &(dyn Fn(usize) -> bool + Sync),
    ) -> Vec<(usize, f64)>;
}

/// A structure derived from the scan's prepared array and edited with it (same positions).
pub trait ScanTable<P>: Send + Sync + 'static {
    /// The table of `prepared`, in order.
    fn build(prepared: &[P]) -> Self;
    /// Inserts `p` at position `at`.
    fn insert(&mut self, at: usize, p: &P);
    /// Replaces position `at` by `p`.
    fn replace(&mut self, at: usize, p: &P);
    /// Removes position `at`.
    fn remove(&mut self, at: usize);
}
