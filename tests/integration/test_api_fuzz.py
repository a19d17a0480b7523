"""Fuzz through the API (issue #16), on SQLite and PostgreSQL: mutated NPZ uploads, mutated JSON bodies and
random options never get a 5xx; every 4xx is problem+json, and a 422 names its fields."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.npz_writer import deterministic_npz_bytes
from common.sequence_io import sequence_to_json_dict
from tests.support.fuzz_strategies import VALID, mutate_json, mutated_members
from tests.support.queue_fixtures import BACKENDS, ApiHarness, tiny_sequence

API_FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
OPTION_VALUES = st.one_of(
    st.integers(-(2**40), 2**40), st.floats(), st.text(max_size=4), st.none(), st.booleans(),
    st.dictionaries(st.sampled_from(["object_pose", "hand_joints", "bogus"]), st.floats(), max_size=2),
)  # fmt: skip
OPTIONS = st.dictionaries(
    st.sampled_from(["seed", "keyframe_interval", "max_generations", "popsize", "loss_weights", "restarts",
                     "priority", "free_wrist_translation", "unknown"]), OPTION_VALUES, max_size=3,
)  # fmt: skip


def _options_text(options: dict[str, Any]) -> str:
    return json.dumps(options, allow_nan=True)  # NaN/Infinity literals on purpose


def _assert_answer(resp: Any) -> None:
    assert resp.status_code < 500, resp.text[:500]
    if resp.status_code >= 400:
        assert resp.headers["content-type"].startswith("application/problem+json"), resp.text[:200]
        if resp.status_code == 422 and "errors" in resp.json():
            assert all(e["field"] for e in resp.json()["errors"])


@pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)
def test_mutated_npz_uploads_never_5xx(api: ApiHarness) -> None:
    @API_FUZZ
    @given(data=st.data(), which=st.integers(0, len(VALID) - 1), options=OPTIONS)
    def run(data: st.DataObject, which: int, options: dict[str, Any]) -> None:
        arrays = data.draw(mutated_members(VALID[which]))
        files = {"sequence": ("s.npz", deterministic_npz_bytes(arrays), "application/octet-stream")}
        resp = api.client.post("/v1/jobs", headers=api.headers, files=files, data={"options": _options_text(options)})
        _assert_answer(resp)

    run()


@pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)
def test_mutated_json_bodies_never_5xx(api: ApiHarness) -> None:
    @API_FUZZ
    @given(data=st.data(), options=OPTIONS)
    def run(data: st.DataObject, options: dict[str, Any]) -> None:
        doc: Any = sequence_to_json_dict(tiny_sequence(data.draw(st.integers(0, 3))).validate())
        doc["options"] = options
        doc = mutate_json(data, doc, data.draw(st.integers(0, 2)))
        body = json.dumps(doc, allow_nan=True).encode()
        headers = {**api.headers, "Content-Type": "application/json"}
        _assert_answer(api.client.post("/v1/jobs", content=body, headers=headers))

    run()
