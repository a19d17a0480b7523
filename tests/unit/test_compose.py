"""docker-compose.yml and the Dockerfile, checked without a Docker engine (issue #5.4).

Every service command is parsed by the real ``hoi-refine`` argument parser (after compose's ``${VAR:-default}``
interpolation with the defaults), so a renamed subcommand or option breaks this test, not a deployment.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from common.cli import build_parser
from common.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
INTERPOLATION = re.compile(r"\$\{([A-Z0-9_]+)(?::-([^}]*))?\}")


def _interpolate(value: str) -> str:
    """Compose's ``${VAR:-default}`` with every variable unset (``$$`` is a literal ``$``)."""
    return INTERPOLATION.sub(lambda m: m.group(2) or "", value).replace("$$", "$")


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    return data


def _command(service: dict[str, Any]) -> list[str]:
    cmd = service["command"]
    assert isinstance(cmd, list), "commands must be exec-form lists (no shell parsing)"
    return [_interpolate(str(c)) for c in cmd]


def test_services_and_roles(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert set(services) == {"postgres", "api", "ray-head", "worker-1", "worker-2"}
    assert services["postgres"]["image"].startswith("postgres:")
    for name in ("api", "ray-head", "worker-1", "worker-2"):
        assert services[name]["build"] == "." and services[name]["image"] == "hoi-refine:latest", name
    assert _command(services["api"])[:2] == ["hoi-refine", "serve"]
    assert _command(services["ray-head"])[:2] == ["hoi-refine", "ray-head"]
    for name in ("worker-1", "worker-2"):
        cmd = _command(services[name])
        assert cmd[:2] == ["hoi-refine", "worker"]
        assert cmd[cmd.index("--ray-address") + 1] == "ray-head:6379" and "--ray-node" in cmd


def test_every_command_is_a_real_hoi_refine_invocation(compose: dict[str, Any]) -> None:
    parser = build_parser()
    for name, service in compose["services"].items():
        if name == "postgres":
            continue
        cmd = _command(service)
        assert cmd[0] == "hoi-refine", name
        args = parser.parse_args(cmd[1:])  # exits (SystemExit) on an unknown subcommand or option
        assert callable(args.func), name
    # The Dockerfile's default command is the API.
    dockerfile = (ROOT / "Dockerfile").read_text()
    cmd_line = next(line for line in dockerfile.splitlines() if line.startswith("CMD "))
    default = yaml.safe_load(cmd_line[4:])
    assert default[0] == "hoi-refine" and callable(parser.parse_args(default[1:]).func)


def test_configuration_is_environment_only_and_consistent(compose: dict[str, Any]) -> None:
    services = compose["services"]
    known = {f"HOI_REFINE_{name.upper()}" for name in Settings.model_fields}
    urls = set()
    for name in ("api", "ray-head", "worker-1", "worker-2"):
        env = services[name]["environment"]
        assert isinstance(env, dict), name
        for key in env:
            assert not key.startswith("HOI_REFINE_") or key in known, f"{name}: {key} is not a setting"
        urls.add(_interpolate(env["HOI_REFINE_DATABASE_URL"]))
        assert "volumes" not in services[name], f"{name} must not need mounted config"
    assert urls == {"postgresql+psycopg://hoi:hoi@postgres:5432/hoi"}
    pg = services["postgres"]["environment"]
    assert {_interpolate(pg[k]) for k in ("POSTGRES_USER", "POSTGRES_DB")} == {"hoi"}


def test_health_checks_and_start_order(compose: dict[str, Any]) -> None:
    services = compose["services"]
    for name, service in services.items():
        test = service["healthcheck"]["test"]
        assert test[0] in ("CMD", "CMD-SHELL") and len(test) > 1, name
    assert "/readyz" in " ".join(services["api"]["healthcheck"]["test"])
    assert services["api"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    for name in ("worker-1", "worker-2"):
        deps = services[name]["depends_on"]
        # Workers start once the API has migrated the schema and the Ray head answers.
        assert deps["api"]["condition"] == deps["ray-head"]["condition"] == "service_healthy"
        health_file = _command(services[name])[_command(services[name]).index("--health-file") + 1]
        assert health_file in " ".join(services[name]["healthcheck"]["test"])


def test_dockerfile_copies_what_the_package_needs() -> None:
    dockerfile = (ROOT / "Dockerfile").read_text()
    copied = {line.split()[1] for line in dockerfile.splitlines() if line.startswith("COPY ")}
    for path in copied:
        assert (ROOT / path).exists(), f"Dockerfile copies {path}, which is not in the repository"
    for package in ("common", "worker", "service", "migrations"):
        assert package in copied
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ".venv" in ignored and ".git" in ignored


# --- docker-compose.test.yml: the stack on the host network of these machines (issue #20.4) -----------------

#: Ports these machines' own services hold, which no container of the test stack may take.
HOST_SERVICES = {6379: "Redis", 5432: "PostgreSQL (used, not bound)"}
#: The Ray nodes' IP: loopback, and not one Ray rewrites to the routable address.
RAY_IP = "127.0.0.2"


@pytest.fixture(scope="module")
def override() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((ROOT / "docker-compose.test.yml").read_text())
    return data


def _ray_start_args(cmd: list[str]) -> list[str]:
    from worker.runtime.commands.pool_options import parse_ray_start_args as parse

    joined = [c.split("=", 1)[1] for c in cmd if c.startswith("--ray-start-args=")]
    assert len(joined) == 1, cmd
    return list(parse(joined[0]))


def _option(args: list[str], name: str) -> str:
    return args[args.index(name) + 1]


def test_compose_v1_can_read_the_base_file(compose: dict[str, Any]) -> None:
    # Debian's docker-compose (v1) rejects a top-level `name:`; the project name comes from -p instead.
    assert set(compose) <= {"services", "volumes", "networks"} | {k for k in compose if k.startswith("x-")}


def test_default_override_publishes_the_api_only() -> None:
    # docker-compose.override.yml is read by a plain `docker compose up`; the test stack names its files instead.
    data = yaml.safe_load((ROOT / "docker-compose.override.yml").read_text())
    assert data == {"services": {"api": {"ports": ["${HOI_REFINE_API_PORT:-8000}:8000"]}}}
    assert _interpolate(data["services"]["api"]["ports"][0]) == "8000:8000"


def test_override_puts_every_service_on_the_host_network(compose: dict[str, Any], override: dict[str, Any]) -> None:
    assert set(override["services"]) == set(compose["services"])
    for name, service in override["services"].items():
        assert service["network_mode"] == "host", name
        assert "ports" not in service, f"{name}: published ports mean nothing on the host network"
        build = service["build"]
        assert build["network"] == "host" and "BASE_IMAGE" in build["args"], name
        env = service["environment"]
        url = _interpolate(env["HOI_REFINE_DATABASE_URL"])
        assert url.startswith("postgresql+psycopg://") and "@127.0.0.1:5432/" in url, (name, url)
    assert override["services"]["postgres"]["image"] == "hoi-refine:latest"  # a stand-in, no postgres image


def test_override_commands_are_real_and_stay_on_loopback(override: dict[str, Any]) -> None:
    parser = build_parser()
    services = override["services"]
    for name in ("api", "ray-head", "worker-1", "worker-2"):
        args = parser.parse_args(_command(services[name])[1:])
        assert callable(args.func), name
    api = _command(services["api"])
    assert _option(api, "--host") == "127.0.0.1"
    assert f"127.0.0.1:{_option(api, '--port')}/readyz" in " ".join(services["api"]["healthcheck"]["test"])

    head = _command(services["ray-head"])
    gcs_port = int(_option(head, "--port"))
    assert gcs_port not in HOST_SERVICES, "Redis holds 6379 on these machines"
    # 127.0.0.2, not 127.0.0.1: Ray replaces 127.0.0.1 with the machine's routable address (off loopback).
    assert services["ray-head"]["healthcheck"]["test"][-1] == f"{RAY_IP}:{gcs_port}"
    for name in ("worker-1", "worker-2"):
        cmd = _command(services[name])
        assert _option(cmd, "--ray-address") == f"{RAY_IP}:{gcs_port}" and "--ray-node" in cmd, name


def test_ray_nodes_pin_disjoint_ports_on_loopback(override: dict[str, Any]) -> None:
    """Three Ray nodes share one network namespace: each pins its IP and ports, and no two ports collide."""
    services = override["services"]
    head_port = int(_option(_command(services["ray-head"]), "--port"))
    taken: dict[int, str] = {head_port: "ray-head GCS", 18000: "API"}
    pinned = ("--node-manager-port", "--object-manager-port", "--metrics-export-port",
              "--dashboard-agent-listen-port", "--dashboard-agent-grpc-port", "--runtime-env-agent-port")  # fmt: skip
    for name in ("ray-head", "worker-1", "worker-2"):
        args = _ray_start_args(_command(services[name]))
        assert _option(args, "--node-ip-address") == RAY_IP, name
        ports = [int(_option(args, flag)) for flag in pinned]
        if name == "ray-head":  # its (minimal) dashboard process listens even with --include-dashboard false
            ports.append(int(_option(args, "--dashboard-port")))
        # No Ray Client server (it needs ray[client], which the image does not install).
        assert "--ray-client-server-port" not in args, name
        low, high = int(_option(args, "--min-worker-port")), int(_option(args, "--max-worker-port"))
        assert low <= high, name
        for port in [*ports, *range(low, high + 1)]:
            assert port not in HOST_SERVICES, (name, port)
            assert port not in taken, f"{name}: port {port} also used by {taken.get(port)}"
            taken[port] = name


def test_ray_start_args_reach_ray_start_only_with_a_node() -> None:
    from worker.runtime.pool import PoolConfig

    args = build_parser().parse_args(
        ["worker", "--ray-address", "h:6380", "--ray-node", "--ray-start-args=--node-ip-address 127.0.0.1 --x 'a b'"]
    )
    assert args.ray_start_args == ("--node-ip-address", "127.0.0.1", "--x", "a b")
    with pytest.raises(ValueError, match="--ray-node"):
        PoolConfig(ray_address="h:6380", node_start_args=("--node-ip-address", "127.0.0.1"))
    with pytest.raises(SystemExit):  # unbalanced quote: argparse's usage error, not a traceback
        build_parser().parse_args(["ray-head", "--ray-start-args=--x 'a"])


def test_dockerfile_base_is_an_argument_and_the_base_script_is_valid() -> None:
    lines = (ROOT / "Dockerfile").read_text().splitlines()
    arg = lines.index("ARG BASE_IMAGE=python:3.11-slim")
    assert lines[arg + 1] == "FROM ${BASE_IMAGE}"
    script = ROOT / "docker" / "build_base_image.sh"
    assert os.access(script, os.X_OK)
    assert subprocess.run(["bash", "-n", str(script)], capture_output=True).returncode == 0
