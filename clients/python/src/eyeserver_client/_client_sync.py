"""The blocking client of the eyeserver API (:class:`Client`).

Generated from ``_client_async.py`` by ``scripts/unasync.py``: do not edit (edit that
file and run the script).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any, Literal, TypeVar

import httpx
from pydantic import BaseModel

from eyeserver_client import _io_sync as io
from eyeserver_client import _operations as ops
from eyeserver_client._config import Connection, resolve
from eyeserver_client._http import RetryPolicy, error_for, parse, transport_error, url_for
from eyeserver_client._operations import Operation
from eyeserver_client._streams_sync import MessageStream
from eyeserver_client.errors import EyeserverError, RequestTimeoutError
from eyeserver_client.extras import (
    CalibrationComparison,
    CalibrationSession,
    PlateStep,
    ReferencePlaneStep,
    ViewStep,
)
from eyeserver_client.messages import parse_event_message, parse_pose_message
from eyeserver_client.models import (
    AuditLine,
    AuditList,
    CalibrationList,
    CalibrationResponse,
    CaptureList,
    CaptureResponse,
    DeviceResponse,
    EllipsoidSpec,
    EyeModelList,
    EyeModelResponse,
    HealthResponse,
    JobList,
    JobResponse,
    Measurement,
    MeasurementList,
    MotionSpec,
    PatientResponse,
    PrerenderResponse,
    QaRun,
    QaRunList,
    QaStatus,
    QaTrends,
    ReconstructionResponse,
    ReferenceList,
    ReferenceResponse,
    SceneSpec,
    SimDeviceResponse,
    SimEyeResponse,
    StatusResponse,
    TrackingStatus,
    WhoAmIResponse,
)

__all__ = ["Client"]

M = TypeVar("M", bound=BaseModel)

DEFAULT_TIMEOUT_S = 60.0
"""Seconds to wait for an answer: a pose measurement (capture, reconstruction, fit) or the start
of live tracking (its workers load the calibration) take seconds on a loaded machine."""
DEFAULT_CONNECT_TIMEOUT_S = 5.0
"""Seconds to wait for a connection to the daemon."""
POSE_SILENCE_S = 2.0
"""The pose stream sends a heartbeat after 1 s without anything else; a link silent for this
long is taken as dead (the README: a beam controller must then hold the beam)."""

JOB_FINISHED = ("succeeded", "failed", "cancelled")


def _body(**fields: Any) -> dict[str, Any]:
    """A JSON body of the fields given (None: left out, so the daemon's default applies)."""
    return {name: value for name, value in fields.items() if value is not None}


def _dump(value: BaseModel | Mapping[str, Any]) -> dict[str, Any]:
    """A request body from a model (only the fields that were set) or a mapping."""
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json", exclude_unset=True)
    return dict(value)


def _time(value: datetime | str | None) -> str | None:
    """A time filter as the daemon reads it: ISO 8601 with a time zone."""
    if isinstance(value, datetime):
        if value.tzinfo is None:
            raise EyeserverError("a time filter needs a time zone (e.g. datetime.now(UTC))")
        return value.isoformat()
    return value


class Client:
    """A client of one eyeserver daemon's HTTP API and streams (blocking).

    Parameters
    ----------
    base_url
        The daemon's address, e.g. ``https://room-pc:8443`` (``/api/v1`` may be included);
        default ``$EYESERVER_URL``, else ``http://127.0.0.1:8000``.
    token
        The bearer token; default the file ``token_file``, else ``$EYESERVER_TOKEN``, else the
        file named by ``$EYESERVER_TOKEN_FILE``. Without one only :meth:`health` answers.
    token_file
        A file holding the token (read once, here).
    ca_file
        PEM file of the CA that signed the daemon's certificate (``https`` only); default the
        system's trust store.
    verify
        False turns certificate verification off (for a bench, never in a treatment room).
    client_cert
        For a daemon that wants client certificates (mutual TLS): a PEM file with certificate
        and key, or a ``(certificate, key)`` pair.
    timeout_s
        Seconds to wait for an answer (default 60: a measurement takes seconds).
    connect_timeout_s
        Seconds to wait for a connection.
    retries
        How often a request is sent again when that is safe (see
        :class:`~eyeserver_client._http.RetryPolicy`: never a request that creates something
        and may have reached the daemon).
    transport
        An httpx transport to use instead of the network (tests).

    Use it as a context manager, or call :meth:`close`, to release its connections.
    """

    def __init__(self, base_url: str | None = None, *, token: str | None = None,
                 token_file: str | os.PathLike[str] | None = None,
                 ca_file: str | os.PathLike[str] | None = None, verify: bool = True,
                 client_cert: str | os.PathLike[str] | tuple[str | os.PathLike[str],
                                                             str | os.PathLike[str]] | None
                 = None,
                 timeout_s: float = DEFAULT_TIMEOUT_S,
                 connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S, retries: int = 2,
                 transport: httpx.BaseTransport | None = None) -> None:
        self.connection: Connection = resolve(base_url, token, token_file, ca_file, verify,
                                              client_cert)
        self.retry = RetryPolicy(retries)
        self._http = httpx.Client(
            headers={**self.connection.headers(), "Accept": "application/json"},
            verify=self.connection.verify,
            timeout=httpx.Timeout(timeout_s, connect=connect_timeout_s),
            transport=transport)

    @property
    def base_url(self) -> str:
        """The API's base URL (``…/api/v1``)."""
        return self.connection.api

    def close(self) -> None:
        """Close the client's connections."""
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # --- the one way requests go ---------------------------------------------------------

    def _call(self, operation: Operation, *, path: Mapping[str, object] | None = None,
              params: Mapping[str, Any] | None = None, json: Any = None,
              content: bytes | None = None, headers: Mapping[str, str] | None = None,
              timeout_s: float | None = None) -> httpx.Response:
        """Send ``operation``, retrying where :attr:`retry` allows; the successful answer.

        Raises the :mod:`~eyeserver_client.errors` tree's exception for an error answer (with
        the daemon's reason) or a request that got none.
        """
        url = url_for(self.connection, operation, path)
        query = None if params is None else {k: v for k, v in params.items() if v is not None}
        extra: dict[str, Any] = {}
        if timeout_s is not None:
            extra["timeout"] = httpx.Timeout(timeout_s, connect=self._http.timeout.connect)
        attempt = 0
        while True:
            try:
                response = self._http.request(
                    operation.method, url, params=query, json=json, content=content,
                    headers=headers, **extra)
            except httpx.TransportError as exc:
                wait_s = self.retry.after_failure(operation, exc, attempt)
                if wait_s is None:
                    raise transport_error(exc, operation.method, url) from exc
            else:
                if response.is_success:
                    return response
                response.read()
                error = error_for(response)
                wait_s = self.retry.after_answer(operation, error, attempt)
                if wait_s is None:
                    raise error
            attempt += 1
            io.sleep(wait_s)

    def _get(self, operation: Operation, kind: type[M], **kwargs: Any) -> M:
        return parse(self._call(operation, **kwargs), kind)

    # --- the daemon --------------------------------------------------------------------------

    def health(self) -> HealthResponse:
        """Whether the daemon is up (no token needed): ``status`` ``ok`` and its version."""
        return self._get(ops.HEALTH, HealthResponse)

    def status(self) -> StatusResponse:
        """The daemon's state (idle, capturing, calibrating, tracking, fault), its devices and
        units with their health, the active calibration, uptime (s) and tracking's beam hold."""
        return self._get(ops.STATUS, StatusResponse)

    def whoami(self) -> WhoAmIResponse:
        """Whose token this client presents: the holder's ``name`` (as the audit trail records
        it), its ``role`` and every role it may act as. Ask this rather than trying a
        physicist's route, which would leave a ``denied`` line in the audit trail."""
        return self._get(ops.WHOAMI, WhoAmIResponse)

    def devices(self) -> list[DeviceResponse]:
        """Every device of the rig: kind, driver, unit, open, health and a fault's reason."""
        return parse(self._call(ops.DEVICES), list[DeviceResponse])

    def device(self, device_id: str) -> DeviceResponse:
        """One device (:class:`~eyeserver_client.errors.NotFound` if unknown)."""
        return self._get(ops.DEVICE, DeviceResponse, path={"device_id": device_id})

    def configure_device(self, device_id: str, *, enabled: bool | None = None,
                         intensity: float | None = None,
                         exposure_us: float | None = None,
                         gain_db: float | None = None) -> DeviceResponse:
        """Change a device's settings (physicists only; audited; all or nothing).

        A projector takes ``enabled`` and ``intensity`` (drive level 0–1), a camera
        ``exposure_us`` (microseconds) and ``gain_db`` (dB); settings left None stay as they
        are. :class:`~eyeserver_client.errors.Invalid` for a setting that does not apply to
        the device or a value outside its range.
        """
        return self._get(ops.CONFIGURE_DEVICE, DeviceResponse,
                         path={"device_id": device_id},
                         json=_body(enabled=enabled, intensity=intensity,
                                    exposure_us=exposure_us, gain_db=gain_db))

    def audit(self, limit: int = 100) -> list[AuditLine]:
        """The newest ``limit`` lines of the audit trail, newest first (physicists only)."""
        return (self._get(ops.AUDIT, AuditList, params={"limit": limit})).items

    def metrics(self) -> str:
        """The daemon's Prometheus metrics (text format)."""
        return (self._call(ops.METRICS)).text

    # --- captures and reconstructions --------------------------------------------------------

    def capture(self, unit: str = "all") -> CaptureResponse:
        """Capture one frame set of ``unit`` (or ``all``, interleaved) and store it.

        Answers once the bundle is durable on disk; waits its turn behind captures already
        queued. :class:`~eyeserver_client.errors.Conflict` while the daemon is calibrating or
        tracking, :class:`~eyeserver_client.errors.Unavailable` when a device fails or the
        acquisition queue is full. Never retried once sent (it would capture twice).
        """
        return self._get(ops.CREATE_CAPTURE, CaptureResponse, json={"unit": unit})

    def captures(self, *, limit: int = 50, offset: int = 0, unit: str | None = None,
                 kind: str | None = None, calibration_id: str | None = None,
                 since: datetime | str | None = None,
                 until: datetime | str | None = None) -> CaptureList:
        """One page of stored captures, newest first, with the ``total`` matching.

        ``since`` (inclusive) and ``until`` (exclusive) filter on the creation time; give
        aware datetimes or ISO 8601 text with a time zone.
        """
        return self._get(ops.LIST_CAPTURES, CaptureList, params={
            "limit": limit, "offset": offset, "unit": unit, "kind": kind,
            "calibration_id": calibration_id, "since": _time(since), "until": _time(until)})

    def get_capture(self, capture_id: str) -> CaptureResponse:
        """One capture's metadata (also after a restart of the daemon)."""
        return self._get(ops.CAPTURE, CaptureResponse, path={"capture_id": capture_id})

    def delete_capture(self, capture_id: str, *, reason: str) -> None:
        """Delete a capture with its cloud and summary (physicists only; the reason goes to
        the audit trail). :class:`~eyeserver_client.errors.Conflict` for a capture kept as
        evidence (a calibration's input, a measurement's or a captured reference's capture)."""
        self._call(ops.DELETE_CAPTURE, path={"capture_id": capture_id},
                   params={"reason": reason})

    def capture_bundle(self, capture_id: str) -> bytes:
        """The capture bundle as a zip (``<id>/bundle.json`` and its PNGs, byte for byte)."""
        return (self._call(ops.CAPTURE_BUNDLE, path={"capture_id": capture_id})).content

    def capture_image(self, capture_id: str, frame: int, camera: str) -> bytes:
        """One stored image (PNG) of a capture: frame ``frame`` of camera ``camera``."""
        return (self._call(ops.CAPTURE_IMAGE, path={
            "capture_id": capture_id, "frame": frame, "camera": camera})).content

    def reconstruct(self, capture_id: str, *,
                    method: Literal["auto", "multi-view", "spatial"] | None = None,
                    depth_prior_mm: float | None = None,
                    roi: Sequence[float] | None = None,
                    min_quality: float | None = None) -> ReconstructionResponse:
        """Reconstruct a capture with the active calibration and store its cloud.

        Options as for ``eyeserver reconstruct``: the fringe-order ``method``, a
        ``depth_prior_mm`` (mm) the surface lies near, an ``roi`` box ``[x0, y0, z0, x1, y1,
        z1]`` (mm, WCS) and a ``min_quality`` (0–1) for points. Takes seconds.
        :class:`~eyeserver_client.errors.Conflict` when no calibration is active.
        """
        return self._get(ops.RECONSTRUCT, ReconstructionResponse,
                         path={"capture_id": capture_id},
                         json=_body(method=method, depth_prior_mm=depth_prior_mm,
                                    roi=None if roi is None else list(roi),
                                    min_quality=min_quality))

    def reconstruction(self, capture_id: str) -> ReconstructionResponse:
        """The kept summary of a capture's last reconstruction (NotFound before one)."""
        return self._get(ops.RECONSTRUCTION, ReconstructionResponse,
                         path={"capture_id": capture_id})

    def cloud_ply(self, capture_id: str) -> bytes:
        """A capture's stored point cloud (PLY, mm, WCS)."""
        return (self._call(ops.CLOUD, path={"capture_id": capture_id})).content

    def preview_png(self, capture_id: str) -> bytes:
        """A capture's height map as a PNG."""
        return (self._call(ops.PREVIEW, path={"capture_id": capture_id})).content

    # --- calibrations ------------------------------------------------------------------------

    def calibrations(self) -> list[CalibrationResponse]:
        """Every stored calibration, newest first, with its quality figures and source."""
        return (self._get(ops.LIST_CALIBRATIONS, CalibrationList)).items

    def calibration(self, calibration_id: str) -> CalibrationResponse:
        """One stored calibration."""
        return self._get(ops.CALIBRATION, CalibrationResponse,
                         path={"calibration_id": calibration_id})

    def import_calibration(self, archive: bytes | str | os.PathLike[str]
                           ) -> CalibrationResponse:
        """Import a calibration: a zip (its bytes or its path) of a directory made by
        ``eyeserver calibrate`` or downloaded from a daemon (physicists only; not activated).
        :class:`~eyeserver_client.errors.Invalid` for an archive the daemon refuses (the reason
        says why)."""
        data = archive if isinstance(archive, bytes) else Path(archive).read_bytes()
        return self._get(ops.IMPORT_CALIBRATION, CalibrationResponse, content=data,
                         headers={"Content-Type": "application/zip"})

    def activate_calibration(self, calibration_id: str) -> CalibrationResponse:
        """Make a calibration the one captures and measurements use (physicists only;
        audited). :class:`~eyeserver_client.errors.Conflict` while the daemon is busy."""
        return self._get(ops.ACTIVATE_CALIBRATION, CalibrationResponse,
                         path={"calibration_id": calibration_id})

    def download_calibration(self, calibration_id: str) -> bytes:
        """A calibration as a zip (with a guided calibration's input bundles: its evidence)."""
        return (self._call(ops.DOWNLOAD_CALIBRATION,
                           path={"calibration_id": calibration_id})).content

    def compare_calibrations(self, a: str, b: str) -> CalibrationComparison:
        """How far calibration ``b`` has drifted from ``a``, per camera: rotation (degrees),
        centre shift (mm), focal and principal point change (px), height change (mm)."""
        return self._get(ops.COMPARE_CALIBRATIONS, CalibrationComparison,
                         params={"a": a, "b": b})

    # --- guided calibration (physicists) -----------------------------------------------------

    def open_stereo_session(self, *, cols: int | None = None, rows: int | None = None,
                            square_mm: float | None = None) -> CalibrationSession:
        """Open a stereo calibration session; the daemon is ``calibrating`` (captures get
        Conflict) until its solve starts or it is closed.

        The board: inner corners ``cols`` × ``rows`` (one odd, one even) and the square's side
        in mm; left out, the simulated room's 9 × 6 corners of 4.5 mm.
        """
        board = _body(cols=cols, rows=rows, square_mm=square_mm)
        return self._get(ops.OPEN_SESSION, CalibrationSession,
                         json={"kind": "stereo", **({"board": board} if board else {})})

    def open_phase_height_session(
      self, calibration_id: str, *, z_range_mm: tuple[float, float] | None = None,
    ) -> CalibrationSession:
        """Open a phase-to-height session extending the geometry of a stored calibration (its
        parent) over ``z_range_mm`` (mm; default the parent's range, else −10…+25); the new
        calibration it solves is stored separately, never changing the parent. Its ``plan``
        says which plate heights this rig needs (or how the session will find out)."""
        body: dict[str, Any] = {"kind": "phase-height", "calibration_id": calibration_id}
        if z_range_mm is not None:
            body["z_range_mm"] = list(z_range_mm)
        return self._get(ops.OPEN_SESSION, CalibrationSession, json=body)

    def calibration_sessions(self) -> list[CalibrationSession]:
        """The sessions of this run of the daemon, newest first (kept in memory)."""
        answer = self._call(ops.LIST_SESSIONS)
        return parse(answer, _SessionList).items

    def calibration_session(self, session_id: str) -> CalibrationSession:
        """A session: its inputs so far, coverage or heights, readiness, job and result."""
        return self._get(ops.SESSION, CalibrationSession, path={"session_id": session_id})

    def close_calibration_session(self, session_id: str) -> CalibrationSession:
        """Abandon a session still acquiring: the daemon is released; its captures stay."""
        return self._get(ops.CLOSE_SESSION, CalibrationSession,
                         path={"session_id": session_id})

    def add_view(self, session_id: str, *, origin: bool | None = None) -> ViewStep:
        """Acquire a chessboard view (all cameras, projectors dark) in a stereo session.

        Answers which cameras found the board and the coverage so far (per camera, the share
        of 4 × 4 image cells touched by corners), ``ready`` and what is ``missing``: move the
        board and add views until ``ready``. The first view is the origin board (it defines
        the WCS) unless posted with ``origin=False``; then one later view needs ``origin=True``.
        """
        return self._get(ops.ADD_VIEW, ViewStep, path={"session_id": session_id},
                         json=None if origin is None else {"origin": origin})

    def add_plate(self, session_id: str, z_mm: float, *, move_stage: bool = False
                  ) -> PlateStep:
        """Acquire the flat plate at height ``z_mm`` (mm, WCS) in a phase-height session;
        with ``move_stage`` the daemon's motorised stage puts it there first, otherwise it was
        put there by hand. Answers what the session still needs (``plan``: the heights). A
        session whose solve failed takes more plates and can be solved again."""
        return self._get(ops.ADD_PLATE, PlateStep, path={"session_id": session_id},
                         json={"z_mm": z_mm, "move_stage": move_stage})

    def add_reference_plane(self, session_id: str, z_mm: float = 10.0
                            ) -> ReferencePlaneStep:
        """Acquire the reference plane at ``z_mm`` (mm; +10 by design) in a phase-height
        session; a second one replaces the first."""
        return self._get(ops.ADD_REFERENCE_PLANE, ReferencePlaneStep,
                         path={"session_id": session_id}, json={"z_mm": z_mm})

    def solve_calibration_session(self, session_id: str) -> JobResponse:
        """Solve a ready session as a job (:meth:`wait_for_job`); its result names the new
        calibration (``calibration_id``, not activated). The daemon is free again at once.
        :class:`~eyeserver_client.errors.Conflict` when not ready (the reason lists what is
        missing)."""
        return self._get(ops.SOLVE_SESSION, JobResponse, path={"session_id": session_id})

    # --- jobs --------------------------------------------------------------------------------

    def jobs(self) -> list[JobResponse]:
        """The jobs the daemon remembers (in memory: a restart forgets them)."""
        return (self._get(ops.LIST_JOBS, JobList)).items

    def job(self, job_id: str) -> JobResponse:
        """A job's state, progress (0–1), message, and its result or error."""
        return self._get(ops.JOB, JobResponse, path={"job_id": job_id})

    def cancel_job(self, job_id: str) -> JobResponse:
        """Ask a job to stop (a queued one at once, a running one at its next step)."""
        return self._get(ops.CANCEL_JOB, JobResponse, path={"job_id": job_id})

    def reconstruct_captures(self, capture_ids: Sequence[str]) -> JobResponse:
        """Reconstruct several captures with the active calibration as one job."""
        return self._get(ops.RECONSTRUCT_BATCH, JobResponse,
                         json={"capture_ids": list(capture_ids)})

    def wait_for_job(self, job_id: str, *, timeout_s: float = 600.0,
                     poll_s: float = 0.25) -> JobResponse:
        """Poll a job every ``poll_s`` seconds until it has finished (succeeded, failed or
        cancelled) and answer it; :class:`~eyeserver_client.errors.RequestTimeoutError` after
        ``timeout_s`` seconds (the job goes on)."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.job(job_id)
            if job.state in JOB_FINISHED:
                return job
            if time.monotonic() > deadline:
                raise RequestTimeoutError(f"job {job_id} has not finished after {timeout_s:g} s "
                                     f"({job.state}, {job.progress:.0%}: {job.message})")
            io.sleep(poll_s)

    # --- patients, eye models, references ---------------------------------------------------

    def put_patient(self, patient_id: str, *, eye: Literal["right", "left"],
                    unit: str | None = None, tolerance_mm: float | None = None,
                    tolerance_gaze_deg: float | None = None,
                    min_confidence: float | None = None) -> PatientResponse:
        """Create or update a patient (physicists only; audited with the id hashed).

        ``patient_id`` is the OIS's id (printable ASCII without spaces or ``/``, ≤ 128).
        ``unit`` is the unit whose cameras see the treated eye (default ``all``); the
        tolerances are the largest accepted translation (mm, default 0.2) and gaze deviation
        (degrees, default 1), ``min_confidence`` the smallest fit confidence that may pass
        (default 0.5). A field left out takes the daemon's default: the PUT stores the
        whole patient, also one that exists.
        """
        return self._get(ops.PUT_PATIENT, PatientResponse,
                         path={"patient_id": patient_id},
                         json=_body(eye=eye, unit=unit, tolerance_mm=tolerance_mm,
                                    tolerance_gaze_deg=tolerance_gaze_deg,
                                    min_confidence=min_confidence))

    def patient(self, patient_id: str) -> PatientResponse:
        """A patient with the eye-model version in use (NotFound if unknown)."""
        return self._get(ops.PATIENT, PatientResponse, path={"patient_id": patient_id})

    def add_eye_model(self, patient_id: str, *, globe_radius_mm: float | None = None,
                      ellipsoid: EllipsoidSpec | Mapping[str, Any] | None = None,
                      cornea_radius_mm: float | None = None,
                      limbus_diameter_mm: float | None = None,
                      globe_sd_mm: float | None = None,
                      source: str | None = None) -> EyeModelResponse:
        """Store a new version of the patient's eye model, used from now on (physicists only).

        Nothing given: the population model (globe radius fitted). ``globe_radius_mm`` gives a
        spherical globe, ``ellipsoid`` the MRI's anterior segment (``semi_axes_mm``,
        ``orientation``, ``centre_mm``), ``globe_sd_mm`` the error of either (default 0.2 mm,
        an MRI's typical): a check against a *planned* reference can pass only with an
        ellipsoid whose error leaves the centre's depth within half the tolerance (2 sd);
        otherwise the globe's uncertain shape fails it. Radii, diameter and sd in mm.
        """
        return self._get(ops.ADD_EYE_MODEL, EyeModelResponse,
                         path={"patient_id": patient_id}, json=_body(
                             globe_radius_mm=globe_radius_mm,
                             ellipsoid=None if ellipsoid is None else _dump(ellipsoid),
                             cornea_radius_mm=cornea_radius_mm,
                             limbus_diameter_mm=limbus_diameter_mm,
                             globe_sd_mm=globe_sd_mm, source=source))

    def eye_models(self, patient_id: str) -> list[EyeModelResponse]:
        """Every eye-model version of a patient, oldest first (the last is in use)."""
        return (self._get(ops.EYE_MODELS, EyeModelList,
                          path={"patient_id": patient_id})).items

    def eye_model(self, patient_id: str, version: int) -> EyeModelResponse:
        """One eye-model version."""
        return self._get(ops.EYE_MODEL, EyeModelResponse,
                         path={"patient_id": patient_id, "version": version})

    def set_reference(self, patient_id: str, fraction: int, *,
                      centre_mm: Sequence[float], gaze: Sequence[float],
                      limbus_centre_mm: Sequence[float] | None = None,
                      plan: str | None = None) -> ReferenceResponse:
        """Store the planned pose as the fraction's next reference version (physicists only):
        globe centre (mm), gaze (normalised by the daemon) and optionally the limbus centre
        (mm), all in the WCS; ``plan`` says which plan it comes from."""
        return self._get(ops.SET_REFERENCE, ReferenceResponse,
                         path={"patient_id": patient_id, "fraction": fraction},
                         json=_body(centre_mm=list(centre_mm), gaze=list(gaze),
                                    limbus_centre_mm=None if limbus_centre_mm is None
                                    else list(limbus_centre_mm), plan=plan))

    def capture_reference(self, patient_id: str, fraction: int) -> ReferenceResponse:
        """Measure the eye at set-up and store its pose as the fraction's next reference
        version, with its evidence (physicists only). Takes seconds; against a reference
        captured so, the eye model's unknown globe shape cancels."""
        return self._get(ops.CAPTURE_REFERENCE, ReferenceResponse,
                         path={"patient_id": patient_id, "fraction": fraction})

    def reference(self, patient_id: str, fraction: int) -> ReferenceResponse:
        """The fraction's reference in use (NotFound without one)."""
        return self._get(ops.REFERENCE, ReferenceResponse,
                         path={"patient_id": patient_id, "fraction": fraction})

    def references(self, patient_id: str, fraction: int) -> list[ReferenceResponse]:
        """Every reference version of a fraction, oldest first (the last is in use)."""
        return (self._get(ops.REFERENCES, ReferenceList,
                          path={"patient_id": patient_id, "fraction": fraction})).items

    # --- position verification ----------------------------------------------------------------

    def measure_pose(self, patient_id: str, fraction: int) -> Measurement:
        """Verify the eye's position before irradiation.

        The daemon captures the patient's unit, reconstructs with the active calibration, fits
        the patient's eye model and compares with the fraction's reference: ``deviation``
        (measured − reference: ``delta_mm``, ``length_mm``, ``gaze_deg``), ``passed`` with the
        ``reasons`` when not, the fitted ``pose`` and the ``evidence``. Stored. Takes seconds;
        never retried once sent (each call is a measurement).

        Raises :class:`~eyeserver_client.errors.NotFound` (no such patient or no reference),
        :class:`~eyeserver_client.errors.Conflict` (no active calibration, or busy; nothing
        captured), :class:`~eyeserver_client.errors.Invalid` (no eye could be fitted: the
        reason says why).
        """
        return self._get(ops.MEASURE, Measurement,
                         json={"patient_id": patient_id, "fraction": fraction})

    def measurements(self, patient_id: str, *, fraction: int | None = None,
                     limit: int = 50, offset: int = 0) -> MeasurementList:
        """A patient's stored measurements (of one ``fraction`` if given), newest first."""
        return self._get(ops.MEASUREMENTS, MeasurementList, params={
            "patient_id": patient_id, "fraction": fraction, "limit": limit, "offset": offset})

    def measurement(self, measurement_id: str) -> Measurement:
        """One stored measurement with its evidence (also after a restart)."""
        return self._get(ops.MEASUREMENT, Measurement,
                         path={"measurement_id": measurement_id})

    def measurement_dicom(self, measurement_id: str, *,
                          dicom_object: Literal["registration", "surface"] | None = None,
                          ) -> bytes:
        """A measurement as DICOM: a zip of ``registration.dcm`` (Spatial Registration: the
        eye's rigid motion from the reference) and ``surface.dcm`` (Surface Segmentation), or
        one of them (``dicom_object``) as the object's bytes.
        :class:`~eyeserver_client.errors.Conflict` for a measurement without a reference."""
        params = {"object": dicom_object} if dicom_object is not None else None
        return (self._call(ops.MEASUREMENT_DICOM, path={"measurement_id": measurement_id},
                           params=params)).content

    def import_plan_dicom(self, patient_id: str, fraction: int,
                          data: bytes | str | os.PathLike[str]) -> dict[str, Any]:
        """Import the plan's eye (physicists only): an RT Structure Set and, optionally, a
        Spatial Registration, as a zip or one DICOM object (its bytes or its path); a new eye
        model version and, with the registration, the fraction's reference. The answer says
        what was read and why anything was not set (``read.notes``)."""
        content = data if isinstance(data, bytes) else Path(data).read_bytes()
        kind = "application/zip" if content[:2] == b"PK" else "application/dicom"
        answer = self._call(ops.IMPORT_PLAN_DICOM, path={
            "patient_id": patient_id, "fraction": fraction}, content=content,
            headers={"Content-Type": kind})
        imported: dict[str, Any] = answer.json()
        return imported

    # --- the daily QA ------------------------------------------------------------------------

    def run_qa(self, *, baseline: bool = False, frames: int | None = None,
               timeout_s: float | None = 300.0) -> QaRun:
        """Run the daily QA: the QA phantom (eye phantom 1 at its QA position) captured by
        every unit ``frames`` times and measured against its drawing; the run, passed or not,
        with every figure against its threshold. ``baseline`` (physicists only) makes a
        passing run the active calibration's QA baseline. Takes seconds to a minute.
        :class:`~eyeserver_client.errors.Conflict` without an active calibration or while
        another run is under way."""
        return self._get(ops.RUN_QA, QaRun, json=_body(baseline=baseline, frames=frames),
                         timeout_s=timeout_s)

    def qa_runs(self, *, day: str | None = None, limit: int = 50,
                offset: int = 0) -> QaRunList:
        """Stored QA runs, newest first (of one local ``day``, YYYY-MM-DD, if given)."""
        return self._get(ops.QA_RUNS, QaRunList,
                         params={"day": day, "limit": limit, "offset": offset})

    def qa_run(self, run_id: str) -> QaRun:
        """One stored QA run."""
        return self._get(ops.QA_RUN, QaRun, path={"run_id": run_id})

    def qa_status(self) -> QaStatus:
        """Whether the daily QA locks position verification and tracking now, and why."""
        return self._get(ops.QA_STATUS, QaStatus)

    def override_qa(self, reason: str) -> QaStatus:
        """Lift the QA lockout for the rest of the day (physicists only; audited).
        :class:`~eyeserver_client.errors.Conflict` when nothing is locked."""
        return self._get(ops.QA_OVERRIDE, QaStatus, json={"reason": reason})

    def withdraw_qa_override(self) -> QaStatus:
        """End the QA override in force (physicists only; audited)."""
        return self._get(ops.WITHDRAW_QA_OVERRIDE, QaStatus)

    def qa_trends(self, *, days: int = 90) -> QaTrends:
        """Every QA figure's values over the last ``days`` days, with thresholds."""
        return self._get(ops.QA_TRENDS, QaTrends, params={"days": days})

    def qa_trend_png(self, figure: str, *, days: int = 90) -> bytes:
        """One QA figure's trend as a PNG."""
        return (self._call(ops.QA_TREND_PNG, path={"figure": figure},
                           params={"days": days})).content

    def qa_report(self, day: str | None = None) -> str:
        """A day's QA report (default today) as printable HTML."""
        return (self._call(ops.QA_REPORT, params={"day": day})).text

    # --- live tracking -----------------------------------------------------------------------

    def start_tracking(self, patient_id: str, fraction: int, *,
                       dwell_frames: int | None = None,
                       hold_on_drop: bool | None = None) -> TrackingStatus:
        """Start live tracking of the patient's unit at 25 Hz against the fraction's
        reference; read the poses and the beam-hold flag with :meth:`poses`.

        ``dwell_frames`` good frames in a row lower the beam hold after it rose (default 3);
        ``hold_on_drop`` holds on a gap of more than two unprocessed frames (default true).
        Answers once the workers are ready (a few seconds).
        :class:`~eyeserver_client.errors.Conflict` when no calibration is active, the daemon
        is busy, or the eye model lacks the globe's shape against a planned reference.
        """
        return self._get(ops.START_TRACKING, TrackingStatus,
                         json=_body(patient_id=patient_id, fraction=fraction,
                                    dwell_frames=dwell_frames, hold_on_drop=hold_on_drop))

    def stop_tracking(self) -> TrackingStatus:
        """End live tracking; the final counts (Conflict when not tracking)."""
        return self._get(ops.STOP_TRACKING, TrackingStatus)

    def tracking(self) -> TrackingStatus:
        """The running or last tracking session: frames acquired, processed, dropped, missed
        and held, the beam hold, a stall, the error that ended it, the last message."""
        return self._get(ops.TRACKING, TrackingStatus)

    def tracking_preview(self, camera: str) -> bytes:
        """The newest frame of a camera of the tracked unit, as a grey JPEG (the frame the
        pose is measured from; no extra exposure). :class:`~eyeserver_client.errors.Conflict`
        when not tracking."""
        return (self._call(ops.TRACKING_PREVIEW, path={"camera": camera})).content

    # --- streams -----------------------------------------------------------------------------

    def events(self, *, reconnect: bool = True, silence_s: float | None = None,
               max_attempts: int | None = None) -> MessageStream:
        """The daemon's event stream (``/ws/events``): a ``Hello``, then every event.

        Yields :mod:`~eyeserver_client.messages` models; reconnects when the connection is
        lost, yielding ``Disconnected`` at once and, once back, ``Resumed`` (how many events
        were lost: the daemon sends again the ones that went by while it keeps them, its
        newest 1024) and those events (see
        :class:`~eyeserver_client._streams_sync.MessageStream`).
        ``silence_s``: take the link as dead after that long without a message (the event
        stream sends nothing while nothing happens: None, the default, waits; the WebSocket's
        own pings still find a dead peer within about 40 s).
        """
        return MessageStream(self.connection, "/ws/events", parse_event_message,
                             reconnect=reconnect, silence_s=silence_s,
                             max_attempts=max_attempts, replays=True)

    def poses(self, *, reconnect: bool = True, silence_s: float = POSE_SILENCE_S,
              max_attempts: int | None = None) -> MessageStream:
        """Live tracking's pose stream (``/ws/pose``): a ``PoseMessage`` per processed frame
        with the beam-hold flag, ``HoldMessage`` when the daemon holds the beam without a
        frame, ``Heartbeat`` after a second of silence.

        A link silent for ``silence_s`` seconds (default 2) is taken as dead: ``Disconnected``
        (``beam_hold`` true) is yielded at once and the stream reconnects.
        """
        return MessageStream(self.connection, "/ws/pose", parse_pose_message,
                             reconnect=reconnect, silence_s=silence_s,
                             max_attempts=max_attempts)

    # --- the simulated room (demonstrations and tests; NotFound on real hardware) ------------

    def sim_scene(self) -> SceneSpec:
        """The scene in front of the simulated cameras."""
        return self._get(ops.SIM_SCENE, SceneSpec)

    def set_sim_scene(self, scene: SceneSpec | Mapping[str, Any]) -> SceneSpec:
        """Place a scene (``kind``: empty, chessboard, plate, reference, pyramid, wedge,
        eye_phantom_1/2, eye; ``position_mm``, ``rotation_deg``, …). Conflict while busy."""
        return self._get(ops.SET_SIM_SCENE, SceneSpec, json=_dump(scene))

    def set_sim_stage(self, z_mm: float) -> SceneSpec:
        """Move the simulated stage's flat plate to ``z_mm`` (mm; travel −15…+30)."""
        return self._get(ops.SET_SIM_STAGE, SceneSpec, json={"z_mm": z_mm})

    def set_sim_chessboard(self, *, position_mm: Sequence[float] | None = None,
                           rotation_deg: Sequence[float] | None = None) -> SceneSpec:
        """Place the calibration chessboard (mm, degrees; left out: the default pose)."""
        return self._get(ops.SET_SIM_CHESSBOARD, SceneSpec, json=_body(
            position_mm=None if position_mm is None else list(position_mm),
            rotation_deg=None if rotation_deg is None else list(rotation_deg)))

    def sim_eye(self) -> SimEyeResponse:
        """The simulated eye's true pose now (ground truth: for people and tests)."""
        return self._get(ops.SIM_EYE, SimEyeResponse)

    def set_sim_eye(self, *, position_mm: Sequence[float] | None = None,
                    rotation_deg: Sequence[float] | None = None,
                    gaze_deg: Sequence[float] | None = None,
                    globe_radius_mm: float | None = None,
                    cornea_radius_mm: float | None = None,
                    limbus_diameter_mm: float | None = None,
                    motion: MotionSpec | Mapping[str, Any] | None = None,
                    still: bool = False) -> SimEyeResponse:
        """Pose the simulated eye (the scene becomes the eye); what is left out stays.

        ``motion`` starts a movement (drift, saccades, blinks, a script) now; ``still=True``
        stops any (``motion: null``). Positions mm, angles degrees.
        """
        body = _body(position_mm=None if position_mm is None else list(position_mm),
                     rotation_deg=None if rotation_deg is None else list(rotation_deg),
                     gaze_deg=None if gaze_deg is None else list(gaze_deg),
                     globe_radius_mm=globe_radius_mm, cornea_radius_mm=cornea_radius_mm,
                     limbus_diameter_mm=limbus_diameter_mm,
                     motion=None if motion is None else _dump(motion))
        if still:
            body["motion"] = None
        return self._get(ops.SET_SIM_EYE, SimEyeResponse, json=body)

    def sim_prerender(self, unit: str, seconds: float) -> PrerenderResponse:
        """Render what ``unit``'s cameras will see of the moving eye over the next ``seconds``
        (0–120) before answering, so live tracking measures the daemon, not the renderer."""
        return self._get(ops.PRERENDER, PrerenderResponse,
                         json={"unit": unit, "seconds": seconds})

    def sim_prerender_status(self) -> dict[str, Any]:
        """Per camera: pre-rendered frames left, used, and rendered live."""
        return parse(self._call(ops.SIM_PRERENDER), dict[str, Any])

    def sim_truth(self, t_s: float | None = None) -> dict[str, Any]:
        """The current scene's ground truth (at clock time ``t_s``, s), as
        ``eyeserver sim render`` writes ``truth.json``."""
        return parse(self._call(ops.SIM_TRUTH, params={"t_s": t_s}), dict[str, Any])

    def connect_sim_device(self, device_id: str, connected: bool) -> SimDeviceResponse:
        """Unplug (``False``) or replug a simulated device: fault injection (physicists)."""
        return self._get(ops.CONNECT_SIM_DEVICE, SimDeviceResponse,
                         path={"device_id": device_id}, json={"connected": connected})


class _SessionList(BaseModel):
    items: list[CalibrationSession]
