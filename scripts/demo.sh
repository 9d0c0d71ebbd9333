#!/usr/bin/env bash
# The main job, end to end: build, start `shapeseek serve` on an embedded sled directory, ingest
# the mini benchmark over REST with curl, search every shape by id, and report how often the top
# hit is of the query's class. The server keeps running afterwards (Ctrl-C stops it) unless
# DEMO_EXIT=1.
#
#   scripts/demo.sh [DATA_DIR] [ADDR]      # defaults: ./shapeseek-data 127.0.0.1:8080
#
# Needs curl and python3 (for JSON). Loopback only.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA="${1:-./shapeseek-data}"
ADDR="${2:-127.0.0.1:8080}"
URL="http://$ADDR"
BENCH="../shared/bench/mini"
cargo build --release --bin shapeseek
BIN="${CARGO_TARGET_DIR:-$PWD/target}/release/shapeseek"
"$BIN" serve --data "$DATA" --addr "$ADDR" &
PID=$!
trap 'kill $PID 2>/dev/null || true; wait $PID 2>/dev/null || true' EXIT
for _ in $(seq 1 100); do curl -sf "$URL/readyz" >/dev/null && break; sleep 0.2; done
curl -sf "$URL/readyz" >/dev/null || { echo "server did not become ready on $URL"; exit 1; }
if [ ! -f "$BENCH/manifest.csv" ]; then
  echo "SKIPPED ingest: $BENCH not found; the server runs on $URL (see README for curl examples)"
else
  echo "ingesting $BENCH into $URL"
  tail -n +2 "$BENCH/manifest.csv" | while IFS=, read -r id path class _; do
    code=$(curl -s -o /dev/null -w '%{http_code}' -X POST --data-binary @"$BENCH/$path" \
      "$URL/v1/shapes?name=$id&tags=$class")
    echo "  $id -> HTTP $code"
  done
  python3 - "$URL" "$BENCH/manifest.csv" <<'PY'
import csv, json, sys, urllib.request
url, manifest = sys.argv[1], sys.argv[2]
cls = {r["id"]: r["class"] for r in csv.DictReader(open(manifest))}
def call(method, path, body=None):
    req = urllib.request.Request(url + path, method=method, data=body,
                                 headers={"content-type": "application/json"})
    with urllib.request.urlopen(req) as r:
        return json.load(r)
shapes, cursor = [], None
while True:
    page = call("GET", "/v1/shapes?limit=100" + (f"&cursor={cursor}" if cursor else ""))
    shapes += page["items"]
    cursor = page.get("next_cursor")
    if not cursor:
        break
good = 0
for s in shapes:
    hits = call("POST", "/v1/search", json.dumps({"id": s["id"], "top_k": 3}).encode())["hits"]
    top = hits[0]["name"] if hits else None
    ok = top is not None and cls.get(top) == cls.get(s["name"])
    good += ok
    print(f"  {s['name']:<22} top hits: {', '.join(h['name'] for h in hits)}{'' if ok else '   <-- other class'}")
print(f"top hit of the query's class for {good} of {len(shapes)} queries ({100.0 * good / max(1, len(shapes)):.1f}%)")
PY
fi
if [ "${DEMO_EXIT:-0}" = "1" ]; then exit 0; fi
echo "server running on $URL (data in $DATA); Ctrl-C to stop"
wait $PID
