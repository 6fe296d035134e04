"""The projector contract: what every :class:`~eyeserver.hardware.base.Projector` driver (an LED
projector's channel of a strobe controller) guarantees, run over the simulated projector and each
real driver on its emulated controller.

==================  ===========================================================================
``sim``             :class:`~eyeserver.hardware.sim.drivers.SimProjector` in a tiny simulated room
``gardasoft-pty``   :class:`~eyeserver.hardware.drivers.gardasoft.GardasoftProjector` on the
                    Gardasoft RT emulator on a pty
``opto-rtu``        :class:`~eyeserver.hardware.drivers.modbus.OptoProjector` on the Modbus RTU
                    emulator on a pty
``opto-tcp``        the same driver on the Modbus TCP emulator on loopback
==================  ===========================================================================

Nothing here needs more than the Python environment, so no case is ever skipped. The drivers'
own files test their protocols, faults and recovery.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

import pytest

from eyeserver.errors import DeviceNotOpenError, DeviceValueError
from eyeserver.hardware.base import Projector
from eyeserver.hardware.drivers.gardasoft import GardasoftProjector
from eyeserver.hardware.drivers.modbus import OptoProjector
from eyeserver.hardware.emulators.gardasoft import GardasoftEmulator
from eyeserver.hardware.emulators.modbus import OptoController, OptoRtuEmulator, OptoTcpEmulator
from eyeserver.hardware.registry import DriverContext
from eyeserver.hardware.sim.drivers import SimProjector, sim_driver_context
from tests.hardware.lifecycle import check_open_close_idempotent
from tests.hardware.simroom import FakeRoom

REPLY_TIMEOUT_S = 0.5
"""Per-reply timeout of the drivers: short, since the emulators answer at once."""


@contextmanager
def _sim() -> Iterator[Projector]:
    projector = SimProjector("P2", context=sim_driver_context(FakeRoom()))
    try:
        yield projector
    finally:
        projector.close()


@contextmanager
def _gardasoft(tmp_path: Path) -> Iterator[Projector]:
    with GardasoftEmulator(channels=2, rating_a=3.0, link_dir=tmp_path) as emulator:
        projector = GardasoftProjector("P1", context=DriverContext(), port=emulator.port,
                                       channel=1, max_current_a=2.0, pulse_us=150.0,
                                       delay_us=20.0, timeout_s=REPLY_TIMEOUT_S)
        try:
            yield projector
        finally:
            projector.close()


@contextmanager
def _opto(emulator: OptoRtuEmulator | OptoTcpEmulator) -> Iterator[Projector]:
    with emulator:
        projector = OptoProjector("P1", context=DriverContext(), **emulator.driver_options(),
                                  channel=1, max_current_ma=2000.0, pulse_us=150.0,
                                  delay_us=20.0, timeout_s=REPLY_TIMEOUT_S)
        try:
            yield projector
        finally:
            projector.close()


@pytest.fixture(params=["sim", "gardasoft-pty", "opto-rtu", "opto-tcp"])
def projector(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Projector]:
    makers: dict[str, Callable[[], AbstractContextManager[Projector]]] = {
        "sim": _sim,
        "gardasoft-pty": lambda: _gardasoft(tmp_path),
        "opto-rtu": lambda: _opto(OptoRtuEmulator(OptoController(channels=4, rating_ma=3000),
                                                  link_dir=tmp_path)),
        "opto-tcp": lambda: _opto(OptoTcpEmulator(OptoController(channels=4, rating_ma=3000))),
    }
    with makers[request.param]() as made:
        yield made


def test_open_close_idempotent(projector: Projector) -> None:
    check_open_close_idempotent(projector)


def _call(projector: Projector, call: str) -> None:
    if call == "set_enabled":
        projector.set_enabled(False)
    elif call == "set_intensity":
        projector.set_intensity(0.5)
    elif call == "set_strobe":
        projector.set_strobe(False)
    else:
        projector.check()


CALLS = ["set_enabled", "set_intensity", "set_strobe", "check"]


@pytest.mark.parametrize("call", CALLS)
def test_use_before_open_raises(projector: Projector, call: str) -> None:
    with pytest.raises(DeviceNotOpenError) as info:
        _call(projector, call)
    assert info.value.device_id == projector.id


@pytest.mark.parametrize("call", CALLS)
def test_use_after_close_raises(projector: Projector, call: str) -> None:
    projector.open()
    projector.close()
    with pytest.raises(DeviceNotOpenError):
        _call(projector, call)


def test_defaults(projector: Projector) -> None:
    assert projector.enabled is True
    assert projector.strobe is True
    assert 0.0 <= projector.intensity <= 1.0


def test_settings_round_trip(projector: Projector) -> None:
    projector.open()
    projector.set_enabled(False)
    projector.set_strobe(False)
    projector.set_intensity(0.25)
    assert (projector.enabled, projector.strobe, projector.intensity) == (False, False, 0.25)
    projector.set_enabled(True)
    projector.set_strobe(True)
    assert (projector.enabled, projector.strobe) == (True, True)


def test_settings_survive_a_reopen(projector: Projector) -> None:
    projector.open()
    projector.set_intensity(0.25)
    projector.set_strobe(False)
    projector.close()
    projector.open()
    assert (projector.intensity, projector.strobe) == (0.25, False)


def test_a_healthy_device_passes_its_check(projector: Projector) -> None:
    projector.open()
    projector.check()
    projector.set_intensity(0.75)
    projector.check()


@pytest.mark.parametrize("value", [-0.1, 1.01, 2.0])
def test_intensity_range(projector: Projector, value: float) -> None:
    projector.open()
    projector.set_intensity(0.5)
    with pytest.raises(DeviceValueError) as info:
        projector.set_intensity(value)
    assert info.value.device_id == projector.id
    assert projector.intensity == 0.5


def test_describe(projector: Projector) -> None:
    info = projector.describe()
    assert info["id"] == projector.id
    assert info["kind"] == "projector"
    assert {"enabled", "intensity", "strobe"} <= info.keys()
