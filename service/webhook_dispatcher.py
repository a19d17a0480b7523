"""Sends webhooks from the outbox (issue #20 item 2): a background task of the API process.

Every ``webhook_poll_seconds`` it asks the webhook store to fan new job events out into delivery rows, claims the
due ones and sends each as its own task (``httpx.AsyncClient``, ``webhook_timeout_seconds``), at most
``MAX_IN_FLIGHT`` at a time, then records the outcome (the store schedules retries with backoff). A slow
or dead receiver therefore holds only its own task; workers never wait for any of this, since all they do
is append ``job_events`` rows as before. Database calls run in the thread pool, off the event loop.

Each send resolves and checks its target again (``common.webhook_targets``) and connects to the checked address
itself (the URL's host goes in the Host header and as the TLS server name), so DNS rebinding between the check
and the connection cannot reach an internal address; redirects are never followed, proxies from the
environment never used, and connections never reused (each delivery checks its own). A send is bounded: one
deadline (``webhook_timeout_seconds``) over resolving, connecting, sending and reading the answer, a connect
timeout within it, and at most ``webhook_max_response_bytes`` of the answer read.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
import time

import httpx
from starlette.concurrency import run_in_threadpool

from common.db_models import utcnow
from common.queue_types import DeliveryToSend
from common.webhook_signing import body_of, signed_headers
from common.webhook_store import WebhookStore
from common.webhook_targets import TargetRefusedError

log = logging.getLogger("hoi_refine.webhooks")

MAX_IN_FLIGHT = 32
USER_AGENT = "hoi-refine-webhooks/1"


class WebhookDispatcher:
    def __init__(self, store: WebhookStore) -> None:
        self.store = store
        self.settings = store.settings
        self._tasks: set[asyncio.Task[None]] = set()
        self._stop = asyncio.Event()

    async def run(self) -> None:
        total = self.settings.webhook_timeout_seconds
        timeout = httpx.Timeout(total, connect=min(total, self.settings.webhook_connect_timeout_seconds))
        limits = httpx.Limits(max_connections=MAX_IN_FLIGHT, max_keepalive_connections=0)
        ca_file = self.settings.webhook_ca_file
        verify: ssl.SSLContext | bool = True if ca_file is None else ssl.create_default_context(cafile=str(ca_file))
        async with httpx.AsyncClient(timeout=timeout, limits=limits, follow_redirects=False, trust_env=False,
                                     verify=verify, headers={"user-agent": USER_AGENT}) as http:  # fmt: skip
            while not self._stop.is_set():
                try:
                    await self.tick(http)
                except Exception:  # a database hiccup must not end the dispatcher; the next tick retries
                    log.exception("webhook dispatcher tick failed")
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), self.settings.webhook_poll_seconds)
            for task in list(self._tasks):
                task.cancel()  # its claim lapses and the delivery comes due again

    def stop(self) -> None:
        self._stop.set()

    async def tick(self, http: httpx.AsyncClient) -> None:
        await run_in_threadpool(self.store.fan_out)
        room = MAX_IN_FLIGHT - len(self._tasks)
        if room <= 0:
            return
        for delivery in await run_in_threadpool(self.store.claim_deliveries, room):
            task = asyncio.create_task(self._send(http, delivery))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _send(self, http: httpx.AsyncClient, delivery: DeliveryToSend) -> None:
        body = body_of(delivery.payload)
        headers = signed_headers(delivery.secret, delivery.msg_id, utcnow(), body)
        status: int | None = None
        error: str | None = None
        t0 = time.perf_counter()
        deadline = self.settings.webhook_timeout_seconds
        try:
            async with asyncio.timeout(deadline):
                status = await self._post(http, delivery.url, body.encode(), headers)
            if not 200 <= status < 300:
                error = f"HTTP {status}" + (" (redirects are not followed)" if 300 <= status < 400 else "")
        except TargetRefusedError as exc:
            error = f"refused target: {exc}"
        except TimeoutError:
            error = f"timed out: no complete answer within {deadline:g} s"
        except httpx.HTTPError as exc:
            error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        elapsed_ms = (time.perf_counter() - t0) * 1e3
        try:
            state = await run_in_threadpool(self.store.record_delivery, delivery.id, status, error, elapsed_ms)
        except Exception:
            log.exception("could not record webhook delivery %d", delivery.id)
            return
        if state != "DELIVERED":
            log.info("webhook delivery %d attempt %d: %s -> %s", delivery.id, delivery.attempt, error, state)

    async def _post(self, http: httpx.AsyncClient, url: str, body: bytes, headers: dict[str, str]) -> int:
        """POST to the address the target check pins (not to whatever the name resolves to by then); returns the
        status after reading at most ``webhook_max_response_bytes`` of the answer."""
        target = await run_in_threadpool(self.store.targets.pin, url)
        parsed = httpx.URL(url)
        pinned = parsed.copy_with(host=str(target.address))
        host = {"host": parsed.netloc.decode("ascii")}
        sni = {"sni_hostname": parsed.raw_host.decode("ascii")}
        async with http.stream("POST", pinned, content=body, headers={**headers, **host}, extensions=sni) as resp:
            limit, read = self.settings.webhook_max_response_bytes, 0
            if limit:
                async for chunk in resp.aiter_raw():
                    read += len(chunk)
                    if read >= limit:
                        break  # the rest is never read: leaving the block closes the connection
            return resp.status_code
