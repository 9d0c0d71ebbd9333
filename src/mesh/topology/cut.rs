//! Cutting a handle along a loop and measuring its neck; [`cut_handles`]. See the parent
//! module for the method.

use super::homology::basis_of;
use super::*;

/// The faces of `mesh` on the "minus" side of the simple cycle `cycle`, as a face → bool map over
/// the faces incident to the cycle; `None` when the cycle touches the boundary, is not a cycle of
/// mesh edges, or is one-sided.
fn sides(mesh: &Mesh, t: &Topo, cycle: &[u32], boundary: &[bool]) -> Option<HashMap<u32, bool>> {
    let k = cycle.len();
    if k < 3 || cycle.iter().any(|&v| boundary[v as usize]) {
        return None;
    }
    let edge_between = |a: u32, b: u32| t.nbrs(a).iter().find(|&&(w, _)| w == b).map(|x| x.1);
    let mut cut_edges = Vec::with_capacity(k);
    for i in 0..k {
        cut_edges.push(edge_between(cycle[i], cycle[(i + 1) % k])?);
    }
    let is_cut: std::collections::HashSet<u32> = cut_edges.iter().copied().collect();
    // Faces around each cycle vertex, grouped by connectivity through non-cut edges.
    let mut incident: HashMap<u32, Vec<u32>> = HashMap::new();
    let on_cycle: std::collections::HashSet<u32> = cycle.iter().copied().collect();
    for (fi, f) in mesh.faces.iter().enumerate() {
        for &v in f {
            if on_cycle.contains(&v) {
                incident.entry(v).or_default().push(fi as u32);
            }
        }
    }
    let mut side: HashMap<u32, bool> = HashMap::new();
    // The "minus" side starts with face 0 of the first cut edge.
    let mut seed = t.edge_faces[cut_edges[0] as usize][0];
    for i in 0..=k {
        let v = cycle[i % k];
        let fan = &incident[&v];
        // Flood the group of `seed` within the fan of v (faces adjacent through a non-cut edge
        // that contains v).
        let mut group = vec![seed];
        let mut stack = vec![seed];
        while let Some(f) = stack.pop() {
            for &e in &t.face_edges[f as usize] {
                let [a, b] = t.edges[e as usize];
                if (a != v && b != v) || is_cut.contains(&e) {
                    continue;
                }
                for &g in &t.edge_faces[e as usize] {
                    if g != NONE && g != f && !group.contains(&g) {
                        group.push(g);
                        stack.push(g);
                    }
                }
            }
        }
        if group.len() == fan.len() {
            return None; // the cut does not separate the fan (should not happen on a manifold)
        }
        if i == k {
            // Closing check: the group of v0 reached again must be the minus group of v0.
            if group.iter().any(|f| side.get(f) == Some(&false)) {
                return None; // one-sided
            }
            break;
        }
        for &f in fan {
            let minus = group.contains(&f);
            if let Some(&s) = side.get(&f) {
                if s != minus {
                    return None;
                }
            }
            side.insert(f, minus);
        }
        // Seed for the next vertex: the minus face of the next cut edge.
        let ne = cut_edges[i] as usize;
        let [f0, f1] = t.edge_faces[ne];
        seed = if group.contains(&f0) { f0 } else { f1 };
        if seed == NONE || !group.contains(&seed) {
            return None;
        }
    }
    Some(side)
}

/// Splits `mesh` along `cycle`: minus-side faces get new copies of the cycle vertices (appended).
fn split(mesh: &Mesh, cycle: &[u32], side: &HashMap<u32, bool>) -> Mesh {
    let mut out = mesh.clone();
    let mut copy: HashMap<u32, u32> = HashMap::new();
    for &v in cycle {
        copy.insert(v, out.vertices.len() as u32);
        out.vertices.push(mesh.vertices[v as usize]);
    }
    let mut faces: Vec<(u32, bool)> = side.iter().map(|(&f, &m)| (f, m)).collect();
    faces.sort_unstable();
    for (f, minus) in faces {
        if minus {
            for v in out.faces[f as usize].iter_mut() {
                if let Some(&c) = copy.get(v) {
                    *v = c;
                }
            }
        }
    }
    out
}

/// Per-vertex area (one third of each incident face).
fn vertex_areas(mesh: &Mesh) -> Vec<f64> {
    let mut a = vec![0.0; mesh.vertices.len()];
    for f in &mesh.faces {
        let [p, q, r] = f.map(|i| mesh.vertices[i as usize]);
        let area = 0.5 * norm(cross(sub(q, p), sub(r, p)));
        for &v in f {
            a[v as usize] += area / 3.0;
        }
    }
    a
}

/// The neck of a split loop, relative to its length `L`: the extents `s₊ / L` and `s₋ / L` of its
/// two sides, and the shortest distance between the two sides over the rest of the surface
/// (`across / L`), on the split mesh (`plus` = original cycle vertices, `minus` = their copies).
struct Neck {
    /// `s₊ / L`, `s₋ / L`.
    sides: [f64; 2],
    /// `across / L`.
    across: f64,
    /// Per side, the length of its stub relative to `L` (infinite where the side never opens).
    stub_sides: [f64; 2],
    /// Per side, the vertices of its stub (nearer to the loop than where the side opens).
    stubs: [Vec<u32>; 2],
}

impl Neck {
    /// `(s₊ + s₋) / L`, the neck aspect.
    fn aspect(&self) -> f64 {
        self.sides[0] + self.sides[1]
    }

    /// `min(s₊, s₋) / L`: how soon the surface flares on the side that flares first.
    fn side_aspect(&self) -> f64 {
        self.sides[0].min(self.sides[1])
    }
}

/// Level curves around a cut loop this many times its length end a stub (`stub` in [`neck`]).
const STUB_FLARE: f64 = 1.5;

/// Measures the neck of a split loop; its stubs only when `stubs` is set (a cut that removes
/// them), else none (`stub_sides` infinite).
fn neck(
    split: &Mesh,
    plus: &[u32],
    minus: &[u32],
    length: f64,
    growth: f64,
    stubs: bool,
) -> Option<Neck> {
    let t = Topo::build(split).ok()?;
    let (dp, _) = dijkstra(&t, plus);
    let (dm, _) = dijkstra(&t, minus);
    let area = vertex_areas(split);
    let h = length / plus.len() as f64;
    // One side's vertices, nearest to the loop first.
    let side = |mine: &[f64], theirs: &[f64]| -> Vec<usize> {
        let mut vs: Vec<usize> = (0..t.n)
            .filter(|&v| mine[v].is_finite() && mine[v] <= theirs[v])
            .collect();
        vs.sort_by(|&a, &b| mine[a].total_cmp(&mine[b]).then(a.cmp(&b)));
        vs
    };
    // The extent of one side (module docs).
    let extent = |mine: &[f64], vs: &[usize]| -> f64 {
        let mut acc = 0.0;
        let mut last = 0.0;
        for &v in vs {
            acc += area[v];
            last = mine[v];
            if acc > growth * length * mine[v].max(h) {
                return mine[v];
            }
        }
        last
    };
    // The stub of one side: the vertices before the first distance `s` at which the level
    // curves around the loop have grown to `STUB_FLARE · L` (their length estimated as the area
    // of a band of width `w` centred on `s`, divided by `w`); with the distance `s`. A tube keeps
    // level curves of about `L`; where it opens into a surface they lengthen at once. Empty
    // (and infinite) where they never do.
    let stub = |mine: &[f64], vs: &[usize]| -> (f64, Vec<u32>) {
        let w = 3.0 * h;
        let (mut lo, mut band) = (0, 0.0);
        for (k, &v) in vs.iter().enumerate() {
            band += area[v];
            while mine[v] - mine[vs[lo]] > w {
                band -= area[vs[lo]];
                lo += 1;
            }
            if mine[v] >= w && band / w > STUB_FLARE * length {
                let s = mine[v] - 0.5 * w;
                let verts = vs[..k]
                    .iter()
                    .take_while(|&&u| mine[u] < s)
                    .map(|&u| u as u32)
                    .collect();
                return (s, verts);
            }
        }
        (f64::INFINITY, Vec::new())
    };
    let (vp, vm) = (side(&dp, &dm), side(&dm, &dp));
    let sides = [extent(&dp, &vp) / length, extent(&dm, &vm) / length];
    let (stub_p, stub_m) = if stubs {
        (stub(&dp, &vp), stub(&dm, &vm))
    } else {
        let none = || (f64::INFINITY, Vec::new());
        (none(), none())
    };
    let across = minus
        .iter()
        .map(|&v| dp[v as usize])
        .fold(f64::INFINITY, f64::min);
    Some(Neck {
        sides,
        across: across / length,
        stub_sides: [stub_p.0 / length, stub_m.0 / length],
        stubs: [stub_p.1, stub_m.1],
    })
}

/// Drops faces touching any of `verts` and compacts unused vertices; also returns, per vertex of
/// `mesh`, its index in the result (`NONE` when dropped).
fn remove_band(mesh: &Mesh, verts: &[u32]) -> (Mesh, Vec<u32>) {
    let bad: std::collections::HashSet<u32> = verts.iter().copied().collect();
    let faces: Vec<[u32; 3]> = mesh
        .faces
        .iter()
        .filter(|f| !f.iter().any(|v| bad.contains(v)))
        .copied()
        .collect();
    compact(&mesh.vertices, faces)
}

/// Drops the vertices no face references (the kept ones in their order) and re-indexes the
/// faces; also returns, per input vertex, its index in the result (`NONE` when dropped). Shared
/// with [`crate::mesh::weld`].
pub(crate) fn compact(vertices: &[[f64; 3]], faces: Vec<[u32; 3]>) -> (Mesh, Vec<u32>) {
    let mut map = vec![NONE; vertices.len()];
    let mut verts = Vec::new();
    for f in &faces {
        for &v in f {
            if map[v as usize] == NONE {
                map[v as usize] = 0;
            }
        }
    }
    for (i, m) in map.iter_mut().enumerate() {
        if *m != NONE {
            *m = verts.len() as u32;
            verts.push(vertices[i]);
        }
    }
    let faces = faces
        .into_iter()
        .map(|f| f.map(|v| map[v as usize]))
        .collect();
    (Mesh::new(verts, faces), map)
}

/// Finds handles that are short welded necks and cuts them (module docs). The returned mesh has
/// the input's vertices first (same indices) unless a band is removed, in which case unused
/// vertices are dropped (relative order kept). The caller may re-run the preparation (e.g. to
/// keep the largest component if a band removal detached a sliver).
///
/// # Errors
/// [`TopologyError`] for an invalid mesh, invalid options or a genus above 64.
pub fn cut_handles(
    mesh: &Mesh,
    opts: &HandleCutOptions,
) -> Result<(Mesh, HandleCutReport), TopologyError> {
    cut_handles_with_map(mesh, opts).map(|(m, r, _)| (m, r))
}

/// [`cut_handles`], also returning for each vertex of `mesh` its index in the output (`None`
/// when it was removed with a band). The copies a cut makes are new vertices: an input vertex on
/// a cut loop maps to its "plus" side copy (the original index), or to `None` when the band was
/// removed.
///
/// # Errors
/// As [`cut_handles`].
pub fn cut_handles_with_map(
    mesh: &Mesh,
    opts: &HandleCutOptions,
) -> Result<(Mesh, HandleCutReport, Vec<Option<u32>>), TopologyError> {
    opts.validate()?;
    let t0 = Topo::build(mesh)?;
    let before = stats_of(mesh, &t0);
    let area0 = mesh.area();
    let mut cur = mesh.clone();
    // Input vertex → index in `cur` (a split only appends vertices; a band removal compacts).
    let mut map: Vec<u32> = (0..mesh.vertices.len() as u32).collect();
    let mut t = t0;
    let mut loops = Vec::new();
    let mut cuts = 0;
    for round in 0..opts.max_cuts {
        let basis = basis_of(&cur, &t, opts.roots, opts.refine_roots)?;
        let area = cur.area();
        let boundary = t.boundary_vertex_flags();
        let mut next = None;
        for lp in &basis {
            let rel = lp.length / area.sqrt();
            let mut rep = LoopReport {
                round,
                length: lp.length,
                length_rel: rel,
                neck_aspect: None,
                side_aspect: None,
                handle_rel: None,
                vertices: lp.vertices.len(),
                cut: false,
            };
            if rel > opts.max_loop_rel {
                loops.push(rep);
                break; // the basis is sorted: every later loop is longer
            }
            if let Some(side) = sides(&cur, &t, &lp.vertices, &boundary) {
                let sp = split(&cur, &lp.vertices, &side);
                let minus: Vec<u32> =
                    (cur.vertices.len() as u32..sp.vertices.len() as u32).collect();
                let stubs = opts.stub_aspect > 0.0;
                if let Some(nk) = neck(&sp, &lp.vertices, &minus, lp.length, opts.growth, stubs) {
                    rep.neck_aspect = Some(nk.aspect());
                    rep.side_aspect = Some(nk.side_aspect());
                    rep.handle_rel = Some(nk.across);
                    if nk.aspect() <= opts.max_neck_aspect
                        || (opts.max_side_aspect > 0.0 && nk.side_aspect() <= opts.max_side_aspect)
                        || rel <= opts.free_loop_rel
                    {
                        rep.cut = true;
                        let mut band = lp.vertices.clone();
                        band.extend(&minus);
                        for (s, stub) in nk.stub_sides.iter().zip(&nk.stubs) {
                            if *s <= opts.stub_aspect {
                                band.extend(stub);
                            }
                        }
                        next = Some((sp, band));
                    }
                }
            }
            loops.push(rep);
            if next.is_some() {
                break;
            }
        }
        let Some((sp, band)) = next else { break };
        cur = if opts.remove_band {
            let (m, step) = remove_band(&sp, &band);
            for v in &mut map {
                if *v != NONE {
                    *v = step[*v as usize];
                }
            }
            m
        } else {
            sp
        };
        cuts += 1;
        t = Topo::build(&cur)?;
        if cur.faces.is_empty() {
            break;
        }
    }
    let after = stats_of(&cur, &t);
    let area_kept = if area0 > 0.0 { cur.area() / area0 } else { 1.0 };
    let map = map.into_iter().map(|v| (v != NONE).then_some(v)).collect();
    Ok((
        cur,
        HandleCutReport {
            before,
            after,
            loops,
            cuts,
            area_kept,
        },
        map,
    ))
}
