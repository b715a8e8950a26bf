#!/usr/bin/env bash
# Debian's chromium for tests/test_html_report.py (Playwright drives it; `playwright
# install` downloads are never used). Installs only when missing and only as root
# (apt-get update, then apt-get install chromium); otherwise it says so and the browser
# tests skip with that reason. When apt-get cannot reach its archive (an offline
# machine) it fails with one line naming what is missing.
set -euo pipefail
CHROMIUM="${DVLA_CHROMIUM:-/usr/bin/chromium}"  # the browser the tests drive
if [ -x "$CHROMIUM" ]; then
    exit 0
fi
if [ "$(id -u)" != "0" ]; then
    echo "ensure_chromium: $CHROMIUM is missing and this is not root; the HTML browser tests will skip" >&2
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
log="$(mktemp)"
trap 'rm -f "$log"' EXIT
if ! { apt-get update -qq && apt-get install -y -qq chromium; } >"$log" 2>&1; then
    last="$(grep -v '^\s*$' "$log" | tail -n 1)"
    echo "ensure_chromium: $CHROMIUM is missing and apt-get could not install Debian's chromium (offline, or no apt archive reachable?): ${last:-no message}; install chromium, or run the tests without it (the HTML browser tests then fail)" >&2
    exit 1
fi
test -x "$CHROMIUM"
