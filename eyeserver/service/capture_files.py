"""A stored capture's files for the API: its bundle as one zip archive, and single images.

Both read the bundle directory as the store keeps it (FORMATS.md); nothing here writes to the
store. Every function blocks on the disk: the API calls them from worker threads.
"""

from __future__ import annotations

import tempfile
from typing import IO

from eyeserver.errors import EyeserverError
from eyeserver.io import Bundle, read_bundle, write_bundle_zip
from eyeserver.service.storage import CaptureRecord, Store

__all__ = ["SPOOL_MAX_BYTES", "CaptureDataNotFoundError", "bundle_archive", "bundle_image"]

SPOOL_MAX_BYTES = 32 * 2**20
"""An archive up to this size is built in memory; a larger one rolls over to a temporary file."""


class CaptureDataNotFoundError(EyeserverError):
    """A capture exists but not the part asked for: a frame, a camera's image in a frame, or its
    bundle directory (a capture whose status is ``missing``) (HTTP 404)."""


def _bundle(store: Store, record: CaptureRecord) -> Bundle:
    if not record.path.is_dir():
        store.get_capture(record.id)  # UnknownIdError when it was deleted meanwhile
        raise CaptureDataNotFoundError(f"capture {record.id}: its bundle is missing from the "
                                       "store (status 'missing')")
    return read_bundle(record.path)


def bundle_archive(store: Store, capture_id: str) -> tuple[IO[bytes], int]:
    """The capture's bundle as a zip archive, in one folder named after the capture.

    See :func:`eyeserver.io.write_bundle_zip`: ``bundle.json`` and the images it names, byte
    for byte, the images stored without compression.

    Returns
    -------
    archive : binary file
        Positioned at its start; the caller closes it. Held in memory up to
        :data:`SPOOL_MAX_BYTES`, then in an anonymous temporary file.
    size : int
        Its length in bytes.

    Raises
    ------
    UnknownIdError, StorageError
        As for :meth:`Store.get_capture` (also when the capture is deleted meanwhile).
    CaptureDataNotFoundError
        The capture's bundle directory is missing.
    FormatError
        The stored bundle breaks FORMATS.md.
    """
    record = store.get_capture(capture_id)
    bundle = _bundle(store, record)
    # Not a with-block: the open file is handed to the caller, who streams and closes it.
    spool = tempfile.SpooledTemporaryFile(max_size=SPOOL_MAX_BYTES, mode="w+b")  # noqa: SIM115
    try:
        try:
            write_bundle_zip(bundle, spool, folder=record.id)
        except FileNotFoundError as exc:
            store.get_capture(capture_id)  # UnknownIdError when it was deleted meanwhile
            raise CaptureDataNotFoundError(f"capture {capture_id}: a file of its bundle is "
                                           f"missing ({exc.filename})") from exc
        size = spool.tell()
        spool.seek(0)
    except BaseException:
        spool.close()
        raise
    return spool, size


def bundle_image(store: Store, capture_id: str, frame: int, camera_id: str) -> bytes:
    """One image of a capture as stored (a PNG, 8- or 16-bit, single channel).

    Raises
    ------
    UnknownIdError, StorageError
        As for :meth:`Store.get_capture`.
    CaptureDataNotFoundError
        The bundle has no frame ``frame``, the frame no image of ``camera_id`` (the message
        names what exists instead), or the bundle directory is missing.
    FormatError
        The stored bundle breaks FORMATS.md.
    """
    record = store.get_capture(capture_id)
    bundle = _bundle(store, record)
    if frame not in bundle.frame_indices:
        raise CaptureDataNotFoundError(
            f"capture {capture_id} has no frame {frame} (its frames are "
            f"{', '.join(str(i) for i in bundle.frame_indices)})")
    cameras = bundle.cameras_in_frame(frame)
    if camera_id not in cameras:
        known = "a camera of the rig" if camera_id in bundle.rig.camera_ids else \
            "not a camera of the rig"
        raise CaptureDataNotFoundError(
            f"frame {frame} of capture {capture_id} holds no image of camera {camera_id!r} "
            f"({known}; the frame holds {', '.join(cameras) or 'no image'})")
    try:
        return bundle.image_bytes(frame, camera_id)
    except FileNotFoundError as exc:
        store.get_capture(capture_id)  # UnknownIdError when it was deleted meanwhile
        raise CaptureDataNotFoundError(f"capture {capture_id}: the image file of camera "
                                       f"{camera_id} in frame {frame} is missing") from exc
