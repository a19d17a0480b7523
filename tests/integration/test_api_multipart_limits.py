"""A multipart body the form parser refuses is a documented 400 problem, not an undocumented status."""

from __future__ import annotations

from tests.support.queue_fixtures import ApiHarness


def test_too_many_multipart_fields_is_a_documented_400_problem(api: ApiHarness) -> None:
    data = {f"field{i}": "x" for i in range(12)}  # Starlette's form parser accepts at most 10 fields
    resp = api.client.post("/v1/jobs", headers=api.headers, data=data, files={"sequence": ("s.npz", b"x")})
    assert resp.status_code == 400
    assert resp.headers["content-type"].startswith("application/problem+json")
    assert resp.json()["status"] == 400
    assert "400" in api.client.get("/openapi.json").json()["paths"]["/v1/jobs"]["post"]["responses"]
