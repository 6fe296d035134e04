"""The benches: one JSON document each, every figure named, measured figures within the goals."""

from __future__ import annotations

import json
from typing import Any

import cv2
import numpy as np
import pytest

from eyeserver.bench import speed, tracking
from eyeserver.bench.figures import FIGURES
from eyeserver.bench.pose import format_text as format_pose_text
from eyeserver.bench.pose import p95_interval
from eyeserver.bench.report import p95_text, render, render_pose, render_speed
from eyeserver.cli import main
from eyeserver.pipeline.demodulate import Carrier, demodulate


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
                "icp_rmse_2view_mm", "seam_error_mm", "static_noise_mm", "eye_model_distance_mm",
                "surface_median_4view_mm", "surface_median_2view_mm", "surface_rmse_4view_mm",
                "surface_rmse_2view_mm"):
        assert report[key] <= FIGURES[key].goal, (key, report[key])
    assert report["surface_median_4view_mm"] < 0.05
    assert report["fiducials"]["measurements"] >= 8  # the dots found in both cameras of a unit
    assert report["4view_measurements"] == 1 and report["2view_measurements"] == 2
    assert report["spatial_4view_measurements"] == 1
    for key in report["pending"]:
        assert report[key] is None
    assert report["noise_model"]["bit_depth"] == 8
    assert report["ftm_phase_error_rad"] < 0.032  # the public 4-step set (test_public_fringes)
    assert report["static_noise"]["repeats"] == 4 and report["seam"]["points"] > 0
    assert "eye_phantom_1#0" in {m["case"] for m in report["measurements"]}
    assert {"phantom", "base"} <= set(report["measurements"][0]["by_surface"])
    page = render(report, {"frameset_2cam_ms": 123.4, "pending": {}})
    assert "| reprojection error, median (px) | 0.88 (IQR 1.44) | ≤ 0.15 |" in page
    assert "`frameset_2cam_ms` | 123.4 |" in page


def test_accuracy_bench_refuses_an_unknown_phantom(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "accuracy", "--phantoms", "teapot"]) == 2
    assert "teapot" in capsys.readouterr().err


def test_speed_bench_times_the_pipeline(calibrated_rooms: Any,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    _, caldir = calibrated_rooms("default")
    report = _json(capsys, ["bench", "speed", "--json", "--frames", "2", "--calibration",
                            str(caldir), "--api-requests", "2", "--tracking-seconds", "0",
                            "--replay-seconds", "0"])
    assert report["frameset_2cam_ms"] > 0 and report["frameset_4cam_ms"] > 0
    assert set(report["reconstruction"]) == {"multi-view_2cam", "multi-view_4cam",
                                             "spatial_2cam", "spatial_4cam"}
    assert report["sim_render_2cam_ms"] > 0
    assert "tracking" not in report and "frame_to_pose_p99_ms" not in report  # skipped
    assert "tracking_replay" not in report
    assert report["goals_ms"] == {"frameset_2cam_ms": 10.0, "frameset_4cam_ms": 20.0}
    # How fast the machine ran, beside the figures: one FFT of a camera image, well under the
    # whole 2-camera frame-set (two of them and much more).
    for when in ("start", "end"):
        assert 0 < report["machine"][f"reference_fft_ms_at_{when}"] < report["frameset_2cam_ms"]
    for key in ("framesets_2cam_per_s", "framesets_4cam_per_s", "frameset_4cam_2threads_ms",
                "framesets_4cam_2threads_per_s", "peak_rss_mib"):
        assert report[key] > 0, key
    threads = report["parallel"]
    assert threads["workers"] == 2
    assert threads["framesets_per_worker_4cam"]["framesets_per_s"] > 0

    stages = report["stages"]
    assert stages["passes"] == 2 and stages["opencv_threads"] == 1
    assert stages["reproduces_unit_clouds"]  # the stages one by one give unit_clouds' points
    assert len(stages["per_camera"]) == 4
    for per_camera in stages["per_camera"].values():
        assert set(per_camera) == set(speed.STAGES)
        for figure in per_camera.values():
            assert figure["median_ms"] > 0 and figure["p95_ms"] >= figure["median_ms"]
            assert figure["n"] == 2
    for label in ("2cam", "4cam"):
        block = stages["per_frameset"][label]
        assert set(block) == {*speed.STAGES, "fusion", "sum_multi_view", "sum_spatial"}
        assert block["sum_multi_view"]["median_ms"] > block["demodulation"]["median_ms"]
    assert (stages["per_frameset"]["4cam"]["demodulation"]["median_ms"]
            > stages["per_frameset"]["2cam"]["demodulation"]["median_ms"] / 2)

    peers = report["peers"]
    for name in ("skimage_unwrap_phase", "numpy_fft_ftm"):
        assert peers[name]["available"], name
        assert peers[name]["time_ratio"] == pytest.approx(
            peers[name]["peer_median_ms"] / peers[name]["ours_median_ms"])
    assert peers["numpy_fft_ftm"]["phase_vs_ours_median_rad"] < 0.1
    contrib = peers["opencv_contrib_ftp"]
    assert contrib["available"] == hasattr(cv2, "structured_light")
    if contrib["available"]:
        assert contrib["phase_vs_ours_median_rad"] < 0.2 and contrib["time_ratio"] > 0
    else:
        assert "opencv-contrib-python-headless" in contrib["reason"]
    memory = report["memory"]
    assert memory["peak_rss_mib"] >= memory["peak_rss_before_reconstruction_mib"] > 0
    assert memory["frameset_4cam_traced_peak_mib"] > 0

    api = report["api"]
    assert api["requests"] == 2
    assert set(api["captures"]) == {"left", "right", "all"}
    assert set(api["reconstructions"]) == {"left", "all"}
    for table in (api["captures"], api["reconstructions"]):
        for figure in table.values():
            assert figure["n"] == 2 and figure["median_ms"] > 0
    # A reconstruction runs the pipeline on what a capture stored: it cannot be quicker than
    # the pipeline alone on the same number of cameras.
    assert api["reconstructions"]["all"]["min_ms"] > report["frameset_4cam_ms"] / 2
    assert report["api_capture_all_ms"] == api["captures"]["all"]["median_ms"]
    page = render_speed(report)
    assert "| capture → 201 of all |" in page and "| reconstruction of left |" in page

    text = speed.format_text(report)
    for expected in ("≤ 10", "≤ 20", "fringe_order_grid", "fusion", "scikit-image unwrap_phase",
                     "plain FFT FTM", "OpenCV contrib FTP", "peak resident set",
                     "capture →201 of all", "reconstruction of left", "machine speed"):
        assert expected in text, expected


@pytest.mark.parametrize("angle_rad", [0.05, 1.5, 0.8])
def test_speed_bench_fft_baseline_demodulates_like_ours(angle_rad: float) -> None:
    rows, cols = np.mgrid[0:240, 0:320].astype(np.float64)
    carrier = Carrier.from_polar(angle_rad, 0.06)
    fy, fx = carrier.frequency
    bump = 2.0 * np.exp(-((rows - 120) ** 2 + (cols - 160) ** 2) / (2 * 50.0 ** 2))
    image = np.rint(90 + 50 * np.cos(2 * np.pi * (fy * rows + fx * cols) + bump))
    ours = demodulate(image.astype(np.uint8), carrier).wrapped_phase
    theirs = speed.fft_ftm(image.astype(np.uint8), carrier)
    inner = (slice(30, -30), slice(30, -30))
    difference = np.abs(np.angle(np.exp(1j * (theirs - ours))))[inner]
    assert theirs.shape == ours.shape and theirs.dtype == np.float32
    assert np.median(difference) < 0.03


def test_speed_bench_contrib_peer_is_guarded() -> None:
    ftp, reason = speed.opencv_ftp()
    if not hasattr(cv2, "structured_light"):
        assert ftp is None
        assert "opencv-contrib-python-headless" in reason and "never install both" in reason
        return
    assert ftp is not None  # only with opencv-contrib-python-headless in place of the plain one
    cols = np.mgrid[0:240, 0:320][1].astype(np.float64)
    image = np.rint(90 + 50 * np.cos(2 * np.pi * 0.05 * cols)).astype(np.uint8)
    carrier = Carrier((0.0, 0.05))
    difference = np.angle(np.exp(1j * (ftp(image, carrier)
                                       - demodulate(image, carrier).wrapped_phase)))
    assert np.median(np.abs(difference[30:-30, 30:-30])) < 0.05


def test_pose_bench_scores_random_eyes(calibrated_rooms: Any,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    _, caldir = calibrated_rooms("default")
    report = _json(capsys, ["bench", "pose", "--json", "--poses", "3", "--calibration",
                            str(caldir)])
    assert report["poses"] == 3 and report["fitted"] == 3
    assert report["gaze_sources"] == {"limbus (images)": 3}
    # Measured on 200 poses: see docs/benchmarks.md; three poses stay well inside these.
    assert report["gaze_error_deg"]["max"] < 1.0
    assert report["limbus_centre_error_mm"]["max"] < 0.05
    assert report["centre_error_mm"]["max"] < 0.6
    assert 0.8 < report["shift"]["measured_shift_mm"] < 1.2 and report["shift"]["fails_tolerance"]
    # How often the errors lie within the poses' stated sds (too few poses here to judge them;
    # test_limbus checks them on one pose per rig, the bench on 200).
    calibration = report["uncertainty"]
    assert 0.0 <= calibration["centre_axes_within_1_sd"] \
        <= calibration["centre_axes_within_2_sd"] <= 1.0
    assert 0.0 <= calibration["gaze_within_1_sd"] <= calibration["gaze_within_2_sd"] <= 1.0
    # The p95s' bootstrap intervals: over the three poses, none for one pose of a globe size.
    low, high = report["centre_error_mm"]["p95_interval"]
    assert low <= report["centre_error_mm"]["p95"] <= high
    assert all(by["centre_error_mm"]["p95_interval"] is None
               for by in report["by_globe_radius"].values())
    section = "\n".join(render_pose(report))
    assert "| p95 (95 % bootstrap interval) |" in section
    text = format_pose_text(report)
    assert "globe 13 mm (1 poses): centre" in text and "95 % bootstrap intervals" in text
    assert report["held_radius"] is False
    assert "## Eye pose, radius fitted" in section and "model: population" in section
    assert "a fail against the 0.2 mm tolerance" in section
    assert "stated uncertainties: centre errors within 1 and 2 sd on" in section

    # One unit with the patient's radius held, as live tracking measures.
    one = _json(capsys, ["bench", "pose", "--json", "--poses", "2", "--unit", "left",
                         "--held-radius", "--calibration", str(caldir)])
    assert one["units"] == ["left"] and one["held_radius"] is True
    assert one["model"].startswith("radius held")
    assert one["fitted"] == 2 and one["gaze_sources"] == {"limbus (images)": 2}
    assert one["gaze_error_deg"]["max"] < 1.0
    # Held: the sphere through the limbus of that radius (hypot(√(R² − r²), r): R to rounding).
    assert one["radius_error_mm"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert "`eyeserver bench pose --poses 2 --seed 0 --held-radius`: 2 of 2" \
        in "\n".join(render_pose(one))
    assert main(["bench", "pose", "--unit", "centre", "--calibration", str(caldir)]) == 2
    assert "no unit centre" in capsys.readouterr().err


def test_tracking_bench_measures_live_tracking(calibrated_rooms: Any,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """A short run through a daemon on loopback, its room rendered ahead (the figures are the
    bench's, not checked)."""
    _, caldir = calibrated_rooms("default")
    report = _json(capsys, ["bench", "tracking", "--json", "--seconds", "15", "--calibration",
                            str(caldir), "--prerendered"])
    frames, latency = report["frames"], report["latency_ms"]
    assert report["error"] is None
    assert frames["processed"] > 0
    assert frames["camera_periods"] == frames["acquired"] + frames["missed"]
    # The camera periods begin with the first frame, after the cameras were prepared.
    assert report["stream_s"] == pytest.approx(frames["camera_periods"] / 25.0)
    assert report["stream_s"] < report["elapsed_s"]
    assert 0 < report["first_pose_after_start_s"] < report["elapsed_s"]
    assert latency["end_to_end_p99"] >= latency["end_to_end_median"] > 0
    assert report["fits"]["with_pose"] > 0
    assert report["clients"]["count"] == 20 and report["clients"]["reader_messages_lost"] == 0
    blink = report["blink"]  # scripted three quarters of the way
    assert blink["duration_s"] == tracking.BLINK_S
    assert max(blink["held"], blink["seen_as_blink"], blink["with_pose"]) \
        <= blink["frames_half_shut"]
    assert "lids half shut or more" in tracking.format_text(report)
    assert report["reference_fft_ms"]["at_start"] > 0 and report["reference_fft_ms"]["at_end"] > 0
    assert "machine speed" in tracking.format_text(report)
    # Every camera frame of the stream came from the frames rendered ahead (and one more, in
    # flight when tracking stopped; the warm-up frame's time is not a whole period: rendered
    # at once).
    ahead = report["prerendered"]
    assert ahead["seconds"] == 15 + 3 + tracking.PRERENDER_MARGIN_S
    assert set(ahead["cameras"]) == {"S1", "S2"}
    for camera in ahead["cameras"].values():
        assert frames["acquired"] <= camera["used"] <= frames["acquired"] + 1
        assert camera["live"] <= 1
    slowest = report["slowest"]
    assert len(slowest) == 8 and slowest[0]["latency_ms"] >= slowest[-1]["latency_ms"]
    assert "rendered ahead" in tracking.format_text(report)
    # The saccade (8° against a 2° tolerance) holds the beam on the first frame after it,
    # seen out of tolerance or, where that frame showed no eye, lost.
    reaction = report["beam_hold_reaction"]
    assert reaction["first_processed_frame_after_saccade_held"] is True
    reasons = set(reaction["first_processed_frame_after_saccade_reasons"])
    assert reasons & {"out_of_tolerance", "lost"}


def test_the_replay_bench_counts_every_frame_it_hands_the_tracking_worker(
        calibrated_rooms: Any) -> None:
    """Two seconds replayed: every frame is processed or dropped (counted), every processed
    one of the visible eye has a pose (the figures are the bench's, not checked)."""
    _, caldir = calibrated_rooms("default")
    report = tracking.replayed(caldir, 2.0)
    assert report["frames"] == 50 and report["error"] is None and report["workers"] == 2
    assert report["processed"] + report["dropped"] == 50 and report["processed"] >= 2
    assert report["with_pose"] == report["processed"]
    latency = report["latency_ms"]
    assert latency["p99"] >= latency["median"] > 0
    assert report["first_frame_latency_ms"] > 0
    assert "of 50 frames processed" in tracking.format_replayed(report)


def test_the_speed_report_shows_live_tracking_rendered_live_and_ahead() -> None:
    """The two runs of ``eyeserver bench tracking`` land in the speed report and its page,
    each with its own figures (made-up reports: the runs themselves are tested above)."""
    def run(median: float, p99: float) -> dict[str, Any]:
        return {"seconds": 60, "slowest": [{"latency_ms": p99 + 20, "script_s": 33.09}],
                "reference_fft_ms": {"at_start": 0.61, "at_end": 0.64},
                "latency_ms": {"end_to_end_median": median, "end_to_end_p99": p99,
                               "delivery_median": 8.0, "delivery_p99": 9.0,
                               "processing_median": 20.0, "processing_p99": 28.0},
                "frames": {"processed": 1494, "camera_periods": 1494, "dropped": 0,
                           "missed": 0, "processed_share": 1.0},
                "beam_hold_reaction": {"saccade_deg": 8.0,
                                       "first_processed_frame_after_saccade_held": p99 < 50},
                "blink": {"frames_half_shut": 5, "duration_s": 0.3, "held": 5},
                "clients": {"readers": 19, "reader_rate_hz_min": 24.9,
                            "reader_rate_hz_max": 25.0, "reader_messages_lost": 0}}

    figures = speed.tracking_figures(run(38.0, 90.0), run(30.0, 39.0))
    assert (figures["frame_to_pose_p99_ms"], figures["prerendered_frame_to_pose_p99_ms"]) \
        == (90.0, 39.0)
    assert figures["frame_to_pose_goal_p99_ms"] == 40.0
    assert "rendered before tracking" in figures["tracking_prerendered"]["what"]
    page = render_speed({"pending": {}, **figures})
    assert "38 ms median, 90 ms p99" in page and "30 ms median, 39 ms p99" in page
    assert "110 at 33.09" in page and "0.61 ms at its start" in page
    assert "8° saccade held the beam" in page and "8° saccade did NOT hold" in page
    assert "Of the 5 processed frames of the 0.3-s blink" in page
    assert "19 WebSocket clients reading beside one that never read received 24.9–25.0" in page
    text = "\n".join(speed.tracking_lines(figures))
    assert "the simulated room rendered ahead): frame → pose message 30 ms median" in text
    assert speed.tracking_figures(None, None) == {}


def test_p95_interval_measures_the_draws_luck() -> None:
    """The bootstrap interval of a p95 holds the population's p95 and narrows with more poses;
    it is deterministic, and undefined for fewer than two values."""
    rng = np.random.default_rng(3)
    many, few = rng.uniform(0.0, 1.0, 1000), rng.uniform(0.0, 1.0, 60)
    wide, narrow = p95_interval(few), p95_interval(many)
    assert wide is not None and narrow is not None
    assert narrow[0] < 0.95 < narrow[1] and narrow[1] - narrow[0] < 0.03
    assert wide[0] <= float(np.percentile(few, 95)) <= wide[1]
    assert wide[1] - wide[0] > 2 * (narrow[1] - narrow[0])
    assert p95_interval(few) == wide
    assert p95_interval([0.1]) is None
    assert (p95_text({"p95": 0.1, "p95_interval": [0.05, 0.12]}, " mm")
            == "0.100 mm (0.050–0.120 mm)")
    assert p95_text({"p95": 0.1}) == "0.100"
