#!/usr/bin/env bash
# Runs a test binary's named tests N times to catch a rare hang, and takes the stacks of one.
#
#   bash scripts/repeat-test.sh BIN N TEST...
#
# BIN is a test binary (e.g. target/release/deps/shapeseek-<hash>, the lib tests); each run is
# `BIN --exact TEST... --test-threads 4`. A run still going after PATIENCE seconds (default 90)
# is reported as HUNG: gdb's `thread apply all bt` goes to hang-RUN.txt in OUT (default a new
# temporary directory) and the run is killed. A run that fails prints its last lines. The last
# line is the count: "N runs: H hung, F failed".
set -u
bin=$1 n=$2
shift 2
patience=${PATIENCE:-90}
out=${OUT:-$(mktemp -d)}
hung=0 failed=0
for i in $(seq 1 "$n"); do
  "$bin" --exact "$@" --test-threads 4 > "$out/run.log" 2>&1 &
  pid=$!
  for _ in $(seq 1 $((patience * 10))); do
    kill -0 "$pid" 2>/dev/null || break
    sleep 0.1
  done
  if kill -0 "$pid" 2>/dev/null; then
    hung=$((hung + 1))
    gdb -p "$pid" -batch -ex "thread apply all bt" > "$out/hang-$i.txt" 2>&1
    kill -9 "$pid"
    wait "$pid" 2>/dev/null
    echo "run $i HUNG: stacks in $out/hang-$i.txt"
  elif ! wait "$pid"; then
    failed=$((failed + 1))
    echo "run $i failed:"
    tail -5 "$out/run.log"
  fi
done
echo "$n runs: $hung hung, $failed failed"
