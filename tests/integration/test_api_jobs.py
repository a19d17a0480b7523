"""The ``/v1`` REST API on a real SQLite database: submission forms, validation, auth, polling headers,
the job lifecycle seen through the API, results/contacts/metrics, pagination, limits, ops endpoints."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from common.result_format import read_summary
from common.sequence_io import sequence_to_npz_bytes
from tests.support.api import PROBLEM, json_body
from tests.support.queue_fixtures import ApiHarness, fake_result, tiny_sequence


def multipart(seed: int = 0, **options: object) -> dict[str, object]:
    npz = sequence_to_npz_bytes(tiny_sequence(seed).validate())
    return {"files": {"sequence": ("tiny.npz", npz, "application/octet-stream")},
            "data": {"options": json.dumps({"seed": seed, **options})}}  # fmt: skip


def fields(resp: object) -> set[str]:
    doc = resp.json()  # type: ignore[attr-defined]
    return {e["field"] for e in doc["errors"]}


def test_json_submission_polling_headers_and_etag(api: ApiHarness) -> None:
    resp = api.client.post("/v1/jobs", json=json_body(keyframe_interval=5, priority=3), headers=api.headers)
    assert resp.status_code == 202, resp.text
    job = resp.json()
    assert resp.headers["Location"] == f"/v1/jobs/{job['id']}"
    assert job["state"] == "QUEUED" and job["attempt"] == 1 and job["priority"] == 3 and job["num_frames"] == 5
    assert job["options"]["keyframe_interval"] == 5
    stored = api.client.get(f"/v1/jobs/{job['id']}/input", headers=api.headers).json()
    assert np.allclose(stored["object_pose"], np.asarray(json_body()["object_pose"])) and stored["name"] == "tiny-box"
    got = api.client.get(f"/v1/jobs/{job['id']}", headers=api.headers)
    assert got.status_code == 200 and got.headers["Retry-After"] == "3"
    etag = got.headers["ETag"]
    same = api.client.get(f"/v1/jobs/{job['id']}", headers={**api.headers, "If-None-Match": etag})
    assert same.status_code == 304 and same.headers["ETag"] == etag
    # A worker reports progress: the representation (and so the ETag) changes, ETA is estimated.
    lease = api.queue.claim("w")
    assert lease is not None
    api.queue.heartbeat(job["id"], lease.lease_token, {"window": 2, "windows": 6, "best_loss": 0.25, "evaluations": 80})
    moved = api.client.get(f"/v1/jobs/{job['id']}", headers={**api.headers, "If-None-Match": etag})
    assert moved.status_code == 200 and moved.headers["ETag"] != etag
    progress = moved.json()["progress"]
    assert progress["window"] == 2 and progress["best_loss"] == 0.25 and progress["eta_s"] >= 0
    assert moved.json()["state"] == "RUNNING" and moved.json()["started_at"] is not None
    # Until the next heartbeat the running job's representation (ETA included) stays the same.
    again = api.client.get(f"/v1/jobs/{job['id']}", headers={**api.headers, "If-None-Match": moved.headers["ETag"]})
    assert again.status_code == 304


def test_multipart_submission_and_idempotency_key(api: ApiHarness) -> None:
    headers = {**api.headers, "Idempotency-Key": "batch-7"}
    first = api.client.post("/v1/jobs", headers=headers, **multipart(7))
    again = api.client.post("/v1/jobs", headers=headers, **multipart(7))
    assert first.status_code == again.status_code == 202
    assert first.json()["id"] == again.json()["id"] and first.json()["options"]["seed"] == 7
    other = api.client.post("/v1/jobs", headers=headers, **multipart(7, max_generations=3))
    assert other.status_code == 422 and other.headers["content-type"] == PROBLEM
    assert "Idempotency-Key" in other.json()["title"]
    # The same payload as JSON is the same sequence and options: the same job.
    as_json = api.client.post("/v1/jobs", headers=headers, json=json_body(7))
    assert as_json.status_code == 202 and as_json.json()["id"] == first.json()["id"]


def test_validation_errors_name_every_field(api: ApiHarness) -> None:
    body = json_body()
    body["fps"] = "fast"
    body["hands"][0]["side"] = "middle"  # type: ignore[index]
    body["options"] = {"seed": -1, "loss_weights": {"nonsense": 1.0}}
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 422 and resp.headers["content-type"] == PROBLEM
    assert {"fps", "hands[0].side", "options.seed", "options.loss_weights.nonsense"} <= fields(resp)
    # Shapes are checked by the schema, content after it: a non-unit quaternion, a hand with 4 frames of 5.
    body = json_body()
    body["hands"][0]["keypoints"][0] = [[0.0, 0.0, 0.0]] * 20  # type: ignore[index]
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 422 and fields(resp) == {"hands[0].keypoints[0]"}
    body = json_body()
    body["object_pose"][1][3] = 3.0  # type: ignore[index]
    body["hands"][0]["valid"] = [True] * 4  # type: ignore[index]
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 422 and {"object_pose", "hands[0].valid"} <= fields(resp), resp.text
    too_long = api.client.post("/v1/jobs", json=json_body(frames=51), headers=api.headers)
    assert too_long.status_code == 422 and fields(too_long) == {"object_pose"}
    bad_opts = api.client.post("/v1/jobs", headers=api.headers, files={"sequence": ("x.npz", b"not an npz")},
                               data={"options": '{"popsize": 1}'})  # fmt: skip
    assert bad_opts.status_code == 422 and fields(bad_opts) == {"options.popsize"}
    not_npz = api.client.post("/v1/jobs", headers=api.headers, files={"sequence": ("x.npz", b"not an npz")})
    assert not_npz.status_code == 422 and fields(not_npz) == {"sequence"}
    big = api.client.post("/v1/jobs", headers={**api.headers, "Content-Type": "application/json"},
                          content=b" " * 2_000_001)  # fmt: skip
    assert big.status_code == 413 and big.headers["content-type"] == PROBLEM



def test_media_type_json_as_a_file_and_strict_numbers(api: ApiHarness) -> None:
    """Issue #53 item 8: 415 for a body of another media type; a JSON sequence sent as the multipart file is told
    how to send it; numbers must be JSON numbers (and booleans JSON booleans), as the schema says."""
    text = api.client.post("/v1/jobs", headers={**api.headers, "Content-Type": "text/plain"}, content=b"seq")
    assert text.status_code == 415 and text.headers["content-type"] == PROBLEM
    assert "application/json or multipart/form-data" in text.json()["detail"]
    assert api.client.post("/v1/jobs", headers=api.headers, content=b"x").status_code == 415  # no Content-Type
    as_file = json.dumps(json_body()).encode()
    resp = api.client.post("/v1/jobs", headers=api.headers, files={"sequence": ("seq.json", b"\n  " + as_file)})
    assert resp.status_code == 422 and fields(resp) == {"sequence"}
    assert "holds JSON, not an NPZ file" in resp.text and "Content-Type: application/json" in resp.text
    for name, value in (("fps", "30"), ("fps", True), ("frame_start", 1.5), ("frame_start", "1")):
        body = {**json_body(), name: value}
        resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
        assert resp.status_code == 422 and fields(resp) == {name}, (name, value, resp.text)
    body = json_body()
    body["hands"][0]["valid"] = [1] * 5  # type: ignore[index]
    body["options"] = {"seed": "3"}
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 422 and {"hands[0].valid[0]", "options.seed"} <= fields(resp), resp.text
    form = multipart(4)
    form["data"] = {"options": '{"seed": "4"}'}
    multi = api.client.post("/v1/jobs", headers=api.headers, **form)
    assert multi.status_code == 422 and fields(multi) == {"options.seed"}
    body = json_body()
    body["fps"] = 30  # an integer where a float is asked for is a number all the same
    assert api.client.post("/v1/jobs", json=body, headers=api.headers).status_code == 202
    # JSON Schema's integer is a mathematical one: 2.0 is an integer, as generated clients may write it.
    body = {**json_body(), "name": "integral-floats", "frame_start": 2.0, "options": {"seed": 7.0, "restarts": 1.0}}
    accepted = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert accepted.status_code == 202, accepted.text
    assert accepted.json()["options"]["seed"] == 7 and accepted.json()["options"]["restarts"] == 1

def test_auth_and_owner_scoping(api: ApiHarness) -> None:
    anonymous = api.client.get("/v1/jobs")
    assert anonymous.status_code == 401 and anonymous.headers["WWW-Authenticate"] == "Bearer"
    wrong = api.client.get("/v1/jobs", headers={"Authorization": "Bearer hoi_wrong"})
    assert wrong.status_code == 401 and wrong.headers["content-type"] == PROBLEM
    job_id = api.client.post("/v1/jobs", json=json_body(), headers=api.headers).json()["id"]
    other = api.other_key_headers()
    for method, path in [("GET", ""), ("POST", ":cancel"), ("POST", ":retry"), ("DELETE", ""), ("GET", "/result"),
                         ("GET", "/contacts"), ("GET", "/metrics"), ("GET", "/events"), ("GET", "/input")]:  # fmt: skip
        assert api.client.request(method, f"/v1/jobs/{job_id}{path}", headers=other).status_code == 404
    assert api.client.get("/v1/jobs", headers=other).json()["count"] == 0


def test_the_json_result_leaves_the_integration_states_to_the_npz(api: ApiHarness) -> None:
    """The per-frame integration states (issue #54, for verify) are in the NPZ only: as JSON text they would be
    the bulk of the answer and of use to no reader."""
    from common.result_format import read_arrays, write_result_npz

    job_id = api.client.post("/v1/jobs", json=json_body(), headers=api.headers).json()["id"]
    lease = api.queue.claim("w")
    assert lease is not None
    blob, summary = fake_result(frames=5)
    stepwise = ("state_sim", "raw_state_sim", "control_sim", "raw_control_sim")
    arrays = {**read_arrays(blob), **{key: np.ones((5, 40)) for key in stepwise}}
    api.queue.complete(job_id, lease.lease_token, write_result_npz(arrays, summary), summary)
    as_json = api.client.get(f"/v1/jobs/{job_id}/result", headers=api.headers).json()
    assert "object_pose_sim" in as_json["arrays"]
    assert not set(stepwise) & set(as_json["arrays"])
    npz = api.client.get(f"/v1/jobs/{job_id}/result", params={"format": "npz"}, headers=api.headers)
    assert read_arrays(npz.content)["state_sim"].shape == (5, 40)


def test_result_contacts_and_metrics_after_completion(api: ApiHarness) -> None:
    job_id = api.client.post("/v1/jobs", json=json_body(), headers=api.headers).json()["id"]
    early = api.client.get(f"/v1/jobs/{job_id}/result", headers=api.headers)
    assert early.status_code == 409 and early.headers["content-type"] == PROBLEM
    lease = api.queue.claim("w")
    assert lease is not None
    blob, summary = fake_result(frames=5, contacts_per_frame=2)
    api.queue.complete(job_id, lease.lease_token, blob, summary)
    job = api.client.get(f"/v1/jobs/{job_id}", headers=api.headers)
    assert job.json()["state"] == "SUCCEEDED" and job.json()["summary"] == summary
    assert "Retry-After" not in job.headers
    npz = api.client.get(f"/v1/jobs/{job_id}/result", params={"format": "npz"}, headers=api.headers)
    assert npz.content == blob and read_summary(npz.content) == summary
    as_json = api.client.get(f"/v1/jobs/{job_id}/result", headers=api.headers).json()
    assert as_json["summary"] == summary
    assert np.allclose(as_json["arrays"]["contact_force"], np.load(io.BytesIO(blob))["contact_force"])
    contacts = api.client.get(f"/v1/jobs/{job_id}/contacts", params={"start": 1, "end": 3}, headers=api.headers)
    rows = contacts.json()["contacts"]
    assert contacts.json()["count"] == 4 and {r["frame"] for r in rows} == {1, 2}
    assert len(rows[0]["force"]) == 3 and rows[0]["hand"] == "right"
    # A half-open range, as the schema allows: end <= start selects nothing (not an error).
    for end in (3, 1):
        empty = api.client.get(f"/v1/jobs/{job_id}/contacts", params={"start": 3, "end": end}, headers=api.headers)
        assert empty.status_code == 200 and empty.json()["count"] == 0 and empty.json()["contacts"] == []
    metrics = api.client.get(f"/v1/jobs/{job_id}/metrics", headers=api.headers).json()
    assert metrics["metrics"] == summary["metrics"]
    events = api.client.get(f"/v1/jobs/{job_id}/events", headers=api.headers).json()["events"]
    assert [e["kind"] for e in events] == ["submitted", "claimed", "succeeded"]
    assert events[1]["detail"]["worker_id"] == "w"


def test_cancel_retry_delete_and_listing(api: ApiHarness) -> None:
    ids = [api.client.post("/v1/jobs", json=json_body(seed=i), headers=api.headers).json()["id"] for i in range(5)]
    cancelled = api.client.post(f"/v1/jobs/{ids[0]}:cancel", headers=api.headers)
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "CANCELLED"
    assert api.client.post(f"/v1/jobs/{ids[0]}:retry", headers=api.headers).status_code == 409
    lease = api.queue.claim("w")  # takes ids[1], the oldest QUEUED
    assert lease is not None and lease.job_id == ids[1]
    assert api.client.delete(f"/v1/jobs/{ids[1]}", headers=api.headers).status_code == 409
    api.queue.fail(ids[1], lease.lease_token, "diverged")
    retried = api.client.post(f"/v1/jobs/{ids[1]}:retry", headers=api.headers)
    assert retried.json()["state"] == "QUEUED" and retried.json()["errors"][0]["error"] == "diverged"
    assert api.client.delete(f"/v1/jobs/{ids[0]}", headers=api.headers).status_code == 204
    assert api.client.get(f"/v1/jobs/{ids[0]}", headers=api.headers).status_code == 404
    seen, token = [], None
    while True:
        params = {"page_size": 2, **({"page_token": token} if token else {})}
        page = api.client.get("/v1/jobs", params=params, headers=api.headers).json()
        seen += [j["id"] for j in page["data"]]
        if not (token := page["next_page_token"]):
            break
    assert seen == ids[1:][::-1]
    queued = api.client.get("/v1/jobs", params={"state": "QUEUED"}, headers=api.headers).json()
    assert queued["count"] == 4
    bad = api.client.get("/v1/jobs", params={"state": "DONE", "page_token": "zzz"}, headers=api.headers)
    assert bad.status_code == 422 and fields(bad) == {"state", "page_token"}
    # Any token of the schema's form is a keyset position: after the year 5000 lists everything, 1970 nothing.
    for token, count in (("99999999999999999.z", 4), ("0.z", 0)):
        page = api.client.get("/v1/jobs", params={"page_token": token}, headers=api.headers)
        assert page.status_code == 200 and page.json()["count"] == count, page.text


def test_active_jobs_limit_answers_429_with_retry_after(api: ApiHarness) -> None:
    api.queue.settings = api.queue.settings.model_copy(update={"max_active_jobs_per_key": 2})
    for seed in (1, 2):
        assert api.client.post("/v1/jobs", json=json_body(seed), headers=api.headers).status_code == 202
    resp = api.client.post("/v1/jobs", json=json_body(3), headers=api.headers)
    assert resp.status_code == 429 and resp.headers["Retry-After"] == "30"


def test_health_readiness_and_prometheus_metrics(api: ApiHarness) -> None:
    assert api.client.get("/healthz").json() == {"status": "ok"}
    assert api.client.get("/readyz").status_code == 200
    api.client.post("/v1/jobs", json=json_body(), headers=api.headers)
    lease = api.queue.claim("w")
    assert lease is not None
    api.queue.complete(lease.job_id, lease.lease_token, *fake_result())
    assert api.client.get("/metrics").status_code == 401  # deployment-wide totals: a key is needed
    text = api.client.get("/metrics", headers=api.headers).text
    assert 'hoi_refine_jobs{state="SUCCEEDED"} 1.0' in text and 'hoi_refine_jobs{state="QUEUED"} 0.0' in text
    assert "hoi_refine_claims_total 1.0" in text
    assert "hoi_refine_queue_wait_seconds_count 1.0" in text and "hoi_refine_run_seconds_count 1.0" in text


def test_dexycb_upload_is_accepted_when_ycb_dir_is_set(
    api: ApiHarness, dexycb_dev_files: list, shared_data: object, monkeypatch: pytest.MonkeyPatch
) -> None:
    from common.settings import get_settings

    blob = dexycb_dev_files[0].read_bytes()
    files = {"sequence": (dexycb_dev_files[0].name, blob, "application/octet-stream")}
    api.client.app.state.settings = api.client.app.state.settings.model_copy(
        update={"max_frames": 3000, "max_request_bytes": 64_000_000}
    )
    monkeypatch.delenv("HOI_REFINE_YCB_DIR", raising=False)
    get_settings.cache_clear()
    missing = api.client.post("/v1/jobs", headers=api.headers, files=files)
    assert missing.status_code == 422 and fields(missing) == {"sequence"}
    monkeypatch.setenv("HOI_REFINE_YCB_DIR", str(shared_data / "ycb"))  # type: ignore[operator]
    get_settings.cache_clear()
    resp = api.client.post("/v1/jobs", headers=api.headers, files=files)
    assert resp.status_code == 202, resp.text
    assert resp.json()["num_frames"] > 5


def test_unreachable_database_answers_503_not_500() -> None:
    from fastapi.testclient import TestClient

    from common.database import create_engine_for
    from common.settings import Settings
    from service.app import create_app

    engine = create_engine_for("postgresql+psycopg://postgres@127.0.0.1:1/nowhere?connect_timeout=2")
    client = TestClient(create_app(Settings(), engine))
    assert client.get("/readyz").status_code == 503
    resp = client.get("/v1/jobs", headers={"Authorization": "Bearer hoi_anything"})
    assert resp.status_code == 503 and resp.headers["content-type"] == PROBLEM and resp.headers["Retry-After"] == "5"
    engine.dispose()
