"""A trigger made of the cameras' own software trigger: ``TriggerSoftware`` sent to each camera
of a step, for rigs without a trigger controller (Aravis's fake cameras, a bench rig).

In a treatment room a trigger controller's output line exposes the cameras of a unit and strobes
its LED at once, so exposures start within microseconds of the pulse. Here each pulse is a
command per camera over the network: the step's cameras start a few hundred microseconds to a
few milliseconds apart, and the projectors light only if they are continuous or their
controller is wired to the cameras' exposure-active outputs. Good for a whole daemon run on fake
devices and for benches; a clinic's rig uses the trigger controller.
"""

from __future__ import annotations

import threading
from typing import Protocol, runtime_checkable

from eyeserver.errors import ConfigError, DeviceValueError
from eyeserver.hardware.base import Camera, PacedTrigger, TriggerPulse, TriggerStep
from eyeserver.hardware.registry import DriverContext, register_driver
from eyeserver.hardware.rig import RIG_CAMERAS

__all__ = ["GenicamTrigger"]


@runtime_checkable
class SoftwareTriggered(Protocol):
    """A camera that exposes on a command (:meth:`GenicamCamera.software_trigger
    <eyeserver.hardware.drivers.genicam.GenicamCamera.software_trigger>`)."""

    def software_trigger(self) -> None: ...


@register_driver("trigger", "GenicamTrigger")
class GenicamTrigger(PacedTrigger):
    """Pulses as software triggers of the rig's cameras, timed on the rig's clock.

    Parameters
    ----------
    device_id : str
        The trigger's id.
    context : DriverContext
        The rig's clock, and its cameras under :data:`~eyeserver.hardware.rig.RIG_CAMERAS`
        (:func:`~eyeserver.hardware.rig.build_rig` puts them there).
    """

    def __init__(self, device_id: str, *, context: DriverContext) -> None:
        super().__init__(device_id, context.clock)
        cameras = context.resources.get(RIG_CAMERAS)
        if not isinstance(cameras, dict):
            raise ConfigError(f"trigger {device_id!r}: GenicamTrigger needs the rig's cameras "
                              "(build it with the rig, from a room file)")
        self._cameras: dict[str, Camera] = cameras
        self._triggered: dict[str, SoftwareTriggered] = {}
        self._fire_lock = threading.Lock()
        self._pulse_index = 0
        self._position = 0

    def _do_open(self) -> None:
        with self._fire_lock:
            self._pulse_index = 0
            self._position = 0

    def _do_close(self) -> None:
        self.stop()

    def _apply_rate_hz(self, value: float) -> None:
        pass  # the paced thread reads the rate at every pulse

    def _apply_sequence(self, steps: tuple[TriggerStep, ...]) -> None:
        triggered: dict[str, SoftwareTriggered] = {}
        for n, step in enumerate(steps):
            for camera_id in step.cameras:
                camera = self._cameras.get(camera_id)
                if not isinstance(camera, SoftwareTriggered):
                    raise DeviceValueError(self.id, f"sequence step {n} names camera "
                                                    f"{camera_id!r}, which has no software "
                                                    "trigger in this rig")
                triggered[camera_id] = camera
        with self._fire_lock:
            self._sequence = steps
            self._triggered = triggered
            self._position = 0

    def _fire(self, at_ns: int | None) -> TriggerPulse:
        # A pulse scheduled ahead waits for its moment: nothing here can fire later by itself.
        if at_ns is not None:
            wait_s = (at_ns - self._clock.now_ns()) / 1e9
            if wait_s > 0:
                self._clock.sleep(wait_s)
        with self._fire_lock:
            step = self._sequence[self._position % len(self._sequence)]
            self._position += 1
            pulse = TriggerPulse(index=self._pulse_index, t_ns=self._clock.now_ns(), step=step)
            self._pulse_index += 1
            for camera_id in step.cameras:
                self._triggered[camera_id].software_trigger()
            return pulse
