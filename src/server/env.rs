//! The server's [`Env`] for the rerank stages of a search: what the stages read (the scan's
//! corpus, the stored re-ranking payloads), with the search's [`Cancel`] token checked before
//! each stage and before each GW candidate, so an abandoned search stops within one candidate
//! (≈ 40 ms of one core) instead of finishing its shortlist.

use super::admission::Cancel;
use super::problem::ApiError;
use super::state::{App, Hit, Hitting};
use crate::index::ScanIndex;
use crate::ranking::QuerySpec;
use crate::rerank::{gw_score, GwPayload, SgwStage};
use crate::search::corpus::{Encoded, Layout};
use crate::search::{Entry, Env, Query, ShapeRef};
use rayon::prelude::*;

/// The first `top_k` entries of a ranked list as the API's hits (rank from 1), all scored under
/// calibration `epoch`. One node's search and a sharded coordinator's answer alike.
pub(super) fn hits(mut list: Vec<Entry<Hitting>>, top_k: usize, epoch: u64) -> Vec<Hit> {
    list.truncate(top_k);
    list.into_iter()
        .enumerate()
        .map(|(r, e)| Hit {
            id: e.item.id,
            name: e.item.name,
            score: e.score,
            rank: r + 1,
            calibration_epoch: epoch,
            stage_scores: e.stage_scores,
        })
        .collect()
}

/// What the stages of a server search read: the scan (locked while a stage reads it, released
/// during GW solves, which take up to seconds and would hold back writers and the readers
/// queued behind them) and the store's payloads.
pub(super) struct ServerEnv<'a> {
    pub(super) app: &'a App,
    pub(super) scan: Option<std::sync::RwLockReadGuard<'a, ScanIndex>>,
    /// The query, encoded under the calibration of epoch `epoch`.
    pub(super) query: Encoded,
    /// The calibration epoch the search ranks under (the scan's when it began).
    pub(super) epoch: u64,
    pub(super) first: QuerySpec,
    pub(super) query_payload: Option<GwPayload>,
    /// The search's cancellation token.
    pub(super) cancel: Cancel,
}

impl ServerEnv<'_> {
    /// The scan, locked again after a stage that ran unlocked: positions may have moved, and
    /// shapes deleted meanwhile leave `list`. A new calibration installed meanwhile is 503
    /// `search.calibration_mismatch` with `Retry-After`: the rows are encoded under it and the
    /// query is not, and scores under two calibrations do not compare.
    fn relocked(&mut self, list: &mut Vec<Entry<Hitting>>) -> Result<&ScanIndex, ApiError> {
        if self.scan.is_none() {
            let guard = self.app.scan.read().unwrap_or_else(|p| p.into_inner());
            let now = guard
                .calibration()
                .map_or(0, |c| self.app.engine.calibration_epoch(c));
            if now != self.epoch {
                return Err(ApiError {
                    retry_after: Some(self.app.cfg.retry_after_secs),
                    ..ApiError::new(
                        axum::http::StatusCode::SERVICE_UNAVAILABLE,
                        "search.calibration_mismatch",
                        format!(
                            "the index installed calibration epoch {now} while this search \
                             (epoch {}) ran a spectral_gw stage; retry",
                            self.epoch
                        ),
                    )
                });
            }
            let s = self.scan.insert(guard);
            list.retain_mut(|e| match s.position(&e.item.id) {
                Some(at) => {
                    e.at = at;
                    true
                }
                None => false,
            });
        }
        Ok(self.scan.as_deref().expect("locked"))
    }
}

impl Env<Hitting> for ServerEnv<'_> {
    type Error = ApiError;

    fn rescore(
        &mut self,
        list: &mut Vec<Entry<Hitting>>,
        query: &QuerySpec,
    ) -> Result<Vec<f64>, ApiError> {
        self.cancel.check()?;
        let qv = self.query.clone();
        let s = self.relocked(list)?;
        let c = s.corpus();
        Ok(rescore(
            c.layout(),
            query,
            qv.view(),
            list.iter().map(|e| c.shape(e.at)),
        ))
    }

    fn pairwise(&mut self, list: &mut Vec<Entry<Hitting>>) -> Result<Vec<f64>, ApiError> {
        self.cancel.check()?;
        let qv = self.query.clone();
        let first = self.first.clone();
        let s = self.relocked(list)?;
        let c = s.corpus();
        Ok(pairwise(
            c.layout(),
            &first,
            qv.view(),
            list.iter().map(|e| c.shape(e.at)),
        ))
    }

    fn gw(&mut self, list: &[Entry<Hitting>], stage: &SgwStage) -> Result<Vec<f64>, ApiError> {
        self.cancel.check()?;
        self.scan = None;
        gw_scores(
            self.app,
            &self.cancel,
            self.query_payload.as_ref(),
            list,
            stage,
        )
    }
}

/// The scores of `shapes` against `query` under `spec` (an exact stage).
pub(super) fn rescore<'a>(
    layout: &Layout,
    spec: &QuerySpec,
    query: ShapeRef<'_>,
    shapes: impl Iterator<Item = ShapeRef<'a>>,
) -> Vec<f64> {
    let q = Query::new(spec, layout);
    shapes.map(|b| q.score(layout, query, b)).collect()
}

/// The first stage's dissimilarities between the query (item 0) and `shapes` (items `1..`):
/// the strict upper triangle of a row-major `(n + 1)²` matrix (a reciprocal stage).
pub(super) fn pairwise<'a>(
    layout: &Layout,
    first: &QuerySpec,
    query: ShapeRef<'a>,
    shapes: impl Iterator<Item = ShapeRef<'a>>,
) -> Vec<f64> {
    let q = Query::new(first, layout);
    // The query and the candidates, each pair once (the upper triangle).
    let items: Vec<ShapeRef<'_>> = std::iter::once(query).chain(shapes).collect();
    let m = items.len();
    let rows: Vec<Vec<f64>> = (0..m)
        .into_par_iter()
        .map(|a| {
            items[a + 1..]
                .iter()
                .map(|&b| q.score(layout, items[a], b))
                .collect()
        })
        .collect();
    let mut d = vec![0.0; m * m];
    for (a, row) in rows.iter().enumerate() {
        d[a * m + a + 1..(a + 1) * m].copy_from_slice(row);
    }
    d
}

/// The GW scores of `list` against the query's payload, each candidate's payload read from the
/// store (∞ where it has none), stopping once `cancel` trips.
pub(super) fn gw_scores(
    app: &App,
    cancel: &Cancel,
    query_payload: Option<&GwPayload>,
    list: &[Entry<Hitting>],
    stage: &SgwStage,
) -> Result<Vec<f64>, ApiError> {
    let Some(qp) = query_payload else {
        return Err(ApiError::internal("no query payload"));
    };
    // Each candidate reads its payload and solves its GW problem only while the search is
    // wanted: an abandoned search stops after the candidates already started.
    let scores: Vec<Result<f64, ApiError>> = list
        .par_iter()
        .map(|e| {
            if cancel.is_cancelled() {
                cancel.note_skipped();
                return Ok(f64::NAN);
            }
            Ok(match app.stored_payload(&e.item.id)? {
                Some(p) => gw_score(qp, &p, &stage.gw),
                None => f64::INFINITY,
            })
        })
        .collect();
    cancel.check()?;
    scores.into_iter().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::test_support::wait_idle;
    use crate::server::test_support::{ingest, meshes, node, runtime, served_epoch, sled_store};
    use std::sync::Arc;

    /// A stage that reads the scan after a GW stage released it: under the search's own
    /// calibration it scores the shortlist; under one installed meanwhile it answers 503
    /// `search.calibration_mismatch` (the query would be compared under another calibration
    /// than the rows).
    #[test]
    fn a_stage_after_gw_refuses_a_calibration_installed_meanwhile() {
        let dir = tempfile::tempdir().unwrap();
        let rt = runtime();
        let store = sled_store(dir.path(), &rt);
        let app = Arc::new(node(dir.path(), &store, &rt));
        for (i, m) in meshes().iter().enumerate() {
            ingest(&app, &rt, m, &format!("s{i}"));
            wait_idle(&app);
        }
        let epoch = served_epoch(&app);
        let query = app.scan.read().unwrap().corpus().encoded(0);
        let shortlist = || -> Vec<Entry<Hitting>> {
            let s = app.scan.read().unwrap();
            (1..4)
                .map(|at| Entry {
                    at,
                    item: Hitting {
                        id: s.id(at).to_string(),
                        name: s.name(at).to_string(),
                    },
                    score: 0.0,
                    stage_scores: vec![0.0],
                })
                .collect()
        };
        let spec = app.engine.default_query();
        let env = |epoch: u64| ServerEnv {
            app: &app,
            scan: None, // as after a GW stage
            query: query.clone(),
            epoch,
            first: spec.clone(),
            query_payload: None,
            cancel: Cancel::never(),
        };
        let scores = env(epoch).rescore(&mut shortlist(), &spec).unwrap();
        assert_eq!(scores.len(), 3);
        assert!(scores.iter().all(|s| s.is_finite()));
        for older in [epoch - 1, 0] {
            let e = env(older).rescore(&mut shortlist(), &spec).unwrap_err();
            assert_eq!(e.status, axum::http::StatusCode::SERVICE_UNAVAILABLE);
            assert_eq!(e.code, "search.calibration_mismatch");
            assert_eq!(e.retry_after, Some(app.cfg.retry_after_secs));
            let e = env(older).pairwise(&mut shortlist()).unwrap_err();
            assert_eq!(e.code, "search.calibration_mismatch");
        }
    }
}
