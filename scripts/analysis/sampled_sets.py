#!/usr/bin/env python3
"""Scores a configuration on many small benchmark sets drawn from larger ones, e.g. sets built
like issue 14's hidden set (three humans and two animals, 35 shapes each) from characters that
never informed a choice (docs/quality.md §32):

    python3 scripts/analysis/sampled_sets.py --pick 3 faust/manifest.csv --pick 2 t2/manifest.csv \\
        --samples 40 --seed 1 --cache C --out OUT [--config default] [--bin target/release/shapeseek]

Each `--pick N MANIFEST` draws N of that manifest's classes (characters) for every sample;
draws are seeded and distinct. Every sample's manifest (absolute paths) is written to
`OUT/sample-K.csv` and ranked with `shapeseek eval --manifest … --config … --json …`, so one
sample is one ordinary eval run (its own calibration, all its shapes as candidates); one
`--cache` folder serves the analyses to every sample. Prints per sample the characters and the
mAP per transformation class, then the mean, the lowest and the share of samples with All ≥ 85
and every class ≥ 70 (the hidden set's bar).
"""
import argparse
import csv
import json
import math
import os
import random
import subprocess
import sys

# As matrix_ap.TR; not imported from there, which needs numpy, so this runs on plain python3.
TR = ["null", "isometry", "topology", "isometry+topology", "partiality", "triangulation", "noise", "scale"]
HEAD = ["Null", "Iso", "Topo", "Iso+Topo", "Part", "Triang.", "Noise", "Scale", "All"]


def read(path):
    base = os.path.dirname(os.path.abspath(path))
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        if not os.path.isabs(r["path"]):
            r["path"] = os.path.join(base, r["path"])
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pick", nargs=2, action="append", metavar=("N", "MANIFEST"), required=True)
    p.add_argument("--samples", type=int, default=20)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--config", default="default")
    p.add_argument("--cache", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--bin", default=os.path.join(os.environ.get("CARGO_TARGET_DIR", "target"), "release", "shapeseek"))
    a = p.parse_args()
    pools = []
    for n, path in a.pick:
        rows = read(path)
        classes = sorted({r["class"] for r in rows})
        if int(n) > len(classes):
            sys.exit(f"{path}: {len(classes)} classes, cannot pick {n}")
        pools.append((int(n), rows, classes))
    combos = math.prod(math.comb(len(classes), n) for n, _, classes in pools)
    if a.samples > combos:
        sys.exit(f"only {combos} distinct samples exist")
    rng = random.Random(a.seed)
    seen, draws = set(), []
    while len(draws) < a.samples:
        d = tuple(tuple(sorted(rng.sample(classes, n))) for n, _, classes in pools)
        if d not in seen:
            seen.add(d)
            draws.append(d)
    os.makedirs(a.out, exist_ok=True)
    header = None
    table = []
    print("| sample | characters | " + " | ".join(HEAD) + " |")
    print("|---" * (len(HEAD) + 2) + "|")
    for k, d in enumerate(draws):
        rows = []
        for (n, pool, _), chosen in zip(pools, d):
            rows += [r for r in pool if r["class"] in chosen]
        header = header or list(rows[0].keys())
        man = os.path.join(a.out, f"sample-{k}.csv")
        with open(man, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=header, lineterminator="\n")
            w.writeheader()
            w.writerows(rows)
        js = os.path.join(a.out, f"sample-{k}.json")
        cmd = [a.bin, "eval", "--manifest", man, "--config", a.config, "--cache", a.cache, "--json", js]
        done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:
            sys.exit(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
        with open(js) as f:
            res = json.load(f)["results"]
        hit = [r for r in res if r["config"] == a.config] or (res if len(res) == 1 else [])
        if not hit:
            sys.exit(f"{js}: configurations {[r['config'] for r in res]}; name one with --config")
        m = hit[0]["map"]
        vals = [100 * m[t] for t in TR] + [100 * m["All"]]
        table.append(vals)
        names = ", ".join(c for chosen in d for c in chosen)
        print(f"| {k} | {names} | " + " | ".join(f"{v:.2f}" for v in vals) + " |", flush=True)
    n = len(table)
    mean = [sum(t[i] for t in table) / n for i in range(len(HEAD))]
    low = [min(t[i] for t in table) for i in range(len(HEAD))]
    print("| mean | | " + " | ".join(f"{v:.2f}" for v in mean) + " |")
    print("| lowest | | " + " | ".join(f"{v:.2f}" for v in low) + " |")
    ok = sum(1 for t in table if t[-1] >= 85 and min(t[:-1]) >= 70)
    print(f"\n{ok} of {n} samples meet All >= 85 and every class >= 70")


if __name__ == "__main__":
    main()
