#!/usr/bin/env bash
# Run the real-time suites (system-tests: end to end, any plant, faults and crashes) RUNS
# times in a row while another process keeps one core busy, and stop at the first failure.
# This is how a real-time test earns trust on a 2-core machine: a flaky one shows here.
# Usage: bash tests/stress.sh [RUNS]   (default 5; uses stress-ng if present, else a busy loop)
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-5}
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/mfc-zenoh/target}"
cargo test -p system-tests --no-run --locked -q
if command -v stress-ng >/dev/null; then
  stress-ng --cpu 1 --timeout 3h >/dev/null 2>&1 &
else
  (while :; do :; done) &
fi
LOAD=$!
trap 'kill $LOAD 2>/dev/null || true' EXIT
for i in $(seq "$RUNS"); do
  start=$(date +%s)
  if cargo test -p system-tests --no-fail-fast --locked -q >"/tmp/mfc-stress-$i.log" 2>&1; then
    passed=$(awk '/^test result:/ {s += $4} END {print s+0}' "/tmp/mfc-stress-$i.log")
    echo "run $i/$RUNS: passed ($passed tests, $(( $(date +%s) - start )) s)"
  else
    echo "run $i/$RUNS: FAILED (log: /tmp/mfc-stress-$i.log)"
    grep -E "panicked|FAILED|failed" "/tmp/mfc-stress-$i.log" | head -20
    exit 1
  fi
done
echo "stress: $RUNS runs passed with one core kept busy"
