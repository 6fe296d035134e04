"""Fourier-transform (Takeda) demodulation of a single fringe image (docs/design.md §4 step 1).

A fringe image ``I(x) = A(x) + B(x)·cos(2π f·x + φ(x))`` carries the surface in the phase ``φ``
(rad). The band of its spectrum around ``+f``, transformed back, is the analytic fringe
``B·exp(i(2π f·x + φ))``: its angle the wrapped phase, its magnitude the modulation ``B``.

Conventions. Pixel positions are ``x = (i, j)``, row then column, integers at pixel centres. A
:class:`Carrier` is a spatial frequency ``(fy, fx)`` in cycles per pixel, same order; the phase
increases along it: for ``I = A + B·cos(2π(fy·i + fx·j) + φ0)`` and the carrier ``(fy, fx)``,
``wrapped_phase ≡ 2π(fy·i + fx·j) + φ0 (mod 2π)``, and with ``(−fy, −fx)`` the negative.
:func:`measure_carrier` returns the sign whose nearest bin has ``fx > 0``, or ``fx = 0`` and
``fy > 0``: vertical fringes give a phase that grows with the column, horizontal ones with the row.

The borders. A discrete Fourier transform treats the image as periodic, and the jump where
opposite borders meet rings over about a fringe period. Mirror padding does not cure it for
fringes (a mirror turns them around), so the image is continued along the carrier itself (cf.
Roddier & Roddier), one axis after the other: along the axis the carrier runs along most, by
whole carrier periods, ``2·T1 − T2`` (``T1``, ``T2`` the image one and two periods further in:
the difference extrapolates phase and background linearly, cancelling to first order the step
either copy alone would leave); along the other axis, along the fringes from the border line.
Both are exact for straight fringes (copies interpolated with Keys' cubic); the continuations of
opposite borders are cross-faded half way, in a padded length of whole carrier periods where a
fast FFT length allows.

The band. A disc (or ellipse, :data:`ELONGATION`) around the carrier, flat up to
``(1 − taper)·bandwidth·|f|`` and falling to zero at ``bandwidth·|f|`` along a raised cosine, so
the background (``|f|`` away) and the conjugate fringe (``2|f|``) are rejected in any direction. A
flat top passes the local frequencies of a curved surface without weighting them (Gaussian or
Hann windows are biased); the smooth edge keeps the impulse response short. Rows go through
``rfft``; only the columns the band touches are transformed along the columns and back.

Bent fringes. Where a surface bends the fringes, the local frequency ``k = ∇φ/2π`` moves onto the
band's tapered edge, which biases the phase, to second order, by ``−(∇B/B)·∇H/(2π·H) −
Σ ∂ᵢ∂ⱼφ·∂ᵢ∂ⱼH/(8π²·H)`` (``H``'s derivatives per cycle/px, the phase's curvature in rad/px²): on
the eye, a sphere's worth of bias in the globe's radius. :func:`demodulate` measures ``k``, the
curvature and the amplitude's gradient (the modulation's, less the band's own gain) from what it
found, over :data:`BEND_SMOOTHING_PERIODS` of a period, into :attr:`Demodulated.bend_bias`,
except within :data:`BEND_EDGE_PERIODS` of where the fringe field ends;
:meth:`Demodulated.surface_phase` is the phase less it, while :attr:`Demodulated.wrapped_phase`
stays the band's own. Measured: docs/notes/demodulation.md.
"""

from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import scipy.fft

from eyeserver.core.arrays import angle, wrap
from eyeserver.core.frames import grey
from eyeserver.core.types import F32, F64

__all__ = ["Carrier", "Demodulated", "band_gain", "carrier_ratios", "demodulate", "measure_carrier",
           "phase_difference", "with_bend_bias"]

_TWO_PI = 2.0 * math.pi
_PI32 = np.float32(math.pi)
_MIN_SIZE = 8


@dataclass(frozen=True)
class Carrier:
    """The spatial carrier frequency of a fringe pattern.

    Attributes
    ----------
    frequency : tuple of float
        ``(fy, fx)``: cycles per pixel along the rows (``i``, down) and the columns (``j``,
        right). Both components lie in ``(−0.5, 0.5)`` (Nyquist), not both zero.

    Examples
    --------
    >>> carrier = Carrier.from_polar(angle_rad=0.0, cycles_per_px=0.04)
    >>> carrier.frequency, carrier.period_px
    ((0.0, 0.04), 25.0)
    """

    frequency: tuple[float, float]

    def __post_init__(self) -> None:
        try:
            fy, fx = (float(f) for f in self.frequency)
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"frequency must be a pair (fy, fx) of numbers, not {self.frequency!r}") from exc
        if not (math.isfinite(fy) and math.isfinite(fx)):
            raise ValueError(f"frequency must be finite, not {(fy, fx)}")
        if fy == 0.0 and fx == 0.0:
            raise ValueError("frequency must not be zero (no carrier)")
        if abs(fy) >= 0.5 or abs(fx) >= 0.5:
            raise ValueError(
                f"frequency {(fy, fx)} is beyond Nyquist (each component below 0.5 cycles/px)")
        object.__setattr__(self, "frequency", (fy, fx))

    @classmethod
    def from_polar(cls, angle_rad: float, cycles_per_px: float) -> Carrier:
        """The carrier of magnitude ``cycles_per_px`` pointing ``angle_rad`` from the column axis.

        The angle turns from the column axis (``+j``, right) towards the row axis (``+i``,
        down): 0 for vertical fringes whose phase grows to the right, ``π/2`` for horizontal
        fringes whose phase grows downwards.
        """
        fy, fx = cycles_per_px * math.sin(angle_rad), cycles_per_px * math.cos(angle_rad)
        # cos(π/2) is 6e-17, not 0: keep axis-aligned carriers exactly on their axis.
        tiny = 1e-12 * abs(cycles_per_px)
        return cls((0.0 if abs(fy) < tiny else fy, 0.0 if abs(fx) < tiny else fx))

    @property
    def cycles_per_px(self) -> float:
        """Magnitude ``|f|`` of the carrier, cycles per pixel."""
        return math.hypot(*self.frequency)

    @property
    def period_px(self) -> float:
        """Fringe period across the fringes, pixels."""
        return 1.0 / self.cycles_per_px

    @property
    def angle_rad(self) -> float:
        """Direction of the carrier, ``atan2(fy, fx)``: 0 along ``+j``, ``π/2`` along ``+i``."""
        fy, fx = self.frequency
        return math.atan2(fy, fx)

    def negated(self) -> Carrier:
        """The same fringes described by the opposite sign (the phase changes sign)."""
        fy, fx = self.frequency
        return Carrier((-fy, -fx))


@dataclass(frozen=True)
class Demodulated:
    """The outcome of :func:`demodulate`, both arrays of the image's shape.

    Attributes
    ----------
    wrapped_phase : ndarray of float32
        Phase of the band-passed fringe including the carrier ramp, radians in ``[−π, π]``:
        with ``modulation`` the fringe the band passed (``B·cos φ`` is what it takes out of the
        image).
    modulation : ndarray of float32
        Fringe amplitude ``B`` (half the peak-to-peak swing) in the image's units (DN): the
        magnitude of the analytic fringe signal.
    bend_bias : ndarray of float32 or None
        The phase the band's edge added where the fringes bend (module docstring), radians;
        None where none was measured or every local frequency lies on the flat top.
    """

    wrapped_phase: F32
    modulation: F32
    bend_bias: F32 | None = None

    def surface_phase(self) -> F32:
        """The surface's wrapped phase: :attr:`wrapped_phase` less :attr:`bend_bias`, radians
        in about ``[−π, π]``."""
        if self.bend_bias is None:
            return self.wrapped_phase
        return wrap(self.wrapped_phase - self.bend_bias)


def checked_image(image: npt.ArrayLike, name: str = "image", min_size: int = _MIN_SIZE,
                  ) -> npt.NDArray[Any]:
    """``image`` as a 2-D real finite array (its own dtype; a colour image
    made :func:`~eyeserver.core.frames.grey`)
    of at least ``min_size`` pixels a side, or a ValueError naming ``name``."""
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] in (3, 4) and array.dtype != np.bool_ and (
            np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)):
        array = grey(array)
    if array.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array (or a colour image of 3 or 4 channels), "
                         f"not {array.ndim}-D of shape {array.shape}")
    if array.dtype == np.bool_ or not (np.issubdtype(array.dtype, np.integer)
                                       or np.issubdtype(array.dtype, np.floating)):
        raise ValueError(f"{name} must hold real numbers (integer or float), not {array.dtype}")
    if min(array.shape) < min_size:
        raise ValueError(f"{name} must be at least {min_size}×{min_size} px, not "
                         f"{array.shape[0]}×{array.shape[1]}")
    if np.issubdtype(array.dtype, np.floating) and not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return array


def _signed_frequencies(n: int) -> npt.NDArray[np.float64]:
    """Bin frequencies of an ``n``-point transform in cycles per sample, negative half last."""
    return np.asarray(np.fft.fftfreq(n), dtype=np.float64)


def _cubic_weights(fraction: npt.NDArray[np.float64]) -> list[F32]:
    """Keys' cubic convolution weights (a = −0.5) of the samples at −1, 0, +1, +2.

    Half-way between samples, linear interpolation attenuates a fringe of 20 px by 1.2 %, this
    cubic by 0.03 %: the copies in the pad then match the image's fringe amplitude.
    """
    t = fraction
    return [np.asarray(w, dtype=np.float32) for w in (
        ((-0.5 * t + 1.0) * t - 0.5) * t,
        (1.5 * t - 2.5) * t * t + 1.0,
        ((-1.5 * t + 2.0) * t + 0.5) * t,
        (0.5 * t - 0.5) * t * t,
    )]


def _interpolation_operator(n: int, terms: list[tuple[npt.NDArray[np.float64], F32]],
                            ) -> tuple[npt.NDArray[np.intp], F32]:
    """Sources and weights of pad lines that are sums of interpolated lines of the image.

    ``terms`` holds ``(positions, coefficients)``: pad line ``k`` receives
    ``coefficients[k]`` times the image interpolated (cubic) at ``positions[k]`` along the
    axis of length ``n``; positions within one sample of an end use the end sample for the
    missing neighbour. Returns the image lines used and the ``(len(used), pad lines)`` matrix
    that maps them to the pad: one small matrix product instead of many strided gathers.
    """
    lines = terms[0][0].size
    operator = np.zeros((n, lines), dtype=np.float64)
    pad_line = np.arange(lines)
    for positions, coefficients in terms:
        base = np.floor(positions)
        lower = base.astype(np.intp)
        for offset, weight in zip((-1, 0, 1, 2), _cubic_weights(positions - base), strict=True):
            np.add.at(operator, (np.clip(lower + offset, 0, n - 1), pad_line),
                      weight * coefficients)
    used = np.flatnonzero(np.any(operator != 0.0, axis=1))
    return used, operator[used].astype(np.float32)


def _shifted_line(line: F32, shifts: npt.NDArray[np.float64]) -> F32:
    """Rows ``line(k + shift)`` (``k`` over the line, periodic, cubic), one row per shift.

    Each row is a contiguous window of the line repeated, so the gather copies whole rows
    rather than indexing in 2-D.
    """
    n = line.shape[0]
    base = np.floor(shifts)
    start = np.mod(base.astype(np.intp), n)
    windows = np.lib.stride_tricks.sliding_window_view(
        np.concatenate([line[-1:], line, line, line[:2]]), n)
    result = np.zeros((shifts.size, n), dtype=np.float32)
    for offset, weight in zip((-1, 0, 1, 2), _cubic_weights(shifts - base), strict=True):
        result += windows[start + offset + 1] * weight[:, None]
    return result


def _bridge(n: int, total: int) -> tuple[F64, F64, F64]:
    """Positions of the pad lines after the end border, the same before the start, and the
    raised-cosine weight of the start border's continuation in each."""
    beyond = np.arange(n, total, dtype=np.float64)
    towards_start = 0.5 * (1.0 - np.cos(np.pi * (beyond - n + 1.0) / (total - n + 1.0)))
    return beyond, beyond - total, towards_start


@functools.lru_cache(maxsize=64)
def _period_operator(n: int, total: int, period: float) -> tuple[npt.NDArray[np.intp], F32]:
    """:func:`_interpolation_operator` of the continuation by whole periods (see
    :func:`_continuation`) of ``n`` lines to ``total``: it depends on the sizes and the
    carrier only, so it is made once per window shape (measured: 0.5 ms a call, a sixth of
    a tracked window's demodulation)."""
    beyond, before, towards_start = _bridge(n, total)
    towards_end = (1.0 - towards_start).astype(np.float32)
    towards_start32 = towards_start.astype(np.float32)
    # Sources end one sample short of the border so the cubic has all its neighbours.
    last = n - 2
    terms: list[tuple[npt.NDArray[np.float64], F32]]
    if period <= last - 1:
        from_end = beyond - np.ceil((beyond - last) / period) * period
        from_start = before + np.ceil((1.0 - before) / period) * period
    if 2.0 * period <= last - 1:
        # Two periods back, extrapolated linearly (2·one period − two periods): the pad's
        # own copy would carry the phase of one period further in, a step of (phase slope
        # × period) at the border; the difference of the two copies cancels it to first
        # order, and the background is extrapolated linearly as well.
        terms = [(from_end, 2.0 * towards_end), (from_end - period, -towards_end),
                 (from_start, 2.0 * towards_start32),
                 (from_start + period, -towards_start32)]
    elif period <= last - 1:
        terms = [(from_end, towards_end), (from_start, towards_start32)]
    else:
        terms = [(np.clip(2.0 * (n - 1) - beyond, 0.0, n - 1.0), towards_end),
                 (np.clip(-before, 0.0, n - 1.0), towards_start32)]
    return _interpolation_operator(n, terms)


def _continuation(block: F32, axis: int, total: int, f_along: float, f_across: float,
                  along_fringes: bool) -> F32:
    """The ``total − n`` lines that continue ``block`` beyond its end along ``axis``.

    The pad is a periodic bridge from the last line back to the first: near the end it
    continues the end border, near the far end (the wrap-around) the start border, cross-faded
    with a raised cosine. Each border is continued along the carrier (module docstring): by
    whole periods along ``axis``, or (``along_fringes``) along the fringes from the border line;
    by a plain mirror when the image is shorter than one period along ``axis`` (degenerate
    images only).
    """
    n = block.shape[axis]
    if not along_fringes:
        period = 1.0 / abs(f_along) if f_along != 0.0 else math.inf
        used, operator = _period_operator(n, total, period)
        if axis == 1:
            return np.asarray(block[:, used] @ operator, dtype=np.float32)
        return np.asarray(operator.T @ block[used, :], dtype=np.float32)
    # Along the fringe through the pad pixel back to the border line: the other coordinate
    # moves by (distance along axis)·f_along/f_across. That axis is already continued
    # periodically (the steep axis is always done first), so positions wrap.
    beyond, before, towards_start = _bridge(n, total)
    slope = f_along / f_across
    end_line = np.ascontiguousarray(block[:, n - 1] if axis == 1 else block[n - 1, :])
    start_line = np.ascontiguousarray(block[:, 0] if axis == 1 else block[0, :])
    end_part = _shifted_line(end_line, (beyond - (n - 1)) * slope)
    start_part = _shifted_line(start_line, before * slope)
    if axis == 1:
        end_part, start_part = end_part.T, start_part.T
    weight = towards_start.astype(np.float32).reshape((1, -1) if axis == 1 else (-1, 1))
    return np.asarray(end_part + (start_part - end_part) * weight, dtype=np.float32)


@functools.lru_cache(maxsize=64)
def _padded_length(length: int, pad_px: int, frequency: float) -> int:
    """A fast FFT length of at least ``length + 2·pad_px`` that holds whole carrier periods.

    Where the periodic transform wraps around, the two borders' continuations meet; if the
    padded length holds a whole number of periods along this axis, their carriers agree there
    and the cross-fade between them is seamless for straight fringes (otherwise the mismatch
    costs a few milliradians at the border). Among the fast lengths up to one period (at
    least 16, at most 64 samples) longer than needed: the shortest within 0.05 period of a
    whole number, else the closest.
    """
    target = length + 2 * pad_px
    shortest = int(scipy.fft.next_fast_len(target, real=True))
    if abs(frequency) * length < 0.5:
        # Less than half a period across the image: nothing to match.
        return shortest
    reach = target + min(max(16, math.ceil(1.0 / abs(frequency))), 64)
    candidates = sorted({int(scipy.fft.next_fast_len(n, real=True))
                         for n in range(target, reach + 1)})

    def mismatch(n: int) -> float:
        cycles = n * abs(frequency)
        return abs(cycles - round(cycles))

    close = [n for n in candidates if mismatch(n) <= 0.05]
    return close[0] if close else min(candidates, key=mismatch)


def _extend(out: F32, height: int, width: int, fy: float, fx: float) -> None:
    """Continue the image in ``out[:height, :width]`` over the rest of ``out``, periodically."""
    padded_h, padded_w = out.shape
    values = out[:height, :width]
    # The axis the carrier runs along most is continued first, by whole periods (at most √2
    # fringe periods long); the other then follows the fringes through the already periodic
    # first axis. Periods on the other axis too would be up to twice as long at oblique
    # carriers and more than that near the axes (1/|f_axis|), copying the surface's phase
    # from further away (measured at 34°: 0.24 against 0.13 rad at the border for a slope of
    # 0.01 rad/px, before the linear extrapolation).
    if abs(fx) >= abs(fy):
        if padded_w > width:
            out[:height, width:] = _continuation(values, 1, padded_w, fx, fy, False)
        if padded_h > height:
            out[height:, :] = _continuation(out[:height, :], 0, padded_h, fy, fx, True)
    else:
        if padded_h > height:
            out[height:, :width] = _continuation(values, 0, padded_h, fy, fx, False)
        if padded_w > width:
            out[:, width:] = _continuation(out[:, :width], 1, padded_w, fx, fy, True)


def measure_carrier(image: npt.ArrayLike, mask: npt.ArrayLike | None = None, *,
                    max_period_px: float | None = None) -> Carrier:
    """Measure the fringe carrier of a (reference) image as the peak of its 2-D spectrum.

    The image, less its mean and multiplied by a separable Hann window (and by ``mask``),
    is transformed with ``scipy.fft.rfft2``; the strongest bin outside the low frequencies is
    the coarse carrier. It is refined by evaluating the windowed image's discrete-time Fourier
    transform on a grid of 1/8 bin around that bin and fitting a parabola to the logarithm of
    its magnitude at the grid maximum (the Hann main lobe is close to a Gaussian there), which
    leaves a small fraction of a bin of error on a clean fringe (0.1 % of ``|f|`` measured on
    noisy, vignetted 320×400 fringes).

    Measure it on the reference plane: a surface phase of several radians over much of the
    image moves the spectral peak itself (a 5 rad bump over a 320×400 image: by 14 %), and the
    pipeline's phase differences need one fixed carrier anyway.

    Parameters
    ----------
    image : array_like, shape (H, W)
        Fringe image, any real dtype (uint8, uint16, float); finite; at least 8×8 px.
    mask : array_like of bool, shape (H, W), optional
        Pixels to use (True); for example the flat reference plate without its dark
        surroundings. Default: all.
    max_period_px : float, optional
        Longest fringe period considered, pixels; longer periods (the background's slow
        variations, vignetting, the DC) are excluded. Default: a quarter of the image's smaller
        side.

    Returns
    -------
    Carrier
        The carrier ``(fy, fx)`` in cycles per pixel with the sign described in the module
        docstring: its nearest bin has ``fx > 0``, or ``fx = 0`` and ``fy > 0``.

    Raises
    ------
    ValueError
        If ``image``, ``mask`` or ``max_period_px`` is invalid; if ``image`` holds no fringe
        (no peak :data:`MIN_CARRIER_STRENGTH` times above the spectrum's median); or if no
        single carrier stands out (:data:`MIN_CARRIER_DOMINANCE`), as on a surface whose phase
        spreads the fringe: the message says which.

    References
    ----------
    .. [1] M. Takeda, H. Ina and S. Kobayashi, "Fourier-transform method of fringe-pattern
       analysis for computer-based topography and interferometry", J. Opt. Soc. Am. 72(1),
       156–160 (1982). doi:10.1364/JOSA.72.000156
    .. [2] M. Gasior and J. L. Gonzalez, "Improving FFT frequency measurement resolution by
       parabolic and Gaussian spectrum interpolation", AIP Conf. Proc. 732, 276–285 (2004).
       doi:10.1063/1.1831158

    Examples
    --------
    >>> import numpy as np
    >>> i, j = np.mgrid[0:128, 0:160]
    >>> fringes = 100 + 50 * np.cos(2 * np.pi * (0.01 * i + 0.06 * j))
    >>> carrier = measure_carrier(fringes)
    >>> [round(f, 4) for f in carrier.frequency]
    [0.01, 0.06]
    """
    values = np.asarray(checked_image(image), dtype=np.float32)
    height, width = values.shape
    if mask is None:
        weights = None
    else:
        weights = np.asarray(mask)
        if weights.shape != values.shape:
            raise ValueError(f"mask must have the image's shape {values.shape}, "
                             f"not {weights.shape}")
        weights = weights.astype(bool)
        if weights.sum() < _MIN_SIZE * _MIN_SIZE:
            raise ValueError("mask must select at least 64 pixels")
    if max_period_px is None:
        max_period_px = min(height, width) / 4.0
    elif not (math.isfinite(max_period_px) and max_period_px > 2.0):
        raise ValueError(f"max_period_px must be a finite number above 2, not {max_period_px}")

    windowed, spectrum, fy_bins, fx_bins = _band_spectrum(values, weights, max_period_px)
    peak = np.unravel_index(int(np.argmax(spectrum)), spectrum.shape)
    fy0 = float(fy_bins[peak[0], 0])
    fx0 = float(fx_bins[0, peak[1]])
    _check_single_carrier(spectrum, fy_bins, fx_bins, (fy0, fx0), (height, width))

    # Zoomed DTFT over ±1 bin in steps of 1/8 bin: a separable matrix product, cheap.
    steps = np.linspace(-1.0, 1.0, 17)
    fy_grid = fy0 + steps / height
    fx_grid = fx0 + steps / width
    rows = np.exp(-2j * np.pi * np.outer(fy_grid, np.arange(height)))
    cols = np.exp(-2j * np.pi * np.outer(np.arange(width), fx_grid))
    zoom = np.abs(rows @ windowed.astype(np.float64) @ cols)
    m, n = np.unravel_index(int(np.argmax(zoom)), zoom.shape)
    log_zoom = np.log(np.maximum(zoom, np.finfo(np.float64).tiny))

    def vertex(left: float, centre: float, right: float) -> float:
        curvature = left - 2.0 * centre + right
        return 0.0 if curvature >= 0.0 else 0.5 * (left - right) / curvature

    step_y = 1.0 / (8.0 * height)
    step_x = 1.0 / (8.0 * width)
    fy = float(fy_grid[m])
    fx = float(fx_grid[n])
    if 0 < m < len(steps) - 1:
        fy += step_y * vertex(log_zoom[m - 1, n], log_zoom[m, n], log_zoom[m + 1, n])
    if 0 < n < len(steps) - 1:
        fx += step_x * vertex(log_zoom[m, n - 1], log_zoom[m, n], log_zoom[m, n + 1])
    return Carrier((fy, fx))


MIN_CARRIER_STRENGTH = 20.0
"""Least ratio of the carrier's spectral peak to the spectrum's median for
:func:`measure_carrier` to call it a fringe: noise alone reaches 4–5 (the largest of some 10⁵
Rayleigh-distributed bins), a plate lit at 5 % about 150 (docs/notes/demodulation.md)."""

MIN_CARRIER_DOMINANCE = 1.5
"""Least ratio of the carrier's peak to the strongest other component of the spectrum (outside
the peak's main lobe, its harmonics and their mirror images) for :func:`measure_carrier` to
name it the carrier: a plate gives ≈ 5; a surface's phase spreads the fringe over several
frequencies of similar strength, between which the largest is a guess
(docs/notes/demodulation.md)."""

_LOBE_BINS = 3.0  # the Hann window's main lobe spans ±2 bins; a bin more for the peak's offset


def _band_spectrum(values: npt.NDArray[np.float32], weights: npt.NDArray[np.bool_] | None,
                   max_period_px: float,
                   ) -> tuple[npt.NDArray[np.float32], npt.NDArray[Any],
                              npt.NDArray[np.floating[Any]], npt.NDArray[np.floating[Any]]]:
    """The Hann-windowed image less its mean (times ``weights``); the magnitude of its
    ``rfft2`` with periods longer than ``max_period_px`` and the duplicate half of the
    ``fx = 0`` column zeroed; the bins' frequencies ``fy`` (H, 1) and ``fx`` (1, W//2 + 1)."""
    height, width = values.shape
    # Hann window: its side lobes fall fast, so the DC and the image borders do not leak a
    # false peak, and its main lobe is nearly Gaussian (ref. 2 of measure_carrier) for the
    # refinement.
    window = (np.hanning(height + 2)[1:-1, None] * np.hanning(width + 2)[None, 1:-1])
    if weights is None:
        centred = values - np.float32(values.mean())
    else:
        centred = np.where(weights, values - np.float32(values[weights].mean()), 0.0)
        window = window * weights
    windowed = (centred * window).astype(np.float32)
    spectrum = np.abs(scipy.fft.rfft2(windowed, workers=1))
    fy_bins = _signed_frequencies(height)[:, None]
    fx_bins = np.fft.rfftfreq(width)[None, :]
    spectrum[np.hypot(fy_bins, fx_bins) < 1.0 / max_period_px] = 0.0
    # Half of the kx = 0 column duplicates the other (Hermitian symmetry): keep fy > 0 there.
    spectrum[(fy_bins[:, 0] < 0), 0] = 0.0
    return windowed, spectrum, fy_bins, fx_bins


def _peak_ratios(spectrum: npt.NDArray[np.floating[Any]], fy_bins: npt.NDArray[np.floating[Any]],
                 fx_bins: npt.NDArray[np.floating[Any]], peak: tuple[float, float],
                 shape: tuple[int, int]) -> tuple[float, float, float | None]:
    """The spectrum's peak at ``peak`` (cycles/px) over the spectrum's median (its strength),
    over the strongest other component outside its main lobe, its harmonics and their mirror
    images (its dominance; inf without one), and that component's period (px; None).
    ``shape`` is the image's (H, W)."""
    height, width = shape
    strongest = float(np.max(spectrum))
    kept = spectrum[spectrum > 0.0]
    median = float(np.median(kept)) if kept.size else 0.0
    strength = strongest / median if median > 0.0 else 0.0
    others = np.ones(spectrum.shape, dtype=bool)
    for harmonic in (1.0, 2.0, 3.0):
        for sign in (1.0, -1.0):
            distance = np.hypot((fy_bins - sign * harmonic * peak[0]) * height,
                                (fx_bins - sign * harmonic * peak[1]) * width)
            others &= distance > _LOBE_BINS
    rivals = np.where(others, spectrum, 0.0)
    rival = np.unravel_index(int(np.argmax(rivals)), rivals.shape)
    runner_up = float(rivals[rival])
    if runner_up <= 0.0:
        return strength, math.inf, None
    rival_period = 1.0 / max(math.hypot(float(fy_bins[rival[0], 0]),
                                        float(fx_bins[0, rival[1]])), 1e-12)
    return strength, strongest / runner_up, rival_period


def carrier_ratios(image: npt.ArrayLike) -> tuple[float, float]:
    """How clearly ``image`` shows one fringe carrier, as :func:`measure_carrier` judges it:
    the strength and the dominance of its spectrum's peak (see :data:`MIN_CARRIER_STRENGTH`
    and :data:`MIN_CARRIER_DOMINANCE`), over periods up to a quarter of the smaller side."""
    values = np.asarray(checked_image(image), dtype=np.float32)
    _, spectrum, fy_bins, fx_bins = _band_spectrum(values, None, min(values.shape) / 4.0)
    peak = np.unravel_index(int(np.argmax(spectrum)), spectrum.shape)
    strength, dominance, _ = _peak_ratios(
        spectrum, fy_bins, fx_bins, (float(fy_bins[peak[0], 0]), float(fx_bins[0, peak[1]])),
        values.shape)
    return strength, dominance


def _check_single_carrier(spectrum: npt.NDArray[np.floating[Any]],
                          fy_bins: npt.NDArray[np.floating[Any]],
                          fx_bins: npt.NDArray[np.floating[Any]],
                          peak: tuple[float, float], shape: tuple[int, int]) -> None:
    """Raise a ValueError with the reason unless the spectrum's peak at ``peak`` (cycles/px) is
    a fringe carrier: far above the noise (:data:`MIN_CARRIER_STRENGTH`) and alone
    (:data:`MIN_CARRIER_DOMINANCE`). ``spectrum`` is :func:`_band_spectrum`'s of an image of
    ``shape``."""
    strength, dominance, rival_period = _peak_ratios(spectrum, fy_bins, fx_bins, peak, shape)
    period = 1.0 / max(math.hypot(*peak), 1e-12)
    if not strength > MIN_CARRIER_STRENGTH:
        raise ValueError(
            f"image holds no fringe carrier: its strongest component (period {period:.1f} px) "
            f"stands {strength:.1f}× above the spectrum's median, and noise alone reaches 4–5× "
            f"(a fringe needs {MIN_CARRIER_STRENGTH:g}×)")
    if dominance < MIN_CARRIER_DOMINANCE:
        raise ValueError(
            f"image has no single fringe carrier: components of periods {period:.1f} and "
            f"{rival_period:.1f} px are within {dominance:.2f}× of each other (a surface's "
            "phase spreads the fringe over several frequencies; measure the carrier on the flat "
            "reference plate)")


BANDWIDTH = 0.9
"""Default radius of the pass band along the carrier, fraction of ``|f|``."""
TAPER = 0.8
"""Default share of the pass band's radius taken by its raised-cosine edge."""
ELONGATION = 2.0
"""Default width of the pass band across the carrier, relative to its width along it."""


def _pass_band(fy: npt.NDArray[np.floating[Any]], fx: npt.NDArray[np.floating[Any]], outer: float,
               flat: float, direction: tuple[float, float] = (0.0, 1.0),
               elongation: float = 1.0) -> npt.NDArray[np.float32]:
    """Pass band at offsets ``(fy, fx)`` from the carrier: 1 up to ``flat``, raised cosine down to
    0 at ``outer``, along the carrier's unit ``direction``; ``elongation`` times wider across it
    (an ellipse; 1 is a disc). Computed in the offsets' precision."""
    along = fy * direction[0] + fx * direction[1]
    across = (fx * direction[0] - fy * direction[1]) / elongation
    # √(a² + b²), not np.hypot: NumPy's hypot is not vectorised on this machine (AVX2), five
    # times slower on the bend bias's points (docs/notes/speed.md).
    radius = np.sqrt(along * along + across * across)
    if outer > flat:
        edge = np.clip((radius - flat) / (outer - flat), 0.0, 1.0)
        gain = 0.5 * (1.0 + np.cos(np.pi * edge))
    else:
        gain = (radius <= outer).astype(np.float64)
    return gain.astype(np.float32)


def _band_shape(carrier: Carrier, bandwidth: float, taper: float,
                ) -> tuple[float, float, tuple[float, float]]:
    """The pass band's outer and flat-top radii along the carrier (cycles/px) and the carrier's
    unit direction ``(dy, dx)``: what :func:`_pass_band` takes besides the offsets."""
    f = carrier.cycles_per_px
    outer = bandwidth * f
    return outer, (1.0 - taper) * outer, (carrier.frequency[0] / f, carrier.frequency[1] / f)


def band_gain(carrier: Carrier, fy: npt.ArrayLike, fx: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """The default pass band's gain (0–1) for fringes of local frequency ``carrier + (fy, fx)``
    (cycles/px): 1 on its flat top, where :func:`demodulate`'s phase is unbiased."""
    return _pass_band(np.asarray(fy, np.float64), np.asarray(fx, np.float64),
                      *_band_shape(carrier, BANDWIDTH, TAPER), ELONGATION)


def demodulate(image: npt.ArrayLike, carrier: Carrier, *, bandwidth: float = BANDWIDTH,
               taper: float = TAPER, elongation: float = ELONGATION, pad_px: int | None = None,
               workers: int = 1, measure_bends: bool = True) -> Demodulated:
    """Wrapped phase and modulation of a fringe image by the Fourier-transform method.

    The image is continued beyond its borders along the carrier, transformed, multiplied by a
    fixed flat-topped disc pass band with raised-cosine edges around the carrier, transformed
    back and cropped (module docstring). The phase includes the carrier ramp, so for
    ``image = A + B·cos(2π(fy·i + fx·j) + φ(i, j))`` and ``carrier = Carrier((fy, fx))`` the
    wrapped phase is ``2π(fy·i + fx·j) + φ`` modulo 2π and the modulation is ``B``, wherever
    ``φ`` varies slowly enough for its local frequency ``∇φ / 2π`` to stay within the flat
    top.

    With the defaults the band closes at 0.9·|f| along the carrier and twice as far across it
    (an ellipse: a curved surface bends the fringes, which moves their local frequency across
    the carrier more than along it), with a long raised-cosine edge (flat out to 0.18·|f|); it
    halved the phase error of the former disc (docs/notes/demodulation.md). White noise of
    σ DN gives a phase noise of ``σ·sqrt(2·∫|H|² df)/B``.

    Parameters
    ----------
    image : array_like, shape (H, W)
        Fringe image, any real dtype (uint8, uint16, float); finite; at least 8×8 px.
    carrier : Carrier
        The carrier to demodulate with, usually :func:`measure_carrier` of the reference
        image (a fixed carrier suffices, as in the paper). Its sign sets the phase's sign.
    bandwidth : float, optional
        Radius of the pass band along the carrier, where its gain reaches zero, as a fraction
        of ``|f|``, in ``(0, 1)``. The background sits ``|f|`` away, so ``bandwidth`` below 1
        rejects it; larger values pass steeper surfaces (local frequency shifts) and more noise.
    taper : float, optional
        Fraction of the radius taken by the raised-cosine edge, in ``[0, 1]`` (as a Tukey
        window's alpha); the flat top has radius ``(1 − taper)·bandwidth·|f|``.
    elongation : float, optional
        Width of the band across the carrier relative to along it, in ``[1, 4]`` (1: a disc).
    pad_px : int, optional
        Continuation beyond each border, pixels (0: none, and the borders then ring over about
        a fringe period). Default: one fringe period (longer pads gained nothing measurable on
        curved surfaces); the padded size is rounded up to a fast FFT length.
    workers : int, optional
        Threads for ``scipy.fft`` (1 by default: the cameras of a frame set are processed in
        parallel instead).
    measure_bends : bool, optional
        Measure the phase bias of the band's tapered edge where the fringes bend
        (:attr:`Demodulated.bend_bias`, module docstring; on by default; its cost is
        ``bend_correction`` in ``eyeserver bench speed``'s stage table). A window of an
        image: :func:`with_bend_bias`, told where the window lies.

    Returns
    -------
    Demodulated
        ``wrapped_phase`` (float32, radians in ``[−π, π]``) and ``modulation`` (float32, the
        fringe amplitude in the image's units), both of shape ``(H, W)``.

    Raises
    ------
    ValueError
        If ``image``, ``carrier``, ``bandwidth``, ``taper``, ``pad_px`` or ``workers`` is
        invalid (named in the message), including a carrier whose pass band would reach
        beyond Nyquist (``|fy|`` or ``|fx|`` plus ``bandwidth·|f|`` at 0.5 cycles/px or more).

    References
    ----------
    .. [1] M. Takeda, H. Ina and S. Kobayashi, "Fourier-transform method of fringe-pattern
       analysis for computer-based topography and interferometry", J. Opt. Soc. Am. 72(1),
       156–160 (1982). doi:10.1364/JOSA.72.000156
    .. [2] M. Takeda and K. Mutoh, "Fourier transform profilometry for the automatic
       measurement of 3-D object shapes", Appl. Opt. 22(24), 3977–3982 (1983).
       doi:10.1364/AO.22.003977
    .. [3] C. Roddier and F. Roddier, "Interferogram analysis using Fourier transform
       techniques", Appl. Opt. 26(9), 1668–1673 (1987). doi:10.1364/AO.26.001668 (the border
       problem; fringes extrapolated beyond the aperture).
    .. [4] Via et al., Phys. Imaging Radiat. Oncol. (2023), doi:10.1016/j.phro.2023.100517
       (the clinical method this follows: a fixed filter on a fixed carrier suffices).

    Examples
    --------
    >>> import numpy as np
    >>> i, j = np.mgrid[0:64, 0:80]
    >>> fringes = 40 + 30 * np.cos(2 * np.pi * 0.1 * j + 1.0)
    >>> result = demodulate(fringes, Carrier((0.0, 0.1)))
    >>> round(float(result.wrapped_phase[10, 0]), 3), round(float(result.modulation[10, 40]), 1)
    (1.0, 30.0)
    """
    values = checked_image(image)
    if not isinstance(carrier, Carrier):
        raise ValueError(f"carrier must be a Carrier, not {type(carrier).__name__}")
    if isinstance(bandwidth, bool) or not (isinstance(bandwidth, numbers.Real)
                                           and 0.0 < bandwidth < 1.0):
        raise ValueError(f"bandwidth must be in (0, 1) (a fraction of |f|), not {bandwidth!r}")
    if isinstance(taper, bool) or not (isinstance(taper, numbers.Real) and 0.0 <= taper <= 1.0):
        raise ValueError(f"taper must be in [0, 1], not {taper!r}")
    if isinstance(elongation, bool) or not (isinstance(elongation, numbers.Real)
                                            and 1.0 <= elongation <= 4.0):
        raise ValueError(f"elongation must be in [1, 4], not {elongation!r}")
    if pad_px is not None and (not isinstance(pad_px, numbers.Integral)
                               or isinstance(pad_px, bool) or pad_px < 0):
        raise ValueError(f"pad_px must be a non-negative integer, not {pad_px!r}")
    if not isinstance(workers, numbers.Integral) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be a positive integer, not {workers!r}")
    if not isinstance(measure_bends, bool):
        raise ValueError(f"measure_bends must be True or False, not {measure_bends!r}")
    fy0, fx0 = carrier.frequency
    outer = bandwidth * carrier.cycles_per_px
    reach = outer * float(elongation)  # the band's extent across the carrier bounds the box
    if abs(fy0) + reach >= 0.5 or abs(fx0) + reach >= 0.5:
        raise ValueError(f"carrier {carrier.frequency} is too close to Nyquist for bandwidth "
                         f"{bandwidth}: its pass band would cross 0.5 cycles/px")
    height, width = values.shape
    pad_px = math.ceil(carrier.period_px) if pad_px is None else int(pad_px)
    workers = int(workers)
    bandwidth = float(bandwidth)
    taper = float(taper)

    padded_h = _padded_length(height, pad_px, fy0) if pad_px else height
    padded_w = _padded_length(width, pad_px, fx0) if pad_px else width
    padded = np.empty((padded_h, padded_w), dtype=np.float32)
    # The mean goes first: the continuation and the float32 transforms then work on the fringe.
    # (cv2.mean and an in-place subtraction: faster than numpy's float64 mean and casting
    # subtraction, docs/notes/speed.md.)
    inner = padded[:height, :width]
    inner[...] = values
    inner -= np.float32(cv2.mean(inner)[0])
    _extend(padded, height, width, fy0, fx0)

    # Rows: real transform of everything; columns: only those the band touches. Bins left of
    # fx = 0 (a carrier close to horizontal) are the conjugates of their mirror images.
    row_spectrum = scipy.fft.rfft(padded, axis=1, workers=workers)
    band_kx, weights = _band(padded_h, padded_w, carrier, bandwidth, taper, float(elongation))
    band = scipy.fft.fft(row_spectrum[:, np.abs(band_kx)], axis=0, workers=workers,
                         overwrite_x=True)
    negative = band_kx < 0
    if negative.any():
        mirrored_rows = np.mod(-np.arange(padded_h), padded_h)
        band[:, negative] = np.conj(band[mirrored_rows][:, negative])
    band *= weights
    band = scipy.fft.ifft(band, axis=0, workers=workers, overwrite_x=True)
    columns = np.zeros((height, padded_w), dtype=np.complex64)
    columns[:, np.mod(band_kx, padded_w)] = band[:height]
    analytic = scipy.fft.ifft(columns, axis=1, workers=workers, overwrite_x=True)[:, :width]

    # Phase and magnitude from contiguous copies of the parts: faster than np.angle's and
    # np.abs's passes over the complex array's strided views (docs/notes/speed.md).
    real, imaginary = np.ascontiguousarray(analytic.real), np.ascontiguousarray(analytic.imag)
    wrapped_phase = angle(imaginary, real)
    # The band holds one side of the spectrum: its magnitude is B/2.
    modulation = np.asarray(cv2.magnitude(real, imaginary), dtype=np.float32)
    modulation *= np.float32(2.0)
    result = Demodulated(wrapped_phase=wrapped_phase, modulation=modulation)
    if measure_bends:
        result = with_bend_bias(result, carrier, bandwidth=bandwidth, taper=taper,
                                elongation=float(elongation))
    return result


def with_bend_bias(result: Demodulated, carrier: Carrier, *, bandwidth: float = BANDWIDTH,
                   taper: float = TAPER, elongation: float = ELONGATION,
                   origin: tuple[int, int] = (0, 0),
                   strong_modulation: float | None = None) -> Demodulated:
    """``result`` (of :func:`demodulate` with ``measure_bends=False`` and the same band) with its
    :attr:`~Demodulated.bend_bias` measured: what ``measure_bends=True`` adds, on its own so
    ``eyeserver bench speed`` can time it apart from the Fourier-transform method itself, and
    so a window of an image can be given the whole image's bias.

    ``origin``: where the image's pixel ``(0, 0)`` lies in the camera's whole image,
    ``(column, row)`` (a window's corner); the correction averages over blocks of the whole
    image's grid. ``strong_modulation``: the whole image's strong fringes' modulation (the
    reconstruction's :func:`~eyeserver.pipeline.reconstruct.fringe_strength`), where the fringe
    field ends at :data:`_WEAK_FRINGE` of it; None: this image's own 95th percentile. Given
    both, a window's bias is the whole image's away from the window's border.

    Raises
    ------
    ValueError
        An ``origin`` that is no pair of non-negative integers, or a ``strong_modulation`` that
        is not a finite number ≥ 0.
    """
    if not (isinstance(origin, tuple) and len(origin) == 2
            and all(isinstance(o, numbers.Integral) and not isinstance(o, bool) and o >= 0
                    for o in origin)):
        raise ValueError(f"origin must be a (column, row) pair of non-negative integers, "
                         f"not {origin!r}")
    if strong_modulation is not None and not (
            isinstance(strong_modulation, numbers.Real) and not isinstance(strong_modulation, bool)
            and math.isfinite(strong_modulation) and strong_modulation >= 0):
        raise ValueError(f"strong_modulation must be a non-negative number, not "
                         f"{strong_modulation!r}")
    bias = _bend_bias(result.wrapped_phase, result.modulation, carrier,
                      *_band_shape(carrier, bandwidth, taper), elongation,
                      (int(origin[0]), int(origin[1])), strong_modulation)
    return Demodulated(result.wrapped_phase, result.modulation, bias)


@functools.lru_cache(maxsize=64)
def _band(padded_h: int, padded_w: int, carrier: Carrier, bandwidth: float, taper: float,
          elongation: float) -> tuple[npt.NDArray[np.intp], F32]:
    """The pass band on a padded image's transform: the signed column bins it touches and its
    gain on every row of those columns (zero on the rows it does not touch). It depends on the
    sizes and the carrier only, so it is made once per window shape (docs/notes/speed.md)."""
    fy0, fx0 = carrier.frequency
    outer, flat, (dy, dx) = _band_shape(carrier, bandwidth, taper)
    # The ellipse's extent along each axis: radius ``outer`` along the carrier, ``elongation``
    # times that across it.
    reach_x = outer * math.hypot(dx, elongation * dy)
    reach_y = outer * math.hypot(dy, elongation * dx)
    band_kx = np.arange(math.floor((fx0 - reach_x) * padded_w),
                        math.ceil((fx0 + reach_x) * padded_w) + 1)
    band_kx = band_kx[np.abs(band_kx / padded_w - fx0) < reach_x]
    fy_offsets = _signed_frequencies(padded_h) - fy0
    band_rows = np.abs(fy_offsets) < reach_y
    weights = np.zeros((padded_h, band_kx.size), np.float32)
    weights[band_rows] = _pass_band(fy_offsets[band_rows, None],
                                    (band_kx / padded_w)[None, :] - fx0, outer, flat, (dy, dx),
                                    elongation)
    for array in (band_kx, weights):
        array.flags.writeable = False  # shared by every call
    return band_kx, weights


BEND_SMOOTHING_PERIODS = 0.5
"""The Gaussian's σ, in carrier periods, over which :func:`demodulate` measures how the fringes
bend before correcting their phase for the band's edge (module docstring)."""

BEND_EDGE_PERIODS = 1.5
"""No bend bias is taken within this many carrier periods of where the fringe field ends: the
averages' reach (twice :data:`BEND_SMOOTHING_PERIODS`) and the band's own blur of the edge."""

_MIN_GAIN = 0.2  # below this the band passes too little of a fringe to correct its phase
_WEAK_FRINGE = 0.25  # the fringe field ends below this share of its strong modulation
# (reconstruct.MODULATION_FRACTION masks there too)


def _gradient_at(values: F64, spacing: int, rows: npt.NDArray[np.intp],
                 columns: npt.NDArray[np.intp]) -> tuple[F64, F64]:
    """``values``' derivatives along the rows and the columns at the points ``(rows, columns)``
    (grid ``spacing``): :func:`numpy.gradient`'s (central inside, one-sided at the borders),
    taken at those points only rather than over the whole grid."""
    height, width = values.shape
    up, down = np.minimum(rows + 1, height - 1), np.maximum(rows - 1, 0)
    right, left = np.minimum(columns + 1, width - 1), np.maximum(columns - 1, 0)
    along_rows = (values[up, columns] - values[down, columns]) / ((up - down) * spacing)
    along_columns = (values[rows, right] - values[rows, left]) / ((right - left) * spacing)
    return along_rows, along_columns


def _bend_bias(wrapped_phase: F32, modulation: F32, carrier: Carrier, outer: float, flat: float,
               direction: tuple[float, float], elongation: float,
               origin: tuple[int, int] = (0, 0),
               strong_modulation: float | None = None) -> F32 | None:
    """The phase the pass band's edge adds where the fringes bend (module docstring); None where
    every local frequency lies on the flat top (no bias). ``origin`` and ``strong_modulation``:
    :func:`with_bend_bias`'s."""
    height, width = wrapped_phase.shape
    if height < 3 or width < 3:
        return None
    sigma = BEND_SMOOTHING_PERIODS * carrier.period_px
    # The bend varies over periods, not pixels: it is measured on a grid ``factor`` times
    # coarser (the averages of blocks of ``factor × factor`` pixels) and the bias interpolated
    # back — 16 times fewer pixels to smooth. The blocks are the whole image's (``origin``),
    # the arrays padded to whole blocks by their edge values: a window's bias is then the whole
    # image's, and OpenCV's area average takes its fast path for a whole ratio, 6 times as fast
    # as for a fractional one (docs/notes/speed.md).
    factor = max(1, int(sigma // 3))
    pad_left, pad_top = origin[0] % factor, origin[1] % factor
    coarse = (max(3, -(-(width + pad_left) // factor)), max(3, -(-(height + pad_top) // factor)))
    padded_w, padded_h = coarse[0] * factor, coarse[1] * factor
    pad_right, pad_bottom = padded_w - width - pad_left, padded_h - height - pad_top
    # The local fringe frequency (rad/px, carrier included) from wrapped central differences,
    # and the modulation's log, averaged over part of a period. (Weighting the average by the
    # modulation, so as not to take a bend from the noise beyond an outline, corrected the
    # simulated eye's sclera less well, measured without the fading term and the edge rule: the
    # radius 0.08 and 0.10 mm too small on 12- and 13-mm globes, against 0.02 and 0.04.)
    slope_y = np.empty_like(wrapped_phase)
    slope_x = np.empty_like(wrapped_phase)
    # (cv2.subtract into the views: NumPy's subtraction of the column-shifted views took four
    # times as long.)
    cv2.subtract(wrapped_phase[2:], wrapped_phase[:-2], dst=slope_y[1:-1])
    slope_y[0], slope_y[-1] = slope_y[1], slope_y[-2]
    cv2.subtract(wrapped_phase[:, 2:], wrapped_phase[:, :-2], dst=slope_x[:, 1:-1])
    slope_x[:, 0], slope_x[:, -1] = slope_x[:, 1], slope_x[:, -2]

    def padded(values: F32) -> F32:
        # To whole blocks of the whole image's grid, by the edge values.
        if not (pad_top or pad_bottom or pad_left or pad_right):
            return values
        return np.asarray(cv2.copyMakeBorder(values, pad_top, pad_bottom, pad_left, pad_right,
                                             cv2.BORDER_REPLICATE), dtype=np.float32)

    def smoothed(values: F32) -> F64:
        # (Halved for the central difference's step of two pixels after the average: the
        # same, on 16 times fewer pixels.)
        small = 0.5 * np.asarray(cv2.resize(wrap(padded(values)), coarse,
                                            interpolation=cv2.INTER_AREA), dtype=np.float32)
        return np.asarray(cv2.GaussianBlur(small, (0, 0), sigma / factor), dtype=np.float64)

    slope_y64, slope_x64 = smoothed(slope_y), smoothed(slope_x)
    # Offsets of the local frequency from the carrier, cycles/px; only pixels off the flat top
    # (within a finite-difference step of its edge) can carry a bias.
    fy0, fx0 = carrier.frequency
    offset_y = slope_y64 / _TWO_PI - fy0
    offset_x = slope_x64 / _TWO_PI - fx0
    step = 0.05 * outer
    along = offset_y * direction[0] + offset_x * direction[1]
    across = (offset_x * direction[0] - offset_y * direction[1]) / elongation
    limit = flat - 2.0 * step
    off_top = (along * along + across * across > limit * limit if limit > 0
               else np.ones(along.shape, bool))
    if not off_top.any():
        return None
    # Near where the fringe ends (an outline, the dark cornea, a shadow) neither bend nor fading
    # is a smooth surface's: no bias is taken there (BEND_EDGE_PERIODS), so it is computed only
    # off the flat top and inside the fringe field.
    fringe = np.asarray(cv2.resize(padded(modulation), coarse, interpolation=cv2.INTER_AREA))
    strong = (float(np.percentile(fringe, 95)) if strong_modulation is None
              else strong_modulation)
    present = (fringe > _WEAK_FRINGE * strong).astype(np.uint8)
    reach = max(1, round(BEND_EDGE_PERIODS * carrier.period_px / factor))
    inside = cv2.erode(present, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8),
                       borderType=cv2.BORDER_REPLICATE)
    # The band's gain: 1 on the flat top, so evaluated off it only.
    centre = np.ones(offset_y.shape)
    centre[off_top] = _pass_band(offset_y[off_top].astype(np.float32),
                                 offset_x[off_top].astype(np.float32), outer, flat, direction,
                                 elongation)
    rows, columns = np.nonzero(off_top & (inside != 0))
    # The band's derivatives by finite differences over ``step``, not in closed form: the raised
    # cosine's curvature jumps at the flat top's edge, and the differences average the jump as
    # the fringes' own spread of frequencies does (the closed form corrected bent fringes less
    # well, docs/notes/speed.md). All eight shifted evaluations in one float32 pass.
    shifts = np.array([(step, 0.0), (-step, 0.0), (0.0, step), (0.0, -step),
                       (step, step), (step, -step), (-step, step), (-step, -step)])
    gains = _pass_band((offset_y[rows, columns][None, :] + shifts[:, :1]).astype(np.float32),
                       (offset_x[rows, columns][None, :] + shifts[:, 1:]).astype(np.float32),
                       outer, flat, direction, elongation).astype(np.float64)
    here = centre[rows, columns]
    up, down, right, left = gains[:4]
    gain_y, gain_x = (up - down) / (2.0 * step), (right - left) / (2.0 * step)
    gain_yy = (up - 2.0 * here + down) / step**2
    gain_xx = (right - 2.0 * here + left) / step**2
    gain_xy = (gains[4] - gains[5] - gains[6] + gains[7]) / (4.0 * step**2)
    # The phase's second derivatives (rad/px²) from the smoothed local frequency, and the
    # fringe amplitude's relative gradient (1/px): the modulation's, less the band's own
    # fading of it (the modulation is the amplitude times the gain).
    curve_yy, curve_yx = _gradient_at(slope_y64, factor, rows, columns)
    curve_xy, curve_xx = _gradient_at(slope_x64, factor, rows, columns)
    # (The log of the block averages, not the average of the logs: the same where the fringe
    # is smooth, and the edge rule above drops the rest; a log of the full image costs more.)
    log_fringe = np.log(np.maximum(fringe, np.float32(1e-3)))
    fading_y, fading_x = _gradient_at(
        np.asarray(cv2.GaussianBlur(log_fringe, (0, 0), sigma / factor), dtype=np.float64)
        - np.log(np.maximum(centre, _MIN_GAIN)), factor, rows, columns)
    bend = curve_yy * gain_yy + (curve_yx + curve_xy) * gain_xy + curve_xx * gain_xx
    values = -((fading_y * gain_y + fading_x * gain_x) / _TWO_PI
               + bend / (8.0 * math.pi**2)) / np.maximum(here, _MIN_GAIN)
    values[here < _MIN_GAIN] = 0.0
    bias = np.zeros(offset_y.shape, np.float32)
    bias[rows, columns] = values
    fine = cv2.resize(bias, (padded_w, padded_h), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(fine[pad_top:pad_top + height, pad_left:pad_left + width],
                                dtype=np.float32)


def phase_difference(wrapped_object: npt.ArrayLike, wrapped_reference: npt.ArrayLike) -> F32:
    """Wrapped difference of two phase maps, radians in ``(−π, π]``.

    Parameters
    ----------
    wrapped_object, wrapped_reference : array_like, same shape
        Phases in radians (any range; typically :attr:`Demodulated.wrapped_phase` of the
        object and of the reference plane, demodulated with the same carrier). NaN propagates.

    Returns
    -------
    ndarray of float32
        ``wrapped_object − wrapped_reference`` wrapped into ``(−π, π]``: the carrier cancels and
        what remains is the phase the surface adds (docs/design.md §4 step 3).

    Raises
    ------
    ValueError
        If the shapes differ or an input is not real.

    References
    ----------
    .. [1] M. Takeda and K. Mutoh, "Fourier transform profilometry for the automatic
       measurement of 3-D object shapes", Appl. Opt. 22(24), 3977–3982 (1983).
       doi:10.1364/AO.22.003977

    Examples
    --------
    >>> import numpy as np
    >>> round(float(phase_difference(np.array([3.0]), np.array([-3.0]))[0]), 4)  # 6 rad wraps
    -0.2832
    """
    obj = np.asarray(wrapped_object)
    ref = np.asarray(wrapped_reference)
    for name, array in (("wrapped_object", obj), ("wrapped_reference", ref)):
        if array.dtype == np.bool_ or not (np.issubdtype(array.dtype, np.integer)
                                           or np.issubdtype(array.dtype, np.floating)):
            raise ValueError(f"{name} must hold real numbers, not {array.dtype}")
    if obj.shape != ref.shape:
        raise ValueError(f"wrapped_object and wrapped_reference must have the same shape, "
                         f"not {obj.shape} and {ref.shape}")
    difference = np.asarray(np.subtract(obj, ref, dtype=np.float32))
    # −π, and whatever float32 rounding leaves beyond ±π, folds to +π.
    wrap(difference)
    np.putmask(difference, difference <= -_PI32, _PI32)
    np.minimum(difference, _PI32, out=difference)
    return np.asarray(difference, dtype=np.float32)


def border_mask(shape: tuple[int, ...], margin: int | tuple[int, int]) -> npt.NDArray[np.bool_]:
    """True except within ``margin`` pixels of the image border, where the FTM's phase is least
    trustworthy (about a fringe period, docs/design.md §4 step 1); ``(rows, columns)``: a margin
    of its own at the top and bottom and at the sides."""
    rows, columns = (margin, margin) if isinstance(margin, int) else margin
    if rows < 0 or columns < 0:
        raise ValueError(f"margin must not be negative, not {margin}")
    mask = np.zeros(shape[:2], dtype=bool)
    mask[rows:shape[0] - rows, columns:shape[1] - columns] = True
    return mask
