#!/usr/bin/env python3
"""Handle cutting on a benchmark split: mAP per transformation class and per strength, with and
without cutting, and a leave-one-class-out choice of the cutting thresholds (docs/quality.md,
"Handle cutting").

    # one cut variant per threshold setting (examples/cut_handles.rs), then eval with --matrices:
    shapeseek eval --manifest M --config default --cache C --matrices /tmp/hc/base.json
    shapeseek eval --manifest /tmp/hc/v1/manifest.csv --config default --cache C --matrices /tmp/hc/v1.json
    ...
    python3 scripts/analysis/handle_cut_eval.py M base=/tmp/hc/base.json v1=/tmp/hc/v1.json ...

M is the original manifest (for the `strength` column). Every matrix file must hold the
configuration `default` (or set CONFIG=name in the environment) over the same shape ids in the
same order. AP per query exactly as the bench README says (full ranking of the 279 others, ties by
manifest order). Prints, per variant: mAP per class, topology and isometry+topology per strength,
All; then the leave-one-class-out protocol: for each class c, the variant with the best mean AP
over the queries of the other seven classes is chosen (ties: the earlier variant on the command
line) and scored on the queries of class c; mean and worst fold per transformation class.
Needs numpy.
"""
import csv
import os
import sys

import numpy as np

from matrix_ap import TR, ap_all, read_matrix

SHORT = ["Null", "Iso", "Topo", "IsoTopo", "Part", "Tri", "Noise", "Scale"]


def load(path, name, ids):
    m, shapes = read_matrix(path, name)
    if [s["id"] for s in shapes] != ids:
        sys.exit(f"{path}: shape ids differ from the manifest")
    return m


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    config = os.environ.get("CONFIG", "default")
    rows = list(csv.DictReader(open(sys.argv[1])))
    ids = [r["id"] for r in rows]
    cls = np.array([r["class"] for r in rows])
    tr = np.array([r["transform"] for r in rows])
    st = np.array([int(r["strength"] or 0) for r in rows])
    variants = []
    for arg in sys.argv[2:]:
        name, path = arg.split("=", 1)
        variants.append((name, ap_all(load(path, config, ids), cls)))
    print("| variant | " + " | ".join(SHORT) + " | All | Topo s1–s4 | IsoTopo s1–s4 |")
    print("|---" * (len(SHORT) + 4) + "|")
    for name, aps in variants:
        per = [100 * aps[tr == t].mean() for t in TR]
        ps = lambda t: " / ".join("%.1f" % (100 * aps[(tr == t) & (st == s)].mean()) for s in range(1, 5))
        print(f"| {name} | " + " | ".join("%.2f" % x for x in per)
              + " | **%.2f** | %s | %s |" % (100 * aps.mean(), ps("topology"), ps("isometry+topology")))
    if len(variants) < 2:
        return
    print("\nLeave-one-class-out: choose the variant on the other seven classes' queries, score the held-out class's queries")
    classes = list(dict.fromkeys(cls))
    chosen, fold = [], {}
    for c in classes:
        other = cls != c
        best = max(range(len(variants)), key=lambda i: (variants[i][1][other].mean(), -i))
        chosen.append(variants[best][0])
        fold[c] = variants[best][1]
        print(f"  fold {c}: chose {variants[best][0]} (in-fold mean {100 * variants[best][1][other].mean():.2f})")
    print("\n| held-out class | chosen | " + " | ".join(SHORT) + " | All |")
    print("|---" * (len(SHORT) + 3) + "|")
    table = {}
    for c, ch in zip(classes, chosen):
        m = cls == c
        vals = [100 * fold[c][m & (tr == t)].mean() for t in TR] + [100 * fold[c][m].mean()]
        table[c] = vals
        print(f"| {c} | {ch} | " + " | ".join("%.2f" % v for v in vals) + " |")
    arr = np.array(list(table.values()))
    print("| **mean** | | " + " | ".join("%.2f" % v for v in arr.mean(0)) + " |")
    print("| **worst** | | " + " | ".join("%.2f" % v for v in arr.min(0)) + " |")
    # The same per-fold view for each variant held fixed (what the protocol compares against).
    print("\nPer-class mean over held-out folds for each fixed variant (All; IsoTopo):")
    for name, aps in variants:
        per_c = [aps[cls == c].mean() for c in classes]
        it = [aps[(cls == c) & (tr == "isometry+topology")].mean() for c in classes]
        print(f"  {name}: All mean {100 * np.mean(per_c):.2f} worst {100 * np.min(per_c):.2f}; "
              f"IsoTopo mean {100 * np.mean(it):.2f} worst {100 * np.min(it):.2f}")


if __name__ == "__main__":
    main()
