"""Bearer tokens and roles: 401 without a valid token, 403 below the route's role."""

from __future__ import annotations

import os
import stat
import tomllib
from pathlib import Path

import pytest

from eyeserver.api.auth import GENERATED_TOKENS_FILE, TokenTable
from eyeserver.config import Settings
from eyeserver.errors import ConfigError
from tests.apiclient import (
    API,
    OPERATOR_TOKEN,
    PHYSICIST_TOKEN,
    Client,
    auth,
)


@pytest.fixture
def clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.upper().startswith("EYESERVER_"):
            monkeypatch.delenv(name)


def test_health_needs_no_token(client: Client) -> None:
    response = client.get(f"{API}/health", headers={"Authorization": ""})
    assert response.status_code == 200


@pytest.mark.parametrize("headers", [
    {"Authorization": ""},
    auth("not-a-token-of-this-daemon"),
    {"Authorization": f"Basic {OPERATOR_TOKEN}"},
    {"Authorization": OPERATOR_TOKEN},
], ids=["none", "unknown", "basic-scheme", "no-scheme"])
def test_every_other_route_answers_401_without_a_valid_token(client: Client,
                                                             headers: dict[str, str]) -> None:
    for method, path in [("GET", "/status"), ("GET", "/devices"), ("GET", "/captures"),
                         ("POST", "/captures"), ("GET", "/calibrations")]:
        response = client.request(method, f"{API}{path}", headers=headers, json={"unit": "all"})
        assert response.status_code == 401, (path, response.text)
        assert response.headers["www-authenticate"] == "Bearer"
        assert "token" in response.json()["detail"]


def test_an_operator_reads_but_may_not_calibrate(client: Client) -> None:
    operator = auth(OPERATOR_TOKEN)
    assert client.get(f"{API}/status", headers=operator).status_code == 200
    assert client.get(f"{API}/calibrations", headers=operator).status_code == 200
    response = client.post(f"{API}/calibrations/cal-20260101T000000000Z-0000/activate",
                           headers=operator)
    assert response.status_code == 403
    assert response.json()["detail"] == ("operator (operator) may not do this: it needs the "
                                         "physicist role")
    response = client.post(f"{API}/calibrations", headers={**operator,
                                                           "content-type": "application/zip"},
                           content=b"PK")
    assert response.status_code == 403


def test_a_physicist_passes_where_an_operator_is_refused(client: Client) -> None:
    # Past authorisation, the unknown id is what fails.
    response = client.post(f"{API}/calibrations/cal-20260101T000000000Z-0000/activate",
                           headers=auth(PHYSICIST_TOKEN))
    assert response.status_code == 404


def test_the_openapi_document_declares_bearer_authentication(client: Client) -> None:
    document = client.get(f"{API}/openapi.json").json()
    schemes = document["components"]["securitySchemes"]
    assert schemes["HTTPBearer"]["scheme"] == "bearer"
    assert "security" not in document["paths"][f"{API}/health"]["get"]
    assert "401" in document["paths"][f"{API}/status"]["get"]["responses"]


def test_tokens_from_the_file_carry_their_holders_names(tmp_path: Path,
                                                        clean_environment: None) -> None:
    config = tmp_path / "eyeserver.toml"
    config.write_text('[[tokens]]\nname = "dr-weber"\nrole = "physicist"\n'
                      'token = "a-long-enough-secret-1"\n\n'
                      '[[tokens]]\nname = "rtt-room-2"\nrole = "operator"\n'
                      'token = "a-long-enough-secret-2"\n')
    table = TokenTable.for_settings(Settings.load(config, data_dir=tmp_path / "data"))
    weber = table.caller("a-long-enough-secret-1")
    assert weber is not None and (weber.name, weber.role) == ("dr-weber", "physicist")
    room = table.caller("a-long-enough-secret-2")
    assert room is not None and room.may("operator") and not room.may("physicist")
    assert table.caller("a-long-enough-secret-") is None
    assert table.caller(None) is None
    assert not (tmp_path / "data" / GENERATED_TOKENS_FILE).exists()


@pytest.mark.parametrize(("value", "reason"), [
    ("operator:short", "at least 16 characters"),
    ("nurse:abcdefghijklmnopqrst", "'operator' or 'physicist'"),
    ("abcdefghijklmnopqrst", "role:token pairs"),
    ("operator:abcdefghijklmnopqrst,physicist:abcdefghijklmnopqrst", "given twice"),
])
def test_bad_token_variables_are_refused_without_echoing_the_secret(
        value: str, reason: str, monkeypatch: pytest.MonkeyPatch,
        clean_environment: None) -> None:
    monkeypatch.setenv("EYESERVER_TOKENS", value)
    with pytest.raises(ConfigError, match="EYESERVER_TOKENS") as raised:
        Settings.load()
    assert reason in str(raised.value)
    assert "klmnopq" not in str(raised.value)


def test_without_tokens_the_daemon_generates_private_ones_once(tmp_path: Path,
                                                               clean_environment: None) -> None:
    settings = Settings.load(data_dir=tmp_path / "data")
    first = TokenTable.for_settings(settings)
    path = tmp_path / "data" / GENERATED_TOKENS_FILE
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    tokens = {t["role"]: t["token"] for t in tomllib.loads(path.read_text())["tokens"]}
    assert sorted(tokens) == ["operator", "physicist"]
    assert len(set(tokens.values())) == 2 and all(len(t) >= 30 for t in tokens.values())
    again = TokenTable.for_settings(settings)  # the same file, not new tokens
    for role, token in tokens.items():
        for table in (first, again):
            caller = table.caller(token)
            assert caller is not None and caller.role == role


def test_a_broken_generated_tokens_file_is_a_clear_error(tmp_path: Path,
                                                         clean_environment: None) -> None:
    (tmp_path / GENERATED_TOKENS_FILE).write_text("[[tokens]]\nname = 1\n")
    with pytest.raises(ConfigError, match=GENERATED_TOKENS_FILE):
        TokenTable.for_settings(Settings.load(data_dir=tmp_path))
