"""A property-based fuzz of every operation of the OpenAPI document, with both roles' tokens,
against a daemon on loopback (schemathesis): no 5xx, no status the document does not list, every
body as its schema says.

Bounded and repeatable: a fixed seed (``derandomize``), a few examples per operation, no
shrinking. Left out, with why: ``POST /sim/eye/prerender`` (renders up to minutes of frames) and
``POST /tracking/start`` (starts worker processes; tests/test_tracking.py covers it). Every
check schemathesis has runs but two: ``positive_data_acceptance`` (a body the schema allows may
still be refused, 422 with its reason, by a rule JSON Schema cannot state: a limbus narrower
than the globe, a region's low corner below its high one, a unit the rig has) and
``negative_data_rejection`` (it counts a request with query parameters or headers the document
does not name as invalid; the daemon ignores those, as HTTP allows. It found the booleans
pydantic read as numbers, now refused: tests/test_sim_api.py, tests/test_patients_api.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, settings
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance

from eyeserver.api import create_app
from eyeserver.bench.reliability import FUZZ_LEFT_OUT
from tests.apiclient import API, OPERATOR_TOKEN, PHYSICIST_TOKEN, test_settings
from tests.liveserver import live_server

pytestmark = pytest.mark.slow  # every test here takes over a second

EXAMPLES = 6

@schemathesis.serializer("application/zip", "application/dicom")
def _zip_body(ctx: object, value: object) -> bytes:
    """A calibration or DICOM upload's body as generated (bytes or text): the daemon must
    refuse any that is not a calibration zip, or a plan's DICOM, with a 4xx."""
    return value if isinstance(value, bytes) else str(value).encode()


# The document is the app's own: generated without serving (no hardware opened for it).
schema = schemathesis.openapi.from_dict(
    create_app(test_settings(Path("/nonexistent-eyeserver-fuzz"))).openapi())


@pytest.fixture(scope="module")
def base_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    app = create_app(test_settings(tmp_path_factory.mktemp("fuzz") / "data"))
    with live_server(app) as url:
        yield url


@pytest.mark.parametrize("token", [OPERATOR_TOKEN, PHYSICIST_TOKEN],
                         ids=["operator", "physicist"])
@schema.exclude(path_regex="|".join(f"^{API}{path}$" for path in FUZZ_LEFT_OUT)).parametrize()
@settings(max_examples=EXAMPLES, derandomize=True, deadline=None, database=None,
          phases=[Phase.explicit, Phase.generate],
          suppress_health_check=list(HealthCheck))
def test_every_operation_answers_as_documented(case: schemathesis.Case, base_url: str,
                                               token: str) -> None:
    case.call_and_validate(base_url=base_url, headers={"Authorization": f"Bearer {token}"},
                           excluded_checks=[positive_data_acceptance, negative_data_rejection],
                           timeout=120)
