#!/usr/bin/env bash
# Generated-client test: a Python client generated from the served /openapi.yaml drives the API.
#
#   scripts/client-test.sh      # builds the binary, starts a server, generates, drives
#
# 1. builds `shapeseek`, starts `shapeseek serve` on a free 127.0.0.1 port with a temp data dir;
# 2. downloads /openapi.yaml from it; checks that PyYAML (YAML 1.1) and ruamel.yaml (YAML 1.2)
#    read the same document and that openapi-spec-validator accepts it;
# 3. generates a client with openapi-python-client and FAILS on any generator warning;
# 4. generates pydantic models with datamodel-code-generator (no --strict-nullable) and checks
#    that they accept a hit whose score is null;
# 5. tests/client/drive.py drives ingest (raw, multipart), list, get, mesh download, signature,
#    search (by id, by upload, with stages), delete and error cases through that client alone and
#    prints `N passed, M failed`.
#
# Env: CARGO_TARGET_DIR (default ./target); the pinned tools (tests/client/requirements.txt) are
# installed from PyPI into $CARGO_TARGET_DIR/client-venv (re-installed when the file changes).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
TARGET="${CARGO_TARGET_DIR:-$PWD/target}"
VENV="$TARGET/client-venv"
REQ="$ROOT/tests/client/requirements.txt"
STAMP="$VENV/.requirements.sha256"
want="$(sha256sum "$REQ" | cut -d' ' -f1)"
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$STAMP" 2>/dev/null)" != "$want" ]; then
  rm -rf "$VENV"
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install -q --disable-pip-version-check -r "$REQ"
  echo "$want" >"$STAMP"
fi
# The generator's post hooks call `ruff` (pinned in the requirements): it must be on PATH.
export PATH="$VENV/bin:$PATH"
PY="$VENV/bin/python"

cargo build --quiet --release --bin shapeseek
BIN="$TARGET/release/shapeseek"
WORK="$(mktemp -d)"
# shellcheck source=scripts/lib/test-server.sh
. scripts/lib/test-server.sh
SHAPESEEK_EIGENPAIRS=60 SHAPESEEK_MAX_VERTICES=20000 start_test_server "$WORK"
echo "== server at $URL"

SPEC="$WORK/openapi.yaml"
curl -sf -o "$SPEC" "$URL/openapi.yaml"

echo "== YAML 1.1 and 1.2 loaders read the same document"
"$PY" - "$SPEC" <<'EOF'
import json, sys
import yaml
from ruamel.yaml import YAML
text = open(sys.argv[1], encoding="utf-8").read()
a = yaml.safe_load(text)
b = YAML(typ="safe", pure=True).load(text)
if json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
    def diff(x, y, p="$"):
        if type(x) is not type(y) or (not isinstance(x, (dict, list)) and x != y):
            print(f"  {p}: PyYAML {x!r} / ruamel {y!r}")
        elif isinstance(x, dict):
            for k in sorted(set(map(str, x)) | set(map(str, y))):
                diff(x.get(k), y.get(k), f"{p}.{k}")
        elif isinstance(x, list):
            for i, (u, v) in enumerate(zip(x, y)):
                diff(u, v, f"{p}[{i}]")
    diff(a, b)
    sys.exit("the YAML 1.1 and YAML 1.2 readings differ")
print("same document")
EOF

echo "== openapi-spec-validator"
"$VENV/bin/openapi-spec-validator" "$SPEC"

echo "== openapi-python-client $("$VENV/bin/openapi-python-client" --version 2>&1 | tail -1)"
GEN="$WORK/gen"
mkdir -p "$GEN"
set +e
"$VENV/bin/openapi-python-client" generate --path "$SPEC" --output-path "$GEN/shapeseek_client" \
  --meta none >"$WORK/generate.log" 2>&1
rc=$?
set -e
cat "$WORK/generate.log"
# The generator reports problems as "Warning(s) encountered", "WARNING ...", "Unable to ...",
# "Error(s) encountered" or a skipped post hook; any of them fails the test.
warnings="$(grep -v '^Generating ' "$WORK/generate.log" |
  grep -ciE 'warning|error|unable|skipping|not in path|cannot' || true)"
echo "generator: exit $rc, $warnings warning line(s)"
if [ "$rc" -ne 0 ] || [ "$warnings" -ne 0 ]; then
  echo "FAILED: the generator did not produce a clean client"
  exit 1
fi

echo "== datamodel-code-generator: pydantic models accept a null score without --strict-nullable"
"$VENV/bin/datamodel-codegen" --input "$SPEC" --input-file-type openapi \
  --output-model-type pydantic_v2.BaseModel --output "$GEN/models_pydantic.py" 2>"$WORK/dmcg.log" ||
  { cat "$WORK/dmcg.log"; echo "FAILED: datamodel-codegen"; exit 1; }
"$PY" - "$GEN" <<'EOF'
import sys
sys.path.insert(0, sys.argv[1])
import models_pydantic as m
hit = m.Hit.model_validate({"id": "0123456789abcdef", "name": "x", "score": None, "rank": 1,
                            "calibration_epoch": 1, "stage_scores": [None, 0.5]})
assert hit.score is None and hit.stage_scores == [None, 0.5]
print("a hit with score null validates")
EOF

echo "== driving the API through the generated client"
"$PY" "$ROOT/tests/client/drive.py" --url "$URL" --client-dir "$GEN" --spec "$SPEC"
