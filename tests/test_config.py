"""Settings: defaults, TOML file, environment and overrides, in that order of priority."""

from __future__ import annotations

import os
from pathlib import Path

import platformdirs
import pytest

from eyeserver.config import Settings
from eyeserver.errors import ConfigError


@pytest.fixture(autouse=True)
def _clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    # The developer's own EYESERVER_* variables must not leak into these tests.
    for name in list(os.environ):
        if name.upper().startswith("EYESERVER_"):
            monkeypatch.delenv(name)


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def test_defaults_need_no_file() -> None:
    settings = Settings.load()

    assert settings.data_dir == platformdirs.user_data_path("eyeserver", appauthor=False)
    assert settings.host == "127.0.0.1"
    assert settings.port == 8000
    assert settings.room_file is None
    assert settings.log_level == "info"
    assert settings.log_json is True


def test_loading_creates_no_data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data_dir = tmp_path / "not" / "yet"
    monkeypatch.setenv("EYESERVER_DATA_DIR", str(data_dir))

    settings = Settings.load()

    assert settings.data_dir == data_dir
    assert not data_dir.exists()
    assert settings.ensure_data_dir() == data_dir
    assert data_dir.is_dir()
    assert settings.ensure_data_dir() == data_dir  # a second time is fine


def test_ensure_data_dir_reports_a_file_in_the_way(tmp_path: Path) -> None:
    blocker = _write(tmp_path / "blocker", "")
    settings = Settings.load(data_dir=blocker / "data")

    with pytest.raises(ConfigError, match="data_dir"):
        settings.ensure_data_dir()


def test_toml_file_sets_keys(tmp_path: Path) -> None:
    config = _write(
        tmp_path / "eyeserver.toml",
        'host = "0.0.0.0"\nport = 9000\nlog_level = "DEBUG"\nlog_json = false\n'
        f'data_dir = "{tmp_path / "data"}"\n',
    )

    settings = Settings.load(config)

    assert settings.host == "0.0.0.0"
    assert settings.port == 9000
    assert settings.log_level == "debug"
    assert settings.log_json is False
    assert settings.data_dir == tmp_path / "data"


def test_relative_paths_in_the_file_are_relative_to_it(tmp_path: Path) -> None:
    config = _write(tmp_path / "eyeserver.toml", 'room_file = "rooms/lab.toml"\ndata_dir = "d"\n')

    settings = Settings.load(config)

    assert settings.room_file == tmp_path / "rooms" / "lab.toml"
    assert settings.data_dir == tmp_path / "d"


def test_environment_beats_toml(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = _write(tmp_path / "eyeserver.toml", 'port = 9000\nhost = "0.0.0.0"\n')
    monkeypatch.setenv("EYESERVER_PORT", "9100")
    monkeypatch.setenv("EYESERVER_DATA_DIR", str(tmp_path / "from-env"))

    settings = Settings.load(config)

    assert settings.port == 9100
    assert settings.data_dir == tmp_path / "from-env"
    assert settings.host == "0.0.0.0"  # not overridden: still the file's


def test_overrides_beat_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = _write(tmp_path / "eyeserver.toml", "port = 9000\n")
    monkeypatch.setenv("EYESERVER_PORT", "9100")
    monkeypatch.setenv("EYESERVER_HOST", "10.0.0.1")

    settings = Settings.load(config, port=9200, host=None)

    assert settings.port == 9200
    assert settings.host == "10.0.0.1"  # a None override means "flag not given"


def test_unknown_environment_variables_are_ignored(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EYESERVER_SOMETHING_ELSE", "x")
    monkeypatch.setenv("EYESERVER_ROOM_FILE", "")

    settings = Settings.load()

    assert settings.room_file is None


def test_bad_toml_names_the_file(tmp_path: Path) -> None:
    config = _write(tmp_path / "broken.toml", "port = \n")

    with pytest.raises(ConfigError, match=r"broken\.toml.*not valid TOML"):
        Settings.load(config)


def test_missing_file_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"absent\.toml.*not found"):
        Settings.load(tmp_path / "absent.toml")


def test_bad_value_names_the_file_and_the_key(tmp_path: Path) -> None:
    config = _write(tmp_path / "eyeserver.toml", 'port = "eighty"\n')

    with pytest.raises(ConfigError) as caught:
        Settings.load(config)

    message = str(caught.value)
    assert str(config) in message
    assert "'port'" in message
    assert "eighty" in message


def test_unknown_key_in_the_file_names_the_file_and_the_key(tmp_path: Path) -> None:
    config = _write(tmp_path / "eyeserver.toml", "prot = 9000\n")

    with pytest.raises(ConfigError, match=r"eyeserver\.toml: key 'prot': unknown key"):
        Settings.load(config)


def test_bad_environment_value_names_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EYESERVER_PORT", "70000")

    with pytest.raises(ConfigError, match="environment variable EYESERVER_PORT"):
        Settings.load()


def test_bad_log_level_is_rejected() -> None:
    with pytest.raises(ConfigError, match="override 'log_level'"):
        Settings.load(log_level="chatty")


def test_unknown_override_is_rejected() -> None:
    with pytest.raises(ConfigError, match="override 'prot': unknown key"):
        Settings.load(prot=1)
