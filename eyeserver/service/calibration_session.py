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
reached by the daemon's motorised stage, then the reference plane, each lit unit in turn and
stored as a ``plate`` or ``reference`` capture. The solve (a job) runs
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
from eyeserver.calibration.phase_height import calibrate_phase_height
from eyeserver.calibration.stereo import MIN_BOARDS, calibrate_stereo
from eyeserver.errors import StateConflictError
from eyeserver.io import BundleFrameData, ChessboardSpec, bundle_hash, read_bundle, write_bundle
from eyeserver.service.core import Service
from eyeserver.service.events import event_time
from eyeserver.service.jobs import Job, JobContext
from eyeserver.service.storage import CalibrationRecord, UnknownIdError

__all__ = [
    "COVERAGE_GRID",
    "MIN_PLATE_HEIGHTS",
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

    def phase_height_status(self) -> dict[str, Any]:
        """What the phase-height session holds and what it still needs."""
        missing = []
        if len(self.plates) < MIN_PLATE_HEIGHTS:
            missing.append(f"plate at {len(self.plates)} height(s), needs at least "
                           f"{MIN_PLATE_HEIGHTS}")
        if self.reference is None:
            missing.append("no reference plane yet")
        return {"ready": not missing, "missing": missing}


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
             calibration_id: str | None = None) -> Session:
        """Open a session and put the daemon in ``calibrating``.

        Stereo sessions take the ``board`` (the default board of the simulated room unless
        given); phase-height sessions the id of the calibration whose geometry they extend.

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
        if kind == "phase-height":
            if calibration_id is None:
                raise ValueError("calibration_id: a phase-height session extends a stored "
                                 "calibration; name it")
            parent = service.store.get_calibration(calibration_id)
            load_calibration(parent.path, service.rig_spec())
        session = Session(id=f"cs-{secrets.token_hex(6)}", kind=kind, actor=actor,
                          created=event_time(), parent_id=calibration_id,
                          board=(board or ChessboardSpec(9, 6, 4.5, origin=False))
                          if kind == "stereo" else None)
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
        stay). A session past its acquisition is left as it is."""
        session = self.get(session_id)
        with session.lock:
            if session.state == "acquiring":
                session.state = "closed"
                self._service.release_session(session.id)
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
        ``z_mm``; with ``move_stage`` the daemon's stage puts the plate there first.

        Raises
        ------
        SessionError
            Not a phase-height session, no longer acquiring, or a height acquired twice.
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
            if not reference and any(abs(p.z_mm - z_mm) < 1e-6 for p in session.plates):
                raise SessionError(f"the plate was acquired at Z = {z_mm} mm already")
            frames, bit_depth = service.acquire_for_session(
                session.id, lit=True, z_mm=float(z_mm), move_stage=move_stage)
            record = service.store.add_capture(
                "reference" if reference else "plate", service.rig_spec(), frames, unit="all",
                calibration_id=None, bit_depth=bit_depth,
                extra={"calibration_session": session.id,
                       "simulated": service.simulated})
            step = PlateStep(record.id, float(z_mm), move_stage)
            if reference:
                session.reference = step
            else:
                session.plates.append(step)
        service.events.publish("calibration_session.plate", session_id=session.id,
                               capture_id=record.id, z_mm=z_mm, reference=reference)
        return step

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
        body.update(session.phase_height_status())
    return body

