//! The numerical core's output, pinned to `shapeseek::ALGORITHM_REVISION`.
//!
//! A welded sample biped goes through the product's path: preparation with the default's handle
//! cutting, the eigenpairs, the default signature (`index::engine::Engine::sign`, as `serve` and
//! `eval --config default` compute it; a torus gives the second cut version) and the re-ranking payload the server stores with it. A few figures of each stage must equal the ones recorded
//! below for the current revision (integers exactly, reals to 1e-6 relative).
//!
//! When this fails after a change that moves spectra or signatures on purpose, bump
//! `ALGORITHM_REVISION` in `src/lib.rs` and paste the figures the failure prints (recorded at
//! the next revision, so pasting them without the bump still fails): stored indexes
//! then recompute their signatures at the next start, and eval's cache stops serving the older
//! code's analyses. When the change was not meant to move them, the failure found a regression.
//! A change of the default *specification* (its channels, say) moves the figures without
//! moving the code: the spec's key changes on its own, so the figures are re-recorded at the
//! same revision (as for the seven channels of `docs/quality.md` §22 and the weighted
//! ShapeDNA channel of §24).

use shapeseek::index::engine::Engine;
use shapeseek::mesh::samples::class_mesh;
use shapeseek::mesh::weld::{weld, WeldOptions};
use shapeseek::rerank::{compute_payload, PayloadSpec};
use shapeseek::signature::ChannelValues;
use shapeseek::ALGORITHM_REVISION;

/// Revision the figures below were recorded at.
const RECORDED_AT: u32 = 0;

/// Vertices and faces of the prepared (cut) mesh, vertices of the signature's mesh, samples of
/// the payload.
const RECORDED_COUNTS: [usize; 4] = [4819, 9572, 4819, 100];

/// Eigenvalues 1–8, then per channel the sketch's total mass and its quantiles at 10, 50 and
/// 90 % (a vector channel: its first four values), then the signature's area; then the payload's first sample weight, the mean of its
/// distances per time and its `lambda1`; then the vertices, sketch figures and area of the second
/// cut version of a torus (a genuine handle, cut only by the default's alternate rule).
const RECORDED: &[f64] = &[
    6.698553331821036,
    13.690990496838664,
    14.270558689116001,
    19.79882613817764,
    30.59973720958614,
    62.62054032816202,
    78.28903229759395,
    80.44101047349181,
    0.9999999999999932,
    4.897737496648487,
    5.56600610912376,
    6.246948969310587,
    0.9999999999999927,
    2.402057362247952,
    3.6085072234744144,
    4.684053795697001,
    0.9999999999999976,
    1.0576580452689928,
    2.454558199960378,
    3.663632102191774,
    0.9999999999999932,
    0.4335068159102068,
    1.588729757682824,
    2.5463274838454497,
    0.7438283443973497,
    0.8941571541152668,
    2.0712746870672354,
    2.9148342369741496,
    0.7142553749886411,
    0.3391403308556119,
    1.209080377182317,
    1.9372673808102991,
    0.7438998781117984,
    0.14752290082844424,
    0.5953160977839276,
    0.9716340349983408,
    0.004099759471691184,
    0.00837938659077439,
    0.008734103507708155,
    0.012117605245115539,
    0.9999999999999987,
    0.012083825923129784,
    2.460301521199219,
    1.592338511540291,
    0.7984462107262913,
    6.698553331821036,
    1424.0,
    0.9999999999999987,
    4.739791463816742,
    5.454232498225898,
    6.077583925234935,
    1.000000000000003,
    2.0513339419178607,
    3.575712566098106,
    4.122848917209321,
    1.0000000000000013,
    0.9346028495797329,
    2.709561561727102,
    3.231942405265626,
    1.000000000000004,
    0.4636205424785339,
    2.011283098260996,
    2.601531356392864,
    0.8563254074367755,
    0.804078118037283,
    2.6651572842088025,
    2.9372091491952275,
    0.5499300131585335,
    0.23290721315667962,
    1.2832612884477346,
    2.0003692407575846,
    0.4253653183742152,
    0.08929102158621038,
    0.5179077543077255,
    0.9779829312634041,
    0.0010818493033957386,
    0.004320531847155062,
    0.009695590640442087,
    0.017173412428440178,
    0.9999999999999805,
];

fn figures() -> ([usize; 4], Vec<f64>) {
    let biped = class_mesh("biped", 0, false);
    let (welded, report) = weld(
        &biped,
        &WeldOptions {
            bridges: 2,
            disc_radius_edges: 2.0,
            seed: 42,
            ..WeldOptions::default()
        },
    )
    .expect("the biped welds");
    assert!(report.made >= 1, "no bridge made: {report:?}");
    let engine = Engine::new();
    let (analysis, sig) = engine.sign(&welded).expect("signature");
    let payload = compute_payload(&analysis, &PayloadSpec::default()).expect("payload");
    let counts = [
        analysis.mesh.vertices.len(),
        analysis.mesh.faces.len(),
        sig.vertices,
        payload.samples,
    ];
    let sketches = |sig: &shapeseek::signature::Signature, v: &mut Vec<f64>| {
        for c in &sig.channels {
            match &c.values {
                ChannelValues::Distribution(s) => {
                    let q = s.quantiles.len() - 1;
                    v.push(s.mass);
                    for j in [q / 10, q / 2, 9 * q / 10] {
                        v.push(s.quantiles[j]);
                    }
                }
                ChannelValues::Vector(x) => v.extend(x.iter().take(4)),
            }
        }
        v.push(sig.area);
    };
    let mut v: Vec<f64> = analysis
        .spectrum
        .eigenvalues
        .iter()
        .skip(1)
        .take(8)
        .copied()
        .collect();
    sketches(&sig, &mut v);
    v.push(payload.weights.first().copied().unwrap_or(f64::NAN));
    for u in &payload.upper {
        v.push(u.iter().map(|&x| f64::from(x)).sum::<f64>() / u.len().max(1) as f64);
    }
    v.push(payload.lambda1);
    // The second cut version, which the default's alternate cut makes of a genuine handle its
    // first cut keeps (a torus of L/√A 0.41): its vertex count, then the sketch figures.
    let (_, ring) = engine
        .sign(&shapeseek::mesh::generate::torus(3.0, 0.5, 90, 16))
        .expect("torus signature");
    let alt = ring
        .alternate
        .as_deref()
        .expect("the torus has a second version");
    v.push(alt.vertices as f64);
    sketches(alt, &mut v);
    (counts, v)
}

#[test]
fn the_core_computes_what_its_revision_recorded() {
    let (counts, v) = figures();
    let paste = format!(
        "const RECORDED_AT: u32 = {ALGORITHM_REVISION};\n\
         const RECORDED_COUNTS: [usize; 4] = {counts:?};\n\
         const RECORDED: &[f64] = &{v:?};"
    );
    assert_eq!(
        RECORDED_AT, ALGORITHM_REVISION,
        "the figures below were recorded at revision {RECORDED_AT}, the code is at \
         ALGORITHM_REVISION = {ALGORITHM_REVISION}: set one to the other (src/lib.rs), or, when \
         the revision was bumped on purpose, record its figures here:\n{paste}"
    );
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * a.abs().max(b.abs()) + 1e-12;
    let same = counts == RECORDED_COUNTS
        && v.len() == RECORDED.len()
        && v.iter().zip(RECORDED).all(|(&a, &b)| close(a, b));
    if !same {
        let moved: Vec<String> = v
            .iter()
            .zip(RECORDED)
            .enumerate()
            .filter(|(_, (&a, &b))| !close(a, b))
            .map(|(i, (a, b))| format!("#{i}: {b} -> {a}"))
            .collect();
        let next = format!(
            "const RECORDED_AT: u32 = {};\n\
             const RECORDED_COUNTS: [usize; 4] = {counts:?};\n\
             const RECORDED: &[f64] = &{v:?};",
            ALGORITHM_REVISION + 1
        );
        panic!(
            "the numerical core's output moved at revision {ALGORITHM_REVISION} (counts \
             {RECORDED_COUNTS:?} -> {counts:?}, {} figures for {} recorded, {} of them moved: \
             {}). If that is meant, set \
             shapeseek::ALGORITHM_REVISION (src/lib.rs) to {} and paste:\n{next}",
            v.len(),
            RECORDED.len(),
            moved.len(),
            moved.join(", "),
            ALGORITHM_REVISION + 1
        );
    }
}
