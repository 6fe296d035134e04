"""Latency through the daemon's API, for ``eyeserver bench speed``.

A real ``eyeserver serve`` process on loopback (:class:`~eyeserver.bench.daemon.DaemonProcess`)
with a calibration imported and activated over HTTP, as the oncology information system would
use it. Timed from the client, request sent → answer received:

* a capture (``POST /captures`` → 201, i.e. the bundle durable on disk) of each unit and of all
  units interleaved; on the simulated room this includes rendering the cameras' images;
* a reconstruction (``POST /captures/{id}/reconstruction`` → 200: reading the bundle, the
  pipeline, writing ``cloud.ply``) of a one-unit and an all-unit capture.

The first capture of a room renders its geometry caches and is left out (a warm-up).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import httpx

from eyeserver.bench.daemon import API, DaemonProcess, checked, zip_directory

__all__ = ["api_latency"]


def _timed(call: Callable[[], httpx.Response], what: str) -> tuple[float, dict[str, Any]]:
    started = time.perf_counter()
    response = call()
    elapsed = time.perf_counter() - started
    return elapsed, checked(response, what)


def api_latency(calibration: Path, work: Path, requests: int = 10,
                room_file: Path | None = None,
                progress: Callable[[str], None] = lambda _: None) -> dict[str, Any]:
    """Capture and reconstruction latencies through HTTP, in seconds per request.

    Returns ``{"captures": {unit: [s, ...]}, "reconstructions": {unit: [s, ...]}}``, each list
    ``requests`` long. ``work`` receives the daemon's data directory and log.

    Raises
    ------
    DaemonError
        The daemon did not start, or a request failed (the message has the answer).
    """
    env = {} if room_file is None else {"EYESERVER_ROOM_FILE": str(room_file)}
    with DaemonProcess(work / "daemon-data", log=work / "daemon.log", env=env) as daemon:
        client = daemon.client
        progress("API latency: importing the calibration into a daemon on loopback")
        imported = checked(client.post(f"{API}/calibrations", content=zip_directory(
            calibration), headers={"content-type": "application/zip"}), "calibration import")
        checked(client.post(f"{API}/calibrations/{imported['id']}/activate"), "activation")
        units = [u["id"] for u in checked(client.get(f"{API}/status"), "status")["units"]]
        checked(client.post(f"{API}/captures", json={"unit": "all"}), "warm-up capture")
        captures: dict[str, list[float]] = {}
        last: dict[str, str] = {}
        for unit in [*units, "all"]:
            progress(f"API latency: {requests} captures of {unit}")
            captures[unit] = []
            for _ in range(requests):
                elapsed, body = _timed(partial(client.post, f"{API}/captures",
                                               json={"unit": unit}), f"capture of {unit}")
                captures[unit].append(elapsed)
                last[unit] = body["id"]
        reconstructions: dict[str, list[float]] = {}
        for unit in (units[0], "all"):
            progress(f"API latency: {requests} reconstructions of a capture of {unit}")
            url = f"{API}/captures/{last[unit]}/reconstruction"
            reconstructions[unit] = [
                _timed(partial(client.post, url), f"reconstruction of {unit}")[0]
                for _ in range(requests)]
    return {"captures": captures, "reconstructions": reconstructions}
