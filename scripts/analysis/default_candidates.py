#!/usr/bin/env python3
"""Writes docs/quality/default-candidates.json: the product default and one-choice-at-a-time
variants of each internal choice it makes, as candidates for `shapeseek eval --protocol loco`
(docs/quality.md §12). Every candidate keeps the default's handle cutting; each varies exactly
one of: the short-range radii, the band of the Weyl fit, the reciprocal stage's neighbourhood
sizes, its query expansion, its first-stage weight, its shortlist. The histogram window
percentile is a run option (`--window-percentile`), varied by separate runs instead.

    python3 scripts/analysis/default_candidates.py > docs/quality/default-candidates.json
"""
import copy
import json
import sys

BASE = "docs/quality/handle-cut-candidates.json"
TIMES = ["0.016", "0.04", "0.1"]
RADII = {  # docs/quality.md §3b: percentiles of the tune classes' pooled distances
    "P75": [3.14, 2.1, 1.09],  # = presets::SHORT_RANGE_RADII
    "P50": [2.44, 1.46, 0.68],
}


def radii_variant(cfg, name, radii):
    c = copy.deepcopy(cfg)
    c["name"] = name
    chans = c["signature"]["channels"]
    for ch, r in zip(chans[3:], radii):
        ch["kind"]["truncated"]["radius"] = r
    c["query"]["channels"] = c["query"]["channels"][:3] + [
        f"heat-l2[t={t}][r={r:g}]" for t, r in zip(TIMES, radii)
    ]
    return c


def main():
    base = next(c for c in json.load(open(BASE))["configs"] if c["name"] == "default-cut[a3,l0.5]")
    base = copy.deepcopy(base)
    base["name"] = "default"
    out = [base]
    # Short-range radii: P50 of the tune classes, and 4/3 of the default's P75.
    out.append(radii_variant(base, "default[r=P50]", RADII["P50"]))
    out.append(radii_variant(base, "default[r=4/3]", [round(r * 4 / 3, 2) for r in RADII["P75"]]))
    # Band of the Weyl fit (docs/quality.md §2c), and no scaling.
    for m in (26, 51):
        c = copy.deepcopy(base)
        c["name"] = f"default[weyl={m}]"
        c["signature"]["spectrum_scaling"] = {"kind": "weyl_fit", "eigenpairs": m}
        out.append(c)
    c = copy.deepcopy(base)
    c["name"] = "default[unscaled]"
    c["signature"]["spectrum_scaling"] = {"kind": "none"}
    out.append(c)
    # Reciprocal stage (docs/quality.md §7).
    for key, vals in (
        ("neighbourhoods", ([4, 8, 16], [16, 32, 64])),
        ("expansion", (1, 2, 8)),
        ("original_weight", (0.0, 0.3)),
        ("shortlist", (100, 279)),
    ):
        for v in vals:
            c = copy.deepcopy(base)
            c["name"] = f"default[{key}={json.dumps(v).replace(' ', '')}]"
            c["rerank"][0][key] = v
            out.append(c)
    json.dump({"configs": out}, sys.stdout, indent=1)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
