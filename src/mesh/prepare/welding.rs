//! Step 2 of [`prepare`](super::prepare): vertex welding, exact or within a tolerance, and the
//! union–find the component step shares.

use crate::mesh::{norm, sub};

/// Lexicographic total order of positions (used to pick a cluster's position independently of
/// the vertex order).
pub(super) fn lex_less(a: [f64; 3], b: [f64; 3]) -> bool {
    a[0].total_cmp(&b[0])
        .then(a[1].total_cmp(&b[1]))
        .then(a[2].total_cmp(&b[2]))
        .is_lt()
}

/// Given `cluster[i]` (= smallest index of the cluster), picks the lexicographically smallest
/// member of each cluster as the source of its position: `source[c]` for cluster ids `c`.
pub(super) fn cluster_sources(vertices: &[[f64; 3]], cluster: &[u32]) -> Vec<u32> {
    let mut source: Vec<u32> = (0..cluster.len() as u32).collect();
    for (i, &c) in cluster.iter().enumerate() {
        let s = &mut source[c as usize];
        if lex_less(vertices[i], vertices[*s as usize]) {
            *s = i as u32;
        }
    }
    source
}

/// Exact welding: clusters of bitwise-equal positions (`-0.0` treated as `0.0`), by sorting.
pub(super) fn weld_exact(vertices: &[[f64; 3]]) -> (Vec<u32>, Vec<u32>) {
    let mut keys: Vec<([u64; 3], u32)> = vertices
        .iter()
        .enumerate()
        .map(|(i, v)| (v.map(|c| (c + 0.0).to_bits()), i as u32))
        .collect();
    keys.sort_unstable();
    let mut cluster = vec![0u32; vertices.len()];
    let mut start = 0;
    while start < keys.len() {
        let mut end = start + 1;
        while end < keys.len() && keys[end].0 == keys[start].0 {
            end += 1;
        }
        let id = keys[start].1; // smallest index: ties are sorted by index
        for k in &keys[start..end] {
            cluster[k.1 as usize] = id;
        }
        start = end;
    }
    let source = cluster_sources(vertices, &cluster);
    (cluster, source)
}

/// Tolerance welding with a spatial hash grid of cell size `eps × bbox diagonal`: vertices at
/// distance `≤` that are united (transitively); exact duplicates are always united.
pub(super) fn weld_tolerance(vertices: &[[f64; 3]], eps: f64) -> (Vec<u32>, Vec<u32>) {
    let n = vertices.len();
    if n == 0 {
        return (Vec::new(), Vec::new());
    }
    let (lo, hi) = crate::mesh::bounding_box(vertices);
    let h = eps * norm(sub(hi, lo));
    if !(h > 0.0 && h.is_finite()) {
        return weld_exact(vertices);
    }
    // Cell coordinates; `as i64` saturates, which only makes cells coarser (still correct).
    let cell =
        |v: &[f64; 3]| -> [i64; 3] { [0, 1, 2].map(|k| ((v[k] - lo[k]) / h).floor() as i64) };
    let mut order: Vec<([i64; 3], u32)> = vertices
        .iter()
        .enumerate()
        .map(|(i, v)| (cell(v), i as u32))
        .collect();
    order.sort_unstable();
    let mut cells: Vec<([i64; 3], usize, usize)> = Vec::new();
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        while end < order.len() && order[end].0 == order[start].0 {
            end += 1;
        }
        cells.push((order[start].0, start, end));
        start = end;
    }
    let h2 = h * h;
    let mut uf = UnionFind::new(n);
    let try_pair = |i: u32, j: u32, uf: &mut UnionFind| {
        let d = sub(vertices[j as usize], vertices[i as usize]);
        if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= h2 {
            uf.union(i, j);
        }
    };
    // Each pair of neighbouring cells once: the cell itself, then the 13 neighbours after it in
    // lexicographic order, as five runs (dx, dy, dz_lo..=dz_hi) that are contiguous in the sorted
    // cell list. The start of each run only moves forward as the cells are visited in order, so
    // one cursor per run finds it without hashing or searching. (`saturating_add` keeps the keys
    // monotone; a saturated run may revisit a pair, which is harmless.)
    const RUNS: [(i64, i64, i64, i64); 5] = [
        (0, 0, 1, 1),
        (0, 1, -1, 1),
        (1, -1, -1, 1),
        (1, 0, -1, 1),
        (1, 1, -1, 1),
    ];
    let mut cursor = [0usize; 5];
    for &(c, s, e) in &cells {
        for a in s..e {
            for b in a + 1..e {
                try_pair(order[a].1, order[b].1, &mut uf);
            }
        }
        for (r, &(dx, dy, z0, z1)) in RUNS.iter().enumerate() {
            let (x, y) = (c[0].saturating_add(dx), c[1].saturating_add(dy));
            let first = [x, y, c[2].saturating_add(z0)];
            let last = [x, y, c[2].saturating_add(z1)];
            while cursor[r] < cells.len() && cells[cursor[r]].0 < first {
                cursor[r] += 1;
            }
            let mut q = cursor[r];
            while q < cells.len() && cells[q].0 <= last {
                let (_, s2, e2) = cells[q];
                for a in s..e {
                    for b in s2..e2 {
                        try_pair(order[a].1, order[b].1, &mut uf);
                    }
                }
                q += 1;
            }
        }
    }
    let cluster: Vec<u32> = (0..n as u32).map(|i| uf.find(i)).collect();
    let source = cluster_sources(vertices, &cluster);
    (cluster, source)
}

/// Union–find with path halving; the root of a set is its smallest element.
pub(super) struct UnionFind {
    parent: Vec<u32>,
}

impl UnionFind {
    pub(super) fn new(n: usize) -> Self {
        Self {
            parent: (0..n as u32).collect(),
        }
    }

    pub(super) fn find(&mut self, mut x: u32) -> u32 {
        while self.parent[x as usize] != x {
            let g = self.parent[self.parent[x as usize] as usize];
            self.parent[x as usize] = g;
            x = g;
        }
        x
    }

    pub(super) fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra < rb {
            self.parent[rb as usize] = ra;
        } else if rb < ra {
            self.parent[ra as usize] = rb;
        }
    }
}
