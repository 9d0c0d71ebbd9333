#!/usr/bin/env python3
"""Neighbourhood re-ranking variants on a full dissimilarity matrix (exploration behind
docs/quality.md §7; the product's stage is `rerank::reciprocal`, measured with `shapeseek eval`).

    shapeseek eval --manifest ../shared/bench/dev/manifest.csv \
        --config docs/quality/default-weyl.json --matrices /tmp/m.json
    python3 scripts/analysis/neighbourhood_rerank.py /tmp/m.json default@weyl

(any configuration without re-ranking stages: --matrices writes what each configuration ranks by).

Prints mAP per transformation class for: the matrix itself, average query expansion of the
distance profiles, diffusion on a self-tuning kNN graph (personalised PageRank), k-reciprocal
re-ranking (Zhong et al. 2017) with one k and with the mean over k = 8, 16, 32. Every variant uses
the whole corpus (every other shape's row), unlike the product's stage, which sees a shortlist.
Needs numpy.
"""
import sys

import numpy as np

from matrix_ap import TR, ap_all, read_matrix


def load(path, name):
    m, shapes = read_matrix(path, name)
    return m, np.array([s["class"] for s in shapes]), np.array([s["transform"] for s in shapes])


def row(label, aps, tr):
    per = "  ".join("%5.1f" % (100 * aps[tr == t].mean()) for t in TR if (tr == t).any())
    return "%-28s %s | All %.2f" % (label, per, 100 * aps.mean())


def query_expansion(D, k, alpha=1.0):
    n = len(D)
    out = np.zeros_like(D)
    for q in range(n):
        o = np.argsort(D[q] + np.where(np.arange(n) == q, np.inf, 0))[:k]
        w = np.concatenate([[1.0], alpha * np.ones(k)])
        out[q] = (w[:, None] * np.vstack([D[q], D[o]])).sum(0) / w.sum()
    return out


def diffusion(D, k=10, knn=15, alpha=0.95):
    n = len(D)
    big = D + np.eye(n) * 1e30
    sig = np.sort(big, axis=1)[:, k - 1]
    W = np.exp(-D ** 2 / np.outer(sig, sig))
    np.fill_diagonal(W, 0)
    mask = np.zeros_like(W, bool)
    for i, nb in enumerate(np.argsort(big, axis=1)[:, :knn]):
        mask[i, nb] = True
    W = W * (mask | mask.T)
    d = W.sum(1)
    F = np.linalg.inv(np.eye(n) - alpha * W / np.sqrt(np.outer(d, d) + 1e-300))
    F = (F + F.T) / 2
    return -F / np.maximum(np.diag(F)[:, None], 1e-300) + 1e-9 * D / D.max()


def reciprocal(D, k1, k2=4, lam=0.1):
    n = len(D)
    Dn = D / D.max(axis=1, keepdims=True)
    ranks = np.argsort(D, axis=1, kind="stable")
    V = np.zeros((n, n))
    for i in range(n):
        fk = ranks[i, : k1 + 1]
        rec = fk[np.any(ranks[fk, : k1 + 1] == i, axis=1)]
        exp = rec.copy()
        h = (k1 + 1) // 2
        for c in rec:
            fc = ranks[c, : h + 1]
            rc = fc[np.any(ranks[fc, : h + 1] == c, axis=1)]
            if len(np.intersect1d(rc, rec)) > 2 / 3 * len(rc):
                exp = np.union1d(exp, rc)
        w = np.exp(-Dn[i, exp])
        V[i, exp] = w / w.sum()
    if k2 > 1:
        V = np.vstack([V[ranks[i, :k2]].mean(0) for i in range(n)])
    J = np.zeros((n, n))
    for i in range(n):
        mn = np.minimum(V[i][None, :], V).sum(1)
        J[i] = 1 - mn / (2 - mn)
    return (1 - lam) * J + lam * Dn


def main():
    D, cls, tr = load(sys.argv[1], sys.argv[2])
    print(row("first stage", ap_all(D, cls), tr))
    for k in (2, 3, 5, 8):
        print(row("query expansion k=%d" % k, ap_all(query_expansion(D, k), cls), tr))
    for k, knn in ((7, 15), (10, 10), (10, 15)):
        print(row("diffusion k=%d knn=%d" % (k, knn), ap_all(diffusion(D, k, knn), cls), tr))
    for k1 in (8, 16, 20, 30, 40):
        print(row("k-reciprocal k=%d" % k1, ap_all(reciprocal(D, k1), cls), tr))
    mean = sum(reciprocal(D, k) for k in (8, 16, 32)) / 3
    print(row("k-reciprocal mean k=8,16,32", ap_all(mean, cls), tr))


if __name__ == "__main__":
    main()
