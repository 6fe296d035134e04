"""What an oncology information system (OIS) does: patient → reference → measure → verdict.

Run against a daemon with an active calibration::

    python ois_verification.py P-0001 --fraction 1 --eye right           # reference at set-up
    python ois_verification.py P-0001 --fraction 2 --eye right \\
        --planned-centre 0 0 -10 --planned-gaze 0 0 1 --ellipsoid 12.1 11.9 12.4

Setting up the patient and the reference needs a physicist's token; measuring an operator's
(``$EYESERVER_TOKEN``, or ``--token-file``). Exit status: 0 when the position verification
passed, 1 when it failed (the reasons are printed), 2 when it could not be done.

A reference is either captured at set-up (the eye is measured and its pose stored) or taken
from the treatment plan. Against a planned reference the eye model must know the globe's shape
(the MRI's ellipsoid): without it the fitted centre may lie ≈ 0.65 mm off along the gaze and
the check fails, saying so.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from eyeserver_client import Client, EyeserverError, Invalid
from eyeserver_client.models import Measurement


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
    args = parser.parse_args(argv)
    try:
        with Client(args.url, token_file=args.token_file) as client:
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
