"""The daily QA and its lockout: the clinic's morning check before the first patient.

A QA run (:meth:`DailyQa.run`) captures every unit ``qa.frames`` times while the QA phantom
stands at its QA position, measures it with the active calibration against the phantom's drawing
(:mod:`eyeserver.service.qa_figures`) and judges each figure against its threshold
(:class:`~eyeserver.config.QaThresholds`); the drift is judged against the active calibration's
*QA baseline*, the run a physicist marked as the baseline for it (``baseline=True``, which
needs every other figure to pass). A calibration without a baseline cannot pass a daily QA: a
new calibration needs a new baseline.

The lockout (:meth:`DailyQa.status`, :meth:`DailyQa.check`), while ``qa.required``: position
verification and tracking are refused (:class:`QaLockedError`, HTTP 409 with the reason)
unless, today (the host's local date) and with the active calibration, a QA run passed and
fewer than ``qa.max_consecutive_failures`` runs have failed since. A physicist may override a
lockout with a reason (:meth:`DailyQa.override`): audited, valid for the rest of the day and
the calibration active when it was given, withdrawn at will.

Everything is kept as JSON under ``DATA_DIR/qa/`` (``runs/<id>.json``, ``baselines/<calibration
id>.json``, ``overrides/<id>.json``), each written atomically; every run, baseline, override and
withdrawal is also an audit row. A run's figures are in its document: its captures are
ordinary measurement captures (the retention rule may delete them; the run keeps its figures).

Trends (:meth:`DailyQa.trends`, :meth:`DailyQa.trend_png`) and the day's printable report
(:meth:`DailyQa.report_html`) read the stored runs.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
import re
import secrets
import threading
from collections.abc import Callable, Sequence
from dataclasses import asdict
from datetime import UTC, date, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from eyeserver.config import QaSettings
from eyeserver.errors import StateConflictError
from eyeserver.io import atomic_write_text
from eyeserver.service.core import NoActiveCalibrationError, Service
from eyeserver.service.qa_figures import (
    EYE_PHANTOM_1,
    FIGURES,
    PhantomDrawing,
    calibration_drift_mm,
    measure_phantom,
)
from eyeserver.service.storage import StorageError, UnknownIdError

__all__ = ["QA_DIR", "DailyQa", "NoQaOverrideError", "QaBusyError", "QaLockedError",
           "QaNotAllowedError"]

QA_DIR = "qa"
"""Under the data directory: the QA runs, baselines and overrides."""

_SAFE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
"""Ids that name a file under ``qa/`` (no separator, no leading dot)."""

_log = logging.getLogger(__name__)


class QaLockedError(StateConflictError):
    """Position verification or tracking was asked for while the daily QA locks them
    (HTTP 409; the message says why and what to do)."""


class QaBusyError(StateConflictError):
    """A QA run was asked for while another one is under way (HTTP 409)."""


class NoQaOverrideError(UnknownIdError):
    """No QA override is in force to withdraw (HTTP 404)."""

    def __init__(self) -> None:
        self.item_id = ""
        StorageError.__init__(self, "no QA override is in force")


class QaNotAllowedError(StateConflictError):
    """An override was asked for with nothing to override, or a baseline could not be set
    (HTTP 409; the message says why)."""


def _utc_now() -> datetime:
    return datetime.now(UTC)


def _utc_text(moment: datetime) -> str:
    return moment.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _new_id(prefix: str, moment: datetime) -> str:
    """``<prefix>-<UTC time to the ms>Z-<hex>``: sorts in order of creation."""
    utc = moment.astimezone(UTC)
    return f"{prefix}-{utc.strftime('%Y%m%dT%H%M%S')}{utc.microsecond // 1000:03d}Z-" \
        f"{secrets.token_hex(2)}"


class DailyQa:
    """The daily QA of one daemon: runs, baselines, overrides and the lockout they make.

    Parameters
    ----------
    service : Service
        The open daemon: its rig captures the phantom, its store knows the active calibration
        and takes the audit rows.
    settings : QaSettings
        Whether QA is required, how many frames a run takes, the thresholds.
    data_dir : Path
        The daemon's data directory; everything is kept under ``data_dir/qa``.
    clock : callable, optional
        The time now, time-zone aware (default: the system's); "today" is its local date.
        Tests pass their own to move to another day.
    drawing : PhantomDrawing, optional
        The QA phantom's reference geometry (default: eye phantom 1 at its QA position).

    Notes
    -----
    Every method blocks (captures, reconstruction, files): the API calls them from worker
    threads. One run at a time; reading is safe beside a run.
    """

    def __init__(self, service: Service, settings: QaSettings, data_dir: Path, *,
                 clock: Callable[[], datetime] = _utc_now,
                 drawing: PhantomDrawing = EYE_PHANTOM_1) -> None:
        self.service = service
        self.settings = settings
        self.clock = clock
        self.drawing = drawing
        self._root = data_dir / QA_DIR
        self._run_lock = threading.Lock()
        self._write_lock = threading.Lock()

    # --- storage ------------------------------------------------------------------------------

    def _dir(self, name: str) -> Path:
        return self._root / name

    def _write(self, name: str, file_id: str, document: dict[str, Any]) -> None:
        directory = self._dir(name)
        directory.mkdir(parents=True, exist_ok=True)
        atomic_write_text(directory / f"{file_id}.json", json.dumps(document, indent=2) + "\n")

    def _read_all(self, name: str) -> list[dict[str, Any]]:
        """Every document of a kind, oldest first (their ids sort by time)."""
        directory = self._dir(name)
        if not directory.is_dir():
            return []
        documents: list[dict[str, Any]] = []
        for path in sorted(directory.glob("*.json")):
            try:
                documents.append(json.loads(path.read_text(encoding="utf-8")))
            except (OSError, ValueError):
                _log.error("unreadable QA document skipped", extra={"path": str(path)})
        return documents

    def _today(self) -> date:
        return self.clock().astimezone().date()

    def _active_calibration_id(self) -> str | None:
        active = self.service.store.active_calibration()
        return None if active is None else active.id

    # --- runs ---------------------------------------------------------------------------------

    def run(self, *, actor: str, baseline: bool = False, may_set_baseline: bool = False,
            frames: int | None = None) -> dict[str, Any]:
        """Capture the QA phantom with every unit, measure it, judge it and store the run.

        Parameters
        ----------
        actor : str
            Who runs it (the audit's actor).
        baseline : bool
            Make this run the active calibration's QA baseline if every figure but the drift
            passes (the drift is then 0 by definition); a failing run sets none (its
            ``baseline`` is false, its ``reasons`` say why).
        may_set_baseline : bool
            Whether the caller may set a baseline (physicists).
        frames : int, optional
            Captures of the still phantom (default ``qa.frames``).

        Returns
        -------
        dict
            The stored run: ``id``, ``created``, ``day``, ``actor``, ``calibration_id``,
            ``phantom``, ``capture_ids``, ``passed``, ``reasons``, ``figures`` (each with
            ``value``, ``threshold`` and ``passed``), ``baseline`` (this run set it),
            ``baseline_run_id`` (the one compared with), ``details``, ``problems``.

        Raises
        ------
        NoActiveCalibrationError
            No calibration is active.
        QaBusyError
            Another run is under way.
        QaNotAllowedError
            ``baseline`` asked for by a caller who may not set one.
        StateConflictError, DeviceError, QueueFullError
            As for :meth:`Service.capture`.
        """
        if baseline and not may_set_baseline:
            raise QaNotAllowedError("only a physicist may set a QA baseline")
        count = self.settings.frames if frames is None else frames
        if not 2 <= count <= 20:
            raise ValueError(f"frames must be within 2…20, not {count}")
        if not self._run_lock.acquire(blocking=False):
            raise QaBusyError("a QA run is under way; wait for its result")
        try:
            with self.service.audit.failures(actor, "qa_run", "qa"):
                return self._run(actor, baseline, count)
        finally:
            self._run_lock.release()

    def _run(self, actor: str, set_baseline: bool, frames: int) -> dict[str, Any]:
        service = self.service
        active = service.store.active_calibration()
        if active is None:
            raise NoActiveCalibrationError(
                "no calibration is active: the QA measures with the active calibration")
        captures = [service.capture("all") for _ in range(frames)]
        measured = service.reconstruction_worker.call(lambda: measure_phantom(
            active.path, [c.path for c in captures], self.drawing))
        stored_baseline = self.baseline(active.id)
        figures: dict[str, float | None] = dict(measured.figures)
        if set_baseline:
            figures["drift_mm"] = 0.0
        elif stored_baseline is not None:
            figures["drift_mm"] = calibration_drift_mm(measured.drift_vectors_mm,
                                                       stored_baseline["drift_vectors_mm"])
        else:
            figures["drift_mm"] = None
        thresholds = self.settings.thresholds.model_dump()
        judged: dict[str, dict[str, Any]] = {}
        reasons: list[str] = []
        # A rig of one unit has no seam: its cross-unit figure does not apply (and passes).
        single_unit = len(service.rig.units) < 2
        for name, value in figures.items():
            limit = float(thresholds[name])
            not_applicable = name == "cross_unit_mm" and single_unit and value is None
            passed = not_applicable or (value is not None and value <= limit)
            judged[name] = {"value": value, "threshold": limit, "passed": passed}
            if value is None and not not_applicable:
                if name != "drift_mm" or stored_baseline is not None:
                    reasons.append(f"{name} was not measured")
            elif not passed:
                reasons.append(f"{name} {value:.3f} mm exceeds {limit:g} mm")
        if stored_baseline is None and not set_baseline:
            reasons.append(f"calibration {active.id} has no QA baseline: a physicist runs the "
                           "QA with baseline=true once after activating it")
        reasons += [p for p in measured.problems if not p.startswith("one unit only")]
        passed = not reasons
        now = self.clock()
        run_id = _new_id("qa", now)
        document: dict[str, Any] = {
            "format": "eyeserver.qa-run/1", "id": run_id, "created": _utc_text(now),
            "day": now.astimezone().date().isoformat(), "actor": actor,
            "calibration_id": active.id, "phantom": self.drawing.name,
            "phantom_drawing": {k: v for k, v in asdict(self.drawing).items()
                                if k != "name"},
            "capture_ids": [c.id for c in captures], "frames": frames,
            "passed": passed, "reasons": reasons, "figures": judged,
            "baseline": set_baseline and passed,
            "baseline_run_id": run_id if set_baseline and passed else
            None if stored_baseline is None else stored_baseline["run_id"],
            "drift_vectors_mm": measured.drift_vectors_mm,
            "details": measured.details, "problems": measured.problems}
        with self._write_lock:
            self._write("runs", run_id, document)
            if document["baseline"]:
                self._write("baselines", active.id, {
                    "calibration_id": active.id, "run_id": run_id, "created": document["created"],
                    "actor": actor, "drift_vectors_mm": measured.drift_vectors_mm,
                    "figures": {k: v["value"] for k, v in judged.items()}})
        service.store.add_audit_entries(actor, "qa_run", run_id, [{
            "passed": passed, "calibration_id": active.id, "baseline": document["baseline"],
            "reasons": reasons}])
        service.events.publish("qa.run", run_id=run_id, passed=passed,
                               calibration_id=active.id, baseline=document["baseline"])
        _log.info("QA run stored", extra={"run_id": run_id, "passed": passed, "actor": actor,
                                          "calibration_id": active.id})
        return document

    def runs(self, *, limit: int = 50, offset: int = 0, day: date | None = None
             ) -> tuple[list[dict[str, Any]], int]:
        """Stored runs, newest first (of one local day with ``day``), and how many there are."""
        every = self._read_all("runs")
        if day is not None:
            every = [r for r in every if r.get("day") == day.isoformat()]
        every.reverse()
        return every[offset:offset + limit], len(every)

    def get(self, run_id: str) -> dict[str, Any]:
        """One stored run; :class:`UnknownIdError` when there is none."""
        if not _SAFE_ID.fullmatch(run_id):
            raise UnknownIdError(run_id, "QA run")
        path = self._dir("runs") / f"{run_id}.json"
        if not path.is_file():
            raise UnknownIdError(run_id, "QA run")
        document: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
        return document

    def baseline(self, calibration_id: str) -> dict[str, Any] | None:
        """The QA baseline of a calibration, or None when it has none."""
        path = self._dir("baselines") / f"{calibration_id}.json"
        if not _SAFE_ID.fullmatch(calibration_id) or not path.is_file():
            return None
        baseline: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
        return baseline

    # --- the lockout --------------------------------------------------------------------------

    def _current_override(self, today: date, calibration_id: str | None
                          ) -> dict[str, Any] | None:
        overrides: list[dict[str, Any]] = self._read_all("overrides")
        for document in reversed(overrides):
            if document.get("day") == today.isoformat() and \
                    document.get("calibration_id") == calibration_id and \
                    document.get("withdrawn") is None:
                return dict(document)
        return None

    def status(self) -> dict[str, Any]:
        """Whether verification and tracking are locked now, and why.

        Returns
        -------
        dict
            ``required``, ``locked``, ``reason`` (null when not locked), ``day`` (local),
            ``calibration_id``, ``baseline_run_id``, ``last_pass`` and ``last_run`` of today
            with the active calibration (ids, or null), ``failures_since_pass``,
            ``max_consecutive_failures`` and ``override`` (the one in force, or null).
        """
        today = self._today()
        calibration_id = self._active_calibration_id()
        runs = [r for r in self._read_all("runs")
                if r.get("day") == today.isoformat() and r.get("calibration_id") == calibration_id]
        passes = [n for n, r in enumerate(runs) if r.get("passed")]
        failures = len(runs) - 1 - passes[-1] if passes else len(runs)
        baseline = None if calibration_id is None else self.baseline(calibration_id)
        override = self._current_override(today, calibration_id)
        limit = self.settings.max_consecutive_failures
        reason: str | None = None
        if calibration_id is None:
            reason = "no calibration is active"
        elif baseline is None:
            reason = (f"the active calibration {calibration_id} has no QA baseline: a physicist "
                      "runs the QA with baseline=true (POST /api/v1/qa/runs) with the QA "
                      "phantom in place")
        elif not passes:
            reason = f"today's QA ({today.isoformat()}) has not passed with calibration " \
                f"{calibration_id}"
            if runs:
                reason += f": the last run {runs[-1]['id']} failed (" + \
                    "; ".join(runs[-1].get("reasons", [])) + ")"
            else:
                reason += ": run it (POST /api/v1/qa/runs) with the QA phantom in place"
        elif failures >= limit:
            reason = (f"{failures} QA run(s) failed since today's pass (at most {limit - 1} "
                      f"allowed): the last, {runs[-1]['id']}, says: "
                      + "; ".join(runs[-1].get("reasons", [])))
        locked = self.settings.required and reason is not None and \
            (override is None or calibration_id is None)
        return {"required": self.settings.required, "locked": locked,
                "reason": reason if locked else None,
                "qa_reason": reason, "day": today.isoformat(), "calibration_id": calibration_id,
                "baseline_run_id": None if baseline is None else baseline["run_id"],
                "last_pass": runs[passes[-1]]["id"] if passes else None,
                "last_run": runs[-1]["id"] if runs else None,
                "failures_since_pass": failures, "max_consecutive_failures": limit,
                "override": override}

    def check(self, what: str) -> None:
        """Refuse ``what`` (``"position verification"``, ``"tracking"``) while locked.

        Raises
        ------
        QaLockedError
            The lockout holds; the message names the reason and the way out.
        """
        status = self.status()
        if status["locked"]:
            raise QaLockedError(f"{what} is locked by the daily QA: {status['reason']} (a "
                                "physicist may override it with a reason: POST "
                                "/api/v1/qa/override)")

    def override(self, *, actor: str, reason: str) -> dict[str, Any]:
        """Lift the lockout for the rest of today and the active calibration, with a reason;
        audited. Returns the new :meth:`status`.

        Raises
        ------
        ValueError
            The reason is blank.
        QaNotAllowedError
            Nothing is locked (QA not required, or it passed), or no calibration is active.
        """
        if not reason.strip():
            raise ValueError("an override needs a reason")
        with self.service.audit.failures(actor, "qa_override", "qa"), self._write_lock:
            status = self.status()
            if status["calibration_id"] is None:
                raise QaNotAllowedError("no calibration is active: there is nothing to measure "
                                        "with, override or not")
            if not status["locked"]:
                raise QaNotAllowedError("nothing to override: " + (
                    "the daily QA is not required (qa.required = false)"
                    if not status["required"] else "verification and tracking are not locked"))
            now = self.clock()
            override_id = _new_id("qa-override", now)
            end = datetime.combine(now.astimezone().date() + timedelta(days=1),
                                   datetime.min.time()).astimezone()
            document = {"id": override_id, "actor": actor, "reason": reason.strip(),
                        "created": _utc_text(now), "day": status["day"],
                        "calibration_id": status["calibration_id"],
                        "until": _utc_text(end), "lockout_reason": status["reason"],
                        "withdrawn": None}
            self._write("overrides", override_id, document)
            self.service.store.add_audit_entries(actor, "qa_override", override_id, [{
                "reason": document["reason"], "calibration_id": document["calibration_id"],
                "day": document["day"], "lockout_reason": document["lockout_reason"]}])
        self.service.events.publish("qa.override", override_id=override_id, actor=actor)
        _log.warning("QA lockout overridden", extra={"actor": actor, "reason": reason,
                                                     "override_id": override_id})
        return self.status()

    def withdraw_override(self, *, actor: str) -> dict[str, Any]:
        """End the override in force (audited); returns the new :meth:`status`.

        Raises
        ------
        UnknownIdError
            No override is in force.
        """
        with self.service.audit.failures(actor, "qa_override_withdrawn", "qa"), \
                self._write_lock:
            current = self._current_override(self._today(), self._active_calibration_id())
            if current is None:
                raise NoQaOverrideError()
            current["withdrawn"] = {"actor": actor, "time": _utc_text(self.clock())}
            self._write("overrides", current["id"], current)
            self.service.store.add_audit_entries(actor, "qa_override_withdrawn", current["id"],
                                                 [{"calibration_id": current["calibration_id"]}])
        # Every console shows the override in force: each must hear that it ended.
        self.service.events.publish("qa.override_withdrawn", override_id=current["id"],
                                    actor=actor)
        _log.warning("QA override withdrawn", extra={"actor": actor,
                                                     "override_id": current["id"]})
        return self.status()

    def overrides(self, day: date | None = None) -> list[dict[str, Any]]:
        """Overrides given (of one local day with ``day``), newest first."""
        every = self._read_all("overrides")
        if day is not None:
            every = [o for o in every if o.get("day") == day.isoformat()]
        return list(reversed(every))

    # --- trends and the report ----------------------------------------------------------------

    def trends(self, days: int = 90) -> dict[str, Any]:
        """Every figure of the runs of the last ``days`` days, oldest first.

        Returns
        -------
        dict
            ``days``, ``since`` (UTC) and ``figures``: per figure its ``description``,
            ``unit`` (mm), ``threshold`` (the current one) and ``points``, each ``run_id``,
            ``created``, ``day``, ``calibration_id``, ``value`` (null: not measured),
            ``threshold`` (the run's), ``passed`` and ``baseline``.
        """
        if days < 1:
            raise ValueError(f"days must be at least 1, not {days}")
        since = self.clock() - timedelta(days=days)
        runs = [r for r in self._read_all("runs")
                if datetime.fromisoformat(r["created"].replace("Z", "+00:00")) >= since]
        thresholds = self.settings.thresholds.model_dump()
        figures = {}
        for name, description in FIGURES.items():
            points = []
            for run in runs:
                judged = run["figures"].get(name, {})
                points.append({"run_id": run["id"], "created": run["created"],
                               "day": run["day"], "calibration_id": run["calibration_id"],
                               "value": judged.get("value"), "threshold": judged.get("threshold"),
                               "passed": bool(judged.get("passed")),
                               "baseline": bool(run.get("baseline"))})
            figures[name] = {"description": description, "unit": "mm",
                             "threshold": thresholds[name], "points": points}
        return {"days": days, "since": _utc_text(since), "figures": figures}

    def trend_png(self, figure: str, days: int = 90) -> bytes:
        """A PNG of one figure's trend: each run's value against its time, the threshold as a
        line, failed runs in red, baselines as squares, calibration changes as dotted lines.

        Raises
        ------
        KeyError
            ``figure`` is not one of :data:`~eyeserver.service.qa_figures.FIGURES`.
        """
        if figure not in FIGURES:
            raise KeyError(figure)
        trends = self.trends(days)
        return _trend_png(figure, trends["figures"][figure], days, trends["since"],
                          _utc_text(self.clock()))

    def report_html(self, day: date) -> str:
        """The day's QA report as a self-contained, printable HTML page: every run of the day
        with its figures against their thresholds, the lockout now, the overrides of the day
        and each figure's 30-day trend."""
        runs, _ = self.runs(limit=10_000, day=day)
        runs.reverse()
        overrides = self.overrides(day)
        status = self.status() if day == self._today() else None
        return _report_html(day, runs, overrides, status, self.drawing,
                            {name: self.trend_png(name, 30) for name in FIGURES})


def _trend_png(figure: str, series: dict[str, Any], days: int, since: str, now: str) -> bytes:
    """Draw one figure's trend over ``since``…``now`` (UTC texts) with matplotlib's object API
    (Agg; no pyplot state)."""
    from matplotlib.figure import Figure  # imported here: a second's import, for pictures only

    points = series["points"]
    fig = Figure(figsize=(7.0, 2.6), dpi=100)
    ax = fig.subplots()
    # numpy's datetime64 (UTC, naive): matplotlib's date axis takes them as they are.
    times = [np.datetime64(p["created"].removesuffix("Z"), "ms") for p in points]
    measured = [(t, p) for t, p in zip(times, points, strict=True) if p["value"] is not None]
    for passed, colour in ((True, "tab:blue"), (False, "tab:red")):
        chosen = [(t, p["value"]) for t, p in measured if p["passed"] == passed]
        if chosen:
            ax.plot(np.asarray([t for t, _ in chosen]), [v for _, v in chosen], "o", color=colour,
                    ms=4,
                    label="passed" if passed else "failed")
    baselines = [(t, p["value"]) for t, p in measured if p["baseline"]]
    if baselines:
        ax.plot(np.asarray([t for t, _ in baselines]), [v for _, v in baselines], "s", mfc="none",
                color="black", ms=8, label="baseline")
    if measured:
        ax.plot(np.asarray([t for t, _ in measured]), [p["value"] for _, p in measured], "-",
                color="0.6", lw=0.8, zorder=0)
    ax.axhline(series["threshold"], color="tab:red", ls="--", lw=1,
               label=f"threshold {series['threshold']:g} mm")
    for before, after, moment in zip(points, points[1:], times[1:], strict=False):
        if before["calibration_id"] != after["calibration_id"]:
            ax.axvline(moment, color="0.4", ls=":", lw=1)  # type: ignore[arg-type]
    ax.set_ylim(bottom=0)
    # The period asked for: a single run would otherwise stretch the date axis over years.
    start, end = (np.datetime64(t.removesuffix("Z"), "ms") for t in (since, now))
    ax.set_xlim(start, end + (end - start) / 40)  # type: ignore[arg-type]
    ax.set_ylabel("mm")
    ax.set_title(f"{figure}: {series['description']} (last {days} days)", fontsize=8)
    ax.tick_params(labelsize=7)
    if not points:
        ax.text(0.5, 0.5, "no QA run in this period", transform=ax.transAxes, ha="center")
    ax.legend(fontsize=7, loc="upper left")
    fig.autofmt_xdate()
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


_STYLE = """
body { font-family: sans-serif; font-size: 10pt; margin: 1.5cm; color: #000; }
h1 { font-size: 15pt; } h2 { font-size: 12pt; margin-top: 1.2em; }
table { border-collapse: collapse; margin: 0.4em 0; }
td, th { border: 1px solid #888; padding: 2px 6px; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.pass { color: #064; font-weight: bold; } .fail { color: #a00; font-weight: bold; }
img { width: 16cm; display: block; page-break-inside: avoid; }
.run { page-break-inside: avoid; }
@media print { body { margin: 0; } }
"""


def _verdict(passed: bool) -> str:
    return '<span class="pass">PASS</span>' if passed else '<span class="fail">FAIL</span>'


def _number(value: object) -> str:
    return "—" if not isinstance(value, int | float) else f"{value:.4f}"


def _report_html(day: date, runs: Sequence[dict[str, Any]],
                 overrides: Sequence[dict[str, Any]], status: dict[str, Any] | None,
                 drawing: PhantomDrawing, plots: dict[str, bytes]) -> str:
    """The page of :meth:`DailyQa.report_html` (every string escaped)."""
    e = html.escape
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>eyeserver "
             f"daily QA {e(day.isoformat())}</title><style>{_STYLE}</style></head><body>",
             f"<h1>eyeserver daily QA — {e(day.isoformat())}</h1>",
             f"<p>Phantom: {e(drawing.name)}; ball centre {e(str(list(drawing.centre_mm)))} mm, "
             f"radius {drawing.radius_mm:g} mm, {len(drawing.fiducials_mm)} dots "
             "(its drawing, docs/qa.md).</p>"]
    if status is not None:
        state = "LOCKED: " + e(str(status["reason"])) if status["locked"] else (
            "not locked" + (" (override in force)" if status["override"] else "")
            + ("" if status["required"] else " (QA not required by the settings)"))
        parts.append(f"<p>Verification and tracking now: <b>{state}</b>; calibration "
                     f"{e(str(status['calibration_id']))}, baseline "
                     f"{e(str(status['baseline_run_id']))}.</p>")
    parts.append(f"<h2>Runs ({len(runs)})</h2>")
    if not runs:
        parts.append("<p>No QA run on this day.</p>")
    for run in runs:
        parts.append(f'<div class="run"><h3>{e(run["id"])} — {_verdict(run["passed"])}'
                     f'{" — baseline" if run.get("baseline") else ""}</h3>')
        parts.append(f"<p>{e(run['created'])} by {e(run['actor'])}; calibration "
                     f"{e(run['calibration_id'])}; {run['frames']} frames; baseline compared "
                     f"with: {e(str(run.get('baseline_run_id')))}</p>")
        parts.append("<table><tr><th>figure</th><th>value (mm)</th><th>threshold (mm)</th>"
                     "<th></th><th>what it is</th></tr>")
        for name, judged in run["figures"].items():
            parts.append(f"<tr><td>{e(name)}</td><td class=\"num\">"
                         f"{_number(judged.get('value'))}</td><td class=\"num\">"
                         f"{_number(judged.get('threshold'))}</td>"
                         f"<td>{_verdict(bool(judged.get('passed')))}</td>"
                         f"<td>{e(FIGURES.get(name, ''))}</td></tr>")
        parts.append("</table>")
        if run["reasons"]:
            parts.append("<ul>" + "".join(f"<li>{e(r)}</li>" for r in run["reasons"]) + "</ul>")
        parts.append("</div>")
    parts.append(f"<h2>Overrides ({len(overrides)})</h2>")
    if not overrides:
        parts.append("<p>None.</p>")
    for override in overrides:
        withdrawn = override.get("withdrawn")
        parts.append(f"<p>{e(override['created'])} by {e(override['actor'])} for calibration "
                     f"{e(str(override['calibration_id']))}: “{e(override['reason'])}” (locked "
                     f"because: {e(str(override['lockout_reason']))})"
                     + (f"; withdrawn {e(withdrawn['time'])} by {e(withdrawn['actor'])}"
                        if withdrawn else "") + "</p>")
    parts.append("<h2>Trends (30 days)</h2>")
    for name, png in plots.items():
        encoded = base64.b64encode(png).decode("ascii")
        parts.append(f'<img alt="{e(name)} trend" src="data:image/png;base64,{encoded}">')
    parts.append("<p>Signature: ______________________ &nbsp; Date: ____________</p>")
    parts.append("</body></html>")
    return "\n".join(parts)
