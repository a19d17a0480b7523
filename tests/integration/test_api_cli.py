"""``hoi-refine keys`` and ``hoi-refine serve``: keys are printed once and stored hashed; serve upgrades an
empty database to head and answers /readyz."""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import sqlalchemy as sa

from common.api_client import wait_until_ready
from common.api_key_store import ApiKeyStore, hash_key
from common.database import create_engine_for, is_at_head
from common.settings import get_settings
from service import cli
from worker.runtime.deployment_state import bind_listener
from worker.runtime.supervisor import hoi_refine_command


def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    commands = parser.add_subparsers(required=True)
    cli.register_serve(commands)
    cli.register_keys(commands)
    args = parser.parse_args(argv)
    return int(args.func(args))


def test_keys_create_prints_the_key_once_and_stores_only_its_hash(capsys: pytest.CaptureFixture[str]) -> None:
    assert run_cli("keys", "create", "alice") == 0
    plaintext = capsys.readouterr().out.strip()
    assert plaintext.startswith("hoi_") and len(plaintext) > 40
    url = get_settings().resolved_database_url()  # the SQLite file under the test's HOI_REFINE_VAR_DIR
    engine = create_engine_for(url)
    try:
        assert is_at_head(engine)
        with engine.connect() as conn:
            stored = conn.execute(sa.text("SELECT name, key_hash FROM api_keys")).all()
        assert [tuple(r) for r in stored] == [("alice", hash_key(plaintext))]
        assert ApiKeyStore(engine).authenticate(plaintext)
    finally:
        engine.dispose()
    assert run_cli("keys", "list") == 0
    listing = capsys.readouterr().out
    assert "alice" in listing and plaintext[:10] in listing and plaintext not in listing


@pytest.mark.slow
def test_serve_upgrades_an_empty_database_and_becomes_ready(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "HOI_REFINE_VAR_DIR": str(tmp_path / "served")}
    env.pop("HOI_REFINE_DATABASE_URL", None)
    code = f"from tests.integration.test_api_cli import run_cli; run_cli('serve', '--port', '{port}')"
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, cwd=Path(__file__).resolve().parents[2])
    try:
        resp = wait_until_ready(f"http://127.0.0.1:{port}", 60, alive=lambda: proc.poll() is None)
        assert resp is not None and resp.json() == {"status": "ready"}
        assert (tmp_path / "served" / "hoi-refine.sqlite3").is_file()
    finally:
        proc.terminate()
        proc.wait(timeout=15)


@pytest.mark.slow
def test_serve_on_an_inherited_socket_keeps_the_port_from_start_to_stop(tmp_path: Path) -> None:
    """``serve --fd`` (how ``hoi-refine up`` starts the API) serves on the socket its parent bound, so no other
    process can take the port while the API starts; the parent's socket stays bound after the API stops."""
    listener = bind_listener("127.0.0.1", 0)
    port = listener.getsockname()[1]
    env = {**os.environ, "HOI_REFINE_VAR_DIR": str(tmp_path / "served")}
    env.pop("HOI_REFINE_DATABASE_URL", None)
    fd = listener.fileno()
    with listener:
        with pytest.raises(OSError):
            bind_listener("127.0.0.1", port)  # taken from the start, before the API runs
        cmd = [*hoi_refine_command(), "serve", "--port", "1", "--fd", str(fd)]  # --port only names it
        proc = subprocess.Popen(cmd, env=env, pass_fds=(fd,))
        try:
            resp = wait_until_ready(f"http://127.0.0.1:{port}", 60, alive=lambda: proc.poll() is None)
            assert resp is not None and resp.json() == {"status": "ready"}
        finally:
            proc.terminate()
            proc.wait(timeout=15)
        with pytest.raises(OSError):
            bind_listener("127.0.0.1", port)
