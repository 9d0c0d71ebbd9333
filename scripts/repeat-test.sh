#!/usr/bin/env bash
# Runs a test binary's named tests N times to catch a rare hang, and takes the stacks of one.
#
#   bash scripts/repeat-test.sh BIN N TEST...
#
# BIN is a test binary (e.g. target/release/deps/shapeseek-<hash>, the lib tests); each run is
# `BIN --exact TEST... --test-threads 4` under `scripts/watchdog.sh PATIENCE` (default 90 s).
# A run still going then is reported as HUNG: the watchdog's output (every thread's stack, from
# gdb) goes to hang-RUN.txt in OUT (default a new temporary directory) and the run is killed. A
# run that fails prints its last lines. The last line is the count: "N runs: H hung, F failed".
set -u
bin=$1 n=$2
shift 2
patience=${PATIENCE:-90}
out=${OUT:-$(mktemp -d)}
watchdog="$(dirname "$0")/watchdog.sh"
hung=0 failed=0
for i in $(seq 1 "$n"); do
  bash "$watchdog" "$patience" "$bin" --exact "$@" --test-threads 4 > "$out/run.log" 2>&1
  rc=$?
  if [ "$rc" -eq 124 ]; then
    hung=$((hung + 1))
    cp "$out/run.log" "$out/hang-$i.txt"
    echo "run $i HUNG: stacks in $out/hang-$i.txt"
  elif [ "$rc" -ne 0 ]; then
    failed=$((failed + 1))
    echo "run $i failed:"
    tail -5 "$out/run.log"
  fi
done
echo "$n runs: $hung hung, $failed failed"
