#!/usr/bin/env bash
# Slow and silent connections against a release `shapeseek serve` on 127.0.0.1 (loopback only).
#
#   scripts/slow-connections.sh [CONNECTIONS] [HEADER_TIMEOUT_SECS] [BODY_TIMEOUT_SECS]
#
# Opens CONNECTIONS (default 900) connections at once, a third of each kind: silent (nothing
# sent), an unfinished request head, and a complete head announcing a 1 MB body of which a
# byte is sent every second. The server runs with `max_connections` above CONNECTIONS (so the
# timeouts, not the cap, must close them), `header_read_timeout_secs` = HEADER_TIMEOUT_SECS
# (default 5) and `body_read_timeout_secs` = BODY_TIMEOUT_SECS (default 10). Meanwhile a probe
# sends GET /healthz every 100 ms on fresh connections. Prints, per kind, how many the server
# closed and when (max seconds after opening), how many slow bodies got 408, the probe's
# p50/p99/max latency and failures; exits 1 if a connection is still open at
# BODY_TIMEOUT_SECS + 10 s or a probe failed.
# CARGO_TARGET_DIR is honoured; the temporary directory is removed at exit.
set -euo pipefail
cd "$(dirname "$0")/.."
N="${1:-900}"
HT="${2:-5}"
BT="${3:-10}"
TARGET="${CARGO_TARGET_DIR:-$PWD/target}"
BIN="$TARGET/release/shapeseek"
cargo build --quiet --release --bin shapeseek
WORK="$(mktemp -d)"
export SHAPESEEK_MAX_CONNECTIONS=$((N + 100))
export SHAPESEEK_HEADER_READ_TIMEOUT_SECS="$HT"
export SHAPESEEK_BODY_READ_TIMEOUT_SECS="$BT"
ulimit -n $((N * 2 + 200)) 2>/dev/null || true
# shellcheck source=lib/test-server.sh
. scripts/lib/test-server.sh
start_test_server "$WORK"
for _ in $(seq 1 100); do curl -sf "$URL/readyz" >/dev/null && break; sleep 0.1; done
ADDR="${URL#http://}"
python3 - "$ADDR" "$N" "$HT" "$BT" <<'EOF'
import socket, sys, threading, time, selectors

host, port = sys.argv[1].rsplit(":", 1)
n, ht, bt = int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
kinds = ["silent", "unfinished head", "slow body"]
conns = []  # (kind, socket, opened_at)
for i in range(n):
    s = socket.create_connection((host, int(port)))
    kind = kinds[i % 3]
    if kind == "unfinished head":
        s.sendall(b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Le")
    elif kind == "slow body":
        s.sendall(b"POST /v1/shapes HTTP/1.1\r\nHost: x\r\nContent-Type: model/obj\r\n"
                  b"Content-Length: 1000000\r\n\r\nv")
    s.setblocking(False)
    conns.append([kind, s, time.monotonic(), None, b""])
opened = time.monotonic()

probe = []
probe_fail = []
stop = False
def prober():
    while not stop:
        t = time.monotonic()
        try:
            c = socket.create_connection((host, int(port)), timeout=5)
            c.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            data = b""
            while True:
                d = c.recv(4096)
                if not d:
                    break
                data += d
            c.close()
            if not data.startswith(b"HTTP/1.1 200"):
                probe_fail.append(data[:40])
            probe.append((time.monotonic() - t) * 1e3)
        except Exception as e:  # noqa: BLE001
            probe_fail.append(str(e))
        time.sleep(0.1)
th = threading.Thread(target=prober)
th.start()

sel = selectors.DefaultSelector()
for c in conns:
    sel.register(c[1], selectors.EVENT_READ, c)
deadline = opened + bt + 10
last_trickle = time.monotonic()
open_left = len(conns)
while open_left and time.monotonic() < deadline:
    for key, _ in sel.select(timeout=0.2):
        c = key.data
        try:
            d = c[1].recv(65536)
        except BlockingIOError:
            continue
        except ConnectionResetError:
            d = b""
        if d:
            c[4] += d
            continue
        c[3] = time.monotonic() - c[2]
        sel.unregister(c[1])
        c[1].close()
        open_left -= 1
    if time.monotonic() - last_trickle >= 1.0:
        last_trickle = time.monotonic()
        for c in conns:
            if c[0] == "slow body" and c[3] is None:
                try:
                    c[1].send(b" ")
                except OSError:
                    pass
stop = True
th.join()
bad = 0
for kind in kinds:
    ks = [c for c in conns if c[0] == kind]
    closed = [c for c in ks if c[3] is not None]
    got408 = sum(1 for c in ks if c[4].startswith(b"HTTP/1.1 408"))
    mx = max((c[3] for c in closed), default=float("nan"))
    print(f"{kind:16s}: {len(closed)}/{len(ks)} closed by the server, last after {mx:.1f} s"
          + (f", {got408} answered 408" if kind == "slow body" else ""))
    bad += len(ks) - len(closed)
probe.sort()
if probe:
    p = lambda q: probe[min(len(probe) - 1, int(q * len(probe)))]
    print(f"probe GET /healthz during the test: {len(probe)} ok, {len(probe_fail)} failed, "
          f"p50 {p(0.5):.1f} ms, p99 {p(0.99):.1f} ms, max {probe[-1]:.1f} ms")
if probe_fail:
    print("probe failures:", probe_fail[:5])
sys.exit(1 if bad or probe_fail else 0)
EOF
