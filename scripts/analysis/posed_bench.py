"""A benchmark built like bench/dev from other posed characters (docs/quality.md §22): a third
proxy of the hidden set, made of characters none of dev's sources contain.

    python3 -m venv /tmp/v && /tmp/v/bin/pip install trimesh numpy scipy rtree pymeshlab
    cargo build --release --examples            # examples/weld_bench makes the welds
    /tmp/v/bin/python scripts/analysis/posed_bench.py SRC OUT dog centaur david michael victoria \
        [--with ../shared/bench/dev/manifest.csv ...]

SRC holds the posed meshes of each character as `<name><pose number>.off`, the poses of one
character sharing one connectivity (the TOSCA layout); the lowest pose number is the reference.
OUT/manifest.csv lists, per character, the shapes of bench/README.md's table, made as that
README describes:

* the reference pose cleaned (degenerate and duplicate faces dropped, largest component kept),
  every pose translated to its area-weighted centroid and scaled to area 1, the reference
  decimated (topology-preserving quadric edge collapse, pymeshlab) to about 4,000 vertices:
  `null`; the other poses mapped onto that connectivity by barycentric coordinates of the
  closest points on the reference: `iso1..8` (fewer where a character has fewer poses);
* `topo1..4`, `isotopo1..4`: welds of the null shape and of four other poses (reused from the
  isometry poses where the character has fewer than 12 poses besides the reference) with 1..4
  bridges and discs of
  1.5..3 mean edge lengths, by `examples/weld_bench` (the project's implementation of the
  README's weld; seed = strength);
* `holes1..3` (2/3/4 geodesic balls removing 3/6/10 % of the area), `cut1..3` (a random plane
  removing 5/12/20 %), largest component kept;
* `tri1..4` from the full-resolution reference: isotropic remeshing aimed at 1.25x and 1.5x the
  null shape's vertices (the edge length of an equilateral mesh of that size; on five TOSCA
  characters it overshoots, 5 700-6 800 and 6 700-7 800 vertices for about 5 000 and 6 000;
  the counts are printed), quadric decimation to 0.75x and 0.5x;
* `noise1..4`: Gaussian displacement along the vertex normals, sigma 0.10/0.20/0.35/0.50 mean
  edge lengths; `scale1..4`: factors 1.25/1.5/2/0.5 about the centroid.

`--with MANIFEST` (repeatable) puts that manifest's rows first (paths made absolute), for one
evaluation of dev and the new characters together. All OBJ (dev in four formats scores as the
OBJ originals, §18). Seeds are fixed (per character, from its
name); the same SRC gives the same shapes. Writes only under OUT; nothing from SRC is committed.
"""
import csv
import os
import re
import subprocess
import sys
import tempfile
import zlib

import numpy as np
import pymeshlab
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

TARGET_VERTICES = 4000
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
WELD = os.path.join(os.environ.get("CARGO_TARGET_DIR", os.path.join(ROOT, "target")),
                    "release", "examples", "weld_bench")


def poses(src, name):
    pat = re.compile(rf"^{re.escape(name)}(\d+)\.off$")
    found = sorted((int(m.group(1)), f) for f in os.listdir(src) if (m := pat.match(f)))
    if len(found) < 2:
        sys.exit(f"{src}: fewer than two poses of {name}")
    return [(n, trimesh.load(os.path.join(src, f), process=False, force="mesh")) for n, f in found]


def largest_component_faces(faces, n_vertices):
    """Indices of the faces of the largest vertex-connected component."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    _, label = connected_components(g, directed=False)
    fl = label[faces[:, 0]]
    return np.flatnonzero(fl == np.bincount(fl).argmax())


def compact(v, f):
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def normalise(v, f):
    """Area-weighted centroid to the origin, total area 1 (bench/README.md step 2)."""
    t = v[f]
    a = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    c = (a[:, None] * t.mean(axis=1)).sum(0) / a.sum()
    return (v - c) / np.sqrt(a.sum())


def clean_faces(v, f):
    """Degenerate and duplicate faces dropped, largest component kept (step 1)."""
    t = v[f]
    a = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    ok = (a > 1e-12 * a.max()) & (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    return f[largest_component_faces(f, len(v))]


def meshlab(v, f, op, **kw):
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(v, f))
    getattr(ms, op)(**kw)
    m = ms.current_mesh()
    return m.vertex_matrix(), m.face_matrix()


def decimate(v, f, vertices):
    return meshlab(v, f, "meshing_decimation_quadric_edge_collapse",
                   targetfacenum=int(2 * vertices), preservetopology=True, preserveboundary=True,
                   optimalplacement=True, planarquadric=True, qualitythr=0.3)


def remesh(v, f, vertices):
    # An equilateral triangle mesh of area A with V vertices (F ~ 2V) has edges sqrt(2A/(sqrt3 V)).
    area = trimesh.Trimesh(v, f, process=False).area
    length = np.sqrt(2 * area / (np.sqrt(3) * vertices))
    return meshlab(v, f, "meshing_isotropic_explicit_remeshing", iterations=6,
                   targetlen=pymeshlab.PureValue(length))


def mean_edge(v, f):
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    return np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean()


def keep_faces(v, f, keep):
    f = f[keep]
    f = f[largest_component_faces(f, len(v))]
    return compact(v, f)


def holes(v, f, count, fraction, rng):
    """`count` geodesic balls (Dijkstra on the edge graph) of fraction/count of the area each."""
    m = trimesh.Trimesh(v, f, process=False)
    e = m.edges_unique
    w = m.edges_unique_length
    g = coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(v), len(v))).tocsr()
    fa = m.area_faces
    removed = np.zeros(len(f), bool)
    for c in rng.choice(len(v), size=count, replace=False):
        d = dijkstra(g, directed=False, indices=c)
        fd = d[f].max(axis=1)
        order = np.argsort(fd)
        k = np.searchsorted(np.cumsum(fa[order]), fraction / count * fa.sum()) + 1
        removed[order[:k]] = True
    return keep_faces(v, f, ~removed)


def cut(v, f, fraction, rng):
    """Everything beyond a random plane removed: `fraction` of the area."""
    m = trimesh.Trimesh(v, f, process=False)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    p = m.triangles_center @ d
    order = np.argsort(-p)
    k = np.searchsorted(np.cumsum(m.area_faces[order]), fraction * m.area) + 1
    keep = np.ones(len(f), bool)
    keep[order[:k]] = False
    return keep_faces(v, f, keep)


def build(src, out, name, rows):
    ps = poses(src, name)
    ref_n, ref = ps[0]
    f0 = clean_faces(np.asarray(ref.vertices, float), np.asarray(ref.faces))
    full = []
    for n, m in ps:
        if len(m.vertices) != len(ref.vertices):
            sys.exit(f"{name}{n}: {len(m.vertices)} vertices, the reference has {len(ref.vertices)}")
        v, f = compact(np.asarray(m.vertices, float), f0)
        full.append((n, normalise(v, f), f))
    _, vr, fr = full[0]
    vd, fd = decimate(vr, fr, TARGET_VERTICES)
    # Barycentric coordinates of the decimated vertices on the reference (README step 3).
    ref_mesh = trimesh.Trimesh(vr, fr, process=False)
    closest, _, tri = trimesh.proximity.closest_point(ref_mesh, vd)
    bary = trimesh.triangles.points_to_barycentric(ref_mesh.triangles[tri], closest)
    mapped = []
    for n, v, f in full:
        w = (bary[:, :, None] * v[f[tri]]).sum(axis=1)
        mapped.append((n, normalise(w, fd)))
    null = mapped[0][1]
    ebar = mean_edge(null, fd)
    others = mapped[1:]
    shapes = [("null", "null", 0, ref_n, null, fd)]
    for i, (n, w) in enumerate(others[:8]):
        shapes.append((f"iso{i + 1}", "isometry", i + 1, n, w, fd))
    # The four isometry+topology sources: poses 9..12 where they exist, else reused.
    extra = others[8:12] if len(others) >= 12 else [others[(2 * i) % len(others)] for i in range(4)]
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    for s, (k, frac) in enumerate([(2, .03), (3, .06), (4, .10)], 1):
        v, f = holes(null, fd, k, frac, rng)
        shapes.append((f"holes{s}", "partiality", s, ref_n, v, f))
    for s, frac in enumerate([.05, .12, .20], 1):
        v, f = cut(null, fd, frac, rng)
        shapes.append((f"cut{s}", "partiality", s, ref_n, v, f))
    nv = len(null)
    for s, (op, x) in enumerate([(remesh, 1.25), (decimate, .75), (remesh, 1.5), (decimate, .5)], 1):
        v, f = op(vr, fr, int(round(x * nv)))
        shapes.append((f"tri{s}", "triangulation", s, ref_n, normalise(v, f), f))
        print(f"{name}-tri{s}: {len(v)} vertices", file=sys.stderr)
    nrm = trimesh.Trimesh(null, fd, process=False).vertex_normals
    for s, sigma in enumerate([.10, .20, .35, .50], 1):
        v = null + (sigma * ebar * rng.normal(size=len(null)))[:, None] * nrm
        shapes.append((f"noise{s}", "noise", s, ref_n, v, fd))
    for s, k in enumerate([1.25, 1.5, 2.0, .5], 1):
        shapes.append((f"scale{s}", "scale", s, ref_n, k * null, fd))
    os.makedirs(os.path.join(out, "meshes"), exist_ok=True)
    for sid, tr, st, n, v, f in shapes:
        path = f"meshes/{name}-{sid}.obj"
        trimesh.Trimesh(v, f, process=False).export(os.path.join(out, path))
        rows.append(dict(id=f"{name}-{sid}", path=path, **{"class": name}, transform=tr,
                         strength=st, source_pose=f"{name}{n}"))
    # Welds, by the project's weld (examples/weld_bench) on a manifest of the sources.
    with tempfile.TemporaryDirectory() as tmp:
        srcs = [("null", ref_n, null)] + [(f"pose{n}", n, w) for n, w in extra]
        with open(os.path.join(tmp, "m.csv"), "w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(["id", "path", "class", "transform", "strength", "source_pose"])
            for sid, n, v in srcs:
                p = os.path.join(tmp, f"{sid}.obj")
                trimesh.Trimesh(v, fd, process=False).export(p)
                w.writerow([f"{name}-{sid}", p, name, "null", 0, f"{name}{n}"])
        for s in range(1, 5):
            for tr, (sid, n, _) in (("topology", srcs[0]), ("isometry+topology", srcs[s])):
                run = os.path.join(tmp, f"{sid}-{s}")
                done = subprocess.run([WELD, os.path.join(tmp, "m.csv"), run, "--class", name,
                                       "--sources", sid, "--bridges", str(s),
                                       "--disc-edges", str(1 + 0.5 * s), "--seed", str(s)],
                                      capture_output=True, text=True)
                if done.returncode != 0:
                    sys.exit(f"weld_bench failed on {name}-{sid}, {s} bridges:\n{done.stderr}")
                with open(os.path.join(run, "report.csv"), newline="") as fh:
                    made = next(csv.DictReader(fh))["bridges_made"]
                new = f"{'topo' if tr == 'topology' else 'isotopo'}{s}"
                path = f"meshes/{name}-{new}.obj"
                os.replace(os.path.join(run, "meshes", f"{name}-weld{s}-{sid}.obj"),
                           os.path.join(out, path))
                rows.append(dict(id=f"{name}-{new}", path=path, **{"class": name},
                                 transform=tr, strength=s, source_pose=f"{name}{n}"))
                print(f"{name}-{new}: {made} of {s} bridges", file=sys.stderr)
    print(f"{name}: {len(ps)} poses, null {nv} vertices, ebar {ebar:.4f}", file=sys.stderr)


def main():
    args, withs = [], []
    it = iter(sys.argv[1:])
    for a in it:
        if a == "--with":
            withs.append(next(it, None) or sys.exit("--with needs a manifest"))
        else:
            args.append(a)
    if len(args) < 3:
        sys.exit(__doc__)
    if not os.access(WELD, os.X_OK):
        sys.exit(f"build it first: cargo build --release --example weld_bench ({WELD})")
    src, out, names = args[0], args[1], args[2:]
    rows = []
    for m in withs:
        base = os.path.dirname(os.path.abspath(m))
        with open(m, newline="") as fh:
            for r in csv.DictReader(fh):
                rows.append(dict(r, path=os.path.normpath(os.path.join(base, r["path"]))))
    for name in names:
        build(src, out, name, rows)
    with open(os.path.join(out, "manifest.csv"), "w", newline="") as fh:
        fields = ["id", "path", "class", "transform", "strength", "source_pose"]
        fields += [k for r in rows for k in r if k not in fields]
        w = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(fields)), lineterminator="\n",
                           restval="")
        w.writeheader()
        w.writerows(rows)
    print(f"{len(rows)} shapes -> {out}/manifest.csv", file=sys.stderr)


if __name__ == "__main__":
    main()
