#!/usr/bin/env python3
"""Offline prototype of the heat kernel signature's distribution as one more term of the first
stage (docs/quality.md §35; the product's channel is `heat_quantiles`). Needs numpy.

    cargo run --release --example hks_dump -- <manifest> HKS        # per-vertex HKS, default preparation
    shapeseek eval --manifest <manifest> --config <default without its stage, named `first`> --matrices MM.json
    python3 scripts/analysis/hks_distribution.py HKS MM.json [--times 0,1,2,3] [--form cdf|quantiles|histogram]

Per shape and chosen time (indices into hks_dump's 32 times), the area-weighted distribution of
r = A h(x, t) / sum_k exp(-lambda_k t) (mean 1). Two shapes are compared, summed over the times:

* `cdf` (default): L1 distance of the cumulative distributions of log r over 64 bins between the
  pooled 0.5th and 99.5th percentiles, divided by 64; the sum over the times is divided by its
  median over the pairs and added to first / its median with a weight w in 0 … 0.5;
* `quantiles`: mean absolute difference of 32 area-weighted quantiles of log r (the
  1-Wasserstein distance; what `heat_quantiles` stores), added to `first` with a weight w in 0 … 2;
* `histogram`: nL1 of the histogram of r itself over 128 bins from 0 to the pooled 90th
  percentile (a histogram channel of the default's kind, unweighted), one configuration per set
  of times.

Each mix is re-ranked by the reciprocal stage over the whole corpus
(neighbourhood_rerank.reciprocal, mean over k = 8, 16, 32); then the leave-one-class-out choice
among the mixes and the held-out figure per fold. Held-in is by default the other classes'
queries ranked over the whole corpus, the held-out class's shapes among their candidates;
`--held-in restricted` removes those shapes and re-runs the stage, as `eval --protocol loco`
does (§35: that difference decides the david fold's choice).
"""
import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from hks_chamfer import read_dump  # noqa: E402
from matrix_ap import TR, ap_all, read_matrix  # noqa: E402
from neighbourhood_rerank import reciprocal  # noqa: E402


def ratios(hks, index, times, sid, sel):
    """(r at the chosen times, n x len(sel)) and the vertex masses normalised to sum 1."""
    h, m, trace = read_dump(hks, index, times, sid)
    return (h / trace * m.sum())[:, sel], m / m.sum()


def pairwise_l1(X):
    return np.abs(X[:, None] - X[None, :]).reshape(len(X), len(X), -1).sum(2)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("hks")
    ap.add_argument("matrices")
    ap.add_argument("--times", default="0,1,2,3")
    ap.add_argument("--form", choices=["cdf", "quantiles", "histogram"], default="cdf")
    ap.add_argument("--held-in", choices=["queries", "restricted"], default="queries",
                    help="queries: the other classes' queries over the whole corpus (§35's "
                         "figures); restricted: queries and candidates of the other classes "
                         "only, the stage re-run on them, as `eval --protocol loco` does")
    args = ap.parse_args()
    index = json.load(open(os.path.join(args.hks, "index.json")))
    times = np.array(index["times"])
    sel = [int(x) for x in args.times.split(",")]
    D, shapes = read_matrix(args.matrices, "first")
    cls = np.array([s["class"] for s in shapes])
    tr = np.array([s["transform"] for s in shapes])
    n = len(cls)
    off = ~np.eye(n, dtype=bool)
    R = [ratios(args.hks, index, times, s["id"], sel) for s in shapes]
    mixes = {}
    if args.form == "cdf":
        F = np.zeros((n, len(sel), 64))
        for j in range(len(sel)):
            lo, hi = np.percentile(np.concatenate([np.log(r[:, j]) for r, _ in R]), [0.5, 99.5])
            for i, (r, m) in enumerate(R):
                h, _ = np.histogram(np.clip(np.log(r[:, j]), lo, hi), bins=64, range=(lo, hi), weights=m)
                F[i, j] = np.cumsum(h) / h.sum()
        Dh = pairwise_l1(F) / 64
        Dh /= np.median(Dh[off])
        Dn = D / np.median(D[off])
        mixes = {f"w={w}": Dn + w * Dh for w in (0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5)}
    elif args.form == "quantiles":
        u = (np.arange(32) + 0.5) / 32
        Q = np.zeros((n, len(sel), 32))
        for i, (r, m) in enumerate(R):
            for j in range(len(sel)):
                o = np.argsort(r[:, j])
                Q[i, j] = np.interp(u, np.cumsum(m[o]) - 0.5 * m[o], np.log(r[o, j]))
        Dq = pairwise_l1(Q) / 32
        mixes = {f"w={w}": D + w * Dq for w in (0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0)}
    else:
        H = np.zeros((n, len(sel), 128))
        for j in range(len(sel)):
            pool = np.concatenate([r[:, j] for r, _ in R])
            wts = np.concatenate([m for _, m in R])
            o = np.argsort(pool)
            hi = pool[o][np.searchsorted(np.cumsum(wts[o]) / wts.sum(), 0.9)]
            for i, (r, m) in enumerate(R):
                h, _ = np.histogram(r[:, j], bins=128, range=(0, hi), weights=m)
                H[i, j] = h / max(h.sum(), 1e-12)
        per_time = [pairwise_l1(H[:, j]) for j in range(len(sel))]
        mixes = {"none": D}
        for k in range(1, len(sel) + 1):
            mixes[f"first {k} time(s)"] = D + sum(per_time[:k])

    def staged(C):
        return np.mean([reciprocal(C, k) for k in (8, 16, 32)], axis=0)

    res = {}
    for label, C in mixes.items():
        b = ap_all(staged(C), cls)
        res[label] = b
        per = " ".join("%5.1f" % (100 * b[tr == t].mean()) for t in TR)
        print("%-16s + stage: %s | All %.2f" % (label, per, 100 * b.mean()), flush=True)
    base = next(iter(res))
    held, fixed, chosen = [], [], []
    for c in sorted(set(cls)):
        inn = cls != c
        if args.held_in == "restricted":
            sub = np.ix_(inn, inn)
            score = {k: ap_all(staged(C[sub]), cls[inn]).mean() for k, C in mixes.items()}
        else:
            score = {k: res[k][inn].mean() for k in res}
        best = max(score, key=score.get)
        chosen.append(best)
        held.append(res[best][~inn].mean())
        fixed.append(res[base][~inn].mean())
    print("chosen per fold: mean %.2f worst %.2f | %s: mean %.2f worst %.2f"
          % (100 * np.mean(held), 100 * min(held), base, 100 * np.mean(fixed), 100 * min(fixed)))
    for c, k, h, f in zip(sorted(set(cls)), chosen, held, fixed):
        print("  %-12s %-16s %.2f (%s %.2f)" % (c, k, 100 * h, base, 100 * f))


if __name__ == "__main__":
    main()
