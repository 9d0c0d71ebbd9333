#!/usr/bin/env python3
"""Concatenates variant manifests into one, each shape id suffixed with `~NAME`, paths made
absolute, so that one `shapeseek eval` run ranks every variant under one calibration (the input
of `examples/min_of_versions.rs`, docs/quality.md §16):

    python3 scripts/analysis/combine_manifests.py s9=/tmp/v/s9/manifest.csv d=/tmp/v/d/manifest.csv > both.csv

Every variant must list the same shapes in the same order (examples/cut_handles.rs keeps the
order of its input manifest).
"""
import csv
import os
import sys


def main():
    args = sys.argv[1:]
    if not args or any("=" not in a for a in args):
        sys.exit(__doc__)
    out = csv.writer(sys.stdout, lineterminator="\n")
    header = None
    ids = None
    for arg in args:
        name, path = arg.split("=", 1)
        base = os.path.dirname(os.path.abspath(path))
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            sys.exit(f"{path}: no rows")
        if header is None:
            header = list(rows[0].keys())
            out.writerow(header)
        elif list(rows[0].keys()) != header:
            sys.exit(f"{path}: columns {list(rows[0].keys())}, the first manifest has {header}")
        these = [r["id"] for r in rows]
        if ids is None:
            ids = these
        elif these != ids:
            sys.exit(f"{path}: not the same shapes in the same order as the first manifest")
        for r in rows:
            r = dict(r)
            r["id"] = f'{r["id"]}~{name}'
            if not os.path.isabs(r["path"]):
                r["path"] = os.path.normpath(os.path.join(base, r["path"]))
            out.writerow([r[h] for h in header])


if __name__ == "__main__":
    main()
