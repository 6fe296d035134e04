"""Pydantic models of the API's request and response bodies (they make the OpenAPI schema)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

__all__ = ["ErrorResponse", "HealthResponse"]


class HealthResponse(BaseModel):
    """The daemon is up and answering."""

    status: Literal["ok"] = Field(
        description="Always 'ok': any answer at all means the daemon is up."
    )
    version: str = Field(description="Version of the running eyeserver.", examples=["0.1.0"])


class ErrorResponse(BaseModel):
    """Body of every error the API reports on purpose."""

    detail: str = Field(
        description="Why the request failed, in words meant for a person.",
        examples=["cam-left: no frame within 500 ms"],
    )
