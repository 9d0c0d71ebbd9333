//! Leave-one-class-out (LOCO) protocol: does a configuration chosen on some characters hold on a
//! character it has never seen?
//!
//! With `C` classes (characters), there are `C` folds. In fold `f`:
//!
//! 1. **Selection, on the held-in characters only.** Every candidate configuration is scored by
//!    its mean AP over the queries of the other `C − 1` characters, each ranked against the shapes
//!    of those `C − 1` characters only (the held-out character's shapes are neither queries nor
//!    candidates, and a configuration's re-ranking stages are re-run on that restricted set, so a
//!    reciprocal-neighbourhood stage never sees a held-out shape). The candidate with the highest
//!    held-in All mAP is chosen (ties: the first in configuration order).
//! 2. **Scoring, on the held-out character.** The chosen configuration's queries of the held-out
//!    character are ranked against the **whole** set (its own character's other shapes plus
//!    every held-in shape as distractors), as the server would rank them in an index holding
//!    everything. Ranking them against their own character alone would make every shape
//!    relevant (AP = 1 trivially), so the other characters are what makes the score meaningful.
//!    A configuration has no parameter fitted to labels apart from the choice itself, so this
//!    ranking is the full-set ranking of that configuration, restricted to the held-out queries.
//!
//! Per fold the held-out figures are the mAP of the held-out queries per transformation class,
//! `All`, `All w/o scale` and per `transform@strength`. Over the folds: the **mean** (the folds
//! have the same size on the bench, so this is also the mean over every query) and the **worst
//! fold** (per column, the lowest fold value of that column).
//!
//! **Fixed** configurations ([`LocoOptions::fixed`], by default `default`) are reported with the
//! same held-out figures without any selection, and so is the configuration with the best
//! full-set All mAP among the candidates (the in-sample choice), for comparison.
//!
//! What is *not* re-done per fold: the corpus calibration (histogram windows at a percentile of
//! the pooled distances, [`crate::ranking::calibrate_with`]) is computed once over every shape.
//! It uses no label, and the server computes it over its whole index, held-out character
//! included; choices baked into a configuration (scales, radii, neighbourhood sizes) are what
//! the configuration is, and `docs/quality.md` says which of them were made on which classes.

use super::metrics::{average_precision, rank, QueryResult, ALL, ALL_WO_SCALE};
use super::report::{group_label, ConfigResult};
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write;

/// Options of the leave-one-class-out protocol.
#[derive(Debug, Clone, PartialEq)]
pub struct LocoOptions {
    /// Configurations reported per fold without selection (added to the run when missing, and
    /// then not candidates). Default: `["default"]`.
    pub fixed: Vec<String>,
    /// Leave the fixed configurations out of the candidates even when the run's configuration
    /// list holds them (e.g. to see what the protocol picks among the paper's methods alone).
    pub exclude_fixed: bool,
}

impl Default for LocoOptions {
    fn default() -> Self {
        LocoOptions {
            fixed: vec!["default".into()],
            exclude_fixed: false,
        }
    }
}

impl LocoOptions {
    /// Is the configuration `name`, `index`-th of the run (the first `n_listed` were asked
    /// for), a candidate?
    pub fn is_candidate(&self, name: &str, index: usize, n_listed: usize) -> bool {
        index < n_listed && !(self.exclude_fixed && self.fixed.iter().any(|f| f == name))
    }
}

/// Recomputes a result's matrix with only the rows of a mask ([`HeldIn::record`]).
pub type Rerun<'a> = &'a mut dyn FnMut(&[bool]) -> Vec<f64>;

/// Held-in selection scores, filled while a run evaluates its configurations.
#[derive(Debug, Clone)]
pub struct HeldIn {
    /// Class index of every manifest row.
    classes: Vec<usize>,
    /// Rows that were ranked.
    included: Vec<bool>,
    /// Folds: class indices that have at least one ranked row.
    folds: Vec<usize>,
    /// Per recorded result (in result order): held-in All mAP per fold.
    scores: Vec<Vec<Option<f64>>>,
}

impl HeldIn {
    /// Folds over the classes with a ranked row.
    pub fn new(classes: &[usize], n_classes: usize, included: &[bool]) -> Self {
        let folds = (0..n_classes)
            .filter(|&c| (0..classes.len()).any(|i| included[i] && classes[i] == c))
            .collect();
        HeldIn {
            classes: classes.to_vec(),
            included: included.to_vec(),
            folds,
            scores: Vec::new(),
        }
    }

    /// The rows ranked in the fold holding out class `c`.
    pub fn mask(&self, c: usize) -> Vec<bool> {
        self.included
            .iter()
            .zip(&self.classes)
            .map(|(&inc, &k)| inc && k != c)
            .collect()
    }

    /// Records the next result's held-in scores. `full` is its matrix on every ranked row
    /// (row = query); `rerun(mask)` recomputes its matrix with only the rows of `mask` (the
    /// result's stages re-run on them), or `None` when the result has no stage, in which case
    /// restricting `full`'s rankings is exact.
    pub fn record(&mut self, full: &[f64], rerun: Option<Rerun<'_>>) {
        let n = self.classes.len();
        let scores = match rerun {
            None => {
                // One ranking per query; each fold filters it.
                use rayon::prelude::*;
                let orders: Vec<Option<Vec<usize>>> = (0..n)
                    .into_par_iter()
                    .map(|q| {
                        self.included[q]
                            .then(|| rank(&full[q * n..(q + 1) * n], q, Some(&self.included)))
                    })
                    .collect();
                self.folds
                    .iter()
                    .map(|&f| {
                        let aps: Vec<f64> = (0..n)
                            .filter_map(|q| {
                                let o = orders[q].as_ref()?;
                                if self.classes[q] == f {
                                    return None;
                                }
                                let rel: Vec<bool> = o
                                    .iter()
                                    .filter(|&&j| self.classes[j] != f)
                                    .map(|&j| self.classes[j] == self.classes[q])
                                    .collect();
                                average_precision(&rel)
                            })
                            .collect();
                        mean(&aps)
                    })
                    .collect()
            }
            Some(rerun) => self
                .folds
                .iter()
                .map(|&f| {
                    let mask = self.mask(f);
                    let m = rerun(&mask);
                    let aps: Vec<f64> = (0..n)
                        .filter(|&q| mask[q])
                        .filter_map(|q| {
                            let o = rank(&m[q * n..(q + 1) * n], q, Some(&mask));
                            let rel: Vec<bool> = o
                                .iter()
                                .map(|&j| self.classes[j] == self.classes[q])
                                .collect();
                            average_precision(&rel)
                        })
                        .collect();
                    mean(&aps)
                })
                .collect(),
        };
        self.scores.push(scores);
    }
}

/// [`HeldIn::record`] for one result: `full` is its matrix on every ranked row; its
/// `stages` (applied to the first-stage matrix `dist`) are re-run per fold on the held-in rows.
#[allow(clippy::too_many_arguments)]
pub(super) fn record_held_in(
    h: &mut HeldIn,
    full: &[f64],
    stages: &[&crate::search::Stage],
    dist: &[f64],
    n: usize,
    payload_sets: &[(String, Vec<Option<crate::rerank::GwPayload>>)],
    rescore: &(dyn Fn(usize, usize, &crate::ranking::QuerySpec) -> f64 + Sync),
    solved_pairs: &mut super::rerank::PairCache,
) {
    if stages.is_empty() {
        h.record(full, None);
        return;
    }
    let mut rerun = |mask: &[bool]| {
        let mut cur = dist.to_vec();
        for st in stages {
            cur =
                super::apply_stage(st, dist, &cur, n, mask, payload_sets, rescore, solved_pairs).0;
        }
        cur
    };
    h.record(full, Some(&mut rerun));
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Held-out figures of one configuration in one fold: mAP per group (transformation classes,
/// `All`, `All w/o scale`) and per `transform@strength`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct FoldFigures {
    /// Group → mAP.
    pub groups: BTreeMap<String, f64>,
    /// `transform@strength` → mAP.
    pub per_strength: BTreeMap<String, f64>,
}

/// Mean and worst fold of a column.
#[derive(Debug, Clone, Serialize)]
pub struct MeanWorst {
    /// Mean over the folds that have the column.
    pub mean: f64,
    /// Lowest fold value.
    pub worst: f64,
    /// Class held out in the worst fold.
    pub worst_fold: String,
}

/// Mean and worst fold of every column of a list of per-fold figures.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Summary {
    /// Group → mean / worst.
    pub groups: BTreeMap<String, MeanWorst>,
    /// `transform@strength` → mean / worst.
    pub per_strength: BTreeMap<String, MeanWorst>,
}

/// One fold of the selection.
#[derive(Debug, Clone, Serialize)]
pub struct LocoFold {
    /// The held-out class.
    pub held_out: String,
    /// The chosen configuration.
    pub chosen: String,
    /// Its held-in All mAP (the selection score).
    pub held_in_map: f64,
    /// The next best candidate and its held-in All mAP.
    pub runner_up: Option<(String, f64)>,
    /// The chosen configuration's held-out figures.
    pub held_out_figures: FoldFigures,
}

/// A configuration reported on every fold without selection.
#[derive(Debug, Clone, Serialize)]
pub struct FixedRow {
    /// Configuration name.
    pub name: String,
    /// Why it is reported: `fixed`, `in-sample best` (the best full-set All among the
    /// candidates) or both (`fixed, in-sample best`).
    pub role: String,
    /// Its full-set All mAP (in-sample).
    pub full_set_map: Option<f64>,
    /// Held-out figures per fold (fold order).
    pub folds: Vec<FoldFigures>,
    /// Held-in All mAP per fold.
    pub held_in: Vec<Option<f64>>,
    /// Over the folds.
    pub summary: Summary,
}

/// The whole LOCO report.
#[derive(Debug, Clone, Serialize)]
pub struct LocoReport {
    /// Held-out class of each fold.
    pub classes: Vec<String>,
    /// Candidate configurations.
    pub candidates: Vec<String>,
    /// Per fold: the selection and the chosen configuration's held-out figures.
    pub folds: Vec<LocoFold>,
    /// Classes whose fold was left out: no candidate had a held-in figure (no other class has
    /// a query with a relevant shape).
    pub skipped: Vec<String>,
    /// Over the folds, for the selected configurations.
    pub summary: Summary,
    /// Fixed configurations and the in-sample best.
    pub fixed: Vec<FixedRow>,
    /// Transformation classes in manifest order.
    pub transforms: Vec<String>,
}

/// Held-out figures of `result` in the fold holding out class `c`.
fn fold_figures(
    queries: &[QueryResult],
    c: usize,
    classes: &[usize],
    transforms: &[String],
    strengths: &[i64],
) -> FoldFigures {
    let mut groups: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut per_strength: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for q in queries {
        let i = q.index;
        if classes[i] != c {
            continue;
        }
        let Some(ap) = q.ap else { continue };
        let t = &transforms[i];
        groups.entry(t.clone()).or_default().push(ap);
        groups.entry(ALL.into()).or_default().push(ap);
        if t != "scale" {
            groups.entry(ALL_WO_SCALE.into()).or_default().push(ap);
        }
        per_strength
            .entry(format!("{t}@{}", strengths[i]))
            .or_default()
            .push(ap);
    }
    let m = |b: BTreeMap<String, Vec<f64>>| {
        b.into_iter()
            .filter_map(|(k, v)| mean(&v).map(|x| (k, x)))
            .collect()
    };
    FoldFigures {
        groups: m(groups),
        per_strength: m(per_strength),
    }
}

fn summarize(folds: &[(&str, &FoldFigures)]) -> Summary {
    fn columns<'a>(
        folds: &[(&str, &'a FoldFigures)],
        pick: impl Fn(&'a FoldFigures) -> &'a BTreeMap<String, f64>,
    ) -> BTreeMap<String, MeanWorst> {
        let mut cols: BTreeMap<String, Vec<(&str, f64)>> = BTreeMap::new();
        for &(c, f) in folds {
            for (k, &v) in pick(f) {
                cols.entry(k.clone()).or_default().push((c, v));
            }
        }
        cols.into_iter()
            .map(|(k, v)| {
                let mean = v.iter().map(|x| x.1).sum::<f64>() / v.len() as f64;
                let (worst_fold, worst) = v.iter().copied().fold(
                    (v[0].0, f64::INFINITY),
                    |a, b| if b.1 < a.1 { b } else { a },
                );
                (
                    k,
                    MeanWorst {
                        mean,
                        worst,
                        worst_fold: worst_fold.to_string(),
                    },
                )
            })
            .collect()
    }
    Summary {
        groups: columns(folds, |f| &f.groups),
        per_strength: columns(folds, |f| &f.per_strength),
    }
}

/// Everything the report needs from the run.
pub struct RunView<'a> {
    /// Every evaluated result, in the order [`HeldIn::record`] saw them.
    pub results: &'a [ConfigResult],
    /// Which results are candidates.
    pub candidate: &'a [bool],
    /// Fixed configurations to report.
    pub fixed: &'a [String],
    /// Class names.
    pub class_ids: &'a [String],
    /// Class index, transformation and strength of every manifest row.
    pub classes: &'a [usize],
    /// Transformation of every row.
    pub transforms: &'a [String],
    /// Strength of every row.
    pub strengths: &'a [i64],
}

impl HeldIn {
    /// Runs the selection of every fold and builds the report.
    pub fn report(&self, v: &RunView<'_>) -> LocoReport {
        assert_eq!(self.scores.len(), v.results.len(), "one record per result");
        let figures = |r: usize, c: usize| {
            fold_figures(
                &v.results[r].eval.queries,
                c,
                v.classes,
                v.transforms,
                v.strengths,
            )
        };
        let cands: Vec<usize> = (0..v.results.len()).filter(|&r| v.candidate[r]).collect();
        let mut folds = Vec::new();
        // The folds reported (fold index into `self.folds`): a fold where no candidate has a
        // held-in figure is left out of every table, fixed rows included.
        let mut kept: Vec<usize> = Vec::new();
        let mut skipped: Vec<String> = Vec::new();
        for (fi, &c) in self.folds.iter().enumerate() {
            let mut ranked: Vec<(usize, f64)> = cands
                .iter()
                .filter_map(|&r| self.scores[r][fi].map(|s| (r, s)))
                .collect();
            // Highest held-in mAP first; ties keep configuration order (stable sort).
            ranked.sort_by(|a, b| b.1.total_cmp(&a.1));
            let Some(&(best, score)) = ranked.first() else {
                skipped.push(v.class_ids[c].clone());
                continue;
            };
            kept.push(fi);
            folds.push((
                c,
                LocoFold {
                    held_out: v.class_ids[c].clone(),
                    chosen: v.results[best].name.clone(),
                    held_in_map: score,
                    runner_up: ranked.get(1).map(|&(r, s)| (v.results[r].name.clone(), s)),
                    held_out_figures: figures(best, c),
                },
            ));
        }
        let summary = summarize(
            &folds
                .iter()
                .map(|(_, f)| (f.held_out.as_str(), &f.held_out_figures))
                .collect::<Vec<_>>(),
        );
        let mut fixed_rows: Vec<(usize, String)> = Vec::new();
        for name in v.fixed {
            if let Some(r) = v.results.iter().position(|x| &x.name == name) {
                fixed_rows.push((r, "fixed".into()));
            }
        }
        let full_map = |r: usize| v.results[r].eval.group(ALL).and_then(|g| g.map);
        if let Some(&best) = cands.iter().max_by(|&&a, &&b| {
            full_map(a)
                .unwrap_or(f64::NEG_INFINITY)
                .total_cmp(&full_map(b).unwrap_or(f64::NEG_INFINITY))
                .then(b.cmp(&a))
        }) {
            match fixed_rows.iter_mut().find(|(r, _)| *r == best) {
                Some(row) => row.1.push_str(", in-sample best"),
                None => fixed_rows.push((best, "in-sample best".into())),
            }
        }
        let fixed = fixed_rows
            .into_iter()
            .map(|(r, role)| {
                let per: Vec<FoldFigures> =
                    kept.iter().map(|&fi| figures(r, self.folds[fi])).collect();
                let summary = summarize(
                    &kept
                        .iter()
                        .map(|&fi| v.class_ids[self.folds[fi]].as_str())
                        .zip(per.iter())
                        .collect::<Vec<_>>(),
                );
                FixedRow {
                    name: v.results[r].name.clone(),
                    role,
                    full_set_map: full_map(r),
                    folds: per,
                    held_in: kept.iter().map(|&fi| self.scores[r][fi]).collect(),
                    summary,
                }
            })
            .collect();
        let mut transforms: Vec<String> = Vec::new();
        for t in v.transforms {
            if !transforms.contains(t) {
                transforms.push(t.clone());
            }
        }
        LocoReport {
            classes: folds.iter().map(|(_, f)| f.held_out.clone()).collect(),
            candidates: cands.iter().map(|&r| v.results[r].name.clone()).collect(),
            folds: folds.into_iter().map(|(_, f)| f).collect(),
            skipped,
            summary,
            fixed,
            transforms,
        }
    }
}

fn pct(x: Option<f64>) -> String {
    x.map(|v| format!("{:.2}", 100.0 * v))
        .unwrap_or_else(|| "–".into())
}

impl LocoReport {
    /// The selected configurations' mean (over folds) mAP of a group.
    pub fn mean(&self, group: &str) -> Option<f64> {
        self.summary.groups.get(group).map(|m| m.mean)
    }

    /// The selected configurations' worst-fold mAP of a group.
    pub fn worst(&self, group: &str) -> Option<f64> {
        self.summary.groups.get(group).map(|m| m.worst)
    }

    /// The row of a fixed configuration.
    pub fn fixed(&self, name: &str) -> Option<&FixedRow> {
        self.fixed
            .iter()
            .find(|r| r.name == name && r.role.starts_with("fixed"))
    }

    fn columns(&self) -> Vec<String> {
        let mut cols = self.transforms.clone();
        cols.push(ALL.into());
        if self.transforms.iter().any(|t| t == "scale") {
            cols.push(ALL_WO_SCALE.into());
        }
        cols
    }

    /// The Markdown section: folds, summary over folds, per-strength tables.
    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let cols = self.columns();
        let head: Vec<String> = cols.iter().map(|c| group_label(c)).collect();
        let _ = writeln!(s, "## Leave-one-class-out (mAP %)\n");
        let cand = if self.candidates.len() <= 8 {
            self.candidates
                .iter()
                .map(|c| format!("`{c}`"))
                .collect::<Vec<_>>()
                .join(", ")
        } else {
            format!("{} configurations", self.candidates.len())
        };
        let _ = writeln!(
            s,
            "{} folds; candidates: {cand}. Per fold the candidate with the best All mAP on the other \
             classes (queries and candidates restricted to them, stages re-run; the histogram \
             windows are calibrated once on every ranked shape, without labels) is chosen, then \
             its queries of the held-out class are ranked against the whole set. Worst = the \
             lowest fold of each column.\n",
            self.folds.len()
        );
        if !self.skipped.is_empty() {
            let _ = writeln!(
                s,
                "Left out (no other class has a query with a relevant shape, so no held-in \
                 figure): {}.\n",
                self.skipped.join(", ")
            );
        }
        let _ = writeln!(
            s,
            "| held out | chosen | held-in All | runner-up (held-in All) | {} |",
            head.join(" | ")
        );
        let _ = writeln!(s, "|---|---|---|---|{}", "---|".repeat(cols.len()));
        for f in &self.folds {
            let cells: Vec<String> = cols
                .iter()
                .map(|c| pct(f.held_out_figures.groups.get(c).copied()))
                .collect();
            let runner = f
                .runner_up
                .as_ref()
                .map(|(n, v)| format!("`{n}` ({})", pct(Some(*v))))
                .unwrap_or_else(|| "–".into());
            let _ = writeln!(
                s,
                "| {} | `{}` | {} | {runner} | {} |",
                f.held_out,
                f.chosen,
                pct(Some(f.held_in_map)),
                cells.join(" | ")
            );
        }
        let _ = writeln!(s, "\n### Over the folds (mAP %)\n");
        let _ = writeln!(s, "| configuration | | {} |", head.join(" | "));
        let _ = writeln!(s, "|---|---|{}", "---|".repeat(cols.len()));
        let row = |s: &mut String, label: &str, sum: &Summary| {
            let worst_all = sum
                .groups
                .get(ALL)
                .map(|m| format!(" (All: {})", m.worst_fold))
                .unwrap_or_default();
            for (what, pick) in [
                ("mean", (|m: &MeanWorst| m.mean) as fn(&MeanWorst) -> f64),
                ("worst fold", |m: &MeanWorst| m.worst),
            ] {
                let cells: Vec<String> = cols
                    .iter()
                    .map(|c| pct(sum.groups.get(c).map(pick)))
                    .collect();
                let what = if what == "mean" {
                    what.to_string()
                } else {
                    format!("{what}{worst_all}")
                };
                let _ = writeln!(s, "| {label} | {what} | {} |", cells.join(" | "));
            }
        };
        row(&mut s, "selected per fold", &self.summary);
        for r in &self.fixed {
            row(&mut s, &format!("`{}` ({})", r.name, r.role), &r.summary);
        }
        let _ = writeln!(
            s,
            "\n### Fixed configurations per fold (All mAP %, held-out / held-in)\n"
        );
        let _ = writeln!(
            s,
            "| configuration | full set | {} |",
            self.classes.join(" | ")
        );
        let _ = writeln!(s, "|---|---|{}", "---|".repeat(self.classes.len()));
        for r in &self.fixed {
            let cells: Vec<String> = r
                .folds
                .iter()
                .zip(&r.held_in)
                .map(|(f, h)| format!("{} / {}", pct(f.groups.get(ALL).copied()), pct(*h)))
                .collect();
            let _ = writeln!(
                s,
                "| `{}` ({}) | {} | {} |",
                r.name,
                r.role,
                pct(r.full_set_map),
                cells.join(" | ")
            );
        }
        let sel = [("selected per fold".to_string(), &self.summary)];
        let fixed: Vec<(String, &Summary)> = self
            .fixed
            .iter()
            .map(|r| (format!("`{}` ({})", r.name, r.role), &r.summary))
            .collect();
        for (label, sum) in sel.iter().map(|(l, s)| (l.clone(), *s)).chain(fixed) {
            let _ = writeln!(
                s,
                "\n### Per strength, {label} (mAP %, mean over folds / worst fold)\n"
            );
            s.push_str(&strength_table(sum, &self.transforms));
        }
        let _ = writeln!(
            s,
            "\n(`isometry` strengths are pose numbers, not severities; `partiality` 1–3 pool \
             the `holes` and `cut` shapes of that level.)"
        );
        s
    }
}

/// Rows = transformations with strengths, columns = strengths.
fn strength_table(sum: &Summary, transforms: &[String]) -> String {
    let mut strengths: Vec<i64> = sum
        .per_strength
        .keys()
        .filter_map(|k| k.rsplit_once('@').and_then(|(_, s)| s.parse().ok()))
        .filter(|&s| s != 0)
        .collect();
    strengths.sort_unstable();
    strengths.dedup();
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| transform | {} |",
        strengths
            .iter()
            .map(|x| x.to_string())
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(s, "|---|{}", "---|".repeat(strengths.len()));
    for t in transforms {
        let cells: Vec<String> = strengths
            .iter()
            .map(|st| match sum.per_strength.get(&format!("{t}@{st}")) {
                Some(m) => format!("{} / {}", pct(Some(m.mean)), pct(Some(m.worst))),
                None => String::new(),
            })
            .collect();
        if cells.iter().all(|c| c.is_empty()) {
            continue;
        }
        let _ = writeln!(s, "| {} | {} |", group_label(t), cells.join(" | "));
    }
    s
}
