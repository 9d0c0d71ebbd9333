//! The order of a shape's change in the store and in this node's scan ([`App::writes`]).
//!
//! An ingest stores a shape and then adds it to the scan; a delete removes it from the store
//! and then from the scan. Ids are sequential, so a client can delete a shape while its upload
//! is being stored: when the delete ran between the ingest's two steps, the shape entered the
//! scan after the delete had left it, and stayed searchable after the 204, its GET 404, until
//! the node restarted (found by an outside review). The change feed's inserts and deletes on a
//! cluster node race the same way.
//!
//! So both second steps run under one lock, and a delete that finds the shape absent from the
//! scan leaves a tombstone there: the insert that comes after it finds the tombstone and adds
//! nothing. No store read is made under the lock (a store that failed there would leave a
//! stored shape out of the scan for good on a node without reconciliation). A delete's two
//! steps run in a task of their own, so a request dropped between them (the client gone, the
//! request's deadline) cannot separate them.

use super::problem::ApiError;
use super::state::App;
use crate::index::ScanIndex;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long a tombstone is kept: far longer than an ingest takes from its store insert to its
/// scan entry (a lock and the scan's write lock), short enough that deletes of shapes that
/// never enter the scan do not pile up.
const TOMBSTONE_TTL: Duration = Duration::from_secs(600);

/// Ids deleted while absent from the scan, with when.
#[derive(Default)]
pub(super) struct Tombstones(HashMap<String, Instant>);

impl Tombstones {
    fn bury(&mut self, id: String) {
        let now = Instant::now();
        self.0
            .retain(|_, at| now.duration_since(*at) < TOMBSTONE_TTL);
        self.0.insert(id, now);
    }

    /// Whether `id` was deleted before it entered the scan (the tombstone is taken).
    fn dug_up(&mut self, id: &str) -> bool {
        self.0.remove(id).is_some()
    }
}

impl App {
    /// Runs `enter` on the scan to add the stored shape `id`, unless it was deleted meanwhile
    /// (false). On a blocking thread (not an async worker).
    pub(super) fn enter_scan(&self, id: &str, enter: impl FnOnce(&mut ScanIndex)) -> bool {
        let mut graves = self.writes.blocking_lock();
        if graves.dug_up(id) {
            return false;
        }
        enter(&mut self.scan.write().unwrap_or_else(|p| p.into_inner()));
        true
    }

    /// Deletes `id` from the store (when `from_store`; else another node did) and then from the
    /// scan, a tombstone left when it was not there yet. Answers (in the store, in the scan):
    /// `(true, _)` without `from_store`.
    pub(super) async fn remove_shape(
        self: &Arc<Self>,
        id: &str,
        from_store: bool,
    ) -> Result<(bool, bool), ApiError> {
        let (app, id) = (self.clone(), id.to_string());
        tokio::spawn(async move {
            let mut graves = app.writes.clone().lock_owned().await;
            let stored = !from_store || app.store.delete(&id).await.map_err(ApiError::from)?;
            let scan = app.clone();
            // The scan's write lock may wait for a running search: not on an async worker.
            let held = tokio::task::spawn_blocking(move || {
                let held = scan
                    .scan
                    .write()
                    .unwrap_or_else(|p| p.into_inner())
                    .remove(&id);
                if stored && !held {
                    graves.bury(id);
                }
                held
            })
            .await
            .map_err(ApiError::internal)?;
            Ok((stored, held))
        })
        .await
        .map_err(ApiError::internal)?
    }
}
