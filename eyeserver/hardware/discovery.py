"""What is attached to this machine, for the one writing a room file (``eyeserver devices
discover``, issue 38): GenICam cameras, serial ports and, when asked, which of eyeserver's
controllers answers on each port, each with the room-file entry that would use it.

Three searches, each returning plain data classes:

* :func:`search_cameras`: the cameras Aravis finds by its discovery broadcast
  (:func:`~eyeserver.hardware.drivers.genicam.list_cameras`), and cameras asked for directly at
  an address the broadcast does not reach. Without PyGObject or Aravis the search says what to
  install instead of failing.
* :func:`list_serial_ports`: the system's serial ports (pyserial's ``comports()``) and any paths
  given (a pty, a symlink: ``comports()`` lists neither), with the stable
  ``/dev/serial/by-id`` link of each where udev made one. Nothing is opened.
* :func:`probe_port`: which controller answers on one port, by the drivers' own probes in turn
  -- :func:`Gardasoft <eyeserver.hardware.drivers.gardasoft.probe>` (``VR``),
  :func:`Zaber <eyeserver.hardware.drivers.zaber.probe>` (the ``/`` broadcast),
  :func:`Opto Modbus RTU <eyeserver.hardware.drivers.modbus.probe>` (DEVICE_TYPE) -- stopping at
  the first that answers. **It writes bytes to the port**, to a device that may be anything, so
  it runs only when asked (``--probe``). A port another process holds open (the running daemon,
  say) is not probed: a probe's bytes and replies would mix with that process's. A port that
  cannot be opened (missing, busy, access denied) is reported, never raised.

:func:`discover` runs them and numbers the room-file entries (:class:`RoomSnippet`): cameras
``S1``, ``S2`` …, projectors ``P1`` …, stages ``Z1`` …. An entry holds what discovery knows (the
port, preferring its ``/dev/serial/by-id`` link, which survives replugging and reboots where
``/dev/ttyUSB0`` does not; the camera's address) and names the options only the user can know
(the LED's current, the stage's microstep) in :attr:`RoomSnippet.to_set`.
"""

from __future__ import annotations

import errno
import inspect
import logging
import os
import stat
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final, Literal

from eyeserver.errors import DeviceDisconnectedError, DeviceError
from eyeserver.hardware.drivers import gardasoft, genicam, modbus, zaber
from eyeserver.hardware.drivers.gardasoft import GardasoftProjector
from eyeserver.hardware.drivers.genicam import FoundCamera, GenicamCamera
from eyeserver.hardware.drivers.modbus import OptoProjector
from eyeserver.hardware.drivers.zaber import ZaberStage

__all__ = [
    "BY_ID_DIR",
    "CameraEntry",
    "CameraSearch",
    "Controller",
    "Discovery",
    "ModbusSettings",
    "PortProbe",
    "RoomSnippet",
    "SerialPort",
    "SnippetIds",
    "Unanswered",
    "discover",
    "list_serial_ports",
    "port_users",
    "probe_port",
    "search_cameras",
]

_log = logging.getLogger(__name__)

try:  # POSIX only, as are the serial ports this lists
    import termios

    _TERMIOS_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # pragma: no cover - not on the Linux hosts eyeserver runs on
    _TERMIOS_ERRORS = ()

BY_ID_DIR: Final = Path("/dev/serial/by-id")
"""Where udev links each USB serial port under a name made of its vendor, product and serial
number: the same name after a replug or a reboot, whichever ``ttyUSBn`` the port became."""

DEFAULT_TIMEOUT_S: Final = 0.3
"""How long each probe waits for an answer, seconds: USB-serial adapters and the controllers
answer within tens of milliseconds, and a silent port costs one wait per probe."""

ROOM_FILE_DOC: Final = "docs/room-file.md, 'A room of real devices'"

_NOT_GIVEN: Final = {"n/a", ""}
"""What pyserial reports for a field the port does not have."""


# --- the room-file entries ----------------------------------------------------------------------


@dataclass(frozen=True)
class RoomSnippet:
    """The room-file entry that would use a found device.

    Attributes
    ----------
    table : {"devices", "stage"}
        ``devices`` for a ``[[devices]]`` entry (cameras, projectors), ``stage`` for the
        ``[stage]`` table.
    kind : str
        The device kind (``camera``, ``projector``, ``stage``); written only in ``[[devices]]``.
    id : str
        A suggested device id.
    driver : str
        The registered driver's name.
    options : dict
        The driver's options discovery knows (port, address, unit id).
    to_set : tuple of str
        The driver's required options only the user knows (currents, timing, microstep): the
        room file is invalid until they are added.
    comment : str
        What was found, for the line above the entry.
    """

    table: Literal["devices", "stage"]
    kind: str
    id: str
    driver: str
    options: dict[str, object]
    to_set: tuple[str, ...]
    comment: str

    def toml(self) -> str:
        """The entry as TOML lines, with comments saying what it is and what to add."""
        lines = [f"# {self.comment}"]
        if self.to_set:
            lines.append(f"# add to options: {', '.join(self.to_set)} ({ROOM_FILE_DOC})")
        options = ", ".join(f"{key} = {_toml_value(value)}" for key, value in self.options.items())
        if self.table == "devices":
            lines += ["[[devices]]", f"kind = {_toml_value(self.kind)}"]
        else:
            lines.append("[stage]")
        lines += [f"id = {_toml_value(self.id)}", f"driver = {_toml_value(self.driver)}",
                  f"options = {{ {options} }}" if options else "options = {}"]
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """The entry as JSON-ready data, its TOML text included."""
        return {"table": self.table, "kind": self.kind, "id": self.id, "driver": self.driver,
                "options": dict(self.options), "to_set": list(self.to_set),
                "comment": self.comment, "toml": self.toml()}


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    # TOML's basic strings take JSON's escapes; a path or an address needs none of the others.
    text = str(value)
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


class SnippetIds:
    """Hands out the suggested device ids, in the order the devices are found: ``S1``, ``S2``
    … for cameras (as the simulated room names them), ``P1`` … for projectors, ``Z1`` … for
    stages."""

    _PREFIXES: Final = {"camera": "S", "projector": "P", "stage": "Z"}

    def __init__(self) -> None:
        self._counts: dict[str, int] = {}

    def take(self, kind: str) -> str:
        """The next id for a device of ``kind``."""
        prefix = self._PREFIXES.get(kind, kind[:1].upper())
        self._counts[prefix] = self._counts.get(prefix, 0) + 1
        return f"{prefix}{self._counts[prefix]}"


def _required_options(driver: type, given: Iterable[str]) -> tuple[str, ...]:
    """The driver's required keyword options not in ``given``, in its signature's order (what
    the registry checks a room file against, so the two cannot disagree)."""
    known = {"device_id", "context", *given}
    return tuple(name for name, parameter in inspect.signature(driver).parameters.items()
                 if parameter.kind is inspect.Parameter.KEYWORD_ONLY
                 and parameter.default is inspect.Parameter.empty and name not in known)


def _snippet(table: Literal["devices", "stage"], kind: str, driver: type,
             options: dict[str, object], comment: str, ids: SnippetIds) -> RoomSnippet:
    return RoomSnippet(table=table, kind=kind, id=ids.take(kind), driver=driver.__name__,
                       options=options, to_set=_required_options(driver, options),
                       comment=comment)


# --- cameras ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraEntry:
    """A camera found, how (``broadcast``: Aravis's discovery; ``address``: asked at an address
    given), and its room-file entry."""

    camera: FoundCamera
    found_by: Literal["broadcast", "address"]
    snippet: RoomSnippet

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data: the camera's fields, ``found_by`` and ``room_file``."""
        return {**_fields(self.camera), "found_by": self.found_by,
                "room_file": self.snippet.to_dict()}


@dataclass(frozen=True)
class Unanswered:
    """An address given where no camera answered, and why (Aravis's message)."""

    address: str
    reason: str


@dataclass(frozen=True)
class CameraSearch:
    """The cameras found; ``unavailable`` says why there was no search at all (Aravis or
    PyGObject missing, and what to install); ``unanswered`` the addresses given where no camera
    answered."""

    cameras: list[CameraEntry]
    unavailable: str | None = None
    unanswered: list[Unanswered] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data."""
        return {"searched": self.unavailable is None, "unavailable": self.unavailable,
                "cameras": [entry.to_dict() for entry in self.cameras],
                "unanswered": [_fields(item) for item in self.unanswered]}


def _camera_snippet(camera: FoundCamera, ids: SnippetIds) -> RoomSnippet:
    # A GigE Vision camera is named by its IP address: asked directly, it needs no broadcast
    # (which a router does not pass). A USB3 Vision camera has only its device id.
    if camera.protocol == "GigE Vision" and camera.address:
        address = camera.address
    else:
        address = camera.device_id or camera.address or ""
    what = " ".join(part for part in (camera.vendor, camera.model) if part) or "camera"
    serial = f", serial {camera.serial}" if camera.serial else ""
    protocol = f" ({camera.protocol})" if camera.protocol else ""
    return _snippet("devices", "camera", GenicamCamera, {"address": address},
                    f"{what}{serial}{protocol}", ids)


def search_cameras(addresses: Sequence[str] = (), *,
                   ids: SnippetIds | None = None) -> CameraSearch:
    """The GenICam cameras Aravis finds, and those at ``addresses``.

    Aravis's discovery broadcast goes first (about a second); an address (IP address or Aravis
    device id) it did not find is then asked directly, for a camera the broadcast cannot reach.
    No camera is left opened.

    Parameters
    ----------
    addresses : sequence of str
        Cameras to ask for directly.
    ids : SnippetIds, optional
        Hands out the room-file ids; a fresh one by default.
    """
    ids = ids if ids is not None else SnippetIds()
    try:
        found = genicam.list_cameras()
    except ImportError as exc:
        return CameraSearch(cameras=[], unavailable=f"GenICam cameras not searched: {exc}")
    entries = [CameraEntry(camera, "broadcast", _camera_snippet(camera, ids)) for camera in found]
    known = {name for camera in found for name in (camera.address, camera.device_id) if name}
    unanswered = []
    for address in dict.fromkeys(addresses):  # each once, in the order given
        if address in known:
            continue
        try:
            camera = genicam.identify_camera(address)
        except DeviceError as exc:
            unanswered.append(Unanswered(address, exc.reason))
            continue
        entries.append(CameraEntry(camera, "address", _camera_snippet(camera, ids)))
    return CameraSearch(cameras=entries, unanswered=unanswered)


# --- serial ports -------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModbusSettings:
    """The serial settings the Modbus RTU probe asks at: by default the controller's factory
    settings as the driver assumes them (unit 1, 19200 baud, even parity)."""

    unit_id: int = modbus.PROBE_UNIT_ID
    baudrate: int = modbus.PROBE_BAUDRATE
    parity: Literal["E", "O", "N"] = modbus.PROBE_PARITY


@dataclass(frozen=True)
class Controller:
    """A controller that answered a probe: what it is (``name``), what it said
    (``identification``), and its room-file entry."""

    name: str
    identification: str
    snippet: RoomSnippet

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data."""
        return {"name": self.name, "identification": self.identification,
                "room_file": self.snippet.to_dict()}


@dataclass(frozen=True)
class PortProbe:
    """What probing one port found.

    ``controllers`` answered (several for a Zaber daisy chain); ``problem`` says why the port
    was not probed or not to the end (busy, access denied, missing), None when it was;
    ``notes`` what a single probe could not do (the Modbus probe's parity on a pty).
    """

    controllers: list[Controller] = field(default_factory=list)
    problem: str | None = None
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data."""
        return {"problem": self.problem, "notes": list(self.notes),
                "controllers": [controller.to_dict() for controller in self.controllers]}


@dataclass(frozen=True)
class SerialPort:
    """A serial port.

    Attributes
    ----------
    device : str
        Its path (``/dev/ttyUSB0``), or the path given for it.
    by_id : str or None
        Its ``/dev/serial/by-id`` link, where udev made one (USB adapters).
    usb_id : str or None
        USB vendor and product id, ``vvvv:pppp`` in hex (``0403:6001``: an FTDI FT232R).
    serial_number, manufacturer, description : str or None
        As the USB adapter reports them.
    listed_by : {"system", "given"}
        Found in the system's list, or given (a pty, a link: the system lists neither).
    present : bool
        Whether the path exists.
    probe : PortProbe or None
        What probing found; None when it was not probed.
    """

    device: str
    by_id: str | None
    usb_id: str | None
    serial_number: str | None
    manufacturer: str | None
    description: str | None
    listed_by: Literal["system", "given"]
    present: bool
    probe: PortProbe | None = None

    @property
    def room_path(self) -> str:
        """The path a room file should name: the ``/dev/serial/by-id`` link where there is
        one, which stays the same when ``ttyUSBn`` numbers change."""
        return self.by_id or self.device

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data."""
        data = {name: value for name, value in _fields(self).items() if name != "probe"}
        return {**data, "probe": self.probe.to_dict() if self.probe is not None else None}


def _known(value: object) -> str | None:
    text = str(value) if value is not None else ""
    return None if text in _NOT_GIVEN else text


def _by_id_links(by_id_dir: Path) -> dict[str, str]:
    """The by-id links of ``by_id_dir`` by the real path of the port each points to."""
    try:
        links = sorted(by_id_dir.iterdir())
    except OSError:  # no USB serial adapter since boot: udev made no directory
        return {}
    return {os.path.realpath(link): str(link) for link in links}


def list_serial_ports(given: Sequence[str] = (), *,
                      by_id_dir: Path = BY_ID_DIR) -> list[SerialPort]:
    """The system's serial ports, then each of ``given`` that is not one of them (a pty or a
    link, which the system's list leaves out). Nothing is opened.

    Parameters
    ----------
    given : sequence of str
        More port paths; one that names a port listed already (a by-id link) is not repeated.
    by_id_dir : Path
        Where the stable links are (:data:`BY_ID_DIR`).
    """
    # Looked up here, not imported by name, so that a test can stand in for the machine's list.
    from serial.tools import list_ports

    links = _by_id_links(by_id_dir)
    ports: list[SerialPort] = []
    seen: set[str] = set()
    for info in sorted(list_ports.comports(), key=lambda info: str(info.device)):
        real = os.path.realpath(info.device)
        seen.add(real)
        usb_id = (f"{info.vid:04x}:{info.pid:04x}" if info.vid is not None
                  and info.pid is not None else None)
        ports.append(SerialPort(
            device=str(info.device), by_id=links.get(real), usb_id=usb_id,
            serial_number=_known(info.serial_number), manufacturer=_known(info.manufacturer),
            description=_known(info.description), listed_by="system", present=True))
    for path in given:
        real = os.path.realpath(path)
        if real in seen:
            continue
        seen.add(real)
        ports.append(SerialPort(device=path, by_id=links.get(real), usb_id=None,
                                serial_number=None, manufacturer=None, description=None,
                                listed_by="given", present=os.path.exists(path)))
    return ports


def port_users(paths: Iterable[str]) -> dict[str, list[str]]:
    """The other processes holding each of ``paths`` open, as ``"PID (name)"``.

    Read from ``/proc/*/fd``: another user's processes are visible only to root, so as an
    ordinary user a port the daemon (running as its own user) holds looks free. This process
    is left out.
    """
    wanted: dict[int, list[str]] = {}
    users: dict[str, list[str]] = {}
    for path in paths:
        users[path] = []
        try:
            status = os.stat(path)
        except OSError:
            continue
        if stat.S_ISCHR(status.st_mode):
            wanted.setdefault(status.st_rdev, []).append(path)
    if not wanted:
        return users
    own = os.getpid()
    for process in os.scandir("/proc"):
        if not process.name.isdigit() or int(process.name) == own:
            continue
        try:
            descriptors = os.listdir(f"/proc/{process.name}/fd")
        except OSError:  # gone since, or another user's
            continue
        for descriptor in descriptors:
            try:
                status = os.stat(f"/proc/{process.name}/fd/{descriptor}")
            except OSError:
                continue
            if stat.S_ISCHR(status.st_mode) and status.st_rdev in wanted:
                user = f"{process.name} ({_process_name(process.name)})"
                for path in wanted[status.st_rdev]:
                    if user not in users[path]:
                        users[path].append(user)
    return users


def _process_name(pid: str) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return "?"


def _errno(exc: BaseException) -> int | None:
    """The system's error number behind ``exc`` (pyserial's SerialException carries it)."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        number = getattr(current, "errno", None)
        if isinstance(number, int):
            return number
        # termios.error (pyserial configuring a file that is no terminal) has only its args.
        if (isinstance(current, _TERMIOS_ERRORS) and current.args
                and isinstance(current.args[0], int)):
            return current.args[0]
        current = current.__cause__ or current.__context__
    return None


def _open_problem(exc: DeviceDisconnectedError) -> str:
    """Why a port could not be probed, in words that say what to do."""
    number = _errno(exc)
    if number in (errno.EACCES, errno.EPERM):
        return ("access denied: the user needs read and write access to the port (on Debian, "
                "membership of the 'dialout' group; log in again after adding it)")
    if number == errno.EBUSY:
        return "busy: another program holds the port exclusively"
    if number in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
        return "missing: no device at this path (unplugged?)"
    if number in (errno.ENOTTY, errno.EISDIR):
        return "not a serial port (not a terminal device)"
    return f"unusable: {exc.reason}"


def probe_port(path: str, *, room_path: str | None = None,
               timeout_s: float = DEFAULT_TIMEOUT_S,
               modbus_settings: ModbusSettings | None = None, users: Sequence[str] = (),
               ids: SnippetIds | None = None) -> PortProbe:
    """Which of eyeserver's controllers answers on the serial port at ``path``.

    **Writes to the port**: the Gardasoft probe (``VR``), then the Zaber one (``/`` and
    ``get device.id``), then the Modbus RTU one (a read of register 0), stopping at the first
    that answers. Each only reads, so none changes a controller's settings, but an unknown
    device may take the bytes for anything. The port is closed after each probe. A port that
    cannot be opened is reported in :attr:`PortProbe.problem`, never raised.

    Parameters
    ----------
    path : str
        The port to open.
    room_path : str, optional
        The path the room-file entry names (the by-id link); ``path`` by default.
    timeout_s : float
        How long each probe waits for an answer, seconds.
    modbus_settings : ModbusSettings, optional
        Unit id, baud rate and parity of the Modbus probe (the factory settings by default).
    users : sequence of str
        Other processes holding the port open (:func:`port_users`): then nothing is sent.
    ids : SnippetIds, optional
        Hands out the room-file ids; a fresh one by default.
    """
    if timeout_s <= 0:
        raise ValueError(f"timeout_s must be positive, not {timeout_s}")
    ids = ids if ids is not None else SnippetIds()
    settings = modbus_settings or ModbusSettings()
    port = room_path or path
    if users:
        return PortProbe(problem=f"busy: open in process {', '.join(users)}; not probed (a "
                                 f"probe's bytes would mix with that program's)")
    try:
        version = gardasoft.probe(path, timeout_s)
        if version is not None:
            return PortProbe(controllers=[Controller(
                "Gardasoft RT controller", version, _snippet(
                    "devices", "projector", GardasoftProjector, {"port": port},
                    f"Gardasoft RT controller on {port}: {version}", ids))])
        chain = zaber.probe(path, timeout_s)
        if chain:
            return PortProbe(controllers=[_zaber_controller(device, port, ids)
                                          for device in chain])
    except DeviceDisconnectedError as exc:
        return PortProbe(problem=_open_problem(exc))
    try:
        identification = modbus.probe(path, timeout_s, unit_id=settings.unit_id,
                                      baudrate=settings.baudrate, parity=settings.parity)
    except DeviceDisconnectedError as exc:
        # The port opened for the probes before: what differs here is the parity (a pty takes
        # none), or pymodbus's exclusive lock on the port.
        _log.debug("%s", exc)
        return PortProbe(notes=[f"Modbus RTU probe not run: the port did not open at "
                                f"{_modbus_settings_text(settings)} (a port that takes no "
                                f"parity, such as a pty, needs parity N)"])
    if identification is None:
        return PortProbe()
    options: dict[str, object] = {"transport": "rtu", "port": port}
    defaults = ModbusSettings()
    for name in ("unit_id", "baudrate", "parity"):
        if getattr(settings, name) != getattr(defaults, name):
            options[name] = getattr(settings, name)
    return PortProbe(controllers=[Controller(
        "Opto Engineering-style Modbus RTU controller", identification, _snippet(
            "devices", "projector", OptoProjector, options,
            f"Opto Modbus RTU controller, unit {settings.unit_id} on {port} "
            f"({_modbus_settings_text(settings)}): {identification}", ids))])


def _modbus_settings_text(settings: ModbusSettings) -> str:
    stop_bits = 2 if settings.parity == "N" else 1
    return f"{settings.baudrate} baud 8{settings.parity}{stop_bits}"


def _zaber_controller(device: zaber.ZaberDevice, port: str, ids: SnippetIds) -> Controller:
    product = (f"product id {device.product_id}" if device.product_id is not None
               else "product id not given")
    identification = f"device {device.address}, {product}"
    return Controller("Zaber device", identification, _snippet(
        "stage", "stage", ZaberStage, {"port": port, "address": device.address},
        f"Zaber device {device.address} on {port} ({product}); the stage's axis is 1 unless "
        f"set", ids))


# --- all of it ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Discovery:
    """What :func:`discover` found: the camera search (None when not run), the serial ports
    (None when not listed), and whether the ports were probed."""

    cameras: CameraSearch | None
    serial_ports: list[SerialPort] | None
    probed: bool

    def snippets(self) -> list[RoomSnippet]:
        """Every room-file entry, cameras first, in the order found."""
        found = [entry.snippet for entry in self.cameras.cameras] if self.cameras else []
        for port in self.serial_ports or []:
            if port.probe is not None:
                found += [controller.snippet for controller in port.probe.controllers]
        return found

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready data (``eyeserver devices discover --json``)."""
        return {"probed": self.probed,
                "cameras": self.cameras.to_dict() if self.cameras is not None else None,
                "serial_ports": ([port.to_dict() for port in self.serial_ports]
                                 if self.serial_ports is not None else None)}


def discover(*, cameras: bool = True, addresses: Sequence[str] = (), serial_ports: bool = True,
             ports: Sequence[str] = (), probe: bool = False,
             timeout_s: float = DEFAULT_TIMEOUT_S, modbus_settings: ModbusSettings | None = None,
             by_id_dir: Path = BY_ID_DIR,
             progress: Callable[[str], None] | None = None) -> Discovery:
    """Search for cameras and list serial ports; with ``probe``, ask each port which controller
    answers.

    Parameters
    ----------
    cameras : bool
        Search for GenICam cameras (:func:`search_cameras`).
    addresses : sequence of str
        Camera addresses to ask directly as well.
    serial_ports : bool
        List the serial ports (:func:`list_serial_ports`).
    ports : sequence of str
        Port paths to list (and probe) besides the system's.
    probe : bool
        Probe every port listed (:func:`probe_port`): **writes bytes to each**.
    timeout_s : float
        How long each probe waits for an answer, seconds.
    modbus_settings : ModbusSettings, optional
        The Modbus probe's serial settings.
    by_id_dir : Path
        Where the stable port links are (:data:`BY_ID_DIR`).
    progress : callable, optional
        Told what is being searched as it begins (the searches take seconds).
    """
    if timeout_s <= 0:
        raise ValueError(f"timeout_s must be positive, not {timeout_s}")
    tell = progress or (lambda message: None)
    ids = SnippetIds()
    camera_search = None
    if cameras:
        tell("searching for GenICam cameras")
        camera_search = search_cameras(addresses, ids=ids)
    if not serial_ports:
        return Discovery(cameras=camera_search, serial_ports=None, probed=False)
    listed = list_serial_ports(ports, by_id_dir=by_id_dir)
    if probe:
        users = port_users(port.device for port in listed)
        probed = []
        for port in listed:
            tell(f"probing {port.device}")
            probed.append(replace(port, probe=probe_port(
                port.device, room_path=port.room_path, timeout_s=timeout_s,
                modbus_settings=modbus_settings, users=users.get(port.device, ()), ids=ids)))
        listed = probed
    return Discovery(cameras=camera_search, serial_ports=listed, probed=probe)


def _fields(instance: Any) -> dict[str, Any]:
    """A flat data class's fields by name."""
    return {name: getattr(instance, name) for name in instance.__dataclass_fields__}
