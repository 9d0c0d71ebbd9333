//! The in-memory scan structure: every stored signature prepared under the current
//! calibration, in one contiguous vector, ranked with rayon over chunks.
//!
//! It is loaded from the store at start and kept in step with every insert and delete by the
//! server (under a write lock held only for the O(1) update). Recalibration builds the new
//! prepared vector outside the lock and swaps it in, so searches never wait for it.

use super::engine::Engine;
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::Arc;

/// A shape to index: (id, name, tags, signature).
pub type ShapeRow<E> = (String, String, Vec<String>, Arc<<E as Engine>::Signature>);

/// One indexed shape.
pub struct Entry<E: Engine> {
    /// Shape id.
    pub id: String,
    /// Display name.
    pub name: String,
    /// Tags (filters).
    pub tags: Vec<String>,
    /// The stored signature (kept for recalibration).
    pub signature: Arc<E::Signature>,
    /// The signature prepared under [`ScanIndex::calibration`].
    pub prepared: E::Prepared,
}

/// Shapes in scan order with their prepared signatures.
pub struct ScanIndex<E: Engine> {
    calibration: Option<Arc<E::Calibration>>,
    calibrated_on: usize,
    entries: Vec<Entry<E>>,
    pos: HashMap<String, usize>,
}

impl<E: Engine> Default for ScanIndex<E> {
    fn default() -> Self {
        Self {
            calibration: None,
            calibrated_on: 0,
            entries: Vec::new(),
            pos: HashMap::new(),
        }
    }
}

/// A candidate found by a scan: position in the scan vector and score.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scored {
    /// Index into [`ScanIndex::entries`].
    pub at: usize,
    /// Dissimilarity (lower = more similar).
    pub score: f64,
}

/// Orders by score (NaN last), then by scan position (ingest order) for determinism.
pub fn by_score(a: &Scored, b: &Scored) -> std::cmp::Ordering {
    let ka = if a.score.is_nan() {
        f64::INFINITY
    } else {
        a.score
    };
    let kb = if b.score.is_nan() {
        f64::INFINITY
    } else {
        b.score
    };
    ka.total_cmp(&kb).then(a.at.cmp(&b.at))
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
        self.entries.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The entries in scan order.
    pub fn entries(&self) -> &[Entry<E>] {
        &self.entries
    }

    /// Position of an id.
    pub fn position(&self, id: &str) -> Option<usize> {
        self.pos.get(id).copied()
    }

    /// Builds the index from stored shapes under `cal`.
    pub fn build(
        engine: &E,
        cal: Arc<E::Calibration>,
        calibrated_on: usize,
        shapes: Vec<ShapeRow<E>>,
    ) -> Self {
        let prepared: Vec<E::Prepared> = shapes
            .par_iter()
            .map(|(_, _, _, s)| engine.prepare(s, &cal))
            .collect();
        let mut idx = Self {
            calibration: Some(cal),
            calibrated_on,
            entries: Vec::with_capacity(shapes.len()),
            pos: HashMap::with_capacity(shapes.len()),
        };
        for ((id, name, tags, signature), prepared) in shapes.into_iter().zip(prepared) {
            idx.pos.insert(id.clone(), idx.entries.len());
            idx.entries.push(Entry {
                id,
                name,
                tags,
                signature,
                prepared,
            });
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
        let entry = Entry {
            id: id.clone(),
            name,
            tags,
            signature,
            prepared,
        };
        match self.pos.get(&id) {
            Some(&at) => self.entries[at] = entry,
            None => {
                self.pos.insert(id, self.entries.len());
                self.entries.push(entry);
            }
        }
    }

    /// Removes a shape (swap-remove). False when absent.
    pub fn remove(&mut self, id: &str) -> bool {
        let Some(at) = self.pos.remove(id) else {
            return false;
        };
        self.entries.swap_remove(at);
        if at < self.entries.len() {
            let moved = self.entries[at].id.clone();
            self.pos.insert(moved, at);
        }
        true
    }

    /// True when the size moved by more than `fraction` since the last calibration.
    pub fn needs_recalibration(&self, fraction: f64) -> bool {
        let n = self.entries.len() as f64;
        let c = self.calibrated_on as f64;
        if self.entries.is_empty() {
            return false;
        }
        self.calibration.is_none() || (n - c).abs() > fraction * c.max(1.0)
    }

    /// A snapshot of (id, signature) for recalibration outside the lock.
    pub fn snapshot(&self) -> Vec<(String, Arc<E::Signature>)> {
        self.entries
            .iter()
            .map(|e| (e.id.clone(), e.signature.clone()))
            .collect()
    }

    /// Installs a calibration and prepared signatures computed on `prepared` (a snapshot);
    /// entries added since the snapshot are prepared here, entries deleted since are ignored.
    pub fn install_calibration(
        &mut self,
        engine: &E,
        cal: Arc<E::Calibration>,
        calibrated_on: usize,
        mut prepared: HashMap<String, E::Prepared>,
    ) {
        for e in self.entries.iter_mut() {
            e.prepared = match prepared.remove(&e.id) {
                Some(p) => p,
                None => engine.prepare(&e.signature, &cal),
            };
        }
        self.calibration = Some(cal);
        self.calibrated_on = calibrated_on;
    }

    /// The `k` best entries for `query` under `spec`, among those passing `keep(position, entry)`, best first.
    /// Ranks all candidates with rayon over chunks, each chunk keeping its own top `k`.
    pub fn rank(
        &self,
        engine: &E,
        query: &E::Prepared,
        spec: &E::Query,
        k: usize,
        keep: &(dyn Fn(usize, &Entry<E>) -> bool + Sync),
    ) -> Vec<Scored> {
        if k == 0 || self.entries.is_empty() {
            return Vec::new();
        }
        const CHUNK: usize = 256;
        let mut all: Vec<Scored> = self
            .entries
            .par_chunks(CHUNK)
            .enumerate()
            .map(|(c, chunk)| {
                let mut local: Vec<Scored> = chunk
                    .iter()
                    .enumerate()
                    .filter(|(i, e)| keep(c * CHUNK + i, e))
                    .map(|(i, e)| Scored {
                        at: c * CHUNK + i,
                        score: engine.score(query, &e.prepared, spec),
                    })
                    .collect();
                local.sort_by(by_score);
                local.truncate(k);
                local
            })
            .reduce(Vec::new, |mut a, b| {
                a.extend(b);
                a.sort_by(by_score);
                a.truncate(k);
                a
            });
        all.sort_by(by_score);
        all.truncate(k);
        all
    }
}
