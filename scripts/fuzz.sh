#!/usr/bin/env bash
# Runs every reader fuzz target (fuzz/fuzz_targets/*.rs) for SECONDS each (default 60) with
# cargo-fuzz, each corpus seeded with one small valid file of its format.
#
#   scripts/fuzz.sh [SECONDS]
#
# Needs cargo-fuzz (`cargo install cargo-fuzz`) and a C++ compiler. cargo-fuzz uses nightly-only
# compiler flags (-Zsanitizer, -Cpasses=sancov-module): on a stable toolchain this script sets
# RUSTC_BOOTSTRAP=1, which unlocks them. Findings land in fuzz/artifacts/<target>/; the script
# exits non-zero if any target found a crash, leak, timeout or out-of-memory input.
set -euo pipefail
secs="${1:-60}"
cd "$(dirname "$0")/../fuzz"
if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "cargo-fuzz is not installed: cargo install cargo-fuzz" >&2
    exit 2
fi
if ! rustc --version | grep -q nightly; then
    export RUSTC_BOOTSTRAP=1
fi
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}"
seed() { [ -n "$(ls -A "corpus/$1" 2>/dev/null)" ] || printf "$2" > "corpus/$1/seed"; }
mkdir -p corpus/read_obj corpus/read_off corpus/read_ply corpus/read_stl corpus/read_gltf
seed read_obj 'o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1 # c\nf 1 2 3\ng b\nf 1/1 3//2 -1 2\n'
seed read_off 'OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n4 0 2 3 1\n'
seed read_ply 'ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n4 0 2 3 1\n'
seed read_stl 'solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n'
seed read_gltf '{"asset":{"version":"2.0"},"buffers":[{"byteLength":48,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAAAAAAAAAAAAAAAIA/"}],"bufferViews":[{"buffer":0,"byteLength":48}],"accessors":[{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3"}],"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],"nodes":[{"mesh":0}]}'
status=0
for src in fuzz_targets/*.rs; do
    t="$(basename "$src" .rs)"
    mkdir -p "corpus/$t"
    echo "== $t: ${secs}s"
    # -rss_limit_mb bounds memory, -timeout flags any single input slower than 10 s.
    if ! cargo fuzz run "$t" -- -max_total_time="$secs" -rss_limit_mb=2048 -timeout=10 \
        -max_len=65536 2>&1 | tee "/tmp/fuzz-$t.log" | grep -E "^#[0-9]+.*(DONE|pulse)|ERROR|SUMMARY|panicked"; then
        :
    fi
    if grep -qE "ERROR: libFuzzer|SUMMARY: .*Sanitizer|panicked at" "/tmp/fuzz-$t.log"; then
        echo "!! $t found a failing input (see fuzz/artifacts/$t/ and /tmp/fuzz-$t.log)" >&2
        status=1
    fi
done
exit "$status"
