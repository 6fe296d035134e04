#!/usr/bin/env bash
# Make .venv ready to run eyeserver and its tests; cheap when nothing changed.
#
# Creates .venv with a Python >= 3.11 if it is missing (set PYTHON to choose the interpreter),
# installs the Debian packages the project needs (scripts/system-packages.sh, as root), then
# runs `pip install -e '.[dev,basler,genicam]'` only when pyproject.toml, the repository's location,
# the venv's Python or the extras changed since the last successful install (recorded in
# .venv/.eyeserver-setup).
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

# The Debian packages of the GenICam driver (Aravis, its fake camera, and the headers PyGObject
# builds against): installed when run as root (CI, the room PC's installer), only checked
# otherwise. A root that cannot install them stops here; without root the venv goes without
# PyGObject and the GenICam tests skip, saying why.
extras="dev,basler"
if bash scripts/system-packages.sh --dev; then
    extras="dev,basler,genicam"
elif [[ "$(id -u)" -eq 0 ]]; then
    say "the system packages above could not be installed" && exit 1
else
    say "continuing without the genicam extra (PyGObject): the GenICam tests will skip"
fi

# What the installed state depends on: the project's metadata, where the repository is (an
# editable install points at it), which Python the venv has and which extras it gets.
wanted="$(
    {
        cat pyproject.toml clients/python/pyproject.toml
        pwd
        "$venv/bin/python" --version 2>&1
        echo "$extras"
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
# The daemon and the Python client (clients/python, whose tests run against the daemon).
if ! "$venv/bin/python" -m pip install -e ".[$extras]" -e ./clients/python \
    >"$venv/setup.log" 2>&1; then
    tail -n 60 "$venv/setup.log" >&2
    say "pip install failed; the whole log is in $venv/setup.log"
    exit 1
fi
printf '%s\n' "$wanted" >"$stamp"
say "done"
