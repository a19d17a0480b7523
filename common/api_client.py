"""The one client of the hoi-refine REST API (``/v1``): used by ``hoi-refine submit``, the demo and the tests
that talk to a live server. Synchronous (httpx), with the retry policy of bulk submission:

* Connection errors, timeouts and 5xx answers are retried with capped exponential backoff and jitter (safe
  for ``POST /v1/jobs`` too: it carries an Idempotency-Key, so a repeated request names the same job).
* 429 answers wait for ``Retry-After`` and try again; they do not use up the error budget, because the server
  is saying "not yet" (for example the per-key limit of active jobs), not "broken".
* Any other 4xx raises ``ApiError`` with the problem+json detail at once: retrying cannot fix the request.

Every wait goes through ``stop.wait`` so that Ctrl-C (which sets ``stop``) ends a backoff at once.
One ``httpx.Client`` is shared by all worker threads (it is thread-safe and pools connections).
"""

from __future__ import annotations

import email.utils
import json
import random
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import httpx

from common.errors import ApiError, HoiRefineError
from common.job_options import JobOptions
from common.job_state import FINISHED

#: Longest wait honoured from one ``Retry-After`` (a server asking for more is asked again after this).
MAX_RETRY_AFTER_S = 300.0


def options_json(options: JobOptions) -> str:
    """Canonical JSON of the options: every field (defaults included), sorted keys, no spaces."""
    return json.dumps(options.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))


def options_key_json(options: JobOptions) -> str:
    """Canonical JSON of the options that differ from their defaults: what identifies a job's options. A release
    that adds an option (with a default) leaves it unchanged, so a resumed batch keeps its jobs."""
    return json.dumps(options.model_dump(mode="json", exclude_defaults=True), sort_keys=True, separators=(",", ":"))


class Stopped(HoiRefineError):
    """The run was asked to stop (Ctrl-C) while this request was waiting to be retried."""


@dataclass(frozen=True)
class RetryPolicy:
    #: Attempts after the first for connection errors and 5xx.
    max_retries: int = 6
    backoff_base_s: float = 0.5
    backoff_max_s: float = 30.0

    def backoff(self, attempt: int) -> float:
        # "Full jitter" halved: spread retries of many threads without ever retrying at once.
        cap = min(self.backoff_max_s, self.backoff_base_s * 2**attempt)
        return cap * random.uniform(0.5, 1.0)


def parse_retry_after(value: str | None) -> float | None:
    """``Retry-After`` as seconds (delta-seconds or HTTP-date), ``None`` when absent or unreadable."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


def wait_until_ready(
    base_url: str,
    timeout_s: float,
    *,
    alive: Callable[[], bool] | None = None,
    stop: threading.Event | None = None,
    paths: tuple[str, ...] = ("/readyz",),
    interval_s: float = 0.3,
) -> httpx.Response | None:
    """Poll a starting server until one of ``paths`` answers 200, and return that answer.

    ``None`` when ``stop`` is set first. ``ApiError`` when ``alive()`` turns False (the server's process
    ended) or after ``timeout_s``. Needs no API key: the health endpoints are public.
    """
    deadline = time.monotonic() + timeout_s
    with httpx.Client(base_url=base_url.rstrip("/"), timeout=2.0) as http:
        while stop is None or not stop.is_set():
            if alive is not None and not alive():
                raise ApiError(f"the API at {base_url} exited before it was ready")
            for path in paths:
                try:
                    resp = http.get(path)
                except httpx.HTTPError:
                    break  # not listening yet
                if resp.status_code == 200:
                    return resp
            if time.monotonic() >= deadline:
                raise ApiError(f"the API did not answer at {base_url} within {timeout_s:.0f} s")
            if stop is not None:
                stop.wait(interval_s)
            else:
                time.sleep(interval_s)
    return None


def _problem(resp: httpx.Response) -> dict[str, Any]:
    try:
        doc = resp.json()
    except ValueError:
        return {"detail": resp.text[:500]}
    return doc if isinstance(doc, dict) else {"detail": doc}


class ApiClient:
    """``/v1`` jobs API with Bearer auth. ``transport`` lets tests substitute ``httpx.MockTransport``."""

    def __init__(
        self,
        base_url: str,
        api_key: str,
        *,
        retry: RetryPolicy | None = None,
        timeout_s: float = 60.0,
        stop: threading.Event | None = None,
        transport: httpx.BaseTransport | None = None,
        pool_size: int = 8,
        user_agent: str = "hoi-refine-client/1",
    ) -> None:
        self.retry = retry or RetryPolicy()
        self.stop = stop or threading.Event()
        self.retries_made = 0
        self.throttled = 0
        self._http = httpx.Client(
            base_url=base_url.rstrip("/"),
            headers={"Authorization": f"Bearer {api_key}", "User-Agent": user_agent},
            timeout=timeout_s,
            transport=transport,
            limits=httpx.Limits(max_connections=pool_size, max_keepalive_connections=pool_size),
        )

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> ApiClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ transport with retries
    def _wait(self, seconds: float) -> None:
        if self.stop.wait(seconds):
            raise Stopped("stopped while waiting to retry")

    def request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        """Send with the retry policy; returns a 2xx/3xx response or raises ``ApiError`` / ``Stopped``."""
        failures = 0
        while True:
            if self.stop.is_set():
                raise Stopped("stopped before sending")
            try:
                resp = self._http.request(method, url, **kwargs)
            except httpx.TransportError as exc:
                failures += 1
                if failures > self.retry.max_retries:
                    raise ApiError(
                        f"{method} {url}: {type(exc).__name__}: {exc} (gave up after {failures} tries)"
                    ) from exc
                self.retries_made += 1
                self._wait(self.retry.backoff(failures - 1))
                continue
            if resp.status_code == 429:
                self.throttled += 1
                delay = parse_retry_after(resp.headers.get("Retry-After"))
                self._wait(min(MAX_RETRY_AFTER_S, delay if delay is not None else self.retry.backoff(2)))
                continue
            if resp.status_code >= 500:
                failures += 1
                if failures > self.retry.max_retries:
                    raise self._error(method, url, resp, f" (gave up after {failures} tries)")
                self.retries_made += 1
                hinted = parse_retry_after(resp.headers.get("Retry-After"))
                self._wait(min(MAX_RETRY_AFTER_S, hinted) if hinted is not None else self.retry.backoff(failures - 1))
                continue
            if resp.status_code >= 400:
                raise self._error(method, url, resp)
            return resp

    @staticmethod
    def _error(method: str, url: str, resp: httpx.Response, suffix: str = "") -> ApiError:
        problem = _problem(resp)
        what = problem.get("detail") or problem.get("title") or resp.reason_phrase
        return ApiError(f"{method} {url}: HTTP {resp.status_code}: {what}{suffix}", resp.status_code, problem)

    # ------------------------------------------------------------------ endpoints
    def submit(
        self,
        payload: bytes,
        filename: str,
        options: JobOptions,
        key: str | None = None,
        batch_id: str | None = None,
    ) -> dict[str, Any]:
        """``POST /v1/jobs`` (multipart: native NPZ + options JSON, into ``batch_id`` when given). Returns the
        job document (has ``id``).

        ``key`` is the Idempotency-Key; without one a fresh key is made, so that a retried POST (after a
        timeout or a 5xx) still names one job and never submits it twice.
        """
        data = {"options": options_json(options), **({"batch_id": batch_id} if batch_id else {})}
        resp = self.request(
            "POST",
            "/v1/jobs",
            headers={"Idempotency-Key": key or uuid.uuid4().hex},
            files={"sequence": (filename, payload, "application/octet-stream")},
            data=data,
        )
        doc = resp.json() if resp.content else {}
        if not isinstance(doc, dict):
            doc = {}
        if "id" not in doc:
            location = resp.headers.get("Location", "")
            if not location:
                raise ApiError("POST /v1/jobs: the answer names no job (no id, no Location)", resp.status_code)
            doc["id"] = location.rstrip("/").rsplit("/", 1)[-1]
        doc["id"] = str(doc["id"])
        return doc

    def job(self, job_id: str) -> tuple[dict[str, Any], float | None]:
        """``GET /v1/jobs/{id}``: the job document and the server's ``Retry-After`` hint (seconds)."""
        resp = self.request("GET", f"/v1/jobs/{job_id}")
        return resp.json(), parse_retry_after(resp.headers.get("Retry-After"))

    def retry_job(self, job_id: str) -> dict[str, Any]:
        """``POST /v1/jobs/{id}:retry``: requeue a FAILED job (409 when it is not FAILED). Returns the job."""
        return self._document(self.request("POST", f"/v1/jobs/{job_id}:retry"))

    def cancel(self, job_id: str) -> dict[str, Any]:
        """``POST /v1/jobs/{id}:cancel``: QUEUED jobs end at once, RUNNING ones at the worker's next heartbeat."""
        return self._document(self.request("POST", f"/v1/jobs/{job_id}:cancel"))

    def result(self, job_id: str) -> bytes:
        """``GET /v1/jobs/{id}/result?format=npz``: the result file (``common.result_format``)."""
        return self.request("GET", f"/v1/jobs/{job_id}/result", params={"format": "npz"}).content

    def file(self, job_id: str, name: str) -> bytes:
        """A file stored beside the result: ``video``, ``recording``, ``export`` or ``plots/NAME.png``."""
        return self.request("GET", f"/v1/jobs/{job_id}/{name}").content

    def plots(self, job_id: str) -> list[dict[str, Any]]:
        """``GET /v1/jobs/{id}/plots``: the names (and sizes) of the job's plots."""
        plots = self.request("GET", f"/v1/jobs/{job_id}/plots").json().get("plots", [])
        return [p for p in plots if isinstance(p, dict)]

    def contacts(self, job_id: str, start: int | None = None, end: int | None = None) -> Any:
        params = {k: v for k, v in (("start", start), ("end", end)) if v is not None}
        return self.request("GET", f"/v1/jobs/{job_id}/contacts", params=params).json()

    def wait(
        self,
        job_id: str,
        timeout_s: float,
        on_poll: Callable[[dict[str, Any]], None] | None = None,
        interval_s: float = 0.5,
    ) -> dict[str, Any]:
        """Poll ``GET /v1/jobs/{id}`` every ``interval_s`` until the job is finished; returns its document.

        ``on_poll`` sees every document (a progress bar); ``HoiRefineError`` after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            job, _ = self.job(job_id)
            if on_poll is not None:
                on_poll(job)
            if job["state"] in FINISHED:
                return job
            if time.monotonic() > deadline:
                raise HoiRefineError(f"job {job_id} still {job['state']} after {timeout_s:.0f} s")
            self._wait(interval_s)

    @staticmethod
    def _document(resp: httpx.Response) -> dict[str, Any]:
        doc = resp.json()
        return doc if isinstance(doc, dict) else {}

    def jobs(self, batch_id: str | None = None, page_size: int = 100) -> list[dict[str, Any]]:
        """``GET /v1/jobs`` page by page: every job of this key (of ``batch_id`` when given), newest first."""
        out: list[dict[str, Any]] = []
        params: dict[str, Any] = {"page_size": page_size, **({"batch_id": batch_id} if batch_id else {})}
        while True:
            doc = self._document(self.request("GET", "/v1/jobs", params=params))
            out.extend(j for j in doc.get("data") or [] if isinstance(j, dict))
            token = doc.get("next_page_token")
            if not token:
                return out
            params["page_token"] = token

    def create_batch(self, name: str, meta: dict[str, str] | None = None) -> dict[str, Any]:
        """``POST /v1/batches``: a new batch to submit into. Returns the batch document (has ``id``)."""
        doc = self.request("POST", "/v1/batches", json={"name": name, "meta": dict(meta or {})}).json()
        return doc if isinstance(doc, dict) else {}

    def batch(self, batch_id: str) -> dict[str, Any]:
        """``GET /v1/batches/{id}``: counts per state and outcome, the aggregate raw / refined metrics, links."""
        doc = self.request("GET", f"/v1/batches/{batch_id}").json()
        return doc if isinstance(doc, dict) else {}

    def batch_report(self, batch_id: str, fmt: str = "csv") -> bytes:
        """``GET /v1/batches/{id}/report?format=csv|parquet``: one row per sequence."""
        return self.request("GET", f"/v1/batches/{batch_id}/report", params={"format": fmt}).content
