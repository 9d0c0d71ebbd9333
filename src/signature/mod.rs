//! Corpus-independent spectral signatures of one shape (paper §2.3–§3).
//!
//! A [`SignatureSpec`] lists *channels* (kernel × norm × scale, a scale aggregate, or a
//! baseline); [`compute_signature`] turns an [`Analysis`](crate::spectrum::Analysis) (unit-area
//! mesh + spectrum) into a [`Signature`] holding, per channel, a distribution of pair distances
//! that does **not** depend on any other shape. Histograms on a corpus window are derived later
//! ([`crate::ranking::prepare_for_ranking`]).
//!
//! The submodules, in dependency order (each uses only those above it):
//!
//! * [`spec`]: the channel and discretisation types, their names, keys and validation;
//! * [`distributions`]: the streaming fine histogram and the [`QuantileSketch`] read from it;
//! * [`sampling`]: the edge graph, geodesic farthest-point samples with Voronoi-cell weights
//!   (the pair quadrature) and the near field of adjacent cells;
//! * [`kernels`]: transfer weights `K(λ_i)` and the diffusion distances between quadrature
//!   points;
//! * [`scale_invariant`]: the scale-invariant kernel of eq. 21 and its distances;
//! * [`baselines`]: geodesic distances, Osada's D2 (ShapeDNA is a plain eigenvalue vector);
//! * [`compute`]: [`compute_signature`] and the [`Signature`] value;
//! * [`codec`]: the binary encoding of a [`Signature`];
//! * [`versions`]: the two cut versions of a shape ([`SignatureSpec::alternate_cut`]) and
//!   [`sign`], mesh to signature with both.
//!
//! # Distances
//!
//! * Kernel weights `K(λ_i)` (eq. 5): heat `e^{-tλ}`, commute time `λ^{-1/2}` (eq. 19), step
//!   `1[λ < λ_c]`, or a kernel-stage aggregate over heat scales (§3.2). Zero modes
//!   (`λ ≤ 10⁻⁶ · 4π / area`, [`crate::spectrum::ZERO_MODE_TOLERANCE`], the λ_0 of each
//!   component) get weight 0 everywhere, so the constant (per component) eigenfunctions never
//!   enter a distance. Modes with `K² < 10⁻¹⁶ · max K²` are dropped (they change `d²` by less
//!   than 10⁻¹⁶ relative).
//! * **L2** (eq. 9): `d²(x,y) = Σ_{i} K(λ_i)² (φ_i(x) − φ_i(y))²`, computed for all quadrature
//!   point pairs at once as `|ψ_x|² + |ψ_y|² − 2 ψ_x·ψ_y` with `ψ = Φ diag(K)`, one GEMM per row
//!   block of the upper triangle. This equals eq. 6 with the A-weighted vertex quadrature
//!   because `Φᵀ A Φ = I` (tested to 1e-8).
//! * **L1 / L∞**: kernel rows `k(x, z) = Σ_i K(λ_i) φ_i(x) φ_i(z)` evaluated on `lp_samples`
//!   (default 500) farthest-point nodes `z` with their Voronoi areas as quadrature weights:
//!   `d(x,y) = Σ_z W_z |k(x,z) − k(y,z)|` resp. `max_z |…|`, the same nodes serving as pair
//!   points (with the near field below). O(m³): paper Table 2's H-L1 and H-L∞ only.
//! * **Scale-invariant kernel** (eq. 21, [`scale_invariant`]): `k̂ = F⁻¹|F(∂_τ log k_τ)|` on a
//!   log-time grid per pair of `lp_samples` nodes, then an L1 / L2 / L∞ norm over the nodes with
//!   the area-normalised measure: invariant under uniform scaling without unit-area
//!   normalisation (tested on a scaled mesh), as is the commute-time kernel under nL1 (eq. 19).
//!
//! # Pair quadrature (eq. 10)
//!
//! F is the push-forward of `μ × μ`. [`PairQuadrature::AllVertices`] uses every ordered vertex
//! pair with weight `a_x a_y` (exact, O(n² k)). The default, [`PairQuadrature::Farthest`], uses
//! `m = 1000` **farthest-point samples** (geodesic FPS on the edge graph, started at the vertex
//! farthest from the area centroid, so the choice is rigid-motion and permutation invariant on
//! asymmetric shapes), each carrying the area of its **Voronoi cell** (every vertex is assigned
//! to its nearest sample in edge-graph distance, weights `a_i`): every ordered sample pair
//! `(i, j)` has weight `W_i W_j`, so the total mass is still `area²`. **Near field**: pairs of
//! the same or of adjacent cells (cells joined by a mesh edge) are evaluated one-sided exactly,
//! `W_i Σ_{y ∈ cell j} a_y δ(d(s_i, y))`, so that small distances are not quantised to the
//! sample spacing (≈ 7 n extra distances; the mass is unchanged). The test
//! `quadrature_and_sketch_errors_against_exact_all_pairs` bounds the error of this quadrature
//! against the exact all-pairs distribution; the measured sweep is in `docs/signature.md`.
//!
//! # Stored representation
//!
//! Distances are streamed (no pair is stored) into a fine histogram of 32 768 bins on
//! `[0, bound]` (`bound` = the sum of the two largest `|ψ|`, an upper bound of every distance)
//! plus an exact atom at 0 (the diagonal pairs) and the exact smallest / largest distance. From
//! it a [`QuantileSketch`] is read: the total mass `F(∞)` and the quantile function at
//! `sketch_quantiles + 1` (default 1 025) equally spaced levels, the CDF linear between knots.
//! Any window, bin count and Parzen bandwidth can be derived from it (1 025 × 8 bytes per
//! channel).
//!
//! # Scales
//!
//! [`DEFAULT_HEAT_SCALES`] = `0.016 · 2.5^j`, j = 0..5, for **unit-area** shapes (the pipeline
//! normalises area): unit-area shapes have `λ_1 ≈ 6`, so `t λ_1` spans ≈ 0.1 … 10, from "many
//! eigenfunctions matter" to "φ_1 dominates", and at the smallest t `e^{-t λ_100} ≈ e^{-20}`, so
//! k = 100 eigenpairs truncate nothing. [`SMALL_HEAT_SCALES`] are the three smallest. The
//! default's full-range channels go two steps further down the same grid
//! ([`crate::presets::DEFAULT_FULL_RANGE_TIMES`], t = 0.00256 and 0.0064): there the 100
//! eigenpairs do truncate the kernel (`e^{−t λ_100}` ≈ 0.04 at t = 0.00256), so those channels
//! are heat kernels band-limited to the first 100 modes — the same band on every shape.
//!
//! # Complexity and determinism
//!
//! FPS: `O(m n)` for the farthest-vertex scans plus pruned Dijkstra runs. Per L2 channel:
//! `O(m² k_eff)` GEMM + `m²/2` histogram updates + `O(n k_eff)` near field. Channels run in
//! parallel (rayon), each over row blocks; per-block histograms are merged in block order, so
//! results are bitwise deterministic whatever the thread count.

pub mod baselines;
pub mod codec;
pub mod compute;
pub mod distributions;
pub mod kernels;
pub mod sampling;
pub mod scale_invariant;
pub mod spec;
pub mod versions;

/// Re-exported from [`crate::spectrum`], where zero modes are defined.
pub use crate::spectrum::ZERO_MODE_TOLERANCE;
pub use compute::{
    compute_signature, compute_signature_interruptible, ChannelData, ChannelValues, Signature,
};
pub use distributions::{truncate_sketch, QuantileSketch};
pub use kernels::transfer_weights;
pub(crate) use sampling::{farthest_points, EdgeGraph};
pub use spec::{
    Aggregation, ChannelKind, ChannelSpec, Kernel, Norm, PairQuadrature, SignatureSpec,
    DEFAULT_HEAT_SCALES, SMALL_HEAT_SCALES,
};
pub use versions::sign;

#[cfg(test)]
mod tests;
