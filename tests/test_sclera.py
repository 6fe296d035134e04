"""The sclera measured again from its own fringes (``eyeserver.eye.sclera``).

Synthetic fringes check the local fit where the band-limited demodulation is biased (beside
the end of the fringe field); a synthetic sphere checks the joint fit of globe and limbus; a
rendered eye checks that the remeasured sclera lies on the true globe, not on the hypothesis it
was measured about, and that the limbus found again with the fringe divided out is sharper than
the band's. Truth is read only after the pipeline ran.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from eyeserver.eye import fit as fit_module
from eyeserver.eye import limbus as limbus_module
from eyeserver.eye import sclera, tunables
from eyeserver.eye.fit import EyeModel, fit_eye, radius_bounds
from eyeserver.eye.limbus import Limbus, LimbusView
from eyeserver.hardware.sim.config import load_room
from eyeserver.hardware.sim.scenes import EyeSpec, SceneSpec
from eyeserver.hardware.sim.sessions import SimSession
from eyeserver.pipeline.demodulate import Carrier, demodulate
from eyeserver.reconstruction import limbus_views, reconstruct_bundle
from tests.conftest import ROOMS


def _fringes(offset: float, shading: float = 0.0
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A chirped fringe on a disc, dark and fringe-free around it: image, true phase, template
    phase (``offset`` less) and the disc; ``shading``: the amplitude's relative variation."""
    rows, cols = np.mgrid[0:96, 0:128].astype(np.float64)
    phase = 2 * np.pi * 0.08 * cols + 0.004 * (cols - 64) ** 2 + 0.002 * (rows - 48) ** 2
    amplitude = 25.0 * (1.0 + shading * np.sin(cols / 20.0))
    disc = (rows - 48) ** 2 + (cols - 64) ** 2 < 36**2
    image = np.where(disc, 60.0 + amplitude * np.cos(phase), 8.0)
    return image, phase, phase - offset, disc


def test_the_local_fit_finds_the_phase_up_to_the_edge_of_the_fringe_field() -> None:
    image, phase, template, disc = _fringes(0.1)

    delta, sd, _ = sclera._local_offsets(image, template, disc)
    fitted = np.isfinite(sd)

    # Every sclera pixel with enough of its window on the sclera, the edge's included.
    edge = disc & ~np.roll(disc, 3, axis=1)
    assert fitted[edge].mean() > 0.9
    assert np.abs(delta[fitted] - 0.1).max() < 1e-6
    # The band-limited demodulation of the same image is biased there (why this exists).
    band = demodulate(image.astype(np.float32), Carrier((0.0, 0.08)), measure_bends=False)
    band_error = np.angle(np.exp(1j * (band.wrapped_phase - phase)))
    assert np.median(np.abs(band_error[edge])) > 0.05


def test_shading_within_a_window_costs_the_local_fit_a_little() -> None:
    # An amplitude that changes 7 % across a window (held constant in it) reads as ≈ 0.013 rad
    # of phase (see _local_offsets), at the edge as inside.
    image, _, template, disc = _fringes(0.1, shading=0.3)

    delta, sd, _ = sclera._local_offsets(image, template, disc)
    fitted = np.isfinite(sd)

    edge = disc & ~np.roll(disc, 3, axis=1)
    assert abs(np.mean(delta[fitted]) - 0.1) < 0.015
    assert abs(np.mean(delta[fitted & edge]) - 0.1) < 0.015


def test_the_local_fit_ignores_what_lies_outside_its_mask() -> None:
    image, _, template, disc = _fringes(0.0)
    # Another surface's fringe, half a period out of step, right beside the sclera.
    rows, cols = np.mgrid[0:96, 0:128].astype(np.float64)
    lid = ~disc & (rows < 48)
    image = np.where(lid, 60.0 + 25.0 * np.cos(2 * np.pi * 0.08 * cols + np.pi), image)

    delta, sd, _ = sclera._local_offsets(image, template, disc)
    fitted = np.isfinite(sd)

    assert np.abs(delta[fitted]).max() < 1e-6


def _limbus(centre: np.ndarray, normal: np.ndarray, radius: float, gaze_sd_deg: float,
            centre_sd_mm: float) -> Limbus:
    return Limbus(centre=centre, normal=normal / np.linalg.norm(normal), radius=radius,
                  centre_sd_mm=centre_sd_mm, gaze_sd_deg=gaze_sd_deg, radius_sd_mm=0.01,
                  residual_px=0.1, coverage={})


def _band(rng: np.random.Generator, centre: np.ndarray, radius: float, gaze: np.ndarray,
          n: int) -> np.ndarray:
    """Points of a sphere 45–65° from the gaze (the visible sclera), on one side only."""
    polar = np.radians(rng.uniform(45.0, 65.0, n))
    azimuth = np.radians(rng.uniform(-60.0, 80.0, n))
    e1 = np.cross(gaze, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(gaze, e1)
    directions = (np.cos(polar)[:, None] * gaze
                  + np.sin(polar)[:, None] * (np.cos(azimuth)[:, None] * e1
                                              + np.sin(azimuth)[:, None] * e2))
    return centre + radius * directions


def test_the_globe_and_gaze_take_the_sclera_where_it_knows_better_than_the_limbus() -> None:
    rng = np.random.default_rng(4)
    centre, radius = np.array([1.0, -0.5, -12.0]), 12.6
    gaze = np.array([0.1, -0.05, 1.0])
    gaze /= np.linalg.norm(gaze)
    r = 11.7 / 2
    depth = math.sqrt(radius**2 - r**2)
    points = _band(rng, centre, radius, gaze, 3000)
    # The limbus as measured: tilted 0.4° and shifted 0.01 mm.
    tilt = np.cross(gaze, [1.0, 0.0, 0.0])
    tilt /= np.linalg.norm(tilt)
    measured_normal = gaze + math.radians(0.4) * tilt
    measured_centre = centre + depth * gaze + 0.01 * np.cross(gaze, tilt)

    loose = sclera.globe_and_gaze(points, _limbus(measured_centre, measured_normal, r, 2.0,
                                                  0.05), depth + 0.3, None)
    tight = sclera.globe_and_gaze(points, _limbus(measured_centre, measured_normal, r, 0.005,
                                                  0.05), depth + 0.3, None)
    held = sclera.globe_and_gaze(points, _limbus(measured_centre, measured_normal, r, 2.0,
                                                 0.05), depth, radius)

    def angle(a: np.ndarray, b: np.ndarray) -> float:
        return math.degrees(math.acos(min(1.0, float(a @ b) / float(np.linalg.norm(a)))))

    # A limbus unsure of its tilt takes the sclera's: the exact globe, and the gaze to what
    # a sclera trusted to REMEASURED_SCLERA_BIAS_MM as a whole says across the globe (≈ 0.05°).
    assert np.linalg.norm(loose.centre - centre) < 0.01
    assert loose.radius == pytest.approx(radius, abs=0.005)
    assert angle(loose.gaze, gaze) < 0.1
    # A limbus sure of it keeps it (and the sclera only sets the depth).
    assert angle(tight.gaze, measured_normal) < 0.02
    # A held radius stays held.
    assert held.radius == pytest.approx(radius, abs=1e-9)
    # Stated uncertainties: the sclera is trusted to REMEASURED_SCLERA_BIAS_MM as a
    # whole.
    assert 0.0 < loose.gaze_sd_deg < 2.0
    assert np.all(np.sqrt(np.diag(loose.centre_cov)) > 0.0)


# A 13-mm globe turned away: the reconstructed sclera of one unit lies 0.07–0.1 mm outside
# the globe (faint fringes), of the other 0.02–0.03 mm inside (measured), which put the centre
# 0.3 mm off.
TURNED = SceneSpec(kind="eye", position_mm=(0.56, -2.29, -6.2),
                   eye=EyeSpec(gaze_deg=(-8.7, 3.6), globe_radius_mm=13.0))


@pytest.fixture(scope="module")
def turned(calibrated_rooms: Any, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The calibration directory and a capture of :data:`TURNED`."""
    _, caldir = calibrated_rooms("default")
    bundle = tmp_path_factory.mktemp("turned") / "eye"
    with SimSession.open(load_room(ROOMS["default"]), seed=3) as session:
        session.record(TURNED, bundle)
    return caldir, bundle


@dataclass(frozen=True)
class _Turned:
    """:data:`TURNED` reconstructed, with its truth (read after the pipeline ran)."""

    views: list[LimbusView]
    points: np.ndarray
    camera: np.ndarray
    centre: np.ndarray
    radius: float
    gaze: np.ndarray
    offset: np.ndarray
    """Each point's distance outside the true globe."""
    on_globe: np.ndarray
    """What the pose fit takes for the sclera: near the globe, behind the limbus."""


def _reconstructed(turned: tuple[Path, Path], method: str = "auto") -> _Turned:
    caldir, bundle = turned
    cloud, _ = reconstruct_bundle(caldir, bundle, method=method)
    truth = json.loads((bundle / "truth.json").read_text())["eye"]
    centre, radius = np.asarray(truth["centre_mm"]), float(truth["globe_radius_mm"])
    points = cloud.points.astype(np.float64)
    offset = np.linalg.norm(points - centre, axis=1) - radius
    gaze = np.asarray(truth["gaze"])
    on_globe = (np.abs(offset) < 0.3) & ((points - centre) @ gaze < 0.8 * radius)
    return _Turned(limbus_views(caldir, bundle), points, cloud.camera, centre, radius, gaze,
                   offset, on_globe)


@pytest.mark.slow
def test_the_remeasured_sclera_lies_on_the_globe_not_on_the_sphere_it_was_measured_about(
        turned: tuple[Path, Path]) -> None:
    # The multi-view order's cloud, whose sclera lies 0.02 mm or more off the globe in each
    # camera (the spatial order's, which the one-shot pose fits, in S1 only 0.006 mm).
    eye = _reconstructed(turned, "multi-view")
    views, points, centre, radius = eye.views, eye.points, eye.centre, eye.radius
    on_globe, offset, gaze = eye.on_globe, eye.offset, eye.gaze

    # Measured about a sphere 0.2 mm too deep: the fringes say where the sclera is.
    hypothesis = centre - 0.2 * gaze
    remeasured = 0
    for k, view in enumerate(views):
        again = sclera.remeasured([view], hypothesis, radius, points[on_globe], points)
        if len(again) < 300:
            continue  # faint fringes in this camera (the other unit's side): left out
        remeasured += 1
        before = float(np.median(offset[on_globe & (eye.camera == k)]))
        after = float(np.median(np.linalg.norm(again - centre, axis=1) - radius))
        assert abs(before) > 0.02 and abs(after) < 0.01, (view.camera.camera_id, before, after)
    assert remeasured >= 2


def test_the_remeasure_fills_the_gaps_of_a_patchy_cloud_sclera(turned: tuple[Path, Path]
                                                                ) -> None:
    """Where the visible sclera is a narrow band, the cloud's comes in patches: the pixels
    between them (within :data:`~eyeserver.eye.tunables.NEAR_MM`) are measured too, and lie
    on the globe like the rest."""
    eye = _reconstructed(turned)
    views, points, centre, radius = eye.views, eye.points, eye.centre, eye.radius
    sclera_points = points[eye.on_globe]
    # Half of it, as a checkerboard of 0.8-mm squares: each missing square's middle lies
    # 0.4 mm from the nearest kept point.
    cells = np.floor(sclera_points[:, :2] / 0.8).astype(int)
    patches = sclera_points[(cells.sum(axis=1) % 2) == 0]
    whole = sclera.remeasured(views, centre, radius, sclera_points, points)
    patchy = sclera.remeasured(views, centre, radius, patches, points)

    def off_globe(again: np.ndarray) -> float:
        return float(np.median(np.abs(np.linalg.norm(again - centre, axis=1) - radius)))

    # Measured: 0.94 of the pixels, 0.028 mm off the globe (median, all cameras) as the whole's
    # (with NEAR_MM 0.2 mm instead of 0.5 mm: 0.68, and 0.033 against 0.029 mm).
    assert len(patchy) > 0.9 * len(whole) > 0
    assert off_globe(patchy) == pytest.approx(off_globe(whole), abs=0.003)


@pytest.mark.slow
def test_the_limbus_found_again_with_the_fringe_divided_out_is_sharper(
        turned: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    # The band's fringe-free intensity leaves fringe at the limbus, where the field ends; the
    # illumination fitted on the sclera beside it and divided out does not (measured on this
    # eye: docs/notes/sclera.md and docs/notes/patient-eye.md, eighteenth session).
    caldir, bundle = turned
    cloud, _ = reconstruct_bundle(caldir, bundle)
    views = limbus_views(caldir, bundle)
    found: list[tuple[Limbus, Limbus]] = []
    real = sclera._sharpened

    def spy(*args: Any, **kwargs: Any) -> Limbus:
        limbus = real(*args, **kwargs)
        found.append((args[1], limbus))
        return limbus

    monkeypatch.setattr(sclera, "_sharpened", spy)
    # What dividing does, apart from the edges the cornea shadows (left out in the pipeline:
    # tests/test_limbus.py; on this eye that tilts the limbus found again 0.15° off the gaze
    # instead of 0.09°, where 200 bench poses with the radius held went 0.065° → 0.057° median).
    monkeypatch.setattr(limbus_module, "in_cornea_shadow",
                        lambda *args: np.zeros(len(args[3]), dtype=bool))
    fit_eye(cloud, EyeModel.population(), views)
    assert len(found) == tunables.PASSES
    truth = json.loads((bundle / "truth.json").read_text())["eye"]
    gaze, centre = np.asarray(truth["gaze"]), np.asarray(truth["limbus_centre_mm"])

    def tilt(limbus: Limbus) -> float:
        return math.degrees(math.acos(min(1.0, float(limbus.normal @ gaze))))

    band, divided = found[0][0], found[-1][1]
    assert tilt(divided) < 0.15 and tilt(divided) < 0.5 * tilt(band), (tilt(band), tilt(divided))
    assert np.linalg.norm(divided.centre - centre) < 0.01
    assert divided.residual_px < band.residual_px
    # The pose's gaze is the sharper limbus's, with the sclera's word on it.
    monkeypatch.undo()
    pose = fit_eye(cloud, EyeModel.population(), views)
    assert math.degrees(math.acos(min(1.0, float(np.asarray(pose.gaze) @ gaze)))) < 0.15


def test_where_no_limbus_is_found_again_the_first_one_stands(turned: tuple[Path, Path]) -> None:
    caldir, bundle = turned
    views = limbus_views(caldir, bundle)
    truth = json.loads((bundle / "truth.json").read_text())["eye"]
    centre, gaze = np.asarray(truth["centre_mm"]), np.asarray(truth["gaze"])
    limbus = _limbus(np.asarray(truth["limbus_centre_mm"]), gaze, 5.85, 0.2, 0.02)
    # Dark images (a blink, the projector off): no sclera to fit, no edge to find.
    dark = [LimbusView(view.camera, np.zeros_like(view.image)) for view in views]
    assert sclera.sharpened(dark, limbus, centre, float(truth["globe_radius_mm"])) is limbus


@pytest.mark.slow
def test_a_remeasured_globe_of_no_eyes_size_is_not_trusted(
        calibrated_rooms: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # One unit's sclera with the radius free gave globes of 17.8 and 18.3 mm, 5–7 mm off, with
    # confidences up to 0.58 (bench pose --unit left): a radius beyond the model's bounds now
    # fails a verification (confidence below 0.5) whatever else looks good.
    _, caldir = calibrated_rooms("default")
    with SimSession.open(load_room(ROOMS["default"]), seed=3) as session:
        session.record(SceneSpec(kind="eye"), tmp_path / "eye")
    cloud, _ = reconstruct_bundle(caldir, tmp_path / "eye")
    views = limbus_views(caldir, tmp_path / "eye")
    model = EyeModel.population()
    # Everything else that sets the confidence held at 0.9, the radius alone differing.
    monkeypatch.setattr(fit_module, "_confidence", lambda *args: 0.9)
    good = fit_eye(cloud, model, views)
    real_refit = fit_module.refit

    def too_large(*args: Any) -> sclera.GlobeFit | None:
        fit = real_refit(*args)
        assert fit is not None
        return replace(fit, radius=radius_bounds(model)[1] + 0.3)

    monkeypatch.setattr(fit_module, "refit", too_large)
    bad = fit_eye(cloud, model, views)

    assert good.confidence == pytest.approx(0.9)
    assert bad.globe_radius_mm > radius_bounds(model)[1]
    assert bad.confidence == pytest.approx(0.9 * tunables.IMPLAUSIBLE_RADIUS)
    assert bad.confidence < 0.5


def test_faint_fringes_are_left_out_of_the_remeasure(turned: tuple[Path, Path],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Light at grazing incidence and the edges of the lids' and the cornea's shadows bias a
    window's phase (:data:`~eyeserver.eye.tunables.MIN_AMPLITUDE`); their fringes are the
    faint ones."""
    eye = _reconstructed(turned)
    views, points, centre, radius = eye.views, eye.points, eye.centre, eye.radius

    def spread() -> tuple[int, float]:
        again = sclera.remeasured(views, centre, radius, points[eye.on_globe], points)
        off = np.linalg.norm(again - centre, axis=1) - radius
        return len(again), float(np.percentile(np.abs(off - np.median(off)), 95))

    kept, floored = spread()
    monkeypatch.setattr(sclera, "MIN_AMPLITUDE", 0.0)
    every, unfloored = spread()
    # Measured: 0.88 of the pixels kept, their spread about the globe (p95 of the distance
    # from the median) 0.102 against 0.121 mm with every pixel (p99 0.21 against 0.25 mm).
    assert 0.6 * every < kept < every
    assert floored < 0.9 * unfloored
