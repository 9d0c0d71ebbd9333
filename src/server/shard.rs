//! A sharded serving node (`serve --shard S/N`, with `--store postgres://…` and
//! `--queue nats://…`): its scan holds only the shapes of shard `S` (`id mod N == S`), it
//! answers the first stage of other nodes' searches for its shard, and it answers its own
//! `/v1/search` by fanning out to every shard (protocol: [`crate::queue::shard`]).
//!
//! * **Replica of a shard**: loading, the change feed and reconciliation keep the shard's
//!   shapes only (`App::foreign_change`, `src/server/load.rs`, `src/server/cluster.rs`).
//!   Several nodes may serve one shard: the queue group lets one of them answer each request.
//! * **Calibration stays global**: a sharded node decides and computes recalibrations on the
//!   whole stored corpus — its size is the store's count, the calibration is computed from the
//!   calibration sample of every stored shape (`src/server/sample.rs`: all of them up to
//!   `calibration_sample`, in id order — what a single node holding everything computes) under
//!   the store's lock, and every node installs the stored epoch. A shard answers only when its
//!   calibration is the coordinator's (epoch and fingerprint), so scores are comparable.
//! * **Coordinator** (`App::sharded_search`): the query is encoded once under this node's
//!   calibration (an upload's signature, or a stored shape's signature read from the store),
//!   sent to every shard with the first stage's spec and `k = max(top_k, largest shortlist)`;
//!   the local top-`k`s are merged by `(score, id)` — a single node's scan orders ties by
//!   position, which is id order — and the rerank stages run here on the candidates'
//!   encodings returned by the shards (`ShardEnv`), GW payloads read from the store.
//! * **Failures**: a shard that does not answer completely within `shard_timeout_secs` (or the
//!   request's deadline) → 503 `search.shard_unavailable` naming it, with `Retry-After`; a
//!   shard under another calibration epoch → retried every 50 ms (this node first installs a
//!   newer stored epoch), then 503 `search.calibration_mismatch`; a shard that fails (busy,
//!   not ready) → its status and code. Never a partial answer.

use super::admission::{Cancel, Cost};
use super::env::{gw_scores, pairwise, rescore};
use super::ms;
use super::problem::ApiError;
use super::state::{App, Hitting, SearchOptions, SearchPlan, SearchResult};
use crate::index::ScanIndex;
use crate::queue::shard::{
    answer_messages, decode_request, encode_reply, fingerprint, id_number, scatter, send_reply,
    subscribe, Candidate, Reply, ScatterError, SearchRequest, ShardAnswer, ShardSpec,
};
use crate::ranking::QuerySpec;
use crate::rerank::{GwPayload, SgwStage};
use crate::search::corpus::{Encoded, Layout};
use crate::search::{Entry, Env, Query};
use axum::http::StatusCode;
use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Pause between two attempts of a search whose shards are at another calibration epoch.
const RETRY_PAUSE: Duration = Duration::from_millis(50);

/// The shard a node holds, and the size of the whole corpus (the store's count, refreshed on
/// every change and reconciliation; recalibration decisions compare with it).
#[derive(Debug)]
pub struct Sharding {
    /// Which shard.
    pub spec: ShardSpec,
    total: AtomicUsize,
}

impl Sharding {
    /// A node of shard `spec` (corpus size unknown yet).
    pub fn new(spec: ShardSpec) -> Sharding {
        Sharding {
            spec,
            total: AtomicUsize::new(0),
        }
    }

    /// Shapes in the whole corpus, as last read from the store.
    pub fn total(&self) -> usize {
        self.total.load(Ordering::Acquire)
    }

    pub(super) fn set_total(&self, n: usize) {
        self.total.store(n, Ordering::Release);
    }
}

/// The tie-break key of a candidate: its id's number (ids are fixed-width hex counters, so this
/// is the id order, which is a single node's scan position order).
fn tie_key(id: &str) -> usize {
    id_number(id).map_or(usize::MAX, |n| n as usize)
}

fn unavailable(detail: String, retry_after: u64) -> ApiError {
    ApiError {
        retry_after: Some(retry_after),
        ..ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "search.shard_unavailable",
            detail,
        )
    }
}

impl App {
    /// This node's shard, when it holds one.
    pub fn shard(&self) -> Option<&Sharding> {
        self.shard.as_ref()
    }

    /// The corpus size calibration is decided on: the whole store's for a sharded node, the
    /// scan's otherwise.
    pub(super) fn corpus_size(&self, s: &ScanIndex) -> usize {
        match self.shard() {
            Some(sh) => sh.total(),
            None => s.len(),
        }
    }

    /// True when the calibration no longer fits the corpus (see [`App::corpus_size`]).
    pub(super) fn calibration_due(&self, s: &ScanIndex) -> bool {
        match self.shard() {
            None => s.needs_recalibration(self.cfg.recalibrate_fraction),
            Some(sh) => {
                let n = sh.total();
                n > 0
                    && (s.calibration().is_none()
                        || super::load::moved(s.calibrated_on(), n, self.cfg.recalibrate_fraction))
            }
        }
    }

    /// Before a change of `id` is applied on a sharded node: the corpus size is read again
    /// from the store, a scan without calibration installs the stored one, and a shape of
    /// another shard is only counted (true: nothing else to apply). False on a node without
    /// shards.
    pub(super) async fn foreign_change(self: &Arc<Self>, id: &str) -> Result<bool, ApiError> {
        let Some(sh) = self.shard() else {
            return Ok(false);
        };
        let n = self.store.count().await.map_err(ApiError::from)?;
        sh.set_total(n as usize);
        if sh.spec.holds(id) {
            let uncalibrated = self
                .scan
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .calibration()
                .is_none();
            if uncalibrated {
                self.adopt_stored_calibration().await?;
            }
            return Ok(false);
        }
        self.after_change();
        Ok(true)
    }

    /// Subscribes this node to its shard's search requests and answers them in the background.
    pub(super) async fn start_shard_responder(self: &Arc<Self>) -> crate::Result<()> {
        let (Some(sh), Some(cl)) = (self.shard(), self.cluster()) else {
            return Ok(());
        };
        let client = cl.bus.client().clone();
        let mut sub = subscribe(&client, sh.spec).await?;
        tracing::info!(shard = %sh.spec, "answering shard search requests");
        let app = self.clone();
        tokio::spawn(async move {
            use futures_util::StreamExt;
            while let Some(msg) = sub.next().await {
                let (app, client) = (app.clone(), client.clone());
                tokio::spawn(async move {
                    let Some(reply) = msg.reply.clone() else {
                        return;
                    };
                    let out = app.answer_shard_request(&msg.payload).await;
                    if let Err(e) = send_reply(&client, reply, out).await {
                        tracing::warn!(error = %e, "could not answer a shard request");
                    }
                });
            }
            tracing::error!("the shard request subscription ended");
        });
        Ok(())
    }

    /// This shard's answer to a coordinator's request (reply messages).
    async fn answer_shard_request(self: &Arc<Self>, payload: &[u8]) -> Vec<Vec<u8>> {
        let spec = self.shard().map(|s| s.spec).expect("a sharded node");
        let fail = |status: StatusCode, code: &str, message: String| {
            vec![encode_reply(&Reply::Failed {
                shard: spec.index,
                status: status.as_u16(),
                code: code.into(),
                message,
            })]
        };
        let (req, query) = match decode_request(payload) {
            Ok(r) => r,
            Err(e) => return fail(StatusCode::BAD_REQUEST, "request.invalid", e.to_string()),
        };
        if req.shard_count != spec.count {
            return fail(
                StatusCode::CONFLICT,
                "search.shard_layout",
                format!(
                    "this node holds shard {spec}; the coordinator fans out over {} shards",
                    req.shard_count
                ),
            );
        }
        if !self.ready.load(Ordering::Acquire) {
            return fail(
                StatusCode::SERVICE_UNAVAILABLE,
                "server.not_ready",
                format!("shard {spec} is not ready"),
            );
        }
        if let Err(e) = self.engine.validate_query(&req.spec) {
            return fail(StatusCode::BAD_REQUEST, "request.invalid", e.to_string());
        }
        // A budget past what the clock can represent is no deadline (the message may say any).
        let deadline = Instant::now().checked_add(Duration::from_millis(req.budget_ms));
        let n = self.scan.read().unwrap_or_else(|p| p.into_inner()).len();
        let app = self.clone();
        let res = self
            .admission
            .run(Cost::search(n, &[]), deadline, move |cancel| {
                let guard = app.scan.read().unwrap_or_else(|p| p.into_inner());
                let s = &*guard;
                let Some(cal) = s.calibration() else {
                    return Ok(Err(0));
                };
                if cal.epoch != req.epoch || fingerprint(cal) != req.fingerprint {
                    return Ok(Err(cal.epoch));
                }
                let layout = s.corpus().layout();
                if !layout.fits(&query) {
                    return Err(ApiError::invalid(
                        "the query's encoding does not fit the layout",
                    ));
                }
                let exclude = req.exclude.as_deref().and_then(|id| s.position(id));
                let filter = s.tag_filter(&req.tags);
                let keep = |at: usize| Some(at) != exclude && s.has_tags(at, &filter);
                let matched = (0..s.len()).filter(|&at| keep(at)).count() as u64;
                cancel.check()?;
                let q = Query::new(&req.spec, layout);
                let hits: Vec<Candidate> = s
                    .rank(&query, &q, req.k, &keep)
                    .into_iter()
                    .map(|sc| Candidate {
                        score: sc.score,
                        id: s.id(sc.at).to_string(),
                        name: s.name(sc.at).to_string(),
                        encoded: s.corpus().encoded(sc.at),
                    })
                    .collect();
                Ok(Ok((matched, hits)))
            })
            .await;
        match res {
            Ok(Ok((matched, hits))) => answer_messages(spec.index, matched, hits),
            Ok(Err(epoch)) => vec![encode_reply(&Reply::Mismatch {
                shard: spec.index,
                epoch,
            })],
            Err(e) => fail(e.status, &e.code, e.detail),
        }
    }

    /// A search answered by fanning out to every shard (see the module docs); the same
    /// options, answers and hits as [`App::search`] on a node holding the whole corpus.
    pub(super) async fn sharded_search(
        self: &Arc<Self>,
        opts: SearchOptions,
        plan: SearchPlan,
        deadline: Option<Instant>,
    ) -> Result<SearchResult, ApiError> {
        let (Some(sh), Some(cl)) = (self.shard(), self.cluster()) else {
            return Err(ApiError::internal("a sharded search without shards"));
        };
        let SearchPlan {
            top_k,
            first_k,
            spec,
            stages,
            needs_payload,
            query_sig,
            upload_payload,
            report,
        } = plan;
        // The query's signature: the upload's, or the stored one (what its shard holds encoded).
        let sig = match (query_sig, &opts.id) {
            (Some(s), _) => s,
            (None, Some(id)) => {
                let b = self
                    .store
                    .signature(id)
                    .await
                    .map_err(ApiError::from)?
                    .ok_or_else(|| ApiError::not_found(id))?;
                self.engine.decode_signature(&b)?
            }
            (None, None) => return Err(ApiError::internal("a search without a query")),
        };
        let query_payload = match (upload_payload, &opts.id) {
            _ if !needs_payload => None,
            (Some(p), _) => Some(p),
            (None, Some(id)) => Some(self.query_payload(id).await?),
            (None, None) => None,
        };
        let exclude = if opts.include_self {
            None
        } else {
            opts.id.clone()
        };
        let wait = Instant::now() + Duration::from_secs_f64(self.cfg.shard_timeout_secs);
        let until = deadline.map_or(wait, |d| d.min(wait));
        let retry_after = self.cfg.retry_after_secs;
        let t1 = Instant::now();
        let (cal, query, answers) = loop {
            let cal = self
                .scan
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .calibration()
                .cloned();
            let Some(cal) = cal else {
                if let Some(id) = &opts.id {
                    return Err(ApiError::not_found(id));
                }
                return Ok(report.empty());
            };
            let layout = Layout::of(&cal);
            let query = Encoded::from_signature(&sig, &cal, &layout);
            let req = SearchRequest {
                shard_count: sh.spec.count,
                spec: spec.clone(),
                k: first_k,
                tags: opts.tags.clone(),
                exclude: exclude.clone(),
                epoch: cal.epoch,
                fingerprint: fingerprint(&cal),
                budget_ms: until.saturating_duration_since(Instant::now()).as_millis() as u64,
            };
            let answers = match scatter(cl.bus.client(), &req, &query, until).await {
                Ok(a) => a,
                Err(ScatterError::Unavailable(missing)) => {
                    let names: Vec<String> = missing
                        .iter()
                        .map(|s| format!("{s}/{}", sh.spec.count))
                        .collect();
                    return Err(unavailable(
                        format!(
                            "shard {} did not answer within {:.1} s; no partial answer is given",
                            names.join(", "),
                            until.saturating_duration_since(t1).as_secs_f64()
                        ),
                        retry_after,
                    ));
                }
                Err(ScatterError::Nats(m)) => return Err(unavailable(m, retry_after)),
            };
            for (s, a) in answers.iter().enumerate() {
                if let ShardAnswer::Failed(status, code, message) = a {
                    let status =
                        StatusCode::from_u16(*status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
                    return Err(ApiError {
                        retry_after: (status == StatusCode::SERVICE_UNAVAILABLE)
                            .then_some(retry_after),
                        ..ApiError::new(
                            status,
                            code.clone(),
                            format!("shard {s}/{}: {message}", sh.spec.count),
                        )
                    });
                }
            }
            let other = answers
                .iter()
                .filter_map(|a| match a {
                    ShardAnswer::Mismatch(e) => Some(*e),
                    _ => None,
                })
                .max();
            let Some(other) = other else {
                break (cal, query, answers);
            };
            let late = || Instant::now() + RETRY_PAUSE >= until;
            if other > cal.epoch && !late() {
                // Within the request's deadline: installing re-encodes the node's shard (it
                // goes on in the background past it).
                self.adopt_until(until).await?;
            }
            if late() {
                return Err(ApiError {
                    retry_after: Some(retry_after),
                    ..ApiError::new(
                        StatusCode::SERVICE_UNAVAILABLE,
                        "search.calibration_mismatch",
                        format!(
                            "the shards have not all installed calibration epoch {} (one is \
                             at {other}); retry shortly",
                            cal.epoch
                        ),
                    )
                });
            }
            tokio::time::sleep(RETRY_PAUSE).await;
        };
        let mut candidates = 0usize;
        let mut merged: Vec<Candidate> = Vec::new();
        for a in answers {
            if let ShardAnswer::Ranked { hits, matched } = a {
                candidates += matched as usize;
                merged.extend(hits);
            }
        }
        let merged = merge_exact(merged, first_k);
        let scan_ms = ms(t1);
        let app = self.clone();
        let epoch = cal.epoch;
        let cost = Cost::search(merged.len(), &stages);
        let (hits, rerank_ms) = self
            .admission
            .run(cost, deadline, move |cancel| -> Result<_, ApiError> {
                let t2 = Instant::now();
                let mut encoded = HashMap::with_capacity(merged.len());
                let list: Vec<Entry<Hitting>> = merged
                    .into_iter()
                    .map(|c| {
                        let at = tie_key(&c.id);
                        encoded.insert(at, c.encoded);
                        Entry {
                            at,
                            item: Hitting {
                                id: c.id,
                                name: c.name,
                            },
                            score: c.score,
                            stage_scores: vec![c.score],
                        }
                    })
                    .collect();
                let mut env = ShardEnv {
                    app: &app,
                    layout: Layout::of(&cal),
                    query,
                    first: spec,
                    query_payload,
                    cancel: cancel.clone(),
                    encoded,
                };
                let list = crate::search::run(&stages, list, &mut env)?;
                Ok((super::env::hits(list, top_k, epoch), ms(t2)))
            })
            .await?;
        Ok(report.finish(hits, epoch, candidates, scan_ms, rerank_ms))
    }
}

/// The global top `k` of the shards' local top `k`s: ordered by `(score, id)`, as a single
/// node's scan orders `(score, position)` (position order is id order).
pub(super) fn merge_exact(mut all: Vec<Candidate>, k: usize) -> Vec<Candidate> {
    all.sort_by(|a, b| {
        a.score
            .total_cmp(&b.score)
            .then_with(|| tie_key(&a.id).cmp(&tie_key(&b.id)))
            .then_with(|| a.id.cmp(&b.id))
    });
    all.truncate(k);
    all
}

/// What the rerank stages of a sharded search read: the candidates' encodings as the shards
/// returned them (keyed by [`Entry::at`], the id's number) and the store's payloads; the
/// scoring is [`super::env`]'s, shared with the single-node [`super::env::ServerEnv`].
pub(super) struct ShardEnv<'a> {
    app: &'a App,
    layout: Layout,
    query: Encoded,
    first: QuerySpec,
    query_payload: Option<GwPayload>,
    cancel: Cancel,
    encoded: HashMap<usize, Encoded>,
}

impl Env<Hitting> for ShardEnv<'_> {
    type Error = ApiError;

    fn rescore(
        &mut self,
        list: &mut Vec<Entry<Hitting>>,
        query: &QuerySpec,
    ) -> Result<Vec<f64>, ApiError> {
        self.cancel.check()?;
        let enc = &self.encoded;
        Ok(rescore(
            &self.layout,
            query,
            self.query.view(),
            list.iter().map(|e| enc[&e.at].view()),
        ))
    }

    fn pairwise(&mut self, list: &mut Vec<Entry<Hitting>>) -> Result<Vec<f64>, ApiError> {
        self.cancel.check()?;
        let enc = &self.encoded;
        Ok(pairwise(
            &self.layout,
            &self.first,
            self.query.view(),
            list.iter().map(|e| enc[&e.at].view()),
        ))
    }

    fn gw(&mut self, list: &[Entry<Hitting>], stage: &SgwStage) -> Result<Vec<f64>, ApiError> {
        self.cancel.check()?;
        gw_scores(
            self.app,
            &self.cancel,
            self.query_payload.as_ref(),
            list,
            stage,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ranking::{Calibration, Dissimilarity};
    use crate::search::corpus::quantise;
    use crate::signature::Aggregation;

    fn cal() -> Arc<Calibration> {
        Arc::new(Calibration {
            epoch: 3,
            spec_key: String::new(),
            channel_names: vec!["a".into()],
            window_max: vec![1.0],
            bins: 8,
            bandwidth_bins: 1.0,
            percentile: 0.95,
            shapes: 0,
        })
    }

    /// One of five distinct histograms: many shapes score alike (ties).
    fn shape(layout: &Layout, i: u64) -> Encoded {
        let mut e = Encoded::absent(layout);
        let prob: Vec<f64> = (0..8)
            .map(|b| 1.0 + ((b as u64 * (i % 5)) % 7) as f64)
            .collect();
        e.shift[0] = quantise(&prob, &mut e.hist[..8]);
        e.mass[0] = 1.0;
        e.present[0] = true;
        e.fill_groups(layout);
        e
    }

    /// Ids of different magnitudes, as 16 hex digits: string order is numeric order, so a
    /// single node's scan position order (sorted ids) is the id order the merge breaks ties by.
    fn ids() -> Vec<String> {
        let mut v: Vec<u64> = (0..60u64).map(|i| i * i * 977 + (i << 36)).collect();
        v.sort();
        v.into_iter().map(|n| format!("{n:016x}")).collect()
    }

    fn index(ids: &[&String]) -> ScanIndex {
        let c = cal();
        let layout = Layout::of(&c);
        let mut s = ScanIndex::with_capacity(c, 0, ids.len());
        for id in ids {
            let n = id_number(id).unwrap();
            s.push_encoded(id, &format!("m{n}"), &[], &shape(&layout, n));
        }
        s
    }

    #[test]
    fn a_shard_needs_a_postgres_store_and_a_queue() {
        use crate::server::ServerConfig;
        let cfg = |shard: &str, store: &str, queue: &str| ServerConfig {
            shard: shard.into(),
            store: store.into(),
            queue: queue.into(),
            ..ServerConfig::default()
        };
        let (pg, nats) = ("postgres://u@h/db", "nats://h:4222");
        assert!(cfg("", "", "").validate().is_ok());
        assert_eq!(cfg("", "", "").shard_spec(), None);
        let ok = cfg("1/2", pg, nats);
        assert!(ok.validate().is_ok());
        assert_eq!(ok.shard_spec(), Some(ShardSpec { index: 1, count: 2 }));
        for (shard, store, queue) in [
            ("0/2", "", ""),
            ("0/2", pg, ""),
            ("0/2", "", nats),
            ("2/2", pg, nats),
            ("x", pg, nats),
        ] {
            let e = cfg(shard, store, queue).validate().unwrap_err().to_string();
            // (a queue without a store is refused by the queue's own check first)
            assert!(
                e.contains("shard") || e.contains("queue needs"),
                "{shard} {store} {queue}: {e}"
            );
        }
    }

    #[test]
    fn position_order_is_id_order() {
        let ids = ids();
        let mut by_string = ids.clone();
        by_string.sort();
        let mut by_number = ids.clone();
        by_number.sort_by_key(|id| tie_key(id));
        assert_eq!(by_string, by_number);
        let s = index(&ids.iter().collect::<Vec<_>>());
        for (at, id) in ids.iter().enumerate() {
            assert_eq!(s.position(id), Some(at));
        }
    }

    /// The merge of the shards' local top-k's is the single scan's top-k, ties included, for
    /// every k and shard count, with and without an excluded shape.
    #[test]
    fn merged_shard_top_k_is_the_single_scan_top_k() {
        let ids = ids();
        let whole = index(&ids.iter().collect::<Vec<_>>());
        let layout = whole.corpus().layout().clone();
        let spec = QuerySpec {
            channels: vec!["a".into()],
            dissimilarity: Dissimilarity::L1,
            aggregation: Aggregation::Single,
            alternate_margin: crate::ranking::DEFAULT_ALTERNATE_MARGIN,
        };
        let q = Query::new(&spec, &layout);
        for count in [1u32, 2, 3, 7] {
            let shards: Vec<ScanIndex> = (0..count)
                .map(|s| {
                    let spec = ShardSpec { index: s, count };
                    index(&ids.iter().filter(|id| spec.holds(id)).collect::<Vec<_>>())
                })
                .collect();
            for (qi, exclude) in [(0u64, None), (3, Some(&ids[7])), (4, Some(&ids[0]))] {
                let query = shape(&layout, qi);
                for k in [1, 5, 13, 60, 100] {
                    let ex = exclude.and_then(|id| whole.position(id));
                    let want: Vec<(String, u64)> = whole
                        .rank(&query, &q, k, &|at| Some(at) != ex)
                        .into_iter()
                        .map(|sc| (whole.id(sc.at).to_string(), sc.score.to_bits()))
                        .collect();
                    let mut all = Vec::new();
                    for s in &shards {
                        let ex = exclude.and_then(|id| s.position(id));
                        all.extend(s.rank(&query, &q, k, &|at| Some(at) != ex).into_iter().map(
                            |sc| Candidate {
                                score: sc.score,
                                id: s.id(sc.at).to_string(),
                                name: s.name(sc.at).to_string(),
                                encoded: s.corpus().encoded(sc.at),
                            },
                        ));
                    }
                    let got: Vec<(String, u64)> = merge_exact(all, k)
                        .into_iter()
                        .map(|c| (c.id, c.score.to_bits()))
                        .collect();
                    assert_eq!(got, want, "{count} shards, k = {k}, query {qi}");
                    let scores: Vec<u64> = want.iter().map(|w| w.1).collect();
                    let mut distinct = scores.clone();
                    distinct.dedup();
                    if k >= 13 {
                        assert!(distinct.len() < scores.len(), "the case has ties");
                    }
                }
            }
        }
    }
}
