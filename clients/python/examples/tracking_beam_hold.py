"""Live tracking with the beam-hold flag: what a beam controller listens to.

Run against a daemon with an active calibration whose daily QA has passed today (else it
answers 409 with the reason: docs/qa.md; ``ois_verification.py --qa`` runs the QA), a patient
and the fraction's reference::

    python tracking_beam_hold.py P-0001 --fraction 1 --seconds 30

It opens the pose stream first (so no message is missed), starts tracking, and prints every
change of the beam hold with its reasons until ``--seconds`` have passed or Ctrl-C, then stops
tracking whatever happened. The beam may be on only while the last word was a pose message
with ``beam_hold`` false: a hold message, a lost link (the client's ``Disconnected``, also
after two seconds of silence) or messages lost to a slow reader (``Dropped``) hold it until
the next pose says otherwise.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from eyeserver_client import (
    Client,
    Disconnected,
    Dropped,
    EyeserverError,
    Heartbeat,
    HoldMessage,
    Message,
    PoseMessage,
)
from eyeserver_client.models import TrackingStatus


@dataclass
class BeamHold:
    """The beam-hold flag as a controller keeps it from the stream: held until a pose says
    otherwise. Starts held."""

    held: bool = True
    changes: list[tuple[int | None, bool, list[str]]] = field(default_factory=list)
    """Each change: the pose frame (None for a notice), the new flag, its reasons."""

    def update(self, message: Message) -> bool:
        """Take ``message`` into account; whether the flag changed."""
        frame: int | None = None
        reasons: list[str] = []
        if isinstance(message, PoseMessage):
            held, frame, reasons = message.beam_hold, message.frame, message.reasons
        elif isinstance(message, HoldMessage | Disconnected):
            held, reasons = True, [message.reason]
        elif isinstance(message, Dropped):
            held, reasons = True, [f"{message.count} message(s) lost"]
        elif isinstance(message, Heartbeat):
            held = message.beam_hold or self.held  # a heartbeat never lowers the hold
        else:
            return False
        if held == self.held:
            return False
        self.held = held
        self.changes.append((frame, held, reasons))
        return True


def track(client: Client, patient_id: str, fraction: int, *, seconds: float,
          until: Callable[[BeamHold, PoseMessage], bool] | None = None,
          say: Callable[[str], None] = print) -> tuple[BeamHold, TrackingStatus]:
    """Track for ``seconds`` (or until ``until(hold, message)`` is true for a pose), print
    each change of the beam hold, stop tracking; the flag's history and the final status."""
    hold = BeamHold()
    with client.poses() as stream:  # connected before tracking starts: nothing missed
        started = client.start_tracking(patient_id, fraction)
        say(f"tracking {patient_id}, fraction {fraction} "
            f"(unit {(started.model_extra or {}).get('unit', '?')})")
        try:
            deadline = time.monotonic() + seconds
            for message in stream:
                if hold.update(message):
                    frame, held, reasons = hold.changes[-1]
                    say(f"frame {frame}: beam {'HELD' if held else 'free'} "
                        f"{'; '.join(reasons)}")
                if isinstance(message, PoseMessage) and until is not None \
                        and until(hold, message):
                    break
                if time.monotonic() > deadline:
                    break
        finally:
            final = client.stop_tracking()
    say(f"stopped: {final.frames_processed} frames processed, {final.frames_dropped} "
        f"dropped, {final.frames_held} held")
    return hold, final


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("patient_id")
    parser.add_argument("--fraction", type=int, required=True)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--url", help="the daemon (default $EYESERVER_URL or 127.0.0.1:8000)")
    args = parser.parse_args(argv)
    try:
        with Client(args.url) as client:
            track(client, args.patient_id, args.fraction, seconds=args.seconds)
    except KeyboardInterrupt:
        return 130
    except EyeserverError as exc:
        print(f"tracking: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
