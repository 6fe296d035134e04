"""Checks shared by the JSON readers: each raises FormatError naming the file and the field."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from eyeserver.core.frames import is_valid_id
from eyeserver.errors import FormatError


def join_field(prefix: str, name: str) -> str:
    """``prefix.name``, or ``name`` alone at the top level."""
    return f"{prefix}.{name}" if prefix else name


def type_name(value: object) -> str:
    """The JSON name of a parsed value's type, for error messages."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def require_key(
    mapping: dict[str, object], key: str, source: str | Path, prefix: str = ""
) -> object:
    """``mapping[key]``, or FormatError when the key is absent."""
    if key not in mapping:
        raise FormatError(source, join_field(prefix, key), "required but missing")
    return mapping[key]


def as_object(value: object, source: str | Path, field: str | None) -> dict[str, object]:
    """``value`` as a JSON object with string keys."""
    if not isinstance(value, dict):
        raise FormatError(source, field, f"must be an object, got {type_name(value)}")
    return value


def as_array(value: object, source: str | Path, field: str) -> list[object]:
    """``value`` as a JSON array."""
    if not isinstance(value, list):
        raise FormatError(source, field, f"must be an array, got {type_name(value)}")
    return value


def as_str(value: object, source: str | Path, field: str) -> str:
    """``value`` as a string."""
    if not isinstance(value, str):
        raise FormatError(source, field, f"must be a string, got {type_name(value)}")
    return value


def as_int(value: object, source: str | Path, field: str) -> int:
    """``value`` as an integer; JSON booleans and numbers with a fraction part are refused."""
    # bool is a subclass of int in Python, but `true` is not a number in JSON.
    if isinstance(value, bool) or not isinstance(value, int):
        raise FormatError(source, field, f"must be an integer, got {type_name(value)}")
    return value


def as_finite_number(value: object, source: str | Path, field: str) -> float:
    """``value`` as a finite float (JSON integers are accepted)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise FormatError(source, field, f"must be a number, got {type_name(value)}")
    number = float(value)
    if not math.isfinite(number):
        raise FormatError(source, field, f"must be a finite number, got {value!r}")
    return number


def as_bool(value: object, source: str | Path, field: str) -> bool:
    """``value`` as a JSON boolean."""
    if not isinstance(value, bool):
        raise FormatError(source, field, f"must be true or false, got {type_name(value)}")
    return value


def as_id(value: object, source: str | Path, field: str) -> str:
    """``value`` as a legal device or unit id."""
    text = as_str(value, source, field)
    if not is_valid_id(text):
        raise FormatError(
            source,
            field,
            f"{text!r} is not a legal id (1 to 64 letters, digits, '-' or '_')",
        )
    return text


def _refuse_constant(name: str) -> object:
    raise ValueError(f"{name} is not valid JSON")


def load_json(path: str | os.PathLike[str]) -> object:
    """Parse a JSON file strictly (no NaN or Infinity), mapping every failure to FormatError."""
    source = Path(path)
    try:
        text = source.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise FormatError(source, None, "file not found") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(source, None, f"cannot read the file: {exc}") from exc
    try:
        return json.loads(text, parse_constant=_refuse_constant)
    except ValueError as exc:
        raise FormatError(source, None, f"not valid JSON: {exc}") from exc


def dump_json(data: object) -> str:
    """Serialise ``data`` the way eyeserver writes its JSON files (UTF-8, indented, finite)."""
    return json.dumps(data, indent=2, ensure_ascii=False, allow_nan=False) + "\n"
