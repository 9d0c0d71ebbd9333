//! The per-shape phase of a run: reading, analysis and signatures, cached, with progress.

use super::*;
use crate::signature::versions::second_version;

pub(super) fn dur(ns: &AtomicU64) -> f64 {
    ns.load(Ordering::Relaxed) as f64 * 1e-9
}

pub(super) fn add(ns: &AtomicU64, d: Duration) {
    ns.fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
}

#[derive(Default)]
pub(super) struct StageClock {
    pub(super) read: AtomicU64,
    pub(super) prepare: AtomicU64,
    pub(super) eigen: AtomicU64,
    pub(super) signature: AtomicU64,
    pub(super) cache: AtomicU64,
}

/// Progress reporting: an indicatif bar on a terminal, plain periodic lines otherwise.
pub(super) struct Progress {
    bar: Option<indicatif::ProgressBar>,
    plain: bool,
    total: usize,
    done: AtomicUsize,
    last: Mutex<Instant>,
    start: Instant,
}

impl Progress {
    pub(super) fn new(total: usize, quiet: bool) -> Progress {
        let tty = std::io::stderr().is_terminal();
        let bar = (!quiet && tty).then(|| {
            let b = indicatif::ProgressBar::new(total as u64);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "{spinner} shapes {pos}/{len} [{bar:40}] {elapsed_precise} eta {eta} {msg}",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            b
        });
        Progress {
            bar,
            plain: !quiet && !tty,
            total,
            done: AtomicUsize::new(0),
            last: Mutex::new(Instant::now()),
            start: Instant::now(),
        }
    }

    pub(super) fn tick(&self, id: &str) {
        let done = self.done.fetch_add(1, Ordering::Relaxed) + 1;
        if let Some(b) = &self.bar {
            b.set_message(id.to_string());
            b.inc(1);
        } else if self.plain {
            let mut last = self.last.lock().unwrap_or_else(|e| e.into_inner());
            if done == self.total || last.elapsed() >= Duration::from_secs(10) {
                *last = Instant::now();
                eprintln!(
                    "eval: {done}/{} shapes ({:.0} s)",
                    self.total,
                    self.start.elapsed().as_secs_f64()
                );
            }
        }
    }

    pub(super) fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

/// Part of the analysis cache key besides the mesh bytes and the options: the crate version,
/// [`crate::revision_tag`] and the fingerprint of the sources the binary was built from
/// (`build.rs`, `src/source_fingerprint.rs`), so that no other build reuses spectra or
/// signatures this one did not compute (the signature keys extend the analysis key). The
/// revision alone did not suffice: two builds at one revision that analyse differently — a
/// candidate under measurement, a fix without its bump — served each other's analyses, and
/// two figures of `docs/quality.md` §28 came from another build's caps (§29). A stored index
/// (`serve`) keys on the revision alone, so that a change that leaves the analysis alone does
/// not make it recompute every shape.
pub(crate) fn analysis_version() -> String {
    format!(
        "shapeseek {}{} src {}",
        env!("CARGO_PKG_VERSION"),
        crate::revision_tag(),
        env!("SHAPESEEK_SOURCE_FINGERPRINT")
    )
}

/// The signatures of one shape (one per union specification), or why it failed.
pub(super) type ShapeResult = std::result::Result<Vec<Signature>, (String, String)>;

/// The signatures of one shape for every spec. Specs that ask for their own preparation
/// (handle cutting, [`SignatureSpec::analysis_options`]) are computed on their own analysis
/// (own cache key); the others share the analysis with `opts`.
#[allow(clippy::too_many_arguments)]
pub(super) fn process_shape(
    path: &Path,
    specs: &[SignatureSpec],
    spec_keys: &[String],
    opts: &AnalyzeOptions,
    opts_json: &[u8],
    limits: &ReadLimits,
    cache: &Cache,
    clock: &StageClock,
) -> ShapeResult {
    let fail = |e: Error| (e.code().to_string(), e.to_string());
    let t = Instant::now();
    let bytes = read_limited(path, limits).map_err(fail)?;
    add(&clock.read, t.elapsed());
    // Group the specs by the analysis they need (first occurrence first).
    let mut groups: Vec<(Vec<u8>, AnalyzeOptions, Vec<usize>)> = Vec::new();
    for (i, spec) in specs.iter().enumerate() {
        let (o, j) = if !spec.has_own_preparation() {
            (opts.clone(), opts_json.to_vec())
        } else {
            let o = spec.analysis_options(opts);
            let j = serde_json::to_vec(&o).expect("options serialise");
            (o, j)
        };
        match groups.iter_mut().find(|g| g.0 == j) {
            Some(g) => g.2.push(i),
            None => groups.push((j, o, vec![i])),
        }
    }
    let mut out: Vec<Option<Signature>> = vec![None; specs.len()];
    for (j, o, idx) in &groups {
        let sub_specs: Vec<SignatureSpec> = idx.iter().map(|&i| specs[i].clone()).collect();
        let sub_keys: Vec<String> = idx.iter().map(|&i| spec_keys[i].clone()).collect();
        let sigs = process_group(
            path, &bytes, &sub_specs, &sub_keys, o, j, limits, cache, clock,
        )?;
        for (&i, s) in idx.iter().zip(sigs) {
            out[i] = Some(s);
        }
    }
    Ok(out
        .into_iter()
        .map(|s| s.expect("every spec in a group"))
        .collect())
}

#[allow(clippy::too_many_arguments)]
fn process_group(
    path: &Path,
    bytes: &[u8],
    specs: &[SignatureSpec],
    spec_keys: &[String],
    opts: &AnalyzeOptions,
    opts_json: &[u8],
    limits: &ReadLimits,
    cache: &Cache,
    clock: &StageClock,
) -> ShapeResult {
    let fail = |e: Error| (e.code().to_string(), e.to_string());
    let content = hash_parts(&[bytes]);
    let akey = hash_parts(&[content.as_bytes(), opts_json, analysis_version().as_bytes()]);
    let mut sigs: Vec<Option<Signature>> = Vec::with_capacity(specs.len());
    let t = Instant::now();
    let mut index: Option<Vec<IndexEntry>> = None;
    for (spec, sk) in specs.iter().zip(spec_keys) {
        let mut sig = load_signature_checked(cache, &akey, sk);
        if sig.is_none() {
            // A cached signature of a larger specification serves as well (channels by name).
            let idx = index.get_or_insert_with(|| load_index(cache, &akey));
            sig = idx
                .iter()
                .filter(|e| &e.key != sk && covers(&e.spec, spec))
                .find_map(|e| load_signature_checked(cache, &akey, &e.key));
        }
        sigs.push(sig);
    }
    add(&clock.cache, t.elapsed());
    if sigs.iter().all(|s| s.is_some()) {
        return Ok(sigs.into_iter().map(|s| s.unwrap()).collect());
    }
    let t = Instant::now();
    let cached = cache.load_analysis(&akey);
    add(&clock.cache, t.elapsed());
    let hint = path
        .extension()
        .and_then(|e| e.to_str())
        .and_then(Format::from_extension);
    let mut mesh: Option<crate::mesh::Mesh> = None;
    let read = |mesh: &mut Option<crate::mesh::Mesh>| -> std::result::Result<(), (String, String)> {
        if mesh.is_none() {
            let t = Instant::now();
            *mesh = Some(read_mesh(bytes, hint, limits).map_err(fail)?);
            add(&clock.read, t.elapsed());
        }
        Ok(())
    };
    let analysis = match cached {
        Some(a) => a,
        None => {
            read(&mut mesh)?;
            let mesh = mesh.as_ref().expect("read");
            let a = analyze(mesh, opts).map_err(fail)?;
            add(
                &clock.prepare,
                Duration::from_secs_f64(a.timings.prepare_ms * 1e-3),
            );
            add(
                &clock.eigen,
                Duration::from_secs_f64(
                    (a.timings.laplacian_ms + a.timings.factorization_ms + a.timings.eigensolve_ms)
                        * 1e-3,
                ),
            );
            let t = Instant::now();
            cache.store_analysis(&akey, &a);
            add(&clock.cache, t.elapsed());
            a
        }
    };
    let mut out = Vec::with_capacity(specs.len());
    for ((spec, sk), sig) in specs.iter().zip(spec_keys).zip(sigs) {
        match sig {
            Some(s) => out.push(s),
            None => {
                let t = Instant::now();
                let mut s = compute_signature(&analysis, spec).map_err(fail)?;
                add(&clock.signature, t.elapsed());
                if spec.alternate_cut.is_some() {
                    // The second cut version (crate::signature::versions), from the mesh.
                    read(&mut mesh)?;
                    let m = mesh.as_ref().expect("read");
                    // Its preparation, spectrum and channels count as signature time.
                    let t = Instant::now();
                    s.alternate = second_version(m, &analysis, spec, opts)
                        .map_err(fail)?
                        .map(Box::new);
                    add(&clock.signature, t.elapsed());
                }
                let t = Instant::now();
                cache.store_signature(
                    &hash_parts(&[akey.as_bytes(), sk.as_bytes()]),
                    &s.to_bytes(),
                );
                if cache.dir().is_some() {
                    let mut idx = index.take().unwrap_or_else(|| load_index(cache, &akey));
                    if !idx.iter().any(|e| &e.key == sk) {
                        idx.push(IndexEntry {
                            key: sk.clone(),
                            spec: spec.clone(),
                        });
                    }
                    cache.store_index(&akey, &serde_json::to_vec(&idx).expect("index serialises"));
                    index = Some(idx);
                }
                add(&clock.cache, t.elapsed());
                out.push(s);
            }
        }
    }
    Ok(out)
}

/// One cached signature specification of an analysis.
#[derive(serde::Serialize, serde::Deserialize)]
pub(super) struct IndexEntry {
    key: String,
    spec: SignatureSpec,
}

pub(super) fn load_index(cache: &Cache, akey: &str) -> Vec<IndexEntry> {
    cache
        .load_index(akey)
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default()
}

pub(super) fn load_signature_checked(
    cache: &Cache,
    akey: &str,
    spec_key: &str,
) -> Option<Signature> {
    let key = hash_parts(&[akey.as_bytes(), spec_key.as_bytes()]);
    cache
        .load_signature(&key)
        .and_then(|b| match Signature::from_bytes(&b) {
            Ok(s) if s.spec_key == spec_key => Some(s),
            _ => {
                cache.note_undecodable();
                None
            }
        })
}

pub(super) fn read_limited(path: &Path, limits: &ReadLimits) -> Result<Vec<u8>> {
    let meta = std::fs::metadata(path)?;
    if meta.len() as u128 > limits.max_bytes as u128 {
        return Err(Error::Limit {
            kind: crate::error::LimitKind::Bytes,
            limit: limits.max_bytes,
            actual: meta.len() as usize,
        });
    }
    Ok(std::fs::read(path)?)
}
