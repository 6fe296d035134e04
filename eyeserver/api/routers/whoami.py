"""``GET /api/v1/whoami``: whose token this is and what its role may do.

A client shows or hides what the caller's role may not do from this answer (the browser
console, issue 39) rather than by trying a physicist's route and reading a 403, which would
also leave a ``denied`` line in the audit trail. The daemon still checks every request itself.
"""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from eyeserver.api.auth import OperatorDep
from eyeserver.config import ROLES, Role

__all__ = ["WhoAmIResponse", "router"]

router = APIRouter(tags=["auth"])


class WhoAmIResponse(BaseModel):
    """The holder of the request's token."""

    name: str = Field(description="The token holder's name, as the audit trail records it.",
                      examples=["dr-weber"])
    role: Role = Field(description="The token's role.", examples=["physicist"])
    roles: list[Role] = Field(description="Every role the token may act as: its own and the "
                              "lower ones (a physicist may do what an operator may).",
                              examples=[["operator", "physicist"]])


@router.get("/whoami", summary="Whose token is this?")
async def whoami(caller: OperatorDep) -> WhoAmIResponse:
    """The token holder's name and role (any valid token; 401 otherwise)."""
    return WhoAmIResponse(name=caller.name, role=caller.role,
                          roles=[role for role in ROLES if caller.may(role)])
