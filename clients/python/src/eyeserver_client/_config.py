"""Where the daemon is and how to present oneself: base URL, bearer token, TLS.

Shared by the blocking and the asyncio client (and their streams), so both read the same
environment the same way.
"""

from __future__ import annotations

import os
import ssl
from dataclasses import dataclass
from pathlib import Path

from eyeserver_client.errors import EyeserverError

__all__ = ["API_PREFIX", "DEFAULT_URL", "Connection", "resolve"]

API_PREFIX = "/api/v1"
"""Every route of the API version this client speaks lives under this prefix."""

DEFAULT_URL = "http://127.0.0.1:8000"
"""Where ``eyeserver serve`` listens when nothing is configured."""

URL_VARIABLE = "EYESERVER_URL"
TOKEN_VARIABLE = "EYESERVER_TOKEN"
TOKEN_FILE_VARIABLE = "EYESERVER_TOKEN_FILE"


@dataclass(frozen=True)
class Connection:
    """The resolved settings of one client.

    ``root`` is the daemon's address without the API prefix (``https://room-pc:8443``);
    ``token`` the bearer token or None (then only ``/health`` answers); ``ssl_context`` the TLS
    context for ``https``/``wss``, or None for plain HTTP. ``verify`` is what httpx is given (the
    context, or False when verification was turned off).
    """

    root: str
    token: str | None
    ssl_context: ssl.SSLContext | None
    verify: ssl.SSLContext | bool

    @property
    def api(self) -> str:
        """The API's base URL (``…/api/v1``)."""
        return self.root + API_PREFIX

    @property
    def websocket_root(self) -> str:
        """The API's base URL for WebSockets (``ws://…/api/v1`` or ``wss://…``)."""
        scheme, rest = self.api.split("://", 1)
        return ("wss" if scheme == "https" else "ws") + "://" + rest

    def headers(self) -> dict[str, str]:
        """The request headers that present the token (none without one)."""
        return {} if self.token is None else {"Authorization": f"Bearer {self.token}"}


def resolve(base_url: str | None, token: str | None, token_file: str | os.PathLike[str] | None,
            ca_file: str | os.PathLike[str] | None, verify: bool,
            client_cert: str | os.PathLike[str] | tuple[str | os.PathLike[str],
                                                        str | os.PathLike[str]] | None,
            ) -> Connection:
    """Settle the client's settings from its arguments and the environment.

    The base URL is ``base_url``, else ``$EYESERVER_URL``, else :data:`DEFAULT_URL`; a
    trailing ``/`` or ``/api/v1`` is dropped. The token is, first found: ``token``; the file
    ``token_file``; ``$EYESERVER_TOKEN``; the file named by ``$EYESERVER_TOKEN_FILE`` (a
    file's content with surrounding whitespace removed, so a token written by ``echo`` works).

    TLS: ``ca_file`` is the PEM bundle of the CA that signed the daemon's certificate (a room's
    own CA; without it the system's trust store is used); ``verify=False`` turns verification
    off (never in a treatment room); ``client_cert`` is a PEM file holding certificate and key,
    or a ``(certificate, key)`` pair, for a daemon that asks for client certificates.

    Raises
    ------
    EyeserverError
        A token file that cannot be read or is empty, or a base URL that is not http(s).
    """
    root = (base_url or os.environ.get(URL_VARIABLE) or DEFAULT_URL).rstrip("/")
    root = root.removesuffix(API_PREFIX).rstrip("/")
    if not root.startswith(("http://", "https://")):
        raise EyeserverError(f"the daemon's URL must start with http:// or https://: {root!r}")
    if token is None and token_file is not None:
        token = _read_token(Path(token_file))
    if token is None:
        token = os.environ.get(TOKEN_VARIABLE) or None
    if token is None and os.environ.get(TOKEN_FILE_VARIABLE):
        token = _read_token(Path(os.environ[TOKEN_FILE_VARIABLE]))
    context: ssl.SSLContext | None = None
    if root.startswith("https://"):
        context = ssl.create_default_context(
            cafile=None if ca_file is None else os.fspath(ca_file))
        if not verify:
            context.check_hostname = False
            context.verify_mode = ssl.CERT_NONE
        if client_cert is not None:
            if isinstance(client_cert, tuple):
                context.load_cert_chain(os.fspath(client_cert[0]), os.fspath(client_cert[1]))
            else:
                context.load_cert_chain(os.fspath(client_cert))
    return Connection(root=root, token=token, ssl_context=context,
                      verify=context if context is not None else verify)


def _read_token(path: Path) -> str:
    try:
        token = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise EyeserverError(f"cannot read the token file {path}: {exc.strerror}") from exc
    if not token:
        raise EyeserverError(f"the token file {path} is empty")
    return token
