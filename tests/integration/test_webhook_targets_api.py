"""Webhooks cannot reach inside (issue #56), on SQLite and PostgreSQL: registration refuses non-public targets
with a 422 naming ``url``; each delivery resolves and checks again and connects to the checked address (so a
name rebound to loopback after registration is refused), never follows a redirect, and is bounded in bytes
read and in time. The allow setting lets a named test receiver through. Names resolve through the policy's
resolver, which these tests replace (``app.state.webhooks.targets.resolver``); nothing leaves loopback."""

from __future__ import annotations

import ipaddress
import ssl
from pathlib import Path
from typing import Any

import pytest

from common.settings import Settings
from common.webhook_targets import IPAddress
from tests.support.api import json_body, run_job, wait_until
from tests.support.live_server import misbehaving_receiver, throwaway_certificates, webhook_receiver
from tests.support.queue_fixtures import BACKENDS, ApiHarness

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)

RECEIVER = "receiver.test"
#: Also allowed and resolving to loopback, but not the name on the test receiver's certificate.
OTHER = "other.test"
#: Where names resolve to in these tests; a name missing here does not resolve.
NAMES: dict[str, list[str]] = {}


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, ssl.SSLContext] | None:
    """A test CA and a server certificate for ``RECEIVER`` (None without the openssl command)."""
    return throwaway_certificates(tmp_path_factory.mktemp("tls"), RECEIVER)


@pytest.fixture
def api_settings(certificates: tuple[Path, ssl.SSLContext] | None) -> Settings:
    """A fast dispatcher with small bounds; only the named test receivers are allowed besides public addresses,
    and https receivers are verified against the test CA."""
    return Settings(webhook_poll_seconds=0.05, webhook_backoff_seconds=0.05, webhook_timeout_seconds=2.0,
                    webhook_connect_timeout_seconds=1.0, webhook_max_response_bytes=4096, webhook_max_attempts=2,
                    webhook_allow_targets=f"{RECEIVER},{OTHER}",
                    webhook_ca_file=None if certificates is None else certificates[0])  # fmt: skip


@pytest.fixture(autouse=True)
def names(api: ApiHarness) -> dict[str, list[str]]:
    table = {RECEIVER: ["127.0.0.1"], OTHER: ["127.0.0.1"], "public.example": ["151.101.1.69"]}

    def resolve(host: str, port: int) -> list[IPAddress]:
        if host not in table:
            raise OSError(f"{host} does not resolve in this test")
        return [ipaddress.ip_address(a) for a in table[host]]

    api.client.app.state.webhooks.targets.resolver = resolve
    return table


def register(api: ApiHarness, url: str, **extra: Any) -> Any:
    return api.client.post("/v1/webhooks", json={"url": url, **extra}, headers=api.headers)


def deliveries(api: ApiHarness, hook_id: str) -> list[dict[str, Any]]:
    return list(api.client.get(f"/v1/webhooks/{hook_id}/deliveries", headers=api.headers).json()["data"])


def settled(api: ApiHarness, hook_id: str) -> dict[str, Any]:
    """The webhook's one delivery, once it is DELIVERED or FAILED."""
    return wait_until(
        lambda: (d := deliveries(api, hook_id)) and d[0]["state"] != "PENDING" and d[0], "the delivery to settle"
    )


def succeed_one_job(api: ApiHarness) -> None:
    job_id = api.client.post("/v1/jobs", json=json_body(), headers=api.headers).json()["id"]
    run_job(api.queue, job_id)


def to_receiver(url: str) -> str:
    """The same receiver under the allowed test name instead of 127.0.0.1."""
    return url.replace("127.0.0.1", RECEIVER)


def test_non_public_targets_are_refused_at_registration(api: ApiHarness, names: dict[str, list[str]]) -> None:
    names["inside.example"] = ["10.0.0.7"]
    names["metadata.example"] = ["8.8.8.8", "169.254.169.254"]
    names["localhost"] = ["127.0.0.1", "::1"]
    refused = {
        "http://127.0.0.1:9/hook": "loopback", "http://localhost/hook": "resolves to 127.0.0.1",
        "http://[::1]:5432/": "loopback", "http://169.254.169.254/latest/meta-data/": "link-local",
        "http://10.1.2.3/": "private", "http://[fd00::1]/": "private", "http://224.0.0.1/": "multicast",
        "http://0.0.0.0:8000/": "unspecified", "http://[::]/": "unspecified", "http://240.0.0.1/": "reserved",
        "http://[::ffff:127.0.0.1]/": "loopback (IPv4 127.0.0.1 inside IPv6)",
        "http://[::ffff:169.254.169.254]/": "link-local", "http://inside.example/": "resolves to 10.0.0.7",
        "http://nowhere.example/": "does not resolve",
        "https://metadata.example/": "resolves to 169.254.169.254, which is link-local",
    }  # fmt: skip
    for url, why in refused.items():
        resp = register(api, url)
        assert resp.status_code == 422, (url, resp.text)
        (error,) = resp.json()["errors"]
        assert error["field"] == "url" and why in error["problem"], (url, error)
    assert api.client.get("/v1/webhooks", headers=api.headers).json()["data"] == []
    assert register(api, "https://public.example/hook").status_code == 201
    assert register(api, "http://8.8.8.8/hook").status_code == 201


def test_the_allow_setting_lets_a_named_receiver_through(api: ApiHarness) -> None:
    with webhook_receiver() as rec:
        assert register(api, rec.url).status_code == 422  # its address itself is not allowed
        url = to_receiver(rec.url)
        hook = register(api, url, event_types=["job.succeeded"]).json()
        succeed_one_job(api)
        rec.wait_for(1)
        headers, _ = rec.requests[0]
        assert headers["host"] == url.split("/")[2]  # the URL's host, although the connection went to 127.0.0.1
        assert settled(api, hook["id"])["state"] == "DELIVERED"


def test_https_to_a_pinned_address_verifies_the_urls_host_name(
    api: ApiHarness, certificates: tuple[Path, ssl.SSLContext] | None
) -> None:
    """The connection goes to the checked address, and TLS still checks the certificate against the URL's host:
    the receiver's certificate names receiver.test, so the same receiver under another allowed name fails."""
    if certificates is None:
        pytest.skip("no openssl command to make test certificates")
    with webhook_receiver(tls=certificates[1]) as rec:
        good = register(api, to_receiver(rec.url), event_types=["job.succeeded"]).json()
        wrong = register(api, rec.url.replace("127.0.0.1", OTHER), event_types=["job.succeeded"]).json()
        succeed_one_job(api)
        assert settled(api, good["id"])["state"] == "DELIVERED"
        failed = settled(api, wrong["id"])
        assert failed["state"] == "FAILED" and all("CERTIFICATE_VERIFY_FAILED" in a["error"] for a in failed["log"])
        assert len(rec.requests) == 1 and rec.requests[0][0]["host"] == to_receiver(rec.url).split("/")[2]


def test_a_name_rebound_to_loopback_after_registration_is_refused_at_delivery(
    api: ApiHarness, names: dict[str, list[str]]
) -> None:
    with webhook_receiver() as rec:
        port = rec.url.split(":")[2].split("/")[0]
        names["rebind.example"] = ["151.101.1.69"]
        hook = register(api, f"http://rebind.example:{port}/hook", event_types=["job.succeeded"]).json()
        assert "id" in hook, hook
        names["rebind.example"] = ["127.0.0.1"]  # the name now points inside
        succeed_one_job(api)
        failed = settled(api, hook["id"])
        assert failed["state"] == "FAILED" and failed["attempts"] == 2, failed
        assert all("refused target" in a["error"] and "127.0.0.1, which is loopback" in a["error"]
                   for a in failed["log"]), failed["log"]  # fmt: skip
        assert rec.requests == []  # nothing reached the loopback receiver


def test_redirects_are_not_followed(api: ApiHarness) -> None:
    with webhook_receiver() as inside, webhook_receiver(statuses=[307, 307], location=inside.url) as rec:
        hook = register(api, to_receiver(rec.url), event_types=["job.succeeded"]).json()
        succeed_one_job(api)
        failed = settled(api, hook["id"])
        assert failed["state"] == "FAILED" and [a["status"] for a in failed["log"]] == [307, 307]
        assert failed["log"][0]["error"] == "HTTP 307 (redirects are not followed)"
        assert len(rec.requests) == 2 and inside.requests == []


def test_an_answer_that_never_ends_is_read_only_up_to_the_bound(api: ApiHarness) -> None:
    with misbehaving_receiver("endless") as rec:
        hook = register(api, to_receiver(rec.url), event_types=["job.succeeded"]).json()
        succeed_one_job(api)
        done = settled(api, hook["id"])
        # Unbounded, the read would run into the deadline and the delivery be retried, then given up.
        assert done["state"] == "DELIVERED" and done["attempts"] == 1, done
        assert done["log"][0]["status"] == 200 and done["log"][0]["error"] is None


def test_an_answer_that_comes_too_slowly_hits_the_deadline(api: ApiHarness) -> None:
    with misbehaving_receiver("dribble") as rec:
        hook = register(api, to_receiver(rec.url), event_types=["job.succeeded"]).json()
        succeed_one_job(api)
        # Every byte arrives well within the read timeout, so only the delivery's deadline ends each attempt.
        failed = settled(api, hook["id"])
        assert failed["state"] == "FAILED" and rec.requests == 2, (failed, rec.requests)
        assert all(a["error"] == "timed out: no complete answer within 2 s" for a in failed["log"]), failed["log"]
