"""Fourier-transform demodulation through a forward model (STYLE rule 4).

Synthetic fringes ``A + B·cos(2π f·x + φ(x))`` with a known smooth ``φ`` (a Gaussian bump of
several radians, as a curved surface gives, on a vignetted background) are demodulated and the
recovered phase is compared with the truth modulo 2π; the simulated room checks the whole
step on rendered plates against the projector's own phase.
"""

from __future__ import annotations

import doctest
import math

import numpy as np
import numpy.typing as npt
import pytest

from eyeserver.core.arrays import ANGLE_ERROR_RAD, angle
from eyeserver.core.types import F64
from eyeserver.pipeline import demodulate as demodulate_module
from eyeserver.pipeline.demodulate import (
    MIN_CARRIER_DOMINANCE,
    MIN_CARRIER_STRENGTH,
    Carrier,
    Demodulated,
    carrier_ratios,
    demodulate,
    measure_carrier,
    phase_difference,
    with_bend_bias,
)

HEIGHT, WIDTH = 320, 400
BACKGROUND_DN = 50.0
FRINGE_DN = 30.0  # B: the fringe amplitude, half the peak-to-peak swing

# Tolerances, radians. The interior is more than one fringe period from every border.
INTERIOR_RMS_RAD = 0.02
INTERIOR_MAX_RAD = 0.05
BORDER_MAX_RAD = 0.1

CARRIERS = {
    "vertical fringes": Carrier.from_polar(0.0, 0.04),
    "horizontal fringes": Carrier.from_polar(math.pi / 2, 0.04),
    "oblique 34°": Carrier.from_polar(0.6, 0.05),
    "oblique −52°": Carrier.from_polar(-0.9, 0.045),
    "nearly vertical, 3°": Carrier.from_polar(0.05, 0.045),
}


def _wrap(phase: F64) -> F64:
    return np.asarray(np.angle(np.exp(1j * phase)), dtype=np.float64)


def _grid(shape: tuple[int, int] = (HEIGHT, WIDTH)) -> tuple[F64, F64]:
    i, j = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return i, j


def _bump(amplitude_rad: float = 5.0, sigma_px: float = 45.0) -> F64:
    """A smooth surface's phase: a Gaussian bump in the middle of the image.

    The default shifts the local fringe frequency by up to 21–27 % of the carriers below.
    """
    i, j = _grid()
    return amplitude_rad * np.exp(-((i - HEIGHT / 2) ** 2 + (j - WIDTH / 2) ** 2)
                                  / (2 * sigma_px**2))


def _background() -> F64:
    """Vignetted illumination: 25 % darker in the corners."""
    i, j = _grid()
    r2 = ((i - HEIGHT / 2) ** 2 + (j - WIDTH / 2) ** 2) / ((HEIGHT / 2) ** 2 + (WIDTH / 2) ** 2)
    return BACKGROUND_DN * (1.0 - 0.25 * r2)


def _carrier_phase(carrier: Carrier) -> F64:
    i, j = _grid()
    fy, fx = carrier.frequency
    return 2 * np.pi * (fy * i + fx * j)


def _fringes(carrier: Carrier, phi: F64, phase0: float = 0.3) -> tuple[F64, F64]:
    """The image and its true (carrier-inclusive) phase."""
    phase = _carrier_phase(carrier) + phi + phase0
    return _background() + FRINGE_DN * np.cos(phase), phase


def _regions(carrier: Carrier) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """(interior, border band of one fringe period)."""
    period = math.ceil(carrier.period_px)
    interior = np.zeros((HEIGHT, WIDTH), dtype=bool)
    interior[period:-period, period:-period] = True
    return interior, ~interior


@pytest.mark.parametrize("name", list(CARRIERS))
def test_phase_of_a_curved_surface_is_recovered_modulo_2pi(name: str) -> None:
    carrier = CARRIERS[name]
    image, true_phase = _fringes(carrier, _bump())
    result = demodulate(image, carrier)
    assert isinstance(result, Demodulated)
    assert result.wrapped_phase.dtype == np.float32 and result.modulation.dtype == np.float32
    assert result.wrapped_phase.shape == result.modulation.shape == (HEIGHT, WIDTH)
    assert np.all(np.abs(result.wrapped_phase) <= np.float32(np.pi))

    error = _wrap(result.wrapped_phase - true_phase)
    interior, border = _regions(carrier)
    assert np.sqrt(np.mean(error[interior] ** 2)) < INTERIOR_RMS_RAD
    assert np.abs(error[interior]).max() < INTERIOR_MAX_RAD
    # The continuation along the carrier keeps the outer period usable (without it, it rings).
    assert np.abs(error[border]).max() < BORDER_MAX_RAD


@pytest.mark.parametrize("name", list(CARRIERS))
def test_modulation_is_the_fringe_amplitude(name: str) -> None:
    carrier = CARRIERS[name]
    image, _ = _fringes(carrier, _bump())
    modulation = demodulate(image, carrier).modulation
    interior, border = _regions(carrier)
    assert np.median(modulation[interior]) == pytest.approx(FRINGE_DN, rel=0.005)
    # The long raised-cosine edge of the default band passes a strongly shifted local frequency
    # at a little less than full gain: a few per cent of amplitude, for a better phase.
    assert np.abs(modulation[interior] - FRINGE_DN).max() < 0.08 * FRINGE_DN
    assert np.abs(modulation[border] - FRINGE_DN).max() < 0.1 * FRINGE_DN


def test_phase_convention_of_a_pure_cosine() -> None:
    """``A + B cos(2π f·x + φ0)`` demodulates to ``2π f·x + φ0``; the negated carrier to minus."""
    carrier = Carrier((0.013, 0.047))
    i, j = _grid()
    phase0 = -2.2
    truth = 2 * np.pi * (0.013 * i + 0.047 * j) + phase0
    image = 40.0 + 25.0 * np.cos(truth)
    phase = demodulate(image, carrier).wrapped_phase
    interior, _ = _regions(carrier)
    assert np.abs(_wrap(phase - truth))[interior].max() < 5e-3
    # The borders too (the band reaches within 0.1·|f| of the background there).
    assert np.abs(_wrap(phase - truth)).max() < 1.5e-2
    assert float(phase[0, 0]) == pytest.approx(phase0, abs=1e-2)
    negated = demodulate(image, carrier.negated()).wrapped_phase
    assert np.abs(_wrap(negated + truth)).max() < 1.5e-2


def test_integer_images_demodulate_like_float_ones() -> None:
    carrier = CARRIERS["vertical fringes"]
    image, true_phase = _fringes(carrier, _bump())
    as_uint8 = np.clip(np.round(image), 0, 255).astype(np.uint8)
    as_uint16 = (as_uint8.astype(np.uint16) * 16)  # 12-bit data in uint16
    from_uint8 = demodulate(as_uint8, carrier)
    from_uint16 = demodulate(as_uint16, carrier)
    from_float = demodulate(as_uint8.astype(np.float64), carrier)
    np.testing.assert_allclose(from_uint8.wrapped_phase, from_float.wrapped_phase, atol=1e-4)
    np.testing.assert_allclose(from_uint16.wrapped_phase, from_uint8.wrapped_phase, atol=1e-4)
    np.testing.assert_allclose(from_uint16.modulation, 16 * from_uint8.modulation, rtol=1e-4)
    interior, _ = _regions(carrier)
    # Quantisation to whole DN costs little against a 30 DN fringe.
    error = _wrap(from_uint8.wrapped_phase - true_phase)
    assert np.sqrt(np.mean(error[interior] ** 2)) < INTERIOR_RMS_RAD


def _expected_noise_rad(noise_dn: float, carrier: Carrier, bandwidth: float,
                        taper: float) -> float:
    """Phase noise of white noise through the pass band: σ_φ² = 2 σ² ∫|H|² df / B²."""
    outer = bandwidth * carrier.cycles_per_px
    flat = (1 - taper) * outer
    radius = np.linspace(0.0, outer, 20001)
    gain = np.where(radius <= flat, 1.0,
                    0.5 * (1 + np.cos(np.pi * (radius - flat) / (outer - flat))))
    power = float(np.sum(gain**2 * 2 * np.pi * radius) * (radius[1] - radius[0]))
    return math.sqrt(2 * noise_dn**2 * power) / FRINGE_DN


@pytest.mark.parametrize("noise_dn", [1.0, 3.0, 9.0])
def test_phase_noise_follows_the_pass_band(noise_dn: float) -> None:
    carrier = CARRIERS["oblique 34°"]
    image, true_phase = _fringes(carrier, np.zeros((HEIGHT, WIDTH)))
    noisy = image + np.random.default_rng(7).normal(0.0, noise_dn, image.shape)
    error = _wrap(demodulate(noisy, carrier).wrapped_phase - true_phase)
    interior, _ = _regions(carrier)
    measured = float(np.sqrt(np.mean(error[interior] ** 2)))
    expected = _expected_noise_rad(noise_dn, carrier, bandwidth=0.8, taper=0.4)
    assert measured == pytest.approx(expected, rel=0.2)


def test_a_narrower_band_passes_less_noise() -> None:
    carrier = CARRIERS["vertical fringes"]
    image, true_phase = _fringes(carrier, np.zeros((HEIGHT, WIDTH)))
    noisy = image + np.random.default_rng(3).normal(0.0, 4.0, image.shape)
    interior, _ = _regions(carrier)

    def rms(bandwidth: float) -> float:
        phase = demodulate(noisy, carrier, bandwidth=bandwidth).wrapped_phase
        return float(np.sqrt(np.mean(_wrap(phase - true_phase)[interior] ** 2)))

    assert rms(0.4) < 0.7 * rms(0.8)


def test_without_the_continuation_the_borders_ring() -> None:
    """A surface whose phase differs at opposite borders (a tilted one) breaks periodicity."""
    carrier = CARRIERS["vertical fringes"]
    i, j = _grid()
    tilt = 0.006 * (0.6 * i + 0.8 * j)
    image, true_phase = _fringes(carrier, _bump() + tilt)
    _, border = _regions(carrier)
    padded = _wrap(demodulate(image, carrier).wrapped_phase - true_phase)
    unpadded = _wrap(demodulate(image, carrier, pad_px=0).wrapped_phase - true_phase)
    assert np.abs(padded[border]).max() < BORDER_MAX_RAD
    assert np.abs(unpadded[border]).max() > 0.5


def test_steep_surface_within_the_flat_top() -> None:
    """A local frequency shift of 40 % of the carrier passes a band flat that far nearly
    unbiased, where a Hann-shaped band of the same reach (taper 1: no flat top) bends the phase
    (both without the bend correction, which would hide the difference)."""
    carrier = CARRIERS["vertical fringes"]
    phi = _bump(amplitude_rad=10.0, sigma_px=60.0)
    steepest = float(np.abs(np.gradient(phi, axis=1)).max()) / (2 * np.pi)
    assert steepest > 0.39 * carrier.cycles_per_px
    image, true_phase = _fringes(carrier, phi)
    interior, _ = _regions(carrier)

    def rms(taper: float) -> float:
        phase = demodulate(image, carrier, taper=taper, measure_bends=False).wrapped_phase
        return float(np.sqrt(np.mean(_wrap(phase - true_phase)[interior] ** 2)))

    flat_topped = rms(0.4)
    assert flat_topped < INTERIOR_RMS_RAD
    assert rms(1.0) > 4 * flat_topped


@pytest.mark.parametrize("fading", [False, True], ids=["even fringes", "fading fringes"])
@pytest.mark.parametrize("name", list(CARRIERS))
def test_fringes_bent_onto_the_bands_edge_are_corrected(name: str, fading: bool) -> None:
    """A bump that shifts the local frequency by 40 % of the carrier (beyond the default band's
    flat top, 18 %) is biased by the band's edge where it bends most, more so where the fringe
    fades across it (to half); :meth:`Demodulated.surface_phase` takes most of that away
    (measured: interior RMS 0.015–0.031 → 0.005–0.013 rad, worst 0.065–0.12 → 0.033–0.068 rad)
    and a plane has no bias to correct."""
    carrier = CARRIERS[name]
    phi = _bump(amplitude_rad=10.0, sigma_px=60.0)
    _, j = _grid()
    amplitude = 1.0 - 0.5 * np.clip((j - 80.0) / 240.0, 0.0, 1.0) if fading else 1.0
    true_phase = _carrier_phase(carrier) + phi + 0.3
    image = _background() + FRINGE_DN * amplitude * np.cos(true_phase)
    interior, _ = _regions(carrier)

    def errors(phase: npt.NDArray[np.float32]) -> tuple[float, float]:
        error = _wrap(phase - true_phase)[interior]
        return float(np.sqrt(np.mean(error**2))), float(np.abs(error).max())

    result = demodulate(image, carrier)
    (rms_raw, worst_raw), (rms, worst) = errors(result.wrapped_phase), errors(
        result.surface_phase())
    assert rms_raw > 0.013
    assert rms < 0.45 * rms_raw and rms < INTERIOR_RMS_RAD
    assert worst < 0.65 * worst_raw
    # The band's own phase stays as it was; asked not to, demodulate measures no bias.
    unmeasured = demodulate(image, carrier, measure_bends=False)
    assert unmeasured.bend_bias is None
    assert np.array_equal(unmeasured.wrapped_phase, result.wrapped_phase)
    plane, _ = _fringes(carrier, 0.3 * _grid()[1] / WIDTH)
    assert demodulate(plane, carrier).bend_bias is None  # every frequency on the flat top


def test_no_bend_bias_is_taken_where_the_fringe_field_ends() -> None:
    """Around a dark disc (as the cornea is) neither the bend nor the fading of the fringes is a
    smooth surface's: near its edge no bias is taken (on the simulated eye the correction had
    put the sclera beside the limbus 0.1 mm outside the globe); beyond, the bump is corrected
    as usual (measured: RMS 0.020 → 0.007 rad)."""
    carrier = CARRIERS["vertical fringes"]
    i, j = _grid()
    true_phase = _carrier_phase(carrier) + _bump(amplitude_rad=10.0, sigma_px=60.0) + 0.3
    radius = np.hypot(i - HEIGHT / 2, j - WIDTH / 2)
    amplitude = np.where(radius < 30.0, 0.02, 1.0)
    result = demodulate(_background() + FRINGE_DN * amplitude * np.cos(true_phase), carrier)
    assert result.bend_bias is not None
    period = carrier.period_px
    assert np.all(result.bend_bias[radius < 30.0 + 0.5 * period] == 0.0)
    far = _regions(carrier)[0] & (radius > 30.0 + 2 * period)
    raw = _wrap(result.wrapped_phase - true_phase)[far]
    corrected = _wrap(result.surface_phase() - true_phase)[far]
    assert np.sqrt(np.mean(corrected**2)) < 0.45 * np.sqrt(np.mean(raw**2))


@pytest.mark.parametrize("name", list(CARRIERS))
def test_a_window_given_its_origin_has_the_whole_images_bend_bias(name: str) -> None:
    """Live tracking demodulates a window of each image: told where the window lies, the bend
    correction averages over the whole image's blocks and the window's bias is the whole
    image's away from its border (measured: within 0.0009 rad of a bias up to 0.15 rad; without
    the origin, blocks of its own, up to 0.009 rad off)."""
    carrier = CARRIERS[name]
    true_phase = _carrier_phase(carrier) + _bump(amplitude_rad=10.0, sigma_px=60.0) + 0.3
    image = _background() + FRINGE_DN * np.cos(true_phase)
    whole = demodulate(image, carrier).bend_bias
    assert whole is not None and np.abs(whole).max() > 0.08
    x0, y0, x1, y1 = 37, 21, 337, 271  # on no block's corner: the blocks are 3 or 4 px here
    margin = 3 * math.ceil(carrier.period_px)
    inner = np.s_[margin:-margin, margin:-margin]

    def gap(origin: tuple[int, int]) -> float:
        part = with_bend_bias(demodulate(image[y0:y1, x0:x1], carrier, measure_bends=False),
                              carrier, origin=origin).bend_bias
        assert part is not None
        return float(np.abs(part[inner] - whole[y0:y1, x0:x1][inner]).max())

    assert gap((x0, y0)) < 1.5e-3
    assert gap((0, 0)) > 1.5 * gap((x0, y0))


def test_an_image_shorter_than_a_period_still_demodulates() -> None:
    carrier = Carrier((0.0, 0.05))
    j = np.arange(12, dtype=np.float64)[None, :] * np.ones((64, 1))
    image = 10 + 5 * np.cos(2 * np.pi * 0.05 * j)
    result = demodulate(image, carrier)
    assert np.isfinite(result.wrapped_phase).all() and np.isfinite(result.modulation).all()


# --- the carrier ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(CARRIERS))
def test_carrier_is_measured_within_half_a_percent(name: str) -> None:
    """On a reference-like image (a plane: no surface phase) with noise and vignetting.

    (A bump of several radians over much of the image moves the spectral peak itself: the
    carrier is measured on the reference plane, as the pipeline does.)
    """
    truth = CARRIERS[name]
    image, _ = _fringes(truth, np.zeros((HEIGHT, WIDTH)))
    noisy = image + np.random.default_rng(1).normal(0.0, 2.0, image.shape)
    measured = measure_carrier(noisy)
    # The canonical sign: the nearest bin has fx > 0, or fx = 0 and fy > 0.
    fy, fx = truth.frequency
    expected = truth if fx > 0 or (fx == 0 and fy > 0) else truth.negated()
    error = math.dist(measured.frequency, expected.frequency)
    assert error < 0.005 * truth.cycles_per_px


def test_carrier_sign_is_canonical() -> None:
    i, j = _grid()
    horizontal = 30 + 20 * np.cos(2 * np.pi * 0.05 * i)
    fy, fx = measure_carrier(horizontal).frequency
    assert fy == pytest.approx(0.05, rel=0.005) and abs(fx) < 1e-4
    leaning_left = 30 + 20 * np.cos(2 * np.pi * (0.03 * i - 0.04 * j))
    fy, fx = measure_carrier(leaning_left).frequency
    assert fx == pytest.approx(0.04, rel=0.005) and fy == pytest.approx(-0.03, rel=0.005)


def test_carrier_with_a_mask_ignores_the_dark_surroundings() -> None:
    truth = Carrier((0.004, 0.042))
    image, _ = _fringes(truth, np.zeros((HEIGHT, WIDTH)))
    i, j = _grid()
    plate = (i - HEIGHT / 2) ** 2 + (j - WIDTH / 2) ** 2 < 120**2
    image = np.where(plate, image, 3.0)
    measured = measure_carrier(image, mask=plate)
    assert math.dist(measured.frequency, truth.frequency) < 0.005 * truth.cycles_per_px


def test_carrier_properties() -> None:
    carrier = Carrier.from_polar(math.pi / 6, 0.05)
    assert carrier.cycles_per_px == pytest.approx(0.05)
    assert carrier.period_px == pytest.approx(20.0)
    assert carrier.angle_rad == pytest.approx(math.pi / 6)
    assert carrier.frequency == pytest.approx((0.025, 0.05 * math.cos(math.pi / 6)))
    assert carrier.negated().negated() == carrier


# --- phase difference ----------------------------------------------------------------------


def test_phase_difference_wraps_into_half_open_interval() -> None:
    obj = np.array([0.5, math.pi, -math.pi, 3.0, -3.0, 2.0, 0.0, -1e-9], dtype=np.float64)
    ref = np.array([0.2, 0.0, 0.0, -3.0, 3.0, 2.0 + 2 * math.pi, math.pi, 0.0])
    result = phase_difference(obj, ref)
    assert result.dtype == np.float32
    expected = [0.3, math.pi, math.pi, 6.0 - 2 * math.pi, 2 * math.pi - 6.0, 0.0, math.pi, 0.0]
    np.testing.assert_allclose(result, expected, atol=1e-6)
    dense = np.linspace(-4 * np.pi, 4 * np.pi, 200_001, dtype=np.float32)
    wrapped = phase_difference(dense, np.zeros_like(dense))
    assert wrapped.min() > -np.float32(np.pi) and wrapped.max() <= np.float32(np.pi)
    np.testing.assert_allclose(np.cos(wrapped), np.cos(dense), atol=1e-5)
    np.testing.assert_allclose(np.sin(wrapped), np.sin(dense), atol=1e-5)


def test_phase_difference_cancels_the_carrier() -> None:
    carrier = CARRIERS["oblique 34°"]
    phi = _bump()
    object_image, _ = _fringes(carrier, phi)
    reference_image, _ = _fringes(carrier, np.zeros_like(phi))
    difference = phase_difference(demodulate(object_image, carrier).wrapped_phase,
                                  demodulate(reference_image, carrier).wrapped_phase)
    interior, _ = _regions(carrier)
    error = _wrap(difference - phi)
    assert np.sqrt(np.mean(error[interior] ** 2)) < INTERIOR_RMS_RAD


# --- validation ----------------------------------------------------------------------------

_GOOD_IMAGE = np.full((32, 32), 10.0)
_GOOD_CARRIER = Carrier((0.0, 0.1))


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"image": np.zeros((4, 32, 32))}, "image"),
    ({"image": np.zeros(32)}, "image"),
    ({"image": np.zeros((4, 32))}, "image"),
    ({"image": np.full((32, 32), np.nan)}, "image"),
    ({"image": np.full((32, 32), np.inf)}, "image"),
    ({"image": np.zeros((32, 32), dtype=bool)}, "image"),
    ({"image": np.zeros((32, 32), dtype=np.complex64)}, "image"),
    ({"carrier": (0.0, 0.1)}, "carrier"),
    ({"carrier": Carrier((0.0, 0.3))}, "carrier"),  # band beyond Nyquist at bandwidth 0.8
    ({"bandwidth": 0.0}, "bandwidth"),
    ({"bandwidth": 1.0}, "bandwidth"),
    ({"bandwidth": math.nan}, "bandwidth"),
    ({"bandwidth": True}, "bandwidth"),
    ({"taper": -0.1}, "taper"),
    ({"taper": 1.5}, "taper"),
    ({"pad_px": -1}, "pad_px"),
    ({"pad_px": 2.5}, "pad_px"),
    ({"workers": 0}, "workers"),
    ({"measure_bends": 1}, "measure_bends"),
])
def test_demodulate_rejects_bad_input(kwargs: dict[str, object], name: str) -> None:
    arguments: dict[str, object] = {"image": _GOOD_IMAGE, "carrier": _GOOD_CARRIER, **kwargs}
    with pytest.raises(ValueError, match=name):
        demodulate(**arguments)  # type: ignore[arg-type]


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"origin": (-1, 0)}, "origin"),
    ({"origin": (0.5, 0)}, "origin"),
    ({"origin": [0, 0]}, "origin"),
    ({"origin": (0, 0, 0)}, "origin"),
    ({"strong_modulation": -1.0}, "strong_modulation"),
    ({"strong_modulation": math.nan}, "strong_modulation"),
    ({"strong_modulation": True}, "strong_modulation"),
])
def test_with_bend_bias_rejects_bad_input(kwargs: dict[str, object], name: str) -> None:
    result = demodulate(_GOOD_IMAGE, _GOOD_CARRIER, measure_bends=False)
    with pytest.raises(ValueError, match=name):
        with_bend_bias(result, _GOOD_CARRIER, **kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize("frequency", [(0.0, 0.0), (0.6, 0.1), (0.1, -0.5), (math.nan, 0.1),
                                       (0.1,), ("a", 0.1)])
def test_carrier_rejects_bad_frequency(frequency: tuple[float, ...]) -> None:
    with pytest.raises(ValueError, match="frequency"):
        Carrier(frequency)  # type: ignore[arg-type]


def test_measure_carrier_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="image"):
        measure_carrier(np.full((64, 64), 7.0))  # no fringe at all
    with pytest.raises(ValueError, match=r"image must be a 2-D array .* shape \(64, 64, 2\)"):
        measure_carrier(np.zeros((64, 64, 2)))
    fringes = 10 + 5 * np.cos(2 * np.pi * 0.1 * np.arange(64))[None, :] * np.ones((64, 1))
    with pytest.raises(ValueError, match="mask"):
        measure_carrier(fringes, mask=np.ones((32, 64), dtype=bool))
    with pytest.raises(ValueError, match="mask"):
        measure_carrier(fringes, mask=np.zeros((64, 64), dtype=bool))
    with pytest.raises(ValueError, match="max_period_px"):
        measure_carrier(fringes, max_period_px=1.0)


def test_a_colour_image_is_demodulated_as_the_mean_of_its_colour_channels() -> None:
    truth = Carrier((0.004, 0.042))
    image, _ = _fringes(truth, np.zeros((HEIGHT, WIDTH)))
    alpha = np.full(image.shape, 255.0)
    colour = np.stack([0.5 * image, image, 1.5 * image, alpha], axis=2)  # BGRA, mean: image

    assert measure_carrier(colour).frequency == pytest.approx(measure_carrier(image).frequency)
    np.testing.assert_allclose(demodulate(colour, truth).wrapped_phase,
                               demodulate(image, truth).wrapped_phase, atol=1e-4)


def test_measure_carrier_refuses_noise_with_the_reason() -> None:
    """Noise alone has a largest bin too (4-5 times the median): no carrier is guessed from it,
    as a dark projector's frame once gave a period of 1.75 px."""
    noise = np.random.default_rng(3).normal(100.0, 2.0, (HEIGHT, WIDTH))
    with pytest.raises(ValueError, match=r"no fringe carrier: .* stands \d+\.\d× above"):
        measure_carrier(noise)
    faint = noise + 0.5 * np.cos(2 * np.pi * 0.042 * _grid()[1])  # a quarter of the noise's sd
    assert measure_carrier(faint).period_px == pytest.approx(1 / 0.042, rel=0.01)
    # The same judgement, as figures: noise under the strength needed, the faint fringe over.
    assert carrier_ratios(noise)[0] < MIN_CARRIER_STRENGTH < carrier_ratios(faint)[0]


def test_measure_carrier_refuses_two_carriers_of_similar_strength() -> None:
    _, j = _grid()
    two = 100 + 30 * np.cos(2 * np.pi * 0.042 * j) + 25 * np.cos(2 * np.pi * 0.07 * j)
    with pytest.raises(ValueError, match=r"no single fringe carrier: components of periods "
                                         r"23\.\d and 14\.\d px"):
        measure_carrier(two)
    one_strong = 100 + 30 * np.cos(2 * np.pi * 0.042 * j) + 15 * np.cos(2 * np.pi * 0.07 * j)
    assert measure_carrier(one_strong).period_px == pytest.approx(1 / 0.042, rel=0.01)
    assert carrier_ratios(two)[1] < MIN_CARRIER_DOMINANCE < carrier_ratios(one_strong)[1]
    # A Ronchi grating's harmonics (a square wave: 3f at a third) are the same carrier's.
    square = 100 + 30 * np.sign(np.cos(2 * np.pi * 0.042 * j + 0.3))
    assert measure_carrier(square).period_px == pytest.approx(1 / 0.042, rel=0.01)


def test_phase_difference_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="wrapped_object and wrapped_reference"):
        phase_difference(np.zeros((4, 4)), np.zeros((4, 5)))
    with pytest.raises(ValueError, match="wrapped_reference"):
        phase_difference(np.zeros(3), np.zeros(3, dtype=np.complex64))


def test_docstring_examples() -> None:
    failures, tested = doctest.testmod(demodulate_module, optionflags=doctest.ELLIPSIS)
    assert tested > 0 and failures == 0


# --- the simulated room --------------------------------------------------------------------


def test_plate_shifted_in_z_gives_a_smooth_nearly_uniform_phase_difference() -> None:
    """Plates at Z = 0 and Z = +3 mm seen by S1 under P1 (the default room)."""
    from eyeserver.hardware.sim.room import SimRoom
    from eyeserver.hardware.sim.scenes import SceneSpec

    room = SimRoom()
    images = {}
    for z_mm, seed in ((0.0, 0), (3.0, 1)):
        room.set_scene(SceneSpec(kind="plate", position_mm=(0.0, 0.0, z_mm)))
        images[z_mm] = room.render("S1", t_s=0, projectors={"P1": 1.0}, exposure_us=10000,
                                   gain_db=0, rng=np.random.default_rng(seed))
    carrier = measure_carrier(images[0.0])
    # S1 sees the vertical grating as vertical fringes of ≈ 24 px.
    assert 20.0 < carrier.period_px < 28.0
    assert abs(carrier.angle_rad) < math.radians(3)

    reference = demodulate(images[0.0], carrier)
    shifted = demodulate(images[3.0], carrier)
    difference = phase_difference(shifted.wrapped_phase, reference.wrapped_phase)
    interior = (slice(100, -100), slice(150, -100))  # on the plate in both images
    assert np.median(reference.modulation[interior]) > 15.0
    values = difference[interior].astype(np.float64)
    mean = float(np.angle(np.mean(np.exp(1j * values))))
    deviation = _wrap(values - mean)

    # Nearly uniform: 3 mm × ≈ 1.2 rad/mm, negative in S1's image (the fringes move towards
    # lower column phase as the plate approaches), i.e. ≈ −3.6 ≡ +2.65 rad; perspective makes
    # the sensitivity fall by ≈ 15 % from left to right, a spread of ±0.19 rad (1st–99th
    # percentile) about the mean.
    assert abs(_wrap(np.array(mean + 3.6))) < 0.15
    assert np.percentile(np.abs(deviation), 99) < 0.3
    # Smooth: a plane in (i, j) leaves only noise (measured 0.006 rad RMS).
    rows, cols = np.mgrid[100:412, 150:540]
    design = np.stack([np.ones(rows.size), rows.ravel(), cols.ravel()], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, deviation.ravel(), rcond=None)
    assert np.std(deviation.ravel() - design @ coefficients) < 0.015

    # Against the projector's own phase (ground truth, tests only): the same modulo 2π.
    camera = room.renderer.cameras["S1"]
    projector = room.renderer.projectors["P1"]
    rays = camera.rays()

    def grating_phase(z_mm: float) -> F64:
        t = (z_mm - camera.centre[2]) / rays[..., 2]
        return projector.phase_at(camera.centre + t[..., None] * rays)[0]

    truth = (grating_phase(3.0) - grating_phase(0.0))[interior]
    error = _wrap(values - truth)
    assert np.sqrt(np.mean(error**2)) < 0.03


def test_the_fast_angle_is_arctan2_within_its_stated_error() -> None:
    """``core.arrays.angle`` (cv2.phase, which demodulate and the order checks use in place of
    NumPy's arctan2) stays within ANGLE_ERROR_RAD of the exact angle in every direction and at
    every scale, keeps the input's shape and gives [−π, π] or [0, 2π) as asked."""
    turns = np.linspace(-math.pi, math.pi, 200_001)
    for scale in (1e-6, 1.0, 3e4):
        x, y = scale * np.cos(turns), scale * np.sin(turns)
        exact = np.arctan2(y, x)
        centred = angle(y, x)
        assert centred.dtype == np.float32 and centred.shape == turns.shape
        error = np.angle(np.exp(1j * (centred.astype(np.float64) - exact)))
        assert np.abs(error).max() <= ANGLE_ERROR_RAD
        assert centred.min() >= -math.pi - 1e-6 and centred.max() <= math.pi + 1e-6
        # Away from the cut at ±π, the centred angle is arctan2's own value, not a turn off.
        inside = np.abs(exact) < math.pi - 1e-3
        assert np.abs(centred[inside] - exact[inside]).max() <= ANGLE_ERROR_RAD
        whole = angle(y, x, centred=False)
        assert whole.min() >= 0.0 and whole.max() < 2 * math.pi + 1e-6
        assert np.abs(np.angle(np.exp(1j * (whole - exact)))).max() <= ANGLE_ERROR_RAD
    grid = np.arange(24.0).reshape(2, 3, 4) - 11.5
    assert angle(grid, -grid).shape == (2, 3, 4)
    assert angle(np.zeros((0, 5)), np.zeros((0, 5))).shape == (0, 5)
    with pytest.raises(ValueError, match="same shape"):
        angle(np.zeros(3), np.zeros(4))

