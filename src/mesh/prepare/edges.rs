//! Steps 3 and 6 of [`prepare`](super::prepare): exact duplicate faces, and the edge statistics of
//! the topology report (boundary edges and loops, non-manifold and inconsistently oriented edges);
//! the walk over the undirected edges ([`for_each_edge`]) is shared with step 5′'s orientation.

use crate::mesh::buckets::Buckets;

/// Marks faces whose vertex set equals that of an earlier face. Bucketed by smallest vertex
/// (counting sort), then sorted within each (small) bucket.
pub(super) fn duplicate_faces(n: usize, faces: &[[u32; 3]]) -> Vec<bool> {
    let sorted: Vec<[u32; 3]> = faces
        .iter()
        .map(|f| {
            let mut s = *f;
            s.sort_unstable();
            s
        })
        .collect();
    let mut buckets = Buckets::new(
        n,
        sorted
            .iter()
            .enumerate()
            .map(|(j, s)| (s[0], (s[1], s[2], j as u32))),
    );
    let mut dup = vec![false; faces.len()];
    for v in 0..n {
        let bucket = buckets.get_mut(v);
        if bucket.len() < 2 {
            continue;
        }
        bucket.sort_unstable();
        for k in 1..bucket.len() {
            if (bucket[k].0, bucket[k].1) == (bucket[k - 1].0, bucket[k - 1].1) {
                dup[bucket[k].2 as usize] = true;
            }
        }
    }
    dup
}

pub(super) struct Topology {
    pub(super) edges: usize,
    pub(super) boundary_edges: usize,
    pub(super) boundary_loops: usize,
    pub(super) nonmanifold_edges: usize,
    pub(super) inconsistent: usize,
}

/// The undirected edges of `faces` over `n` vertices, each visited once with its half-edges:
/// `visit(v, group)` gets edge `(v, group[0].0)`'s half-edges as `(larger vertex, payload)`,
/// sorted, `payload(face index, forward)` computed per half-edge (`forward`: it runs from the
/// smaller vertex to the larger). Half-edges are bucketed by their smaller vertex (the counting
/// sort of [`Buckets`]) and sorted within each bucket. Shared by the topology report and the
/// orientation pass.
pub(super) fn for_each_edge<T: Copy + Default + Ord>(
    n: usize,
    faces: &[[u32; 3]],
    payload: impl Fn(u32, bool) -> T,
    mut visit: impl FnMut(u32, &[(u32, T)]),
) {
    let mut buckets = Buckets::new(
        n,
        faces.iter().enumerate().flat_map(|(fi, f)| {
            let payload = &payload;
            (0..3).map(move |k| {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                (a.min(b), (a.max(b), payload(fi as u32, a < b)))
            })
        }),
    );
    for v in 0..n {
        let bucket = buckets.get_mut(v);
        bucket.sort_unstable();
        let mut s = 0;
        while s < bucket.len() {
            let mut e = s + 1;
            while e < bucket.len() && bucket[e].0 == bucket[s].0 {
                e += 1;
            }
            visit(v as u32, &bucket[s..e]);
            s = e;
        }
    }
}

/// Edge statistics of a mesh without degenerate faces ([`for_each_edge`]).
pub(super) fn analyse_edges(n: usize, faces: &[[u32; 3]]) -> Topology {
    let mut topo = Topology {
        edges: 0,
        boundary_edges: 0,
        boundary_loops: 0,
        nonmanifold_edges: 0,
        inconsistent: 0,
    };
    let mut boundary: Vec<(u32, u32)> = Vec::new();
    for_each_edge(
        n,
        faces,
        |_, forward| forward,
        |v, group| {
            topo.edges += 1;
            match group {
                [(w, _)] => boundary.push((v, *w)),
                [(_, f), (_, g)] => {
                    if f == g {
                        topo.inconsistent += 1;
                    }
                }
                _ => topo.nonmanifold_edges += 1,
            }
        },
    );
    topo.boundary_edges = boundary.len();
    topo.boundary_loops = count_boundary_loops(n, &boundary);
    topo
}

/// Decomposes the boundary-edge graph into edge-disjoint simple cycles and open chains, and
/// counts them. On a manifold boundary (every boundary vertex has two boundary edges) this is
/// exactly the number of boundary cycles. At a vertex with more boundary edges (pinch), every
/// return to a vertex already on the current walk closes a cycle; walks start at odd-degree
/// vertices first, so that open chains are not split needlessly.
pub(super) fn count_boundary_loops(n: usize, edges: &[(u32, u32)]) -> usize {
    if edges.is_empty() {
        return 0;
    }
    // (neighbour, edge id)
    let adj = Buckets::new(
        n,
        edges
            .iter()
            .enumerate()
            .flat_map(|(e, &(a, b))| [(a, (b, e as u32)), (b, (a, e as u32))]),
    );
    // How many of its edges each vertex's walk has passed over.
    let mut passed = vec![0usize; n];
    let mut used = vec![false; edges.len()];
    let mut on_path = vec![usize::MAX; n];
    let mut path: Vec<u32> = Vec::new();
    let mut loops = 0;
    let odd = (0..n).filter(|&v| adj.count(v) % 2 == 1);
    let even = (0..n).filter(|&v| adj.count(v) % 2 == 0);
    for s in odd.chain(even) {
        loop {
            // Start a walk at `s` if it has an unused edge.
            path.clear();
            path.push(s as u32);
            on_path[s] = 0;
            let mut moved = false;
            loop {
                let v = *path.last().expect("non-empty path") as usize;
                let around = adj.get(v);
                while passed[v] < around.len() && used[around[passed[v]].1 as usize] {
                    passed[v] += 1;
                }
                let Some(&(w, e)) = around.get(passed[v]) else {
                    break;
                };
                used[e as usize] = true;
                moved = true;
                let w = w as usize;
                if on_path[w] != usize::MAX {
                    loops += 1;
                    let keep = on_path[w] + 1;
                    for &u in &path[keep..] {
                        on_path[u as usize] = usize::MAX;
                    }
                    path.truncate(keep);
                } else {
                    on_path[w] = path.len();
                    path.push(w as u32);
                }
            }
            if path.len() > 1 {
                loops += 1; // an open chain
            }
            for &u in &path {
                on_path[u as usize] = usize::MAX;
            }
            if !moved {
                break;
            }
        }
    }
    loops
}
