#!/usr/bin/env bash
# Issue 11, findings 4 and 5, from outside the process: starts a server on 127.0.0.1 (free
# port, temporary data directory) and runs scripts/degenerate-probe.py against it (uploads
# that cannot be a shape or whose declared counts disagree with their data must be refused;
# two consistent controls must be stored). Exit status: the probe's.
#
#   bash scripts/degenerate-test.sh
#
# CARGO_TARGET_DIR is honoured; the temporary directory is removed at exit.
set -euo pipefail
cd "$(dirname "$0")/.."
TARGET="${CARGO_TARGET_DIR:-$PWD/target}"
cargo build --quiet --release --bin shapeseek
BIN="$TARGET/release/shapeseek"
DATA="$(mktemp -d)"
. scripts/lib/test-server.sh
start_test_server "$DATA"
python3 scripts/degenerate-probe.py "$URL"
