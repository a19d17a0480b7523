"""``/v1/batches``: a dataset's jobs as one resource (issue #20 item 1); thin routes over ``JobQueue``.

Jobs join a batch at submission (``batch_id`` in the JSON body or the multipart form of ``POST /v1/jobs``).
A batch of another key answers 404, like a missing one.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from common.queue_types import JobEventRecord
from service import batch_report, event_stream
from service.deps import KeyDep, PageToken, QueueDep, SettingsDep, reject_unknown_query_parameters
from service.links import REPORT_TYPES
from service.routes.jobs import COMMON_ERRORS, PROBLEM
from service.schemas import OutcomeStatus
from service.schemas_batches import BatchActionPublic, BatchCreate, BatchesPublic, BatchPublic

router = APIRouter(
    prefix="/v1/batches",
    tags=["batches"],
    responses=COMMON_ERRORS,
    dependencies=[Depends(reject_unknown_query_parameters)],
)


@router.post("", status_code=201, response_model=BatchPublic, summary="Create a batch to submit jobs into",
             responses={400: PROBLEM})  # fmt: skip
def create_batch(body: BatchCreate, response: Response, queue: QueueDep, key_id: KeyDep) -> BatchPublic:
    batch = queue.create_batch(key_id, body.name, body.meta)
    response.headers["Location"] = f"/v1/batches/{batch.id}"
    return BatchPublic.from_record(batch)


@router.get("", response_model=BatchesPublic, summary="List your batches, newest first (with counts)")
def list_batches(
    queue: QueueDep,
    key_id: KeyDep,
    page_size: Annotated[int, Query(ge=1, le=500)] = 50,
    page_token: PageToken = None,
    outcome: Annotated[
        OutcomeStatus | None, Query(description="only batches with at least one job of this outcome")
    ] = None,
) -> BatchesPublic:
    page, token = queue.list_batches(key_id, page_size=page_size, page_token=page_token, outcome=outcome)
    return BatchesPublic(data=[BatchPublic.from_record(b) for b in page], count=len(page), next_page_token=token)


@router.get("/{batch_id}", response_model=BatchPublic,
            summary="Counts per state and the mean raw-replay vs refined metrics of the succeeded jobs")  # fmt: skip
def get_batch(batch_id: str, queue: QueueDep, key_id: KeyDep) -> BatchPublic:
    return BatchPublic.from_record(queue.get_batch(key_id, batch_id))


@router.get(
    "/{batch_id}/report",
    summary="One row per sequence (outcome and reasons, state, timing, verification, raw and refined metrics on "
    "both protocols, penetration) as CSV or Parquet",
    responses={200: {"content": {t: {} for t in REPORT_TYPES.values()}}},
)
def get_report(
    batch_id: str, queue: QueueDep, key_id: KeyDep, format: Literal["csv", "parquet"] = "csv"
) -> Response:
    jobs = queue.batch_jobs(key_id, batch_id)
    body = batch_report.to_csv(jobs) if format == "csv" else batch_report.to_parquet(jobs)
    disposition = f'attachment; filename="batch-{batch_id}.{format}"'
    return Response(body, media_type=REPORT_TYPES[format], headers={"Content-Disposition": disposition})


@router.post("/{batch_id}:cancel", response_model=BatchActionPublic,
             summary="Cancel every unfinished job (QUEUED at once, RUNNING by flag)")  # fmt: skip
def cancel_batch(batch_id: str, queue: QueueDep, key_id: KeyDep) -> BatchActionPublic:
    batch, changed = queue.cancel_batch(key_id, batch_id)
    return BatchActionPublic(batch=BatchPublic.from_record(batch), changed=changed)


@router.post("/{batch_id}:retry-failed", response_model=BatchActionPublic, summary="Requeue every FAILED job")
def retry_failed(batch_id: str, queue: QueueDep, key_id: KeyDep) -> BatchActionPublic:
    batch, changed = queue.retry_failed_batch(key_id, batch_id)
    return BatchActionPublic(batch=BatchPublic.from_record(batch), changed=changed)


@router.get(
    "/{batch_id}/events",
    summary="Server-sent events: state changes and progress of the batch's jobs (Last-Event-ID resumes)",
    response_class=StreamingResponse,
    responses={200: {"content": {event_stream.MEDIA_TYPE: {}}}, 422: PROBLEM},
)
async def batch_events(
    batch_id: str, request: Request, queue: QueueDep, settings: SettingsDep, key_id: KeyDep
) -> StreamingResponse:
    after = event_stream.last_event_id(request)

    def read(after_id: int) -> tuple[bool, list[JobEventRecord], dict[str, Any]]:
        batch, events, complete = queue.batch_events_after(key_id, batch_id, after_id)
        snapshot = {"batch_id": batch.id, "state": batch.state, "total": batch.total, "counts": batch.counts}
        return batch.state == "COMPLETED" and complete, events, snapshot

    await run_in_threadpool(read, after)  # 404 before the stream starts
    body = event_stream.stream(request, settings, read, after, "end")
    return StreamingResponse(body, media_type=event_stream.MEDIA_TYPE, headers={"Cache-Control": "no-cache"})
