//! The product [`Engine`]: the framework's signatures and ranking (`crate::signature`,
//! `crate::ranking`), exactly the calls the evaluation harness makes.

use super::engine::{Engine, ScanTable};
use crate::ranking::{self, Calibration, Config, Prepared, QuerySpec};
use crate::signature::{compute_signature, Signature};
use crate::spectrum::{Analysis, AnalyzeOptions};
use crate::topk::BoundTable;
use crate::{Error, Result};

/// Framework engine: a signature spec + default query spec ([`Config`]) and the analysis
/// options (number of eigenpairs) the signatures are computed from.
#[derive(Clone, Debug)]
pub struct FwEngine {
    /// Signature spec and default query spec.
    pub config: Config,
    /// Preparation and eigensolver options of [`crate::spectrum::analyze`].
    pub analyze: AnalyzeOptions,
}

impl FwEngine {
    /// The product default ([`ranking::default_config`], default analysis options).
    pub fn new() -> Self {
        Self {
            config: ranking::default_config(),
            analyze: AnalyzeOptions::default(),
        }
    }
}

impl Default for FwEngine {
    fn default() -> Self {
        Self::new()
    }
}

/// The engine `shapeseek serve` uses.
pub fn default_engine() -> FwEngine {
    FwEngine::new()
}

impl Engine for FwEngine {
    type Signature = Signature;
    type Calibration = Calibration;
    type Prepared = Prepared;
    type Query = QuerySpec;
    type Table = BoundTable;

    fn name(&self) -> String {
        format!("framework:{}", self.config.name)
    }
    fn analyze_options(&self) -> AnalyzeOptions {
        self.analyze.clone()
    }
    fn spec_key(&self) -> String {
        // The eigenpair count changes the signature too: part of the key.
        format!("{}-k{}", self.config.signature.key(), self.analyze.eigen.k)
    }
    fn spec_json(&self) -> serde_json::Value {
        serde_json::json!({
            "signature": self.config.signature,
            "eigenpairs": self.analyze.eigen.k,
        })
    }
    fn compute(&self, analysis: &Analysis) -> Result<Signature> {
        compute_signature(analysis, &self.config.signature)
    }
    fn signature_spec_key(&self, sig: &Signature) -> String {
        // Stored signatures are written by this engine only; the framework's key covers the
        // spec, and the record's spec_key (checked at load) covers the analysis options.
        format!("{}-k{}", sig.spec_key, self.analyze.eigen.k)
    }
    fn encode_signature(&self, sig: &Signature) -> Vec<u8> {
        sig.to_bytes()
    }
    fn decode_signature(&self, bytes: &[u8]) -> Result<Signature> {
        Signature::from_bytes(bytes)
    }
    fn signature_json(&self, sig: &Signature) -> serde_json::Value {
        serde_json::to_value(sig).unwrap_or(serde_json::Value::Null)
    }
    fn calibrate(&self, sigs: &[&Signature], epoch: u64) -> Calibration {
        ranking::calibrate(sigs, &self.config.signature, epoch)
    }
    fn calibration_epoch(&self, cal: &Calibration) -> u64 {
        cal.epoch
    }
    fn prepare(&self, sig: &Signature, cal: &Calibration) -> Prepared {
        ranking::prepare_for_ranking(sig, cal)
    }
    fn default_query(&self) -> QuerySpec {
        self.config.query.clone()
    }
    fn default_rerank(&self) -> Vec<crate::rerank::RerankStage> {
        self.config.rerank.clone()
    }
    fn validate_query(&self, q: &QuerySpec) -> Result<()> {
        let known = self.config.signature.channel_names();
        if q.channels.is_empty() {
            return Err(Error::InvalidArgument("channels: at least one".into()));
        }
        for c in &q.channels {
            if !known.contains(c) {
                return Err(Error::InvalidArgument(format!(
                    "channel {c:?} is not in the index's signature (channels: {known:?})"
                )));
            }
        }
        Ok(())
    }
    fn score(&self, query: &Prepared, candidate: &Prepared, spec: &QuerySpec) -> f64 {
        ranking::score(query, candidate, spec)
    }
    fn score_row(&self, query: &Prepared, candidates: &[&Prepared], spec: &QuerySpec) -> Vec<f64> {
        let s = ranking::Scorer::new(query, spec);
        candidates.iter().map(|c| s.score(c)).collect()
    }
    fn top_k(
        &self,
        query: &Prepared,
        candidates: &[Prepared],
        table: &BoundTable,
        spec: &QuerySpec,
        k: usize,
        keep: &(dyn Fn(usize) -> bool + Sync),
    ) -> Vec<(usize, f64)> {
        table.top_k(query, candidates, spec, k, keep)
    }
}

impl ScanTable<Prepared> for BoundTable {
    fn build(prepared: &[Prepared]) -> Self {
        BoundTable::build(prepared)
    }
    fn insert(&mut self, at: usize, p: &Prepared) {
        BoundTable::insert(self, at, p)
    }
    fn replace(&mut self, at: usize, p: &Prepared) {
        BoundTable::replace(self, at, p)
    }
    fn remove(&mut self, at: usize) {
        BoundTable::remove(self, at)
    }
}
