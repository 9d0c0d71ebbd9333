#!/usr/bin/env bash
# SIGKILL soak of a release `shapeseek serve` on 127.0.0.1 (loopback only, bounded in time).
#
#   scripts/soak-kill.sh [ROUNDS] [INGESTERS]
#
# ROUNDS (default 20) times: start the server on one data directory, run INGESTERS (default 3)
# concurrent curl upload loops over distinct generated meshes (`shapeseek bench meshes`),
# SIGKILL the server 0.3 to 1.5 s later, in the middle of the uploads. Every upload answered
# 201 is an acknowledged shape (id + the SHA-256 of the bytes sent). At the end the server is
# started once more and every acknowledged shape must be there: record (200), original bytes
# identical, signature (200), and re-uploading the same bytes answers 200 with the same id.
# Prints rounds, acknowledged, cut mid-request, stored, lost; exits 1 if any is lost.
#
# SHAPESEEK_* settings come from the environment (default here: SHAPESEEK_EIGENPAIRS=60).
# CARGO_TARGET_DIR is honoured; the temporary directory is removed at exit.
set -euo pipefail
cd "$(dirname "$0")/.."
ROUNDS="${1:-20}"
INGESTERS="${2:-3}"
TARGET="${CARGO_TARGET_DIR:-$PWD/target}"
BIN="$TARGET/release/shapeseek"
export SHAPESEEK_EIGENPAIRS="${SHAPESEEK_EIGENPAIRS:-60}"
cargo build --quiet --release --bin shapeseek
WORK="$(mktemp -d)"
PID=""
cleanup() {
  if [ -n "$PID" ]; then kill -9 "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT

start_server() {
  : >"$WORK/log"
  "$BIN" serve --data "$WORK/index" --addr 127.0.0.1:0 --log-format json >"$WORK/log" 2>&1 &
  PID=$!
  ADDR=""
  for _ in $(seq 1 600); do
    ADDR="$(grep -o '"addr":"[^"]*"' "$WORK/log" | head -1 | cut -d'"' -f4 || true)"
    [ -n "$ADDR" ] && curl -sf "http://$ADDR/readyz" >/dev/null 2>&1 && break
    kill -0 "$PID" 2>/dev/null || { cat "$WORK/log"; echo "server exited"; exit 1; }
    sleep 0.1
  done
  [ -n "$ADDR" ] || { cat "$WORK/log"; echo "server did not start"; exit 1; }
  URL="http://$ADDR"
}

# Distinct meshes: each ingester takes its own slice.
PER=$((ROUNDS * 12))
"$BIN" bench meshes --out "$WORK/meshes" --count $((PER * INGESTERS)) --size 400 >/dev/null
mapfile -t MESHES < <(ls "$WORK/meshes" | sort)
: >"$WORK/acked"
: >"$WORK/cut"

ingest_loop() { # worker index, first mesh, url
  local w="$1" i="$2" url="$3" end=$(($2 + PER)) f code id
  while [ "$i" -lt "$end" ]; do
    f="$WORK/meshes/${MESHES[$i]}"
    if [ -e "$WORK/done.$w.$i" ]; then i=$((i + 1)); continue; fi
    if ! code="$(curl -s -o "$WORK/resp.$w" -w '%{http_code}' --max-time 30 \
      -H 'Content-Type: model/off' --data-binary "@$f" "$url/v1/shapes")"; then
      echo "$f" >>"$WORK/cut"
      return 0
    fi
    if [ "$code" = 201 ] || [ "$code" = 200 ]; then
      id="$(jq -r .id "$WORK/resp.$w")"
      [ "$code" = 201 ] && echo "$id $(sha256sum "$f" | cut -d' ' -f1) $f" >>"$WORK/acked"
      touch "$WORK/done.$w.$i"
    elif [ "$code" = 000 ]; then
      echo "$f" >>"$WORK/cut"
      return 0
    fi
    i=$((i + 1))
  done
}

for round in $(seq 1 "$ROUNDS"); do
  start_server
  pids=()
  for w in $(seq 0 $((INGESTERS - 1))); do
    ingest_loop "$w" $((w * PER)) "$URL" &
    pids+=($!)
  done
  # Kill somewhere between 0.3 and 1.5 s into the uploads.
  sleep "$(awk -v r="$RANDOM" 'BEGIN { printf "%.2f", 0.3 + 1.2 * r / 32768 }')"
  kill -9 "$PID"
  wait "$PID" 2>/dev/null || true
  PID=""
  for p in "${pids[@]}"; do wait "$p" || true; done
  printf 'round %d: %d acknowledged so far\n' "$round" "$(wc -l <"$WORK/acked")"
done

start_server
lost=0
while read -r id sha f; do
  rec="$(curl -s -o /dev/null -w '%{http_code}' "$URL/v1/shapes/$id")"
  got="$(curl -s "$URL/v1/shapes/$id/mesh" | sha256sum | cut -d' ' -f1)"
  sig="$(curl -s -o /dev/null -w '%{http_code}' "$URL/v1/shapes/$id/signature")"
  again="$(curl -s -H 'Content-Type: model/off' --data-binary "@$f" "$URL/v1/shapes" | jq -r .id)"
  if [ "$rec" != 200 ] || [ "$got" != "$sha" ] || [ "$sig" != 200 ] || [ "$again" != "$id" ]; then
    echo "LOST or damaged: $id (record $rec, bytes match $([ "$got" = "$sha" ] && echo yes || echo no), signature $sig, re-upload id $again)"
    lost=$((lost + 1))
  fi
done <"$WORK/acked"
stored="$(curl -s "$URL/v1/index" | jq .shapes)"
printf 'soak-kill: %d rounds, %d acknowledged, %d cut mid-request, %d stored after restart, %d lost\n' \
  "$ROUNDS" "$(wc -l <"$WORK/acked")" "$(wc -l <"$WORK/cut")" "$stored" "$lost"
[ "$lost" = 0 ]
