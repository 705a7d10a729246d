#!/usr/bin/env bash
# Set up the browser test of the console (tests/tests/console.rs): Debian's Chromium and
# playwright-core, pinned, from npm. Playwright only drives the system's Chromium
# (`executablePath`); it never downloads a browser of its own (no `playwright install`:
# this project's machines reach package registries, not browser builds).
#
#   bash tests/browser/setup.sh              # from any directory
#   MFC_NODE_PREFIX=/some/where setup.sh     # another place for node_modules
#
# Idempotent and quiet on success. It prints three lines, `KEY=VALUE`:
#   chromium=/usr/bin/chromium
#   node=/usr/bin/node
#   prefix=$HOME/.cache/mfc-zenoh/node        (holds node_modules/playwright-core)
set -euo pipefail

PLAYWRIGHT_CORE=1.64.1
prefix="${MFC_NODE_PREFIX:-$HOME/.cache/mfc-zenoh/node}"
chromium="${MFC_CHROMIUM:-/usr/bin/chromium}"

fail() {
    echo "setup.sh: $*" >&2
    exit 1
}

apt_install() {
    [ "$(id -u)" = 0 ] || fail "$1 is missing and this is not root: apt-get install $*"
    log="$(mktemp)"
    if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@"; } >"$log" 2>&1; then
        cat "$log" >&2
        rm -f "$log"
        fail "apt-get install $* failed"
    fi
    rm -f "$log"
}

# 1. Debian's Chromium (and Node.js with npm, which this project's machines have, but a
#    bare Debian does not).
[ -x "$chromium" ] || apt_install chromium
[ -x "$chromium" ] || fail "no $chromium after installing Debian's chromium"
command -v node >/dev/null 2>&1 && command -v npm >/dev/null 2>&1 || apt_install nodejs npm
node="$(command -v node)"

# 2. playwright-core at the pinned version (installed only if missing or another version).
have() {
    "$node" -e 'process.stdout.write(require(process.argv[1]).version)' \
        "$prefix/node_modules/playwright-core/package.json" 2>/dev/null || true
}
if [ "$(have)" != "$PLAYWRIGHT_CORE" ]; then
    mkdir -p "$prefix"
    log="$(mktemp)"
    # --ignore-scripts: nothing runs at install time (playwright-core has no install script,
    # and nothing else may fetch a browser).
    if ! PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 npm install --prefix "$prefix" --no-audit --no-fund \
        --ignore-scripts --save-exact "playwright-core@$PLAYWRIGHT_CORE" >"$log" 2>&1; then
        cat "$log" >&2
        rm -f "$log"
        fail "npm install playwright-core@$PLAYWRIGHT_CORE failed (it needs the npm registry the first time)"
    fi
    rm -f "$log"
    [ "$(have)" = "$PLAYWRIGHT_CORE" ] || fail "playwright-core $PLAYWRIGHT_CORE is still not in $prefix"
fi

# 3. A smoke check, so that a broken install is reported here and not by the test.
"$chromium" --version >/dev/null 2>&1 || fail "$chromium does not run"

echo "chromium=$chromium"
echo "node=$node"
echo "prefix=$prefix"
