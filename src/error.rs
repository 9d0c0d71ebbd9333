//! The one error type of the library, with a stable machine-readable code for each kind.
//!
//! Codes (`mesh.parse`, `limit.vertices`, ...) are part of the public contract: the CLI prints
//! them and the server maps them to `application/problem+json` documents. Never rename one.

use std::fmt;

/// Where in an input file a problem was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Location {
    /// 1-based line number of a text format.
    Line(usize),
    /// 0-based byte offset of a binary format.
    Byte(usize),
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::Line(l) => write!(f, "line {l}"),
            Location::Byte(b) => write!(f, "byte {b}"),
        }
    }
}

/// Which configurable limit an input exceeded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LimitKind {
    /// Input size in bytes.
    Bytes,
    /// Number of vertices.
    Vertices,
    /// Number of faces (triangles after triangulation).
    Faces,
}

impl fmt::Display for LimitKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            LimitKind::Bytes => "bytes",
            LimitKind::Vertices => "vertices",
            LimitKind::Faces => "faces",
        })
    }
}

/// Which minimum of the preparation a mesh failed (see `PrepareOptions`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DegenerateKind {
    /// Fewer vertices than `min_vertices` after preparation.
    TooFewVertices,
    /// Fewer triangles than `min_faces` after preparation.
    TooFewFaces,
    /// The kept part holds less than `min_area_kept` of the area.
    AreaKept,
}

/// Every failure the library reports. Never a panic on user input.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The bytes are not a valid file of the named format.
    #[error("{format}: {message}{}", location.map(|l| format!(" (at {l})")).unwrap_or_default())]
    Parse {
        /// Format name (`OBJ`, `PLY`, `glTF`, `OFF`, `STL`).
        format: &'static str,
        /// Where the problem is, when known.
        location: Option<Location>,
        /// What is wrong.
        message: String,
    },
    /// The format could not be recognised from the bytes, the extension or the hint.
    #[error("unknown mesh format: {0}")]
    UnknownFormat(String),
    /// A glTF file refers to an external buffer or image (file path or URL): refused.
    #[error("glTF: external reference refused: {0}")]
    ExternalReference(String),
    /// The input exceeds a configured limit.
    #[error("too many {kind}: {actual} > limit {limit}")]
    Limit {
        /// Which limit.
        kind: LimitKind,
        /// The configured maximum.
        limit: usize,
        /// What the input has (or a lower bound of it).
        actual: usize,
    },
    /// Nothing usable is left (no triangles, or every triangle degenerate).
    #[error("empty mesh: {0}")]
    EmptyMesh(String),
    /// A polygon has more corners than the configured maximum (triangulating it would cost too
    /// much, and a fan of that many triangles is no usable surface).
    #[error("{format}: polygon with {corners} corners > limit {limit}{}", location.map(|l| format!(" (at {l})")).unwrap_or_default())]
    PolygonTooLarge {
        /// Format name.
        format: &'static str,
        /// Where the polygon is, when known.
        location: Option<Location>,
        /// Corners of the polygon.
        corners: usize,
        /// The configured maximum.
        limit: usize,
    },
    /// A count or length declared by the file disagrees with its data (refused unless the read
    /// is lenient).
    #[error("{format}: {message}{}", location.map(|l| format!(" (at {l})")).unwrap_or_default())]
    Inconsistent {
        /// Format name.
        format: &'static str,
        /// Where, when known.
        location: Option<Location>,
        /// What disagrees.
        message: String,
    },
    /// What is left after preparation cannot be a shape (too small, or too little of the input).
    #[error("degenerate mesh: {message}")]
    Degenerate {
        /// Which minimum was not met.
        kind: DegenerateKind,
        /// The measured value and the minimum.
        message: String,
    },
    /// A vertex coordinate is NaN or infinite.
    #[error("non-finite coordinate at vertex {vertex}")]
    NonFinite {
        /// 0-based index of the first offending vertex in the file.
        vertex: usize,
    },
    /// The numerical core failed (factorisation, convergence, residual check).
    #[error("numerical failure: {0}")]
    Numerical(String),
    /// The eigensolver returned fewer eigenpairs than asked (the mesh has fewer vertices than
    /// `k`). Refused unless [`crate::eigen::EigenOptions::allow_fewer`] is set.
    #[error(
        "too few eigenpairs: {asked} asked, {found} found (the prepared mesh has too few \
         vertices for the requested spectrum)"
    )]
    TooFewEigenpairs {
        /// Eigenpairs requested (`k`).
        asked: usize,
        /// Eigenpairs the problem has (its number of unknowns).
        found: usize,
    },
    /// The caller's [`Interrupt`] asked a long computation (an eigensolve) to stop.
    #[error("interrupted: {0}")]
    Interrupted(&'static str),
    /// An argument or specification is invalid.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// An I/O error while reading or writing a file.
    #[error("I/O: {0}")]
    Io(#[from] std::io::Error),
    /// The storage backend (the index database) failed to open, read, write or flush, or holds
    /// an index this build cannot use as it is (another version, another program's data).
    #[error("storage: {0}")]
    Storage(String),
    /// The storage backend could not be reached or put the work off (a database that is down,
    /// restarting, out of connections or cut off; a serialization conflict): nothing is known
    /// to have been written, and the request may be retried.
    #[error("storage unavailable: {0}")]
    StorageUnavailable(String),
    /// The work queue or change feed (NATS JetStream) could not be reached or refused a
    /// message; the request may be retried.
    #[error("queue: {0}")]
    Queue(String),
    /// Stored data could not be decoded: a signature, payload, record or file whose bytes are
    /// not what was written.
    #[error("corrupt {what}{}: {detail}", id.as_ref().map(|i| format!(" of {i}")).unwrap_or_default())]
    Corrupt {
        /// What was being decoded (`signature`, `shape record`, ...).
        what: &'static str,
        /// The stored item it belongs to (a shape id), when known.
        id: Option<String>,
        /// What is wrong with it.
        detail: String,
    },
}

impl Error {
    /// The stable machine-readable code of this error.
    pub fn code(&self) -> &'static str {
        match self {
            Error::Parse { .. } => "mesh.parse",
            Error::UnknownFormat(_) => "mesh.format",
            Error::ExternalReference(_) => "mesh.external_reference",
            Error::Limit { kind, .. } => match kind {
                LimitKind::Bytes => "limit.bytes",
                LimitKind::Vertices => "limit.vertices",
                LimitKind::Faces => "limit.faces",
            },
            Error::EmptyMesh(_) => "mesh.empty",
            Error::NonFinite { .. } => "mesh.non_finite",
            Error::PolygonTooLarge { .. } => "limit.polygon_vertices",
            Error::Inconsistent { .. } => "mesh.inconsistent",
            Error::Degenerate { kind, .. } => match kind {
                DegenerateKind::TooFewVertices => "mesh.too_few_vertices",
                DegenerateKind::TooFewFaces => "mesh.too_few_faces",
                DegenerateKind::AreaKept => "mesh.area_kept",
            },
            Error::Numerical(_) => "spectrum.numerical",
            Error::TooFewEigenpairs { .. } => "spectrum.too_few_eigenpairs",
            Error::Interrupted(_) => "interrupted",
            Error::InvalidArgument(_) => "request.invalid",
            Error::Io(_) => "io",
            Error::Storage(_) => "storage",
            Error::StorageUnavailable(_) => "storage.unavailable",
            Error::Queue(_) => "queue.unavailable",
            Error::Corrupt { .. } => "storage.corrupt",
        }
    }

    /// Shorthand for a [`Error::Corrupt`] error.
    pub fn corrupt(what: &'static str, id: Option<&str>, detail: impl Into<String>) -> Self {
        Error::Corrupt {
            what,
            id: id.map(str::to_string),
            detail: detail.into(),
        }
    }

    /// Shorthand for a parse error.
    pub fn parse(
        format: &'static str,
        location: Option<Location>,
        message: impl Into<String>,
    ) -> Self {
        Error::Parse {
            format,
            location,
            message: message.into(),
        }
    }
}

/// Result alias of the library.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// A caller's request to stop a long computation early: a check the computation calls between
/// its steps (the eigensolver before each block of operator applications), which then ends with
/// [`Error::Interrupted`]. The default never interrupts. It carries no data of the computation
/// and is not part of any options' serialised form (so it changes no cache key).
#[derive(Clone, Default)]
pub struct Interrupt(Option<std::sync::Arc<dyn Fn() -> bool + Send + Sync>>);

impl Interrupt {
    /// An interrupt that fires once `stop` returns true.
    pub fn new(stop: impl Fn() -> bool + Send + Sync + 'static) -> Interrupt {
        Interrupt(Some(std::sync::Arc::new(stop)))
    }

    /// True once the caller asked to stop.
    pub fn fired(&self) -> bool {
        self.0.as_ref().is_some_and(|f| f())
    }

    /// `Err(Error::Interrupted(during))` once the caller asked to stop.
    pub fn check(&self, during: &'static str) -> Result<()> {
        if self.fired() {
            return Err(Error::Interrupted(during));
        }
        Ok(())
    }
}

impl fmt::Debug for Interrupt {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(if self.0.is_some() {
            "Interrupt(set)"
        } else {
            "Interrupt(none)"
        })
    }
}
