"""A calibration of the simulated rig, made the way a physicist makes one (for the benches)."""

from __future__ import annotations

from pathlib import Path

from eyeserver.calibration.artefact import stereo_document, write_calibration
from eyeserver.calibration.phase_height import add_phase_height
from eyeserver.calibration.stereo import calibrate_stereo
from eyeserver.core.types import Progress, quiet
from eyeserver.hardware.sim.config import RoomConfig
from eyeserver.hardware.sim.sessions import SimSession, write_calibration_set


def calibrate_room(config: RoomConfig, work: Path, seed: int,
                   progress: Progress = quiet) -> Path:
    """Record a calibration set in the simulated room and calibrate it; the calibration
    directory."""
    calset, caldir = work / "calset", work / "calibration"
    with SimSession.open(config, seed=seed) as session:
        write_calibration_set(session, calset, overwrite=True, progress=progress)
    boards = sorted(calset.glob("chessboard_*"))
    result = calibrate_stereo(boards, progress=progress)
    write_calibration(caldir, stereo_document(result), overwrite=True)
    add_phase_height(caldir, calset / "plate", calset / "reference", progress=progress)
    return caldir
