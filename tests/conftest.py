"""Shared fixtures: simulated rigs calibrated once per test session (they take ~40 s each), and
the daemon's app in process, one per module."""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI

from eyeserver.api import create_app
from eyeserver.cli import main
from eyeserver.service.core import Service
from tests.apiclient import Client, serving, test_settings

ROOT = Path(__file__).resolve().parents[1]
ROOMS: dict[str, Path | None] = {
    "default": None,
    "wide": ROOT / "examples" / "rooms" / "wide.toml",
    "horizontal": ROOT / "examples" / "rooms" / "horizontal.toml",
    "blind": ROOT / "examples" / "rooms" / "blind.toml",
    "single": ROOT / "examples" / "rooms" / "single.toml",
}


def calibrate_room(name: str, base: Path) -> tuple[Path, Path]:
    """Record a calibration set in room ``name`` and calibrate it with the command line."""
    room = ["--room", str(ROOMS[name])] if ROOMS[name] else []
    calset, caldir = base / "calset", base / "cal"
    assert main(["sim", "calibration-set", *room, "--out", str(calset)]) == 0
    boards = sorted(str(p) for p in calset.glob("chessboard_*"))
    assert main(["calibrate", "stereo", "--out", str(caldir), *boards]) == 0
    assert main(["calibrate", "p2h", "--calibration", str(caldir), str(calset / "plate"),
                 str(calset / "reference")]) == 0
    return calset, caldir


# What a calibration of the simulated room is made from: a change to any of it makes a new one.
# Not the real devices' drivers and emulators (hardware/drivers, hardware/emulators, the
# discovery): they take no part in it.
_CALIBRATION_SOURCES = ("calibration", "hardware/sim", "hardware/base.py", "hardware/rig.py",
                        "hardware/registry.py", "hardware/room.py", "hardware/bundling.py",
                        "pipeline", "core", "io", "commands", "cli.py", "config.py")

_CACHE: dict[str, tuple[Path, Path]] = {}


def _calibration_key(name: str) -> str:
    """A digest of the code and room file a calibration of room ``name`` is made from."""
    digest = hashlib.sha256(name.encode())
    package = ROOT / "eyeserver"
    for source in _CALIBRATION_SOURCES:
        path = package / source
        for file in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            digest.update(str(file.relative_to(package)).encode())
            digest.update(file.read_bytes())
    room = ROOMS[name]
    if room is not None:
        digest.update(room.read_bytes())
    return digest.hexdigest()[:16]


def _tree_digest(directory: Path) -> str:
    """A digest of the names and contents of every file under ``directory`` but ``done``."""
    digest = hashlib.sha256()
    for file in sorted(directory.rglob("*")):
        if file.is_file() and file.name != "done":
            digest.update(str(file.relative_to(directory)).encode())
            digest.update(file.read_bytes())
    return digest.hexdigest()


@pytest.fixture(scope="session")
def calibrated_rooms(request: pytest.FixtureRequest,
                    tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """``get(name) -> (calibration set, calibration directory)``, made on first use.

    Kept between runs in pytest's cache directory (``.pytest_cache``), keyed by a digest of the
    code that makes them and the room file, so that a run after a change elsewhere does not
    spend ≈ 40 s per room again; ``pytest --cache-clear`` (or ``-p no:cacheprovider``, as CI's
    fresh clone) makes them anew.
    """
    cache = getattr(request.config, "cache", None)

    def get(name: str) -> tuple[Path, Path]:
        if name not in _CACHE:
            if cache is None:
                _CACHE[name] = calibrate_room(name, tmp_path_factory.mktemp(name))
            else:
                kept = Path(cache.mkdir("calibrations")) / f"{name}-{_calibration_key(name)}"
                done = kept / "done"
                # Marked done with a digest of its files once complete: one left half-made by
                # an interrupted run, or changed by a test, is made anew.
                if not done.exists() or done.read_text() != _tree_digest(kept):
                    work = tmp_path_factory.mktemp(name)
                    calibrate_room(name, work)
                    shutil.rmtree(kept, ignore_errors=True)
                    shutil.copytree(work, kept)
                    done.write_text(_tree_digest(kept))
                _CACHE[name] = (kept / "calset", kept / "cal")
        return _CACHE[name]
    return get


# --- the daemon's app in process, one per test module (a module may define its own) ----------


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> Path:
    """A fresh data directory for the module's daemon."""
    return tmp_path_factory.mktemp(request.module.__name__.rsplit(".", 1)[-1]) / "data"


@pytest.fixture(scope="module")
def app(data_dir: Path) -> FastAPI:
    """The daemon's app with the test tokens (tests/apiclient.py), not started."""
    return create_app(test_settings(data_dir))


@pytest.fixture(scope="module")
def client(app: FastAPI) -> Iterator[Client]:
    """The app running with its lifespan (simulated room, store), and a client of it."""
    with serving(app) as running:
        yield running


@pytest.fixture
def service(app: FastAPI, client: Client) -> Service:
    """The running app's service."""
    running = app.state.service
    assert isinstance(running, Service)
    return running
