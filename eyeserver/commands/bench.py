"""``eyeserver bench …``: benchmarks that print figures (JSON on stdout with ``--json``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress
from eyeserver.errors import NotBuiltError


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def add_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver bench speed`` and ``eyeserver bench accuracy``."""
    bench = subparsers.add_parser("bench", help="benchmarks (speed, accuracy)",
                                  description="Measure speed and accuracy on the simulated room.")
    commands = bench.add_subparsers(title="benchmarks", dest="bench_command", metavar="COMMAND")
    commands.required = True
    speed = commands.add_parser("speed", help="render and processing times on this machine")
    speed.add_argument("--json", action="store_true", help="one JSON document on stdout")
    speed.add_argument("--frames", type=_positive_int, default=30,
                       help="frame-sets per figure (default 30)")
    speed.add_argument("--room", type=Path, metavar="FILE", help="room file (default room)")
    speed.set_defaults(handler=_speed)
    accuracy = commands.add_parser("accuracy", help="the paper's validation (not built yet)")
    accuracy.add_argument("--json", action="store_true")
    accuracy.set_defaults(handler=_accuracy)


def _speed(args: argparse.Namespace) -> int:
    from eyeserver.bench import speed
    from eyeserver.hardware.sim.config import load_room

    report = speed.run(load_room(args.room), frames=args.frames, progress=_progress)
    print(json.dumps(report, indent=1) if args.json else speed.format_text(report))
    return 0


def _accuracy(args: argparse.Namespace) -> int:
    raise NotBuiltError("bench accuracy needs the reconstruction pipeline (issue 3) and the "
                        "accuracy bench (issue 4), which are not built yet")
