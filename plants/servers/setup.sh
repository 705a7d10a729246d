#!/usr/bin/env bash
# The venv of the plant servers (plants/servers/*.py): the Python client's venv
# (clients/python/setup.sh makes it) with the pinned servers of requirements.txt.
# Idempotent and quiet on success; the last line printed is the venv's python.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
py="$(bash "$here/../../clients/python/setup.sh" | tail -n 1)"
pinned() {
    "$py" - "$here/requirements.txt" <<'PY'
import sys
from importlib.metadata import PackageNotFoundError, version

for line in open(sys.argv[1]):
    name, _, want = line.split("#", 1)[0].strip().partition("==")
    if not name:
        continue
    try:
        if version(name.strip()) != want.strip():
            sys.exit(1)
    except PackageNotFoundError:
        sys.exit(1)
PY
}
if ! pinned; then
    log="$(mktemp)"
    if ! "$py" -m pip install --disable-pip-version-check -q -r "$here/requirements.txt" >"$log" 2>&1; then
        cat "$log" >&2
        rm -f "$log"
        echo "setup.sh: pip install of the plant servers failed" >&2
        exit 1
    fi
    rm -f "$log"
fi
echo "$py"
