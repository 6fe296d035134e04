"""The fringe mask of one camera image (docs/design.md §4 step 2) on synthetic fringes."""

from __future__ import annotations

import numpy as np

from eyeserver.pipeline.demodulate import Carrier
from eyeserver.pipeline.phase_height import PhaseHeightModel
from eyeserver.pipeline.reconstruct import CalibratedCamera, camera_phase

HEIGHT, WIDTH = 200, 240
CARRIER = Carrier((0.0, 0.1))


def _camera() -> CalibratedCamera:
    model = PhaseHeightModel((10.0, 1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
                             0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, (-10.0, 25.0))
    K = np.array([[400.0, 0, WIDTH / 2], [0, 400.0, HEIGHT / 2], [0, 0, 1]])
    return CalibratedCamera("S1", K, np.zeros(5), np.eye(3), np.array([0.0, 0.0, 250.0]), model,
                            CARRIER, np.zeros((HEIGHT, WIDTH), np.float32), border_px=10)


def _fringes(amplitude: np.ndarray, background: float = 100.0) -> np.ndarray:
    j = np.arange(WIDTH)[None, :]
    return background + amplitude * np.cos(2 * np.pi * 0.1 * j)


def test_low_modulation_and_the_border_are_masked() -> None:
    amplitude = np.full((HEIGHT, WIDTH), 60.0)
    amplitude[80:120, 100:160] = 3.0  # a dark patch: a shadow or a fiducial's paint
    phase = camera_phase(_camera(), _fringes(amplitude))
    assert not phase.valid[90:110, 110:150].any()
    # The frame: a whole period (border_px) where the carrier crosses it, half a period where
    # the fringes run into it, and no erosion beyond (the image is continued past its frame).
    assert not phase.valid[:, -10:].any() and phase.valid[40:60, -11].all()
    assert not phase.valid[:5].any() and phase.valid[5:10, 40:200].all()
    assert phase.valid[40:60, 40:200].all()
    # About half a period around every masked area goes too: the band-pass spreads its edge.
    assert not phase.valid[80:120, 97:100].any()


def test_heavy_saturation_is_masked_light_clipping_is_not() -> None:
    amplitude = np.full((HEIGHT, WIDTH), 60.0)
    image = _fringes(amplitude)
    image[40:160, 20:110] = np.minimum(image[40:160, 20:110] * 3.0, 255.0)  # most clipped
    image[40:160, 130:220] = np.minimum(image[40:160, 130:220] + 100.0, 255.0)  # crests only
    clipped = np.clip(image, 0, 255).astype(np.uint8)
    phase = camera_phase(_camera(), clipped, saturation_dn=255)
    assert not phase.valid[60:140, 40:90].any()
    assert phase.valid[60:140, 150:200].mean() > 0.95
    # Without a full scale no saturation check is made.
    assert camera_phase(_camera(), clipped).valid[60:140, 40:90].mean() > 0.5
