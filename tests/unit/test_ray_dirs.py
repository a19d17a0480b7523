"""Ray's sessions and logs go under the deployment's var dir (issue #53 item 8), within Ray's Unix socket limit."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from worker.runtime.pool import RAY_SOCKET_SUFFIX_BYTES, SOCKET_PATH_MAX, ray_temp_dir, with_temp_dir

#: The longest socket Ray makes below its temp dir, spelled as Ray 2.x spells it (7-digit pid, suffix ".9").
LONGEST = "/session_2026-12-06_19-52-06_123456_1234567/sockets/plasma_store.9"


def test_the_suffix_budget_covers_rays_longest_socket_name() -> None:
    assert len(LONGEST) <= RAY_SOCKET_SUFFIX_BYTES


@pytest.fixture
def short_dir() -> Iterator[Path]:
    """A folder with a short path (pytest's ``tmp_path`` is too long for Ray's sockets)."""
    folder = Path(tempfile.mkdtemp(prefix="r", dir="/tmp"))
    try:
        yield folder
    finally:
        shutil.rmtree(folder)


def test_a_short_var_dir_holds_rays_folder_itself(short_dir: Path) -> None:
    var = short_dir / "var"
    got = ray_temp_dir(var)
    assert got == var.resolve() / "ray" and got.is_dir() and not got.is_symlink()
    assert len(str(got) + LONGEST) <= SOCKET_PATH_MAX


def test_a_long_var_dir_links_rays_short_folder_and_stays_the_same(tmp_path: Path) -> None:
    var = tmp_path / ("deep-" * 12) / "var"
    got = ray_temp_dir(var)
    assert len(str(got) + LONGEST) <= SOCKET_PATH_MAX
    link = var.resolve() / "ray"
    assert link.is_symlink() and link.resolve() == got.resolve()
    assert ray_temp_dir(var) == got  # the same folder on every start
    (got / "session_latest").mkdir()
    assert (link / "session_latest").is_dir()  # the logs are found under the var dir
    other = ray_temp_dir(tmp_path / ("wide-" * 12) / "var")
    assert other != got
    for made in (got, other):
        shutil.rmtree(made)


def test_ray_start_gets_the_temp_dir_unless_the_user_named_one(short_dir: Path) -> None:
    var = short_dir / "var"
    args = with_temp_dir(("--node-ip-address", "127.0.0.2"), var)
    assert args[:2] == ("--node-ip-address", "127.0.0.2") and args[2] == "--temp-dir"
    assert Path(args[3]) == ray_temp_dir(var)
    assert with_temp_dir(("--temp-dir", "/srv/ray"), var) == ("--temp-dir", "/srv/ray")
    assert with_temp_dir(("--temp-dir=/srv/ray",), var) == ("--temp-dir=/srv/ray",)
