"""Phase to height: the Du & Wang (2007) rational model for reference-subtracted phase.

docs/design.md §4 step 5. Per camera, the height of the surface seen through undistorted normalised
coordinates ``(x, y)`` with phase ``Δφ`` (radians, relative to the reference plane) is

    Z = (c0 + c1·Δφ + (c2 + c3·Δφ)·i + (c4 + c5·Δφ)·j)
        / (1 + d1·Δφ + (d2 + d3·Δφ)·i + (d4 + d5·Δφ)·j)

with ``i ↔ y`` and ``j ↔ x``: eleven coefficients, a free numerator constant and ``d0 = 1``.
Du & Wang fix the numerator's constant instead, which suits absolute (carrier-inclusive) phase
but cannot express Z = 0 at Δφ = 0; with reference-subtracted phase the free ``c0`` is the
well-posed choice (0.036 mm against 4.3 mm RMSE: docs/notes/design-measurements.md).

Why the form holds. A pinhole camera's ray through ``(x, y)`` meets the plane Z at a point whose
homogeneous coordinates are affine in ``(x, y)`` and in Z; a pinhole projector's straight fringes
make the *absolute* phase a ratio of two affine functions of that point. Solving for Z gives
exactly the rational form above in the absolute phase, provided ``(x, y)`` are undistorted (on
coordinates that still carry a lens's 1–4 px of edge distortion it leaves 0.015–0.05 mm).
Subtracting the reference plane's phase ``φ_ref(x, y)`` (itself a ratio of affine functions)
turns the identity into an approximation: on the simulated rigs it leaves 0.2–1.9 µm RMS over
−10…+25 mm, far below the phase noise, and then hardly depends on the distortion. Undistorted
coordinates remain the contract all the same; the transversal mapping (step 6) needs them.

Numerics. In raw units (x, y ≈ 0.1, Δφ ≈ 40 rad, Z ≈ 30 mm) the columns of the Jacobian differ by
orders of magnitude, so the module centres and scales x, y, Δφ and Z before fitting and stores
those constants with the coefficients; an affine change of i, j, Δφ and Z keeps the model's form,
so the eleven normalised coefficients describe the same family of surfaces. The fit multiplies
the equation out, ``Z·(1 + d1·Δφ + …) = c0 + c1·Δφ + …``, which is linear in the coefficients
and gives an excellent start, then polishes the true height residual with Levenberg–Marquardt
(MINPACK through ``scipy.optimize.least_squares``) and an analytic Jacobian.

The model is linear in Δφ for fixed (x, y, Z), so :meth:`PhaseHeightModel.phase` inverts it in
closed form: the phase a camera should see for a given 3-D point (what multi-view fringe-order
selection needs, docs/design.md §4 step 4).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from eyeserver.core.types import F64

ArrayLike = npt.ArrayLike

MODEL_NAME = "du-wang-2007-reference-subtracted"
"""The ``model`` key of :meth:`PhaseHeightModel.to_dict`."""

N_COEFFICIENTS = 11
"""``c0 … c5`` and ``d1 … d5``."""

COEFFICIENT_NAMES = ("c0", "c1", "c2", "c3", "c4", "c5", "d1", "d2", "d3", "d4", "d5")
"""Order of :attr:`PhaseHeightModel.coefficients`."""

_NORMALISATION_KEYS = ("x_centre", "x_scale", "y_centre", "y_scale",
                       "dphi_centre", "dphi_scale", "z_centre", "z_scale")


@dataclass(frozen=True)
class PhaseHeightModel:
    """One camera's fitted phase-to-height model.

    The coefficients act on normalised variables: ``x̂ = (x − x_centre)/x_scale`` (likewise ŷ and
    Δφ̂) give ``Ẑ``, and ``Z = z_centre + z_scale·Ẑ``. Build it with :func:`fit_phase_height` or
    :meth:`from_dict`.

    Attributes
    ----------
    coefficients : tuple of 11 float
        ``(c0, c1, c2, c3, c4, c5, d1, d2, d3, d4, d5)`` of the normalised model (see
        :data:`COEFFICIENT_NAMES`); ``i`` is ŷ, ``j`` is x̂.
    x_centre, x_scale, y_centre, y_scale : float
        Normalisation of the undistorted normalised camera coordinates (dimensionless).
    dphi_centre, dphi_scale : float
        Normalisation of the reference-subtracted phase, radians.
    z_centre, z_scale : float
        Normalisation of the height, mm.
    z_range : tuple of 2 float
        Lowest and highest Z (mm) of the calibration data: the volume where the model is valid.

    Raises
    ------
    ValueError
        If a coefficient or constant is not finite, a scale is not positive, there are not eleven
        coefficients, or ``z_range`` is not increasing; the message names the field.
    """

    coefficients: tuple[float, ...]
    x_centre: float
    x_scale: float
    y_centre: float
    y_scale: float
    dphi_centre: float
    dphi_scale: float
    z_centre: float
    z_scale: float
    z_range: tuple[float, float]

    def __post_init__(self) -> None:
        coefficients = tuple(float(c) for c in self.coefficients)
        if len(coefficients) != N_COEFFICIENTS:
            raise ValueError(f"coefficients: expected {N_COEFFICIENTS} values, "
                             f"got {len(coefficients)}")
        if not all(math.isfinite(c) for c in coefficients):
            raise ValueError("coefficients: every value must be finite")
        object.__setattr__(self, "coefficients", coefficients)
        for key in _NORMALISATION_KEYS:
            value = float(getattr(self, key))
            if not math.isfinite(value):
                raise ValueError(f"{key}: must be finite, not {value}")
            if key.endswith("_scale") and value <= 0:
                raise ValueError(f"{key}: must be positive, not {value}")
            object.__setattr__(self, key, value)
        z_range = tuple(float(v) for v in self.z_range)
        if (len(z_range) != 2 or not all(math.isfinite(v) for v in z_range)
                or z_range[0] >= z_range[1]):
            raise ValueError(f"z_range: must be two finite increasing heights, not {z_range}")
        object.__setattr__(self, "z_range", z_range)

    # --- evaluation ------------------------------------------------------------------------

    def _normalise(self, x: ArrayLike, y: ArrayLike, third: ArrayLike, third_name: str,
                   third_centre: float, third_scale: float) -> tuple[F64, F64, F64]:
        arrays = [np.asarray(a, dtype=np.float64) for a in (x, y, third)]
        try:
            xa, ya, ta = np.broadcast_arrays(*arrays)
        except ValueError:
            raise ValueError(f"x, y and {third_name} must broadcast together, not shapes "
                             f"{[a.shape for a in arrays]}") from None
        return ((xa - self.x_centre) / self.x_scale, (ya - self.y_centre) / self.y_scale,
                (ta - third_centre) / third_scale)

    def height(self, x: ArrayLike, y: ArrayLike, dphi: ArrayLike) -> F64:
        """Height Z (mm) of the surface seen at ``(x, y)`` with phase ``dphi``.

        Parameters
        ----------
        x, y : array_like
            Undistorted normalised camera coordinates, ``x = (u_undist − cx)/fx`` and
            ``y = (v_undist − cy)/fy``; any shapes that broadcast together with ``dphi``.
        dphi : array_like
            Phase relative to the reference plane, radians (unwrapped, absolute fringe order).

        Returns
        -------
        ndarray of float64
            Z in mm, the broadcast shape; ``inf``/NaN where the model's denominator vanishes
            (far outside the calibrated volume).

        Examples
        --------
        >>> model = PhaseHeightModel((10.0, 2.0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
        ...                          0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, (-10.0, 25.0))
        >>> model.height(0.0, 0.0, [0.0, 1.0]).tolist()
        [10.0, 12.0]
        """
        xn, yn, pn = self._normalise(x, y, dphi, "dphi", self.dphi_centre, self.dphi_scale)
        numerator, denominator = _numerator_denominator(np.asarray(self.coefficients), xn, yn, pn)
        with np.errstate(divide="ignore", invalid="ignore"):
            zn = numerator / denominator
        return np.asarray(self.z_centre + self.z_scale * zn, dtype=np.float64)

    def phase(self, x: ArrayLike, y: ArrayLike, z: ArrayLike) -> F64:
        """Phase (radians, relative to the reference plane) that ``(x, y)`` sees at height ``z``.

        The closed-form inverse of :meth:`height`: for fixed ``(x, y, Z)`` the model is linear in
        Δφ, ``Δφ̂ = (A0 − Ẑ·B0) / (Ẑ·B1 − A1)`` with ``A0 = c0 + c2·i + c4·j``,
        ``A1 = c1 + c3·i + c5·j``, ``B0 = 1 + d2·i + d4·j``, ``B1 = d1 + d3·i + d5·j``.

        Parameters
        ----------
        x, y : array_like
            Undistorted normalised camera coordinates (as in :meth:`height`).
        z : array_like
            Heights in mm; any shape that broadcasts with ``x`` and ``y``.

        Returns
        -------
        ndarray of float64
            Δφ in radians, the broadcast shape; ``inf``/NaN where no phase gives that height
            (the ray's Z no longer depends on Δφ).
        """
        xn, yn, zn = self._normalise(x, y, z, "z", self.z_centre, self.z_scale)
        c0, c1, c2, c3, c4, c5, d1, d2, d3, d4, d5 = self.coefficients
        a0 = c0 + c2 * yn + c4 * xn
        a1 = c1 + c3 * yn + c5 * xn
        b0 = 1.0 + d2 * yn + d4 * xn
        b1 = d1 + d3 * yn + d5 * xn
        with np.errstate(divide="ignore", invalid="ignore"):
            pn = (a0 - zn * b0) / (zn * b1 - a1)
        return np.asarray(self.dphi_centre + self.dphi_scale * pn, dtype=np.float64)

    # --- plain data --------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """The model as plain JSON types (str, float, list), for calibration artefacts."""
        data: dict[str, Any] = {"model": MODEL_NAME, "coefficients": list(self.coefficients)}
        for key in _NORMALISATION_KEYS:
            data[key] = float(getattr(self, key))
        data["z_range"] = list(self.z_range)
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PhaseHeightModel:
        """Rebuild a model from :meth:`to_dict`'s output.

        Raises
        ------
        ValueError
            If ``data`` is not a mapping, a key is missing or unknown, or a value has the wrong
            type or is out of range; the message names the key.
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"data: expected a mapping, not {type(data).__name__}")
        expected = {"model", "coefficients", "z_range", *_NORMALISATION_KEYS}
        unknown = sorted(str(k) for k in data if k not in expected)
        if unknown:
            raise ValueError(f"{unknown[0]}: unknown key")
        for key in sorted(expected):
            if key not in data:
                raise ValueError(f"{key}: missing")
        if data["model"] != MODEL_NAME:
            raise ValueError(f"model: expected {MODEL_NAME!r}, not {data['model']!r}")
        coefficients = _float_list(data["coefficients"], "coefficients", N_COEFFICIENTS)
        z_range = _float_list(data["z_range"], "z_range", 2)
        constants = {key: _float(data[key], key) for key in _NORMALISATION_KEYS}
        return cls(coefficients=tuple(coefficients), z_range=(z_range[0], z_range[1]),
                   **constants)


def _float(value: Any, key: str) -> float:
    # bool is an int subclass but never a meaningful coefficient.
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{key}: expected a number, not {type(value).__name__}")
    result = float(value)
    if not math.isfinite(result):
        raise ValueError(f"{key}: must be finite, not {result}")
    return result


def _float_list(value: Any, key: str, length: int) -> list[float]:
    if not isinstance(value, list | tuple):
        raise ValueError(f"{key}: expected a list of {length} numbers, not {type(value).__name__}")
    if len(value) != length:
        raise ValueError(f"{key}: expected {length} numbers, got {len(value)}")
    return [_float(v, f"{key}[{n}]") for n, v in enumerate(value)]


@dataclass(frozen=True, eq=False)
class FitResult:
    """What :func:`fit_phase_height` returns.

    Attributes
    ----------
    model : PhaseHeightModel
        The fitted model.
    residual_mm : ndarray of float64
        ``Z_model − Z`` for every input point, the inputs' shape, mm.
    rmse_mm : float
        Root mean square of ``residual_mm``.
    median_abs_mm, iqr_mm : float
        Median and interquartile range of ``|residual_mm|`` (the paper's and docs/design.md
        §6's figures).
    condition_number : float
        2-norm condition number of the Jacobian of the normalised height residual at the solution
        (over the fitted subsample): how well the data pin the eleven coefficients down.
    evaluations : int
        Residual evaluations Levenberg–Marquardt needed from the linear start.
    """

    model: PhaseHeightModel
    residual_mm: F64
    rmse_mm: float
    median_abs_mm: float
    iqr_mm: float
    condition_number: float
    evaluations: int


def _numerator_denominator(theta: F64, xn: F64, yn: F64, pn: F64) -> tuple[F64, F64]:
    c0, c1, c2, c3, c4, c5, d1, d2, d3, d4, d5 = theta
    numerator = c0 + c1 * pn + (c2 + c3 * pn) * yn + (c4 + c5 * pn) * xn
    denominator = 1.0 + d1 * pn + (d2 + d3 * pn) * yn + (d4 + d5 * pn) * xn
    return numerator, denominator


def _numerator_basis(xn: F64, yn: F64, pn: F64) -> F64:
    """Columns multiplying ``c0 … c5`` (those of ``d1 … d5`` are the same without the first)."""
    return np.stack([np.ones_like(pn), pn, yn, pn * yn, xn, pn * xn], axis=1)


def _linear_start(xn: F64, yn: F64, pn: F64, zn: F64) -> F64:
    """Coefficients minimising the multiplied-out residual ``num − Z·(den − 1) − Z``.

    This algebraic residual weights each point by its denominator, so it is not the height
    residual, but with the denominator close to 1 over the calibrated volume it lands within
    a few LM steps of it (cold starts take 10× longer or find a wrong minimum:
    docs/notes/design-measurements.md).
    """
    basis = _numerator_basis(xn, yn, pn)
    design = np.concatenate([basis, -zn[:, None] * basis[:, 1:]], axis=1)
    theta, *_ = np.linalg.lstsq(design, zn, rcond=None)
    return np.asarray(theta, dtype=np.float64)


def _jacobian(theta: F64, xn: F64, yn: F64, pn: F64) -> F64:
    """∂Ẑ/∂θ: ``basis/den`` for the c's, ``−Ẑ·basis/den`` for the d's."""
    numerator, denominator = _numerator_denominator(theta, xn, yn, pn)
    basis = _numerator_basis(xn, yn, pn) / denominator[:, None]
    return np.concatenate([basis, -(numerator / denominator)[:, None] * basis[:, 1:]], axis=1)


def _refine(theta0: F64, xn: F64, yn: F64, pn: F64, zn: F64) -> tuple[F64, int]:
    """Levenberg–Marquardt on the normalised height residual from ``theta0``."""
    def residual(theta: F64) -> F64:
        numerator, denominator = _numerator_denominator(theta, xn, yn, pn)
        return np.asarray(numerator / denominator - zn, dtype=np.float64)

    def jacobian(theta: F64) -> F64:
        return _jacobian(theta, xn, yn, pn)

    solution = least_squares(residual, theta0, jac=jacobian, method="lm",
                             xtol=1e-12, ftol=1e-12, gtol=1e-12)
    theta = np.asarray(solution.x, dtype=np.float64)
    # A failed polish (non-finite, or worse than the start) must not replace a good start.
    if not np.all(np.isfinite(theta)) or (
            np.sum(residual(theta) ** 2) > np.sum(residual(theta0) ** 2)):
        theta = theta0
    return theta, int(solution.nfev)


def _as_float_array(value: ArrayLike, name: str) -> F64:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be an array of numbers") from None
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: every value must be finite (mask invalid pixels first)")
    return array


def _centre_scale(values: F64, name: str) -> tuple[float, float]:
    centre = float(np.mean(values))
    scale = float(np.std(values))
    if not scale > 1e-12 * max(1.0, abs(centre)):
        raise ValueError(f"{name}: the values do not vary, so the model cannot be fitted")
    return centre, scale


def fit_phase_height(x: ArrayLike, y: ArrayLike, dphi: ArrayLike, z: ArrayLike, *,
                     max_points: int = 200_000,
                     rng: np.random.Generator | int | None = None) -> FitResult:
    """Fit the Du & Wang phase-to-height model to one camera's calibration stack.

    Parameters
    ----------
    x, y : array_like
        Undistorted normalised camera coordinates of every valid sample,
        ``x = (u_undist − cx)/fx``, ``y = (v_undist − cy)/fy``; same shape as ``z``.
    dphi : array_like
        Unwrapped phase relative to the reference plane, radians, same shape. Every plane's
        fringe order must be right: one plane off by 2π ruins the fit (millimetres of RMSE).
    z : array_like
        Nominal height of the plate each sample lies on, mm, same shape; at least three
        distinct heights.
    max_points : int, optional
        The coefficients are fitted on a random subsample of at most this many points (the
        residuals are still reported for every point).
    rng : numpy.random.Generator or int or None, optional
        Source (or seed) of the subsample.

    Returns
    -------
    FitResult
        The model, per-point residuals ``Z_model − Z`` (mm, the inputs' shape), their RMSE, the
        median and IQR of their absolute values, and the Jacobian's condition number.

    Raises
    ------
    ValueError
        If the inputs differ in shape, hold non-finite values or fewer than eleven points, ``z``
        has fewer than three distinct values, ``x``, ``y`` or ``dphi`` do not vary, or
        ``max_points`` is below eleven; the message names the parameter.

    Notes
    -----
    Variables are centred and scaled (mean, standard deviation) before fitting: in raw units
    the Jacobian's condition number is orders of magnitude worse. A linear least-squares solve
    of the multiplied-out equation is the start; Levenberg–Marquardt then minimises the height
    residual itself with an analytic Jacobian, converging in a handful of evaluations.

    References
    ----------
    .. [1] H. Du and Z. Wang, "Three-dimensional shape measurement with an arbitrarily arranged
       fringe projection profilometry system", Optics Letters 32(16), 2438–2440 (2007),
       doi:10.1364/OL.32.002438.
    .. [2] J. J. Moré, "The Levenberg–Marquardt algorithm: implementation and theory", in
       Numerical Analysis, Lecture Notes in Mathematics 630, 105–116 (1978).
    .. [3] E. Via et al., Physics and Imaging in Radiation Oncology (2023),
       doi:10.1016/j.phro.2023.100517 (the clinical method and its figures).
    """
    names = ("x", "y", "dphi", "z")
    arrays = [_as_float_array(value, name)
              for value, name in zip((x, y, dphi, z), names, strict=True)]
    shape = arrays[3].shape
    for array, name in zip(arrays[:3], names[:3], strict=True):
        if array.shape != shape:
            raise ValueError(f"{name}: shape {array.shape} differs from z's {shape}")
    x_all, y_all, p_all, z_all = (a.reshape(-1) for a in arrays)
    n = z_all.size
    if n < N_COEFFICIENTS:
        raise ValueError(f"z: {n} points cannot fix {N_COEFFICIENTS} coefficients")
    if isinstance(max_points, bool) or not isinstance(max_points, int | np.integer):
        raise ValueError(f"max_points: expected an integer, not {type(max_points).__name__}")
    if max_points < N_COEFFICIENTS:
        raise ValueError(f"max_points: must be at least {N_COEFFICIENTS}, not {max_points}")
    if np.unique(z_all).size < 3:
        raise ValueError("z: needs at least three distinct plate heights")

    x_centre, x_scale = _centre_scale(x_all, "x")
    y_centre, y_scale = _centre_scale(y_all, "y")
    p_centre, p_scale = _centre_scale(p_all, "dphi")
    z_centre, z_scale = _centre_scale(z_all, "z")

    if n > max_points:
        generator = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        chosen = np.sort(generator.choice(n, size=int(max_points), replace=False))
        x_fit, y_fit, p_fit, z_fit = (a[chosen] for a in (x_all, y_all, p_all, z_all))
    else:
        x_fit, y_fit, p_fit, z_fit = x_all, y_all, p_all, z_all
    xn = (x_fit - x_centre) / x_scale
    yn = (y_fit - y_centre) / y_scale
    pn = (p_fit - p_centre) / p_scale
    zn = (z_fit - z_centre) / z_scale

    theta, evaluations = _refine(_linear_start(xn, yn, pn, zn), xn, yn, pn, zn)
    condition = float(np.linalg.cond(_jacobian(theta, xn, yn, pn)))

    model = PhaseHeightModel(
        coefficients=tuple(float(c) for c in theta),
        x_centre=x_centre, x_scale=x_scale, y_centre=y_centre, y_scale=y_scale,
        dphi_centre=p_centre, dphi_scale=p_scale, z_centre=z_centre, z_scale=z_scale,
        z_range=(float(np.min(z_all)), float(np.max(z_all))),
    )
    residual = model.height(x_all, y_all, p_all) - z_all
    absolute = np.abs(residual)
    q25, q50, q75 = (float(q) for q in np.percentile(absolute, [25, 50, 75]))
    return FitResult(
        model=model,
        residual_mm=residual.reshape(shape),
        rmse_mm=float(np.sqrt(np.mean(residual**2))),
        median_abs_mm=q50,
        iqr_mm=q75 - q25,
        condition_number=condition,
        evaluations=evaluations,
    )
