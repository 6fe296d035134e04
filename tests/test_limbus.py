"""The limbus found in the fringe images (``eyeserver.eye.limbus``), on three rigs.

The rendered patient eye is reconstructed and fitted as ``eyeserver pose`` does; truth is read
only afterwards. Over many random poses of the default rig: docs/benchmarks.md (``eyeserver
bench pose --eyes sharp``; the radius comes from a narrow band of sclera, and sclera and limbus
are measured again from the fringes: tests/test_sclera.py).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.optimize import least_squares

from eyeserver.bench.pose import RADII_MM, random_spec
from eyeserver.eye import limbus, tunables
from eyeserver.eye.fit import EyeModel, EyePose, PoseError, fit_eye
from eyeserver.eye.limbus import LimbusNotFoundError, find_limbus
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.optics import ProjectorModel
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.reconstruction import limbus_views, reconstruct_bundle
from eyeserver.service.patients import DEFAULT_MIN_CONFIDENCE, Tolerances
from eyeserver.service.verification import deviation, judge
from tests.conftest import ROOMS

LOOKING = SceneSpec(kind="eye", position_mm=(1.5, -1.0, -11.0),
                    eye=EyeSpec(gaze_deg=(7.0, -4.0), globe_radius_mm=12.5))


def _record(room: str, spec: SceneSpec, out: Path) -> dict[str, Any]:
    with SimSession.open(load_room(ROOMS[room]), seed=3) as session:
        session.record(spec, out)
    truth: dict[str, Any] = json.loads((out / "truth.json").read_text())["eye"]
    return truth


def _angle_deg(a: Any, b: Any) -> float:
    cos = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def _fit(caldir: Path, bundle: Path) -> EyePose:
    cloud, _ = reconstruct_bundle(caldir, bundle)
    return fit_eye(cloud, EyeModel.population(), limbus_views(caldir, bundle))


@pytest.mark.slow
@pytest.mark.parametrize("room", ["default", "wide", "horizontal"])
def test_gaze_and_limbus_from_the_images(calibrated_rooms: Any, room: str, tmp_path: Path
                                         ) -> None:
    _, caldir = calibrated_rooms(room)
    truth = _record(room, LOOKING, tmp_path / "eye")

    pose = _fit(caldir, tmp_path / "eye")

    assert pose.gaze_source == "limbus (images)"
    assert pose.limbus_centre_mm is not None
    # Measured (default, wide, horizontal): see the module docstring for the default rig's
    # spread over many poses.
    assert _angle_deg(pose.gaze, truth["gaze"]) < 0.5
    assert np.linalg.norm(np.subtract(pose.limbus_centre_mm, truth["limbus_centre_mm"])) < 0.05
    assert np.linalg.norm(np.subtract(pose.centre_mm, truth["centre_mm"])) < 0.4
    assert pose.boundary_radius_mm == pytest.approx(11.7 / 2, abs=0.05)
    assert pose.gaze_sd_deg < 0.5
    assert pose.confidence > 0.5
    # The stated uncertainties hold the errors (they said 0.002–0.01 mm along the gaze for
    # errors of 0.1 mm before the edges' and the sclera's shared errors were counted).
    error = np.abs(np.subtract(pose.centre_mm, truth["centre_mm"]))
    assert np.all(error < 3.0 * np.asarray(pose.centre_sd_mm)), (error, pose.centre_sd_mm)
    assert _angle_deg(pose.gaze, truth["gaze"]) < 2.0 * pose.gaze_sd_deg


@pytest.mark.slow
@pytest.mark.parametrize("room", ["default", "wide", "horizontal"])
@pytest.mark.parametrize(("width_mm", "iris", "within_mm", "radius_within_mm"),
                         [(0.5, 0.06, 0.1, 0.05), (0.2, 0.25, 0.15, 0.1)])
def test_a_soft_limbus_is_found_on_its_junction(calibrated_rooms: Any, room: str,
                                                width_mm: float, iris: float, within_mm: float,
                                                radius_within_mm: float, tmp_path: Path
                                                ) -> None:
    """A patient's limbus is a transition, not a step: the one found lies on the
    corneoscleral junction (the transition's middle) on each rig, with a dark iris behind a
    0.5-mm transition and a light one behind a 0.2-mm one. With the sharpened image's
    illumination fitted from the transition's outer half (tunables.LIMBUS_MARGIN_MM 0.05 mm)
    each pass pulled the limbus further in; wider transitions and a light iris behind a 0.5-mm
    one are not found yet, and refused. Measured: docs/notes/patient-eye.md, eighteenth
    session."""
    _, caldir = calibrated_rooms(room)
    assert LOOKING.eye is not None
    eye = LOOKING.eye.model_copy(update={"limbus_width_mm": width_mm, "iris_albedo": iris,
                                         "sclera_albedo": 0.42})
    truth = _record(room, LOOKING.model_copy(update={"eye": eye}), tmp_path / "eye")

    pose = _fit(caldir, tmp_path / "eye")

    assert pose.limbus_centre_mm is not None
    off = np.linalg.norm(np.subtract(pose.limbus_centre_mm, truth["limbus_centre_mm"]))
    assert off < within_mm
    assert pose.boundary_radius_mm == pytest.approx(11.7 / 2, abs=radius_within_mm)


INVISIBLE = SceneSpec(kind="eye", position_mm=(1.5, -1.0, -11.0), eye=EyeSpec(
    gaze_deg=(7.0, -4.0), globe_radius_mm=12.5, limbus_vertical_ratio=0.88,
    limbus_width_mm=1.0, iris_albedo=0.4, sclera_albedo=0.4, tear_reflectance=0.02))


@pytest.mark.slow
@pytest.mark.parametrize("room", ["default", "wide", "horizontal"])
def test_an_invisible_limbus_gives_no_confident_pose(calibrated_rooms: Any, room: str,
                                                    tmp_path: Path) -> None:
    """A light iris as bright as the sclera in near-infrared behind a soft limbus leaves no
    limbus to see (a patient's eye: clear cornea, the iris behind it, wet): the fit refuses,
    or gives a pose whose confidence fails a verification, on each rig (measured: confidence
    0.13, 0.10 and 0.15 on the default, wide and horizontal rigs)."""
    _, caldir = calibrated_rooms(room)
    _record(room, INVISIBLE, tmp_path / "eye")

    try:
        pose = _fit(caldir, tmp_path / "eye")
    except PoseError:
        return
    assert pose.confidence < DEFAULT_MIN_CONFIDENCE, pose


FAINT = SceneSpec(kind="eye", position_mm=(3.89, 2.46, -5.57), eye=EyeSpec(
    gaze_deg=(6.43, 8.35), globe_radius_mm=10.6, globe_semi_axes_mm=(10.48, 10.54, 10.79),
    cornea_radius_mm=7.70, cornea_asphericity=-0.38, limbus_diameter_mm=11.78,
    limbus_vertical_ratio=0.887, limbus_width_mm=1.24, limbus_scatter=0.001, sclera_albedo=0.377,
    iris_albedo=0.116, iris_depth_mm=2.91, pupil_diameter_mm=2.68, tear_reflectance=0.023,
    tear_glints=2, aperture_mm=(12.12, 7.85), aperture_offset_mm=(-0.29, -0.53),
    lid_gap_mm=0.83, lashes=19, features_seed=18933009))
"""A drawn patient eye (eye_012 of ``scripts/pose_set.py render --eyes patient --count 16 --seed
11``): a 1.24-mm transition under lids and lashes, whose shadow and lid edges fit a circle
better than the limbus does."""


@pytest.mark.slow
@pytest.mark.parametrize("room", ["default", "wide"])
def test_a_faint_limbus_is_not_taken_from_edges_off_the_globes_axis(calibrated_rooms: Any,
                                                                    room: str,
                                                                    tmp_path: Path) -> None:
    """The limbus lies within a few tenths of a millimetre of the globe's axis (on it in this
    eye, drawn before the population drew an offset). Searched for freely, this eye's limbus was a
    circle of other edges 2 mm and 16° off, and the globe placed on it 5.9 and 7.0 mm off (the
    default and wide rigs); held near the axis of both units' cloud globe
    (:data:`~eyeserver.eye.tunables.LIMBUS_AXIS_SD_MM`), the pose is the cloud's, 0.06 and
    0.57 mm off. Either way refused: a limbus this faint is not seen well."""
    _, caldir = calibrated_rooms(room)
    truth = _record(room, FAINT, tmp_path / "eye")

    pose = _fit(caldir, tmp_path / "eye")

    assert np.linalg.norm(np.subtract(pose.centre_mm, truth["centre_mm"])) < 1.0
    assert pose.confidence < DEFAULT_MIN_CONFIDENCE


ELLIPSOIDAL = SceneSpec(kind="eye", position_mm=(1.5, -1.0, -11.0), eye=EyeSpec(
    gaze_deg=(7.0, -4.0), globe_radius_mm=12.0, globe_semi_axes_mm=(12.3, 12.1, 11.7)))
"""An ellipsoidal globe (axial semi-axis 0.5 mm shorter than the others), the rest of the
patient's eye as sharp as the painted one's: clear cornea, iris behind it."""


@pytest.mark.slow
def test_the_physicists_ellipsoid_places_the_globe(calibrated_rooms: Any, tmp_path: Path
                                                  ) -> None:
    """The MRI's ellipsoid places the globe's centre on the limbus at the ellipsoid's own depth
    and the sclera is fitted to it; reduced to a sphere of its mean radius the centre lies
    ≈ 1.5 × 0.5 mm / 2 off along the gaze (measured: 0.036 against 0.20 mm, gaze 0.07°)."""
    _, caldir = calibrated_rooms("default")
    truth = _record("default", ELLIPSOIDAL, tmp_path / "eye")
    cloud, _ = reconstruct_bundle(caldir, tmp_path / "eye")
    views = limbus_views(caldir, tmp_path / "eye")
    axes = (12.3, 12.1, 11.7)

    pose = fit_eye(cloud, EyeModel(globe_semi_axes_mm=axes), views)
    mean = fit_eye(cloud, EyeModel(globe_radius_mm=float(np.mean(axes))), views)

    assert pose.gaze_source == "limbus (images)"
    assert np.linalg.norm(np.subtract(pose.centre_mm, truth["centre_mm"])) < 0.08
    assert _angle_deg(pose.gaze, truth["gaze"]) < 0.2
    assert pose.confidence > DEFAULT_MIN_CONFIDENCE
    assert np.linalg.norm(np.subtract(mean.centre_mm, truth["centre_mm"])) > 0.15


@pytest.mark.slow
def test_an_unknown_ellipsoid_is_refused_against_a_planned_pose(calibrated_rooms: Any,
                                                                tmp_path: Path) -> None:
    """With population defaults the sphere puts the ellipsoidal globe's centre ≈ 0.9 mm off
    along the gaze at a confidence near 0.9 (measured: 0.86 mm, 0.90): the pose says what the
    model leaves unknown of the globe's shape, which holds the error and makes the daemon's
    check against a planned pose refuse it, not pass it."""
    _, caldir = calibrated_rooms("default")
    truth = _record("default", ELLIPSOIDAL, tmp_path / "eye")
    pose = _fit(caldir, tmp_path / "eye")
    error = np.subtract(pose.centre_mm, truth["centre_mm"])
    along = abs(float(error @ np.asarray(truth["gaze"])))

    assert pose.shape_sd_mm == tunables.SHAPE_SD_MM
    stated = math.hypot(float(np.asarray(pose.centre_sd_mm) @ np.abs(truth["gaze"])),
                        pose.shape_sd_mm)
    assert along < 2.0 * stated
    found = replace(deviation(pose.centre_mm, pose.gaze, truth["centre_mm"], truth["gaze"]),
                    model_sd_mm=pose.shape_sd_mm)
    verdict = judge(found, Tolerances(), pose.confidence)
    assert not verdict.passed
    assert any("leaves the globe's shape uncertain" in reason for reason in verdict.reasons)


OVAL = SceneSpec(kind="eye", position_mm=(1.5, -1.0, -11.0), eye=EyeSpec(
    gaze_deg=(7.0, -4.0), globe_radius_mm=12.5, limbus_vertical_ratio=0.88,
    limbus_width_mm=0.2, iris_albedo=0.06, sclera_albedo=0.42, tear_reflectance=0.02))
"""A patient's visible limbus: an oval 0.88 as high as wide (the sclera overlaps the cornea
above and below) with a 0.2-mm transition, behind a clear, wet cornea."""


CLOSE_LIDS = SceneSpec(kind="eye", position_mm=(0.5, -0.5, -10.5), eye=EyeSpec(
    gaze_deg=(3.0, -2.0), globe_radius_mm=12.0, aperture_mm=(10.2, 7.5),
    aperture_offset_mm=(-0.1, -0.6), lid_gap_mm=0.3))
"""The painted eye with a patient's lids: a shell 0.3 mm outside the globe (the population's
closest), with more points in the cloud than the sclera beside the limbus."""

NARROW_LIDS = SceneSpec(kind="eye", position_mm=(0.5, -0.5, -10.5), eye=EyeSpec(
    gaze_deg=(3.0, -2.0), globe_radius_mm=12.0, aperture_mm=(11.0, 6.5),
    aperture_offset_mm=(0.0, -0.3), lid_gap_mm=0.3))
"""The same lids opened less high: they cover the top and bottom of the limbus."""


@pytest.mark.slow
@pytest.mark.parametrize(("room", "spec", "bound_mm"), [
    ("default", CLOSE_LIDS, 0.1), ("default", NARROW_LIDS, 0.1), ("wide", CLOSE_LIDS, 0.1),
    # Fringes parallel to the lid margins: the lids blend into the sclera beside them.
    ("horizontal", NARROW_LIDS, 0.15)], ids=["default", "default-narrow", "wide",
                                              "horizontal-narrow"])
def test_lids_close_to_the_globe_are_not_fitted_as_sclera(calibrated_rooms: Any, room: str,
                                                         spec: SceneSpec, bound_mm: float,
                                                         tmp_path: Path) -> None:
    """Lids taken for the sclera make the globe too large and put the centre off along the
    gaze with a confident face. On `wide` the multi-view order's cloud kept too little sclera
    beside them to tell them apart; in the default room the votes' mean shift drifted from the
    sclera's shell towards the lids' heavier votes; on `horizontal` no trough separates a
    dominant lid shell from the sclera. Measured: docs/notes/patient-eye.md, thirteenth,
    nineteenth and twentieth sessions."""
    _, caldir = calibrated_rooms(room)
    truth = _record(room, spec, tmp_path / "eye")

    pose = _fit(caldir, tmp_path / "eye")

    error = np.subtract(pose.centre_mm, truth["centre_mm"])
    assert np.linalg.norm(error) < bound_mm
    assert np.all(np.abs(error) <= 2.0 * np.asarray(pose.centre_sd_mm)), (error,
                                                                            pose.centre_sd_mm)
    assert pose.globe_radius_mm == pytest.approx(12.0, abs=0.1)
    assert pose.confidence > DEFAULT_MIN_CONFIDENCE


@pytest.mark.slow
def test_close_lids_across_horizontal_fringes_are_refused_not_fitted(calibrated_rooms: Any,
                                                                     tmp_path: Path) -> None:
    """With fringes parallel to the lid margins the band-limited demodulation blends the lids
    into the sclera beside them, across the fringes, and the cloud cannot tell the two shells
    apart: the pose must say so, its stated sd covering its error, and the daemon's check
    refuse it (it was a confident wrong pose: docs/notes/patient-eye.md, twentieth session)."""
    _, caldir = calibrated_rooms("horizontal")
    truth = _record("horizontal", CLOSE_LIDS, tmp_path / "eye")

    pose = _fit(caldir, tmp_path / "eye")

    error = np.subtract(pose.centre_mm, truth["centre_mm"])
    assert np.all(np.abs(error) <= 2.0 * np.asarray(pose.centre_sd_mm)), (error,
                                                                            pose.centre_sd_mm)
    found = replace(deviation(pose.centre_mm, pose.gaze, truth["centre_mm"], truth["gaze"]),
                    measured_sd_mm=pose.centre_sd_mm)
    verdict = judge(found, Tolerances(), pose.confidence)
    assert not verdict.passed
    assert any("only to ±" in reason for reason in verdict.reasons), verdict.reasons


@pytest.mark.slow
def test_an_oval_limbus_is_found_with_its_junctions_radius(calibrated_rooms: Any,
                                                           tmp_path: Path) -> None:
    """The one-shot fit finds the visible oval and reports the horizontal half-width (the
    corneoscleral junction, on which the globe's depth depends); a circle fitted to it came
    out 21° and 7 mm off (measured before the oval)."""
    _, caldir = calibrated_rooms("default")
    truth = _record("default", OVAL, tmp_path / "eye")
    pose = _fit(caldir, tmp_path / "eye")

    assert pose.gaze_source == "limbus (images)"
    assert _angle_deg(pose.gaze, truth["gaze"]) < 0.3
    assert pose.boundary_radius_mm == pytest.approx(11.7 / 2, abs=0.05)
    views = limbus_views(caldir, tmp_path / "eye")
    found = find_limbus(views, pose.centre_mm, pose.gaze, pose.globe_radius_mm, 11.7 / 2,
                        oval=True)
    assert found.ratio == pytest.approx(0.88, abs=0.03)
    assert np.linalg.norm(found.centre - truth["limbus_centre_mm"]) < 0.15


@pytest.mark.slow
def test_a_wrong_start_is_recovered(calibrated_rooms: Any, tmp_path: Path) -> None:
    """The cloud fit's gaze can be 25° off: the start search finds the limbus anyway."""
    _, caldir = calibrated_rooms("default")
    truth = _record("default", LOOKING, tmp_path / "eye")
    views = limbus_views(caldir, tmp_path / "eye")
    gaze = np.asarray(truth["gaze"])
    tilted = gaze + math.tan(math.radians(20.0)) * np.array([0.0, 1.0, 0.0])

    limbus = find_limbus(views, truth["centre_mm"], tilted, truth["globe_radius_mm"] + 0.5,
                         11.7 / 2)

    assert _angle_deg(limbus.normal, gaze) < 0.5
    assert np.linalg.norm(limbus.centre - truth["limbus_centre_mm"]) < 0.05


@pytest.mark.slow
def test_the_circle_fit_is_scipys_robust_least_squares(calibrated_rooms: Any, tmp_path: Path
                                                       ) -> None:
    """The hand-written Levenberg–Marquardt fit of the limbus circle (written for speed) finds
    what ``scipy.optimize.least_squares`` with the same Cauchy loss finds, from a start 0.3 mm
    and 3° off the limbus, with the same loss-scaled Jacobian for the uncertainties."""
    _, caldir = calibrated_rooms("default")
    truth = _record("default", LOOKING, tmp_path / "eye")
    views = limbus_views(caldir, tmp_path / "eye")
    gaze = np.asarray(truth["gaze"])
    normal = gaze + math.tan(math.radians(3.0)) * np.array([1.0, 0.0, 0.0])
    normal /= np.linalg.norm(normal)
    centre = np.asarray(truth["limbus_centre_mm"]) + np.array([0.2, -0.2, 0.1])
    images = [limbus._Image(view, None) for view in views[:2]]
    edges = [limbus._edges(image, centre, normal, 11.7 / 2, 8.0) for image in images]

    rows = limbus._circle_residuals(images, edges, centre, normal, 11.7 / 2)
    # The circle (6 parameters), and the oval with its height ratio free (7).
    for size in (6, 7):
        ours = limbus._fit_circle(images, edges, centre, normal, 11.7 / 2, 1.0, size == 7)
        start = np.array([*centre, normal[0], normal[1], 11.7 / 2, 1.0][:size])
        scale = tunables.CIRCLE_X_SCALE[:size]
        scipys = least_squares(lambda x: rows(x[None])[0], start, loss="cauchy", f_scale=1.0,
                               x_scale=scale, xtol=1e-12, ftol=1e-12, gtol=1e-12)

        assert np.linalg.norm(ours.x[:3] - start[:3]) > 0.1  # it did move
        assert np.all(np.abs(ours.x - scipys.x) < 1e-4 * scale), ours.x - scipys.x
        assert np.allclose(ours.fun, scipys.fun, atol=1e-3)
        assert np.allclose(ours.jac, scipys.jac, rtol=1e-3, atol=1e-3)
    assert ours.x[6] == pytest.approx(1.0, abs=0.01)  # this limbus is round


@pytest.mark.slow
def test_following_the_eye_takes_one_round_where_the_last_gaze_still_fits(
        calibrated_rooms: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Live tracking (no search) from the last frame's gaze: the last search round alone finds
    the limbus; from a gaze a saccade away, the rounds before it bring the start closer."""
    _, caldir = calibrated_rooms("default")
    truth = _record("default", LOOKING, tmp_path / "eye")
    views = limbus_views(caldir, tmp_path / "eye")
    fits: list[int] = []
    fit = limbus._fit_circle
    monkeypatch.setattr(limbus, "_fit_circle", lambda *a: fits.append(1) or fit(*a))
    gaze = np.asarray(truth["gaze"])
    away = gaze + math.tan(math.radians(6.0)) * np.array([1.0, 0.0, 0.0])
    for start, rounds in ((gaze, 1), (away / np.linalg.norm(away), 2)):
        fits.clear()
        found = find_limbus(views, truth["centre_mm"], start, truth["globe_radius_mm"],
                            11.7 / 2, search=False)
        assert len(fits) == rounds
        assert _angle_deg(found.normal, gaze) < 0.5
        assert np.linalg.norm(found.centre - truth["limbus_centre_mm"]) < 0.05


@pytest.mark.slow
def test_closed_lids_have_no_limbus(calibrated_rooms: Any, tmp_path: Path) -> None:
    """Lids closed (an opening too small to show the cornea): no limbus is made up."""
    _, caldir = calibrated_rooms("default")
    blink = SceneSpec(kind="eye", eye=EyeSpec(aperture_mm=(11.0, 0.3)))
    truth = _record("default", blink, tmp_path / "blink")
    views = limbus_views(caldir, tmp_path / "blink")

    with pytest.raises(LimbusNotFoundError):
        find_limbus(views, truth["centre_mm"], truth["gaze"], truth["globe_radius_mm"], 11.7 / 2)


@pytest.mark.slow
def test_two_cameras_are_needed(calibrated_rooms: Any, tmp_path: Path) -> None:
    _, caldir = calibrated_rooms("default")
    truth = _record("default", LOOKING, tmp_path / "eye")
    views = limbus_views(caldir, tmp_path / "eye")

    with pytest.raises(LimbusNotFoundError, match="two cameras"):
        find_limbus(views[:1], truth["centre_mm"], truth["gaze"], 12.0, 11.7 / 2)


def _record_one_unit(spec: SceneSpec, out: Path) -> dict[str, Any]:
    with SimSession.open(load_room(ROOMS["default"]), seed=3) as session:
        session.record(spec, out, units=["left"])
    truth: dict[str, Any] = json.loads((out / "truth.json").read_text())["eye"]
    return truth


@pytest.mark.slow
def test_one_unit_finds_the_limbus_about_the_cameras_when_the_cloud_gaze_is_far_off(
        calibrated_rooms: Any, tmp_path: Path) -> None:
    # One unit's cloud alone can put the gaze 40° off (measured on a rendered pose of eyeserver
    # bench pose): beyond the start search's 30° about it; the search about +Z finds it.
    _, caldir = calibrated_rooms("default")
    spec = SceneSpec(kind="eye", position_mm=(3.9, -2.7, -8.8),
                     eye=EyeSpec(gaze_deg=(-8.3, 6.7), globe_radius_mm=12.0))
    truth = _record_one_unit(spec, tmp_path / "eye")
    views = limbus_views(caldir, tmp_path / "eye")
    assert len(views) == 2
    gaze = np.asarray(truth["gaze"])
    off = gaze + math.tan(math.radians(42.0)) * np.array([0.0, -1.0, 0.0])

    limbus = find_limbus(views, truth["centre_mm"], off, truth["globe_radius_mm"], 11.7 / 2)

    assert _angle_deg(limbus.normal, gaze) < 0.5
    assert np.linalg.norm(limbus.centre - truth["limbus_centre_mm"]) < 0.05


@pytest.mark.slow
def test_a_held_radius_places_the_globe_on_a_limbus_seen_with_hardly_any_sclera(
        calibrated_rooms: Any, tmp_path: Path) -> None:
    # Turned away from the one unit that sees it, the eye shows its limbus whole and hardly
    # any sclera beside it: a few hundred points squeezed against the lids, 0.4–0.5 mm off
    # (the fringe analysis smears lid and sclera there). With the patient's radius the limbus
    # places the globe (measured 0.06–0.08 mm; the cloud-only pose was 1.3 mm and 8° off), and
    # the confidence says how little carries it (measured 0.43 with 161 sclera points; 0.001
    # with 8 before the speckle filter kept the sclera's smaller patches; 0.9 and more for an
    # eye in view).
    _, caldir = calibrated_rooms("default")
    spec = SceneSpec(kind="eye", position_mm=(1.29, 4.27, -10.6),
                     eye=EyeSpec(gaze_deg=(9.1, 0.0), globe_radius_mm=13.0))
    truth = _record_one_unit(spec, tmp_path / "eye")
    cloud, _ = reconstruct_bundle(caldir, tmp_path / "eye")

    pose = fit_eye(cloud, EyeModel(globe_radius_mm=13.0), limbus_views(caldir, tmp_path / "eye"))

    assert pose.gaze_source == "limbus (images)"
    assert _angle_deg(pose.gaze, truth["gaze"]) < 0.5
    assert np.linalg.norm(np.subtract(pose.centre_mm, truth["centre_mm"])) < 0.15
    assert pose.sclera_points < 300 and pose.confidence < 0.6


@pytest.mark.slow
def test_one_unit_tries_the_dark_disc_too_when_a_fit_from_the_cloud_looks_good(
        calibrated_rooms: Any, tmp_path: Path) -> None:
    # The fourth pose of `eyeserver bench pose --unit left --held-radius` (its random draws
    # replayed): one unit's cloud starts the limbus 60° off, and the circle fitted from there
    # fits its edges well yet lay 5° off (centre 1.3 mm) — one camera pair's circle depends
    # on its start. Started from the cornea's dark disc as well, the closer fit is the limbus.
    _, caldir = calibrated_rooms("default")
    rng = np.random.default_rng(0)
    with SimSession.open(load_room(None), seed=1) as session:
        for n in range(4):
            spec = random_spec(rng, RADII_MM[n % len(RADII_MM)])
            session.record(spec, tmp_path / "eye", units=["left"], overwrite=True)
    truth = json.loads((tmp_path / "eye" / "truth.json").read_text())["eye"]
    cloud, _ = reconstruct_bundle(caldir, tmp_path / "eye")

    pose = fit_eye(cloud, EyeModel(globe_radius_mm=spec.eye.globe_radius_mm),
                   limbus_views(caldir, tmp_path / "eye"))

    assert _angle_deg(pose.gaze, truth["gaze"]) < 0.5
    assert np.linalg.norm(np.subtract(pose.centre_mm, truth["centre_mm"])) < 0.15


def _found_limbus(radius: float) -> limbus.Limbus:
    """A limbus circle found at the origin, facing +Z, of ``radius`` (mm)."""
    return limbus.Limbus(centre=np.zeros(3), normal=np.array([0.0, 0.0, 1.0]), radius=radius,
                         centre_sd_mm=0.01, gaze_sd_deg=0.1, radius_sd_mm=0.01, residual_px=0.2,
                         coverage={})


def _shell(rng: np.random.Generator, centre: np.ndarray, radii: np.ndarray,
           polar_deg: tuple[float, float]) -> np.ndarray:
    """Points on spheres about ``centre`` (one radius each) at polar angles from +Z."""
    polar = np.radians(rng.uniform(*polar_deg, radii.size))
    azimuth = rng.uniform(0.0, 2 * math.pi, radii.size)
    directions = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                           np.cos(polar)], axis=1)
    return np.asarray(centre + radii[:, None] * directions)


def test_the_globe_on_the_limbus_is_supported_by_a_sclera_shell_not_by_lids() -> None:
    """The sclera votes for one sphere through the limbus; lids, spread over millimetres, do
    not: where no sclera is seen the innermost shell is the lids', and its little support
    (what the pose's confidence counts; measured on a rendered pose of `bench pose` whose
    globe came out 3.9 mm off: 43 against 196–1,775 on 24 others) gives it away."""
    rng = np.random.default_rng(5)
    r, radius = 11.7 / 2, 12.0
    centre = np.array([0.0, 0.0, -math.sqrt(radius**2 - r**2)])
    found = _found_limbus(r)
    sclera = _shell(rng, centre, radius + rng.normal(0.0, 0.02, 1500), (32.0, 50.0))
    lids = _shell(rng, centre, rng.uniform(12.8, 15.0, 3000), (30.0, 70.0))

    seen = limbus.globe_on_limbus(np.vstack([sclera, lids]), found)
    hidden = limbus.globe_on_limbus(lids, found)

    assert seen.radius == pytest.approx(radius, abs=0.02) and seen.support > 200
    assert abs(hidden.radius - radius) > 0.5  # the lids taken for the sclera
    assert hidden.support < 0.1 * seen.support


def test_lids_close_to_the_globe_are_told_from_the_sclera_by_their_own_shell() -> None:
    """Lids 0.3–0.5 mm outside the globe (a patient's may lie as close) lie within the fixed
    0.5 mm the sphere's points were once taken from, and were fitted as sclera (here the radius
    0.14 mm large at 0.35 mm): the trough between the two shells' offsets separates them. The
    sclera alone, its flanks spread outwards by the band-limited FTM, shows no second shell and
    keeps the fixed clearance (:data:`~eyeserver.eye.tunables.LID_GAP_MM`)."""
    rng = np.random.default_rng(12)
    r, radius = 11.7 / 2, 12.0
    centre = np.array([0.0, 0.0, -math.sqrt(radius**2 - r**2)])
    found = _found_limbus(r)
    sclera_radii = radius + np.concatenate([rng.normal(0.0, 0.04, 3000),
                                            rng.exponential(0.1, 600)])  # the flanks
    sclera = _shell(rng, centre, sclera_radii, (32.0, 55.0))
    for gap in (0.35, 0.45):
        lids = _shell(rng, centre, radius + gap + rng.normal(0.0, 0.04, 3000), (40.0, 70.0))
        globe = limbus.globe_on_limbus(np.vstack([sclera, lids]), found)
        assert globe.radius == pytest.approx(radius, abs=0.05), gap
    assert limbus._lid_gap(np.linalg.norm(sclera - centre, axis=1) - radius) == (
        tunables.LID_GAP_MM)
    assert limbus._lid_gap(np.empty(0)) == tunables.LID_GAP_MM  # nothing behind the limbus


def test_the_globe_depth_takes_the_whole_shell_and_states_the_bias_it_cannot_see() -> None:
    """The depth behind the limbus comes from every sclera point of the shell, not from the
    votes' mode: on a noisy shell the least-squares radius is closer than the mode's (measured on
    180 rendered poses: globe centre 0.103 → 0.083 mm median). A bias shared by the whole sclera
    cannot be told from a larger globe, so the stated depth uncertainty holds the gain such a
    bias has on the depth times :data:`~eyeserver.eye.tunables.CLOUD_SCLERA_BIAS_MM`, and the
    depth moves by that gain when the sclera is shifted."""
    rng = np.random.default_rng(8)
    r, radius = 11.7 / 2, 12.5
    depth = math.sqrt(radius**2 - r**2)
    centre = np.array([0.0, 0.0, -depth])
    found = _found_limbus(r)
    polar = (37.0, 60.0)
    exact = limbus.globe_on_limbus(_shell(rng, centre, np.full(3000, radius), polar), found)
    noisy = [limbus.globe_on_limbus(
        _shell(rng, centre, radius + rng.normal(0.0, 0.08, 3000), polar), found)
        for _ in range(8)]
    shifted = limbus.globe_on_limbus(_shell(rng, centre, np.full(3000, radius + 0.02), polar),
                                     found)

    assert exact.radius == pytest.approx(radius, abs=1e-4)
    assert exact.centre == pytest.approx(centre, abs=1e-4)
    assert max(abs(g.radius - radius) for g in noisy) < 0.01  # the mode: 0.037 mm at worst
    gain = (-float(shifted.centre[2]) - depth) / 0.02
    assert 2.0 < gain < 8.0  # how far the depth moves per millimetre of the sclera's bias
    assert exact.depth_sd_mm == pytest.approx(gain * tunables.CLOUD_SCLERA_BIAS_MM, rel=0.05)


def test_the_cornea_shadows_the_sclera_beyond_the_limbus_from_light_past_its_rim() -> None:
    """A 7.8-mm cornea meets a 5.85-mm limbus 48.6° off the gaze, so light from more than
    41.4° off the gaze is kept off the sclera just beyond the limbus on the side away from it;
    from nearer the gaze, or past a cornea no wider than the limbus, nothing is."""
    gaze, radius, globe_radius = np.array([0.0, 0.0, 1.0]), 5.85, 13.0
    globe = np.array([1.0, -2.0, -10.0])
    centre = globe + math.sqrt(globe_radius**2 - radius**2) * gaze
    angles = np.linspace(0.0, 2 * math.pi, 360, endpoint=False)
    rim = limbus.circle_points(limbus.Limbus(centre, gaze, radius, 0.0, 0.0, 0.0, 0.0, {}),
                               angles)

    def shadowed(off_gaze_deg: float, cornea_mm: float = 7.8) -> np.ndarray:
        light = np.array([math.sin(math.radians(off_gaze_deg)), 0.0,
                          math.cos(math.radians(off_gaze_deg))])
        return limbus.in_cornea_shadow(centre, gaze, radius, angles,
                                       limbus.Shade(globe, globe_radius, cornea_mm), light)

    assert not shadowed(40.0).any()
    at_45, at_55 = shadowed(45.0), shadowed(55.0)
    assert 0 < at_45.sum() < at_55.sum() < len(angles) // 2
    # On the far side from the light (+X), symmetric about its plane.
    assert np.all(rim[at_55, 0] < centre[0])
    assert abs(float(np.mean(rim[at_55, 1])) - centre[1]) < 0.05
    assert not shadowed(55.0, cornea_mm=radius).any()


@pytest.mark.slow
@pytest.mark.parametrize("room", ["default", "wide", "horizontal"])
def test_each_camera_knows_where_its_projector_lights_the_eye_from(
        calibrated_rooms: Any, room: str, tmp_path: Path) -> None:
    """Straight fringes put the projector on a line through every iso-phase plane: the
    calibration gives the direction from the eye across the fringes to within 2.5° of the
    renderer's projector (its offset along the fringes from the eye is the rest), on rigs with
    vertical fringes beside the eye and horizontal ones above it (measured: at most 2.0° on
    eight rendered eyes of the default rig)."""
    _, caldir = calibrated_rooms(room)
    truth = _record(room, LOOKING, tmp_path / "eye")
    projectors = {camera.id: ProjectorModel(unit.projector).centre
                  for unit in load_room(ROOMS[room]).units for camera in unit.cameras}
    at = np.asarray(truth["limbus_centre_mm"])
    for view in limbus_views(caldir, tmp_path / "eye"):
        light = view.camera.light_direction(at)
        assert light is not None
        assert _angle_deg(light, projectors[view.camera.camera_id] - at) < 2.5
