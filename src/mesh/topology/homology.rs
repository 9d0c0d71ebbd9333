//! Z₂ homology annotations (tree–cotree) and the greedy short homology basis
//! (Erickson & Whittlesey 2005); see the parent module for the method.

use super::*;

/// Z₂ homology annotation of every edge (bit `i` = generator `i`) and the number of generators.
pub(super) fn annotations(mesh: &Mesh, t: &Topo) -> Result<(Vec<u128>, usize), TopologyError> {
    let ne = t.edges.len();
    // Primal spanning forest (BFS, deterministic).
    let mut in_tree = vec![false; ne];
    let mut seen = vec![false; t.n];
    let mut queue = std::collections::VecDeque::new();
    for s in 0..t.n {
        if seen[s] || t.adj.count(s) == 0 {
            continue;
        }
        seen[s] = true;
        queue.push_back(s as u32);
        while let Some(v) = queue.pop_front() {
            for &(w, e) in t.nbrs(v) {
                if !seen[w as usize] {
                    seen[w as usize] = true;
                    in_tree[e as usize] = true;
                    queue.push_back(w);
                }
            }
        }
    }
    // Dual graph: faces 0..F, then one node per boundary loop (the cap).
    let nf = mesh.faces.len();
    let (loop_of, nb) = t.boundary_loops();
    let nd = nf + nb;
    let dual_ends = |e: usize| -> [usize; 2] {
        let [f0, f1] = t.edge_faces[e];
        if f1 == NONE {
            [f0 as usize, nf + loop_of[e] as usize]
        } else {
            [f0 as usize, f1 as usize]
        }
    };
    // Dual node → its edges.
    let mut node_edges: Vec<Vec<u32>> = vec![Vec::new(); nb];
    for e in 0..ne {
        if t.is_boundary_edge(e) {
            node_edges[loop_of[e] as usize].push(e as u32);
        }
    }
    let edges_of = |d: usize| -> &[u32] {
        if d < nf {
            &t.face_edges[d]
        } else {
            &node_edges[d - nf]
        }
    };
    // Dual spanning forest among non-tree edges (BFS), recording the order and parent edges.
    let mut in_cotree = vec![false; ne];
    let mut dseen = vec![false; nd];
    let mut dparent = vec![NONE; nd];
    let mut order = Vec::with_capacity(nd);
    for s in 0..nd {
        if dseen[s] {
            continue;
        }
        dseen[s] = true;
        order.push(s);
        let mut head = order.len() - 1;
        while head < order.len() {
            let d = order[head];
            head += 1;
            for &e in edges_of(d) {
                let e = e as usize;
                if in_tree[e] {
                    continue;
                }
                let [a, b] = dual_ends(e);
                let o = if a == d { b } else { a };
                if !dseen[o] {
                    dseen[o] = true;
                    in_cotree[e] = true;
                    dparent[o] = e as u32;
                    order.push(o);
                }
            }
        }
    }
    let generators: Vec<usize> = (0..ne).filter(|&e| !in_tree[e] && !in_cotree[e]).collect();
    if generators.len() > 128 {
        return Err(TopologyError::GenusTooLarge(generators.len() / 2));
    }
    let mut ann = vec![0u128; ne];
    for (i, &e) in generators.iter().enumerate() {
        ann[e] = 1u128 << i;
    }
    for &d in order.iter().rev() {
        let pe = dparent[d];
        if pe == NONE {
            continue;
        }
        let mut x = 0u128;
        for &e in edges_of(d) {
            if e != pe {
                x ^= ann[e as usize];
            }
        }
        ann[pe as usize] = x;
    }
    Ok((ann, generators.len()))
}

struct Candidate {
    length: f64,
    class: u128,
    root: u32,
    edge: u32,
}

/// Candidate loops `σ(r, e)` of one root (stripped lengths and classes).
fn root_candidates(t: &Topo, ann: &[u128], root: u32, out: &mut Vec<Candidate>) -> Vec<f64> {
    let (dist, parent) = dijkstra(t, &[root]);
    // Prefix annotation along the tree and depth.
    let mut order: Vec<u32> = (0..t.n as u32)
        .filter(|&v| dist[v as usize].is_finite())
        .collect();
    order.sort_by(|&a, &b| {
        dist[a as usize]
            .total_cmp(&dist[b as usize])
            .then(a.cmp(&b))
    });
    let mut pre = vec![0u128; t.n];
    let mut depth = vec![0u32; t.n];
    for &v in &order {
        let pe = parent[v as usize];
        if pe != NONE {
            let p = other(t, pe, v);
            pre[v as usize] = pre[p as usize] ^ ann[pe as usize];
            depth[v as usize] = depth[p as usize] + 1;
        }
    }
    for (e, &[u, v]) in t.edges.iter().enumerate() {
        if !dist[u as usize].is_finite()
            || parent[u as usize] == e as u32
            || parent[v as usize] == e as u32
        {
            continue;
        }
        let class = pre[u as usize] ^ pre[v as usize] ^ ann[e];
        if class == 0 {
            continue;
        }
        // Lowest common ancestor by walking up.
        let (mut a, mut b) = (u, v);
        while depth[a as usize] > depth[b as usize] {
            a = other(t, parent[a as usize], a);
        }
        while depth[b as usize] > depth[a as usize] {
            b = other(t, parent[b as usize], b);
        }
        while a != b {
            a = other(t, parent[a as usize], a);
            b = other(t, parent[b as usize], b);
        }
        let length = dist[u as usize] + dist[v as usize] + t.len[e] - 2.0 * dist[a as usize];
        out.push(Candidate {
            length,
            class,
            root,
            edge: e as u32,
        });
    }
    dist
}

/// The simple cycle of a candidate (recomputes the root's tree).
fn candidate_cycle(t: &Topo, root: u32, edge: u32) -> Vec<u32> {
    let (_, parent) = dijkstra(t, &[root]);
    let [u, v] = t.edges[edge as usize];
    let path = |mut x: u32| {
        let mut p = vec![x];
        while parent[x as usize] != NONE {
            x = other(t, parent[x as usize], x);
            p.push(x);
        }
        p
    };
    let (mut pu, mut pv) = (path(u), path(v));
    // Strip the common suffix (towards the root), keeping the last common vertex once.
    let mut lca = root;
    while let (Some(&a), Some(&b)) = (pu.last(), pv.last()) {
        if a == b {
            lca = a;
            pu.pop();
            pv.pop();
        } else {
            break;
        }
    }
    let mut cycle = vec![lca];
    cycle.extend(pu.iter().rev());
    cycle.extend(pv.iter());
    cycle
}

/// Greedy choice by increasing length among the candidates, keeping independent classes.
fn greedy(mut cands: Vec<Candidate>, rank: usize) -> Vec<Candidate> {
    cands.sort_by(|a, b| {
        a.length
            .total_cmp(&b.length)
            .then(a.root.cmp(&b.root))
            .then(a.edge.cmp(&b.edge))
    });
    // Z₂ elimination: basis vectors keyed by their highest bit.
    let mut basis: Vec<u128> = vec![0; 128];
    let mut out = Vec::new();
    for c in cands {
        let mut x = c.class;
        while x != 0 {
            let h = 127 - x.leading_zeros() as usize;
            if basis[h] == 0 {
                basis[h] = x;
                break;
            }
            x ^= basis[h];
        }
        if x != 0 {
            out.push(c);
            if out.len() == rank {
                break;
            }
        }
    }
    out
}

pub(super) fn basis_of(
    mesh: &Mesh,
    t: &Topo,
    roots: usize,
    refine_roots: usize,
) -> Result<Vec<HomologyLoop>, TopologyError> {
    let (ann, rank) = annotations(mesh, t)?;
    if rank == 0 {
        return Ok(Vec::new());
    }
    // Farthest-point roots, starting from the lowest-index referenced vertex.
    let Some(first) = (0..t.n).find(|&v| t.adj.count(v) > 0) else {
        return Ok(Vec::new());
    };
    let mut cands = Vec::new();
    let mut mind = vec![f64::INFINITY; t.n];
    let mut used_roots = Vec::new();
    let mut r = first as u32;
    for _ in 0..roots.max(1) {
        used_roots.push(r);
        let d = root_candidates(t, &ann, r, &mut cands);
        for v in 0..t.n {
            mind[v] = mind[v].min(d[v]);
        }
        let next = (0..t.n)
            .filter(|&v| t.adj.count(v) > 0)
            .max_by(|&a, &b| mind[a].total_cmp(&mind[b]).then(b.cmp(&a)));
        match next {
            Some(v) if mind[v] > 0.0 => r = v as u32,
            _ => break,
        }
    }
    let first_basis = greedy(cands, rank);
    let mut cands = Vec::new();
    let mut extra: Vec<u32> = Vec::new();
    for c in &first_basis {
        let cyc = candidate_cycle(t, c.root, c.edge);
        for j in 0..refine_roots {
            let v = cyc[j * cyc.len() / refine_roots.max(1)];
            if !used_roots.contains(&v) && !extra.contains(&v) {
                extra.push(v);
            }
        }
    }
    cands.extend(first_basis);
    for &v in &extra {
        root_candidates(t, &ann, v, &mut cands);
    }
    Ok(greedy(cands, rank)
        .into_iter()
        .map(|c| HomologyLoop {
            vertices: candidate_cycle(t, c.root, c.edge),
            length: c.length,
        })
        .collect())
}

/// A short basis of the first Z₂ homology of the surface with its boundary loops capped: `2g`
/// loops, by increasing length (module docs). `roots` farthest-point roots, then `refine_roots`
/// more along each loop found.
///
/// # Errors
/// [`TopologyError`] for an invalid mesh or a genus above 64.
pub fn short_homology_basis(
    mesh: &Mesh,
    roots: usize,
    refine_roots: usize,
) -> Result<Vec<HomologyLoop>, TopologyError> {
    let t = Topo::build(mesh)?;
    basis_of(mesh, &t, roots, refine_roots)
}
