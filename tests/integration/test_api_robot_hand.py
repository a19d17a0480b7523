"""A robot hand description travels with a job through the API (issue #55 item 4): a packed description is
accepted and named in the job's status; an unpacked one, or one naming a body its model lacks, is a field-named 422."""

from __future__ import annotations

import json
from pathlib import Path

from tests.integration.test_api_jobs import fields, multipart
from tests.support.queue_fixtures import ApiHarness
from tests.support.robot_hand import description, write_robot_hand
from worker.robot import resolve_hand


def test_a_packed_hand_travels_with_the_job(api: ApiHarness, tmp_path: Path) -> None:
    packed = resolve_hand(write_robot_hand(tmp_path))
    assert packed is not None
    hand = packed.model_dump(mode="json")
    resp = api.client.post("/v1/jobs", headers=api.headers, **multipart(1, hand=hand))
    assert resp.status_code == 202, resp.text
    job = resp.json()
    assert job["hand"] == "test-hand" and job["options"]["hand"]["model_xml"] == packed.model_xml
    listed = api.client.get("/v1/jobs", headers=api.headers).json()["data"]
    assert [j["hand"] for j in listed] == ["test-hand"]
    human = api.client.post("/v1/jobs", headers=api.headers, **multipart(2))
    assert human.json()["hand"] == "human"


def test_bad_hands_are_field_named_422s(api: ApiHarness, tmp_path: Path) -> None:
    unpacked = api.client.post("/v1/jobs", headers=api.headers,
                               **multipart(3, hand=description()))
    assert unpacked.status_code == 422 and fields(unpacked) == {"options.hand"}, unpacked.text
    assert "pack" in json.dumps(unpacked.json())
    packed = resolve_hand(write_robot_hand(tmp_path))
    assert packed is not None
    data = packed.model_dump(mode="json")
    data["keypoints"]["index4"] = {"body": "nowhere", "pos": [0, 0, 0]}
    bad = api.client.post("/v1/jobs", headers=api.headers, **multipart(4, hand=data))
    assert bad.status_code == 422 and fields(bad) == {"options.hand"}
    assert "hand.keypoints.index4.body" in bad.text
