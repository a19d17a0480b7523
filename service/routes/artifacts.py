"""``/v1/jobs/{id}/video | close-up | recording | export | plots``: the files a worker stored beside a job's result
(issue #18 item 4). Thin routes over ``JobQueue.get_artifact`` / ``list_artifacts``, scoped to the caller's key
like every job route: another key gets 404, a job not yet SUCCEEDED 409, a job run with ``preview_video`` off
(or whose preview failed: see the summary's ``preview`` entry) 404, and so does ``close-up`` for a job run without
``preview_close_up``.

Names match the worker's preview (``service.links`` maps each to its route; the service does not import the
worker).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, Path, Response

from common.job_state import JobState
from service.deps import KeyDep, QueueDep, reject_unknown_query_parameters
from service.links import CLOSE_UP, EXPORT, PLOTS_PREFIX, RECORDING, VIDEO
from service.routes.jobs import COMMON_ERRORS, PROBLEM
from service.schemas import PlotPublic, PlotsPublic

PLOT_NAME = r"^[A-Za-z0-9_.-]{1,80}\.png$"

router = APIRouter(
    prefix="/v1/jobs",
    tags=["results"],
    responses={**COMMON_ERRORS, 409: PROBLEM},
    dependencies=[Depends(reject_unknown_query_parameters)],
)


def _file(queue: Any, key_id: str, job_id: str, name: str, download: str | None) -> Response:
    art = queue.get_artifact(key_id, job_id, name)
    headers = {"Cache-Control": "private, max-age=3600"}
    if download is not None:
        headers["Content-Disposition"] = f'attachment; filename="{download}"'
    return Response(art.data, media_type=art.content_type, headers=headers)


@router.get("/{job_id}/video", summary="Preview video (MP4, H.264): raw replay and refined side by side",
            responses={200: {"content": {"video/mp4": {}}}})  # fmt: skip
def get_video(job_id: str, queue: QueueDep, key_id: KeyDep) -> Response:
    return _file(queue, key_id, job_id, VIDEO, None)


@router.get("/{job_id}/close-up", summary="Close-up video (MP4, H.264), raw replay and refined: the camera follows "
            "the object, the fingers at it (jobs run with preview_close_up)",
            responses={200: {"content": {"video/mp4": {}}}})  # fmt: skip
def get_close_up(job_id: str, queue: QueueDep, key_id: KeyDep) -> Response:
    return _file(queue, key_id, job_id, CLOSE_UP, None)


@router.get("/{job_id}/recording", summary="Rerun recording (.rrd): open with `rerun FILE.rrd`",
            responses={200: {"content": {"application/octet-stream": {}}}})  # fmt: skip
def get_recording(job_id: str, queue: QueueDep, key_id: KeyDep) -> Response:
    return _file(queue, key_id, job_id, RECORDING, f"{job_id}.rrd")


@router.get("/{job_id}/export", summary="Plain-MuJoCo export (zip): MJCF, controls, trajectories, replay.py",
            responses={200: {"content": {"application/zip": {}}}})  # fmt: skip
def get_export(job_id: str, queue: QueueDep, key_id: KeyDep) -> Response:
    return _file(queue, key_id, job_id, EXPORT, f"{job_id}_export.zip")


@router.get("/{job_id}/plots", response_model=PlotsPublic, summary="The job's plots (PNG), by name")
def list_plots(job_id: str, queue: QueueDep, key_id: KeyDep) -> PlotsPublic:
    job = queue.get(key_id, job_id)
    if job.state != JobState.SUCCEEDED:
        queue.get_artifact(key_id, job_id, VIDEO)  # raises the queue's 409 with its message
    plots = [
        PlotPublic(name=a.name[len(PLOTS_PREFIX):], url=f"/v1/jobs/{job_id}/plots/{a.name[len(PLOTS_PREFIX):]}",
                   size_bytes=a.size_bytes)
        for a in queue.list_artifacts(key_id, job_id)
        if a.name.startswith(PLOTS_PREFIX)
    ]  # fmt: skip
    return PlotsPublic(job_id=job_id, plots=plots)


@router.get("/{job_id}/plots/{name}", summary="One plot (PNG)", responses={200: {"content": {"image/png": {}}}})
def get_plot(
    job_id: str, queue: QueueDep, key_id: KeyDep, name: str = Path(pattern=PLOT_NAME, description="e.g. errors.png")
) -> Response:
    return _file(queue, key_id, job_id, PLOTS_PREFIX + name, None)
