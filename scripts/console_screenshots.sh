#!/usr/bin/env bash
# Renew the console's screenshots in docs/images/ (console-<view>.png): runs the browser tests
# (tests/test_console.py, Debian's chromium through Playwright) with EYESERVER_SCREENSHOTS set,
# which writes each view's screenshot there as well, reduced to a 256-colour PNG.
#   bash scripts/console_screenshots.sh [pytest options]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

EYESERVER_SCREENSHOTS="$PWD/docs/images" exec .venv/bin/python -m pytest -q \
    tests/test_console.py -k "not without_a_token and not ships_with_it and not whoami" "$@"
