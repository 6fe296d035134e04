"""Live tracking's reconstruction and fit in a process of their own.

The daemon's process also drives the rig (the simulated room renders there), serves HTTP and
feeds the WebSocket clients. Reconstruction and fit are numpy and SciPy work with many short
Python steps between the array operations; in the daemon's process they would hold the GIL
against acquisition and the event loop, and neither could use the machine's other core while
the other runs. So :class:`PoseWorker` runs :class:`~eyeserver.service.frame_pose.PoseFinder`
(:class:`~eyeserver.service.frame_pose.RigReconstructor` of the active calibration,
:func:`~eyeserver.eye.track.track_eye`, :func:`~eyeserver.eye.fit.fit_eye`)
in a child process (started with ``spawn``: the daemon has threads, and a forked child would
inherit their locks):

::

    processing thread ── ("pose", frame set, last pose) ──► child: reconstruct, follow or fit
                      ◄── pose | "lost: why" | "failed: traceback" ──

Before the stream, the session warms each child on a frame set taken for it (``"warm"``: the
window's cameras and the fringe strength of the expected eye; answered ``"warmed"``).

A frame set is two 640 × 512 images (≈ 0.7 MB at 8 bits pickled through a pipe, under a
millisecond); the cropped cameras of the tracking window stay cached in the child. The child
loads the calibration once, at the start, so a calibration that cannot reconstruct fails
:meth:`PoseWorker.start` (the session does not start) rather than the first frame. The child
ends when asked (:meth:`PoseWorker.close`), when the daemon's end of the pipe closes (the
daemon died), and ignores Ctrl-C (the daemon decides when tracking ends). A child that dies is
reported as :class:`TrackingWorkerError` on the next frame: the session ends with that error
(and the beam controller, without messages, holds the beam).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import signal
import sys
import traceback
from multiprocessing import get_context
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, NoReturn

import cv2
from threadpoolctl import threadpool_limits

from eyeserver.core.memory import keep_freed_memory
from eyeserver.errors import EyeserverError
from eyeserver.eye import EyeModel, EyePose, PoseError, fit_eye, track_eye
from eyeserver.io import RigSpec
from eyeserver.reconstruction import ReconstructionError
from eyeserver.service.frame_pose import FrameSet, PoseFinder, RigReconstructor

__all__ = ["FRAME_TIMEOUT_S", "START_TIMEOUT_S", "PoseWorker", "TrackingWorkerError"]

START_TIMEOUT_S = 120.0
"""How long the child may take to start (imports, the calibration's cameras): a few seconds."""

FRAME_TIMEOUT_S = 30.0
"""Longest a frame may take in the child (the global fit of a whole image takes about a second):
a child that hangs ends the session with :class:`TrackingWorkerError` instead of stalling it."""

_CLOSE_S = 5.0
_log = logging.getLogger(__name__)


# The workers run at the daemon's own priority, not below it. Nicer than the daemon (5, until
# 2026-12-03) they lost their core to it and to other programs of normal priority whenever the
# scheduler put them on the same core, though the two cores were three-fifths idle: measured in
# `eyeserver bench tracking --prerendered` (one slow machine hour, FFT reference 0.8 ms), a
# tracked frame's processing took 19.9 ms median and 29.0 ms p99 at niceness 5, 17.9 and
# 22.9 ms at the daemon's (latency p99 39.5 → 33.6 ms); rendered live, every frame was still
# acquired and processed. Acquisition needs little CPU and is woken ahead of a busy worker; the
# simulated room's rendering stays below both (RENDER_NICENESS).


class TrackingWorkerError(EyeserverError):
    """The tracking worker process failed: it did not start, died, or a frame raised an
    unexpected error in it (the child's traceback is in the message)."""


PIPE_BYTES = 1 << 20
"""Capacity asked for the pipe that carries frame sets to the child (Linux's default limit for
an unprivileged process, /proc/sys/fs/pipe-max-size): a frame set of two 8-bit images
(≈ 0.7 MB) is written whole without waiting for the child to read it. Through a socket pair's
≈ 200 kB the daemon's send waited for the child's reads, each as soon as the child got a core.
Measured in the tracking bench, with the rendering on the same cores: the send took 1.1 ms
median, 10.8 ms p99 through the socket pair, 0.5 and 8 ms through this pipe (what is left: the
sending thread waiting for a core or for the daemon's interpreter lock)."""


class _Channel:
    """One end of the two pipes between the daemon and a child: one way each."""

    def __init__(self, receive: Connection, send: Connection) -> None:
        self._receive, self._send = receive, send

    def send(self, message: object) -> None:
        self._send.send(message)

    def recv(self) -> Any:
        return self._receive.recv()

    def poll(self, timeout_s: float) -> bool:
        return self._receive.poll(timeout_s)

    def close(self) -> None:
        self._receive.close()
        self._send.close()


def _widen(connection: Connection) -> None:
    """Ask for :data:`PIPE_BYTES` of pipe (Linux); elsewhere, or refused, the pipe stays."""
    setting = getattr(fcntl, "F_SETPIPE_SZ", None)  # Linux only
    if setting is not None:
        with contextlib.suppress(OSError):
            fcntl.fcntl(connection.fileno(), setting, PIPE_BYTES)


KEPT_MEMORY_BYTES = 64 << 20
"""Memory a worker touches once at its start and keeps (:func:`_keep_memory`)."""


def _keep_memory() -> None:
    """Keep the C allocator's memory (:func:`~eyeserver.core.memory.keep_freed_memory`) and
    touch :data:`KEPT_MEMORY_BYTES` of it before the stream.

    A frame set whose tracking window is new (the eye turned or blinked) allocates arrays of
    new sizes: measured in the tracking bench without this, such frames took 1300–2900 page
    faults and 20–50 ms of system time (51–96 ms a frame set against ≈ 20), the frames right
    after a saccade or a blink, when the beam hold matters most.
    """
    keep_freed_memory(KEPT_MEMORY_BYTES)


def _serve(connection: _Channel, calibration: str, rig: RigSpec, model: EyeModel) -> None:
    """The child: load the calibration, then answer frame sets until told to stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # One thread: a frame's arrays are small, and the BLAS's and OpenCV's own threads fight
    # the other workers and the rig for the cores. Measured on 2 cores: two workers with a
    # BLAS thread per core each processed 52 % of 10 s replayed at 25 Hz, 92 % with one each;
    # a lone worker with two threads had its second spin at 98 % of a core in live tracking
    # (52 ms a frame; with one thread, 41 ms). OpenCV's pool is not reached by threadpoolctl.
    threadpool_limits(limits=1, user_api="blas")
    cv2.setNumThreads(1)
    _keep_memory()
    try:
        finder = PoseFinder(RigReconstructor(calibration, rig), fit_eye, model, track=track_eye)
    except ReconstructionError as exc:
        connection.send(("unreconstructable", str(exc)))
        return
    except Exception as exc:
        connection.send(("failed", _failure(exc)))
        return
    connection.send(("ready", None))
    while True:
        try:
            request = connection.recv()
        except (EOFError, OSError):
            return  # the daemon went away
        if request is None:
            _exit_now(connection)
        kind, frame_set, previous = request
        reply: tuple[str, Any]
        if kind == "warm":
            try:
                finder.warm(frame_set, previous)
                reply = ("warmed", None)
            except Exception as exc:
                reply = ("failed", _failure(exc))
            connection.send(reply)
            continue
        try:
            reply = ("pose", finder(frame_set, previous))
        except (PoseError, ValueError) as exc:
            reply = ("lost", str(exc) or type(exc).__name__)
        except ReconstructionError as exc:
            reply = ("unreconstructable", str(exc))
        except Exception as exc:
            reply = ("failed", _failure(exc))
        connection.send(reply)


def _exit_now(connection: _Channel) -> NoReturn:
    """End the child at once, without the interpreter's finalisation: it writes no files, and
    tearing down NumPy, SciPy and OpenCV with the kept memory took 1.4–1.8 s per worker on a
    loaded machine (measured), during which ``POST /tracking/stop`` waited for each worker in
    turn (``PoseWorker.close``, killed only after :data:`_CLOSE_S`: up to 10 s with two)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    connection.close()
    os._exit(0)


def _failure(exc: Exception) -> tuple[str, str]:
    """What the daemon says (the exception) and logs (its traceback in the child)."""
    return f"{type(exc).__name__}: {exc}", traceback.format_exc()


class PoseWorker:
    """:class:`~eyeserver.service.frame_pose.FindPose` in a child process (see the module).

    Parameters
    ----------
    calibration : path
        The calibration directory (the active one).
    rig : RigSpec
        The rig it belongs to.
    model : EyeModel
        The patient's eye model (with the reference's radius held, where there is one).

    Call :meth:`start` before the first frame and :meth:`close` after the last.
    """

    def __init__(self, calibration: str | Path, rig: RigSpec, model: EyeModel) -> None:
        self._args = (str(calibration), rig, model)
        self.frame_timeout_s = FRAME_TIMEOUT_S
        self._connection: _Channel | None = None
        self._process: Any = None

    def start(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Start the child and wait until it has loaded the calibration.

        Raises
        ------
        ReconstructionError
            The calibration cannot reconstruct (no phase-to-height models).
        TrackingWorkerError
            The child did not start in ``timeout_s`` or failed to.
        """
        context = get_context("spawn")
        requests_read, requests_write = context.Pipe(duplex=False)
        replies_read, replies_write = context.Pipe(duplex=False)
        _widen(requests_write)
        ours, theirs = (_Channel(replies_read, requests_write),
                        _Channel(requests_read, replies_write))
        process = context.Process(target=_serve, args=(theirs, *self._args),
                                  name="eyeserver-tracking", daemon=True)
        process.start()
        theirs.close()  # ours alone: the child's death then reads as EOF here
        self._connection, self._process = ours, process
        try:
            kind, detail = self._receive(timeout_s, "to start")
            if kind == "unreconstructable":
                raise ReconstructionError(detail)
            if kind != "ready":
                raise TrackingWorkerError(
                    f"the tracking worker failed to start: {self._failed(detail)}")
        except BaseException:
            self.close()
            raise
        _log.info("tracking worker started", extra={"pid": process.pid})

    def _receive(self, timeout_s: float | None, what: str) -> tuple[str, Any]:
        connection, process = self._connection, self._process
        if connection is None:
            raise TrackingWorkerError("the tracking worker is not running")
        try:
            if timeout_s is not None and not connection.poll(timeout_s):
                raise TrackingWorkerError(
                    f"the tracking worker (pid {process.pid}) took longer than {timeout_s:g} s "
                    f"{what}")
            reply: tuple[str, Any] = connection.recv()
        except (EOFError, OSError):
            process.join(1.0)
            raise TrackingWorkerError(
                f"the tracking worker (pid {process.pid}) ended unexpectedly (exit code "
                f"{process.exitcode})") from None
        return reply

    def __call__(self, frame_set: FrameSet, previous: EyePose | None) -> EyePose:
        """The frame set's pose from the child.

        Raises
        ------
        PoseError
            No eye in the frame (or it was lost).
        ReconstructionError
            The frame set cannot be reconstructed.
        TrackingWorkerError
            The child is gone, failed unexpectedly, or took longer than
            :attr:`frame_timeout_s` (the child is then stopped).
        """
        kind, detail = self._ask("pose", frame_set, previous)
        if kind == "pose":
            pose: EyePose = detail
            return pose
        if kind == "lost":
            raise PoseError(detail)
        if kind == "unreconstructable":
            raise ReconstructionError(detail)
        raise TrackingWorkerError(f"the tracking worker failed on frame "
                                  f"{frame_set.frame}: {self._failed(detail)}")

    def warm(self, frame_set: FrameSet, expected: EyePose) -> None:
        """:meth:`PoseFinder.warm <eyeserver.service.frame_pose.PoseFinder.warm>` in the child.

        Raises
        ------
        TrackingWorkerError
            The child is gone, failed, or took longer than :attr:`frame_timeout_s`.
        """
        kind, detail = self._ask("warm", frame_set, expected)
        if kind != "warmed":
            raise TrackingWorkerError(f"the tracking worker failed to warm up: "
                                      f"{self._failed(detail)}")

    def _ask(self, kind: str, frame_set: FrameSet, pose: EyePose | None) -> tuple[str, Any]:
        """Send the child a frame set with a pose; its answer."""
        if self._connection is None:
            raise TrackingWorkerError("the tracking worker is not running")
        try:
            self._connection.send((kind, frame_set, pose))
        except (OSError, ValueError) as exc:
            raise TrackingWorkerError(f"cannot reach the tracking worker: {exc}") from None
        try:
            return self._receive(self.frame_timeout_s, "to answer")
        except TrackingWorkerError:
            self.close()  # a late answer would be taken for the next frame's
            raise

    @staticmethod
    def _failed(detail: tuple[str, str]) -> str:
        """Log the child's traceback; the one-line reason."""
        reason, trace = detail
        _log.error("tracking worker failed", extra={"reason": reason, "traceback": trace})
        return reason

    def close(self) -> None:
        """Ask the child to end and wait for it (killed after a few seconds). Idempotent."""
        connection, process = self._connection, self._process
        self._connection = None
        if connection is not None:
            with contextlib.suppress(OSError, ValueError):
                connection.send(None)
            connection.close()
        if process is not None:
            process.join(_CLOSE_S)
            if process.is_alive():
                _log.warning("tracking worker did not end; killing it", extra={
                    "pid": process.pid})
                process.kill()
                process.join(_CLOSE_S)
            self._process = None
