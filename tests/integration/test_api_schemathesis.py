"""Property-based API test (schemathesis) against the app's own OpenAPI schema, on SQLite and on PostgreSQL: for
bounded generated requests to every operation but the event streams, no 5xx, every response conforms to the
schema (status codes, content types, bodies, headers), and every request the schema allows is accepted (the
positive-data check: a 422 for schema-valid data means the schema does not say what the server enforces).

What a JSON schema cannot say about a submitted sequence (rules across fields: one frame count for every
per-frame array, unit quaternions, one hand per side, exactly one of mesh and primitive, a primitive's size
count by kind, a rigid world transform, an NPZ file's content) is made to hold by ``tests.support.schema_cases``
before the request goes out; everything else about the request stays as generated.

``HOI_SCHEMATHESIS_EXAMPLES`` sets the examples per operation (default 20: well under a minute per database).
"""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance

from common.database import create_engine_for, upgrade_to_head
from common.settings import Settings
from common.webhook_targets import IPAddress
from service.app import create_app
from tests.support import schema_cases
from tests.support.queue_fixtures import BACKENDS, empty_database

MAX_EXAMPLES = int(os.environ.get("HOI_SCHEMATHESIS_EXAMPLES", "20"))
#: No webhook is sent here (no dispatcher); registration still checks targets, through ``resolve_public``.
SETTINGS = Settings(max_frames=200, max_request_bytes=1_000_000, max_active_jobs_per_key=10_000,
                    webhook_dispatcher=False)  # fmt: skip
#: The document is the same on every database; this app only serves it (building an app touches no database).
#: Every operation but the event streams (which stream until their time limit) is tested.
app_for_schema = create_app(SETTINGS, create_engine_for("sqlite://"))
schema = schemathesis.openapi.from_asgi("/openapi.json", app_for_schema).exclude(path_regex=r"/events$")


#: id(case) -> (case, body, headers, generated positive) as first seen (the case is kept so that its id stays its own).
AS_GENERATED: dict[int, tuple[Any, Any, dict[str, Any], bool]] = {}


def _generated_positive(case: Any) -> bool:
    return case.meta is not None and not case.meta.generation.mode.is_negative


def resolve_public(host: str, port: int) -> list[IPAddress]:
    """Every generated host name resolves to one public address (no network in tests; nothing is sent to it)."""
    return [ipaddress.ip_address("151.101.1.69")]


@pytest.fixture(scope="module", params=BACKENDS)
def served(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, str]]:
    """(app on a migrated database of the backend, API key) for every operation's test on that backend."""
    folder: Path = tmp_path_factory.mktemp("schemathesis")
    with empty_database(request.param, folder) as url:
        upgrade_to_head(url)
        engine = create_engine_for(url)
        app = create_app(SETTINGS, engine)
        app.state.webhooks.targets.resolver = resolve_public
        _, plaintext = app.state.api_keys.create("schemathesis")
        yield app, plaintext
        engine.dispose()


@pytest.mark.slow
@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_api_conforms_to_its_openapi_schema(case: Any, served: tuple[Any, str]) -> None:
    app, api_key = served
    # Coverage-phase cases are hypothesis' explicit examples: the same objects for both databases' runs, so the
    # first run's edits (and schemathesis' relabelling of the edited body) would reach the second. Each run starts
    # from the case as generated.
    first = AS_GENERATED.setdefault(id(case), (case, dict(case.body) if isinstance(case.body, dict) else case.body,
                                              dict(case.headers or {}), _generated_positive(case)))
    _, body, headers, generated_positive = first
    case.body, case.headers = (dict(body) if isinstance(body, dict) else body), dict(headers)
    case._record_starting_state()
    edited = schema_cases.consistent_body(case, SETTINGS.max_frames)
    # A multipart case's sequence file is replaced by a real NPZ, and schemathesis may re-check the edited body and
    # count the file as breaking the schema (it cannot check one); a case generated positive and edited only to
    # satisfy the rules above is still positive, so the negative-data check does not apply to it.
    excluded = [negative_data_rejection] if generated_positive and edited else []
    # All of schemathesis's other checks; the positive-data one named as well, so that it stays on.
    case.call_and_validate(
        app=app, headers={"Authorization": f"Bearer {api_key}"}, additional_checks=[positive_data_acceptance],
        excluded_checks=excluded,
    )


def test_openapi_documents_both_submission_forms() -> None:
    doc = schema.raw_schema
    content = doc["paths"]["/v1/jobs"]["post"]["requestBody"]["content"]
    assert set(content) == {"application/json", "multipart/form-data"}
    assert "JobCreate" in doc["components"]["schemas"] and "HandIn" in doc["components"]["schemas"]


def test_bounds_are_json_schema_keywords() -> None:
    """A field's bounds are minimum/maximum in the document: pydantic writes an annotated integer's bounds inside a
    union as "ge"/"le", which JSON Schema (and every generated client) ignores."""

    def keys(node: Any) -> Iterator[str]:
        if isinstance(node, dict):
            for key, value in node.items():
                yield key
                yield from keys(value)
        elif isinstance(node, list):
            for value in node:
                yield from keys(value)

    assert not {"ge", "le", "gt", "lt"} & set(keys(schema.raw_schema["components"]))
