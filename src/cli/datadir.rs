//! Checks a data directory before a command writes to it, so that an unwritable one (a
//! root-owned bind mount under the container's uid 10001, a read-only volume) fails with its
//! path, who owns it and what to do, instead of sled's bare `Permission denied`.

use super::CliError;
use std::io::ErrorKind;
use std::path::Path;

/// The uid the container image runs as (docker/Dockerfile).
pub const CONTAINER_UID: u32 = 10001;

/// Makes sure `dir` (created when missing, with its parents) and its `db` folder, if present,
/// accept new files. The error names the directory, the process's uid and the directory's
/// owner, and says how to fix the ownership.
pub fn ensure_writable(dir: &Path) -> Result<(), CliError> {
    if let Err(e) = std::fs::create_dir_all(dir) {
        return Err(unwritable(dir, &e));
    }
    probe(dir)?;
    let db = dir.join("db");
    if db.is_dir() {
        probe(&db)?;
    }
    Ok(())
}

/// Creates and removes a probe file in `dir`.
fn probe(dir: &Path) -> Result<(), CliError> {
    let file = dir.join(format!(".shapeseek-write-probe-{}", std::process::id()));
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&file)
    {
        Ok(f) => {
            drop(f);
            let _ = std::fs::remove_file(&file);
            Ok(())
        }
        // A leftover probe of an earlier process with the same pid: the directory is writable.
        Err(e) if e.kind() == ErrorKind::AlreadyExists => {
            let _ = std::fs::remove_file(&file);
            Ok(())
        }
        Err(e) => Err(unwritable(dir, &e)),
    }
}

fn unwritable(dir: &Path, e: &std::io::Error) -> CliError {
    let mut msg = format!(
        "data directory {} is not writable: {}",
        dir.display(),
        super::io_reason(e)
    );
    if e.kind() == ErrorKind::PermissionDenied || e.kind() == ErrorKind::ReadOnlyFilesystem {
        if let Some(who) = ownership(dir) {
            msg.push_str(&format!(" ({who})"));
        }
        msg.push_str(&format!(
            ". Give the directory to the user that runs shapeseek, e.g. for the container image \
             (uid {CONTAINER_UID}): `chown -R {CONTAINER_UID}:{CONTAINER_UID} DIR` on the host \
             (rootless podman: `podman unshare chown -R {CONTAINER_UID}:{CONTAINER_UID} DIR`), \
             or choose another directory with --data / SHAPESEEK_DATA"
        ));
    }
    CliError::new("io.data_dir", msg, 74)
}

/// "running as uid U; DIR belongs to uid O, mode M" where known.
#[cfg(unix)]
fn ownership(dir: &Path) -> Option<String> {
    use std::os::unix::fs::MetadataExt;
    let me = std::fs::metadata("/proc/self").ok().map(|m| m.uid());
    // The nearest existing ancestor tells who may create things in it.
    let existing = dir.ancestors().find(|p| p.exists())?;
    let m = std::fs::metadata(existing).ok()?;
    let mut s = String::new();
    if let Some(uid) = me {
        s.push_str(&format!("running as uid {uid}; "));
    }
    s.push_str(&format!(
        "{} belongs to uid {}, mode {:o}",
        existing.display(),
        m.uid(),
        m.mode() & 0o7777
    ));
    Some(s)
}

#[cfg(not(unix))]
fn ownership(_dir: &Path) -> Option<String> {
    None
}
