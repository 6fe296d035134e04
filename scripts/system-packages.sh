#!/usr/bin/env bash
# Install the Debian packages eyeserver needs besides what pip installs; cheap when done.
#
# Aravis (the GenICam camera library behind the GenicamCamera driver) comes from Debian, with its
# fake GigE Vision camera that the driver's tests run against; PyGObject, which the venv gets
# from PyPI (the `genicam` extra), is built against Debian's GObject introspection and cairo
# headers, with a C compiler.
#
#   gir1.2-aravis-0.8        Aravis 0.8 and its GObject introspection data (what `gi` loads)
#   aravis-tools             arv-fake-gv-camera-0.8, the fake camera of tests/test_driver_genicam.py
#   libgirepository1.0-dev   PyGObject's build: girepository 1.x (bookworm; PyGObject < 3.51)
#   libcairo2-dev            PyGObject's dependency pycairo's build
#   pkg-config, gcc, libc6-dev   what those builds call
#
# With --dev (scripts/setup.sh: a development machine or CI), also what only the tests need:
#
#   chromium                 the headless browser tests/test_console.py drives (Playwright)
#   dicom3tools              dciodvfy, which tests/test_dicom.py checks every exported DICOM
#                            object with
#
# Run as root (CI and the development machines are); without root it only checks, and fails
# naming what is missing. Nothing is done when every package is installed already.
set -euo pipefail

packages=(
    gir1.2-aravis-0.8
    aravis-tools
    libgirepository1.0-dev
    libcairo2-dev
    pkg-config
    gcc
    libc6-dev
)
if [[ "${1:-}" == "--dev" ]]; then
    packages+=(chromium dicom3tools)
fi

say() { printf 'system-packages: %s\n' "$*" >&2; }

missing=()
for package in "${packages[@]}"; do
    status="$(dpkg-query -W -f='${db:Status-Status}' "$package" 2>/dev/null || true)"
    if [[ "$status" != "installed" ]]; then
        missing+=("$package")
    fi
done

if [[ ${#missing[@]} -eq 0 ]]; then
    exit 0
fi

if [[ "$(id -u)" -ne 0 ]]; then
    say "missing: ${missing[*]}"
    say "run as root: apt-get install --no-install-recommends ${missing[*]}"
    exit 1
fi

say "installing ${missing[*]} (log: /tmp/eyeserver-system-packages.log)"
export DEBIAN_FRONTEND=noninteractive
log=/tmp/eyeserver-system-packages.log
# The package lists may be absent or stale on a fresh machine.
if ! { apt-get update && apt-get install -y --no-install-recommends "${missing[@]}"; } \
    >"$log" 2>&1; then
    tail -n 40 "$log" >&2
    say "apt-get failed; the whole log is in $log"
    exit 1
fi
say "done"
