"""``make demo`` over HTTP: start ``hoi-refine up`` (unless given a running API), submit the built-in example,
poll with a progress bar, print raw vs refined metrics, save the result and its contacts (issue #5.3).

Everything goes through the public REST API (``/v1/jobs``), as a user's client would.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import httpx

from common.errors import ConfigurationError, HoiRefineError
from common.job_options import JobOptions

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
        sink.close()


class ApiClient:
    """The few ``/v1/jobs`` calls the demo (and the acceptance test) needs."""

    def __init__(self, base_url: str, api_key: str, timeout: float = 30.0) -> None:
        self.http = httpx.Client(base_url=base_url, headers={"Authorization": f"Bearer {api_key}"}, timeout=timeout)

    def close(self) -> None:
        self.http.close()

    def _ok(self, response: httpx.Response) -> httpx.Response:
        if response.status_code >= 400:
            raise HoiRefineError(f"{response.request.method} {response.request.url.path}: "
                                 f"HTTP {response.status_code} {response.text[:500]}")  # fmt: skip
        return response

    def submit_npz(self, payload: bytes, options: JobOptions, name: str = "sequence.npz") -> dict[str, Any]:
        files = {"sequence": (name, payload, "application/octet-stream")}
        data = {"options": options.model_dump_json()}
        out: dict[str, Any] = self._ok(self.http.post("/v1/jobs", files=files, data=data)).json()
        return out

    def job(self, job_id: str) -> dict[str, Any]:
        out: dict[str, Any] = self._ok(self.http.get(f"/v1/jobs/{job_id}")).json()
        return out

    def cancel(self, job_id: str) -> dict[str, Any]:
        out: dict[str, Any] = self._ok(self.http.post(f"/v1/jobs/{job_id}:cancel")).json()
        return out

    def result_npz(self, job_id: str) -> bytes:
        return self._ok(self.http.get(f"/v1/jobs/{job_id}/result", params={"format": "npz"})).content

    def contacts(self, job_id: str) -> dict[str, Any]:
        out: dict[str, Any] = self._ok(self.http.get(f"/v1/jobs/{job_id}/contacts")).json()
        return out

    def wait(self, job_id: str, timeout_s: float, on_poll: Any = None, interval: float = 0.5) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.job(job_id)
            if on_poll is not None:
                on_poll(job)
            if job["state"] in ("SUCCEEDED", "FAILED", "CANCELLED"):
                return job
            if time.monotonic() > deadline:
                raise HoiRefineError(f"job {job_id} still {job['state']} after {timeout_s:.0f} s")
            time.sleep(interval)


def poll_with_progress_bar(client: ApiClient, job_id: str, timeout_s: float) -> dict[str, Any]:
    """Poll until the job ends, showing window i/N, best loss, evaluations and ETA (rich)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"), TimeElapsedColumn())
    with Progress(*columns, transient=False) as bar:
        task = bar.add_task("queued", total=1, info="")

        def update(job: dict[str, Any]) -> None:
            p = job.get("progress") or {}
            windows = p.get("windows") or 1
            info = (
                f"best loss {p['best_loss']:.3f}  evals {p.get('evaluations', 0)}  ETA {p.get('eta_s') or 0:.0f}s"
                if p.get("best_loss") is not None else ""
            )  # fmt: skip
            desc = f"{job['state'].lower()} window {p.get('window', 0)}/{windows}"
            bar.update(task, total=windows, completed=p.get("window", 0), description=desc, info=info)

        job = client.wait(job_id, timeout_s, on_poll=update)
        bar.update(task, completed=bar.tasks[0].total, description=job["state"].lower())
    return job


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
) -> int:
    """The demo; with no ``base_url`` it runs its own ``hoi-refine up`` and stops it afterwards."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if base_url is None:
        print(f"starting `hoi-refine up --workers {workers}` (log: {out / 'up.log'}) ...", flush=True)
        with local_deployment(out / "up.log", workers, threads_per_worker, port) as dep:
            return run_demo(dep.base_url, dep.api_key, out, short=short, options=options, timeout_s=timeout_s)
    if not api_key:
        raise ConfigurationError("an API key is needed with a base URL (HOI_REFINE_API_KEY)")
    from common.result_format import read_summary
    from common.sequence_io import sequence_to_npz_bytes
    from worker.commands.refine import print_refine_metrics
    from worker.example.sequences import example_sequence, short_example_sequence

    seq = short_example_sequence() if short else example_sequence()
    client = ApiClient(base_url, api_key)
    try:
        job = client.submit_npz(sequence_to_npz_bytes(seq), options or JobOptions(), f"{seq.name}.npz")
        print(f"submitted {seq.name!r} ({seq.num_frames} frames) as job {job['id']} to {base_url}", flush=True)
        job = poll_with_progress_bar(client, job["id"], timeout_s)
        if job["state"] != "SUCCEEDED":
            errors = "; ".join(e["error"] for e in job.get("errors", [])) or "no error recorded"
            print(f"job {job['id']} ended {job['state']}: {errors}", file=sys.stderr)
            return 1
        blob = client.result_npz(job["id"])
        contacts = client.contacts(job["id"])
    finally:
        client.close()
    result_path, contacts_path = out / f"{seq.name}.result.npz", out / f"{seq.name}.contacts.json"
    result_path.write_bytes(blob)
    contacts_path.write_text(json.dumps(contacts, indent=1))
    print_refine_metrics(read_summary(blob))
    print(f"result: {result_path}\ncontacts ({contacts['count']}): {contacts_path}")
    return 0
