"""The benches: one JSON document each, every figure named, measured figures within the goals."""

from __future__ import annotations

import json
from typing import Any

import pytest

from eyeserver.bench.figures import FIGURES
from eyeserver.cli import main


def _json(capsys: pytest.CaptureFixture[str], args: list[str]) -> dict[str, Any]:
    capsys.readouterr()  # what the calibration fixture printed, when it ran in this test
    assert main(args) == 0
    report: dict[str, Any] = json.loads(capsys.readouterr().out)
    return report


def test_accuracy_bench_reports_the_papers_figures(calibrated_rooms: Any,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    _, caldir = calibrated_rooms("default")
    report = _json(capsys, ["bench", "accuracy", "--quick", "--json", "--phantoms",
                            "eye_phantom_1", "--calibration", str(caldir)])
    for key in FIGURES:
        assert key in report, key
    for key in ("reprojection_px", "p2h_residual_mm", "fiducial_error_mm", "icp_rmse_4view_mm",
                "icp_rmse_2view_mm",
                "surface_median_4view_mm", "surface_median_2view_mm", "surface_rmse_4view_mm",
                "surface_rmse_2view_mm"):
        assert report[key] <= FIGURES[key].goal, (key, report[key])
    assert report["surface_median_4view_mm"] < 0.05
    assert report["fiducials"]["measurements"] >= 8  # the dots found in both cameras of a unit
    assert report["4view_measurements"] == 1 and report["2view_measurements"] == 2
    assert report["spatial_4view_measurements"] == 1
    assert report["spatial_coverage_4view"] > report["coverage_4view"]
    for key in report["pending"]:
        assert report[key] is None
    assert report["noise_model"]["bit_depth"] == 8


def test_accuracy_bench_refuses_an_unknown_phantom(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "accuracy", "--phantoms", "teapot"]) == 2
    assert "teapot" in capsys.readouterr().err


def test_speed_bench_times_the_pipeline(calibrated_rooms: Any,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    _, caldir = calibrated_rooms("default")
    report = _json(capsys, ["bench", "speed", "--json", "--frames", "2", "--calibration",
                            str(caldir)])
    assert report["frameset_2cam_ms"] > 0 and report["frameset_4cam_ms"] > 0
    assert set(report["reconstruction"]) == {"multi-view_2cam", "multi-view_4cam",
                                             "spatial_2cam", "spatial_4cam"}
    assert report["sim_render_2cam_ms"] > 0
    assert "frame_to_pose_p99_ms" in report["pending"]
