//! All-pairs dissimilarity matrices of a run, per channel and per configuration.

use crate::ranking::{Dissimilarity, QuerySpec};
use crate::search::corpus::Corpus;
use crate::search::score::channel_dissimilarity;
use crate::search::Query;
use rayon::prelude::*;
use std::collections::HashMap;

/// All-pairs per-channel dissimilarity matrices, computed once per (channel, dissimilarity)
/// and shared by every configuration of a signature family: `Heat-L2-nL1-Single[t]`, `…-Sum`,
/// `…-Sum2` and `…-Max` all reuse the same six matrices. A configuration's matrix is then
/// [`Query::aggregate`] of the channels' values and [`Query::with_second`] for pairs with a
/// second cut version, which is how [`Query::score`] is computed: the same numbers as the
/// server's scan, by construction.
#[derive(Default)]
pub(super) struct ChannelMatrices {
    mats: HashMap<(usize, Dissimilarity), Vec<f64>>,
}

impl ChannelMatrices {
    fn matrix(&mut self, corpus: &Corpus, included: &[bool], c: usize, d: Dissimilarity) {
        self.mats.entry((c, d)).or_insert_with(|| {
            let n = corpus.len();
            let l = corpus.layout();
            let mut m = vec![f64::NAN; n * n];
            m.par_chunks_mut(n.max(1)).enumerate().for_each(|(i, row)| {
                if included[i] {
                    for (j, x) in row.iter_mut().enumerate() {
                        if i != j && included[j] {
                            *x = channel_dissimilarity(l, d, c, corpus.shape(i), corpus.shape(j));
                        }
                    }
                }
            });
            m
        });
    }

    /// The configuration's all-pairs matrix (row = query; NaN on the diagonal and for shapes
    /// left out).
    pub(super) fn aggregate(
        &mut self,
        corpus: &Corpus,
        included: &[bool],
        spec: &QuerySpec,
    ) -> Vec<f64> {
        let l = corpus.layout();
        let q = Query::new(spec, l);
        for &c in q.channels.iter().flatten() {
            self.matrix(corpus, included, c, q.dissimilarity);
        }
        let mats = &self.mats;
        let n = corpus.len();
        let mut out = vec![f64::NAN; n * n];
        out.par_chunks_mut(n.max(1))
            .enumerate()
            .for_each(|(i, row)| {
                if !included[i] {
                    return;
                }
                for (j, x) in row.iter_mut().enumerate() {
                    if i != j && included[j] {
                        let first = q.aggregate(|c| mats[&(c, q.dissimilarity)][i * n + j]);
                        *x = q.with_second(l, corpus.shape(i), corpus.shape(j), first);
                    }
                }
            });
        out
    }
}
