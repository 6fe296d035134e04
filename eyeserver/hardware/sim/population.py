"""Simulated patient eyes drawn from documented population ranges.

A patient's eye is not the painted eye the simulator used to draw (:data:`SHARP`): its limbus is a
band, not an edge, its contrast in near-infrared follows the iris's pigmentation, its globe is an
ellipsoid, its cornea flattens towards the limbus, its limbus sits off the globe's axis, its lids
cover part of the limbus and its tear film glints. :func:`draw_eye` draws each of these properties
per eye, independently of the others and of what the pose fit assumes (cornea 7.8 mm, limbus 11.7 mm
on the globe's axis, lids a shell 1.2 mm outside the globe); :func:`describe` gives the descriptors
a bench bins its figures by, and :func:`biometry` what a physicist would enter from the patient's
MRI and biometry, each off by its typical measurement error. Ranges, distributions and their sources
are in docs/eye-model.md.

Only the eye's own properties are drawn: gaze and motion stay at rest ((0, 0) and None) for the
caller to set, and the position of the eye is the scene's.

References
----------
.. [1] F. Rüfer, A. Schröder, C. Erb, "White-to-white corneal diameter: normal values in healthy
   humans obtained with the Orbscan II topography system", Cornea 24(3):259–261, 2005,
   doi:10.1097/01.ico.0000148312.01805.53.
.. [2] M. Dubbelman et al., "Radius and asphericity of the posterior corneal surface determined
   by corrected Scheimpflug photography", Acta Ophthalmol. Scand. 80, 2002,
   doi:10.1034/j.1600-0420.2002.800406.x (anterior radius 7.87 ± 0.27 mm, 83 eyes).
.. [3] Xiong et al., 2017, the Handan Eye Study's corneal Q values (1683 eyes, anterior
   Q −0.28 ± 0.18), PMC5436654.
.. [4] D. A. Atchison et al., "Eye shape in emmetropia and myopia", Invest. Ophthalmol. Vis.
   Sci. 45(10):3380–3386, 2004.
.. [5] S. Patel, L. Tutchenko, "The refractive index of the human cornea: a review", Cont. Lens
   Anterior Eye 42:575–580, 2019, doi:10.1016/j.clae.2019.04.018.
.. [6] A. Abass et al., "Three-dimensional non-parametric method for limbus detection", PLoS
   ONE 13(11):e0207710, 2018, doi:10.1371/journal.pone.0207710 (the limbus's tilt).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from eyeserver.hardware.sim.scenes import EyeSpec, conic_sagitta

__all__ = [
    "BIOMETRY_SD",
    "FIT_CORNEA_RADIUS_MM",
    "FIT_LID_GAP_MM",
    "FIT_LIMBUS_DIAMETER_MM",
    "KERATOMETRY_SEMI_CHORD_MM",
    "MRI_ERROR_SCALE",
    "SHARP",
    "SHARP_RADII_MM",
    "VARIANTS",
    "biometry",
    "describe",
    "draw",
    "draw_eye",
    "draw_sharp",
    "keratometric_radius",
    "lid_cover",
]

SHARP = EyeSpec()
"""The old painted eye, the named variant ``"sharp"``: a 12-mm spherical globe, a spherical
7.8-mm cornea, a sharp circular 11.7-mm limbus between constant reflectances (sclera 0.42,
iris 0.06), lids a shell 1.2 mm outside the globe with an 11 × 7.5 mm (half-axes) opening that
leaves the limbus free, no glints, no lashes: anatomy equal to the fit's own defaults."""

SHARP_RADII_MM = (11.0, 12.0, 13.0)
"""Globe radii the ``"sharp"`` variant draws from, as the old pose bench did."""

FIT_CORNEA_RADIUS_MM = 7.8
FIT_LIMBUS_DIAMETER_MM = 11.7
FIT_LID_GAP_MM = 1.2
"""What the pose fit assumes by default (``EyeModel.population()`` and the lids' shell), the
reference of :func:`describe`'s ``anatomy_mismatch_mm``."""

KERATOMETRY_SEMI_CHORD_MM = 1.5
"""Where a keratometer reads the cornea: its mires fall on a ≈ 3-mm zone, so on an aspheric
cornea it reports the sagittal radius there, not the apical radius."""

BIOMETRY_SD: dict[str, float] = {
    "globe_radius_mm": 0.15,
    "globe_semi_axes_mm": 0.2,
    "cornea_radius_mm": 0.05,
    "limbus_diameter_mm": 0.25,
}
"""Standard deviations (mm) of :func:`biometry`'s measurement errors, each truncated at ±3 sd;
the globe's (the MRI's) are a typical patient's, scaled per patient by :data:`MRI_ERROR_SCALE`.
Sources and reasoning in docs/eye-model.md (MRI radius and semi-axes: assumed from the
sub-voxel repeatability of MRI ellipsoid fits and the 0.1–0.2 mm repeatability of MRI axial
lengths; keratometry: repeatability ≈ 0.02 mm plus device differences; white-to-white:
agreement between devices and against the topographic limbus ≈ 0.2–0.3 mm)."""

MRI_ERROR_SCALE = (0.5, 2.0)
"""The range (uniform) of a patient's MRI error as a multiple of :data:`BIOMETRY_SD`'s globe
entries, drawn per patient: 0.1–0.4 mm a semi-axis, from the sub-voxel repeatability of a
dedicated ocular MRI to a protocol with twice the assumed error. The fit's default
(``tunables.MEASURED_GLOBE_SD_MM``, 0.2 mm) sits inside the range, below its mean, so the
bench's MRIs are worse on average than the fit assumes, never equal to it by construction."""

_ERROR_TRUNCATION_SD = 3.0

# Population ranges (mm unless stated), each drawn independently; docs/eye-model.md cites them.
_GLOBE_RADIUS = (12.0, 0.6, 10.8, 13.4)  # mean, sd, low, high: outer radius ≈ axial length / 2
_GLOBE_SPHERE_SHARE = 0.15  # the rest are ellipsoids
_GLOBE_AXIS_DEVIATION = 0.5  # each semi-axis within ± this of the mean: differences ≤ 1 mm
_CORNEA_RADIUS = (7.87, 0.27, 7.2, 8.55)  # Dubbelman 2002 (83 eyes), ±2.5 sd
_CORNEA_Q = (-0.25, 0.18, -0.70, 0.20)  # Xiong 2017, Dubbelman 2002, Al-Somali 2023
_LIMBUS_DIAMETER = (11.71, 0.42, 10.7, 12.6)  # Rüfer 2005, cut at its normal ranges
_LIMBUS_VERTICAL_RATIO = (0.91, 0.03, 0.84, 0.98)  # 10.6 / 11.7 mm, textbook oval cornea
_LIMBUS_WIDTH = (0.2, 2.0)  # visible 10–90 % width of the transition
_LIMBUS_SCATTER = (0.0, 0.6)
_SCLERA_ALBEDO = (0.30, 0.50)
_IRIS_ALBEDO = (0.03, 0.30)
_IRIS_DEPTH = (2.6, 3.4)  # apparent: anterior chamber depth ≈ 3.1 ± 0.4 mm, less ≈ 0.5 mm
_PUPIL_DIAMETER = (2.5, 6.0)  # NIR light does not narrow the pupil
_TEAR_REFLECTANCE = (0.020, 0.025)  # Fresnel at n = 1.337 (tears) … 1.376 (cornea)
_TEAR_GLINTS = (0, 6)
_APERTURE_HALF_WIDTH = (9.5, 13.0)
_APERTURE_HALF_HEIGHT = (4.5, 8.0)
_APERTURE_OFFSET_X = (-1.0, 1.0)
_APERTURE_OFFSET_Y = (-2.5, 0.5)  # negative: the upper lid low over the top of the limbus
_LID_GAP = (0.3, 1.5)
_LASHES = (0, 30)  # along the opening's upper margin (some droop across it)
_LIMBUS_OFFSET_SD = 0.2  # each of x, y; assumed from the limbus's tilt (Abass 2018 [6])
_LIMBUS_OFFSET_MAX = 0.6  # the offset's length, redrawn beyond
_LIMBUS_OFFSET_STREAM = 1
"""Mixed with ``features_seed`` to seed the limbus offset's own generator: drawn after every
other property (and from its own stream) so that adding it left each seeded eye's other
properties, and the eyes drawn after it, as they were."""

_COVER_SAMPLES = 3600
"""Points along the limbus ellipse for :func:`lid_cover` (0.1° apart)."""


def _truncated_normal(rng: np.random.Generator, spec: tuple[float, float, float, float]
                      ) -> float:
    """A normal draw (``mean``, ``sd``) kept within [``low``, ``high``] by redrawing."""
    mean, sd, low, high = spec
    while True:
        value = float(rng.normal(mean, sd))
        if low <= value <= high:
            return value


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(*bounds))


def _integer(rng: np.random.Generator, bounds: tuple[int, int]) -> int:
    """A uniform integer in [low, high], both included."""
    return int(rng.integers(bounds[0], bounds[1] + 1))


def draw_eye(rng: np.random.Generator) -> EyeSpec:
    """One patient eye, each property drawn independently from its population range.

    Parameters
    ----------
    rng : numpy.random.Generator
        The source of randomness; the same state gives the same eye.

    Returns
    -------
    EyeSpec
        At rest: gaze (0, 0) and no motion, for the caller to set. The ranges are cut so that
        every combination validates (the limbus narrower than the globe and within the
        cornea's reach).

    Notes
    -----
    Distributions and sources in docs/eye-model.md. The globe is an ellipsoid in 85 % of the
    eyes, its (horizontal, vertical, axial) semi-axes each within ±0.5 mm of a radius drawn
    around 12 mm (so they differ by up to 1 mm); ``globe_radius_mm`` is then their mean. The
    limbus (with the cornea and the iris) sits ``limbus_offset_mm`` off the globe's axis.
    """
    radius = _truncated_normal(rng, _GLOBE_RADIUS)
    semi_axes: tuple[float, float, float] | None = None
    if rng.uniform() >= _GLOBE_SPHERE_SHARE:
        deviation = rng.uniform(-_GLOBE_AXIS_DEVIATION, _GLOBE_AXIS_DEVIATION, 3)
        h, v, a = (float(radius + d) for d in deviation)
        semi_axes = (h, v, a)
        radius = (h + v + a) / 3
    eye = EyeSpec(
        globe_radius_mm=radius,
        globe_semi_axes_mm=semi_axes,
        cornea_radius_mm=_truncated_normal(rng, _CORNEA_RADIUS),
        cornea_asphericity=_truncated_normal(rng, _CORNEA_Q),
        limbus_diameter_mm=_truncated_normal(rng, _LIMBUS_DIAMETER),
        limbus_vertical_ratio=_truncated_normal(rng, _LIMBUS_VERTICAL_RATIO),
        limbus_width_mm=_uniform(rng, _LIMBUS_WIDTH),
        limbus_scatter=_uniform(rng, _LIMBUS_SCATTER),
        sclera_albedo=_uniform(rng, _SCLERA_ALBEDO),
        iris_albedo=_uniform(rng, _IRIS_ALBEDO),
        iris_depth_mm=_uniform(rng, _IRIS_DEPTH),
        pupil_diameter_mm=_uniform(rng, _PUPIL_DIAMETER),
        tear_reflectance=_uniform(rng, _TEAR_REFLECTANCE),
        tear_glints=_integer(rng, _TEAR_GLINTS),
        gaze_deg=(0.0, 0.0),
        aperture_mm=(_uniform(rng, _APERTURE_HALF_WIDTH), _uniform(rng, _APERTURE_HALF_HEIGHT)),
        aperture_offset_mm=(_uniform(rng, _APERTURE_OFFSET_X),
                            _uniform(rng, _APERTURE_OFFSET_Y)),
        lid_gap_mm=_uniform(rng, _LID_GAP),
        lashes=_integer(rng, _LASHES),
        features_seed=int(rng.integers(0, 2**31 - 1)),
        motion=None,
    )
    offset = _limbus_offset(np.random.default_rng([eye.features_seed, _LIMBUS_OFFSET_STREAM]))
    return EyeSpec.model_validate({**eye.model_dump(), "limbus_offset_mm": offset})


def _limbus_offset(rng: np.random.Generator) -> tuple[float, float]:
    """The limbus's centre across the globe's axis (mm): each component normal, sd
    ``_LIMBUS_OFFSET_SD``, the offset's length redrawn beyond ``_LIMBUS_OFFSET_MAX``."""
    while True:
        x, y = (float(v) for v in rng.normal(0.0, _LIMBUS_OFFSET_SD, 2))
        if math.hypot(x, y) <= _LIMBUS_OFFSET_MAX:
            return x, y


def draw_sharp(rng: np.random.Generator) -> EyeSpec:
    """The old painted eye (:data:`SHARP`) with a globe radius of 11, 12 or 13 mm.

    Parameters
    ----------
    rng : numpy.random.Generator
        Chooses the radius, each with probability 1/3.

    Returns
    -------
    EyeSpec
        :data:`SHARP` with only ``globe_radius_mm`` changed.
    """
    radius = float(SHARP_RADII_MM[int(rng.integers(len(SHARP_RADII_MM)))])
    return EyeSpec.model_validate({**SHARP.model_dump(), "globe_radius_mm": radius})


VARIANTS: dict[str, Callable[[np.random.Generator], EyeSpec]] = {
    "patient": draw_eye,
    "sharp": draw_sharp,
}
"""The eyes a bench can draw, by name: ``"patient"`` the population (:func:`draw_eye`),
``"sharp"`` the old painted eye (:func:`draw_sharp`)."""


def draw(rng: np.random.Generator, variant: str = "patient") -> EyeSpec:
    """One eye of the named variant (a key of :data:`VARIANTS`).

    Parameters
    ----------
    rng : numpy.random.Generator
        The source of randomness.
    variant : str
        ``"patient"`` or ``"sharp"``.

    Returns
    -------
    EyeSpec
        The eye at rest (gaze (0, 0), no motion).

    Raises
    ------
    ValueError
        If ``variant`` is not a known variant.
    """
    try:
        drawer = VARIANTS[variant]
    except KeyError:
        known = ", ".join(sorted(VARIANTS))
        raise ValueError(f"variant must be one of {known}, not {variant!r}") from None
    return drawer(rng)


def lid_cover(eye: EyeSpec) -> float:
    """Share of the visible limbus's circumference that the lids hide, the eye at rest.

    Seen along the eye's axis in its own frame, the limbus is an ellipse centred
    ``limbus_offset_mm`` off the axis (horizontal semi-axis ``limbus_diameter_mm / 2``, vertical
    ``limbus_vertical_ratio`` times that) and the lid opening an ellipse of half-axes
    ``aperture_mm`` centred at ``aperture_offset_mm``; the lid shell lies in front of the limbus
    everywhere outside the opening (as the renderer's lids do: a point on the opening's edge is
    lid). Lashes are not counted.

    Parameters
    ----------
    eye : EyeSpec
        The eye.

    Returns
    -------
    float
        The hidden share of the limbus's arc length, in [0, 1].
    """
    t = np.linspace(0.0, 2.0 * math.pi, _COVER_SAMPLES, endpoint=False)
    a = eye.limbus_diameter_mm / 2
    b = eye.limbus_vertical_ratio * a
    centre_x, centre_y = eye.limbus_offset_mm
    x, y = centre_x + a * np.cos(t), centre_y + b * np.sin(t)
    arc = np.hypot(a * np.sin(t), b * np.cos(t))  # |dP/dt|: equal steps in t are unequal arcs
    half_w, half_h = eye.aperture_mm
    off_x, off_y = eye.aperture_offset_mm
    hidden = ((x - off_x) / half_w) ** 2 + ((y - off_y) / half_h) ** 2 >= 1.0
    return float(arc[hidden].sum() / arc.sum())


def describe(eye: EyeSpec) -> dict[str, float]:
    """Descriptors a bench bins its figures by.

    Parameters
    ----------
    eye : EyeSpec
        The eye.

    Returns
    -------
    dict of str to float
        ``limbus_width_mm``
            The limbus transition's 10–90 % width (0 a sharp step).
        ``limbus_contrast``
            Michelson contrast of the reflectances across the limbus,
            (sclera − iris) / (sclera + iris).
        ``lid_cover``
            Share of the limbus's circumference hidden by the lids at rest
            (:func:`lid_cover`).
        ``anatomy_mismatch_mm``
            How far the anatomy lies from what the fit assumes: the largest of
            |cornea radius − 7.8|, |limbus diameter − 11.7| / 2, the spread (max − min) of the
            globe's semi-axes, |lid gap − 1.2|, the cornea's departure from a sphere at the
            limbus (the conic's sagitta less the sphere's of the same apical radius, at half
            the limbus diameter) and the limbus's offset from the globe's axis.
    """
    half_limbus = eye.limbus_diameter_mm / 2
    cornea = eye.cornea_radius_mm
    asphere = abs(conic_sagitta(cornea, eye.cornea_asphericity, half_limbus)
                  - conic_sagitta(cornea, 0.0, half_limbus))
    axes = eye.globe_semi_axes_mm
    spread = 0.0 if axes is None else max(axes) - min(axes)
    mismatch = max(abs(cornea - FIT_CORNEA_RADIUS_MM),
                   abs(eye.limbus_diameter_mm - FIT_LIMBUS_DIAMETER_MM) / 2,
                   spread,
                   abs(eye.lid_gap_mm - FIT_LID_GAP_MM),
                   asphere,
                   math.hypot(*eye.limbus_offset_mm))
    sclera, iris = eye.sclera_albedo, eye.iris_albedo
    return {
        "limbus_width_mm": eye.limbus_width_mm,
        "limbus_contrast": (sclera - iris) / (sclera + iris),
        "lid_cover": lid_cover(eye),
        "anatomy_mismatch_mm": mismatch,
    }


def _error(rng: np.random.Generator, sd: float) -> float:
    """A normal measurement error of ``sd``, cut at ±3 sd (a gross error is a blunder the
    physicist catches, not a typical error)."""
    limit = _ERROR_TRUNCATION_SD * sd
    return float(np.clip(rng.normal(0.0, sd), -limit, limit))


def keratometric_radius(eye: EyeSpec) -> float:
    """The radius a keratometer reads on this cornea: the conic's sagittal radius
    √(R² − Q·y²) at the mires' semi-chord y (:data:`KERATOMETRY_SEMI_CHORD_MM`), flatter than
    the apical radius R where the cornea flattens (Q < 0)."""
    y = KERATOMETRY_SEMI_CHORD_MM
    return math.sqrt(eye.cornea_radius_mm**2 - eye.cornea_asphericity * y * y)


def biometry(eye: EyeSpec, rng: np.random.Generator
             ) -> dict[str, float | tuple[float, float, float] | None]:
    """What a physicist would enter for this eye from its MRI and biometry: never the truth.

    Parameters
    ----------
    eye : EyeSpec
        The true eye.
    rng : numpy.random.Generator
        Draws the measurement errors.

    Returns
    -------
    dict
        ``globe_semi_axes_mm``
            The MRI's ellipsoid: each true semi-axis plus an independent error of sd
            ``mri_sd_mm``; None for a spherical globe.
        ``globe_radius_mm``
            For an ellipsoid the mean of the measured semi-axes (its error has sd
            ``mri_sd_mm``/√3); for a sphere the true radius plus an error of sd
            0.75 ``mri_sd_mm`` (:data:`BIOMETRY_SD`'s ratio).
        ``mri_sd_mm``
            This patient's MRI error per semi-axis: ``BIOMETRY_SD["globe_semi_axes_mm"]``
            (0.2 mm) times a scale drawn from :data:`MRI_ERROR_SCALE`. A record for the bench,
            not an entry: the physicist does not know it and the daemon takes its default.
        ``cornea_radius_mm``
            Keratometry: the cornea's sagittal radius at the mires
            (:func:`keratometric_radius`, ≈ 0.04 mm flatter than the apex at Q = −0.25) plus
            an error of sd 0.05 mm.
        ``limbus_diameter_mm``
            White-to-white: the true horizontal limbus diameter plus an error of sd 0.25 mm.

    Notes
    -----
    Every error is normal, truncated at ±3 sd, and independent of the others
    (:data:`BIOMETRY_SD`, the globe's scaled per patient; sources in docs/eye-model.md).
    """
    scale = float(rng.uniform(*MRI_ERROR_SCALE))
    axes_sd = scale * BIOMETRY_SD["globe_semi_axes_mm"]
    semi_axes: tuple[float, float, float] | None = None
    if eye.globe_semi_axes_mm is not None:
        h, v, a = (axis + _error(rng, axes_sd) for axis in eye.globe_semi_axes_mm)
        semi_axes = (h, v, a)
        radius = (h + v + a) / 3
    else:
        radius = eye.globe_radius_mm + _error(rng, scale * BIOMETRY_SD["globe_radius_mm"])
    cornea = keratometric_radius(eye) + _error(rng, BIOMETRY_SD["cornea_radius_mm"])
    limbus = eye.limbus_diameter_mm + _error(rng, BIOMETRY_SD["limbus_diameter_mm"])
    return {
        "globe_radius_mm": radius,
        "globe_semi_axes_mm": semi_axes,
        "cornea_radius_mm": cornea,
        "limbus_diameter_mm": limbus,
        "mri_sd_mm": axes_sd,
    }
