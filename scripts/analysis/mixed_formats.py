"""Rewrites a benchmark manifest's meshes with an independent writer (trimesh), the format
cycling over GLB, binary PLY, OFF and OBJ by row, as the hidden sets mix them; OUT/manifest.csv
points at the copies (docs/quality.md §18).

    python3 -m venv /tmp/v && /tmp/v/bin/pip install trimesh numpy
    /tmp/v/bin/python scripts/analysis/mixed_formats.py ../shared/bench/dev/manifest.csv /tmp/devmix

Writes only under OUT (never beside the manifest).
"""
import csv
import os
import sys

import trimesh

src, out = sys.argv[1], sys.argv[2]
base = os.path.dirname(os.path.abspath(src))
os.makedirs(os.path.join(out, "meshes"), exist_ok=True)
formats = ["glb", "ply", "off", "obj"]
rows = list(csv.DictReader(open(src, newline="")))
with open(os.path.join(out, "manifest.csv"), "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=rows[0].keys())
    w.writeheader()
    for i, r in enumerate(rows):
        mesh = trimesh.load(os.path.join(base, r["path"]), process=False, force="mesh")
        path = f"meshes/{r['id']}.{formats[i % 4]}"
        mesh.export(os.path.join(out, path), file_type=formats[i % 4])
        w.writerow(dict(r, path=path))
print(f"{len(rows)} meshes written under {out}")
