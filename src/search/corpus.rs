//! The corpus layout: every stored shape's channels under one calibration, shape-major, in a
//! few flat arrays.
//!
//! The channel layout (names, bin count, bin width, which channels are histograms and which
//! are vectors) is held once per corpus in a [`Layout`]. Per shape and histogram channel the
//! corpus keeps:
//!
//! * the normalised bin probabilities quantised to `u16` counts `a_b` summing exactly to
//!   `T_s = TOTAL · 2^s` ([`TOTAL`] = 65 535), with the **scale exponent** `s` (one byte) the
//!   largest for which the largest count still fits in 16 bits: a histogram spread over many
//!   bins gets a finer quantum `1/T_s` than a peaked one. Rounding is largest-remainder, except
//!   that a positive probability never rounds to 0 (it gets at least one count: the symmetric
//!   KL weighs the smallest bins most). An empty histogram is all zeros;
//! * the in-window mass `M` (one `f64`), from which the densities follow:
//!   `f_b = M · a_b / (T_s · h)`, and the cumulative sums are running sums of the counts;
//! * the sums of the counts over [`GROUPS`] groups of adjacent bins at the common scale
//!   `T_max = TOTAL · 2^MAX_SHIFT` (`u32`: `Σ_{b∈g} a_b · 2^{MAX_SHIFT − s}`, exact), the first
//!   level of the lower bounds of [`super::prune`], comparable across shapes without a shift.
//!
//! Vector channels (ShapeDNA) are kept as `f32` ([`Vector`]: half the bytes of the `f64` they
//! are computed in; their rounding, a relative 6·10⁻⁸, is far below the counts' quantum of
//! 1/65 535), with the sums of their values over [`VECTOR_GROUPS`] groups (`f32`), from which
//! the bounds of [`super::prune`] follow; a channel a shape lacks is marked absent. A shape
//! with a second cut version
//! ([`crate::signature::Signature::alternate`]) keeps it as a row of a second set of the same
//! flat arrays, in position order, and every shape the row of its second version (4 bytes per
//! shape; the default gives one to the shapes whose short loops its first cut leaves). Per
//! channel, the default's 128 bins cost 256 bytes of counts, 32 of group sums, 8 of mass and 1
//! of exponent (297; its seven histogram channels:
//! 2 079 per version, 2 087 with the presence bytes of its eight channels, plus its 50
//! eigenvalues, 200 bytes in their own allocation, and their 8 group sums, 32 bytes); the
//! paper's 256 bins cost 553, against
//! 6 144 for the three `f64` arrays per bin this encoding replaced.
//!
//! [`Encoded`] is one shape in the same encoding (a query, or a row being inserted); a
//! [`ShapeRef`] views either.

pub use super::quantise::quantise;
use crate::ranking::{Calibration, Prepared, PreparedChannel};
use crate::signature::Signature;

/// Sum of the quantised counts of a non-empty histogram at scale exponent 0 (the largest
/// `u16`, so that a histogram with all its mass in one bin still fits); at exponent `s` the
/// counts sum to `TOTAL · 2^s`.
pub const TOTAL: u32 = u16::MAX as u32;

/// The largest scale exponent; the group sums are kept at this scale (below 2^24, so that a row
/// of group sums adds up within 32 bits). A histogram of `n` bins has its largest probability
/// at least `1/n`, so the limit binds only above 256 bins.
pub const MAX_SHIFT: u8 = 8;

/// `TOTAL · 2^s` as a float: the sum of the counts of a histogram of scale exponent `s`.
pub fn total_at(s: u8) -> f64 {
    ((TOTAL as u64) << s) as f64
}

/// Groups per histogram of the bound table: a layout's groups are `bins / GROUPS` bins wide
/// (rounded up; the last group of a channel may be shorter), 32 for the paper's 256 bins.
pub const GROUPS: usize = 8;

/// One shape's values of a vector channel, as the corpus keeps and compares them.
pub type Vector = Box<[f32]>;

/// Groups per vector channel of the bound table: a vector of `n` values is summed in groups of
/// [`vector_group_width`]`(n)` consecutive values (the last may be shorter; unused groups are
/// 0), 8 groups of 7 (the last of 1) for the default's 50 eigenvalues.
pub const VECTOR_GROUPS: usize = 8;

/// Values per group of a vector of `n` values (see [`VECTOR_GROUPS`]).
pub fn vector_group_width(n: usize) -> usize {
    n.div_ceil(VECTOR_GROUPS).max(1)
}

/// Writes the group sums of `v` into `out` ([`VECTOR_GROUPS`] entries): each summed in `f64`
/// from the `f32` values, then rounded to `f32`, so within `2^-23` of its magnitude of the
/// exact sum (the bounds allow for that). A sum whose `f64` accumulation may be further off
/// (values of both signs that cancel to below `(w − 1) · 2^-29` of their absolute sum, for groups of
/// `w` values) is NaN: it bounds nothing. Unused groups are 0.
fn vector_groups(v: &[f32], out: &mut [f32]) {
    out.iter_mut().for_each(|x| *x = 0.0);
    for (o, chunk) in out.iter_mut().zip(v.chunks(vector_group_width(v.len()))) {
        let sum: f64 = chunk.iter().map(|&x| x as f64).sum();
        let abs: f64 = chunk.iter().map(|&x| (x as f64).abs()).sum();
        // Accumulation error ≤ (w − 1) 2^-53 Σ|x|; allowed: 2^-24 |sum| (f32 rounding adds as much).
        let exact_enough = (chunk.len() - 1) as f64 * abs <= sum.abs() * (1u64 << 29) as f64;
        *o = if exact_enough { sum as f32 } else { f32::NAN };
    }
}

/// Where a channel's values live.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Slot {
    /// The `k`-th histogram channel.
    Histogram(usize),
    /// The `k`-th vector channel.
    Vector(usize),
}

/// The channel layout of a corpus, derived from its calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    /// Calibration epoch.
    pub epoch: u64,
    /// Channel names, in the calibration's order.
    pub names: Vec<String>,
    /// Where each channel is stored.
    pub slots: Vec<Slot>,
    /// Bin width `h` of each histogram channel (indexed by histogram slot).
    pub bin_width: Vec<f64>,
    /// Bins per histogram.
    pub bins: usize,
    /// Bins per group of the bound table (`bins / GROUPS`, rounded up).
    pub group_bins: usize,
    /// Groups per histogram (`bins / group_bins`, rounded up: at most [`GROUPS`]).
    pub groups: usize,
}

impl Layout {
    /// The layout of `cal`: a channel with window 0 is a vector channel (see
    /// [`crate::ranking::calibrate_with`]), every other one a histogram of `cal.bins` bins.
    pub fn of(cal: &Calibration) -> Layout {
        let bins = cal.bins.max(1);
        let (mut nh, mut nv) = (0, 0);
        let mut bin_width = Vec::new();
        let slots = cal
            .window_max
            .iter()
            .map(|&w| {
                if w > 0.0 {
                    bin_width.push(w / bins as f64);
                    nh += 1;
                    Slot::Histogram(nh - 1)
                } else {
                    nv += 1;
                    Slot::Vector(nv - 1)
                }
            })
            .collect();
        Layout {
            epoch: cal.epoch,
            names: cal.channel_names.clone(),
            slots,
            bin_width,
            bins,
            group_bins: bins.div_ceil(GROUPS),
            groups: bins.div_ceil(bins.div_ceil(GROUPS)),
        }
    }

    /// Number of histogram channels.
    pub fn histograms(&self) -> usize {
        self.bin_width.len()
    }

    /// Number of vector channels.
    pub fn vectors(&self) -> usize {
        self.slots.len() - self.histograms()
    }

    /// Index of the channel called `name`.
    pub fn channel(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Bins in group `g`.
    pub fn group_width(&self, g: usize) -> usize {
        self.group_bins.min(self.bins - g * self.group_bins)
    }

    /// True when `e` has this layout's array lengths, and so has its second version, which has
    /// none of its own: what [`Corpus`] and the scoring and bounds index by.
    pub fn fits(&self, e: &Encoded) -> bool {
        e.hist.len() == self.histograms() * self.bins
            && e.shift.len() == self.histograms()
            && e.groups.len() == self.histograms() * self.groups
            && e.mass.len() == self.histograms()
            && e.present.len() == self.names.len()
            && e.vectors.len() == self.vectors()
            && e.vgroups.len() == self.vectors() * VECTOR_GROUPS
            && e.alt
                .as_deref()
                .is_none_or(|a| a.alt.is_none() && self.fits(a))
    }
}

/// One shape in the corpus encoding (a query, or a row to insert).
#[derive(Clone, Debug, PartialEq)]
pub struct Encoded {
    /// Counts, `[histogram channel][bin]`.
    pub hist: Vec<u16>,
    /// Scale exponent per histogram channel (the counts sum to `TOTAL · 2^s`).
    pub shift: Vec<u8>,
    /// Group sums of the counts at scale [`MAX_SHIFT`], `[histogram channel][group]`.
    pub groups: Vec<u32>,
    /// In-window mass per histogram channel.
    pub mass: Vec<f64>,
    /// Per channel (layout order): whether the shape has it.
    pub present: Vec<bool>,
    /// Per vector channel (empty when absent).
    pub vectors: Vec<Vector>,
    /// Group sums of the vectors, `[vector channel][group]` ([`VECTOR_GROUPS`] per channel).
    pub vgroups: Vec<f32>,
    /// The second cut version in the same layout (its own `alt` is `None`).
    pub alt: Option<Box<Encoded>>,
}

/// One version of a shape (its first, or its second cut version): the arrays, no second
/// version of its own.
#[derive(Clone, Copy, Debug)]
pub struct VersionRef<'a> {
    /// Counts, `[histogram channel][bin]`.
    pub hist: &'a [u16],
    /// Scale exponent per histogram channel.
    pub shift: &'a [u8],
    /// Group sums at scale [`MAX_SHIFT`], `[histogram channel][group]`.
    pub groups: &'a [u32],
    /// Mass per histogram channel.
    pub mass: &'a [f64],
    /// Presence per channel.
    pub present: &'a [bool],
    /// Vectors per vector channel.
    pub vectors: &'a [Vector],
    /// Group sums of the vectors, `[vector channel][group]`.
    pub vgroups: &'a [f32],
}

/// A view of one shape, in the corpus or an [`Encoded`]: its first version (the fields, by
/// `Deref`) and its second cut version if it has one.
#[derive(Clone, Copy, Debug)]
pub struct ShapeRef<'a> {
    /// The first version.
    pub first: VersionRef<'a>,
    /// The second cut version, if the shape has one.
    pub alt: Option<VersionRef<'a>>,
}

impl<'a> std::ops::Deref for ShapeRef<'a> {
    type Target = VersionRef<'a>;
    fn deref(&self) -> &VersionRef<'a> {
        &self.first
    }
}

impl<'a> ShapeRef<'a> {
    /// The second version's view, or this one when there is none: the version a pair's
    /// second comparison uses ([`super::score::Query::score`]).
    pub fn second(self) -> ShapeRef<'a> {
        ShapeRef {
            first: self.alt.unwrap_or(self.first),
            alt: None,
        }
    }
}

impl Encoded {
    /// An empty shape (no channel present).
    pub fn absent(layout: &Layout) -> Encoded {
        Encoded {
            hist: vec![0; layout.histograms() * layout.bins],
            shift: vec![0; layout.histograms()],
            groups: vec![0; layout.histograms() * layout.groups],
            mass: vec![0.0; layout.histograms()],
            present: vec![false; layout.names.len()],
            vectors: vec![Vector::default(); layout.vectors()],
            vgroups: vec![0.0; layout.vectors() * VECTOR_GROUPS],
            alt: None,
        }
    }

    /// Encodes prepared histograms (`p` must come from the layout's calibration; channels are
    /// matched by name, a channel of the wrong kind or bin count is absent), its second version
    /// too.
    pub fn from_prepared(p: &Prepared, layout: &Layout) -> Encoded {
        let mut e = Encoded::absent(layout);
        for (c, (name, slot)) in layout.names.iter().zip(&layout.slots).enumerate() {
            match (p.channel(name), *slot) {
                (Some(PreparedChannel::Histogram(h)), Slot::Histogram(k))
                    if h.prob.len() == layout.bins =>
                {
                    let row = &mut e.hist[k * layout.bins..(k + 1) * layout.bins];
                    e.shift[k] = quantise(&h.prob, row);
                    e.mass[k] = if h.prob.iter().any(|&x| x > 0.0) {
                        h.mass
                    } else {
                        0.0
                    };
                    e.present[c] = true;
                }
                (Some(PreparedChannel::Vector(v)), Slot::Vector(k)) => {
                    e.vectors[k] = v.iter().map(|&x| x as f32).collect();
                    e.present[c] = true;
                }
                _ => {}
            }
        }
        e.fill_groups(layout);
        e.alt = p
            .alternate
            .as_deref()
            .map(|a| Box::new(Encoded::from_prepared(a, layout)));
        e
    }

    /// Prepares and encodes a signature under `cal` (whose layout is `layout`), its second
    /// version too when it has one.
    pub fn from_signature(sig: &Signature, cal: &Calibration, layout: &Layout) -> Encoded {
        Encoded::from_prepared(&crate::ranking::prepare_for_ranking(sig, cal), layout)
    }

    /// Heap bytes held, the box of the second version included.
    pub fn heap_bytes(&self) -> usize {
        arrays_bytes(
            &self.hist,
            &self.shift,
            &self.groups,
            &self.mass,
            &self.present,
            &self.vectors,
            &self.vgroups,
        ) + self
            .alt
            .as_ref()
            .map_or(0, |a| std::mem::size_of::<Encoded>() + a.heap_bytes())
    }

    /// Recomputes the vectors' group sums (after editing `vectors`).
    pub fn fill_vector_groups(&mut self) {
        self.vgroups.resize(self.vectors.len() * VECTOR_GROUPS, 0.0);
        for (v, out) in self
            .vectors
            .iter()
            .zip(self.vgroups.chunks_exact_mut(VECTOR_GROUPS))
        {
            vector_groups(v, out);
        }
    }

    /// Recomputes the group sums from the counts and exponents and from the vectors (after
    /// editing `hist` or `vectors`).
    pub fn fill_groups(&mut self, layout: &Layout) {
        self.fill_vector_groups();
        for k in 0..layout.histograms() {
            let row = &self.hist[k * layout.bins..(k + 1) * layout.bins];
            let up = MAX_SHIFT - self.shift[k].min(MAX_SHIFT);
            for (g, chunk) in row.chunks(layout.group_bins).enumerate() {
                let s: u64 = chunk.iter().map(|&x| (x as u64) << up).sum();
                self.groups[k * layout.groups + g] = s.min(u32::MAX as u64) as u32;
            }
        }
    }

    /// A view.
    pub fn view(&self) -> ShapeRef<'_> {
        ShapeRef {
            first: self.version(),
            alt: self.alt.as_deref().map(Encoded::version),
        }
    }

    /// This version's arrays (its second version, if any, not included).
    fn version(&self) -> VersionRef<'_> {
        VersionRef {
            hist: &self.hist,
            shift: &self.shift,
            groups: &self.groups,
            mass: &self.mass,
            present: &self.present,
            vectors: &self.vectors,
            vgroups: &self.vgroups,
        }
    }
}

/// Rows of one layout in flat arrays, row-major: the first versions of a corpus, or its
/// second versions.
#[derive(Clone, Debug, Default)]
struct Rows {
    len: usize,
    hist: Vec<u16>,
    shift: Vec<u8>,
    groups: Vec<u32>,
    mass: Vec<f64>,
    present: Vec<bool>,
    vectors: Vec<Vector>,
    vgroups: Vec<f32>,
}

/// Per-row lengths of [`Rows`]' arrays: histogram counts, group sums, histogram channels,
/// channels, vector channels, vector group sums.
fn strides(l: &Layout) -> [usize; 6] {
    [
        l.histograms() * l.bins,
        l.histograms() * l.groups,
        l.histograms(),
        l.names.len(),
        l.vectors(),
        l.vectors() * VECTOR_GROUPS,
    ]
}

impl Rows {
    fn reserve_exact(&mut self, l: &Layout, n: usize) {
        let [h, g, m, p, v, vg] = strides(l);
        self.hist.reserve_exact(n * h);
        self.shift.reserve_exact(n * m);
        self.groups.reserve_exact(n * g);
        self.mass.reserve_exact(n * m);
        self.present.reserve_exact(n * p);
        self.vectors.reserve_exact(n * v);
        self.vgroups.reserve_exact(n * vg);
    }

    fn get(&self, l: &Layout, at: usize) -> VersionRef<'_> {
        let [h, g, m, p, v, vg] = strides(l);
        VersionRef {
            hist: &self.hist[at * h..(at + 1) * h],
            shift: &self.shift[at * m..(at + 1) * m],
            groups: &self.groups[at * g..(at + 1) * g],
            mass: &self.mass[at * m..(at + 1) * m],
            present: &self.present[at * p..(at + 1) * p],
            vectors: &self.vectors[at * v..(at + 1) * v],
            vgroups: &self.vgroups[at * vg..(at + 1) * vg],
        }
    }

    /// Inserts the arrays of `e` (not its second version) as row `at`.
    fn insert(&mut self, l: &Layout, at: usize, e: &Encoded) {
        let [h, g, m, p, v, vg] = strides(l);
        splice(&mut self.hist, at * h, &e.hist);
        splice(&mut self.shift, at * m, &e.shift);
        splice(&mut self.groups, at * g, &e.groups);
        splice(&mut self.mass, at * m, &e.mass);
        splice(&mut self.present, at * p, &e.present);
        splice(&mut self.vectors, at * v, &e.vectors);
        splice(&mut self.vgroups, at * vg, &e.vgroups);
        self.len += 1;
    }

    fn replace(&mut self, l: &Layout, at: usize, e: &Encoded) {
        let [h, g, m, p, v, vg] = strides(l);
        self.hist[at * h..(at + 1) * h].copy_from_slice(&e.hist);
        self.shift[at * m..(at + 1) * m].copy_from_slice(&e.shift);
        self.groups[at * g..(at + 1) * g].copy_from_slice(&e.groups);
        self.mass[at * m..(at + 1) * m].copy_from_slice(&e.mass);
        self.present[at * p..(at + 1) * p].copy_from_slice(&e.present);
        self.vectors[at * v..(at + 1) * v].clone_from_slice(&e.vectors);
        self.vgroups[at * vg..(at + 1) * vg].copy_from_slice(&e.vgroups);
    }

    fn remove(&mut self, l: &Layout, at: usize) {
        let [h, g, m, p, v, vg] = strides(l);
        self.hist.drain(at * h..(at + 1) * h);
        self.shift.drain(at * m..(at + 1) * m);
        self.groups.drain(at * g..(at + 1) * g);
        self.mass.drain(at * m..(at + 1) * m);
        self.present.drain(at * p..(at + 1) * p);
        self.vectors.drain(at * v..(at + 1) * v);
        self.vgroups.drain(at * vg..(at + 1) * vg);
        self.len -= 1;
    }

    fn heap_bytes(&self) -> usize {
        arrays_bytes(
            &self.hist,
            &self.shift,
            &self.groups,
            &self.mass,
            &self.present,
            &self.vectors,
            &self.vgroups,
        )
    }
}

/// No second version (an entry of [`Corpus`]'s `alt_of`).
const NO_ALT: u32 = u32::MAX;

/// Every shape of a corpus in one layout, shape-major, positions `0..len`: the first versions
/// in one set of flat arrays, the second versions in another (in position order), and per
/// shape the row of its second version or `NO_ALT` (4 bytes per shape).
#[derive(Clone, Debug)]
pub struct Corpus {
    layout: Layout,
    first: Rows,
    alts: Rows,
    alt_of: Vec<u32>,
}

impl Corpus {
    /// An empty corpus of `layout`.
    pub fn new(layout: Layout) -> Corpus {
        Corpus {
            layout,
            first: Rows::default(),
            alts: Rows::default(),
            alt_of: Vec::new(),
        }
    }

    /// An empty corpus with room for `n` shapes (allocated exactly once; the second versions'
    /// arrays grow as they come).
    pub fn with_capacity(layout: Layout, n: usize) -> Corpus {
        let mut c = Corpus::new(layout);
        c.first.reserve_exact(&c.layout, n);
        c.alt_of.reserve_exact(n);
        c
    }

    /// A corpus of `shapes` in order.
    pub fn build(layout: Layout, shapes: &[Encoded]) -> Corpus {
        let mut c = Corpus::with_capacity(layout, shapes.len());
        let alts = shapes.iter().filter(|e| e.alt.is_some()).count();
        c.alts.reserve_exact(&c.layout, alts);
        for e in shapes {
            c.push(e);
        }
        c
    }

    /// The layout.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// Number of shapes.
    pub fn len(&self) -> usize {
        self.first.len
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.first.len == 0
    }

    /// The shape at `at`.
    pub fn shape(&self, at: usize) -> ShapeRef<'_> {
        ShapeRef {
            first: self.first.get(&self.layout, at),
            alt: self.alt(at),
        }
    }

    /// The second version of the shape at `at`, if it has one.
    pub(crate) fn alt(&self, at: usize) -> Option<VersionRef<'_>> {
        match self.alt_of[at] {
            NO_ALT => None,
            j => Some(self.alts.get(&self.layout, j as usize)),
        }
    }

    /// A copy of the shape at `at`.
    pub fn encoded(&self, at: usize) -> Encoded {
        let s = self.shape(at);
        let copy = |v: VersionRef<'_>| Encoded {
            hist: v.hist.to_vec(),
            shift: v.shift.to_vec(),
            groups: v.groups.to_vec(),
            mass: v.mass.to_vec(),
            present: v.present.to_vec(),
            vectors: v.vectors.to_vec(),
            vgroups: v.vgroups.to_vec(),
            alt: None,
        };
        Encoded {
            alt: s.alt.map(|a| Box::new(copy(a))),
            ..copy(s.first)
        }
    }

    /// Positions `range` that have a second version (read by the bounds of
    /// [`super::prune`]).
    pub(crate) fn alts_in(
        &self,
        range: std::ops::Range<usize>,
    ) -> impl Iterator<Item = usize> + '_ {
        let base = range.start;
        self.alt_of[range]
            .iter()
            .enumerate()
            .filter(|(_, &a)| a != NO_ALT)
            .map(move |(j, _)| base + j)
    }

    /// The second versions of the shapes at `range`: their positions, in order, and their
    /// group sums and vector group sums, contiguous (second versions are kept in position
    /// order, so those of a range of positions are consecutive rows).
    pub(crate) fn alt_groups_in(
        &self,
        range: std::ops::Range<usize>,
    ) -> (Vec<usize>, &[u32], &[f32]) {
        let at: Vec<usize> = self.alts_in(range).collect();
        let [_, g, _, _, _, vg] = strides(&self.layout);
        match (at.first(), at.last()) {
            (Some(&a), Some(&b)) => {
                let (j0, j1) = (self.alt_of[a] as usize, self.alt_of[b] as usize + 1);
                assert_eq!(j1 - j0, at.len(), "second versions out of order");
                let groups = &self.alts.groups[j0 * g..j1 * g];
                (at, groups, &self.alts.vgroups[j0 * vg..j1 * vg])
            }
            _ => (at, &[], &[]),
        }
    }

    /// In-window mass of histogram slot `k` of the shape at `at`.
    pub(crate) fn mass_of(&self, at: usize, k: usize) -> f64 {
        self.first.mass[at * self.layout.histograms() + k]
    }

    /// Group sums of every shape's first version (`[shape][histogram channel][group]`).
    pub(crate) fn all_groups(&self) -> &[u32] {
        &self.first.groups
    }

    /// Vector group sums of every shape's first version (`[shape][vector channel][group]`).
    pub(crate) fn all_vgroups(&self) -> &[f32] {
        &self.first.vgroups
    }

    fn check(&self, e: &Encoded) {
        assert!(
            self.layout.fits(e),
            "encoded shape does not match the corpus layout"
        );
    }

    /// The row the second version of a shape at `at` takes: the number of shapes before `at`
    /// that have one (second versions are kept in position order).
    fn alt_row(&self, at: usize) -> usize {
        self.alt_of[..at].iter().filter(|&&a| a != NO_ALT).count()
    }

    /// Adds `delta` to every second-version row after shape `at`.
    fn shift_alt_rows(&mut self, at: usize, delta: i64) {
        for a in self.alt_of[at + 1..].iter_mut().filter(|a| **a != NO_ALT) {
            *a = (*a as i64 + delta) as u32;
        }
    }

    /// Appends a shape.
    pub fn push(&mut self, e: &Encoded) {
        self.insert(self.len(), e);
    }

    /// Inserts a shape at `at` (shifting the following ones).
    pub fn insert(&mut self, at: usize, e: &Encoded) {
        assert!(
            at <= self.len(),
            "insert position {at} > len {}",
            self.len()
        );
        self.check(e);
        self.first.insert(&self.layout, at, e);
        let row = match &e.alt {
            Some(a) => {
                let j = if at == self.alt_of.len() {
                    self.alts.len
                } else {
                    self.alt_row(at)
                };
                assert!(j < NO_ALT as usize, "too many second versions");
                self.alts.insert(&self.layout, j, a);
                j as u32
            }
            None => NO_ALT,
        };
        self.alt_of.insert(at, row);
        if row != NO_ALT {
            self.shift_alt_rows(at, 1);
        }
    }

    /// Replaces the shape at `at`.
    pub fn replace(&mut self, at: usize, e: &Encoded) {
        assert!(
            at < self.len(),
            "replace position {at} >= len {}",
            self.len()
        );
        self.check(e);
        self.first.replace(&self.layout, at, e);
        match (self.alt_of[at], e.alt.as_deref()) {
            (NO_ALT, None) => {}
            (NO_ALT, Some(a)) => {
                let j = self.alt_row(at);
                self.alts.insert(&self.layout, j, a);
                self.alt_of[at] = j as u32;
                self.shift_alt_rows(at, 1);
            }
            (j, Some(a)) => self.alts.replace(&self.layout, j as usize, a),
            (j, None) => {
                self.alts.remove(&self.layout, j as usize);
                self.alt_of[at] = NO_ALT;
                self.shift_alt_rows(at, -1);
            }
        }
    }

    /// Removes the shape at `at`.
    pub fn remove(&mut self, at: usize) {
        assert!(
            at < self.len(),
            "remove position {at} >= len {}",
            self.len()
        );
        self.first.remove(&self.layout, at);
        let j = self.alt_of[at];
        if j != NO_ALT {
            self.alts.remove(&self.layout, j as usize);
            self.shift_alt_rows(at, -1);
        }
        self.alt_of.remove(at);
    }

    /// Heap bytes held (capacity of the arrays, vectors' contents included).
    pub fn heap_bytes(&self) -> usize {
        self.first.heap_bytes() + self.alts.heap_bytes() + self.alt_of.capacity() * 4
    }
}

/// Heap bytes of the seven arrays of an [`Encoded`] or a [`Corpus`] (capacities, vectors'
/// contents included).
fn arrays_bytes(
    hist: &Vec<u16>,
    shift: &Vec<u8>,
    groups: &Vec<u32>,
    mass: &Vec<f64>,
    present: &Vec<bool>,
    vectors: &Vec<Vector>,
    vgroups: &Vec<f32>,
) -> usize {
    hist.capacity() * 2
        + shift.capacity()
        + groups.capacity() * 4
        + mass.capacity() * 8
        + present.capacity()
        + vectors.capacity() * std::mem::size_of::<Vector>()
        + vectors.iter().map(|v| v.len() * 4).sum::<usize>()
        + vgroups.capacity() * 4
}

/// Inserts `items` at `at`, appending without a temporary when `at` is the end.
fn splice<T: Clone>(v: &mut Vec<T>, at: usize, items: &[T]) {
    if at == v.len() {
        v.extend_from_slice(items);
    } else {
        v.splice(at..at, items.iter().cloned());
    }
}
