#!/usr/bin/env python3
"""Per-query AP of one configuration from `shapeseek eval --matrices`, averaged per group of
characters and transformation (docs/quality.md §18, §20, §21: "the two humans' queries"), and
the queries that move most between two configurations.

    shapeseek eval --manifest /tmp/aug/manifest.csv --config C.json --matrices /tmp/aug/m.json
    python3 scripts/analysis/group_ap.py /tmp/aug/m.json default
    python3 scripts/analysis/group_ap.py /tmp/aug/m.json default --twins
    python3 scripts/analysis/group_ap.py /tmp/aug/m.json default --diff other --min 10

Rows: the queries of the classes in GROUP (`--group crane-man,thick-man`, the default: the
proxy's two humans, §18) and those of every other class, each per transformation class and All.
`--twins`: a GROUP query does not see the GROUP's other classes (the proxy's second human is
crane-man thickened, the same poses and welds: its near-twin hits say nothing about a real
second performer). `--diff OTHER`: the queries whose AP differs by at least `--min` points
(default 5) between the configuration and OTHER, largest loss first. Needs numpy.
"""
import argparse

import numpy as np

from matrix_ap import TR, ap_all, read_matrix


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("matrices")
    p.add_argument("config")
    p.add_argument("--group", default="crane-man,thick-man")
    p.add_argument("--twins", action="store_true")
    p.add_argument("--diff")
    p.add_argument("--min", type=float, default=5.0)
    a = p.parse_args()
    group = set(a.group.split(","))
    D, shapes = read_matrix(a.matrices, a.config)
    cls = np.array([s["class"] for s in shapes])
    tr = np.array([s["transform"] for s in shapes])
    ids = [s["id"] for s in shapes]
    ingroup = np.isin(cls, sorted(group))
    hidden = (lambda q: ingroup & (cls != cls[q]) if ingroup[q] else np.zeros(len(cls), bool)) if a.twins else None
    aps = 100 * ap_all(D, cls, hidden)
    print("| queries | " + " | ".join(TR) + " | All |")
    print("|---" * (len(TR) + 2) + "|")
    for label, m in [(",".join(sorted(group)), ingroup), ("the other classes", ~ingroup)]:
        cells = ["%.1f" % aps[m & (tr == t)].mean() if (m & (tr == t)).any() else "–" for t in TR]
        print(f"| {label} | " + " | ".join(cells) + " | %.1f |" % aps[m].mean())
    if a.diff:
        D2, shapes2 = read_matrix(a.matrices, a.diff)
        if [s["id"] for s in shapes2] != ids:
            raise SystemExit("the two configurations rank different shapes")
        other = 100 * ap_all(D2, cls, hidden)
        print(f"\nmean AP {aps.mean():.2f} ({a.config}) -> {other.mean():.2f} ({a.diff})")
        for q in np.argsort(other - aps):
            if abs(other[q] - aps[q]) >= a.min:
                print(f"{ids[q]:30} {aps[q]:6.1f} -> {other[q]:6.1f}")


if __name__ == "__main__":
    main()
