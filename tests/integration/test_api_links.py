"""Links (issue #53 item 5) on SQLite and PostgreSQL: every link in a job body and a batch body resolves, with
the media type it names; a finished job links its result, contacts, metrics, events, input and each stored
file; the summary's preview files are URLs; the outcome is in the body and filters the listing."""

from __future__ import annotations

from typing import Any

import pytest

from common.queue_types import Artifact
from tests.support.api import json_body
from tests.support.queue_fixtures import BACKENDS, ApiHarness, fake_result

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)

FILES = (
    Artifact("video.mp4", "video/mp4", b"\x00\x00\x00\x18ftypmp42"),
    Artifact("close_up.mp4", "video/mp4", b"\x00\x00\x00\x18ftypmp42close"),
    Artifact("recording.rrd", "application/octet-stream", b"RRF2"),
    Artifact("export.zip", "application/zip", b"PK\x05\x06" + b"\x00" * 18),
    Artifact("plots/errors.png", "image/png", b"\x89PNG\r\n"),
    Artifact("plots/loss_history.png", "image/png", b"\x89PNG\r\n"),
)
REASON = {"code": "object_falls_before_contact", "frame": 3, "value": 4.2, "unit": "cm",
          "message": "the object drops 4.2 cm before any finger touches it (frame 3)"}  # fmt: skip


def summary(executable: bool) -> dict[str, Any]:
    _, doc = fake_result()
    outcome = {"executable": executable, "protocol": "paper", "reasons": [] if executable else [REASON]}
    return {**doc, "outcome": outcome, "preview": {"files": [f.name for f in FILES], "seconds": 2.5}}


def run_to_end(api: ApiHarness, batch_id: str | None, executable: bool, files: tuple[Artifact, ...] = ()) -> str:
    body = {**json_body(len(files) + int(executable)), **({"batch_id": batch_id} if batch_id else {})}
    resp = api.client.post("/v1/jobs", json=body, headers=api.headers)
    assert resp.status_code == 202, resp.text
    lease = api.queue.claim("w")
    assert lease is not None
    api.queue.complete(lease.job_id, lease.lease_token, fake_result()[0], summary(executable), files)
    return str(resp.json()["id"])


def follow(api: ApiHarness, links: dict[str, Any]) -> None:
    """GET every link: 200 with the media type it names (the SSE link streams until its ``end`` event)."""
    for rel, target in links.items():
        resp = api.client.get(target["href"], headers={**api.headers, "Accept": target["type"]})
        assert resp.status_code == 200, (rel, target, resp.text[:200])
        assert resp.headers["content-type"].split(";")[0] == target["type"], (rel, target)


def test_a_finished_job_links_everything_and_every_link_resolves(api: ApiHarness) -> None:
    batch_id = api.client.post("/v1/batches", json={"name": "b"}, headers=api.headers).json()["id"]
    job_id = run_to_end(api, batch_id, True, FILES)
    job = api.client.get(f"/v1/jobs/{job_id}", headers=api.headers).json()
    assert set(job["links"]) == {"self", "events", "input", "dashboard", "batch", "result", "result_npz",
                                 "contacts", "metrics", "video", "close_up", "recording", "export",
                                 "plots"}  # fmt: skip
    assert job["links"]["video"] == {"href": f"/v1/jobs/{job_id}/video", "type": "video/mp4",
                                     "title": "preview video: raw replay and refined side by side"}  # fmt: skip
    assert job["links"]["close_up"]["href"] == f"/v1/jobs/{job_id}/close-up"
    assert job["links"]["close_up"]["type"] == "video/mp4"
    follow(api, job["links"])
    stored = sorted(FILES, key=lambda f: f.name)
    assert [(f["name"], f["type"]) for f in job["files"]] == [(f.name, f.content_type) for f in stored]
    for f in job["files"]:
        got = api.client.get(f["href"], headers=api.headers)
        assert got.status_code == 200 and got.headers["content-type"].split(";")[0] == f["type"]
        assert len(got.content) == f["size_bytes"]
    assert job["summary"]["preview"] == {"files": [f"/v1/jobs/{job_id}/{n}" for n in
                                                   ("video", "close-up", "recording", "export", "plots/errors.png",
                                                    "plots/loss_history.png")], "seconds": 2.5}  # fmt: skip
    assert job["outcome"] == {"status": "executable", "protocol": "paper", "reasons": [], "reasons_total": 0,
                              "E_t": 0.5, "E_r": None, "metrics_protocol": "all_frames"}  # fmt: skip
    assert list(job)[:4] == ["id", "batch_id", "name", "state"] and list(job)[4] == "outcome"

    # The list carries the same links and files (no summary).
    listed = api.client.get("/v1/jobs", params={"batch_id": batch_id}, headers=api.headers).json()["data"]
    assert listed[0]["links"] == job["links"] and listed[0]["files"] == job["files"] and listed[0]["summary"] is None


def test_a_waiting_job_links_only_what_exists_and_a_batch_links_its_jobs_events_and_reports(api: ApiHarness) -> None:
    batch_id = api.client.post("/v1/batches", json={"name": "b"}, headers=api.headers).json()["id"]
    failing = run_to_end(api, batch_id, False)
    queued = api.client.post("/v1/jobs", json={**json_body(7), "batch_id": batch_id}, headers=api.headers).json()
    assert set(queued["links"]) == {"self", "events", "input", "dashboard", "batch"} and queued["files"] == []
    assert queued["outcome"] is None
    follow(api, queued["links"])
    api.client.post(f"/v1/jobs/{queued['id']}:cancel", headers=api.headers)  # the batch completes

    batch = api.client.get(f"/v1/batches/{batch_id}", headers=api.headers).json()
    assert batch["outcomes"] == {"executable": 0, "not_executable": 1, "unknown": 0}
    assert set(batch["links"]) == {"self", "jobs", "not_executable", "failed", "events", "report_csv",
                                   "report_parquet", "dashboard"}  # fmt: skip
    follow(api, batch["links"])
    not_executable = api.client.get(batch["links"]["not_executable"]["href"], headers=api.headers).json()["data"]
    assert [j["id"] for j in not_executable] == [failing]
    assert not_executable[0]["outcome"]["status"] == "not_executable"
    assert not_executable[0]["outcome"]["reasons"] == [REASON]
    assert not_executable[0]["outcome"]["E_t"] == 0.5  # no paper section in fake results: all frames
    # Batches by outcome; a value outside the set is a field-named 422.
    assert [b["id"] for b in api.client.get("/v1/batches", params={"outcome": "not_executable"},
                                            headers=api.headers).json()["data"]] == [batch_id]  # fmt: skip
    assert api.client.get("/v1/batches", params={"outcome": "executable"}, headers=api.headers).json()["data"] == []
    bad = api.client.get("/v1/jobs", params={"outcome": "good"}, headers=api.headers)
    assert bad.status_code == 422 and bad.json()["errors"][0]["field"] == "outcome"


def test_metrics_carry_the_outcome(api: ApiHarness) -> None:
    job_id = run_to_end(api, None, False)
    metrics = api.client.get(f"/v1/jobs/{job_id}/metrics", headers=api.headers).json()["metrics"]
    assert metrics["outcome"]["executable"] is False and metrics["outcome"]["reasons"] == [REASON]
