//! Convention check against REFERENCE.md on `shared/bench/mini` (24 shapes): corpus windows and
//! mAP of a few configurations, side by side with the Python reference. Reads files outside the
//! crate, so it is ignored by default:
//! `cargo test --release --test mini_bench -- --ignored --nocapture`.

use shapeseek::mesh::Mesh;
use shapeseek::pipeline::{analyze, AnalyzeOptions};
use shapeseek::ranking::{calibrate, config_by_name, prepare_for_ranking, score, Prepared};
use shapeseek::signature::{compute_signature, Signature, SignatureSpec};
use std::path::PathBuf;

fn read_obj(path: &std::path::Path) -> Mesh {
    let text = std::fs::read_to_string(path).expect("read obj");
    let mut v = Vec::new();
    let mut f = Vec::new();
    for line in text.lines() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let c: Vec<f64> = it.take(3).map(|x| x.parse().expect("coord")).collect();
                v.push([c[0], c[1], c[2]]);
            }
            Some("f") => {
                let idx: Vec<u32> = it
                    .map(|x| {
                        x.split('/')
                            .next()
                            .expect("idx")
                            .parse::<u32>()
                            .expect("idx")
                            - 1
                    })
                    .collect();
                for k in 1..idx.len() - 1 {
                    f.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Mesh::new(v, f)
}

/// Non-interpolated AP of each query over all other shapes (ties by manifest order).
fn mean_ap(dist: &[Vec<f64>], class: &[String], queries: &[usize]) -> f64 {
    let n = class.len();
    let mut total = 0.0;
    for &q in queries {
        let mut others: Vec<usize> = (0..n).filter(|&j| j != q).collect();
        others.sort_by(|&a, &b| dist[q][a].total_cmp(&dist[q][b]).then(a.cmp(&b)));
        let r = others.iter().filter(|&&j| class[j] == class[q]).count();
        let (mut hits, mut ap) = (0.0, 0.0);
        for (k, &j) in others.iter().enumerate() {
            if class[j] == class[q] {
                hits += 1.0;
                ap += hits / (k + 1) as f64;
            }
        }
        total += ap / r as f64;
    }
    total / queries.len() as f64
}

#[test]
#[ignore]
fn mini_bench_against_reference() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/bench/mini");
    let Ok(manifest) = std::fs::read_to_string(dir.join("manifest.csv")) else {
        eprintln!("no bench/mini here; skipped");
        return;
    };
    let rows: Vec<Vec<String>> = manifest
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(String::from).collect())
        .collect();
    let names = [
        "Heat-L2-nL1-Single[t=0.016]",
        "Heat-L2-nL1-Single[t=0.1]",
        "Heat-L2-L1-Single[t=0.1]",
        "Heat-L2-KL-Single[t=0.1]",
        "Heat-L2-nL1-Max",
        "Heat-L2-nL1-Sum2[t=0.016..0.1]",
        "Heat-L2-nL1-Sum[t=0.016..0.1]",
        "CT-L2-nL1",
        "CT-L2-L2",
        "Step-L2-nL1[lc=4pi*10]",
        "ShapeDNA[50]-L2",
        "D2-nL1",
        "Geo-nL1",
        "Heat-L1-nL1-Single[t=0.1]",
        "Heat-Linf-nL1-Single[t=0.1]",
        "Heat-L2-nL1-DistanceSum[t=0.016..0.1]",
        "Heat-L2-nL1-DistributionSum[t=0.016..0.1]",
        "Heat-L2-nL1-KernelSum[t=0.016..0.1]",
        "default",
    ];
    let configs: Vec<_> = names
        .iter()
        .map(|n| config_by_name(n).expect("config"))
        .collect();
    let first = configs[0].signature.clone();
    let rest: Vec<&SignatureSpec> = configs.iter().map(|c| &c.signature).collect();
    let spec = first.union(&rest);
    let opts = AnalyzeOptions::default();
    let t0 = std::time::Instant::now();
    let sigs: Vec<Signature> = rows
        .iter()
        .map(|r| {
            let a = analyze(&read_obj(&dir.join(&r[1])), &opts).expect("analysis");
            compute_signature(&a, &spec).expect("signature")
        })
        .collect();
    println!(
        "{} signatures in {:.1} s",
        sigs.len(),
        t0.elapsed().as_secs_f64()
    );
    let refs: Vec<&Signature> = sigs.iter().collect();
    let cal = calibrate(&refs, &spec, 1);
    let reference: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("reference-map.json")).expect("reference"),
    )
    .expect("json");
    let windows = &reference["_meta"]["window_dmax"];
    for (ours, theirs) in [
        ("heat-l2[t=0.016]", "Heat[t=0.016]"),
        ("heat-l2[t=0.04]", "Heat[t=0.04]"),
        ("heat-l2[t=0.1]", "Heat[t=0.1]"),
        ("heat-l2[t=0.25]", "Heat[t=0.25]"),
        ("heat-l2[t=0.625]", "Heat[t=0.625]"),
        ("heat-l2[t=1.5625]", "Heat[t=1.5625]"),
        ("ct-l2", "CT"),
        ("step-l2[lc=4pi*10]", "Step[lc=4pi*10]"),
        ("d2[n=2000]", "D2"),
        ("geo", "Geo"),
    ] {
        let i = cal
            .channel_names
            .iter()
            .position(|n| n == ours)
            .expect("channel");
        let w = windows[theirs].as_f64().unwrap_or(f64::NAN);
        println!(
            "window {ours:<20} ours {:>10.6}  reference {:>10.6}  ratio {:.3}",
            cal.window_max[i],
            w,
            cal.window_max[i] / w
        );
    }
    let prepared: Vec<Prepared> = sigs.iter().map(|s| prepare_for_ranking(s, &cal)).collect();
    let class: Vec<String> = rows.iter().map(|r| r[2].clone()).collect();
    let all: Vec<usize> = (0..rows.len()).collect();
    for c in &configs {
        let dist: Vec<Vec<f64>> = prepared
            .iter()
            .map(|q| prepared.iter().map(|x| score(q, x, &c.query)).collect())
            .collect();
        let ours = mean_ap(&dist, &class, &all);
        let theirs = reference[&c.name]["All"].as_f64();
        println!(
            "mAP All {:<45} ours {:6.2}  reference {}",
            c.name,
            100.0 * ours,
            theirs.map_or("-".to_string(), |t| format!("{:6.2}", 100.0 * t))
        );
    }
}
