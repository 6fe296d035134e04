"""``eyeserver bench …``: benchmarks that print figures (JSON on stdout with ``--json``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress
from eyeserver.errors import EyeserverError


def _whole_number(text: str, least: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"must be at least {least}, not {value}")
    return value


def _positive_int(text: str) -> int:
    return _whole_number(text, 1)


def _non_negative_int(text: str) -> int:
    return _whole_number(text, 0)


def _non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number ≥ 0, not {text}")
    return value


def add_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver bench speed``, ``accuracy``, ``pose``, ``tracking`` and
    ``reliability``."""
    bench = subparsers.add_parser("bench", help="benchmarks (speed, accuracy)",
                                  description="Measure speed and accuracy on the simulated room.")
    commands = bench.add_subparsers(title="benchmarks", dest="bench_command", metavar="COMMAND")
    commands.required = True
    speed = commands.add_parser(
        "speed", help="render and processing times on this machine",
        description="Time the simulated room's rendering and the reconstruction of an eye "
        "phantom: whole frame-sets (one thread, and two worker threads), every stage on its own "
        "per camera and per 2- and 4-camera frame-set, peers on the same images (scikit-image's "
        "unwrapping, a plain FFT demodulation, OpenCV contrib's FTP when installed) as time "
        "ratios, and peak memory; the goals beside them (progress on stderr).")
    speed.add_argument("--json", action="store_true", help="one JSON document on stdout")
    speed.add_argument("--frames", type=_positive_int, default=100,
                       help="repetitions per figure: frame-sets, stage passes, rendered frames "
                       "(default 100; the spatial path's frame-sets a fifth as many)")
    speed.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    speed.add_argument("--api-requests", type=_non_negative_int, default=10, metavar="N",
                       help="captures and reconstructions of each kind timed through the API "
                       "of a daemon on loopback (default 10; 0 skips them)")
    speed.add_argument("--tracking-seconds", type=_non_negative_int, default=60, metavar="S",
                       help="live tracking through a daemon for the frame → pose latency, as "
                       "'eyeserver bench tracking' (default 60; 0 skips it)")
    speed.add_argument("--replay-seconds", type=_non_negative_int, default=10, metavar="S",
                       help="live tracking's pipeline alone: S seconds of the moving eye "
                       "rendered beforehand, replayed at 25 Hz through the tracking worker "
                       "(default 10; 0 skips it)")
    speed.add_argument("--replay-workers", type=_positive_int, default=2, metavar="N",
                       help="tracking worker processes in the replay, each on its own frames "
                       "(the daemon's tracking_workers; default 2)")
    speed.add_argument("--calibration", type=Path, metavar="CALDIR",
                       help="a calibration of the simulated rig for the pipeline timings "
                       "(default: make one, ≈ 1 minute)")
    speed.set_defaults(handler=_speed)
    accuracy = commands.add_parser(
        "accuracy", help="the paper's validation on the simulated room",
        description="Calibrate a simulated rig, reconstruct phantoms at several poses with 4 "
        "and 2 views, and print the paper's figures beside the goals (progress on stderr).")
    accuracy.add_argument("--json", action="store_true", help="one JSON document on stdout")
    accuracy.add_argument("--quick", action="store_true",
                          help="one pose per phantom instead of four")
    accuracy.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    accuracy.add_argument("--out", type=Path, metavar="DIR",
                          help="keep the calibration set, calibration and scenes here")
    accuracy.add_argument("--calibration", type=Path, metavar="CALDIR",
                          help="use this calibration of the simulated rig instead of making one")
    accuracy.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    accuracy.add_argument("--phantoms", metavar="NAMES",
                          help="comma-separated phantoms (default: pyramid,wedge,eye_phantom_1,"
                          "eye_phantom_2)")
    accuracy.add_argument("--rig", type=Path, metavar="FILE", action="append",
                          help="a room file whose rig is calibrated and its coverage measured "
                          "with the default options beside the room's own (repeatable; "
                          "default: every file of examples/rooms; none with --quick)")
    accuracy.set_defaults(handler=_accuracy)
    pose = commands.add_parser(
        "pose", help="eye pose accuracy on random simulated eyes",
        description="Render random simulated eyes (patient eyes drawn from population ranges, "
        "or the old sharp-limbus eye; ±5 mm, ±10°), reconstruct, fit the eye model and compare "
        "globe centre and gaze with the truth, overall and per bin of limbus width, limbus "
        "contrast, lid cover and anatomy mismatch; how well the stated uncertainties cover the "
        "errors, and how many poses off by more than 0.2 mm pass the daemon's min_confidence; "
        "a 1 mm shift between two captures must be detected (progress on stderr).")
    pose.add_argument("--json", action="store_true", help="one JSON document on stdout")
    pose.add_argument("--poses", type=_positive_int, default=200, help="random poses (default 200)")
    pose.add_argument("--seed", type=int, default=0, help="pose and noise seed (default 0)")
    pose.add_argument("--calibration", type=Path, metavar="CALDIR",
                      help="use this calibration of the simulated rig instead of making one")
    pose.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    pose.add_argument("--unit", action="append", metavar="ID", dest="units",
                      help="capture only this unit (repeatable; default all of the room's)")
    pose.add_argument("--eyes", choices=("patient", "sharp"), default="patient",
                      help="patient: every property of each eye drawn from its population "
                      "range (docs/eye-model.md; default); sharp: the old painted eye with a "
                      "sharp limbus and the fit's own anatomy, globes of 12, 11 and 13 mm in "
                      "turn (the figures before issue 34)")
    pose.add_argument("--biometry", action="store_true",
                      help="the patient's model from the eye's MRI and biometry, each off by "
                      "its typical measurement error (default: the population model, radius "
                      "fitted)")
    pose.add_argument("--displacement", action="store_true",
                      help="capture each fitted eye again, moved by up to 1 mm and turned by "
                      "up to 2° per axis, and score the move measured: what a check against "
                      "a reference captured at set-up sees (twice the renders)")
    pose.add_argument("--jobs", type=_positive_int, default=1, metavar="N",
                      help="worker processes sharing the poses, one per core at most "
                      "(default 1; the figures are the same for any N)")
    pose.set_defaults(handler=_pose)
    tracking = commands.add_parser(
        "tracking", help="live tracking end to end through a daemon on loopback",
        description="Track the moving simulated eye (drift and a scripted saccade) for a while "
        "through a daemon on loopback with 20 WebSocket clients on /api/v1/ws/pose (one never "
        "reads): frames delivered at 25 Hz, latency frame → client, the beam hold's reaction "
        "to the saccade (progress on stderr).")
    tracking.add_argument("--json", action="store_true", help="one JSON document on stdout")
    tracking.add_argument("--seconds", type=_positive_int, default=60,
                          help="how long to track (default 60)")
    tracking.add_argument("--calibration", type=Path, metavar="CALDIR",
                          help="use this calibration of the simulated rig instead of making one")
    tracking.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    tracking.add_argument("--workers", type=_positive_int, default=2, metavar="N",
                          help="the daemon's tracking worker processes (setting "
                          "tracking_workers; default 2)")
    tracking.add_argument("--prerendered", action="store_true",
                          help="render the tracked unit's frames of the whole script before "
                          "tracking (POST /api/v1/sim/eye/prerender), so that the stream costs "
                          "the cores nothing, as real cameras: the daemon's own latency "
                          "(default: the room renders each frame live, on the same cores)")
    tracking.add_argument("--eyes", choices=("sharp", "patient"), default="sharp",
                          help="sharp: the room's painted eye (default); patient: a patient's "
                          "eye drawn from the population (docs/eye-model.md) with --seed")
    tracking.add_argument("--seed", type=int, default=0,
                          help="which patient's eye (--eyes patient; default 0)")
    tracking.add_argument("--unit", default="left", metavar="ID",
                          help="the patient's unit: left (default), right, or all (both units "
                          "interleaved; with the room rendering live)")
    tracking.set_defaults(handler=_tracking)
    reliability = commands.add_parser(
        "reliability", help="crashes, unplugged devices, a full disk, load and fuzz",
        description="Through daemons on loopback: kill -9 during captures (acknowledged, lost, "
        "corrupted), each device kind unplugged and replugged during captures (detected, "
        "recovered, how fast), the data directory's disk full and freed (a tmpfs; root only), "
        "status latency, capture throughput and event stream under load, and a schemathesis "
        "fuzz of every operation; what went wrong listed at the end (progress on stderr). "
        "Each part is skipped with 0.")
    reliability.add_argument("--json", action="store_true", help="one JSON document on stdout")
    reliability.add_argument("--kill-cycles", type=_non_negative_int, default=12, metavar="N",
                             help="SIGKILLs of the daemon while captures are posted, each "
                             "restarted on the same data directory (default 12)")
    reliability.add_argument("--unplug-rounds", type=_non_negative_int, default=1, metavar="N",
                             help="times each device is unplugged and replugged (default 1)")
    reliability.add_argument("--devices", metavar="IDS",
                             help="comma-separated device ids to unplug (default: the first "
                             "camera, projector and trigger of /api/v1/devices)")
    reliability.add_argument("--unplugged-seconds", type=_non_negative_float, default=2.0,
                             metavar="S", help="how long a device stays unplugged after its "
                             "fault was seen, captures posted meanwhile (default 2)")
    reliability.add_argument("--disk-mib", type=_non_negative_int, default=128, metavar="MIB",
                             help="size of the tmpfs the full-disk daemon stores on "
                             "(default 128)")
    reliability.add_argument("--load-seconds", type=_non_negative_int, default=30, metavar="S",
                             help="how long the load lasts (default 30)")
    reliability.add_argument("--status-clients", type=_positive_int, default=100, metavar="N",
                             help="connections reading GET /api/v1/status under load: wrk's "
                             "when installed, else threads (default 100)")
    reliability.add_argument("--capture-clients", type=_positive_int, default=20, metavar="N",
                             help="threads posting captures under load (default 20)")
    reliability.add_argument("--fuzz-examples", type=_non_negative_int, default=3, metavar="N",
                             help="fuzz cases per operation and role at most (default 3)")
    reliability.add_argument("--fuzz-operations", metavar="REGEX",
                             help="fuzz only the operations whose path matches (default all "
                             "but rendering ahead and tracking's start)")
    reliability.add_argument("--seed", type=int, default=0,
                             help="seed of the kill delays and the fuzz (default 0)")
    reliability.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    reliability.add_argument("--out", type=Path, metavar="DIR",
                             help="keep the daemons' data directories and logs here (a fresh "
                             "directory)")
    reliability.set_defaults(handler=_reliability)


def _speed(args: argparse.Namespace) -> int:
    from eyeserver.bench import speed
    from eyeserver.hardware.sim.config import load_room

    report = speed.run(load_room(args.room), frames=args.frames, progress=_progress,
                       calibration=args.calibration, room_file=args.room,
                       api_requests=args.api_requests,
                       tracking_seconds=args.tracking_seconds,
                       replay_seconds=args.replay_seconds,
                       replay_workers=args.replay_workers)
    print(json.dumps(report, indent=1) if args.json else speed.format_text(report))
    return 0


def _accuracy(args: argparse.Namespace) -> int:
    from eyeserver.bench import accuracy
    from eyeserver.hardware.sim.config import load_room

    phantoms = accuracy.PHANTOMS
    if args.phantoms:
        phantoms = tuple(args.phantoms.split(","))
        unknown = sorted(set(phantoms) - set(accuracy.PHANTOMS))
        if unknown:
            raise EyeserverError(f"--phantoms: unknown {', '.join(unknown)} (choose from "
                                 f"{', '.join(accuracy.PHANTOMS)})")
    # Every room file read before the long run: a bad one fails now, naming its file and field.
    rigs = [] if args.quick else [(path.stem, load_room(path))
                                  for path in (args.rig or accuracy.example_rooms())]
    report = accuracy.run(load_room(args.room), quick=args.quick, seed=args.seed, out=args.out,
                          calibration=args.calibration, phantoms=phantoms, rigs=rigs,
                          progress=_progress)
    print(json.dumps(report, indent=1) if args.json else accuracy.format_text(report))
    return 0


def _pose(args: argparse.Namespace) -> int:
    from eyeserver.bench import pose
    from eyeserver.hardware.sim.config import load_room

    report = pose.run(load_room(args.room), poses=args.poses, seed=args.seed,
                      calibration=args.calibration, units=args.units,
                      eyes=args.eyes, biometry=args.biometry,
                      displacement=args.displacement, jobs=args.jobs, progress=_progress)
    print(json.dumps(report, indent=1) if args.json else pose.format_text(report))
    return 0


def _tracking(args: argparse.Namespace) -> int:
    from eyeserver.bench import tracking

    if args.unit == "all" and args.prerendered:
        raise EyeserverError("bench tracking: --unit all needs the room rendering live (the "
                             "room renders ahead for one unit); leave out --prerendered")
    report = tracking.run(args.seconds, calibration=args.calibration, room_file=args.room,
                          workers=args.workers, prerendered=args.prerendered,
                          eyes=args.eyes, seed=args.seed, unit=args.unit,
                          progress=_progress)
    print(json.dumps(report, indent=1) if args.json else tracking.format_text(report))
    return 0


def _reliability(args: argparse.Namespace) -> int:
    import re

    from eyeserver.bench import reliability
    from eyeserver.hardware.sim.config import load_room

    if args.room is not None:
        load_room(args.room)  # a bad room file said in one line, before any daemon starts
    if args.fuzz_operations:
        try:
            re.compile(args.fuzz_operations)
        except re.error as exc:
            raise EyeserverError(f"--fuzz-operations: not a regular expression: {exc}") from None
    devices = [d for d in args.devices.split(",") if d] if args.devices else None
    report = reliability.run(
        kill_cycles=args.kill_cycles, unplug_rounds=args.unplug_rounds, devices=devices,
        unplugged_s=args.unplugged_seconds, disk_mib=args.disk_mib,
        load_seconds=args.load_seconds, status_clients=args.status_clients,
        capture_clients=args.capture_clients, fuzz_examples=args.fuzz_examples,
        fuzz_operations=args.fuzz_operations, seed=args.seed, room_file=args.room,
        work=args.out, progress=_progress)
    print(json.dumps(report, indent=1) if args.json else reliability.format_text(report))
    return 0
