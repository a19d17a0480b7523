"""Articulated, two-handed sequences through the ``/v1`` API (issue #52 item 8): accepted as JSON and NPZ and stored
as sent, refused with every problem named (the corpus, ``tests/corpus``, holds the full list of bad inputs), the
schema the API documents describes the parts, joints and articulation, and contacts name the part and the hand."""

from __future__ import annotations

import io
import json
from typing import Any

import numpy as np

from common.result_format import write_result_npz
from common.sequence_io import sequence_to_json_dict, sequence_to_npz_bytes
from tests.support.api import PROBLEM
from tests.support.articulated import tiny_articulated_sequence
from tests.support.queue_fixtures import ApiHarness, fake_result


def _body(seed: int = 0) -> dict[str, Any]:
    doc = sequence_to_json_dict(tiny_articulated_sequence(seed).validate())
    doc["options"] = {"seed": seed}
    return doc


def test_articulated_json_and_npz_are_accepted_and_stored_as_sent(api: ApiHarness) -> None:
    body = _body()
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 202, resp.text
    stored = api.client.get(f"/v1/jobs/{resp.json()['id']}/input", headers=api.headers).json()
    assert stored["format_version"] == 2 and stored["object"]["parts"] == body["object"]["parts"]
    assert stored["object"]["base_part"] == "base" and stored["articulation"] == body["articulation"]
    assert [h["side"] for h in stored["hands"]] == ["right", "left"]
    # The same sequence as NPZ is the same payload: with the same Idempotency-Key, the same job.
    npz = sequence_to_npz_bytes(tiny_articulated_sequence(1).validate())
    headers = {**api.headers, "Idempotency-Key": "hinged-1"}
    first = api.client.post("/v1/jobs", headers=headers, files={"sequence": ("h.npz", npz)},
                            data={"options": json.dumps({"seed": 1})})  # fmt: skip
    again = api.client.post("/v1/jobs", headers=headers, json=_body(1))
    assert first.status_code == again.status_code == 202 and first.json()["id"] == again.json()["id"]


def test_every_articulation_problem_is_named_in_one_answer(api: ApiHarness) -> None:
    body = _body()
    joint = body["object"]["parts"][0]["joint"]
    joint["axis"] = [0.0, 0.0, 0.0]
    body["articulation"][3][0] = 4.0
    body["object"]["parts"][0]["mass_kg"] = 0.0  # the schema's own bound
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 422 and resp.headers["content-type"] == PROBLEM
    assert {e["field"] for e in resp.json()["errors"]} == {"object.parts[0].mass_kg"}
    body["object"]["parts"][0]["mass_kg"] = 0.05
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    errors = {e["field"]: e["problem"] for e in resp.json()["errors"]}
    assert resp.status_code == 422 and set(errors) == {"object.parts[0].joint.axis", "articulation"}
    assert "zero length" in errors["object.parts[0].joint.axis"] and "outside its limits" in errors["articulation"]
    assert api.client.get("/v1/jobs", headers=api.headers).json()["count"] == 0


def test_the_documented_schema_describes_parts_joints_and_articulation(api: ApiHarness) -> None:
    schemas = api.client.get("/openapi.json").json()["components"]["schemas"]
    job = schemas["JobCreate"]["properties"]
    assert "articulation" in job and set(schemas["JobCreate"]["properties"]["format_version"]["enum"]) == {1, 2}
    obj = schemas["ObjectIn"]["properties"]
    assert {"parts", "base_part"} <= set(obj) and obj["parts"]["maxItems"] == 16
    assert {"name", "mass_kg", "mesh", "primitive", "joint"} <= set(schemas["PartIn"]["properties"])
    joint = schemas["JointIn"]
    assert set(joint["required"]) == {"name", "type", "parent", "axis", "limits"}
    assert joint["properties"]["type"]["enum"] == ["revolute", "prismatic"]
    assert {"pos", "quat"} <= set(schemas["OriginIn"]["properties"])
    assert "part" in schemas["ContactPublic"]["properties"]


def test_contacts_name_the_part_and_the_hand(api: ApiHarness) -> None:
    job_id = api.client.post("/v1/jobs", json=_body(), headers=api.headers).json()["id"]
    lease = api.queue.claim("w")
    assert lease is not None
    blob, summary = fake_result(frames=4, contacts_per_frame=2)
    arrays = dict(np.load(io.BytesIO(blob)))
    arrays.pop("summary_json")
    arrays["contact_hand"] = np.array(["right", "left"] * 4)
    arrays["contact_part"] = np.array(["base", "lid"] * 4)
    blob = write_result_npz(arrays, summary)
    api.queue.complete(job_id, lease.lease_token, blob, summary)
    rows = api.client.get(f"/v1/jobs/{job_id}/contacts", params={"start": 1, "end": 2}, headers=api.headers).json()
    assert [(r["frame"], r["hand"], r["part"]) for r in rows["contacts"]] == [(1, "right", "base"), (1, "left", "lid")]
    # A result without contact_part (a rigid object's) answers part null.
    rigid_id = api.client.post("/v1/jobs", json=_body(2), headers=api.headers).json()["id"]
    lease = api.queue.claim("w")
    assert lease is not None
    blob, summary = fake_result(frames=2, contacts_per_frame=1)
    api.queue.complete(rigid_id, lease.lease_token, blob, summary)
    rows = api.client.get(f"/v1/jobs/{rigid_id}/contacts", headers=api.headers).json()["contacts"]
    assert len(rows) == 2 and all(r["part"] is None for r in rows)
