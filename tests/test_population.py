"""The simulated patient eye's population (eyeserver.hardware.sim.population)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from eyeserver.eye.tunables import MEASURED_GLOBE_SD_MM
from eyeserver.hardware.sim.population import (
    BIOMETRY_SD,
    MRI_ERROR_SCALE,
    SHARP,
    SHARP_RADII_MM,
    VARIANTS,
    biometry,
    describe,
    draw,
    draw_eye,
    keratometric_radius,
    lid_cover,
)
from eyeserver.hardware.sim.scenes import EyeSpec


def _eyes(count: int, seed: int = 34) -> list[EyeSpec]:
    rng = np.random.default_rng(seed)
    return [draw_eye(rng) for _ in range(count)]


def _with(eye: EyeSpec, **changes: Any) -> EyeSpec:
    """``eye`` with ``changes``, validated again."""
    return EyeSpec.model_validate({**eye.model_dump(), **changes})


@pytest.fixture(scope="module")
def eyes() -> list[EyeSpec]:
    return _eyes(2000)


def test_every_draw_validates_and_is_at_rest(eyes: list[EyeSpec]) -> None:
    for eye in eyes[:1000]:
        again = EyeSpec.model_validate(eye.model_dump())  # the validator passes on its own
        assert again == eye
        half = eye.limbus_diameter_mm / 2
        equator = (eye.globe_radius_mm if eye.globe_semi_axes_mm is None
                   else min(eye.globe_semi_axes_mm[:2]))
        assert half < equator
        assert half < eye.cornea_radius_mm / math.sqrt(1 + eye.cornea_asphericity)
        assert eye.gaze_deg == (0.0, 0.0)
        assert eye.motion is None
        assert not eye.sharp


def test_same_seed_same_eye() -> None:
    assert _eyes(5, seed=7) == _eyes(5, seed=7)
    assert _eyes(5, seed=7) != _eyes(5, seed=8)


def test_properties_span_their_ranges(eyes: list[EyeSpec]) -> None:
    def values(name: str) -> np.ndarray:
        return np.array([getattr(eye, name) for eye in eyes], dtype=float)

    spans = {  # property: (at most this low, at least this high)
        "cornea_radius_mm": (7.4, 8.3),
        "cornea_asphericity": (-0.6, 0.1),
        "limbus_diameter_mm": (11.0, 12.4),
        "limbus_vertical_ratio": (0.87, 0.95),
        "limbus_width_mm": (0.3, 1.9),
        "limbus_scatter": (0.05, 0.55),
        "sclera_albedo": (0.31, 0.49),
        "iris_albedo": (0.05, 0.28),
        "tear_reflectance": (0.0205, 0.0245),
        "lid_gap_mm": (0.4, 1.4),
        "globe_radius_mm": (11.2, 12.8),
    }
    for name, (low, high) in spans.items():
        v = values(name)
        assert v.min() <= low and v.max() >= high, name
    assert set(values("tear_glints")) == set(range(7))
    assert values("lashes").min() == 0 and values("lashes").max() == 30
    half_heights = np.array([eye.aperture_mm[1] for eye in eyes])
    assert half_heights.min() < 4.7 and half_heights.max() > 7.8
    contrast = np.array([describe(eye)["limbus_contrast"] for eye in eyes[:500]])
    assert contrast.min() < 0.1 and contrast.max() > 0.8  # weak to strong
    assert len({eye.features_seed for eye in eyes}) > 1990


def test_the_fit_defaults_are_not_built_in(eyes: list[EyeSpec]) -> None:
    def near(name: str, value: float) -> float:
        return float(np.mean([abs(getattr(eye, name) - value) <= 0.01 for eye in eyes]))

    assert near("cornea_radius_mm", 7.8) < 0.05
    assert near("limbus_diameter_mm", 11.7) < 0.05
    assert near("lid_gap_mm", 1.2) < 0.05
    assert near("cornea_asphericity", 0.0) < 0.05
    assert not any(eye.cornea_radius_mm == 7.8 or eye.limbus_diameter_mm == 11.7
                   or eye.lid_gap_mm == 1.2 for eye in eyes)


def test_the_limbus_is_decentred_on_the_globe_within_its_range(eyes: list[EyeSpec]) -> None:
    offsets = np.array([eye.limbus_offset_mm for eye in eyes])
    length = np.hypot(offsets[:, 0], offsets[:, 1])
    assert length.max() <= 0.6
    assert 0.2 < float(np.median(length)) < 0.27  # sd 0.2 each way: a Rayleigh median 0.235
    assert np.abs(offsets.mean(axis=0)).max() < 0.02  # no side preferred
    assert not _with(SHARP, limbus_offset_mm=(0.1, 0.0)).sharp
    # Drawn from a stream of its own: the other properties are what they were without it.
    eye = _eyes(1, seed=5)[0]
    rng = np.random.default_rng(5)
    again = draw_eye(rng)
    assert again == eye and draw_eye(rng) == _eyes(2, seed=5)[1]


def test_the_globe_is_mostly_an_ellipsoid(eyes: list[EyeSpec]) -> None:
    ellipsoids = [eye for eye in eyes if eye.globe_semi_axes_mm is not None]
    assert 0.80 < len(ellipsoids) / len(eyes) < 0.90
    spreads = []
    for eye in ellipsoids:
        axes = eye.globe_semi_axes_mm
        assert axes is not None
        assert eye.globe_radius_mm == pytest.approx(sum(axes) / 3)
        spreads.append(max(axes) - min(axes))
    assert max(spreads) <= 1.0
    assert np.percentile(spreads, 90) > 0.35


def test_properties_are_drawn_independently(eyes: list[EyeSpec]) -> None:
    table = np.array([[
        eye.cornea_radius_mm, eye.cornea_asphericity, eye.limbus_diameter_mm,
        eye.limbus_vertical_ratio, eye.limbus_width_mm, eye.limbus_scatter, eye.sclera_albedo,
        eye.iris_albedo, eye.tear_reflectance, eye.tear_glints, eye.aperture_mm[1],
        eye.aperture_offset_mm[1], eye.lid_gap_mm, eye.lashes, eye.globe_radius_mm,
        *eye.limbus_offset_mm,
    ] for eye in eyes])
    correlation = np.corrcoef(table, rowvar=False)
    off_diagonal = correlation[~np.eye(len(correlation), dtype=bool)]
    assert np.abs(off_diagonal).max() < 0.1  # 1/√2000 ≈ 0.022 is one sd of r
    described = [describe(eye) for eye in eyes]
    width = [d["limbus_width_mm"] for d in described]
    contrast = [d["limbus_contrast"] for d in described]
    assert abs(np.corrcoef(width, contrast)[0, 1]) < 0.1


def test_lids_cover_part_of_the_limbus_never_all(eyes: list[EyeSpec]) -> None:
    cover = np.array([lid_cover(eye) for eye in eyes[:1000]])
    assert 0.3 < float(np.mean(cover == 0.0)) < 0.7  # many limbi free, many partly covered
    assert np.percentile(cover, 90) > 0.25
    assert float(np.mean(cover > 0.35)) < 0.2  # more than a third only sometimes
    assert cover.max() < 0.6  # most of the limbus stays visible


def test_sharp_eye_descriptors() -> None:
    # The default opening (half-axes 11 × 7.5 mm) holds the 11.7-mm limbus: the limbus's
    # circle of radius 5.85 reaches at most (5.85 / 7.5)² ≈ 0.61 of the opening's ellipse.
    t = np.linspace(0.0, 2 * math.pi, 721)
    assert np.max((5.85 * np.cos(t) / 11.0) ** 2 + (5.85 * np.sin(t) / 7.5) ** 2) < 1.0
    assert describe(SHARP) == {"limbus_width_mm": 0.0,
                               "limbus_contrast": pytest.approx(0.36 / 0.48),
                               "lid_cover": 0.0, "anatomy_mismatch_mm": 0.0}


@pytest.mark.parametrize(("offset_y", "half_height", "expected"), [
    # A very wide opening whose upper edge crosses a circular limbus at 30° above the
    # horizontal (y = 5.85·sin 30° = 2.925 mm) and whose lower edge lies far below: the
    # lid hides the arc from 30° to 150°, a third.
    (2.925 - 11.4625, 11.4625, 1 / 3),
    # Upper and lower edges at ±2.925 mm: both arcs, two thirds.
    (0.0, 2.925, 2 / 3),
])
def test_a_lowered_opening_hides_a_known_share(offset_y: float, half_height: float,
                                               expected: float) -> None:
    eye = _with(SHARP, aperture_mm=(1000.0, half_height), aperture_offset_mm=(0.0, offset_y))
    assert lid_cover(eye) == pytest.approx(expected, abs=2e-3)
    assert describe(eye)["lid_cover"] == pytest.approx(expected, abs=2e-3)
    # The opening and the limbus lowered together (a decentred limbus): the same share.
    both = _with(eye, aperture_offset_mm=(0.0, offset_y - 0.3), limbus_offset_mm=(0.0, -0.3))
    assert lid_cover(both) == pytest.approx(expected, abs=2e-3)


def test_an_oval_limbus_is_covered_by_arc_length() -> None:
    # Upper edge at half the vertical semi-axis: on the ellipse x = a cos t, y = b sin t the
    # hidden part is t in (30°, 150°); its share of the arc length, integrated independently.
    a, ratio = 5.85, 0.85
    b = ratio * a
    eye = _with(SHARP, limbus_vertical_ratio=ratio, aperture_mm=(1000.0, 20.0),
                aperture_offset_mm=(0.0, b / 2 - 20.0))
    t = np.linspace(0.0, 2 * math.pi, 200_000, endpoint=False)  # a periodic Riemann sum
    speed = np.hypot(a * np.sin(t), b * np.cos(t))
    inside = (t > math.radians(30)) & (t < math.radians(150))
    expected = float(np.sum(speed * inside) / np.sum(speed))
    assert lid_cover(eye) == pytest.approx(expected, abs=2e-3)
    assert expected > 1 / 3  # the flat top is longer per degree than the sides


def test_anatomy_mismatch() -> None:
    assert describe(_with(SHARP, cornea_radius_mm=8.1))["anatomy_mismatch_mm"] == \
        pytest.approx(0.3)
    assert describe(_with(SHARP, limbus_diameter_mm=11.1))["anatomy_mismatch_mm"] == \
        pytest.approx(0.3)
    assert describe(_with(SHARP, lid_gap_mm=0.4))["anatomy_mismatch_mm"] == pytest.approx(0.8)
    decentred = _with(SHARP, limbus_offset_mm=(0.3, -0.4))
    assert describe(decentred)["anatomy_mismatch_mm"] == pytest.approx(0.5)
    ellipsoid = _with(SHARP, globe_semi_axes_mm=(12.1, 11.9, 12.35))
    assert describe(ellipsoid)["anatomy_mismatch_mm"] == pytest.approx(0.45)
    # The conic's sagitta from (1+Q)z² − 2Rz + r² = 0 against the sphere's R − √(R² − r²).
    radius, q, r = 7.8, -0.26, 11.7 / 2
    conic = (radius - math.sqrt(radius**2 - (1 + q) * r**2)) / (1 + q)
    sphere = radius - math.sqrt(radius**2 - r**2)
    aspheric = _with(SHARP, cornea_asphericity=q)
    assert describe(aspheric)["anatomy_mismatch_mm"] == pytest.approx(sphere - conic)
    assert 0.1 < sphere - conic < 0.2


def test_contrast_follows_the_reflectances() -> None:
    light_iris = _with(SHARP, sclera_albedo=0.32, iris_albedo=0.28)
    dark_iris = _with(SHARP, sclera_albedo=0.48, iris_albedo=0.04)
    assert describe(light_iris)["limbus_contrast"] == pytest.approx(0.04 / 0.60)
    assert describe(dark_iris)["limbus_contrast"] == pytest.approx(0.44 / 0.52)


def test_biometry_is_never_the_truth(eyes: list[EyeSpec]) -> None:
    rng = np.random.default_rng(3)
    errors: dict[str, list[float]] = {"globe_radius_mm": [], "globe_semi_axes_mm": [],
                                      "cornea_radius_mm": [], "limbus_diameter_mm": []}
    scales: list[float] = []  # each patient's MRI error in units of the typical one
    for eye in eyes[:1000]:
        measured = biometry(eye, rng)
        assert set(measured) == {*errors, "mri_sd_mm"}
        mri_sd = measured["mri_sd_mm"]
        assert isinstance(mri_sd, float)
        scale = mri_sd / BIOMETRY_SD["globe_semi_axes_mm"]
        scales.append(scale)
        radius, axes = measured["globe_radius_mm"], measured["globe_semi_axes_mm"]
        cornea, limbus = measured["cornea_radius_mm"], measured["limbus_diameter_mm"]
        assert isinstance(radius, float) and isinstance(cornea, float)
        assert isinstance(limbus, float)
        assert radius != eye.globe_radius_mm
        assert cornea != eye.cornea_radius_mm
        assert limbus != eye.limbus_diameter_mm
        if eye.globe_semi_axes_mm is None:
            assert axes is None
            errors["globe_radius_mm"].append((radius - eye.globe_radius_mm) / scale)
        else:
            assert isinstance(axes, tuple) and len(axes) == 3
            assert radius == pytest.approx(sum(axes) / 3)  # the physicist's mean radius
            for got, true in zip(axes, eye.globe_semi_axes_mm, strict=True):
                assert got != true
                errors["globe_semi_axes_mm"].append((got - true) / scale)
        errors["cornea_radius_mm"].append(cornea - keratometric_radius(eye))
        errors["limbus_diameter_mm"].append(limbus - eye.limbus_diameter_mm)
    for name, values in errors.items():
        sd = BIOMETRY_SD[name]
        v = np.array(values)
        assert np.abs(v).max() <= 3 * sd + 1e-12, name  # within a few sd, never a blunder
        assert abs(float(v.mean())) < 0.2 * sd, name  # unbiased about what is measured
        assert 0.8 * sd < float(v.std()) < 1.1 * sd, name
    # The MRI's error varies between patients over its whole range, the fit's default inside.
    low, high = MRI_ERROR_SCALE
    assert low <= min(scales) < low + 0.05 and high - 0.05 < max(scales) <= high
    assert low < MEASURED_GLOBE_SD_MM / BIOMETRY_SD["globe_semi_axes_mm"] < float(np.mean(scales))


def test_keratometry_reads_the_cornea_flatter_than_its_apex() -> None:
    prolate = _with(SHARP, cornea_asphericity=-0.25)
    assert keratometric_radius(SHARP) == pytest.approx(7.8)
    assert keratometric_radius(prolate) == pytest.approx(math.sqrt(7.8**2 + 0.25 * 1.5**2))
    assert 0.03 < keratometric_radius(prolate) - 7.8 < 0.05


def test_variants() -> None:
    assert set(VARIANTS) == {"patient", "sharp"}
    rng = np.random.default_rng(11)
    sharp = [draw(rng, "sharp") for _ in range(60)]
    assert {eye.globe_radius_mm for eye in sharp} == set(SHARP_RADII_MM)
    for eye in sharp:
        assert eye.sharp
        assert _with(eye, globe_radius_mm=SHARP.globe_radius_mm) == SHARP
    patient = draw(np.random.default_rng(5), "patient")
    assert patient == draw_eye(np.random.default_rng(5))
    assert draw(np.random.default_rng(5)) == patient  # the default variant
    with pytest.raises(ValueError, match="'painted'"):
        draw(rng, "painted")
