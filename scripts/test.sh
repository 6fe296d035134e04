#!/usr/bin/env bash
# Set up if needed, then run every check: ruff, mypy, import-linter and the test suite.
# --fast (first argument): the fast tier, every test but those marked slow (each over about a
# second), for the loop of a change; the full run is CI's. Further arguments go to pytest
# (`bash scripts/test.sh -k health`, `bash scripts/test.sh --fast -x`).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

tier=()
if [[ "${1:-}" == "--fast" ]]; then
    tier=(-m "not slow")
    shift
fi

bash scripts/setup.sh

step() { printf '\n== %s\n' "$*" >&2; }

step "ruff check"
.venv/bin/ruff check eyeserver tests clients
step "mypy (strict, eyeserver/ and the Python client)"
.venv/bin/mypy
.venv/bin/mypy --strict clients/python/src
step "import-linter (layers)"
.venv/bin/lint-imports
step "pytest"
# Any non-zero status fails the run, including 5 (no tests collected). The slowest tests are
# listed at the end: the run should stay near 15 minutes on 2 cores, and they are where it goes.
.venv/bin/pytest -q --durations=25 "${tier[@]}" "$@"
