//! Connectivity and distances for [`weld`](super::weld): the edge graph with its half-edges and
//! outward normals, Dijkstra scratch space, components and their geodesic diameters.

use super::super::buckets::Buckets;
use super::super::topology::HeapItem;
use super::super::{cross, dot, norm, sub, Mesh};
use std::collections::{BinaryHeap, HashMap};

/// Edge graph, directed half-edges and vertex normals of a manifold mesh.
pub(super) struct Graph {
    pub(super) n: usize,
    /// Vertex → (neighbour, edge length).
    pub(super) adj: Buckets<(u32, f64)>,
    /// Directed half-edge `(a, b)` → the face traversing it.
    pub(super) half: HashMap<(u32, u32), u32>,
    /// Vertex → incident faces.
    pub(super) vf: Buckets<u32>,
    /// On a boundary edge or an inconsistently oriented edge: never inside or on a disc.
    pub(super) avoid: Vec<bool>,
    /// Referenced by a face.
    pub(super) used: Vec<bool>,
    /// Unit outward normals (zero where undefined).
    pub(super) normal: Vec<[f64; 3]>,
    /// `1` when the faces are counter-clockwise seen from outside (enclosed volume `≥ 0`), else
    /// `-1`.
    pub(super) orient: f64,
    pub(super) mean_edge: f64,
}

impl Graph {
    pub(super) fn build(mesh: &Mesh) -> Self {
        let n = mesh.vertices.len();
        let mut half: HashMap<(u32, u32), u32> = HashMap::with_capacity(mesh.faces.len() * 3);
        let mut avoid = vec![false; n];
        let mut used = vec![false; n];
        let mut normal = vec![[0.0f64; 3]; n];
        let mut volume = 0.0;
        for (fi, f) in mesh.faces.iter().enumerate() {
            let [a, b, c] = f.map(|i| mesh.vertices[i as usize]);
            let fnrm = cross(sub(b, a), sub(c, a));
            volume += dot(a, cross(b, c));
            for k in 0..3 {
                let v = f[k] as usize;
                used[v] = true;
                for i in 0..3 {
                    normal[v][i] += fnrm[i];
                }
                if half.insert((f[k], f[(k + 1) % 3]), fi as u32).is_some() {
                    avoid[f[k] as usize] = true;
                    avoid[f[(k + 1) % 3] as usize] = true;
                }
            }
        }
        let sign = if volume < 0.0 { -1.0 } else { 1.0 };
        for nv in &mut normal {
            let l = norm(*nv);
            if l > 0.0 {
                *nv = nv.map(|x| sign * x / l);
            }
        }
        // Undirected edges: each once, from its half-edges.
        let mut edges: Vec<(u32, u32)> = Vec::with_capacity(half.len() / 2 + 4);
        for &(a, b) in half.keys() {
            let twin = half.contains_key(&(b, a));
            if !twin {
                // Boundary edge (or its twin traverses it the same way: flagged above).
                avoid[a as usize] = true;
                avoid[b as usize] = true;
            }
            if a < b || !twin {
                edges.push((a.min(b), a.max(b)));
            }
        }
        edges.sort_unstable();
        edges.dedup();
        let lengths: Vec<f64> = edges
            .iter()
            .map(|&(a, b)| norm(sub(mesh.vertices[a as usize], mesh.vertices[b as usize])))
            .collect();
        let total: f64 = lengths.iter().sum();
        let adj = Buckets::new(
            n,
            edges
                .iter()
                .zip(&lengths)
                .flat_map(|(&(a, b), &l)| [(a, (b, l)), (b, (a, l))]),
        );
        let vf = Buckets::new(
            n,
            mesh.faces
                .iter()
                .enumerate()
                .flat_map(|(fi, f)| f.map(|v| (v, fi as u32))),
        );
        Self {
            n,
            adj,
            half,
            vf,
            avoid,
            used,
            normal,
            orient: sign,
            mean_edge: total / edges.len().max(1) as f64,
        }
    }

    pub(super) fn nbrs(&self, v: u32) -> &[(u32, f64)] {
        self.adj.get(v as usize)
    }

    pub(super) fn faces_of(&self, v: u32) -> &[u32] {
        self.vf.get(v as usize)
    }
}

/// Reusable Dijkstra buffers: `dist` is `∞` except at `touched`.
pub(super) struct Scratch {
    pub(super) dist: Vec<f64>,
    pub(super) touched: Vec<u32>,
    pub(super) heap: BinaryHeap<HeapItem>,
}

impl Scratch {
    pub(super) fn new(n: usize) -> Self {
        Self {
            dist: vec![f64::INFINITY; n],
            touched: Vec::new(),
            heap: BinaryHeap::new(),
        }
    }

    /// Dijkstra from `sources`, stopped once the nearest unsettled vertex is beyond `limit`:
    /// afterwards `dist[v]` is exact where `≤ limit`, and any `v` farther has `dist[v] > limit`.
    pub(super) fn run(&mut self, g: &Graph, sources: &[u32], limit: f64) {
        for &v in &self.touched {
            self.dist[v as usize] = f64::INFINITY;
        }
        self.touched.clear();
        self.heap.clear();
        for &s in sources {
            if self.dist[s as usize] > 0.0 {
                self.dist[s as usize] = 0.0;
                self.touched.push(s);
                self.heap.push(HeapItem(0.0, s));
            }
        }
        while let Some(HeapItem(d, v)) = self.heap.pop() {
            if d > limit {
                break;
            }
            if d > self.dist[v as usize] {
                continue;
            }
            for &(w, l) in g.nbrs(v) {
                let nd = d + l;
                if nd < self.dist[w as usize] {
                    if self.dist[w as usize].is_infinite() {
                        self.touched.push(w);
                    }
                    self.dist[w as usize] = nd;
                    self.heap.push(HeapItem(nd, w));
                }
            }
        }
    }

    /// The touched vertex farthest from the sources (smallest index on ties).
    pub(super) fn farthest(&self) -> (u32, f64) {
        let d = |v: u32| self.dist[v as usize];
        let far = self.touched.iter().copied();
        let v = far.max_by(|&a, &b| d(a).total_cmp(&d(b)).then(b.cmp(&a)));
        v.map_or((0, 0.0), |v| (v, d(v)))
    }
}

/// Component of every used vertex (`u32::MAX` for unused ones) and the double-sweep geodesic
/// diameter of each component.
pub(super) fn components_and_diameters(g: &Graph, s: &mut Scratch) -> (Vec<u32>, Vec<f64>) {
    let mut comp = vec![u32::MAX; g.n];
    let mut diam = Vec::new();
    for v0 in 0..g.n as u32 {
        if !g.used[v0 as usize] || comp[v0 as usize] != u32::MAX {
            continue;
        }
        s.run(g, &[v0], f64::INFINITY);
        let c = diam.len() as u32;
        for &v in &s.touched {
            comp[v as usize] = c;
        }
        let (a, _) = s.farthest();
        s.run(g, &[a], f64::INFINITY);
        diam.push(s.farthest().1);
    }
    (comp, diam)
}
