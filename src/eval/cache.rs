//! On-disk cache of analyses (prepared mesh + spectrum) and signatures.
//!
//! Layout under the cache directory:
//! * `analysis/<h>.bin`, `h = sha256(sha256(mesh file bytes) ‖ AnalyzeOptions as JSON ‖ the
//!   build's analysis version)`: the prepared mesh, prepare report, eigen statistics, timings
//!   and spectrum of one mesh file. The version names the crate version, the
//!   `ALGORITHM_REVISION` and the fingerprint of the sources the binary was built from
//!   (`super::analysis_version`), so another build never reads this build's entries;
//! * `signature/<h>.bin`, `h = sha256(analysis key ‖ SignatureSpec::key())`: the bytes of
//!   `Signature::to_bytes`;
//! * `index/<analysis key>.bin`: which signature specifications are cached for that analysis
//!   (JSON), so that a run needing a subset of the channels of a cached signature reuses it.
//!
//! Every file is `MAGIC ‖ payload ‖ sha256(payload)`; a file whose magic or checksum does not match
//! (truncated, corrupt, older format) is treated as missing and recomputed. Writes go to a
//! temporary file in the same directory that is then renamed over the target, so a reader never
//! sees a partial file, and concurrent writers of the same entry (same content) are harmless.

use crate::bytes::{put_f64, put_f64s, put_u64, ByteReader};
use crate::eigen::EigenStats;
use crate::mesh::prepare::PrepareReport;
use crate::mesh::Mesh;
use crate::spectrum::Spectrum;
use crate::spectrum::{Analysis, StageTimings};
use faer::Mat;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

const MAGIC_ANALYSIS: &[u8; 8] = b"SSEVAN01";
const MAGIC_SIGNATURE: &[u8; 8] = b"SSEVSG01";
const MAGIC_INDEX: &[u8; 8] = b"SSEVIX01";

/// Hex sha256 of the parts, each length-prefixed (so `("ab","c") ≠ ("a","bc")`).
pub fn hash_parts(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update((p.len() as u64).to_le_bytes());
        h.update(p);
    }
    hex::encode(h.finalize())
}

/// The default cache directory: `$XDG_CACHE_HOME/shapeseek/eval` when `XDG_CACHE_HOME` is set
/// (and non-empty), else `./.cache/shapeseek-eval` (relative to the working directory; the
/// benchmark folder itself may be read-only).
pub fn default_dir() -> PathBuf {
    match std::env::var_os("XDG_CACHE_HOME") {
        Some(x) if !x.is_empty() => PathBuf::from(x).join("shapeseek").join("eval"),
        _ => PathBuf::from(".cache").join("shapeseek-eval"),
    }
}

/// Counters of cache use.
#[derive(Debug, Default)]
pub struct CacheStats {
    /// Entries found valid.
    pub hits: AtomicU64,
    /// Entries absent.
    pub misses: AtomicU64,
    /// Entries present but invalid (recomputed).
    pub corrupt: AtomicU64,
    /// Entries that could not be written (the run goes on).
    pub write_errors: AtomicU64,
}

/// The cache (or none: every lookup misses and nothing is written).
#[derive(Debug)]
pub struct Cache {
    dir: Option<PathBuf>,
    /// Use counters.
    pub stats: CacheStats,
}

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

impl Cache {
    /// A cache in `dir` (created with its subfolders), or a disabled one for `None`.
    pub fn new(dir: Option<PathBuf>) -> crate::Result<Cache> {
        if let Some(d) = &dir {
            std::fs::create_dir_all(d.join("analysis"))?;
            std::fs::create_dir_all(d.join("signature"))?;
            std::fs::create_dir_all(d.join("index"))?;
        }
        Ok(Cache {
            dir,
            stats: CacheStats::default(),
        })
    }

    /// The directory, when enabled.
    pub fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    fn path(&self, kind: &str, key: &str) -> Option<PathBuf> {
        self.dir
            .as_ref()
            .map(|d| d.join(kind).join(format!("{key}.bin")))
    }

    fn load(&self, kind: &str, key: &str, magic: &[u8; 8]) -> Option<Vec<u8>> {
        let path = self.path(kind, key)?;
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(_) => {
                self.stats.misses.fetch_add(1, Ordering::Relaxed);
                return None;
            }
        };
        match unwrap_envelope(&bytes, magic) {
            Some(p) => {
                self.stats.hits.fetch_add(1, Ordering::Relaxed);
                Some(p.to_vec())
            }
            None => {
                self.stats.corrupt.fetch_add(1, Ordering::Relaxed);
                None
            }
        }
    }

    fn store(&self, kind: &str, key: &str, magic: &[u8; 8], payload: &[u8]) {
        let Some(path) = self.path(kind, key) else {
            return;
        };
        if write_atomic(&path, &wrap_envelope(payload, magic)).is_err() {
            self.stats.write_errors.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// A cached analysis.
    pub fn load_analysis(&self, key: &str) -> Option<Analysis> {
        self.load("analysis", key, MAGIC_ANALYSIS)
            .and_then(|p| decode_analysis(&p))
    }

    /// Stores an analysis.
    pub fn store_analysis(&self, key: &str, a: &Analysis) {
        self.store("analysis", key, MAGIC_ANALYSIS, &encode_analysis(a));
    }

    /// Cached signature bytes (as produced by `Signature::to_bytes`).
    pub fn load_signature(&self, key: &str) -> Option<Vec<u8>> {
        self.load("signature", key, MAGIC_SIGNATURE)
    }

    /// Stores signature bytes.
    pub fn store_signature(&self, key: &str, bytes: &[u8]) {
        self.store("signature", key, MAGIC_SIGNATURE, bytes);
    }

    /// The signature index of an analysis (not counted in the statistics).
    pub fn load_index(&self, analysis_key: &str) -> Option<Vec<u8>> {
        let bytes = std::fs::read(self.path("index", analysis_key)?).ok()?;
        unwrap_envelope(&bytes, MAGIC_INDEX).map(|p| p.to_vec())
    }

    /// Stores the signature index of an analysis.
    pub fn store_index(&self, analysis_key: &str, bytes: &[u8]) {
        self.store("index", analysis_key, MAGIC_INDEX, bytes);
    }

    /// Counts a payload that passed the checksum but could not be decoded (treated as corrupt).
    pub fn note_undecodable(&self) {
        self.stats.hits.fetch_sub(1, Ordering::Relaxed);
        self.stats.corrupt.fetch_add(1, Ordering::Relaxed);
    }
}

/// `magic ‖ payload ‖ sha256(payload)`.
pub fn wrap_envelope(payload: &[u8], magic: &[u8; 8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload.len() + 40);
    out.extend_from_slice(magic);
    out.extend_from_slice(payload);
    out.extend_from_slice(&Sha256::digest(payload));
    out
}

/// The payload of a valid envelope.
pub fn unwrap_envelope<'a>(bytes: &'a [u8], magic: &[u8; 8]) -> Option<&'a [u8]> {
    if bytes.len() < 40 || &bytes[..8] != magic {
        return None;
    }
    let (body, sum) = bytes[8..].split_at(bytes.len() - 40);
    (Sha256::digest(body).as_slice() == sum).then_some(body)
}

/// Writes `bytes` to a temporary file next to `path`, then renames it over `path`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let tmp = dir.join(format!(
        ".tmp-{}-{}-{}",
        std::process::id(),
        TMP_COUNTER.fetch_add(1, Ordering::Relaxed),
        path.file_name().and_then(|s| s.to_str()).unwrap_or("entry")
    ));
    let res = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_data()?;
        drop(f);
        std::fs::rename(&tmp, path)
    })();
    if res.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    res
}

#[derive(Serialize, Deserialize)]
struct AnalysisHeader {
    n: usize,
    m: usize,
    k: usize,
    report: PrepareReport,
    eigen_stats: EigenStats,
    timings: StageTimings,
    eigenvalues: Vec<f64>,
    residuals: Vec<f64>,
}

fn encode_analysis(a: &Analysis) -> Vec<u8> {
    let n = a.mesh.vertices.len();
    let m = a.mesh.faces.len();
    let k = a.spectrum.eigenvectors.ncols();
    let header = AnalysisHeader {
        n,
        m,
        k,
        report: a.report.clone(),
        eigen_stats: a.eigen_stats.clone(),
        timings: a.timings.clone(),
        eigenvalues: a.spectrum.eigenvalues.clone(),
        residuals: a.spectrum.residuals.clone(),
    };
    let h = serde_json::to_vec(&header).expect("header serialises");
    let mut out = Vec::with_capacity(8 + h.len() + n * 24 + m * 12 + n * 8 + n * k * 8);
    put_u64(&mut out, h.len() as u64);
    out.extend_from_slice(&h);
    for v in &a.mesh.vertices {
        put_f64s(&mut out, v);
    }
    for f in &a.mesh.faces {
        for i in f {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    put_f64s(&mut out, &a.spectrum.mass);
    let ev = &a.spectrum.eigenvectors;
    for j in 0..k {
        for i in 0..ev.nrows() {
            put_f64(&mut out, ev[(i, j)]);
        }
    }
    out
}

fn decode_analysis(p: &[u8]) -> Option<Analysis> {
    let mut r = ByteReader::new(p);
    let hl = r.u64()? as usize;
    let header: AnalysisHeader = serde_json::from_slice(r.take(hl)?).ok()?;
    let (n, m, k) = (header.n, header.m, header.k);
    let coords = r.f64s(n.checked_mul(3)?)?;
    let vertices: Vec<[f64; 3]> = coords.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let idx = r.u32s(m.checked_mul(3)?)?;
    let faces: Vec<[u32; 3]> = idx.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    if faces.iter().any(|f| f.iter().any(|&i| i as usize >= n)) {
        return None;
    }
    let mass = r.f64s(n)?;
    let ev = r.f64s(n.checked_mul(k)?)?;
    if !r.at_end() || header.eigenvalues.len() != k {
        return None;
    }
    let eigenvectors = Mat::from_fn(n, k, |i, j| ev[j * n + i]);
    Some(Analysis {
        mesh: Mesh::new(vertices, faces),
        report: header.report,
        spectrum: Spectrum {
            eigenvalues: header.eigenvalues,
            eigenvectors,
            mass,
            residuals: header.residuals,
        },
        eigen_stats: header.eigen_stats,
        timings: header.timings,
    })
}
