//! The first 50 eigenvalues of every mesh listed in the benchmark's
//! `mini/reference_eigenvalues.json` (dense LAPACK, the same cotangent/lumped-mass/unit-area
//! conventions as ours, stated in the file) agree to 1e-6 relative, and λ0 to 1e-9 absolute. The
//! benchmark folder is found by [`common::bench_dir`] (`SHAPESEEK_BENCH_DIR`, or `shared/bench`
//! beside the clone or one of its ancestors).

mod common;

use shapeseek::eigen::EigenOptions;
use shapeseek::mesh::{read_path, ReadLimits};
use shapeseek::spectrum::{analyze, AnalyzeOptions};

#[test]
fn mini_benchmark_reference_eigenvalues() {
    let Some(dir) = common::bench_dir("mini") else {
        println!("SKIPPED: benchmark folder shared/bench/mini not found (set SHAPESEEK_BENCH_DIR)");
        return;
    };
    let file = dir.join("reference_eigenvalues.json");
    if !file.exists() {
        println!("SKIPPED: {} not found", file.display());
        return;
    }
    let text = std::fs::read_to_string(&file).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let per_shape = json["convention"]["per_shape"]
        .as_object()
        .expect("per_shape");
    let opts = AnalyzeOptions {
        eigen: EigenOptions {
            k: 60,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut worst: f64 = 0.0;
    let mut checked = 0;
    for (id, meta) in per_shape {
        let expected: Vec<f64> = json[id.as_str()]
            .as_array()
            .unwrap_or_else(|| panic!("values of {id}"))
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert!(expected.len() >= 50);
        let path = dir.join(meta["path"].as_str().unwrap());
        let mesh = read_path(&path, &ReadLimits::default()).unwrap();
        let a = analyze(&mesh, &opts).unwrap();
        assert_eq!(
            a.mesh.vertices.len() as u64,
            meta["nv"].as_u64().unwrap(),
            "{id}: vertex count"
        );
        assert_eq!(
            a.mesh.faces.len() as u64,
            meta["nf"].as_u64().unwrap(),
            "{id}: face count"
        );
        let ev = &a.spectrum.eigenvalues;
        assert!(
            (ev[0] - expected[0]).abs() <= 1e-9,
            "{id}: λ0 {} vs {}",
            ev[0],
            expected[0]
        );
        for i in 1..50 {
            let rel = (ev[i] - expected[i]).abs() / expected[i].abs();
            worst = worst.max(rel);
            assert!(
                rel <= 1e-6,
                "{id}: λ{i} = {} vs reference {}",
                ev[i],
                expected[i]
            );
        }
        checked += 1;
    }
    assert_eq!(checked, per_shape.len());
    println!("{checked} reference shapes: max relative difference of λ1..λ49 = {worst:.2e}");
}
