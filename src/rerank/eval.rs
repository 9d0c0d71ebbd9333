//! `shapeseek eval --rerank STAGE`: re-ranks each query's top `K` of a first-stage
//! configuration and evaluates the result as an extra configuration named `<config>+<STAGE>`.
//!
//! STAGE syntax: `none`, a JSON object / JSON file holding a [`RerankStage`], or the short form
//! `sgw:K[:key=value]…` with keys `m` (samples, default 100), `t` (comma-separated times,
//! default 0.016,0.04,0.1), `metric` (`dist` | `kernel`), `rule` (`abs` | `lambda1`: `t = τ/λ₁`),
//! `eps` (relative ε, default 0.003), `outer` (outer iterations, default 5), `blend` (weight
//! `w` of the first-stage rank in [`Fusion::RankBlend`]; absent: GW alone); or
//! `recip:K[:key=value]…` ([`ReciprocalStage`]) with keys `k` (comma-separated neighbourhood
//! sizes, default 8,16,32), `expand` (default 4) and `lambda` (default 0.1).
//!
//! Payloads are cached under `<cache>/gw/` keyed by the analysis key and
//! [`PayloadSpec::key`], so only the first run of a payload spec pays for it.
//!
//! Row values after re-ranking: the re-ranked top `K` get `0, 1, …, K−1`, the rest
//! `K + first-stage position`. AP and per-query ROC only depend on each query's order, so they
//! are exact; the pooled EER of such a run compares ranks, not distances.

use super::{
    fuse, gw_score, Fusion, GwMetric, GwPayload, PayloadSpec, ReciprocalStage, RerankStage,
    SgwStage, TimeRule,
};
use crate::eval::cache::{hash_parts, unwrap_envelope, wrap_envelope, write_atomic, Cache};
use crate::eval::manifest::Manifest;
use crate::eval::metrics;
use crate::mesh::read::{read_mesh, Format, ReadLimits};
use crate::spectrum::{analyze, AnalyzeOptions};
use crate::{Error, Result};
use rayon::prelude::*;
use std::collections::HashMap;
use std::time::Instant;

const PAYLOAD_MAGIC: &[u8; 8] = b"SSGWPL01";

/// Parses a `--rerank` value (see the module docs).
pub fn parse_stage(s: &str) -> Result<RerankStage> {
    let st = parse_stage_unchecked(s)?;
    st.validate()
        .map_err(|m| Error::InvalidArgument(format!("--rerank {s}: {m}")))?;
    Ok(st)
}

fn parse_stage_unchecked(s: &str) -> Result<RerankStage> {
    let bad = |m: String| Error::InvalidArgument(format!("--rerank {s}: {m}"));
    let t = s.trim();
    if t == "none" {
        return Ok(RerankStage::None);
    }
    if t.starts_with('{') {
        return serde_json::from_str(t).map_err(|e| bad(e.to_string()));
    }
    let p = std::path::Path::new(t);
    if p.is_file() {
        let text = std::fs::read_to_string(p)?;
        return serde_json::from_str(&text).map_err(|e| bad(e.to_string()));
    }
    let mut parts = t.split(':');
    let kind = parts.next();
    if kind == Some("recip") {
        return parse_reciprocal(parts).map_err(bad);
    }
    if kind != Some("sgw") {
        return Err(bad(
            "expected none, a JSON stage, sgw:K[:key=value]... or recip:K[:key=value]...".into(),
        ));
    }
    let k: usize = parts
        .next()
        .ok_or_else(|| bad("missing K".into()))?
        .parse()
        .map_err(|_| bad("K must be an integer".into()))?;
    let mut st = SgwStage {
        shortlist: k,
        ..SgwStage::default()
    };
    for kv in parts {
        let (key, val) = kv
            .split_once('=')
            .ok_or_else(|| bad(format!("'{kv}' is not key=value")))?;
        let num = |v: &str| {
            v.parse::<f64>()
                .map_err(|_| bad(format!("{key}: not a number")))
        };
        match key {
            "m" => st.payload.samples = num(val)? as usize,
            "t" => st.payload.times = val.split(',').map(num).collect::<Result<Vec<_>>>()?,
            "metric" => {
                st.payload.metric = match val {
                    "dist" | "diffusion" => GwMetric::Diffusion,
                    "kernel" | "heat" => GwMetric::HeatKernel,
                    _ => return Err(bad(format!("metric {val}"))),
                }
            }
            "rule" => {
                st.payload.time_rule = match val {
                    "abs" | "absolute" => TimeRule::Absolute,
                    "lambda1" => TimeRule::Lambda1,
                    _ => return Err(bad(format!("rule {val}"))),
                }
            }
            "eps" => st.gw.eps_rel = num(val)?,
            "outer" => st.gw.outer_iterations = num(val)? as usize,
            "blend" => st.fusion = Fusion::RankBlend { weight: num(val)? },
            _ => return Err(bad(format!("unknown key {key}"))),
        }
    }
    Ok(RerankStage::SpectralGw(st))
}

/// `recip:K[:k=a,b,..][:expand=e][:lambda=l]` after the `recip` word.
fn parse_reciprocal<'a>(
    mut parts: impl Iterator<Item = &'a str>,
) -> std::result::Result<RerankStage, String> {
    let mut st = ReciprocalStage {
        shortlist: parts
            .next()
            .ok_or("missing K")?
            .parse()
            .map_err(|_| "K must be an integer")?,
        ..ReciprocalStage::default()
    };
    for kv in parts {
        let (key, val) = kv
            .split_once('=')
            .ok_or_else(|| format!("'{kv}' is not key=value"))?;
        let int = |v: &str| {
            v.parse::<usize>()
                .map_err(|_| format!("{key}: not an integer"))
        };
        match key {
            "k" => st.neighbourhoods = val.split(',').map(int).collect::<Result<_, _>>()?,
            "expand" => st.expansion = int(val)?,
            "lambda" => {
                st.original_weight = val.parse().map_err(|_| format!("{key}: not a number"))?
            }
            _ => return Err(format!("unknown key {key}")),
        }
    }
    Ok(RerankStage::Reciprocal(st))
}

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
            let pl = super::compute_payload(&analysis, spec).ok()?;
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
    /// Wall time of all solves.
    pub wall_s: f64,
    /// Mean CPU time of one GW solve (ms; sum of per-solve times / pairs).
    pub per_candidate_ms: f64,
    /// Mean wall time of [`super::apply`] on one query's shortlist (ms), measured on up to 8
    /// queries with every worker thread.
    pub per_query_ms: f64,
}

/// The reciprocal stage on every query: the shortlist's mutual dissimilarities are read from
/// `base` (what the server computes with the first stage's scorer).
fn reciprocal_matrix(
    base: &[f64],
    n: usize,
    queries: &[usize],
    orders: &[Vec<usize>],
    stage: &ReciprocalStage,
) -> (Vec<f64>, RerankStats) {
    let k = stage.shortlist;
    let t0 = Instant::now();
    let rows: Vec<(Vec<(usize, f64)>, f64)> = queries
        .par_iter()
        .zip(orders)
        .map(|(&q, order)| {
            let t = Instant::now();
            let items: Vec<usize> = std::iter::once(q)
                .chain(order.iter().take(k).copied())
                .collect();
            let m = items.len();
            // The stage reads the upper triangle only.
            let mut d = vec![0.0; m * m];
            for (a, &i) in items.iter().enumerate() {
                for (b, &j) in items.iter().enumerate().skip(a + 1) {
                    d[a * m + b] = base[i * n + j];
                }
            }
            let r = super::reciprocal::rerank(&d, m, stage);
            (r, t.elapsed().as_secs_f64())
        })
        .collect();
    let wall_s = t0.elapsed().as_secs_f64();
    let mut out = vec![f64::NAN; n * n];
    for ((&q, order), (r, _)) in queries.iter().zip(orders).zip(&rows) {
        let row = &mut out[q * n..(q + 1) * n];
        for (rank, &(i, _)) in r.iter().enumerate() {
            row[order[i]] = rank as f64;
        }
        for (pos, &j) in order.iter().enumerate().skip(r.len()) {
            row[j] = (k + pos) as f64;
        }
    }
    let per_query_ms = if rows.is_empty() {
        0.0
    } else {
        1e3 * rows.iter().map(|x| x.1).sum::<f64>() / rows.len() as f64
    };
    (
        out,
        RerankStats {
            pairs: 0,
            wall_s,
            per_candidate_ms: 0.0,
            per_query_ms,
        },
    )
}

/// GW values of solved (unordered) pairs, per payload key and solver options.
pub type PairCache = HashMap<String, HashMap<(usize, usize), f64>>;

/// Re-ranks every query row of `dist` (n × n, row = query; the shortlist is each row's best `K`)
/// with `stage`; see the module docs for the values written. `base` is the first stage's
/// dissimilarity matrix (the same as `dist` unless earlier stages re-ordered it): a reciprocal
/// stage compares the shortlist's members with it.
pub fn rerank_matrix(
    base: &[f64],
    dist: &[f64],
    n: usize,
    included: &[bool],
    payloads: &[Option<GwPayload>],
    stage: &RerankStage,
    solved_pairs: &mut PairCache,
) -> (Vec<f64>, RerankStats) {
    let k = stage.shortlist_len();
    let queries: Vec<usize> = (0..n).filter(|&i| included[i]).collect();
    let orders: Vec<Vec<usize>> = queries
        .par_iter()
        .map(|&q| metrics::rank(&dist[q * n..(q + 1) * n], q, Some(included)))
        .collect();
    let s: &SgwStage = match stage {
        RerankStage::None => return (dist.to_vec(), RerankStats::default()),
        RerankStage::SpectralGw(s) => s,
        RerankStage::Reciprocal(r) => return reciprocal_matrix(base, n, &queries, &orders, r),
    };
    let mut pairs: Vec<(usize, usize)> = Vec::new();
    for (qi, &q) in queries.iter().enumerate() {
        for &j in orders[qi].iter().take(k) {
            pairs.push((q.min(j), q.max(j)));
        }
    }
    pairs.sort_unstable();
    pairs.dedup();
    // Pairs already solved with the same payload and solver options (another stage of this
    // run that differs only in K or fusion) are reused.
    let ckey = format!(
        "{}|{}",
        s.payload.key(),
        serde_json::to_string(&s.gw).unwrap_or_default()
    );
    let known = solved_pairs.entry(ckey.clone()).or_default();
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
    let map = &*known;
    let mut out = vec![f64::NAN; n * n];
    for (qi, &q) in queries.iter().enumerate() {
        let order = &orders[qi];
        let top = &order[..k.min(order.len())];
        let gw: Vec<f64> = top.iter().map(|&j| map[&(q.min(j), q.max(j))]).collect();
        let row = &mut out[q * n..(q + 1) * n];
        for (r, (i, _)) in fuse(&gw, s.fusion).into_iter().enumerate() {
            row[top[i]] = r as f64;
        }
        for (pos, &j) in order.iter().enumerate().skip(top.len()) {
            row[j] = (k + pos) as f64;
        }
    }
    // Wall latency of the public entry point on a few queries.
    let mut lat = Vec::new();
    for (qi, &q) in queries
        .iter()
        .enumerate()
        .take(if todo.is_empty() { 0 } else { 8 })
    {
        let Some(qp) = &payloads[q] else { continue };
        let cands: Vec<super::Candidate<'_, usize>> = orders[qi]
            .iter()
            .take(k)
            .map(|&j| super::Candidate {
                id: j,
                score: dist[q * n + j],
                payload: payloads[j].as_ref(),
            })
            .collect();
        let t = Instant::now();
        let r = super::apply(stage, qp, &cands);
        lat.push(t.elapsed().as_secs_f64());
        debug_assert_eq!(r.len(), cands.len());
    }
    let per_query_ms = if lat.is_empty() {
        0.0
    } else {
        1e3 * lat.iter().sum::<f64>() / lat.len() as f64
    };
    (
        out,
        RerankStats {
            pairs: todo.len(),
            wall_s,
            per_candidate_ms: if todo.is_empty() {
                0.0
            } else {
                1e3 * cpu / todo.len() as f64
            },
            per_query_ms,
        },
    )
}
