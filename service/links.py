"""Where a job's and a batch's resources are, with their media types (issue #53 item 5): the links every job
and batch body carries, so a client needs nothing but the body to find the result, the files and the reports.

Hrefs are relative to the API's base URL (as ``Location`` headers are). A stored artifact's name (as the worker
names it: ``video.mp4``, ``close_up.mp4``, ``recording.rrd``, ``export.zip``, ``plots/NAME.png``) maps to its route
here; the routes in ``service.routes.artifacts`` read the same names.
"""

from __future__ import annotations

from typing import Any

from common.job_state import JobState

VIDEO, CLOSE_UP, RECORDING, EXPORT, PLOTS_PREFIX = "video.mp4", "close_up.mp4", "recording.rrd", "export.zip", "plots/"
JSON = "application/json"
#: Artifact name -> the link relation naming its route (plots are listed at ``plots`` and linked one by one).
ARTIFACT_RELS: dict[str, str] = {VIDEO: "video", CLOSE_UP: "close_up", RECORDING: "recording", EXPORT: "export"}
#: Artifact name -> its route's last path segment (a relation's underscore is a hyphen in the URL).
ARTIFACT_PATHS: dict[str, str] = {name: rel.replace("_", "-") for name, rel in ARTIFACT_RELS.items()}
ARTIFACT_TITLES: dict[str, str] = {
    VIDEO: "preview video: raw replay and refined side by side",
    CLOSE_UP: "close-up video: the camera follows the object, the fingers at it",
    RECORDING: "Rerun recording",
    EXPORT: "plain-MuJoCo export (zip)",
}
REPORT_TYPES: dict[str, str] = {"csv": "text/csv", "parquet": "application/vnd.apache.parquet"}
EVENT_STREAM = "text/event-stream"


def link(href: str, media_type: str, title: str) -> dict[str, str]:
    return {"href": href, "type": media_type, "title": title}


def job_href(job_id: str) -> str:
    return f"/v1/jobs/{job_id}"


def artifact_href(job_id: str, name: str) -> str | None:
    """The route serving a stored artifact, or None for a name this service has no route for."""
    if name in ARTIFACT_PATHS:
        return f"{job_href(job_id)}/{ARTIFACT_PATHS[name]}"
    if name.startswith(PLOTS_PREFIX) and "/" not in name[len(PLOTS_PREFIX):]:
        return f"{job_href(job_id)}/{name}"
    return None


def job_links(
    job_id: str, state: str, batch_id: str | None, files: list[tuple[str, str]]
) -> dict[str, dict[str, str]]:
    """Links of one job: itself, its events, its input and batch; once SUCCEEDED also the result (JSON and NPZ),
    contacts, metrics, and each stored file (``files``: name, media type) that has a route."""
    base = job_href(job_id)
    out = {
        "self": link(base, JSON, "this job"),
        "events": link(f"{base}/events", JSON, f"state changes and progress ({EVENT_STREAM} with that Accept)"),
        "input": link(f"{base}/input", JSON, "the submitted sequence, native JSON form"),
        "dashboard": link(f"/ui#/jobs/{job_id}", "text/html", "this job in the web dashboard"),
    }
    if batch_id is not None:
        out["batch"] = link(f"/v1/batches/{batch_id}", JSON, "the batch this job belongs to")
    if state != JobState.SUCCEEDED:
        return out
    out["result"] = link(f"{base}/result", JSON, "the result: summary and every array")
    out["result_npz"] = link(f"{base}/result?format=npz", "application/octet-stream", "the result file (NPZ)")
    out["contacts"] = link(f"{base}/contacts", JSON, "per-frame hand-object contacts")
    out["metrics"] = link(f"{base}/metrics", JSON, "raw-replay and refined metrics")
    for name, media_type in files:
        if name in ARTIFACT_RELS:
            out[ARTIFACT_RELS[name]] = link(f"{base}/{ARTIFACT_PATHS[name]}", media_type, ARTIFACT_TITLES[name])
    if any(name.startswith(PLOTS_PREFIX) for name, _ in files):
        out["plots"] = link(f"{base}/plots", JSON, "the job's plots, by name")
    return out


def file_entries(job_id: str, files: list[tuple[str, str, int]]) -> list[dict[str, Any]]:
    """Every stored file that has a route: name, href, media type, size."""
    out = []
    for name, media_type, size in files:
        href = artifact_href(job_id, name)
        if href is not None:
            out.append({"name": name, "href": href, "type": media_type, "size_bytes": size})
    return out


def batch_links(batch_id: str) -> dict[str, dict[str, str]]:
    base = f"/v1/batches/{batch_id}"
    jobs = f"/v1/jobs?batch_id={batch_id}"
    return {
        "self": link(base, JSON, "this batch: counts and aggregate metrics"),
        "jobs": link(jobs, JSON, "the batch's jobs, newest first"),
        "not_executable": link(
            f"{jobs}&outcome=not_executable", JSON, "jobs whose refined sequence is not executable, with reasons"
        ),
        "failed": link(f"{jobs}&state=FAILED", JSON, "jobs that FAILED, with their errors"),
        "events": link(f"{base}/events", EVENT_STREAM, "server-sent events of the batch's jobs"),
        "report_csv": link(f"{base}/report?format=csv", REPORT_TYPES["csv"], "one row per sequence (CSV)"),
        "report_parquet": link(
            f"{base}/report?format=parquet", REPORT_TYPES["parquet"], "one row per sequence (Parquet)"
        ),
        "dashboard": link(f"/ui#/batches/{batch_id}", "text/html", "this batch in the web dashboard"),
    }
