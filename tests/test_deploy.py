"""deploy/: the example configuration loads and documents every key, the unit asks for what
the daemon provides, and install.sh is valid bash (it is never run here)."""

from __future__ import annotations

import configparser
import importlib.metadata
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from eyeserver.config import Settings

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


def test_the_example_configuration_loads_and_names_every_key() -> None:
    Settings.load(DEPLOY / "eyeserver.toml")
    text = (DEPLOY / "eyeserver.toml").read_text()
    undocumented = [key for key in Settings.model_fields if key not in text]
    assert undocumented == []


def test_the_unit_is_a_notify_service_with_a_watchdog_user_and_state_directory() -> None:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]  # keys are case-sensitive
    unit.read(DEPLOY / "eyeserver.service")
    service = unit["Service"]
    assert service["Type"] == "notify"
    assert int(service["WatchdogSec"]) > 0
    assert service["User"] == "eyeserver"
    assert service["StateDirectory"] == "eyeserver"
    assert service["Environment"] == "EYESERVER_DATA_DIR=/var/lib/eyeserver"
    assert service["EnvironmentFile"].endswith("/etc/eyeserver/eyeserver.env")
    assert service["ExecStart"].split()[1:3] == ["serve", "--config"]
    assert service["NoNewPrivileges"] == "yes" and service["ProtectSystem"] == "strict"


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_install_script_is_valid_bash() -> None:
    subprocess.run(["bash", "-n", str(DEPLOY / "install.sh")], check=True)


def test_every_runtime_dependency_is_pinned_and_has_a_purpose() -> None:
    # The SOUP list (docs/soup.md) and the installer's pins come from one script.
    subprocess.run([sys.executable, str(DEPLOY.parent / "scripts" / "soup.py"), "--check"],
                   check=True)
    pinned = {line.split("==")[0] for line in (DEPLOY / "constraints.txt").read_text()
              .splitlines() if "==" in line}
    soup = (DEPLOY.parent / "docs" / "soup.md").read_text()
    for requirement in importlib.metadata.requires("eyeserver") or []:
        if "extra ==" in requirement:
            continue
        name = re.split(r"[ <>=!~;\[]", requirement, maxsplit=1)[0].lower()
        assert name in pinned, name
        assert f"| {name} |" in soup, name
