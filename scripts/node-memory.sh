#!/usr/bin/env bash
# A serving node's peak memory at start and during a recalibration (docs/scale-out.md §4).
#
#   scripts/node-memory.sh BIN STORE [recal MESH]
#
# STORE: `postgres://…` or a sled data directory, already populated, e.g.
#   shapeseek bench populate --store postgres://postgres@127.0.0.1:5432/memtest --count 100000
# Starts `BIN serve` on STORE, waits until /v1/index answers and prints the time, peak RSS
# (VmHWM) and the calibration. With `recal MESH` it then uploads MESH (a shape not stored yet)
# with recalibrate_fraction 0, waits for the recalibration and prints the peak again.
set -euo pipefail
bin=$1 store=$2 mode=${3:-} mesh=${4:-}
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
log=$(mktemp)
if [[ $store == postgres://* ]]; then where=(--store "$store"); else where=(--data "$store"); fi
SHAPESEEK_RECALIBRATE_FRACTION=0 "$bin" serve "${where[@]}" --addr "127.0.0.1:$port" >"$log" 2>&1 &
pid=$!
trap 'kill -INT $pid 2>/dev/null; wait $pid 2>/dev/null; rm -f "$log"' EXIT
t0=$(date +%s.%N)
until curl -sf "http://127.0.0.1:$port/v1/index" -o "$log.idx"; do
  kill -0 $pid 2>/dev/null || { echo "serve exited:"; tail -5 "$log"; exit 1; }
  sleep 0.2
done
t1=$(date +%s.%N)
peak() { grep VmHWM /proc/$pid/status | tr -s ' ' | cut -d' ' -f2-; }
echo "ready after $(awk "BEGIN {printf \"%.1f\", $t1 - $t0}") s, peak $(peak)"
python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print({k: d.get(k) for k in ['shapes','calibration_epoch','calibrated_on','calibration_shapes']})" "$log.idx"
rm -f "$log.idx"
if [[ $mode == recal ]]; then
  t0=$(date +%s.%N)
  curl -s -o /dev/null -w "upload: %{http_code}\n" --data-binary @"$mesh" \
    "http://127.0.0.1:$port/v1/shapes?name=recalibration-probe"
  until grep -q '"recalibrated"\|recalibrated epoch' "$log"; do sleep 0.5; done
  t1=$(date +%s.%N)
  echo "recalibrated after $(awk "BEGIN {printf \"%.1f\", $t1 - $t0}") s, peak $(peak)"
fi
