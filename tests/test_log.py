"""Structured logging: one JSON object per line on stderr."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from eyeserver.log import configure_logging


@pytest.fixture(autouse=True)
def _restore_root_logger() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in list(root.handlers):
        if handler not in handlers:
            root.removeHandler(handler)
            handler.close()
    root.setLevel(level)


def test_json_lines_carry_the_fields_and_extras(capsys: pytest.CaptureFixture[str]) -> None:
    configure_logging("debug", json=True)

    logging.getLogger("eyeserver.test").info(
        "frame %d captured", 7, extra={"unit": "left", "path": Path("/data/f.png")}
    )

    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1
    record = json.loads(lines[0])
    assert record["level"] == "info"
    assert record["logger"] == "eyeserver.test"
    assert record["message"] == "frame 7 captured"
    assert record["unit"] == "left"
    assert record["path"] == "/data/f.png"
    assert record["time"].endswith("Z")


def test_exceptions_stay_on_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    configure_logging("info")

    try:
        raise ValueError("bad frame")
    except ValueError:
        logging.getLogger("eyeserver.test").exception("processing failed")

    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1
    assert "ValueError: bad frame" in json.loads(lines[0])["exception"]


def test_level_filters_and_reconfiguring_replaces_the_handler(
    capsys: pytest.CaptureFixture[str],
) -> None:
    configure_logging("info")
    configure_logging("WARNING", json=False)

    logger = logging.getLogger("eyeserver.test")
    logger.info("hidden")
    logger.warning("shown")

    err = capsys.readouterr().err
    assert "hidden" not in err
    assert err.count("shown") == 1
    assert "WARNING eyeserver.test: shown" in err


def test_unknown_level_is_rejected() -> None:
    with pytest.raises(ValueError, match="level"):
        configure_logging("chatty")


def test_no_token_ever_reaches_a_log_line(capsys: pytest.CaptureFixture[str]) -> None:
    configure_logging("info", json=True)
    access = logging.getLogger("uvicorn.access")
    access.info('%s - "%s %s HTTP/%s" %d', "127.0.0.1:5", "GET",
                "/api/v1/ws/pose?token=s3cr3t-one&x=1", "1.1", 101)
    logging.getLogger("uvicorn.error").info('%s - "WebSocket %s" [accepted]', "127.0.0.1:5",
                                            "/api/v1/ws/events?access_token=s3cr3t-two")
    logging.getLogger("eyeserver.test").warning("Authorization: Bearer s3cr3t-three",
                                                extra={"url": "/x?token=s3cr3t-four"})
    configure_logging("info", json=False)
    access.info('%s - "%s %s HTTP/%s" %d', "127.0.0.1:5", "GET", "/?token=s3cr3t-five", "1.1",
                200)

    err = capsys.readouterr().err
    assert "s3cr3t" not in err
    assert err.count("[redacted]") == 6  # the access line has it in message and path
    first = json.loads(err.splitlines()[0])
    assert first["path"] == "/api/v1/ws/pose?token=[redacted]&x=1"
