#!/usr/bin/env python3
"""Other channel mixes for the partial queries, with the transform label as an oracle, and two
hubness corrections of the first stage (docs/quality.md §34). Needs numpy and scipy.

    shapeseek eval --manifest M --config C --matrices MM.json
    python3 scripts/analysis/channel_mix.py MM.json

C lists the default (`default`), the default without its stage (`first`, `"rerank": []`) and one
configuration per channel of the default's query, each without the stage (`ch0` … `ch7`, in the
default's channel order: four full-range heat channels, three short-range, ShapeDNA). Prints,
per mix, the partial queries' and all queries' mAP of the first stage, then of the reciprocal
stage over the whole corpus (neighbourhood_rerank.reciprocal, mean over k = 8, 16, 32); then
the same for mutual proximity and local scaling applied to the whole first-stage matrix.
"""
import os
import sys

import numpy as np
from scipy.stats import norm

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from matrix_ap import TR, ap_all, read_matrix  # noqa: E402
from neighbourhood_rerank import reciprocal  # noqa: E402

MIXES = {
    "ShapeDNA left out": [1, 1, 1, 1, 1, 1, 1, 0],
    "ShapeDNA x 0.5": [1, 1, 1, 1, 1, 1, 1, 0.5],
    "ShapeDNA x 2": [1, 1, 1, 1, 1, 1, 1, 2],
    "full range only": [1, 1, 1, 1, 0, 0, 0, 0],
    "short range only": [0, 0, 0, 0, 1, 1, 1, 0],
    "short range + ShapeDNA": [0, 0, 0, 0, 1, 1, 1, 1],
    "short range x 2": [1, 1, 1, 1, 2, 2, 2, 1],
    "full range x 2": [2, 2, 2, 2, 1, 1, 1, 1],
    "without the two smallest t": [0, 0, 1, 1, 1, 1, 1, 1],
    "without t = 0.016, 0.04": [1, 1, 0, 0, 1, 1, 1, 1],
}


def report(label, D, cls, tr):
    part = tr == "partiality"
    a = ap_all(D, cls)
    R = np.mean([reciprocal(D, k) for k in (8, 16, 32)], axis=0)
    b = ap_all(R, cls)
    per = " ".join("%5.1f" % (100 * b[tr == t].mean()) for t in TR)
    print("%-30s first: part %.2f All %.2f | + stage: %s | part %.2f All %.2f"
          % (label, 100 * a[part].mean(), 100 * a.mean(), per, 100 * b[part].mean(), 100 * b.mean()),
          flush=True)


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    path = sys.argv[1]
    first, shapes = read_matrix(path, "first")
    ch = [read_matrix(path, f"ch{i}")[0] for i in range(8)]
    cls = np.array([s["class"] for s in shapes])
    tr = np.array([s["transform"] for s in shapes])
    n = len(cls)
    off = ~np.eye(n, dtype=bool)
    print("largest |sum of channels - first| %.3f, median first %.3f"
          % (np.abs(sum(ch) - first)[off].max(), np.median(first[off])))
    part = tr == "partiality"
    d = ap_all(read_matrix(path, "default")[0], cls)
    print("%-30s part %.2f All %.2f" % ("default (the product's stage)", 100 * d[part].mean(), 100 * d.mean()))
    report("first", first, cls, tr)
    for label, w in MIXES.items():
        D = first.copy()
        D[part] = sum(wi * c for wi, c in zip(w, ch))[part]
        report("partial rows: " + label, D, cls, tr)
    S = (first + first.T) / 2
    mu = np.array([S[i, off[i]].mean() for i in range(n)])
    sd = np.array([S[i, off[i]].std() for i in range(n)])
    P = norm.sf((S - mu[:, None]) / sd[:, None])
    MP = 1 - P * P.T
    np.fill_diagonal(MP, 0)
    report("mutual proximity", MP, cls, tr)
    srt = np.sort(np.where(off, S, np.inf), axis=1)
    for k in (5, 10, 20, 40):
        LS = S / np.sqrt(srt[:, k - 1][:, None] * srt[:, k - 1][None, :])
        np.fill_diagonal(LS, 0)
        report("local scaling k=%d" % k, LS, cls, tr)


if __name__ == "__main__":
    main()
