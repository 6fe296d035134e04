"""``GET /api/v1/audit``: the audit file's newest entries (physicists only).

The entries are the lines of the append-only audit file (:mod:`eyeserver.service.audit`): who
(name and role) did what to which item, when, with what detail (patient ids hashed) and with
what outcome.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from eyeserver.api.auth import PhysicistDep
from eyeserver.api.deps import ServiceDep

__all__ = ["AuditLine", "AuditList", "router"]

router = APIRouter(tags=["audit"])


class AuditLine(BaseModel):
    """One audited action, as its line in the audit file says."""

    time: str = Field(description="UTC, ISO 8601 with milliseconds.")
    seq: int | None = Field(default=None, description="The store's audit row; null for a "
                            "failed action, which changed nothing.")
    actor: str = Field(description="The token holder's name, or the daemon's own actor "
                       "(eyeserver, retention).")
    role: str = Field(description="operator, physicist, or system for the daemon's actors.")
    action: str = Field(examples=["delete_capture"])
    target: str = Field(description="The capture, calibration or device acted on.")
    detail: dict[str, Any] = Field(default_factory=dict,
                                   description="What else was recorded (patient ids hashed).")
    outcome: Literal["ok", "error", "denied"]


class AuditList(BaseModel):
    """The newest audit entries, newest first."""

    items: list[AuditLine]


@router.get("/audit", summary="Who did what (physicists only)")
async def list_audit(
    service: ServiceDep, caller: PhysicistDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Entries to return.")] = 100,
) -> AuditList:
    """The newest ``limit`` entries of the audit file, newest first."""
    entries = await run_in_threadpool(service.audit.entries, limit)
    return AuditList(items=[AuditLine.model_validate(entry) for entry in entries])
