"""The SOUP list (software of unknown provenance, IEC 62304): every package the daemon runs with,
its version as installed in this environment and why it is there; and the pins for deploy/.

    .venv/bin/python scripts/soup.py              # docs/soup.md and deploy/constraints.txt
    .venv/bin/python scripts/soup.py --check      # exit 1 if a direct dependency lacks a purpose

Run it in the environment the release was tested in (``bash scripts/test.sh`` passed there):
the pins are what was tested, and deploy/install.sh installs exactly those.
"""

from __future__ import annotations

import argparse
import importlib.metadata as metadata
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PURPOSE = {
    "numpy": "arrays: images, point clouds, every computation of the pipeline",
    "scipy": "optimisation (eye fit, calibration), k-d trees, special functions",
    "opencv-contrib-python-headless": "camera calibration, chessboard detection, image "
                                      "filtering and remapping",
    "fastapi": "the REST API and its OpenAPI document",
    "uvicorn": "the HTTP and WebSocket server",
    "httptools": "uvicorn's compiled HTTP/1.1 parser (fast status reads under load)",
    "websockets": "the WebSocket protocol of /ws/events and /ws/pose (server and clients)",
    "httpx": "HTTP client of the command line, the benches and the Python client",
    "pydantic": "validation of every request body, settings and file format",
    "pydantic-settings": "configuration from the TOML file and the environment",
    "pyserial": "the projectors' and trigger's serial controllers (real hardware)",
    "pydicom": "DICOM: pose measurements out as Spatial Registration and Surface "
               "Segmentation; the plan's RT Structure Set and Spatial Registration in",
    "pymodbus": "Modbus RTU/TCP client of the Opto Engineering-style LED strobe controller "
                "(real hardware)",
    "platformdirs": "the user's data directory when none is configured",
    "scikit-image": "quality-guided phase unwrapping (robust fringe-order path)",
    "matplotlib": "the benches' figures (PNG)",
    "prometheus-client": "GET /metrics in the Prometheus text format",
    "threadpoolctl": "one BLAS thread per live-tracking worker process",
    "pygobject": "the GenICam camera driver's way to Aravis (Debian's gir1.2-aravis-0.8); "
                 "the genicam extra",
    "pypylon": "the Basler camera driver: pylon's runtime (the basler extra)",
}
"""Why each direct runtime dependency (pyproject.toml's ``dependencies``, and those of the
:data:`RUNTIME_EXTRAS`) is there."""

RUNTIME_EXTRAS = ("basler", "genicam")
"""The extras a room PC installs with the daemon (deploy/install.sh): real devices' drivers."""


def _name(requirement: str) -> str:
    return re.split(r"[ <>=!~;\[]", requirement, maxsplit=1)[0].strip().lower()


def _closure(direct: list[str]) -> dict[str, set[str]]:
    """Every runtime package reachable from ``direct`` → the direct ones that need it."""
    needed_by: dict[str, set[str]] = {}
    for root in direct:
        stack = [root]
        seen: set[str] = set()
        while stack:
            name = stack.pop()
            if name in seen:
                continue
            seen.add(name)
            needed_by.setdefault(name, set()).add(root)
            for requirement in metadata.requires(name) or []:
                if "extra ==" in requirement:
                    continue
                marker = requirement.split(";", 1)[1] if ";" in requirement else ""
                if marker and "sys_platform" in marker and "linux" not in marker:
                    continue
                child = _name(requirement)
                try:
                    metadata.version(child)
                except metadata.PackageNotFoundError:
                    continue  # an optional or other-platform requirement, not installed
                stack.append(child)
    return needed_by


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args()
    direct = [_name(r) for r in metadata.requires("eyeserver") or []
              if "extra ==" not in r
              or any(f'extra == "{extra}"' in r for extra in RUNTIME_EXTRAS)]
    missing = [name for name in direct if name not in PURPOSE]
    if missing:
        print(f"soup: no purpose written for {', '.join(missing)} (scripts/soup.py PURPOSE)",
              file=sys.stderr)
        return 1
    if args.check:
        return 0
    needed_by = _closure(direct)
    python = ".".join(str(v) for v in sys.version_info[:3])
    rows = ["| package | version | why |", "|---|---|---|", f"| CPython | {python} | the "
            "interpreter |"]
    pins = []
    for name in sorted(needed_by, key=lambda n: (n not in PURPOSE, n)):
        version = metadata.version(name)
        why = PURPOSE.get(name) or "needed by " + ", ".join(sorted(needed_by[name] - {name}))
        rows.append(f"| {name} | {version} | {why} |")
        pins.append(f"{name}=={version}")
    (ROOT / "docs" / "soup.md").write_text(
        "# SOUP: the software the daemon runs with\n\n"
        "Generated by `scripts/soup.py` in the environment the release was tested in; "
        "`deploy/constraints.txt` pins the same versions and `deploy/install.sh` installs "
        "them. Direct dependencies first, with their purpose; then what they need.\n\n"
        + "\n".join(rows) + "\n", encoding="utf-8")
    (ROOT / "deploy" / "constraints.txt").write_text(
        "# The versions eyeserver was tested with (scripts/soup.py); deploy/install.sh uses "
        "them.\n" + "\n".join(pins) + "\n", encoding="utf-8")
    print(f"soup: {len(pins)} packages written to docs/soup.md and deploy/constraints.txt")
    return 0


if __name__ == "__main__":
    sys.exit(main())
