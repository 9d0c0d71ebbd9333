//! What the index computes per shape and how it ranks by default: a [`Config`] (signature spec,
//! default query spec and stages) and the analysis options its signatures are computed from.
//! Signatures, calibrations and scores are the framework's own calls (`crate::signature`,
//! `crate::ranking`, `crate::search`), the calls eval makes, so a ranking by the server equals
//! the one of `eval` for the same query spec and calibration.

use crate::presets::{self, Config};
use crate::ranking::{self, Calibration, QuerySpec};
use crate::search::Stage;
use crate::signature::Signature;
use crate::spectrum::{Analysis, AnalyzeOptions};
use crate::{Error, Result};

/// The index's signature and ranking configuration.
#[derive(Clone, Debug)]
pub struct Engine {
    /// Signature spec, default query spec and default stages.
    pub config: Config,
    /// Preparation and eigensolver options of [`crate::spectrum::analyze`].
    pub analyze: AnalyzeOptions,
}

impl Default for Engine {
    fn default() -> Self {
        Self::new()
    }
}

/// The engine `shapeseek serve` uses.
pub fn default_engine() -> Engine {
    Engine::new()
}

impl Engine {
    /// The product default ([`presets::default_config`], default analysis options with the
    /// vertex budget [`presets::ANALYSIS_VERTEX_BUDGET`]).
    pub fn new() -> Self {
        let mut analyze = AnalyzeOptions::default();
        analyze.prepare.max_vertices = Some(presets::ANALYSIS_VERTEX_BUDGET);
        Self {
            config: presets::default_config(),
            analyze,
        }
    }

    /// A short name for logs and `/v1/index`.
    pub fn name(&self) -> String {
        format!("framework:{}", self.config.name)
    }

    /// The analysis (preparation + eigenpairs) the signature needs: the engine's options with
    /// the signature spec's handle cutting ([`crate::signature::SignatureSpec::analysis_options`]).
    pub fn analyze_options(&self) -> AnalyzeOptions {
        self.config.signature.analysis_options(&self.analyze)
    }

    /// A stable key of the signature spec: stored signatures with another key are stale. The
    /// eigenpair count changes the signature too: part of the key; so does handle cutting in
    /// preparation (`+cut<hash of its options>` before `-k`, absent without it, so keys of
    /// indexes built without cutting are unchanged); the signature key carries
    /// [`crate::ALGORITHM_REVISION`] ([`crate::signature::SignatureSpec::key`]). A changed key
    /// makes the server recompute every stored signature (and payload) from the stored originals
    /// at start-up.
    pub fn spec_key(&self) -> String {
        format!(
            "{}{}-k{}",
            self.config.signature.key(),
            self.analysis_tag(),
            self.analyze.eigen.k
        )
    }

    /// The part of the key that comes from the analysis options (handle cutting).
    fn analysis_tag(&self) -> String {
        use sha2::{Digest, Sha256};
        match &self.analyze.prepare.cut_handles {
            None => String::new(),
            Some(c) => {
                let json = serde_json::to_vec(c).expect("options serialise");
                let d = Sha256::digest(&json);
                let hex: String = d[..6].iter().map(|b| format!("{b:02x}")).collect();
                format!("+cut{hex}")
            }
        }
    }

    /// The signature spec as JSON (for `/v1/index`), with the vertex budget of the analysis
    /// (`null`: none).
    pub fn spec_json(&self) -> serde_json::Value {
        serde_json::json!({
            "signature": self.config.signature,
            "eigenpairs": self.analyze.eigen.k,
            "vertex_budget": self.analyze.prepare.max_vertices,
        })
    }

    /// Analyses `mesh` and computes its signature with both cut versions
    /// ([`crate::signature::sign`]): the one path of ingest, search by upload and the
    /// recomputation of stale signatures. Returns the first version's analysis.
    pub fn sign(&self, mesh: &crate::mesh::Mesh) -> Result<(Analysis, Signature)> {
        crate::signature::sign(mesh, &self.config.signature, &self.analyze)
    }

    /// [`Engine::sign`] that stops with [`crate::Error::Interrupted`] once `interrupt` fires
    /// (checked in both versions' analyses and signatures: after the preparation, inside the
    /// eigensolve, after the sampling and before each channel).
    pub fn sign_interruptible(
        &self,
        mesh: &crate::mesh::Mesh,
        interrupt: crate::error::Interrupt,
    ) -> Result<(Analysis, Signature)> {
        let mut analyze = self.analyze.clone();
        analyze.eigen.interrupt = interrupt;
        crate::signature::sign(mesh, &self.config.signature, &analyze)
    }

    /// The spec key a signature was computed with (the record's spec key, checked at load,
    /// covers the analysis options).
    pub fn signature_spec_key(&self, sig: &Signature) -> String {
        format!(
            "{}{}-k{}",
            sig.spec_key,
            self.analysis_tag(),
            self.analyze.eigen.k
        )
    }

    /// Serialises a signature for the `signatures` tree.
    pub fn encode_signature(&self, sig: &Signature) -> Vec<u8> {
        sig.to_bytes()
    }

    /// Reads a stored signature back.
    pub fn decode_signature(&self, bytes: &[u8]) -> Result<Signature> {
        Signature::from_bytes(bytes)
    }

    /// The distributions of a signature as JSON (for `GET /v1/shapes/{id}/signature`).
    pub fn signature_json(&self, sig: &Signature) -> serde_json::Value {
        serde_json::to_value(sig).unwrap_or(serde_json::Value::Null)
    }

    /// Calibrates the histogram windows on a set of signatures.
    pub fn calibrate(&self, sigs: &[&Signature], epoch: u64) -> Calibration {
        ranking::calibrate_with(
            sigs,
            &self.config.signature,
            epoch,
            &self.config.calibration,
        )
    }

    /// A stored calibration (its JSON) this engine can scan with: `None` when it does not parse,
    /// was computed for another signature spec (key or channels) or with other calibration
    /// options (bins, bandwidth, window percentile) than the configuration's, e.g. by a release
    /// with another default, which then recalibrates.
    pub fn stored_calibration(&self, json: &[u8]) -> Option<Calibration> {
        let cal = serde_json::from_slice::<Calibration>(json).ok()?;
        let spec = &self.config.signature;
        (self.config.calibration.made(&cal)
            && cal.spec_key == spec.key()
            && cal.channel_names == spec.channel_names())
        .then_some(cal)
    }

    /// The epoch of a calibration.
    pub fn calibration_epoch(&self, cal: &Calibration) -> u64 {
        cal.epoch
    }

    /// The default query spec.
    pub fn default_query(&self) -> QuerySpec {
        self.config.query.clone()
    }

    /// The stages a search applies when the request names none.
    pub fn default_stages(&self) -> Vec<Stage> {
        self.config.rerank.clone()
    }

    /// Checks a query spec against the signature spec (its channels must exist).
    pub fn validate_query(&self, q: &QuerySpec) -> Result<()> {
        let known = self.config.signature.channel_names();
        if q.channels.is_empty() {
            return Err(Error::InvalidArgument("channels: at least one".into()));
        }
        q.validate().map_err(Error::InvalidArgument)?;
        for c in &q.channels {
            if !known.contains(c) {
                return Err(Error::InvalidArgument(format!(
                    "channel {c:?} is not in the index's signature (channels: {known:?})"
                )));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::topology::HandleCutOptions;

    /// The engine scans with a stored calibration only when it was made for its signature spec
    /// with the configuration's calibration options (the default's window is the 90th
    /// percentile, the paper's the 95th); and the default's JSON carries them while a paper
    /// configuration's JSON stays as it was.
    #[test]
    fn a_stored_calibration_must_have_the_configurations_options() {
        let e = Engine::new();
        assert_eq!(
            e.config.calibration.percentile,
            presets::DEFAULT_WINDOW_PERCENTILE
        );
        let own = e.calibrate(&[], 3);
        assert_eq!(own.percentile, 0.9);
        let json = serde_json::to_vec(&own).unwrap();
        assert_eq!(e.stored_calibration(&json), Some(own.clone()));
        let paper = ranking::calibrate(&[], &e.config.signature, 3);
        assert_eq!(paper.percentile, ranking::DEFAULT_PERCENTILE);
        assert_eq!(
            e.stored_calibration(&serde_json::to_vec(&paper).unwrap()),
            None
        );
        // A calibration stored by the release before (256 bins, one bin of smoothing): the
        // node recalibrates.
        assert_eq!(
            (own.bins, own.bandwidth_bins),
            (presets::DEFAULT_HISTOGRAM_BINS, 0.5)
        );
        let mut other_bins = own.clone();
        other_bins.bins = 256;
        assert_eq!(
            e.stored_calibration(&serde_json::to_vec(&other_bins).unwrap()),
            None
        );
        let mut other_bandwidth = own.clone();
        other_bandwidth.bandwidth_bins = 1.0;
        assert_eq!(
            e.stored_calibration(&serde_json::to_vec(&other_bandwidth).unwrap()),
            None
        );
        assert_eq!(e.stored_calibration(b"not json"), None);
        // Made for another signature spec (a node of another release in the same cluster):
        // its windows belong to other channels or distributions.
        let mut other_spec = own.clone();
        other_spec.spec_key = "0123456789abcdef".into();
        assert_eq!(
            e.stored_calibration(&serde_json::to_vec(&other_spec).unwrap()),
            None
        );
        let mut other_channels = own;
        other_channels.channel_names.pop();
        other_channels.window_max.pop();
        assert_eq!(
            e.stored_calibration(&serde_json::to_vec(&other_channels).unwrap()),
            None
        );

        let v = serde_json::to_value(&e.config).unwrap();
        assert_eq!(v["calibration"]["percentile"], 0.9);
        assert_eq!(v["calibration"]["bins"], 128);
        let back: Config = serde_json::from_value(v).unwrap();
        assert_eq!(back, e.config);
        let p = presets::config_by_name("Heat-L2-nL1-Sum[t=0.016..0.1]").unwrap();
        assert!(p.calibration.is_paper());
        assert!(serde_json::to_value(&p)
            .unwrap()
            .get("calibration")
            .is_none());
        let partial: ranking::CalibrationOptions =
            serde_json::from_str(r#"{"percentile": 0.8}"#).unwrap();
        assert_eq!((partial.bins, partial.percentile), (256, 0.8));
        assert!(partial.validate().is_ok());
        let bad = ranking::CalibrationOptions {
            percentile: 1.5,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn handle_cutting_changes_the_spec_key_and_nothing_else_does() {
        let plain = Engine::new();
        assert_eq!(
            plain.spec_key(),
            format!(
                "{}-k{}",
                plain.config.signature.key(),
                plain.analyze.eigen.k
            )
        );
        let mut cut = Engine::new();
        cut.analyze.prepare.cut_handles = Some(HandleCutOptions::default());
        let mut other = Engine::new();
        other.analyze.prepare.cut_handles = Some(HandleCutOptions {
            max_loop_rel: 0.2,
            ..Default::default()
        });
        let (a, b, c) = (plain.spec_key(), cut.spec_key(), other.spec_key());
        assert!(a != b && b != c && a != c, "{a} {b} {c}");
        // The eigenpair count is still the `-k` suffix (read back by the migrations).
        assert_eq!(b.rsplit_once("-k").map(|x| x.1), Some("100"));
    }

    /// An index built by the default before handle cutting (same spec without `cut_handles`)
    /// has another key, so the server recomputes its signatures from the stored originals; and
    /// the default's analysis options cut handles.
    #[test]
    fn the_default_with_cutting_makes_indexes_built_without_it_stale() {
        let now = Engine::new();
        let mut before = Engine::new();
        before.config.signature.cut_handles = None;
        assert_ne!(now.spec_key(), before.spec_key());
        assert_eq!(
            now.analyze_options().prepare.cut_handles,
            Some(presets::DEFAULT_HANDLE_CUT)
        );
        assert_eq!(before.analyze_options().prepare.cut_handles, None);
    }
}
