"""Batches through the API on SQLite and PostgreSQL: counts and aggregate metrics match the jobs, the CSV and
Parquet reports read back, cancel / retry-failed act on the whole batch, keyset listing, key scoping."""

from __future__ import annotations

import csv
import io
import json
import math

import pyarrow.parquet as pq
import pytest

from common.sequence_io import sequence_to_npz_bytes
from tests.support.api import json_body
from tests.support.queue_fixtures import BACKENDS, ApiHarness, fake_result, tiny_sequence

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)


def summary(raw_t: float, ref_t: float, ok: bool, paper: bool = False) -> dict[str, object]:
    """A result summary as the worker writes it (E_* in cm / deg, success per sequence)."""
    stage = {"raw": {"E_t": raw_t, "E_r": 10.0, "E_j": 2.0, "E_ft": 3.0, "success": False},
             "refined": {"E_t": ref_t, "E_r": 2.0, "E_j": 1.0, "E_ft": 1.5, "success": ok}}  # fmt: skip
    doc: dict[str, object] = {"kind": "refine", "metrics": dict(stage)}
    if paper:
        doc["protocols"] = {"paper": {"raw": {"E_t": raw_t - 1, "success": True}, "refined": {"E_t": ref_t - 0.1}}}
    return doc


def submit(api: ApiHarness, seed: int, batch_id: str | None, multipart: bool = False) -> str:
    if multipart:
        npz = sequence_to_npz_bytes(tiny_sequence(seed).validate())
        data = {"options": json.dumps({"seed": seed}), **({"batch_id": batch_id} if batch_id else {})}
        resp = api.client.post("/v1/jobs", headers=api.headers, files={"sequence": ("s.npz", npz)}, data=data)
    else:
        body = {**json_body(seed), **({"batch_id": batch_id} if batch_id else {})}
        resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 202, resp.text
    assert resp.json()["batch_id"] == batch_id
    return str(resp.json()["id"])


def finish(api: ApiHarness, job_id: str, doc: dict[str, object] | None) -> None:
    """Claim the job and complete it with ``doc`` as its summary (fail it when None)."""
    lease = api.queue.claim("w")
    assert lease is not None and lease.job_id == job_id
    if doc is None:
        api.queue.fail(job_id, lease.lease_token, "diverged")
    else:
        api.queue.complete(job_id, lease.lease_token, fake_result()[0], doc)


def test_batch_counts_aggregates_and_reports_match_the_jobs(api: ApiHarness) -> None:
    created = api.client.post("/v1/batches", json={"name": "dexycb-s01", "meta": {"split": "dev"}},
                              headers=api.headers)  # fmt: skip
    assert created.status_code == 201 and created.json()["state"] == "EMPTY"
    batch_id = created.json()["id"]
    assert created.headers["Location"] == f"/v1/batches/{batch_id}"
    ids = [submit(api, i, batch_id, multipart=i % 2 == 1) for i in range(5)]
    outside = submit(api, 9, None)
    docs = [summary(2.0, 0.5, True, paper=True), summary(4.0, 1.5, False), None]
    for job_id, doc in zip(ids, docs, strict=False):
        finish(api, job_id, doc)
    lease = api.queue.claim("w")  # ids[3] runs; ids[4] stays queued
    assert lease is not None and lease.job_id == ids[3]

    batch = api.client.get(f"/v1/batches/{batch_id}", headers=api.headers).json()
    assert batch["state"] == "ACTIVE" and batch["total"] == 5 and batch["meta"] == {"split": "dev"}
    listed = api.client.get("/v1/jobs", params={"batch_id": batch_id}, headers=api.headers).json()["data"]
    assert sorted(j["id"] for j in listed) == sorted(ids) and outside not in {j["id"] for j in listed}
    for state in ("QUEUED", "RUNNING", "SUCCEEDED", "FAILED", "CANCELLED"):
        assert batch["counts"][state] == sum(j["state"] == state for j in listed), state
    raw, refined = batch["metrics"]["all_frames"]["raw"], batch["metrics"]["all_frames"]["refined"]
    assert raw["n"] == refined["n"] == 2
    assert raw["E_t"] == pytest.approx(3.0) and refined["E_t"] == pytest.approx(1.0)
    assert refined["SR"] == pytest.approx(0.5) and raw["SR"] == 0.0 and refined["E_ft"] == pytest.approx(1.5)
    paper = batch["metrics"]["paper"]  # a second protocol is aggregated by its key
    assert paper["raw"]["n"] == 1 and paper["raw"]["E_t"] == pytest.approx(1.0) and paper["raw"]["E_r"] is None

    text = api.client.get(f"/v1/batches/{batch_id}/report", headers=api.headers)
    assert text.status_code == 200 and text.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(text.text)))
    assert [r["job_id"] for r in rows] == ids
    assert [r["state"] for r in rows] == ["SUCCEEDED", "SUCCEEDED", "FAILED", "RUNNING", "QUEUED"]
    assert float(rows[0]["all_frames_refined_E_t"]) == 0.5 and float(rows[1]["all_frames_raw_E_t"]) == 4.0
    assert rows[0]["paper_raw_E_t"] == "1.0" and rows[1]["paper_raw_E_t"] == "" and rows[2]["error"] == "diverged"
    assert rows[0]["all_frames_refined_SR"] == "1.0" and rows[1]["all_frames_refined_SR"] == "0.0"

    parquet = api.client.get(f"/v1/batches/{batch_id}/report", params={"format": "parquet"}, headers=api.headers)
    table = pq.read_table(io.BytesIO(parquet.content))
    assert table.num_rows == 5 and table.column("job_id").to_pylist() == ids
    assert table.column("all_frames_refined_E_t").to_pylist()[:3] == [0.5, 1.5, None]
    assert table.schema.field("all_frames_raw_E_t").type == "double"
    assert math.isclose(sum(v for v in table.column("all_frames_raw_E_t").to_pylist() if v is not None), 6.0)
    assert table.column("run_s").to_pylist()[0] >= 0 and table.column("started_at").to_pylist()[4] is None
    assert {r["name"] for r in rows} == {"tiny-box"}

    # Another key sees no such batch and cannot submit into it.
    other = api.other_key_headers()
    for path in ("", "/report", "/events"):
        assert api.client.get(f"/v1/batches/{batch_id}{path}", headers=other).status_code == 404
    for action in (":cancel", ":retry-failed"):
        assert api.client.post(f"/v1/batches/{batch_id}{action}", headers=other).status_code == 404
    foreign = api.client.post("/v1/jobs", json={**json_body(20), "batch_id": batch_id}, headers=other)
    assert foreign.status_code == 404
    assert api.client.get("/v1/batches", headers=other).json()["count"] == 0


def test_cancel_and_retry_failed_act_on_the_whole_batch(api: ApiHarness) -> None:
    batch_id = api.client.post("/v1/batches", json={}, headers=api.headers).json()["id"]
    ids = [submit(api, i, batch_id) for i in range(4)]
    finish(api, ids[0], None)
    finish(api, ids[1], None)
    lease = api.queue.claim("w")  # ids[2] RUNNING, ids[3] QUEUED
    assert lease is not None
    retried = api.client.post(f"/v1/batches/{batch_id}:retry-failed", headers=api.headers).json()
    assert retried["changed"] == 2 and retried["batch"]["counts"]["QUEUED"] == 3
    job = api.client.get(f"/v1/jobs/{ids[0]}", headers=api.headers).json()
    assert job["state"] == "QUEUED" and job["attempt"] == 1 and job["errors"][0]["error"] == "diverged"
    cancelled = api.client.post(f"/v1/batches/{batch_id}:cancel", headers=api.headers).json()
    assert cancelled["changed"] == 4
    assert cancelled["batch"]["counts"]["CANCELLED"] == 3 and cancelled["batch"]["counts"]["RUNNING"] == 1
    assert api.client.get(f"/v1/jobs/{ids[2]}", headers=api.headers).json()["cancel_requested"] is True
    api.queue.acknowledge_cancel(ids[2], lease.lease_token)
    done = api.client.get(f"/v1/batches/{batch_id}", headers=api.headers).json()
    assert done["state"] == "COMPLETED" and done["counts"]["CANCELLED"] == 4
    # Nothing left to do: both actions change nothing and say so.
    again = api.client.post(f"/v1/batches/{batch_id}:cancel", headers=api.headers).json()
    assert again["changed"] == 0


def test_batches_list_newest_first_with_keyset_pages(api: ApiHarness) -> None:
    made = [api.client.post("/v1/batches", json={"name": f"b{i}"}, headers=api.headers).json()["id"]
            for i in range(5)]  # fmt: skip
    submit(api, 1, made[2])
    seen, token, counts = [], None, {}
    while True:
        params = {"page_size": 2, **({"page_token": token} if token else {})}
        page = api.client.get("/v1/batches", params=params, headers=api.headers).json()
        assert page["count"] <= 2
        seen += [b["id"] for b in page["data"]]
        counts.update({b["id"]: b["total"] for b in page["data"]})
        if not (token := page["next_page_token"]):
            break
    assert seen == made[::-1] and counts[made[2]] == 1 and counts[made[0]] == 0
    bad = api.client.get("/v1/batches", params={"page_token": "zzz"}, headers=api.headers)
    assert bad.status_code == 422


def test_idempotent_resubmission_adopts_the_job_into_the_batch(api: ApiHarness) -> None:
    headers = {**api.headers, "Idempotency-Key": "seq-1"}
    first = api.client.post("/v1/jobs", json=json_body(1), headers=headers).json()
    assert first["batch_id"] is None
    batch_id = api.client.post("/v1/batches", json={}, headers=api.headers).json()["id"]
    again = api.client.post("/v1/jobs", json={**json_body(1), "batch_id": batch_id}, headers=headers)
    assert again.status_code == 202 and again.json()["id"] == first["id"] and again.json()["batch_id"] == batch_id
    other_batch = api.client.post("/v1/batches", json={}, headers=api.headers).json()["id"]
    moved = api.client.post("/v1/jobs", json={**json_body(1), "batch_id": other_batch}, headers=headers)
    assert moved.status_code == 409
    missing = api.client.post("/v1/jobs", json={**json_body(2), "batch_id": "nope"}, headers=api.headers)
    assert missing.status_code == 404


def worker_summary(executable: bool, reasons: list[dict[str, object]]) -> dict[str, object]:
    """The layout the worker writes (issue #53): the paper's protocol nested in each stage, penetration,
    verification, and the outcome (also copied among the metrics)."""
    def stage(e_t: float, ok: bool) -> dict[str, object]:
        return {"E_t": e_t, "E_r": 5.0, "success": ok, "penetration_mean_mm": 1.5, "penetration_max_mm": 4.0,
                "paper": {"E_t": e_t + 0.2, "E_r": 6.0, "success": ok, "penetration_max_mm": 3.5}}
    outcome = {"executable": executable, "protocol": "paper", "reasons": reasons}
    return {"kind": "refine", "outcome": outcome,
            "metrics": {"raw": stage(3.0, False), "refined": stage(0.5 if executable else 4.0, executable),
                        "verification": {"verified": True, "content_sha256": "ab"}, "outcome": outcome}}  # fmt: skip


def test_the_report_puts_the_outcome_first_with_both_protocols_penetration_and_verification(api: ApiHarness) -> None:
    batch_id = api.client.post("/v1/batches", json={"name": "r"}, headers=api.headers).json()["id"]
    ids = [submit(api, i, batch_id) for i in range(3)]
    rescued: dict[str, object] = {"code": "rescued_on_finer_parts", "frame": None, "value": None, "unit": None,
                                  "message": "kept on the finer convex parts"}  # fmt: skip
    jump: dict[str, object] = {"code": "recording_too_fast", "frame": 41, "value": 38.5, "unit": "deg/frame",
            "message": "the recorded object turns 38.5 deg between frames 40 and 41"}  # fmt: skip
    finish(api, ids[0], worker_summary(False, [rescued, jump]))
    finish(api, ids[1], worker_summary(True, [rescued]))
    finish(api, ids[2], summary(2.0, 0.5, True))  # an older result: no outcome

    rows = list(csv.DictReader(io.StringIO(api.client.get(f"/v1/batches/{batch_id}/report",
                                                          headers=api.headers).text)))  # fmt: skip
    assert list(rows[0])[:4] == ["job_id", "name", "outcome", "reason"]
    assert [r["outcome"] for r in rows] == ["not_executable", "executable", "unknown"]
    # The primary reason is the first that explains a failure; every code is listed.
    assert (rows[0]["reason"], rows[0]["reason_frame"], rows[0]["reason_value"], rows[0]["reason_unit"]) == (
        "recording_too_fast", "41", "38.5", "deg/frame")
    assert rows[0]["reasons"] == "rescued_on_finer_parts;recording_too_fast"
    assert rows[1]["reason"] == "rescued_on_finer_parts" and rows[2]["reason"] == rows[2]["reasons"] == ""
    assert [r["verified"] for r in rows] == ["True", "True", ""]
    assert float(rows[0]["paper_refined_E_t"]) == pytest.approx(4.2) and rows[0]["paper_refined_SR"] == "0.0"
    assert float(rows[0]["all_frames_refined_penetration_max_mm"]) == 4.0
    assert float(rows[1]["paper_raw_penetration_max_mm"]) == 3.5 and rows[1]["paper_raw_penetration_mean_mm"] == ""

    table = pq.read_table(io.BytesIO(api.client.get(f"/v1/batches/{batch_id}/report", params={"format": "parquet"},
                                                    headers=api.headers).content))  # fmt: skip
    assert table.column("outcome").to_pylist() == ["not_executable", "executable", "unknown"]
    assert table.schema.field("verified").type == "bool" and table.schema.field("reason_frame").type == "int64"
    assert table.column("paper_refined_E_r").to_pylist() == [6.0, 6.0, None]
    batch = api.client.get(f"/v1/batches/{batch_id}", headers=api.headers).json()
    assert batch["outcomes"] == {"executable": 1, "not_executable": 1, "unknown": 1}
    assert batch["metrics"]["paper"]["refined"]["n"] == 2
    assert batch["metrics"]["paper"]["refined"]["penetration_max_mm"] == pytest.approx(3.5)
