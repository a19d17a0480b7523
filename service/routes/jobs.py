"""``/v1/jobs``: thin routes over ``common.queue.JobQueue`` (no SQL here; DESIGN §4)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Header, Query, Request, Response
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from common.batch_metrics import outcome_of
from common.job_state import ACTIVE, JobState
from common.queue_types import JobEventRecord
from common.result_format import STEPWISE_KEYS, read_arrays, read_contacts
from common.sequence_io import sequence_to_json_dict
from service import event_stream
from service.deps import KeyDep, PageToken, QueueDep, SettingsDep, reject_unknown_query_parameters
from service.schemas import (
    ContactsPublic,
    JobEventPublic,
    JobEventsPublic,
    JobPublic,
    JobsPublic,
    MetricsPublic,
    OutcomeStatus,
    Problem,
    ResultJson,
)
from service.submission import MULTIPART_ENCODING, MULTIPART_SCHEMA, read_submission

PROBLEM = {"model": Problem, "content": {"application/problem+json": {}}}
COMMON_ERRORS: dict[int | str, dict[str, Any]] = {401: PROBLEM, 404: PROBLEM, 422: PROBLEM}

router = APIRouter(
    prefix="/v1/jobs",
    tags=["jobs"],
    responses=COMMON_ERRORS,
    dependencies=[Depends(reject_unknown_query_parameters)],
)


def _job_response(response: Response, job: JobPublic, retry_after: int) -> JobPublic:
    if job.state in ACTIVE:
        response.headers["Retry-After"] = str(retry_after)
    return job


@router.post(
    "",
    status_code=202,
    response_model=JobPublic,
    summary="Submit a sequence for refinement",
    # 400: a multipart body the form parser refuses (e.g. more parts than it accepts).
    responses={400: PROBLEM, 409: PROBLEM, 413: PROBLEM, 415: PROBLEM, 429: PROBLEM},
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {"schema": {"$ref": "#/components/schemas/JobCreate"}},
                "multipart/form-data": {"schema": MULTIPART_SCHEMA, "encoding": MULTIPART_ENCODING},
            },
        }
    },
)
async def submit_job(
    request: Request,
    response: Response,
    queue: QueueDep,
    settings: SettingsDep,
    key_id: KeyDep,
    idempotency_key: Annotated[
        str | None,
        Header(max_length=200, pattern=r"^[\x20-\x7E]+$",
               description="Resending with the same key and payload returns the first job; the same key with "
               "another payload is a 422 (IETF Idempotency-Key draft)"),
    ] = None,
) -> JobPublic:
    sub = await read_submission(request, settings)
    job, _created = await run_in_threadpool(
        queue.submit, key_id, sub.payload, sub.options, idempotency_key, sub.sequence.name, sub.sequence.num_frames,
        sub.batch_id,
    )
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return _job_response(response, JobPublic.from_record(job), settings.poll_retry_after_seconds)


@router.get("", response_model=JobsPublic, summary="List your jobs, newest first")
def list_jobs(
    queue: QueueDep,
    key_id: KeyDep,
    page_size: Annotated[int, Query(ge=1, le=500)] = 50,
    page_token: PageToken = None,
    state: JobState | None = None,
    batch_id: Annotated[str | None, Query(max_length=32, description="only the jobs of this batch")] = None,
    outcome: Annotated[
        OutcomeStatus | None,
        Query(description="only SUCCEEDED jobs whose refined sequence is executable, not_executable, or unknown "
              "(a result made before outcomes existed)"),
    ] = None,
) -> JobsPublic:
    jobs, token = queue.list(key_id, state=state, page_size=page_size, page_token=page_token, batch_id=batch_id,
                             outcome=outcome)  # fmt: skip
    return JobsPublic(data=[JobPublic.from_record(j) for j in jobs], count=len(jobs), next_page_token=token)


@router.post("/{job_id}:cancel", response_model=JobPublic, summary="Cancel (QUEUED at once, RUNNING by flag)",
             responses={409: PROBLEM})  # fmt: skip
def cancel_job(job_id: str, response: Response, queue: QueueDep, settings: SettingsDep, key_id: KeyDep) -> JobPublic:
    job = JobPublic.from_record(queue.cancel(key_id, job_id))
    return _job_response(response, job, settings.poll_retry_after_seconds)


@router.post("/{job_id}:retry", response_model=JobPublic, summary="Requeue a FAILED job", responses={409: PROBLEM})
def retry_job(job_id: str, response: Response, queue: QueueDep, settings: SettingsDep, key_id: KeyDep) -> JobPublic:
    job = JobPublic.from_record(queue.retry(key_id, job_id))
    return _job_response(response, job, settings.poll_retry_after_seconds)


@router.delete("/{job_id}", status_code=204, summary="Delete a finished job and its result", responses={409: PROBLEM})
def delete_job(job_id: str, queue: QueueDep, key_id: KeyDep) -> Response:
    queue.delete(key_id, job_id)
    return Response(status_code=204)


@router.get(
    "/{job_id}/result",
    response_model=ResultJson,
    summary="The result: the NPZ file, or its arrays and summary as JSON",
    responses={200: {"content": {"application/octet-stream": {}}}, 409: PROBLEM},
)
def get_result(
    job_id: str, queue: QueueDep, key_id: KeyDep, format: Literal["json", "npz"] = "json"
) -> Any:
    blob, summary = queue.get_result(key_id, job_id)
    if format == "npz":
        return Response(
            blob,
            media_type="application/octet-stream",
            headers={"Content-Disposition": f'attachment; filename="{job_id}.npz"'},
        )
    arrays = {k: _jsonable(v) for k, v in read_arrays(blob).items()
              if k != "summary_json" and k not in STEPWISE_KEYS}
    return ResultJson(job_id=job_id, summary=summary, arrays=arrays)


@router.get("/{job_id}/contacts", response_model=ContactsPublic, summary="Per-frame contacts, start <= frame < end",
            responses={409: PROBLEM})  # fmt: skip
def get_contacts(
    job_id: str,
    queue: QueueDep,
    key_id: KeyDep,
    start: Annotated[int | None, Query(ge=0, description="first frame (default: the first)")] = None,
    end: Annotated[
        int | None, Query(ge=0, description="frame after the last (default: past the last); end <= start selects none")
    ] = None,
) -> ContactsPublic:
    # The range is a half-open slice, as in Python: end <= start is an empty range, not an error (OpenAPI cannot
    # say end >= start, so refusing it would refuse requests the schema allows).
    blob, _ = queue.get_result(key_id, job_id)
    rows = read_contacts(blob, start, end)
    return ContactsPublic.model_validate(
        {"job_id": job_id, "start": start, "end": end, "count": len(rows), "contacts": rows}
    )


@router.get("/{job_id}/metrics", response_model=MetricsPublic, summary="Raw-replay and refined metrics",
            responses={409: PROBLEM})  # fmt: skip
def get_metrics(job_id: str, queue: QueueDep, key_id: KeyDep) -> MetricsPublic:
    _, summary = queue.get_result(key_id, job_id)
    metrics = dict(summary.get("metrics", {}))
    outcome = outcome_of(summary)
    if outcome is not None:
        metrics.setdefault("outcome", dict(outcome))
    return MetricsPublic(job_id=job_id, metrics=metrics)


@router.get(
    "/{job_id}/events",
    response_model=JobEventsPublic,
    summary="The job's state changes and progress, oldest first; as server-sent events with "
    "'Accept: text/event-stream' (Last-Event-ID resumes)",
    responses={200: {"content": {"application/json": {}, event_stream.MEDIA_TYPE: {}}}},
)
async def get_events(job_id: str, request: Request, queue: QueueDep, settings: SettingsDep, key_id: KeyDep) -> Any:
    if not event_stream.wants_stream(request):
        rows = await run_in_threadpool(queue.events, key_id, job_id)
        return JobEventsPublic(
            job_id=job_id, events=[JobEventPublic(id=e.id, at=e.at, kind=e.kind, detail=e.detail) for e in rows]
        )
    after = event_stream.last_event_id(request)

    def read(after_id: int) -> tuple[bool, list[JobEventRecord], dict[str, Any]]:
        job, events = queue.job_events_after(key_id, job_id, after_id)
        snapshot = {"job_id": job.id, "state": job.state, "attempt": job.attempt, "progress": job.progress}
        return job.is_terminal, events, snapshot

    await run_in_threadpool(read, after)  # 404 before the stream starts
    body = event_stream.stream(request, settings, read, after, "end")
    return StreamingResponse(body, media_type=event_stream.MEDIA_TYPE, headers={"Cache-Control": "no-cache"})


@router.get("/{job_id}/input", summary="The submitted sequence in the native JSON form")
def get_input(job_id: str, queue: QueueDep, key_id: KeyDep) -> Any:
    from common.sequence_io import sequence_from_npz_bytes

    queue.get(key_id, job_id)  # ownership check
    return sequence_to_json_dict(sequence_from_npz_bytes(queue.get_payload(job_id)))


def _jsonable(value: np.ndarray) -> Any:
    if value.dtype.kind == "f" and not np.isfinite(value).all():
        out = value.astype(object)
        out[~np.isfinite(value)] = None  # JSON has no NaN/inf
        return out.tolist()
    return value.tolist()


