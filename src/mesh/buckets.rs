//! Items grouped by a small integer key (a vertex, usually): the compressed-sparse-row layout
//! that every adjacency list, faces-of-a-vertex list and edge bucket of the mesh code shares.
//!
//! Written here rather than taken from a crate: it is a counting sort of a dozen lines, and the
//! sparse-matrix crates' CSR types (faer's, sprs's) carry values, row-column semantics and a
//! dependency that these graph walks do not need.

/// Items grouped by key in `0..n`: one contiguous slice per key, each in the order the items
/// came (a stable counting sort), so that every walk over a group is deterministic.
#[derive(Clone, Debug, Default)]
pub(crate) struct Buckets<T> {
    /// `start[k]..start[k + 1]` is key `k`'s range of `items`; `start.len() == n + 1`.
    start: Vec<usize>,
    items: Vec<T>,
}

impl<T: Copy + Default> Buckets<T> {
    /// Groups the `(key, item)` pairs by key (`key < n`; a larger key panics). Each pair is
    /// produced once (collected, then counted and placed), so an item computed on the way (an
    /// edge length) is computed once.
    pub(crate) fn new(n: usize, pairs: impl IntoIterator<Item = (u32, T)>) -> Self {
        let pairs: Vec<(u32, T)> = pairs.into_iter().collect();
        let mut start = vec![0usize; n + 1];
        for &(k, _) in &pairs {
            start[k as usize + 1] += 1;
        }
        for k in 0..n {
            start[k + 1] += start[k];
        }
        let mut fill = start[..n].to_vec();
        let mut items = vec![T::default(); start[n]];
        for (k, item) in pairs {
            let p = &mut fill[k as usize];
            items[*p] = item;
            *p += 1;
        }
        Self { start, items }
    }
}

impl<T> Buckets<T> {
    /// The items of key `k`.
    #[inline]
    pub(crate) fn get(&self, k: usize) -> &[T] {
        &self.items[self.start[k]..self.start[k + 1]]
    }

    /// The items of key `k`, to reorder in place.
    #[inline]
    pub(crate) fn get_mut(&mut self, k: usize) -> &mut [T] {
        &mut self.items[self.start[k]..self.start[k + 1]]
    }

    /// How many items key `k` has.
    #[inline]
    pub(crate) fn count(&self, k: usize) -> usize {
        self.start[k + 1] - self.start[k]
    }
}

#[cfg(test)]
mod tests {
    use super::Buckets;

    #[test]
    fn groups_by_key_in_input_order() {
        let b = Buckets::new(4, [(2u32, 'a'), (0, 'b'), (2, 'c'), (3, 'd'), (2, 'e')]);
        assert_eq!(b.get(0), &['b']);
        assert!(b.get(1).is_empty());
        assert_eq!(b.get(2), &['a', 'c', 'e']);
        assert_eq!(b.get(3), &['d']);
        assert_eq!((0..4).map(|k| b.count(k)).collect::<Vec<_>>(), [1, 0, 3, 1]);
    }

    #[test]
    fn empty_and_reorder_in_place() {
        let e: Buckets<u32> = Buckets::new(3, std::iter::empty());
        assert!((0..3).all(|k| e.get(k).is_empty()));
        let mut b = Buckets::new(2, [(1u32, 5u32), (1, 3), (0, 9), (1, 4)]);
        b.get_mut(1).sort_unstable();
        assert_eq!(b.get(1), &[3, 4, 5]);
        assert_eq!(b.get(0), &[9]);
    }

    #[test]
    #[should_panic]
    fn a_key_out_of_range_panics() {
        let _ = Buckets::new(2, [(2u32, 0u8)]);
    }
}
