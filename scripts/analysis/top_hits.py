#!/usr/bin/env python3
"""What the first hits of a group of queries are, from `shapeseek eval --matrices` files
(docs/quality.md §30): of each query's first K hits, the share of its own class, of shapes of
another class with the same transformation as a marker set, and of the rest.

    shapeseek eval --manifest M --config default --matrices m.json ...
    python3 scripts/analysis/top_hits.py m.json default --queries cut2,cut3,holes3
    python3 scripts/analysis/top_hits.py m.json default --queries cut2,cut3,holes3 --k 10 --transform partiality

`--queries`: id suffixes (`<class>-<suffix>`) of the queries looked at; `--transform`: the
transformation whose other-class shapes are counted apart (default partiality). Ranks are the
matrix rows' order (ties by manifest order, as eval's AP). Needs numpy.
"""
import argparse

import numpy as np

from matrix_ap import read_matrix


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("matrices")
    p.add_argument("config")
    p.add_argument("--queries", required=True)
    p.add_argument("--k", type=int, default=10)
    p.add_argument("--transform", default="partiality")
    a = p.parse_args()
    D, shapes = read_matrix(a.matrices, a.config)
    cls = np.array([s["class"] for s in shapes])
    tr = np.array([s["transform"] for s in shapes])
    ids = [s["id"] for s in shapes]
    suffixes = a.queries.split(",")
    queries = [i for i, s in enumerate(ids) if any(s.endswith("-" + x) for x in suffixes)]
    if not queries:
        raise SystemExit(f"no query id ends with one of {suffixes}")
    own = marked = rest = 0
    for q in queries:
        others = np.flatnonzero(np.arange(len(ids)) != q)
        hits = others[np.lexsort((others, D[q, others]))][: a.k]
        own += int((cls[hits] == cls[q]).sum())
        marked += int(((cls[hits] != cls[q]) & (tr[hits] == a.transform)).sum())
        rest += int(((cls[hits] != cls[q]) & (tr[hits] != a.transform)).sum())
    n = own + marked + rest
    share = 100.0 * (tr == a.transform).mean()
    print(f"{len(queries)} queries, first {a.k} hits each ({a.config}):")
    print(f"  own class {100 * own / n:.0f} %, other classes' {a.transform} {100 * marked / n:.0f} %, "
          f"other classes' other shapes {100 * rest / n:.0f} % ({a.transform} is {share:.0f} % of the set)")


if __name__ == "__main__":
    main()
