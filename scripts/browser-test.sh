#!/usr/bin/env bash
# Browser tests of the web viewer: playwright-core (npm, tests/browser) drives Debian's chromium
# headless against a live `shapeseek serve` (temporary data directory, free port, 127.0.0.1)
# holding the generated sample meshes; one sample is held out and uploaded as the query.
#
#   scripts/browser-test.sh                 # what CI runs
#   UPDATE_SCREENSHOTS=1 scripts/browser-test.sh   # also refresh docs/screenshots/*.png
#   SHAPESEEK_BIN=path/to/shapeseek scripts/browser-test.sh   # test a prebuilt binary
#
# Installs what is missing: chromium (apt-get) and the npm packages (npm ci). Also checks that
# rebuilding the viewer from web/package-lock.json reproduces the committed web/dist (the
# binary embeds web/dist). Prints "browser tests: N passed, M failed"; exits non-zero on failure.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
CHROMIUM="${CHROMIUM:-/usr/bin/chromium}"
if [ ! -x "$CHROMIUM" ]; then
  echo "installing chromium (apt-get)"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium fonts-dejavu-core >/dev/null
fi
command -v npm >/dev/null || {
  echo "installing nodejs and npm (apt-get)"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nodejs npm >/dev/null
}

echo "== web/dist is reproducible from web/package-lock.json"
CHECK="$(mktemp -d)"
(cd web && npm ci --no-audit --no-fund --loglevel=error && WEB_DIST_OUT="$CHECK" npm run --silent build)
# Compared, not rebuilt in place: rewriting web/dist would make cargo rebuild the binary.
if ! diff -r "$CHECK" web/dist; then
  echo "web/dist differs from a fresh build: run 'npm run build' in web/ and commit web/dist"
  exit 1
fi
rm -rf "$CHECK"

echo "== browser tests"
(cd tests/browser && npm ci --no-audit --no-fund --loglevel=error)
# SHAPESEEK_BIN: use that binary instead of building one.
BIN="${SHAPESEEK_BIN:-}"
if [ -z "$BIN" ]; then
  cargo build --quiet --release --bin shapeseek
  BIN="$TARGET/release/shapeseek"
fi
WORK="$(mktemp -d)"
LOG="$WORK/server.log"
"$BIN" samples --out "$WORK/samples" >/dev/null
HOLD_OUT="quadruped-iso2"
"$BIN" serve --data "$WORK/index" --addr 127.0.0.1:0 --log-format json >"$LOG" 2>&1 &
PID=$!
cleanup() { kill "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; rm -rf "$WORK"; }
trap cleanup EXIT
ADDR=""
for _ in $(seq 1 300); do
  ADDR="$(grep -o '"addr":"[^"]*"' "$LOG" | head -1 | cut -d'"' -f4 || true)"
  [ -n "$ADDR" ] && break
  kill -0 "$PID" 2>/dev/null || { cat "$LOG"; echo "server exited"; exit 1; }
  sleep 0.1
done
[ -n "$ADDR" ] || { cat "$LOG"; echo "server did not report its address"; exit 1; }
URL="http://$ADDR"
echo "server on $URL; ingesting the samples except $HOLD_OUT"
tail -n +2 "$WORK/samples/manifest.csv" | grep -v "^$HOLD_OUT," \
  | xargs -P 2 -L 1 sh -c 'IFS=,; set -- $0; code=$(curl -s -o /dev/null -w "%{http_code}" -X POST \
      --data-binary @"'"$WORK/samples"'/$2" "'"$URL"'/v1/shapes?name=$1&tags=$3"); \
      case $code in 200|201) ;; *) echo "ingest $1: HTTP $code"; exit 255;; esac'
SHOTS="$WORK/screenshots"
[ "${UPDATE_SCREENSHOTS:-0}" = "1" ] && SHOTS="$ROOT/docs/screenshots"
set +e
(cd tests/browser && SHAPESEEK_URL="$URL" SAMPLES_DIR="$WORK/samples" HOLD_OUT="$HOLD_OUT" \
  SCREENSHOT_DIR="$SHOTS" CHROMIUM="$CHROMIUM" \
  node --test --test-concurrency=1 --test-reporter=spec viewer.test.mjs) 2>&1 | tee "$WORK/out.txt"
STATUS=${PIPESTATUS[0]}
set -e
PASS=$(grep -Eo '^ℹ pass [0-9]+' "$WORK/out.txt" | grep -Eo '[0-9]+' || echo 0)
FAIL=$(grep -Eo '^ℹ fail [0-9]+' "$WORK/out.txt" | grep -Eo '[0-9]+' || echo 1)
echo "browser tests: $PASS passed, $FAIL failed"
if [ "$STATUS" -ne 0 ] || [ "$FAIL" -ne 0 ] || [ "$PASS" -eq 0 ]; then exit 1; fi
