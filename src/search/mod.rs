//! The search pipeline: one corpus layout, one scoring function, one exact top-k, one list of
//! re-ranking stages — shared by the server's scan, its re-ranking and `eval`.
//!
//! ```text
//! signatures ──calibrate──▶ Calibration ──Layout::of──▶ Layout
//!      │                                                  │
//!      └──prepare_for_ranking + Encoded::from_prepared──▶ Corpus (shape-major, u16 counts)
//!                                                          │
//! QuerySpec ──Query::new──▶ Query ──prune::top_k──▶ first stage ──stage::run──▶ hits
//! ```
//!
//! * [`corpus`]: the layout held once per corpus and the compact per-shape encoding
//!   (quantised bin probabilities, in-window mass, group sums).
//! * [`score`]: the nine dissimilarities on that encoding and their aggregation, with the
//!   tolerance against the `f64` histograms of [`crate::ranking`].
//! * [`prune`]: the exact top-k by lower bounds, and the full ranking it equals.
//! * [`stage`]: the validated [`Stage`] type (exact, reciprocal, spectral GW), its request and
//!   configuration forms, and [`run`].

pub mod corpus;
pub mod prune;
mod quantise;
pub mod score;
pub mod stage;

pub use corpus::{Corpus, Encoded, Layout, ShapeRef, VersionRef};
pub use prune::{rank_all, top_k};
pub use score::Query;
pub use stage::{run, Entry, Env, Stage, StageRequest};

#[cfg(test)]
mod tests;
