"""Deleting measurements older than ``retention_days``.

With ``retention_days`` set, :func:`purge_expired` runs at start-up and then every
:data:`RETENTION_INTERVAL_S` (:mod:`eyeserver.service.operations`). It deletes every
*measurement* capture created before ``now - retention_days`` through
:meth:`~eyeserver.service.core.Service.delete_capture`, so each deletion is audited like a
person's, with the actor :data:`RETENTION_ACTOR` and the rule as its reason. Calibration captures
(chessboard, plate, reference) are kept: they are no patient data, and they document how the
calibrations in use were made. So are the measurements that are a stored result's evidence (a
pose measurement's, a captured reference pose's:
:meth:`~eyeserver.service.core.Service.evidence_captures`): they stay as long as the result.
Without ``retention_days`` nothing is ever deleted automatically.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING

from eyeserver.errors import EyeserverError
from eyeserver.service.storage import UnknownIdError

if TYPE_CHECKING:
    from eyeserver.service.core import Service

__all__ = ["RETAINED_KIND", "RETENTION_ACTOR", "RETENTION_INTERVAL_S", "purge_expired"]

RETENTION_ACTOR = "retention"
"""The actor recorded in the audit for deletions by the retention rule."""

RETENTION_INTERVAL_S = 3600.0
"""Seconds between two runs of the retention rule."""

RETAINED_KIND = "measurement"
"""The only kind of capture the retention rule deletes."""

_PAGE = 500

_log = logging.getLogger(__name__)


def purge_expired(service: Service, retention_days: float,
                  clock: Callable[[], datetime] | None = None) -> list[str]:
    """Delete the measurements created more than ``retention_days`` before ``clock()``.

    Parameters
    ----------
    service : Service
        An open service.
    retention_days : float
        The age, in days, from which a measurement is deleted; more than 0.
    clock : callable, optional
        The current time, time zone-aware (default: the system clock); tests pass their own.

    Returns
    -------
    list of str
        The ids deleted, newest first. A capture that cannot be deleted is logged and left for
        the next run.
    """
    if not retention_days > 0:
        raise ValueError(f"retention_days must be more than 0, not {retention_days!r}")
    now = (clock or _utc_now)()
    cutoff = now - timedelta(days=retention_days)
    # Collected before deleting, so the paging is not shifted by the deletions.
    expired: list[str] = []
    while True:
        page, total = service.store.list_captures(limit=_PAGE, offset=len(expired),
                                                  until=cutoff, kind=RETAINED_KIND)
        expired += [record.id for record in page]
        if not page or len(expired) >= total:
            break
    evidence = service.evidence_captures()
    kept = [capture_id for capture_id in expired if capture_id in evidence]
    reason = f"retention: older than {retention_days:g} days (before {cutoff.isoformat()})"
    deleted = []
    for capture_id in (c for c in expired if c not in evidence):
        try:
            # The evidence taken once for the run (it reads every captured reference).
            service.delete_capture(capture_id, actor=RETENTION_ACTOR, reason=reason,
                                   evidence=evidence)
        except UnknownIdError:
            continue  # deleted by someone else meanwhile
        except EyeserverError as exc:
            _log.error("retention could not delete a capture", extra={
                "capture_id": capture_id, "reason": str(exc)})
            continue
        deleted.append(capture_id)
    if deleted or kept:
        _log.info("retention deleted captures", extra={
            "count": len(deleted), "kept_as_evidence": len(kept),
            "retention_days": retention_days})
    return deleted


def _utc_now() -> datetime:
    return datetime.now(UTC)
