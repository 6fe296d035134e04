"""Structured logging: one JSON object per line on stderr.

Each line carries ``time`` (UTC, ISO 8601 with milliseconds), ``level``, ``logger`` and
``message``, then every extra field passed with ``extra={...}``, then ``exception`` (the formatted
traceback) when there is one. uvicorn's access lines also get ``client``, ``method``, ``path``,
``http_version`` and ``status_code``::

    {"time": "2026-11-01T10:00:00.123Z", "level": "info", "logger": "eyeserver.api",
     "message": "eyeserver starting", "data_dir": "/home/me/.local/share/eyeserver"}

Code logs through the standard library (``logging.getLogger(__name__)``); only the entry point
calls :func:`configure_logging`. The module is named ``log`` rather than ``logging`` so that it can
never shadow the standard library.
"""

from __future__ import annotations

import json as jsonlib
import logging
import re
import sys
from datetime import UTC, datetime
from typing import Any, TextIO

__all__ = ["JsonFormatter", "TokenRedactor", "configure_logging", "redacted"]

# Attributes every LogRecord has; anything else on a record came in through ``extra=``.
_RECORD_ATTRIBUTES = frozenset(
    logging.LogRecord("", logging.INFO, "", 0, "", None, None).__dict__
) | {"message", "asctime", "taskName"}

# Extras that libraries add for their own console formatters (uvicorn's ANSI-coloured copy of
# the message); they are noise in a JSON line.
_DROPPED_EXTRAS = frozenset({"color_message"})

_TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


_SECRETS = re.compile(r"(?i)(?P<key>[?&;](?:access_)?token=|bearer\s+)(?P<value>[^&;\s\"']+)")
REDACTED = "[redacted]"


def redacted(text: str) -> str:
    """``text`` with the value of every ``token=`` query parameter and ``Bearer`` credential
    replaced by ``[redacted]``."""
    return _SECRETS.sub(lambda m: m.group("key") + REDACTED, text)


class TokenRedactor(logging.Filter):
    """Takes tokens out of every record before it is formatted: uvicorn logs request paths
    with their query string (``/api/v1/ws/pose?token=…``, the documented way for a browser)
    and would write the token to the journal otherwise (issue 35). Rewrites the message and
    its string arguments; never drops a record."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redacted(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redacted(a) if isinstance(a, str) else a for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: redacted(v) if isinstance(v, str) else v
                           for k, v in record.args.items()}
        for key, value in list(record.__dict__.items()):
            if key not in _RECORD_ATTRIBUTES and isinstance(value, str):
                setattr(record, key, redacted(value))
        return True


def _access_fields(record: logging.LogRecord) -> dict[str, Any]:
    """The fields of a uvicorn access-log line, which uvicorn only passes as format arguments."""
    if record.name != "uvicorn.access" or not isinstance(record.args, tuple):
        return {}
    if len(record.args) != 5:
        return {}
    client, method, path, http_version, status_code = record.args
    return {
        "client": client,
        "method": method,
        "path": path,
        "http_version": http_version,
        "status_code": status_code,
    }


def _utc_timestamp(seconds: float) -> str:
    moment = datetime.fromtimestamp(seconds, UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


class JsonFormatter(logging.Formatter):
    """Format a record as a single-line JSON object (see the module docstring for the keys)."""

    def format(self, record: logging.LogRecord) -> str:
        """Return the JSON line for ``record`` (without the newline)."""
        entry: dict[str, Any] = {
            "time": _utc_timestamp(record.created),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in record.__dict__.items():
            if key not in _RECORD_ATTRIBUTES and key not in _DROPPED_EXTRAS:
                entry[key] = value
        entry.update(_access_fields(record))
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            entry["exception"] = record.exc_text
        if record.stack_info:
            entry["stack"] = self.formatStack(record.stack_info)
        # default=str: a Path, a UUID or a numpy scalar in ``extra`` must not break logging.
        return jsonlib.dumps(entry, default=str, ensure_ascii=False)


class _StderrHandler(logging.StreamHandler[TextIO]):
    """Write to whatever ``sys.stderr`` is at the time of each record.

    Binding the stream once would keep writing to a replaced (and possibly closed) stream, e.g.
    under pytest's output capture.
    """

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    def emit(self, record: logging.LogRecord) -> None:
        """Point at the current ``sys.stderr``, then write the record."""
        self.stream = sys.stderr
        super().emit(record)


def configure_logging(level: str | int = "info", json: bool = True) -> None:
    """Send all log records at ``level`` and above to stderr, as JSON lines or plain text.

    Configures the root logger, so the records of libraries (uvicorn, for one) come out the same
    way. Calling it again replaces the handler installed by the previous call; handlers installed
    by others are left alone.

    Parameters
    ----------
    level
        A level name (``"debug"``, ``"info"``, …, any case) or a :mod:`logging` level number.
    json
        ``True`` for one JSON object per line, ``False`` for human-readable text.

    Raises
    ------
    ValueError
        ``level`` is not a known level name.
    """
    if isinstance(level, str):
        number = logging.getLevelNamesMapping().get(level.upper())
        if number is None:
            raise ValueError(f"level: unknown log level {level!r}")
        level = number
    root = logging.getLogger()
    for handler in list(root.handlers):
        if isinstance(handler, _StderrHandler):
            root.removeHandler(handler)
            handler.close()
    handler = _StderrHandler()
    handler.addFilter(TokenRedactor())
    handler.setFormatter(JsonFormatter() if json else logging.Formatter(_TEXT_FORMAT))
    root.addHandler(handler)
    root.setLevel(level)
    # pymodbus logs an error of its own for every failed connect or missing reply, without the
    # device's id; the driver raises (and the daemon logs) the same fault with it.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
