"""``eyeserver devices discover``: the cameras and serial ports attached to this machine, and the
room-file entries that would use them (issue 38)."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

from eyeserver.commands import Subparsers
from eyeserver.commands import progress as _progress

if TYPE_CHECKING:
    from eyeserver.hardware.discovery import Discovery, PortProbe

# The discovery module's defaults, for the help text only (it imports the drivers, which the
# parser must not); a test holds them equal.
DEFAULT_TIMEOUT_S = 0.3
MODBUS_UNIT_ID, MODBUS_BAUDRATE, MODBUS_PARITY = 1, 19200, "E"


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a time in seconds: {text!r}") from None
    if not 0 < value <= 10:  # NaN fails too
        raise argparse.ArgumentTypeError(f"must be above 0 and at most 10 s, not {text}")
    return value


def _unit_id(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a Modbus unit id: {text!r}") from None
    if not 1 <= value <= 247:
        raise argparse.ArgumentTypeError(f"must be 1 to 247 on Modbus RTU, not {value}")
    return value


def _baudrate(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a baud rate: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, not {value}")
    return value


def add_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver devices discover``."""
    devices = subparsers.add_parser(
        "devices", help="the devices attached to this machine",
        description="The cameras and controllers attached to this machine.")
    commands = devices.add_subparsers(title="devices commands", dest="devices_command",
                                      metavar="COMMAND")
    commands.required = True

    discover = commands.add_parser(
        "discover", help="list cameras and serial ports, with room-file entries",
        description="List the GenICam cameras Aravis finds (GigE Vision, USB3 Vision) and the "
        "serial ports of this machine, and print for each device found the room-file entry "
        "that would use it ([[devices]] or [stage], docs/room-file.md 'A room of real "
        "devices'), naming the options left for you to set. Without --probe nothing is sent "
        "to any serial port: the ports are listed, not opened. The camera search waits about "
        "a second for GigE Vision answers.")
    discover.add_argument(
        "--probe", action="store_true",
        help="ask each serial port which controller answers: a Gardasoft RT LED controller "
        "(VR), a Zaber stage (the '/' broadcast), an Opto Modbus RTU strobe controller "
        "(register 0). This SENDS BYTES to every port listed, whatever device is on it, so it "
        "is never the default. Each probe only reads, and the port is closed after it. A port "
        "another program holds open is not probed; stop the daemon first, and run as root to "
        "see the ports another user's programs hold")
    discover.add_argument(
        "--port", action="append", default=[], metavar="PATH",
        help="a serial port to list (and probe) besides the system's, such as a pty or a "
        "symlink, which the system's list leaves out; repeatable")
    discover.add_argument(
        "--address", action="append", default=[], metavar="IP",
        help="ask for a GenICam camera at this address directly (an IP address, or an Aravis "
        "device id), for a camera the discovery broadcast does not reach (another subnet, "
        "loopback on some hosts); repeatable. Nothing answering costs 2.5 s")
    discover.add_argument(
        "--timeout", type=_seconds, default=DEFAULT_TIMEOUT_S, metavar="S",
        help=f"seconds each probe waits for an answer (default {DEFAULT_TIMEOUT_S:g})")
    modbus = discover.add_argument_group(
        "the Modbus RTU probe", "The serial settings it asks at; the defaults are the "
        "controller's factory settings as the OptoProjector driver assumes them.")
    modbus.add_argument("--modbus-unit", type=_unit_id, metavar="N",
                        help=f"the controller's unit id (default {MODBUS_UNIT_ID})")
    modbus.add_argument("--modbus-baudrate", type=_baudrate, metavar="BAUD",
                        help=f"bits per second (default {MODBUS_BAUDRATE})")
    modbus.add_argument("--modbus-parity", choices=("E", "O", "N"),
                        help=f"even, odd or none (then two stop bits); default "
                        f"{MODBUS_PARITY}. A pty takes no parity: N")
    discover.add_argument("--no-cameras", action="store_true",
                          help="do not search for cameras")
    discover.add_argument("--no-serial", action="store_true",
                          help="do not list (or probe) serial ports")
    discover.add_argument("--json", action="store_true", help="one JSON document on stdout")
    discover.set_defaults(handler=_discover)


@contextlib.contextmanager
def _quiet_pymodbus() -> Iterator[None]:
    """Keep pymodbus from logging each silent port as an error: to a probe, silence is an
    answer (no controller there), and without a logging configuration Python would print
    every such record on stderr."""
    logger = logging.getLogger("pymodbus")
    level = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(level)


def _discover(args: argparse.Namespace) -> int:
    from eyeserver.hardware.discovery import ModbusSettings, discover

    given = {"unit_id": args.modbus_unit, "baudrate": args.modbus_baudrate,
             "parity": args.modbus_parity}
    settings = ModbusSettings(**{name: value for name, value in given.items()
                                 if value is not None})
    with _quiet_pymodbus():
        found = discover(cameras=not args.no_cameras, addresses=args.address,
                         serial_ports=not args.no_serial, ports=args.port, probe=args.probe,
                         timeout_s=args.timeout, modbus_settings=settings,
                         progress=_progress)
    if args.json:
        print(json.dumps(found.to_dict(), indent=1))
    else:
        print("\n".join(report(found)))
    return 0


def report(found: Discovery) -> list[str]:
    """The human-readable report of ``found``: a table of cameras, a table of serial ports,
    then the room-file entries."""
    lines: list[str] = []
    if found.cameras is not None:
        lines.append("GenICam cameras (Aravis)")
        search = found.cameras
        if search.unavailable is not None:
            lines.append(f"  {search.unavailable}")
        elif not search.cameras:
            lines.append("  none found")
        else:
            lines += _table(
                ("DEVICE ID", "VENDOR", "MODEL", "SERIAL", "ADDRESS", "PHYSICAL ID", "PROTOCOL",
                 "FOUND BY"),
                [(entry.camera.device_id, entry.camera.vendor, entry.camera.model,
                  entry.camera.serial, entry.camera.address, entry.camera.physical_id,
                  entry.camera.protocol, entry.found_by) for entry in search.cameras])
        lines += [f"  no camera answered at {item.address}: {item.reason}"
                  for item in search.unanswered]
        lines.append("")
    if found.serial_ports is not None:
        lines.append("Serial ports")
        if not found.serial_ports:
            lines.append("  none found")
        else:
            lines += _table(("PORT", "BY-ID LINK", "USB ID", "SERIAL", "DESCRIPTION", "FOUND"),
                            [(port.device, port.by_id, port.usb_id, port.serial_number,
                              port.description, _found_on(port.probe, port.present))
                             for port in found.serial_ports])
            for port in found.serial_ports:
                if port.probe is not None:
                    lines += [f"  {port.device}: {note}" for note in port.probe.notes]
        if not found.probed:
            lines.append("  Not probed: --probe asks each port which controller answers (it "
                         "sends bytes to every port).")
        lines.append("")
    snippets = found.snippets()
    if snippets:
        lines.append("Room-file entries (docs/room-file.md, 'A room of real devices'):")
        for snippet in snippets:
            lines += ["", snippet.toml()]
    else:
        lines.append("No device found for a room file.")
    return lines


def _found_on(probe: PortProbe | None, present: bool) -> str:
    if probe is None:
        return "not probed" if present else "not probed (no such path)"
    if probe.problem is not None:
        return probe.problem
    if not probe.controllers:
        return "no known controller answered"
    return "; ".join(f"{controller.name}: {controller.identification}"
                     for controller in probe.controllers)


def _table(headers: Sequence[str], rows: Sequence[Sequence[str | None]]) -> list[str]:
    """Rows under headers in columns as wide as their widest cell; a missing value is ``-``."""
    cells = [list(headers)] + [[value if value else "-" for value in row] for row in rows]
    widths = [max(len(row[n]) for row in cells) for n in range(len(headers))]
    return ["  " + "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True))
            .rstrip() for row in cells]
