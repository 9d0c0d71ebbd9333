//! The encoding check (`eval --check-encoding`): every configuration ranked once more on the
//! `f64` histograms of its definition ([`crate::ranking::channel_dissimilarity`] on
//! [`crate::ranking::Prepared`]), beside the ranking on the corpus encoding that the search and
//! eval use ([`crate::search::score`]), so that the effect of the encoding on retrieval is
//! measured on every run that asks for it rather than against figures of an older build.
//!
//! # Ties at rounding level
//!
//! The bench protocol breaks ties in distance by manifest order. On the encoding, two shapes
//! whose histograms quantise to the same counts score exactly 0 (or exactly the same value), so
//! that rule applies. In `f64`, the same two mathematically equal histograms usually differ by a
//! few units of rounding (e.g. shapes whose distances all lie below half a bin: their linear
//! binning and Parzen window give the same bins, summed in another order), and that noise, not
//! the protocol, decides their order. The reference is therefore reported twice: as computed
//! (`raw`), and with the values of each query's row that lie within [`TIE_TOLERANCE`] × the
//! row's largest finite value of a smaller one merged into it (`ties`), so that the protocol's
//! tie rule applies to them too. The same merge is applied to the encoding's matrix, whose
//! floating-point dissimilarities (L1, L2, L∞, KL, Bhattacharyya with the masses and logarithms
//! in `f64`) have rounding noise of their own; both sides are compared with ties merged, and
//! both figures as computed are shown beside them. The tolerance is far above the rounding error of the sums
//! (≤ 256 bins × a few channels × 2⁻⁵³ relative) and far below the encoding's quantum
//! (`1/(65 535 · 2⁸)` ≈ 6·10⁻⁸ in probability).
//!
//! The re-ranking stages of a configuration run on the reference too, with the reference's own
//! first stage and exact re-scoring (`f64`); spectral GW payloads are the run's (they do not
//! depend on the encoding).

use super::metrics::{self, Evaluation, ALL};
use crate::presets::Config;
use crate::ranking::{self, Dissimilarity, Prepared, QuerySpec};
use crate::search::corpus::Layout;
use crate::search::Query;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;

/// Values of a query's reference row within this fraction of the row's largest finite value of
/// a smaller value count as tied with it (see the module docs).
pub const TIE_TOLERANCE: f64 = 1e-12;

/// The largest difference in mAP (points) between the encoding and the reference (ties merged
/// on both sides) that the check counts as agreement (the restructuring's bar for `All`).
pub const ACCEPTED_POINTS: f64 = 0.1;

/// One configuration's figures on both sides.
#[derive(Debug, Clone, Serialize)]
pub struct CheckRow {
    /// Configuration name.
    pub name: String,
    /// mAP (points) per group on the encoding with rounding ties merged, in the run's group
    /// order (`All` included).
    pub encoded: Vec<(String, f64)>,
    /// mAP per group on the `f64` reference with rounding ties merged.
    pub reference: Vec<(String, f64)>,
    /// `All` mAP on the encoding as computed: the run's own figure.
    pub encoded_raw_all: f64,
    /// `All` mAP on the `f64` reference as computed (rounding noise breaks ties).
    pub reference_raw_all: f64,
    /// |encoded − reference| of `All`, ties merged on both sides (points).
    pub all_abs_diff: f64,
    /// Largest |encoded − reference| over the groups, ties merged on both sides (points).
    pub max_abs_diff: f64,
    /// The group where it occurs.
    pub max_group: String,
}

/// The check over a run's configurations.
#[derive(Debug, Clone, Serialize)]
pub struct EncodingCheck {
    /// [`TIE_TOLERANCE`].
    pub tie_tolerance: f64,
    /// [`ACCEPTED_POINTS`].
    pub accepted_points: f64,
    /// Per configuration, in run order.
    pub rows: Vec<CheckRow>,
}

impl EncodingCheck {
    /// Configurations whose `All` mAP is within [`ACCEPTED_POINTS`].
    pub fn within_all(&self) -> usize {
        self.rows
            .iter()
            .filter(|r| r.all_abs_diff <= self.accepted_points)
            .count()
    }

    /// Configurations whose every group is within [`ACCEPTED_POINTS`].
    pub fn within_every_group(&self) -> usize {
        self.rows
            .iter()
            .filter(|r| r.max_abs_diff <= self.accepted_points)
            .count()
    }

    /// The Markdown section of the report.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "## Encoding check (`--check-encoding`)\n\nEvery configuration ranked on the `f64` histograms of its definition beside the corpus encoding; reference ties at rounding level (≤ {:e} × the row's largest value) merged on both sides so that the protocol's tie rule applies (see `src/eval/encoding_check.rs`). **{} of {} configurations within {p} point of the reference's All mAP; {} within {p} point in every group** (per transformation and All).\n\n| config | All (encoding, ties) | All (f64, ties) | \\|Δ All\\| | largest \\|Δ\\| | in group | All (encoding, as run) | All (f64, as computed) |\n|---|---|---|---|---|---|---|---|\n",
            self.tie_tolerance,
            self.within_all(),
            self.rows.len(),
            self.within_every_group(),
            p = self.accepted_points
        );
        let all = |v: &[(String, f64)]| {
            v.iter()
                .find(|(g, _)| g == ALL)
                .map(|(_, m)| format!("{m:.2}"))
                .unwrap_or_else(|| "–".into())
        };
        for r in &self.rows {
            s.push_str(&format!(
                "| {} | {} | {} | {:.2} | {:.2} | {} | {:.2} | {:.2} |\n",
                r.name,
                all(&r.encoded),
                all(&r.reference),
                r.all_abs_diff,
                r.max_abs_diff,
                r.max_group,
                r.encoded_raw_all,
                r.reference_raw_all,
            ));
        }
        s
    }
}

/// mAP per group (points), groups without an mAP left out.
pub fn group_maps(e: &Evaluation) -> Vec<(String, f64)> {
    e.groups
        .iter()
        .filter_map(|(g, s)| s.map.map(|m| (g.clone(), 100.0 * m)))
        .collect()
}

fn all_map(e: &Evaluation) -> f64 {
    e.group(ALL)
        .and_then(|g| g.map)
        .map(|m| 100.0 * m)
        .unwrap_or(f64::NAN)
}

/// The row of the check for one configuration: `encoded` and `reference` are
/// [`evaluate_with_ties`] pairs `(ties merged, as computed)`.
pub fn compare(
    name: &str,
    encoded: &(Evaluation, Evaluation),
    reference: &(Evaluation, Evaluation),
) -> CheckRow {
    let enc = group_maps(&encoded.0);
    let reff = group_maps(&reference.0);
    let (mut max_abs_diff, mut max_group) = (0.0f64, String::new());
    for (g, a) in &enc {
        if let Some((_, b)) = reff.iter().find(|(h, _)| h == g) {
            let d = (a - b).abs();
            if d > max_abs_diff || max_group.is_empty() {
                max_abs_diff = d;
                max_group = g.clone();
            }
        }
    }
    let all_abs_diff = (all_map(&encoded.0) - all_map(&reference.0)).abs();
    CheckRow {
        name: name.to_string(),
        encoded: enc,
        reference: reff,
        all_abs_diff,
        encoded_raw_all: all_map(&encoded.1),
        reference_raw_all: all_map(&reference.1),
        max_abs_diff,
        max_group,
    }
}

/// Merges, in every row of the `n × n` matrix, the finite values within `tol` × the row's
/// largest finite value of the smallest value of their run (values sorted ascending; a run
/// starts at the first value more than that above the current run's start). NaN and ∞ are left.
pub fn merge_rounding_ties(dist: &mut [f64], n: usize, tol: f64) {
    dist.par_chunks_mut(n.max(1)).for_each(|row| {
        let scale = row
            .iter()
            .filter(|v| v.is_finite())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        let eps = tol * scale;
        let mut idx: Vec<usize> = (0..row.len()).filter(|&j| row[j].is_finite()).collect();
        idx.sort_by(|&a, &b| row[a].total_cmp(&row[b]));
        let mut start = f64::NEG_INFINITY;
        for j in idx {
            if row[j] - start <= eps {
                row[j] = start;
            } else {
                start = row[j];
            }
        }
    });
}

/// Per-channel all-pairs matrices on the `f64` histograms (the reference side of
/// `super::matrices::ChannelMatrices`).
#[derive(Default)]
pub struct ReferenceMatrices {
    mats: HashMap<(usize, Dissimilarity), Vec<f64>>,
}

impl ReferenceMatrices {
    /// The configuration's all-pairs reference matrix (row = query; NaN on the diagonal and for
    /// shapes left out), aggregated over channels as [`Query::aggregate`], second cut versions
    /// as [`Query::with_second`].
    pub fn aggregate(
        &mut self,
        prepared: &[Option<Prepared>],
        layout: &Layout,
        included: &[bool],
        spec: &QuerySpec,
    ) -> Vec<f64> {
        let n = prepared.len();
        let q = Query::new(spec, layout);
        for &c in q.channels.iter().flatten() {
            self.mats.entry((c, q.dissimilarity)).or_insert_with(|| {
                let mut m = vec![f64::NAN; n * n];
                m.par_chunks_mut(n.max(1)).enumerate().for_each(|(i, row)| {
                    for (j, x) in row.iter_mut().enumerate() {
                        if i != j && included[i] && included[j] {
                            *x = reference_channel(prepared, c, q.dissimilarity, i, j);
                        }
                    }
                });
                m
            });
        }
        let mats = &self.mats;
        let mut out = vec![f64::NAN; n * n];
        out.par_chunks_mut(n.max(1))
            .enumerate()
            .for_each(|(i, row)| {
                for (j, x) in row.iter_mut().enumerate() {
                    if i != j && included[i] && included[j] {
                        let first = q.aggregate(|c| mats[&(c, q.dissimilarity)][i * n + j]);
                        *x = reference_with_second(prepared, &q, i, j, first);
                    }
                }
            });
        out
    }
}

/// The `f64` dissimilarity of channel `c` (layout index = the calibration's channel order, as
/// [`Prepared::channels`]) between shapes `i` and `j`.
pub fn reference_channel(
    prepared: &[Option<Prepared>],
    c: usize,
    d: Dissimilarity,
    i: usize,
    j: usize,
) -> f64 {
    match (&prepared[i], &prepared[j]) {
        (Some(a), Some(b)) => ranking::channel_dissimilarity(
            d,
            a.channels.get(c).and_then(|x| x.as_ref()),
            b.channels.get(c).and_then(|x| x.as_ref()),
        ),
        _ => f64::INFINITY,
    }
}

/// Exact `f64` re-scoring of a pair under `spec` (what an exact stage does on the reference).
pub fn reference_score(
    prepared: &[Option<Prepared>],
    layout: &Layout,
    spec: &QuerySpec,
    i: usize,
    j: usize,
) -> f64 {
    let q = Query::new(spec, layout);
    let first = q.aggregate(|c| reference_channel(prepared, c, q.dissimilarity, i, j));
    reference_with_second(prepared, &q, i, j, first)
}

/// [`Query::with_second`] on the `f64` histograms: `min(first, f · D₂)` when either shape has
/// a second cut version, `D₂` the aggregated dissimilarity of the second versions (a shape
/// without one takes part with its first).
fn reference_with_second(
    prepared: &[Option<Prepared>],
    q: &Query,
    i: usize,
    j: usize,
    first: f64,
) -> f64 {
    match (&prepared[i], &prepared[j]) {
        (Some(a), Some(b)) if a.alternate.is_some() || b.alternate.is_some() => {
            let a2 = a.alternate.as_deref().unwrap_or(a);
            let b2 = b.alternate.as_deref().unwrap_or(b);
            let second = q.aggregate(|c| {
                ranking::channel_dissimilarity(
                    q.dissimilarity,
                    a2.channels.get(c).and_then(|x| x.as_ref()),
                    b2.channels.get(c).and_then(|x| x.as_ref()),
                )
            });
            first.min(q.alternate_margin * second)
        }
        _ => first,
    }
}

/// [`metrics::evaluate`] of a matrix after and before merging rounding ties:
/// `(ties merged, as computed)`.
pub fn evaluate_with_ties(
    mut dist: Vec<f64>,
    n: usize,
    classes: &[usize],
    transforms: &[String],
    strengths: &[i64],
    included: &[bool],
) -> (Evaluation, Evaluation) {
    let raw = metrics::evaluate(&dist, n, classes, transforms, strengths, included);
    merge_rounding_ties(&mut dist, n, TIE_TOLERANCE);
    let ties = metrics::evaluate(&dist, n, classes, transforms, strengths, included);
    (ties, raw)
}

/// One configuration of `--check-encoding`: its ranking (with its own stages) on the `f64`
/// histograms, evaluated with and without merging rounding ties, beside `encoded`.
#[allow(clippy::too_many_arguments)]
pub(super) fn check_configuration(
    cfg: &Config,
    encoded: (&[f64], &Evaluation),
    mats: &mut ReferenceMatrices,
    prepared: &[Option<ranking::Prepared>],
    layout: &Layout,
    included: &[bool],
    payload_sets: &[(String, Vec<Option<crate::rerank::GwPayload>>)],
    solved_pairs: &mut super::rerank::PairCache,
    labels: (&[usize], &[String], &[i64]),
) -> CheckRow {
    let n = prepared.len();
    let base = mats.aggregate(prepared, layout, included, &cfg.query);
    let rescore =
        |q: usize, j: usize, spec: &QuerySpec| reference_score(prepared, layout, spec, q, j);
    let mut cur = base.clone();
    for st in &cfg.rerank {
        let (next, _) = super::apply_stage(
            st,
            &base,
            &cur,
            n,
            included,
            payload_sets,
            &rescore,
            solved_pairs,
        );
        cur = next;
    }
    let (classes, transforms, strengths) = labels;
    let reference = evaluate_with_ties(cur, n, classes, transforms, strengths, included);
    let (enc_dist, enc_eval) = encoded;
    let mut merged = enc_dist.to_vec();
    merge_rounding_ties(&mut merged, n, TIE_TOLERANCE);
    let enc_ties = metrics::evaluate(&merged, n, classes, transforms, strengths, included);
    compare(&cfg.name, &(enc_ties, enc_eval.clone()), &reference)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_ties_merge_into_the_smallest_value_of_their_run() {
        let n = 5;
        let big = 1.0;
        let mut d = vec![
            f64::NAN,
            1e-16,
            0.0,
            0.5,
            big, //
            1e-16,
            f64::NAN,
            2e-13,
            0.5 + 1e-14,
            f64::INFINITY, //
            0.0,
            0.0,
            f64::NAN,
            0.0,
            0.0, //
            0.0,
            0.0,
            0.0,
            f64::NAN,
            0.0, //
            0.0,
            0.0,
            0.0,
            0.0,
            f64::NAN,
        ];
        merge_rounding_ties(&mut d, n, 1e-12);
        // Row 0: 1e-16 and 0 tie (scale 1); 0.5 and 1 stay apart.
        assert_eq!(&d[1..5], &[0.0, 0.0, 0.5, 1.0]);
        assert!(d[0].is_nan());
        // Row 1: scale 0.5 + 1e-14 (∞ ignored): 1e-16 and 2e-13 tie at 1e-16; ∞ untouched.
        assert_eq!(d[5], 1e-16);
        assert_eq!(d[7], 1e-16);
        assert_eq!(d[8], 0.5 + 1e-14);
        assert_eq!(d[9], f64::INFINITY);
    }

    #[test]
    fn values_apart_by_more_than_the_tolerance_stay_apart() {
        let mut d = vec![f64::NAN, 0.0, 1e-6, 1.0];
        merge_rounding_ties(&mut d, 4, 1e-12);
        assert_eq!(d[1..], [0.0, 1e-6, 1.0]);
        // A chain of small steps merges only within the tolerance of the run's start.
        let mut d = vec![f64::NAN, 0.0, 0.6e-12, 1.2e-12, 1.0];
        merge_rounding_ties(&mut d, 5, 1e-12);
        assert_eq!(d[1..], [0.0, 0.0, 1.2e-12, 1.0]);
    }
}
