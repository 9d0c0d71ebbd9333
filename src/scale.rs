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
//! # Which eigenvalues the Weyl fit sees
//!
//! `ŝ` is not a property of the shape alone: it depends on the band of the spectrum it is
//! fitted over. On a unit-area closed surface the leading Weyl term gives `ŝ ≈ 4π` whatever
//! the band, but a surface with boundary (open meshes, holes, cuts) has the Neumann boundary
//! term `N(λ) ≈ A λ / 4π + L λ^{1/2} / 4π` (L = boundary length), whose relative weight decays
//! like `λ^{-1/2}`, and the cotangent operator's discretisation error grows with `λ h²`. A fit
//! over the first 29 non-zero modes therefore gives a unit square 1.28 (1.42–1.49 on
//! 144–196-vertex grids) against 0.97–1.0 (1.08–1.14) for closed spheres and tori, while over
//! 99 modes the bench's open shapes get ≈ 1.1–1.2. The band also matters for retrieval (the
//! measurements are in `docs/quality.md` §2c).
//! [`SpectrumScaling::WeylFit`]`{ eigenpairs: Some(m) }` therefore fixes the band: the
//! non-zero modes among the first `m` eigenpairs, whatever `k` the index computed, and **no
//! scaling** (factor 1, i.e. the leading-order Weyl law `λ_i ≈ 4π i / A` the unit-area
//! normalisation already imposes) when fewer than `m` eigenpairs were computed, instead of a
//! fit over a band it was not validated on.
//!
//! Scaling only the eigenvalues (not the eigenfunctions) relabels time: distances computed at
//! time `t` on the rescaled spectrum are the distances at time `t · c` on the original one.

use crate::spectrum::{Analysis, ZERO_MODE_TOLERANCE};
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
    WeylFit {
        /// Fit over the non-zero modes among the first `eigenpairs` eigenpairs, and leave the
        /// spectrum unscaled when fewer were computed (module docs). `None` (serde: omitted,
        /// the original `{"kind": "weyl_fit"}` key): every computed mode, so the factor
        /// depends on the number of eigenpairs.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        eigenpairs: Option<usize>,
    },
}

/// The band of the product default's Weyl fit ([`crate::presets::default_config`]): the first
/// 100 eigenpairs, i.e. the spectrum the scale rule was evaluated with on bench/dev (k = 100).
pub const WEYL_FIT_EIGENPAIRS: usize = 100;

impl SpectrumScaling {
    /// `true` for [`SpectrumScaling::None`] (serde: omitted, so existing spec keys are unchanged).
    pub fn is_none(&self) -> bool {
        matches!(self, SpectrumScaling::None)
    }

    /// The factor `c` with `λ ← c λ` for eigenvalues `ev` of a shape of area `area`.
    pub fn factor(&self, ev: &[f64], area: f64) -> f64 {
        let ev = match *self {
            SpectrumScaling::WeylFit {
                eigenpairs: Some(m),
            } => match ev.get(..m) {
                Some(band) => band,
                None => return 1.0,
            },
            _ => ev,
        };
        let zero_tol = ZERO_MODE_TOLERANCE * 4.0 * std::f64::consts::PI / area;
        let nz: Vec<f64> = ev.iter().copied().filter(|&l| l > zero_tol).collect();
        if nz.is_empty() {
            return 1.0;
        }
        match self {
            SpectrumScaling::None => 1.0,
            SpectrumScaling::Lambda1 { reference } => reference / nz[0],
            SpectrumScaling::WeylFit { .. } => {
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
        let all = SpectrumScaling::WeylFit { eigenpairs: None };
        let w = all.factor(&ev, 1.0);
        assert!((w - 4.0 * std::f64::consts::PI / 5.0).abs() < 1e-12);
        let four = SpectrumScaling::WeylFit {
            eigenpairs: Some(4),
        };
        assert_eq!(four.factor(&ev, 1.0).to_bits(), w.to_bits());
    }

    /// A fixed band gives the same factor whatever the number of eigenpairs computed beyond it,
    /// and no scaling when the band was not computed; the unbounded fit drifts with `k`.
    #[test]
    fn weyl_fit_band_is_independent_of_k() {
        // Neumann-like spectrum with a boundary term: i = λ/4π + 1.13 (λ/4π)^{1/2}.
        let ev: Vec<f64> = std::iter::once(0.0)
            .chain((1..200).map(|i| {
                let s = (-1.13 + (1.13f64 * 1.13 + 4.0 * i as f64).sqrt()) / 2.0;
                4.0 * std::f64::consts::PI * s * s
            }))
            .collect();
        let band = SpectrumScaling::WeylFit {
            eigenpairs: Some(WEYL_FIT_EIGENPAIRS),
        };
        let f100 = band.factor(&ev[..100], 1.0);
        assert_eq!(band.factor(&ev[..150], 1.0).to_bits(), f100.to_bits());
        assert_eq!(band.factor(&ev, 1.0).to_bits(), f100.to_bits());
        assert_eq!(band.factor(&ev[..99], 1.0), 1.0);
        assert_eq!(band.factor(&ev[..30], 1.0), 1.0);
        assert!(f100 > 1.05, "the boundary term lowers the slope: {f100}");
        let all = SpectrumScaling::WeylFit { eigenpairs: None };
        assert_eq!(all.factor(&ev[..100], 1.0).to_bits(), f100.to_bits());
        assert!(all.factor(&ev[..30], 1.0) > f100 + 0.05);
        assert!(all.factor(&ev, 1.0) < f100 - 0.01);
    }

    #[test]
    fn serde_keeps_the_unbounded_key() {
        let all = SpectrumScaling::WeylFit { eigenpairs: None };
        assert_eq!(
            serde_json::to_string(&all).unwrap(),
            r#"{"kind":"weyl_fit"}"#
        );
        let back: SpectrumScaling = serde_json::from_str(r#"{"kind":"weyl_fit"}"#).unwrap();
        assert_eq!(back, all);
        let band: SpectrumScaling =
            serde_json::from_str(r#"{"kind":"weyl_fit","eigenpairs":100}"#).unwrap();
        assert_eq!(
            band,
            SpectrumScaling::WeylFit {
                eigenpairs: Some(100)
            }
        );
    }
}
