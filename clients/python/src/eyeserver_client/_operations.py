"""Every operation of the daemon's HTTP API this client calls, and whether it may be repeated.

One table for both clients. ``idempotent`` says whether sending the request twice leaves the
daemon as sending it once: only those are retried after a failure that leaves unknown whether
the daemon acted (a broken connection, a 503 with ``Retry-After``). The API has no idempotency
key, so nothing that creates (a capture, a measurement, a reference version, a session step, a
job) is ever repeated; a request that never reached the daemon (no connection made) is retried
whatever it is. The tests check this table against the daemon's OpenAPI document both ways.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["OPERATIONS", "Operation"]


@dataclass(frozen=True)
class Operation:
    """One HTTP operation: ``method`` and ``path`` as the OpenAPI document writes them (under
    ``/api/v1`` unless ``under_api`` is false)."""

    method: str
    path: str
    idempotent: bool
    under_api: bool = True


def _get(path: str, *, under_api: bool = True) -> Operation:
    return Operation("GET", path, idempotent=True, under_api=under_api)


def _once(method: str, path: str) -> Operation:
    return Operation(method, path, idempotent=False)


def _again(method: str, path: str) -> Operation:
    return Operation(method, path, idempotent=True)


# The daemon
HEALTH = _get("/health")
STATUS = _get("/status")
WHOAMI = _get("/whoami")
METRICS = _get("/metrics", under_api=False)
AUDIT = _get("/audit")
DEVICES = _get("/devices")
DEVICE = _get("/devices/{device_id}")
CONFIGURE_DEVICE = _again("PATCH", "/devices/{device_id}")  # absolute values
# Captures and reconstructions
CREATE_CAPTURE = _once("POST", "/captures")
LIST_CAPTURES = _get("/captures")
CAPTURE = _get("/captures/{capture_id}")
DELETE_CAPTURE = _once("DELETE", "/captures/{capture_id}")  # a second one is a 404
CAPTURE_BUNDLE = _get("/captures/{capture_id}/bundle.zip")
CAPTURE_IMAGE = _get("/captures/{capture_id}/frames/{frame}/{camera}.png")
RECONSTRUCT = _once("POST", "/captures/{capture_id}/reconstruction")
RECONSTRUCTION = _get("/captures/{capture_id}/reconstruction")
CLOUD = _get("/captures/{capture_id}/cloud.ply")
PREVIEW = _get("/captures/{capture_id}/preview.png")
# Calibrations
LIST_CALIBRATIONS = _get("/calibrations")
IMPORT_CALIBRATION = _once("POST", "/calibrations")
COMPARE_CALIBRATIONS = _get("/calibrations/compare")
CALIBRATION = _get("/calibrations/{calibration_id}")
DOWNLOAD_CALIBRATION = _get("/calibrations/{calibration_id}/download")
ACTIVATE_CALIBRATION = _again("POST", "/calibrations/{calibration_id}/activate")
# Guided calibration sessions
LIST_SESSIONS = _get("/calibration-sessions")
OPEN_SESSION = _once("POST", "/calibration-sessions")
SESSION = _get("/calibration-sessions/{session_id}")
CLOSE_SESSION = _again("DELETE", "/calibration-sessions/{session_id}")  # a closed one stays so
ADD_VIEW = _once("POST", "/calibration-sessions/{session_id}/views")
ADD_PLATE = _once("POST", "/calibration-sessions/{session_id}/plates")
ADD_REFERENCE_PLANE = _once("POST", "/calibration-sessions/{session_id}/reference")
SOLVE_SESSION = _once("POST", "/calibration-sessions/{session_id}/solve")
# Jobs
LIST_JOBS = _get("/jobs")
JOB = _get("/jobs/{job_id}")
CANCEL_JOB = _again("POST", "/jobs/{job_id}/cancel")  # a finished job is left as it is
RECONSTRUCT_BATCH = _once("POST", "/jobs/reconstructions")
# Patients, eye models, references
PUT_PATIENT = _again("PUT", "/patients/{patient_id}")  # the same body, the same patient
PATIENT = _get("/patients/{patient_id}")
ADD_EYE_MODEL = _once("POST", "/patients/{patient_id}/eye-models")
EYE_MODELS = _get("/patients/{patient_id}/eye-models")
EYE_MODEL = _get("/patients/{patient_id}/eye-models/{version}")
# Each PUT stores the fraction's next reference version: not repeated.
SET_REFERENCE = _once("PUT", "/patients/{patient_id}/fractions/{fraction}/reference")
REFERENCE = _get("/patients/{patient_id}/fractions/{fraction}/reference")
CAPTURE_REFERENCE = _once("POST", "/patients/{patient_id}/fractions/{fraction}/reference/capture")
REFERENCES = _get("/patients/{patient_id}/fractions/{fraction}/references")
# Each import stores a new eye-model version (and reference): not repeated.
IMPORT_PLAN_DICOM = _once("POST", "/patients/{patient_id}/fractions/{fraction}/dicom")
# Position verification
MEASURE = _once("POST", "/pose/measure")
MEASUREMENTS = _get("/pose/measurements")
MEASUREMENT = _get("/pose/measurements/{measurement_id}")
MEASUREMENT_DICOM = _get("/pose/measurements/{measurement_id}/dicom")
# Live tracking
START_TRACKING = _once("POST", "/tracking/start")
STOP_TRACKING = _once("POST", "/tracking/stop")  # a second one is a 409
TRACKING = _get("/tracking")
TRACKING_PREVIEW = _get("/tracking/preview/{camera}.jpg")
# The daily QA (docs/qa.md)
RUN_QA = _once("POST", "/qa/runs")
QA_RUNS = _get("/qa/runs")
QA_RUN = _get("/qa/runs/{run_id}")
QA_STATUS = _get("/qa/status")
QA_OVERRIDE = _once("POST", "/qa/override")  # a second one is a 409 (nothing locked)
WITHDRAW_QA_OVERRIDE = _once("DELETE", "/qa/override")  # a second one is a 404
QA_TRENDS = _get("/qa/trends")
QA_TREND_PNG = _get("/qa/trends/{figure}.png")
QA_REPORT = _get("/qa/report")
# The simulated room (demonstrations and tests; 404 on real hardware)
SIM_SCENE = _get("/sim/scene")
SET_SIM_SCENE = _again("PUT", "/sim/scene")
SET_SIM_STAGE = _again("PUT", "/sim/stage")
SET_SIM_CHESSBOARD = _again("PUT", "/sim/chessboard")
SIM_EYE = _get("/sim/eye")
SET_SIM_EYE = _once("PUT", "/sim/eye")  # a motion restarts when it is set again
SIM_PRERENDER = _get("/sim/eye/prerender")
PRERENDER = _once("POST", "/sim/eye/prerender")
SIM_TRUTH = _get("/sim/truth")
CONNECT_SIM_DEVICE = _again("PUT", "/sim/devices/{device_id}")

OPERATIONS: dict[str, Operation] = {
    name: value for name, value in dict(globals()).items() if isinstance(value, Operation)}
"""Every operation above by its constant's name."""
