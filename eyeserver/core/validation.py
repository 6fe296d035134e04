"""What the pydantic models share: numbers are numbers; files and specs take no unknown keys; a
settings file (TOML, or JSON by extension) read and validated with its errors naming the file
and the field."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError, model_validator

from eyeserver.errors import FormatError

__all__ = ["NumbersOnly", "StrictModel", "read_table", "validated"]

_M = TypeVar("_M", bound=BaseModel)


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


def read_table(path: str | Path, what: str) -> dict[str, Any]:
    """The table of settings in the file ``path`` (TOML, or JSON by its extension).

    Raises
    ------
    FormatError
        Naming the file: it cannot be read, does not parse, or holds no table; ``what`` says
        which file it is meant to be ("room file").
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise FormatError(path, None, f"cannot read the {what} ({exc.strerror})") from exc
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(raw)
        else:
            data = tomllib.loads(raw.decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise FormatError(path, None, f"not valid {path.suffix.lstrip('.') or 'TOML'}: {exc}") \
            from exc
    if not isinstance(data, dict):
        raise FormatError(path, None, f"the {what} must hold a table of settings")
    return data


def validated(model: type[_M], data: Any, source: str | Path, keys_doc: str) -> _M:
    """``model`` validated from ``data``, its first error a :class:`FormatError` naming
    ``source`` and the field (dotted path); an unknown key points to ``keys_doc``, the document
    that lists the keys."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(p) for p in first["loc"]) or first.get("ctx", {}).get("field")
        message = first["msg"]
        if first["type"] == "extra_forbidden":
            message = f"unknown key ({keys_doc} lists the keys)"
        raise FormatError(source, field or None, message) from exc
