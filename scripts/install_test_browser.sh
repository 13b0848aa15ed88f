#!/usr/bin/env bash
# A headless browser for tests/bags/report/test_pictures.py (it renders report.html to a PNG): installs
# Debian's chromium-headless-shell with apt-get when no chromium is on PATH, apt-get exists and
# we are root. Quiet; never fails the caller: without a browser that test skips, saying why.
set -uo pipefail
for b in chromium-headless-shell chromium chromium-browser google-chrome; do
  command -v "$b" >/dev/null 2>&1 && exit 0
done
if ! command -v apt-get >/dev/null 2>&1 || [ "$(id -u)" != 0 ]; then
  echo "note: no chromium-headless-shell (needs apt-get as root to install it); the report" \
       "rendering test will be skipped" >&2
  exit 0
fi
log=$(mktemp -t install_test_browser.XXXXXX)
export DEBIAN_FRONTEND=noninteractive
echo "installing chromium-headless-shell for the report rendering test (apt-get)" >&2
if ! apt-get install -y -qq --no-install-recommends chromium-headless-shell >"$log" 2>&1; then
  # an empty or stale package list: refresh it once and retry
  apt-get update -qq >>"$log" 2>&1
  if ! apt-get install -y -qq --no-install-recommends chromium-headless-shell >>"$log" 2>&1; then
    tail -n 5 "$log" >&2
    echo "note: installing chromium-headless-shell failed (log: $log); the report rendering" \
         "test will be skipped" >&2
    exit 0
  fi
fi
rm -f "$log"
