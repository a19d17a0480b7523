"""Docker and compose plumbing for ``bench/compose_test.py``: build the images, run the test stack, tear it down.

Kept apart from the scenario so that one reads as the test and this one as the machinery. Every command has a
timeout; nothing here deletes anything but this project's containers, networks and volumes.
"""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILES = ("docker-compose.yml", "docker-compose.test.yml")
IMAGE = "hoi-refine:latest"
#: Host ports docker-compose.test.yml binds (API, Ray GCS): checked free before the stack starts.
TEST_PORTS = (18000, 6380)
#: Logged by each worker actor once its loop runs (worker/runtime/loop.py).
WORKER_STARTED = re.compile(r"worker (\S+) \(pid \d+\) started")


class StackError(RuntimeError):
    """A docker / compose step failed; the message says which and shows its output."""


def run(cmd: list[str], timeout: float, env: dict[str, str] | None = None, check: bool = True) -> str:
    """Run ``cmd`` in the repository root; its stdout (stderr is appended on failure)."""
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        raise StackError(f"{' '.join(cmd)}: no answer within {timeout:.0f} s") from exc
    if check and proc.returncode != 0:
        raise StackError(f"{' '.join(cmd)} exited {proc.returncode}:\n{(proc.stdout + proc.stderr)[-4000:]}")
    return proc.stdout


def compose_command() -> list[str]:
    """``docker compose`` (v2 plugin) where it exists, else Debian's ``docker-compose`` (v1)."""
    docker = shutil.which("docker")
    if docker is None:
        raise StackError("docker is not installed (apt-get install docker.io, then start dockerd)")
    if subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0:
        return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    if legacy is None:
        raise StackError("neither `docker compose` nor `docker-compose` is installed (apt-get install docker-compose)")
    return [legacy]


def check_engine() -> str:
    """The engine's version; a clear error when dockerd is not running."""
    try:
        return run(["docker", "version", "--format", "{{.Server.Version}}"], timeout=30).strip()
    except StackError as exc:
        hint = "start it: dockerd >/tmp/dockerd.log 2>&1 &"
        raise StackError(f"the Docker engine does not answer ({hint})\n{exc}") from exc


def check_ports_free(ports: tuple[int, ...] = TEST_PORTS) -> None:
    for port in ports:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                raise StackError(f"127.0.0.1:{port} is in use; docker-compose.test.yml needs it (another stack?)")


def build_base_image(tag: str, force: bool = False) -> float | None:
    """``docker/build_base_image.sh`` (idempotent); seconds it took, or None when the image already existed."""
    if not force and run(["docker", "image", "ls", "-q", tag], timeout=30).strip():
        return None
    t0 = time.monotonic()
    run([str(ROOT / "docker" / "build_base_image.sh"), *(["--force"] if force else []), tag], timeout=1800)
    return time.monotonic() - t0


def build_image(base_image: str, no_cache: bool) -> float:
    """``docker build`` of the project image with host networking; its wall-clock seconds."""
    cmd = ["docker", "build", "--network", "host", "--build-arg", f"BASE_IMAGE={base_image}", "-t", IMAGE]
    t0 = time.monotonic()
    run([*cmd, *(["--no-cache"] if no_cache else []), "."], timeout=3600)
    return time.monotonic() - t0


def image_size_mb(image: str = IMAGE) -> float:
    return int(run(["docker", "image", "inspect", image, "--format", "{{.Size}}"], timeout=30)) / 1e6


@dataclass
class Stack:
    """One compose project of the test stack (``-p project``) with the environment it interpolates."""

    project: str
    env: dict[str, str]
    compose: list[str] = field(default_factory=compose_command)

    def cmd(self, *args: str) -> list[str]:
        files = [a for f in COMPOSE_FILES for a in ("-f", str(ROOT / f))]
        return [*self.compose, *files, "-p", self.project, *args]

    def version(self) -> str:
        name = " ".join(Path(c).name for c in self.compose)
        return f"{name} {run([*self.compose, 'version', '--short'], timeout=60).strip()}"

    def up(self, timeout: float) -> None:
        # Without --build: the image was built (and timed) just before; compose waits for the health checks of
        # each service's dependencies before starting it.
        run(self.cmd("up", "-d", "--no-build"), timeout=timeout, env=self.env)

    def container(self, service: str) -> str:
        cid = run(self.cmd("ps", "-q", service), timeout=60, env=self.env).strip()
        if not cid:
            raise StackError(f"service {service} has no container")
        return cid

    def logs(self, service: str | None = None) -> str:
        return run(self.cmd("logs", "--no-color", *([service] if service else [])), timeout=120, env=self.env,
                   check=False)  # fmt: skip

    def exec(self, service: str, *args: str, timeout: float = 120) -> str:
        return run(self.cmd("exec", "-T", service, *args), timeout=timeout, env=self.env)

    def worker_ids(self, service: str) -> set[str]:
        """Ids of the worker actors that service's container started (from its log)."""
        return set(WORKER_STARTED.findall(self.logs(service)))

    def wait_for_workers(self, services: tuple[str, ...], per_service: int, timeout: float) -> dict[str, set[str]]:
        deadline = time.monotonic() + timeout
        while True:
            ids = {s: self.worker_ids(s) for s in services}
            if all(len(v) >= per_service for v in ids.values()):
                return ids
            if time.monotonic() > deadline:
                raise StackError(f"worker actors not started within {timeout:.0f} s: {ids}")
            time.sleep(1.0)

    def inspect_state(self, container: str) -> dict[str, object]:
        state: dict[str, object] = json.loads(run(["docker", "inspect", "--format", "{{json .State}}", container],
                                                  timeout=30))  # fmt: skip
        state["RestartCount"] = int(run(["docker", "inspect", "--format", "{{.RestartCount}}", container], timeout=30))
        return state

    def project_containers(self) -> list[str]:
        label = f"label=com.docker.compose.project={self.project}"
        return run(["docker", "ps", "-aq", "--filter", label], timeout=30).split()

    def down(self, timeout_s: int = 20) -> float:
        """Stop and remove the project's containers, networks and volumes; seconds taken. Leaves no container."""
        t0 = time.monotonic()
        try:
            run(self.cmd("down", "-v", "--remove-orphans", "-t", str(timeout_s)), timeout=timeout_s * 6 + 60,
                env=self.env)  # fmt: skip
        finally:
            leftover = self.project_containers()
            if leftover:  # compose failed or timed out: remove them by id, this project's only
                run(["docker", "rm", "-f", "-v", *leftover], timeout=120, check=False)
        return time.monotonic() - t0
