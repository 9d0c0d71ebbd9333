//! Per-shape scale selection: rescaling a shape's spectrum so that one set of diffusion times
//! means the same thing on every shape.
//!
//! The pipeline already normalises every shape to unit area, which makes the times agree with
//! Weyl's law in the mean: `λ_i ≈ 4π i / area`, so on a unit-area shape `t` sits where
//! `t · λ_i ≈ 4π t i`. The rules here go one step further and tie the times to each shape's own
//! spectrum:
//!
//! * [`SpectrumScaling::Lambda1`]: `λ ← λ · ref / λ₁`, i.e. the heat kernel at time `t` becomes
//!   `e^{−(t·ref/λ₁) λ}`: every shape is seen at the same `t λ₁` (the "size" of the shape as the
//!   lowest vibration mode sees it).
//! * [`SpectrumScaling::WeylFit`]: `λ ← λ · 4π / ŝ`, with `ŝ` the least-squares slope of the
//!   shape's own `λ_i` against `i` (through the origin, non-zero modes): the empirical Weyl
//!   constant of the discrete operator, robust to a change of any single eigenvalue.
//!
//! Scaling only the eigenvalues (not the eigenfunctions) relabels time: distances computed at
//! time `t` on the rescaled spectrum are the distances at time `t · c` on the original one.

use crate::pipeline::Analysis;
use crate::signature::ZERO_MODE_TOLERANCE;
use serde::{Deserialize, Serialize};

/// How the spectrum is rescaled before kernels are evaluated.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Default)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum SpectrumScaling {
    /// Times as given on the unit-area shape.
    #[default]
    None,
    /// `λ ← λ · reference / λ₁`.
    Lambda1 {
        /// The `λ₁` every shape is mapped to (`6.0` keeps the default times' meaning: the bench
        /// shapes' unit-area `λ₁` is ≈ 6).
        reference: f64,
    },
    /// `λ ← λ · 4π / ŝ` with `ŝ` the fitted Weyl slope of the shape's own spectrum.
    WeylFit,
}

impl SpectrumScaling {
    /// `true` for [`SpectrumScaling::None`] (serde: omitted, so existing spec keys are unchanged).
    pub fn is_none(&self) -> bool {
        matches!(self, SpectrumScaling::None)
    }

    /// The factor `c` with `λ ← c λ` for eigenvalues `ev` of a shape of area `area`.
    pub fn factor(&self, ev: &[f64], area: f64) -> f64 {
        let zero_tol = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI / area;
        let nz: Vec<f64> = ev.iter().copied().filter(|&l| l > zero_tol).collect();
        if nz.is_empty() {
            return 1.0;
        }
        match self {
            SpectrumScaling::None => 1.0,
            SpectrumScaling::Lambda1 { reference } => reference / nz[0],
            SpectrumScaling::WeylFit => {
                let (mut sxy, mut sxx) = (0.0, 0.0);
                for (i, l) in nz.iter().enumerate() {
                    let x = (i + 1) as f64;
                    sxy += x * l;
                    sxx += x * x;
                }
                let slope = sxy / sxx;
                4.0 * std::f64::consts::PI / (slope * area)
            }
        }
    }

    /// A copy of `a` with the rescaled spectrum (eigenfunctions unchanged).
    pub fn apply(&self, a: &Analysis) -> Analysis {
        let mut out = a.clone();
        let area: f64 = a.spectrum.mass.iter().sum();
        let c = self.factor(&a.spectrum.eigenvalues, area);
        out.spectrum.eigenvalues.iter_mut().for_each(|l| *l *= c);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn factors() {
        let ev = [0.0, 5.0, 10.0, 15.0];
        assert_eq!(SpectrumScaling::None.factor(&ev, 1.0), 1.0);
        assert!((SpectrumScaling::Lambda1 { reference: 6.0 }.factor(&ev, 1.0) - 1.2).abs() < 1e-12);
        // λ_i = 5 i: slope 5 → 4π / 5.
        let w = SpectrumScaling::WeylFit.factor(&ev, 1.0);
        assert!((w - 4.0 * std::f64::consts::PI / 5.0).abs() < 1e-12);
    }
}

#[cfg(test)]
mod print_configs {
    /// Prints the default configuration as JSON (for writing eval config files).
    #[test]
    #[ignore]
    fn print_default_config_json() {
        println!(
            "{}",
            serde_json::to_string(&crate::ranking::default_config()).unwrap()
        );
    }
}
