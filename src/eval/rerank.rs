//! Re-ranking stages in eval: every query's ranking of a configuration is passed through
//! [`crate::search::run`], with an [`Env`] that reads the all-pairs matrices (`shapeseek eval
//! --rerank STAGE` adds `<config>+<STAGE>` configurations; a configuration's own stages run
//! the same way).
//!
//! Payloads are cached under `<cache>/gw/` keyed by the analysis key and
//! [`PayloadSpec::key`], so only the first run of a payload spec pays for it. GW values of
//! solved pairs are kept per payload key and solver options ([`PairCache`]) and reused by every
//! stage of a run that differs only in its shortlist or fusion.
//!
//! Row values after re-ranking: the re-ranked top `K` get `0, 1, …, K−1`, the rest
//! `K + first-stage position`. AP and per-query ROC only depend on each query's order, so they
//! are exact; the pooled EER of such a run compares ranks, not distances.

use crate::eval::cache::{hash_parts, unwrap_envelope, wrap_envelope, write_atomic, Cache};
use crate::eval::manifest::Manifest;
use crate::eval::metrics;
use crate::mesh::read::{read_mesh, Format, ReadLimits};
use crate::ranking::QuerySpec;
use crate::rerank::{gw_score, rerank_gw, Candidate, GwPayload, PayloadSpec, SgwStage};
use crate::search::{run, Entry, Env, Stage};
use crate::spectrum::{analyze, AnalyzeOptions};
use rayon::prelude::*;
use std::collections::HashMap;
use std::convert::Infallible;
use std::time::Instant;

const PAYLOAD_MAGIC: &[u8; 8] = b"SSGWPL01";

/// Payload of every manifest shape (`None` where the shape failed), from the cache or computed
/// from the cached analysis (analysing again when that is missing).
pub fn shape_payloads(
    manifest: &Manifest,
    included: &[bool],
    opts: &AnalyzeOptions,
    analysis_key: &(dyn Fn(&[u8]) -> String + Sync),
    cache: &Cache,
    spec: &PayloadSpec,
) -> Vec<Option<GwPayload>> {
    let skey = spec.key();
    let dir = cache.dir().map(|d| d.join("gw"));
    if let Some(d) = &dir {
        let _ = std::fs::create_dir_all(d);
    }
    manifest
        .entries
        .par_iter()
        .zip(included.par_iter())
        .map(|(e, &ok)| {
            if !ok {
                return None;
            }
            let bytes = std::fs::read(&e.resolved).ok()?;
            let akey = analysis_key(&bytes);
            let pkey = hash_parts(&[akey.as_bytes(), skey.as_bytes()]);
            let path = dir.as_ref().map(|d| d.join(format!("{pkey}.bin")));
            if let Some(p) = &path {
                if let Ok(raw) = std::fs::read(p) {
                    if let Some(inner) = unwrap_envelope(&raw, PAYLOAD_MAGIC) {
                        if let Ok(pl) = GwPayload::from_bytes(inner) {
                            if pl.spec_key == skey {
                                return Some(pl);
                            }
                        }
                    }
                }
            }
            let analysis = match cache.load_analysis(&akey) {
                Some(a) => a,
                None => {
                    let hint = e
                        .resolved
                        .extension()
                        .and_then(|x| x.to_str())
                        .and_then(Format::from_extension);
                    let mesh = read_mesh(&bytes, hint, &ReadLimits::default()).ok()?;
                    analyze(&mesh, opts).ok()?
                }
            };
            let pl = crate::rerank::compute_payload(&analysis, spec).ok()?;
            if let Some(p) = &path {
                let _ = write_atomic(p, &wrap_envelope(&pl.to_bytes(), PAYLOAD_MAGIC));
            }
            Some(pl)
        })
        .collect()
}

/// Timing of one re-ranking run.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RerankStats {
    /// Distinct (unordered) pairs solved.
    pub pairs: usize,
    /// Wall time of all solves (GW) or of every query's stage (others).
    pub wall_s: f64,
    /// Mean CPU time of one GW solve (ms; sum of per-solve times / pairs).
    pub per_candidate_ms: f64,
    /// Mean wall time of one query's stage (ms): for GW, [`rerank_gw`] on up to 8 queries
    /// with every worker thread; otherwise the mean over every query on one thread.
    pub per_query_ms: f64,
}

/// GW values of solved (unordered) pairs, per payload key and solver options.
pub type PairCache = HashMap<String, HashMap<(usize, usize), f64>>;

/// What a stage reads in eval: `base` (the first stage's matrix) for a reciprocal stage,
/// `rescore` for an exact stage, solved GW pairs for a GW stage.
struct MatrixEnv<'a> {
    q: usize,
    n: usize,
    base: &'a [f64],
    rescore: &'a (dyn Fn(usize, usize, &QuerySpec) -> f64 + Sync),
    gw: Option<&'a HashMap<(usize, usize), f64>>,
}

impl Env<()> for MatrixEnv<'_> {
    type Error = Infallible;

    fn rescore(
        &mut self,
        list: &mut Vec<Entry<()>>,
        query: &QuerySpec,
    ) -> Result<Vec<f64>, Infallible> {
        Ok(list
            .iter()
            .map(|e| (self.rescore)(self.q, e.at, query))
            .collect())
    }

    fn pairwise(&mut self, list: &mut Vec<Entry<()>>) -> Result<Vec<f64>, Infallible> {
        let items: Vec<usize> = std::iter::once(self.q)
            .chain(list.iter().map(|e| e.at))
            .collect();
        let m = items.len();
        // The stage reads the upper triangle only.
        let mut d = vec![0.0; m * m];
        for (a, &i) in items.iter().enumerate() {
            for (b, &j) in items.iter().enumerate().skip(a + 1) {
                d[a * m + b] = self.base[i * self.n + j];
            }
        }
        Ok(d)
    }

    fn gw(&mut self, list: &[Entry<()>], _: &SgwStage) -> Result<Vec<f64>, Infallible> {
        let q = self.q;
        Ok(list
            .iter()
            .map(|e| {
                self.gw
                    .and_then(|m| m.get(&(q.min(e.at), q.max(e.at))).copied())
                    .unwrap_or(f64::INFINITY)
            })
            .collect())
    }
}

/// Re-ranks every query row of `dist` (n × n, row = query; the shortlist is each row's best
/// `K`) with `stage`; see the module docs for the values written. `base` is the first stage's
/// dissimilarity matrix (the same as `dist` unless earlier stages re-ordered it): a reciprocal
/// stage compares the shortlist's members with it. `rescore(q, j, spec)` is the score of `j`
/// for query `q` under another query spec (an exact stage).
#[allow(clippy::too_many_arguments)]
pub fn rerank_matrix(
    base: &[f64],
    dist: &[f64],
    n: usize,
    included: &[bool],
    payloads: &[Option<GwPayload>],
    stage: &Stage,
    rescore: &(dyn Fn(usize, usize, &QuerySpec) -> f64 + Sync),
    solved_pairs: &mut PairCache,
) -> (Vec<f64>, RerankStats) {
    let k = stage.shortlist();
    let queries: Vec<usize> = (0..n).filter(|&i| included[i]).collect();
    let orders: Vec<Vec<usize>> = queries
        .par_iter()
        .map(|&q| metrics::rank(&dist[q * n..(q + 1) * n], q, Some(included)))
        .collect();
    let mut stats = RerankStats::default();
    let mut known: Option<&HashMap<(usize, usize), f64>> = None;
    if let Stage::SpectralGw(s) = stage {
        let (map, st) = solve_pairs(&queries, &orders, payloads, s, solved_pairs);
        stats = st;
        known = Some(map);
    }
    let t0 = Instant::now();
    let rows: Vec<(Vec<usize>, f64)> = queries
        .par_iter()
        .zip(&orders)
        .map(|(&q, order)| {
            let t = Instant::now();
            let list: Vec<Entry<()>> = order
                .iter()
                .take(k)
                .map(|&j| Entry {
                    at: j,
                    item: (),
                    score: dist[q * n + j],
                    stage_scores: vec![dist[q * n + j]],
                })
                .collect();
            let mut env = MatrixEnv {
                q,
                n,
                base,
                rescore,
                gw: known,
            };
            let out = match run(std::slice::from_ref(stage), list, &mut env) {
                Ok(v) => v,
                Err(never) => match never {},
            };
            (
                out.into_iter().map(|e| e.at).collect(),
                t.elapsed().as_secs_f64(),
            )
        })
        .collect();
    if known.is_none() {
        stats.wall_s = t0.elapsed().as_secs_f64();
        stats.per_query_ms = if rows.is_empty() {
            0.0
        } else {
            1e3 * rows.iter().map(|x| x.1).sum::<f64>() / rows.len() as f64
        };
    } else if stats.pairs > 0 {
        stats.per_query_ms = gw_latency(&queries, &orders, dist, n, payloads, stage, k);
    }
    let mut out = vec![f64::NAN; n * n];
    for ((&q, order), (r, _)) in queries.iter().zip(&orders).zip(&rows) {
        let row = &mut out[q * n..(q + 1) * n];
        for (rank, &j) in r.iter().enumerate() {
            row[j] = rank as f64;
        }
        for (pos, &j) in order.iter().enumerate().skip(k.min(order.len())) {
            row[j] = (k + pos) as f64;
        }
    }
    (out, stats)
}

/// Solves every (unordered) pair of a query and a shortlisted candidate not solved yet with the
/// same payload and solver options.
fn solve_pairs<'c>(
    queries: &[usize],
    orders: &[Vec<usize>],
    payloads: &[Option<GwPayload>],
    s: &SgwStage,
    solved_pairs: &'c mut PairCache,
) -> (&'c HashMap<(usize, usize), f64>, RerankStats) {
    let mut pairs: Vec<(usize, usize)> = Vec::new();
    for (qi, &q) in queries.iter().enumerate() {
        for &j in orders[qi].iter().take(s.shortlist) {
            pairs.push((q.min(j), q.max(j)));
        }
    }
    pairs.sort_unstable();
    pairs.dedup();
    let ckey = format!(
        "{}|{}",
        s.payload.key(),
        serde_json::to_string(&s.gw).unwrap_or_default()
    );
    let known = solved_pairs.entry(ckey).or_default();
    let todo: Vec<(usize, usize)> = pairs
        .iter()
        .copied()
        .filter(|p| !known.contains_key(p))
        .collect();
    let t0 = Instant::now();
    let solved: Vec<(f64, f64)> = todo
        .par_iter()
        .map(|&(a, b)| {
            let t = Instant::now();
            let v = match (&payloads[a], &payloads[b]) {
                (Some(x), Some(y)) => gw_score(x, y, &s.gw),
                _ => f64::INFINITY,
            };
            (v, t.elapsed().as_secs_f64())
        })
        .collect();
    let wall_s = t0.elapsed().as_secs_f64();
    let cpu: f64 = solved.iter().map(|x| x.1).sum();
    for (p, v) in todo.iter().zip(&solved) {
        known.insert(*p, v.0);
    }
    let stats = RerankStats {
        pairs: todo.len(),
        wall_s,
        per_candidate_ms: if todo.is_empty() {
            0.0
        } else {
            1e3 * cpu / todo.len() as f64
        },
        per_query_ms: 0.0,
    };
    (known, stats)
}

/// Wall latency of [`rerank_gw`] on up to 8 queries' shortlists (0 when nothing was solved).
fn gw_latency(
    queries: &[usize],
    orders: &[Vec<usize>],
    dist: &[f64],
    n: usize,
    payloads: &[Option<GwPayload>],
    stage: &Stage,
    k: usize,
) -> f64 {
    let Stage::SpectralGw(s) = stage else {
        return 0.0;
    };
    let mut lat = Vec::new();
    for (qi, &q) in queries.iter().enumerate().take(8) {
        let Some(qp) = &payloads[q] else { continue };
        let cands: Vec<Candidate<'_, usize>> = orders[qi]
            .iter()
            .take(k)
            .map(|&j| Candidate {
                id: j,
                score: dist[q * n + j],
                payload: payloads[j].as_ref(),
            })
            .collect();
        let t = Instant::now();
        let r = rerank_gw(s, qp, &cands);
        lat.push(t.elapsed().as_secs_f64());
        debug_assert_eq!(r.len(), cands.len());
    }
    if lat.is_empty() {
        0.0
    } else {
        1e3 * lat.iter().sum::<f64>() / lat.len() as f64
    }
}

/// One re-ranking stage over every query row ([`rerank_matrix`]), with the run's
/// payloads for the stage's payload spec.
#[allow(clippy::too_many_arguments)]
pub(super) fn apply_stage(
    st: &Stage,
    base: &[f64],
    cur: &[f64],
    n: usize,
    included: &[bool],
    payload_sets: &[(String, Vec<Option<crate::rerank::GwPayload>>)],
    rescore: &(dyn Fn(usize, usize, &QuerySpec) -> f64 + Sync),
    solved_pairs: &mut PairCache,
) -> (Vec<f64>, RerankStats) {
    let none = vec![None; n];
    let payloads = st
        .payload_spec()
        .and_then(|ps| payload_sets.iter().find(|(k, _)| *k == ps.key()))
        .map(|(_, p)| p)
        .filter(|p| !p.is_empty())
        .unwrap_or(&none);
    rerank_matrix(base, cur, n, included, payloads, st, rescore, solved_pairs)
}

/// The report's line about one re-ranking stage (also printed unless `quiet`).
pub(super) fn stage_note(name: &str, st: &Stage, stats: &RerankStats, quiet: bool) -> String {
    let line = match st {
        Stage::SpectralGw(_) => format!(
            "`{name}` ({}): {} newly solved pairs in {:.1} s wall; {:.2} ms CPU per GW solve; `rerank_gw` on one query's shortlist: {:.1} ms wall",
            st.label(),
            stats.pairs,
            stats.wall_s,
            stats.per_candidate_ms,
            stats.per_query_ms
        ),
        _ => format!(
            "`{name}` ({}): {:.1} s wall for every query; {:.2} ms per query's shortlist (one thread)",
            st.label(),
            stats.wall_s,
            stats.per_query_ms
        ),
    };
    if !quiet {
        eprintln!("eval: {line}");
    }
    format!("- {line}\n")
}
