use shapeseek::eigen::EigenOptions;
use shapeseek::mesh::generate;
use shapeseek::spectrum::compute_spectrum;

#[test]
fn quick_bench() {
    for (nu, nv, k) in [(250, 200, 100)] {
        let mut m = generate::bumpy_torus(nu, nv);
        let a = m.area();
        m.scale(1.0 / a.sqrt());
        let t = std::time::Instant::now();
        let (s, st, tm) = compute_spectrum(
            &m,
            &EigenOptions {
                k,
                block_size: std::env::var("BS").map(|s| s.parse().unwrap()).unwrap_or(0),
                ..Default::default()
            },
        )
        .unwrap();
        let r = s.residuals.iter().cloned().fold(0.0, f64::max);
        eprintln!(
            "n={} k={k} {:?} {:?} {:?} maxres {r:e} l1 {} lk {}",
            nu * nv,
            t.elapsed(),
            st,
            tm,
            s.eigenvalues[1],
            s.eigenvalues[k - 1]
        );
    }
}
