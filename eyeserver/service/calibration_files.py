"""Stored calibrations for the API: their lineage, their download and their comparison.

Calibrations are immutable once stored: nothing rewrites a calibration directory, and a new
phase-to-height fit is a new calibration whose ``lineage.parent_id`` (in ``calibration.json``)
names the one whose geometry it extends. A calibration's ``version`` is its place in the order
of creation in this store (1 for the first), so it never changes either.

The download is a zip of the calibration directory (``calibration.json``, ``arrays.npz``) under
one folder named after the calibration, with the input bundles of a calibration made in a
guided session under ``<id>/inputs/<capture id>/`` (the evidence, byte for byte), as long as
those captures are still in the store; a missing one is listed in ``inputs/MISSING.txt``.
"""

from __future__ import annotations

import io
import json
import tempfile
import zipfile
from dataclasses import dataclass
from typing import IO, Any

from eyeserver.calibration.artefact import CALIBRATION_FILE, load_calibration
from eyeserver.calibration.compare import compare_calibrations
from eyeserver.errors import EyeserverError, FormatError
from eyeserver.io import read_bundle, write_bundle_zip
from eyeserver.service.storage import CalibrationRecord, Store, UnknownIdError, is_capture_id

__all__ = ["Lineage", "calibration_archive", "compare", "input_capture_ids", "lineage"]

_SPOOL_MAX_BYTES = 16 * 2**20


@dataclass(frozen=True)
class Lineage:
    """Where a calibration stands among the others."""

    version: int
    parent_id: str | None
    session_id: str | None


def _document(record: CalibrationRecord) -> dict[str, Any]:
    try:
        document: dict[str, Any] = json.loads(
            (record.path / CALIBRATION_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return document


def lineage(store: Store, record: CalibrationRecord,
            order: list[CalibrationRecord] | None = None) -> Lineage:
    """The version (place in the order of creation), parent and session of ``record``.

    ``order`` is :meth:`Store.list_calibrations` when the caller has it already.
    """
    records = order if order is not None else store.list_calibrations()
    ids = sorted(r.id for r in records)  # ids sort in creation order
    version = ids.index(record.id) + 1 if record.id in ids else 0
    stored = _document(record).get("lineage")
    stored = stored if isinstance(stored, dict) else {}
    parent, session = stored.get("parent_id"), stored.get("session_id")
    return Lineage(version, parent if isinstance(parent, str) else None,
                   session if isinstance(session, str) else None)


def input_capture_ids(record: CalibrationRecord) -> list[str]:
    """The stored captures a calibration was made from (guided sessions only)."""
    inputs = _document(record).get("inputs")
    found: list[str] = []
    if isinstance(inputs, dict):
        for entries in inputs.values():
            for entry in entries if isinstance(entries, list) else []:
                name = entry.get("bundle") if isinstance(entry, dict) else None
                if isinstance(name, str) and is_capture_id(name) and name not in found:
                    found.append(name)
    return found


def calibration_archive(store: Store, calibration_id: str) -> tuple[IO[bytes], int]:
    """The calibration directory with its input bundles as a zip (see the module docstring).

    Returns the archive positioned at its start (the caller closes it) and its size.

    Raises
    ------
    UnknownIdError, StorageError
        As for :meth:`Store.get_calibration`.
    """
    record = store.get_calibration(calibration_id)
    spool = tempfile.SpooledTemporaryFile(max_size=_SPOOL_MAX_BYTES, mode="w+b")  # noqa: SIM115
    try:
        with zipfile.ZipFile(spool, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            for path in sorted(record.path.iterdir()):
                if path.is_file():
                    archive.write(path, f"{record.id}/{path.name}")
            missing = []
            for capture_id in input_capture_ids(record):
                try:
                    bundle = read_bundle(store.capture_path(capture_id))
                    # A bundle's own zip (images stored, bundle.json deflated), member by member.
                    part = io.BytesIO()
                    write_bundle_zip(bundle, part, folder=f"{record.id}/inputs/{capture_id}")
                except (UnknownIdError, FormatError, FileNotFoundError):
                    missing.append(capture_id)
                    continue
                with zipfile.ZipFile(part) as members:
                    for info in members.infolist():
                        archive.writestr(info, members.read(info))
            if missing:
                archive.writestr(f"{record.id}/inputs/MISSING.txt",
                                 "input captures no longer in the store:\n"
                                 + "".join(f"{m}\n" for m in missing))
        size = spool.tell()
        spool.seek(0)
    except BaseException:
        spool.close()
        raise
    return spool, size


def compare(store: Store, id_a: str, id_b: str) -> dict[str, Any]:
    """:func:`~eyeserver.calibration.compare.compare_calibrations` of two stored calibrations,
    with their ids.

    Raises
    ------
    UnknownIdError, StorageError
        As for :meth:`Store.get_calibration`.
    EyeserverError
        The two were made for different rigs.
    """
    record_a, record_b = store.get_calibration(id_a), store.get_calibration(id_b)
    document_a, document_b = load_calibration(record_a.path), load_calibration(record_b.path)
    if document_a["rig"] != document_b["rig"]:
        raise EyeserverError(f"{id_a} and {id_b} were made for different rigs")
    return {"a": id_a, "b": id_b, **compare_calibrations(document_a, document_b)}
