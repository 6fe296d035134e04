"""Unpack an uploaded calibration archive safely.

A client sends a calibration directory (``calibration.json`` and, usually, ``arrays.npz``, as
``eyeserver calibrate`` writes them) as a zip file. Nothing in the archive is trusted: only those
two names are extracted, flat or under one top-level folder; absolute names, ``..``
components, backslashes, symbolic links, encrypted members and anything else are refused before
a byte is written, and the unpacked size is bounded while copying (a member's declared size can
lie: a "zip bomb").
"""

from __future__ import annotations

import io
import stat
import zipfile
import zlib
from pathlib import Path, PurePosixPath

from eyeserver.calibration.artefact import ARRAYS_FILE, CALIBRATION_FILE
from eyeserver.errors import EyeserverError, FormatError

__all__ = ["ARCHIVE_NAME", "UploadTooLargeError", "unpack_calibration_zip"]

ARCHIVE_NAME = "<uploaded calibration.zip>"
"""How error messages name the uploaded archive (it has no path of its own)."""

_ALLOWED = (CALIBRATION_FILE, ARRAYS_FILE)
EVIDENCE_FOLDER = "inputs"
"""Where a downloaded calibration keeps its input bundles (``GET /calibrations/{id}/download``):
skipped on import, so a download can be uploaded again (to another daemon, after a reinstall)."""
_CHUNK = 1 << 20


class UploadTooLargeError(EyeserverError):
    """An upload, or what it unpacks to, exceeds the configured limit (the API answers 413)."""


def _refuse(member: str | None, reason: str) -> FormatError:
    return FormatError(ARCHIVE_NAME, member, reason)


def _evidence_of(parts: tuple[str, ...], is_dir: bool) -> str | None:
    """The calibration's folder (``""`` in a flat archive) when a member lies under
    ``<folder>/inputs/`` (or ``inputs/``): the input bundles a downloaded calibration carries
    as its evidence; None for any other member."""
    for at in (1, 0):
        if len(parts) > at and parts[at] == EVIDENCE_FOLDER:
            if len(parts) < at + 3 and not is_dir:
                return None  # not inside a bundle folder: the calibration's own checks
            return parts[0] if at else ""
    return None


def _safe_parts(info: zipfile.ZipInfo) -> tuple[str, ...]:
    """A member's path parts; refuses unsafe names (every member, the skipped ones too)."""
    name = info.filename
    if "\\" in name or name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise _refuse(name, "absolute or non-POSIX member names are not allowed")
    parts = PurePosixPath(name).parts
    if any(part in ("..", ".") for part in parts) or not parts:
        raise _refuse(name, "member names must not contain '..' or '.'")
    mode = info.external_attr >> 16
    if stat.S_ISLNK(mode):
        raise _refuse(name, "symbolic links are not allowed")
    if info.flag_bits & 0x1:
        raise _refuse(name, "encrypted members are not allowed")
    return parts


def _member_target(info: zipfile.ZipInfo, parts: tuple[str, ...]) -> str | None:
    """The file name a safe member (:func:`_safe_parts`) unpacks to (None for a directory
    entry); refuses any but the calibration's files."""
    name = info.filename
    if info.is_dir():
        if len(parts) != 1:
            raise _refuse(name, "only one top-level folder is allowed")
        return None
    if len(parts) > 2 or parts[-1] not in _ALLOWED:
        raise _refuse(name, f"only {' and '.join(_ALLOWED)} may be in the archive "
                      "(flat or in one top-level folder)")
    return parts[-1]


def unpack_calibration_zip(archive: bytes, target: Path, *, max_unpacked_bytes: int) -> None:
    """Check ``archive`` (a zip of a calibration directory) and extract it into ``target``.

    Parameters
    ----------
    archive : bytes
        The zip file.
    target : Path
        An existing empty directory; receives ``calibration.json`` (and ``arrays.npz``).
    max_unpacked_bytes : int
        Most bytes the members may unpack to, all together.

    Raises
    ------
    FormatError
        The archive is not a zip, holds an unsafe or unexpected member, holds two members of the
        same name or lacks ``calibration.json`` (names the member). The input bundles of a
        downloaded calibration (:data:`EVIDENCE_FOLDER`) are checked for safety and skipped.
        Nothing validates the calibration itself here: that is
        :func:`eyeserver.calibration.artefact.load_calibration`.
    UploadTooLargeError
        The members unpack to more than ``max_unpacked_bytes``.
    """
    try:
        bundle = zipfile.ZipFile(io.BytesIO(archive))
    except zipfile.BadZipFile as exc:
        raise _refuse(None, f"not a zip file ({exc})") from exc
    with bundle:
        chosen: dict[str, zipfile.ZipInfo] = {}
        folders = set()
        for info in bundle.infolist():
            parts = _safe_parts(info)
            evidence_folder = _evidence_of(parts, info.is_dir())
            if evidence_folder is not None:
                # The evidence stays in the archive; the calibration is what is stored. It
                # must lie in the calibration's own folder.
                folders.add(evidence_folder)
                continue
            name = _member_target(info, parts)
            if len(parts) == 2 or info.is_dir():
                folders.add(parts[0])
            elif len(parts) == 1:
                folders.add("")
            if name is None:
                continue
            if name in chosen:
                raise _refuse(info.filename, f"{name} appears twice in the archive")
            chosen[name] = info
        if len(folders) > 1:
            raise _refuse(None, "the files must be flat or in one top-level folder, found "
                          f"{sorted(f or '<top level>' for f in folders)}")
        if CALIBRATION_FILE not in chosen:
            raise _refuse(None, f"the archive holds no {CALIBRATION_FILE}")
        if sum(info.file_size for info in chosen.values()) > max_unpacked_bytes:
            raise UploadTooLargeError(f"{ARCHIVE_NAME}: unpacks to more than "
                                      f"{max_unpacked_bytes} bytes")
        written = 0
        for name, info in chosen.items():
            try:
                with bundle.open(info) as source, (target / name).open("xb") as sink:
                    while chunk := source.read(_CHUNK):
                        written += len(chunk)
                        if written > max_unpacked_bytes:
                            raise UploadTooLargeError(f"{ARCHIVE_NAME}: unpacks to more than "
                                                      f"{max_unpacked_bytes} bytes")
                        sink.write(chunk)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
                # A CRC mismatch, a truncated member or an unknown compression method.
                raise _refuse(info.filename, f"cannot be unpacked ({exc})") from exc
