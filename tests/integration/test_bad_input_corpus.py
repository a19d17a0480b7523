"""The bad-input corpus (``tests/corpus/bad_inputs``, issue #16) through the API on SQLite and PostgreSQL:
every case gets its expected status with a problem naming its field, no 5xx, no server path (nor any reference
to the source) in the answer,
and nothing is queued. The committed files must be exactly what ``tests/corpus/make_bad_inputs.py`` writes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.corpus.make_bad_inputs import OUT, cases
from tests.support.queue_fixtures import BACKENDS, ApiHarness
from tests.support.user_text import source_references

MANIFEST: list[dict[str, Any]] = json.loads((OUT / "manifest.json").read_text())
REPO = str(Path(__file__).resolve().parents[2])


def post_case(api: ApiHarness, case: dict[str, Any]) -> Any:
    blob = (OUT / case["file"]).read_bytes()
    if case["kind"] == "json":
        headers = {**api.headers, "Content-Type": "application/json"}
        return api.client.post("/v1/jobs", content=blob, headers=headers)
    data = {"options": case["options"]} if "options" in case else {}
    files = {"sequence": (case["file"], blob, "application/octet-stream")}
    return api.client.post("/v1/jobs", headers=api.headers, files=files, data=data)


def test_corpus_is_what_the_script_writes() -> None:
    files, manifest = cases()
    assert len(manifest) >= 50
    assert manifest == MANIFEST
    on_disk = {p.name for p in OUT.iterdir()} - {"manifest.json"}
    assert on_disk == set(files)
    for name, data in files.items():
        assert (OUT / name).read_bytes() == data, name


@pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)
def test_every_bad_input_is_refused_with_its_field(api: ApiHarness, tmp_path: Path) -> None:
    failures = []
    for case in MANIFEST:
        resp = post_case(api, case)
        doc = resp.json()
        fields = [e["field"] for e in doc.get("errors") or []]
        ok = (
            resp.status_code == case["status"]
            and resp.headers["content-type"].startswith("application/problem+json")
            and case["field"] in fields
            and REPO not in resp.text and str(tmp_path) not in resp.text
            and not source_references(resp.text)
        )  # fmt: skip
        if not ok:
            failures.append(f"{case['file']}: {resp.status_code} {resp.text[:300]}")
    assert not failures, "\n".join(failures)
    assert api.client.get("/v1/jobs", headers=api.headers).json()["count"] == 0
    # The connection and the service are fine afterwards.
    assert api.client.get("/healthz").status_code == 200


@pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)
def test_hostile_job_ids_and_page_tokens(api: ApiHarness) -> None:
    """Ids and page tokens come from the client too: NUL (which PostgreSQL cannot compare), controls and
    overlong text answer like a missing job (404) or a bad token (422), never 500, and are echoed escaped."""
    import base64
    from urllib.parse import quote

    for raw in ("\x00abc", "a\u202eb", "x" * 5000, "../../etc/passwd", "' OR 1=1 --"):
        job = quote(raw, safe="")
        for method, path in [("GET", f"/v1/jobs/{job}"), ("POST", f"/v1/jobs/{job}:cancel"),
                             ("POST", f"/v1/jobs/{job}:retry"), ("DELETE", f"/v1/jobs/{job}"),
                             ("GET", f"/v1/jobs/{job}/result"), ("GET", f"/v1/jobs/{job}/contacts"),
                             ("GET", f"/v1/jobs/{job}/metrics"), ("GET", f"/v1/jobs/{job}/events"),
                             ("GET", f"/v1/jobs/{job}/input")]:  # fmt: skip
            resp = api.client.request(method, path, headers=api.headers)
            assert resp.status_code == 404, (method, path[:80], resp.status_code, resp.text[:200])
            detail = resp.json().get("detail", "")  # a path with '/' in it matches no route: plain 404
            assert "\u202e" not in detail and "\x00" not in detail
    for token_text in ("2026-01-01T00:00:00+00:00|\x00", "2026-01-01T00:00:00+00:00|a\u202e", "x|y"):
        token = base64.urlsafe_b64encode(token_text.encode()).decode().rstrip("=")
        resp = api.client.get("/v1/jobs", params={"page_token": token}, headers=api.headers)
        assert resp.status_code == 422 and resp.json()["errors"][0]["field"] == "page_token", resp.text
