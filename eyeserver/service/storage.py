"""The daemon's store: an SQLite index over capture bundles and calibrations kept on disk.

::

    DATA_DIR/
      index.sqlite3       the index (WAL, synchronous=FULL): captures, calibrations, audit log
      store.lock          held (flock) while a Store is open, so two daemons never share a store
      captures/<id>/      one capture bundle each (FORMATS.md), written by io.write_bundle
      calibrations/<id>/  one calibration directory each (calibration/artefact.py)
      quarantine/         leftovers of interrupted writes, moved here at start-up, never deleted
      patients/<key>/     eye models, reference poses and pose measurements (JSON), never deleted

Every write is atomic and durable before it is acknowledged: the files go to a hidden sibling
directory, are fsynced, the directory is renamed into place and its parent fsynced, and only then
is the index row committed (SQLite in WAL mode with ``synchronous=FULL`` fsyncs the log on every
commit). A crash can therefore leave a complete directory without its row (re-indexed at the next
start) or a hidden staging directory (quarantined), never a row without its data.

Nothing is removed except by :meth:`Store.delete_capture`, which writes its audit row first.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import secrets
import shutil
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE, load_calibration
from eyeserver.errors import EyeserverError, StateConflictError
from eyeserver.io import (
    BundleFrameData,
    BundleKind,
    ChessboardSpec,
    RigSpec,
    atomic_write_text,
    fsync_dir,
    makedirs_synced,
    read_bundle,
    write_bundle,
    write_synced,
)

try:  # POSIX only; on Windows the store is not guarded against a second process.
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "SCHEMA_VERSION",
    "AuditEntry",
    "CalibrationRecord",
    "CaptureRecord",
    "RecoveryReport",
    "StorageError",
    "Store",
    "UnknownIdError",
    "is_calibration_id",
    "is_capture_id",
]

_log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
INDEX_FILE = "index.sqlite3"
LOCK_FILE = "store.lock"
CAPTURES_DIR = "captures"
CALIBRATIONS_DIR = "calibrations"
QUARANTINE_DIR = "quarantine"
_CAPTURE_KEY = "capture"  # the bundle's extra key holding what the index row holds

_ID_PATTERN = re.compile(r"^(cap|cal)-(\d{8}T\d{9})Z-[0-9a-f]{4}$")
_DELETING_PATTERN = re.compile(r"^\.(?P<id>[A-Za-z0-9-]+)\.[0-9a-f]{12}\.deleting$")

Status = Literal["ok", "missing"]

_SCHEMA = """
CREATE TABLE captures (
    id TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    unit TEXT NOT NULL,
    calibration_id TEXT,
    created TEXT NOT NULL,
    frame_count INTEGER NOT NULL,
    status TEXT NOT NULL DEFAULT 'ok' CHECK (status IN ('ok', 'missing'))
);
CREATE INDEX captures_by_unit ON captures (unit, id);
CREATE INDEX captures_by_created ON captures (created);
CREATE INDEX captures_by_kind ON captures (kind, id);
CREATE INDEX captures_by_calibration ON captures (calibration_id, id);
CREATE TABLE calibrations (
    id TEXT PRIMARY KEY,
    created TEXT NOT NULL,
    imported TEXT NOT NULL,
    source TEXT NOT NULL,
    quality TEXT NOT NULL,
    active INTEGER NOT NULL DEFAULT 0 CHECK (active IN (0, 1)),
    status TEXT NOT NULL DEFAULT 'ok' CHECK (status IN ('ok', 'missing'))
);
-- At most one active calibration, enforced by the database itself.
CREATE UNIQUE INDEX one_active_calibration ON calibrations (active) WHERE active = 1;
CREATE TABLE audit (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    time TEXT NOT NULL,
    actor TEXT NOT NULL,
    action TEXT NOT NULL,
    target TEXT NOT NULL,
    detail TEXT NOT NULL
);
"""

# Indexes added within schema version 1: created when an older index lacks them. They change
# no data, so a store that has them still opens with an eyeserver that does not know them.
_ADDED_INDEXES = """
CREATE INDEX IF NOT EXISTS captures_by_kind ON captures (kind, id);
CREATE INDEX IF NOT EXISTS captures_by_calibration ON captures (calibration_id, id);
"""

# Tables added within schema version 1 for patients, their eye models, reference poses and pose
# measurements (eyeserver.service.patients and .verification keep them through the public
# hooks below: transaction, audit_in, query, write_document). Created when missing, like the
# indexes above; an older eyeserver ignores them. Their documents are JSON files under
# ``patients/``, written before their rows, so a row never lacks its file.
_ADDED_TABLES = """
CREATE TABLE IF NOT EXISTS patients (
    patient_id TEXT PRIMARY KEY,
    key TEXT NOT NULL UNIQUE,
    eye TEXT NOT NULL CHECK (eye IN ('right', 'left')),
    unit TEXT NOT NULL,
    settings TEXT NOT NULL,
    created TEXT NOT NULL,
    updated TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS eye_models (
    patient_id TEXT NOT NULL REFERENCES patients (patient_id),
    version INTEGER NOT NULL,
    created TEXT NOT NULL,
    actor TEXT NOT NULL,
    file TEXT NOT NULL,
    PRIMARY KEY (patient_id, version)
);
CREATE TABLE IF NOT EXISTS pose_references (
    patient_id TEXT NOT NULL REFERENCES patients (patient_id),
    fraction INTEGER NOT NULL,
    version INTEGER NOT NULL,
    created TEXT NOT NULL,
    actor TEXT NOT NULL,
    source TEXT NOT NULL,
    file TEXT NOT NULL,
    PRIMARY KEY (patient_id, fraction, version)
);
CREATE TABLE IF NOT EXISTS pose_measurements (
    id TEXT PRIMARY KEY,
    patient_id TEXT NOT NULL REFERENCES patients (patient_id),
    fraction INTEGER NOT NULL,
    created TEXT NOT NULL,
    passed INTEGER NOT NULL CHECK (passed IN (0, 1)),
    capture_id TEXT NOT NULL,
    file TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS pose_measurements_by_patient
    ON pose_measurements (patient_id, fraction, id);
"""


class StorageError(EyeserverError):
    """The store cannot do what was asked (bad id, unusable data directory, corrupt index)."""


class UnknownIdError(StorageError):
    """No capture or calibration has this id; ``item_id`` names it."""

    def __init__(self, item_id: str, what: str) -> None:
        self.item_id = item_id
        super().__init__(f"no {what} with id {item_id!r}")


def is_capture_id(value: str) -> bool:
    """True when ``value`` has the form of a capture id (``cap-YYYYMMDDTHHMMSSmmmZ-hhhh``)."""
    match = _ID_PATTERN.fullmatch(value)
    return match is not None and match.group(1) == "cap"


def is_calibration_id(value: str) -> bool:
    """True when ``value`` has the form of a calibration id (``cal-YYYYMMDDTHHMMSSmmmZ-hhhh``)."""
    match = _ID_PATTERN.fullmatch(value)
    return match is not None and match.group(1) == "cal"


@dataclass(frozen=True)
class CaptureRecord:
    """One capture as the index knows it.

    Attributes
    ----------
    id : str
        ``cap-<UTC time to the millisecond>-<4 hex digits>``; sorts in order of creation.
    kind : {"measurement", "chessboard", "plate", "reference"}
    unit : str
        The unit that took it (or ``"all"``).
    calibration_id : str or None
        The calibration active when it was taken.
    created : str
        UTC time of creation, ISO 8601 with milliseconds (``2026-11-23T15:12:00.123Z``).
    frame_count : int
        Frames in the bundle.
    status : {"ok", "missing"}
        ``missing`` when start-up recovery found the row without its directory.
    path : Path
        The bundle directory.
    """

    id: str
    kind: str
    unit: str
    calibration_id: str | None
    created: str
    frame_count: int
    status: Status
    path: Path


@dataclass(frozen=True)
class CalibrationRecord:
    """One imported calibration.

    Attributes
    ----------
    id : str
        ``cal-<UTC time to the millisecond>-<4 hex digits>``.
    created : str
        The ``created`` time written in its ``calibration.json``.
    imported : str
        UTC time of the import, ISO 8601 with milliseconds.
    source : str
        Where it came from: the directory it was imported from, or what the importer said
        (``upload by <name>, sha256:<hash of the archive>`` for an upload through the API).
    quality : Mapping of str to object
        The ``quality`` figures of its ``calibration.json`` (empty when it has none).
    active : bool
        True for the one calibration in use.
    status : {"ok", "missing"}
    path : Path
        The calibration directory inside the store.
    """

    id: str
    created: str
    imported: str
    source: str
    quality: Mapping[str, object]
    active: bool
    status: Status
    path: Path


@dataclass(frozen=True)
class AuditEntry:
    """One row of the audit log: who did what to which item, and when (UTC, ISO 8601)."""

    seq: int
    time: str
    actor: str
    action: str
    target: str
    detail: Mapping[str, object]


@dataclass(frozen=True)
class RecoveryReport:
    """What :meth:`Store.open` found and did before accepting work.

    Attributes
    ----------
    recovered : tuple of str
        Ids of complete directories that had no index row (a crash between the rename and the
        commit) and were indexed again.
    quarantined : tuple of Path
        Hidden staging directories of interrupted writes, each moved into ``quarantine/`` (this
        tuple holds their new paths). Their data was never acknowledged.
    missing : tuple of str
        Ids whose index row has no directory; their rows are kept and marked ``missing``.
    deletions_completed : tuple of str
        Ids whose audited deletion was interrupted and has now been finished.
    unrecognised : tuple of Path
        Visible entries under ``captures/`` or ``calibrations/`` that are not a valid item;
        left in place for a person to look at.
    """

    recovered: tuple[str, ...] = ()
    quarantined: tuple[Path, ...] = ()
    missing: tuple[str, ...] = ()
    deletions_completed: tuple[str, ...] = ()
    unrecognised: tuple[Path, ...] = ()

    @property
    def clean(self) -> bool:
        """True when the store was found exactly as it was left."""
        return not (self.recovered or self.quarantined or self.missing
                    or self.deletions_completed or self.unrecognised)


@dataclass
class _Recovery:
    recovered: list[str] = field(default_factory=list)
    quarantined: list[Path] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    deletions_completed: list[str] = field(default_factory=list)
    unrecognised: list[Path] = field(default_factory=list)

    def freeze(self) -> RecoveryReport:
        return RecoveryReport(tuple(self.recovered), tuple(self.quarantined),
                              tuple(self.missing), tuple(self.deletions_completed),
                              tuple(self.unrecognised))


def _utc_text(moment: datetime) -> str:
    utc = moment.astimezone(UTC)
    return utc.strftime("%Y-%m-%dT%H:%M:%S.") + f"{utc.microsecond // 1000:03d}Z"


def _ceil_millis(moment: datetime) -> datetime:
    partial = moment.microsecond % 1000
    return moment + timedelta(microseconds=1000 - partial) if partial else moment


def _now_text() -> str:
    return _utc_text(datetime.now(UTC))


def _id_time(item_id: str) -> str:
    """The ISO 8601 creation time encoded in a valid id."""
    match = _ID_PATTERN.fullmatch(item_id)
    assert match is not None
    stamp = match.group(2)
    return (f"{stamp[0:4]}-{stamp[4:6]}-{stamp[6:8]}T{stamp[9:11]}:{stamp[11:13]}:"
            f"{stamp[13:15]}.{stamp[15:18]}Z")


def _id_millis(item_id: str) -> int:
    stamp = datetime.strptime(_id_time(item_id)[:-5], "%Y-%m-%dT%H:%M:%S").replace(tzinfo=UTC)
    return int(stamp.timestamp()) * 1000 + int(item_id[19:22])


def _quality_of(document: Mapping[str, Any]) -> dict[str, object]:
    quality = document.get("quality")
    return dict(quality) if isinstance(quality, dict) else {}


class Store:
    """The index and the on-disk store of one data directory.

    Open it with :meth:`Store.open`; use it as a context manager or call :meth:`close`. All
    methods are thread-safe: one SQLite connection is shared under a lock, and the slow part of a
    write (encoding and fsyncing the files) runs outside that lock.
    """

    def __init__(self, data_dir: Path, connection: sqlite3.Connection, lock_fd: int | None
                 ) -> None:
        """Use :meth:`Store.open`."""
        self.data_dir = data_dir
        self.captures_dir = data_dir / CAPTURES_DIR
        self.calibrations_dir = data_dir / CALIBRATIONS_DIR
        self.quarantine_dir = data_dir / QUARANTINE_DIR
        self._connection: sqlite3.Connection | None = connection
        self._lock_fd = lock_fd
        self._lock = threading.RLock()
        self._last_millis = 0
        self.recovery = RecoveryReport()
        self.audit_sink: Callable[[AuditEntry], None] | None = None
        self._audit_pending: list[AuditEntry] = []

    # --- lifecycle ------------------------------------------------------------------------

    @classmethod
    def open(cls, data_dir: str | os.PathLike[str], *,
             audit_sink: Callable[[AuditEntry], None] | None = None) -> Store:
        """Open (creating it if need be) the store in ``data_dir`` and run start-up recovery.

        ``audit_sink``, when given, is called with every audit row once its transaction has
        committed (the daemon copies them to its audit file, :mod:`eyeserver.service.audit`),
        under the store's lock, so in the order of ``seq``.

        Raises
        ------
        StateConflictError
            When another process has the store open.
        StorageError
            When the index cannot be opened in WAL mode with ``synchronous=FULL`` or has a
            schema version this eyeserver does not know.
        """
        root = Path(data_dir)
        try:
            for name in (CAPTURES_DIR, CALIBRATIONS_DIR, QUARANTINE_DIR):
                makedirs_synced(root / name)
        except OSError as exc:
            raise StorageError(f"{root}: cannot create the data directory ({exc})") from exc
        lock_fd = _take_lock(root / LOCK_FILE)
        try:
            connection = _connect(root / INDEX_FILE)
        except BaseException:
            _release_lock(lock_fd)
            raise
        fsync_dir(root)  # the index file and its WAL are directory entries too
        store = cls(root, connection, lock_fd)
        store.audit_sink = audit_sink  # before recovery, which may audit too
        try:
            store.recovery = store._recover()
            store._last_millis = store._newest_millis()  # after recovery re-indexed orphans
        except BaseException:
            store.close()
            raise
        if not store.recovery.clean:
            _log.warning("storage recovery", extra={
                "data_dir": str(root),
                "recovered": list(store.recovery.recovered),
                "quarantined": [str(p) for p in store.recovery.quarantined],
                "missing": list(store.recovery.missing),
                "deletions_completed": list(store.recovery.deletions_completed),
                "unrecognised": [str(p) for p in store.recovery.unrecognised]})
        return store

    def close(self) -> None:
        """Close the index and release the data directory; idempotent."""
        with self._lock:
            if self._connection is not None:
                self._connection.close()
                self._connection = None
            if self._lock_fd is not None:
                _release_lock(self._lock_fd)
                self._lock_fd = None

    def __enter__(self) -> Store:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()

    def pragmas(self) -> dict[str, object]:
        """The index's ``journal_mode``, ``synchronous`` (2 is FULL) and ``user_version``."""
        with self._lock:
            db = self._db()
            return {name: db.execute(f"PRAGMA {name}").fetchone()[0]
                    for name in ("journal_mode", "synchronous", "user_version")}

    # --- captures -------------------------------------------------------------------------

    def add_capture(self, kind: BundleKind, rig: RigSpec, frames: Sequence[BundleFrameData], *,
                    unit: str, calibration_id: str | None, bit_depth: int | None = None,
                    extra: Mapping[str, object] | None = None,
                    chessboard: ChessboardSpec | None = None) -> CaptureRecord:
        """Write a capture bundle and index it; returns once both are durable.

        Parameters
        ----------
        kind, rig, frames, bit_depth, extra, chessboard
            As for :func:`eyeserver.io.write_bundle`; ``extra`` must not use the key
            ``"capture"``, which the store fills with the id, unit and calibration.
        unit : str
            The unit that took the capture.
        calibration_id : str or None
            The calibration in use.

        Raises
        ------
        ValueError
            When the bundle would break FORMATS.md (nothing is written).
        StorageError
            When the files cannot be written.
        """
        if calibration_id is not None and not is_calibration_id(calibration_id):
            raise StorageError(f"calibration_id {calibration_id!r} is not a calibration id")
        extra = dict(extra or {})
        if _CAPTURE_KEY in extra:
            raise ValueError(f"extra: the key {_CAPTURE_KEY!r} is reserved for the store")
        for _attempt in range(8):
            capture_id = self._new_id("cap")
            extra[_CAPTURE_KEY] = {"id": capture_id, "unit": unit,
                                   "calibration_id": calibration_id}
            try:
                bundle = write_bundle(self.captures_dir / capture_id, kind, rig, frames,
                                      bit_depth=bit_depth, created=_id_time(capture_id),
                                      extra=extra, chessboard=chessboard)
            except FileExistsError:
                continue  # an id left by an earlier run with a clock set back: draw again
            except OSError as exc:
                raise StorageError(f"capture {capture_id}: cannot write the bundle ({exc})"
                                   ) from exc
            break
        else:
            raise StorageError(f"{self.captures_dir}: no free capture id (is it a directory?)")
        record = CaptureRecord(capture_id, kind, unit, calibration_id, _id_time(capture_id),
                               len(bundle.frames), "ok", bundle.path)
        with self._transaction() as db:
            self._insert_capture(db, record)
        return record

    def get_capture(self, capture_id: str) -> CaptureRecord:
        """The record of one capture.

        Raises
        ------
        StorageError
            When ``capture_id`` is not a capture id.
        UnknownIdError
            When there is no such capture.
        """
        self._check_capture_id(capture_id)
        with self._lock:
            row = self._db().execute(f"SELECT {_CAPTURE_COLUMNS} FROM captures WHERE id = ?",
                                     (capture_id,)).fetchone()
        if row is None:
            raise UnknownIdError(capture_id, "capture")
        return self._capture_record(row)

    def capture_path(self, capture_id: str) -> Path:
        """The bundle directory of a known capture (see :meth:`get_capture` for errors)."""
        return self.get_capture(capture_id).path

    def list_captures(self, limit: int = 50, offset: int = 0, unit: str | None = None,
                      since: datetime | None = None, *, until: datetime | None = None,
                      kind: str | None = None, calibration_id: str | None = None,
                      ) -> tuple[list[CaptureRecord], int]:
        """Captures newest first, one page at a time.

        Every filter given must hold (each is an indexed column).

        Parameters
        ----------
        limit : int
            Page size, 1 to 1000.
        offset : int
            Records to skip, at least 0.
        unit : str, optional
            Only captures of this unit.
        since : datetime, optional
            Only captures created at or after this time zone-aware moment.
        until : datetime, optional
            Only captures created before this time zone-aware moment (so consecutive windows
            ``since=a, until=b`` and ``since=b, until=c`` neither overlap nor leave a gap).
        kind : str, optional
            Only captures of this bundle kind.
        calibration_id : str, optional
            Only captures taken while this calibration was active.

        Returns
        -------
        records : list of CaptureRecord
            The page.
        total : int
            How many captures match the filters, over all pages.
        """
        if isinstance(limit, bool) or not 1 <= limit <= 1000:
            raise ValueError(f"limit must be between 1 and 1000, got {limit!r}")
        if isinstance(offset, bool) or offset < 0:
            raise ValueError(f"offset must be at least 0, got {offset!r}")
        clauses: list[str] = []
        parameters: list[object] = []
        if unit is not None:
            clauses.append("unit = ?")
            parameters.append(unit)
        if kind is not None:
            clauses.append("kind = ?")
            parameters.append(kind)
        if calibration_id is not None:
            clauses.append("calibration_id = ?")
            parameters.append(calibration_id)
        # ``created`` holds whole milliseconds; rounding a bound up keeps both comparisons exact.
        for name, moment, operator in (("since", since, ">="), ("until", until, "<")):
            if moment is None:
                continue
            if moment.tzinfo is None or moment.utcoffset() is None:
                raise ValueError(f"{name} must be time zone-aware")
            clauses.append(f"created {operator} ?")
            parameters.append(_utc_text(_ceil_millis(moment)))
        where = f"WHERE {' AND '.join(clauses)}" if clauses else ""
        with self._lock:
            db = self._db()
            total = int(db.execute(f"SELECT COUNT(*) FROM captures {where}",
                                   parameters).fetchone()[0])
            rows = db.execute(f"SELECT {_CAPTURE_COLUMNS} FROM captures {where} "
                              "ORDER BY id DESC LIMIT ? OFFSET ?",
                              [*parameters, limit, offset]).fetchall()
        return [self._capture_record(row) for row in rows], total

    def delete_capture(self, capture_id: str, *, actor: str, reason: str) -> None:
        """Delete a capture's bundle and index row, after recording the request in the audit log.

        The directory is first renamed to a hidden ``.<id>.<hex>.deleting`` name; a deletion
        interrupted after its audit row is finished at the next start-up.

        Raises
        ------
        StorageError, UnknownIdError
            As for :meth:`get_capture`; also when ``actor`` or ``reason`` is empty.
        """
        _check_who(actor, reason)
        record = self.get_capture(capture_id)
        with self._transaction() as db:
            self._audit(db, actor, "delete_capture", capture_id,
                        {"reason": reason, "status": record.status, "unit": record.unit})
        with self._lock:
            directory = self.captures_dir / capture_id
            if os.path.lexists(directory):
                doomed = self.captures_dir / f".{capture_id}.{secrets.token_hex(6)}.deleting"
                try:
                    os.rename(directory, doomed)
                    fsync_dir(self.captures_dir)
                    shutil.rmtree(doomed)
                    fsync_dir(self.captures_dir)
                except OSError as exc:
                    # Audited and (if renamed) hidden: the next start-up finishes the deletion.
                    raise StorageError(f"capture {capture_id}: cannot delete ({exc})") from exc
            with self._transaction() as db:
                db.execute("DELETE FROM captures WHERE id = ?", (capture_id,))

    # --- calibrations ---------------------------------------------------------------------

    def import_calibration(self, source_dir: str | os.PathLike[str], *, actor: str,
                           source: str | None = None) -> CalibrationRecord:
        """Validate a calibration directory and copy it into the store under a new id.

        ``source`` is recorded as where the calibration came from (default: ``source_dir``);
        give it when ``source_dir`` is a temporary directory that means nothing later.

        Raises
        ------
        FormatError
            When ``source_dir`` is not a valid calibration (names the file and the field).
        StorageError
            When the copy cannot be written.
        """
        _check_who(actor)
        directory = Path(source_dir)
        origin = str(directory) if source is None else source
        if not origin.strip():
            raise StorageError("source: say where the calibration came from")
        document = load_calibration(directory)
        calibration_id = self._new_id("cal")
        target = self.calibrations_dir / calibration_id
        staging = self.calibrations_dir / f".{calibration_id}.{secrets.token_hex(6)}.partial"
        try:
            staging.mkdir()
            try:
                for name in (CALIBRATION_FILE, ARRAYS_FILE):
                    if (directory / name).is_file():
                        write_synced(staging / name, (directory / name).read_bytes())
                fsync_dir(staging)
                os.rename(staging, target)
                fsync_dir(self.calibrations_dir)
            except BaseException:
                with contextlib.suppress(OSError):
                    shutil.rmtree(staging)
                raise
        except OSError as exc:
            raise StorageError(f"{directory}: cannot copy the calibration into the store ({exc})"
                               ) from exc
        load_calibration(target)  # the copy, as the pipeline will read it
        record = CalibrationRecord(calibration_id, str(document.get("created", "")),
                                   _now_text(), origin, _quality_of(document), False, "ok",
                                   target)
        with self._transaction() as db:
            self._insert_calibration(db, record)
            self._audit(db, actor, "import_calibration", calibration_id,
                        {"source": origin})
        return record

    def get_calibration(self, calibration_id: str) -> CalibrationRecord:
        """The record of one calibration (errors as for :meth:`get_capture`)."""
        if not is_calibration_id(calibration_id):
            raise StorageError(f"{calibration_id!r} is not a calibration id")
        with self._lock:
            row = self._db().execute(
                f"SELECT {_CALIBRATION_COLUMNS} FROM calibrations WHERE id = ?",
                (calibration_id,)).fetchone()
        if row is None:
            raise UnknownIdError(calibration_id, "calibration")
        return self._calibration_record(row)

    def list_calibrations(self) -> list[CalibrationRecord]:
        """Every calibration, newest first."""
        with self._lock:
            rows = self._db().execute(
                f"SELECT {_CALIBRATION_COLUMNS} FROM calibrations ORDER BY id DESC").fetchall()
        return [self._calibration_record(row) for row in rows]

    def activate_calibration(self, calibration_id: str, *, actor: str) -> CalibrationRecord:
        """Make ``calibration_id`` the one active calibration (one audited transaction).

        Raises
        ------
        StorageError, UnknownIdError
            As for :meth:`get_calibration`; also when its directory is missing.
        """
        _check_who(actor)
        with self._lock:
            record = self.get_calibration(calibration_id)
            if record.status != "ok":
                raise StorageError(f"calibration {calibration_id} is {record.status}; "
                                   "it cannot be activated")
            previous = self.active_calibration()
            with self._transaction() as db:
                db.execute("UPDATE calibrations SET active = 0 WHERE active = 1")
                db.execute("UPDATE calibrations SET active = 1 WHERE id = ?", (calibration_id,))
                self._audit(db, actor, "activate_calibration", calibration_id,
                            {"previous": previous.id if previous else None})
            return self.get_calibration(calibration_id)

    def active_calibration(self) -> CalibrationRecord | None:
        """The active calibration, or None before one is activated."""
        with self._lock:
            row = self._db().execute(
                f"SELECT {_CALIBRATION_COLUMNS} FROM calibrations WHERE active = 1").fetchone()
        return None if row is None else self._calibration_record(row)

    # --- audit ----------------------------------------------------------------------------

    def add_audit_entries(self, actor: str, action: str, target: str,
                          details: Sequence[Mapping[str, object]]) -> None:
        """Record changes made outside the store (a device's settings), one row per detail,
        in one durable transaction.

        Raises
        ------
        StorageError
            ``actor`` is empty, or the index cannot be written.
        """
        _check_who(actor)
        with self._transaction() as db:
            for detail in details:
                self._audit(db, actor, action, target, detail)

    def audit_log(self, limit: int = 100) -> list[AuditEntry]:
        """The newest ``limit`` audit entries, newest first."""
        if isinstance(limit, bool) or limit < 1:
            raise ValueError(f"limit must be at least 1, got {limit!r}")
        with self._lock:
            rows = self._db().execute(
                "SELECT seq, time, actor, action, target, detail FROM audit "
                "ORDER BY seq DESC LIMIT ?", (limit,)).fetchall()
        return [AuditEntry(int(seq), when, actor, action, target, json.loads(detail))
                for seq, when, actor, action, target, detail in rows]

    # --- hooks for the tables of other modules (patients, pose verification) --------------

    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One durable write transaction (``BEGIN IMMEDIATE`` … ``COMMIT``) on the index, for
        the tables of :data:`_ADDED_TABLES`; audit rows go in it with :meth:`audit_in`."""
        with self._transaction() as db:
            yield db

    def audit_in(self, db: sqlite3.Connection, actor: str, action: str, target: str,
                 detail: Mapping[str, object]) -> None:
        """Add an audit row inside a :meth:`transaction` (it reaches ``audit_sink`` once that
        commits). Raises :class:`StorageError` for an empty ``actor``."""
        _check_who(actor)
        self._audit(db, actor, action, target, detail)

    def query(self, sql: str, parameters: Sequence[object] = ()) -> list[tuple[Any, ...]]:
        """The rows of one read-only statement on the index."""
        with self._lock:
            return list(self._db().execute(sql, tuple(parameters)).fetchall())

    def new_id(self, prefix: str) -> str:
        """A new ``<prefix>-<UTC time to the millisecond>-<4 hex digits>`` id, strictly later
        than every id this store handed out before (they sort in creation order)."""
        return self._new_id(prefix)

    def write_document(self, relative: str, text: str) -> Path:
        """Write ``text`` to ``DATA_DIR/<relative>`` atomically and durably (directories made
        and fsynced as needed); returns the path. Write it before the row that names it.

        Raises
        ------
        StorageError
            ``relative`` leaves the data directory, or the file cannot be written.
        """
        path = (self.data_dir / relative).resolve()
        if not path.is_relative_to(self.data_dir.resolve()) or path == self.data_dir.resolve():
            raise StorageError(f"{relative!r} is not a path inside the data directory")
        try:
            makedirs_synced(path.parent)
            atomic_write_text(path, text)
        except OSError as exc:
            raise StorageError(f"{relative}: cannot write ({exc})") from exc
        return path

    def read_document(self, relative: str) -> str:
        """The text of a document written by :meth:`write_document`.

        Raises
        ------
        StorageError
            The file is missing or unreadable (the message names it).
        """
        try:
            return (self.data_dir / relative).read_text(encoding="utf-8")
        except OSError as exc:
            raise StorageError(f"{relative}: cannot read ({exc})") from exc

    # --- internals ------------------------------------------------------------------------

    def _db(self) -> sqlite3.Connection:
        if self._connection is None:
            raise StorageError(f"{self.data_dir}: the store is closed")
        return self._connection

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        # BEGIN IMMEDIATE takes the write lock up front; COMMIT returns once the WAL is fsynced.
        with self._lock:
            db = self._db()
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                self._audit_pending.clear()
                raise
            db.execute("COMMIT")
            committed, self._audit_pending = self._audit_pending, []
            if self.audit_sink is not None:
                for entry in committed:
                    self.audit_sink(entry)

    def _new_id(self, prefix: str) -> str:
        # Strictly increasing milliseconds within the store, so ids sort in creation order even
        # when two threads ask in the same millisecond or the clock steps back.
        with self._lock:
            millis = max(time.time_ns() // 1_000_000, self._last_millis + 1)
            self._last_millis = millis
        moment = datetime.fromtimestamp(millis / 1000, UTC)
        stamp = moment.strftime("%Y%m%dT%H%M%S") + f"{millis % 1000:03d}Z"
        return f"{prefix}-{stamp}-{secrets.token_hex(2)}"

    def _newest_millis(self) -> int:
        db = self._db()
        newest = 0
        for table in ("captures", "calibrations"):
            row = db.execute(f"SELECT MAX(id) FROM {table}").fetchone()
            if row[0] is not None and _ID_PATTERN.fullmatch(row[0]):
                newest = max(newest, _id_millis(row[0]))
        return newest

    def _check_capture_id(self, capture_id: str) -> None:
        if not isinstance(capture_id, str) or not is_capture_id(capture_id):
            raise StorageError(f"{capture_id!r} is not a capture id "
                               "(expected cap-YYYYMMDDTHHMMSSmmmZ-hhhh)")

    def _capture_record(self, row: tuple[Any, ...]) -> CaptureRecord:
        capture_id, kind, unit, calibration_id, created, frame_count, status = row
        return CaptureRecord(capture_id, kind, unit, calibration_id, created, int(frame_count),
                             status, self.captures_dir / capture_id)

    def _calibration_record(self, row: tuple[Any, ...]) -> CalibrationRecord:
        calibration_id, created, imported, source, quality, active, status = row
        return CalibrationRecord(calibration_id, created, imported, source, json.loads(quality),
                                 bool(active), status, self.calibrations_dir / calibration_id)

    @staticmethod
    def _insert_capture(db: sqlite3.Connection, record: CaptureRecord) -> None:
        db.execute(f"INSERT INTO captures ({_CAPTURE_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (record.id, record.kind, record.unit, record.calibration_id, record.created,
                    record.frame_count, record.status))

    @staticmethod
    def _insert_calibration(db: sqlite3.Connection, record: CalibrationRecord) -> None:
        db.execute(f"INSERT INTO calibrations ({_CALIBRATION_COLUMNS}) "
                   "VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (record.id, record.created, record.imported, record.source,
                    json.dumps(dict(record.quality)), int(record.active), record.status))

    def _audit(self, db: sqlite3.Connection, actor: str, action: str, target: str,
               detail: Mapping[str, object]) -> None:
        # Inside a _transaction: the row is handed to audit_sink once that commits.
        when = _now_text()
        cursor = db.execute("INSERT INTO audit (time, actor, action, target, detail) "
                            "VALUES (?, ?, ?, ?, ?)",
                            (when, actor, action, target, json.dumps(dict(detail))))
        self._audit_pending.append(AuditEntry(int(cursor.lastrowid or 0), when, actor, action,
                                              target, dict(detail)))

    # --- start-up recovery ----------------------------------------------------------------

    def _recover(self) -> RecoveryReport:
        found = _Recovery()
        self._recover_area(self.captures_dir, "captures", found)
        self._recover_area(self.calibrations_dir, "calibrations", found)
        return found.freeze()

    def _recover_area(self, area: Path, table: str, found: _Recovery) -> None:
        db = self._db()
        known = {row[0]: row[1] for row in db.execute(f"SELECT id, status FROM {table}")}
        audited_deletions = {row[0] for row in db.execute(
            "SELECT target FROM audit WHERE action = 'delete_capture'")}
        present: set[str] = set()
        for entry in sorted(area.iterdir()):
            if entry.name.startswith("."):
                deleting = _DELETING_PATTERN.fullmatch(entry.name)
                if deleting and deleting.group("id") in audited_deletions:
                    self._finish_deletion(entry, deleting.group("id"), table)
                    known.pop(deleting.group("id"), None)
                    found.deletions_completed.append(deleting.group("id"))
                else:
                    found.quarantined.append(self._quarantine(entry, table))
                continue
            valid = is_capture_id(entry.name) if table == "captures" else is_calibration_id(
                entry.name)
            if not valid or not entry.is_dir() or entry.is_symlink():
                found.unrecognised.append(entry)
                continue
            present.add(entry.name)
            if entry.name in known:
                continue
            try:
                if table == "captures":
                    self._reindex_capture(entry)
                else:
                    self._reindex_calibration(entry)
            except EyeserverError as exc:
                _log.warning("unreadable directory left in place",
                             extra={"path": str(entry), "reason": str(exc)})
                found.unrecognised.append(entry)
                continue
            found.recovered.append(entry.name)
        with self._transaction() as db:
            for item_id, status in known.items():
                if item_id not in present:
                    found.missing.append(item_id)
                    db.execute(f"UPDATE {table} SET status = 'missing' WHERE id = ?", (item_id,))
                elif status != "ok":  # a directory restored by hand
                    db.execute(f"UPDATE {table} SET status = 'ok' WHERE id = ?", (item_id,))

    def _reindex_capture(self, directory: Path) -> None:
        bundle = read_bundle(directory)
        stored = bundle.extra.get(_CAPTURE_KEY)
        stored = stored if isinstance(stored, dict) else {}
        unit = stored.get("unit")
        calibration_id = stored.get("calibration_id")
        record = CaptureRecord(
            directory.name, bundle.kind, unit if isinstance(unit, str) else "unknown",
            calibration_id if isinstance(calibration_id, str) else None,
            _id_time(directory.name), len(bundle.frames), "ok", directory)
        with self._transaction() as db:
            self._insert_capture(db, record)

    def _reindex_calibration(self, directory: Path) -> None:
        document = load_calibration(directory)
        record = CalibrationRecord(directory.name, str(document.get("created", "")),
                                   _now_text(), "recovered", _quality_of(document), False, "ok",
                                   directory)
        with self._transaction() as db:
            self._insert_calibration(db, record)
            self._audit(db, "eyeserver", "recover_calibration", directory.name, {})

    def _finish_deletion(self, doomed: Path, item_id: str, table: str) -> None:
        shutil.rmtree(doomed)
        fsync_dir(doomed.parent)
        with self._transaction() as db:
            db.execute(f"DELETE FROM {table} WHERE id = ?", (item_id,))

    def _quarantine(self, entry: Path, area: str) -> Path:
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        while True:
            target = self.quarantine_dir / f"{stamp}-{area}-{entry.name.lstrip('.')}"
            if not os.path.lexists(target):
                break
            stamp += "-" + secrets.token_hex(2)
        os.rename(entry, target)
        fsync_dir(self.quarantine_dir)
        fsync_dir(entry.parent)
        return target


_CAPTURE_COLUMNS = "id, kind, unit, calibration_id, created, frame_count, status"
_CALIBRATION_COLUMNS = "id, created, imported, source, quality, active, status"


def _check_who(actor: str, reason: str | None = None) -> None:
    if not isinstance(actor, str) or not actor.strip():
        raise StorageError("actor: every change to the store must name who asked for it")
    if reason is not None and (not isinstance(reason, str) or not reason.strip()):
        raise StorageError("reason: a deletion must give its reason")


def _connect(path: Path) -> sqlite3.Connection:
    try:
        # isolation_level=None: no implicit transactions; _transaction() issues BEGIN/COMMIT.
        db = sqlite3.connect(path, check_same_thread=False, isolation_level=None, timeout=30)
    except sqlite3.Error as exc:
        raise StorageError(f"{path}: cannot open the index ({exc})") from exc
    try:
        mode = db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise StorageError(f"{path}: the index refuses WAL mode (journal_mode is {mode})")
        db.execute("PRAGMA synchronous=FULL")
        synchronous = db.execute("PRAGMA synchronous").fetchone()[0]
        if synchronous != 2:
            raise StorageError(f"{path}: synchronous=FULL did not take (it is {synchronous})")
        db.execute("PRAGMA foreign_keys=ON")
        version = db.execute("PRAGMA user_version").fetchone()[0]
        if version == 0:
            # One transaction: a crash leaves either no schema or the whole versioned one.
            db.executescript(f"BEGIN IMMEDIATE; {_SCHEMA} {_ADDED_TABLES} "
                             f"PRAGMA user_version={SCHEMA_VERSION}; COMMIT;")
        elif version != SCHEMA_VERSION:
            raise StorageError(f"{path}: index schema version {version}; this eyeserver "
                               f"knows version {SCHEMA_VERSION}")
        else:
            db.executescript(f"BEGIN IMMEDIATE; {_ADDED_INDEXES} {_ADDED_TABLES} COMMIT;")
    except sqlite3.DatabaseError as exc:
        db.close()
        raise StorageError(f"{path}: unusable index ({exc})") from exc
    except BaseException:
        db.close()
        raise
    return db


def _take_lock(path: Path) -> int | None:
    if fcntl is None:  # pragma: no cover
        return None
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise StateConflictError(f"{path.parent}: the store is open in another process") from None
    return fd


def _release_lock(fd: int | None) -> None:
    if fd is not None:
        os.close(fd)  # closing the descriptor drops the flock
