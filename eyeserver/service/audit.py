"""The audit file: one JSON line per audited action, append-only and fsynced.

::

    {"time": "2026-11-23T15:12:00.123Z", "seq": 42, "actor": "dr.weber", "role": "physicist",
     "action": "delete_capture", "target": "cap-20261123T151100000Z-1a2b",
     "detail": {"reason": "test shot", "status": "ok", "unit": "left"}, "outcome": "ok"}

It is separate from the debug log (stderr, rotated and filtered by journald) and meant to be
kept, shipped and read by people who were not there. Every row the store writes to its
``audit`` table reaches the file through :meth:`AuditTrail.record_stored`, the store's
``audit_sink`` (same ``time``, and ``seq`` is the row's number), so nothing is audited twice
and nothing is audited in one place only; actions that failed, which change nothing in the
store, are written to the file alone with ``"outcome": "error"`` (:meth:`AuditTrail.failures`).

``role`` is the role of the token holder named ``actor`` (:meth:`AuditTrail.set_roles`, from the
token table; several roles joined by ``|`` if one name holds tokens of several), ``system`` for
the daemon's own actors (``eyeserver`` for start-up recovery, ``retention``).

Patient identifiers never reach the file in clear: any ``patient_id`` field of a detail, at any
depth, is replaced by :func:`hash_patient_id` with a secret salt of this installation, kept in
``DATA_DIR/audit_salt`` (mode 0600, created at the first start). The same patient gives the same
hash on this installation, so one patient's entries can still be found; without the salt the
hash cannot be turned back into the identifier, not even by trying every plausible one.

The file is opened with ``O_APPEND`` and never rewritten; a line is fsynced before the action
is acknowledged. A line torn by a power cut is closed with a newline at the next start and
skipped by readers.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import json
import logging
import os
import secrets
import threading
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from eyeserver.config import Settings
from eyeserver.errors import ConfigError
from eyeserver.io import fsync_dir, write_synced
from eyeserver.service.storage import AuditEntry

__all__ = [
    "AUDIT_FILE",
    "SALT_FILE",
    "SYSTEM_ROLE",
    "AuditRecord",
    "AuditTrail",
    "audit_log_path",
    "hash_patient_id",
    "load_salt",
    "pseudonymise",
]

AUDIT_FILE = "audit.jsonl"
"""The audit file's name under the data directory, unless ``audit_log`` says otherwise."""

SALT_FILE = "audit_salt"
"""The installation's secret salt for :func:`hash_patient_id`, under the data directory."""

SYSTEM_ROLE = "system"
"""The role recorded for the daemon's own actors (``eyeserver``, ``retention``)."""

PATIENT_ID_FIELD = "patient_id"

Outcome = Literal["ok", "error", "denied"]

_log = logging.getLogger(__name__)

_TAIL_BLOCK_BYTES = 64 * 1024


def audit_log_path(settings: Settings) -> Path:
    """Where the audit file of ``settings`` is: ``audit_log`` or ``DATA_DIR/audit.jsonl``."""
    return settings.audit_log if settings.audit_log is not None else (
        settings.data_dir / AUDIT_FILE)


def hash_patient_id(value: str, salt: bytes) -> str:
    """A patient identifier as it may appear in the audit file: ``hmac-sha256:<64 hex>``.

    A keyed hash (HMAC-SHA256, RFC 2104) rather than a plain one: patient numbers are short
    and guessable, so a plain hash could be reversed by hashing every candidate; without the
    installation's ``salt`` that is not possible.

    >>> hash_patient_id("P-0001", b"k" * 32) == hash_patient_id("P-0001", b"k" * 32)
    True
    >>> hash_patient_id("P-0001", b"k" * 32)[:12]
    'hmac-sha256:'
    """
    if not salt:
        raise ValueError("salt: an empty salt protects nothing")
    digest = hmac.new(salt, str(value).encode("utf-8"), hashlib.sha256).hexdigest()
    return f"hmac-sha256:{digest}"


def pseudonymise(detail: object, salt: bytes) -> Any:
    """``detail`` with every ``patient_id`` value (at any depth) replaced by its hash."""
    if isinstance(detail, Mapping):
        return {key: (hash_patient_id(str(value), salt)
                      if key == PATIENT_ID_FIELD and value is not None
                      else pseudonymise(value, salt))
                for key, value in detail.items()}
    if isinstance(detail, list | tuple):
        return [pseudonymise(value, salt) for value in detail]
    return detail


def load_salt(path: Path) -> bytes:
    """The installation's salt in ``path``, created (32 random bytes, mode 0600) if missing.

    Raises
    ------
    ConfigError
        The file cannot be read or written, or holds no salt.
    """
    try:
        if not path.exists():
            staging = path.with_name(f".{path.name}.tmp")
            staging.unlink(missing_ok=True)
            write_synced(staging, (secrets.token_hex(32) + "\n").encode(), mode=0o600)
            os.replace(staging, path)  # atomic: never a half-written salt
            fsync_dir(path.parent)
            _log.info("generated the audit salt", extra={"file": str(path)})
        text = path.read_text(encoding="ascii").strip()
        salt = bytes.fromhex(text)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read or create the audit salt: {exc}") from exc
    if len(salt) < 16:
        raise ConfigError(f"{path}: the audit salt is too short (need at least 16 bytes)")
    return salt


def _now_text() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass(frozen=True)
class AuditRecord:
    """One line of the audit file.

    ``seq`` is the store's audit row number, None for a line with no row (a failed action).
    """

    time: str
    actor: str
    role: str
    action: str
    target: str
    detail: Mapping[str, object] = field(default_factory=dict)
    outcome: Outcome = "ok"
    seq: int | None = None

    def to_json(self) -> str:
        """The record as one line of JSON (no newline), keys in a fixed order."""
        document = asdict(self)
        ordered = {key: document[key] for key in ("time", "seq", "actor", "role", "action",
                                                  "target", "detail", "outcome")}
        return json.dumps(ordered, ensure_ascii=False, default=str, separators=(", ", ": "))


class AuditTrail:
    """The audit file of one daemon, with who holds which role and the patient-id salt.

    Parameters
    ----------
    path : Path
        The JSON-lines file (created, mode 0600, on :meth:`open`).
    salt_file : Path
        The salt of :func:`hash_patient_id` (created on :meth:`open` if missing).

    Notes
    -----
    Nothing happens in the constructor. All methods are thread-safe; a line is written and
    fsynced under a lock, so lines never interleave.
    """

    def __init__(self, path: Path, salt_file: Path) -> None:
        self.path = path
        self.salt_file = salt_file
        self._lock = threading.Lock()
        self._fd: int | None = None
        self._salt = b""
        self._roles: dict[str, str] = {}

    def open(self) -> None:
        """Open the file for appending (creating it and the salt if need be).

        Raises
        ------
        ConfigError
            The file or the salt cannot be opened or created; the message names it.
        """
        salt = load_salt(self.salt_file)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            created = not self.path.exists()
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise ConfigError(f"audit_log {self.path}: cannot open for appending: "
                              f"{exc.strerror or exc}") from exc
        try:
            if created:
                fsync_dir(self.path.parent)
            elif not _ends_with_newline(self.path):
                # A line torn by a power cut: end it, so the next line parses on its own.
                os.write(fd, b"\n")
                os.fsync(fd)
        except OSError as exc:
            os.close(fd)
            raise ConfigError(f"audit_log {self.path}: cannot write: {exc.strerror or exc}"
                              ) from exc
        with self._lock:
            self._fd, self._salt = fd, salt

    def close(self) -> None:
        """Close the file. Idempotent."""
        with self._lock:
            fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    def set_roles(self, roles: Mapping[str, str]) -> None:
        """Who holds which role (token holder name -> role), for the ``role`` of each line."""
        with self._lock:
            self._roles = dict(roles)

    def role_of(self, actor: str) -> str:
        """The role recorded for ``actor``: its token's role, else :data:`SYSTEM_ROLE`."""
        with self._lock:
            return self._roles.get(actor, SYSTEM_ROLE)

    def record(self, actor: str, action: str, target: str,
               detail: Mapping[str, object] | None = None, outcome: Outcome = "ok", *,
               time: str | None = None, seq: int | None = None) -> AuditRecord:
        """Append one line (patient ids hashed) and fsync it; returns what was written.

        A line that cannot be written is logged as an error and not raised: the action it
        records has already happened (its store row is committed) and must not be reported as
        failed.
        """
        with self._lock:
            salt, fd = self._salt, self._fd
            role = self._roles.get(actor, SYSTEM_ROLE)
        record = AuditRecord(time=time or _now_text(), actor=actor, role=role, action=action,
                             target=target,
                             detail=pseudonymise(dict(detail or {}), salt) if salt else
                             dict(detail or {}),
                             outcome=outcome, seq=seq)
        if fd is None:
            _log.error("audit file closed: entry not written", extra={
                "action": action, "actor": actor, "target": target})
            return record
        line = (record.to_json() + "\n").encode("utf-8")
        try:
            with self._lock:
                if self._fd is None:
                    raise OSError("the audit file was closed")
                os.write(self._fd, line)  # O_APPEND: one write, at the end, whole
                os.fsync(self._fd)
        except OSError as exc:
            _log.error("audit file not written", extra={
                "file": str(self.path), "reason": str(exc), "action": action, "actor": actor,
                "target": target})
        return record

    def record_stored(self, entry: AuditEntry) -> None:
        """The store's ``audit_sink``: a committed audit row, as a line with its ``seq``."""
        self.record(entry.actor, entry.action, entry.target, entry.detail, "ok",
                    time=entry.time, seq=entry.seq)

    @contextlib.contextmanager
    def failures(self, actor: str, action: str, target: str) -> Iterator[None]:
        """Record the block's exception, if any, as an ``error`` line; then re-raise it."""
        try:
            yield
        except Exception as exc:
            self.record(actor, action, target, {"error": str(exc) or type(exc).__name__},
                        "error")
            raise

    def entries(self, limit: int = 100) -> list[dict[str, Any]]:
        """The newest ``limit`` lines of the file, newest first (torn lines skipped)."""
        if isinstance(limit, bool) or limit < 1:
            raise ValueError(f"limit must be at least 1, got {limit!r}")
        found: list[dict[str, Any]] = []
        for line in _lines_backwards(self.path):
            try:
                document = json.loads(line)
            except ValueError:
                continue
            if isinstance(document, dict):
                found.append(document)
                if len(found) == limit:
                    break
        return found


def _ends_with_newline(path: Path) -> bool:
    with path.open("rb") as stream:
        stream.seek(0, os.SEEK_END)
        if stream.tell() == 0:
            return True
        stream.seek(-1, os.SEEK_END)
        return stream.read(1) == b"\n"


def _lines_backwards(path: Path) -> Iterator[bytes]:
    """The non-empty lines of ``path`` from the last to the first, read in blocks from the end
    (the file only grows; the newest entries are what people ask for)."""
    try:
        stream = path.open("rb")
    except FileNotFoundError:
        return
    with stream:
        position = stream.seek(0, os.SEEK_END)
        rest = b""
        while position > 0:
            size = min(_TAIL_BLOCK_BYTES, position)
            position -= size
            stream.seek(position)
            block = stream.read(size) + rest
            lines = block.split(b"\n")
            rest = lines.pop(0)  # may continue in the block before
            for line in reversed(lines):
                if line.strip():
                    yield line
        if rest.strip():
            yield rest
