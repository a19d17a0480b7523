"""Loopback HTTP servers for tests that need real sockets: the app under uvicorn in a thread (server-sent
events must stream, which the in-process TestClient does not do), a whole deployment of it with in-test workers, a
webhook receiver, and receivers that answer too much or too slowly."""

from __future__ import annotations

import socket
import ssl
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import sqlalchemy as sa
import uvicorn

from common.api_key_store import ApiKeyStore
from common.database import create_engine_for
from common.queue import JobQueue
from common.settings import Settings
from service.app import create_app
from worker.runtime.loop import JobFunction, WorkerLoop


@contextmanager
def serve_app(app: Any) -> Iterator[str]:
    """Run ``app`` with uvicorn on 127.0.0.1 in a thread; yields its base URL. The socket is bound here and handed
    to uvicorn, so no other process can take the port between choosing it and serving on it."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False, lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)
        sock.close()


class LiveDeployment:
    """The API (``serve_app``) over ``settings.database_url`` and, once ``start_workers``, in-test workers:
    ``WorkerLoop`` threads that run ``job`` on the queue. ``key`` is an API key of the deployment's owner."""

    def __init__(self, settings: Settings, job: JobFunction) -> None:
        if settings.database_url is None:
            raise ValueError("a live deployment needs a database_url")
        self.settings, self.job = settings, job
        self.api_engine = create_engine_for(settings.database_url)
        self.worker_engine = create_engine_for(settings.database_url)
        self.queue = JobQueue(self.worker_engine, settings)
        self.key_id, self.key = ApiKeyStore(self.worker_engine).create("owner")
        self._stack = ExitStack()
        self.url = self._stack.enter_context(serve_app(create_app(settings, self.api_engine)))
        self.workers: list[WorkerLoop] = []
        self._threads: list[threading.Thread] = []

    def start_workers(self, count: int = 1) -> None:
        lease = self.settings.lease_seconds
        new = [WorkerLoop(self.queue, self.job, f"w{len(self.workers) + i + 1}", lease_seconds=lease,
                          idle_poll_seconds=0.05) for i in range(count)]  # fmt: skip
        self.workers += new
        for w in new:
            self._threads.append(threading.Thread(target=w.run, daemon=True))
            self._threads[-1].start()

    def stop(self) -> None:
        for w in self.workers:
            w.stop()
        for t in self._threads:
            t.join(timeout=30)
        self._stack.close()
        self.api_engine.dispose()
        self.worker_engine.dispose()

    def jobs(self) -> list[Any]:
        """Every job's id, name, state, idempotency key and batch, straight from the database."""
        with self.worker_engine.connect() as conn:
            return list(conn.execute(sa.text("SELECT id, name, state, idempotency_key, batch_id FROM jobs")).all())


@dataclass
class Receiver:
    """What a webhook receiver saw: (headers, body) per request, and the statuses it will answer with."""

    statuses: list[int] = field(default_factory=list)
    requests: list[tuple[dict[str, str], bytes]] = field(default_factory=list)
    #: A hanging receiver holds every request until this is set.
    release: threading.Event = field(default_factory=threading.Event)
    arrived: threading.Condition = field(default_factory=threading.Condition)
    url: str = ""

    def wait_for(self, count: int, timeout: float = 30.0) -> None:
        with self.arrived:
            if not self.arrived.wait_for(lambda: len(self.requests) >= count, timeout):
                raise AssertionError(f"receiver got {len(self.requests)} requests, expected {count}")


@contextmanager
def webhook_receiver(
    statuses: list[int] | None = None, hang: bool = False, location: str | None = None,
    tls: ssl.SSLContext | None = None,
) -> Iterator[Receiver]:
    """A loopback receiver: answers each request with the next of ``statuses`` (then 200). ``hang``: every
    request is held until ``receiver.release`` is set (a stuck endpoint). ``location``: sent as the Location
    header of every answer (a redirect, with a 3xx status). ``tls``: serves https with this server context."""
    rec = Receiver(statuses=list(statuses or []))

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers.get("content-length", "0")))
            with rec.arrived:
                rec.requests.append(({k.lower(): v for k, v in self.headers.items()}, body))
                status = rec.statuses.pop(0) if rec.statuses else 200
                rec.arrived.notify_all()
            if hang:
                rec.release.wait(60)
            self.send_response(status)
            if location is not None:
                self.send_header("location", location)
            self.send_header("content-length", "0")
            self.end_headers()

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    if tls is not None:
        server.socket = tls.wrap_socket(server.socket, server_side=True)
    rec.url = f"{'https' if tls else 'http'}://127.0.0.1:{server.server_address[1]}/hook"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield rec
    finally:
        rec.release.set()
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)


@dataclass
class RawReceiver:
    """A loopback TCP server that reads a request and then misbehaves; counts requests and bytes it sent."""

    url: str = ""
    requests: int = 0
    bytes_sent: int = 0
    stop: threading.Event = field(default_factory=threading.Event)
    arrived: threading.Condition = field(default_factory=threading.Condition)

    def wait_for(self, count: int, timeout: float = 30.0) -> None:
        with self.arrived:
            if not self.arrived.wait_for(lambda: self.requests >= count, timeout):
                raise AssertionError(f"receiver got {self.requests} requests, expected {count}")


@contextmanager
def misbehaving_receiver(kind: str) -> Iterator[RawReceiver]:
    """``endless``: answers 200 and then a body that never ends (as fast as the client reads); ``dribble``:
    sends its status line and headers one byte every 50 ms, never finishing them. Either stops when the client
    hangs up."""
    rec = RawReceiver()
    chunk = b"x" * 65536 if kind == "endless" else b""
    dribble = b"HTTP/1.1 200 OK\r\n" + b"x-slow: " + b"z" * 10_000_000

    def serve(conn: socket.socket) -> None:
        with conn:
            request = b""
            while b"\r\n\r\n" not in request and (data := conn.recv(65536)):
                request += data
            with rec.arrived:
                rec.requests += 1
                rec.arrived.notify_all()
            try:
                if kind == "endless":
                    conn.sendall(b"HTTP/1.1 200 OK\r\ncontent-length: 100000000000\r\n\r\n")
                    while not rec.stop.is_set():
                        conn.sendall(chunk)
                        rec.bytes_sent += len(chunk)
                else:
                    for byte in dribble:
                        if rec.stop.wait(0.05):
                            break
                        conn.sendall(bytes([byte]))
                        rec.bytes_sent += 1
            except OSError:
                pass  # the client hung up: what a bounded client does

    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.2)
    rec.url = f"http://127.0.0.1:{listener.getsockname()[1]}/hook"

    def accept() -> None:
        while not rec.stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(30)
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield rec
    finally:
        rec.stop.set()
        thread.join(timeout=10)
        listener.close()


def throwaway_certificates(folder: Path, name: str) -> tuple[Path, ssl.SSLContext] | None:
    """A throwaway CA (its PEM file) and a server context whose certificate names ``name``, made with the
    ``openssl`` command; None when it is missing."""
    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True, timeout=60)

    try:
        openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
                "-subj", "/CN=hoi-refine test CA", "-addext", "basicConstraints=critical,CA:TRUE",
                "-addext", "keyUsage=critical,keyCertSign,cRLSign")  # fmt: skip
    except FileNotFoundError:
        return None
    (folder / "server.ext").write_text(f"subjectAltName=DNS:{name}\nextendedKeyUsage=serverAuth\n")
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
            "-subj", f"/CN={name}")  # fmt: skip
    openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", "server.pem", "-days", "2", "-extfile", "server.ext")  # fmt: skip
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(folder / "server.pem", folder / "server.key")
    return folder / "ca.pem", context
