"""Live tracking of the simulated eye through a scripted head shift: does the room keep
delivering frames (issue 35, 1b)? A daemon on loopback tracks unit ``left`` for 30 s; at script
time 8 s the head moves 1 mm sideways over ``--duration`` seconds. Prints the session's frame
counts, the gaps of more than 0.3 s between pose messages on ``/api/v1/ws/pose`` (seconds from
the motion's start, length) and the fail-safe holds.

    .venv/bin/python scripts/tracking_shift.py [--duration 0.03] [--calibration CALDIR]

Without ``--calibration`` a calibration of the default room is made first (≈ 1 minute).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from websockets.sync.client import connect

from eyeserver.bench.daemon import DaemonProcess, zip_directory
from eyeserver.bench.simcal import calibrate_room
from eyeserver.hardware.sim.config import load_room

API = "/api/v1"
SHIFT_AT_S = 8.0
TRACK_S = 30.0
GAP_S = 0.3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=0.03,
                        help="how long the shift takes (s, default 0.03)")
    parser.add_argument("--calibration", type=Path, help="a calibration of the default room")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="eyeserver-shift-") as scratch:
        work = Path(scratch)
        calibration = args.calibration or calibrate_room(
            load_room(None), work / "cal", seed=0, progress=lambda m: print(m, file=sys.stderr))
        with DaemonProcess(work / "data", log=work / "daemon.log") as daemon:
            print(json.dumps(_track(daemon, calibration, args.duration), indent=1))
    return 0


def _track(daemon: DaemonProcess, calibration: Path, duration_s: float) -> dict[str, Any]:
    client = daemon.client
    imported = client.post(f"{API}/calibrations", content=zip_directory(calibration),
                           headers={"content-type": "application/zip"}).json()
    client.post(f"{API}/calibrations/{imported['id']}/activate").raise_for_status()
    client.put(f"{API}/patients/P1", json={"eye": "right", "unit": "left",
                                           "tolerance_mm": 0.5, "tolerance_gaze_deg": 2.0}
               ).raise_for_status()
    client.put(f"{API}/sim/eye", json={"motion": None, "gaze_deg": [0.0, 0.0]}
               ).raise_for_status()
    client.post(f"{API}/patients/P1/fractions/1/reference/capture").raise_for_status()
    motion = {"seed": 1, "drift_deg": 0.02, "saccade_rate_hz": 0.0, "blink_rate_hz": 0.0,
              "script": [{"t_s": SHIFT_AT_S, "kind": "shift", "shift_mm": [1.0, 0.0, 0.0],
                          "duration_s": duration_s}]}
    client.put(f"{API}/sim/eye", json={"motion": motion}).raise_for_status()
    start = time.monotonic()
    received: list[tuple[float, dict[str, Any]]] = []
    url = daemon.url.replace("http://", "ws://", 1) + f"{API}/ws/pose?token=" \
        + daemon.operator_token
    with connect(url, ping_interval=None) as ws:
        client.post(f"{API}/tracking/start", json={"patient_id": "P1", "fraction": 1}
                    ).raise_for_status()
        end = time.monotonic() + TRACK_S
        while time.monotonic() < end:
            try:
                message = json.loads(ws.recv(timeout=1))
            except TimeoutError:
                continue
            received.append((time.monotonic() - start, message))
        status = client.post(f"{API}/tracking/stop").json()
    poses = [t for t, m in received if m["type"] == "pose"]
    return {
        "shift": {"at_s": SHIFT_AT_S, "duration_s": duration_s, "mm": [1.0, 0.0, 0.0]},
        "frames": {k: status.get(k) for k in ("frames_acquired", "frames_processed",
                                               "frames_dropped", "frames_missed",
                                               "frames_held", "stalls")},
        "pose_messages": len(poses),
        "gaps_s": [[round(a, 2), round(b - a, 2)] for a, b in itertools.pairwise(poses)
                   if b - a > GAP_S],
        "holds": [[round(t, 2), m.get("reason")] for t, m in received if m["type"] == "hold"],
    }


if __name__ == "__main__":
    raise SystemExit(main())
