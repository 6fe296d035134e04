"""What a machine may lack for a driver's tests, as skip reasons (None: nothing lacking).

A test that needs one is skipped with the reason printed (pytest's ``-ra``), never silently; CI
installs everything (scripts/system-packages.sh, the ``genicam`` and ``basler`` extras).
"""

from __future__ import annotations

import importlib.util

import pytest

from eyeserver.hardware.drivers import basler, genicam
from eyeserver.hardware.emulators.fakegv import find_fake_camera_program


def _why_no_aravis() -> str | None:
    if find_fake_camera_program() is None:
        return ("arv-fake-gv-camera-0.8 is not installed (Debian package aravis-tools: "
                "scripts/system-packages.sh)")
    try:
        genicam._load_aravis()
    except ImportError as exc:
        return str(exc)
    return None


NO_ARAVIS = _why_no_aravis()
"""Why Aravis's fake GigE camera cannot run here, or None."""

NO_PYLON = (None if importlib.util.find_spec("pypylon") is not None
            else f"pypylon is not installed ({basler.INSTALL_HINT})")
"""Why pylon's camera emulation cannot run here, or None."""

needs_aravis = pytest.mark.skipif(NO_ARAVIS is not None, reason=NO_ARAVIS or "")
needs_pylon = pytest.mark.skipif(NO_PYLON is not None, reason=NO_PYLON or "")
