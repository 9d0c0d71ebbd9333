//! Which stored shapes a calibration is computed on.
//!
//! A calibration (`ranking::calibrate`: per channel, the percentile of the pooled distance
//! distributions of the corpus) reads every shape's whole signature — its quantile sketches,
//! ≈ 58 KB with the default's seven histogram channels (a sixth more than the 49.5 KB measured
//! with six, docs/scale-out.md; its ShapeDNA channel adds 400 bytes) — and holds them all while
//! it computes: 6 GB at 100 000 shapes, 60 GB at a million, where the scan itself keeps ≈ 3.9 KB
//! per shape. Up to
//! `calibration_sample` shapes (10 000 by default) it is still computed on every one; above, on
//! a sample of that many: the shapes with the smallest content hashes (the SHA-256 of the
//! upload). Content hashes are spread uniformly and do not depend on ids, arrival order or the
//! backend, so every node — whole-corpus or shard, PostgreSQL or sled — that holds the same
//! uploads picks the same shapes, and a shape added or deleted changes at most one member. The
//! members are calibrated on in id order, the order the whole corpus is taken in below the
//! limit.
//!
//! The 95th percentile of a pooled distribution over 10 000 shapes differs from the whole
//! corpus's by sampling error only (each shape contributes a whole distribution of distances);
//! `calibration_sample = 0` calibrates on every shape.

use crate::signature::Signature;
use std::collections::BTreeMap;

/// The bottom-`cap` shapes by content hash among those offered.
pub(super) struct Sample {
    cap: usize,
    /// sha256 (hex) → (id, signature once read).
    members: BTreeMap<String, (String, Option<Signature>)>,
    offered: usize,
}

impl Sample {
    /// An empty sample of at most `cap` shapes (0: no limit).
    pub(super) fn new(cap: usize) -> Sample {
        Sample {
            cap: if cap == 0 { usize::MAX } else { cap },
            members: BTreeMap::new(),
            offered: 0,
        }
    }

    /// Whether a shape of content hash `sha` would enter the sample now.
    fn admits(&self, sha: &str) -> bool {
        self.members.len() < self.cap
            || self
                .members
                .last_key_value()
                .is_some_and(|(k, _)| sha < k.as_str())
    }

    fn admit(&mut self, sha: &str, id: &str, sig: Option<Signature>) {
        self.members.insert(sha.to_string(), (id.to_string(), sig));
        if self.members.len() > self.cap {
            self.members.pop_last();
        }
    }

    /// Offers a shape whose signature `read` yields (called only when the shape enters the
    /// sample; `None`, an unreadable signature, leaves it out).
    pub(super) fn offer(&mut self, sha: &str, id: &str, read: impl FnOnce() -> Option<Signature>) {
        self.offered += 1;
        if self.admits(sha) {
            if let Some(sig) = read() {
                self.admit(sha, id, Some(sig));
            }
        }
    }

    /// Offers a shape whose signature is read later ([`Sample::fill`]).
    pub(super) fn offer_id(&mut self, sha: &str, id: &str) {
        self.offered += 1;
        if self.admits(sha) {
            self.admit(sha, id, None);
        }
    }

    /// Reads the members' missing signatures with `read` (in parallel); an unreadable one stays
    /// without, and [`Sample::into_signatures`] leaves it out.
    pub(super) fn fill(&mut self, read: impl Fn(&str) -> Option<Signature> + Sync) {
        use rayon::prelude::*;
        let missing: Vec<(String, String)> = self
            .members
            .iter()
            .filter(|(_, (_, s))| s.is_none())
            .map(|(sha, (id, _))| (sha.clone(), id.clone()))
            .collect();
        let read: Vec<(String, Option<Signature>)> = missing
            .into_par_iter()
            .map(|(sha, id)| {
                let s = read(&id);
                (sha, s)
            })
            .collect();
        for (sha, sig) in read {
            if let (Some(s), Some(m)) = (sig, self.members.get_mut(&sha)) {
                m.1 = Some(s);
            }
        }
    }

    /// True when every shape offered is a member (the corpus is within the limit).
    pub(super) fn is_whole(&self) -> bool {
        self.offered <= self.cap
    }

    /// Shapes offered.
    pub(super) fn offered(&self) -> usize {
        self.offered
    }

    /// The members with their signatures, in id order.
    pub(super) fn into_signatures(self) -> Vec<(String, Signature)> {
        let mut v: Vec<(String, Signature)> = self
            .members
            .into_values()
            .filter_map(|(id, s)| s.map(|s| (id, s)))
            .collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sig(tag: usize) -> Signature {
        Signature {
            spec_key: format!("s{tag}"),
            channels: Vec::new(),
            vertices: tag,
            area: 1.0,
            quadrature_points: 0,
            alternate: None,
        }
    }

    fn sha(i: usize) -> String {
        // Distinct, unordered with respect to i.
        format!("{:064x}", (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
    }

    fn ids(s: Sample) -> Vec<String> {
        s.into_signatures().into_iter().map(|(id, _)| id).collect()
    }

    #[test]
    fn keeps_the_smallest_hashes_whatever_the_order_in_id_order() {
        let n = 50;
        let mut expected: Vec<(String, String)> =
            (0..n).map(|i| (sha(i), format!("{i:016x}"))).collect();
        expected.sort();
        let mut want: Vec<String> = expected[..7].iter().map(|(_, id)| id.clone()).collect();
        want.sort();
        for order in [
            (0..n).collect::<Vec<_>>(),
            (0..n).rev().collect(),
            (0..n).map(|i| (i * 17) % n).collect(),
        ] {
            let mut s = Sample::new(7);
            let mut reads = 0;
            for i in order {
                s.offer(&sha(i), &format!("{i:016x}"), || {
                    reads += 1;
                    Some(sig(i))
                });
            }
            assert!(!s.is_whole());
            assert_eq!(s.offered(), n);
            assert!(reads < n, "only entering shapes are read ({reads})");
            assert_eq!(ids(s), want);
        }
    }

    #[test]
    fn within_the_limit_every_shape_is_taken_and_zero_means_no_limit() {
        for cap in [0, 10, 11] {
            let mut s = Sample::new(cap);
            for i in (0..10).rev() {
                s.offer(&sha(i), &format!("{i:016x}"), || Some(sig(i)));
            }
            assert!(s.is_whole());
            let got = ids(s);
            let want: Vec<String> = (0..10).map(|i| format!("{i:016x}")).collect();
            assert_eq!(got, want, "cap {cap}");
        }
    }

    #[test]
    fn one_change_moves_at_most_one_member_and_fill_reads_the_deferred() {
        let id = |i: usize| format!("{i:016x}");
        let mut by_hash: Vec<usize> = (0..30).collect();
        by_hash.sort_by_key(|&i| sha(i));
        // Deleting a member (the second smallest hash) lets the sixth in, and nothing else moves.
        let gone = by_hash[1];
        let mut a = Sample::new(5);
        let mut b = Sample::new(5);
        for i in 0..30 {
            a.offer_id(&sha(i), &id(i));
            if i != gone {
                b.offer_id(&sha(i), &id(i));
            }
        }
        b.fill(|_| Some(sig(0)));
        let mut before: Vec<String> = a.members.values().map(|(i, _)| i.clone()).collect();
        // An unreadable member is left out of the signatures.
        let unreadable = id(by_hash[0]);
        a.fill(|x| (x != unreadable).then(|| sig(0)));
        let (a, b) = (ids(a), ids(b));
        before.retain(|x| *x != unreadable);
        before.sort();
        assert_eq!(a, before, "only the unreadable member is left out");
        let only_a: Vec<&String> = a.iter().filter(|x| !b.contains(x)).collect();
        let only_b: Vec<&String> = b.iter().filter(|x| !a.contains(x)).collect();
        assert_eq!(only_a, vec![&id(gone)]);
        let mut want_b = vec![id(by_hash[0]), id(by_hash[5])];
        want_b.sort();
        let mut got_b: Vec<String> = only_b.into_iter().cloned().collect();
        got_b.sort();
        assert_eq!(
            got_b, want_b,
            "the sixth enters (and the unreadable one stays in b)"
        );
    }
}
