//! Retrieval metrics of the bench protocol: rankings, non-interpolated AP, ROC/AUC, PR curves,
//! equal error rate, and their aggregation per transformation class.
//!
//! Conventions (bench README, "Retrieval protocol"):
//! * a query is ranked against every *other* shape; ties in distance are broken by manifest order
//!   (lower index first); a NaN distance ranks last (as +∞);
//! * `AP = (1/R) Σ_k P@k · rel(k)` over the full ranking, `R` = number of relevant shapes in it;
//!   a query with `R = 0` has no AP (it is left out of every mean, and counted);
//! * ROC: TPR against FPR when thresholding the query's distances (`d ≤ θ` retrieved). Tied
//!   distances cannot be separated by a threshold, so a run of ties is one diagonal step; the AUC
//!   (trapezoid) equals the Mann–Whitney probability `P(d⁺ < d⁻) + ½ P(d⁺ = d⁻)`;
//! * PR curve of a query: (recall, precision) after each rank of the tie-broken ranking;
//! * EER: the error rate where FPR = 1 − TPR on the ROC of the *pooled* (query, other) distances of
//!   a group of queries (pooled as the reference pools them), linearly interpolated between ROC
//!   vertices. The reference's values look like `(FPR + FNR) / 2` at a vertex instead (most of
//!   them are multiples of neither `1/N` nor `1/P`), which can differ from this by up to half
//!   a step of the ROC (half of `1/N` or `1/P` of the group's negative or positive pairs).

use std::cmp::Ordering;
use std::collections::BTreeMap;

/// Orders distances for ranking: NaN as +∞, then by value.
#[inline]
fn key(d: f64) -> f64 {
    if d.is_nan() {
        f64::INFINITY
    } else {
        d
    }
}

/// The other shapes ranked for `query`: indices into `distances` (one per shape, the query's own
/// entry ignored) by increasing distance, ties by index. `candidates` restricts the ranking
/// (e.g. to shapes whose mesh could be read); `None` means every shape.
pub fn rank(distances: &[f64], query: usize, candidates: Option<&[bool]>) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..distances.len())
        .filter(|&j| j != query && candidates.is_none_or(|c| c[j]))
        .collect();
    idx.sort_by(|&a, &b| {
        key(distances[a])
            .partial_cmp(&key(distances[b]))
            .unwrap_or(Ordering::Equal)
            .then(a.cmp(&b))
    });
    idx
}

/// Non-interpolated average precision of a ranking given as relevance flags in rank order;
/// `None` when nothing is relevant.
pub fn average_precision(relevant: &[bool]) -> Option<f64> {
    let mut hits = 0usize;
    let mut sum = 0.0;
    for (k, &r) in relevant.iter().enumerate() {
        if r {
            hits += 1;
            sum += hits as f64 / (k + 1) as f64;
        }
    }
    (hits > 0).then(|| sum / hits as f64)
}

/// Precision–recall points `(recall, precision)` after each rank; empty when nothing is relevant.
pub fn pr_curve(relevant: &[bool]) -> Vec<(f64, f64)> {
    let total = relevant.iter().filter(|&&r| r).count();
    if total == 0 {
        return Vec::new();
    }
    let mut hits = 0usize;
    relevant
        .iter()
        .enumerate()
        .map(|(k, &r)| {
            hits += r as usize;
            (hits as f64 / total as f64, hits as f64 / (k + 1) as f64)
        })
        .collect()
}

/// ROC vertices `(FPR, TPR)` from `(0,0)` to `(1,1)` for scored pairs `(distance, relevant)`;
/// a threshold is placed between distinct distances only. `None` when either class is empty.
pub fn roc_curve(pairs: &[(f64, bool)]) -> Option<Vec<(f64, f64)>> {
    let p = pairs.iter().filter(|x| x.1).count();
    let n = pairs.len() - p;
    if p == 0 || n == 0 {
        return None;
    }
    let mut v: Vec<(f64, bool)> = pairs.iter().map(|&(d, r)| (key(d), r)).collect();
    v.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap_or(Ordering::Equal));
    let mut out = Vec::with_capacity(v.len() + 1);
    out.push((0.0, 0.0));
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut i = 0;
    while i < v.len() {
        let d = v[i].0;
        while i < v.len() && v[i].0 == d {
            if v[i].1 {
                tp += 1;
            } else {
                fp += 1;
            }
            i += 1;
        }
        out.push((fp as f64 / n as f64, tp as f64 / p as f64));
    }
    Some(out)
}

/// Area under a ROC polyline (trapezoid rule).
pub fn auc(roc: &[(f64, f64)]) -> f64 {
    roc.windows(2)
        .map(|w| (w[1].0 - w[0].0) * 0.5 * (w[1].1 + w[0].1))
        .sum()
}

/// Equal error rate of a ROC polyline: the FPR where FPR = 1 − TPR (linear interpolation).
pub fn eer(roc: &[(f64, f64)]) -> f64 {
    // g = FPR − (1 − TPR) goes from −1 at (0,0) to +1 at (1,1), monotonically non-decreasing.
    for w in roc.windows(2) {
        let g0 = w[0].0 - (1.0 - w[0].1);
        let g1 = w[1].0 - (1.0 - w[1].1);
        if g0 <= 0.0 && g1 >= 0.0 {
            if g1 == g0 {
                return w[0].0;
            }
            let s = -g0 / (g1 - g0);
            return w[0].0 + s * (w[1].0 - w[0].0);
        }
    }
    0.5
}

/// TPR of a ROC polyline at a given FPR (the upper envelope at vertical steps).
pub fn roc_tpr_at(roc: &[(f64, f64)], fpr: f64) -> f64 {
    let mut best: f64 = 0.0;
    for w in roc.windows(2) {
        let (a, b) = (w[0], w[1]);
        if fpr >= a.0 && fpr <= b.0 {
            let t = if b.0 > a.0 {
                a.1 + (b.1 - a.1) * (fpr - a.0) / (b.0 - a.0)
            } else {
                b.1
            };
            best = best.max(t);
        }
    }
    best
}

/// Interpolated precision at recall `r`: the best precision at any recall ≥ r.
pub fn pr_precision_at(pr: &[(f64, f64)], r: f64) -> f64 {
    pr.iter()
        .filter(|p| p.0 >= r - 1e-12)
        .map(|p| p.1)
        .fold(0.0, f64::max)
}

/// What one query scored.
#[derive(Debug, Clone)]
pub struct QueryResult {
    /// Index of the query in the manifest.
    pub index: usize,
    /// Average precision (`None` when the query's class has no other readable shape).
    pub ap: Option<f64>,
    /// ROC vertices (`None` as for `ap`, or when every other shape is relevant).
    pub roc: Option<Vec<(f64, f64)>>,
    /// PR points.
    pub pr: Vec<(f64, f64)>,
    /// TPR on the FPR grid ([`CURVE_GRID`] points), as [`roc_tpr_at`].
    pub roc_grid: Option<Vec<f64>>,
    /// Interpolated precision on the recall grid, as [`pr_precision_at`].
    pub pr_grid: Option<Vec<f64>>,
}

/// [`roc_tpr_at`] on the whole FPR grid in one sweep.
pub fn roc_on_grid(roc: &[(f64, f64)]) -> Vec<f64> {
    let mut k = 0;
    grid()
        .map(|f| {
            while k + 1 < roc.len() && roc[k + 1].0 <= f {
                k += 1;
            }
            let a = roc[k];
            if a.0 == f || k + 1 >= roc.len() {
                a.1
            } else {
                let b = roc[k + 1];
                a.1 + (b.1 - a.1) * (f - a.0) / (b.0 - a.0)
            }
        })
        .collect()
}

/// [`pr_precision_at`] on the whole recall grid in one sweep.
pub fn pr_on_grid(pr: &[(f64, f64)]) -> Vec<f64> {
    let mut suffix_max = vec![0.0f64; pr.len() + 1];
    for i in (0..pr.len()).rev() {
        suffix_max[i] = suffix_max[i + 1].max(pr[i].1);
    }
    let mut k = 0;
    grid()
        .map(|r| {
            while k < pr.len() && pr[k].0 < r - 1e-12 {
                k += 1;
            }
            suffix_max[k]
        })
        .collect()
}

/// Scores one query from its row of the distance matrix.
pub fn evaluate_query(
    distances: &[f64],
    query: usize,
    classes: &[usize],
    candidates: Option<&[bool]>,
) -> QueryResult {
    let order = rank(distances, query, candidates);
    let rel: Vec<bool> = order
        .iter()
        .map(|&j| classes[j] == classes[query])
        .collect();
    let pairs: Vec<(f64, bool)> = order
        .iter()
        .zip(&rel)
        .map(|(&j, &r)| (distances[j], r))
        .collect();
    let roc = roc_curve(&pairs);
    let pr = pr_curve(&rel);
    QueryResult {
        index: query,
        ap: average_precision(&rel),
        roc_grid: roc.as_deref().map(roc_on_grid),
        pr_grid: (!pr.is_empty()).then(|| pr_on_grid(&pr)),
        roc,
        pr,
    }
}

/// Number of points of the mean ROC and PR curves (FPR / recall grid `0, 1/(G-1), …, 1`).
pub const CURVE_GRID: usize = 101;

/// Aggregate figures of one group of queries (a transformation class, `All`, ...).
#[derive(Debug, Clone, Default)]
pub struct GroupSummary {
    /// Queries in the group.
    pub queries: usize,
    /// Queries with an AP (the others are left out of the means).
    pub scored: usize,
    /// Mean AP.
    pub map: Option<f64>,
    /// Mean per-query ROC AUC.
    pub auc: Option<f64>,
    /// EER of the pooled (query, other) distances of the group.
    pub eer: Option<f64>,
    /// Mean ROC (vertical averaging of TPR on the FPR grid).
    pub mean_roc: Vec<(f64, f64)>,
    /// Mean PR (interpolated precision averaged on the recall grid).
    pub mean_pr: Vec<(f64, f64)>,
}

fn grid() -> impl Iterator<Item = f64> {
    (0..CURVE_GRID).map(|i| i as f64 / (CURVE_GRID - 1) as f64)
}

/// Summarises the queries `members` (indices into `results`); `pooled` holds, per query, its
/// `(distance, relevant)` pairs for the pooled EER. Mean curves only when `curves`.
pub fn summarize(
    results: &[QueryResult],
    members: &[usize],
    pooled: &[Vec<(f64, bool)>],
    curves: bool,
) -> GroupSummary {
    let aps: Vec<f64> = members.iter().filter_map(|&q| results[q].ap).collect();
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    let aucs: Vec<f64> = members
        .iter()
        .filter_map(|&q| results[q].roc.as_deref().map(auc))
        .collect();
    let all_pairs: Vec<(f64, bool)> = members
        .iter()
        .flat_map(|&q| pooled[q].iter().copied())
        .collect();
    let eer = roc_curve(&all_pairs).map(|r| eer(&r));
    let mean_grid = |pick: &dyn Fn(&QueryResult) -> Option<&Vec<f64>>| -> Vec<(f64, f64)> {
        let vs: Vec<&Vec<f64>> = members.iter().filter_map(|&q| pick(&results[q])).collect();
        if !curves || vs.is_empty() {
            return Vec::new();
        }
        grid()
            .enumerate()
            .map(|(i, x)| (x, vs.iter().map(|v| v[i]).sum::<f64>() / vs.len() as f64))
            .collect()
    };
    GroupSummary {
        queries: members.len(),
        scored: aps.len(),
        map: mean(&aps),
        auc: mean(&aucs),
        eer,
        mean_roc: mean_grid(&|r| r.roc_grid.as_ref()),
        mean_pr: mean_grid(&|r| r.pr_grid.as_ref()),
    }
}

/// The name of the group of every query.
pub const ALL: &str = "All";
/// The group of every query except those of transformation `scale`.
pub const ALL_WO_SCALE: &str = "All w/o scale";

/// Per-group summaries of one configuration: per transformation (manifest order), `All`,
/// `All w/o scale` (when the manifest has a `scale` class), and per `transform@strength`.
#[derive(Debug, Clone, Default)]
pub struct Evaluation {
    /// Group name → summary, groups in report order.
    pub groups: Vec<(String, GroupSummary)>,
    /// `transform@strength` → summary (without mean curves).
    pub per_strength: BTreeMap<String, GroupSummary>,
    /// Per-query results (indexed like the manifest; queries that were not ranked are absent).
    pub queries: Vec<QueryResult>,
}

impl Evaluation {
    /// The summary of a group.
    pub fn group(&self, name: &str) -> Option<&GroupSummary> {
        self.groups.iter().find(|g| g.0 == name).map(|g| &g.1)
    }
}

/// Evaluates a full `n × n` distance matrix (row-major, row = query). Only shapes with
/// `included[i]` are queries or candidates.
pub fn evaluate(
    dist: &[f64],
    n: usize,
    classes: &[usize],
    transforms: &[String],
    strengths: &[i64],
    included: &[bool],
) -> Evaluation {
    assert_eq!(dist.len(), n * n);
    let queries: Vec<usize> = (0..n).filter(|&i| included[i]).collect();
    let results: Vec<QueryResult> = {
        use rayon::prelude::*;
        queries
            .par_iter()
            .map(|&q| evaluate_query(&dist[q * n..(q + 1) * n], q, classes, Some(included)))
            .collect()
    };
    let pooled: Vec<Vec<(f64, bool)>> = queries
        .iter()
        .map(|&q| {
            (0..n)
                .filter(|&j| j != q && included[j])
                .map(|j| (dist[q * n + j], classes[j] == classes[q]))
                .collect()
        })
        .collect();
    // Positions in `results` of each group's members.
    let mut order: Vec<String> = Vec::new();
    for &q in &queries {
        if !order.contains(&transforms[q]) {
            order.push(transforms[q].clone());
        }
    }
    let pos = |pred: &dyn Fn(usize) -> bool| -> Vec<usize> {
        queries
            .iter()
            .enumerate()
            .filter(|(_, &q)| pred(q))
            .map(|(p, _)| p)
            .collect()
    };
    let mut specs: Vec<(String, Vec<usize>, bool)> = Vec::new();
    for t in &order {
        specs.push((t.clone(), pos(&|q| &transforms[q] == t), true));
    }
    specs.push((ALL.to_string(), pos(&|_| true), true));
    if order.iter().any(|t| t == "scale") {
        specs.push((
            ALL_WO_SCALE.to_string(),
            pos(&|q| transforms[q] != "scale"),
            true,
        ));
    }
    let n_main = specs.len();
    let mut keys: Vec<String> = queries
        .iter()
        .map(|&q| format!("{}@{}", transforms[q], strengths[q]))
        .collect();
    keys.sort();
    keys.dedup();
    for k in keys {
        let members = pos(&|q| format!("{}@{}", transforms[q], strengths[q]) == k);
        specs.push((k, members, false));
    }
    let summaries: Vec<(String, GroupSummary)> = {
        use rayon::prelude::*;
        specs
            .par_iter()
            .map(|(name, members, curves)| {
                (name.clone(), summarize(&results, members, &pooled, *curves))
            })
            .collect()
    };
    let mut it = summaries.into_iter();
    let groups: Vec<(String, GroupSummary)> = it.by_ref().take(n_main).collect();
    let per_strength: BTreeMap<String, GroupSummary> = it.collect();
    Evaluation {
        groups,
        per_strength,
        queries: results,
    }
}
