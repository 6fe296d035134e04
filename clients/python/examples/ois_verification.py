"""What an oncology information system (OIS) does: patient → reference → measure → verdict.

Run against a daemon with an active calibration::

    python ois_verification.py P-0001 --fraction 1 --eye right --qa --simulated
    python ois_verification.py P-0001 --fraction 2 --eye right \\
        --planned-centre 0 0 -10 --planned-gaze 0 0 1 --ellipsoid 12.1 11.9 12.4

The daemon refuses to verify (409) until the day's QA has passed with the active calibration,
and a new calibration needs a physicist's QA baseline first (docs/qa.md). ``--qa`` runs that
QA first when the lockout asks for it (the baseline run when the calibration has none): it
asks you to put the QA phantom at its QA position and, after the run, the patient back; with
``--simulated`` it places the phantom in the simulated room itself and then the scene that
was there before. Without ``--qa`` the QA is someone else's morning routine.

Setting up the patient and the reference, and a QA baseline, need a physicist's token;
measuring and the daily QA an operator's (``$EYESERVER_TOKEN``, or ``--token-file``). Exit
status: 0 when the position verification passed, 1 when it failed (the reasons are printed), 2
when it could not be done (a failed QA among the reasons).

A reference is either captured at set-up (the eye is measured and its pose stored) or taken
from the treatment plan. Against a planned reference the eye model must know the globe's shape
(the MRI's ellipsoid): without it the fitted centre may lie ≈ 0.65 mm off along the gaze and
the check fails, saying so.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from eyeserver_client import Client, EyeserverError, Invalid
from eyeserver_client.models import Measurement, QaStatus

#: The QA phantom at its QA position in the simulated room (docs/qa.md): eye phantom 1's ball
#: centred on the isocentre.
QA_PHANTOM_SCENE = {"kind": "eye_phantom_1", "position_mm": [0.0, 0.0, 0.0]}

Prompt = Callable[[str], None]
"""Asks someone in the room to do something and returns when it is done."""


def ask(what: str) -> None:
    """The real room's prompt: say what to do, wait for Enter."""
    input(f"{what}, then press Enter ")


def daily_qa(client: Client, *, simulated: bool = False, place: Prompt = ask,
             say: Prompt = print) -> QaStatus:
    """The day's QA, when the lockout asks for it: nothing if verification is not locked;
    otherwise the QA phantom at its QA position (``place`` asks for it; ``simulated``: put
    there in the simulated room), a QA run (the calibration's baseline if it has none: a
    physicist's token), the patient's scene again. Raises :class:`EyeserverError` with the
    reasons when the run fails or verification stays locked; returns the QA status."""
    status = client.qa_status()
    if not status.locked:
        return status
    if status.calibration_id is None:
        raise EyeserverError(f"the daily QA cannot run: {status.reason}")
    baseline = status.baseline_run_id is None  # a new calibration: its baseline first
    say(f"QA lockout: {status.reason}")
    scene = client.sim_scene() if simulated else None  # to put back: the eye as it was
    if scene is not None:
        client.set_sim_scene(QA_PHANTOM_SCENE)
    else:
        place("put the QA phantom at its QA position (ball centre on the isocentre)")
    try:
        run = client.run_qa(baseline=baseline)
    finally:
        if scene is not None:
            client.set_sim_scene(scene)
        else:
            place("take the QA phantom away and seat the patient")
    figures = ", ".join(f"{name} {figure.value:.4f}" for name, figure in run.figures.items()
                        if figure.value is not None)
    say(f"QA {run.id}{' (baseline)' if run.baseline else ''}: "
        f"{'passed' if run.passed else 'FAILED'} ({figures})")
    if not run.passed:
        raise EyeserverError(f"the daily QA failed: {'; '.join(run.reasons)}")
    status = client.qa_status()
    if status.locked:
        raise EyeserverError(f"still locked after the QA: {status.reason}")
    return status


def prepare(client: Client, patient_id: str, fraction: int, *, eye: str, unit: str = "all",
            planned_centre_mm: Sequence[float] | None = None,
            planned_gaze: Sequence[float] | None = None,
            ellipsoid_mm: Sequence[float] | None = None) -> None:
    """The physicist's part: the patient, its eye model, the fraction's reference."""
    client.put_patient(patient_id, eye="left" if eye == "left" else "right", unit=unit)
    if ellipsoid_mm is not None:
        client.add_eye_model(patient_id, ellipsoid={"semi_axes_mm": list(ellipsoid_mm)},
                             source="MRI")
    if planned_centre_mm is not None and planned_gaze is not None:
        client.set_reference(patient_id, fraction, centre_mm=planned_centre_mm,
                             gaze=planned_gaze, plan="from the OIS")
    else:
        reference = client.capture_reference(patient_id, fraction)  # the eye, now
        print(f"reference v{reference.version} captured: centre "
              f"{_mm(reference.pose.centre_mm)} mm, gaze {_mm(reference.pose.gaze)}")


def verify(client: Client, patient_id: str, fraction: int) -> Measurement:
    """The OIS's call before irradiation: measure and judge against the reference."""
    result = client.measure_pose(patient_id, fraction)
    deviation = result.deviation
    verdict = "PASS" if result.passed else "FAIL"
    print(f"{verdict} {result.id}: Δ {_mm(deviation.delta_mm)} mm (|Δ| "
          f"{deviation.length_mm:.3f} mm), gaze {deviation.gaze_deg:.2f}°, confidence "
          f"{result.pose.confidence:.2f}")
    for reason in result.reasons:
        print(f"  {reason}")
    print(f"  evidence: capture {result.evidence.capture_id}, calibration "
          f"{result.evidence.calibration_id}")
    return result


def _mm(vector: Sequence[float]) -> str:
    return "[" + ", ".join(f"{v:+.3f}" for v in vector) + "]"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("patient_id")
    parser.add_argument("--fraction", type=int, required=True)
    parser.add_argument("--eye", choices=("right", "left"), required=True)
    parser.add_argument("--unit", default="all", help="the unit that sees the treated eye")
    parser.add_argument("--planned-centre", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="planned globe centre, mm, WCS (default: capture at set-up)")
    parser.add_argument("--planned-gaze", type=float, nargs=3, metavar=("X", "Y", "Z"))
    parser.add_argument("--ellipsoid", type=float, nargs=3, metavar=("A", "B", "C"),
                        help="the MRI ellipsoid's semi-axes, mm")
    parser.add_argument("--url", help="the daemon (default $EYESERVER_URL or 127.0.0.1:8000)")
    parser.add_argument("--token-file", help="file holding the token")
    parser.add_argument("--skip-setup", action="store_true",
                        help="patient and reference exist: only measure")
    parser.add_argument("--qa", action="store_true",
                        help="run the day's QA first if the lockout asks for it")
    parser.add_argument("--simulated", action="store_true",
                        help="with --qa: place the QA phantom in the simulated room")
    args = parser.parse_args(argv)
    try:
        with Client(args.url, token_file=args.token_file) as client:
            if args.qa:
                daily_qa(client, simulated=args.simulated)
            if not args.skip_setup:
                prepare(client, args.patient_id, args.fraction, eye=args.eye, unit=args.unit,
                        planned_centre_mm=args.planned_centre, planned_gaze=args.planned_gaze,
                        ellipsoid_mm=args.ellipsoid)
            result = verify(client, args.patient_id, args.fraction)
    except Invalid as exc:  # e.g. no eye could be fitted: a failed verification, with why
        print(f"FAIL: {exc.reason}", file=sys.stderr)
        return 1
    except EyeserverError as exc:
        print(f"verification not done: {exc}", file=sys.stderr)
        return 2
    return 0 if result.passed else 1


if __name__ == "__main__":
    sys.exit(main())
