"""The machine a bench ran on, and how fast it ran right then (for the reports of the benches)."""

from __future__ import annotations

import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import scipy.fft

__all__ = ["code_version", "machine", "reference_ms"]


def machine() -> dict[str, Any]:
    """Where the figures came from: the machine and the code (:func:`code_version`)."""
    return {"python": platform.python_version(), "numpy": np.__version__,
            "platform": platform.platform(), "processor": platform.processor() or "unknown",
            "cpu_count": os.cpu_count(), "code": code_version()}


def code_version() -> str | None:
    """The checkout that ran a bench, as ``git describe --always --dirty`` names it (a commit,
    ``-dirty`` with uncommitted changes), or None where the code is not a git checkout (an
    installed package): the page of figures is made from runs of several benches, each of
    which may have run on other code, and says which."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "pyproject.toml").is_file():
        return None
    try:
        done = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty"],
                              capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() or None if done.returncode == 0 else None


def reference_ms(repeats: int = 50) -> float:
    """How fast the machine runs right now: the median time of one FFT of a 640 × 512 image
    (``scipy.fft.rfft2``, one thread), a fixed piece of the pipeline's own work.

    Timings are only comparable at similar values: on the shared 2-core virtual machine of
    docs/benchmarks.md the same code's figures moved by up to 2× within an hour, with the load
    average near zero throughout (a tracked frame alone 10–22 ms, NumPy's FFT of this image
    4.4–8.7 ms).
    """
    image = np.random.default_rng(0).random((512, 640), dtype=np.float32)
    samples = []
    for _ in range(repeats):
        started = time.perf_counter()
        scipy.fft.rfft2(image, workers=1)
        samples.append(time.perf_counter() - started)
    return float(np.median(samples) * 1e3)
