//! Where distances are evaluated: the mesh edge graph, geodesic farthest-point sampling with
//! Voronoi cells (the pair quadrature), and the near field of adjacent cells.

use crate::mesh::buckets::Buckets;
use crate::mesh::{norm, sub, Mesh};
use faer::{Mat, MatRef};
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// The undirected edge graph of a mesh: per vertex, its neighbours and the Euclidean edge
/// lengths to them, in neighbour order.
#[derive(Clone, Debug)]
pub(crate) struct EdgeGraph {
    adj: Buckets<(u32, f64)>,
}

impl EdgeGraph {
    pub(crate) fn new(mesh: &Mesh) -> Self {
        let n = mesh.vertices.len();
        let mut e: Vec<(u32, u32)> = Vec::with_capacity(mesh.faces.len() * 6);
        for f in &mesh.faces {
            for k in 0..3 {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                if a != b && (a as usize) < n && (b as usize) < n {
                    e.push((a, b));
                    e.push((b, a));
                }
            }
        }
        e.sort_unstable();
        e.dedup();
        let adj = Buckets::new(
            n,
            e.iter().map(|&(a, b)| {
                let l = norm(sub(mesh.vertices[a as usize], mesh.vertices[b as usize]));
                (a, (b, l))
            }),
        );
        Self { adj }
    }

    /// The neighbours of vertex `v` and the edge lengths to them.
    #[inline]
    pub(crate) fn nbrs(&self, v: usize) -> &[(u32, f64)] {
        self.adj.get(v)
    }

    /// Dijkstra from `src`, lowering `dist` only where the new distance is strictly smaller
    /// (with `owner` set to `id` there): run with `dist = ∞` for a full single-source run, or
    /// repeatedly for an incremental multi-source (Voronoi) run.
    pub(crate) fn relax_from(
        &self,
        src: usize,
        dist: &mut [f64],
        owner: &mut [u32],
        id: u32,
        heap: &mut BinaryHeap<Reverse<(u64, u32)>>,
    ) {
        heap.clear();
        dist[src] = 0.0;
        owner[src] = id;
        heap.push(Reverse((0f64.to_bits(), src as u32)));
        while let Some(Reverse((db, v))) = heap.pop() {
            let d = f64::from_bits(db);
            let v = v as usize;
            if d > dist[v] {
                continue;
            }
            for &(u, l) in self.nbrs(v) {
                let u = u as usize;
                let nd = d + l;
                if nd < dist[u] {
                    dist[u] = nd;
                    owner[u] = id;
                    heap.push(Reverse((nd.to_bits(), u as u32)));
                }
            }
        }
    }
}

/// Farthest-point samples (edge-graph geodesic FPS) and their Voronoi assignments at the
/// requested prefix sizes.
pub(crate) struct FarthestPoints {
    pub(crate) samples: Vec<u32>,
    /// (prefix size, owner of every vertex among the first `prefix` samples).
    owners: Vec<(usize, Vec<u32>)>,
}

/// Point set with weights: either sample vertices with their Voronoi-cell areas, or all
/// vertices with their areas.
pub(crate) struct Quadrature {
    /// Sample vertices (`None`: all vertices).
    pub(crate) points: Option<Vec<u32>>,
    /// Owner (cell) of every vertex, for cell means.
    pub(crate) owner: Option<Vec<u32>>,
    /// Weight of each point (sums to the area).
    pub(crate) weights: Vec<f64>,
}

impl Quadrature {
    pub(crate) fn all_vertices(mass: &[f64]) -> Self {
        Self {
            points: None,
            owner: None,
            weights: mass.to_vec(),
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.weights.len()
    }

    /// Eigenmap rows at the points themselves.
    pub(crate) fn point_rows(&self, phi: MatRef<'_, f64>) -> Mat<f64> {
        match &self.points {
            None => phi.to_owned(),
            Some(p) => Mat::from_fn(p.len(), phi.ncols(), |r, c| phi[(p[r] as usize, c)]),
        }
    }

    /// Sample vertex indices (all vertices when the quadrature is exact).
    pub(crate) fn point_indices(&self) -> Vec<u32> {
        match &self.points {
            Some(p) => p.clone(),
            None => (0..self.weights.len() as u32).collect(),
        }
    }

    /// Representative eigenmap rows of the pair points: the sample vertices' rows, or (with
    /// `cell_means`) the area-weighted mean row of each Voronoi cell.
    pub(crate) fn rows(&self, phi: MatRef<'_, f64>, mass: &[f64], cell_means: bool) -> Mat<f64> {
        match (&self.owner, cell_means) {
            (Some(owner), true) => {
                let m = self.weights.len();
                let k = phi.ncols();
                let mut out = Mat::<f64>::zeros(m, k);
                for c in 0..k {
                    let col = phi.col(c);
                    let o = out.col_as_slice_mut(c);
                    for (v, &ow) in owner.iter().enumerate() {
                        if (ow as usize) < m {
                            o[ow as usize] += mass[v] * col[v];
                        }
                    }
                    for (x, w) in o.iter_mut().zip(&self.weights) {
                        if *w > 0.0 {
                            *x /= w;
                        }
                    }
                }
                out
            }
            _ => self.point_rows(phi),
        }
    }
}

impl FarthestPoints {
    pub(crate) fn quadrature(&self, count: usize, mass: &[f64]) -> Quadrature {
        let (size, owner) = self
            .owners
            .iter()
            .find(|(s, _)| *s >= count)
            .or_else(|| self.owners.last())
            .expect("at least one prefix");
        let size = (*size).min(self.samples.len());
        let mut weights = vec![0.0; size];
        for (v, &o) in owner.iter().enumerate() {
            if (o as usize) < size {
                weights[o as usize] += mass[v];
            }
        }
        Quadrature {
            points: Some(self.samples[..size].to_vec()),
            owner: Some(owner.clone()),
            weights,
        }
    }
}

/// Geodesic farthest-point sampling on the edge graph. The first sample is the vertex farthest
/// (Euclidean) from the area-weighted centroid; each next one is the vertex farthest (graph
/// distance) from all previous samples (lowest index on exact ties; vertices of components
/// without a sample are at distance ∞, so every component gets one early). Vertex owners are
/// snapshotted when the sample count reaches each of `prefixes`.
pub(crate) fn farthest_points(
    mesh: &Mesh,
    graph: &EdgeGraph,
    prefixes: &[usize],
) -> FarthestPoints {
    let n = mesh.vertices.len();
    let mut wanted: Vec<usize> = prefixes.iter().map(|&p| p.clamp(1, n)).collect();
    wanted.sort_unstable();
    wanted.dedup();
    let total = *wanted.last().unwrap_or(&1);
    // Area-weighted centroid (vertex areas from the faces).
    let mut c = [0.0; 3];
    let mut asum = 0.0;
    for f in &mesh.faces {
        let a = crate::mesh::triangle_area(mesh, f);
        for &v in f {
            let p = mesh.vertices[v as usize];
            for k in 0..3 {
                c[k] += a * p[k];
            }
        }
        asum += 3.0 * a;
    }
    if asum > 0.0 {
        for x in &mut c {
            *x /= asum;
        }
    }
    let mut start = 0usize;
    let mut best = -1.0;
    for (i, p) in mesh.vertices.iter().enumerate() {
        let d = norm(sub(*p, c));
        if d > best {
            best = d;
            start = i;
        }
    }
    let mut dist = vec![f64::INFINITY; n];
    let mut owner = vec![u32::MAX; n];
    let mut heap = BinaryHeap::new();
    let mut samples = Vec::with_capacity(total);
    let mut owners = Vec::with_capacity(wanted.len());
    let mut next = start;
    while samples.len() < total {
        let id = samples.len() as u32;
        samples.push(next as u32);
        graph.relax_from(next, &mut dist, &mut owner, id, &mut heap);
        if wanted.contains(&samples.len()) {
            owners.push((samples.len(), owner.clone()));
        }
        // Farthest vertex from the current samples.
        let mut far = 0usize;
        let mut fd = -1.0;
        for (i, &d) in dist.iter().enumerate() {
            if d > fd {
                fd = d;
                far = i;
            }
        }
        if fd <= 0.0 {
            break;
        }
        next = far;
    }
    if owners.last().map(|(s, _)| *s) != Some(samples.len()) {
        owners.push((samples.len(), owner));
    }
    FarthestPoints { samples, owners }
}

/// Near field of a farthest-point quadrature: pairs of the same or adjacent Voronoi cells are
/// evaluated one-sided exactly, `W_i Σ_{y ∈ cell j} a_y δ(d(s_i, y))` instead of
/// `W_i W_j δ(d(s_i, s_j))`, so that small distances are not quantised to the sample spacing.
pub(crate) struct NearField<'a> {
    /// Per sample: adjacent samples (cells sharing a mesh edge) with a larger index, sorted.
    pub(crate) adj: Vec<Vec<u32>>,
    /// Per sample: every adjacent sample, sorted.
    pub(crate) nbrs: Vec<Vec<u32>>,
    /// Per sample: member vertices of its cell.
    pub(crate) members: Vec<Vec<u32>>,
    /// Sample vertices.
    pub(crate) samples: Vec<u32>,
    /// Eigenvectors at every vertex.
    pub(crate) phi: &'a Mat<f64>,
    /// Vertex areas.
    pub(crate) mass: &'a [f64],
}

impl<'a> NearField<'a> {
    pub(crate) fn new(
        graph: &EdgeGraph,
        owner: &[u32],
        samples: Vec<u32>,
        phi: &'a Mat<f64>,
        mass: &'a [f64],
    ) -> Self {
        let m = samples.len();
        let mut adj = vec![Vec::new(); m];
        let mut members = vec![Vec::new(); m];
        for (v, &o) in owner.iter().enumerate() {
            if (o as usize) >= m {
                continue;
            }
            members[o as usize].push(v as u32);
            for &(u, _) in graph.nbrs(v) {
                let p = owner[u as usize];
                if p > o && (p as usize) < m {
                    adj[o as usize].push(p);
                }
            }
        }
        for a in &mut adj {
            a.sort_unstable();
            a.dedup();
        }
        let mut nbrs = adj.clone();
        for (i, a) in adj.iter().enumerate() {
            for &j in a {
                nbrs[j as usize].push(i as u32);
            }
        }
        for a in &mut nbrs {
            a.sort_unstable();
        }
        Self {
            adj,
            nbrs,
            members,
            samples,
            phi,
            mass,
        }
    }
}
