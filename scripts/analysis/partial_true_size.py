#!/usr/bin/env python3
"""A benchmark's partial shapes at their true size relative to their character, for measuring
what unit-area normalisation costs them (docs/quality.md §31).

The pipeline scales every prepared shape (after smoothing, capping and handle cutting) to unit
area, so a shape missing part of its surface is enlarged. This writes a copy of a manifest
whose meshes are pre-scaled so that, with `shapeseek eval --no-normalize`, every shape ends at
the size the default pipeline gives it, except the partial ones: those are scaled by their
character's null shape's factor, so they keep their final area relative to that null.

    cut -d, -f2 M.csv | tail -n +2 | xargs target/release/examples/probe_prepare P > probe.txt
    python3 scripts/analysis/partial_true_size.py M.csv probe.txt OUT
    shapeseek eval --manifest OUT/manifest.csv --config default --no-normalize --matrices m.json

`probe.txt` is `examples/probe_prepare`'s output for the manifest's meshes in manifest order
(its `scale_factor` is 1 / sqrt of the prepared area in the mesh's units). Meshes must be OBJ
(vertex lines are scaled, every other line is copied). Every class needs a `null` shape.
"""
import csv
import json
import os
import sys


def main():
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    manifest, probe, out = sys.argv[1:]
    base = os.path.dirname(os.path.abspath(manifest))
    with open(manifest, newline="") as f:
        rows = list(csv.DictReader(f))
    with open(probe) as f:
        reports = [json.loads(line.split(": ", 1)[1]) for line in f if line.strip()]
    if len(reports) != len(rows):
        sys.exit(f"{probe}: {len(reports)} reports for {len(rows)} shapes")
    factor = {r["id"]: p["scale_factor"] for r, p in zip(rows, reports)}
    null = {r["class"]: factor[r["id"]] for r in rows if r["transform"] == "null"}
    os.makedirs(os.path.join(out, "meshes"), exist_ok=True)
    written = []
    for r in rows:
        if not r["path"].lower().endswith(".obj"):
            sys.exit(f"{r['id']}: {r['path']} is not OBJ")
        if r["class"] not in null:
            sys.exit(f"class {r['class']} has no null shape")
        s = null[r["class"]] if r["transform"] == "partiality" else factor[r["id"]]
        src = r["path"] if os.path.isabs(r["path"]) else os.path.join(base, r["path"])
        dst = os.path.abspath(os.path.join(out, "meshes", r["id"] + ".obj"))
        with open(src) as fi, open(dst, "w") as fo:
            for line in fi:
                if line.startswith("v "):
                    x = [float(t) * s for t in line.split()[1:4]]
                    fo.write("v %.9g %.9g %.9g\n" % tuple(x))
                else:
                    fo.write(line)
        if r["transform"] == "partiality":
            rel = (null[r["class"]] / factor[r["id"]]) ** 2
            print(f"{r['id']}: prepared area / its null's {rel:.3f}")
        written.append(dict(r, path=dst))
    with open(os.path.join(out, "manifest.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()), lineterminator="\n")
        w.writeheader()
        w.writerows(written)


if __name__ == "__main__":
    main()
