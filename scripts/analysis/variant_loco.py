#!/usr/bin/env python3
"""Leave-one-class-out choice among *preparation variants* of one configuration (e.g. handle
cutting with different thresholds, docs/quality.md §9), from `shapeseek eval --protocol loco
--json` outputs, one per variant manifest (examples/cut_handles.rs writes them):

    shapeseek eval --manifest M          --config default --protocol loco --json base.json ...
    shapeseek eval --manifest V1/manifest.csv --config default --protocol loco --json v1.json ...
    python3 scripts/analysis/variant_loco.py base=base.json v1=v1.json ...

Eval's own protocol gives, per fold, the configuration's held-in All mAP (queries *and*
candidates restricted to the seven held-in characters, re-ranking stages re-run on them) and its
held-out figures (the held-out character's queries ranked against the whole set). This script
makes the choice of eval's protocol across the variant runs: per fold, the variant with the best
held-in All (ties: the earlier on the command line) is chosen and its held-out figures reported.
Prints, per variant, the full-set mAP per class and per strength (topology, isometry+topology);
then the per-fold choice, the mean and worst fold per class, and each variant held fixed.
CONFIG=name selects another configuration than `default`.
"""
import json
import os
import sys

TR = ["null", "isometry", "topology", "isometry+topology", "partiality", "triangulation", "noise", "scale"]
SHORT = ["Null", "Iso", "Topo", "IsoTopo", "Part", "Tri", "Noise", "Scale"]


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    config = os.environ.get("CONFIG", "default")
    runs = []
    for arg in sys.argv[1:]:
        name, path = arg.split("=", 1)
        d = json.load(open(path))
        res = next(r for r in d["results"] if r["config"] == config)
        lo = d["loco"]
        fixed = next(f for f in lo["fixed"] if f.get("config", config) == config) if lo.get("fixed") else None
        folds = {f["held_out"]: f for f in lo["folds"]}
        runs.append((name, res, folds, fixed))

    def strengths(ps, t):
        return " / ".join("%.1f" % (100 * ps[f"{t}@{s}"]) for s in range(1, 5))

    print("Full set (in-sample), mAP %:\n")
    print("| variant | " + " | ".join(SHORT) + " | All | Topo s1–s4 | IsoTopo s1–s4 |")
    print("|---" * (len(SHORT) + 4) + "|")
    for name, res, _, _ in runs:
        m, ps = res["map"], res["per_strength"]
        print(f"| {name} | " + " | ".join("%.2f" % (100 * m[t]) for t in TR)
              + " | **%.2f** | %s | %s |" % (100 * m["All"], strengths(ps, "topology"),
                                             strengths(ps, "isometry+topology")))

    classes = list(runs[0][2].keys())
    print("\nLeave-one-class-out across the variants (choice by held-in All of eval's protocol):\n")
    print("| held out | chosen | held-in All (chosen; " + ", ".join(r[0] for r in runs) + ") | "
          + " | ".join(SHORT) + " | All | Topo s3 / s4 | IsoTopo s3 / s4 |")
    print("|---" * (len(SHORT) + 6) + "|")
    table = []
    for c in classes:
        hin = [r[2][c]["held_in_map"] for r in runs]
        best = max(range(len(runs)), key=lambda i: (hin[i], -i))
        f = runs[best][2][c]["held_out_figures"]
        g, ps = f["groups"], f["per_strength"]
        vals = [100 * g[t] for t in TR] + [100 * g["All"]]
        st = [100 * ps.get(k, float("nan")) for k in
              ("topology@3", "topology@4", "isometry+topology@3", "isometry+topology@4")]
        table.append(vals + st)
        print(f"| {c} | {runs[best][0]} | " + ", ".join("%.2f" % (100 * h) for h in hin) + " | "
              + " | ".join("%.2f" % v for v in vals)
              + " | %.1f / %.1f | %.1f / %.1f |" % tuple(st))
    n = len(table)
    mean = [sum(r[i] for r in table) / n for i in range(len(table[0]))]
    worst = [min(r[i] for r in table) for i in range(len(table[0]))]
    for label, row in (("**mean**", mean), ("**worst fold**", worst)):
        print(f"| {label} | | | " + " | ".join("%.2f" % v for v in row[:9])
              + " | %.1f / %.1f | %.1f / %.1f |" % tuple(row[9:]))

    print("\nEach variant held fixed, over the folds (held-out figures; mean / worst fold):\n")
    print("| variant | " + " | ".join(SHORT) + " | All |")
    print("|---" * (len(SHORT) + 2) + "|")
    for name, _, folds, _ in runs:
        rows = [[100 * folds[c]["held_out_figures"]["groups"][t] for t in TR + ["All"]] for c in classes]
        cells = []
        for i in range(len(TR) + 1):
            col = [r[i] for r in rows]
            cells.append("%.2f / %.2f" % (sum(col) / len(col), min(col)))
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("\ncrane-man fold per variant (held-out):\n")
    print("| variant | " + " | ".join(SHORT) + " | All | Topo s1–s4 | IsoTopo s1–s4 |")
    print("|---" * (len(SHORT) + 4) + "|")
    for name, _, folds, _ in runs:
        if "crane-man" not in folds:
            continue
        f = folds["crane-man"]["held_out_figures"]
        g, ps = f["groups"], f["per_strength"]
        print(f"| {name} | " + " | ".join("%.2f" % (100 * g[t]) for t in TR)
              + " | %.2f | %s | %s |" % (100 * g["All"], strengths(ps, "topology"),
                                         strengths(ps, "isometry+topology")))


if __name__ == "__main__":
    main()
