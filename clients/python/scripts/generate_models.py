"""Write (or check) the client's models from the daemon's OpenAPI document.

Usage, from the repository root::

    python clients/python/scripts/generate_models.py            # from eyeserver's own app
    python clients/python/scripts/generate_models.py --check    # exit 1 when out of date
    python clients/python/scripts/generate_models.py --url http://127.0.0.1:8000 --check

Without ``--url`` the document comes from ``eyeserver.api.create_app`` (the daemon's package
must be importable, as in the repository's ``.venv``); with it, from a running daemon's
``/api/v1/openapi.json`` (give ``--token`` if that daemon's ``public_api_docs`` is off). The
output is ``src/eyeserver_client/models.py``: one pydantic model per component schema, field
documentation from the schema's descriptions. :func:`render` is what the tests call to see
that the committed file is what the daemon's document gives today.

The mapping is plain JSON Schema → Python: ``string``/``integer``/``number``/``boolean`` → ``str``
/``int``/``float``/``bool``, ``enum``/``const`` → ``Literal``, ``prefixItems`` → ``tuple``,
``items`` → ``list``, an object without properties → ``dict``, ``anyOf`` → ``|``, ``$ref`` → the
model. Schemas with ``additionalProperties: false`` are request bodies (unknown fields refused,
as the daemon refuses them); every other model keeps fields it does not know, so a newer daemon
that adds some does not break an older client. Constraints (ranges, patterns) are left to the
daemon, which checks every request and says what was wrong (422). Where the document leaves a
field untyped (``dict``) and the client knows its shape, :data:`FIELD_OVERRIDES` names a model
of ``eyeserver_client.extras`` instead.
"""

from __future__ import annotations

import argparse
import json
import keyword
import sys
import tempfile
import textwrap
from collections.abc import Iterable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
MODELS_FILE = HERE.parent / "src" / "eyeserver_client" / "models.py"
WIDTH = 100

#: FastAPI's own validation schemas: the daemon answers every error with ErrorResponse
#: (eyeserver/api/app.py makes HTTPValidationError a copy of it), so the client has no use
#: for them (and ``ValidationError`` would shadow pydantic's).
SKIPPED = frozenset({"HTTPValidationError", "ValidationError"})

#: (model, field) → a model of ``eyeserver_client.extras`` for a field the document types as
#: a bare object. Each must exist in the document (else the generator fails: drift).
FIELD_OVERRIDES: dict[tuple[str, str], str] = {
    ("Measurement", "deviation"): "Deviation",
    ("Measurement", "pose"): "FittedPose",
    ("Measurement", "reference"): "MeasuredReference",
    ("Measurement", "evidence"): "Evidence",
    ("ReferenceResponse", "pose"): "ReferencePose",
}

_HEADER = '''\
"""The API's resources as pydantic models, generated from the daemon's OpenAPI document.

Do not edit: ``python clients/python/scripts/generate_models.py`` writes this file from the
daemon's document (``--check`` says whether it is current; the client's tests fail when it is
not). Request bodies refuse unknown fields, as the daemon does; answers keep fields this
client does not know (``model_extra``), so a newer daemon that adds some does not break it.
Units are in the field names where they are not mm or rad (``_deg``, ``_px``, ``_s``, ``_us``).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

'''

_BASES = '''

class _Answer(BaseModel):
    """Base of what the daemon answers: fields it adds later are kept, not refused."""

    model_config = ConfigDict(extra="allow", use_attribute_docstrings=True)


class _Body(BaseModel):
    """Base of request bodies: unknown fields are refused, as the daemon refuses them."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)
'''


def render(document: dict[str, Any]) -> str:
    """The text of ``models.py`` for the OpenAPI ``document``.

    Raises
    ------
    ValueError
        A construct the generator does not know, or a :data:`FIELD_OVERRIDES` entry whose field
        the document does not have.
    """
    schemas: dict[str, dict[str, Any]] = {
        name: schema for name, schema in document["components"]["schemas"].items()
        if name not in SKIPPED}
    for model, field in FIELD_OVERRIDES:
        if field not in schemas.get(model, {}).get("properties", {}):
            raise ValueError(f"FIELD_OVERRIDES: {model}.{field} is not in the document")
    order = _ordered(schemas)
    extras = sorted(set(FIELD_OVERRIDES.values()))
    parts = [_HEADER]
    parts.append("from eyeserver_client.extras import (\n"
                 + "".join(f"    {name},\n" for name in extras) + ")\n\n")
    parts.append("__all__ = [\n" + "".join(f'    "{name}",\n' for name in sorted(order))
                 + "]\n")
    parts.append(_BASES)
    for name in order:
        parts.append("\n\n" + _model(name, schemas[name]))
    return "".join(parts)


def _ordered(schemas: dict[str, dict[str, Any]]) -> list[str]:
    """Names in an order where each model comes after the models it refers to."""
    done: list[str] = []
    seen: set[str] = set()

    def visit(name: str, path: tuple[str, ...]) -> None:
        if name in seen:
            return
        if name in path:
            raise ValueError(f"circular models: {' -> '.join((*path, name))}")
        for ref in sorted(_refs(schemas[name])):
            if ref in schemas:
                visit(ref, (*path, name))
        seen.add(name)
        done.append(name)

    for name in sorted(schemas):
        visit(name, ())
    return done


def _refs(schema: Any) -> set[str]:
    found: set[str] = set()
    if isinstance(schema, dict):
        ref = schema.get("$ref")
        if isinstance(ref, str):
            found.add(ref.rsplit("/", 1)[-1])
        for value in schema.values():
            found |= _refs(value)
    elif isinstance(schema, list):
        for value in schema:
            found |= _refs(value)
    return found


def _model(name: str, schema: dict[str, Any]) -> str:
    if schema.get("type") != "object":
        raise ValueError(f"{name}: only object schemas become models")
    base = "_Body" if schema.get("additionalProperties") is False else "_Answer"
    lines = [f"class {name}({base}):"]
    lines += _docstring(schema.get("description") or name, "    ")
    required = set(schema.get("required", ()))
    properties: dict[str, dict[str, Any]] = schema.get("properties", {})
    if properties:
        lines.append("")
    for field, spec in properties.items():
        if not field.isidentifier() or keyword.iskeyword(field):
            raise ValueError(f"{name}.{field}: not a Python name (an alias would be needed)")
        annotation = FIELD_OVERRIDES.get((name, field)) or _type(spec, f"{name}.{field}")
        lines += _field(field, annotation, spec, field in required)
        if spec.get("description"):
            lines += _docstring(spec["description"], "    ")
    return "\n".join(lines) + "\n"


def _field(field: str, annotation: str, spec: dict[str, Any], required: bool) -> list[str]:
    if not required and "default" not in spec and not _nullable(annotation):
        annotation += " | None"  # optional without a default: the daemon may leave it out
    head = f"    {field}: {annotation}"
    if len(head) > WIDTH - 4:
        head = f"    {field}: {_wrapped(annotation)}"
    if required:
        return [head]
    if "default" not in spec:
        return [f"{head} = None"]
    default = _tuples(spec["default"], spec)
    if isinstance(default, dict | list | tuple) and _refs(spec):
        # A model's default given as JSON: pydantic turns it into the model.
        text = _literal(default, 8)
        if "\n" in text:
            return [f"{head} = Field(", f"        default={text},",
                    "        validate_default=True,", "    )"]
        line = f"{head} = Field(default={text}, validate_default=True)"
        if _fits(line):
            return [line]
        return [f"{head} = Field(", f"        default={text}, validate_default=True", "    )"]
    text = _literal(default, len(head.rsplit("\n", 1)[-1]) + 3)
    line = f"{head} = {text}"
    if "\n" not in text and _fits(line):
        return [line]
    return [f"{head} = (", f"        {_literal(default, 8)}", "    )"]


def _fits(text: str) -> bool:
    return all(len(line) <= WIDTH for line in text.split("\n"))


def _wrapped(annotation: str) -> str:
    """A long annotation split one item a line inside its outermost brackets."""
    start = annotation.index("[")
    depth, end, cuts = 0, -1, []
    for n, char in enumerate(annotation[start:], start):
        depth += {"[": 1, "]": -1}.get(char, 0)
        if char == "," and depth == 1:
            cuts.append(n)
        if depth == 0:
            end = n
            break
    items, last = [], start + 1
    for cut in [*cuts, end]:
        items.append(annotation[last:cut].strip())
        last = cut + 1
    inner = "".join(f"        {item},\n" for item in items)
    return f"{annotation[:start]}[\n{inner}    ]{annotation[end + 1:]}"


def _tuples(value: Any, spec: dict[str, Any]) -> Any:
    """A JSON default as the Python value of its annotation (lists of prefixItems: tuples)."""
    for option in spec.get("anyOf", [spec]):
        if "prefixItems" in option and isinstance(value, list):
            return tuple(_tuples(v, s) for v, s in zip(value, option["prefixItems"],
                                                           strict=True))
    return value


def _nullable(annotation: str) -> bool:
    return annotation == "Any" or annotation.split(" | ")[-1] == "None"


def _type(spec: dict[str, Any], where: str) -> str:
    if "$ref" in spec:
        return str(spec["$ref"]).rsplit("/", 1)[-1]
    if "anyOf" in spec:
        options = _unique(_type(option, where) for option in spec["anyOf"])
        if "None" in options:  # None last, as written by hand
            options = [o for o in options if o != "None"] + ["None"]
        return " | ".join(options)
    if "const" in spec:
        return f"Literal[{spec['const']!r}]".replace("'", '"')
    if "enum" in spec:
        return "Literal[" + ", ".join(json.dumps(v) for v in spec["enum"]) + "]"
    kind = spec.get("type")
    simple = {"string": "str", "integer": "int", "number": "float", "boolean": "bool",
              "null": "None"}
    if kind in simple:
        return simple[kind]
    if kind == "array":
        if "prefixItems" in spec:
            return "tuple[" + ", ".join(_type(i, where) for i in spec["prefixItems"]) + "]"
        if "items" in spec:
            return f"list[{_type(spec['items'], where)}]"
        return "list[Any]"
    if kind == "object":
        if "properties" in spec:
            raise ValueError(f"{where}: an inline object with properties (make it a model)")
        extra = spec.get("additionalProperties", True)
        value = "Any" if extra is True or extra == {} else _type(extra, where)
        return f"dict[str, {value}]"
    if kind is None and not spec:
        return "Any"
    raise ValueError(f"{where}: cannot map {spec!r}")


def _unique(items: Iterable[str]) -> list[str]:
    out: list[str] = []
    for item in items:
        if item not in out:
            out.append(item)
    return out


def _literal(value: Any, indent: int) -> str:
    """``value`` as a Python literal, wrapped one item a line when it does not fit."""
    flat = repr(value).replace("'", '"')
    if indent + len(flat) <= WIDTH - 2 or not isinstance(value, dict | list | tuple):
        return flat
    pad = " " * (indent + 4)
    if isinstance(value, dict):
        items = [f'{pad}"{key}": {_literal(item, indent + 4 + len(key) + 4)},'
                 for key, item in value.items()]
        return "{\n" + "\n".join(items) + "\n" + " " * indent + "}"
    items = [f"{pad}{_literal(item, indent + 4)}," for item in value]
    brackets = "()" if isinstance(value, tuple) else "[]"
    return brackets[0] + "\n" + "\n".join(items) + "\n" + " " * indent + brackets[1]


def _docstring(text: str, indent: str) -> list[str]:
    text = text.strip().replace("\\", "\\\\").replace('"""', '\\"\\"\\"')
    paragraphs = [" ".join(p.split()) for p in text.split("\n\n")]
    lines: list[str] = []
    for n, paragraph in enumerate(paragraphs):
        if n:
            lines.append("")
        lines += textwrap.wrap(paragraph, width=WIDTH - len(indent) - 3,
                               break_long_words=False, break_on_hyphens=False)
    lines[0] = '"""' + lines[0]
    if len(lines) == 1 and len(lines[0]) + 3 <= WIDTH - len(indent):
        lines[0] += '"""'
    elif len(lines[-1]) + 3 <= WIDTH - len(indent):
        lines[-1] += '"""'
    else:
        lines.append('"""')
    return [f"{indent}{line}" if line else "" for line in lines]


def document_from_app() -> dict[str, Any]:
    """The OpenAPI document of eyeserver's own app (needs the daemon's package)."""
    from eyeserver.api import create_app
    from eyeserver.config import Settings

    with tempfile.TemporaryDirectory(prefix="eyeserver-openapi-") as scratch:
        # Nothing is started: the document comes from the routes alone.
        app = create_app(Settings.load(data_dir=Path(scratch) / "data"))
        return dict(app.openapi())


def document_from_url(url: str, token: str | None) -> dict[str, Any]:
    """The OpenAPI document a running daemon serves at ``url`` (its base URL)."""
    import httpx

    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    root = url.rstrip("/").removesuffix("/api/v1")
    response = httpx.get(f"{root}/api/v1/openapi.json", headers=headers, timeout=30.0)
    response.raise_for_status()
    document: dict[str, Any] = response.json()
    return document


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", help="a running daemon's base URL (default: eyeserver's app)")
    parser.add_argument("--token", help="bearer token, if the daemon's document needs one")
    parser.add_argument("--check", action="store_true",
                        help="do not write; exit 1 when models.py is not what it would be")
    parser.add_argument("--out", type=Path, default=MODELS_FILE, help="the file to write")
    args = parser.parse_args(argv)
    document = (document_from_app() if args.url is None
                else document_from_url(args.url, args.token))
    text = render(document)
    current = args.out.read_text(encoding="utf-8") if args.out.exists() else ""
    if args.check:
        if current != text:
            print(f"{args.out} is out of date: run {Path(__file__).name} without --check",
                  file=sys.stderr)
            return 1
        return 0
    if current != text:
        args.out.write_text(text, encoding="utf-8")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
