#!/usr/bin/env bash
# Load figures of a release `shapeseek serve` on 127.0.0.1 (loopback only, bounded in time).
#
#   scripts/load-test.sh ingest [MESH_DIR] [PARALLEL]
#       Ingest throughput: uploads every mesh of MESH_DIR (default: 20 generated bumpy tori of
#       10 000 vertices, `shapeseek bench meshes`) with PARALLEL (default 2) concurrent curl
#       uploads into an empty index; prints shapes/s and the server's per-stage ingest times.
#
#   scripts/load-test.sh search [N|MESH_DIR] [REQUESTS] [CONCURRENCY] [RERANK_JSON]
#       Search latency: writes N (default 100000) synthetic shapes (`shapeseek bench populate`)
#       into a fresh index (or, given a directory, ingests its meshes over HTTP, 2 at a time),
#       starts the server on it, then runs `hey` (Debian package) with
#       REQUESTS (default 200) POST /v1/search by id (top_k 10) for each of 8 query ids at
#       CONCURRENCY (default 1) and prints p50/p90/p99 over all requests. With RERANK_JSON
#       (e.g. '[{"stage":"spectral_gw","shortlist":50}]') the shapes get re-ranking payloads
#       and every search carries those stages.
#
# The server's settings come from the environment as usual (e.g. SHAPESEEK_HEAVY_SHARE=1 gives
# ingest and GW stages every worker, SHAPESEEK_HEAVY_BORROW=false keeps them on the heavy lane's
# threads even on an idle server; docs/reliability.md); the first line printed says how many
# threads the heavy lane has. The temporary index is removed at exit. CARGO_TARGET_DIR is
# honoured.
set -euo pipefail
cd "$(dirname "$0")/.."
MODE="${1:-}"
TARGET="${CARGO_TARGET_DIR:-$PWD/target}"
BIN="$TARGET/release/shapeseek"
case "$MODE" in
  ingest|search) ;;
  *) sed -n '2,22p' "$0"; exit 2 ;;
esac
command -v hey >/dev/null || { echo "hey not installed (apt-get install hey)"; exit 1; }
cargo build --quiet --release --bin shapeseek
WORK="$(mktemp -d)"
PID=""
cleanup() {
  if [ -n "$PID" ]; then kill "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT

start_server() {
  "$BIN" serve --data "$WORK/index" --addr 127.0.0.1:0 --log-format json >"$WORK/log" 2>&1 &
  PID=$!
  ADDR=""
  for _ in $(seq 1 6000); do
    ADDR="$(grep -o '"addr":"[^"]*"' "$WORK/log" | head -1 | cut -d'"' -f4 || true)"
    [ -n "$ADDR" ] && curl -sf "http://$ADDR/readyz" >/dev/null 2>&1 && break
    kill -0 "$PID" 2>/dev/null || { cat "$WORK/log"; exit 1; }
    sleep 0.1
  done
  URL="http://$ADDR"
  echo "server ready at $URL: $(curl -s "$URL/v1/index" | python3 -c '
import json, sys
q = json.load(sys.stdin)["queue"]
print(q["workers"], "workers,", q["heavy_threads"], "of them for analyses and GW stages (heavy_share);",
      q.get("borrow_threads", q["heavy_threads"]), "for one that starts on an idle server (heavy_borrow)")')"
}

if [ "$MODE" = ingest ]; then
  MESHES="${2:-}"
  PAR="${3:-2}"
  if [ -z "$MESHES" ]; then
    MESHES="$WORK/meshes"
    "$BIN" bench meshes --out "$MESHES" --count 20 --size 10000
  fi
  start_server
  N=$(ls "$MESHES" | wc -l)
  echo "ingesting $N meshes from $MESHES, $PAR at a time"
  START=$(date +%s.%N)
  ls "$MESHES" | xargs -P "$PAR" -I{} sh -c \
    "curl -s -o /dev/null -w '%{http_code}\n' --max-time 600 -X POST --data-binary @'$MESHES/{}' '$URL/v1/shapes?name={}'" \
    > "$WORK/codes"
  END=$(date +%s.%N)
  echo "status codes: $(sort "$WORK/codes" | uniq -c | tr '\n' ' ')"
  python3 -c "n=$N; t=$END-$START; print(f'ingest: {n} shapes in {t:.1f} s = {n/t:.2f} shapes/s')"
  curl -s "$URL/metrics" | grep -E '^shapeseek_ingest_stage_seconds_(sum|count)' || true
  echo "load average: $(cut -d' ' -f1-3 /proc/loadavg)"
  exit 0
fi

N="${2:-100000}"
REQ="${3:-200}"
CONC="${4:-1}"
RERANK="${5:-}"
EXTRA="${RERANK:+,\"rerank\":$RERANK}"
if [ -d "$N" ]; then
  start_server
  ls "$N" | xargs -P 2 -I{} sh -c \
    "curl -s -o /dev/null -w '%{http_code}\n' --max-time 600 -X POST --data-binary @'$N/{}' '$URL/v1/shapes?name={}'" \
    > "$WORK/codes"
  echo "ingested $(ls "$N" | wc -l) meshes from $N: $(sort "$WORK/codes" | uniq -c | tr '\n' ' ')"
  N=$(ls "$N" | wc -l)
else
  "$BIN" bench populate --data "$WORK/index" --count "$N" ${RERANK:+--payloads}
  start_server
fi
IDS=$(curl -s "$URL/v1/shapes?limit=100" | python3 -c '
import json, sys
items = json.load(sys.stdin)["items"]
print(" ".join(items[i]["id"] for i in range(0, len(items), max(1, len(items) // 8))[:8]))')
echo "search by id: $REQ requests for each of 8 ids, concurrency $CONC, index of $N shapes${RERANK:+, rerank $RERANK}"
: > "$WORK/times.csv"
for ID in $IDS; do
  hey -n "$REQ" -c "$CONC" -o csv -m POST -T application/json \
    -d "{\"id\":\"$ID\",\"top_k\":10$EXTRA}" "$URL/v1/search" | tail -n +2 >> "$WORK/times.csv"
done
python3 - "$WORK/times.csv" <<'EOF'
import sys
rows = [l.split(",") for l in open(sys.argv[1]) if l.strip()]
codes = {}
for r in rows:
    codes[r[6]] = codes.get(r[6], 0) + 1
t = sorted(float(r[0]) * 1e3 for r in rows)
pct = lambda p: t[min(len(t) - 1, round((len(t) - 1) * p))]
print(f"requests {len(t)}, status {codes}")
print(f"latency ms: p50 {pct(0.5):.1f}  p90 {pct(0.9):.1f}  p99 {pct(0.99):.1f}  max {t[-1]:.1f}")
EOF
curl -s "$URL/metrics" | grep -E '^shapeseek_index_shapes' || true
echo "load average: $(cut -d' ' -f1-3 /proc/loadavg)"
