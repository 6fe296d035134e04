"""The OpenAPI document's examples of the clinical workflow (eyeserver/api/examples.py): every
operation of the workflow carries request and response examples, and each validates against
its operation's schema in the document (a small validator of the JSON Schema keywords pydantic
emits) and against the pydantic model the daemon itself validates with."""

from __future__ import annotations

from typing import Any

import pytest
from pydantic import BaseModel

from eyeserver.api.examples import operation
from eyeserver.api.routers.captures import CaptureList, CaptureRequest, CaptureResponse
from eyeserver.api.routers.patients import PatientRequest, PatientResponse, ReferenceResponse
from eyeserver.api.routers.pose import Measurement, MeasureRequest
from eyeserver.api.routers.tracking import TrackingStart, TrackingStatus
from eyeserver.service.patients import ReferencePoseSpec
from tests.apiclient import API, Client

# (method, path, status, request model, response model)
WORKFLOW: list[tuple[str, str, str, type[BaseModel] | None, type[BaseModel]]] = [
    ("put", "/patients/{patient_id}", "200", PatientRequest, PatientResponse),
    ("put", "/patients/{patient_id}/fractions/{fraction}/reference", "201", ReferencePoseSpec,
     ReferenceResponse),
    ("post", "/patients/{patient_id}/fractions/{fraction}/reference/capture", "201", None,
     ReferenceResponse),
    ("post", "/pose/measure", "201", MeasureRequest, Measurement),
    ("post", "/tracking/start", "201", TrackingStart, TrackingStatus),
    ("post", "/tracking/stop", "200", None, TrackingStatus),
    ("post", "/captures", "201", CaptureRequest, CaptureResponse),
    ("get", "/captures", "200", None, CaptureList),
]


def _problems(value: Any, schema: dict[str, Any], document: dict[str, Any],
              where: str = "$") -> list[str]:
    """What in ``value`` breaks ``schema`` (the keywords pydantic's schemas use)."""
    if "$ref" in schema:
        node: Any = document
        for key in schema["$ref"].removeprefix("#/").split("/"):
            node = node[key]
        return _problems(value, node, document, where)
    if "anyOf" in schema:
        options = [_problems(value, option, document, where) for option in schema["anyOf"]]
        return [] if any(not found for found in options) else min(options, key=len)
    if "const" in schema and value != schema["const"]:
        return [f"{where}: {value!r} is not {schema['const']!r}"]
    if "enum" in schema and value not in schema["enum"]:
        return [f"{where}: {value!r} not in {schema['enum']}"]
    kind = schema.get("type")
    types = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None),
             "integer": int, "number": (int, float)}
    if kind is not None and (not isinstance(value, types[kind])
                             or (kind in ("integer", "number") and isinstance(value, bool))):
        return [f"{where}: {value!r} is not of type {kind}"]
    problems: list[str] = []
    for bound, holds in (("minimum", lambda v, b: v >= b), ("maximum", lambda v, b: v <= b),
                         ("exclusiveMinimum", lambda v, b: v > b)):
        if bound in schema and isinstance(value, int | float) and not holds(value, schema[bound]):
            problems.append(f"{where}: {value!r} breaks {bound} {schema[bound]}")
    if isinstance(value, dict):
        properties = schema.get("properties", {})
        problems += [f"{where}: {name} is required" for name in schema.get("required", [])
                     if name not in value]
        for name, item in value.items():
            if name in properties:
                problems += _problems(item, properties[name], document, f"{where}.{name}")
            elif schema.get("additionalProperties") is False:
                problems.append(f"{where}: {name} is not allowed")
            elif isinstance(schema.get("additionalProperties"), dict):
                problems += _problems(item, schema["additionalProperties"], document,
                                      f"{where}.{name}")
    if isinstance(value, list):
        if "minItems" in schema and len(value) < schema["minItems"]:
            problems.append(f"{where}: fewer than {schema['minItems']} items")
        if "maxItems" in schema and len(value) > schema["maxItems"]:
            problems.append(f"{where}: more than {schema['maxItems']} items")
        for k, item in enumerate(value):
            if "items" in schema:
                problems += _problems(item, schema["items"], document, f"{where}[{k}]")
            elif "prefixItems" in schema and k < len(schema["prefixItems"]):
                problems += _problems(item, schema["prefixItems"][k], document, f"{where}[{k}]")
    return problems


@pytest.fixture(scope="module")
def document(client: Client) -> dict[str, Any]:
    answer = client.get(f"{API}/openapi.json")
    assert answer.status_code == 200
    found: dict[str, Any] = answer.json()
    return found


@pytest.mark.parametrize(("method", "path", "status", "request_model", "response_model"),
                         WORKFLOW, ids=[f"{m} {p}" for m, p, *_ in WORKFLOW])
def test_a_workflow_operation_has_examples_that_fit_its_schemas(
        document: dict[str, Any], method: str, path: str, status: str,
        request_model: type[BaseModel] | None, response_model: type[BaseModel]) -> None:
    op = document["paths"][f"{API}{path}"][method]
    if request_model is not None:
        body = op["requestBody"]["content"]["application/json"]
        assert body["examples"], "no request example"
        for name, example in body["examples"].items():
            assert example["summary"] and isinstance(example["value"], dict), name
            assert _problems(example["value"], body["schema"], document) == [], name
            request_model.model_validate(example["value"])
    else:
        assert "requestBody" not in op
    answer = op["responses"][status]["content"]["application/json"]
    assert answer["examples"], "no response example"
    for name, example in answer["examples"].items():
        assert example["summary"], name
        assert _problems(example["value"], answer["schema"], document) == [], name
        response_model.model_validate(example["value"])


def test_the_schema_check_finds_what_breaks_a_schema(document: dict[str, Any]) -> None:
    # The validator above is this test's own: show it refuses what it must.
    start = {"$ref": "#/components/schemas/TrackingStart"}
    assert _problems({"patient_id": "P-1", "fraction": 1}, start, document) == []
    assert _problems({"patient_id": "P-1"}, start, document) == ["$: fraction is required"]
    assert _problems({"patient_id": "P-1", "fraction": 0}, start, document) == [
        "$.fraction: 0 breaks minimum 1.0"]
    assert _problems({"patient_id": "P-1", "fraction": 1, "unit": "left"}, start, document) == [
        "$: unit is not allowed"]
    assert _problems({"patient_id": "P-1", "fraction": "1"}, start, document) == [
        "$.fraction: '1' is not of type integer"]


def test_examples_go_where_fastapi_merges_them() -> None:
    assert operation(request={"a": {"value": 1}}, response={"b": {"value": 2}},
                     status_code=201) == {
        "requestBody": {"content": {"application/json": {"examples": {"a": {"value": 1}}}}},
        "responses": {"201": {"content": {"application/json": {"examples": {
            "b": {"value": 2}}}}}}}
