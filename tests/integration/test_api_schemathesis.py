"""Property-based API test (schemathesis) against the app's own OpenAPI schema: for bounded generated
requests, no 5xx and every response conforms to the schema (status codes, content types, bodies, headers).

The app is built at import (schemathesis reads its schema while collecting); building it touches no
database, which is migrated by the module fixture before the first request.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.specs.openapi.checks import positive_data_acceptance

from common.database import create_engine_for, upgrade_to_head
from common.settings import Settings
from service.app import create_app

MAX_EXAMPLES = int(__import__("os").environ.get("HOI_SCHEMATHESIS_EXAMPLES", "20"))
_DB_DIR = Path(tempfile.mkdtemp(prefix="hoi-schemathesis-"))
_DB_URL = f"sqlite:///{_DB_DIR / 'api.sqlite3'}"
_ENGINE = create_engine_for(_DB_URL)
app = create_app(Settings(max_frames=200, max_request_bytes=1_000_000, max_active_jobs_per_key=10_000), _ENGINE)
schema = schemathesis.openapi.from_asgi("/openapi.json", app)


@pytest.fixture(scope="module")
def api_key() -> Iterator[str]:
    upgrade_to_head(_DB_URL)
    _, plaintext = app.state.api_keys.create("schemathesis")
    yield plaintext
    _ENGINE.dispose()
    shutil.rmtree(_DB_DIR, ignore_errors=True)


@pytest.mark.slow
@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_api_conforms_to_its_openapi_schema(case: Any, api_key: str) -> None:
    # Schema-valid sequences may still be wrong in ways a JSON schema cannot say (unit quaternions, one of
    # mesh/primitive, per-hand frame counts), so a 422 for schema-valid data is not a failure here.
    case.call_and_validate(
        headers={"Authorization": f"Bearer {api_key}"}, excluded_checks=[positive_data_acceptance]
    )


def test_openapi_documents_both_submission_forms() -> None:
    doc = app.openapi()
    content = doc["paths"]["/v1/jobs"]["post"]["requestBody"]["content"]
    assert set(content) == {"application/json", "multipart/form-data"}
    assert "JobCreate" in doc["components"]["schemas"] and "HandIn" in doc["components"]["schemas"]
