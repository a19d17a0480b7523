"""``hoi-refine keys revoke``: a revoked key gets 401 "API key revoked" on every ``/v1`` endpoint, other keys
keep working, ``keys list`` marks it; which key a name or prefix picks (SQLite and PostgreSQL)."""

from __future__ import annotations

from typing import Any

import pytest

from common.api_key_store import ApiKeyStore
from common.cli import main
from common.errors import AuthenticationError, ConflictError, NotFoundError
from common.settings import get_settings
from service import deps
from tests.support.api import PROBLEM, json_body
from tests.support.queue_fixtures import BACKENDS, ApiHarness

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)


class Clock:
    """Stands in for the ``time`` module in ``service.deps`` so the key cache can be aged at will."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now


def _v1_requests(api: ApiHarness, job_id: str) -> list[tuple[str, str]]:
    """(method, path) of every ``/v1`` operation in the OpenAPI document, so a new endpoint is covered too."""
    paths: dict[str, dict[str, Any]] = api.client.app.openapi()["paths"]
    return [(method.upper(), path.replace("{job_id}", job_id))
            for path, operations in paths.items() if path.startswith("/v1") for method in operations]  # fmt: skip


def test_revoked_key_gets_401_everywhere_and_other_keys_still_work(
    api: ApiHarness, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = Clock()
    monkeypatch.setattr(deps, "time", clock)
    job_id = api.client.post("/v1/jobs", json=json_body(), headers=api.headers).json()["id"]
    other_key, other_plain = api.keys.create("colleague")
    other = {"Authorization": f"Bearer {other_plain}"}
    assert api.client.get("/v1/jobs", headers=other).status_code == 200

    key, newly = api.keys.revoke("tests")
    assert newly and key.id == api.key_id and key.revoked_at is not None
    # The server remembers a good key for KEY_CACHE_SECONDS; after that the revocation is seen.
    assert api.client.get("/v1/jobs", headers=api.headers).status_code == 200
    clock.now += deps.KEY_CACHE_SECONDS + 0.1

    listing = api.client.get("/v1/jobs", headers=api.headers)
    assert listing.status_code == 401 and listing.headers["content-type"] == PROBLEM
    assert listing.headers["WWW-Authenticate"] == "Bearer" and listing.json()["detail"] == "API key revoked"
    requests = _v1_requests(api, job_id)
    assert len(requests) >= 10 and ("POST", "/v1/jobs") in requests
    for method, path in requests:
        resp = api.client.request(method, path, headers=api.headers)
        assert resp.status_code == 401, (method, path, resp.text)
        assert resp.json()["detail"] == "API key revoked", (method, path)
    assert api.queue.get(None, job_id).state == "QUEUED"  # the :cancel and DELETE above changed nothing

    # Another key is untouched; an unknown key still reads as unknown, not as revoked.
    mine = api.client.post("/v1/jobs", json=json_body(seed=1), headers=other)
    assert mine.status_code == 202 and api.queue.get(other_key, mine.json()["id"]).state == "QUEUED"
    unknown = api.client.get("/v1/jobs", headers={"Authorization": "Bearer hoi_nobody"})
    assert unknown.status_code == 401 and unknown.json()["detail"] != "API key revoked"


def test_which_key_a_name_prefix_or_id_picks(keys: ApiKeyStore) -> None:
    a_id, a_plain = keys.create("alice")
    b_id, b_plain = keys.create("bob")
    c_id, c_plain = keys.create("bob")
    with pytest.raises(ConflictError, match="matches 2 keys") as err:
        keys.revoke("bob")
    assert b_id in str(err.value) and c_id in str(err.value)
    with pytest.raises(NotFoundError):
        keys.revoke("carol")
    with pytest.raises(NotFoundError):
        keys.revoke("hoi_")  # too short to be a prefix: it must not pick a key by luck
    assert keys.revoke(b_plain[:10] + "...")[0].id == b_id  # as `keys list` prints it
    # bob's revoked key no longer competes: the name now names his live key alone.
    assert keys.revoke("bob")[0].id == c_id
    assert keys.revoke("bob") == (keys.revoke(c_id)[0], False)  # again: nothing changes
    with pytest.raises(AuthenticationError, match="API key revoked"):
        keys.authenticate(c_plain)
    assert keys.authenticate(a_plain) == a_id
    assert keys.revoke(a_plain[:20])[1]  # part of the leaked key names it
    record, newly = keys.revoke(a_plain)  # so does the whole key
    assert not newly and record.id == a_id and record.name == "alice"
    assert all(k.revoked_at is not None for k in keys.list())


def _cli(*argv: str) -> int:
    return main(list(argv))


def test_cli_revoke_and_list(db_url: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("HOI_REFINE_DATABASE_URL", db_url)
    get_settings.cache_clear()
    assert _cli("keys", "create", "ci") == 0 and _cli("keys", "create", "ci") == 0
    first, second = capsys.readouterr().out.split()
    assert _cli("keys", "revoke", "ci") == 2  # two keys are called ci
    err = capsys.readouterr().err
    assert "matches 2 keys" in err and first[:10] in err and second[:10] in err
    assert _cli("keys", "revoke", "nobody") == 2
    assert "no API key" in capsys.readouterr().err

    assert _cli("keys", "revoke", first[:10]) == 0
    assert "revoked" in capsys.readouterr().out
    assert _cli("keys", "list") == 0
    lines: dict[str, Any] = {line.split()[1]: line for line in capsys.readouterr().out.splitlines()}
    assert "REVOKED" in lines[f"{first[:10]}..."] and "REVOKED" not in lines[f"{second[:10]}..."]
    assert _cli("keys", "revoke", first[:10]) == 0
    assert "already revoked" in capsys.readouterr().out
