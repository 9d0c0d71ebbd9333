"""Average precision per query from `shapeseek eval --matrices` files, shared by the analysis
scripts of this folder (import it; it is not a command). AP exactly as the bench README says:
the full ranking of every other shape, ties by manifest order. Needs numpy.
"""
import json

import numpy as np

TR = ["null", "isometry", "topology", "isometry+topology", "partiality", "triangulation", "noise", "scale"]


def read_matrix(path, name):
    """The matrix of configuration `name` (NaN where eval wrote none, 0 on the diagonal) and the
    file's shape rows (`id`, `class`, `transform`, `strength`)."""
    d = json.load(open(path))
    if name not in d["matrices"]:
        raise SystemExit(f"{path}: no configuration {name!r} (has {', '.join(d['matrices'])})")
    m = np.array([[np.nan if v is None else v for v in row] for row in d["matrices"][name]], float)
    np.fill_diagonal(m, 0.0)
    return m, d["shapes"]


def ap_all(D, cls, hidden=None):
    """AP of every query q over the other shapes, relevant = same class. `hidden(q)`, when
    given, is a boolean mask of candidates q does not see (e.g. a near-twin class)."""
    n = len(cls)
    aps = np.zeros(n)
    for q in range(n):
        keep = np.arange(n) != q
        if hidden is not None:
            keep &= ~hidden(q)
        idx = np.flatnonzero(keep)
        order = np.lexsort((idx, D[q, idx]))  # ties by manifest order
        rel = (cls[idx[order]] == cls[q]).astype(float)
        prec = np.cumsum(rel) / np.arange(1, len(rel) + 1)
        aps[q] = (prec * rel).sum() / rel.sum()
    return aps
