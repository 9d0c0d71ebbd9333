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

/// Upgrade steps, in order. Version 1 is the first on-disk format, so there is none yet; a
/// version-2 format adds `Step { from: 1, .. }` and `migrations/0002_*.md`.
pub const STEPS: &[Step] = &[];

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
