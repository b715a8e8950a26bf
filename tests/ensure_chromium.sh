#!/usr/bin/env bash
# Debian's chromium for tests/test_html_report.py (Playwright drives it; `playwright
# install` downloads are never used). Installs only when missing and only as root;
# otherwise it says so and the browser tests skip with that reason.
set -euo pipefail
if [ -x /usr/bin/chromium ]; then
    exit 0
fi
if [ "$(id -u)" != "0" ]; then
    echo "ensure_chromium: /usr/bin/chromium is missing and this is not root; the HTML browser tests will skip" >&2
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq chromium >/dev/null
test -x /usr/bin/chromium
