"""Calibrate the pose's unexplained error (eyeserver.eye.tunables.MODEL_ERROR_*) on bench draws.

Usage::

    .venv/bin/python scripts/calibrate_model_error.py [--percentile P] POSE.json...

POSE.json are ``eyeserver bench pose --json`` documents of seeds the benchmarks never report
(docs/benchmarks.md reports seed 0; the constants came from seeds 7 and 8,
docs/notes/patient-eye.md).
For each power ``p`` of ``(max(0, c₀ − c)/c)^p`` it prints the scales (mm for the centre's axes,
degrees for the gaze) that leave ``P`` % of the draws' errors (default 97.5) within 2 of their
stated sds once added, and, per document, the median sd that results against the median error and
the share within 2 sd (centre axes / gaze). Each fitted pose's stated sd here is the bench's
less the unexplained error the current constants add for its confidence
(:func:`eyeserver.eye.fit.model_error_sds`): the fit's covariances and the globe's unknown
shape. Documents must therefore come from a checkout with the current constants.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.eye.fit import model_error_sds
from eyeserver.eye.tunables import MODEL_ERROR_BELOW_CONFIDENCE, MODEL_ERROR_MIN_CONFIDENCE

POWERS = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0)


def weakness(confidence: float, power: float) -> float:
    """``(max(0, c₀ − c)/c)^power``, as :func:`eyeserver.eye.fit.with_model_error` takes it."""
    c = min(max(confidence, MODEL_ERROR_MIN_CONFIDENCE), 1.0)
    return float((max(0.0, MODEL_ERROR_BELOW_CONFIDENCE - c) / c) ** power)


def _without_model_error(row: dict[str, Any]) -> dict[str, Any]:
    """``row`` with the current unexplained error taken out of its stated sds again."""
    centre, gaze = model_error_sds(row["confidence"])
    return {**row,
            "centre_sd_stated_mm": [float(np.sqrt(max(0.0, s**2 - centre**2)))
                                    for s in row["centre_sd_stated_mm"]],
            "gaze_sd_deg": float(np.sqrt(max(0.0, row["gaze_sd_deg"] ** 2 - gaze**2)))}


def _needed(rows: list[dict[str, Any]], power: float) -> tuple[list[float], list[float]]:
    """Per centre axis and per gaze: the scale that would put that error at 2 sd."""
    centre, gaze = [], []
    for r in rows:
        w = weakness(r["confidence"], power)
        for e, s in zip(r["centre_error_axes_mm"], r["centre_sd_stated_mm"], strict=True):
            centre.append(float(np.sqrt(max(0.0, (abs(e) / 2) ** 2 - s**2))) / w if w else 0.0)
        e, s = r["gaze_error_deg"], r["gaze_sd_deg"]
        gaze.append(float(np.sqrt(max(0.0, (e / 2) ** 2 - s**2))) / w if w else 0.0)
    return centre, gaze


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("documents", nargs="+", type=Path)
    parser.add_argument("--percentile", type=float, default=97.5)
    args = parser.parse_args()
    sets: dict[str, list[dict[str, Any]]] = {}
    for path in args.documents:
        try:
            cases = json.loads(path.read_text())["cases"]
        except (OSError, ValueError, KeyError) as exc:
            print(f"{path}: not an eyeserver bench pose --json document ({exc})", file=sys.stderr)
            return 2
        sets[path.name] = [_without_model_error(r) for r in cases
                           if r.get("centre_error_axes_mm") is not None]
        if not sets[path.name]:
            print(f"{path}: no fitted pose with its axes' errors (a bench from before they were "
                  "recorded?)", file=sys.stderr)
            return 2
    pooled = [r for rows in sets.values() for r in rows]
    for power in POWERS:
        centre_need, gaze_need = _needed(pooled, power)
        a = float(np.percentile(centre_need, args.percentile))
        b = float(np.percentile(gaze_need, args.percentile))
        parts = []
        for name, rows in sets.items():
            sds = [float(np.hypot(s, a * weakness(r["confidence"], power))) for r in rows
                   for s in r["centre_sd_stated_mm"]]
            errors = [abs(e) for r in rows for e in r["centre_error_axes_mm"]]
            within = np.mean([e <= 2 * s for e, s in zip(errors, sds, strict=True)])
            gaze_within = np.mean([r["gaze_error_deg"] <= 2 * float(np.hypot(
                r["gaze_sd_deg"], b * weakness(r["confidence"], power))) for r in rows])
            parts.append(f"{name}: sd {np.median(sds):.3f} mm (error {np.median(errors):.3f}), "
                         f"within 2 sd {within:.2f}/{gaze_within:.2f}")
        print(f"power {power:g}: centre {a:.3f} mm, gaze {b:.2f}° | " + " | ".join(parts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
