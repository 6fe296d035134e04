"""The ``eyeserver`` command line.

Each subcommand group is added by a *registrar*: a function ``(subparsers) -> None`` that calls
``subparsers.add_parser(...)`` and sets ``handler`` as a default, a function ``(args) -> int``
returning the exit status::

    def add_parser(subparsers: Subparsers) -> None:
        parser = subparsers.add_parser("sim", help="the simulated room")
        parser.set_defaults(handler=_run_sim)

Registrars of other modules are listed in :data:`REGISTRARS`. They should import anything heavy
inside their handlers, so that ``eyeserver --version`` and ``eyeserver serve`` stay quick.

Exit status: what the handler returns; 2 for a usage error or any
:class:`~eyeserver.errors.EyeserverError` (printed as ``eyeserver: error: <message>``, without a
traceback); 130 after Ctrl-C.
"""

from __future__ import annotations

import argparse
import gc
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import eyeserver
from eyeserver.commands import Subparsers
from eyeserver.commands import bench as bench_commands
from eyeserver.commands import calibrate as calibrate_commands
from eyeserver.commands import devices as devices_commands
from eyeserver.commands import pose as pose_commands
from eyeserver.commands import sim as sim_commands
from eyeserver.core.memory import keep_freed_memory
from eyeserver.errors import EyeserverError

__all__ = ["REGISTRARS", "Registrar", "Subparsers", "build_parser", "main"]

PROG = "eyeserver"

SHUTDOWN_GRACE_S = 10
"""Seconds ``eyeserver serve`` waits for open connections when asked to stop."""


#: Adds one subcommand (or group of them) to the command line.
Registrar = Callable[[Subparsers], None]

#: A subcommand's handler: parsed arguments in, exit status out.
Handler = Callable[[argparse.Namespace], int]


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port must be between 1 and 65535, not {port}")
    return port


def add_serve_parser(subparsers: Subparsers) -> None:
    """Register ``eyeserver serve [--host H] [--port P] [--config FILE]``."""
    parser = subparsers.add_parser(
        "serve",
        help="run the daemon (HTTP API)",
        description="Run the eyeserver daemon. Without options it serves the simulated room on "
        "http://127.0.0.1:8000 and keeps its data in the user's data directory "
        "(EYESERVER_DATA_DIR to change it).",
    )
    parser.add_argument("--host", help="address to listen on (default: 127.0.0.1)")
    parser.add_argument("--port", type=_port, help="TCP port to listen on (default: 8000)")
    parser.add_argument("--config", type=Path, metavar="FILE", help="TOML configuration file")
    parser.set_defaults(handler=_serve)


def _serve(args: argparse.Namespace) -> int:
    # Imported here: building the app pulls in FastAPI, which other subcommands do not need.
    import uvicorn

    from eyeserver.api import create_app
    from eyeserver.api.wsprotocol import UVICORN_OPTIONS
    from eyeserver.config import Settings
    from eyeserver.log import configure_logging
    from eyeserver.tls import uvicorn_ssl_options

    settings = Settings.load(args.config, host=args.host, port=args.port)
    configure_logging(settings.log_level, json=settings.log_json)
    # Fail here with a one-line message rather than inside uvicorn's lifespan with a traceback.
    settings.ensure_data_dir()
    ssl_options = uvicorn_ssl_options(settings)  # {} for plain HTTP
    app = create_app(settings)
    # Everything imported so far lives as long as the daemon: out of the cyclic collector's
    # full passes, which otherwise stopped every thread for 40-90 ms a few times a minute
    # under load (the status p99; docs/notes/hardening.md).
    gc.collect()
    gc.freeze()
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        # No uvicorn logging config: its loggers propagate to our root handler (JSON lines).
        log_config=None,
        log_level=settings.log_level,
        # A client that never reads (an event stream) must not hold the shut-down up forever.
        timeout_graceful_shutdown=SHUTDOWN_GRACE_S,
        **UVICORN_OPTIONS,
        **ssl_options,
    )
    return 0


#: Every subcommand group of the command line, in the order ``--help`` lists them.
REGISTRARS: list[Registrar] = [add_serve_parser, sim_commands.add_parser,
                               calibrate_commands.add_parser,
                               calibrate_commands.add_reconstruct_parser,
                               pose_commands.add_parser,
                               bench_commands.add_parser,
                               devices_commands.add_parser]


def build_parser(registrars: Iterable[Registrar] | None = None) -> argparse.ArgumentParser:
    """The argument parser with the subcommands of ``registrars`` (default :data:`REGISTRARS`)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Eye surface and pose by single-shot fringe projection.",
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {eyeserver.__version__}")
    subparsers = parser.add_subparsers(title="commands", dest="command", metavar="COMMAND")
    subparsers.required = True
    for register in REGISTRARS if registrars is None else registrars:
        register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``) and return the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version and usage errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    handler: Handler = args.handler
    keep_freed_memory()  # every command's array work runs faster (eyeserver.core.memory)
    try:
        return handler(args)
    except EyeserverError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
