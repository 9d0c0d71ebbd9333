//! What the server's unit tests share: a small engine, a runtime, a node on a given store,
//! uploads of generated meshes.

use super::config::ServerConfig;
use super::state::{App, Upload};
use crate::index::{default_engine, Engine};
use crate::mesh::generate::{bumpy_sphere, bumpy_torus, icosphere, torus};
use crate::mesh::read::Format;
use crate::mesh::write::write_mesh;
use crate::mesh::Mesh;
use crate::storage::faulty::Faulty;
use crate::storage::ShapeStore;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Eigenpairs per shape (the default signature's ShapeDNA channel needs 50 non-zero ones).
pub const K: usize = 60;

/// The product engine with [`K`] eigenpairs.
pub fn engine() -> Engine {
    let mut e = default_engine();
    e.analyze.eigen.k = K;
    e
}

/// A runtime for the store's futures ([`App::block`] runs them on it).
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// A sled store in `dir`.
pub fn sled_store(dir: &std::path::Path, rt: &tokio::runtime::Runtime) -> Arc<dyn ShapeStore> {
    rt.block_on(crate::storage::open_dir(dir.to_path_buf()))
        .unwrap()
}

/// A node loaded from `store` with the default configuration (two workers, [`K`]).
pub fn node(
    dir: &std::path::Path,
    store: &Arc<dyn ShapeStore>,
    rt: &tokio::runtime::Runtime,
) -> App {
    node_with(dir, store, rt, |_| {})
}

/// [`node`] with the configuration changed by `tweak`.
pub fn node_with(
    dir: &std::path::Path,
    store: &Arc<dyn ShapeStore>,
    rt: &tokio::runtime::Runtime,
    tweak: impl FnOnce(&mut ServerConfig),
) -> App {
    let mut cfg = ServerConfig {
        data: dir.to_path_buf(),
        workers: 2,
        eigenpairs: K,
        ..ServerConfig::default()
    };
    tweak(&mut cfg);
    App::load(cfg, engine(), store.clone(), rt.handle().clone()).unwrap()
}

/// Six small, distinct shapes.
pub fn meshes() -> Vec<Mesh> {
    vec![
        icosphere(3),
        bumpy_sphere(3, 0.05),
        bumpy_sphere(3, 0.1),
        torus(1.0, 0.3, 40, 16),
        torus(1.0, 0.45, 40, 16),
        bumpy_torus(40, 16),
    ]
}

/// The upload of `mesh` as OBJ, named `name`.
pub fn upload(mesh: &Mesh, name: &str) -> Upload {
    let mut bytes = Vec::new();
    write_mesh(mesh, Format::Obj, &mut bytes).unwrap();
    Upload {
        bytes: bytes.into(),
        hint: Some(Format::Obj),
        name: Some(name.to_string()),
        tags: Vec::new(),
    }
}

/// Ingests `mesh` as an OBJ upload named `name` (a new shape).
pub fn ingest(app: &Arc<App>, rt: &tokio::runtime::Runtime, mesh: &Mesh, name: &str) -> String {
    let r = rt.block_on(app.ingest(upload(mesh, name))).unwrap();
    assert!(r.created);
    r.id
}

/// Waits until no recalibration runs (at most 2 min).
pub fn wait_idle(app: &App) {
    let t0 = Instant::now();
    while app.recalibrating.load(Ordering::Acquire) {
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "recalibration did not end"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The calibration epoch of `app`'s scan (0 without one).
pub fn served_epoch(app: &App) -> u64 {
    let scan = app.scan.read().unwrap();
    scan.calibration()
        .map_or(0, |c| app.engine.calibration_epoch(c))
}

/// A node (configured by `tweak`) on a sled store behind [`Faulty`] (a store that fails on
/// demand), holding the first `count` of [`meshes`] (named `s0`, `s1`, …) under a committed
/// calibration.
pub struct OnFaulty {
    pub app: Arc<App>,
    pub store: Arc<dyn ShapeStore>,
    pub faulty: Arc<Faulty>,
    pub rt: tokio::runtime::Runtime,
    pub dir: tempfile::TempDir,
}

impl OnFaulty {
    pub fn start(count: usize, tweak: impl FnOnce(&mut ServerConfig)) -> OnFaulty {
        let dir = tempfile::tempdir().unwrap();
        let rt = runtime();
        let faulty = Arc::new(Faulty::new(sled_store(dir.path(), &rt)));
        let store: Arc<dyn ShapeStore> = faulty.clone();
        let app = Arc::new(node_with(dir.path(), &store, &rt, tweak));
        for (i, m) in meshes()[..count].iter().enumerate() {
            ingest(&app, &rt, m, &format!("s{i}"));
            wait_idle(&app);
        }
        OnFaulty {
            app,
            store,
            faulty,
            rt,
            dir,
        }
    }

    /// The store's calibration.
    pub fn stored(&self) -> crate::storage::StoredCalibration {
        self.app.block(self.store.calibration()).unwrap().unwrap()
    }
}
