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
# ${CARGO_TARGET_DIR:-<repository>/target}/release/examples/weld_bench; runs from any folder.
set -euo pipefail
M=${1:?usage: weld_augment.sh MANIFEST OUT [STRENGTHS] [SOURCES]}
O=${2:?usage: weld_augment.sh MANIFEST OUT [STRENGTHS] [SOURCES]}
STRENGTHS=${3:-2,3,4}
SOURCES=${4:-null,iso1,iso3,iso5,iso7}
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
W=${CARGO_TARGET_DIR:-$ROOT/target}/release/examples/weld_bench
[ -x "$W" ] || { echo "build it first: cargo build --release --example weld_bench ($W)" >&2; exit 1; }
mkdir -p "$O"
# The classes, by the header's `class` column, in manifest order.
mapfile -t classes < <(python3 -c '
import csv, sys
seen = []
for r in csv.DictReader(open(sys.argv[1], newline="")):
    if r["class"] not in seen:
        seen.append(r["class"])
print("\n".join(seen))' "$M")
runs=()
for c in "${classes[@]}"; do
  for s in ${STRENGTHS//,/ }; do
    d=$(awk -v s="$s" 'BEGIN { print 1 + 0.5 * s }')
    run="$O/$c-s$s"
    echo "weld_augment: $c, $s bridges, discs of $d edges" >&2
    rm -rf "$run"
    "$W" "$M" "$run" --class "$c" --sources "$SOURCES" --bridges "$s" --disc-edges "$d" \
      --seed "$s" > "$run.log" 2>&1 || { echo "weld_bench failed, see $run.log" >&2; exit 1; }
    runs+=("$run")
  done
done
python3 - "$M" "$O" "${runs[@]}" <<'PY'
import csv, os, sys
m, o, runs = sys.argv[1], sys.argv[2], sorted(sys.argv[3:])
base = os.path.dirname(os.path.abspath(m))
with open(m, newline="") as f:
    dev = list(csv.DictReader(f))
header = list(dev[0].keys())
for r in dev:
    if not os.path.isabs(r["path"]):
        r["path"] = os.path.normpath(os.path.join(base, r["path"]))
made, reports = {}, []
for run in runs:  # only the folders this run made, by name
    with open(os.path.join(run, "report.csv"), newline="") as f:
        for r in csv.DictReader(f):
            made[r["id"]] = int(r["bridges_made"])
            reports.append(r)
welded, seen = [], set()
for run in runs:
    with open(os.path.join(run, "manifest.csv"), newline="") as f:
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
      f"({sum(made[r['id']] for r in welded)} bridges; "
      f"{sum(1 for v in made.values() if v == 0)} copies without a bridge dropped) -> {o}/manifest.csv",
      file=sys.stderr)
PY
