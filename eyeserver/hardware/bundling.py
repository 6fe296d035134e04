"""From the rig's acquired steps to the frames of a capture bundle (FORMATS.md).

The daemon's captures and the simulated room's recorded sessions both turn
:meth:`Rig.acquire <eyeserver.hardware.rig.Rig.acquire>` results into bundle frames the same way,
so a bundle looks the same whoever wrote it.
"""

from __future__ import annotations

from collections.abc import Sequence

from eyeserver.hardware.rig import AcquiredStep, Rig
from eyeserver.io import BundleFrameData

__all__ = ["bundle_bit_depth", "bundle_frames"]


def bundle_frames(steps: Sequence[AcquiredStep], z_mm: float | None = None
                  ) -> list[BundleFrameData]:
    """One bundle frame per trigger pulse: its cameras' images, lit projectors and time.

    Parameters
    ----------
    steps : sequence of AcquiredStep
        What :meth:`Rig.acquire` or :meth:`Rig.acquire_unlit` returned.
    z_mm : float, optional
        Nominal Z of a flat surface (plate and reference bundles only), mm.

    Returns
    -------
    list of BundleFrameData
        In pulse order; ``t_ns`` is the first camera's mid-exposure time.
    """
    return [BundleFrameData(images={cid: f.image for cid, f in step.frames.items()},
                            z_mm=z_mm, projectors_on=tuple(step.pulse.step.projectors),
                            t_ns=next(iter(step.frames.values())).meta.t_ns)
            for step in steps]


def bundle_bit_depth(rig: Rig, frames: Sequence[BundleFrameData]) -> int | None:
    """The ``bit_depth`` to write for ``frames``: the deepest camera's, or None for 8 bits."""
    depth = max(rig.camera(c).bit_depth for f in frames for c in f.images)
    return depth if depth > 8 else None
