"""What ``hoi-refine up`` leaves under the var dir, so the next ``up`` can find and clear a dead one (issue #16).

* ``up.lock``: held with ``flock`` for as long as an ``up`` runs. The kernel drops the lock when that
  process dies, however it dies (SIGKILL included), so "locked" means "alive" with no pid guessing.
* ``up.json``: the running deployment: supervisor pid and host, the API child's pid and start time, its
  URL. Written when the API starts (again after each API restart), removed on a clean stop. Found with
  the lock free, it describes a deployment that died: ``clear_stale`` stops its API child if that very
  process (same pid *and* start time) still runs, and names the supervisor whose workers' jobs should go
  back to the queue.
* ``up-dev-key`` (mode 0600): the development API key, reused by the next ``up`` while it is valid, so
  jobs submitted with it stay readable across restarts; ``hoi-refine keys revoke`` retires it and the next
  ``up`` makes a new one.

``die_with_parent()`` gives a child process ``PR_SET_PDEATHSIG`` (Linux): it gets SIGTERM when the thread
that started it exits, so an ``up`` killed with SIGKILL does not leave its API holding the port.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import signal
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from common.errors import ConfigurationError

log = logging.getLogger(__name__)

LOCK_NAME, STATE_NAME, KEY_NAME = "up.lock", "up.json", "up-dev-key"
PR_SET_PDEATHSIG = 1


@dataclass
class DeploymentRecord:
    supervisor_pid: int
    host: str
    url: str
    api_pid: int | None = None
    api_start_time: str | None = None

    @property
    def worker_prefix(self) -> str:
        """Worker ids of this deployment's actors start with this (see ``worker.runtime.pool``)."""
        return f"{self.host}-{self.supervisor_pid}-w"


def process_start_time(pid: int) -> str | None:
    """The kernel's start time of ``pid`` (``/proc/PID/stat`` field 22), or None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]  # fields after "(comm)": state is field 3, starttime 22


def die_with_parent() -> Callable[[], None] | None:
    """A ``preexec_fn`` that makes the child receive SIGTERM when this process's calling thread dies."""
    if not sys.platform.startswith("linux"):
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl  # resolved here: the child only calls it
    parent = os.getpid()

    def preexec() -> None:
        prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl: nobody would signal us
            os._exit(1)

    return preexec


def bind_listener(host: str, port: int) -> socket.socket:
    """The API's listening socket, bound here so that no other process (Ray's, for one, which starts beside the
    API and takes ephemeral ports) can take the port between the check and the API's start; the API child
    inherits it (``hoi-refine serve --fd``). Raises ``OSError`` when the port is in use."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(2048)
    except OSError:
        sock.close()
        raise
    return sock


class DeploymentState:
    """The lock, record and key file of one var dir (see the module doc)."""

    def __init__(self, var_dir: Path) -> None:
        self.dir = Path(var_dir)
        self._lock_fd: int | None = None

    @property
    def state_path(self) -> Path:
        return self.dir / STATE_NAME

    def acquire(self) -> DeploymentRecord | None:
        """Take the lock; returns the record of a dead deployment found here (None when there was none)."""
        import fcntl

        self.dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            alive = self.read()
            where = f" (pid {alive.supervisor_pid}, API at {alive.url})" if alive else ""
            raise ConfigurationError(
                f"another `hoi-refine up` is running from {self.dir}{where}; stop it first (Ctrl-C or SIGTERM)"
            ) from None
        self._lock_fd = fd
        return self.read()

    def read(self) -> DeploymentRecord | None:
        try:
            return DeploymentRecord(**json.loads(self.state_path.read_text()))
        except (OSError, ValueError, TypeError):
            return None

    def write(self, record: DeploymentRecord) -> None:
        tmp = self.state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(asdict(record)))
        tmp.replace(self.state_path)

    def release(self) -> None:
        with contextlib.suppress(OSError):
            self.state_path.unlink()
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # closing drops the flock
            self._lock_fd = None

    # ------------------------------------------------------------------ the development key
    def saved_key(self) -> str | None:
        try:
            return (self.dir / KEY_NAME).read_text().strip() or None
        except OSError:
            return None

    def save_key(self, plaintext: str) -> None:
        path = self.dir / KEY_NAME
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(plaintext + "\n")
        os.chmod(path, 0o600)


def clear_stale(record: DeploymentRecord, grace_s: float = 10.0) -> bool:
    """Stop the dead deployment's API child if that same process still runs; True when one was stopped."""
    pid = record.api_pid
    if pid is None or record.api_start_time is None or process_start_time(pid) != record.api_start_time:
        return False
    log.warning("a previous `hoi-refine up` (pid %s) died and left its API (pid %s) running: stopping it",
                record.supervisor_pid, pid)  # fmt: skip
    _signal(pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and process_start_time(pid) == record.api_start_time:
        time.sleep(0.1)
    if process_start_time(pid) == record.api_start_time:
        _signal(pid, signal.SIGKILL)
    return True


def _signal(pid: int, sig: Any) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.kill(pid, sig)
