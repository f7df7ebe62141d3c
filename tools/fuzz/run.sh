#!/usr/bin/env bash
# The long schemathesis run against a live server started as the README says (make serve's command),
# with the hooks and schemathesis.toml of the bounded test in `make test`.
#
#   tools/fuzz/run.sh [EXAMPLES_PER_OPERATION] [extra schemathesis options...]
#
# Prints schemathesis' summary (cases generated / passed, failures by check) and leaves its NDJSON and
# JUnit reports and the server log under ${FUZZ_DIR:-/tmp/svrnet-fuzz}. Exit status: schemathesis'.
set -euo pipefail
cd "$(dirname "$0")/../.."
EXAMPLES="${1:-2500}"; shift || true
OUT="${FUZZ_DIR:-/tmp/svrnet-fuzz}"; mkdir -p "$OUT"
PORT="${SVRNET_PORT:-8765}"
PY=.venv/bin/python
SVRNET_PORT="$PORT" SVRNET_DATA_DIR="$OUT/data" SVRNET_MAX_CONCURRENT="${SVRNET_MAX_CONCURRENT:-8}" \
  setsid "$PY" -c "from service.main import run; run()" >"$OUT/server.log" 2>&1 &
SERVER=$!
trap 'kill -TERM "$SERVER" 2>/dev/null; wait "$SERVER" 2>/dev/null || true' EXIT
for _ in $(seq 120); do curl -sf "http://127.0.0.1:$PORT/readyz" >/dev/null && break; sleep 1; done
START=$(date +%s)
set +e
SCHEMATHESIS_HOOKS=tools.fuzz.hooks .venv/bin/schemathesis run "http://127.0.0.1:$PORT/openapi.json" \
  --checks all --max-examples "$EXAMPLES" --workers "${WORKERS:-2}" --request-timeout 60 \
  --suppress-health-check all \
  --report junit,ndjson --report-dir "$OUT" "$@" | tee "$OUT/summary.txt" | grep -v '^    curl'
STATUS=${PIPESTATUS[0]}
set -e
echo "wall time: $(( $(date +%s) - START )) s; server alive: $(kill -0 "$SERVER" 2>/dev/null && echo yes || echo no);" \
     "5xx in server log: $(grep -c '"status": 5' "$OUT/server.log" || true)"
exit "$STATUS"
