//! Values that are persisted as JSON must decode to the same bits.
//!
//! The server stores the corpus [`Calibration`] as JSON (index `meta`) and scans with the decoded
//! copy after a restart; the histogram windows (`window_max`) feed every bin edge, so a window
//! that comes back one ULP off moves scores by about one ULP (seen in `tests/server.rs`'
//! restart test with the Weyl-scaled default: 1.311255241231611 before, 1.311255241231612
//! after). serde_json's default float parser is not correctly rounded for every input; the
//! crate enables its `float_roundtrip` feature, and these tests pin that down.

use proptest::prelude::*;
use shapeseek::ranking::Calibration;
use shapeseek::signature::{ChannelData, ChannelValues, QuantileSketch, Signature};

fn calibration(window_max: Vec<f64>) -> Calibration {
    Calibration {
        epoch: 9,
        spec_key: "k".into(),
        channel_names: (0..window_max.len()).map(|i| format!("c{i}")).collect(),
        window_max,
        bins: 256,
        bandwidth_bins: 1.0,
        percentile: 0.95,
        shapes: 9,
    }
}

fn json_round_trip<T: serde::Serialize + serde::de::DeserializeOwned>(v: &T) -> T {
    serde_json::from_slice(&serde_json::to_vec(v).unwrap()).unwrap()
}

fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// The window of the server test's corpus that came back one ULP off (`…2cc` → `…2cb`) with
/// serde_json's default parser.
#[test]
fn calibration_window_of_the_restart_test_round_trips() {
    let w = f64::from_bits(0x4005_f6c6_da39_72cc);
    assert_eq!(format!("{w}"), "2.7454964684278362");
    let back = json_round_trip(&calibration(vec![w]));
    assert_eq!(bits(&back.window_max), bits(&[w]));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn calibration_json_is_bit_exact(w in proptest::collection::vec(
        proptest::num::f64::POSITIVE | proptest::num::f64::NORMAL | proptest::num::f64::SUBNORMAL, 1..6)
    ) {
        let c = calibration(w);
        let back = json_round_trip(&c);
        prop_assert_eq!(bits(&back.window_max), bits(&c.window_max));
    }

    #[test]
    fn signature_json_is_bit_exact(
        q in proptest::collection::vec(0.0f64..10.0, 2..40),
        mass in 0.0f64..2.0,
        area in 0.5f64..2.0,
    ) {
        let s = Signature {
            spec_key: "k".into(),
            channels: vec![ChannelData {
                name: "c".into(),
                values: ChannelValues::Distribution(QuantileSketch { mass, quantiles: q }),
            }],
            vertices: 10,
            area,
            quadrature_points: 10,
            alternate: None,
        };
        prop_assert_eq!(json_round_trip(&s), s);
    }
}
