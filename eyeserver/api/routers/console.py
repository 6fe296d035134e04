"""``/console/``: the browser console, served by the daemon from its package data.

A treatment room has no internet, so everything the console needs ships in the package
(``eyeserver/api/console/``: HTML, hand-written CSS, plain ES modules; no CDN, no build step).
The files hold no data and need no token; the console asks for one and sends it with every API
request, keeping it in the tab's ``sessionStorage`` only (never ``localStorage`` or a cookie:
closing the tab forgets it, and no request carries it unasked, so there is nothing for a
cross-site request to ride on).

Every file is sent with a Content-Security-Policy that lets the page load only its own files
and talk only to its own daemon (no inline script, no other origin, no framing), so a string
from the API that slipped into the page as markup could neither run nor send the token away.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from starlette.datastructures import MutableHeaders
from starlette.responses import RedirectResponse
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["CONSOLE_DIR", "CONSOLE_PATH", "CONTENT_SECURITY_POLICY", "mount"]

CONSOLE_PATH = "/console"
"""Where the console is served (its page is ``/console/``)."""

CONSOLE_DIR = Path(__file__).resolve().parents[1] / "console"
"""The console's files (package data of ``eyeserver.api``)."""

CONTENT_SECURITY_POLICY = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
    # 'self' covers the daemon's own ws:// and wss:// (CSP level 3), the streams' origin.
    "connect-src 'self'; font-src 'self'; base-uri 'none'; form-action 'self'; "
    "frame-ancestors 'none'")
"""Sent with every file of the console: its own files only, its own daemon only."""

_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    # Revalidated on every load: after an upgrade of the daemon the console is its own version.
    "Cache-Control": "no-cache",
}


class _Secured:
    """An ASGI app that adds the console's security headers to ``app``'s answers."""

    def __init__(self, app: ASGIApp) -> None:
        self._app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in _HEADERS.items():
                    headers[name] = value
            await send(message)

        await self._app(scope, receive, send_with_headers)


def mount(app: FastAPI, directory: Path = CONSOLE_DIR) -> None:
    """Serve the console's files from ``directory`` at ``/console/`` (``index.html`` for the
    directory itself; ``/console`` and the daemon's root ``/`` are redirected there).

    Raises
    ------
    RuntimeError
        ``directory`` does not exist (the package was installed without its data).
    """
    files = StaticFiles(directory=directory, html=True, follow_symlink=False)
    app.mount(CONSOLE_PATH, _Secured(files), name="console")

    async def home() -> RedirectResponse:
        # The daemon's address alone, as people type it into a browser, opens the console.
        return RedirectResponse(f"{CONSOLE_PATH}/", status_code=307)

    app.add_api_route("/", home, include_in_schema=False)
