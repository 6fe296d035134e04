"""What the pydantic models share: numbers are numbers; files and specs take no unknown keys."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, model_validator

__all__ = ["NumbersOnly", "StrictModel"]


def _has_bool(value: Any) -> bool:
    if isinstance(value, bool):
        return True
    return isinstance(value, list | tuple) and any(_has_bool(item) for item in value)


class NumbersOnly(BaseModel):
    """A model whose fields hold numbers (or lists of them), never ``true``/``false``.

    pydantic reads a JSON ``false`` as the number 0 where a float is expected: a rotation of
    ``[0, 0, false]`` was accepted, against the schema (the API fuzz, issue 35). Strict floats
    would also refuse a JSON array for a tuple, so the booleans are refused here, before
    validation, at any depth of the model's own fields (a nested model checks its own).
    """

    @model_validator(mode="before")
    @classmethod
    def _no_booleans(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, value in data.items():
                if _has_bool(value):
                    raise ValueError(f"{name}: a number is needed, not true or false")
        return data


class StrictModel(BaseModel):
    """A frozen model that refuses unknown keys: a misspelt key in a rig, room or settings file
    is an error naming it, not a default silently kept. Strict about keys, not about types
    (this is not pydantic's ``strict`` mode: a JSON integer still fills a float)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
