"""HTTPS for ``eyeserver serve``: the TLS settings checked and turned into uvicorn's options.

Without ``tls_certfile`` the API is plain HTTP, which is only fit for loopback (the default
``127.0.0.1``). With it, uvicorn serves HTTPS with the certificate and ``tls_keyfile``; with
``tls_ca_certs`` and ``tls_client_cert = "required"`` every client must also present a
certificate signed by that CA (mutual TLS) before it reaches the bearer-token check, which
still applies.

The files are loaded here once, before uvicorn starts, so that a missing, unreadable or
mismatched file is a one-line :class:`~eyeserver.errors.ConfigError` naming the setting instead
of a traceback from inside the server.
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Any

from eyeserver.config import ClientCertMode, Settings
from eyeserver.errors import ConfigError

__all__ = ["CLIENT_CERT_REQUIREMENTS", "uvicorn_ssl_options"]

CLIENT_CERT_REQUIREMENTS: dict[ClientCertMode, ssl.VerifyMode] = {
    "none": ssl.CERT_NONE,
    "optional": ssl.CERT_OPTIONAL,
    "required": ssl.CERT_REQUIRED,
}
"""``tls_client_cert`` as the :mod:`ssl` verify mode uvicorn's ``ssl_cert_reqs`` takes."""


def _readable(key: str, path: Path) -> str:
    try:
        with path.open("rb") as stream:
            stream.read(1)
    except FileNotFoundError:
        raise ConfigError(f"{key} {path}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{key} {path}: is a directory, not a PEM file") from None
    except OSError as exc:
        raise ConfigError(f"{key} {path}: cannot read: {exc.strerror or exc}") from exc
    return str(path)


def uvicorn_ssl_options(settings: Settings) -> dict[str, Any]:
    """The ``ssl_*`` keyword arguments of :func:`uvicorn.run` for ``settings``.

    Returns an empty dict when TLS is not configured (plain HTTP).

    Raises
    ------
    ConfigError
        A certificate without a key (or the reverse), a CA or client-certificate mode without a
        certificate, client certificates asked for without ``tls_ca_certs``, or a file that is
        missing, unreadable or not a matching PEM certificate and key; the message names the
        setting.
    """
    certfile, keyfile, ca_certs = settings.tls_certfile, settings.tls_keyfile, settings.tls_ca_certs
    mode = settings.tls_client_cert
    if certfile is None:
        if keyfile is not None:
            raise ConfigError("tls_keyfile is set but tls_certfile is not: give both for HTTPS")
        if ca_certs is not None or mode != "none":
            raise ConfigError("tls_ca_certs and tls_client_cert need HTTPS: set tls_certfile "
                              "and tls_keyfile too")
        return {}
    if keyfile is None:
        raise ConfigError("tls_certfile is set but tls_keyfile is not: give the certificate's "
                          "private key too")
    if mode != "none" and ca_certs is None:
        raise ConfigError(f"tls_client_cert = {mode!r} needs tls_ca_certs: the CA that signs "
                          "the client certificates")
    cert_path = _readable("tls_certfile", certfile)
    key_path = _readable("tls_keyfile", keyfile)
    # A trial context: uvicorn would load the same files, but fail with a traceback.
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        context.load_cert_chain(cert_path, key_path)
    except ssl.SSLError as exc:
        raise ConfigError(f"tls_certfile {certfile} / tls_keyfile {keyfile}: not a PEM "
                          f"certificate and its matching private key ({exc.reason or exc})"
                          ) from exc
    options: dict[str, Any] = {"ssl_certfile": cert_path, "ssl_keyfile": key_path,
                               "ssl_cert_reqs": CLIENT_CERT_REQUIREMENTS[mode]}
    if ca_certs is not None:
        ca_path = _readable("tls_ca_certs", ca_certs)
        try:
            context.load_verify_locations(cafile=ca_path)
        except ssl.SSLError as exc:
            raise ConfigError(f"tls_ca_certs {ca_certs}: not a PEM CA certificate "
                              f"({exc.reason or exc})") from exc
        options["ssl_ca_certs"] = ca_path
    return options
