//! The synthetic corpus of `shapeseek bench search` and `bench populate`: signatures of 24 base
//! shapes, each stored shape a perturbed copy of one, and the two benches that query and fill it.

use super::*;

/// Base shapes of the synthetic index: bumpy spheres and bumpy tori, each stretched by its own
/// anisotropic factors (which changes its intrinsic geometry, hence its signature).
const SYNTHETIC_BASES: usize = 24;

/// A deterministic uniform number in [0, 1) for `i` (SplitMix64).
pub(super) fn unit(i: u64) -> f64 {
    let mut z = i.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

/// The 24 base shapes' signatures under `spec` (and their re-ranking payloads when asked).
fn synthetic_bases(
    spec: &SignatureSpec,
    payloads: bool,
) -> Result<Vec<(Signature, Option<shapeseek::rerank::GwPayload>)>> {
    use shapeseek::rerank::{compute_payload, PayloadSpec};
    use shapeseek::signature::sign;
    use shapeseek::spectrum::AnalyzeOptions;
    (0..SYNTHETIC_BASES)
        .into_par_iter()
        .map(|j| {
            let mut m = if j % 2 == 0 {
                generate::bumpy_sphere(3, 0.1 + 0.02 * j as f64)
            } else {
                generate::bumpy_torus(36 + 2 * j, 18)
            };
            let s = [
                1.0 + 0.06 * (j % 5) as f64,
                1.0,
                1.0 - 0.05 * (j % 3) as f64,
            ];
            for v in &mut m.vertices {
                *v = [v[0] * s[0], v[1] * s[1], v[2] * s[2]];
            }
            // As the server signs (both cut versions when the spec has an alternate cut: the
            // bumpy tori are genuine handles, which the default's second cut takes).
            let (a, sig) = sign(&m, spec, &AnalyzeOptions::default())?;
            let p = if payloads {
                Some(compute_payload(&a, &PayloadSpec::default())?)
            } else {
                None
            };
            Ok((sig, p))
        })
        .collect()
}

/// Synthetic signature `i` from the bases: base `i % 24` with every distance scaled by a
/// factor in [1 − spread, 1 + spread] (copies `0..24` are the bases themselves). With the
/// default spread 0.05 a query has a few thousand same-base neighbours at 10⁵ shapes, most of
/// them close; a wider spread makes neighbours farther apart (more exact scores per query).
fn synthetic_signature(
    bases: &[(Signature, Option<shapeseek::rerank::GwPayload>)],
    i: usize,
    spread: f64,
) -> Signature {
    let sig = &bases[i % bases.len()].0;
    if i < bases.len() {
        return sig.clone();
    }
    scaled(sig, 1.0 + spread * (2.0 * unit(i as u64) - 1.0))
}

/// `sig` with every distance multiplied by `f` and every eigenvalue (ShapeDNA) by `f⁻²`, as the
/// shape scaled by `f` would have them (its second cut version's too).
fn scaled(sig: &Signature, f: f64) -> Signature {
    use shapeseek::signature::ChannelValues;
    let mut sig = sig.clone();
    for c in &mut sig.channels {
        match &mut c.values {
            ChannelValues::Distribution(q) => q.quantiles.iter_mut().for_each(|x| *x *= f),
            ChannelValues::Vector(v) => v.iter_mut().for_each(|x| *x /= f * f),
        }
    }
    sig.alternate = sig.alternate.map(|a| Box::new(scaled(&a, f)));
    sig
}

/// Resident set size of this process (VmRSS), in bytes.
fn rss_bytes() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmRSS:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<f64>().ok())
            })
        })
        .map(|kib| kib * 1024.0)
        .unwrap_or(f64::NAN)
}

/// Copy `c ≥ 1` of an encoded row: up to four counts moved by one unit to the next bin of
/// the same channel (positions from `i`), group sums recomputed; its second version likewise.
fn perturbed(e: &Encoded, layout: &Layout, i: usize) -> Encoded {
    let mut e = e.clone();
    let bins = layout.bins;
    for k in 0..layout.histograms() {
        for r in 0..4u64 {
            let j = (unit(i as u64 * 131 + k as u64 * 17 + r) * (bins - 1) as f64) as usize;
            let at = k * bins + j;
            if e.hist[at] > 0 && e.hist[at + 1] < u16::MAX {
                e.hist[at] -= 1;
                e.hist[at + 1] += 1;
            }
        }
    }
    e.fill_groups(layout);
    // The second version, moved the same way (copies do not share one exactly).
    e.alt = e.alt.map(|a| Box::new(perturbed(&a, layout, i)));
    e
}

pub(super) fn run_search(b: &SearchBench) -> Result<()> {
    use shapeseek::index::ScanIndex;
    use shapeseek::presets::default_config;
    use shapeseek::ranking::calibrate_with;
    use shapeseek::search::{rank_all, top_k, Query};
    use std::sync::Arc;
    if b.sizes.contains(&0) || b.queries == 0 || b.top_k == 0 {
        return Err(Error::InvalidArgument(
            "--sizes, --queries and --top-k must be at least 1".into(),
        ));
    }
    let mut cfg = default_config();
    if let Some(d) = &b.dissimilarity {
        cfg.query.dissimilarity = serde_json::from_value(serde_json::Value::String(d.clone()))
            .map_err(|e| Error::InvalidArgument(format!("--dissimilarity {d}: {e}")))?;
    }
    let bases = synthetic_bases(&cfg.signature, false)?;
    println!(
        "config `{}` ({:?}), top {}, {} queries per size, rayon threads {}; reference = the \
         full ranking (every candidate scored, sorted) on the verified queries; memory = \
         resident set growth while the index (corpus + ids, names, tags) was built, and the \
         index's own heap bytes, per shape",
        cfg.name,
        cfg.query.dissimilarity,
        b.top_k,
        b.queries,
        rayon::current_num_threads()
    );
    println!(
        "{:>10} {:>9} {:>9} {:>9} {:>12} {:>10} {:>9} {:>9} {:>11} {:>11}",
        "stored",
        "p50 ms",
        "p99 ms",
        "max ms",
        "scored (mean)",
        "full p50",
        "speed-up",
        "verified",
        "RSS B/shape",
        "heap B/shape"
    );
    for &n in &b.sizes {
        let distinct = b.distinct.max(SYNTHETIC_BASES) / SYNTHETIC_BASES * SYNTHETIC_BASES;
        let d = distinct.min(n);
        // Calibration on (up to) the distinct signatures, then dropped: the index keeps none.
        let sigs: Vec<Signature> = (0..d)
            .into_par_iter()
            .map(|i| synthetic_signature(&bases, i, b.spread))
            .collect();
        let cal = Arc::new(calibrate_with(
            &sigs.iter().collect::<Vec<_>>(),
            &cfg.signature,
            1,
            &cfg.calibration,
        ));
        let layout = Layout::of(&cal);
        let rows: Vec<Encoded> = sigs
            .par_iter()
            .map(|s| Encoded::from_signature(s, &cal, &layout))
            .collect();
        drop(sigs);
        let rss0 = rss_bytes();
        let mut index = ScanIndex::with_capacity(cal.clone(), n, n);
        let tags = |i: usize| {
            vec![
                "synthetic".to_string(),
                format!("base{}", i % SYNTHETIC_BASES),
            ]
        };
        for i in 0..n {
            let id = format!("{i:016x}");
            let name = format!("synthetic-{i:07}");
            if i < d {
                index.push_encoded(&id, &name, &tags(i), &rows[i]);
            } else {
                index.push_encoded(&id, &name, &tags(i), &perturbed(&rows[i % d], &layout, i));
            }
        }
        let rss = (rss_bytes() - rss0) / n as f64;
        let heap = index.heap_bytes() as f64 / n as f64;
        let corpus = index.corpus();
        let q = Query::new(&cfg.query, corpus.layout());
        let queries: Vec<usize> = (0..b.queries.max(1))
            .map(|q| (unit(1_000_000 + q as u64) * n as f64) as usize % n)
            .collect();
        let verify = b
            .verify
            .unwrap_or(if n <= 100_000 { queries.len() } else { 3 });
        let (mut times, mut full, mut scored) = (Vec::new(), Vec::new(), 0usize);
        for (qi, &qpos) in queries.iter().enumerate() {
            let outside = b.query_scale.map(|f| {
                Encoded::from_signature(&scaled(&bases[qpos % bases.len()].0, f), &cal, &layout)
            });
            let (query, skip) = match &outside {
                Some(p) => (p.clone(), usize::MAX),
                None => (corpus.encoded(qpos), qpos),
            };
            let t = Instant::now();
            let (hits, count) = top_k(corpus, &q, query.view(), b.top_k, &|i| i != skip);
            times.push(t.elapsed().as_secs_f64() * 1e3);
            scored += count;
            if qi < verify {
                let t = Instant::now();
                let all = rank_all(corpus, &q, query.view());
                full.push(t.elapsed().as_secs_f64() * 1e3);
                let head: Vec<(usize, f64)> = all
                    .into_iter()
                    .filter(|&(i, _)| i != skip)
                    .take(b.top_k)
                    .collect();
                if head != hits {
                    return Err(Error::InvalidArgument(format!(
                        "pruned top-k differs from the full ranking for query {qpos}"
                    )));
                }
            }
        }
        times.sort_by(f64::total_cmp);
        full.sort_by(f64::total_cmp);
        let pct = |v: &[f64], p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        let full50 = if full.is_empty() {
            f64::NAN
        } else {
            pct(&full, 0.5)
        };
        println!(
            "{n:>10} {:>9.2} {:>9.2} {:>9.2} {:>12.0} {:>10.2} {:>8.1}x {:>9} {:>11.0} {:>11.0}",
            pct(&times, 0.5),
            pct(&times, 0.99),
            times[times.len() - 1],
            scored as f64 / queries.len() as f64,
            full50,
            full50 / pct(&times, 0.5),
            full.len(),
            rss,
            heap
        );
    }
    Ok(())
}

/// What every synthetic shape shares: the base signatures and payloads, the tiny original.
struct Synthetic {
    engine: shapeseek::index::Engine,
    bases: Vec<(Signature, Option<shapeseek::rerank::GwPayload>)>,
    payloads: Vec<Option<Vec<u8>>>,
    obj: Vec<u8>,
    vertices: usize,
    faces: usize,
    area: f64,
    report: shapeseek::mesh::prepare::PrepareReport,
}

impl Synthetic {
    fn new(payloads: bool) -> Result<Synthetic> {
        use shapeseek::mesh::write::write_obj;
        let engine = shapeseek::index::Engine::new();
        let bases = synthetic_bases(&engine.config.signature, payloads)?;
        let payloads = bases
            .iter()
            .map(|(_, p)| p.as_ref().map(|p| p.to_bytes()))
            .collect();
        let tiny = generate::icosphere(0);
        let (_, report) = prepare(&tiny, &PrepareOptions::default())?;
        let mut obj = Vec::new();
        write_obj(&tiny, &mut obj)?;
        Ok(Synthetic {
            engine,
            bases,
            payloads,
            obj,
            vertices: tiny.vertices.len(),
            faces: tiny.faces.len(),
            area: tiny.area(),
            report,
        })
    }

    /// Synthetic shape `i` under the id `id`.
    fn shape(&self, i: usize, id: String) -> shapeseek::storage::NewShape {
        use sha2::{Digest, Sha256};
        use shapeseek::index::store::{now_unix_ms, ShapeRecord};
        let sig = &synthetic_signature(&self.bases, i, 0.05);
        let mut original = format!("# shapeseek synthetic shape {i}\n").into_bytes();
        original.extend_from_slice(&self.obj);
        let sha256: [u8; 32] = Sha256::digest(&original).into();
        shapeseek::storage::NewShape {
            record: ShapeRecord {
                name: format!("synthetic-{i:06}"),
                tags: vec!["synthetic".into(), format!("base{}", i % SYNTHETIC_BASES)],
                id,
                format: "obj".into(),
                content_type: "model/obj".into(),
                bytes: original.len() as u64,
                vertices: self.vertices,
                faces: self.faces,
                area: self.area,
                sha256: hex::encode(sha256),
                created_unix_ms: now_unix_ms(),
                prepare: self.report.clone(),
                spec_key: self.engine.spec_key(),
            },
            sha256,
            signature: self.engine.encode_signature(sig),
            original,
            // With `--payloads`, a base shape's payload, else none (a spectral-GW stage then
            // ranks these after shapes that have one). The payload's base is decoupled from
            // the signature's (`i / 24` vs `i % 24`), so that a shortlist of same-signature
            // shapes holds different payloads: identical metric spaces would make the GW
            // solves unrealistically cheap.
            payload: self.payloads[(i / SYNTHETIC_BASES) % SYNTHETIC_BASES].clone(),
        }
    }
}

pub(super) fn run_populate(b: &PopulateBench) -> Result<()> {
    use shapeseek::index::store::{BatchItem, Store};
    let t0 = Instant::now();
    let syn = Synthetic::new(b.payloads)?;
    if let Some(url) = &b.store {
        return populate_store(b, url, syn, t0);
    }
    let data = b.data.as_ref().expect("--data or --store");
    let store = Store::open(data)?;
    let mut written = 0usize;
    while written < b.count {
        let chunk = (b.count - written).min(5000);
        let mut items = Vec::with_capacity(chunk);
        for i in written..written + chunk {
            let s = syn.shape(i, store.new_id()?);
            items.push(BatchItem {
                record: s.record,
                sha256: s.sha256,
                signature: s.signature,
                original: s.original,
                payload: s.payload,
            });
        }
        store.insert_batch(&items)?;
        written += items.len();
        eprint!("\rwritten {written}/{}", b.count);
    }
    eprintln!();
    println!(
        "{} synthetic shapes written to {} in {:.1} s ({} shapes now)",
        b.count,
        data.display(),
        t0.elapsed().as_secs_f64(),
        store.len()
    );
    Ok(())
}

/// `bench populate --store postgres://…`: the same shapes through [`shapeseek::storage`]'s
/// `insert`, 8 at a time.
fn populate_store(b: &PopulateBench, url: &str, syn: Synthetic, t0: Instant) -> Result<()> {
    const WRITERS: usize = 8;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let count = b.count;
    let n = rt.block_on(async move {
        let store = shapeseek::storage::open(url).await?;
        let syn = std::sync::Arc::new(syn);
        let done = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let tasks: Vec<_> = (0..WRITERS)
            .map(|w| {
                let (store, syn, done) = (store.clone(), syn.clone(), done.clone());
                tokio::spawn(async move {
                    for i in (w..count).step_by(WRITERS) {
                        let id = store.new_id().await?;
                        let shape = syn.shape(i, id);
                        store.insert(shape).await?;
                        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                        if d % 1000 == 0 {
                            eprint!("\rwritten {d}/{count}");
                        }
                    }
                    Ok::<(), Error>(())
                })
            })
            .collect();
        for t in tasks {
            t.await
                .map_err(|e| Error::Io(std::io::Error::other(e.to_string())))??;
        }
        store.count().await
    })?;
    eprintln!();
    println!(
        "{count} synthetic shapes written to {url} in {:.1} s ({n} shapes now)",
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
