"""``/api/v1/jobs``: long operations (batch reconstructions, calibration solves) as jobs.

A job is queued at once (``202`` with its id) and runs on the daemon's jobs thread; poll
``GET /jobs/{id}`` or watch ``job.progress`` and ``job.state`` on ``/api/v1/ws/events``. Jobs are
kept in memory: a restart forgets them (what they finished stays in the store).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import OperatorDep
from eyeserver.api.deps import ServiceDep
from eyeserver.api.schemas import ErrorResponse
from eyeserver.errors import EyeserverError
from eyeserver.service.core import NoActiveCalibrationError, Service
from eyeserver.service.jobs import Job, JobContext, JobWork
from eyeserver.service.storage import is_capture_id

__all__ = ["JobList", "JobResponse", "ReconstructionBatch", "job_response", "router"]

router = APIRouter(tags=["jobs"])

_NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "No such job (or forgotten: jobs are kept "
          "in memory, the newest 200 finished ones)."}}


class JobResponse(BaseModel):
    """One job."""

    id: str = Field(examples=["job-3f9a0c2b71de"])
    kind: str = Field(description="What it does: reconstructions, stereo-solve, "
                      "phase-height-solve.", examples=["reconstructions"])
    actor: str = Field(description="Who asked for it.")
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    progress: float = Field(ge=0, le=1, description="How far it got, 0 to 1.")
    message: str = Field(description="What it is doing, or did last.")
    result: dict[str, Any] | None = Field(
        description="What it produced once succeeded; for a failed or cancelled job, what it "
        "had finished (each item complete).")
    error: str | None = Field(description="Why it failed or was cancelled.")
    created: str
    started: str | None
    finished: str | None


class JobList(BaseModel):
    """The jobs remembered, newest first."""

    items: list[JobResponse]


class ReconstructionBatch(BaseModel):
    """Captures to reconstruct, in order, with the active calibration."""

    model_config = ConfigDict(extra="forbid")

    capture_ids: Annotated[list[str], Field(min_length=1, max_length=1000)] = Field(
        description="Capture ids; each reconstruction is kept beside its capture as soon as it "
        "is done.", examples=[["cap-20261123T151200123Z-a1b2"]])


def job_response(job: Job) -> JobResponse:
    """The API's view of a job snapshot."""
    return JobResponse(id=job.id, kind=job.kind, actor=job.actor, state=job.state,
                       progress=job.progress, message=job.message, result=job.result,
                       error=job.error, created=job.created, started=job.started,
                       finished=job.finished)


@router.get("/jobs", summary="List jobs")
async def list_jobs(service: ServiceDep) -> JobList:
    """Every job of this run the daemon remembers, newest first."""
    return JobList(items=[job_response(j) for j in service.jobs.list_jobs()])


@router.get("/jobs/{job_id}", summary="One job", responses=_NOT_FOUND)
async def get_job(job_id: str, service: ServiceDep) -> JobResponse:
    """A job's state, progress, result or reason of failure."""
    return job_response(service.jobs.get(job_id))


@router.post("/jobs/{job_id}/cancel", summary="Cancel a job", responses=_NOT_FOUND)
async def cancel_job(job_id: str, service: ServiceDep, caller: OperatorDep) -> JobResponse:
    """Ask a job to stop: a queued job is cancelled at once, a running one at its next step
    (what it finished is kept). A finished job is left as it is."""
    return job_response(service.jobs.cancel(job_id))


def _reconstructions(service: Service, capture_ids: list[str]) -> JobWork:
    def work(context: JobContext) -> dict[str, Any]:
        done: list[dict[str, Any]] = []
        failed: list[dict[str, Any]] = []
        for n, capture_id in enumerate(capture_ids):
            context.check_cancelled()
            context.progress(n / len(capture_ids),
                             f"reconstructing {capture_id} ({n + 1}/{len(capture_ids)})",
                             partial={"done": done, "failed": failed})
            try:
                summary = service.reconstruct(capture_id)
            except EyeserverError as exc:  # one bad capture does not stop the batch
                failed.append({"capture_id": capture_id, "error": str(exc)})
                continue
            done.append({"capture_id": capture_id, "points": summary["points"],
                         "calibration_id": summary["calibration_id"]})
        context.progress(1.0, f"{len(done)} reconstructed, {len(failed)} failed",
                         partial={"done": done, "failed": failed})
        return {"done": done, "failed": failed}
    return work


@router.post("/jobs/reconstructions", status_code=202, summary="Reconstruct captures in a batch",
             responses={409: {"model": ErrorResponse, "description": "No calibration is "
                              "active."},
                        422: {"model": ErrorResponse, "description": "Not capture ids."},
                        503: {"model": ErrorResponse, "description": "The job queue is full."}})
async def reconstruct_batch(batch: ReconstructionBatch, service: ServiceDep,
                            caller: OperatorDep) -> JobResponse:
    """Queue a job that reconstructs each capture with the active calibration, in order,
    reporting progress after each; a capture that cannot be reconstructed is listed under
    ``failed`` with its reason and the batch goes on. Cancelling stops it between captures."""
    bad = [c for c in batch.capture_ids if not is_capture_id(c)]
    if bad:
        raise HTTPException(422, f"capture_ids: not capture ids: {', '.join(bad[:5])}")
    if await run_in_threadpool(service.store.active_calibration) is None:
        raise NoActiveCalibrationError("no calibration is active: activate one "
                                       "(POST /api/v1/calibrations/{id}/activate)")
    job = await run_in_threadpool(lambda: service.jobs.submit(
        "reconstructions", _reconstructions(service, list(batch.capture_ids)),
        actor=caller.name))
    return job_response(job)
