"""docker-compose.yml and the Dockerfile, checked without a Docker engine (issue #5.4).

Every service command is parsed by the real ``hoi-refine`` argument parser (after compose's ``${VAR:-default}``
interpolation with the defaults), so a renamed subcommand or option breaks this test, not a deployment.
"""

from __future__ import annotations

import re
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
