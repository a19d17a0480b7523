"""Request bodies and constants for the API tests."""

from __future__ import annotations

from common.sequence_io import sequence_to_json_dict
from tests.support.queue_fixtures import tiny_sequence

PROBLEM = "application/problem+json"


def json_body(seed: int = 0, frames: int = 5, **options: object) -> dict[str, object]:
    body = sequence_to_json_dict(tiny_sequence(seed, frames).validate())
    body["options"] = {"seed": seed, **options}
    return body
