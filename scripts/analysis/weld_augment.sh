#!/bin/bash
# Welded copies of every character of a benchmark manifest at the benchmark's own strengths
# (docs/quality.md §16): for each class and strength s of STRENGTHS, examples/weld_bench welds
# the sources SOURCES with s bridges and discs of radius 1 + 0.5 s mean edge lengths (the
# bench README's table: 1.5, 2, 2.5, 3), seed s. OUT/manifest.csv = MANIFEST's rows followed by
# every welded copy that got at least one bridge; OUT/report.csv = weld_bench's reports.
#
#   cargo build --release --examples
#   scripts/analysis/weld_augment.sh ../shared/bench/dev/manifest.csv /tmp/aug [STRENGTHS] [SOURCES]
#
# STRENGTHS defaults to 2,3,4 and SOURCES to null,iso1,iso3,iso5,iso7. Uses
# ${CARGO_TARGET_DIR:-target}/release/examples/weld_bench.
set -euo pipefail
M=${1:?usage: weld_augment.sh MANIFEST OUT [STRENGTHS] [SOURCES]}
O=${2:?usage: weld_augment.sh MANIFEST OUT [STRENGTHS] [SOURCES]}
STRENGTHS=${3:-2,3,4}
SOURCES=${4:-null,iso1,iso3,iso5,iso7}
W=${CARGO_TARGET_DIR:-target}/release/examples/weld_bench
[ -x "$W" ] || { echo "build it first: cargo build --release --example weld_bench" >&2; exit 1; }
mkdir -p "$O"
classes=$(tail -n +2 "$M" | cut -d, -f3 | awk '!seen[$0]++')
for c in $classes; do
  for s in ${STRENGTHS//,/ }; do
    d=$(awk -v s="$s" 'BEGIN { print 1 + 0.5 * s }')
    echo "weld_augment: $c, $s bridges, discs of $d edges" >&2
    "$W" "$M" "$O/$c-s$s" --class "$c" --sources "$SOURCES" --bridges "$s" --disc-edges "$d" \
      --seed "$s" > "$O/$c-s$s.log" 2>&1 || { echo "weld_bench failed, see $O/$c-s$s.log" >&2; exit 1; }
  done
done
python3 - "$M" "$O" <<'PY'
import csv, glob, os, sys
m, o = sys.argv[1], sys.argv[2]
base = os.path.dirname(os.path.abspath(m))
with open(m, newline="") as f:
    dev = list(csv.DictReader(f))
header = list(dev[0].keys())
for r in dev:
    if not os.path.isabs(r["path"]):
        r["path"] = os.path.normpath(os.path.join(base, r["path"]))
made, reports = {}, []
for rep in sorted(glob.glob(os.path.join(o, "*", "report.csv"))):
    with open(rep, newline="") as f:
        for r in csv.DictReader(f):
            made[r["id"]] = int(r["bridges_made"])
            reports.append(r)
welded, seen = [], set()
for man in sorted(glob.glob(os.path.join(o, "*", "manifest.csv"))):
    with open(man, newline="") as f:
        for r in csv.DictReader(f):
            if r["id"] in made and made[r["id"]] > 0 and r["id"] not in seen:
                seen.add(r["id"])
                welded.append(r)
with open(os.path.join(o, "manifest.csv"), "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=header, lineterminator="\n")
    w.writeheader()
    w.writerows(dev + welded)
with open(os.path.join(o, "report.csv"), "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=list(reports[0].keys()), lineterminator="\n")
    w.writeheader()
    w.writerows(reports)
print(f"weld_augment: {len(dev)} shapes + {len(welded)} welded copies "
      f"({sum(made[r['id']] for r in welded)} bridges; {sum(1 for v in made.values() if v == 0)} copies without a bridge dropped) -> {o}/manifest.csv", file=sys.stderr)
PY
