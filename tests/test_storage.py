"""The daemon's store (eyeserver.service.storage): index, atomic writes, recovery, audit."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from eyeserver.calibration.artefact import write_calibration
from eyeserver.errors import FormatError, StateConflictError
from eyeserver.io import BundleFrameData, RigSpec, read_bundle, rig_from_dict, write_bundle
from eyeserver.service.storage import (
    SCHEMA_VERSION,
    StorageError,
    Store,
    UnknownIdError,
    is_calibration_id,
    is_capture_id,
)

WIDTH, HEIGHT = 16, 12

RIG_DOCUMENT: dict[str, Any] = {
    "format": "eyeserver.rig/1",
    "cameras": [{"id": "S1", "width": WIDTH, "height": HEIGHT},
                {"id": "S2", "width": WIDTH, "height": HEIGHT}],
    "projectors": [{"id": "P1"}],
    "units": [{"id": "left", "projector": "P1", "cameras": ["S1", "S2"]}],
}


@pytest.fixture
def rig() -> RigSpec:
    return rig_from_dict(RIG_DOCUMENT, "test")


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    with Store.open(tmp_path / "data") as opened:
        yield opened


def frames(seed: int = 0, count: int = 2) -> list[BundleFrameData]:
    rng = np.random.default_rng(seed)
    return [BundleFrameData(images={cam: rng.integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
                                    for cam in ("S1", "S2")}, projectors_on=("P1",))
            for _ in range(count)]


def calibration_dir(path: Path, reprojection_px: float = 0.2) -> Path:
    """A minimal calibration directory that load_calibration accepts (no stereo run needed)."""
    camera = {"width": WIDTH, "height": HEIGHT,
              "K": [[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]],
              "dist": [0.0, 0.0, 0.0, 0.0, 0.0],
              "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
              "T": [0.0, 0.0, 300.0]}
    document = {"format": "eyeserver.calibration/1", "version": 1,
                "created": "2026-11-23T10:00:00Z", "rig": RIG_DOCUMENT,
                "cameras": {"S1": camera, "S2": camera},
                "quality": {"reprojection_median_px": reprojection_px}}
    return write_calibration(path, document,
                             {"phase_S1": np.zeros((HEIGHT, WIDTH), np.float32)})


# --- opening --------------------------------------------------------------------------------

def test_index_is_wal_with_full_sync_and_versioned(store: Store) -> None:
    assert store.pragmas() == {"journal_mode": "wal", "synchronous": 2,
                               "user_version": SCHEMA_VERSION}
    # WAL is a property of the file: a fresh connection sees it too.
    with sqlite3.connect(store.data_dir / "index.sqlite3") as other:
        assert other.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    for name in ("captures", "calibrations", "quarantine"):
        assert (store.data_dir / name).is_dir()
    assert store.recovery.clean


def test_second_process_cannot_open_the_same_store(store: Store) -> None:
    code = "import sys; from eyeserver.service.storage import Store; Store.open(sys.argv[1])"
    result = subprocess.run([sys.executable, "-c", code, str(store.data_dir)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode != 0
    assert "open in another process" in result.stderr


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    Store.open(tmp_path).close()
    with sqlite3.connect(tmp_path / "index.sqlite3") as db:
        db.execute("PRAGMA user_version=99")
    with pytest.raises(StorageError, match="schema version 99"):
        Store.open(tmp_path)


def test_closed_store_refuses_work(tmp_path: Path) -> None:
    opened = Store.open(tmp_path)
    opened.close()
    opened.close()
    with pytest.raises(StorageError, match="closed"):
        opened.list_captures()


# --- captures -------------------------------------------------------------------------------

def test_capture_round_trips(store: Store, rig: RigSpec) -> None:
    taken = frames(seed=3)
    record = store.add_capture("measurement", rig, taken, unit="left",
                               calibration_id=None, extra={"note": "hello"})
    assert is_capture_id(record.id) and not is_calibration_id(record.id)
    assert record.path == store.data_dir / "captures" / record.id
    assert (record.kind, record.unit, record.frame_count, record.status) == (
        "measurement", "left", 2, "ok")
    assert store.get_capture(record.id) == record
    assert store.capture_path(record.id) == record.path
    bundle = read_bundle(record.path)
    assert bundle.kind == "measurement"
    assert bundle.extra["note"] == "hello"
    assert bundle.extra["capture"] == {"id": record.id, "unit": "left", "calibration_id": None}
    assert bundle.created == record.created
    np.testing.assert_array_equal(bundle.load_image(1, "S2"), taken[1].images["S2"])
    # The id's time is the creation time, within the clock's reach.
    created = datetime.fromisoformat(record.created.replace("Z", "+00:00"))
    assert abs(created - datetime.now(UTC)) < timedelta(seconds=30)


def test_paging_and_filters(store: Store, rig: RigSpec) -> None:
    ids = [store.add_capture("measurement", rig, frames(n, 1),
                             unit="left" if n % 3 else "all", calibration_id=None).id
           for n in range(7)]
    newest_first = ids[::-1]
    page, total = store.list_captures(limit=3)
    assert total == 7 and [r.id for r in page] == newest_first[:3]
    page, total = store.list_captures(limit=3, offset=6)
    assert total == 7 and [r.id for r in page] == newest_first[6:]
    page, total = store.list_captures(unit="all")
    assert total == 3 and [r.id for r in page] == [ids[6], ids[3], ids[0]]
    since = datetime.fromisoformat(store.get_capture(ids[4]).created.replace("Z", "+00:00"))
    page, total = store.list_captures(since=since)
    assert [r.id for r in page] == newest_first[:3] and total == 3
    page, total = store.list_captures(unit="left", since=since)
    assert [r.id for r in page] == [ids[5], ids[4]] and total == 2
    with pytest.raises(ValueError, match="limit"):
        store.list_captures(limit=0)
    with pytest.raises(ValueError, match="time zone"):
        store.list_captures(since=datetime(2026, 1, 1))


def test_ids_are_unique_and_sorted_under_concurrency(store: Store, rig: RigSpec) -> None:
    per_thread, threads = 6, 4
    taken: dict[int, list[str]] = {n: [] for n in range(threads)}
    errors: list[BaseException] = []

    def work(worker: int) -> None:
        try:
            for n in range(per_thread):
                record = store.add_capture("measurement", rig, frames(n, 1), unit=f"u{worker}",
                                           calibration_id=None)
                taken[worker].append(record.id)
        except BaseException as exc:  # reported below, in the test's thread
            errors.append(exc)

    workers = [threading.Thread(target=work, args=(n,)) for n in range(threads)]
    for thread in workers:
        thread.start()
    for thread in workers:
        thread.join()
    assert not errors
    every = [i for ids in taken.values() for i in ids]
    assert len(set(every)) == per_thread * threads
    for ids in taken.values():  # each thread's ids sort in the order it made them
        assert ids == sorted(ids)
    listed, total = store.list_captures(limit=100)
    assert total == per_thread * threads
    assert [r.id for r in listed] == sorted(every, reverse=True)
    for record in listed:
        read_bundle(record.path)


def test_ids_keep_increasing_after_reopen(tmp_path: Path, rig: RigSpec) -> None:
    with Store.open(tmp_path) as first:
        # An id from the future, as if the clock had been set back since.
        future = "cap-29991231T235959000Z-abcd"
        write_bundle(first.captures_dir / future, "measurement", rig, frames(0, 1))
    with Store.open(tmp_path) as second:
        assert second.recovery.recovered == (future,)
        fresh = second.add_capture("measurement", rig, frames(1, 1), unit="left",
                                   calibration_id=None)
        assert fresh.id > future


@pytest.mark.parametrize("bad", ["../etc", "cap-../../x", "cap-20261123T151200123Z-ABCD",
                                 "cal-20261123T151200123Z-abcd", "", "cap-1/2"])
def test_malformed_capture_ids_are_refused(store: Store, bad: str) -> None:
    with pytest.raises(StorageError, match="is not a capture id") as caught:
        store.get_capture(bad)
    assert repr(bad) in str(caught.value)
    with pytest.raises(StorageError, match="is not a capture id"):
        store.delete_capture(bad, actor="tester", reason="cleanup")


def test_unknown_capture_names_its_id(store: Store) -> None:
    unknown = "cap-20261123T151200123Z-beef"
    with pytest.raises(UnknownIdError, match=unknown) as caught:
        store.get_capture(unknown)
    assert caught.value.item_id == unknown


def test_bad_capture_arguments_write_nothing(store: Store, rig: RigSpec) -> None:
    with pytest.raises(ValueError, match="frames"):
        store.add_capture("measurement", rig, [], unit="left", calibration_id=None)
    with pytest.raises(ValueError, match="reserved"):
        store.add_capture("measurement", rig, frames(), unit="left", calibration_id=None,
                          extra={"capture": 1})
    with pytest.raises(StorageError, match="calibration_id"):
        store.add_capture("measurement", rig, frames(), unit="left", calibration_id="../x")
    assert store.list_captures() == ([], 0)
    assert list(store.captures_dir.iterdir()) == []


def test_delete_is_audited_and_removes_the_data(store: Store, rig: RigSpec) -> None:
    kept = store.add_capture("measurement", rig, frames(1), unit="left", calibration_id=None)
    doomed = store.add_capture("measurement", rig, frames(2), unit="left", calibration_id=None)
    with pytest.raises(StorageError, match="reason"):
        store.delete_capture(doomed.id, actor="alice", reason=" ")
    with pytest.raises(StorageError, match="actor"):
        store.delete_capture(doomed.id, actor="", reason="test")
    assert doomed.path.is_dir() and store.audit_log() == []

    store.delete_capture(doomed.id, actor="alice", reason="duplicate")
    assert not doomed.path.exists()
    assert [p.name for p in store.captures_dir.iterdir()] == [kept.id]
    with pytest.raises(UnknownIdError):
        store.get_capture(doomed.id)
    assert store.list_captures()[1] == 1
    (entry,) = store.audit_log()
    assert (entry.actor, entry.action, entry.target) == ("alice", "delete_capture", doomed.id)
    assert entry.detail["reason"] == "duplicate"
    assert datetime.fromisoformat(entry.time.replace("Z", "+00:00")).tzinfo is not None


# --- recovery -------------------------------------------------------------------------------

def test_recovery_quarantines_partials_and_reindexes_orphans(tmp_path: Path,
                                                             rig: RigSpec) -> None:
    with Store.open(tmp_path) as first:
        indexed = first.add_capture("measurement", rig, frames(0), unit="left",
                                    calibration_id=None)
        vanished = first.add_capture("measurement", rig, frames(1), unit="left",
                                     calibration_id=None)
    # A bundle renamed into place whose index row was never committed (crash between the two).
    orphan = "cap-20261123T151200123Z-0a0b"
    write_bundle(tmp_path / "captures" / orphan, "plate", rig,
                 [BundleFrameData(images={}, z_mm=2.5)],
                 extra={"capture": {"id": orphan, "unit": "left",
                                    "calibration_id": "cal-20261123T100000000Z-cafe"}})
    # A staging directory of an interrupted write, with a torn file in it.
    partial = tmp_path / "captures" / f".{orphan[:-4]}beef.0123456789ab.partial"
    partial.mkdir()
    (partial / "S1_0000.png").write_bytes(b"\x89PNG torn")
    # A row whose directory vanished, and a stray file no one knows.
    os.rename(vanished.path, tmp_path / "elsewhere")
    (tmp_path / "captures" / "notes.txt").write_text("hi")

    with Store.open(tmp_path) as second:
        report = second.recovery
        assert report.recovered == (orphan,)
        assert report.missing == (vanished.id,)
        assert report.unrecognised == (tmp_path / "captures" / "notes.txt",)
        (moved,) = report.quarantined
        assert moved.parent == tmp_path / "quarantine"
        assert (moved / "S1_0000.png").read_bytes() == b"\x89PNG torn"  # kept, not deleted
        assert not partial.exists()
        assert not report.clean

        recovered = second.get_capture(orphan)
        assert (recovered.kind, recovered.unit, recovered.calibration_id, recovered.frame_count,
                recovered.status) == ("plate", "left", "cal-20261123T100000000Z-cafe", 1, "ok")
        assert recovered.created == "2026-11-23T15:12:00.123Z"
        assert second.get_capture(vanished.id).status == "missing"
        assert second.get_capture(indexed.id).status == "ok"
        assert second.list_captures()[1] == 3  # nothing was dropped from the index

    os.rename(tmp_path / "elsewhere", vanished.path)  # restored by hand
    with Store.open(tmp_path) as third:
        assert third.recovery.clean is False  # notes.txt is still there
        assert third.recovery.missing == ()
        assert third.get_capture(vanished.id).status == "ok"


def test_missing_capture_can_still_be_deleted(tmp_path: Path, rig: RigSpec) -> None:
    with Store.open(tmp_path) as first:
        record = first.add_capture("measurement", rig, frames(0), unit="left",
                                   calibration_id=None)
    shutil.rmtree(record.path)
    with Store.open(tmp_path) as second:
        assert second.recovery.missing == (record.id,)
        second.delete_capture(record.id, actor="bob", reason="lost disk")
        assert second.list_captures()[1] == 0
        assert second.audit_log()[0].detail["status"] == "missing"


def test_interrupted_audited_delete_is_finished(tmp_path: Path, rig: RigSpec) -> None:
    with Store.open(tmp_path) as first:
        record = first.add_capture("measurement", rig, frames(0), unit="left",
                                   calibration_id=None)
        other = first.add_capture("measurement", rig, frames(1), unit="left",
                                  calibration_id=None)
        # The audit row is written, the directory renamed, then the process dies.
        with first._transaction() as db:
            first._audit(db, "carol", "delete_capture", record.id, {"reason": "test"})
    doomed = tmp_path / "captures" / f".{record.id}.0123456789ab.deleting"
    os.rename(record.path, doomed)
    # A .deleting directory without an audited request is not deleted but quarantined.
    unaudited = tmp_path / "captures" / f".{other.id}.0123456789ab.deleting"
    os.rename(other.path, unaudited)
    with Store.open(tmp_path) as second:
        assert second.recovery.deletions_completed == (record.id,)
        assert not doomed.exists()
        assert len(second.recovery.quarantined) == 1
        assert (second.recovery.quarantined[0] / "bundle.json").is_file()
        assert second.recovery.missing == (other.id,)
        with pytest.raises(UnknownIdError):
            second.get_capture(record.id)


_WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    from eyeserver.io import BundleFrameData, rig_from_dict
    from eyeserver.service.storage import Store

    rig = rig_from_dict({rig!r}, "child")
    rng = np.random.default_rng(0)
    # Noise compresses badly, so each bundle takes a while to encode and fsync: a kill is
    # likely to land in the middle of a write.
    images = [rng.integers(0, 256, (480, 640), dtype=np.uint8) for _ in range(4)]
    store = Store.open(sys.argv[1])
    print("open", flush=True)
    while True:
        frames = [BundleFrameData(images={{"S1": images[n], "S2": images[n + 2]}})
                  for n in range(2)]
        record = store.add_capture("measurement", rig, frames, unit="left",
                                   calibration_id=None)
        print(record.id, flush=True)
""")


@pytest.mark.slow
def test_acknowledged_captures_survive_sigkill(tmp_path: Path) -> None:
    big = dict(RIG_DOCUMENT)
    big["cameras"] = [{"id": cam, "width": 640, "height": 480} for cam in ("S1", "S2")]
    code = _WRITER.format(rig=big)
    acknowledged: list[str] = []
    kills = 0
    for round_ in range(3):  # several kills at different points of a write
        child = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert child.stdout is not None
        try:
            assert child.stdout.readline().strip() == "open"
            for _ in range(3 + round_):
                line = child.stdout.readline().strip()
                assert is_capture_id(line), line
                acknowledged.append(line)
            time.sleep(0.013 * (round_ + 1))  # land somewhere in the next write
        finally:
            child.send_signal(signal.SIGKILL)
            child.wait(timeout=30)
            child.stdout.close()
            assert child.stderr is not None
            child.stderr.close()
        assert child.returncode == -signal.SIGKILL
        kills += 1
        # Lines printed after the last read were acknowledged too: the id is printed only
        # once add_capture has returned. They may be lost from the pipe, never from the store.

        with Store.open(tmp_path) as store:
            report = store.recovery
            records, total = store.list_captures(limit=1000)
            indexed = {r.id for r in records}
            assert set(acknowledged) <= indexed
            for record in records:  # nothing half-written is indexed
                bundle = read_bundle(record.path)
                assert len(bundle.frames) == 2
                bundle.load_image(1, "S2")
            assert not [p for p in store.captures_dir.iterdir() if p.name.startswith(".")]
            for moved in report.quarantined:
                assert moved.parent == store.quarantine_dir and moved.exists()
            assert report.missing == ()
            assert total == len(indexed)
    assert kills == 3 and len(acknowledged) == 3 + 4 + 5
    print(f"{len(acknowledged)} acknowledged before {kills} kills, all found; "
          f"{total} indexed; {len(list((tmp_path / 'quarantine').iterdir()))} quarantined")


# --- calibrations ---------------------------------------------------------------------------

def test_calibration_import_and_single_activation(store: Store, tmp_path: Path) -> None:
    first = store.import_calibration(calibration_dir(tmp_path / "a", 0.2), actor="alice")
    second = store.import_calibration(calibration_dir(tmp_path / "b", 0.3), actor="alice")
    assert is_calibration_id(first.id) and first.id < second.id
    assert first.quality == {"reprojection_median_px": 0.2}
    assert first.created == "2026-11-23T10:00:00Z"
    assert first.source == str(tmp_path / "a")
    assert sorted(p.name for p in first.path.iterdir()) == ["arrays.npz", "calibration.json"]
    assert json.loads((first.path / "calibration.json").read_text())["quality"] == {
        "reprojection_median_px": 0.2}
    assert store.active_calibration() is None
    assert [c.id for c in store.list_calibrations()] == [second.id, first.id]

    assert store.activate_calibration(first.id, actor="bob").active
    assert store.active_calibration() == store.get_calibration(first.id)
    store.activate_calibration(second.id, actor="bob")
    store.activate_calibration(second.id, actor="bob")
    active = [c.id for c in store.list_calibrations() if c.active]
    assert active == [second.id]
    # The database itself refuses a second active row.
    with pytest.raises(sqlite3.IntegrityError), store._transaction() as db:
        db.execute("UPDATE calibrations SET active = 1 WHERE id = ?", (first.id,))
    assert [c.id for c in store.list_calibrations() if c.active] == [second.id]

    actions = [(e.actor, e.action, e.target) for e in store.audit_log()]
    assert actions == [("bob", "activate_calibration", second.id),
                       ("bob", "activate_calibration", second.id),
                       ("bob", "activate_calibration", first.id),
                       ("alice", "import_calibration", second.id),
                       ("alice", "import_calibration", first.id)]
    assert store.audit_log(limit=1)[0].detail == {"previous": second.id}
    assert store.audit_log()[2].detail == {"previous": None}


def test_calibrations_survive_reopen_and_orphans_are_recovered(tmp_path: Path) -> None:
    with Store.open(tmp_path / "data") as first:
        kept = first.import_calibration(calibration_dir(tmp_path / "a"), actor="alice")
        first.activate_calibration(kept.id, actor="alice")
    orphan = "cal-20261123T090000000Z-1234"
    calibration_dir(tmp_path / "data" / "calibrations" / orphan, 0.4)
    with Store.open(tmp_path / "data") as second:
        assert second.recovery.recovered == (orphan,)
        assert second.active_calibration() == second.get_calibration(kept.id)
        assert second.get_calibration(orphan).quality == {"reprojection_median_px": 0.4}


def test_invalid_calibration_is_refused_naming_the_file(store: Store, tmp_path: Path) -> None:
    source = calibration_dir(tmp_path / "bad")
    document = json.loads((source / "calibration.json").read_text())
    document["cameras"]["S2"]["R"] = [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    (source / "calibration.json").write_text(json.dumps(document))
    with pytest.raises(FormatError, match=r"cameras\.S2\.R") as caught:
        store.import_calibration(source, actor="alice")
    assert str(source / "calibration.json") in str(caught.value)
    with pytest.raises(FormatError, match="cannot read"):
        store.import_calibration(tmp_path / "nowhere", actor="alice")
    assert store.list_calibrations() == []
    assert list(store.calibrations_dir.iterdir()) == []
    assert store.audit_log() == []


def test_bad_calibration_ids_are_refused(store: Store) -> None:
    with pytest.raises(StorageError, match=r"'\.\./x' is not a calibration id"):
        store.get_calibration("../x")
    with pytest.raises(UnknownIdError, match="cal-20261123T090000000Z-1234"):
        store.activate_calibration("cal-20261123T090000000Z-1234", actor="bob")
    with pytest.raises(StorageError, match="actor"):
        store.activate_calibration("cal-20261123T090000000Z-1234", actor="")


def test_missing_calibration_cannot_be_activated(tmp_path: Path) -> None:
    with Store.open(tmp_path / "data") as first:
        record = first.import_calibration(calibration_dir(tmp_path / "a"), actor="alice")
    os.rename(record.path, tmp_path / "moved")
    with Store.open(tmp_path / "data") as second:
        assert second.recovery.missing == (record.id,)
        with pytest.raises(StorageError, match=f"{record.id} is missing"):
            second.activate_calibration(record.id, actor="bob")


def test_second_store_in_process_conflicts(store: Store) -> None:
    with pytest.raises(StateConflictError, match="another process"):
        Store.open(store.data_dir)
