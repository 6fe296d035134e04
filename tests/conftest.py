"""Shared fixtures: simulated rigs calibrated once per test session (they take ~40 s each)."""

from __future__ import annotations

from pathlib import Path

import pytest

from eyeserver.cli import main

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
