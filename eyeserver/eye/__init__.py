"""The eye: its model, its pose fitted once from a capture, and live tracking from frame to frame
(docs/design.md §4 step 8).

It sits on top of :mod:`eyeserver.pipeline` (it reads the reconstruction's clouds, cameras and
phases; the pipeline never imports it) and beside :mod:`eyeserver.service`, which uses it.
Pure numerics, as the pipeline's: arrays in, arrays out; no I/O, no logging.

- :mod:`~eyeserver.eye.fit`: the eye model (:class:`EyeModel`), the one-shot fit
  (:func:`fit_eye`) and the pose it gives (:class:`EyePose`);
- :mod:`~eyeserver.eye.limbus`: the limbus found in the fringe images (:class:`LimbusView` is one
  camera's image with its calibration) and the globe that carries it;
- :mod:`~eyeserver.eye.sclera`: the sclera measured again from its own fringes;
- :mod:`~eyeserver.eye.track`: the warm-started fit of live tracking (:func:`track_eye`) and
  the image window the eye is in (:func:`pose_window`);
- :mod:`~eyeserver.eye.tunables`: every constant of the four, what it is, its unit and where its
  value comes from.

What was measured, and the variants not used: docs/notes/limbus.md, docs/notes/sclera.md,
docs/notes/tracking.md (and docs/notes/patient-eye.md for the patient's eye).
"""

from eyeserver.eye.fit import (
    LIMBUS_FROM_IMAGES,
    CloudLike,
    EyeModel,
    EyePose,
    PoseError,
    fit_eye,
)
from eyeserver.eye.limbus import LimbusView, fringe_removed
from eyeserver.eye.track import pose_window, track_eye

__all__ = ["LIMBUS_FROM_IMAGES", "CloudLike", "EyeModel", "EyePose", "LimbusView", "PoseError",
           "fit_eye", "fringe_removed", "pose_window", "track_eye"]
