//! The in-memory scan structure: every stored signature prepared under the current
//! calibration, as parallel arrays sorted by id (= ingest order), with the engine's scan table
//! (for the framework: `topk::BoundTable`, contiguous group sums giving lower bounds), ranked
//! by the engine's `top_k` — exactly the head of the framework's full ranking (sorted by score,
//! ties by position: the same scores and tie rule as the evaluation harness).
//!
//! It is loaded from the store at start and kept in step with every insert and delete by the
//! server (under a write lock held only for the update). Recalibration builds the new prepared
//! array outside the lock and swaps it in; only the engine's table is rebuilt under the lock
//! (one pass over the prepared histograms), so searches wait for that pass at most.

use super::engine::{Engine, ScanTable};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::Arc;

/// A shape to index: (id, name, tags, signature).
pub type ShapeRow<E> = (String, String, Vec<String>, Arc<<E as Engine>::Signature>);

/// Shapes in id order with their prepared signatures (struct of arrays).
pub struct ScanIndex<E: Engine> {
    calibration: Option<Arc<E::Calibration>>,
    calibrated_on: usize,
    ids: Vec<String>,
    names: Vec<String>,
    tags: Vec<Vec<String>>,
    signatures: Vec<Arc<E::Signature>>,
    prepared: Vec<E::Prepared>,
    table: E::Table,
}

impl<E: Engine> Default for ScanIndex<E> {
    fn default() -> Self {
        Self {
            calibration: None,
            calibrated_on: 0,
            ids: Vec::new(),
            names: Vec::new(),
            tags: Vec::new(),
            signatures: Vec::new(),
            prepared: Vec::new(),
            table: E::Table::build(&[]),
        }
    }
}

/// A candidate found by a scan: position in the scan arrays and score.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scored {
    /// Position (id order).
    pub at: usize,
    /// Dissimilarity (lower = more similar).
    pub score: f64,
}

impl<E: Engine> ScanIndex<E> {
    /// The current calibration (None only while the index has never held a shape).
    pub fn calibration(&self) -> Option<&Arc<E::Calibration>> {
        self.calibration.as_ref()
    }

    /// How many shapes the current calibration was computed on.
    pub fn calibrated_on(&self) -> usize {
        self.calibrated_on
    }

    /// Number of shapes.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Position of an id.
    pub fn position(&self, id: &str) -> Option<usize> {
        self.ids.binary_search_by(|x| x.as_str().cmp(id)).ok()
    }

    /// Id at a position.
    pub fn id(&self, at: usize) -> &str {
        &self.ids[at]
    }

    /// Name at a position.
    pub fn name(&self, at: usize) -> &str {
        &self.names[at]
    }

    /// Tags at a position.
    pub fn tags(&self, at: usize) -> &[String] {
        &self.tags[at]
    }

    /// Signature at a position.
    pub fn signature(&self, at: usize) -> &Arc<E::Signature> {
        &self.signatures[at]
    }

    /// The prepared signatures, contiguous, in id order.
    pub fn prepared(&self) -> &[E::Prepared] {
        &self.prepared
    }

    /// Builds the index from stored shapes under `cal`.
    pub fn build(
        engine: &E,
        cal: Arc<E::Calibration>,
        calibrated_on: usize,
        mut shapes: Vec<ShapeRow<E>>,
    ) -> Self {
        shapes.sort_by(|a, b| a.0.cmp(&b.0));
        let prepared: Vec<E::Prepared> = shapes
            .par_iter()
            .map(|(_, _, _, s)| engine.prepare(s, &cal))
            .collect();
        let mut idx = Self {
            calibration: Some(cal),
            calibrated_on,
            table: E::Table::build(&prepared),
            prepared,
            ..Self::default()
        };
        for (id, name, tags, signature) in shapes {
            idx.ids.push(id);
            idx.names.push(name);
            idx.tags.push(tags);
            idx.signatures.push(signature);
        }
        idx
    }

    /// Adds (or replaces) a shape, prepared under the current calibration; a first shape is
    /// calibrated on itself (epoch `first_epoch`).
    pub fn insert(
        &mut self,
        engine: &E,
        id: String,
        name: String,
        tags: Vec<String>,
        signature: Arc<E::Signature>,
        first_epoch: u64,
    ) {
        let cal = match &self.calibration {
            Some(c) => c.clone(),
            None => {
                let c = Arc::new(engine.calibrate(&[&*signature], first_epoch));
                self.calibration = Some(c.clone());
                self.calibrated_on = 1;
                c
            }
        };
        let prepared = engine.prepare(&signature, &cal);
        match self.ids.binary_search(&id) {
            Ok(at) => {
                self.names[at] = name;
                self.tags[at] = tags;
                self.signatures[at] = signature;
                self.table.replace(at, &prepared);
                self.prepared[at] = prepared;
            }
            Err(at) => {
                self.ids.insert(at, id);
                self.names.insert(at, name);
                self.tags.insert(at, tags);
                self.signatures.insert(at, signature);
                self.table.insert(at, &prepared);
                self.prepared.insert(at, prepared);
            }
        }
    }

    /// Removes a shape. False when absent.
    pub fn remove(&mut self, id: &str) -> bool {
        let Some(at) = self.position(id) else {
            return false;
        };
        self.ids.remove(at);
        self.names.remove(at);
        self.tags.remove(at);
        self.signatures.remove(at);
        self.prepared.remove(at);
        self.table.remove(at);
        true
    }

    /// True when the size moved by more than `fraction` since the last calibration.
    pub fn needs_recalibration(&self, fraction: f64) -> bool {
        if self.ids.is_empty() {
            return false;
        }
        let n = self.ids.len() as f64;
        let c = self.calibrated_on as f64;
        self.calibration.is_none() || (n - c).abs() > fraction * c.max(1.0)
    }

    /// A snapshot of (id, signature) for recalibration outside the lock.
    pub fn snapshot(&self) -> Vec<(String, Arc<E::Signature>)> {
        self.ids
            .iter()
            .cloned()
            .zip(self.signatures.iter().cloned())
            .collect()
    }

    /// Installs a calibration and prepared signatures computed on a snapshot; shapes added
    /// since the snapshot are prepared here, shapes deleted since are ignored.
    pub fn install_calibration(
        &mut self,
        engine: &E,
        cal: Arc<E::Calibration>,
        calibrated_on: usize,
        mut prepared: HashMap<String, E::Prepared>,
    ) {
        for (at, id) in self.ids.iter().enumerate() {
            self.prepared[at] = match prepared.remove(id) {
                Some(p) => p,
                None => engine.prepare(&self.signatures[at], &cal),
            };
        }
        self.table = E::Table::build(&self.prepared);
        self.calibration = Some(cal);
        self.calibrated_on = calibrated_on;
    }

    /// The `k` best shapes for `query` under `spec` among positions passing `keep`, best
    /// first: the head of the engine's full ranking, filtered.
    pub fn rank(
        &self,
        engine: &E,
        query: &E::Prepared,
        spec: &E::Query,
        k: usize,
        keep: &(dyn Fn(usize) -> bool + Sync),
    ) -> Vec<Scored> {
        if k == 0 || self.ids.is_empty() {
            return Vec::new();
        }
        engine
            .top_k(query, &self.prepared, &self.table, spec, k, keep)
            .into_iter()
            .map(|(at, score)| Scored { at, score })
            .collect()
    }
}
