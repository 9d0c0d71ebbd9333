//! The migrations runner: upgrades an index directory to [`SCHEMA_VERSION`] after a backup.
//!
//! One file per on-disk schema version lives in `migrations/` (`0001_initial.md`, ...) and says
//! what the version holds and how to upgrade to it. Each upgrade step `vN → vN+1` is a function
//! in [`STEPS`]; the runner copies the whole data directory to a backup first, applies the steps
//! in order, stamps the new version and flushes. A newer or unknown version is refused and the
//! directory is left untouched.

use super::store::{open_db, read_schema_version, storage_err, Store, SCHEMA_VERSION};
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// One upgrade step: from version `from` to `from + 1`, applied to an open database.
pub struct Step {
    /// The version the step upgrades from.
    pub from: u32,
    /// What it does (printed by `shapeseek migrate`).
    pub description: &'static str,
    /// The upgrade itself.
    pub apply: fn(&sled::Db) -> Result<()>,
}

/// Upgrade steps, in order (`migrations/000N_*.md` describes version N).
pub const STEPS: &[Step] = &[Step {
    from: 1,
    description: "adds the `payloads` tree: the spectral Gromov–Wasserstein payload of every \
                  stored shape, computed from its stored original",
    apply: add_payloads,
}];

/// Version 1 → 2: computes the re-ranking payload ([`PayloadSpec::default`], the one the
/// server computes at ingest) of every shape from its stored original, with the product
/// engine's analysis options and the index's eigenpair count (the `-k<N>` suffix of
/// `meta/spec_key`, as version 1 documents it). A shape whose original cannot be analysed is
/// left without a payload (a spectral-GW stage ranks it after the scored ones) and reported
/// on stderr.
fn add_payloads(db: &sled::Db) -> Result<()> {
    use crate::mesh::read::{read_mesh, Format, ReadLimits};
    use crate::rerank::{compute_payload, PayloadSpec};
    let shapes = db.open_tree("shapes").map_err(storage_err)?;
    let meshes = db.open_tree("meshes").map_err(storage_err)?;
    let payloads = db.open_tree("payloads").map_err(storage_err)?;
    let mut options = crate::index::default_engine().analyze_options();
    let meta = db.open_tree("meta").map_err(storage_err)?;
    if let Some(key) = meta.get("spec_key").map_err(storage_err)? {
        let key = String::from_utf8_lossy(&key).into_owned();
        if let Some(k) = key.rsplit_once("-k").and_then(|(_, k)| k.parse().ok()) {
            options.eigen.k = k;
        }
    }
    let spec = PayloadSpec::default();
    let total = shapes.len();
    let (mut done, mut failed) = (0usize, 0usize);
    for entry in shapes.iter() {
        let (key, rec) = entry.map_err(storage_err)?;
        let id = String::from_utf8_lossy(&key).into_owned();
        let payload = (|| -> Result<Vec<u8>> {
            let rec: super::ShapeRecord = serde_json::from_slice(&rec)
                .map_err(|e| Error::InvalidArgument(format!("record: {e}")))?;
            let orig = meshes
                .get(&key)
                .map_err(storage_err)?
                .ok_or_else(|| Error::InvalidArgument("no stored original".into()))?;
            let mesh = read_mesh(
                &orig,
                Format::from_extension(&rec.format),
                &ReadLimits::unlimited(),
            )?;
            let analysis = crate::spectrum::analyze(&mesh, &options)?;
            Ok(compute_payload(&analysis, &spec)?.to_bytes())
        })();
        match payload {
            Ok(p) => {
                payloads.insert(&key, p).map_err(storage_err)?;
            }
            Err(e) => {
                failed += 1;
                eprintln!("shape {id}: no payload ({e})");
            }
        }
        done += 1;
        if done % 50 == 0 || done == total {
            eprintln!("payloads: {done}/{total}");
        }
    }
    if failed > 0 {
        eprintln!("payloads: {failed} of {total} shapes left without one");
    }
    Ok(())
}

/// What [`migrate`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum MigrateOutcome {
    /// The directory held no index: a new one was created at this version.
    Created(u32),
    /// Already at the current version: nothing done.
    UpToDate(u32),
    /// Upgraded; the original directory was copied to `backup` first.
    Upgraded {
        /// Version found.
        from: u32,
        /// Version written.
        to: u32,
        /// Where the untouched copy is.
        backup: PathBuf,
    },
}

/// Brings the index in `dir` to [`SCHEMA_VERSION`] (see the module docs). Fails, changing
/// nothing, when the version is newer than this build or has no upgrade path, or when the
/// index is in use by a running server (sled's lock).
pub fn migrate(dir: &Path) -> Result<MigrateOutcome> {
    migrate_with(dir, STEPS, SCHEMA_VERSION)
}

/// [`migrate`] with an explicit step list and target version (the runner itself; tests use
/// it with their own steps).
pub fn migrate_with(dir: &Path, steps: &[Step], target: u32) -> Result<MigrateOutcome> {
    let db_path = dir.join("db");
    if !db_path.exists() {
        Store::open(dir)?;
        return Ok(MigrateOutcome::Created(SCHEMA_VERSION));
    }
    let found = {
        let db = open_db(&db_path)?;
        read_schema_version(&db)?
    };
    let Some(from) = found else {
        Store::open(dir)?;
        return Ok(MigrateOutcome::Created(SCHEMA_VERSION));
    };
    if from == target {
        return Ok(MigrateOutcome::UpToDate(from));
    }
    if from > target {
        return Err(Error::InvalidArgument(format!(
            "index at {} has schema version {from}, newer than this build's {target}: \
             refusing to touch it (use a newer shapeseek)",
            dir.display()
        )));
    }
    // Check the whole path exists before touching anything.
    let mut v = from;
    let mut plan = Vec::new();
    while v < target {
        let step = steps.iter().find(|s| s.from == v).ok_or_else(|| {
            Error::InvalidArgument(format!(
                "index at {} has schema version {from}: no upgrade path from version {v} \
                 (known steps: {:?}); refusing",
                dir.display(),
                steps.iter().map(|s| s.from).collect::<Vec<_>>()
            ))
        })?;
        plan.push(step);
        v += 1;
    }
    let backup = backup_dir(dir, from)?;
    let db = open_db(&db_path)?;
    for step in plan {
        (step.apply)(&db)?;
        let meta = db.open_tree("meta").map_err(storage_err)?;
        meta.insert("schema_version", &(step.from + 1).to_be_bytes())
            .map_err(storage_err)?;
        db.flush().map_err(storage_err)?;
    }
    Ok(MigrateOutcome::Upgraded {
        from,
        to: target,
        backup,
    })
}

/// Copies `dir` to a new sibling `DIR.backup-vN-UNIXMS` and returns its path.
pub fn backup_dir(dir: &Path, version: u32) -> Result<PathBuf> {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "shapeseek-data".into());
    let target = dir.with_file_name(format!(
        "{name}.backup-v{version}-{}",
        super::store::now_unix_ms()
    ));
    copy_tree(dir, &target)?;
    Ok(target)
}

fn copy_tree(from: &Path, to: &Path) -> Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let ty = entry.file_type()?;
        let dest = to.join(entry.file_name());
        if ty.is_dir() {
            copy_tree(&entry.path(), &dest)?;
        } else if ty.is_file() {
            std::fs::copy(entry.path(), &dest)?;
        }
    }
    Ok(())
}

/// Writes a schema version into an index directory (for tests of the refusal paths and for
/// hand repairs). Creates the database if needed.
pub fn stamp_version(dir: &Path, version: u32) -> Result<()> {
    let db = open_db(&dir.join("db"))?;
    db.open_tree("meta")
        .map_err(storage_err)?
        .insert("schema_version", &version.to_be_bytes())
        .map_err(storage_err)?;
    db.flush().map_err(storage_err)?;
    Ok(())
}
