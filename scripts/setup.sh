#!/usr/bin/env bash
# Make .venv ready to run eyeserver and its tests; cheap when nothing changed.
#
# Creates .venv with a Python >= 3.11 if it is missing (set PYTHON to choose the interpreter),
# then runs `pip install -e '.[dev]'` only when pyproject.toml, the repository's location or the
# venv's Python changed since the last successful install (recorded in .venv/.eyeserver-setup).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

venv=.venv
stamp="$venv/.eyeserver-setup"

say() { printf 'setup: %s\n' "$*" >&2; }

is_recent_python() {
    "$1" -c 'import sys; sys.exit(sys.version_info < (3, 11))' >/dev/null 2>&1
}

if [[ ! -x "$venv/bin/python" ]] || ! is_recent_python "$venv/bin/python"; then
    if [[ -e "$venv" ]]; then
        say "$venv exists but has no working Python >= 3.11; remove it and run again" && exit 1
    fi
    python=""
    for candidate in "${PYTHON:-}" python3 python3.13 python3.12 python3.11; do
        if [[ -n "$candidate" ]] && command -v "$candidate" >/dev/null \
            && is_recent_python "$candidate"; then
            python="$candidate"
            break
        fi
    done
    if [[ -z "$python" ]]; then
        say "no Python >= 3.11 found (set PYTHON=/path/to/python3.11 or newer)" && exit 1
    fi
    say "creating $venv with $("$python" --version 2>&1)"
    "$python" -m venv "$venv"
fi

# What the installed state depends on: the project's metadata, where the repository is (an
# editable install points at it) and which Python the venv has.
wanted="$(
    {
        cat pyproject.toml
        pwd
        "$venv/bin/python" --version 2>&1
    } | sha256sum | cut -d' ' -f1
)"
if [[ -f "$stamp" && "$(cat "$stamp")" == "$wanted" ]]; then
    exit 0
fi

say "installing eyeserver and its development tools into $venv (log: $venv/setup.log)"
export PIP_DISABLE_PIP_VERSION_CHECK=1
# OpenCV's plain and contrib wheels share the cv2 package and must never be installed together:
# a venv made before the project moved to contrib loses the plain one (and a contrib left
# broken by removing it) before the install.
if "$venv/bin/python" -m pip show opencv-python-headless >/dev/null 2>&1; then
    say "replacing opencv-python-headless by opencv-contrib-python-headless"
    "$venv/bin/python" -m pip uninstall -y opencv-python-headless \
        opencv-contrib-python-headless >"$venv/setup.log" 2>&1
fi
# The build backend's chatter goes to the log; it is shown only when the install fails.
if ! "$venv/bin/python" -m pip install -e '.[dev]' >"$venv/setup.log" 2>&1; then
    tail -n 60 "$venv/setup.log" >&2
    say "pip install failed; the whole log is in $venv/setup.log"
    exit 1
fi
printf '%s\n' "$wanted" >"$stamp"
say "done"
