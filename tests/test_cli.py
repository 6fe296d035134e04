"""The command line's contract: version, usage errors, error reporting and exit statuses."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

import eyeserver
from eyeserver import cli
from eyeserver.errors import ConfigError


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"eyeserver {eyeserver.__version__}"


def test_no_command_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main([]) == 2
    assert "usage: eyeserver" in capsys.readouterr().err


def test_bad_port_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["serve", "--port", "70000"]) == 2
    assert "between 1 and 65535" in capsys.readouterr().err


def test_eyeserver_error_is_one_line_and_status_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "missing.toml"

    assert cli.main(["serve", "--config", str(missing)]) == 2

    err = capsys.readouterr().err
    assert err.startswith("eyeserver: error: ")
    assert str(missing) in err
    assert "Traceback" not in err


def _add_failing_commands(subparsers: cli.Subparsers) -> None:
    def raise_config_error(args: argparse.Namespace) -> int:
        raise ConfigError("room file is broken")

    def interrupt(args: argparse.Namespace) -> int:
        raise KeyboardInterrupt

    subparsers.add_parser("fail").set_defaults(handler=raise_config_error)
    subparsers.add_parser("interrupt").set_defaults(handler=interrupt)


def test_registrars_add_commands(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cli, "REGISTRARS", [*cli.REGISTRARS, _add_failing_commands])

    assert cli.main(["fail"]) == 2
    assert capsys.readouterr().err == "eyeserver: error: room file is broken\n"
    assert cli.main(["interrupt"]) == 130


def test_python_dash_m_runs_the_cli() -> None:
    environment = {**os.environ, "PYTHONWARNINGS": "error"}
    result = subprocess.run(
        [sys.executable, "-m", "eyeserver", "--version"],
        capture_output=True,
        text=True,
        env=environment,
        timeout=60,
        check=False,
    )

    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"eyeserver {eyeserver.__version__}"
