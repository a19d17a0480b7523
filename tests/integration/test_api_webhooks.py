"""Webhooks on SQLite and PostgreSQL with loopback receivers: deliveries carry Standard Webhooks signatures
that the ``standardwebhooks`` package verifies, a 500 is retried with backoff and logged, batch completion
is announced once, and a receiver that hangs holds neither the queue nor deliveries to other receivers."""

from __future__ import annotations

import socket
from datetime import datetime

import pytest
from standardwebhooks.webhooks import Webhook, WebhookVerificationError

from common.settings import Settings
from tests.support.api import json_body, run_job, wait_until
from tests.support.live_server import webhook_receiver
from tests.support.queue_fixtures import BACKENDS, ApiHarness

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)


@pytest.fixture
def api_settings() -> Settings:
    """The ``api`` harness (tests/support/queue_fixtures.py) with a fast webhook dispatcher: TestClient runs the
    app's lifespan, so the dispatcher task runs. The receivers listen on loopback, which the operator setting
    allows here (webhooks go to public addresses only by default)."""
    return Settings(webhook_poll_seconds=0.05, webhook_backoff_seconds=0.05, webhook_timeout_seconds=30,
                    max_active_jobs_per_key=50, webhook_allow_targets="127.0.0.1")  # fmt: skip


def test_signed_deliveries_verify_and_a_500_is_retried(api: ApiHarness) -> None:
    with webhook_receiver(statuses=[500]) as rec:
        made = api.client.post("/v1/webhooks", json={"url": rec.url}, headers=api.headers)
        assert made.status_code == 201, made.text
        hook = made.json()
        assert hook["secret"].startswith("whsec_")
        assert "secret" not in api.client.get("/v1/webhooks", headers=api.headers).json()["data"][0]
        batch_id = api.client.post("/v1/batches", json={"name": "b"}, headers=api.headers).json()["id"]
        body = {**json_body(), "batch_id": batch_id}
        job_id = api.client.post("/v1/jobs", json=body, headers=api.headers).json()["id"]
        # The batch's state is read when its jobs' events are fanned out: wait for that before running the
        # job, or ACTIVE and COMPLETED would be seen together and only batch.completed sent.
        rec.wait_for(1)
        run_job(api.queue, job_id)
        # job.queued (answered 500, then again 200), job.running, job.succeeded, batch.active, batch.completed
        rec.wait_for(6)
        verifier = Webhook(hook["secret"])
        payloads = [verifier.verify(body, headers) for headers, body in rec.requests]
        wrong = Webhook("whsec_" + "A" * 43)
        with pytest.raises(WebhookVerificationError):
            wrong.verify(rec.requests[0][1], rec.requests[0][0])
        tampered = rec.requests[0][1].replace(b'"type":"', b'"type":"x')
        assert tampered != rec.requests[0][1]
        with pytest.raises(WebhookVerificationError):
            verifier.verify(tampered, rec.requests[0][0])
        # The retry of the first request (answered 500) is the same message: same webhook-id and body.
        retries = [i for i, (h, _) in enumerate(rec.requests) if h["webhook-id"] == rec.requests[0][0]["webhook-id"]]
        assert len(retries) == 2 and rec.requests[retries[1]][1] == rec.requests[0][1]
        types = [p["type"] for p in payloads[1:]]
        assert sorted(types) == sorted(["job.queued", "job.running", "job.succeeded", "batch.active",
                                        "batch.completed"])  # fmt: skip
        done = next(p for p in payloads if p["type"] == "job.succeeded")
        assert done["data"]["job_id"] == job_id and done["data"]["batch_id"] == batch_id
        assert done["data"]["outcome"] == "unknown"  # the fake result carries no outcome
        completed = next(p for p in payloads if p["type"] == "batch.completed")
        assert completed["data"]["counts"] == {"SUCCEEDED": 1}

        log_url = f"/v1/webhooks/{hook['id']}/deliveries"
        log = wait_until(
            lambda: (d := api.client.get(log_url, headers=api.headers).json()["data"])
            and all(x["state"] == "DELIVERED" for x in d) and len(d) == 5 and d,
            "every delivery to be logged DELIVERED",
        )
        (retried,) = [d for d in log if d["attempts"] == 2]
        assert retried["msg_id"] == rec.requests[0][0]["webhook-id"]
        assert [a["status"] for a in retried["log"]] == [500, 200] and retried["log"][0]["error"] == "HTTP 500"
        assert all(d["attempts"] == 1 and len(d["log"]) == 1 for d in log if d is not retried)
        assert api.client.get(log_url, headers=api.other_key_headers()).status_code == 404
        assert api.client.delete(f"/v1/webhooks/{hook['id']}", headers=api.headers).status_code == 204
        assert api.client.get(log_url, headers=api.headers).status_code == 404


def test_a_hanging_receiver_blocks_neither_the_queue_nor_other_webhooks(api: ApiHarness) -> None:
    with webhook_receiver(hang=True) as stuck, webhook_receiver() as healthy:
        for url, types in ((stuck.url, []), (healthy.url, ["job.succeeded"])):
            resp = api.client.post("/v1/webhooks", json={"url": url, "event_types": types}, headers=api.headers)
            assert resp.status_code == 201
        ids = [api.client.post("/v1/jobs", json=json_body(i), headers=api.headers).json()["id"] for i in range(3)]
        stuck.wait_for(1)  # the first delivery is now held open by the stuck receiver
        for job_id in ids:  # a worker finishes its jobs meanwhile: no queue call waits for a webhook
            run_job(api.queue, job_id)
        states = {api.client.get(f"/v1/jobs/{j}", headers=api.headers).json()["state"] for j in ids}
        assert states == {"SUCCEEDED"}
        healthy.wait_for(3)  # and the other receiver got every job.succeeded while the first still hangs
        assert not stuck.release.is_set()
        assert sorted(h["webhook-id"] for h, _ in healthy.requests) == sorted({h["webhook-id"]
                                                                            for h, _ in healthy.requests})  # fmt: skip
        hooks = api.client.get("/v1/webhooks", headers=api.headers).json()["data"]
        stuck_id = next(h["id"] for h in hooks if h["url"] == stuck.url)
        pending = api.client.get(f"/v1/webhooks/{stuck_id}/deliveries", headers=api.headers).json()["data"]
        in_flight = [d for d in pending if d["attempts"] == 1 and not d["log"]]
        assert in_flight and all(d["state"] == "PENDING" for d in pending)
        stuck.release.set()
        wait_until(
            lambda: all(d["state"] == "DELIVERED" for d in api.client.get(
                f"/v1/webhooks/{stuck_id}/deliveries", headers=api.headers).json()["data"]),
            "the stuck receiver's deliveries to go through once it answers",
        )  # fmt: skip


def test_webhook_input_is_validated(api: ApiHarness) -> None:
    bad = api.client.post("/v1/webhooks", json={"url": "ftp://x", "event_types": ["job.exploded"]},
                          headers=api.headers)  # fmt: skip
    assert bad.status_code == 422
    assert {e["field"] for e in bad.json()["errors"]} == {"url", "event_types[0]"}


def test_a_dead_receiver_is_retried_with_backoff_then_given_up(api: ApiHarness) -> None:
    store = api.client.app.state.webhooks
    store.settings = store.settings.model_copy(update={"webhook_max_attempts": 3})
    with socket.socket() as s:  # a port nothing listens on: every attempt is refused
        s.bind(("127.0.0.1", 0))
        dead = f"http://127.0.0.1:{s.getsockname()[1]}/hook"
    hook = api.client.post("/v1/webhooks", json={"url": dead, "event_types": ["job.succeeded"]},
                           headers=api.headers).json()  # fmt: skip
    job_id = api.client.post("/v1/jobs", json=json_body(), headers=api.headers).json()["id"]
    run_job(api.queue, job_id)
    assert api.client.get(f"/v1/jobs/{job_id}", headers=api.headers).json()["state"] == "SUCCEEDED"
    url = f"/v1/webhooks/{hook['id']}/deliveries"
    (failed,) = wait_until(
        lambda: [d for d in api.client.get(url, headers=api.headers).json()["data"] if d["state"] == "FAILED"],
        "the delivery to be given up",
    )
    assert failed["attempts"] == 3 and len(failed["log"]) == 3 and failed["last_status"] is None
    assert all(a["error"].startswith("ConnectError") for a in failed["log"])
    times = [datetime.fromisoformat(a["at"]) for a in failed["log"]]
    assert times == sorted(times)  # one attempt after another, each after its backoff
