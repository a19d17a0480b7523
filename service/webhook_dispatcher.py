"""Sends webhooks from the outbox (issue #20 item 2): a background task of the API process.

Every ``webhook_poll_seconds`` it asks the webhook store to fan new job events out into delivery rows, claims the
due ones and sends each as its own task (``httpx.AsyncClient``, ``webhook_timeout_seconds``), at most
``MAX_IN_FLIGHT`` at a time, then records the outcome (the store schedules retries with backoff). A slow
or dead receiver therefore holds only its own task; workers never wait for any of this, since all they do
is append ``job_events`` rows as before. Database calls run in the thread pool, off the event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

import httpx
from starlette.concurrency import run_in_threadpool

from common.db_models import utcnow
from common.queue_types import DeliveryToSend
from common.webhook_signing import body_of, signed_headers
from common.webhook_store import WebhookStore

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
        timeout = httpx.Timeout(self.settings.webhook_timeout_seconds)
        async with httpx.AsyncClient(timeout=timeout, follow_redirects=False,
                                     headers={"user-agent": USER_AGENT}) as http:  # fmt: skip
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
        try:
            resp = await http.post(delivery.url, content=body.encode(), headers=headers)
            status = resp.status_code
            if not 200 <= status < 300:
                error = f"HTTP {status}"
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
