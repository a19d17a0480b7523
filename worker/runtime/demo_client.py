"""``make demo`` over HTTP: start ``hoi-refine up`` (unless given a running API), submit the built-in example,
poll with a progress bar, print raw vs refined metrics, save the result and its contacts (issue #5.3).

Everything goes through the public REST API (``/v1/jobs``) with ``common.api_client.ApiClient``, as a
user's client would.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from common.api_client import ApiClient
from common.errors import ConfigurationError, HoiRefineError
from common.job_options import JobOptions
from common.job_state import JobState

URL_LINE = re.compile(r"^hoi-refine API: (\S+)")
KEY_LINE = re.compile(r"^development API key: (\S+)")


@dataclass
class LocalDeployment:
    base_url: str
    api_key: str
    process: subprocess.Popen[str]
    log_path: Path


def _pump(stream: IO[str], sink: IO[str], found: dict[str, str], ready: threading.Event) -> None:
    for line in stream:
        sink.write(line)
        sink.flush()
        if m := URL_LINE.match(line):
            found["url"] = m.group(1)
        if m := KEY_LINE.match(line):
            found["key"] = m.group(1)
        if "url" in found and "key" in found:
            ready.set()
    ready.set()  # the process ended: wake the waiter either way


@contextmanager
def local_deployment(
    log_path: Path, workers: int = 2, threads_per_worker: int = 1, port: int = 8000, timeout_s: float = 180.0,
    env: dict[str, str] | None = None, extra_args: tuple[str, ...] = (),
) -> Iterator[LocalDeployment]:
    """``hoi-refine up`` in a child process; yields its URL and development key; SIGINT on exit."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    from worker.runtime.supervisor import hoi_refine_command

    cmd = [*hoi_refine_command(), "up", "--workers", str(workers)]
    cmd += ["--threads-per-worker", str(threads_per_worker), "--port", str(port), *extra_args]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env or dict(os.environ),
        start_new_session=True,
    )  # fmt: skip
    found: dict[str, str] = {}
    ready = threading.Event()
    sink = log_path.open("w")
    assert proc.stdout is not None
    pump = threading.Thread(target=_pump, args=(proc.stdout, sink, found, ready), daemon=True)
    pump.start()
    try:
        ready.wait(timeout_s)
        if "url" not in found or "key" not in found:
            raise ConfigurationError(f"`hoi-refine up` did not report its URL and key; see {log_path}")
        yield LocalDeployment(found["url"], found["key"], proc, log_path)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(90)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        pump.join(5)
        if not pump.is_alive():  # it reached the end of the pipe: close our end (else a ResourceWarning)
            proc.stdout.close()
        sink.close()


def poll_with_progress_bar(client: ApiClient, job_id: str, timeout_s: float) -> dict[str, Any]:
    """Poll until the job ends, showing the whole job's bar and stage, the window, best loss, evaluations and the
    job's ETA (rich; the progress document of ``common.progress``)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"), TimeElapsedColumn())
    with Progress(*columns, transient=False) as bar:
        task = bar.add_task("queued", total=1.0, info="")

        def update(job: dict[str, Any]) -> None:
            desc, fraction, info = progress_columns(job)
            bar.update(task, completed=fraction, description=desc, info=info)

        job = client.wait(job_id, timeout_s, on_poll=update)
        bar.update(task, completed=1.0, description=job["state"].lower())
    return job


def progress_columns(job: dict[str, Any]) -> tuple[str, float, str]:
    """A job's progress as (state and stage, fraction of the whole job, details with the job's ETA)."""
    p = job.get("progress") or {}
    stage = p.get("stage")
    desc = job["state"].lower() + (f": {stage}" if stage else "")
    details = []
    if p.get("windows"):
        details.append(f"window {p.get('window', 0)}/{p['windows']}")
    if p.get("best_loss") is not None:
        details.append(f"best loss {p['best_loss']:.3f}")
    if p.get("evaluations") is not None:
        details.append(f"evals {p['evaluations']}")
    if p.get("eta_s") is not None:
        details.append(f"ETA {p['eta_s']:.0f}s")
    return desc, float(min(max(p.get("fraction") or 0.0, 0.0), 1.0)), "  ".join(details)


def run_demo(
    base_url: str | None = None,
    api_key: str | None = None,
    out_dir: Path | str = Path("var/demo"),
    workers: int = 2,
    threads_per_worker: int = 1,
    port: int = 8000,
    short: bool = False,
    options: JobOptions | None = None,
    timeout_s: float = 1800.0,
    example: str = "box",
) -> int:
    """The demo of the built-in ``example`` (``worker.example.catalogue``); with no ``base_url`` it runs its own
    ``hoi-refine up`` and stops it afterwards."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if base_url is None:
        print(f"starting `hoi-refine up --workers {workers}` (log: {out / 'up.log'}) ...", flush=True)
        with local_deployment(out / "up.log", workers, threads_per_worker, port) as dep:
            return run_demo(dep.base_url, dep.api_key, out, short=short, options=options, timeout_s=timeout_s,
                            example=example)
    if not api_key:
        raise ConfigurationError("an API key is needed with a base URL (HOI_REFINE_API_KEY)")
    from common.result_format import read_summary
    from common.sequence_io import sequence_to_npz_bytes
    from worker.commands.refine import print_refine_metrics
    from worker.example.catalogue import example_named

    chosen = example_named(example)
    seq = chosen.build_short() if short else chosen.build()
    client = ApiClient(base_url, api_key)
    try:
        job = client.submit(sequence_to_npz_bytes(seq), f"{seq.name}.npz", options or JobOptions())
        print(f"submitted {seq.name!r} ({seq.num_frames} frames) as job {job['id']} to {base_url}", flush=True)
        job = poll_with_progress_bar(client, job["id"], timeout_s)
        if job["state"] != JobState.SUCCEEDED:
            errors = "; ".join(e["error"] for e in job.get("errors", [])) or "no error recorded"
            print(f"job {job['id']} ended {job['state']}: {errors}", file=sys.stderr)
            return 1
        blob = client.result(job["id"])
        contacts = client.contacts(job["id"])
        result_path, contacts_path = out / f"{seq.name}.result.npz", out / f"{seq.name}.contacts.json"
        result_path.write_bytes(blob)
        contacts_path.write_text(json.dumps(contacts, indent=1))
        print_refine_metrics(read_summary(blob))
        print(f"result: {result_path}\ncontacts ({contacts['count']}): {contacts_path}")
        save_visuals(client, job["id"], blob, out, seq.name)
    finally:
        client.close()
    return 0


def save_visuals(client: ApiClient, job_id: str, blob: bytes, out: Path, name: str) -> tuple[Path, list[Path]]:
    """Save the preview video and plots the worker stored with the job (``GET /v1/jobs/{id}/video``, ``/plots``);
    when the job has none (``preview_video`` off, or no OpenGL on the worker) make them here from the result."""
    video, plot_dir = out / f"{name}.mp4", out / f"{name}_plots"
    plot_dir.mkdir(parents=True, exist_ok=True)
    try:
        video.write_bytes(client.file(job_id, "video"))
        plots = []
        for plot in client.plots(job_id):
            path = plot_dir / plot["name"]
            path.write_bytes(client.file(job_id, f"plots/{plot['name']}"))
            plots.append(path)
        source = "rendered by the worker"
    except HoiRefineError as exc:
        print(f"no stored preview ({exc}); rendering it here", file=sys.stderr)
        from common.settings import get_settings
        from worker.visual import render_video, resimulate, write_plots

        render_video(resimulate(blob, cache_dir=get_settings().resolved_cache_dir()), str(video))
        plots = write_plots(blob, plot_dir)
        source = "rendered locally"
    print(f"video ({source}): {video}\nplots: {', '.join(str(p) for p in plots)}")
    return video, plots
