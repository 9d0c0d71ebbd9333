//! Named configurations: what to compute per shape, how to rank, which stages follow — the
//! paper's configurations ([`paper_configs`]), the product default ([`default_config`]) and a
//! look-up by name with suggestions ([`config_by_name`], [`closest_names`]).
//!
//! This module sits above [`crate::ranking`] (query specs, dissimilarities) and
//! [`crate::search`] (stages): both are ingredients of a [`Config`].

use crate::mesh::cap::CapOptions;
use crate::mesh::smooth::{SmoothOptions, UntilSettled};
use crate::mesh::topology::HandleCutOptions;
use crate::ranking::{CalibrationOptions, Dissimilarity, QuerySpec};
use crate::rerank::ReciprocalStage;
use crate::search::Stage;
use crate::signature::{
    Aggregation, ChannelKind, ChannelSpec, Kernel, Norm, SignatureSpec, DEFAULT_HEAT_SCALES,
    SMALL_HEAT_SCALES,
};
use serde::{Deserialize, Serialize};

/// A named method: what to compute per shape and how to rank.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Config {
    /// Name, as in REFERENCE.md where the configuration appears there.
    pub name: String,
    /// Signature to compute.
    pub signature: SignatureSpec,
    /// Ranking.
    pub query: QuerySpec,
    /// Re-ranking stages applied in order to the ranking of `query` (none by default; omitted
    /// from the JSON when empty; legacy `{"kind": "none"}` entries are skipped).
    #[serde(
        default,
        skip_serializing_if = "Vec::is_empty",
        deserialize_with = "crate::search::stage::deserialize_list"
    )]
    pub rerank: Vec<Stage>,
    /// How the corpus this configuration ranks is calibrated (histogram bins, Parzen bandwidth,
    /// window percentile). The paper's values (256 bins, one bin, 95th percentile) unless set;
    /// omitted from the JSON when they are those.
    #[serde(default, skip_serializing_if = "CalibrationOptions::is_paper")]
    pub calibration: CalibrationOptions,
}

fn fmt_range(ts: &[f64]) -> String {
    match ts {
        [] => String::new(),
        [t] => format!("t={t}"),
        [a, .., b] => format!("t={a}..{b}"),
    }
}

/// The six default heat scales under the L2 norm: the signature shared by every `Heat-L2-*`
/// configuration.
pub fn heat_l2_spec() -> SignatureSpec {
    SignatureSpec::with_channels(
        DEFAULT_HEAT_SCALES
            .iter()
            .map(|&t| ChannelSpec::heat(t, Norm::L2))
            .collect(),
    )
}

fn single_channel_spec(c: ChannelSpec) -> SignatureSpec {
    SignatureSpec::with_channels(vec![c])
}

fn config(
    name: String,
    signature: SignatureSpec,
    channels: Vec<String>,
    d: Dissimilarity,
    a: Aggregation,
) -> Config {
    Config {
        name,
        signature,
        query: QuerySpec {
            channels,
            dissimilarity: d,
            aggregation: a,
            alternate_margin: crate::ranking::DEFAULT_ALTERNATE_MARGIN,
        },
        rerank: Vec::new(),
        calibration: CalibrationOptions::default(),
    }
}

/// The eight dissimilarities of paper Table 1.
const TABLE1: [Dissimilarity; 8] = [
    Dissimilarity::L1,
    Dissimilarity::L2,
    Dissimilarity::NL1,
    Dissimilarity::NL2,
    Dissimilarity::KL,
    Dissimilarity::Bhattacharyya,
    Dissimilarity::Chi2,
    Dissimilarity::Emd,
];

/// Every named configuration, named as in REFERENCE.md (`<Kernel>-<Norm>-<Dissimilarity>-
/// <Aggregation>[params]`):
///
/// * `Heat-L2-<D>-Single[t=<t>]` for the six default scales and every dissimilarity `<D>` of
///   Table 1 (`L1 L2 nL1 nL2 KL Bhatt chi2 EMD`) plus `Linf`;
/// * `Heat-L2-<D>-{Sum,Sum2,Max}` over the six scales and `…[t=0.016..0.1]` over the three
///   smallest (Table 3, dissimilarity-stage aggregation);
/// * `CT-L2-<D>`, `Step-L2-<D>[lc=4pi*10]`, `Step-L2-<D>[lc=4pi*30]`, `D2-<D>`, `Geo-<D>`,
///   `ShapeDNA[50]-L2` (Table 2 and baselines);
/// * `Heat-L1-nL1-Single[t=0.1]`, `Heat-Linf-nL1-Single[t=0.1]` (paper Table 2, H-L1 / H-L∞);
/// * the other aggregation stages over the three smallest scales:
///   `Heat-L2-nL1-KernelSum[t=0.016..0.1]`, `Heat-L2-nL1-DistanceSum[…]`,
///   `Heat-L2-nL1-DistanceSum2[…]`, `Heat-L2-nL1-DistanceMax[…]`,
///   `Heat-L2-nL1-DistributionSum[…]`;
/// * presets: `Mahmoudi-Sapiro[t=0.1]` (heat, L2, L2 dissimilarity, single t), `DSS` (sum over
///   the six scales of Mahmoudi–Sapiro), `GPS` (commute time, L2, L2 dissimilarity),
///   `paper-best` (heat, L2, nL1, max over six scales), and `default` ([`default_config`]).
///
/// Configurations of one family share one [`SignatureSpec`] (same key), so a harness computes
/// each shape's signature once per family.
pub fn paper_configs() -> Vec<Config> {
    let mut out = Vec::new();
    let heat = heat_l2_spec();
    let names = heat.channel_names();
    let small: Vec<String> = names[..SMALL_HEAT_SCALES.len()].to_vec();
    let mut dissims: Vec<Dissimilarity> = TABLE1.to_vec();
    dissims.push(Dissimilarity::LInf);
    for (i, &t) in DEFAULT_HEAT_SCALES.iter().enumerate() {
        for &d in &dissims {
            out.push(config(
                format!("Heat-L2-{}-Single[t={t}]", d.label()),
                heat.clone(),
                vec![names[i].clone()],
                d,
                Aggregation::Single,
            ));
        }
    }
    for (suffix, chans) in [
        (String::new(), names.clone()),
        (
            format!("[{}]", fmt_range(&SMALL_HEAT_SCALES)),
            small.clone(),
        ),
    ] {
        for &d in &TABLE1 {
            for a in [Aggregation::Sum, Aggregation::Sum2, Aggregation::Max] {
                out.push(config(
                    format!("Heat-L2-{}-{}{suffix}", d.label(), a.label()),
                    heat.clone(),
                    chans.clone(),
                    d,
                    a,
                ));
            }
        }
    }
    let four_pi = 4.0 * std::f64::consts::PI;
    let families: Vec<(String, String, ChannelSpec)> = vec![
        ("CT-L2".into(), String::new(), ChannelSpec::commute_time()),
        (
            "Step-L2".into(),
            "[lc=4pi*10]".into(),
            ChannelSpec::step(four_pi * 10.0),
        ),
        (
            "Step-L2".into(),
            "[lc=4pi*30]".into(),
            ChannelSpec::step(four_pi * 30.0),
        ),
        ("D2".into(), String::new(), ChannelSpec::d2(2000)),
        ("Geo".into(), String::new(), ChannelSpec::geodesic(None)),
    ];
    for (prefix, suffix, ch) in families {
        let spec = single_channel_spec(ch);
        let chans = spec.channel_names();
        for &d in &TABLE1 {
            out.push(config(
                format!("{prefix}-{}{suffix}", d.label()),
                spec.clone(),
                chans.clone(),
                d,
                Aggregation::Single,
            ));
        }
    }
    let dna = single_channel_spec(ChannelSpec::shape_dna(50));
    out.push(config(
        "ShapeDNA[50]-L2".into(),
        dna.clone(),
        dna.channel_names(),
        Dissimilarity::L2,
        Aggregation::Single,
    ));
    for (label, norm) in [("L1", Norm::L1), ("Linf", Norm::LInf)] {
        let spec = single_channel_spec(ChannelSpec::heat(0.1, norm));
        out.push(config(
            format!("Heat-{label}-nL1-Single[t=0.1]"),
            spec.clone(),
            spec.channel_names(),
            Dissimilarity::NL1,
            Aggregation::Single,
        ));
    }
    let ts = SMALL_HEAT_SCALES.to_vec();
    let range = fmt_range(&ts);
    let staged: Vec<(String, ChannelKind)> = vec![
        (
            "KernelSum".into(),
            ChannelKind::Spectral {
                kernel: Kernel::HeatAggregate {
                    ts: ts.clone(),
                    aggregation: Aggregation::Sum,
                },
                norm: Norm::L2,
            },
        ),
        (
            "DistanceSum".into(),
            ChannelKind::DistanceAggregate {
                ts: ts.clone(),
                norm: Norm::L2,
                aggregation: Aggregation::Sum,
            },
        ),
        (
            "DistanceSum2".into(),
            ChannelKind::DistanceAggregate {
                ts: ts.clone(),
                norm: Norm::L2,
                aggregation: Aggregation::Sum2,
            },
        ),
        (
            "DistanceMax".into(),
            ChannelKind::DistanceAggregate {
                ts: ts.clone(),
                norm: Norm::L2,
                aggregation: Aggregation::Max,
            },
        ),
        (
            "DistributionSum".into(),
            ChannelKind::DistributionSum {
                ts: ts.clone(),
                norm: Norm::L2,
            },
        ),
    ];
    for (label, kind) in staged {
        let spec = single_channel_spec(ChannelSpec { kind });
        out.push(config(
            format!("Heat-L2-nL1-{label}[{range}]"),
            spec.clone(),
            spec.channel_names(),
            Dissimilarity::NL1,
            Aggregation::Single,
        ));
    }
    // Presets of §3.3 and §5.
    out.push(config(
        "Mahmoudi-Sapiro[t=0.1]".into(),
        heat.clone(),
        vec![names[2].clone()],
        Dissimilarity::L2,
        Aggregation::Single,
    ));
    out.push(config(
        "DSS".into(),
        heat.clone(),
        names.clone(),
        Dissimilarity::L2,
        Aggregation::Sum,
    ));
    let ct = single_channel_spec(ChannelSpec::commute_time());
    out.push(config(
        "GPS".into(),
        ct.clone(),
        ct.channel_names(),
        Dissimilarity::L2,
        Aggregation::Single,
    ));
    out.push(config(
        "paper-best".into(),
        heat.clone(),
        names.clone(),
        Dissimilarity::NL1,
        Aggregation::Max,
    ));
    out.push(default_config());
    out
}

/// The product default: heat kernel, L2 norm, over their full range the times
/// [`DEFAULT_FULL_RANGE_TIMES`] (t = 0.00256 … 0.04) and over their short range the three
/// smallest default scales ([`SMALL_HEAT_SCALES`], t = 0.016, 0.04, 0.1, i.e. t·λ_1 ≈ 0.1–0.6
/// on unit-area shapes), nL1, summed over these seven channels and a weighted ShapeDNA channel
/// (the first 50 eigenvalues, L1).
///
/// The paragraphs below give the history of the choices, each with the figures of its time:
/// until `docs/quality.md` §22 the full range used the three small scales too.
///
/// Why: nL1 is the paper's best dissimilarity (Table 1) and does not depend on in-window mass;
/// scales with t·λ_1 ≫ 1 see only the first few eigenfunctions and were measured worse
/// (REFERENCE.md Table 3: every single scale above 0.1 and every aggregate including them rank
/// lower), while aggregating a few small scales beat each single one; Sum is preferred to Sum²
/// and Max because it weights the scales evenly and no single scale can dominate, the least
/// tuned choice among near-equal results (83.47 vs 83.59 vs 82.46 mAP there).
///
/// Scale selection (`docs/quality.md` §2): every shape's eigenvalues are multiplied by
/// `c = 4π / (ŝ · area)`, `ŝ` the Weyl slope fitted over its first 100 eigenpairs
/// ([`crate::scale::SpectrumScaling::WeylFit`], [`crate::scale::WEYL_FIT_EIGENPAIRS`]). As a
/// uniform scaling does (eq. 17, `λ' = α⁻²λ`), this relabels time: the heat kernel `e^{−tλ}`
/// (eq. 5) is evaluated at `c·t`, so the three times sit at the same place in every shape's own
/// spectrum, boundary and discretisation included. Measured on bench/dev: All mAP 83.37 → 84.30
/// (partiality +2.5, topology +1.5); on the class split the held-out classes 88.76 → 90.76 at
/// a tie on the tune classes (89.00 → 88.93). The band is fixed because the fitted slope depends
/// on it (`crate::scale` docs: a fit over 10 / 30 / 99 modes gives dev 78.9 / 86.2 / 84.3, and
/// the class split confirms no narrower band): the signature does not change when an index
/// computes more eigenpairs, and an index with fewer than 100 (e.g. the server tests' k = 30)
/// keeps the unscaled unit-area spectrum rather than a fit over a band never validated.
///
/// Short range (`docs/quality.md` §3b): each of the three channels is also compared on its
/// pairs closer than [`SHORT_RANGE_RADII`] (a [`ChannelKind::Truncated`] channel, calibrated
/// and histogrammed on its own), six channels summed then. Topology bridges change the long
/// diffusion distances and partial shapes lose pairs at all ranges; the full range and the
/// short range fail on different shapes. dev 84.30 → 86.28, tune / held-out classes 91.05 / 91.06.
///
/// Re-ranking (`docs/quality.md` §7): the top 200 are re-ordered by their reciprocal
/// neighbourhoods within the shortlist ([`crate::rerank::ReciprocalStage`] with its defaults:
/// neighbourhood sizes 8, 16, 32 averaged so that no class size is assumed). dev 86.28 →
/// 91.17, every transformation class ≥ 81.8; tune / held-out classes 94.32 / 93.52.
///
/// Handle cutting (`docs/quality.md` §9): before the spectrum, short handles that are short
/// necks ([`DEFAULT_HANDLE_CUT`]) are cut ([`crate::mesh::topology::cut_handles`]), undoing
/// the welds by which limbs touching the body become bridges (paper §5.3's topological noise,
/// which the diffusion distances of eq. 9 follow at every scale). Chosen by the
/// leave-one-class-out protocol among the thresholds that keep the genuine-handle test shapes
/// (torus, mug, thick ring, arms joined into a ring): dev 91.17 → 94.38 (iso+topology 81.83 →
/// 92.09); the rule chosen per fold scores mean All 94.37 on the held-out characters, and the
/// crane-man (human) fold goes from 84.36 to 90.92.
///
/// Boundary capping (`docs/quality.md` §19): before handle cutting, every boundary loop not
/// longer than [`DEFAULT_CAP`]'s `2.5 · sqrt(area)` — holes, the rim of a part cut away — is
/// closed by a domed cap ([`crate::mesh::cap`]), so a partial shape is analysed as a closed
/// surface like the complete shapes of its character. Chosen by the leave-one-class-out
/// protocol in all 8 folds (length 2.5 in 6, 1.5 in 2): held-out mean All 95.88 → 96.79,
/// partiality 86.68 → 90.38; with hemispherical caps instead of half-height ones (§20, chosen
/// in all 8 folds) 96.94 → 97.36, partiality 91.00 → 92.95.
///
/// Two cut versions (`docs/quality.md` §17, §20): a shape that [`DEFAULT_ALTERNATE_CUT`] cuts
/// differently also gets a second version, and a pair scores the smaller of the two versions'
/// dissimilarities ([`crate::ranking::DEFAULT_ALTERNATE_MARGIN`], re-chosen with capping).
///
/// Smaller times over the full range (`docs/quality.md` §22): [`DEFAULT_FULL_RANGE_TIMES`].
///
/// Histograms of [`DEFAULT_HISTOGRAM_BINS`] bins with half a bin of smoothing
/// (`docs/quality.md` §23).
///
/// The eigenvalues themselves (`docs/quality.md` §24): an eighth channel, the first
/// [`DEFAULT_SHAPE_DNA_EIGENVALUES`] non-zero eigenvalues of the unit-area shape (ShapeDNA,
/// paper §5's baseline) weighted by [`DEFAULT_SHAPE_DNA_WEIGHT`] in the sum.
///
/// Smoothing (`docs/quality.md` §25): before everything else that reads the geometry, a few
/// Taubin steps ([`DEFAULT_SMOOTH`]) filter out noise at the scale of the edges.
pub fn default_config() -> Config {
    let full = DEFAULT_FULL_RANGE_TIMES
        .iter()
        .map(|&t| ChannelSpec::heat(t, Norm::L2));
    let short = SMALL_HEAT_SCALES
        .iter()
        .zip(SHORT_RANGE_RADII)
        .map(|(&t, r)| ChannelSpec::truncated(ChannelSpec::heat(t, Norm::L2), r));
    let channels: Vec<ChannelSpec> = full
        .chain(short)
        .chain(std::iter::once(ChannelSpec::weighted_shape_dna(
            DEFAULT_SHAPE_DNA_EIGENVALUES,
            DEFAULT_SHAPE_DNA_WEIGHT,
        )))
        .collect();
    let mut spec = SignatureSpec::with_channels(channels);
    spec.spectrum_scaling = crate::scale::SpectrumScaling::WeylFit {
        eigenpairs: Some(crate::scale::WEYL_FIT_EIGENPAIRS),
    };
    spec.cut_handles = Some(DEFAULT_HANDLE_CUT);
    spec.alternate_cut = Some(DEFAULT_ALTERNATE_CUT);
    spec.cap_boundaries = Some(DEFAULT_CAP);
    spec.smooth = Some(DEFAULT_SMOOTH);
    Config {
        name: "default".into(),
        query: QuerySpec {
            channels: spec.channel_names(),
            dissimilarity: Dissimilarity::NL1,
            aggregation: Aggregation::Sum,
            alternate_margin: crate::ranking::DEFAULT_ALTERNATE_MARGIN,
        },
        signature: spec,
        rerank: vec![Stage::Reciprocal(ReciprocalStage::default())],
        calibration: CalibrationOptions {
            bins: DEFAULT_HISTOGRAM_BINS,
            bandwidth_bins: DEFAULT_BANDWIDTH_BINS,
            percentile: DEFAULT_WINDOW_PERCENTILE,
        },
    }
}

/// Bins of the default's histograms: 128, half the paper's 256, with a Parzen bandwidth of
/// [`DEFAULT_BANDWIDTH_BINS`] = half a bin, which is the paper's smoothing (one of its bins) in
/// distance units. A stored version then costs 2 086 bytes instead of 3 878 (the counts are 2
/// bytes per bin). Chosen by the leave-one-class-out protocol among 256, 128 and 64 bins with one
/// or half a bin (`docs/quality.md` §23): 128 with half a bin in 8 of 8 folds, held-out mean All
/// 98.10 → 98.13, iso+topology 98.43 → 98.58; on the posed proxy of §22 83.35 → 83.32.
pub const DEFAULT_HISTOGRAM_BINS: usize = 128;

/// Vertices a shape is analysed at, at most ([`crate::mesh::prepare::PrepareOptions::max_vertices`],
/// [`crate::mesh::decimate`]): a larger mesh is simplified to this many before its spectrum
/// (capping may add its caps' vertices after). The benchmarks' shapes have 2 001–6 669 vertices
/// (`dev`) and 1 429–2 230 (`mini`) and are never simplified; a 180 000-vertex upload otherwise
/// took 28 s and 1 GiB of memory (`docs/reliability.md`, "Large meshes").
pub const ANALYSIS_VERTEX_BUDGET: usize = 20_000;

/// Eigenvalues in the default's ShapeDNA channel (`docs/quality.md` §24): an index needs at
/// least one eigenpair more ([`SignatureSpec::min_eigenpairs`]).
///
/// Why: the diffusion distances' distributions, summaries of a whole shape, do not tell human
/// figures of a similar build apart (`docs/quality.md` §22: a human query's first 33 shapes
/// held 18–57 % other humans). The low eigenvalues of the unit-area shape do, to a degree: they
/// depend on its proportions and girth, and handle cutting and capping (before the spectrum)
/// keep them close under welds and holes. Alone they rank far below the distributions (the
/// `ShapeDNA[50]-L2` baseline); added to the sum they move the rankings where the distributions
/// are undecided. Chosen with [`DEFAULT_SHAPE_DNA_WEIGHT`] by the leave-one-class-out protocol
/// over 14 characters among nine pairs of a count (20, 30 or 50) and a weight: 50 at 0.0006 in
/// 14 of 14 folds, held-out mean All 87.75 → 89.94 (topology 87.04 → 91.38, iso+topology 84.40 →
/// 87.04, partiality 77.09 → 78.74); on bench/dev 98.13 → 98.75, on the posed proxy of §22
/// 83.32 → 85.93.
pub const DEFAULT_SHAPE_DNA_EIGENVALUES: usize = 50;

/// Weight of the default's ShapeDNA channel: its eigenvalues (of the unit-area shape, where
/// `λ_n ≈ 4πn` by Weyl's law) are multiplied by it, so that its L1 dissimilarity `Σ|λ − λ'|`
/// counts in the sum with the histogram channels' nL1 (each at most 2). At 0.0006 its median
/// over the pairs of bench/dev is about a third of the seven histogram channels' sum (0.60
/// against 1.94, `docs/quality.md` §24).
pub const DEFAULT_SHAPE_DNA_WEIGHT: f64 = 0.0006;

/// Parzen bandwidth of the default's histograms, in bins ([`DEFAULT_HISTOGRAM_BINS`]).
pub const DEFAULT_BANDWIDTH_BINS: f64 = 0.5;

/// The times of the default's full-range channels: the paper's grid `0.016 · 2.5^j`
/// ([`crate::signature::DEFAULT_HEAT_SCALES`]) from two steps below its smallest time,
/// j = −2 … 1 (`docs/quality.md` §22). Until then the full range used t = 0.016, 0.04, 0.1,
/// which cannot tell human figures of a similar build apart: on a benchmark built like
/// bench/dev from other posed characters (three humans, two animals) a human query's first 33
/// shapes held 18–57 % other humans. Smaller times resolve finer geometry (proportions, girth).
/// At t = 0.00256 the k = 100 eigenpairs truncate the kernel (`e^{−t λ_100} ≈ 0.04` after the
/// Weyl scaling), so those channels are heat kernels band-limited to the first 100 modes, the
/// same band on every shape. Chosen by the leave-one-class-out protocol over 14 characters
/// (bench/dev, a second human, welds of all nine, the other posed characters) in 9 of 14 folds
/// (the rest: the same with t = 0.1 added): held-out mean All 85.66 → 87.82; on bench/dev
/// alone 97.36 → 98.10 (iso+topology 96.58 → 98.43, partiality 92.95 → 96.26; topology
/// 98.78 → 96.26).
pub const DEFAULT_FULL_RANGE_TIMES: [f64; 4] = [0.00256, 0.0064, 0.016, 0.04];

/// The default's histogram window: the 90th percentile of the pooled corpus distances of each
/// channel (the paper's §5 uses the 95th). Chosen by the leave-one-class-out protocol
/// (`docs/quality.md` §12): among 0.85, 0.90, 0.95 and 0.99 (each with the default and 14
/// variants of its other choices) the protocol picks 0.90 in 7 of the 8 folds (0.85 in the
/// eighth); held-out mean All 94.38 → 95.00 and iso+topology 92.09 → 95.97 for the default held
/// fixed, the worst fold 90.92 → 92.86. A narrower window drops more of the longest distances
/// (mass beyond the window is not binned), the ones a weld or a missing part moves most.
pub const DEFAULT_WINDOW_PERCENTILE: f64 = 0.9;

/// Radii (unit-area units, after the Weyl scaling) of the default's short-range channels, one
/// per [`SMALL_HEAT_SCALES`] time: the 75th percentile of the pooled diffusion distances of the
/// bench/dev *tune* classes (cat, horse, face, camel) at t = 0.016, 0.04, 0.1, so that the
/// held-out classes never informed them (`docs/quality.md` §3b).
#[allow(clippy::approx_constant)] // 3.14 is a measured percentile, not π.
pub const SHORT_RANGE_RADII: [f64; 3] = [3.14, 2.1, 1.09];

/// The default's handle cutting: a basis loop with `L/√A ≤ 0.5` is cut when its neck aspect
/// `(s₊ + s₋)/L` is `≤ 3` or its side aspect `min(s₊, s₋)/L` is `≤ 0.9` (the other options at
/// their defaults). Why these (`docs/quality.md` §9 and §13): on bench/dev the weld tunnel loops
/// have `L/√A` 0.04–0.27 and aspects 0–10 (median 2.1); the genuine handles of the tests have
/// aspect ≥ 3.2 (mug 3.24 at `L/√A` 0.24, a ring of arms on a body 5.4 at 0.13, torus 5.6 at
/// 0.41, thick ring 5.4 at 0.36) and side aspect ≥ 1.12 (mug 1.13, arms 1.49, thick ring 2.68,
/// torus 2.80). A length-only rule cuts the ring of arms (≤ 0.2) or the mug (≤ 0.3); among the
/// rules that keep all four, the two-sided test was chosen by the leave-one-class-out protocol in
/// 7 of 8 folds (§9), and the side test added to it in all 8 folds (§13): a limb welded to the
/// body (a hand to a thigh) flares into the body at once on one side and runs along the limb on
/// the other, so only one side is short. The length bound stays below the genuine handles'
/// second basis loops (through the body, `L/√A` ≥ 0.607 in the tests): 0.65, which the
/// protocol preferred over the 14 characters of §22 by a few hundredths (§30), cuts the short
/// joined arms through that loop (§31).
pub const DEFAULT_HANDLE_CUT: HandleCutOptions = HandleCutOptions {
    max_loop_rel: 0.5,
    max_neck_aspect: 3.0,
    max_side_aspect: 0.9,
    stub_aspect: 0.0,
    free_loop_rel: 0.0,
    growth: 2.0,
    roots: 8,
    refine_roots: 3,
    max_cuts: 16,
    remove_band: true,
};

/// The default's second cut ([`crate::signature::SignatureSpec::alternate_cut`]): every basis
/// loop with `L/√A ≤ 0.5`, whatever its aspects — genuine handles too, which
/// [`DEFAULT_HANDLE_CUT`] keeps. A shape the two rules cut differently is compared both ways
/// and a pair scores the smaller, the cut one multiplied by
/// [`crate::ranking::DEFAULT_ALTERNATE_MARGIN`] ([`crate::search::Query::score`]): a weld the
/// first rule must leave because it looks like a genuine handle (limb-to-limb welds, which
/// neither aspect test takes) is compared cut, while a genuine handle keeps its uncut
/// comparison. Chosen by the leave-one-class-out protocol (`docs/quality.md` §16–§17).
pub const DEFAULT_ALTERNATE_CUT: HandleCutOptions = HandleCutOptions {
    max_neck_aspect: 1e9,
    max_side_aspect: 0.0,
    ..DEFAULT_HANDLE_CUT
};

/// The default's boundary capping ([`crate::signature::SignatureSpec::cap_boundaries`]): loops
/// up to `2.5 · sqrt(area)` long are capped; an open surface's own long border (bench/dev's
/// face mask: ≥ 4.2) stays open. Chosen by the leave-one-class-out protocol among 1.5, 2.5,
/// 3.5 and every loop (`docs/quality.md` §19); the caps are domes of height 1 × the loop's
/// radius, chosen by the same protocol among 0.25, 0.5, 1, 1.5 and 2 (§20). Since §28 that
/// radius is the one of a disc as large as what the loop encloses (it was the one of a circle
/// as long as the loop, which noise lengthens), and the caps' rings and edge flips leave
/// jagged rims capped instead of open (chosen by the protocol over 14 characters in 14 of 14
/// folds: held-out mean All 92.11 → 92.66, partiality 80.61 → 83.90).
pub const DEFAULT_CAP: CapOptions = CapOptions {
    max_length: 2.5,
    dome_height: 1.0,
};

/// The default's smoothing ([`crate::signature::SignatureSpec::smooth`],
/// [`crate::mesh::smooth`]): 2 pairs of Taubin steps with `λ = 0.5`, `μ = −0.53`.
///
/// Why: normal noise of a few tenths of an edge length adds area unevenly (most where the edges
/// are short) and so changes the intrinsic geometry every spectral descriptor reads. On human
/// figures, which differ little, it mixed them up: on ten FAUST bodies (`docs/quality.md` §25,
/// not used to choose) the noise queries fell from 87.7 at σ = 0.1 ē to 28.3 at 0.5 ē.
/// Chosen by the leave-one-class-out protocol over the 14 characters of §22 among 0, 2, 3 and 5
/// steps (0, 2, 3 in the final run): 2 steps in 8 of 14 folds, 3 in 6; held fixed, held-out mean
/// All 89.94 → 91.89 with 2 steps (91.91 with 3, whose worst fold is lower: 75.50 against 79.83),
/// iso+topology 87.04 → 90.44, noise 90.14 → 93.36.
///
/// Then more pairs for noisy shapes ([`DEFAULT_UNTIL_SETTLED`]).
pub const DEFAULT_SMOOTH: SmoothOptions = SmoothOptions {
    until_settled: Some(DEFAULT_UNTIL_SETTLED),
    ..SmoothOptions::steps(2)
};

/// When the default's smoothing goes on past its 2 pairs: while the last pair lowered the
/// surface's roughness ([`crate::mesh::smooth::mesh_roughness`]) by more than a fifth, up to 10
/// pairs in all.
///
/// Why: after two pairs a shape with strong normal noise (σ = 0.5 ē) is still 1.2 to 3.3 times
/// as rough as its clean sibling after two pairs (david 0.097 against 0.083, the face 0.078
/// against 0.024); a pair more or two bring it down to that level, while on a clean surface a
/// pair after the first lowers it by a tenth or less. On the 606 shapes of the protocol only
/// noise shapes took more (noise2 5 of 14, noise3 13 of 14, noise4 all 14: 3 or 4 pairs); every
/// other shape's analysis is the same as with 2 pairs. Chosen by the leave-one-class-out protocol
/// over the 14 characters among a reduction of 0.12, 0.2, 0.3 and none: 0.2 in 12 of 14 folds;
/// held fixed, held-out mean All 91.89 → 92.11, worst fold (david) 79.83 → 81.51, noise 93.36 →
/// 94.75 (`docs/quality.md` §27). Out of sample, FAUST 81.15 → 82.00 and TOSCA-2 99.51 → 99.76.
pub const DEFAULT_UNTIL_SETTLED: UntilSettled = UntilSettled {
    max_steps: 10,
    min_reduction: 0.2,
};

/// The configuration called `name` in [`paper_configs`].
pub fn config_by_name(name: &str) -> Option<Config> {
    paper_configs().into_iter().find(|c| c.name == name)
}

/// Up to `n` preset names closest to `name` (edit distance, case-insensitive; ties by name).
pub fn closest_names(name: &str, n: usize) -> Vec<String> {
    let lower = name.to_lowercase();
    let mut scored: Vec<(usize, String)> = paper_configs()
        .into_iter()
        .map(|c| (edit_distance(&lower, &c.name.to_lowercase()), c.name))
        .collect();
    scored.sort();
    scored.into_iter().take(n).map(|(_, s)| s).collect()
}

/// Levenshtein distance over chars.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, &cb) in b.iter().enumerate() {
            cur[j + 1] = (prev[j] + usize::from(ca != cb))
                .min(prev[j + 1] + 1)
                .min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}
