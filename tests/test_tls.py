"""HTTPS for ``eyeserver serve``: the settings' checks, and a real daemon on loopback with a CA,
a server certificate and a client certificate made here by the ``openssl`` command line."""

from __future__ import annotations

import shutil
import ssl
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from eyeserver.bench.daemon import DaemonProcess
from eyeserver.config import Settings
from eyeserver.errors import ConfigError
from eyeserver.tls import uvicorn_ssl_options

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")


@dataclass(frozen=True)
class Pki:
    ca: Path
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path
    stranger_cert: Path  # signed by a CA the daemon does not trust
    stranger_key: Path


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _ca(directory: Path, name: str) -> tuple[Path, Path]:
    key, cert = directory / f"{name}.key", directory / f"{name}.pem"
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
             "-nodes", "-keyout", key.name, "-out", cert.name, "-days", "2",
             "-subj", f"/CN={name}", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=directory)
    return cert, key


def _signed(directory: Path, name: str, ca: tuple[Path, Path], extensions: str
            ) -> tuple[Path, Path]:
    key, csr, cert = (directory / f"{name}.key", directory / f"{name}.csr",
                      directory / f"{name}.pem")
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", key.name, "-out", csr.name, "-subj", f"/CN={name}", cwd=directory)
    (directory / f"{name}.ext").write_text(extensions)
    _openssl("x509", "-req", "-in", csr.name, "-CA", ca[0].name, "-CAkey", ca[1].name,
             "-CAcreateserial", "-out", cert.name, "-days", "2", "-extfile", f"{name}.ext",
             cwd=directory)
    return cert, key


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    directory = tmp_path_factory.mktemp("pki")
    ca = _ca(directory, "room-ca")
    server = _signed(directory, "server", ca, "subjectAltName=IP:127.0.0.1,DNS:localhost\n"
                     "extendedKeyUsage=serverAuth\n")
    client = _signed(directory, "console", ca, "extendedKeyUsage=clientAuth\n")
    other_ca = _ca(directory, "other-ca")
    stranger = _signed(directory, "stranger", other_ca, "extendedKeyUsage=clientAuth\n")
    return Pki(ca[0], *server, *client, *stranger)


def _settings(**values: object) -> Settings:
    return Settings.load(**values)


# --- the settings' checks -------------------------------------------------------------------


def test_no_tls_settings_mean_plain_http() -> None:
    assert uvicorn_ssl_options(_settings()) == {}


def test_certificate_and_key_become_uvicorn_options(pki: Pki) -> None:
    options = uvicorn_ssl_options(_settings(tls_certfile=pki.server_cert,
                                            tls_keyfile=pki.server_key, tls_ca_certs=pki.ca,
                                            tls_client_cert="required"))
    assert options == {"ssl_certfile": str(pki.server_cert), "ssl_keyfile": str(pki.server_key),
                       "ssl_ca_certs": str(pki.ca), "ssl_cert_reqs": ssl.CERT_REQUIRED}


@pytest.mark.parametrize(("values", "named"), [
    ({"tls_certfile": "server.pem"}, "tls_keyfile"),
    ({"tls_keyfile": "server.key"}, "tls_certfile"),
    ({"tls_client_cert": "required"}, "tls_certfile"),
])
def test_incomplete_settings_name_the_missing_key(pki: Pki, values: dict[str, str],
                                                  named: str) -> None:
    paths = {k: pki.server_cert.parent / v if k.endswith("file") else v
             for k, v in values.items()}
    with pytest.raises(ConfigError, match=named):
        uvicorn_ssl_options(_settings(**paths))


def test_client_certificates_need_a_ca(pki: Pki) -> None:
    with pytest.raises(ConfigError, match="tls_ca_certs"):
        uvicorn_ssl_options(_settings(tls_certfile=pki.server_cert, tls_keyfile=pki.server_key,
                                      tls_client_cert="optional"))


def test_missing_unreadable_and_mismatched_files_name_the_key(pki: Pki, tmp_path: Path
                                                              ) -> None:
    with pytest.raises(ConfigError, match=r"tls_keyfile .*nope\.key: file not found"):
        uvicorn_ssl_options(_settings(tls_certfile=pki.server_cert,
                                      tls_keyfile=tmp_path / "nope.key"))
    with pytest.raises(ConfigError, match=r"tls_ca_certs .*is a directory"):
        uvicorn_ssl_options(_settings(tls_certfile=pki.server_cert, tls_keyfile=pki.server_key,
                                      tls_ca_certs=tmp_path))
    # The client's key does not belong to the server's certificate.
    with pytest.raises(ConfigError, match=r"tls_certfile .* tls_keyfile"):
        uvicorn_ssl_options(_settings(tls_certfile=pki.server_cert,
                                      tls_keyfile=pki.client_key))
    garbage = tmp_path / "ca.pem"
    garbage.write_text("not a certificate\n")
    with pytest.raises(ConfigError, match="tls_ca_certs"):
        uvicorn_ssl_options(_settings(tls_certfile=pki.server_cert, tls_keyfile=pki.server_key,
                                      tls_ca_certs=garbage))


def test_serve_refuses_to_start_with_a_bad_tls_setting(tmp_path: Path) -> None:
    from eyeserver.cli import main

    config = tmp_path / "eyeserver.toml"
    config.write_text(f'data_dir = "{tmp_path / "data"}"\ntls_certfile = "missing.pem"\n'
                      'tls_keyfile = "missing.key"\n')
    assert main(["serve", "--config", str(config)]) == 2


# --- a real daemon over HTTPS ---------------------------------------------------------------


def _client_context(pki: Pki, cert: tuple[Path, Path] | None = None) -> ssl.SSLContext:
    context = ssl.create_default_context(cafile=str(pki.ca))
    if cert is not None:
        context.load_cert_chain(str(cert[0]), str(cert[1]))
    return context


def _tls_env(pki: Pki, client_cert: str = "none") -> dict[str, str]:
    return {"EYESERVER_TLS_CERTFILE": str(pki.server_cert),
            "EYESERVER_TLS_KEYFILE": str(pki.server_key),
            "EYESERVER_TLS_CA_CERTS": str(pki.ca),
            "EYESERVER_TLS_CLIENT_CERT": client_cert}


@pytest.fixture
def https_daemon(pki: Pki, tmp_path: Path) -> Iterator[DaemonProcess]:
    with DaemonProcess(tmp_path / "data", log=tmp_path / "serve.log", env=_tls_env(pki),
                       tls=_client_context(pki)) as daemon:
        yield daemon


@pytest.mark.slow
def test_https_with_the_room_ca_works_and_plain_http_does_not(https_daemon: DaemonProcess,
                                                              pki: Pki) -> None:
    assert https_daemon.url.startswith("https://127.0.0.1:")
    response = https_daemon.client.get("/api/v1/status")
    assert response.status_code == 200, response.text

    plain = https_daemon.url.replace("https://", "http://")
    with pytest.raises(httpx.TransportError):
        httpx.get(f"{plain}/api/v1/health", timeout=5.0)
    # Nor does HTTPS without trusting the room's CA.
    with pytest.raises(httpx.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
        httpx.get(f"{https_daemon.url}/api/v1/health", timeout=5.0)


@pytest.mark.slow
def test_required_client_certificates_refuse_clients_without_one(pki: Pki,
                                                                 tmp_path: Path) -> None:
    console = (pki.client_cert, pki.client_key)
    with DaemonProcess(tmp_path / "data", log=tmp_path / "serve.log",
                       env=_tls_env(pki, "required"),
                       tls=_client_context(pki, console)) as daemon:
        token = {"Authorization": f"Bearer {daemon.operator_token}"}
        passed = httpx.get(f"{daemon.url}/api/v1/status", headers=token, timeout=5.0,
                           verify=_client_context(pki, console))
        assert passed.status_code == 200, passed.text

        for refused in (_client_context(pki),
                        _client_context(pki, (pki.stranger_cert, pki.stranger_key))):
            # TLS 1.3 reports the refusal after the handshake: on the first read.
            with pytest.raises(httpx.TransportError):
                httpx.get(f"{daemon.url}/api/v1/health", timeout=5.0, verify=refused)
