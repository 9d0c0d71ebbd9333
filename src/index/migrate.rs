//! The migrations runner: upgrades an index directory to [`SCHEMA_VERSION`] after a backup.
//!
//! One file per on-disk schema version lives in `migrations/` (`0001_initial.md`, ...) and says
//! what the version holds and how to upgrade to it. Each upgrade step `vN → vN+1` is a function
//! in [`STEPS`]; the runner copies the index to a backup first, applies the steps in order,
//! stamps the new version and flushes. A newer or unknown version is refused and the directory is
//! left untouched; so is a directory that holds no index (a mistyped `--data` must not create
//! one).
//!
//! Backups live inside the data directory, in `DATA/backups/<UTC time>-v<N>/` (see
//! [`BACKUPS_DIR`]): a container's data volume then keeps them (its parent is not writable and
//! not persistent), and sled, which only opens `DATA/db`, never reads them.

use super::store::{
    open_db, put_chunked, read_schema_version, storage_err, MESH_CHUNKS, PAYLOAD_CHUNKS,
    SCHEMA_VERSION, SIGNATURE_CHUNKS,
};
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
pub const STEPS: &[Step] = &[
    Step {
        from: 1,
        description: "adds the `payloads` tree: the spectral Gromov–Wasserstein payload of every \
                      stored shape, computed from its stored original",
        apply: add_payloads,
    },
    Step {
        from: 2,
        description: "stores signatures, originals and payloads in pieces of at most 4 KB \
                      (trees `signature_chunks`, `mesh_chunks`, `payload_chunks`), so that \
                      sled's cache bounds a node's memory",
        apply: chunk_values,
    },
];

/// Version 2 → 3: every value of `signatures`, `meshes` and `payloads` is written, byte for
/// byte, as a chunked value of `signature_chunks`, `mesh_chunks` and `payload_chunks`
/// (`super::store`'s module docs), then the old tree is dropped. A tree is converted only while
/// its old tree still holds values (its new tree is cleared first), so a step cut short by a
/// crash converts again what it had not finished and leaves a finished tree alone.
fn chunk_values(db: &sled::Db) -> Result<()> {
    // The shapes' count for the progress lines (`len` reads a tree through: the records, not
    // the large values).
    let shapes = db.open_tree("shapes").map_err(storage_err)?.len();
    for (old, new) in [
        ("signatures", SIGNATURE_CHUNKS),
        ("meshes", MESH_CHUNKS),
        ("payloads", PAYLOAD_CHUNKS),
    ] {
        let from = db.open_tree(old).map_err(storage_err)?;
        let to = db.open_tree(new).map_err(storage_err)?;
        if from.is_empty() {
            continue;
        }
        to.clear().map_err(storage_err)?;
        let mut done = 0usize;
        for entry in from.iter() {
            let (key, value) = entry.map_err(storage_err)?;
            let res: std::result::Result<(), sled::transaction::TransactionError<()>> =
                to.transaction(|t| put_chunked(t, &key, &value));
            res.map_err(|e| storage_err(format!("{e:?}")))?;
            done += 1;
            if done % 1000 == 0 {
                eprintln!("{old}: {done} values in pieces (of at most {shapes})");
            }
        }
        eprintln!("{old}: all {done} values in pieces");
        db.flush().map_err(storage_err)?;
        db.drop_tree(old).map_err(storage_err)?;
        db.flush().map_err(storage_err)?;
    }
    Ok(())
}

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
    // Indexes of schema 1 predate the vertex budget: their signatures were computed at full
    // resolution, and the payloads added here must describe the same meshes.
    options.prepare.max_vertices = None;
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
                .map_err(|e| Error::corrupt("shape record", Some(&id), e.to_string()))?;
            let orig = meshes
                .get(&key)
                .map_err(storage_err)?
                .ok_or_else(|| Error::corrupt("shape record", Some(&id), "no stored original"))?;
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

/// The folder of the data directory that holds migration backups (never opened by sled).
pub const BACKUPS_DIR: &str = "backups";

/// What [`migrate`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum MigrateOutcome {
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
/// nothing, when `dir` holds no index, when the version is newer than this build or has no
/// upgrade path, or when the index is in use by a running server (sled's lock).
pub fn migrate(dir: &Path) -> Result<MigrateOutcome> {
    migrate_with(dir, STEPS, SCHEMA_VERSION)
}

/// [`migrate`] with an explicit step list and target version (the runner itself; tests use
/// it with their own steps).
pub fn migrate_with(dir: &Path, steps: &[Step], target: u32) -> Result<MigrateOutcome> {
    let db_path = dir.join("db");
    let no_index = |why: &str| {
        Error::InvalidArgument(format!(
            "{}: {why}, so there is nothing to migrate (check --data / SHAPESEEK_DATA; \
             `shapeseek serve` creates a new index)",
            dir.display()
        ))
    };
    if !dir.is_dir() {
        return Err(no_index("no such directory"));
    }
    if !db_path.join("conf").is_file() {
        return Err(no_index(
            "not a shapeseek data directory (it has no db/conf)",
        ));
    }
    let found = {
        let db = open_db(&db_path)?;
        read_schema_version(&db)?
    };
    let Some(from) = found else {
        return Err(no_index("the database in db/ has no schema version"));
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

/// Copies everything in `dir` but its [`BACKUPS_DIR`] to a new `DIR/backups/<UTC time>-v<N>/`
/// and returns its path. A failed copy is removed again; the error names the path it is about.
pub fn backup_dir(dir: &Path, version: u32) -> Result<PathBuf> {
    let root = dir.join(BACKUPS_DIR);
    std::fs::create_dir_all(&root).map_err(|e| io_at(&root, "cannot create", e))?;
    let stamp = utc_stamp(super::store::now_unix_ms());
    let mut target = root.join(format!("{stamp}-v{version}"));
    let mut n = 1;
    loop {
        match std::fs::create_dir(&target) {
            Ok(()) => break,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && n < 100 => {
                n += 1;
                target = root.join(format!("{stamp}-v{version}-{n}"));
            }
            Err(e) => return Err(io_at(&target, "cannot create", e)),
        }
    }
    let copied = (|| -> Result<()> {
        for entry in std::fs::read_dir(dir).map_err(|e| io_at(dir, "cannot read", e))? {
            let entry = entry.map_err(|e| io_at(dir, "cannot read", e))?;
            if entry.file_name() == BACKUPS_DIR {
                continue;
            }
            copy_entry(&entry, &target.join(entry.file_name()))?;
        }
        Ok(())
    })();
    if let Err(e) = copied {
        let _ = std::fs::remove_dir_all(&target);
        return Err(e);
    }
    Ok(target)
}

/// An I/O error that names its path (and keeps its kind).
fn io_at(path: &Path, what: &str, e: std::io::Error) -> Error {
    Error::Io(std::io::Error::new(
        e.kind(),
        format!("{what} {}: {e}", path.display()),
    ))
}

fn copy_entry(entry: &std::fs::DirEntry, dest: &Path) -> Result<()> {
    let src = entry.path();
    let ty = entry
        .file_type()
        .map_err(|e| io_at(&src, "cannot stat", e))?;
    if ty.is_dir() {
        copy_tree(&src, dest)
    } else if ty.is_file() {
        std::fs::copy(&src, dest)
            .map(drop)
            .map_err(|e| io_at(dest, &format!("cannot copy {} to", src.display()), e))
    } else {
        Ok(())
    }
}

fn copy_tree(from: &Path, to: &Path) -> Result<()> {
    std::fs::create_dir_all(to).map_err(|e| io_at(to, "cannot create", e))?;
    for entry in std::fs::read_dir(from).map_err(|e| io_at(from, "cannot read", e))? {
        let entry = entry.map_err(|e| io_at(from, "cannot read", e))?;
        copy_entry(&entry, &to.join(entry.file_name()))?;
    }
    Ok(())
}

/// `YYYYMMDDTHHMMSS.mmmZ` of Unix milliseconds (UTC, proleptic Gregorian calendar).
pub fn utc_stamp(unix_ms: u64) -> String {
    let secs = unix_ms / 1000;
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}{month:02}{day:02}T{:02}{:02}{:02}.{:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        unix_ms % 1000
    )
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

#[cfg(test)]
mod tests {
    use super::utc_stamp;

    #[test]
    fn utc_stamps() {
        assert_eq!(utc_stamp(0), "19700101T000000.000Z");
        assert_eq!(utc_stamp(951_782_400_000), "20000229T000000.000Z");
        assert_eq!(utc_stamp(1_796_140_212_345), "20261201T155012.345Z");
    }
}
