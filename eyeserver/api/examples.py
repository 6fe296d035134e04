"""Request and response examples of the clinical workflow's operations, for the OpenAPI
document (Swagger UI at ``/api/v1/docs`` shows them beside each schema).

:func:`install` puts them into the document once FastAPI has generated it: given to FastAPI as
a route's ``openapi_extra`` they would lose every null (the document is serialised with
``exclude_none``), and the examples' nulls are part of what they show.

The answers are shaped after what the simulated room answers (ids, times and figures of one
run, shortened where a list is long). tests/test_openapi_examples.py checks that every operation
of the workflow carries them and that each one validates against its operation's models.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI

__all__ = ["CAPTURE", "CAPTURES", "EXAMPLES", "MEASUREMENT", "PATIENT", "REFERENCE_CAPTURED",
           "REFERENCE_PLANNED", "TRACKING_RUNNING", "TRACKING_STOPPED", "install", "operation"]

_CALIBRATION = "cal-20261205T101502117Z-3c9e"
_CAPTURE_ID = "cap-20261205T113912410Z-8a1f"

PATIENT: dict[str, Any] = {
    "patient_id": "P-0001", "key": "pat-3f2a9c1d0b7e4a65", "eye": "right", "unit": "left",
    "tolerance_mm": 0.5, "tolerance_gaze_deg": 1.0, "min_confidence": 0.5,
    "eye_model_version": None, "created": "2026-12-05T11:38:02.511Z",
    "updated": "2026-12-05T11:38:02.511Z"}

_FIT: dict[str, Any] = {
    "centre_mm": [0.012, -0.031, -10.004], "centre_sd_mm": [0.004, 0.004, 0.006],
    "globe_radius_mm": 12.01, "limbus_centre_mm": [0.009, -0.022, 0.893], "limbus_sd_mm": 0.008,
    "gaze": [0.0002, 0.0007, 0.99999], "gaze_sd_deg": 0.05, "torsion_deg": None,
    "surface_mad_mm": 0.011, "sclera_points": 5936, "confidence": 0.93, "gaze_source": "limbus",
    "boundary_radius_mm": 5.82, "cornea_points": 2114, "fit_ms": 640.2, "shape_sd_mm": 0.0}

_EVIDENCE: dict[str, Any] = {
    "capture_id": _CAPTURE_ID, "unit": "left", "calibration_id": _CALIBRATION,
    "eye_model_version": None, "eye_model": None, "cloud_points": 48213,
    "units": {"left": {"points": 48213, "cameras": {"S1": 24410, "S2": 23803}}}, "fit": _FIT}

REFERENCE_PLANNED: dict[str, Any] = {
    "centre_mm": [0.0, 0.0, -10.0], "gaze": [0.0, 0.0, 1.0], "limbus_centre_mm": None,
    "plan": "plan 4, v2"}

REFERENCE_CAPTURED: dict[str, Any] = {
    "fraction": 1, "version": 2, "created": "2026-12-05T11:39:14.902Z", "actor": "therapist",
    "source": "capture", "plan": None,
    "pose": {"centre_mm": _FIT["centre_mm"], "gaze": _FIT["gaze"],
             "limbus_centre_mm": _FIT["limbus_centre_mm"]},
    "evidence": _EVIDENCE}

MEASUREMENT: dict[str, Any] = {
    "id": "pose-20261205T114031077Z-51c0", "patient_id": "P-0001", "fraction": 1,
    "eye": "right", "created": "2026-12-05T11:40:31.077Z", "actor": "therapist",
    "passed": True, "in_tolerance": True, "reasons": [],
    "deviation": {"delta_mm": [0.021, -0.013, 0.034], "length_mm": 0.042, "gaze_deg": 0.06,
                  "limbus_delta_mm": [0.018, -0.009, 0.029], "model_sd_mm": 0.0,
                  "measured_sd_mm": [0.021, 0.024, 0.068]},
    "tolerances": {"translation_mm": 0.5, "gaze_deg": 1.0, "min_confidence": 0.5},
    "pose": _FIT,
    "reference": {"version": 2, "source": "capture", "pose": REFERENCE_CAPTURED["pose"]},
    "evidence": {**_EVIDENCE, "capture_id": "cap-20261205T114028544Z-0d77"},
    "format": "eyeserver.pose-measurement/1"}

CAPTURE: dict[str, Any] = {
    "id": _CAPTURE_ID, "kind": "measurement", "unit": "left", "calibration_id": _CALIBRATION,
    "created": "2026-12-05T11:39:12.410Z", "frame_count": 1, "status": "ok"}

CAPTURES: dict[str, Any] = {"items": [CAPTURE], "total": 1, "limit": 50, "offset": 0}

_POSE_MESSAGE: dict[str, Any] = {
    "type": "pose", "seq": 412, "time": "2026-12-05T11:41:07.262Z", "t": 5104.84, "t_ns":
    5104840000000, "frame": 87, "pose": {"centre_mm": [0.015, -0.028, -10.011],
                                        "limbus_centre_mm": [0.011, -0.02, 0.887],
                                        "gaze": [0.0003, 0.0006, 0.99999]},
    "deviation": {"delta_mm": [0.003, 0.003, -0.007], "length_mm": 0.008, "gaze_deg": 0.01},
    "in_tolerance": True, "beam_hold": False, "confidence": 0.91, "eye": "seen", "reasons": [],
    "dropped_frames": 3, "missed_frames": 0, "delivery_ms": 4.1, "processing_ms": 31.7,
    "latency_ms": 36.2}

_TRACKING: dict[str, Any] = {
    "patient_id": "P-0001", "fraction": 1, "unit": "left", "rate_hz": 25.0, "workers": 2,
    "reference_version": 2, "eye_model_version": None}

TRACKING_RUNNING: dict[str, Any] = {
    **_TRACKING, "running": True, "started": "2026-12-05T11:41:03.710Z", "stopped": None,
    "frames_acquired": 0, "frames_processed": 0, "frames_dropped": 0, "frames_missed": 0,
    "frames_held": 0, "beam_hold": True, "stalled": None, "stalls": 0, "deadline_ms": 80.0,
    "error": None, "last_message": None}

TRACKING_STOPPED: dict[str, Any] = {
    **TRACKING_RUNNING, "running": False, "stopped": "2026-12-05T11:41:07.301Z",
    "frames_acquired": 91, "frames_processed": 86, "frames_dropped": 4, "frames_held": 3,
    "last_message": _POSE_MESSAGE}


def operation(*, request: dict[str, dict[str, Any]] | None = None,
              response: dict[str, dict[str, Any]] | None = None,
              status_code: int = 200) -> dict[str, Any]:
    """The parts of an OpenAPI operation that carry ``request`` and ``response`` examples by
    name, each ``{"summary": …, "value": …}``."""
    extra: dict[str, Any] = {}
    if request:
        extra["requestBody"] = {"content": {"application/json": {"examples": request}}}
    if response:
        extra["responses"] = {str(status_code): {"content": {"application/json": {
            "examples": response}}}}
    return extra


EXAMPLES: dict[tuple[str, str], dict[str, Any]] = {
    ("put", "/patients/{patient_id}"): operation(
        request={"right_eye_left_unit": {
            "summary": "The right eye, seen by unit left, the plan's tolerances",
            "value": {"eye": "right", "unit": "left", "tolerance_mm": 0.5,
                      "tolerance_gaze_deg": 1.0, "min_confidence": 0.5}}},
        response={"patient": {"summary": "The patient as stored (201 when created)",
                              "value": PATIENT}}),
    ("put", "/patients/{patient_id}/fractions/{fraction}/reference"): operation(
        request={"planned": {"summary": "The plan's globe centre and gaze",
                             "value": REFERENCE_PLANNED}},
        response={"stored": {"summary": "Version 1 of fraction 1, from the plan", "value": {
            "fraction": 1, "version": 1, "created": "2026-12-05T11:38:05.130Z",
            "actor": "physicist", "source": "plan", "plan": "plan 4, v2",
            "pose": {"centre_mm": [0.0, 0.0, -10.0], "gaze": [0.0, 0.0, 1.0],
                     "limbus_centre_mm": None}, "evidence": None}}},
        status_code=201),
    ("post", "/patients/{patient_id}/fractions/{fraction}/reference/capture"): operation(
        response={"captured": {"summary": "The eye as measured at set-up, with its evidence",
                               "value": REFERENCE_CAPTURED}}, status_code=201),
    ("post", "/pose/measure"): operation(
        request={"fraction": {"summary": "Verify fraction 1 of P-0001",
                              "value": {"patient_id": "P-0001", "fraction": 1}}},
        response={"passed": {"summary": "In tolerance: the verdict with its evidence",
                             "value": MEASUREMENT}}, status_code=201),
    ("post", "/tracking/start"): operation(
        request={"fraction": {"summary": "Track P-0001 for fraction 1",
                              "value": {"patient_id": "P-0001", "fraction": 1,
                                        "dwell_frames": 3, "hold_on_drop": True}}},
        response={"started": {"summary": "Started: no frame yet, the beam held",
                              "value": TRACKING_RUNNING}}, status_code=201),
    ("post", "/tracking/stop"): operation(
        response={"stopped": {"summary": "The session's counts and its last pose message",
                              "value": TRACKING_STOPPED}}),
    ("post", "/captures"): operation(
        request={"unit": {"summary": "One frame set of unit left", "value": {"unit": "left"}},
                 "all": {"summary": "Every unit, interleaved", "value": {"unit": "all"}}},
        response={"stored": {"summary": "The capture, durable on disk", "value": CAPTURE}},
        status_code=201),
    ("get", "/captures"): operation(
        response={"page": {"summary": "A page of captures, newest first",
                           "value": CAPTURES}}),
}
"""The examples by (method, path under the API prefix)."""


def install(app: FastAPI, prefix: str) -> None:
    """Add :data:`EXAMPLES` to ``app``'s OpenAPI document as it is generated (an operation the
    app does not have is an error: the table must follow the routes)."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        document = generate()
        for (method, path), parts in EXAMPLES.items():
            found = document["paths"][f"{prefix}{path}"][method]
            if "requestBody" in parts:
                found["requestBody"]["content"]["application/json"].update(
                    parts["requestBody"]["content"]["application/json"])
            for status_code, answer in parts.get("responses", {}).items():
                found["responses"][status_code]["content"]["application/json"].update(
                    answer["content"]["application/json"])
        app.openapi_schema = document
        return document

    app.openapi = openapi  # type: ignore[method-assign]
