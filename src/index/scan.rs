//! The in-memory scan structure: every stored shape under the current calibration, sorted by id
//! (= ingest order), as one [`Corpus`] plus compact arenas of ids, names and tags. Ranked by
//! [`crate::search::top_k`]: exactly the head of the full ranking (sorted by score, ties by
//! position), the scores and tie rule of the evaluation harness.
//!
//! It is loaded from the store at start and kept in step with every insert and delete by the
//! server (under a write lock held only for the update). Signatures are not kept: recalibration
//! reads them from the store, builds the new corpus outside the lock and swaps it in
//! ([`ScanIndex::install_calibration`]); only shapes added since its snapshot are encoded under
//! the lock.

use super::engine::Engine;
use crate::ranking::Calibration;
use crate::search::corpus::{Corpus, Encoded, Layout};
use crate::search::{top_k, Query};
use crate::signature::Signature;
use std::collections::HashMap;
use std::sync::Arc;

/// A shape to index: (id, name, tags, signature).
pub type ShapeRow = (String, String, Vec<String>, Signature);

/// Strings in one buffer, addressed by position.
#[derive(Clone, Debug, Default)]
struct Strings {
    buf: String,
    ends: Vec<u32>,
}

impl Strings {
    fn len(&self) -> usize {
        self.ends.len()
    }
    fn range(&self, i: usize) -> std::ops::Range<usize> {
        let start = if i == 0 { 0 } else { self.ends[i - 1] as usize };
        start..self.ends[i] as usize
    }
    fn get(&self, i: usize) -> &str {
        &self.buf[self.range(i)]
    }
    fn insert(&mut self, i: usize, s: &str) {
        let at = if i == 0 { 0 } else { self.ends[i - 1] as usize };
        self.buf.insert_str(at, s);
        let n = s.len() as u32;
        self.ends.insert(i, at as u32 + n);
        self.ends[i + 1..].iter_mut().for_each(|e| *e += n);
    }
    fn remove(&mut self, i: usize) {
        let r = self.range(i);
        let n = r.len() as u32;
        self.buf.replace_range(r, "");
        self.ends.remove(i);
        self.ends[i..].iter_mut().for_each(|e| *e -= n);
    }
    fn set(&mut self, i: usize, s: &str) {
        self.remove(i);
        self.insert(i, s);
    }
    fn search(&self, s: &str) -> Result<usize, usize> {
        let (mut lo, mut hi) = (0, self.len());
        while lo < hi {
            let mid = (lo + hi) / 2;
            match self.get(mid).cmp(s) {
                std::cmp::Ordering::Less => lo = mid + 1,
                std::cmp::Ordering::Greater => hi = mid,
                std::cmp::Ordering::Equal => return Ok(mid),
            }
        }
        Err(lo)
    }
    fn bytes(&self) -> usize {
        self.buf.capacity() + 4 * self.ends.capacity()
    }
}

/// Per shape a set of tags, as indices into a dictionary of distinct tags.
#[derive(Clone, Debug, Default)]
struct TagSets {
    dict: Vec<String>,
    lookup: HashMap<String, u32>,
    ids: Vec<u32>,
    ends: Vec<u32>,
}

impl TagSets {
    fn range(&self, i: usize) -> std::ops::Range<usize> {
        let start = if i == 0 { 0 } else { self.ends[i - 1] as usize };
        start..self.ends[i] as usize
    }
    fn intern(&mut self, t: &str) -> u32 {
        if let Some(&k) = self.lookup.get(t) {
            return k;
        }
        self.dict.push(t.to_string());
        let k = (self.dict.len() - 1) as u32;
        self.lookup.insert(t.to_string(), k);
        k
    }
    fn insert(&mut self, i: usize, tags: &[String]) {
        let ks: Vec<u32> = tags.iter().map(|t| self.intern(t)).collect();
        let at = if i == 0 { 0 } else { self.ends[i - 1] as usize };
        self.ids.splice(at..at, ks.iter().copied());
        let n = ks.len() as u32;
        self.ends.insert(i, at as u32 + n);
        self.ends[i + 1..].iter_mut().for_each(|e| *e += n);
    }
    fn remove(&mut self, i: usize) {
        let r = self.range(i);
        let n = r.len() as u32;
        self.ids.drain(r);
        self.ends.remove(i);
        self.ends[i..].iter_mut().for_each(|e| *e -= n);
    }
    fn set(&mut self, i: usize, tags: &[String]) {
        self.remove(i);
        self.insert(i, tags);
    }
    fn get(&self, i: usize) -> impl Iterator<Item = &str> {
        self.ids[self.range(i)]
            .iter()
            .map(|&k| self.dict[k as usize].as_str())
    }
    fn bytes(&self) -> usize {
        4 * (self.ids.capacity() + self.ends.capacity())
            + self.dict.iter().map(|t| 2 * t.len() + 64).sum::<usize>()
    }
}

/// A tag filter resolved against an index (see [`ScanIndex::tag_filter`]).
#[derive(Clone, Debug)]
pub enum TagFilter {
    /// Shapes having all of these tags.
    All(Vec<u32>),
    /// A tag no shape has: nothing matches.
    Nothing,
}

/// Shapes in id order with their encoded channels.
pub struct ScanIndex {
    calibration: Option<Arc<Calibration>>,
    calibrated_on: usize,
    ids: Strings,
    names: Strings,
    tags: TagSets,
    corpus: Corpus,
}

impl Default for ScanIndex {
    fn default() -> Self {
        Self {
            calibration: None,
            calibrated_on: 0,
            ids: Strings::default(),
            names: Strings::default(),
            tags: TagSets::default(),
            corpus: Corpus::new(Layout::of(&Calibration {
                epoch: 0,
                spec_key: String::new(),
                channel_names: Vec::new(),
                window_max: Vec::new(),
                bins: 1,
                bandwidth_bins: 1.0,
                percentile: 0.95,
                shapes: 0,
            })),
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

/// `corpus`, the encoding of the sorted ids `snapshot`, re-keyed to `ids` (sorted): the row of
/// an id in the snapshot is copied, any other comes from `encode`, called in `ids` order.
pub fn rekey<'a>(
    corpus: &Corpus,
    snapshot: &[String],
    ids: impl ExactSizeIterator<Item = &'a str>,
    encode: &mut dyn FnMut(&str) -> Encoded,
) -> Corpus {
    let mut c = Corpus::with_capacity(corpus.layout().clone(), ids.len());
    for id in ids {
        match snapshot.binary_search_by(|s| s.as_str().cmp(id)) {
            Ok(j) => c.push(&corpus.encoded(j)),
            Err(_) => c.push(&encode(id)),
        }
    }
    c
}

impl ScanIndex {
    /// The current calibration (None only while the index has never held a shape).
    pub fn calibration(&self) -> Option<&Arc<Calibration>> {
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
        self.ids.len() == 0
    }

    /// Position of an id.
    pub fn position(&self, id: &str) -> Option<usize> {
        self.ids.search(id).ok()
    }

    /// Id at a position.
    pub fn id(&self, at: usize) -> &str {
        self.ids.get(at)
    }

    /// Name at a position.
    pub fn name(&self, at: usize) -> &str {
        self.names.get(at)
    }

    /// Tags at a position.
    pub fn tags(&self, at: usize) -> Vec<&str> {
        self.tags.get(at).collect()
    }

    /// Resolves the tags every hit must have.
    pub fn tag_filter(&self, tags: &[String]) -> TagFilter {
        let mut ks = Vec::with_capacity(tags.len());
        for t in tags {
            match self.tags.lookup.get(t) {
                Some(&k) => ks.push(k),
                None => return TagFilter::Nothing,
            }
        }
        TagFilter::All(ks)
    }

    /// True when the shape at `at` passes `filter`.
    pub fn has_tags(&self, at: usize, filter: &TagFilter) -> bool {
        match filter {
            TagFilter::Nothing => false,
            TagFilter::All(ks) => {
                let have = &self.tags.ids[self.tags.range(at)];
                ks.iter().all(|k| have.contains(k))
            }
        }
    }

    /// The encoded shapes, in id order.
    pub fn corpus(&self) -> &Corpus {
        &self.corpus
    }

    /// The ids, in order.
    pub fn ids(&self) -> Vec<String> {
        (0..self.len()).map(|i| self.id(i).to_string()).collect()
    }

    /// Heap bytes held by the index (corpus and arenas).
    pub fn heap_bytes(&self) -> usize {
        self.corpus.heap_bytes() + self.ids.bytes() + self.names.bytes() + self.tags.bytes()
    }

    /// Builds the index from stored shapes under `cal`.
    pub fn build(cal: Arc<Calibration>, calibrated_on: usize, mut shapes: Vec<ShapeRow>) -> Self {
        use rayon::prelude::*;
        shapes.sort_by(|a, b| a.0.cmp(&b.0));
        let layout = Layout::of(&cal);
        let encoded: Vec<Encoded> = shapes
            .par_iter()
            .map(|(_, _, _, s)| Encoded::from_signature(s, &cal, &layout))
            .collect();
        let mut idx = Self {
            corpus: Corpus::build(layout, &encoded),
            calibration: Some(cal),
            calibrated_on,
            ..Self::default()
        };
        for (i, (id, name, tags, _)) in shapes.iter().enumerate() {
            idx.ids.insert(i, id);
            idx.names.insert(i, name);
            idx.tags.insert(i, tags);
        }
        idx
    }

    /// An empty index under `cal` with room for `n` shapes (filled by
    /// [`ScanIndex::push_encoded`]).
    pub fn with_capacity(cal: Arc<Calibration>, calibrated_on: usize, n: usize) -> Self {
        Self {
            corpus: Corpus::with_capacity(Layout::of(&cal), n),
            calibration: Some(cal),
            calibrated_on,
            ..Self::default()
        }
    }

    /// Appends a shape already encoded under the index's calibration; its id must sort after
    /// every id held (bulk loading in id order).
    pub fn push_encoded(&mut self, id: &str, name: &str, tags: &[String], e: &Encoded) {
        let at = self.len();
        assert!(
            at == 0 || self.id(at - 1) < id,
            "push_encoded: ids must increase"
        );
        self.ids.insert(at, id);
        self.names.insert(at, name);
        self.tags.insert(at, tags);
        self.corpus.push(e);
    }

    /// Adds (or replaces) a shape, encoded under the current calibration; a first shape is
    /// calibrated on itself (epoch `first_epoch`).
    pub fn insert(
        &mut self,
        engine: &Engine,
        id: &str,
        name: &str,
        tags: &[String],
        signature: &Signature,
        first_epoch: u64,
    ) {
        let cal = match &self.calibration {
            Some(c) => c.clone(),
            None => {
                let c = Arc::new(engine.calibrate(&[signature], first_epoch));
                self.corpus = Corpus::new(Layout::of(&c));
                self.calibration = Some(c.clone());
                self.calibrated_on = 1;
                c
            }
        };
        let e = Encoded::from_signature(signature, &cal, self.corpus.layout());
        match self.ids.search(id) {
            Ok(at) => {
                self.names.set(at, name);
                self.tags.set(at, tags);
                self.corpus.replace(at, &e);
            }
            Err(at) => {
                self.ids.insert(at, id);
                self.names.insert(at, name);
                self.tags.insert(at, tags);
                self.corpus.insert(at, &e);
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
        self.corpus.remove(at);
        true
    }

    /// True when the size moved by more than `fraction` since the last calibration.
    pub fn needs_recalibration(&self, fraction: f64) -> bool {
        if self.is_empty() {
            return false;
        }
        let n = self.len() as f64;
        let c = self.calibrated_on as f64;
        self.calibration.is_none() || (n - c).abs() > fraction * c.max(1.0)
    }

    /// Installs a calibration and the corpus built under it for the shapes `snapshot` (sorted
    /// ids, in `corpus` order). When the index still holds exactly those shapes the corpus is
    /// swapped in; otherwise shapes deleted since are left out and shapes added since are
    /// encoded by `encode` (under the new calibration).
    pub fn install_calibration(
        &mut self,
        cal: Arc<Calibration>,
        calibrated_on: usize,
        snapshot: &[String],
        corpus: Corpus,
        encode: &mut dyn FnMut(&str, &Calibration, &Layout) -> Encoded,
    ) {
        let same = snapshot.len() == self.len()
            && snapshot.iter().enumerate().all(|(i, s)| s == self.id(i));
        self.corpus = if same {
            corpus
        } else {
            let layout = corpus.layout().clone();
            let ids = (0..self.len()).map(|i| self.id(i));
            rekey(&corpus, snapshot, ids, &mut |id| encode(id, &cal, &layout))
        };
        self.calibration = Some(cal);
        self.calibrated_on = calibrated_on;
    }

    /// The `k` best shapes for `query` under `q` among positions passing `keep`, best first:
    /// the head of the full ranking, filtered.
    pub fn rank(
        &self,
        query: &Encoded,
        q: &Query,
        k: usize,
        keep: &(dyn Fn(usize) -> bool + Sync),
    ) -> Vec<Scored> {
        if k == 0 || self.is_empty() {
            return Vec::new();
        }
        top_k(&self.corpus, q, query.view(), k, keep)
            .0
            .into_iter()
            .map(|(at, score)| Scored { at, score })
            .collect()
    }
}
