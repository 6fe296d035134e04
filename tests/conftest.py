"""Shared fixtures: simulated rigs calibrated once per test session (they take ~40 s each), and
the daemon's app in process, one per module."""

from __future__ import annotations

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


_CACHE: dict[str, tuple[Path, Path]] = {}


@pytest.fixture(scope="session")
def calibrated_rooms(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """``get(name) -> (calibration set, calibration directory)``, made on first use."""
    def get(name: str) -> tuple[Path, Path]:
        if name not in _CACHE:
            _CACHE[name] = calibrate_room(name, tmp_path_factory.mktemp(name))
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
