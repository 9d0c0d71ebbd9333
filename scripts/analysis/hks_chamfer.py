"""Offline prototype of a partial-matching stage (docs/quality.md §33): the default's final
ranking re-ordered, within its first K, by a one-sided Chamfer distance between per-point heat
kernel signatures, and that distance alone as a ranking of the partial queries.

    cargo run --release --example hks_dump -- <manifest> HKS        # per-vertex HKS, default preparation
    shapeseek eval --manifest <manifest> --config default --matrices M.json
    python3 scripts/analysis/hks_chamfer.py HKS M.json [--times 0,2,4,6,8,10] [--shortlist 40] [--alone]

Per shape: log of h(x, t) over the heat trace sum_k exp(-lambda_k t) (at unit area, a density
over the surface), at the chosen of hks_dump's 32 times; 200 points drawn by area
(queries) and 1000 (targets), seed 0. one_sided(a, b) = mean over a's points of the distance to
the nearest of b's; a pair's distance = the smaller of its two directions, so a partial shape
inside a complete one is close from either side. Re-ranking: shortlist position + alpha * rank
by that distance; prints the per-class mAP of every alpha, then the leave-one-class-out choice
among them and the default (held-in: the other classes' queries). Needs numpy.
"""
import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from matrix_ap import TR, ap_all, read_matrix  # noqa: E402


def read_dump(hks, index, times, sid):
    """One shape of an hks_dump folder: h(x, t) (n x len(times)), the vertex masses, and the
    heat trace sum_k exp(-lambda_k t) per time."""
    n = index["shapes"][sid]["n"]
    ev = np.maximum(np.array(index["shapes"][sid]["eigenvalues"]), 0)
    a = np.fromfile(os.path.join(hks, f"{sid}.f32"), dtype="<f4")
    h = a[: n * len(times)].reshape(n, len(times)).astype(float)
    m = a[n * len(times):].astype(float)
    return h, m, np.exp(-np.outer(times, ev)).sum(1)


def load(hks, index, times, sid, sel, rng, nq=200, nt=1000):
    h, m, trace = read_dump(hks, index, times, sid)
    n = len(m)
    d = np.log(np.maximum(h / trace, 1e-12))[:, sel]
    p = m / m.sum()
    return d[rng.choice(n, nq, p=p)], d[rng.choice(n, nt, p=p)]


def one_sided(a, b):
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2 * a @ b.T
    return np.sqrt(np.maximum(d2.min(1), 0)).mean()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("hks")
    ap.add_argument("matrices")
    ap.add_argument("--config", default="default")
    ap.add_argument("--times", default="0,2,4,6,8,10")
    ap.add_argument("--shortlist", type=int, default=40)
    ap.add_argument("--alone", action="store_true", help="also rank the partial queries by the distance alone")
    args = ap.parse_args()
    index = json.load(open(os.path.join(args.hks, "index.json")))
    times = np.array(index["times"])
    sel = [int(x) for x in args.times.split(",")]
    D, shapes = read_matrix(args.matrices, args.config)
    ids = [s["id"] for s in shapes]
    cls = np.array([s["class"] for s in shapes])
    tr = np.array([s["transform"] for s in shapes])
    rng = np.random.default_rng(0)
    S, T = zip(*[load(args.hks, index, times, i, sel, rng) for i in ids])
    n, K = len(ids), args.shortlist
    dist = {}

    def pair(q, j):
        k = (min(q, j), max(q, j))
        if k not in dist:
            dist[k] = min(one_sided(S[q], T[j]), one_sided(S[j], T[q]))
        return dist[k]

    order = np.argsort(D + np.eye(n) * 1e9, axis=1, kind="stable")[:, :K]

    def reranked(alpha):
        R = D.copy()
        for q in range(n):
            c = np.array([pair(q, j) for j in order[q]])
            rc = np.argsort(np.argsort(c, kind="stable"), kind="stable")
            new = np.argsort(np.arange(K) + alpha * rc, kind="stable")
            R[q, order[q][new]] = np.arange(K) - 1e6
        return R

    def row(name, aps):
        print(f"{name:<14}", " ".join(f"{100 * aps[tr == t].mean():6.2f}" for t in TR), f"All {100 * aps.mean():6.2f}")

    print(f"{'':<14}", " ".join(f"{t[:6]:>6}" for t in TR))
    variants = {"default": ap_all(D, cls)}
    row("default", variants["default"])
    for alpha in [0.25, 0.5, 1, 2, 4]:
        variants[f"alpha {alpha}"] = ap_all(reranked(alpha), cls)
        row(f"alpha {alpha}", variants[f"alpha {alpha}"])
    held = []
    for c in sorted(set(cls)):
        inn = cls != c
        best = max(variants, key=lambda k: variants[k][inn].mean())
        held.append(100 * variants[best][~inn].mean())
        print(f"  fold {c}: {best}, held out {held[-1]:.2f} (default {100 * variants['default'][~inn].mean():.2f})")
    print(f"leave-one-class-out: selected {np.mean(held):.2f}, default {100 * np.mean([variants['default'][cls == c].mean() for c in sorted(set(cls))]):.2f}")
    if args.alone:
        P = np.flatnonzero(tr == "partiality")
        st = np.array([int(shapes[q]["strength"]) for q in P])
        R = D.copy()
        for q in P:
            R[q] = [pair(q, j) if j != q else 0.0 for j in range(n)]
        aps = ap_all(R, cls)[P]
        print(f"the distance alone, partial queries: {100 * aps.mean():.2f}; by strength",
              " / ".join(f"{100 * aps[st == s].mean():.2f}" for s in sorted(set(st))))


if __name__ == "__main__":
    main()
