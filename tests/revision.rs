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
//! same revision (as for the seven channels of `docs/quality.md` §22, the weighted ShapeDNA
//! channel of §24 and the two smoothing steps of §25).

use shapeseek::index::engine::Engine;
use shapeseek::mesh::samples::class_mesh;
use shapeseek::mesh::weld::{weld, WeldOptions};
use shapeseek::rerank::{compute_payload, PayloadSpec};
use shapeseek::signature::ChannelValues;
use shapeseek::ALGORITHM_REVISION;

/// Revision the figures below were recorded at.
const RECORDED_AT: u32 = 2;

/// Vertices and faces of the prepared (cut) mesh, vertices of the signature's mesh, samples of
/// the payload.
const RECORDED_COUNTS: [usize; 4] = [4820, 9576, 4820, 100];

/// Eigenvalues 1–8, then per channel the sketch's total mass and its quantiles at 10, 50 and
/// 90 % (a vector channel: its first four values), then the signature's area; then the payload's first sample weight, the mean of its
/// distances per time and its `lambda1`; then the vertices, sketch figures and area of the second
/// cut version of a torus (a genuine handle, cut only by the default's alternate rule).
const RECORDED: &[f64] = &[
    6.703562915697239,
    13.701360936230332,
    14.2764199744793,
    19.802276318941967,
    30.596382686020082,
    62.5847120826558,
    78.20495508835648,
    80.41226899573942,
    0.9999999999999901,
    4.899993576587376,
    5.566275221787591,
    6.261292075835366,
    0.9999999999999906,
    2.404190496006787,
    3.6085405381331044,
    4.690342317877829,
    0.9999999999999996,
    1.0595268181234845,
    2.453543558076412,
    3.666751400596328,
    0.9999999999999959,
    0.43417204065018883,
    1.5873804185825957,
    2.5466014112743105,
    0.7439362748729994,
    0.8947154935325659,
    2.0710070788206174,
    2.9132664716166112,
    0.7144982784103847,
    0.3395708351277618,
    1.20895028126661,
    1.936894455671458,
    0.7443882275344127,
    0.14782917563052958,
    0.5946712338053474,
    0.9718670675698058,
    0.004102906484739589,
    0.008385899161680373,
    0.008737863257014651,
    0.012119956050735696,
    0.9999999999999954,
    0.010421193245437778,
    2.479730356082019,
    1.6087324079818497,
    0.8055581467390776,
    6.703562915697239,
    1424.0,
    0.9999999999999836,
    4.7417224716529125,
    5.453719632926858,
    6.050046014543935,
    0.9999999999999789,
    2.0499437895669894,
    3.5746839774920836,
    4.1219207539408815,
    0.999999999999977,
    0.9334862294016371,
    2.708257520749331,
    3.230284172859769,
    0.9999999999999826,
    0.46310675045379107,
    2.009305571310227,
    2.6003015802152345,
    0.8563133067831212,
    0.8031958751759748,
    2.6636584570863207,
    2.936146396768281,
    0.5512960100829633,
    0.23284020508567838,
    1.283704330075553,
    2.0010366137173716,
    0.42602191974212444,
    0.0900581400419437,
    0.5185330256623688,
    0.9777626354131396,
    0.0010838501429260875,
    0.004328488384686409,
    0.0097133190499581,
    0.017204503972216074,
    0.9999999999999915,
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
