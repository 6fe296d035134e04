"""A tiny simulated room for the simulated drivers' tests: two units rendering a flat grey level.

Used by tests/test_hardware_sim.py and by the contract suites of tests/hardware/.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from eyeserver.core.clock import Clock, ManualClock

START_NS = 1_000_000_000
BACKGROUND_DN = 20.0
FRINGE_DN = 100.0


class FakeRoom:
    """A room of two units (P1: S1, S2; P2: S3, S4) rendering a flat grey level plus noise.

    The grey level rises with the lit projectors' intensities, so tests can see what was lit;
    every render call is recorded. S4 is a 12-bit camera, the others 8-bit.
    """

    def __init__(self, seed: int = 7, clock: Clock | None = None) -> None:
        self.clock: Clock = clock if clock is not None else ManualClock(START_NS)
        self.seed = seed
        self.renders: list[dict[str, Any]] = []
        self.prepared: list[tuple[str, tuple[str, ...]]] = []
        self._lock = threading.Lock()

    def camera_ids(self) -> list[str]:
        return ["S1", "S2", "S3", "S4"]

    def projector_ids(self) -> list[str]:
        return ["P1", "P2"]

    def units(self) -> list[tuple[str, str, list[str]]]:
        return [("left", "P1", ["S1", "S2"]), ("right", "P2", ["S3", "S4"])]

    def camera_format(self, camera_id: str) -> tuple[int, int, int]:
        return (24, 16, 12) if camera_id == "S4" else (32, 24, 8)

    def prepare(self, camera_id: str, projectors: Sequence[str]) -> None:
        with self._lock:
            self.prepared.append((camera_id, tuple(projectors)))

    def render(self, camera_id: str, *, t_s: float, projectors: Mapping[str, float],
               exposure_us: float, gain_db: float, rng: np.random.Generator) -> np.ndarray:
        with self._lock:
            self.renders.append({"camera": camera_id, "t_s": t_s, "projectors": dict(projectors),
                                 "exposure_us": exposure_us, "gain_db": gain_db,
                                 "rendered_ns": self.clock.now_ns()})
        width, height, bit_depth = self.camera_format(camera_id)
        level = BACKGROUND_DN + FRINGE_DN * sum(projectors.values())
        image = level + rng.normal(0.0, 2.0, (height, width))
        dtype = np.uint8 if bit_depth == 8 else np.uint16
        return np.clip(np.rint(image), 0, 2**bit_depth - 1).astype(dtype)
