//! Proof of correctness of the spectral core on analytic cases: the unit sphere (λ = l(l+1),
//! multiplicity 2l+1), a flat rectangle (Neumann spectrum), invariance to rigid motion and vertex
//! order, A-orthonormality, residuals, determinism, dense/Krylov agreement, and that an interrupted
//! analysis never yields a signature.

mod common;

use common::{analyze_opts as opts, unit_area_sphere_eigenvalue as sphere_exact};
use shapeseek::eigen::{EigenOptions, Method};
use shapeseek::mesh::generate;
use shapeseek::mesh::Mesh;
use shapeseek::spectrum::{analyze, compute_spectrum};
use std::f64::consts::PI;

#[test]
fn icosphere_spectrum_converges_to_l_l_plus_1_with_multiplicity() {
    let k = 25; // l = 0..4: 1 + 3 + 5 + 7 + 9
    let mut previous_error = f64::INFINITY;
    for s in 1..=4 {
        let method = if s == 4 { Method::Krylov } else { Method::Auto };
        let a = analyze(&generate::icosphere(s), &opts(k, method)).unwrap();
        let ev = &a.spectrum.eigenvalues;
        assert!(ev[0].abs() < 1e-8, "λ0 = {}", ev[0]);
        let mut worst: f64 = 0.0;
        for (i, &v) in ev.iter().enumerate().skip(1) {
            worst = worst.max((v - sphere_exact(i)).abs() / sphere_exact(i));
        }
        eprintln!(
            "subdivision {s}: {} vertices, max relative error of λ1..λ24 = {worst:.3e}",
            a.mesh.vertices.len()
        );
        assert!(worst < previous_error, "error must shrink with refinement");
        previous_error = worst;
        // Multiplicity 2l+1: every cluster of 2l+1 values is far tighter than the gap to the next.
        for l in 1..4usize {
            let (lo, hi) = (l * l, (l + 1) * (l + 1)); // indices of the cluster
            let spread = ev[hi - 1] - ev[lo];
            let gap = ev[hi] - ev[hi - 1];
            if s >= 2 {
                assert!(
                    spread < 0.1 * gap,
                    "l={l} s={s}: spread {spread} vs gap {gap}"
                );
            }
        }
    }
    assert!(
        previous_error < 0.01,
        "finest sphere within 1%: {previous_error}"
    );
}

/// The vertex budget (`PrepareOptions::max_vertices`, `shapeseek::mesh::decimate`): a sphere of
/// 40 962 vertices simplified to 5 000 keeps the 100 eigenvalues a signature reads (l ≤ 9)
/// closer to the analytic ones than a regular icosphere of 2 562 vertices (second-order
/// convergence puts a regular mesh of 5 000 vertices at about half that one's error); a sheet of
/// 20 301 vertices simplified to 3 000 keeps its Neumann spectrum (its border is kept) within a
/// quarter of the error of a regular grid of as many vertices.
#[test]
fn a_fine_mesh_simplified_to_the_budget_keeps_its_low_spectrum() {
    let k = 100;
    let worst = |ev: &[f64]| {
        (1..k)
            .map(|i| (ev[i] - sphere_exact(i)).abs() / sphere_exact(i))
            .fold(0.0, f64::max)
    };
    let mut o = opts(k, Method::Krylov);
    let regular = analyze(&generate::icosphere(4), &o).unwrap();
    o.prepare.max_vertices = Some(5000);
    let simple = analyze(&generate::icosphere(6), &o).unwrap();
    let d = simple.report.decimated.as_ref().expect("simplified");
    assert_eq!((d.vertices_before, d.budget), (40962, 5000));
    assert_eq!(simple.mesh.vertices.len(), d.vertices_after);
    assert!(d.vertices_after <= 5000, "{d:?}");
    assert_eq!(simple.report.vertices_in, 40962);
    assert_eq!(simple.report.vertices_out, d.vertices_after);
    assert!(regular.report.decimated.is_none());
    let (w_simple, w_regular) = (
        worst(&simple.spectrum.eigenvalues),
        worst(&regular.spectrum.eigenvalues),
    );
    eprintln!(
        "sphere: λ1..λ99 max relative error {w_simple:.3e} simplified to {} vertices, \
         {w_regular:.3e} regular at {}",
        d.vertices_after,
        regular.mesh.vertices.len()
    );
    assert!(w_simple < 0.8 * w_regular);

    // [0,2]×[0,1], free boundary: λ = π²(m²/4 + n²), not area-normalised.
    let mut exact: Vec<f64> = (0..12)
        .flat_map(|m| (0..12).map(move |n| PI * PI * ((m * m) as f64 / 4.0 + (n * n) as f64)))
        .collect();
    exact.sort_by(f64::total_cmp);
    let mut o = opts(30, Method::Krylov);
    o.prepare.normalize_area = false;
    o.prepare.max_vertices = Some(3000);
    let a = analyze(&generate::rectangle(2.0, 1.0, 200, 100), &o).unwrap();
    assert!(a.report.decimated.is_some() && a.mesh.vertices.len() <= 3000);
    assert_eq!(a.report.boundary_loops, 1);
    let worst = |ev: &[f64]| {
        (1..30)
            .map(|i| (ev[i] - exact[i]).abs() / exact[i])
            .fold(0.0, f64::max)
    };
    let w = worst(&a.spectrum.eigenvalues);
    let half = analyze(&generate::rectangle(2.0, 1.0, 54, 27), &o).unwrap();
    let w_half = worst(&half.spectrum.eigenvalues);
    let full = analyze(&generate::rectangle(2.0, 1.0, 76, 38), &o).unwrap();
    eprintln!(
        "sheet: λ1..λ29 max relative error {w:.3e} simplified to {} vertices, {w_half:.3e} regular at {}, {:.3e} regular at {}",
        a.mesh.vertices.len(),
        half.mesh.vertices.len(),
        worst(&full.spectrum.eigenvalues),
        full.mesh.vertices.len()
    );
    let w_full = worst(&full.spectrum.eigenvalues);
    assert!(
        w < 0.8 * w_half && w < 1.25 * w_full,
        "{w} vs {w_half}, {w_full}"
    );
}

#[test]
fn flat_rectangle_matches_the_neumann_spectrum() {
    // [0,2]×[0,1] with free boundary: λ = π²(m²/4 + n²). Not area-normalised.
    let mut exact: Vec<f64> = (0..10)
        .flat_map(|m| (0..10).map(move |n| PI * PI * ((m * m) as f64 / 4.0 + (n * n) as f64)))
        .collect();
    exact.sort_by(f64::total_cmp);
    let mut prev = f64::INFINITY;
    for (nx, ny) in [(40, 20), (80, 40)] {
        let mesh = generate::rectangle(2.0, 1.0, nx, ny);
        let (s, _, _) = compute_spectrum(
            &mesh,
            &EigenOptions {
                k: 12,
                ..Default::default()
            },
        )
        .unwrap();
        let worst = (1..12)
            .map(|i| (s.eigenvalues[i] - exact[i]).abs() / exact[i])
            .fold(0.0, f64::max);
        eprintln!("rectangle {nx}x{ny}: max relative error λ1..λ11 = {worst:.3e}");
        // Second-order convergence: halving h divides the error by about 4.
        assert!(worst < prev / 3.0, "{worst} vs {prev}");
        prev = worst;
    }
    assert!(prev < 3e-3, "{prev}");
}

fn rotation(ax: f64, ay: f64, az: f64) -> [[f64; 3]; 3] {
    let (sx, cx, sy, cy, sz, cz) = (ax.sin(), ax.cos(), ay.sin(), ay.cos(), az.sin(), az.cos());
    let rx = [[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]];
    let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
    let rz = [[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]];
    let mul = |a: [[f64; 3]; 3], b: [[f64; 3]; 3]| {
        let mut c = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                c[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
            }
        }
        c
    };
    mul(rz, mul(ry, rx))
}

fn assert_same_values(a: &[f64], b: &[f64], tol: f64) {
    assert_eq!(a.len(), b.len());
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        let scale = x.abs().max(1.0);
        assert!((x - y).abs() <= tol * scale, "λ{i}: {x} vs {y}");
    }
}

#[test]
fn invariant_to_rigid_motion_scale_and_vertex_order() {
    let mesh = generate::bumpy_sphere(3, 0.25);
    let o = opts(40, Method::Krylov);
    let base = analyze(&mesh, &o).unwrap();

    let mut moved = mesh.clone();
    moved.transform(rotation(0.3, -1.1, 2.0), [5.0, -3.0, 0.25]);
    moved.scale(3.7);
    let m = analyze(&moved, &o).unwrap();
    assert_same_values(&base.spectrum.eigenvalues, &m.spectrum.eigenvalues, 1e-9);

    // Permute vertices (a fixed pseudo-random permutation) and remap faces.
    let n = mesh.vertices.len();
    let perm: Vec<usize> = {
        let mut p: Vec<usize> = (0..n).collect();
        let mut state = 12345u64;
        for i in (1..n).rev() {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            p.swap(i, (state >> 33) as usize % (i + 1));
        }
        p
    };
    let mut inverse = vec![0u32; n];
    let mut vertices = vec![[0.0; 3]; n];
    for (new, &old) in perm.iter().enumerate() {
        vertices[new] = mesh.vertices[old];
        inverse[old] = new as u32;
    }
    let faces = mesh
        .faces
        .iter()
        .map(|f| f.map(|i| inverse[i as usize]))
        .collect();
    let permuted = analyze(&Mesh::new(vertices, faces), &o).unwrap();
    assert_same_values(
        &base.spectrum.eigenvalues,
        &permuted.spectrum.eigenvalues,
        1e-9,
    );
    // Eigenvectors of simple eigenvalues are the same functions, with the same sign convention.
    for j in 1..10 {
        for (new, &old) in perm.iter().enumerate() {
            let a = base.spectrum.eigenvectors[(old, j)];
            let b = permuted.spectrum.eigenvectors[(new, j)];
            assert!((a - b).abs() < 1e-6, "φ{j} at vertex {old}: {a} vs {b}");
        }
    }
}

#[test]
fn eigenvectors_are_mass_orthonormal_with_small_residuals_and_deterministic() {
    let mesh = generate::bumpy_torus(60, 30);
    let o = opts(60, Method::Krylov);
    let a = analyze(&mesh, &o).unwrap();
    let s = &a.spectrum;
    let (n, k) = (s.eigenvectors.nrows(), s.eigenvectors.ncols());
    assert_eq!(k, 60);
    for i in 0..k {
        for j in 0..=i {
            let dot: f64 = (0..n)
                .map(|v| s.mass[v] * s.eigenvectors[(v, i)] * s.eigenvectors[(v, j)])
                .sum();
            let expect = if i == j { 1.0 } else { 0.0 };
            assert!((dot - expect).abs() < 1e-9, "<φ{i},φ{j}>_A = {dot}");
        }
    }
    let worst = s.residuals.iter().cloned().fold(0.0, f64::max);
    assert!(worst <= 1e-8, "max residual {worst}");
    assert!(s.eigenvalues.windows(2).all(|w| w[0] <= w[1]));
    let again = analyze(&mesh, &o).unwrap();
    assert_eq!(
        again.spectrum.eigenvalues, s.eigenvalues,
        "bitwise deterministic eigenvalues"
    );
    assert_eq!(
        again.spectrum.eigenvectors, s.eigenvectors,
        "bitwise deterministic eigenvectors"
    );
}

#[test]
fn krylov_agrees_with_dense_and_finds_repeated_eigenvalues() {
    // The icosphere has eigenvalues of multiplicity 3, 5, 4+3 (icosahedral splitting), ...
    let mesh = generate::icosphere(3);
    let dense = analyze(&mesh, &opts(60, Method::Dense)).unwrap();
    let krylov = analyze(&mesh, &opts(60, Method::Krylov)).unwrap();
    assert_same_values(
        &dense.spectrum.eigenvalues,
        &krylov.spectrum.eigenvalues,
        1e-9,
    );
    assert_eq!(krylov.eigen_stats.method, "krylov");
    assert_eq!(dense.eigen_stats.method, "dense");
}

#[test]
fn disconnected_components_kept_give_one_zero_mode_each() {
    let mut a = generate::icosphere(2);
    let mut b = generate::icosphere(2);
    b.transform(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [5.0, 0.0, 0.0],
    );
    let offset = a.vertices.len() as u32;
    a.vertices.extend(b.vertices);
    a.faces
        .extend(b.faces.iter().map(|f| f.map(|i| i + offset)));
    let mut o = opts(8, Method::Auto);
    o.prepare.components = shapeseek::mesh::prepare::ComponentPolicy::All;
    let r = analyze(&a, &o).unwrap();
    let zeros = r
        .spectrum
        .eigenvalues
        .iter()
        .filter(|v| v.abs() < 1e-8)
        .count();
    assert_eq!(zeros, 2, "{:?}", r.spectrum.eigenvalues);
}

#[test]
fn same_shape_in_every_format_gives_the_same_spectrum() {
    use shapeseek::mesh::write::{write_ply, write_stl, PlyEncoding, StlEncoding};
    use shapeseek::mesh::{read_mesh, write_mesh, Format, ReadLimits};
    let mesh = generate::bumpy_sphere(3, 0.25);
    let o = opts(30, Method::Krylov);
    let reference = analyze(&mesh, &o).unwrap().spectrum.eigenvalues;
    let mut files: Vec<(String, Vec<u8>, f64)> = Vec::new();
    for format in Format::ALL {
        let mut bytes = Vec::new();
        write_mesh(&mesh, format, &mut bytes).unwrap();
        // glTF and STL store f32 coordinates: the spectrum moves by about f32 epsilon.
        let tol = if matches!(format, Format::Gltf | Format::Glb | Format::Stl) {
            1e-5
        } else {
            1e-10
        };
        files.push((format.name().to_string(), bytes, tol));
    }
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        let mut bytes = Vec::new();
        write_ply(&mesh, enc, &mut bytes).unwrap();
        files.push((format!("ply {enc:?}"), bytes, 1e-10));
    }
    for enc in [StlEncoding::Ascii, StlEncoding::Binary] {
        let mut bytes = Vec::new();
        write_stl(&mesh, enc, &mut bytes).unwrap();
        files.push((format!("stl {enc:?}"), bytes, 1e-5));
    }
    for (name, bytes, tol) in files {
        // No hint: the format is recognised from the bytes.
        let read = read_mesh(&bytes, None, &ReadLimits::default()).unwrap();
        let ev = analyze(&read, &o).unwrap().spectrum.eigenvalues;
        for (i, (a, b)) in reference.iter().zip(&ev).enumerate().skip(1) {
            assert!((a - b).abs() <= tol * a, "{name}: λ{i} {a} vs {b}");
        }
    }
}

#[test]
fn intrinsic_delaunay_laplacian_is_robust_to_a_bad_triangulation() {
    // The same flat rectangle, meshed well and with sheared interior vertices (obtuse
    // triangles, negative cotangent weights): the intrinsic Delaunay operator's spectrum stays
    // closer to the analytic Neumann spectrum than the plain cotangent one.
    use shapeseek::laplace::LaplacianKind;
    use shapeseek::spectrum::compute_spectrum_with;
    let mut exact: Vec<f64> = (0..8)
        .flat_map(|m| (0..8).map(move |n| PI * PI * ((m * m) as f64 / 4.0 + (n * n) as f64)))
        .collect();
    exact.sort_by(f64::total_cmp);
    let mut mesh = generate::rectangle(2.0, 1.0, 60, 30);
    for (i, v) in mesh.vertices.iter_mut().enumerate() {
        let interior = v[0] > 1e-9 && v[0] < 2.0 - 1e-9 && v[1] > 1e-9 && v[1] < 1.0 - 1e-9;
        if interior {
            v[0] += 0.02 * (((i * 7919) % 101) as f64 / 101.0 - 0.5);
            v[1] += 0.02 * (((i * 104729) % 97) as f64 / 97.0 - 0.5);
        }
    }
    let eo = EigenOptions {
        k: 10,
        ..Default::default()
    };
    let err = |kind| {
        let (s, _, _) = compute_spectrum_with(&mesh, kind, &eo).unwrap();
        (1..10)
            .map(|i| (s.eigenvalues[i] - exact[i]).abs() / exact[i])
            .fold(0.0, f64::max)
    };
    let (plain, robust) = (
        err(LaplacianKind::Cotangent),
        err(LaplacianKind::IntrinsicDelaunay),
    );
    eprintln!(
        "sheared rectangle: cotangent error {plain:.3e}, intrinsic Delaunay error {robust:.3e}"
    );
    assert!(robust <= plain && robust < 0.01, "{robust} vs {plain}");
}

/// A stored signature does not depend on the thread count of the process that computed it: the
/// generated noisy ring (14 462 vertices) signed under the default spec
/// in pools of one, two and three threads gives the same bits. A cluster's workers and a single
/// node sign on pools of different sizes, and their rankings must agree exactly.
#[test]
fn default_signature_does_not_depend_on_the_thread_count() {
    let ring = shapeseek::mesh::samples::samples()
        .into_iter()
        .find(|s| s.id == "ring-noise")
        .expect("the generated noisy ring");
    let spec = shapeseek::presets::default_config().signature;
    let sign = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool")
            .install(|| {
                let (_, sig) = shapeseek::signature::sign(
                    &ring.mesh,
                    &spec,
                    &shapeseek::spectrum::AnalyzeOptions::default(),
                )
                .expect("signed");
                serde_json::to_string(&sig).expect("json")
            })
    };
    let one = sign(1);
    for threads in [2, 3] {
        assert!(
            sign(threads) == one,
            "{threads} threads sign differently from one"
        );
    }
}

/// The server's path from a mesh to its signature under an interrupt: a torus, which the
/// default's alternate cut gives a second version. Whichever check the interrupt fires at — in
/// the first version's analysis or signature or in the second's — the result is
/// `Error::Interrupted`, never a signature (and never one whose missing second version would
/// only mean that its solve was cut short); one check later than the last there is, the
/// signature has both versions.
#[test]
fn an_interrupted_signature_is_an_error_at_every_check() {
    use shapeseek::error::Interrupt;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;
    let engine = shapeseek::index::Engine::new();
    let mesh = generate::bumpy_torus(40, 16);
    let checks = Arc::new(AtomicUsize::new(0));
    let firing_at = |at: usize| {
        checks.store(0, Ordering::Relaxed);
        let c = checks.clone();
        Interrupt::new(move || c.fetch_add(1, Ordering::Relaxed) + 1 >= at)
    };
    let (_, whole) = engine
        .sign_interruptible(&mesh, firing_at(usize::MAX))
        .unwrap();
    assert!(
        whole.alternate.is_some(),
        "the torus should have two versions"
    );
    let total = checks.load(Ordering::Relaxed);
    assert!(total >= 4, "{total} checks");
    eprintln!("{total} checks in the two versions' analyses and signatures");
    for at in 1..=total {
        match engine.sign_interruptible(&mesh, firing_at(at)) {
            Err(shapeseek::Error::Interrupted(_)) => {}
            Err(e) => panic!("check {at} of {total}: {e}"),
            Ok((_, sig)) => panic!(
                "check {at} of {total}: a signature (second version: {})",
                sig.alternate.is_some()
            ),
        }
    }
    let (_, again) = engine
        .sign_interruptible(&mesh, firing_at(total + 1))
        .unwrap();
    assert!(again.alternate.is_some());
}
