# Sourced by the test scripts (contract-test.sh, client-test.sh): starts `"$BIN" serve` on a free
# 127.0.0.1 port with its index in DIR/index and its JSON log in DIR/server.log, stops it and
# removes DIR when the script exits, and sets PID and URL. SHAPESEEK_* settings come from the
# caller's environment (e.g. `SHAPESEEK_EIGENPAIRS=60 start_test_server "$DIR"`).
start_test_server() {
  TEST_SERVER_DIR="$1"
  local log="$1/server.log" addr=""
  "$BIN" serve --data "$1/index" --addr 127.0.0.1:0 --log-format json >"$log" 2>&1 &
  PID=$!
  trap 'kill "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; rm -rf "$TEST_SERVER_DIR"' EXIT
  for _ in $(seq 1 200); do
    addr="$(grep -o '"addr":"[^"]*"' "$log" | head -1 | cut -d'"' -f4 || true)"
    [ -n "$addr" ] && break
    kill -0 "$PID" 2>/dev/null || { cat "$log"; echo "server exited"; exit 1; }
    sleep 0.1
  done
  [ -n "$addr" ] || { cat "$log"; echo "server did not start"; exit 1; }
  URL="http://$addr"
}
