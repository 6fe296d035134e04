"""``retention_days``: measurements older than that are deleted, each deletion audited as
``retention``; calibration captures and younger measurements are kept."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from eyeserver.errors import ConfigError
from eyeserver.hardware.bundling import bundle_frames
from eyeserver.io import rig_from_dict
from eyeserver.service.audit import AUDIT_FILE
from eyeserver.service.core import Service
from eyeserver.service.operations import retention_loop
from eyeserver.service.retention import RETENTION_ACTOR, purge_expired
from eyeserver.service.storage import CaptureRecord
from tests.apiclient import test_settings


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    with Service(test_settings(tmp_path / "data", retention_days=30)) as running:
        yield running


def _calibration_capture(service: Service) -> CaptureRecord:
    steps = service.rig.acquire([u.id for u in service.rig.units])
    return service.store.add_capture("plate", rig_from_dict(service.rig.spec(), "<rig>"),
                                     bundle_frames(steps, 0.0), unit="all",
                                     calibration_id=None)


def _ids(service: Service) -> set[str]:
    return {r.id for r in service.store.list_captures(limit=1000)[0]}


@pytest.mark.slow
def test_old_measurements_are_deleted_and_audited_as_retention(service: Service,
                                                               tmp_path: Path) -> None:
    old = [service.capture("all").id for _ in range(2)]
    plate = _calibration_capture(service).id
    created = datetime.fromisoformat(service.store.get_capture(old[-1]).created)

    # Not yet 30 days old: nothing goes.
    assert purge_expired(service, 30, clock=lambda: created + timedelta(days=29)) == []
    young = service.capture("all").id
    later = datetime.fromisoformat(service.store.get_capture(young).created)

    def cutoff_clock() -> datetime:  # the young one is a millisecond short of 30 days
        return later + timedelta(days=30) - timedelta(microseconds=1000)

    deleted = purge_expired(service, 30, clock=cutoff_clock)

    assert sorted(deleted) == sorted(old)
    assert _ids(service) == {young, plate}  # younger measurement and calibration data stay
    lines = [json.loads(line) for line in
             (tmp_path / "data" / AUDIT_FILE).read_text().splitlines()]
    retained = [line for line in lines if line["actor"] == RETENTION_ACTOR]
    assert sorted(line["target"] for line in retained) == sorted(old)
    for line in retained:
        assert (line["action"], line["role"], line["outcome"]) == (
            "delete_capture", "system", "ok")
        assert line["detail"]["reason"].startswith("retention: older than 30 days")
    assert {e.target for e in service.store.audit_log() if e.actor == RETENTION_ACTOR
            } == set(old)
    assert purge_expired(service, 30, clock=cutoff_clock) == []  # nothing twice


@pytest.mark.slow
def test_a_stored_results_evidence_is_kept(service: Service) -> None:
    evidence, plain = (service.capture("all").id for _ in range(2))
    service.keep_as_evidence(lambda: {evidence: "the evidence of pose measurement pose-1"})
    later = datetime.fromisoformat(service.store.get_capture(plain).created)

    assert purge_expired(service, 30, clock=lambda: later + timedelta(days=31)) == [plain]
    assert _ids(service) == {evidence}


@pytest.mark.slow
def test_the_periodic_task_applies_the_rule_again_and_again(service: Service) -> None:
    first = service.capture("all").id
    now = [datetime.now(UTC)]

    async def run() -> None:
        task = asyncio.create_task(retention_loop(service, 1, interval_s=0.02,
                                                  clock=lambda: now[0]))
        await asyncio.sleep(0.2)
        assert first in _ids(service)  # a fresh capture survives the first runs
        now[0] += timedelta(days=2)
        for _ in range(100):
            await asyncio.sleep(0.02)
            if first not in _ids(service):
                break
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(run())
    assert first not in _ids(service)


def test_retention_days_must_be_positive(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="retention_days"):
        test_settings(tmp_path, retention_days=0)
    assert test_settings(tmp_path).retention_days is None  # default: keep forever
