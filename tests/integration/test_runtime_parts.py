"""Small parts of the runtime: signal handling, the progress record, the actor environment, pool settings."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path

import pytest

from common.errors import ConfigurationError
from common.settings import get_settings
from worker.refine.windowed import RefineProgress
from worker.runtime.backoff import WorkerStopping
from worker.runtime.jobs import RefineJob, SelfTestJob, _progress_dict, make_job_function
from worker.runtime.pool import PoolConfig, actor_environment
from worker.runtime.supervisor import stop_on_signals


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_stop_on_signals_sets_the_event_and_restores_handlers(sig: signal.Signals) -> None:
    before = signal.getsignal(sig)
    stop = threading.Event()
    with stop_on_signals(stop):
        os.kill(os.getpid(), sig)
        assert stop.wait(2)
        os.kill(os.getpid(), sig)  # a second signal while stopping is not fatal either
    assert signal.getsignal(sig) is before


def test_progress_record_is_json_ready_and_keeps_window_loss_evaluations_eta() -> None:
    import numpy as np

    p = RefineProgress(window=3, windows=9, best_loss=float(np.float64(1.5)), evaluations=240, elapsed_s=12.0,
                       eta_s=24.0)  # fmt: skip
    out = _progress_dict(p)
    assert out == {"window": 3, "windows": 9, "best_loss": 1.5, "evaluations": 240, "elapsed_s": 12.0,
                   "eta_s": 24.0, "skipped": 0, "fraction": 0.0, "attempt": 1, "attempts": 1, "polish_sweep": 0,
                   "rescue": False, "deriving": False, "compiling_rescue": False}  # fmt: skip
    assert _progress_dict({"window": np.int64(2), "junk": object()}) == {"window": 2}


def test_actor_environment_makes_paths_absolute(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOI_REFINE_VAR_DIR", "relative/var")
    monkeypatch.setenv("HOI_REFINE_LEASE_SECONDS", "7")
    monkeypatch.delenv("HOI_REFINE_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    env = actor_environment()
    assert env["HOI_REFINE_VAR_DIR"] == str(tmp_path / "relative" / "var")
    assert env["HOI_REFINE_DATABASE_URL"] == f"sqlite:///{tmp_path / 'relative' / 'var' / 'hoi-refine.sqlite3'}"
    assert env["HOI_REFINE_LEASE_SECONDS"] == "7"
    assert all(k.startswith("HOI_REFINE_") for k in env)


def test_pool_and_job_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="workers"):
        PoolConfig(workers=0)
    with pytest.raises(ValueError, match="threads_per_worker"):
        PoolConfig(threads_per_worker=0)
    with pytest.raises(ValueError, match="ray_address"):
        PoolConfig(join_as_node=True)
    assert isinstance(make_job_function("refine", 2), RefineJob)
    assert isinstance(make_job_function("selftest", 1), SelfTestJob)
    with pytest.raises(ConfigurationError, match="job kind"):
        make_job_function("nope", 1)


def _fake_ray(tmp_path: Path, failures: int) -> Path:
    """A `ray` executable that logs its arguments and fails its first ``failures`` `ray start` calls."""
    script = tmp_path / "ray"
    script.write_text(
        "#!/bin/sh\n"
        f'echo "$@" >> {tmp_path}/calls\n'
        f'if [ "$1" = start ] && [ "$(grep -c ^start {tmp_path}/calls)" -le {failures} ]; then exit 1; fi\n'
    )
    script.chmod(0o755)
    return script


def test_joining_the_ray_cluster_retries_a_failed_ray_start(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import worker.runtime.pool as pool_module

    monkeypatch.setattr(pool_module, "ray_executable", lambda: str(_fake_ray(tmp_path, failures=2)))
    monkeypatch.setattr(pool_module, "NODE_START_RETRY_SECONDS", 0.01)
    cfg = PoolConfig(ray_address="10.0.0.1:6380", join_as_node=True, node_start_args=("--node-ip-address", "10.0.0.2"))
    pool = pool_module.WorkerPool(cfg)
    pool._start_node(threading.Event())
    calls = (tmp_path / "calls").read_text().splitlines()
    temp_dir = pool_module.ray_temp_dir(get_settings().var_dir)  # Ray's session files go under the var dir
    start = ("start --address 10.0.0.1:6380 --num-cpus 1 --disable-usage-stats --node-ip-address 10.0.0.2 "
             f"--temp-dir {temp_dir}")
    # Two failed starts, each cleaned up with `ray stop --force`, then the third joins.
    assert calls == [start, "stop --force", start, "stop --force", start]
    assert pool._node_started

    (tmp_path / "calls").unlink()
    monkeypatch.setattr(pool_module, "ray_executable", lambda: str(_fake_ray(tmp_path, failures=99)))
    with pytest.raises(ConfigurationError, match="after 3 attempts"):
        pool_module.WorkerPool(PoolConfig(ray_address="h:6380", join_as_node=True))._start_node(None)
    stop = threading.Event()
    stop.set()
    with pytest.raises(WorkerStopping):  # a stop during the wait ends it at once
        pool_module.WorkerPool(PoolConfig(ray_address="h:6380", join_as_node=True))._start_node(stop)


def test_worker_waits_for_an_unmigrated_database_says_why_and_stops_on_sigterm(tmp_path: Path) -> None:
    import subprocess

    from worker.runtime.supervisor import hoi_refine_command

    env = {**os.environ, "HOI_REFINE_DATABASE_URL": f"sqlite:///{tmp_path / 'empty.sqlite3'}"}
    proc = subprocess.Popen(
        [*hoi_refine_command(), "worker", "--job-kind", "selftest"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    watchdog = threading.Timer(60, proc.kill)
    watchdog.start()
    seen: list[str] = []
    assert proc.stdout is not None
    for line in proc.stdout:
        seen.append(line)
        if sum("database unreachable during schema check" in x for x in seen) >= 2:
            break
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=30)
    watchdog.cancel()
    out = "".join(seen) + rest
    assert proc.returncode == 0, out
    lines = [line for line in out.splitlines() if "database unreachable during schema check" in line]
    assert len(lines) >= 2, out  # retried with backoff, and said so each time
    assert "not at the migration head" in lines[0] and "Ray" not in out
