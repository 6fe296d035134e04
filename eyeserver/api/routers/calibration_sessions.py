"""``/api/v1/calibration-sessions``: guided calibration of the rig through the daemon.

Physicists only. A session puts the daemon in ``calibrating`` (captures answer 409) until its
solve starts or it is closed; see :mod:`eyeserver.service.calibration_session` for the steps.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Self

from fastapi import APIRouter, Depends
from pydantic import BaseModel, ConfigDict, Field, model_validator
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import PhysicistDep, require
from eyeserver.api.deps import app_state
from eyeserver.api.routers.jobs import JobResponse, job_response
from eyeserver.api.schemas import ErrorResponse
from eyeserver.io import ChessboardSpec
from eyeserver.service.calibration_session import CalibrationSessions, describe

__all__ = ["router"]

_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "No such session."},
    409: {"model": ErrorResponse, "description": "The session cannot do this now (its kind, "
          "its state, not ready), or the daemon is busy."},
}

router = APIRouter(prefix="/calibration-sessions", tags=["calibration sessions"],
                   dependencies=[Depends(require("physicist"))], responses=_ERRORS)


_sessions = app_state("calibration_sessions", CalibrationSessions)


SessionsDep = Annotated[CalibrationSessions, Depends(_sessions)]


class Board(BaseModel):
    """The chessboard held in front of the cameras (FORMATS.md)."""

    model_config = ConfigDict(extra="forbid")

    cols: int = Field(9, ge=2, description="Inner corners per row.")
    rows: int = Field(6, ge=2, description="Inner corners per column; one of cols and rows is "
                      "odd, the other even.")
    square_mm: float = Field(4.5, gt=0, description="Side of one square, mm.")

    @model_validator(mode="after")
    def _parity(self) -> Self:
        if (self.cols + self.rows) % 2 == 0:
            raise ValueError("one of cols and rows must be odd and the other even (FORMATS.md)")
        return self


class SessionRequest(BaseModel):
    """A new guided calibration session."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["stereo", "phase-height"]
    board: Board | None = Field(None, description="Stereo: the board (default: the simulated "
                                "room's 9 × 6 corners, 4.5 mm squares).")
    calibration_id: str | None = Field(None, description="Phase-height: the stored calibration "
                                       "whose geometry the new one extends (its parent).")
    z_range_mm: tuple[float, float] | None = Field(
        None, description="Phase-height: the Z range to calibrate, mm (default: the parent's "
        "calibrated range, else −10…+25). The session's plan lists the plate heights this "
        "range needs on this rig.", examples=[[-8.0, 10.0]])

    @model_validator(mode="after")
    def _fits_kind(self) -> Self:
        if self.kind == "phase-height" and self.calibration_id is None:
            raise ValueError("a phase-height session needs calibration_id (its parent)")
        if self.kind == "stereo" and self.calibration_id is not None:
            raise ValueError("a stereo session takes no calibration_id")
        if self.kind == "phase-height" and self.board is not None:
            raise ValueError("a phase-height session takes no board")
        if self.kind == "stereo" and self.z_range_mm is not None:
            raise ValueError("a stereo session takes no z_range_mm")
        if self.z_range_mm is not None and not (
                -100 <= min(self.z_range_mm) < max(self.z_range_mm) <= 100):
            raise ValueError("z_range_mm must be two different heights within ±100 mm")
        return self


class ViewRequest(BaseModel):
    """One chessboard view."""

    model_config = ConfigDict(extra="forbid")

    origin: bool | None = Field(None, description="Whether this board defines the WCS. By "
                                "default the first view does; post the first with false to "
                                "mark a later one true instead (exactly one origin).")


class PlateRequest(BaseModel):
    """One plate height."""

    model_config = ConfigDict(extra="forbid")

    z_mm: float = Field(ge=-100, le=100, description="Nominal Z of the plate's surface, mm.")
    move_stage: bool = Field(False, description="true: the daemon's motorised stage moves the "
                             "plate there first; false: it was put there by hand.")


class ReferenceRequest(BaseModel):
    """The reference plane, put in place by hand."""

    model_config = ConfigDict(extra="forbid")

    z_mm: float = Field(10.0, ge=-100, le=100, description="Nominal Z of the reference plane, "
                        "mm (docs/design.md §5: +10 mm).")


@router.post("", status_code=201, summary="Open a guided calibration session")
async def open_session(body: SessionRequest, sessions: SessionsDep,
                       caller: PhysicistDep) -> dict[str, Any]:
    """Open a stereo or phase-height session; the daemon is ``calibrating`` until its solve
    starts or it is closed. 409 when the daemon is busy; 404 for an unknown parent. A
    phase-height session answers its ``plan`` at once: the heights it needs when the parent's
    own phase-to-height models give the rig's fringe sensitivity, else the reference plane and
    a probe plate 1 mm from it to measure it."""
    board = None
    if body.board is not None:
        board = ChessboardSpec(body.board.cols, body.board.rows, body.board.square_mm)
    session = await run_in_threadpool(lambda: sessions.open(
        body.kind, actor=caller.name, board=board, calibration_id=body.calibration_id,
        z_range_mm=body.z_range_mm))
    return describe(session)


@router.get("", summary="List calibration sessions")
async def list_sessions(sessions: SessionsDep) -> dict[str, Any]:
    """The sessions of this run, newest first (kept in memory)."""
    return {"items": [describe(s) for s in sessions.list_sessions()]}


@router.get("/{session_id}", summary="One calibration session")
async def get_session(session_id: str, sessions: SessionsDep) -> dict[str, Any]:
    """A session: its inputs so far, coverage (stereo) or heights (phase-height), readiness,
    its solve job and the calibration it made."""
    return describe(sessions.get(session_id))


@router.delete("/{session_id}", summary="Close a calibration session")
async def close_session(session_id: str, sessions: SessionsDep) -> dict[str, Any]:
    """Abandon a session still acquiring: the daemon is released; its captures stay."""
    return describe(await run_in_threadpool(sessions.close, session_id))


@router.post("/{session_id}/views", status_code=201, summary="Acquire a chessboard view")
async def add_view(session_id: str, sessions: SessionsDep,
                   body: ViewRequest | None = None) -> dict[str, Any]:
    """Acquire the board (every camera, projectors dark, room light) and store it as a
    ``chessboard`` capture; answers which cameras found it and the coverage so far: per camera
    the views that found the board and the share of a 4 × 4 grid of image cells its corners
    touched, ``ready`` and what is still ``missing``."""
    origin = None if body is None else body.origin
    view, coverage = await run_in_threadpool(lambda: sessions.add_view(session_id, origin))
    return {"capture_id": view.capture_id, "origin": view.origin, "found": view.found,
            **coverage}


@router.post("/{session_id}/plates", status_code=201, summary="Acquire the plate at a height")
async def add_plate(session_id: str, body: PlateRequest, sessions: SessionsDep,
                    ) -> dict[str, Any]:
    """Acquire the flat plate at ``z_mm`` (moved there by the stage with ``move_stage``), each
    unit lit in turn, and store it as a ``plate`` capture; answers the session's readiness and
    ``plan`` (the heights still needed). A session whose solve failed takes more plates: it
    acquires again (the daemon is ``calibrating``) and can be solved anew. 409 without a stage
    for ``move_stage``, 422 beyond its travel."""
    step = await run_in_threadpool(lambda: sessions.add_plate(
        session_id, body.z_mm, move_stage=body.move_stage))
    return {"capture_id": step.capture_id, "z_mm": step.z_mm,
            "moved_by_stage": step.moved_by_stage,
            **sessions.get(session_id).phase_height_status()}


@router.post("/{session_id}/reference", status_code=201, summary="Acquire the reference plane")
async def add_reference(session_id: str, sessions: SessionsDep,
                        body: ReferenceRequest | None = None) -> dict[str, Any]:
    """Acquire the reference plane at ``z_mm`` (default +10) and store it as a ``reference``
    capture; a second one replaces the first in the session."""
    z_mm = 10.0 if body is None else body.z_mm
    step = await run_in_threadpool(lambda: sessions.add_plate(session_id, z_mm,
                                                              reference=True))
    return {"capture_id": step.capture_id, "z_mm": step.z_mm,
            **sessions.get(session_id).phase_height_status()}


@router.post("/{session_id}/solve", status_code=202, summary="Solve the session as a job",
             responses={503: {"model": ErrorResponse, "description": "The job queue is full."}})
async def solve(session_id: str, sessions: SessionsDep, caller: PhysicistDep) -> JobResponse:
    """Release the daemon and solve the session as a job (``GET /jobs/{id}``); its result
    names the new calibration (``calibration_id``, not activated) and its quality figures.
    409 when the session is not ready (the reason lists what is missing)."""
    job = await run_in_threadpool(lambda: sessions.solve(session_id, actor=caller.name))
    return job_response(job)

