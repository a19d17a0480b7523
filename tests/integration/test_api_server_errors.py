"""A real server-side error (a bug: an exception no handler expects) answers 500 problem+json with a
correlation id that is also logged, and the keep-alive connection stays usable (issue #16): the next
request on the same socket succeeds. Runs the app under uvicorn in a thread, talks raw HTTP/1.1."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import uvicorn
from fastapi import FastAPI

from common.database import create_engine_for, upgrade_to_head
from common.errors import ConfigurationError
from common.settings import Settings
from service.app import create_app


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture()
def served(tmp_path: Path) -> Iterator[int]:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    upgrade_to_head(url)
    engine = create_engine_for(url)
    app: FastAPI = create_app(Settings(), engine)

    @app.get("/test-bug")
    def bug() -> None:
        raise RuntimeError("a bug the handlers do not know")

    @app.get("/test-config-error")
    def config_error() -> None:
        raise ConfigurationError("HOI_REFINE_SOMETHING is wrong")

    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="off"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive()
        time.sleep(0.05)
    yield port
    server.should_exit = True
    thread.join(10)
    engine.dispose()


def _request(sock: socket.socket, path: str) -> tuple[int, dict[str, str], bytes]:
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: test\r\n\r\n".encode())
    buf = b""
    while b"\r\n\r\n" not in buf:
        data = sock.recv(65536)
        assert data, "the server closed the connection"
        buf += data
    head, body = buf.split(b"\r\n\r\n", 1)
    lines = head.decode().split("\r\n")
    headers = {k.lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
    while len(body) < int(headers["content-length"]):
        data = sock.recv(65536)
        assert data, "the server closed the connection mid-body"
        body += data
    return int(lines[0].split()[1]), headers, body


@pytest.mark.parametrize("path", ["/test-bug", "/test-config-error"])
def test_500_keeps_the_connection_and_carries_a_logged_correlation_id(
    served: int, path: str, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR, logger="hoi_refine.service"), socket.create_connection(
        ("127.0.0.1", served), timeout=10
    ) as sock:
        status, headers, body = _request(sock, path)
        assert status == 500 and headers["content-type"] == "application/problem+json"
        doc = json.loads(body)
        cid = doc["correlation_id"]
        assert len(cid) == 32 and headers["x-correlation-id"] == cid
        if path == "/test-bug":  # a bug's internals stay in the log; the answer says where to look
            assert cid in doc["detail"] and "RuntimeError" not in body.decode() and "a bug" not in body.decode()
        assert headers.get("connection", "").lower() != "close"
        for _ in range(3):  # the same socket keeps serving
            status, _, body = _request(sock, "/healthz")
            assert status == 200 and json.loads(body) == {"status": "ok"}
    assert any(cid in record.getMessage() for record in caplog.records), [r.getMessage() for r in caplog.records]
