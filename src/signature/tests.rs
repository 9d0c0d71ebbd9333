//! Tests of [`crate::signature`] (run in release mode: `cargo test --release --lib signature`).

use super::distributions::FINE_BINS;
use super::kernels::weighted_embedding;
use super::*;
use crate::eigen::EigenOptions;
use crate::mesh::generate;
use crate::mesh::prepare::PrepareOptions;
use crate::mesh::{norm, Mesh};
use crate::ranking::{parzen_histogram, sketch_histogram, Histogram};
use crate::spectrum::Analysis;
use crate::spectrum::{analyze, AnalyzeOptions};
use crate::Error;
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, Par};
use rayon::prelude::*;

fn analysis_of(mesh: &Mesh, k: usize, normalize_area: bool) -> Analysis {
    let opts = AnalyzeOptions {
        prepare: PrepareOptions {
            normalize_area,
            ..PrepareOptions::default()
        },
        eigen: EigenOptions {
            k,
            ..EigenOptions::default()
        },
        ..AnalyzeOptions::default()
    };
    analyze(mesh, &opts).expect("analysis")
}

/// Heat-L2 channels at `times`, in that order.
fn heat_at(times: &[f64]) -> Vec<ChannelSpec> {
    times
        .iter()
        .map(|&t| ChannelSpec::heat(t, Norm::L2))
        .collect()
}

fn heat6() -> Vec<ChannelSpec> {
    heat_at(&DEFAULT_HEAT_SCALES)
}

fn nl1(a: &[f64], b: &[f64]) -> f64 {
    let (sa, sb): (f64, f64) = (a.iter().sum(), b.iter().sum());
    a.iter().zip(b).map(|(x, y)| (x / sa - y / sb).abs()).sum()
}

fn sketch_of(sig: &Signature, i: usize) -> &QuantileSketch {
    match &sig.channels[i].values {
        ChannelValues::Distribution(s) => s,
        ChannelValues::Vector(_) => panic!("not a distribution"),
    }
}

/// All ordered vertex pairs, weights a_x a_y, eq. 9 distances with `w` (GEMM by row blocks).
fn exact_pairs(a: &Analysis, w: &[f64]) -> Vec<(f64, f64)> {
    let phi = a.spectrum.eigenvectors.as_ref();
    let psi = weighted_embedding(phi, w);
    let n = psi.nrows();
    let sq: Vec<f64> = (0..n)
        .map(|i| (0..psi.ncols()).map(|c| psi[(i, c)] * psi[(i, c)]).sum())
        .collect();
    let mass = &a.spectrum.mass;
    let mut out = Vec::with_capacity(n * n);
    let block = 512;
    for r0 in (0..n).step_by(block) {
        let r = block.min(n - r0);
        let mut g = Mat::<f64>::zeros(n, r);
        matmul(
            g.as_mut(),
            Accum::Replace,
            psi.as_ref(),
            psi.as_ref().subrows(r0, r).transpose(),
            1.0,
            Par::rayon(0),
        );
        for ii in 0..r {
            let i = r0 + ii;
            let col = g.col_as_slice(ii);
            for j in 0..n {
                let d = if i == j {
                    0.0
                } else {
                    (sq[i] + sq[j] - 2.0 * col[j]).max(0.0).sqrt()
                };
                out.push((d, mass[i] * mass[j]));
            }
        }
    }
    out
}

/// Weighted `p`-quantile of pairs.
fn weighted_quantile(pairs: &mut [(f64, f64)], p: f64) -> f64 {
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = pairs.iter().map(|x| x.1).sum();
    let mut acc = 0.0;
    for &(d, w) in pairs.iter() {
        acc += w;
        if acc >= p * total {
            return d;
        }
    }
    pairs.last().map_or(0.0, |x| x.0)
}

fn hist(s: &QuantileSketch, window: f64) -> Histogram {
    sketch_histogram(s, window, 256, 1.0)
}

/// Measures, on a generated ~3 000-vertex shape (bumpy torus 75 × 40, k = 100), the nL1 error of
/// the heat-L2 histograms of each spec (its channels at `times`, in order) against binning the
/// exact all-pairs a_x a_y
/// distances directly, on the shape's own 95th-percentile window and on half / twice it (a
/// corpus window differs from the shape's own). Returns per spec (own-window worst,
/// other-windows worst).
fn quadrature_errors(specs: &[(&str, SignatureSpec)], times: &[f64]) -> Vec<(f64, f64)> {
    let mesh = generate::bumpy_torus(75, 40);
    let a = analysis_of(&mesh, 100, true);
    let zero_tol = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI;
    let sigs: Vec<Signature> = specs
        .iter()
        .map(|(_, s)| compute_signature(&a, s).expect("signature"))
        .collect();
    // Every quadrature carries the whole mass of μ × μ (area² = 1).
    for sig in &sigs {
        for c in 0..sig.channels.len() {
            let m = sketch_of(sig, c).mass;
            assert!((m - 1.0).abs() < 1e-9, "mass {m}");
        }
    }
    let mut worst = vec![(0.0f64, 0.0f64); specs.len()];
    for (c, &t) in times.iter().enumerate() {
        let w = transfer_weights(&Kernel::Heat { t }, &a.spectrum.eigenvalues, zero_tol);
        let mut pairs = exact_pairs(&a, &w);
        let window = weighted_quantile(&mut pairs, 0.95);
        let mut line = format!("t={t:<7} window={window:.5}");
        for f in [1.0, 0.5, 2.0] {
            let direct = parzen_histogram(pairs.iter().copied(), f * window, 256, 1.0);
            for (k, ((name, _), sig)) in specs.iter().zip(&sigs).enumerate() {
                let e = nl1(&hist(sketch_of(sig, c), f * window).prob, &direct);
                line += &format!(" {name}@{f}x={e:.4}");
                if f == 1.0 {
                    worst[k].0 = worst[k].0.max(e);
                } else {
                    worst[k].1 = worst[k].1.max(e);
                }
            }
        }
        println!("{line}");
    }
    worst
}

/// The quadrature bar: the default farthest-point quadrature (1 000 samples) is within 0.02 nL1
/// of the exact all-pairs distributions on the shape's own window (measured ≤ 0.008), and within
/// 0.03 on half / twice that window (measured ≤ 0.023, the worst at t = 0.016, half window);
/// the histogram derived from a quantile sketch of the exact pairs is within 0.002 of binning
/// the raw pairs on the own window (measured ≤ 0.001) and 0.01 otherwise (≤ 0.006). Those bars
/// are for the six default scales; the default's two smaller full-range times have their own
/// for the other windows (below).
#[test]
fn quadrature_and_sketch_errors_against_exact_all_pairs() {
    // Own window: sketch < 0.002, quadrature < 0.02; other windows: the bars given.
    let check = |times: &[f64], sketch_other: f64, quadrature_other: f64| {
        let default = SignatureSpec::with_channels(heat_at(times));
        let mut exact = default.clone();
        exact.quadrature = PairQuadrature::AllVertices;
        let w = quadrature_errors(&[("exact", exact), ("default", default)], times);
        println!(
            "{times:?}: worst nL1 (own window, other windows): exact-sketch {:?}, default \
             quadrature {:?}",
            w[0], w[1]
        );
        assert!(
            w[0].0 < 0.002 && w[0].1 < sketch_other,
            "{times:?}: sketch derivation error {:?}",
            w[0]
        );
        assert!(
            w[1].0 < 0.02 && w[1].1 < quadrature_other,
            "{times:?}: quadrature error {:?}",
            w[1]
        );
    };
    check(&DEFAULT_HEAT_SCALES, 0.01, 0.03);
    // The default's two smaller full-range times (presets::DEFAULT_FULL_RANGE_TIMES): the same
    // bars on the shape's own window (measured ≤ 0.0016 and ≤ 0.0076); on half of it the
    // distribution, concentrated near its upper end at these times, leaves the window's lower
    // half to a few of the sketch's 1 025 quantiles, so sketch and quadrature err by up to
    // 0.078 and 0.094 (t = 0.00256; twice the window ≤ 0.010). The bars record that: how far a
    // corpus window (the pooled 90th percentile) falls below a shape's own at these times was
    // not measured (docs/quality.md §22).
    let small: Vec<f64> = crate::presets::DEFAULT_FULL_RANGE_TIMES
        .iter()
        .copied()
        .filter(|t| !DEFAULT_HEAT_SCALES.contains(t))
        .collect();
    check(&small, 0.1, 0.12);
}

/// Sample-count / representative / sketch-size sweep behind the defaults (not a pass/fail test):
/// `cargo test --release --lib signature::tests::quadrature_sweep -- --ignored --nocapture`.
#[test]
#[ignore]
fn quadrature_sweep() {
    let base = SignatureSpec::with_channels(heat6());
    let mut specs = Vec::new();
    for q in [512, 1024, 2048] {
        let mut s = base.clone();
        s.quadrature = PairQuadrature::AllVertices;
        s.sketch_quantiles = q;
        specs.push((["exactQ512", "exactQ1024", "exactQ2048"][q / 1024], s));
    }
    for (name, samples, cell_means, near_field) in [
        ("fps500", 500, false, true),
        ("fps1000", 1000, false, true),
        ("fps1000-nonear", 1000, false, false),
        ("fps1000cm", 1000, true, false),
        ("fps1500", 1500, false, true),
    ] {
        let mut s = base.clone();
        s.quadrature = PairQuadrature::Farthest {
            samples,
            cell_means,
            near_field,
        };
        specs.push((name, s));
    }
    let w = quadrature_errors(&specs, &DEFAULT_HEAT_SCALES);
    for ((n, _), e) in specs.iter().zip(&w) {
        println!("{n}: own window {:.4}, half/twice {:.4}", e.0, e.1);
    }
}

fn quantiles(sig: &Signature, i: usize) -> &[f64] {
    &sketch_of(sig, i).quantiles
}

/// Largest difference of two quantile vectors relative to the larger maximum.
fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = a.iter().chain(b).fold(0.0f64, |m, &x| m.max(x.abs()));
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
        / scale
}

fn rotation(axis: [f64; 3], angle: f64) -> [[f64; 3]; 3] {
    let n = norm(axis);
    let [x, y, z] = axis.map(|c| c / n);
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ]
}

/// eq. 6 (L2 norm of kernel-row differences, A-weighted quadrature over all vertices) equals
/// eq. 9 (eigenmap distance) on a small mesh, for heat, commute-time and step kernels.
#[test]
fn eigenmap_distance_equals_kernel_row_distance() {
    let a = analysis_of(&generate::bumpy_sphere(3, 0.2), 60, true);
    let phi = &a.spectrum.eigenvectors;
    let mass = &a.spectrum.mass;
    let n = phi.nrows();
    let k = phi.ncols();
    let zt = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI;
    for kernel in [
        Kernel::Heat { t: 0.02 },
        Kernel::Heat { t: 0.1 },
        Kernel::CommuteTime,
        Kernel::Step {
            lambda_c: 4.0 * std::f64::consts::PI * 10.0,
        },
    ] {
        let w = transfer_weights(&kernel, &a.spectrum.eigenvalues, zt);
        assert_eq!(w[0], 0.0, "zero mode must get weight 0");
        let row = |x: usize| -> Vec<f64> {
            (0..n)
                .map(|z| (0..k).map(|i| w[i] * phi[(x, i)] * phi[(z, i)]).sum())
                .collect()
        };
        for &(x, y) in &[(0usize, 1usize), (3, 400), (17, 641), (100, 250)] {
            let eq9: f64 = (0..k)
                .map(|i| (w[i] * (phi[(x, i)] - phi[(y, i)])).powi(2))
                .sum::<f64>()
                .sqrt();
            let (rx, ry) = (row(x), row(y));
            let eq6: f64 = (0..n)
                .map(|z| mass[z] * (rx[z] - ry[z]).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(
                (eq6 - eq9).abs() <= 1e-8 * eq9.max(1e-12),
                "{kernel:?} ({x},{y}): eq6 {eq6} eq9 {eq9}"
            );
        }
    }
}

/// The L1 / L∞ channel machinery with every vertex as a quadrature point equals a direct
/// evaluation of `Σ_z a_z |k(x,z) − k(y,z)|` and `max_z |k(x,z) − k(y,z)|` over all pairs.
#[test]
fn lp_channels_match_direct_kernel_rows() {
    let a = analysis_of(&generate::bumpy_sphere(2, 0.2), 40, true);
    let n = a.mesh.vertices.len();
    let mut spec = SignatureSpec::with_channels(vec![
        ChannelSpec::heat(0.05, Norm::L1),
        ChannelSpec::heat(0.05, Norm::LInf),
    ]);
    spec.lp_samples = n;
    let sig = compute_signature(&a, &spec).expect("signature");
    let phi = &a.spectrum.eigenvectors;
    let mass = &a.spectrum.mass;
    let k = phi.ncols();
    let zt = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI;
    let w = transfer_weights(&Kernel::Heat { t: 0.05 }, &a.spectrum.eigenvalues, zt);
    let rows: Vec<Vec<f64>> = (0..n)
        .map(|x| {
            (0..n)
                .map(|z| (0..k).map(|i| w[i] * phi[(x, i)] * phi[(z, i)]).sum())
                .collect()
        })
        .collect();
    for (c, inf) in [(0usize, false), (1, true)] {
        let mut pairs = Vec::with_capacity(n * n);
        for x in 0..n {
            for y in 0..n {
                let d = if inf {
                    (0..n).fold(0.0f64, |m, z| m.max((rows[x][z] - rows[y][z]).abs()))
                } else {
                    (0..n)
                        .map(|z| mass[z] * (rows[x][z] - rows[y][z]).abs())
                        .sum()
                };
                pairs.push((d, mass[x] * mass[y]));
            }
        }
        // Every stored quantile lies (to within two fine bins) between the exact weighted
        // quantiles just below and just above its level.
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
        let total: f64 = pairs.iter().map(|p| p.1).sum();
        let mut cum = Vec::with_capacity(pairs.len());
        let mut acc = 0.0;
        for p in &pairs {
            acc += p.1;
            cum.push(acc);
        }
        let at = |level: f64| -> f64 {
            let i = cum
                .partition_point(|&c| c < level * total)
                .min(pairs.len() - 1);
            pairs[i].0
        };
        let dmax = pairs.last().expect("pairs").0;
        let qs = quantiles(&sig, c);
        let nq = qs.len() - 1;
        let tol = 4.0 * dmax / FINE_BINS as f64;
        for (j, &qv) in qs.iter().enumerate().skip(1).take(nq - 1) {
            let level = j as f64 / nq as f64;
            let (lo, hi) = (at(level - 1e-9), at(level + 1e-9));
            assert!(
                qv >= lo - tol && qv <= hi + tol,
                "channel {c} q{j}: {qv} not in [{lo}, {hi}]"
            );
        }
        let smax = *qs.last().expect("quantiles");
        assert!((dmax - smax).abs() <= 1e-9 * dmax, "max {dmax} vs {smax}");
    }
}

/// Commute-time distances are scale invariant (eq. 19, §3.1): scaling a mesh without area
/// normalisation leaves the normalised CT distribution unchanged (mass × s⁴); heat is not.
#[test]
fn commute_time_is_scale_invariant_heat_is_not() {
    let base = generate::bumpy_sphere(3, 0.2);
    let mut big = base.clone();
    big.scale(2.5);
    let spec = SignatureSpec::with_channels(vec![
        ChannelSpec::commute_time(),
        ChannelSpec::heat(0.1, Norm::L2),
    ]);
    let s1 = compute_signature(&analysis_of(&base, 60, false), &spec).expect("sig");
    let s2 = compute_signature(&analysis_of(&big, 60, false), &spec).expect("sig");
    let ct = rel_diff(quantiles(&s1, 0), quantiles(&s2, 0));
    let heat = rel_diff(quantiles(&s1, 1), quantiles(&s2, 1));
    println!("relative quantile change under scaling: CT {ct:.2e}, heat {heat:.2e}");
    assert!(ct < 1e-6, "CT changed by {ct}");
    assert!(heat > 0.1, "heat unchanged ({heat})");
    let ratio = sketch_of(&s2, 0).mass / sketch_of(&s1, 0).mass;
    assert!(
        (ratio - 2.5f64.powi(4)).abs() < 1e-9 * ratio,
        "mass ratio {ratio}"
    );
}

/// Rigid motions and vertex/face permutations leave the distributions unchanged.
#[test]
fn invariant_to_rigid_motion_and_permutation() {
    let base = generate::bumpy_sphere(3, 0.25);
    let spec = SignatureSpec::with_channels(heat6());
    let s0 = compute_signature(&analysis_of(&base, 100, true), &spec).expect("sig");

    let mut moved = base.clone();
    moved.transform(rotation([1.0, 2.0, 3.0], 0.7), [3.0, -1.0, 0.5]);
    let s1 = compute_signature(&analysis_of(&moved, 100, true), &spec).expect("sig");

    // Permute vertices, reverse the face order and rotate each face's indices.
    let n = base.vertices.len();
    let perm: Vec<usize> = (0..n).map(|i| (i * 7919 + 13) % n).collect();
    let mut inv = vec![0u32; n];
    for (new, &old) in perm.iter().enumerate() {
        inv[old] = new as u32;
    }
    let vertices = perm.iter().map(|&old| base.vertices[old]).collect();
    let faces = base
        .faces
        .iter()
        .rev()
        .map(|f| [inv[f[1] as usize], inv[f[2] as usize], inv[f[0] as usize]])
        .collect();
    let permuted = Mesh::new(vertices, faces);
    let s2 = compute_signature(&analysis_of(&permuted, 100, true), &spec).expect("sig");
    let (mut rigid, mut permd) = (0.0f64, 0.0f64);
    for c in 0..spec.channels.len() {
        rigid = rigid.max(rel_diff(quantiles(&s0, c), quantiles(&s1, c)));
        permd = permd.max(rel_diff(quantiles(&s0, c), quantiles(&s2, c)));
    }
    println!("relative quantile change: rigid motion {rigid:.2e}, permutation {permd:.2e}");
    assert!(
        rigid < 1e-7,
        "rigid motion changed the signature by {rigid}"
    );
    assert!(permd < 1e-7, "permutation changed the signature by {permd}");
}

#[test]
fn serialisation_round_trip_and_determinism() {
    let a = analysis_of(&generate::bumpy_sphere(2, 0.2), 60, true);
    let spec = SignatureSpec::with_channels(vec![
        ChannelSpec::heat(0.04, Norm::L2),
        ChannelSpec::commute_time(),
        ChannelSpec::shape_dna(20),
        ChannelSpec::d2(300),
        ChannelSpec::geodesic(Some(0.3)),
    ]);
    let s = compute_signature(&a, &spec).expect("sig");
    let bytes = s.to_bytes();
    let back = Signature::from_bytes(&bytes).expect("decode");
    assert_eq!(back, s);
    assert_eq!(back.to_bytes(), bytes);
    // Determinism: a second computation gives the same bytes.
    assert_eq!(compute_signature(&a, &spec).expect("sig").to_bytes(), bytes);
    // Malformed input is a corruption error (these bytes are only read back from storage),
    // never a panic.
    let corrupt = |b: &[u8]| Signature::from_bytes(b).map(|_| ()).unwrap_err().code();
    for cut in [0, 3, 4, 10, bytes.len() / 2, bytes.len() - 1] {
        assert_eq!(corrupt(&bytes[..cut]), "storage.corrupt", "cut {cut}");
    }
    let mut bad = bytes.clone();
    bad.push(0);
    assert_eq!(corrupt(&bad), "storage.corrupt");
    bad = bytes.clone();
    bad[0] = b'X';
    assert_eq!(corrupt(&bad), "storage.corrupt");
    assert_eq!(s.spec_key, spec.key());
    assert_eq!(s.channels[3].name, "d2[n=300]");
    assert_eq!(s.channels[4].name, "geo[r=0.3]");
}

/// Closed forms on the sphere (unit area, radius r = 1/√(4π)): D2 has CDF (d/2r)², the
/// geodesic distance CDF is (1 − cos(g/r))/2, ShapeDNA starts with λ = 2/r² (×3), 6/r² (×5).
#[test]
fn baselines_on_the_sphere() {
    let a = analysis_of(&generate::icosphere(4), 60, true);
    let spec = SignatureSpec::with_channels(vec![
        ChannelSpec::d2(2000),
        ChannelSpec::geodesic(None),
        ChannelSpec::shape_dna(8),
        ChannelSpec::geodesic(Some(0.2)),
    ]);
    let s = compute_signature(&a, &spec).expect("sig");
    let r = (1.0 / (4.0 * std::f64::consts::PI)).sqrt();
    // Radius cap: only pairs closer than 0.2 remain; on the sphere their share of μ × μ is
    // (1 − cos(0.2/r))/2 (up to the edge-graph excess).
    let capped = sketch_of(&s, 3);
    assert!(*capped.quantiles.last().expect("q") <= 0.2);
    let share = capped.mass / sketch_of(&s, 1).mass;
    let expected = (1.0 - (0.2 / r).cos()) / 2.0;
    assert!(
        share < expected && share > 0.7 * expected,
        "capped share {share} vs {expected}"
    );
    let d2 = quantiles(&s, 0);
    let q = d2.len() - 1;
    let mut d2_err = 0.0f64;
    for (j, &d) in d2.iter().enumerate() {
        let expected = 2.0 * r * (j as f64 / q as f64).sqrt();
        d2_err = d2_err.max((d - expected).abs() / (2.0 * r));
    }
    // Geodesic: edge-graph paths overestimate; measure the mean relative excess on the
    // quantiles between 10 % and 90 %.
    let geo = quantiles(&s, 1);
    let mut excess = Vec::new();
    for (j, &g) in geo.iter().enumerate() {
        let p = j as f64 / q as f64;
        if (0.1..=0.9).contains(&p) {
            let expected = r * (1.0 - 2.0 * p).acos();
            excess.push(g / expected - 1.0);
        }
    }
    let mean_excess = excess.iter().sum::<f64>() / excess.len() as f64;
    println!("D2 max quantile error {d2_err:.4} (of the diameter); edge-graph geodesic mean excess {:.2} %", 100.0 * mean_excess);
    assert!(d2_err < 0.05, "D2 quantiles off by {d2_err}");
    assert!(
        mean_excess > 0.0 && mean_excess < 0.1,
        "geodesic excess {mean_excess}"
    );
    match &s.channels[2].values {
        ChannelValues::Vector(v) => {
            assert_eq!(v.len(), 8);
            for (i, &l) in v.iter().enumerate() {
                let expected = if i < 3 { 2.0 } else { 6.0 } / (r * r);
                assert!(
                    (l / expected - 1.0).abs() < 0.01,
                    "λ_{} = {l}, expected {expected}",
                    i + 1
                );
            }
        }
        ChannelValues::Distribution(_) => panic!("ShapeDNA must be a vector"),
    }
}

/// A weighted ShapeDNA channel holds the eigenvalues times its weight, under its own name; the
/// unit weight leaves the JSON, the name and the key of an unweighted spec as they were.
#[test]
fn weighted_shape_dna_scales_the_eigenvalues() {
    let a = analysis_of(&generate::icosphere(3), 30, true);
    let plain = ChannelSpec::shape_dna(10);
    let weighted = ChannelSpec::weighted_shape_dna(10, 0.25);
    assert_eq!(plain.name(), "shapedna[10]");
    assert_eq!(weighted.name(), "shapedna[10][w=0.25]");
    assert_eq!(
        serde_json::to_string(&plain).expect("json"),
        r#"{"kind":{"shape_dna":{"count":10}}}"#
    );
    let back: ChannelSpec =
        serde_json::from_str(r#"{"kind":{"shape_dna":{"count":10,"weight":0.25}}}"#)
            .expect("parse");
    assert_eq!(back, weighted);
    // The weight is part of the key: a stored signature of another weight is stale.
    assert_ne!(
        SignatureSpec::with_channels(vec![weighted.clone()]).key(),
        SignatureSpec::with_channels(vec![plain.clone()]).key()
    );
    let spec = SignatureSpec::with_channels(vec![plain, weighted]);
    let s = compute_signature(&a, &spec).expect("sig");
    match (&s.channels[0].values, &s.channels[1].values) {
        (ChannelValues::Vector(x), ChannelValues::Vector(y)) => {
            assert_eq!(x.len(), 10);
            for (l, w) in x.iter().zip(y) {
                assert_eq!(*w, 0.25 * l);
            }
        }
        _ => panic!("ShapeDNA must be a vector"),
    }
    for w in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let bad = SignatureSpec::with_channels(vec![ChannelSpec::weighted_shape_dna(10, w)]);
        assert!(compute_signature(&a, &bad).is_err(), "weight {w} accepted");
    }
}

/// Kernel-, distance- and distribution-stage aggregation against their definitions.
#[test]
fn aggregation_stages() {
    let a = analysis_of(&generate::bumpy_sphere(2, 0.2), 60, true);
    let ts = vec![0.02, 0.05];
    let spec = SignatureSpec::with_channels(vec![
        ChannelSpec::heat(0.02, Norm::L2),
        ChannelSpec {
            kind: ChannelKind::DistanceAggregate {
                ts: vec![0.02],
                norm: Norm::L2,
                aggregation: Aggregation::Sum,
            },
        },
        ChannelSpec {
            kind: ChannelKind::DistributionSum {
                ts: vec![0.02, 0.02],
                norm: Norm::L2,
            },
        },
        ChannelSpec {
            kind: ChannelKind::Spectral {
                kernel: Kernel::HeatAggregate {
                    ts: ts.clone(),
                    aggregation: Aggregation::Sum2,
                },
                norm: Norm::L2,
            },
        },
        ChannelSpec {
            kind: ChannelKind::DistanceAggregate {
                ts: ts.clone(),
                norm: Norm::L2,
                aggregation: Aggregation::Sum2,
            },
        },
        ChannelSpec {
            kind: ChannelKind::DistanceAggregate {
                ts: ts.clone(),
                norm: Norm::L2,
                aggregation: Aggregation::Max,
            },
        },
    ]);
    let s = compute_signature(&a, &spec).expect("sig");
    // A one-scale distance aggregate and a doubled distribution sum are the single scale.
    assert!(rel_diff(quantiles(&s, 0), quantiles(&s, 1)) < 1e-12);
    assert!(rel_diff(quantiles(&s, 0), quantiles(&s, 2)) < 1e-12);
    let m0 = sketch_of(&s, 0).mass;
    assert!((sketch_of(&s, 2).mass - 2.0 * m0).abs() < 1e-12 * m0);
    // Kernel sum² gives d = (Σ d_t²)^{1/2}; distance sum² gives Σ d_t²: same ranks, so the
    // quantiles agree after squaring (up to the fine-bin interpolation).
    let k2: Vec<f64> = quantiles(&s, 3).iter().map(|x| x * x).collect();
    let e = rel_diff(&k2, quantiles(&s, 4));
    assert!(e < 2e-3, "kernel vs distance sum²: {e}");
    // max_t d_t = d_{min t} for heat distances at these scales? Not in general; check bounds:
    // every quantile of max lies between those of the single scales' max and their sum.
    let single = SignatureSpec::with_channels(vec![
        ChannelSpec::heat(0.02, Norm::L2),
        ChannelSpec::heat(0.05, Norm::L2),
    ]);
    let ss = compute_signature(&a, &single).expect("sig");
    let (q1, q2, qm) = (quantiles(&ss, 0), quantiles(&ss, 1), quantiles(&s, 5));
    let top = q1.last().expect("q").max(*q2.last().expect("q"));
    for j in 0..qm.len() {
        assert!(
            qm[j] + 1e-3 * top >= q1[j].max(q2[j]),
            "max below a scale at {j}"
        );
        assert!(
            qm[j] <= q1[j] + q2[j] + 1e-3 * top,
            "max above the sum at {j}"
        );
    }
}

#[test]
fn invalid_specs_are_errors() {
    let a = analysis_of(&generate::icosphere(2), 30, true);
    for c in [
        ChannelSpec::heat(0.0, Norm::L2),
        ChannelSpec::heat(f64::NAN, Norm::L2),
        ChannelSpec::step(-1.0),
        ChannelSpec::shape_dna(100),
        ChannelSpec::d2(1),
    ] {
        let r = compute_signature(&a, &SignatureSpec::with_channels(vec![c.clone()]));
        assert!(
            matches!(r, Err(Error::InvalidArgument(_))),
            "{} accepted",
            c.name()
        );
    }
    let mut spec = SignatureSpec::with_channels(heat6());
    spec.sketch_quantiles = 0;
    assert!(compute_signature(&a, &spec).is_err());
}

/// A truncated channel is the short range of its full channel: half the mass at the median,
/// the lower half of the quantiles, the same normalised histogram on `[0, r]`; computed once
/// beside its full channel or alone, with the same values.
#[test]
fn truncated_channel_is_the_short_range_of_the_full_one() {
    let a = analysis_of(&generate::bumpy_torus(40, 20), 60, true);
    let full = ChannelSpec::heat(0.04, Norm::L2);
    let sig_full =
        compute_signature(&a, &SignatureSpec::with_channels(vec![full.clone()])).unwrap();
    let s = sketch_of(&sig_full, 0).clone();
    let nq = s.quantiles.len() - 1;
    let r = s.quantiles[nq / 2];
    let tr = ChannelSpec {
        kind: ChannelKind::Truncated {
            channel: Box::new(full.kind.clone()),
            radius: r,
        },
    };
    assert_eq!(tr.name(), format!("heat-l2[t=0.04][r={r}]"));
    let alone = compute_signature(&a, &SignatureSpec::with_channels(vec![tr.clone()])).unwrap();
    let both = compute_signature(
        &a,
        &SignatureSpec::with_channels(vec![full.clone(), tr.clone()]),
    )
    .unwrap();
    assert_eq!(both.channels[0], sig_full.channels[0]);
    assert_eq!(both.channels[1], alone.channels[0]);
    assert_eq!(alone.channels[0].name, tr.name());

    let t = sketch_of(&alone, 0);
    assert_eq!(t.quantiles.len(), nq + 1);
    assert!((t.mass / s.mass - 0.5).abs() < 1e-9, "{}", t.mass / s.mass);
    assert_eq!(t.quantiles[nq], r);
    for i in 0..=nq / 2 {
        assert!(
            (t.quantiles[2 * i] - s.quantiles[i]).abs() <= 1e-9 * r,
            "level {i}"
        );
    }
    let (hf, ht) = (hist(&s, r), hist(t, r));
    let e = nl1(&hf.density, &ht.density);
    assert!(e < 1e-3, "nL1 on [0, r] {e}");

    let top = s.quantiles[nq];
    assert_eq!(truncate_sketch(&s, 2.0 * top), s);
    let empty = truncate_sketch(&s, 0.5 * s.quantiles[0]);
    assert_eq!(empty.mass, 0.0);

    for bad in [
        ChannelKind::Truncated {
            channel: Box::new(full.kind.clone()),
            radius: 0.0,
        },
        ChannelKind::Truncated {
            channel: Box::new(tr.kind.clone()),
            radius: r,
        },
        ChannelKind::Truncated {
            channel: Box::new(ChannelSpec::shape_dna(10).kind),
            radius: r,
        },
    ] {
        let c = ChannelSpec { kind: bad };
        let res = compute_signature(&a, &SignatureSpec::with_channels(vec![c.clone()]));
        assert!(
            matches!(res, Err(Error::InvalidArgument(_))),
            "{} accepted",
            c.name()
        );
    }
}

/// Two components: both zero modes get weight 0 and the distributions stay finite.
#[test]
fn two_components_have_two_zero_modes() {
    let mut b = generate::icosphere(2);
    b.transform(rotation([0.0, 0.0, 1.0], 0.0), [5.0, 0.0, 0.0]);
    let a0 = generate::bumpy_sphere(2, 0.2);
    let off = a0.vertices.len() as u32;
    let mut mesh = a0.clone();
    mesh.vertices.extend(b.vertices.iter().copied());
    mesh.faces
        .extend(b.faces.iter().map(|f| f.map(|i| i + off)));
    let opts = AnalyzeOptions {
        prepare: PrepareOptions {
            components: crate::mesh::prepare::ComponentPolicy::All,
            ..PrepareOptions::default()
        },
        eigen: EigenOptions {
            k: 30,
            ..EigenOptions::default()
        },
        ..AnalyzeOptions::default()
    };
    let a = analyze(&mesh, &opts).expect("analysis");
    let zt = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI;
    let w = transfer_weights(&Kernel::CommuteTime, &a.spectrum.eigenvalues, zt);
    assert_eq!(w.iter().filter(|&&x| x == 0.0).count(), 2);
    let s = compute_signature(
        &a,
        &SignatureSpec::with_channels(vec![
            ChannelSpec::commute_time(),
            ChannelSpec::geodesic(None),
        ]),
    )
    .expect("sig");
    for c in 0..2 {
        assert!(quantiles(&s, c).iter().all(|x| x.is_finite()));
    }
}

/// The quadrature bar at 10 000 vertices (bumpy torus 125 × 80, k = 100): exact all-pairs
/// histograms are streamed block by block (O(n² k), minutes), so this is not a regular test:
/// `cargo test --release --lib signature::tests::quadrature_error_10k -- --ignored --nocapture`.
#[test]
#[ignore]
fn quadrature_error_10k() {
    let mesh = generate::bumpy_torus(125, 80);
    let a = analysis_of(&mesh, 100, true);
    let n = a.mesh.vertices.len();
    let zero_tol = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI;
    let default = SignatureSpec::with_channels(heat6());
    let t = std::time::Instant::now();
    let sig = compute_signature(&a, &default).expect("signature");
    println!(
        "default signature {:.0} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let mut exact_spec = default.clone();
    exact_spec.quadrature = PairQuadrature::AllVertices;
    let exact = compute_signature(&a, &exact_spec).expect("exact signature");
    let mass = &a.spectrum.mass;
    let factors = [1.0, 0.5, 2.0];
    let mut worst = [0.0f64; 3];
    let mut worst_sketch = [0.0f64; 3];
    for (c, &tt) in DEFAULT_HEAT_SCALES.iter().enumerate() {
        let es = sketch_of(&exact, c);
        let q = es.quantiles.len() - 1;
        let p95 = es.quantiles[(0.95 * q as f64).round() as usize];
        let w = transfer_weights(&Kernel::Heat { t: tt }, &a.spectrum.eigenvalues, zero_tol);
        let psi = weighted_embedding(a.spectrum.eigenvectors.as_ref(), &w);
        let sq: Vec<f64> = (0..n)
            .map(|i| (0..psi.ncols()).map(|k| psi[(i, k)] * psi[(i, k)]).sum())
            .collect();
        let block = 256;
        let parts: Vec<Vec<Vec<f64>>> = (0..n.div_ceil(block))
            .into_par_iter()
            .map(|b| {
                let r0 = b * block;
                let r = block.min(n - r0);
                let mut g = Mat::<f64>::zeros(n, r);
                matmul(
                    g.as_mut(),
                    Accum::Replace,
                    psi.as_ref(),
                    psi.as_ref().subrows(r0, r).transpose(),
                    1.0,
                    Par::Seq,
                );
                let mut raw = vec![vec![0.0; 256]; 3];
                for ii in 0..r {
                    let i = r0 + ii;
                    let col = g.col_as_slice(ii);
                    for j in 0..n {
                        let d = if i == j {
                            0.0
                        } else {
                            (sq[i] + sq[j] - 2.0 * col[j]).max(0.0).sqrt()
                        };
                        let wt = mass[i] * mass[j];
                        for (f, rw) in factors.iter().zip(raw.iter_mut()) {
                            let win = f * p95;
                            if d > win {
                                continue;
                            }
                            let u = d * 256.0 / win - 0.5;
                            if u <= 0.0 {
                                rw[0] += wt;
                            } else if u >= 255.0 {
                                rw[255] += wt;
                            } else {
                                let k = u as usize;
                                let fr = u - k as f64;
                                rw[k] += wt * (1.0 - fr);
                                rw[k + 1] += wt * fr;
                            }
                        }
                    }
                }
                raw
            })
            .collect();
        let mut line = format!("t={tt:<7}");
        for (fi, f) in factors.iter().enumerate() {
            let win = f * p95;
            let mut raw = vec![0.0; 256];
            for p in &parts {
                for (x, y) in raw.iter_mut().zip(&p[fi]) {
                    *x += y;
                }
            }
            let h = win / 256.0;
            let direct = parzen_histogram(
                raw.iter()
                    .enumerate()
                    .map(|(b, &m)| ((b as f64 + 0.5) * h, m)),
                win,
                256,
                1.0,
            );
            let e = nl1(&hist(sketch_of(&sig, c), win).prob, &direct);
            let es_err = nl1(&hist(es, win).prob, &direct);
            worst[fi] = worst[fi].max(e);
            worst_sketch[fi] = worst_sketch[fi].max(es_err);
            line += &format!("  {f}x window: fps1000 {e:.4} exact-sketch {es_err:.4}");
        }
        println!("{line}");
    }
    println!(
        "worst nL1 at 1x / 0.5x / 2x window: default {worst:.4?}, exact sketch {worst_sketch:.4?}"
    );
    assert!(worst[0] < 0.02);
}

/// Quadrature error of the L1 / L∞ channels (300, 500, 800 nodes) against 1 200 nodes on a
/// 2 562-vertex shape (not a pass/fail test:
/// `cargo test --release --lib signature::tests::lp_quadrature_error -- --ignored --nocapture`).
#[test]
#[ignore]
fn lp_quadrature_error() {
    let a = analysis_of(&generate::bumpy_sphere(4, 0.2), 100, true);
    let n = 1200;
    let chans = vec![
        ChannelSpec::heat(0.04, Norm::L1),
        ChannelSpec::heat(0.1, Norm::L1),
        ChannelSpec::heat(0.1, Norm::LInf),
    ];
    let mut exact = SignatureSpec::with_channels(chans.clone());
    exact.lp_samples = n;
    let e = compute_signature(&a, &exact).expect("sig");
    for m in [300, 500, 800] {
        let mut s = SignatureSpec::with_channels(chans.clone());
        s.lp_samples = m;
        let sig = compute_signature(&a, &s).expect("sig");
        for (c, ch) in chans.iter().enumerate() {
            let es = sketch_of(&e, c);
            let w = es.quantiles[(0.95 * (es.quantiles.len() - 1) as f64) as usize];
            let err = nl1(&hist(sketch_of(&sig, c), w).prob, &hist(es, w).prob);
            println!("{} with {m} nodes vs {n}: nL1 {err:.4}", ch.name());
        }
    }
}

/// A spec's smoothing reaches both versions' preparation, changes the key only when set, and is
/// validated like the other preparation steps (`docs/quality.md` §25).
#[test]
fn smoothing_is_a_preparation_step_of_both_versions() {
    use crate::mesh::smooth::SmoothOptions;
    use crate::mesh::topology::HandleCutOptions;
    let plain = SignatureSpec::with_channels(heat6());
    assert!(!plain.has_own_preparation());
    assert!(!serde_json::to_string(&plain).unwrap().contains("smooth"));
    let spec = SignatureSpec {
        smooth: Some(SmoothOptions::steps(5)),
        alternate_cut: Some(HandleCutOptions::default()),
        ..plain.clone()
    };
    assert!(spec.has_own_preparation());
    assert_ne!(spec.key(), plain.key());
    let base = AnalyzeOptions::default();
    assert_eq!(
        spec.analysis_options(&base).prepare.smooth,
        Some(SmoothOptions::steps(5))
    );
    let alt = spec.alternate_analysis_options(&base).unwrap();
    assert_eq!(alt.prepare.smooth, Some(SmoothOptions::steps(5)));
    assert!(alt.prepare.cut_handles.is_some());
    assert_eq!(plain.analysis_options(&base).prepare, base.prepare);
    let bad = SignatureSpec {
        smooth: Some(SmoothOptions {
            mu: -0.1,
            ..SmoothOptions::steps(5)
        }),
        ..plain
    };
    let e = super::spec::validate_spec(&bad).unwrap_err().to_string();
    assert!(e.contains("smooth: mu"), "{e}");
}

/// The heat kernel signature's quantiles on a hand-made spectrum: two vertices of equal mass,
/// one eigenpair (the zero mode) with `φ² = ¼, ¾`: the ratios `A h / trace` are ½ and 3/2, at
/// mid-mass positions ¼ and ¾; quantiles between them interpolate, beyond them clamp; every
/// value is scaled by `weight / q`.
#[test]
fn heat_quantiles_on_a_two_vertex_spectrum() {
    let phi = Mat::from_fn(2, 1, |i, _| if i == 0 { 0.5 } else { 0.75f64.sqrt() });
    let mass = [1.0, 1.0];
    let (lo, hi) = (0.5f64.ln(), 1.5f64.ln());
    let v = compute::heat_quantiles(phi.as_ref(), &[0.0], &mass, &[0.01], 4, 1.0);
    let expect = [lo, lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo), hi];
    for (a, b) in v.iter().zip(expect) {
        assert!((a - b / 4.0).abs() < 1e-12, "{v:?}");
    }
    // Two times, q = 2, weight 3: the same two values per time (the zero mode does not decay).
    let v = compute::heat_quantiles(phi.as_ref(), &[0.0], &mass, &[0.01, 0.1], 2, 3.0);
    for (a, b) in v.iter().zip([lo, hi, lo, hi]) {
        assert!((a - 1.5 * b).abs() < 1e-12, "{v:?}");
    }
}

/// On a sphere every point is alike, so the heat kernel signature is the same everywhere and
/// every quantile of `log(A h / trace)` is close to 0 (the icosphere is not exactly uniform);
/// the channel is unchanged by a uniform scaling of the input (unit-area preparation); its
/// quantiles are non-decreasing per time; an invalid channel is refused.
#[test]
fn heat_quantiles_of_a_sphere_and_a_scaled_shape() {
    let ts = [0.005, 0.01, 0.05];
    let spec = SignatureSpec::with_channels(vec![ChannelSpec::heat_quantiles(&ts, 16, 1.0)]);
    assert_eq!(
        spec.channels[0].name(),
        "hks-q[t=0.005,0.01,0.05][n=16][w=1]"
    );
    let sphere =
        compute_signature(&analysis_of(&generate::icosphere(4), 80, true), &spec).expect("sphere");
    let ChannelValues::Vector(v) = &sphere.channels[0].values else {
        panic!("a vector channel")
    };
    assert_eq!(v.len(), 48);
    // Values are log ratios / 16: |log ratio| < 0.05 on the icosphere.
    assert!(v.iter().all(|x| (16.0 * x).abs() < 0.05), "{v:?}");

    let shape = generate::bumpy_sphere(3, 0.2);
    let mut big = shape.clone();
    for p in big.vertices.iter_mut() {
        for c in p.iter_mut() {
            *c *= 3.7;
        }
    }
    let a_analysis = analysis_of(&shape, 80, true);
    let a = compute_signature(&a_analysis, &spec).expect("shape");
    let b = compute_signature(&analysis_of(&big, 80, true), &spec).expect("scaled");
    let (ChannelValues::Vector(x), ChannelValues::Vector(y)) =
        (&a.channels[0].values, &b.channels[0].values)
    else {
        panic!("vector channels")
    };
    for (p, q) in x.iter().zip(y) {
        assert!((p - q).abs() < 1e-6, "{p} vs {q}");
    }
    // A bumpy shape is not uniform: its spread at the smallest time is far larger than the
    // sphere's.
    assert!(
        x[15] - x[0] > 5.0 * (v[15] - v[0]),
        "bumpy {} vs sphere {}",
        x[15] - x[0],
        v[15] - v[0]
    );
    for block in x.chunks(16) {
        assert!(block.windows(2).all(|w| w[0] <= w[1]), "{block:?}");
    }
    for bad in [
        ChannelSpec::heat_quantiles(&[], 16, 1.0),
        ChannelSpec::heat_quantiles(&[0.01], 0, 1.0),
        ChannelSpec::heat_quantiles(&[0.01], 16, 0.0),
        ChannelSpec::heat_quantiles(&[-0.01], 16, 1.0),
    ] {
        let s = SignatureSpec::with_channels(vec![bad]);
        assert!(
            compute_signature(&a_analysis, &s).is_err(),
            "{:?}",
            s.channels
        );
    }
}
