"""One ``hoi-refine up`` per var dir (a ``flock`` held while it lives), and the record a dead one leaves."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from common.errors import ConfigurationError
from worker.runtime.deployment_state import DeploymentRecord, DeploymentState, clear_stale, process_start_time


def test_one_up_per_var_dir_and_stale_records(tmp_path: Path) -> None:
    state = DeploymentState(tmp_path / "var")
    assert state.acquire() is None
    state.write(DeploymentRecord(supervisor_pid=1, host="h", url="http://127.0.0.1:1", api_pid=None))
    with pytest.raises(ConfigurationError, match="another `hoi-refine up` is running"):
        DeploymentState(tmp_path / "var").acquire()
    # The lock holder vanishes without cleaning up (its lock is dropped with its file descriptor).
    assert state._lock_fd is not None
    os.close(state._lock_fd)
    state._lock_fd = None
    again = DeploymentState(tmp_path / "var")
    stale = again.acquire()
    assert stale is not None and stale.supervisor_pid == 1
    assert clear_stale(stale) is False  # no API process recorded: nothing to stop
    again.release()
    assert not (tmp_path / "var" / "up.json").exists()


def test_clear_stale_stops_only_the_recorded_process(tmp_path: Path) -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        started = process_start_time(child.pid)
        assert started is not None
        other_start = DeploymentRecord(1, "h", "u", api_pid=child.pid, api_start_time="0")
        assert clear_stale(other_start) is False and child.poll() is None  # same pid, another process: left alone
        assert clear_stale(DeploymentRecord(1, "h", "u", api_pid=child.pid, api_start_time=started)) is True
        assert child.wait(10) == -15  # SIGTERM
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
