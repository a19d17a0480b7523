"""Issue #6.1 "must show": ``hoi-refine submit --wait`` against ``hoi-refine up --workers 2``, Ctrl-C, re-run.

A folder of 8 real DexYCB development sequences (cut to 12 frames each, from the first frame with a hand,
so that the refinement takes about a second) goes through the real command in a child process; SIGINT
arrives once about half of them are submitted; the same command run again submits each sequence exactly
once in total (counted in the database), downloads every result and contacts file and prints the summary.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

from common.database import create_engine_for
from common.result_format import read_summary
from common.sequence import Sequence
from common.sequence_io import load_sequence, save_sequence
from worker.runtime.demo_client import local_deployment
from worker.runtime.supervisor import hoi_refine_command

pytestmark = pytest.mark.slow

SEQUENCES = 8
FRAMES = 12


def _cut(seq: Sequence, frames: int) -> Sequence:
    """``frames`` frames from the first one where the hand is annotated (DexYCB hands enter late)."""
    start = int(np.flatnonzero(seq.hands[0].valid)[0])
    sl = slice(start, start + frames)
    seq.object_pose = seq.object_pose[sl]
    for hand in seq.hands:
        hand.valid = hand.valid[sl]
        hand.keypoints = None if hand.keypoints is None else hand.keypoints[sl]
        if hand.mano is not None:
            m = hand.mano
            m.global_orient, m.hand_pose, m.trans = m.global_orient[sl], m.hand_pose[sl], m.trans[sl]
    seq.frame_start = start
    return seq.validate()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _submitted(out: Path) -> int:
    try:
        doc = json.loads((out / "manifest.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):  # not written yet
        return 0
    return sum(1 for e in doc["entries"] if e.get("job_id"))


def test_submit_folder_to_two_workers_interrupt_and_resume(dexycb_dev_files: list[Path], tmp_path: Path) -> None:
    data, out = tmp_path / "dev", tmp_path / "out"
    data.mkdir()
    for path in dexycb_dev_files[:: len(dexycb_dev_files) // SEQUENCES][:SEQUENCES]:
        save_sequence(_cut(load_sequence(path), FRAMES), data / path.name)
    db_url = f"sqlite:///{tmp_path / 'up.sqlite3'}"
    env = {**os.environ, "HOI_REFINE_DATABASE_URL": db_url, "HOI_REFINE_VAR_DIR": str(tmp_path / "var")}

    with local_deployment(tmp_path / "up.log", workers=2, port=_free_port(), env=env) as dep:
        cmd = [
            *hoi_refine_command(), "submit", str(data), "--api", dep.base_url, "--key", dep.api_key,
            "--out", str(out), "--wait", "--concurrency", "1", "--poll-interval", "0.3",
            "--max-generations", "1", "--popsize", "4", "--seed", "3",
        ]  # fmt: skip
        # A shell's background job starts with SIGINT ignored, and an ignored signal stays ignored in the children:
        # the Ctrl-C below would then never reach the command. With a handler (not "ignore") here the child starts
        # with the default disposition, as it does from a terminal.
        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            first = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        finally:
            signal.signal(signal.SIGINT, previous)
        deadline = time.monotonic() + 120
        while _submitted(out) < SEQUENCES // 2 and first.poll() is None:
            assert time.monotonic() < deadline, "submission did not start"
            time.sleep(0.01)
        first.send_signal(signal.SIGINT)  # Ctrl-C
        _, err1 = first.communicate(timeout=120)
        assert first.returncode == 130, err1
        assert "Run the same command again to resume" in err1
        interrupted_at = _submitted(out)

        second = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
        assert second.returncode == 0, second.stderr[-3000:]

    engine = create_engine_for(db_url)
    with engine.connect() as conn:
        jobs = conn.execute(sa.text("SELECT name, state FROM jobs")).all()
    engine.dispose()
    assert len(jobs) == SEQUENCES  # each sequence submitted once in total
    assert len({name for name, _ in jobs}) == SEQUENCES and {s for _, s in jobs} == {"SUCCEEDED"}

    manifest = json.loads((out / "manifest.json").read_text())
    entries = manifest["entries"]
    assert len(entries) == SEQUENCES and sum(e["posts"] for e in entries) == SEQUENCES
    for e in entries:
        summary = read_summary((out / e["files"]["result"]).read_bytes())
        assert {"raw", "refined"} <= summary["metrics"].keys()
        # The worker's proof travels with the dataset, and this copy is the file it verified (issue #15 item 2).
        proof = e["metrics"]["verification"]
        assert proof["verified"] is True and proof["download_matches"] is True
        contacts = json.loads((out / e["files"]["contacts"]).read_text())
        assert contacts["count"] == len(contacts["contacts"])
    assert "Jobs by state" in second.stderr and "SUCCEEDED" in second.stderr and "refined" in second.stderr
    print(f"interrupted with {interrupted_at}/{SEQUENCES} submitted; summary:\n{second.stderr[-2500:]}")
