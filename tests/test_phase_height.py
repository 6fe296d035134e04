"""The Du & Wang phase-to-height model, checked against the simulated rig's exact optics.

The forward model: each sampled pixel's ray (the simulated camera's own, lens distortion included)
meets the calibration plate at Z = −10…+25 mm; the simulated projector says which grating phase
lands there; the phase at the reference plane Z = +10 mm for the same pixel is subtracted. That is
the calibration stack a perfect demodulation and unwrapping would deliver, so a fit to it
measures the model itself, and a fit to it with noise or a wrong fringe order measures what
those do to it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from eyeserver.core.types import F64
from eyeserver.hardware.sim.config import room_from_dict
from eyeserver.hardware.sim.optics import CameraModel, ProjectorModel
from eyeserver.hardware.sim.room import SimRoom
from eyeserver.pipeline import phase_height
from eyeserver.pipeline.phase_height import FitResult, PhaseHeightModel, fit_phase_height

PLANES_MM = np.arange(-10.0, 25.5, 1.0)
REFERENCE_MM = 10.0
PIXEL_STEP = 16

# A rig unlike the default one: projector nearer the cameras' azimuths and farther away, a
# coarser grating, cameras at other distances, elevations and a roll, and a strongly distorted
# lens (the model must see undistorted coordinates).
OTHER_RIG: dict[str, Any] = {"units": [{
    "id": "left",
    "projector": {"id": "P1", "distance_mm": 230.0, "azimuth_deg": 38.0, "elevation_deg": 3.0,
                  "period_mm": 2.6},
    "cameras": [{"id": "S1", "distance_mm": 280.0, "azimuth_deg": 15.0, "elevation_deg": 14.0,
                 "roll_deg": 5.0, "distortion": (-0.2, 0.05, 0.001, -0.001, 0.0)},
                {"id": "S2", "distance_mm": 220.0, "azimuth_deg": 20.0,
                 "elevation_deg": -10.0}],
}]}


@dataclass(frozen=True)
class Stack:
    """A noise-free calibration stack, one row per plane: ``(planes, pixels)`` arrays."""

    x: F64  # undistorted normalised camera coordinates
    y: F64
    x_distorted: F64  # (u − cx)/fx, (v − cy)/fy: what raw pixels would give
    y_distorted: F64
    dphi: F64  # exact reference-subtracted phase, rad
    reference_phase: F64  # absolute phase on the reference plane, rad
    z: F64  # plate height, mm
    sensitivity: F64  # ∂Δφ/∂Z at each sample, rad/mm


def _phase_on_plane(camera: CameraModel, projector: ProjectorModel, rays: F64,
                    z_mm: float) -> tuple[F64, npt.NDArray[np.bool_]]:
    t = (z_mm - camera.centre[2]) / rays[:, 2]
    phase, _, inside = projector.phase_at(camera.centre + t[:, None] * rays)
    return phase, inside


def make_stack(room: SimRoom, camera_id: str, projector_id: str) -> Stack:
    camera = room.renderer.cameras[camera_id]
    projector = room.renderer.projectors[projector_id]
    height, width = camera.shape
    v, u = np.mgrid[PIXEL_STEP // 2:height:PIXEL_STEP, PIXEL_STEP // 2:width:PIXEL_STEP]
    u, v = u.astype(np.float64).ravel(), v.astype(np.float64).ravel()
    rays = camera.rays_for_pixels(u, v)
    x, y = camera.normalised_for_pixels(u, v)
    reference, seen = _phase_on_plane(camera, projector, rays, REFERENCE_MM)
    phases, sensitivities = [], []
    for z_mm in PLANES_MM:
        phase, inside = _phase_on_plane(camera, projector, rays, z_mm)
        above, _ = _phase_on_plane(camera, projector, rays, z_mm + 1e-3)
        below, _ = _phase_on_plane(camera, projector, rays, z_mm - 1e-3)
        seen &= inside
        phases.append(phase - reference)
        sensitivities.append((above - below) / 2e-3)
    keep = np.flatnonzero(seen)  # pixels lit on every plane, so every row has the same length
    planes = len(PLANES_MM)
    return Stack(
        x=np.tile(x[keep], (planes, 1)), y=np.tile(y[keep], (planes, 1)),
        x_distorted=np.tile((u[keep] - camera.K[0, 2]) / camera.K[0, 0], (planes, 1)),
        y_distorted=np.tile((v[keep] - camera.K[1, 2]) / camera.K[1, 1], (planes, 1)),
        dphi=np.stack(phases)[:, keep],
        reference_phase=np.tile(reference[keep], (planes, 1)),
        z=np.repeat(PLANES_MM[:, None], keep.size, axis=1),
        sensitivity=np.stack(sensitivities)[:, keep],
    )


GEOMETRIES = [("default", "S1", "P1"), ("default", "S2", "P1"), ("other", "S1", "P1")]


@pytest.fixture(scope="module")
def rooms() -> dict[str, SimRoom]:
    return {"default": SimRoom(), "other": SimRoom(room_from_dict(OTHER_RIG))}


@pytest.fixture(scope="module")
def stacks(rooms: dict[str, SimRoom]) -> dict[tuple[str, str, str], Stack]:
    return {g: make_stack(rooms[g[0]], g[1], g[2]) for g in GEOMETRIES}


@pytest.fixture(scope="module")
def fits(stacks: dict[tuple[str, str, str], Stack]) -> dict[tuple[str, str, str], FitResult]:
    return {g: fit_phase_height(s.x, s.y, s.dphi, s.z, rng=0) for g, s in stacks.items()}


def geometry_ids(geometry: tuple[str, str, str]) -> str:
    return "-".join(geometry)


# --- the model against exact data ------------------------------------------------------------


@pytest.mark.parametrize("geometry", GEOMETRIES, ids=geometry_ids)
def test_noise_free_stack_is_fitted_to_micrometres(
        geometry: tuple[str, str, str], stacks: dict[tuple[str, str, str], Stack],
        fits: dict[tuple[str, str, str], FitResult]) -> None:
    # Exact for absolute phase; reference subtraction makes it a ≈ 1 µm approximation
    # (measured 0.2–1.9 µm RMS over these rigs).
    stack, fit = stacks[geometry], fits[geometry]
    assert stack.z.shape[1] > 1000  # the projector lights most of the view
    assert fit.residual_mm.shape == stack.z.shape
    assert fit.rmse_mm < 0.005
    assert np.max(np.abs(fit.residual_mm)) < 0.02
    assert fit.median_abs_mm < 0.002
    assert fit.iqr_mm < 0.003
    assert math.isclose(fit.rmse_mm, float(np.sqrt(np.mean(fit.residual_mm**2))))
    assert fit.model.z_range == (-10.0, 25.0)
    # Residuals are Z_model − Z, recomputable from the model.
    np.testing.assert_allclose(fit.model.height(stack.x, stack.y, stack.dphi) - stack.z,
                               fit.residual_mm, atol=1e-12)
    # From the linear start Levenberg–Marquardt needs only a few steps.
    assert fit.evaluations <= 15


def test_model_is_exact_for_absolute_phase_on_undistorted_coordinates(
        stacks: dict[tuple[str, str, str], Stack]) -> None:
    # Why the model has its form: for a pinhole camera and projector the *absolute* phase gives Z as
    # exactly this rational function of undistorted (x, y); coordinates that still carry the lens
    # distortion cost tens of micrometres (docs/notes/design-measurements.md: 0.015–0.046 mm;
    # measured 0.018 and 0.050 mm here). Reference subtraction turns the identity into a micrometre
    # approximation that hardly depends on the distortion (measured 0.2–1.9 µm either way), but
    # undistorted coordinates stay the contract: step 6's rays and the inversion need them too.
    for geometry in [("default", "S1", "P1"), ("other", "S1", "P1")]:
        stack = stacks[geometry]
        absolute = stack.dphi + stack.reference_phase
        exact = fit_phase_height(stack.x, stack.y, absolute, stack.z, rng=0)
        assert exact.rmse_mm < 1e-9
        distorted = fit_phase_height(stack.x_distorted, stack.y_distorted, absolute, stack.z,
                                     rng=0)
        assert distorted.rmse_mm > 0.01
        relative = fit_phase_height(stack.x_distorted, stack.y_distorted, stack.dphi, stack.z,
                                    rng=0)
        assert relative.rmse_mm < 0.005


@pytest.mark.parametrize("geometry", GEOMETRIES, ids=geometry_ids)
def test_phase_noise_gives_the_residual_noise_over_sensitivity_predicts(
        geometry: tuple[str, str, str], stacks: dict[tuple[str, str, str], Stack]) -> None:
    stack = stacks[geometry]
    sigma_rad = 0.05
    noise = np.random.default_rng(7).normal(0.0, sigma_rad, stack.dphi.shape)
    fit = fit_phase_height(stack.x, stack.y, stack.dphi + noise, stack.z, rng=1)
    # A phase error n at a pixel of sensitivity s (rad/mm) reads as a height error n/s.
    predicted = float(np.median(np.abs(noise / stack.sensitivity)))
    assert fit.median_abs_mm == pytest.approx(predicted, rel=0.05)
    assert fit.iqr_mm == pytest.approx(float(np.subtract(
        *np.percentile(np.abs(noise / stack.sensitivity), [75, 25]))), rel=0.1)
    # The eleven coefficients average the noise of ~50 k samples away: on exact phase the noisy
    # fit still reads the plates to a few micrometres.
    clean = fit.model.height(stack.x, stack.y, stack.dphi) - stack.z
    assert float(np.sqrt(np.mean(clean**2))) < 0.005


def test_default_rig_noise_meets_the_design_goal(
        stacks: dict[tuple[str, str, str], Stack]) -> None:
    # docs/design.md §6: phase-to-height residual median ≤ 0.03 mm. 0.05 rad at ≈ 1.2 rad/mm
    # is ≈ 0.03.
    stack = stacks[("default", "S1", "P1")]
    assert 1.0 < float(np.median(np.abs(stack.sensitivity))) < 1.4
    noise = np.random.default_rng(3).normal(0.0, 0.05, stack.dphi.shape)
    fit = fit_phase_height(stack.x, stack.y, stack.dphi + noise, stack.z, rng=0)
    assert fit.median_abs_mm < 0.03


# --- a wrong fringe order in the stack -----------------------------------------------------


def _plane_medians(fit: FitResult) -> F64:
    return np.asarray(np.median(np.abs(fit.residual_mm), axis=1), dtype=np.float64)


@pytest.mark.parametrize("bad_plane_mm", [-10.0, 0.0, 20.0, 25.0])
def test_one_plane_off_by_two_pi_ruins_the_fit(
        bad_plane_mm: float, stacks: dict[tuple[str, str, str], Stack],
        fits: dict[tuple[str, str, str], FitResult]) -> None:
    # One plate's phase a fringe off reads ≈ 5 mm (2π at 1.2 rad/mm) too far; the eleven
    # coefficients bend towards it and spoil every plane. Measured: RMSE 0.65–0.88 mm, the bad
    # plane's own median |residual| 3.4–5.0 mm: the stack's unwrapping must be checked, and
    # the per-plane residual shows which plane to look at.
    geometry = ("default", "S1", "P1")
    stack = stacks[geometry]
    dphi = stack.dphi.copy()
    row = int(np.argmin(np.abs(PLANES_MM - bad_plane_mm)))
    dphi[row] += 2 * math.pi
    fit = fit_phase_height(stack.x, stack.y, dphi, stack.z, rng=0)
    assert fit.rmse_mm > 0.5
    assert fit.rmse_mm > 100 * fits[geometry].rmse_mm
    medians = _plane_medians(fit)
    assert int(np.argmax(medians)) == row
    assert medians[row] > 3.0


@pytest.mark.parametrize("slip_plane_mm", [20.0, -5.0])
def test_a_fringe_slip_walking_out_from_the_reference_ruins_the_fit(
        slip_plane_mm: float, stacks: dict[tuple[str, str, str], Stack]) -> None:
    # Unwrapping along Z walks out from the reference plane (docs/design.md §5), so one slip offsets
    # every plane beyond it by 2π. Measured: RMSE 1.2–1.7 mm.
    stack = stacks[("default", "S1", "P1")]
    dphi = stack.dphi.copy()
    side = np.sign(slip_plane_mm - REFERENCE_MM)
    beyond = (PLANES_MM - slip_plane_mm) * side >= 0
    dphi[beyond] += 2 * math.pi * side
    fit = fit_phase_height(stack.x, stack.y, dphi, stack.z, rng=0)
    assert fit.rmse_mm > 1.0


# --- inversion, serialisation, numerics -------------------------------------------------------


@pytest.mark.parametrize("geometry", GEOMETRIES, ids=geometry_ids)
def test_phase_and_height_invert_each_other(
        geometry: tuple[str, str, str], stacks: dict[tuple[str, str, str], Stack],
        fits: dict[tuple[str, str, str], FitResult]) -> None:
    stack, model = stacks[geometry], fits[geometry].model
    heights = model.height(stack.x, stack.y, stack.dphi)
    np.testing.assert_allclose(model.phase(stack.x, stack.y, heights), stack.dphi,
                               rtol=0, atol=1e-9)
    # And the phase model predicts for a known plate is the forward model's phase to the fit's
    # accuracy (≈ µm × sensitivity).
    predicted = model.phase(stack.x, stack.y, stack.z)
    np.testing.assert_allclose(model.height(stack.x, stack.y, predicted), stack.z,
                               rtol=0, atol=1e-6)
    assert float(np.max(np.abs(predicted - stack.dphi))) < 0.05


def test_model_evaluates_any_broadcastable_shape(
        fits: dict[tuple[str, str, str], FitResult]) -> None:
    model = fits[("default", "S1", "P1")].model
    y, x = np.mgrid[-0.1:0.1:5j, -0.12:0.12:7j]
    grid = model.height(x, y, 1.5)
    assert grid.shape == (5, 7)
    assert grid.dtype == np.float64
    assert model.height(float(x[2, 3]), float(y[2, 3]), 1.5).shape == ()
    assert model.height(float(x[2, 3]), float(y[2, 3]), 1.5) == pytest.approx(grid[2, 3])
    # Candidate heights along a new axis, as fringe-order selection evaluates them.
    candidates = np.array([-5.0, 0.0, 5.0])[:, None, None]
    assert model.phase(x, y, candidates).shape == (3, 5, 7)
    with pytest.raises(ValueError, match="dphi"):
        model.height(x, y, np.zeros(4))
    with pytest.raises(ValueError, match="z"):
        model.phase(x, y, np.zeros(4))


def test_dict_round_trip_through_json(fits: dict[tuple[str, str, str], FitResult]) -> None:
    model = fits[("other", "S1", "P1")].model
    data = json.loads(json.dumps(model.to_dict()))
    again = PhaseHeightModel.from_dict(data)
    assert again == model
    assert again.to_dict() == data
    x, y, dphi = np.array([0.01, -0.05]), np.array([0.02, 0.03]), np.array([-3.0, 7.0])
    np.testing.assert_array_equal(again.height(x, y, dphi), model.height(x, y, dphi))


def _mutated(model: PhaseHeightModel, key: str, value: Any) -> dict[str, Any]:
    data = model.to_dict()
    if value is _DELETE:
        del data[key]
    else:
        data[key] = value
    return data


_DELETE = object()


@pytest.mark.parametrize(("key", "value", "named"), [
    ("model", "zhang-2004", "model"),
    ("coefficients", [1.0] * 10, "coefficients"),
    ("coefficients", "1, 2", "coefficients"),
    ("coefficients", [1.0] * 10 + ["a"], r"coefficients\[10\]"),
    ("coefficients", [1.0] * 10 + [float("nan")], r"coefficients\[10\]"),
    ("x_scale", 0.0, "x_scale"),
    ("dphi_scale", -1.0, "dphi_scale"),
    ("z_centre", None, "z_centre"),
    ("z_centre", True, "z_centre"),
    ("y_centre", float("inf"), "y_centre"),
    ("z_range", [5.0, 5.0], "z_range"),
    ("z_range", [1.0], "z_range"),
    ("dphi_centre", _DELETE, "dphi_centre"),
    ("gain", 2.0, "gain"),
])
def test_from_dict_names_the_bad_key(key: str, value: Any, named: str,
                                     fits: dict[tuple[str, str, str], FitResult]) -> None:
    data = _mutated(fits[("default", "S1", "P1")].model, key, value)
    with pytest.raises(ValueError, match=named):
        PhaseHeightModel.from_dict(data)


def test_from_dict_refuses_a_non_mapping() -> None:
    with pytest.raises(ValueError, match="data"):
        PhaseHeightModel.from_dict([1, 2, 3])  # type: ignore[arg-type]


def test_normalisation_is_what_makes_the_problem_well_conditioned(
        stacks: dict[tuple[str, str, str], Stack],
        fits: dict[tuple[str, str, str], FitResult]) -> None:
    # Measured: ≈ 50 normalised; ≈ 5·10⁴ on raw normalised coordinates, rad and mm; ≈ 3·10⁵ on
    # raw pixels (docs/notes/design-measurements.md: 3·10⁶ against 5·10³ with another
    # parametrisation).
    stack, fit = stacks[("default", "S1", "P1")], fits[("default", "S1", "P1")]
    x, y, dphi, z = (a.ravel() for a in (stack.x, stack.y, stack.dphi, stack.z))
    raw = phase_height._linear_start(x, y, dphi, z)
    raw_condition = float(np.linalg.cond(phase_height._jacobian(raw, x, y, dphi)))
    assert fit.condition_number < 1e3
    assert raw_condition > 100 * fit.condition_number


def test_subsample_fits_on_max_points_and_reports_every_point(
        stacks: dict[tuple[str, str, str], Stack]) -> None:
    stack = stacks[("default", "S2", "P1")]
    small = fit_phase_height(stack.x, stack.y, stack.dphi, stack.z, max_points=2000, rng=5)
    assert small.residual_mm.shape == stack.z.shape
    assert small.rmse_mm < 0.005
    same = fit_phase_height(stack.x, stack.y, stack.dphi, stack.z, max_points=2000,
                            rng=np.random.default_rng(5))
    assert same.model == small.model
    other = fit_phase_height(stack.x, stack.y, stack.dphi, stack.z, max_points=2000, rng=6)
    assert other.model != small.model


# --- input validation ------------------------------------------------------------------------


def _good_inputs() -> dict[str, Any]:
    rng = np.random.default_rng(0)
    z = np.repeat([-5.0, 0.0, 5.0, 10.0], 10)
    return {"x": rng.uniform(-0.1, 0.1, z.size), "y": rng.uniform(-0.1, 0.1, z.size),
            "dphi": z * 1.2 + rng.normal(0, 0.01, z.size), "z": z}


@pytest.mark.parametrize(("name", "value"), [
    ("x", np.zeros(39)),
    ("y", np.zeros((40, 1))),
    ("dphi", np.full(40, np.nan)),
    ("z", np.concatenate([np.zeros(39), [np.inf]])),
    ("x", np.full(40, 0.05)),
    ("dphi", np.zeros(40)),
    ("z", np.repeat([0.0, 1.0], 20)),
    ("x", ["a"] * 40),
])
def test_fit_names_the_bad_parameter(name: str, value: Any) -> None:
    inputs = _good_inputs()
    inputs[name] = value
    with pytest.raises(ValueError, match=f"^{name}:"):
        fit_phase_height(**inputs)


def test_fit_needs_enough_points_and_a_sane_max_points() -> None:
    z = np.array([0.0, 1.0, 2.0] * 3)
    with pytest.raises(ValueError, match=r"^z:"):
        fit_phase_height(z, z, z, z)
    with pytest.raises(ValueError, match=r"^max_points:"):
        fit_phase_height(**_good_inputs(), max_points=10)
    with pytest.raises(ValueError, match=r"^max_points:"):
        fit_phase_height(**_good_inputs(), max_points=1e5)  # type: ignore[arg-type]


def test_model_refuses_bad_fields() -> None:
    good: dict[str, Any] = dict(coefficients=(0.0,) * 11, x_centre=0.0, x_scale=1.0,
                                y_centre=0.0, y_scale=1.0, dphi_centre=0.0, dphi_scale=1.0,
                                z_centre=0.0, z_scale=1.0, z_range=(-1.0, 1.0))
    PhaseHeightModel(**good)
    for key, value in [("coefficients", (0.0,) * 12), ("z_scale", 0.0),
                       ("x_centre", float("nan")), ("z_range", (2.0, 1.0))]:
        with pytest.raises(ValueError, match=f"^{key}:"):
            PhaseHeightModel(**{**good, key: value})
