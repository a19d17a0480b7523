"""CPU of ``hoi-refine submit --wait`` while its jobs wait in the queue (issue #53 item 8).

A ``hoi-refine serve`` subprocess on 127.0.0.1 over a scratch SQLite file, no workers: every job stays QUEUED,
so the client has nothing to do but poll. ``submit --wait`` runs as a subprocess twice, once with its output to
a pipe (progress lines) and once on a pseudo-terminal (the progress bar); once every sequence is submitted, the
CPU seconds it spends (user + system, psutil) are counted over ``--window`` seconds, then SIGINT stops it
(its exit status is reported too).

    .venv/bin/python bench/submit_idle.py --out bench/results/submit_idle.md
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import pty
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.provenance import cpu_model, git_commit  # noqa: E402
from common.api_client import wait_until_ready  # noqa: E402
from common.sequence import HandTrack, ObjectSpec, Sequence  # noqa: E402
from common.sequence_io import save_sequence  # noqa: E402

HOI = str(Path(sys.executable).with_name("hoi-refine"))


def _sequence(seed: int) -> Sequence:
    import numpy as np

    rng = np.random.default_rng(seed)
    pose = np.zeros((8, 7))
    pose[:, 0], pose[:, 2], pose[:, 3] = np.arange(8) * 1e-3, 0.02, 1.0
    hand = HandTrack(side="right", valid=np.ones(8, dtype=bool),
                     keypoints=rng.normal(scale=0.03, size=(8, 21, 3)) + np.array([0.0, 0.0, 0.08]))  # fmt: skip
    obj = ObjectSpec(name="box", mass_kg=0.1, primitive="box", size=np.array([0.02, 0.02, 0.02]))
    return Sequence(name=f"idle-{seed}", fps=30.0, object=obj, object_pose=pose, hands=[hand],
                    up=np.array([0.0, 0.0, 1.0]))  # fmt: skip


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _submitted(out: Path, n: int) -> bool:
    try:
        entries = json.loads((out / "manifest.json").read_text())["entries"]
    except (OSError, ValueError, KeyError):
        return False
    return len(entries) == n and all(e.get("job_id") for e in entries)


def measure(url: str, key: str, data: Path, out: Path, n: int, window_s: float, terminal: bool, seed: int) -> dict:
    cmd = [HOI, "submit", str(data), "--api", url, "--key", key, "--out", str(out), "--wait", "--seed", str(seed)]
    master = None
    if terminal:
        master, slave = pty.openpty()
        proc = subprocess.Popen(cmd, stdin=slave, stdout=slave, stderr=slave)
        os.close(slave)
    else:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def drain(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if master is not None and select.select([master], [], [], 0.1)[0]:
                with contextlib.suppress(OSError):
                    os.read(master, 65536)
            elif master is None:
                time.sleep(0.1)

    deadline = time.monotonic() + 120
    while not _submitted(out, n):
        if proc.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"submit did not submit every sequence (exit {proc.poll()})")
        drain(0.2)
    client = psutil.Process(proc.pid)
    before, t0 = client.cpu_times(), time.monotonic()
    drain(window_s)
    after, wall = client.cpu_times(), time.monotonic() - t0
    cpu = (after.user + after.system) - (before.user + before.system)
    proc.send_signal(signal.SIGINT)
    try:
        code = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        code = None
    if master is not None:
        os.close(master)
    return {"output": "terminal (bar)" if terminal else "pipe (lines)", "cpu_s": cpu, "wall_s": wall,
            "share": cpu / wall, "exit": code}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=3)
    ap.add_argument("--window", type=float, default=20.0, help="seconds the CPU is counted over")
    ap.add_argument("--out", type=Path, default=None, help="write the results as Markdown")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="submit-idle-") as tmp:
        tmp_path = Path(tmp)
        env = {**os.environ, "HOI_REFINE_VAR_DIR": str(tmp_path / "var")}
        port = _port()
        url = f"http://127.0.0.1:{port}"
        log = (tmp_path / "serve.log").open("wb")
        server = subprocess.Popen([HOI, "serve", "--port", str(port), "--log-level", "warning"], env=env,
                                  stdout=log, stderr=subprocess.STDOUT)  # fmt: skip
        try:
            wait_until_ready(url, 300, alive=lambda: server.poll() is None)
            key = subprocess.run([HOI, "keys", "create", "bench"], env=env, capture_output=True, text=True,
                                 check=True).stdout.strip()  # fmt: skip
            data = tmp_path / "data"
            data.mkdir()
            for i in range(args.sequences):
                save_sequence(_sequence(i), data / f"s{i}.npz")
            rows = [measure(url, key, data, tmp_path / f"out{i}", args.sequences, args.window, terminal, seed=i)
                    for i, terminal in enumerate((False, True))]  # fmt: skip
        finally:
            server.send_signal(signal.SIGINT)
            try:
                server.wait(timeout=60)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()
            log.close()
    head = (f"`hoi-refine submit --wait` waiting on {args.sequences} QUEUED jobs (no worker), CPU counted over "
            f"{args.window:.0f} s by psutil; commit {git_commit()}, {cpu_model()} ({os.cpu_count()} CPUs, shared "
            f"with other work), Python {platform.python_version()}.")  # fmt: skip
    lines = [head, "", "| output | CPU s | wall s | share of a core | exit on SIGINT |", "|---|---|---|---|---|"]
    for r in rows:
        share = f"{100 * r['share']:.1f} %"
        lines.append(f"| {r['output']} | {r['cpu_s']:.2f} | {r['wall_s']:.1f} | {share} | {r['exit']} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
