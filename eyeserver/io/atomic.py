"""Crash-safe file replacement.

A reader sees either the old file or the complete new one, never a torn write, and once a
function here returns the new content survives a power loss: the data is fsynced before the
rename and the directory entry is fsynced after it (POSIX does not promise that a rename is
durable until its directory is synced).
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path

__all__ = [
    "atomic_write_bytes",
    "atomic_write_text",
    "fsync_dir",
    "makedirs_synced",
    "write_synced",
]


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """Flush a directory's entries (creations, renames, deletions) to stable storage.

    Parameters
    ----------
    path : str or path-like
        The directory.

    Notes
    -----
    Windows cannot open a directory as a file and makes renames durable by itself, so this is a
    no-op there.
    """
    if os.name == "nt":
        return
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def makedirs_synced(path: str | os.PathLike[str]) -> None:
    """Create a directory and any missing parents, durably.

    Like ``os.makedirs(path, exist_ok=True)``, but each directory it creates is fsynced into its
    parent, so files later made durable inside it cannot vanish with their directory.

    Parameters
    ----------
    path : str or path-like
        The directory; nothing happens when it exists.

    Raises
    ------
    FileExistsError
        When ``path`` exists and is not a directory.
    """
    target = Path(path)
    missing: list[Path] = []
    directory = target
    while not directory.exists() and directory.parent != directory:
        missing.append(directory)
        directory = directory.parent
    for directory in reversed(missing):
        with contextlib.suppress(FileExistsError):  # another process may have made it meanwhile
            directory.mkdir()
        fsync_dir(directory.parent)
    if not target.is_dir():
        raise FileExistsError(f"{target} exists and is not a directory")


def write_synced(path: str | os.PathLike[str], data: bytes | bytearray | memoryview, *,
                 mode: int = 0o666) -> None:
    """Create ``path`` (which must not exist), write ``data`` and fsync it.

    Not atomic by itself: it is the building block for files inside a directory that is
    published as a whole (see :func:`eyeserver.io.write_bundle`). The directory itself is not
    synced; call :func:`fsync_dir` once after the last file.

    Parameters
    ----------
    path : str or path-like
        The file to create.
    data : bytes-like
        Its content.
    mode : int
        Permissions of the new file, before the process umask (0o600 for secrets).

    Raises
    ------
    FileExistsError
        When ``path`` already exists.
    """
    # The default 0o666 lets the process umask decide the permissions, as open() would.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), mode)
    try:
        view = memoryview(data)
        while view:
            written = os.write(fd, view)
            view = view[written:]
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes | bytearray | memoryview) -> None:
    """Replace ``path`` with ``data`` atomically and durably.

    The data goes to a hidden temporary file in the same directory (a rename is only atomic
    within one file system), which is fsynced, renamed over ``path`` with :func:`os.replace`,
    and followed by an fsync of the directory. On failure the temporary file is removed and
    ``path`` is untouched.

    Parameters
    ----------
    path : str or path-like
        The file to write; its directory must exist.
    data : bytes-like
        The complete new content.
    """
    target = Path(path)
    directory = target.parent
    while True:
        temporary = directory / f".{target.name}.{secrets.token_hex(6)}.tmp"
        try:
            write_synced(temporary, data)
        except FileExistsError:
            continue
        except BaseException:
            with contextlib.suppress(OSError):
                temporary.unlink()
            raise
        break
    try:
        os.replace(temporary, target)
    except BaseException:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise
    fsync_dir(directory)


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> None:
    """Replace ``path`` with ``text`` atomically and durably.

    Line endings are written as given (no platform translation).

    Parameters
    ----------
    path : str or path-like
        The file to write; its directory must exist.
    text : str
        The complete new content.
    encoding : str, optional
        Text encoding, UTF-8 by default.
    """
    atomic_write_bytes(path, text.encode(encoding))
