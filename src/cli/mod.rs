//! Subcommands of the `shapeseek` binary whose flags are not the library's: `eval` (options and
//! the stage grammar), `ingest` and `search` (collections and servers), and the checks the other commands share (files named in errors, data directories
//! that must be writable).

pub mod datadir;
pub mod eval;
mod http;
pub mod ingest;
pub mod search;
pub mod worker;

use std::fmt;
use std::path::Path;

/// A command-line failure: a stable code (the library's, the server's problem code, or one of
/// the CLI's: `io`, `server.unreachable`, `ingest.failed`), a message that names the path or URL
/// it is about, and the process exit status.
#[derive(Debug)]
pub struct CliError {
    /// Stable machine-readable code.
    pub code: String,
    /// What went wrong, for humans.
    pub message: String,
    /// Exit status (65 data or usage, 69 service unavailable, 74 I/O, 1 some inputs failed).
    pub exit: u8,
}

impl CliError {
    /// A new error.
    pub fn new(code: impl Into<String>, message: impl Into<String>, exit: u8) -> Self {
        Self {
            code: code.into(),
            message: message.into(),
            exit,
        }
    }

    /// `request.invalid` (exit 65): a bad argument.
    pub fn usage(message: impl Into<String>) -> Self {
        Self::new("request.invalid", message, 65)
    }

    /// A library error about `path`: the message starts with the path.
    pub fn at(path: &Path, e: shapeseek::Error) -> Self {
        let mut err = CliError::from(e);
        err.message = format!("{}: {}", path.display(), err.message);
        err
    }
}

impl fmt::Display for CliError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "error [{}]: {}", self.code, self.message)
    }
}

impl From<shapeseek::Error> for CliError {
    fn from(e: shapeseek::Error) -> Self {
        let exit = if matches!(
            e,
            shapeseek::Error::Io(_)
                | shapeseek::Error::Storage(_)
                | shapeseek::Error::StorageUnavailable(_)
                | shapeseek::Error::Queue(_)
        ) {
            74
        } else {
            65
        };
        let message = match &e {
            // The library's Display prefixes "I/O: "; the CLI's messages name the path instead.
            shapeseek::Error::Io(io) => io.to_string(),
            // The code already says `request.invalid`.
            shapeseek::Error::InvalidArgument(m) => m.clone(),
            other => other.to_string(),
        };
        CliError::new(e.code(), message, exit)
    }
}

/// Reads a whole file; the error names it (`cannot read PATH: No such file or directory`).
pub fn read_file(path: &Path) -> Result<Vec<u8>, CliError> {
    std::fs::read(path).map_err(|e| io_error(path, "cannot read", &e))
}

/// An I/O failure about `path` as a [`CliError`] (code `io`, exit 74).
pub fn io_error(path: &Path, what: &str, e: &std::io::Error) -> CliError {
    CliError::new(
        "io",
        format!("{what} {}: {}", path.display(), io_reason(e)),
        74,
    )
}

/// The OS reason of an I/O error without Rust's ` (os error N)` suffix.
pub fn io_reason(e: &std::io::Error) -> String {
    let s = e.to_string();
    match s.rfind(" (os error ") {
        Some(i) if s.ends_with(')') => s[..i].to_string(),
        _ => s,
    }
}

/// The mesh-format hint of a file name's extension (`.obj`, `.glb`, ...).
pub fn format_hint(path: &Path) -> Option<shapeseek::mesh::Format> {
    path.extension()
        .and_then(|e| e.to_str())
        .and_then(|e| e.parse::<shapeseek::mesh::Format>().ok())
}
