"""``eyeserver bench reliability``: one tiny run of every part through real daemons (one kill
cycle, one camera unplugged, a small tmpfs, seconds of light load, the fuzz on two operations),
then the counting and the report fed made-up failures, so that a lost capture, a damaged bundle
or an unannounced gap in the event stream is seen to be reported. No test asserts on wall-clock
time; the run's timeouts only keep a broken daemon from hanging it. The tests through daemons
are marked slow; the counting and the skips are the fast tier's."""

from __future__ import annotations

import contextlib
import copy
import io
import json
import os
import random
import sys
from pathlib import Path
from typing import Any

import pytest

from eyeserver.bench import reliability
from eyeserver.bench.daemon import DaemonError, DaemonProcess
from eyeserver.bench.reliability import (
    check_bundle,
    choose_devices,
    findings,
    format_text,
    list_captures,
    stream_losses,
    tally_captures,
)
from eyeserver.bench.report import main as report_main
from eyeserver.bench.report import render_reliability
from eyeserver.cli import main
from eyeserver.errors import EyeserverError

GOAL_FINDING = "load: status p99"
"""The one finding a healthy daemon may give here: the latency goal depends on the machine."""


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    """The bench through the command line, every part at its smallest; (report, --out DIR)."""
    out = tmp_path_factory.mktemp("reliability") / "out"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["bench", "reliability", "--json", "--kill-cycles", "1",
                     "--devices", "S1", "--unplugged-seconds", "0.3", "--disk-mib", "64",
                     "--load-seconds", "2", "--status-clients", "4", "--capture-clients", "2",
                     "--fuzz-examples", "1", "--fuzz-operations", "^/api/v1/(status|captures)$",
                     "--seed", "3", "--out", str(out)])
    assert code == 0
    report: dict[str, Any] = json.loads(stdout.getvalue())
    return report, out


@pytest.mark.slow  # through real daemons
def test_every_part_reports_sane_figures(bench_run: tuple[dict[str, Any], Path]) -> None:
    report, _ = bench_run
    assert report["format"] == reliability.FORMAT
    assert report["machine"]["cpu_count"] >= 1 and report["seed"] == 3

    kill = report["kill"]
    assert kill["cycles"] == len(kill["kills"]) == 1
    assert kill["acknowledged"] == kill["statuses"]["201"] >= 1
    assert kill["lost"] == kill["corrupted"] == 0
    assert kill["intact_acknowledged"] == kill["acknowledged"]
    assert kill["listed"] == kill["acknowledged"] + kill["stored_without_answer"]
    assert kill["stored_without_answer"] <= kill["no_answer"]
    assert kill["state_after_restart"] == "idle"

    (camera,) = report["unplug"]["devices"]
    assert camera["device"] == "S1" and camera["kind"] == "camera"
    for flag in ("injected", "replugged", "detected", "state_fault_seen", "fault_event",
                 "recovered", "recovered_event"):
        assert camera[flag], flag
    assert camera["detect_s"] >= 0 and camera["recover_s"] >= 0
    assert set(camera["captures_while_unplugged"]) <= {"201", "503"}
    assert "S1" in camera["refusal_reasons"]["503"]
    assert camera["acknowledged_after_detection"] == 0
    assert camera["capture_after_recovery"] == 201
    assert report["unplug"]["events"]["lost"] == 0

    disk = report["disk_full"]
    if os.geteuid() != 0:
        assert "root" in disk["skipped"]
    else:
        assert disk["while_full"]["statuses"].get("507", 0) >= 1
        assert disk["while_full"]["all_failures_507_with_reason"]
        assert "space" in disk["while_full"]["reason"]
        assert disk["store_while_full"]["lost"] == disk["store_while_full"]["corrupted"] == 0
        assert disk["after_freeing"]["recovered"]
        assert disk["store_after_restart"]["acknowledged"] >= reliability.STORED_BEFORE_FULL + 2
        assert disk["store_after_restart"]["lost"] == 0
        assert disk["store_after_restart"]["corrupted"] == 0

    load = report["load"]
    assert load["seconds"] == 2 <= load["elapsed_s"]
    assert load["cpu_s"]["client"] > 0 and load["cpu_s"]["daemon"] > 0  # Linux: /proc
    idle, busy = load["status_idle"], load["status_under_load"]
    assert idle["requests"] == reliability.IDLE_STATUS_REQUESTS
    assert busy["requests"] >= 4 and busy["statuses"] == {"200": busy["requests"]}
    for summary in (idle, busy):
        assert 0 < summary["p50_ms"] <= summary["p99_ms"] <= summary["max_ms"]
    assert load["status_p99_goal_ms"] == reliability.STATUS_P99_GOAL_MS
    captures = load["captures"]
    assert captures["acknowledged"] >= 1 and captures["per_s"] > 0
    assert sum(captures["statuses"].values()) == captures["posted"]
    assert load["events"]["lost"] == load["events"]["capture_stored_missing"] == 0
    assert load["events"]["by_type"]["capture.stored"] >= captures["acknowledged"]

    fuzz = report["fuzz"]
    assert fuzz["operations"] == 3  # GET /status, POST and GET /captures
    assert fuzz["requests"] >= fuzz["operations"] * 2
    assert fuzz["server_errors"] == fuzz["undocumented_status"] == 0
    assert fuzz["schema_mismatches"] == 0 and fuzz["errors"] == []

    assert [f for f in report["findings"] if not f.startswith(GOAL_FINDING)] == []


@pytest.mark.slow  # through real daemons
def test_the_text_and_the_page_section_show_the_figures(
        bench_run: tuple[dict[str, Any], Path]) -> None:
    report, _ = bench_run
    text = format_text(report)
    assert "kill -9, 1 cycles" in text and "S1" in text and "goal p99 ≤ 100 ms" in text
    section = render_reliability(report)
    assert section.startswith("## Reliability\n")
    for heading in ("### kill -9 during captures", "### Devices unplugged and replugged",
                    "### Disk full and freed", "### Load", "### Fuzz"):
        assert heading in section
    kill = report["kill"]
    assert (f"| {kill['acknowledged']} | 0 | 0 | {kill['no_answer']} | "
            f"{kill['stored_without_answer']} |") in section
    assert f"| p99 (ms) | {report['load']['status_idle']['p99_ms']:.1f} |" in section


@pytest.mark.slow  # through real daemons
def test_a_damaged_bundle_is_found(bench_run: tuple[dict[str, Any], Path]) -> None:
    _, out = bench_run
    data = out / "kill" / "data"
    with DaemonProcess(data, log=out / "kill" / "check.log") as daemon:
        listed = list_captures(daemon.client)
        damaged, *others = sorted(listed)
        assert check_bundle(daemon.client, listed[damaged]) is None
        listed_more = {**listed[damaged], "frame_count": listed[damaged]["frame_count"] + 1}
        assert "frames in the bundle" in str(check_bundle(daemon.client, listed_more))
        image = sorted((data / "captures" / damaged).glob("**/*.png"))[0]
        image.write_bytes(image.read_bytes()[:200])  # a torn write
        assert image.name in str(check_bundle(daemon.client, listed[damaged]))
        for other in others[:1]:
            assert check_bundle(daemon.client, listed[other]) is None


def _capture(capture_id: str, created: str = "2026-01-01T00:00:00.000Z") -> dict[str, Any]:
    return {"id": capture_id, "kind": "measurement", "unit": "left", "calibration_id": None,
            "created": created, "frame_count": 1, "status": "ok"}


def test_lost_and_corrupted_captures_are_counted() -> None:
    acknowledged = {c: _capture(c) for c in ("cap-a", "cap-b", "cap-c", "cap-d")}
    listed = {"cap-a": _capture("cap-a"), "cap-c": _capture("cap-c", "2026-01-02T00:00:00.000Z"),
              "cap-d": _capture("cap-d"), "cap-e": _capture("cap-e")}
    tally = tally_captures(acknowledged, listed, {"cap-d": "bundle.zip: HTTP 500"},
                           no_answer=2)
    assert tally["acknowledged"] == 4 and tally["no_answer"] == 2
    assert tally["lost"] == 1 and tally["lost_ids"] == ["cap-b"]
    assert tally["corrupted"] == 2
    assert tally["corrupted_ids"]["cap-d"] == "bundle.zip: HTTP 500"
    assert "2026-01-02" in tally["corrupted_ids"]["cap-c"]  # listed otherwise than answered
    assert tally["intact_acknowledged"] == 1
    assert tally["stored_without_answer"] == 1  # cap-e: in flight, yet stored
    whole = tally_captures({"cap-a": _capture("cap-a")}, {"cap-a": _capture("cap-a")}, {})
    assert whole["lost"] == whole["corrupted"] == 0 and whole["intact_acknowledged"] == 1


@pytest.mark.slow  # through real daemons
def test_findings_name_what_went_wrong(bench_run: tuple[dict[str, Any], Path]) -> None:
    report = copy.deepcopy(bench_run[0])
    report["kill"].update(tally_captures({"cap-a": _capture("cap-a")}, {}, {}))
    camera = report["unplug"]["devices"][0]
    camera.update({"recovered": False, "recover_s": None})
    camera["captures_while_unplugged"] = {"500": 1, "503": 2}
    report["load"]["status_under_load"]["p99_ms"] = 5900.0
    report["load"]["events"]["unannounced_lost"] = report["load"]["events"]["lost"] = 3
    report["fuzz"]["server_errors"] = 2
    if "skipped" not in report["disk_full"]:
        report["disk_full"]["while_full"].update({"statuses": {"500": 1},
                                                  "all_failures_507_with_reason": False})
    found = "\n".join(findings(report))
    assert "kill -9: 1 acknowledged capture(s) LOST: cap-a" in found
    assert "unplug S1 (camera): NOT recovered after the replug" in found
    assert "unplug S1 (camera): captures answered {'500': 1, '503': 2}" in found
    assert "load: status p99 5900.0 ms under load, goal ≤ 100 ms" in found
    assert "load: event stream lost 3 event(s)" in found
    assert "fuzz: 2 5xx answers" in found
    if "skipped" not in report["disk_full"]:
        assert "disk full: captures answered {'500': 1}" in found
    report["findings"] = findings(report)
    assert "- kill -9: 1 acknowledged capture(s) LOST: cap-a" in render_reliability(report)
    assert "FINDINGS:" in format_text(report)


def test_stream_losses_tell_announced_from_unannounced_gaps() -> None:
    messages = [{"type": "hello", "last_seq": 10},
                {"type": "state", "seq": 11},
                {"type": "dropped", "count": 2},
                {"type": "capture.stored", "seq": 14},  # 12 and 13 dropped, and said so
                {"type": "state", "seq": 17},  # 15 and 16 gone without a word
                {"type": "state", "seq": 16}]
    losses = stream_losses(messages)
    assert losses["messages"] == 6 and losses["dropped_notices"] == 1
    assert losses["announced_lost"] == 2 and losses["unannounced_lost"] == 2
    assert losses["out_of_order"] == 1 and losses["lost"] == 4
    whole = stream_losses([{"type": "hello", "last_seq": 0}, {"type": "state", "seq": 1},
                           {"type": "state", "seq": 2}])
    assert whole["lost"] == whole["out_of_order"] == 0


def test_devices_are_chosen_one_of_each_kind_or_by_id() -> None:
    devices = [{"id": "P1", "kind": "projector"}, {"id": "P2", "kind": "projector"},
               {"id": "S1", "kind": "camera"}, {"id": "T1", "kind": "trigger"}]
    assert [d["id"] for d in choose_devices(devices, None)] == ["P1", "S1", "T1"]
    assert [d["id"] for d in choose_devices(devices, ["P2"])] == ["P2"]
    with pytest.raises(EyeserverError, match="no device X9"):
        choose_devices(devices, ["X9"])


def test_parts_that_cannot_run_say_why(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "schemathesis", None)  # as if not installed
    assert "schemathesis is not installed" in reliability.fuzz(tmp_path, 1)["skipped"]
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert "root" in reliability.disk_full(tmp_path, 64)["skipped"]


@pytest.mark.slow  # through real daemons
def test_a_daemon_that_does_not_start_is_an_error_not_a_traceback(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "reliability", "--room", str(tmp_path / "none.toml")]) == 2
    assert capsys.readouterr().err.startswith("eyeserver: error: ")
    # A room file that reads but that the daemon refuses: its log is quoted in the error.
    room = tmp_path / "room.toml"
    room.write_text("[room\n")
    with pytest.raises(DaemonError, match="exited with"):
        reliability.kill_during_captures(tmp_path / "kill", 1, random.Random(0),
                                         env={"EYESERVER_ROOM_FILE": str(room)})


@pytest.mark.slow  # through real daemons
def test_the_page_gets_a_reliability_section_only_when_asked(
        bench_run: tuple[dict[str, Any], Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    accuracy = {"machine": bench_run[0]["machine"], "seed": 0, "quick": True,
                "noise_model": {"shot_noise_full_well_e": 10000, "read_noise_dn": 1.0,
                                "bit_depth": 8}}
    paths = []
    for name, document in (("accuracy", accuracy), ("speed", {}),
                           ("reliability", bench_run[0])):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps(document))
    assert report_main([str(paths[0]), str(paths[1])]) == 0
    assert "## Reliability" not in capsys.readouterr().out
    assert report_main([str(paths[0]), "--reliability", str(paths[2]), str(paths[1])]) == 0
    page = capsys.readouterr().out
    assert "## Speed" in page and page.index("## Reliability") > page.index("## Speed")
    assert report_main([str(paths[0]), str(paths[1]), "--reliability"]) == 2
    assert "usage" in capsys.readouterr().err


WRK_REPORT = """Running 10s test @ http://127.0.0.1:41503/api/v1/status
  2 threads and 100 connections
  Thread Stats   Avg      Stdev     Max   +/- Stdev
    Latency    97.36ms   27.80ms    1.23s    86.44%
    Req/Sec   517.62    138.02   800.00     73.23%
  Latency Distribution
     50%   86.94ms
     75%  103.22ms
     90%  134.26ms
     99%  186.32ms
  10265 requests in 10.02s, 22.93MB read
  Non-2xx or 3xx responses: 7
Requests/sec:   1024.75
Transfer/sec:      2.29MB
"""


def test_wrks_report_is_read_with_its_units_and_refusals() -> None:
    assert reliability.parse_wrk(WRK_REPORT) == {
        "requests": 10265, "p50_ms": 86.94, "p99_ms": 186.32, "max_ms": 1230.0,
        "statuses": {"200": 10258, "not 2xx": 7}}
    quick = WRK_REPORT.replace("86.94ms", "870.00us").replace("Non-2xx or 3xx responses: 7\n", "")
    assert reliability.parse_wrk(quick)["p50_ms"] == 0.87
    assert reliability.parse_wrk(quick)["statuses"] == {"200": 10265}
    with pytest.raises(ValueError, match="no latency distribution"):
        reliability.parse_wrk("unable to connect to 127.0.0.1:1 Connection refused\n")


def test_the_reliability_section_is_spliced_into_the_page_alone() -> None:
    from eyeserver.bench.report import splice

    page = "# Benchmarks\n\n## Speed\n\nfast\n\n## Reliability\n\nold run\n\n## After\n\nkept\n"
    assert splice(page, "## Reliability\n\nnew run\n") == (
        "# Benchmarks\n\n## Speed\n\nfast\n\n## Reliability\n\nnew run\n\n## After\n\nkept\n")
    last = "# Benchmarks\n\n## Speed\n\nfast\n\n## Reliability\n\nold run\n"
    assert splice(last, "## Reliability\n\nnew\n") == (
        "# Benchmarks\n\n## Speed\n\nfast\n\n## Reliability\n\nnew\n")
    assert splice("# Benchmarks\n\n## Speed\n\nfast\n", "## Reliability\n\nnew\n") \
        == "# Benchmarks\n\n## Speed\n\nfast\n\n## Reliability\n\nnew\n"


def test_splicing_needs_a_page_and_a_reliability_report(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert report_main(["--splice", str(tmp_path / "page.md")]) == 2
    assert "usage" in capsys.readouterr().err
    (tmp_path / "r.json").write_text("{}")
    assert report_main(["--splice", str(tmp_path / "missing.md"), "--reliability",
                        str(tmp_path / "r.json")]) == 2
    assert "missing.md" in capsys.readouterr().err
