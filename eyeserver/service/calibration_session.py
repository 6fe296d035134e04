"""Guided calibration sessions: a physicist calibrates the rig through the daemon, step by step.

::

    open (POST)  ──► acquiring ──── views / plates / reference (the rig acquires; feedback) ──┐
      (daemon: calibrating)  │                                                                │
                             ├──── DELETE ──► closed                                          │
                             └──── solve ──► solving (a job; daemon idle again) ──► done │ failed

A **stereo** session acquires chessboard views, one per request, as ``eyeserver sim
calibration-set`` records them: every camera on one pulse, all projectors dark, in room light.
Each view is stored at once as a ``chessboard`` capture and answered with which cameras found
the board and how far the views so far cover each camera's field (:data:`COVERAGE_GRID`² image
cells touched by detected corners), with ``ready`` and what is still missing. The origin board
(it defines the WCS, FORMATS.md) is the first view unless that was posted with ``origin: false``;
then exactly one later view must say ``origin: true``, as the offline tool wants exactly one
bundle marked so. The solve is :func:`~eyeserver.calibration.stereo.calibrate_stereo` over the
stored views, run as a job; its result is stored as a new calibration.

A **phase-height** session starts from a stored calibration (its parent): it acquires the flat
plate at nominal heights, each typed by the physicist (the plate was put there by hand) or
reached by the daemon's motorised stage, and the reference plane, each lit unit in turn and
stored as a ``plate`` or ``reference`` capture. Which heights it needs depends on the rig: the
solve walks each pixel's phase along Z from plane to plane, which slips by a fringe wherever
one step moves the phase by π or more, so neighbouring planes (the reference among them) may
be at most :func:`~eyeserver.calibration.phase_height.safe_step_mm` of the fringe phase's
sensitivity to height apart, over the session's Z range. The sensitivity comes from the parent's
own phase-to-height models when it has them (known at the opening), else it is measured on the
reference plane and the first plate acquired near it (the session asks for that probe first).
The session's ``plan`` then lists every height still needed, and it is ``ready`` only once they
are acquired. A solve that fails (a slip, a plate that was not where it was said to be) leaves
the session ``failed`` but open to more plates: the next plate (or reference) takes the daemon
again and the session acquires and solves anew. The solve (a job) runs
:func:`~eyeserver.calibration.phase_height.calibrate_phase_height` on the plate stack and the
reference with the parent's geometry and stores the result as a *new* calibration whose
``lineage.parent_id`` names the parent: a calibration never changes once stored.

The daemon is ``calibrating`` from the session's opening until its solve starts or it is closed:
captures and activations answer 409, while scenes may change between acquisitions (the board or
the plate is moved). The input captures are the evidence: their ids and hashes are in the
calibration's ``inputs``, and the calibration's download carries them. Sessions are kept in
memory; a restart forgets them (their stored captures stay).
"""

from __future__ import annotations

import logging
import math
import secrets
import statistics
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np

from eyeserver.calibration.artefact import load_calibration, stereo_document, write_calibration
from eyeserver.calibration.chessboard import detect_chessboard
from eyeserver.calibration.phase_height import (
    calibrate_phase_height,
    heights_needed,
    model_sensitivity,
    phase_sensitivity,
    safe_step_mm,
)
from eyeserver.calibration.stereo import MIN_BOARDS, CalibrationError, calibrate_stereo
from eyeserver.errors import StateConflictError
from eyeserver.io import BundleFrameData, ChessboardSpec, bundle_hash, read_bundle, write_bundle
from eyeserver.service.core import Service
from eyeserver.service.events import event_time
from eyeserver.service.jobs import Job, JobContext
from eyeserver.service.storage import CalibrationRecord, UnknownIdError

__all__ = [
    "COVERAGE_GRID",
    "DEFAULT_Z_RANGE_MM",
    "MIN_PLATE_HEIGHTS",
    "PROBE_MM",
    "READY_COVERAGE",
    "CalibrationSessions",
    "PlateStep",
    "Session",
    "SessionError",
    "SessionKind",
    "StereoView",
    "describe",
]

SessionKind = Literal["stereo", "phase-height"]
SessionState = Literal["acquiring", "solving", "done", "failed", "closed"]

COVERAGE_GRID = 4
"""Each camera's image is cut into this many cells along each axis for the coverage figure."""
READY_COVERAGE = 0.75
"""Share of a camera's cells its detected corners must touch before the session is ready: the
distortion fit needs corners out towards the edges, not only in the middle."""
MIN_PLATE_HEIGHTS = 3
"""Plate heights the phase-to-height fit needs at the least (it fits a model along Z)."""
DEFAULT_Z_RANGE_MM = (-10.0, 25.0)
"""The Z range a phase-height session calibrates unless told (that of ``eyeserver sim
calibration-set``: the eye's surface and the reference plane at +10 mm with room to spare), or
the parent's calibrated range when it has one."""
PROBE_MM = 1.0
"""How far from the reference plane the probe plate that measures the sensitivity should be:
near enough that its phase moves by well under π on any rig whose fringes span 2 mm of height
or more."""

_log = logging.getLogger(__name__)


class SessionError(StateConflictError):
    """The session cannot do this now (wrong kind or state, not ready); HTTP 409."""


@dataclass(frozen=True)
class StereoView:
    """One acquired chessboard view: its capture, whether it is the origin board, and per
    camera whether the board was found."""

    capture_id: str
    origin: bool
    found: dict[str, bool]


@dataclass(frozen=True)
class PlateStep:
    """One acquired plate (or reference) position."""

    capture_id: str
    z_mm: float
    moved_by_stage: bool


@dataclass
class Session:
    """One guided calibration session (see the module docstring)."""

    id: str
    kind: SessionKind
    actor: str
    created: str
    state: SessionState = "acquiring"
    board: ChessboardSpec | None = None
    parent_id: str | None = None
    views: list[StereoView] = field(default_factory=list)
    cells: dict[str, set[tuple[int, int]]] = field(default_factory=dict)
    plates: list[PlateStep] = field(default_factory=list)
    reference: PlateStep | None = None
    job_id: str | None = None
    calibration_id: str | None = None
    error: str | None = None
    z_range_mm: tuple[float, float] = DEFAULT_Z_RANGE_MM
    sensitivity: dict[str, float] | None = None
    """Phase-height: rad/mm per camera (None until known)."""
    sensitivity_source: str | None = None
    sensitivity_error: str | None = None
    failures: list[dict[str, Any]] = field(default_factory=list)
    """Phase-height: the solves that failed (job id, error, heights then), oldest first."""
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def coverage(self) -> dict[str, Any]:
        """Per camera: views that found the board, share of cells covered, whether it saw the
        origin board; plus ``ready`` and the list of what is ``missing``."""
        cameras: dict[str, Any] = {}
        missing: list[str] = []
        origin = next((v for v in self.views if v.origin), None)
        total = COVERAGE_GRID * COVERAGE_GRID
        for camera_id, cells in self.cells.items():
            found = sum(1 for v in self.views if v.found.get(camera_id))
            share = len(cells) / total
            uncovered = sorted({(r, c) for r in range(COVERAGE_GRID)
                                for c in range(COVERAGE_GRID)} - cells)
            cameras[camera_id] = {"views_found": found, "coverage": share,
                                  "cells_covered": len(cells), "cells_total": total,
                                  "uncovered_cells": [list(rc) for rc in uncovered],
                                  "origin_found": bool(origin and origin.found.get(camera_id))}
            if found < MIN_BOARDS:
                missing.append(f"{camera_id}: board found in {found} view(s), needs "
                               f"{MIN_BOARDS}")
            if share < READY_COVERAGE:
                missing.append(f"{camera_id}: corners cover {len(cells)} of {total} image cells, "
                               f"needs {int(np.ceil(READY_COVERAGE * total))}; uncovered cells "
                               f"(row, col): {', '.join(f'({r},{c})' for r, c in uncovered)}")
        if origin is None:
            missing.insert(0, "no origin board yet (the first view, or one posted with "
                           "\"origin\": true)")
        else:
            for camera_id, entry in cameras.items():
                if not entry["origin_found"]:
                    missing.append(f"{camera_id}: did not find the origin board, so its pose "
                                   "in the WCS would be unknown; repeat it in a new session")
        return {"cameras": cameras, "ready": not missing, "missing": missing}

    def acquired_heights(self) -> list[float]:
        """The heights of the plates and the reference plane so far (mm, ascending)."""
        heights = {p.z_mm for p in self.plates}
        if self.reference is not None:
            heights.add(self.reference.z_mm)
        return sorted(heights)

    def plate_plan(self) -> dict[str, Any]:
        """Phase-height: the rig's sensitivity, the largest safe step between planes and every
        height still needed over :attr:`z_range_mm` (None until the sensitivity is known), with
        what to do next."""
        low, high = self.z_range_mm
        plan: dict[str, Any] = {"z_range_mm": [low, high], "sensitivity_rad_per_mm": None,
                                "sensitivity_source": self.sensitivity_source,
                                "max_step_mm": None, "needed_heights_mm": None}
        if self.sensitivity:
            # A solve whose walk along Z slipped all the same (the sensitivity is steeper
            # somewhere than where it was measured) halves the step for the next attempt.
            errors = [f["error"] or "" for f in self.failures] + [self.error or ""]
            slips = sum("slipped" in error for error in errors)
            step = max(0.1, math.floor(10 * safe_step_mm(max(self.sensitivity.values()))
                                       / 2**slips) / 10)
            needed = heights_needed(self.acquired_heights(), (low, high), step)
            plan.update(sensitivity_rad_per_mm=dict(self.sensitivity), max_step_mm=step,
                        needed_heights_mm=needed)
            if self.reference is None:
                plan["next"] = "the reference plane (POST …/reference)"
            elif needed:
                plan["next"] = ("the plate at Z = " + ", ".join(f"{z:+.2f}" for z in needed)
                                + " mm (any order)")
            elif len(self.plates) < MIN_PLATE_HEIGHTS:
                plan["next"] = f"the plate at {MIN_PLATE_HEIGHTS} heights at the least"
            else:
                plan["next"] = "solve"
        elif self.reference is None:
            plan["next"] = (f"the reference plane (POST …/reference), then a probe plate "
                            f"{PROBE_MM:g} mm from it: the session measures this rig's fringe "
                            "sensitivity on the two and lists the heights it needs")
        else:
            z = self.reference.z_mm
            plan["next"] = (f"a probe plate at Z = {z - PROBE_MM:+.2f} or {z + PROBE_MM:+.2f} "
                            "mm, to measure this rig's fringe sensitivity")
        if self.sensitivity_error is not None:
            plan["sensitivity_error"] = self.sensitivity_error
        return plan

    def phase_height_status(self) -> dict[str, Any]:
        """What the phase-height session holds and what it still needs (``plan``: the
        heights)."""
        missing = []
        if len(self.plates) < MIN_PLATE_HEIGHTS:
            missing.append(f"plate at {len(self.plates)} height(s), needs at least "
                           f"{MIN_PLATE_HEIGHTS}")
        if self.reference is None:
            missing.append("no reference plane yet")
        plan = self.plate_plan()
        if plan["needed_heights_mm"] is None:
            missing.append("the fringe sensitivity of this rig is not known yet: "
                           + (self.sensitivity_error or plan["next"]))
        elif plan["needed_heights_mm"]:
            missing.append(f"no two neighbouring planes may be more than {plan['max_step_mm']} "
                           "mm apart over Z " + f"{plan['z_range_mm'][0]:+g}…"
                           f"{plan['z_range_mm'][1]:+g} mm: the plate at Z = "
                           + ", ".join(f"{z:+.2f}" for z in plan["needed_heights_mm"]) + " mm")
        return {"ready": not missing, "missing": missing, "plan": plan}


def _cells(corners: np.ndarray, width: int, height: int) -> set[tuple[int, int]]:
    cols = np.clip((corners[:, 0] / width * COVERAGE_GRID).astype(int), 0, COVERAGE_GRID - 1)
    rows = np.clip((corners[:, 1] / height * COVERAGE_GRID).astype(int), 0, COVERAGE_GRID - 1)
    return {(int(r), int(c)) for r, c in zip(rows, cols, strict=True)}


def _now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


class CalibrationSessions:
    """The guided calibration sessions of one daemon (kept in memory).

    Every method blocks (hardware, disk, corner detection): the API calls them from worker
    threads. Solving runs as a job on :attr:`Service.jobs`.
    """

    def __init__(self, service: Service) -> None:
        self._service = service
        self._lock = threading.Lock()
        self._sessions: dict[str, Session] = {}

    # --- opening, reading, closing --------------------------------------------------------

    def open(self, kind: SessionKind, *, actor: str, board: ChessboardSpec | None = None,
             calibration_id: str | None = None,
             z_range_mm: tuple[float, float] | None = None) -> Session:
        """Open a session and put the daemon in ``calibrating``.

        Stereo sessions take the ``board`` (the default board of the simulated room unless
        given); phase-height sessions the id of the calibration whose geometry they extend, and
        the Z range to calibrate (default: the parent's, else :data:`DEFAULT_Z_RANGE_MM`).

        Raises
        ------
        StateConflictError
            The daemon is busy (another session, a capture).
        UnknownIdError, FormatError
            The parent calibration is unknown or not for this rig.
        ValueError
            A phase-height session without ``calibration_id``.
        """
        service = self._service
        session = Session(id=f"cs-{secrets.token_hex(6)}", kind=kind, actor=actor,
                          created=event_time(), parent_id=calibration_id,
                          board=(board or ChessboardSpec(9, 6, 4.5, origin=False))
                          if kind == "stereo" else None)
        if kind == "phase-height":
            if calibration_id is None:
                raise ValueError("calibration_id: a phase-height session extends a stored "
                                 "calibration; name it")
            parent = service.store.get_calibration(calibration_id)
            document = load_calibration(parent.path, service.rig_spec())
            sensitivity = model_sensitivity(document)
            if sensitivity:
                session.sensitivity = sensitivity
                session.sensitivity_source = f"the phase-to-height models of {calibration_id}"
            ranges = [c["z_range_mm"] for c in (document.get("phase_to_height") or {}).get(
                "cameras", {}).values()]
            if z_range_mm is not None:
                session.z_range_mm = (float(min(z_range_mm)), float(max(z_range_mm)))
            elif ranges:
                session.z_range_mm = (float(min(r[0] for r in ranges)),
                                      float(max(r[1] for r in ranges)))
        if kind == "stereo":
            session.cells = {cid: set() for cid in service.rig_spec().camera_ids}
        service.hold_session(session.id)
        with self._lock:
            self._sessions[session.id] = session
        service.events.publish("calibration_session.opened", session_id=session.id, kind=kind,
                               actor=actor)
        _log.info("calibration session opened",
                  extra={"session_id": session.id, "kind": kind, "actor": actor})
        return session

    def get(self, session_id: str) -> Session:
        """One session; :class:`UnknownIdError` if unknown."""
        with self._lock:
            session = self._sessions.get(session_id)
        if session is None:
            raise UnknownIdError(session_id, "calibration session")
        return session

    def list_sessions(self) -> list[Session]:
        """Every session of this run, newest first."""
        with self._lock:
            return list(reversed(self._sessions.values()))

    def close(self, session_id: str) -> Session:
        """Abandon a session that is still acquiring (the daemon is released; its captures
        stay), or a failed one (it takes no more plates). A session solving or done is left as
        it is."""
        session = self.get(session_id)
        with session.lock:
            if session.state in ("acquiring", "failed"):
                if session.state == "acquiring":
                    self._service.release_session(session.id)
                session.state = "closed"
                _log.info("calibration session closed", extra={"session_id": session.id})
        return session

    def close_all(self) -> None:
        """Release the daemon from any session still acquiring (at shut-down)."""
        for session in self.list_sessions():
            self.close(session.id)

    # --- acquiring ------------------------------------------------------------------------

    def _acquiring(self, session: Session, kind: SessionKind) -> None:
        if session.kind != kind:
            raise SessionError(f"session {session.id} is a {session.kind} session")
        if session.state == "failed" and kind == "phase-height":
            # Extended after a failed solve: it holds the daemon again and acquires anew
            # (StateConflictError while the daemon is busy: the session stays failed).
            self._service.hold_session(session.id)
            session.failures.append({"job_id": session.job_id, "error": session.error,
                                     "heights_mm": session.acquired_heights()})
            session.state, session.job_id, session.error = "acquiring", None, None
            _log.info("calibration session extended after a failed solve",
                      extra={"session_id": session.id})
        if session.state != "acquiring":
            raise SessionError(f"session {session.id} is {session.state}; it acquires no more")

    def add_view(self, session_id: str, origin: bool | None = None) -> tuple[StereoView,
                                                                              dict[str, Any]]:
        """Acquire and store one chessboard view; returns it with the coverage so far.

        Raises
        ------
        SessionError
            Not a stereo session, no longer acquiring, or a second origin board.
        DeviceError
            A device failed (nothing stored).
        """
        session = self.get(session_id)
        service = self._service
        with session.lock:
            self._acquiring(session, "stereo")
            has_origin = any(v.origin for v in session.views)
            if origin and has_origin:
                raise SessionError("the session has its origin board already (exactly one view "
                                   "defines the WCS); post the first view with \"origin\": false "
                                   "to choose a later one")
            is_origin = bool(origin) or (origin is None and not session.views)
            assert session.board is not None
            board = ChessboardSpec(session.board.cols, session.board.rows,
                                   session.board.square_mm, origin=is_origin)
            frames, bit_depth = service.acquire_for_session(session.id, lit=False)
            record = service.store.add_capture(
                "chessboard", service.rig_spec(), frames, unit="all", calibration_id=None,
                bit_depth=bit_depth, chessboard=board,
                extra={"calibration_session": session.id,
                       "simulated": service.simulated})
            found: dict[str, bool] = {}
            rig = service.rig_spec()
            for camera_id in rig.camera_ids:
                image = frames[0].images.get(camera_id)
                corners = None if image is None else detect_chessboard(
                    image, board.cols, board.rows)
                found[camera_id] = corners is not None
                if corners is not None:
                    spec = rig.camera(camera_id)
                    session.cells[camera_id] |= _cells(corners, spec.width, spec.height)
            view = StereoView(record.id, is_origin, found)
            session.views.append(view)
            coverage = session.coverage()
        service.events.publish("calibration_session.view", session_id=session.id,
                               capture_id=record.id, found=found, ready=coverage["ready"])
        return view, coverage

    def add_plate(self, session_id: str, z_mm: float, *, move_stage: bool = False,
                  reference: bool = False) -> PlateStep:
        """Acquire and store the plate (or, with ``reference``, the reference plane) at nominal
        ``z_mm``; with ``move_stage`` the daemon's stage puts the plate there first. A height
        acquired before is acquired anew and replaces the earlier plate (a plate that was not
        where it was said to be, found by a failed solve), as a second reference plane replaces
        the first. A session whose solve failed acquires again (it holds the daemon anew).

        Raises
        ------
        SessionError
            Not a phase-height session, or solving, done or closed.
        StateConflictError
            ``move_stage`` and the daemon has no stage.
        DeviceValueError
            ``z_mm`` beyond the stage's travel (422).
        DeviceError
            A device failed (nothing stored).
        """
        session = self.get(session_id)
        service = self._service
        with session.lock:
            self._acquiring(session, "phase-height")
            frames, bit_depth = service.acquire_for_session(
                session.id, lit=True, z_mm=float(z_mm), move_stage=move_stage)
            record = service.store.add_capture(
                "reference" if reference else "plate", service.rig_spec(), frames, unit="all",
                calibration_id=None, bit_depth=bit_depth,
                extra={"calibration_session": session.id,
                       "simulated": service.simulated})
            step = PlateStep(record.id, float(z_mm), move_stage)
            replaced = (session.reference is not None) if reference else any(
                abs(p.z_mm - z_mm) < 1e-6 for p in session.plates)
            if reference:
                session.reference = step
            else:
                session.plates = [p for p in session.plates if abs(p.z_mm - z_mm) >= 1e-6]
                session.plates.append(step)
            if replaced and (session.sensitivity_source or "").startswith("measured"):
                session.sensitivity = None  # it may have been measured on the replaced one
            if session.sensitivity is None:
                self._measure_sensitivity(session)
        service.events.publish("calibration_session.plate", session_id=session.id,
                               capture_id=record.id, z_mm=z_mm, reference=reference)
        return step

    def _measure_sensitivity(self, session: Session) -> None:
        """Measure the rig's fringe sensitivity on the reference plane and the plate nearest
        it, once both are there (under the session's lock)."""
        if session.reference is None or not session.plates:
            return
        z_reference = session.reference.z_mm
        probe = min(session.plates, key=lambda p: (abs(p.z_mm - z_reference) < 1e-6,
                                                   abs(p.z_mm - z_reference)))
        if abs(probe.z_mm - z_reference) < 1e-6:
            return
        store = self._service.store
        try:
            session.sensitivity = phase_sensitivity(store.capture_path(probe.capture_id),
                                                    store.capture_path(session.reference.capture_id))
        except CalibrationError as exc:
            session.sensitivity_error = str(exc)
            return
        session.sensitivity_error = None
        session.sensitivity_source = (f"measured: the plate at Z = {probe.z_mm:+.2f} mm against "
                                      f"the reference plane at {z_reference:+.2f} mm")
        _log.info("fringe sensitivity measured", extra={
            "session_id": session.id, "rad_per_mm": max(session.sensitivity.values())})

    # --- solving --------------------------------------------------------------------------

    def solve(self, session_id: str, *, actor: str) -> Job:
        """Release the daemon and solve the session as a job; its result names the new
        calibration (``calibration_id``) and its quality figures.

        Raises
        ------
        SessionError
            No longer acquiring, or not ready (the reason lists what is missing).
        QueueFullError
            The job queue is full (the session stays acquiring).
        """
        session = self.get(session_id)
        service = self._service
        with session.lock:
            if session.state != "acquiring":
                raise SessionError(f"session {session.id} is {session.state}")
            status = (session.coverage() if session.kind == "stereo"
                      else session.phase_height_status())
            if not status["ready"]:
                raise SessionError(f"session {session.id} is not ready to solve: "
                                   + "; ".join(status["missing"]))
            work = (self._stereo_work(session, actor) if session.kind == "stereo"
                    else self._phase_height_work(session, actor))
            job = service.jobs.submit(f"{session.kind}-solve", work, actor=actor)
            session.state, session.job_id = "solving", job.id
            service.release_session(session.id)
        return job

    def _finished(self, session: Session, record: CalibrationRecord | None,
                  error: str | None) -> None:
        with session.lock:
            session.state = "done" if record is not None else "failed"
            session.calibration_id = None if record is None else record.id
            session.error = error

    def _run_solve(self, session: Session, solve: Callable[[JobContext], CalibrationRecord],
                   ) -> Callable[[JobContext], dict[str, Any]]:
        def work(context: JobContext) -> dict[str, Any]:
            try:
                record = solve(context)
            except Exception as exc:
                self._finished(session, None, str(exc) or type(exc).__name__)
                raise
            self._finished(session, record, None)
            self._service.events.publish("calibration.created", calibration_id=record.id,
                                         session_id=session.id, actor=session.actor)
            return {"calibration_id": record.id, "session_id": session.id,
                    "quality": dict(record.quality)}
        return work

    def _store(self, document: dict[str, Any], arrays: dict[str, Any] | None, session: Session,
               actor: str, what: str) -> CalibrationRecord:
        document["created"] = _now()
        document["lineage"] = {"parent_id": session.parent_id, "session_id": session.id,
                               "method": what}
        with tempfile.TemporaryDirectory(prefix="eyeserver-session-") as scratch:
            directory = write_calibration(Path(scratch) / "calibration", document, arrays)
            return self._service.store.import_calibration(
                directory, actor=actor,
                source=f"calibration session {session.id} ({what}) by {session.actor}")

    def _stereo_work(self, session: Session, actor: str) -> Callable[[JobContext], dict[str, Any]]:
        store = self._service.store
        paths = [store.capture_path(v.capture_id) for v in session.views]
        steps = len(paths) + len(session.cells)

        def solve(context: JobContext) -> CalibrationRecord:
            done = [0]

            def progress(message: str) -> None:
                context.check_cancelled()
                done[0] += 1
                context.progress(0.9 * done[0] / steps, message)

            result = calibrate_stereo(paths, progress=progress)
            context.check_cancelled()
            context.progress(0.95, "storing the calibration")
            return self._store(stereo_document(result), None, session, actor,
                               f"guided stereo, {len(paths)} views")

        return self._run_solve(session, solve)

    def _phase_height_work(self, session: Session, actor: str,
                           ) -> Callable[[JobContext], dict[str, Any]]:
        service = self._service
        assert session.parent_id is not None and session.reference is not None
        parent = service.store.get_calibration(session.parent_id)
        plates = sorted(session.plates, key=lambda p: p.z_mm)
        reference = session.reference
        cameras = len(service.rig_spec().camera_ids)

        def solve(context: JobContext) -> CalibrationRecord:
            document = load_calibration(parent.path, service.rig_spec())
            arrays = document.pop("arrays")
            store = service.store
            context.progress(0.02, f"gathering the plate at {len(plates)} heights")
            with tempfile.TemporaryDirectory(prefix="eyeserver-plate-") as scratch:
                # The solver takes one plate bundle with every height; the session stored one
                # capture per height, so they are joined here (the captures are the evidence).
                frames: list[BundleFrameData] = []
                bit_depth = None
                for step in plates:
                    bundle = read_bundle(store.capture_path(step.capture_id))
                    bit_depth = bundle.bit_depth
                    for frame in bundle.frames:
                        frames.append(BundleFrameData(
                            images={cid: bundle.load_image(frame.index, cid)
                                    for cid in frame.images},
                            z_mm=frame.z_mm, projectors_on=tuple(frame.projectors_on),
                            t_ns=frame.t_ns))
                    context.check_cancelled()
                plate_dir = write_bundle(Path(scratch) / "plate", "plate", service.rig_spec(),
                                         frames, bit_depth=bit_depth).path
                done = [0]

                def progress(message: str) -> None:
                    context.check_cancelled()
                    done[0] += 1
                    context.progress(0.05 + 0.85 * done[0] / (2 * cameras), message)

                section, new_arrays = calibrate_phase_height(
                    document, plate_dir, store.capture_path(reference.capture_id),
                    progress=progress)
            context.check_cancelled()
            context.progress(0.95, "storing the calibration")
            document["phase_to_height"] = section
            document["inputs"]["phase_to_height"] = [
                {"bundle": step.capture_id, "sha256": bundle_hash(
                    store.capture_path(step.capture_id)), "z_mm": step.z_mm,
                 "kind": kind}
                for kind, group in (("plate", plates), ("reference", [reference]))
                for step in group]
            medians = [c["quality"]["median_abs_mm"] for c in section["cameras"].values()]
            iqrs = [c["quality"]["iqr_mm"] for c in section["cameras"].values()]
            margins = [u["margin_rad"] for u in section["units"].values()
                       if u.get("margin_rad") is not None]
            document["quality"] = {
                **document.get("quality", {}),
                "p2h_residual_median_mm": float(statistics.median(medians)),
                "p2h_residual_iqr_mm": float(statistics.median(iqrs)),
                "p2h_residual_median_mm_per_camera": {
                    cid: c["quality"]["median_abs_mm"]
                    for cid, c in section["cameras"].items()},
                "fringe_order_margin_rad": min(margins) if margins else None,
                "plate_heights": len(plates)}
            return self._store(document, {**arrays, **new_arrays}, session, actor,
                               f"guided phase-to-height, {len(plates)} plate heights")

        return self._run_solve(session, solve)


def describe(session: Session) -> dict[str, Any]:
    """A session as the API shows it."""
    body: dict[str, Any] = {
        "id": session.id, "kind": session.kind, "actor": session.actor,
        "created": session.created, "state": session.state, "job_id": session.job_id,
        "calibration_id": session.calibration_id, "error": session.error}
    if session.kind == "stereo":
        assert session.board is not None
        body["board"] = {"cols": session.board.cols, "rows": session.board.rows,
                         "square_mm": session.board.square_mm}
        body["views"] = [{"capture_id": v.capture_id, "origin": v.origin, "found": v.found}
                         for v in session.views]
        body["coverage"] = session.coverage()
    else:
        body["parent_id"] = session.parent_id
        body["plates"] = [{"capture_id": p.capture_id, "z_mm": p.z_mm,
                           "moved_by_stage": p.moved_by_stage} for p in session.plates]
        body["reference"] = None if session.reference is None else {
            "capture_id": session.reference.capture_id, "z_mm": session.reference.z_mm}
        body["failures"] = list(session.failures)
        body.update(session.phase_height_status())
    return body

