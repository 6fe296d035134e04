"""Running an app behind a real uvicorn server on loopback, for tests that need real sockets.

:func:`live_server` serves the app (with its lifespan) on a free port of 127.0.0.1 from a thread
and yields its base URL; WebSocket clients, flow control and disconnects then behave as they do
in production, which the in-process client of :mod:`tests.apiclient` cannot show.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import uvicorn
from fastapi import FastAPI

from eyeserver.api.wsprotocol import UVICORN_OPTIONS

__all__ = ["live_server"]


@contextmanager
def live_server(app: FastAPI, *, start_timeout_s: float = 60.0,
                stop_timeout_s: float = 30.0) -> Iterator[str]:
    """Serve ``app`` on ``http://127.0.0.1:<free port>`` for the duration of the block.

    Yields the base URL (no trailing slash). Waits until uvicorn has run the lifespan's start-up
    and is listening; on leaving, asks it to exit and joins its thread (the lifespan's shut-down
    has then run).

    Raises
    ------
    RuntimeError
        The server did not start (its thread ended, e.g. the lifespan failed) or did not stop
        in time.
    """
    # The listening socket is made here and handed over, so no other process can take the port
    # between finding it free and binding it.
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None, lifespan="on",
                            **UVICORN_OPTIONS)
    server = uvicorn.Server(config)
    # uvicorn installs signal handlers only on the main thread, so this thread leaves them alone.
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]},
                              name=f"uvicorn-{port}", daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + start_timeout_s
        while not server.started:
            if not thread.is_alive():
                raise RuntimeError("the live server stopped while starting (see the log)")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the live server did not start in {start_timeout_s} s")
            time.sleep(0.02)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(stop_timeout_s)
        listener.close()
        if thread.is_alive():
            raise RuntimeError(f"the live server did not stop in {stop_timeout_s} s")
