"""``/api/v1/qa``: the daily QA, its lockout, its history and the day's report.

``POST /qa/runs`` captures the QA phantom (eye phantom 1 at its QA position; docs/qa.md) with
every unit, measures it against the phantom's drawing with the active calibration and judges
each figure against its threshold (:mod:`eyeserver.service.qa`). Any token may run the daily
QA; setting a calibration's QA baseline (``"baseline": true``) and overriding the lockout need
the physicist role. ``GET /qa/status`` says whether position verification and tracking are
locked and why; while they are, ``POST /pose/measure`` and ``POST /tracking/start`` answer 409
with that reason (:func:`qa_gate`). ``GET /qa/trends`` gives every figure's history as data,
``GET /qa/trends/{figure}.png`` as a plot, ``GET /qa/report`` a day's printable HTML report.

The daily QA object lives in ``app.state.qa``, made on first use for the running service.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from datetime import date
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import OperatorDep, PhysicistDep
from eyeserver.api.schemas import ErrorResponse
from eyeserver.config import Settings
from eyeserver.errors import StateConflictError
from eyeserver.service.core import Service
from eyeserver.service.qa import DailyQa

__all__ = ["DailyQaDep", "get_daily_qa", "qa_gate", "router"]

router = APIRouter(prefix="/qa", tags=["quality assurance"])

Figure = Literal["localisation_mm", "surface_mm", "fiducial_mm", "cross_unit_mm",
                 "static_noise_mm", "drift_mm"]
"""The figures of :data:`~eyeserver.service.qa_figures.FIGURES` (tests/test_qa.py checks)."""


async def get_daily_qa(request: Request) -> DailyQa:
    """The running daemon's daily QA (409 while the daemon is not running).

    Made here, on the event loop (so never twice), the first time a request needs it for the
    service the lifespan opened; it holds nothing but its settings and the data directory.
    """
    service = getattr(request.app.state, "service", None)
    if not isinstance(service, Service):
        raise StateConflictError("the daemon's service is not running")
    qa = getattr(request.app.state, "qa", None)
    if not isinstance(qa, DailyQa) or qa.service is not service:
        settings: Settings = request.app.state.settings
        qa = DailyQa(service, settings.qa, settings.data_dir)
        request.app.state.qa = qa
    return qa


DailyQaDep = Annotated[DailyQa, Depends(get_daily_qa)]


def qa_gate(what: str) -> Callable[[DailyQa], Coroutine[Any, Any, None]]:
    """A dependency that refuses ``what`` with 409 (the reason) while the daily QA locks it."""
    async def gate(qa: DailyQaDep) -> None:
        await run_in_threadpool(qa.check, what)

    gate.__name__ = f"qa_gate_{what.replace(' ', '_')}"
    return gate


RUN_ID_PATTERN = r"^[A-Za-z0-9._-]+$"
"""What a QA run id may hold (they are ``qa-<time>-<hex>``): never a path's separator."""

QA_LOCKED = ("the daily QA locks it (today's QA has not passed with the active calibration, "
             "it has no QA baseline, or runs failed since the pass); the reason says which")
"""How the 409 of a locked route is described in the OpenAPI document."""


# --- schemas ----------------------------------------------------------------------------------


class QaRunRequest(BaseModel):
    """A QA run: the QA phantom must stand at its QA position."""

    model_config = ConfigDict(extra="forbid")

    baseline: bool = Field(False, description="Make this run the active calibration's QA "
                           "baseline if every other figure passes (physicists only); needed "
                           "once after every new calibration.")
    frames: int | None = Field(None, ge=2, le=20, description="Captures of the still phantom "
                               "(default: the setting qa.frames, 4).")


class QaFigure(BaseModel):
    """One figure of a run against its threshold."""

    value: float | None = Field(description="mm; null when it could not be measured (then it "
                                "fails).")
    threshold: float = Field(description="The pass limit when the run was made, mm.")
    passed: bool


class QaRun(BaseModel):
    """A stored QA run."""

    model_config = ConfigDict(extra="allow")

    id: str = Field(description="qa-<UTC time>-<hex>; sorts in order of creation.",
                    examples=["qa-20261205T071502123Z-9c1e"])
    created: str = Field(description="UTC, ISO 8601.")
    day: str = Field(description="The daemon host's local date the run counts for.")
    actor: str
    calibration_id: str = Field(description="The calibration it measured with.")
    phantom: str
    capture_ids: list[str] = Field(description="The captures of the phantom (ordinary "
                                   "measurement captures).")
    frames: int
    passed: bool = Field(description="Every figure within its threshold, and the calibration "
                         "has a QA baseline.")
    reasons: list[str] = Field(description="Why it failed (empty when it passed).")
    figures: dict[str, QaFigure] = Field(description="localisation_mm, surface_mm, "
                                         "fiducial_mm, cross_unit_mm, static_noise_mm, "
                                         "drift_mm (docs/qa.md).")
    baseline: bool = Field(description="This run became the calibration's QA baseline.")
    baseline_run_id: str | None = Field(description="The baseline the drift was measured "
                                        "against (this run's own id when it is one).")
    drift_vectors_mm: dict[str, list[float]] = Field(description="Per unit what the drift is "
                                                     "measured with: its dots' mean miss "
                                                     "against the phantom placed by all units "
                                                     "(one unit: its ball centre), WCS, mm.")
    details: dict[str, Any] = Field(description="How each figure was measured: points, dots "
                                    "matched and their residuals, placement, per-camera noise.")
    problems: list[str] = Field(description="What could not be measured.")


class QaRunList(BaseModel):
    """One page of QA runs, newest first."""

    items: list[QaRun]
    total: int
    limit: int
    offset: int


class QaOverrideRequest(BaseModel):
    """Why the lockout is overridden (kept in the audit and the day's report)."""

    model_config = ConfigDict(extra="forbid")

    reason: str = Field(min_length=3, max_length=1000, pattern=r"\S",
                        examples=["phantom damaged; QA by X-ray clip check, see log 12/05"])


class QaOverride(BaseModel):
    """An override of the lockout."""

    id: str
    actor: str
    reason: str
    created: str
    day: str
    calibration_id: str | None
    until: str = Field(description="When it ends by itself: the end of its day (UTC).")
    lockout_reason: str | None = Field(description="What it overrode.")
    withdrawn: dict[str, Any] | None = Field(description="actor and time, once withdrawn.")


class QaStatus(BaseModel):
    """Whether position verification and tracking are locked, and why."""

    required: bool = Field(description="The setting qa.required.")
    locked: bool = Field(description="Verification and tracking answer 409.")
    reason: str | None = Field(description="Why they are locked (null when not).")
    qa_reason: str | None = Field(description="What the QA lacks today even when an override "
                                  "(or qa.required = false) lifts the lockout.")
    day: str = Field(description="Today, the daemon host's local date.")
    calibration_id: str | None
    baseline_run_id: str | None = Field(description="The active calibration's QA baseline.")
    last_pass: str | None = Field(description="Today's last passing run with the active "
                                  "calibration.")
    last_run: str | None
    failures_since_pass: int
    max_consecutive_failures: int
    override: QaOverride | None = Field(description="The override in force.")


class QaTrendPoint(BaseModel):
    """One run's value of a figure."""

    run_id: str
    created: str
    day: str
    calibration_id: str
    value: float | None
    threshold: float | None
    passed: bool
    baseline: bool


class QaTrend(BaseModel):
    """One figure's history."""

    description: str
    unit: str
    threshold: float = Field(description="The current threshold.")
    points: list[QaTrendPoint] = Field(description="Oldest first.")


class QaTrends(BaseModel):
    """Every figure's history over the last ``days`` days."""

    days: int
    since: str
    figures: dict[str, QaTrend]


# --- routes -----------------------------------------------------------------------------------


@router.post("/runs", status_code=201, summary="Run the daily QA",
             responses={403: {"model": ErrorResponse, "description": "A baseline asked for "
                              "without the physicist role."},
                        409: {"model": ErrorResponse, "description": "No active calibration, "
                              "another QA run is under way, or the daemon is busy."},
                        503: {"model": ErrorResponse, "description": "A device failed, or a "
                              "queue is full."}})
async def run_qa(qa: DailyQaDep, caller: OperatorDep,
                 body: QaRunRequest | None = None) -> QaRun:
    """Capture the QA phantom (eye phantom 1 at its QA position: ball centre on the isocentre,
    base plate facing +Z) with every unit ``frames`` times, measure it with the active
    calibration against the phantom's drawing and judge every figure against its threshold.
    The run is stored, audited and answered whether it passed or failed (``passed``,
    ``reasons``). Takes seconds."""
    request = body or QaRunRequest()
    if request.baseline and not caller.may("physicist"):
        raise HTTPException(403, "only a physicist may set a QA baseline")
    document = await run_in_threadpool(lambda: qa.run(
        actor=caller.name, baseline=request.baseline, may_set_baseline=caller.may("physicist"),
        frames=request.frames))
    return QaRun.model_validate(document)


@router.get("/runs", summary="QA history")
async def list_runs(
    qa: DailyQaDep,
    day: Annotated[date | None, Query(description="Only this local day's runs.")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
) -> QaRunList:
    """Stored QA runs, newest first."""
    items, total = await run_in_threadpool(lambda: qa.runs(limit=limit, offset=offset,
                                                           day=day))
    return QaRunList(items=[QaRun.model_validate(i) for i in items], total=total, limit=limit,
                     offset=offset)


@router.get("/runs/{run_id}", summary="One QA run",
            responses={404: {"model": ErrorResponse, "description": "No such run."}})
async def get_run(run_id: Annotated[str, Path(pattern=RUN_ID_PATTERN, max_length=80)],
                  qa: DailyQaDep) -> QaRun:
    """A stored QA run with every figure and how it was measured."""
    return QaRun.model_validate(await run_in_threadpool(qa.get, run_id))


@router.get("/status", summary="The QA lockout")
async def get_status(qa: DailyQaDep) -> QaStatus:
    """Whether position verification and tracking are locked by the daily QA now, and why."""
    return QaStatus.model_validate(await run_in_threadpool(qa.status))


@router.post("/override", summary="Override the QA lockout (physicists only)",
             responses={409: {"model": ErrorResponse, "description": "Nothing is locked, or "
                              "no calibration is active."}})
async def post_override(body: QaOverrideRequest, qa: DailyQaDep, caller: PhysicistDep,
                        ) -> QaStatus:
    """Lift the lockout for the rest of today (the host's local day) and the active
    calibration, with a reason; audited and shown in the day's report. Another calibration
    activated ends it."""
    return QaStatus.model_validate(await run_in_threadpool(
        lambda: qa.override(actor=caller.name, reason=body.reason)))


@router.delete("/override", summary="Withdraw the QA override (physicists only)",
               responses={404: {"model": ErrorResponse, "description": "No override is in "
                                "force."}})
async def delete_override(qa: DailyQaDep, caller: PhysicistDep) -> QaStatus:
    """End the override in force (audited): the lockout holds again if its reason does."""
    return QaStatus.model_validate(await run_in_threadpool(
        lambda: qa.withdraw_override(actor=caller.name)))


@router.get("/trends", summary="Every QA figure's history, as data")
async def get_trends(
    qa: DailyQaDep,
    days: Annotated[int, Query(ge=1, le=3660, description="How far back.")] = 90,
) -> QaTrends:
    """Per figure: what it is, its threshold and every run's value (oldest first)."""
    return QaTrends.model_validate(await run_in_threadpool(qa.trends, days))


@router.get("/trends/{figure}.png", summary="One QA figure's history, as a plot",
            response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "Values against "
                             "time, the threshold dashed, failures red, baselines squared, "
                             "calibration changes dotted."}})
async def get_trend_png(
    figure: Annotated[Figure, Path(description="The figure's name.")], qa: DailyQaDep,
    days: Annotated[int, Query(ge=1, le=3660)] = 90,
) -> Response:
    """A PNG of one figure's trend."""
    png = await run_in_threadpool(qa.trend_png, figure, days)
    return Response(png, media_type="image/png")


@router.get("/report", summary="A day's QA report (printable HTML)", response_class=Response,
            responses={200: {"content": {"text/html": {}}, "description": "A self-contained "
                             "page: runs, figures against thresholds, overrides, trends."}})
async def get_report(
    qa: DailyQaDep,
    day: Annotated[date | None, Query(description="The local day (default: today).")] = None,
) -> Response:
    """Every run of the day with its figures against their thresholds, the lockout, the day's
    overrides and 30-day trend plots, as one HTML page to print or archive."""
    def render() -> str:
        return qa.report_html(day or qa.clock().astimezone().date())

    return Response(await run_in_threadpool(render), media_type="text/html; charset=utf-8")
