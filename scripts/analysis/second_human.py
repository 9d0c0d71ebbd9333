"""A synthetic second human for a benchmark manifest (docs/quality.md §18): every shape of
class SOURCE (default crane-man) offset along its vertex normals by D * sqrt(area) — thicker
limbs and torso in every pose and transformation alike — as class `thick-man`. OUT/manifest.csv
= the manifest's rows (absolute paths) followed by the new shapes.

    python3 -m venv /tmp/v && /tmp/v/bin/pip install trimesh numpy
    /tmp/v/bin/python scripts/analysis/second_human.py ../shared/bench/dev/manifest.csv /tmp/thick 0.008

A proxy, not a performer: two real people differ in proportions and clothing, not only in
thickness. Writes only under OUT.
"""
import csv
import os
import sys

import numpy as np
import trimesh

src, out, d = sys.argv[1], sys.argv[2], float(sys.argv[3])
source = sys.argv[4] if len(sys.argv) > 4 else "crane-man"
base = os.path.dirname(os.path.abspath(src))
os.makedirs(os.path.join(out, "meshes"), exist_ok=True)
rows = list(csv.DictReader(open(src, newline="")))
extra = []
for r in rows:
    if r["class"] != source:
        continue
    m = trimesh.load(os.path.join(base, r["path"]), process=False, force="mesh")
    v = m.vertices + d * np.sqrt(m.area) * m.vertex_normals
    rid = r["id"].replace(source, "thick-man")
    path = f"meshes/{rid}.obj"
    trimesh.Trimesh(v, m.faces, process=False).export(os.path.join(out, path))
    extra.append(dict(r, id=rid, path=path, **{"class": "thick-man"}))
with open(os.path.join(out, "manifest.csv"), "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=rows[0].keys())
    w.writeheader()
    w.writerows(dict(r, path=os.path.join(base, r["path"])) for r in rows)
    w.writerows(extra)
print(f"{len(rows)} + {len(extra)} shapes; manifest {out}/manifest.csv")
