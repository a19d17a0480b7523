"""Job artifacts (issue #18 item 4): stored with the result in the worker's token-checked transaction, served
under /v1/jobs/{id}/video | recording | export | plots to the owning key only; the dashboard page at /ui.
Runs on SQLite and PostgreSQL (``BACKENDS``)."""

from __future__ import annotations

from typing import Any

import pytest

from common.api_key_store import ApiKeyStore
from common.errors import ConflictError, LeaseLostError, NotFoundError
from common.job_options import JobOptions
from common.queue import JobQueue
from common.queue_types import Artifact
from tests.support.queue_fixtures import BACKENDS, ApiHarness, fake_result, submit_tiny, tiny_payload
from worker.runtime.jobs import SelfTestJob, make_artifact_function, refine_preview
from worker.runtime.loop import WorkerLoop

on_both_backends = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)

FILES = [
    Artifact("video.mp4", "video/mp4", b"\x00\x00\x00\x18ftypmp42" + b"v" * 100),
    Artifact("plots/errors.png", "image/png", b"\x89PNG\r\n\x1a\nerrors"),
    Artifact("plots/contact_forces.png", "image/png", b"\x89PNG\r\n\x1a\nforces"),
    Artifact("recording.rrd", "application/octet-stream", b"RRF2" + b"r" * 50),
    Artifact("export.zip", "application/zip", b"PK\x03\x04export"),
]


def _finish(queue: JobQueue, owner: str, files: list[Artifact]) -> str:
    job_id = submit_tiny(queue, owner)
    claimed = queue.claim("w1")
    assert claimed is not None and claimed.job_id == job_id
    blob, summary = fake_result()
    queue.complete(job_id, claimed.lease_token, blob, summary, artifacts=files)
    return job_id


@on_both_backends
def test_artifacts_are_stored_with_the_result_and_scoped_to_the_owner(
    queue: JobQueue, keys: ApiKeyStore, owner: str
) -> None:
    job_id = _finish(queue, owner, FILES)
    listed = queue.list_artifacts(owner, job_id)
    assert [a.name for a in listed] == sorted(a.name for a in FILES)
    assert all(a.data == b"" and a.size_bytes > 0 for a in listed)
    video = queue.get_artifact(owner, job_id, "video.mp4")
    assert video.data == FILES[0].data and video.content_type == "video/mp4"
    other = keys.create("someone else")[0]
    with pytest.raises(NotFoundError):
        queue.get_artifact(other, job_id, "video.mp4")
    with pytest.raises(NotFoundError):
        queue.list_artifacts(other, job_id)
    with pytest.raises(NotFoundError, match="preview"):
        queue.get_artifact(owner, job_id, "plots/nothing.png")
    queue.delete(owner, job_id)
    with pytest.raises(NotFoundError):
        queue.list_artifacts(None, job_id)


@on_both_backends
def test_a_lost_lease_writes_no_artifact_and_a_queued_job_has_none(queue: JobQueue, owner: str) -> None:
    job_id = submit_tiny(queue, owner)
    with pytest.raises(ConflictError):
        queue.get_artifact(owner, job_id, "video.mp4")
    claimed = queue.claim("w1")
    assert claimed is not None
    blob, summary = fake_result()
    with pytest.raises(LeaseLostError):
        queue.complete(job_id, "not-the-token", blob, summary, artifacts=FILES)
    assert queue.list_artifacts(owner, job_id) == []
    with pytest.raises(ValueError, match="unique"):
        queue.complete(job_id, claimed.lease_token, blob, summary, artifacts=[FILES[0], FILES[0]])
    assert queue.get(owner, job_id).state == "RUNNING"  # the failed transaction changed nothing


@on_both_backends
def test_routes_serve_the_files_to_the_owner_only(api: ApiHarness) -> None:
    job_id = _finish(api.queue, api.key_id, FILES)
    c, h = api.client, api.headers
    r = c.get(f"/v1/jobs/{job_id}/video", headers=h)
    assert r.status_code == 200 and r.headers["content-type"] == "video/mp4" and r.content == FILES[0].data
    r = c.get(f"/v1/jobs/{job_id}/recording", headers=h)
    assert r.status_code == 200 and r.content == FILES[3].data and ".rrd" in r.headers["content-disposition"]
    r = c.get(f"/v1/jobs/{job_id}/export", headers=h)
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    plots = c.get(f"/v1/jobs/{job_id}/plots", headers=h).json()
    assert [p["name"] for p in plots["plots"]] == ["contact_forces.png", "errors.png"]
    r = c.get(plots["plots"][1]["url"], headers=h)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png" and r.content == FILES[1].data
    assert c.get(f"/v1/jobs/{job_id}/plots/..%2Fvideo.mp4", headers=h).status_code in (404, 422)
    other = api.other_key_headers()
    for path in ("video", "recording", "export", "plots", "plots/errors.png"):
        r = c.get(f"/v1/jobs/{job_id}/{path}", headers=other)
        assert r.status_code == 404, path
        assert r.headers["content-type"] == "application/problem+json"
    assert c.get(f"/v1/jobs/{job_id}/video").status_code == 401


@on_both_backends
def test_routes_before_success_and_without_a_preview(api: ApiHarness) -> None:
    queued = submit_tiny(api.queue, api.key_id)
    r = api.client.get(f"/v1/jobs/{queued}/video", headers=api.headers)
    assert r.status_code == 409
    assert api.client.get(f"/v1/jobs/{queued}/plots", headers=api.headers).status_code == 409
    api.queue.cancel(api.key_id, queued)
    done = _finish(api.queue, api.key_id, [])
    r = api.client.get(f"/v1/jobs/{done}/video", headers=api.headers)
    assert r.status_code == 404 and "preview" in r.json()["detail"]
    assert api.client.get(f"/v1/jobs/{done}/plots", headers=api.headers).json()["plots"] == []


@on_both_backends
def test_dashboard_page_is_served(api: ApiHarness) -> None:
    r = api.client.get("/ui")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "Authorization" in r.text and "/v1/jobs" in r.text  # it talks to the API with the entered key
    assert api.client.get("/", follow_redirects=False).headers["location"] == "/ui"
    assert "/ui" not in api.client.get("/openapi.json").json()["paths"]


@on_both_backends
def test_the_worker_loop_stores_the_preview_or_records_why_not(queue: JobQueue, owner: str) -> None:
    calls: list[JobOptions] = []

    def preview(result: bytes, options: JobOptions) -> list[Any]:
        calls.append(options)
        if options.seed == 1:
            raise RuntimeError("no OpenGL here")
        return [Artifact("video.mp4", "video/mp4", b"mp4:" + result[:10])]

    loop = WorkerLoop(queue, SelfTestJob(), "w", lease_seconds=30, idle_poll_seconds=0.01, artifact_fn=preview)
    ok, _ = queue.submit(owner, tiny_payload(0), JobOptions(seed=0, max_generations=1), None, "ok", 5)
    assert loop.run_once() == "succeeded"
    assert queue.get_artifact(owner, ok.id, "video.mp4").data.startswith(b"mp4:")
    assert queue.get(owner, ok.id).summary["preview"]["files"] == ["video.mp4"]  # type: ignore[index]
    broken, _ = queue.submit(owner, tiny_payload(1), JobOptions(seed=1, max_generations=1), None, "broken", 5)
    assert loop.run_once() == "succeeded"  # a failed preview does not fail the job
    assert "no OpenGL here" in queue.get(owner, broken.id).summary["preview"]["error"]  # type: ignore[index]
    assert queue.list_artifacts(owner, broken.id) == []
    skipped, _ = queue.submit(owner, tiny_payload(2), JobOptions(seed=2, max_generations=1, preview_video=False),
                              None, "no preview", 5)  # fmt: skip
    assert loop.run_once() == "succeeded"
    assert queue.list_artifacts(owner, skipped.id) == []
    assert "preview" not in queue.get(owner, skipped.id).summary  # type: ignore[operator]
    assert [o.seed for o in calls] == [0, 1]  # the job that asked for no preview never reached the renderer


def test_preview_option_and_job_kinds() -> None:
    assert make_artifact_function("refine") is refine_preview
    assert make_artifact_function("selftest") is None
    assert refine_preview(b"not even a result", JobOptions(preview_video=False)) == []
    assert JobOptions().preview_video is True
