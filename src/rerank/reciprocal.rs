//! Reciprocal-neighbourhood re-ranking: the shortlist is re-ordered by how much the
//! neighbourhoods of the query and of each candidate overlap, within the shortlist.
//!
//! Method: k-reciprocal encoding (Zhong, Zheng, Cao, Li, "Re-ranking person re-identification
//! with k-reciprocal encoding", CVPR 2017), applied to the first stage's spectral dissimilarity
//! and averaged over several neighbourhood sizes. For the `N = K + 1` items of a shortlist (item
//! 0 = the query, items 1..=K = the candidates in first-stage order) and the first stage's
//! dissimilarities `D` between all of them:
//!
//! 1. `R(i, k)` = the items among the `k + 1` nearest of `i` (itself included) that also have `i`
//!    among their `k + 1` nearest: the *k-reciprocal* neighbours of `i`.
//! 2. `R*(i, k)` = `R(i, k)` ∪ every `R(c, ⌈k/2⌉)`, `c ∈ R(i, k)`, that shares more than two
//!    thirds of its items with `R(i, k)` (recovers the reciprocal neighbours a pose or a
//!    topology change pushed just outside the `k` nearest).
//! 3. `V_i` = `exp(−D̂(i, j))` on `R*(i, k)`, 0 elsewhere, normalised to sum 1; `D̂` = `D` over
//!    the row's largest finite value. Local query expansion: `V_i ← mean of V_j` over the
//!    `expansion` nearest `j` of `i` (itself included).
//! 4. Jaccard distance `J(0, j) = 1 − Σ min(V_0, V_j) / Σ max(V_0, V_j)`.
//! 5. Score `(1 − λ) · mean_k J_k(0, j) + λ · D̂(0, j)`; ties keep the first-stage order.
//!    Sizes with `2k + 1 > N` are left out (small indexes; the smallest is kept if none is left).
//!
//! Why several `k`: a single `k` is a prior on how many relevant shapes a query has. On
//! bench/dev (35 shapes per class) `k = 30` is the best single value, but it loses to the first
//! stage when classes have 8 members, where k = 8 or 16 is best; the mean over `k ∈ {8, 16, 32}`
//! gained at every class size measured (8, 15, 25, 35; docs/quality.md §7), i.e. it does not have
//! to know the class size. The shortlist must be a few times larger than the largest relevant
//! set (default 200), and every pair in it is scored once (`K(K + 1)/2` first-stage scores,
//! ≈ 20 000 for the default; the server's default search took p50 20.6 ms at 1 000 stored shapes,
//! docs/quality.md §7).
//!
//! Written here rather than taken from a crate: no Rust crate implements this re-ranking, and
//! its reference implementation (Python, for feature vectors) assumes Euclidean features, while
//! only a dissimilarity matrix exists here.

use serde::{Deserialize, Serialize};

/// Parameters of the reciprocal-neighbourhood stage (module docs).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ReciprocalStage {
    /// How many first-stage results to re-rank (`K`).
    pub shortlist: usize,
    /// Neighbourhood sizes `k` whose Jaccard distances are averaged.
    pub neighbourhoods: Vec<usize>,
    /// Local query expansion: how many nearest items' encodings are averaged (1 = none).
    pub expansion: usize,
    /// Weight `λ` of the (row-normalised) first-stage dissimilarity in the final score.
    pub original_weight: f64,
}

impl Default for ReciprocalStage {
    fn default() -> Self {
        Self {
            shortlist: 200,
            neighbourhoods: vec![8, 16, 32],
            expansion: 4,
            original_weight: 0.1,
        }
    }
}

impl ReciprocalStage {
    /// Why the stage cannot run, if it cannot.
    pub fn validate(&self) -> Result<(), String> {
        if self.shortlist == 0 {
            return Err("shortlist must be ≥ 1".into());
        }
        if self.neighbourhoods.is_empty() || self.neighbourhoods.len() > 8 {
            return Err("neighbourhoods: 1 to 8 sizes".into());
        }
        if self.neighbourhoods.iter().any(|&k| k == 0 || k > 1000) {
            return Err("neighbourhoods must be in 1..=1000".into());
        }
        if self.expansion == 0 || self.expansion > 100 {
            return Err("expansion must be in 1..=100".into());
        }
        if !(0.0..=1.0).contains(&self.original_weight) {
            return Err("original_weight must be in [0, 1]".into());
        }
        Ok(())
    }
}

/// Scores of the candidates of one shortlist (module docs).
///
/// `d` is the row-major `n × n` first-stage dissimilarity of the query (row and column 0) and its
/// `n − 1` candidates. Only the strict upper triangle is read (entry `(a, b)`, `a < b`, is the
/// score of `b` with `a` as the query; the dissimilarities of [`crate::ranking`] are symmetric),
/// so a caller may leave the rest unset. Returns one score per candidate (index `j − 1`
/// for item `j`), lower = more similar. Deterministic: ties between equal dissimilarities are
/// broken by item index, never by memory order or thread count.
pub fn scores(d: &[f64], n: usize, stage: &ReciprocalStage) -> Vec<f64> {
    assert_eq!(d.len(), n * n, "dissimilarity matrix must be n × n");
    if n <= 1 {
        return Vec::new();
    }
    // The upper triangle, mirrored.
    let at = |a: usize, b: usize| if a < b { d[a * n + b] } else { d[b * n + a] };
    // Row-normalised dissimilarity; the diagonal is 0.
    let mut dn = vec![0.0; n * n];
    for i in 0..n {
        let row: Vec<f64> = (0..n)
            .map(|j| if i == j { 0.0 } else { at(i, j) })
            .collect();
        let max = (0..n)
            .filter(|&j| j != i && row[j].is_finite())
            .map(|j| row[j])
            .fold(0.0f64, f64::max);
        let scale = if max > 0.0 { max } else { 1.0 };
        for j in 0..n {
            dn[i * n + j] = if i == j {
                0.0
            } else if row[j].is_finite() {
                row[j] / scale
            } else {
                f64::INFINITY
            };
        }
    }
    // ranks[i]: items by increasing dissimilarity from i, i itself first, ties by index;
    // pos[i][j]: the position of j in ranks[i].
    let mut ranks = vec![0usize; n * n];
    let mut pos = vec![0usize; n * n];
    for i in 0..n {
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| {
            (a != i)
                .cmp(&(b != i))
                .then(dn[i * n + a].total_cmp(&dn[i * n + b]))
                .then(a.cmp(&b))
        });
        for (p, &j) in order.iter().enumerate() {
            ranks[i * n + p] = j;
            pos[i * n + j] = p;
        }
    }
    let reciprocal = |i: usize, k: usize| -> Vec<usize> {
        let m = (k + 1).min(n);
        ranks[i * n..i * n + m]
            .iter()
            .copied()
            .filter(|&j| pos[j * n + i] <= k)
            .collect()
    };
    let lambda = stage.original_weight;
    let sizes = effective_sizes(&stage.neighbourhoods, n);
    if sizes.is_empty() {
        // No neighbourhood size (an unvalidated stage): the first stage's order.
        return dn[1..n].to_vec();
    }
    let mut total = vec![0.0; n - 1];
    for &k in &sizes {
        // R(c, ⌈k/2⌉) of every item, computed once (each is read by every set it belongs to).
        let halves: Vec<Vec<usize>> = (0..n).map(|c| reciprocal(c, k.div_ceil(2))).collect();
        // Encodings V_i (dense rows).
        let mut v = vec![0.0; n * n];
        let mut in_rec = vec![false; n];
        let mut member = vec![false; n];
        for i in 0..n {
            let rec = reciprocal(i, k);
            in_rec.iter_mut().for_each(|m| *m = false);
            for &j in &rec {
                in_rec[j] = true;
            }
            member.copy_from_slice(&in_rec);
            for &c in &rec {
                let rc = &halves[c];
                let shared = rc.iter().filter(|&&j| in_rec[j]).count();
                if 3 * shared > 2 * rc.len() {
                    for &j in rc {
                        member[j] = true;
                    }
                }
            }
            let row = &mut v[i * n..(i + 1) * n];
            let mut sum = 0.0;
            for j in 0..n {
                if member[j] {
                    row[j] = (-dn[i * n + j]).exp();
                    sum += row[j];
                }
            }
            if sum > 0.0 {
                row.iter_mut().for_each(|x| *x /= sum);
            }
        }
        // Local query expansion.
        let e = stage.expansion.min(n);
        let v = if e > 1 {
            let mut w = vec![0.0; n * n];
            for i in 0..n {
                for p in 0..e {
                    let j = ranks[i * n + p];
                    for l in 0..n {
                        w[i * n + l] += v[j * n + l];
                    }
                }
                w[i * n..(i + 1) * n]
                    .iter_mut()
                    .for_each(|x| *x /= e as f64);
            }
            w
        } else {
            v
        };
        // Jaccard distance of the query's encoding to each candidate's.
        let q = &v[..n];
        for j in 1..n {
            let c = &v[j * n..(j + 1) * n];
            let shared: f64 = q.iter().zip(c).map(|(a, b)| a.min(*b)).sum();
            total[j - 1] += 1.0 - shared / (2.0 - shared);
        }
    }
    let m = sizes.len() as f64;
    (1..n)
        .map(|j| (1.0 - lambda) * total[j - 1] / m + lambda * dn[j])
        .collect()
}

/// The neighbourhood sizes used for `n` items: those with `2k + 1 ≤ n` (a neighbourhood of more
/// than half the shortlist holds most of it for every item and says nothing about the query's
/// own relevant set), or the smallest size when none qualifies.
fn effective_sizes(sizes: &[usize], n: usize) -> Vec<usize> {
    let kept: Vec<usize> = sizes.iter().copied().filter(|&k| 2 * k < n).collect();
    if kept.is_empty() {
        sizes.iter().copied().min().into_iter().collect()
    } else {
        kept
    }
}

/// Re-orders a shortlist: `d` as in [`scores`]; returns `(candidate index, score)` best first
/// (candidate index `j − 1` for item `j`), ties by first-stage order.
pub fn rerank(d: &[f64], n: usize, stage: &ReciprocalStage) -> Vec<(usize, f64)> {
    let s = scores(d, n, stage);
    let mut idx: Vec<usize> = (0..s.len()).collect();
    idx.sort_by(|&a, &b| s[a].total_cmp(&s[b]).then(a.cmp(&b)));
    idx.into_iter().map(|i| (i, s[i])).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Euclidean distances of 2-D points, row-major.
    fn matrix(p: &[[f64; 2]]) -> Vec<f64> {
        let n = p.len();
        let mut d = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                d[i * n + j] = ((p[i][0] - p[j][0]).powi(2) + (p[i][1] - p[j][1]).powi(2)).sqrt();
            }
        }
        d
    }

    /// Query at the start of a chain of 12 points (its class, spacing 1 with a small zigzag)
    /// and a tight clump of 12 points of another class at distance 5 from the query: the first
    /// stage ranks the clump before the far half of the chain.
    fn chain_and_clump() -> (Vec<[f64; 2]>, Vec<bool>) {
        let mut p = vec![[0.0, 0.0]];
        let mut same = vec![true];
        for i in 1..=12 {
            p.push([i as f64, if i % 2 == 0 { 0.1 } else { -0.1 }]);
            same.push(true);
        }
        for i in 0..12 {
            let a = i as f64 * std::f64::consts::TAU / 12.0;
            p.push([0.3 * a.cos(), 5.0 + 0.3 * a.sin()]);
            same.push(false);
        }
        (p, same)
    }

    fn ap(order: &[usize], relevant: &[bool]) -> f64 {
        let (mut hits, mut sum) = (0.0, 0.0);
        for (r, &i) in order.iter().enumerate() {
            if relevant[i] {
                hits += 1.0;
                sum += hits / (r + 1) as f64;
            }
        }
        sum / hits
    }

    fn stage(ks: &[usize]) -> ReciprocalStage {
        ReciprocalStage {
            shortlist: 100,
            neighbourhoods: ks.to_vec(),
            expansion: 2,
            original_weight: 0.1,
        }
    }

    #[test]
    fn chain_members_move_ahead_of_a_closer_clump() {
        let (p, same) = chain_and_clump();
        let n = p.len();
        let d = matrix(&p);
        let relevant: Vec<bool> = same[1..].to_vec();
        let mut first: Vec<usize> = (0..n - 1).collect();
        first.sort_by(|&a, &b| d[a + 1].total_cmp(&d[b + 1]).then(a.cmp(&b)));
        let before = ap(&first, &relevant);
        let order: Vec<usize> = rerank(&d, n, &stage(&[4, 8])).iter().map(|x| x.0).collect();
        let after = ap(&order, &relevant);
        // Measured: 0.622 → 0.915; the two far ends of the chain (not reciprocal neighbours of
        // anything near the query at k ≤ 8) stay behind the clump.
        assert!(
            before < 0.65,
            "the first stage must be imperfect here ({before})"
        );
        assert!(after > 0.9, "AP {before} → {after}, order {order:?}");
        assert!(
            order[..10].iter().all(|&i| relevant[i]),
            "the ten nearest chain points come first: {order:?}"
        );
    }

    #[test]
    fn scores_follow_candidates_not_their_order() {
        // Jittered (no equal distances: ties are broken by position, on purpose).
        let (mut p, _) = chain_and_clump();
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for q in p.iter_mut() {
            for c in q.iter_mut() {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                *c += 1e-3 * ((x >> 11) as f64 / (1u64 << 53) as f64 - 0.5);
            }
        }
        let n = p.len();
        let st = stage(&[4, 8]);
        let s0 = scores(&matrix(&p), n, &st);
        // Reverse the candidates (the query stays item 0).
        let mut q = vec![p[0]];
        q.extend(p[1..].iter().rev());
        let s1 = scores(&matrix(&q), n, &st);
        for j in 0..n - 1 {
            let k = n - 2 - j;
            assert!(
                (s0[j] - s1[k]).abs() <= 1e-12,
                "{j}: {} vs {}",
                s0[j],
                s1[k]
            );
        }
        // Deterministic.
        assert_eq!(s0, scores(&matrix(&p), n, &st));
    }

    #[test]
    fn large_neighbourhoods_are_left_out_of_small_shortlists() {
        assert_eq!(effective_sizes(&[8, 16, 32], 201), vec![8, 16, 32]);
        assert_eq!(effective_sizes(&[8, 16, 32], 64), vec![8, 16]);
        assert_eq!(effective_sizes(&[8, 16, 32], 24), vec![8]);
        assert_eq!(effective_sizes(&[16, 8, 32], 10), vec![8]);
        // A size that covers the whole shortlist is then the only one, and the scores stay
        // finite and ordered by the first stage's weight.
        let (p, _) = chain_and_clump();
        let s = scores(&matrix(&p[..5]), 5, &stage(&[32]));
        assert!(s.iter().all(|x| x.is_finite()));
    }

    #[test]
    fn degenerate_inputs() {
        assert!(scores(&[0.0], 1, &ReciprocalStage::default()).is_empty());
        // Infinite dissimilarities (a candidate missing a channel) rank last.
        let mut d = matrix(&[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]);
        d[3] = f64::INFINITY;
        d[3 * 4] = f64::INFINITY;
        let order = rerank(&d, 4, &stage(&[1]));
        assert_eq!(order.last().unwrap().0, 2, "{order:?}");
        for bad in [
            ReciprocalStage {
                shortlist: 0,
                ..ReciprocalStage::default()
            },
            ReciprocalStage {
                neighbourhoods: vec![],
                ..ReciprocalStage::default()
            },
            ReciprocalStage {
                neighbourhoods: vec![0],
                ..ReciprocalStage::default()
            },
            ReciprocalStage {
                expansion: 0,
                ..ReciprocalStage::default()
            },
            ReciprocalStage {
                original_weight: 1.5,
                ..ReciprocalStage::default()
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
        assert!(ReciprocalStage::default().validate().is_ok());
    }
}
