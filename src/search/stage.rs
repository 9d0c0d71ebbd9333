//! Re-ranking stages: the one validated [`Stage`] type, its two serialised forms, and [`run`].
//!
//! * [`Stage`] is what runs: an exact re-scoring under another query spec, a reciprocal-
//!   neighbourhood re-ranking ([`ReciprocalStage`]) or a spectral Gromov–Wasserstein
//!   re-ranking ([`SgwStage`]). A list of stages follows the first stage (the scan); an empty
//!   list is the scan alone. A `Stage` is validated when it is built ([`Stage::new`]) or parsed.
//! * In configurations (eval's `Config.rerank`, JSON files) a stage is tagged by `kind`:
//!   `{"kind": "reciprocal", "shortlist": 200, …}`; a legacy `{"kind": "none"}` entry is
//!   skipped when a list is read ([`deserialize_list`]).
//! * In search requests a stage is a [`StageRequest`], tagged by `stage`, with optional fields
//!   that default relative to the request (`top_k`, its query spec) and limits of the server;
//!   [`StageRequest::resolve`] turns it into a `Stage`.
//!
//! [`run`] applies a list of stages to a first-stage result through an [`Env`], which provides
//! what a stage reads: first-stage scores between shortlisted shapes, scores under another
//! query spec, and GW scores of re-ranking payloads. The server's env reads its corpus and
//! store, eval's reads its all-pairs matrices; both run the same code.

use crate::ranking::QuerySpec;
use crate::rerank::{fuse, reciprocal, Fusion, GwOptions, PayloadSpec, ReciprocalStage, SgwStage};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// Most candidates a spectral Gromov–Wasserstein stage of a search re-scores (≈ 40 ms of one
/// core each).
pub const MAX_GW_SHORTLIST: usize = 200;

/// Most candidates a reciprocal-neighbourhood stage of a search re-ranks (it scores every pair
/// of them: 10⁶ first-stage scores at the limit).
pub const MAX_RECIPROCAL_SHORTLIST: usize = 1000;

/// A validated re-ranking stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "StageRepr", into = "StageRepr")]
pub enum Stage {
    /// Re-scores the best `shortlist` candidates exactly under `query` and re-sorts them
    /// (ties by position).
    Exact {
        /// Candidates re-scored.
        shortlist: usize,
        /// The query spec of this stage.
        query: QuerySpec,
    },
    /// Reciprocal-neighbourhood re-ranking of the best `shortlist` under the first stage's
    /// dissimilarity.
    Reciprocal(ReciprocalStage),
    /// Spectral Gromov–Wasserstein re-ranking of the best `shortlist` by their payloads.
    SpectralGw(SgwStage),
}

/// The configuration form of a stage (tagged by `kind`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
enum StageRepr {
    None,
    Exact { shortlist: usize, query: QuerySpec },
    SpectralGw(SgwStage),
    Reciprocal(ReciprocalStage),
}

impl TryFrom<StageRepr> for Stage {
    type Error = Error;
    fn try_from(r: StageRepr) -> Result<Stage> {
        Stage::new(match r {
            StageRepr::None => {
                return Err(Error::InvalidArgument(
                    "\"none\" is not a stage (an empty list is the scan alone)".into(),
                ))
            }
            StageRepr::Exact { shortlist, query } => Stage::Exact { shortlist, query },
            StageRepr::SpectralGw(s) => Stage::SpectralGw(s),
            StageRepr::Reciprocal(s) => Stage::Reciprocal(s),
        })
    }
}

impl From<Stage> for StageRepr {
    fn from(s: Stage) -> StageRepr {
        match s {
            Stage::Exact { shortlist, query } => StageRepr::Exact { shortlist, query },
            Stage::SpectralGw(s) => StageRepr::SpectralGw(s),
            Stage::Reciprocal(s) => StageRepr::Reciprocal(s),
        }
    }
}

/// Reads a list of stages in the configuration form, skipping legacy `{"kind": "none"}`
/// entries (for `#[serde(deserialize_with)]`).
pub fn deserialize_list<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<Vec<Stage>, D::Error> {
    let raw: Vec<StageRepr> = Vec::deserialize(d)?;
    raw.into_iter()
        .filter(|r| !matches!(r, StageRepr::None))
        .map(|r| Stage::try_from(r).map_err(serde::de::Error::custom))
        .collect()
}

fn invalid(m: impl Into<String>) -> Error {
    Error::InvalidArgument(m.into())
}

impl Stage {
    /// Validates `s`.
    pub fn new(s: Stage) -> Result<Stage> {
        match &s {
            Stage::Exact { shortlist, query } => {
                if *shortlist == 0 {
                    return Err(invalid("exact shortlist must be ≥ 1"));
                }
                if query.channels.is_empty() {
                    return Err(invalid("exact: at least one channel"));
                }
                query
                    .validate()
                    .map_err(|e| invalid(format!("exact: {e}")))?;
            }
            Stage::Reciprocal(r) => r
                .validate()
                .map_err(|m| invalid(format!("reciprocal {m}")))?,
            Stage::SpectralGw(g) => {
                if g.shortlist == 0 {
                    return Err(invalid("spectral_gw shortlist must be ≥ 1"));
                }
                if !(1e-4..=1.0).contains(&g.gw.eps_rel) {
                    return Err(invalid("spectral_gw eps_rel must be in [1e-4, 1]"));
                }
                if !(1..=20).contains(&g.gw.outer_iterations) {
                    return Err(invalid("spectral_gw outer_iterations must be in 1..=20"));
                }
                if let Fusion::RankBlend { weight } = g.fusion {
                    if !(0.0..=1.0).contains(&weight) {
                        return Err(invalid("spectral_gw blend must be in [0, 1]"));
                    }
                }
                if g.payload.samples < 2 || g.payload.times.is_empty() {
                    return Err(invalid(
                        "spectral_gw payload: at least 2 samples and one time",
                    ));
                }
            }
        }
        Ok(s)
    }

    /// How many candidates of the previous stage it reads.
    pub fn shortlist(&self) -> usize {
        match self {
            Stage::Exact { shortlist, .. } => *shortlist,
            Stage::Reciprocal(r) => r.shortlist,
            Stage::SpectralGw(g) => g.shortlist,
        }
    }

    /// The stage's name in a search answer (its `stage` tag in a request).
    pub fn name(&self) -> &'static str {
        match self {
            Stage::Exact { .. } => "exact",
            Stage::Reciprocal(_) => "reciprocal",
            Stage::SpectralGw(_) => "spectral_gw",
        }
    }

    /// The payload every shape needs (`None` when the stage reads none).
    pub fn payload_spec(&self) -> Option<&PayloadSpec> {
        match self {
            Stage::SpectralGw(g) => Some(&g.payload),
            _ => None,
        }
    }

    /// Short label, e.g. `sgw:50`, `recip:200:k=8,16`.
    pub fn label(&self) -> String {
        match self {
            Stage::Exact { shortlist, .. } => format!("exact:{shortlist}"),
            Stage::SpectralGw(s) => format!("sgw:{}", s.shortlist),
            Stage::Reciprocal(s) => {
                let d = ReciprocalStage::default();
                let mut l = format!("recip:{}", s.shortlist);
                if s.neighbourhoods != d.neighbourhoods {
                    let ks: Vec<String> = s.neighbourhoods.iter().map(|k| k.to_string()).collect();
                    l.push_str(&format!(":k={}", ks.join(",")));
                }
                if s.expansion != d.expansion {
                    l.push_str(&format!(":expand={}", s.expansion));
                }
                if s.original_weight != d.original_weight {
                    l.push_str(&format!(":lambda={}", s.original_weight));
                }
                l
            }
        }
    }
}

/// One stage of a search request (the HTTP form, tagged by `stage`; absent fields take the
/// defaults documented per field).
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(tag = "stage", rename_all = "snake_case", deny_unknown_fields)]
pub enum StageRequest {
    /// Re-scores the best `shortlist` candidates of the previous stage with another query spec
    /// (typically more channels or a costlier dissimilarity), exactly, and re-sorts them.
    Exact {
        /// How many candidates of the previous stage to re-score (default: 4 × top_k).
        #[serde(default)]
        shortlist: Option<usize>,
        /// Query spec overrides for this stage (merged over the request's spec).
        #[serde(default)]
        spec: Option<serde_json::Value>,
    },
    /// Spectral Gromov–Wasserstein re-ranking (paper footnote 2; `crate::rerank`): the best
    /// `shortlist` candidates of the previous stage are re-scored by the entropic GW
    /// discrepancy between the query's and each candidate's stored payload (diffusion
    /// distances on farthest-point samples) and re-sorted (ties keep the previous order).
    SpectralGw {
        /// How many candidates to re-score (default 20, at most [`MAX_GW_SHORTLIST`]).
        #[serde(default)]
        shortlist: Option<usize>,
        /// Entropic regularisation relative to the mean cost (default 0.003, in [1e-4, 1]).
        #[serde(default)]
        eps_rel: Option<f64>,
        /// Outer linearisation iterations (default 5, in 1..=20).
        #[serde(default)]
        outer_iterations: Option<usize>,
        /// Also solve from two anchored starts and keep the lowest energy (default false;
        /// 2–5× the time; see [`GwOptions::anchored_starts`]).
        #[serde(default)]
        anchored_starts: Option<bool>,
        /// Weight of the previous stage's rank in a rank blend (`w·rank_prev + (1−w)·rank_gw`,
        /// in [0, 1]); absent: order by the GW score alone.
        #[serde(default)]
        blend: Option<f64>,
    },
    /// Reciprocal-neighbourhood re-ranking (`crate::rerank::reciprocal`): the best `shortlist`
    /// candidates are re-ordered by how much their neighbourhoods (within the shortlist, under
    /// the first stage's dissimilarity) overlap the query's. Part of the default search.
    Reciprocal {
        /// How many candidates to re-rank (default 200, at most [`MAX_RECIPROCAL_SHORTLIST`]).
        #[serde(default)]
        shortlist: Option<usize>,
        /// Neighbourhood sizes averaged (default [8, 16, 32]; 1 to 8 sizes in 1..=1000).
        #[serde(default)]
        neighbourhoods: Option<Vec<usize>>,
        /// Local query expansion (default 4, in 1..=100).
        #[serde(default)]
        expansion: Option<usize>,
        /// Weight of the first-stage dissimilarity in the score (default 0.1, in [0, 1]).
        #[serde(default)]
        original_weight: Option<f64>,
    },
}

impl StageRequest {
    /// The stage this request asks for: `top_k` and `max_shortlist` bound the exact stage's
    /// shortlist (default 4 × top_k), `spec` turns the exact stage's overrides into its query
    /// spec (merged over the request's).
    pub fn resolve(
        &self,
        top_k: usize,
        max_shortlist: usize,
        spec: &dyn Fn(Option<&serde_json::Value>) -> Result<QuerySpec>,
    ) -> Result<Stage> {
        Stage::new(match self {
            StageRequest::Exact { shortlist, spec: s } => {
                // The default is clamped to the bound (a request with a top_k over a quarter
                // of it, and no shortlist, was refused for a shortlist it did not ask for); a
                // shortlist asked for is checked as it is.
                let n = shortlist.unwrap_or((4 * top_k).clamp(1, max_shortlist));
                if n == 0 || n > max_shortlist {
                    return Err(invalid(format!(
                        "rerank shortlist must be in 1..={max_shortlist}"
                    )));
                }
                Stage::Exact {
                    shortlist: n,
                    query: spec(s.as_ref())?,
                }
            }
            StageRequest::SpectralGw {
                shortlist,
                eps_rel,
                outer_iterations,
                anchored_starts,
                blend,
            } => {
                let d = SgwStage::default();
                let n = shortlist.unwrap_or(d.shortlist);
                if n == 0 || n > MAX_GW_SHORTLIST {
                    return Err(invalid(format!(
                        "spectral_gw shortlist must be in 1..={MAX_GW_SHORTLIST}"
                    )));
                }
                let g = GwOptions::default();
                Stage::SpectralGw(SgwStage {
                    shortlist: n,
                    payload: PayloadSpec::default(),
                    gw: GwOptions {
                        eps_rel: eps_rel.unwrap_or(g.eps_rel),
                        outer_iterations: outer_iterations.unwrap_or(g.outer_iterations),
                        anchored_starts: anchored_starts.unwrap_or(g.anchored_starts),
                        ..g
                    },
                    fusion: match blend {
                        None => Fusion::Replace,
                        Some(w) => Fusion::RankBlend { weight: *w },
                    },
                })
            }
            StageRequest::Reciprocal {
                shortlist,
                neighbourhoods,
                expansion,
                original_weight,
            } => {
                let d = ReciprocalStage::default();
                let st = ReciprocalStage {
                    shortlist: shortlist.unwrap_or(d.shortlist),
                    neighbourhoods: neighbourhoods.clone().unwrap_or(d.neighbourhoods),
                    expansion: expansion.unwrap_or(d.expansion),
                    original_weight: original_weight.unwrap_or(d.original_weight),
                };
                if st.shortlist == 0 || st.shortlist > MAX_RECIPROCAL_SHORTLIST {
                    return Err(invalid(format!(
                        "reciprocal shortlist must be in 1..={MAX_RECIPROCAL_SHORTLIST}"
                    )));
                }
                Stage::Reciprocal(st)
            }
        })
    }

    /// True for a stage that compares re-ranking payloads.
    pub fn needs_payload(&self) -> bool {
        matches!(self, StageRequest::SpectralGw { .. })
    }
}

/// A candidate between stages: `at` orders ties (position in the corpus, or manifest row),
/// `item` is the caller's.
#[derive(Clone, Debug)]
pub struct Entry<I> {
    /// Position (ties of an exact stage are ordered by it).
    pub at: usize,
    /// The caller's data.
    pub item: I,
    /// Score of the last stage (lower = more similar).
    pub score: f64,
    /// Score of each stage that scored this entry (first stage first).
    pub stage_scores: Vec<f64>,
}

/// What stages read, provided by the caller of [`run`].
pub trait Env<I> {
    /// The error a stage's inputs can fail with.
    type Error;
    /// The scores of `list`'s entries under `query` (an exact stage). May drop entries that no
    /// longer exist.
    fn rescore(
        &mut self,
        list: &mut Vec<Entry<I>>,
        query: &QuerySpec,
    ) -> std::result::Result<Vec<f64>, Self::Error>;
    /// The first stage's dissimilarities between the query (item 0) and `list` (items `1..`):
    /// a row-major `(n + 1)²` matrix whose strict upper triangle is filled (a reciprocal stage).
    /// May drop entries that no longer exist.
    fn pairwise(&mut self, list: &mut Vec<Entry<I>>) -> std::result::Result<Vec<f64>, Self::Error>;
    /// The GW scores of `list`'s entries against the query (∞ where a payload is missing).
    fn gw(
        &mut self,
        list: &[Entry<I>],
        stage: &SgwStage,
    ) -> std::result::Result<Vec<f64>, Self::Error>;
}

/// Applies `stages` in order to `list` (the first stage's result, best first): each stage
/// keeps the best `shortlist` of the previous one and re-orders them.
pub fn run<I, E>(
    stages: &[Stage],
    mut list: Vec<Entry<I>>,
    env: &mut dyn Env<I, Error = E>,
) -> std::result::Result<Vec<Entry<I>>, E> {
    for st in stages {
        list.truncate(st.shortlist());
        match st {
            Stage::Exact { query, .. } => {
                let scores = env.rescore(&mut list, query)?;
                for (e, s) in list.iter_mut().zip(scores) {
                    e.score = s;
                    e.stage_scores.push(s);
                }
                list.sort_by(|a, b| a.score.total_cmp(&b.score).then(a.at.cmp(&b.at)));
            }
            Stage::Reciprocal(r) => {
                let d = env.pairwise(&mut list)?;
                let m = list.len() + 1;
                list = reorder(list, reciprocal::rerank(&d, m, r));
            }
            Stage::SpectralGw(g) => {
                let gw = env.gw(&list, g)?;
                list = reorder(list, fuse(&gw, g.fusion));
            }
        }
    }
    Ok(list)
}

/// A shortlist re-ordered by a stage: `order` = (index in `list`, new score), best first.
fn reorder<I>(list: Vec<Entry<I>>, order: Vec<(usize, f64)>) -> Vec<Entry<I>> {
    let mut old: Vec<Option<Entry<I>>> = list.into_iter().map(Some).collect();
    order
        .into_iter()
        .filter_map(|(i, score)| {
            let mut e = old[i].take()?;
            e.score = score;
            e.stage_scores.push(score);
            Some(e)
        })
        .collect()
}
