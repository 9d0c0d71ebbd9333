//! Re-ranking stages applied to a shortlist of the distribution-based ranking.
//!
//! The paper (Bronstein & Bronstein 2011, footnote 2) suggests filtering a large database with a
//! cheap spectral distance and re-ranking a fixed-size shortlist with a Gromov–Hausdorff-type
//! distance; Mémoli's spectral Gromov–Wasserstein distance is the one it names. This module
//! implements that second stage:
//!
//! * [`payload`]: per shape, `m` farthest-point samples with their Voronoi areas as the measure
//!   and their diffusion-distance (or heat-kernel) matrices at one or a few scales
//!   ([`GwPayload`], computed once per shape and stored with the signature).
//! * [`gw`]: entropic Gromov–Wasserstein with the square loss (Peyré–Cuturi–Solomon 2016,
//!   decomposition trick with faer GEMM, stabilised Sinkhorn inner loop, product-measure init).
//! * [`SgwStage`] + [`rerank_gw`]: the stage's options and its re-ordering of one shortlist
//!   (the stage type the search pipeline runs is [`crate::search::Stage`]).
//! * [`reciprocal`]: a second kind of stage, k-reciprocal neighbourhood re-ranking of a shortlist
//!   from the first stage's own dissimilarities between the candidates (no payload).
//!
//! Scores are symmetric by construction: the pair is always solved in a canonical order (the
//! payload that compares lower first), so `score(a, b) == score(b, a)` bit for bit and a
//! shortlist's order never depends on which shape is the query.

pub mod gw;
pub mod payload;
pub mod reciprocal;

pub use gw::{entropic_gw, GwOptions, GwResult};
pub use payload::{compute_payload, GwMetric, GwPayload, PayloadSpec, TimeRule};
pub use reciprocal::ReciprocalStage;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::cmp::Ordering;

/// How re-ranked scores combine with the first stage.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Default)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Fusion {
    /// Order the shortlist by the GW score alone.
    #[default]
    Replace,
    /// Order by `w · rank_first + (1 − w) · rank_gw` (ranks within the shortlist, 0-based; ties
    /// by the first-stage order).
    RankBlend {
        /// Weight of the first-stage rank.
        weight: f64,
    },
}

/// Spectral Gromov–Wasserstein re-ranking of the top `shortlist` results.
///
/// Default (the best measured on bench/dev, `docs/quality.md`): top 20, 100 samples, diffusion
/// distances at t = 0.016, 0.04, 0.1 (the three small default scales), ε = 0.003, 5 outer
/// iterations, GW alone.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct SgwStage {
    /// How many first-stage results to re-rank.
    pub shortlist: usize,
    /// Per-shape payload (samples, times, metric).
    pub payload: PayloadSpec,
    /// Solver options.
    #[serde(default)]
    pub gw: GwOptions,
    /// Combination with the first stage.
    #[serde(default)]
    pub fusion: Fusion,
}

impl Default for SgwStage {
    fn default() -> Self {
        Self {
            shortlist: 20,
            payload: PayloadSpec::default(),
            gw: GwOptions::default(),
            fusion: Fusion::Replace,
        }
    }
}

/// One shortlist entry: the caller's id, its first-stage score and its payload.
#[derive(Clone, Debug)]
pub struct Candidate<'a, I> {
    /// Caller's identifier.
    pub id: I,
    /// First-stage score (lower = more similar); the shortlist is given in first-stage order.
    pub score: f64,
    /// The candidate's payload (`None`: no payload stored; ranked after every scored one).
    pub payload: Option<&'a GwPayload>,
}

fn cmp_f32s(a: &[f32], b: &[f32]) -> Ordering {
    for (x, y) in a.iter().zip(b) {
        match x.total_cmp(y) {
            Ordering::Equal => {}
            o => return o,
        }
    }
    a.len().cmp(&b.len())
}

/// Canonical order of two payloads (deterministic, content based).
fn canonical(a: &GwPayload, b: &GwPayload) -> Ordering {
    a.samples
        .cmp(&b.samples)
        .then_with(|| {
            for (x, y) in a.weights.iter().zip(&b.weights) {
                match x.total_cmp(y) {
                    Ordering::Equal => {}
                    o => return o,
                }
            }
            Ordering::Equal
        })
        .then_with(|| {
            for (x, y) in a.upper.iter().zip(&b.upper) {
                match cmp_f32s(x, y) {
                    Ordering::Equal => {}
                    o => return o,
                }
            }
            Ordering::Equal
        })
}

/// Symmetric entropic-GW score of two payloads (`+∞` when their specs differ).
pub fn gw_score(a: &GwPayload, b: &GwPayload, opts: &GwOptions) -> f64 {
    if a.spec_key != b.spec_key || a.upper.len() != b.upper.len() || a.upper.is_empty() {
        return f64::INFINITY;
    }
    let (x, y) = if canonical(a, b) == Ordering::Greater {
        (b, a)
    } else {
        (a, b)
    };
    let cx = x.matrices();
    let cy = y.matrices();
    let rx: Vec<_> = cx.iter().map(|m| m.as_ref()).collect();
    let ry: Vec<_> = cy.iter().map(|m| m.as_ref()).collect();
    entropic_gw(&rx, &x.weights, &ry, &y.weights, opts).value
}

/// Re-ranks `shortlist` (given in first-stage order) for `query` by spectral GW: returns
/// `(id, score)` best first. Every entry is scored (the caller passes the stage's top
/// `shortlist`); the score is the GW energy ([`Fusion::Replace`]) or the blended rank
/// ([`Fusion::RankBlend`]); ties keep the first-stage order. Candidates are scored in parallel
/// (rayon); each GW solve is sequential, so results do not depend on the thread count.
pub fn rerank_gw<I: Clone + Send + Sync>(
    stage: &SgwStage,
    query: &GwPayload,
    shortlist: &[Candidate<'_, I>],
) -> Vec<(I, f64)> {
    let gw: Vec<f64> = shortlist
        .par_iter()
        .map(|c| match c.payload {
            Some(p) => gw_score(query, p, &stage.gw),
            None => f64::INFINITY,
        })
        .collect();
    fuse(&gw, stage.fusion)
        .into_iter()
        .map(|(i, sc)| (shortlist[i].id.clone(), sc))
        .collect()
}

/// Orders a shortlist from its GW scores (`gw[i]` of the `i`-th first-stage result): returns
/// `(shortlist index, final score)` best first, ties by first-stage order.
pub fn fuse(gw: &[f64], fusion: Fusion) -> Vec<(usize, f64)> {
    let score: Vec<f64> = match fusion {
        Fusion::Replace => gw.to_vec(),
        Fusion::RankBlend { weight } => {
            let mut order: Vec<usize> = (0..gw.len()).collect();
            order.sort_by(|&a, &b| gw[a].total_cmp(&gw[b]).then(a.cmp(&b)));
            let mut gw_rank = vec![0.0; gw.len()];
            for (r, &i) in order.iter().enumerate() {
                gw_rank[i] = r as f64;
            }
            (0..gw.len())
                .map(|i| {
                    if gw[i].is_finite() {
                        weight * i as f64 + (1.0 - weight) * gw_rank[i]
                    } else {
                        f64::INFINITY
                    }
                })
                .collect()
        }
    };
    let mut idx: Vec<usize> = (0..gw.len()).collect();
    idx.sort_by(|&a, &b| score[a].total_cmp(&score[b]).then(a.cmp(&b)));
    idx.into_iter().map(|i| (i, score[i])).collect()
}

#[cfg(test)]
mod tests;
