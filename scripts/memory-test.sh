#!/usr/bin/env bash
# Resident memory of a release `shapeseek serve` under concurrent maximum-size uploads
# (loopback only, bounded in time).
#
#   scripts/memory-test.sh [CONCURRENT] [UPLOAD_MIB]
#
# The server runs with its defaults (`max_body_bytes` 64 MiB, `max_inflight_body_bytes`
# 256 MiB, `workers` = cores). For each of three kinds — an OBJ of a 2 000-vertex mesh padded
# with comment lines, a glTF whose buffer is a data URI holding the same mesh and padding, and
# the OBJ again as the `file` part of a `multipart/form-data` body (as the web page and
# `ingest --url` send it; its parts are parsed by copying) — CONCURRENT (default 16) distinct
# uploads of UPLOAD_MIB (default 60) MiB are sent at once with curl. Prints the statuses, the server's peak resident set (VmHWM of /proc/PID/status) and
# its resident set (VmRSS) once the uploads are answered, per kind; the server is restarted
# between kinds so each peak is its own. Exits 1 if a peak exceeds BOUND_MIB or an answer is a
# 5xx other than 503. BOUND_MIB defaults to the bound documented in docs/reliability.md for
# the default limits: 64 + max_inflight_body_bytes (256) + heavy_threads × 2 × max_body_bytes
# (128 each) MiB, heavy_threads = max(1, min(⌊0.75 · cores⌋, cores − 1)).
# CARGO_TARGET_DIR is honoured (SHAPESEEK_BIN runs that binary instead of building); the
# temporary directory is removed at exit.
set -euo pipefail
cd "$(dirname "$0")/.."
C="${1:-16}"
MIB="${2:-60}"
CORES="$(nproc)"
HEAVY=$((CORES * 3 / 4)); [ "$HEAVY" -gt $((CORES - 1)) ] && HEAVY=$((CORES - 1)); [ "$HEAVY" -lt 1 ] && HEAVY=1
BOUND_MIB="${BOUND_MIB:-$((64 + 256 + HEAVY * 128))}"
TARGET="${CARGO_TARGET_DIR:-$PWD/target}"
if [ -n "${SHAPESEEK_BIN:-}" ]; then
  BIN="$SHAPESEEK_BIN" # another build, e.g. the code before the fix
else
  BIN="$TARGET/release/shapeseek"
  cargo build --quiet --release --bin shapeseek
fi
WORK="$(mktemp -d)"
PID=""
cleanup() {
  if [ -n "$PID" ]; then kill "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT
export SHAPESEEK_EIGENPAIRS="${SHAPESEEK_EIGENPAIRS:-60}"

start_server() {
  rm -rf "$WORK/index"
  "$BIN" serve --data "$WORK/index" --addr 127.0.0.1:0 --log-format json >"$WORK/log" 2>&1 &
  PID=$!
  ADDR=""
  for _ in $(seq 1 600); do
    ADDR="$(grep -o '"addr":"[^"]*"' "$WORK/log" | head -1 | cut -d'"' -f4 || true)"
    [ -n "$ADDR" ] && curl -sf "http://$ADDR/readyz" >/dev/null 2>&1 && break
    kill -0 "$PID" 2>/dev/null || { cat "$WORK/log"; exit 1; }
    sleep 0.1
  done
  URL="http://$ADDR"
}
stop_server() { kill "$PID"; wait "$PID" 2>/dev/null || true; PID=""; }
kib() { awk -v k="$1" '/^'"$1"':/ { print $2 }' "/proc/$PID/status"; }

"$BIN" bench meshes --out "$WORK/mesh" --count 1 --size 2000 >/dev/null
python3 - "$WORK" "$C" "$MIB" <<'EOF'
import base64, json, os, struct, sys
work, c, mib = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
size = mib << 20
off = open(os.path.join(work, "mesh", sorted(os.listdir(os.path.join(work, "mesh")))[0])).read().split()
nv, nf = int(off[1]), int(off[2])
vals = off[4:]
verts = [tuple(map(float, vals[3 * i:3 * i + 3])) for i in range(nv)]
rest = vals[3 * nv:]
faces = [tuple(map(int, rest[4 * i + 1:4 * i + 4])) for i in range(nf)]
for k in range(c):
    # OBJ: the mesh, then comment lines up to the size (distinct per upload).
    head = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in verts)
    head += "".join(f"f {a + 1} {b + 1} {d + 1}\n" for a, b, d in faces)
    line = f"# padding {k} " + "x" * 100 + "\n"
    n = (size - len(head)) // len(line)
    with open(os.path.join(work, f"pad-{k}.obj"), "w") as f:
        f.write(head)
        f.write(line * n)
    # glTF: one buffer (positions, indices, then zero padding) as a base64 data URI.
    pos = b"".join(struct.pack("<3f", *v) for v in verts)
    idx = b"".join(struct.pack("<3I", *t) for t in faces)
    lo = [min(v[i] for v in verts) for i in range(3)]
    hi = [max(v[i] for v in verts) for i in range(3)]
    raw_len = (size * 3 // 4) - 4096
    buf = pos + idx + bytes([k]) * (raw_len - len(pos) - len(idx))
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(buf),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(buf).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
                        {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx)}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": nv, "type": "VEC3",
                       "min": lo, "max": hi},
                      {"bufferView": 1, "componentType": 5125, "count": 3 * nf, "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0,
    }
    with open(os.path.join(work, f"pad-{k}.gltf"), "w") as f:
        json.dump(doc, f)
EOF

fail=0
for kind in obj gltf multipart; do
  start_server
  base="$(kib VmRSS)"
  pids=()
  for k in $(seq 0 $((C - 1))); do
    case "$kind" in
      obj) body=(-H "Content-Type: model/obj" --data-binary "@$WORK/pad-$k.obj") ;;
      gltf) body=(-H "Content-Type: model/gltf+json" --data-binary "@$WORK/pad-$k.gltf") ;;
      multipart) body=(-F "file=@$WORK/pad-$k.obj;type=model/obj") ;;
    esac
    curl -s -o /dev/null -w '%{http_code}\n' --max-time 300 "${body[@]}" "$URL/v1/shapes" \
      >"$WORK/status-$k" &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait "$p" || true; done
  statuses="$(cat "$WORK"/status-* | sort | uniq -c | awk '{ printf "%s×%s ", $1, $2 }')"
  hwm="$(kib VmHWM)"
  rss="$(kib VmRSS)"
  stored="$(curl -s "$URL/v1/shapes?limit=100" | jq '[.items[].bytes] | max // 0')"
  printf '%-4s: %d × %d MiB uploads at once: %s| resident before %d MiB, peak %d MiB, after %d MiB | largest stored original %s bytes\n' \
    "$kind" "$C" "$MIB" "$statuses" $((base / 1024)) $((hwm / 1024)) $((rss / 1024)) "$stored"
  if [ $((hwm / 1024)) -gt "$BOUND_MIB" ]; then echo "peak over the bound of $BOUND_MIB MiB"; fail=1; fi
  echo "      bound $BOUND_MIB MiB ($HEAVY heavy threads on $CORES cores)"
  if grep -qE '^5(0[0-2]|0[4-9]|[1-9][0-9])$' "$WORK"/status-*; then echo "a 5xx other than 503"; fail=1; fi
  stop_server
  rm -f "$WORK"/status-*
done
exit "$fail"
