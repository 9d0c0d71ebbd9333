//! The benchmark manifest: `id,path,class,transform,strength,source_pose` (bench README).
//!
//! Paths are relative to the manifest's folder. Column order is free; extra columns are ignored;
//! the six named columns are required. Every row must have a non-empty `id` (unique), `path`,
//! `class` and `transform`; `strength` must be an integer (empty means 0).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The columns a manifest must have.
pub const REQUIRED_COLUMNS: [&str; 6] = [
    "id",
    "path",
    "class",
    "transform",
    "strength",
    "source_pose",
];

/// One shape of the benchmark.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// Shape id, unique in the manifest.
    pub id: String,
    /// Path as written in the manifest (relative to the manifest's folder unless absolute).
    pub path: String,
    /// Mesh file, resolved against the manifest's folder.
    pub resolved: PathBuf,
    /// Class (relevance = same class).
    pub class: String,
    /// Transformation class (`null`, `isometry`, ...).
    pub transform: String,
    /// Level of the transformation.
    pub strength: i64,
    /// Source pose (informational).
    pub source_pose: String,
}

/// A parsed manifest, rows in file order (the tie-break order of the protocol).
#[derive(Debug, Clone, PartialEq)]
pub struct Manifest {
    /// The manifest's folder (paths are resolved against it).
    pub base: PathBuf,
    /// The rows.
    pub entries: Vec<Entry>,
}

/// Why a manifest could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    /// The file could not be read.
    #[error("manifest {path}: {source}")]
    Io {
        /// The manifest path.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A required column is missing from the header.
    #[error(
        "manifest: missing column '{0}' (required: id,path,class,transform,strength,source_pose)"
    )]
    MissingColumn(String),
    /// A row is malformed.
    #[error("manifest line {line}: {message}")]
    BadRow {
        /// 1-based line number in the file (the header is line 1).
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// Two rows share an id.
    #[error("manifest line {line}: duplicate id '{id}' (first on line {first})")]
    DuplicateId {
        /// The repeated id.
        id: String,
        /// Line of the repetition.
        line: usize,
        /// Line of the first occurrence.
        first: usize,
    },
    /// No rows.
    #[error("manifest has no rows")]
    Empty,
}

impl From<ManifestError> for crate::Error {
    fn from(e: ManifestError) -> Self {
        match e {
            ManifestError::Io { source, .. } => crate::Error::Io(source),
            other => crate::Error::InvalidArgument(other.to_string()),
        }
    }
}

impl Manifest {
    /// Reads and validates the manifest at `path`.
    pub fn read(path: &Path) -> Result<Manifest, ManifestError> {
        let text = std::fs::read_to_string(path).map_err(|source| ManifestError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let base = path
            .parent()
            .map(|p| {
                if p.as_os_str().is_empty() {
                    Path::new(".")
                } else {
                    p
                }
            })
            .unwrap_or(Path::new("."))
            .to_path_buf();
        Manifest::parse(&text, &base)
    }

    /// Parses manifest text; relative paths are resolved against `base`.
    pub fn parse(text: &str, base: &Path) -> Result<Manifest, ManifestError> {
        let mut rdr = csv::ReaderBuilder::new()
            .has_headers(true)
            .flexible(true)
            .trim(csv::Trim::All)
            .from_reader(text.as_bytes());
        let headers = rdr
            .headers()
            .map_err(|e| ManifestError::BadRow {
                line: 1,
                message: e.to_string(),
            })?
            .clone();
        let mut col = [0usize; 6];
        for (slot, name) in col.iter_mut().zip(REQUIRED_COLUMNS) {
            *slot = headers
                .iter()
                .position(|h| h.trim_start_matches('\u{feff}').eq_ignore_ascii_case(name))
                .ok_or_else(|| ManifestError::MissingColumn(name.to_string()))?;
        }
        let ncols = headers.len();
        let mut entries = Vec::new();
        let mut seen: HashMap<String, usize> = HashMap::new();
        for rec in rdr.records() {
            let rec = rec.map_err(|e| ManifestError::BadRow {
                line: e.position().map(|p| p.line() as usize).unwrap_or(0),
                message: e.to_string(),
            })?;
            let line = rec.position().map(|p| p.line() as usize).unwrap_or(0);
            if rec.iter().all(|f| f.is_empty()) {
                continue;
            }
            if rec.len() != ncols {
                return Err(ManifestError::BadRow {
                    line,
                    message: format!("{} fields, the header has {ncols}", rec.len()),
                });
            }
            let get = |i: usize| rec.get(col[i]).unwrap_or("").to_string();
            let (id, p, class, transform, strength, source_pose) =
                (get(0), get(1), get(2), get(3), get(4), get(5));
            for (name, v) in [
                ("id", &id),
                ("path", &p),
                ("class", &class),
                ("transform", &transform),
            ] {
                if v.is_empty() {
                    return Err(ManifestError::BadRow {
                        line,
                        message: format!("empty '{name}'"),
                    });
                }
            }
            let strength = if strength.is_empty() {
                0
            } else {
                strength.parse::<i64>().map_err(|_| ManifestError::BadRow {
                    line,
                    message: format!("strength '{strength}' is not an integer"),
                })?
            };
            if let Some(&first) = seen.get(&id) {
                return Err(ManifestError::DuplicateId { id, line, first });
            }
            seen.insert(id.clone(), line);
            let resolved = if Path::new(&p).is_absolute() {
                PathBuf::from(&p)
            } else {
                base.join(&p)
            };
            entries.push(Entry {
                id,
                path: p,
                resolved,
                class,
                transform,
                strength,
                source_pose,
            });
        }
        if entries.is_empty() {
            return Err(ManifestError::Empty);
        }
        Ok(Manifest {
            base: base.to_path_buf(),
            entries,
        })
    }

    /// Transformation names in order of first appearance.
    pub fn transforms(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for e in &self.entries {
            if !out.contains(&e.transform) {
                out.push(e.transform.clone());
            }
        }
        out
    }
}
