"""The job API carries each result's proof (issue #15 item 2): the worker verifies the finished result from a
fresh replay before storing it, and the job's metrics say so, with the digests a downloaded copy is checked
against. On SQLite and PostgreSQL, the refinement (not the self-test job) behind a real queue and the API."""

from __future__ import annotations

import pytest

from common.job_options import JobOptions
from common.result_format import content_digest, read_summary
from common.sequence_io import sequence_to_npz_bytes
from tests.support.queue_fixtures import BACKENDS, ApiHarness
from worker.runtime.jobs import RefineJob, verification
from worker.runtime.loop import WorkerLoop
from worker.verification import check_result

BACKEND = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)


def _push_payload() -> bytes:
    from tests.support.synthetic_push import push_sequence

    return sequence_to_npz_bytes(push_sequence(frames=12))


@BACKEND
def test_a_refined_job_reports_its_verification_and_the_download_matches(api: ApiHarness) -> None:
    options = JobOptions(seed=1, popsize=4, max_generations=1, restarts=0)
    job, _ = api.queue.submit(api.key_id, _push_payload(), options, None, "push", 12)
    loop = WorkerLoop(api.queue, RefineJob(1), worker_id="w1", lease_seconds=30, idle_poll_seconds=0.05)
    assert loop.run_once() == "succeeded"

    metrics = api.client.get(f"/v1/jobs/{job.id}/metrics", headers=api.headers).json()["metrics"]
    proof = metrics["verification"]
    assert proof["verified"] is True and proof["exact"] is True and proof["failures"] == []
    assert proof["max_object_deviation_m"] == 0.0 and proof["checked_fields"] > 20
    # Both protocols, the first attempt and the plausibility figures reach the API too.
    refined = metrics["refined"]
    assert refined["paper"]["first_frame"] == 10 and "success_first_attempt" in refined
    assert "penetration_max_mm" in refined and "hand_only_fraction" in refined
    state = api.client.get(f"/v1/jobs/{job.id}", headers=api.headers).json()
    assert state["summary"]["metrics"]["verification"]["verified"] is True

    resp = api.client.get(f"/v1/jobs/{job.id}/result", params={"format": "npz"}, headers=api.headers)
    assert resp.status_code == 200
    blob = resp.content
    assert content_digest(blob) == proof["content_sha256"]
    report = check_result(blob)  # what a user runs on the downloaded file
    assert report.failures == [] and report.digest == proof["checked_sha256"]
    assert "verification" not in read_summary(blob)["metrics"]  # the proof lives beside the file, not in it


def test_a_result_that_does_not_reproduce_is_flagged_with_the_field() -> None:
    from common.result_format import read_arrays, write_result_npz
    from tests.support.synthetic_push import push_sequence
    from worker.refine.run import refine_sequence

    outcome = refine_sequence(push_sequence(frames=12), JobOptions(popsize=4, max_generations=1, restarts=0))
    arrays = read_arrays(outcome.to_npz_bytes())
    arrays["right_wrist_pos"] = arrays["right_wrist_pos"] + 0.05
    proof = verification(write_result_npz(arrays, outcome.summary))
    assert proof["verified"] is False
    assert any(f.startswith("right_wrist_pos") for f in proof["failures"])
