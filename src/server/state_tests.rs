//! A delete that races an ingest or a search on the same node; a reconciliation that races an
//! ingest.

use super::state::SearchOptions;
use super::test_support::{ingest, meshes, upload, OnFaulty};
use std::sync::Arc;

/// Ids are sequential: a client can delete a shape while its upload is being stored. When the
/// delete reaches the store between the ingest's insert and its entry into the scan, the
/// shape must not enter the scan (before `App::writes`: it did, and stayed searchable after
/// the 204 until the node restarted, its GET answering 404).
#[test]
fn a_delete_between_an_ingests_store_insert_and_its_scan_entry_leaves_no_ghost() {
    let n = OnFaulty::start(2, |_| {});
    let (app, handle) = (n.app.clone(), n.rt.handle().clone());
    let deleted = Arc::new(std::sync::Mutex::new(None));
    let seen = deleted.clone();
    *n.faulty.after_insert.lock().unwrap() = Some(Arc::new(move |id: &str| {
        // The delete runs to its end (another thread, the node's own path) before the
        // ingest goes on.
        let (app, handle, id) = (app.clone(), handle.clone(), id.to_string());
        let ok = std::thread::spawn(move || handle.block_on(app.delete(id)))
            .join()
            .unwrap()
            .unwrap();
        *seen.lock().unwrap() = Some(ok);
    }));
    let id = ingest(&n.app, &n.rt, &meshes()[2], "raced");
    *n.faulty.after_insert.lock().unwrap() = None;
    assert_eq!(
        *deleted.lock().unwrap(),
        Some(true),
        "the delete found it stored"
    );
    assert!(n.app.block(n.store.get(&id)).unwrap().is_none());
    let scan = n.app.scan.read().unwrap();
    assert!(
        scan.position(&id).is_none(),
        "{id} is in the scan after its delete"
    );
    assert_eq!(scan.len(), 2);
}

/// A search by id whose stage reads the query's payload, after the shape's delete reached the
/// store and before it reached the scan: 404 `shape.not_found`, not 409 `shape.no_payload`
/// ("its original could not be analysed"), which is what it answered before.
#[test]
fn a_search_by_a_shape_deleted_from_the_store_is_not_found() {
    let n = OnFaulty::start(3, |_| {});
    let id = n.app.scan.read().unwrap().id(0).to_string();
    // The store's delete alone, as a concurrent delete leaves it until the scan's lock frees.
    assert!(n.app.block(n.store.delete(&id)).unwrap());
    let opts: SearchOptions = serde_json::from_value(serde_json::json!({
        "id": id, "top_k": 2, "rerank": [{"stage": "spectral_gw", "shortlist": 2}]
    }))
    .unwrap();
    let e = n.rt.block_on(n.app.search(opts, None, None)).unwrap_err();
    assert_eq!(
        (e.status.as_u16(), e.code.as_str()),
        (404, "shape.not_found"),
        "{}",
        e.detail
    );
}

/// A reconciliation that lists the store while a shape is being stored, and reads the scan
/// after that shape entered it, must not take the shape out of the scan: it was stored after
/// the listing, not deleted. (It read the scan after listing the store, and removed such a
/// shape until the change feed's insert or the next reconciliation: on a cluster node, right
/// after the ingest's 201 said it was searchable there.)
#[test]
fn a_reconciliation_keeps_a_shape_stored_while_it_listed_the_store() {
    let n = OnFaulty::start(2, |_| {});
    let (app, handle) = (n.app.clone(), n.rt.handle().clone());
    let stored = Arc::new(std::sync::Mutex::new(None));
    let seen = stored.clone();
    let once = std::sync::Mutex::new(Some(meshes()[2].clone()));
    *n.faulty.after_list.lock().unwrap() = Some(Arc::new(move || {
        let Some(mesh) = once.lock().unwrap().take() else {
            return;
        };
        // An ingest on this node runs to its end (store, then scan) after the page was read.
        let (app, handle) = (app.clone(), handle.clone());
        let r = std::thread::spawn(move || handle.block_on(app.ingest(upload(&mesh, "late"))))
            .join()
            .unwrap()
            .unwrap();
        *seen.lock().unwrap() = Some(r.id);
    }));
    n.rt.block_on(n.app.reconcile()).unwrap();
    *n.faulty.after_list.lock().unwrap() = None;
    let id = stored
        .lock()
        .unwrap()
        .clone()
        .expect("the ingest ran during the listing");
    assert!(n.app.block(n.store.get(&id)).unwrap().is_some());
    let scan = n.app.scan.read().unwrap();
    assert!(
        scan.position(&id).is_some(),
        "{id} is stored but was taken out of the scan"
    );
    assert_eq!(scan.len(), 3);
}

/// An insert that stored the shape and answered an error all the same (a flush that failed
/// after the commit; on PostgreSQL, a commit whose acknowledgement was lost): the ingest
/// answers 500 and the shape is not in the scan. The client's retry of the same bytes finds it
/// stored and must leave it searchable (it answered 200 `created: false` and the shape stayed
/// out of every search until the node restarted).
#[test]
fn a_retry_after_an_insert_that_stored_but_failed_makes_the_shape_searchable() {
    let n = OnFaulty::start(2, |_| {});
    let mesh = meshes()[3].clone();
    n.faulty
        .fail_after_insert
        .store(true, std::sync::atomic::Ordering::SeqCst);
    let e =
        n.rt.block_on(n.app.ingest(upload(&mesh, "stored-anyway")))
            .unwrap_err();
    n.faulty
        .fail_after_insert
        .store(false, std::sync::atomic::Ordering::SeqCst);
    assert_eq!(e.status.as_u16(), 500, "{}", e.detail);
    assert_eq!(
        n.app.scan.read().unwrap().len(),
        2,
        "the failed ingest's shape entered"
    );
    let r =
        n.rt.block_on(n.app.ingest(upload(&mesh, "stored-anyway")))
            .unwrap();
    assert!(!r.created, "the first attempt stored it");
    assert!(
        n.app.scan.read().unwrap().position(&r.id).is_some(),
        "{} is stored, answered 200, and is not in the scan",
        r.id
    );
    let opts: SearchOptions = serde_json::from_value(serde_json::json!({
        "id": r.id, "top_k": 2, "rerank": []
    }))
    .unwrap();
    let hits = n.rt.block_on(n.app.search(opts, None, None)).unwrap();
    assert_eq!(hits.candidates, 2, "the others, the query left out");
}
