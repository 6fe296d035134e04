"""The eye subsystem's tunable constants, each with what it is, its unit and where its value
comes from.

One constant, one place: :mod:`~eyeserver.eye.limbus`, :mod:`~eyeserver.eye.sclera`,
:mod:`~eyeserver.eye.fit` and :mod:`~eyeserver.eye.track` import them from here (``from
eyeserver.eye.tunables import NAME``, so a test that patches ``limbus.NAME`` patches what
:mod:`~eyeserver.eye.limbus` reads). Counts are points, pixels or samples; lengths are mm in
the WCS, pixels (``_PX``) in a camera's image; angles degrees (``_DEG``) or radians (``_RAD``);
shares and factors are dimensionless. "Chosen by hand" means no measurement of the value is
recorded; the others name theirs (the notes: docs/notes/limbus.md, sclera.md, tracking.md,
patient-eye.md).
"""

from __future__ import annotations

import numpy as np

# --- Shared -----------------------------------------------------------------------------------

MIN_SCLERA_POINTS = 30
"""Fewest sclera points (of the cloud) a globe is fitted to or placed on: fewer and the
one-shot fit raises :class:`~eyeserver.eye.fit.PoseError`, the warm fit loses the eye, the globe
through the limbus is not placed (:func:`~eyeserver.eye.limbus.globe_on_limbus`) and the sclera
is not measured again. The searches that lead there count against it too (the votes for the
globe's depth behind the limbus, a shell's support about the voted centre, the lid shell's
points), and so do shut lids inside the limbus (:func:`~eyeserver.eye.track.lids_closed`).
Count; chosen by hand."""

# --- The limbus in the images (limbus.py) -----------------------------------------------------

SAMPLES = 120
"""Points of the projected circle where an edge is looked for, per camera. Count; chosen by
hand."""

EDGE_SHARE = 0.4
"""An edge counts when it rises at least this share of the profile's strongest rise. Share;
chosen by hand."""

MIN_EDGE_DN_PER_PX = 2.0
"""And by at least this much (DN per pixel): flatter profiles hold no edge. Chosen by hand
(what it does on soft limbi: docs/notes/patient-eye.md)."""

REACHES_PX = (20.0, 8.0, 4.0)
"""Half-widths of the edge search, round by round (image pixels). Chosen by hand."""

LIMBUS_AXIS_SD_MM = 0.1
"""How far (sd, mm) the one-shot search lets the limbus centre stray from the axis through the
cloud's globe centre along its own normal, where both units see the eye (one unit's is not
held): the fit takes the limbus on the globe's axis, which both units' cloud places to a few
tenths of a millimetre at worst (measured:
docs/notes/patient-eye.md, twenty-third session). A real limbus may lie off it; the fit does not
model that yet (the twenty-fourth session's notes)."""

LIMBUS_AXIS_STRAY_SDS = 3.0
"""The held search's last round fits the edges alone, so a limbus they place well keeps its own
circle; it is held again only where that circle's centre lies more than this many
:data:`LIMBUS_AXIS_SD_MM` from the axis. Chosen by hand (why not every round: the same notes)."""

MIN_COVERAGE = 0.4
"""Share of the circle's samples that must hold an edge, in at least two cameras. Share;
chosen by hand."""

MAX_RESIDUAL_PX = 1.0
"""A fit whose median edge distance exceeds this (pixels) is not the limbus. Chosen by hand
(what was measured: :data:`GOOD_RESIDUAL_PX`)."""

GOOD_RESIDUAL_PX = 0.5
"""One within this (pixels) needs no second start (measured: 0.1–0.2 px on the limbus, ≈ 1 px
on a circle stuck on a lid or shadow edge)."""

LID_CLEARANCE_MM = 1.0
"""Sclera points closer than this (mm) to the lid shell are left out of the globe's fit.
Chosen by hand."""

LID_GAP_MM = 0.5
"""Points further than this (mm) outside the sphere through the limbus are taken for lids when
their offsets show no lid shell of their own (:func:`~eyeserver.eye.limbus.globe_on_limbus`).
Chosen by hand."""

LID_SHELL_DOMINANCE = 2.0
"""A shell of points closer than :data:`LID_GAP_MM` outside the sphere through the limbus that
holds this many times the sclera's points is taken for lids even where no trough separates
the two (:func:`~eyeserver.eye.limbus._lid_gap`). Chosen by hand; where the sphere sits on the
noise inside the globe the sclera itself can be taken for lids, and the pose is refused rather
than wrong (docs/notes/patient-eye.md, twentieth session)."""

LIMBUS_CLEARANCE_MM = 1.5
"""And so are those closer than this (mm) to the limbus. Chosen by hand."""

GLOBE_DEPTHS_MM = (6.0, 17.0)
"""Distances (mm) from the globe centre to the limbus plane considered when the radius is
fitted (globes of ≈ 8–18 mm with a 11.7 mm limbus)."""

CLOUD_SCLERA_BIAS_MM = 0.02
"""The reconstructed (cloud's) sclera's systematic radial error in one capture (mm): the spread,
over 150 rendered poses, of the sclera's mean distance from the true globe (each point weighted
as it weighs in ``h``; 0.018 mm on 200 others). It does not average over the points: it sets
the floor of the globe depth's uncertainty (:func:`~eyeserver.eye.limbus.globe_on_limbus`).
The sclera measured again in the images has its own, :data:`REMEASURED_SCLERA_BIAS_MM`."""

DEPTH_REFIT_LIMIT_MM = 0.3
"""How far (mm) the robust fit of the sclera's points may move the globe's depth ``h`` from the
votes' mode it starts at and still count as refining it (a vote's own noise, the sclera's
≈ 0.06 mm amplified about four times, is ≈ 0.25 mm). A larger move has left the mode's shell:
rightly where the mode sat on noise inside the globe, onto a lid shell where the mode holds a
shell of its own (:func:`~eyeserver.eye.limbus.globe_on_limbus`). The votes' mean shift is held
to the innermost shell by the same limit. Measured: docs/notes/patient-eye.md, nineteenth and
twentieth sessions."""

SHELL_SEARCH_MM = 2.0
"""How far (mm) beyond the first votes for ``h`` the sclera's shell is looked for. Measured on
200 rendered poses: the first window alone sat on the noise inside the globe in one pose in
ten; a longer search reaches the lids' votes on the `wide` rig, where they begin ≈ 2.8 mm
beyond the sclera's (docs/notes/limbus.md)."""

SHELL_TROUGH = 0.6
"""Two shells (the sclera and a lid shell close to it) are told apart where the counts between
their peaks fall below this share of the smaller peak's (:func:`~eyeserver.eye.limbus.
globe_on_limbus`). Chosen on rendered eyes with lids 0.3–0.8 mm outside the globe
(docs/notes/patient-eye.md): 0.5 missed a lid shell 0.45 mm out whose trough stood at 0.56."""

DARK_SHARE = 0.35
"""Fringe-free intensity below this share of the image's bright level (its 95th percentile)
counts as dark (the cornea returns ≈ 0.06 of the white plate's light, sclera and skin
0.4–0.5). Share; chosen by hand."""

LIMBUS_WINDOW_MARGIN_PX = 40
"""Margin (pixels) about the projection of the ball around the rough limbus that bounds each
camera's window of the limbus search. Chosen by hand."""

START_TILTS_DEG = (0.0, 6.0, 12.0, 18.0, 24.0, 30.0)
"""Tilts (degrees) about the rough gaze of the circles scored for a start (each at 12 azimuths
30° apart): the cloud fit's gaze can be 10–25° off. Live tracking after a saccade scores the
first three. Chosen by hand."""

SHADOW_PROBE_MM = 0.01
"""How far (mm) beyond the limbus, along the globe, the sclera is tested for the cornea's
shadow (:func:`~eyeserver.eye.limbus.refined` with a :class:`~eyeserver.eye.limbus.Shade`):
≈ 0.1 px on the default rig. Chosen by hand (what it leaves: docs/notes/limbus.md)."""

OVAL_CORNEA_MM = 7.8
"""Radius (mm) of the cornea whose sagitta lifts the visible oval's top and bottom (on the
cornea, inside the junction's radius) in front of the junction's plane. The textbook anterior
corneal radius (:meth:`~eyeserver.eye.fit.EyeModel.population`'s 7.8 mm; not tied to the
patient's model)."""

OVAL_RATIOS = (0.7, 1.15)
"""Heights over widths an oval fit may end at; beyond them the edges fit no limbus. Ratios;
chosen by hand (a patient's visible limbus is ≈ 0.9 as high as wide:
docs/notes/patient-eye.md)."""

FOLLOWED_TURN_DEG = 1.0
"""Live tracking takes the limbus that the last round alone finds from the last gaze only when
it turned the gaze by no more than this (degrees; a frame at 25 Hz turns it by hundredths of a
degree but in a saccade); else the search scores tilted circles first
(:func:`~eyeserver.eye.limbus.find_limbus`, whose comments give what was measured)."""

CIRCLE_STEPS = np.array([1e-6, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6, 1e-7])
"""Forward-difference steps of the circle's parameters (centre mm, gaze X and Y components,
radius mm; an oval's height ratio). Chosen by hand."""

CIRCLE_X_SCALE = np.array([0.1, 0.1, 0.1, 0.01, 0.01, 0.1, 0.01])
"""Typical changes of the circle's parameters (units as :data:`CIRCLE_STEPS`'s); a fit stops
when its steps fall below :data:`CIRCLE_XTOL` of them. Chosen by hand; the fit so stopped finds
SciPy's circles within 1e-4 of these scales (docs/notes/limbus.md)."""

CIRCLE_XTOL = 1e-4
"""The circle fit's step tolerance, a share of :data:`CIRCLE_X_SCALE`. Chosen by hand."""

CIRCLE_ITERATIONS = 30
"""Most Levenberg–Marquardt iterations of one circle fit. Count; chosen by hand."""

# --- The sclera measured again (sclera.py) ----------------------------------------------------

WINDOW_PX = 9
"""Side (pixels) of the square of pixels one phase offset is fitted over (≈ 0.7 fringe period on
the default rig); only the sclera's pixels in it count. Chosen on rendered eyes
(docs/notes/sclera.md: against 15 pixels for the sharpened image's fit on 36 poses, 7 and 11
for the remeasure on 120 eyes)."""

MIN_SHARE = 0.4
"""A window needs this share of its pixels on the sclera for a fit. Share; chosen by hand."""

MAX_OFFSET_RAD = 0.6
"""Pixels whose phase lies further than this (rad) from the sphere's are not its sclera (a lid
in front of it from this camera: the lids lie ≈ 1.2 mm, ≈ 1.4 rad, outside). Chosen by
hand."""

MAX_PHASE_SD_RAD = 0.04
"""Windows whose phase is less sure than this (rad) are left out (faint fringes: the sclera at
grazing light or in a lid's half-shadow, where the noise also biases ``atan2``; the sclera's in
full light is good to ≈ 0.01 rad). Chosen by hand."""

MIN_AMPLITUDE = 0.8
"""Pixels whose fringe amplitude (their window's, fitted over the pixels kept) is below this
share of the camera's median over the sclera are left out: light at grazing incidence and the
edges of the shadows that the lids and the cornea cast, where a window's phase is biased (the
light changes steeply across it, or ends inside it). Share; chosen on 120 rendered eyes against
0.7 and 0.9 (docs/notes/sclera.md)."""

NEAR_MM = 0.5
"""A pixel sees the sclera where its ray meets the sphere this close (mm) to a sclera point of
the cloud (any camera's). Where the visible sclera is a narrow band, the cloud's is patchy, and
a globe's depth rests on how far out the sclera is seen (0.2 mm did worse: docs/notes/sclera.md).
Pixels that see a lid, not the sphere, are still left out by their phase
(:data:`MAX_OFFSET_RAD`)."""

ROUNDS = 2
"""Fits of the phase offsets, each about the last one's phase. Count; chosen by hand."""

REMEASURED_SCLERA_BIAS_MM = 0.01
"""The remeasured sclera's systematic radial error in one capture (mm): what the sclera as a
whole is trusted to. Chosen on 36 rendered poses so that the stated sds cover the errors without
letting the limbus hold the gaze too firmly (docs/notes/sclera.md). The cloud's sclera has its
own, :data:`CLOUD_SCLERA_BIAS_MM`."""

MIN_REMEASURED_POINTS = 30
"""Fewest remeasured points a globe is fitted to; also the fewest sclera points a camera must
see, and pixels it must keep, to be remeasured at all. Count; chosen by hand (the same number
as :data:`MIN_SCLERA_POINTS`, but a count of remeasured pixels, not of the cloud's points)."""

ROBUST_MM = 0.05
"""Scale (mm) of the soft-L1 loss on the remeasured points' distances to the globe. Chosen by
hand."""

PASSES = 2
"""Remeasure-and-fit passes, each about the last pass's globe. Count; chosen by hand."""

OUTSIDE_MM = 0.4
"""Points of the cloud this far (mm) outside the sphere are not its sclera: they can hide it.
Chosen by hand."""

IN_FRONT_MM = 0.25
"""A pixel whose ray meets a point of the cloud this much (mm) before the sphere does not see
the sphere (a lid in front of it). Chosen by hand."""

LIMBUS_MARGIN_MM = 0.6
"""Sclera pixels closer than this (mm, along the gaze) to the limbus's plane are not fitted for
the illumination: they may lie on the limbus's transition, and dividing by a fit that follows its
albedo flattens the transition's outer half and pulls the edge inwards, further at each pass. A
patient's transition is up to 2 mm wide (10–90 %, docs/eye-model.md); beyond its outer half,
1 mm over the globe's surface, lie ≈ 0.5 mm along the gaze at the limbus of a 12-mm globe, and
the fit window reaches a little further in. Measured on rendered soft limbi against 0.05 mm
(chosen on sharp ones) and 0.15–0.3 mm (docs/notes/patient-eye.md, eighteenth session)."""

MIN_ILLUMINATION = 0.25
"""The illumination divided out is at least this share of the sclera's median background.
Share; chosen by hand."""

# --- The one-shot fit (fit.py) ----------------------------------------------------------------

OVAL_LIMBUS = True
"""The one-shot fit finds the limbus as an oval (:func:`~eyeserver.eye.limbus.find_limbus`
``oval``); live tracking follows a circle. A switch; measured on and off:
docs/notes/patient-eye.md."""

SHAPE_SD_MM = 0.65
"""The globe centre's sd along the gaze (mm) where the model gives no globe shape (population
defaults, or a sphere): real globes are ellipsoids whose semi-axes differ from their mean by
up to ±0.5 mm each (docs/eye-model.md), and the sphere fitted through the limbus to one's
visible sclera puts the centre 1.5 times the axial semi-axis's difference from the others off
along the gaze: 0.62–0.72 mm sd for 11–13-mm globes (geometry alone, no rendering;
docs/notes/patient-eye.md)."""

MEASURED_GLOBE_SD_MM = 0.2
"""The sd (mm) of a globe radius or semi-axis the eye model gives (an MRI's), where the
physicist states none (:attr:`~eyeserver.eye.fit.EyeModel.globe_sd_mm`): the typical error of
an MRI-derived radius or ellipsoid semi-axis (docs/eye-model.md: the sub-voxel repeatability of
MRI ellipsoid fits and the 0.1–0.2 mm repeatability of MRI axial lengths; the larger). The fit
places the centre behind the limbus at the depth the model's shape gives, so this error moves
the centre along the gaze by ≈ 0.18 mm (sd) for a 12-mm globe."""

MODEL_ERROR_CENTRE_MM = 2.39
"""Scale (mm) of the error the fit's own covariances do not count (the limbus mistaken, the lids
taken for sclera, a globe that is no sphere), added per axis to a pose's centre sd as
``MODEL_ERROR_CENTRE_MM · (max(0, c₀ − c)/c)^MODEL_ERROR_POWER`` for its confidence ``c`` and
``c₀`` = :data:`MODEL_ERROR_BELOW_CONFIDENCE` (:func:`~eyeserver.eye.fit.model_error_sds`).
Calibrated on draws the benchmarks never report (seeds 7 and 8: 120 patient eyes, 48 with
biometry), so that 97.5 % of their errors lie within 2 sd (``scripts/calibrate_model_error.py``;
docs/notes/patient-eye.md, "Sixth session", "Seventh session" and, for these values, the fit as
it is since the twentieth, "Twenty-first session")."""

MODEL_ERROR_GAZE_DEG = 17.3
"""The same for the gaze's sd, degrees (calibrated with :data:`MODEL_ERROR_CENTRE_MM`)."""

MODEL_ERROR_BELOW_CONFIDENCE = 0.5
"""Poses this confident or more have none added: on the calibration draws their covariances
(with the globe's unknown shape and the MRI's error, :data:`MEASURED_GLOBE_SD_MM`) already
held every error within 2 sd (docs/notes/patient-eye.md, "Seventh session")."""

MODEL_ERROR_POWER = 0.5
"""How fast the unexplained error grows as the confidence falls (see
:data:`MODEL_ERROR_CENTRE_MM`): the power that left the narrowest sds covering the calibration
draws."""

MODEL_ERROR_MIN_CONFIDENCE = 0.01
"""The confidence below which the unexplained error stops growing (a pose of no confidence)."""

WELL_SEEN_POINTS = 300
"""Sclera points at which the confidence's point term reaches 1 − 1/e. Count; chosen by hand."""

WELL_SEEN_LIMBUS_POINTS = 100
"""The same when the limbus comes from the images: the sclera then only sets one number, the
globe's depth behind the limbus, from the points clear of lids and limbus. Count (image pixels
where the cloud was decimated); chosen by hand."""

IMPLAUSIBLE_RADIUS = 0.3
"""Scales the confidence of a pose whose globe radius lies outside the model's bounds
(:func:`~eyeserver.eye.fit.radius_bounds`): below the 0.5 that fails a verification. Factor;
chosen by hand."""

NO_GLOBE_FACTOR = 2.0
"""A globe whose fitted radius lies more than this factor outside the model's bounds
(:func:`~eyeserver.eye.fit.radius_bounds`) is no fit at all: refused
(:class:`~eyeserver.eye.fit.PoseError`) rather than reported at a low confidence. Factor;
chosen by hand. Measured: one patient eye of 60 (`eyeserver bench pose --poses 60`, a soft
limbus) gave a globe of 68 km at confidence 0.02."""

UNSEEN_LIMBUS = 0.3
"""Scales the confidence of a pose from the cloud alone when the images were there and showed
no limbus (lids shut, the eye turned away or hidden): below the 0.5 that fails a verification
and holds the beam. Factor; chosen by hand. Measured: shut lids on the simulated eye gave such a
pose 1.3 mm and 40–50° off with confidence up to 0.97 (the lids taken for the globe, their slit
for the limbus); the cloud's gaze is ≈ 5° off at best (4.8° median, p95 13° on 24 poses)."""

VOXEL_MM = 0.5
"""Side (mm) of the voxels whose mean points the globe search works on (averaging ≈ 50 points
per voxel cuts the noise enough for curvature at a millimetre's scale). Chosen by hand."""

NORMAL_REACH_MM = 1.6
"""Radius (mm) of each voxel's neighbourhood whose PCA gives its normal. Chosen by hand."""

VOTED_CENTRE_MM = 0.5
"""How far (mm) the centre the voxels' normals vote for (:func:`~eyeserver.eye.fit.
_hough_centre`) may lie from the globe's (it is refined later): a shell counts as the globe's
when its radius lies within the model's bounds widened by this. Chosen by hand. Measured
without it: a held radius of 12 mm ± 5 % missed the sclera's peak at 11.35 mm on 2 of 30 noise
draws of an eye at rest, and on 4 of 60 draws of another noise generator."""

SHELL_BAND_MM = 0.25
"""Half-width (mm) of the band about a sphere whose points count as on it: a hypothesis's
support in the LO-MSAC shell search and its last local optimisation, and the one-shot fit's
last refining band (:func:`~eyeserver.eye.fit.fit_eye`). Chosen by hand."""

MSAC_LOCAL_MM = 6.0
"""Radius (mm) of the neighbourhood a shell hypothesis's four points are drawn from. Chosen by
hand."""

MSAC_HYPOTHESES = 400
"""Sphere hypotheses drawn per shell in the LO-MSAC shell search. Count; chosen by hand."""

BOUNDARY_SECTORS = 36
"""Azimuthal sectors (10° each) of the sclera's directions whose innermost points outline the
hole the cornea leaves (the cloud-only gaze). Count; chosen by hand."""

CONE_POINTS = 1500
"""Directions subsampled for the widest-empty-cone search of the cloud-only gaze (its score is
a high percentile). Count; chosen by hand."""

EDGE_IS_LIMBUS_MM = 0.5
"""The hole's edge circle gives the cloud-only gaze only where its radius lies within this (mm)
of the model's limbus radius; else the empty cone's axis does. Chosen by hand."""

# --- Live tracking's warm fit (track.py) ------------------------------------------------------

WARM_FIT_BAND_MM = 1.5
"""Points this far (mm) from the last sphere (or its lid shell) take part in the warm fit; the
sclera's shell is looked for within it of the last radius. Chosen by hand."""

WARM_FIT_COARSE_BANDS_MM = (WARM_FIT_BAND_MM, 1.0, 0.7)
"""Half-widths (mm) of the warm fit's first passes where no lid shell is seen (the sclera alone
is searched in wider bands), before :data:`WARM_FIT_REFINE_BANDS_MM`. Chosen by hand."""

WARM_FIT_REFINE_BANDS_MM = (0.45, 0.3, 0.25, 0.2)
"""Half-widths (mm) of the warm fit's refining passes, from a seed good to ≈ 0.5 mm: the bands
of the one-shot fit's refinement (0.45, 0.3 and :data:`SHELL_BAND_MM`;
:func:`~eyeserver.eye.fit.fit_eye`) and a last one of 0.2 mm. Chosen by hand."""

MAX_LID_POINTS = 4000
"""Most lid-shell points a warm-fit pass uses (a fixed subsample, weighted up: the lid shell
only pins the depth). Count; chosen by hand."""

WINDOW_QUANTUM_PX = 32
"""Windows are rounded out to multiples of this (pixels), so a still eye keeps one window.
Chosen by hand."""

LID_REACH_MM = 3.0
"""The lids (or retractors) rest up to this far (mm) outside the globe (the outermost lid shell
:func:`~eyeserver.eye.fit.fit_eye` accepts)."""

FRONT_HALF_ANGLE_DEG = 50.0
"""The window holds the cap of the lid shell within this angle (degrees) of +Z: the limbus of a
gaze up to ≈ 25° off +Z with the limbus search's margin around it, and the sclera and lids beside
it. Measured on the simulated eye: poses from windows of 65°, 50°, 40° and 30° were the same (to
the printed 0.001 mm and 0.0001), the reconstruction 57, 42, 26 and 18 ms; 50° keeps room for
the gaze to turn and for the cloud-only fit's lid shell."""

LIMBUS_HALF_ANGLE_DEG = 35.0
"""Once the last frame's limbus was found in the images, the window holds the cap within this
angle (degrees) of its gaze: the limbus after a saccade the limbus search follows (≤ 12°) and a
ring of sclera beside it, all the pose from the images needs. Measured on three rendered
saccades of 8° (one unit, radius held): poses from 50° about +Z and 35° or 40° about the last
gaze within 0.0004 mm and 0.001° of each other, the reconstruction 38–43, 25–45 and 20–26 ms."""

MOTION_MM = 1.5
"""The window's allowance (mm) for the eye's motion since the last pose. Chosen by hand."""

PAD_PERIODS = 1.5
"""The window's padding in fringe periods: the band-pass corrupts a period at the border
(masked), and the fringe order's check needs the other camera's view around each point. Chosen
by hand."""

LIDS_COVER_SHARE = 0.3
"""The share of the ring's points (:func:`~eyeserver.eye.track.lids_closed`) that shut lids
leave inside the limbus at least (as the areas go, ≈ 0.9 when they cover the disc whole).
Share; chosen by hand."""
