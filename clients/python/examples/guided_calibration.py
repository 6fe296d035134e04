"""The physicist's guided calibration: stereo views, plate heights, solve, compare, activate.

Run against a daemon (a physicist's token in ``$EYESERVER_TOKEN``)::

    python guided_calibration.py                       # stereo, then phase-to-height on it
    python guided_calibration.py --parent cal-…        # phase-to-height on a stored one
    python guided_calibration.py --simulated --activate

In a real room the script asks you to place the chessboard (then the reference plane) and
waits for Enter; the plate moves on the motorised stage. With ``--simulated`` it places them
itself in the simulated room. The daemon says after each view which cameras found the board
and which image cells still lack corners: add views until it says the session is ready.
Nothing is activated unless you ask (``--activate``): compare first.

A calibration just activated has no QA baseline, and the daemon refuses position verification
and tracking until it has one (docs/qa.md). With ``--activate`` the script then runs the QA
baseline: it asks you to put the QA phantom at its QA position (``--simulated``: it puts it in
the simulated room, then the patient's eye), and fails when the baseline run does.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from eyeserver_client import Client, EyeserverError
from eyeserver_client.models import CalibrationResponse, QaRun

#: Chessboard poses (position mm, rotation degrees) that calibrate the simulated room: the
#: first is the origin board; the others tilt and turn it so each camera sees it
#: foreshortened several ways.
SIMULATED_BOARD_POSES: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = [
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ((0.0, 0.0, 5.0), (20.0, 0.0, 0.0)),
    ((0.0, 0.0, 5.0), (-20.0, 0.0, 0.0)),
    ((0.0, 0.0, -5.0), (0.0, 22.0, 0.0)),
    ((0.0, 0.0, -5.0), (0.0, -22.0, 0.0)),
    ((3.0, -2.0, 10.0), (15.0, 15.0, 10.0)),
    ((-3.0, 2.0, 10.0), (-15.0, -15.0, -10.0)),
    ((2.0, 3.0, -8.0), (18.0, -18.0, 25.0)),
    ((-2.0, -3.0, -8.0), (-18.0, 18.0, -25.0)),
    ((0.0, 0.0, 15.0), (0.0, 0.0, 90.0)),
    ((0.0, 0.0, 0.0), (10.0, -25.0, 180.0)),
    ((4.0, 0.0, 3.0), (-25.0, 10.0, 45.0)),
]

#: The Z range (mm, WCS) the phase-to-height calibration covers here: the eye's surface near
#: 0 and the reference plane. The daemon says which plate heights in it this rig needs.
Z_RANGE_MM = (-4.0, 10.0)
REFERENCE_Z_MM = 10.0
#: The QA phantom at its QA position in the simulated room (docs/qa.md).
QA_PHANTOM_SCENE = {"kind": "eye_phantom_1", "position_mm": [0.0, 0.0, 0.0]}
#: Solves tried before giving up: after a failed one the session takes the plates its plan
#: asks for next (finer steps) and solves again.
SOLVE_ATTEMPTS = 2

Prompt = Callable[[str], None]
"""Asks the physicist to do something and returns when it is done."""


def ask(what: str) -> None:
    """The real room's prompt: say what to do, wait for Enter."""
    input(f"{what}, then press Enter ")


def stereo(client: Client, place_board: Callable[[int], bool], *, say: Prompt = print
           ) -> CalibrationResponse:
    """A stereo session: views until ready, then the solve. ``place_board(n)`` puts the board
    in its ``n``-th pose (False: no more poses). Returns the new calibration."""
    session = client.open_stereo_session()
    try:
        view = None
        for n in range(100):
            if not place_board(n):
                break
            view = client.add_view(session.id)
            found = ", ".join(c for c, ok in view.found.items() if ok) or "no camera"
            say(f"view {n + 1}: board found by {found}; "
                + ("ready" if view.ready else f"{len(view.missing)} thing(s) missing"))
            if view.ready:
                break
        if view is None or not view.ready:
            raise EyeserverError("the stereo session is not ready: "
                                 + "; ".join(view.missing if view else ["no views"]))
    except BaseException:
        client.close_calibration_session(session.id)  # release the daemon
        raise
    return _solve(client, session.id, say)


def phase_height(client: Client, parent_id: str, *, z_range_mm: tuple[float, float],
                 place_reference: Prompt, say: Prompt = print) -> CalibrationResponse:
    """A phase-to-height session on ``parent_id``'s geometry over ``z_range_mm``: the
    reference plane (placed by hand), a probe plate near it when the daemon must measure the
    rig's fringe sensitivity, then the plate at every height the session's plan asks for
    (moved by the stage), the solve; after a failed solve, the heights the plan asks for next
    and the solve again."""
    session = client.open_phase_height_session(parent_id, z_range_mm=z_range_mm)
    assert session.plan is not None
    say(f"the session needs: {session.plan.next}")
    try:
        place_reference(f"put the reference plane at {REFERENCE_Z_MM:+.1f} mm")
        plan = client.add_reference_plane(session.id, REFERENCE_Z_MM).plan
        for attempt in range(1, SOLVE_ATTEMPTS + 1):
            while plan is not None and plan.needed_heights_mm is None:
                probe = REFERENCE_Z_MM - 1.0  # the daemon measures the sensitivity on it
                say(f"probe plate at {probe:+.1f} mm: {plan.next}")
                plan = client.add_plate(session.id, probe, move_stage=True).plan
                if plan is not None and plan.needed_heights_mm is None:
                    raise EyeserverError(f"the sensitivity is still unknown: {plan.next}")
            assert plan is not None and plan.needed_heights_mm is not None
            say(f"sensitivity {max((plan.sensitivity_rad_per_mm or {}).values()):.2f} rad/mm "
                f"({plan.sensitivity_source}): planes at most {plan.max_step_mm} mm apart")
            for z_mm in plan.needed_heights_mm:
                step = client.add_plate(session.id, z_mm, move_stage=True)
                say(f"plate at {step.z_mm:+.2f} mm: capture {step.capture_id}")
                plan = step.plan
            ready = client.calibration_session(session.id)
            if not ready.is_ready:
                raise EyeserverError("the phase-height session is not ready: "
                                     + "; ".join(ready.still_missing))
            try:
                return _solve(client, session.id, say)
            except EyeserverError as exc:
                if attempt == SOLVE_ATTEMPTS:
                    raise
                plan = client.calibration_session(session.id).plan
                say(f"{exc}; the session takes more plates: {plan.next if plan else '?'}")
    except BaseException:
        client.close_calibration_session(session.id)
        raise
    raise AssertionError("unreachable")


def _solve(client: Client, session_id: str, say: Prompt) -> CalibrationResponse:
    job = client.solve_calibration_session(session_id)  # the daemon is free again now
    say(f"solving as job {job.id} …")
    job = client.wait_for_job(job.id, timeout_s=1800.0)
    if job.state != "succeeded" or job.result is None:
        raise EyeserverError(f"the solve {job.state}: {job.error}")
    calibration = client.calibration(str(job.result["calibration_id"]))
    say(f"new calibration {calibration.id} (version {calibration.version}): "
        f"{calibration.quality}")
    return calibration


def qa_baseline(client: Client, place_phantom: Prompt, *, put_back: Prompt,
                say: Prompt = print) -> QaRun | None:
    """The active calibration's QA baseline when it has none (None when it has one or the
    daemon does not require the QA): the phantom placed, the baseline run, ``put_back``.
    Raises :class:`EyeserverError` with the reasons when the run fails."""
    status = client.qa_status()
    if status.baseline_run_id is not None or not status.required:
        return None
    place_phantom("put the QA phantom at its QA position (ball centre on the isocentre)")
    try:
        run = client.run_qa(baseline=True)
    finally:
        put_back("take the QA phantom away")
    say(f"QA baseline {run.id}: {'passed' if run.passed else 'FAILED'} ("
        + ", ".join(f"{name} {figure.value:.4f}" for name, figure in run.figures.items()
                    if figure.value is not None) + ")")
    if not run.passed or not run.baseline:
        raise EyeserverError(f"the QA baseline failed: {'; '.join(run.reasons)}")
    return run


def run(client: Client, *, parent_id: str | None = None, simulated: bool = False,
        activate: bool = False, z_range_mm: tuple[float, float] = Z_RANGE_MM,
        say: Prompt = print) -> CalibrationResponse:
    """The whole guided calibration; returns the new (phase-to-height) calibration."""
    if parent_id is None:
        def place_board(n: int) -> bool:
            if not simulated:
                ask(f"place the chessboard ({'origin board' if n == 0 else f'view {n + 1}'})")
                return True
            if n >= len(SIMULATED_BOARD_POSES):
                return False
            position, rotation = SIMULATED_BOARD_POSES[n]
            client.set_sim_chessboard(position_mm=position, rotation_deg=rotation)
            return True

        parent_id = stereo(client, place_board, say=say).id

    def place_reference(what: str) -> None:
        if simulated:
            client.set_sim_scene({"kind": "reference", "position_mm": [0, 0, REFERENCE_Z_MM]})
        else:
            ask(what)

    made = phase_height(client, parent_id, z_range_mm=z_range_mm,
                        place_reference=place_reference, say=say)
    active = client.status().active_calibration_id
    if active is not None and active != made.id:
        drift = client.compare_calibrations(active, made.id).summary
        say(f"against the active {active}: rotation ≤ {drift.max_rotation_deg:.4f}°, shift ≤ "
            f"{drift.max_centre_shift_mm:.4f} mm, height change ≤ "
            f"{drift.max_height_change_mm} mm")
    if activate:
        made = client.activate_calibration(made.id)
        say(f"{made.id} is active")
        if simulated:
            def place_phantom(what: str) -> None:
                client.set_sim_scene(QA_PHANTOM_SCENE)

            def put_eye_back(what: str) -> None:
                client.set_sim_scene({"kind": "eye"})  # the default patient eye

            qa_baseline(client, place_phantom, put_back=put_eye_back, say=say)
        else:
            qa_baseline(client, ask, put_back=ask, say=say)
    return made


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", help="the daemon (default $EYESERVER_URL or 127.0.0.1:8000)")
    parser.add_argument("--parent", help="phase-to-height only, on this stored calibration")
    parser.add_argument("--simulated", action="store_true",
                        help="place board and reference plane in the simulated room")
    parser.add_argument("--activate", action="store_true", help="activate the result")
    args = parser.parse_args(argv)
    try:
        with Client(args.url) as client:
            run(client, parent_id=args.parent, simulated=args.simulated,
                activate=args.activate)
    except EyeserverError as exc:
        print(f"guided calibration: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
