#!/usr/bin/env bash
# Set up if needed, then run every check: ruff, mypy, import-linter and the test suite.
# Extra arguments go to pytest (`bash scripts/test.sh -k health`).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

bash scripts/setup.sh

step() { printf '\n== %s\n' "$*" >&2; }

step "ruff check"
.venv/bin/ruff check eyeserver tests
step "mypy (strict, eyeserver/)"
.venv/bin/mypy
step "import-linter (layers)"
.venv/bin/lint-imports
step "pytest"
# Any non-zero status fails the run, including 5 (no tests collected).
.venv/bin/pytest -q "$@"
