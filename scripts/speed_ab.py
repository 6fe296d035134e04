"""Side by side: the reconstruction's speed with glibc's default allocator and with freed memory
kept (eyeserver.core.memory), on the eye phantom ``eyeserver bench speed`` records.

Usage::

    .venv/bin/python scripts/speed_ab.py CALDIR [--room FILE] [--runs N]

Each mode runs in a child process of its own (the allocator's settings are per process), the
modes alternated ``--runs`` times (this virtual machine's speed drifts within minutes); each
child prints the medians of ``demodulate`` without and with its bend correction, of the bend
correction alone summed over the frame-set's cameras, of the plain FFT peer
(``eyeserver.bench.speed.fft_ftm``) and of a 2- and a 4-camera multi-view frame-set.

The old path: run this script against an older checkout's code, e.g.
``git worktree add /tmp/old a04b128~1`` then ``PYTHONPATH=/tmp/old .venv/bin/python
scripts/speed_ab.py CALDIR`` (the script sets the allocator itself, so it needs nothing newer
than the functions it times). docs/notes/speed.md has what it measured.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def _median_ms(call: Callable[[], object], runs: int) -> float:
    # bench.speed._repeat's loop, kept here: this script also runs against older checkouts.
    call()
    samples = []
    for _ in range(runs):
        started = time.perf_counter()
        call()
        samples.append(time.perf_counter() - started)
    return statistics.median(samples) * 1e3


def _bend_ms(camera: Any, image: Any) -> float:
    """The median ms of the bend correction alone on one camera's image."""
    from eyeserver.pipeline.demodulate import demodulate, with_bend_bias

    found = demodulate(image, camera.carrier, measure_bends=False)
    return _median_ms(lambda: with_bend_bias(found, camera.carrier), 100)


def child(frameset_path: str, kept: bool) -> None:
    """Time the stages in this process (allocator as ``kept`` says) and print them as JSON."""
    if kept:
        mallopt = ctypes.CDLL(None).mallopt
        mallopt(-1, ctypes.c_int(2**31 - 1))  # M_TRIM_THRESHOLD
        mallopt(-3, ctypes.c_int(32 << 20))  # M_MMAP_THRESHOLD
    import cv2

    from eyeserver.bench.speed import fft_ftm, reconstruct_frameset
    from eyeserver.pipeline.demodulate import demodulate

    cv2.setNumThreads(1)
    with open(frameset_path, "rb") as handle:
        frameset = pickle.load(handle)
    unit = frameset.units[0]
    image, carrier = unit.image_a, unit.cam_a.carrier
    figures = {
        "demodulate_ms": _median_ms(lambda: demodulate(image, carrier, measure_bends=False), 100),
        "demodulate_bent_ms": _median_ms(lambda: demodulate(image, carrier), 100),
        "fft_ftm_ms": _median_ms(lambda: fft_ftm(image, carrier), 100),
        # The bend correction alone, summed over every camera of the frame-set (their carriers'
        # periods differ, and with them the correction's coarse grid).
        "bend_correction_all_cameras_ms": sum(_bend_ms(camera, image) for one in frameset.units
                                              for camera, image in ((one.cam_a, one.image_a),
                                                                    (one.cam_b, one.image_b))),
    }
    for label, used in frameset.sizes().items():
        figures[f"frameset_{label}_ms"] = _median_ms(
            lambda used=used: reconstruct_frameset(frameset, used, "multi-view"), 20)
    print(json.dumps(figures))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("calibration", type=Path)
    parser.add_argument("--room", type=Path, default=None)
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child[0], args.child[1] == "kept")
        return 0
    from eyeserver.bench.speed import record_frameset
    from eyeserver.hardware.sim.config import load_room

    with tempfile.TemporaryDirectory() as work:
        frameset = record_frameset(load_room(args.room), args.calibration, Path(work))
        frameset_path = Path(work) / "frameset.pkl"
        frameset_path.write_bytes(pickle.dumps(frameset))
        results: dict[str, list[dict[str, float]]] = {"default": [], "kept": []}
        for _ in range(args.runs):
            for mode in results:
                out = subprocess.run([sys.executable, __file__, str(args.calibration),
                                      "--child", str(frameset_path), mode],
                                     check=True, capture_output=True, text=True).stdout
                results[mode].append(json.loads(out.strip().splitlines()[-1]))
    names = list(results["default"][0])
    print(f"{'median ms (runs: ' + str(args.runs) + ')':<28}{'default':>10}{'kept':>10}")
    for name in names:
        row = [statistics.median(r[name] for r in results[mode]) for mode in results]
        print(f"{name:<28}{row[0]:>10.1f}{row[1]:>10.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
