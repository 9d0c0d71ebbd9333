#!/usr/bin/env bash
# Ingest throughput and search latency of a release `shapeseek serve` on 127.0.0.1.
#
#   scripts/load-test.sh [MESH_DIR] [INGEST_PARALLEL] [SEARCH_SECONDS]
#
# Ingests every mesh of MESH_DIR (default ../shared/bench/mini/meshes) with INGEST_PARALLEL
# concurrent uploads (curl), then runs `hey` (Debian package) for SEARCH_SECONDS against
# POST /v1/search by id (top_k 10) at concurrency 4. Bounded in count and time; loopback only.
set -euo pipefail
cd "$(dirname "$0")/.."
MESHES="${1:-../shared/bench/mini/meshes}"
PAR="${2:-2}"
SECS="${3:-10}"
TARGET="${CARGO_TARGET_DIR:-$PWD/target}"
command -v hey >/dev/null || { echo "hey not installed (apt-get install hey)"; exit 1; }
cargo build --quiet --release --bin shapeseek
DATA="$(mktemp -d)"
"$TARGET/release/shapeseek" serve --data "$DATA/index" --addr 127.0.0.1:0 --log-format json \
  >"$DATA/log" 2>&1 &
PID=$!
trap 'kill $PID 2>/dev/null || true; wait $PID 2>/dev/null || true; rm -rf "$DATA"' EXIT
for _ in $(seq 1 300); do
  ADDR="$(grep -o '"addr":"[^"]*"' "$DATA/log" | head -1 | cut -d'"' -f4 || true)"
  [ -n "${ADDR:-}" ] && break
  sleep 0.1
done
URL="http://$ADDR"
N=$(ls "$MESHES" | wc -l)
echo "ingesting $N meshes from $MESHES, $PAR at a time, into $URL"
START=$(date +%s.%N)
ls "$MESHES" | xargs -P "$PAR" -I{} sh -c \
  "curl -s -o /dev/null -w '%{http_code}\n' --max-time 600 -X POST --data-binary @'$MESHES/{}' '$URL/v1/shapes?name={}'" \
  > "$DATA/codes"
END=$(date +%s.%N)
echo "status codes: $(sort "$DATA/codes" | uniq -c | tr '\n' ' ')"
python3 -c "import sys; n=$N; t=$END-$START; print(f'ingest: {n} shapes in {t:.1f} s = {n/t:.2f} shapes/s')"
curl -s "$URL/metrics" | grep -E '^shapeseek_ingest_stage_seconds_(sum|count)' || true
ID=$(curl -s "$URL/v1/shapes?limit=1" | python3 -c 'import json,sys; print(json.load(sys.stdin)["items"][0]["id"])')
echo "search by id $ID for $SECS s, concurrency 4:"
hey -z "${SECS}s" -c 4 -m POST -T application/json -d "{\"id\":\"$ID\",\"top_k\":10}" "$URL/v1/search" \
  | sed -n '/Summary/,/Status code distribution/p;/\[200\]/p'
curl -s "$URL/v1/index" | python3 -c 'import json,sys; d=json.load(sys.stdin); print("index:", d["shapes"], "shapes, epoch", d["calibration_epoch"], "size", d["size_on_disk"], "bytes")'
