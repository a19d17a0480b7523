"""Hostile uploads against a real ``hoi-refine serve`` process, with its peak memory measured (issue #16).

The server runs with an 8 MiB request limit (2 MiB for JSON) and an 8 MiB uncompressed-sequence limit.
Attacks: a 1 GiB chunked upload (multipart and JSON), NPZ zip bombs (an honest member declaring 1 GiB,
a lying member whose deflate stream inflates to 1 GiB behind a 5-frame header, members adding up past
the limit) and, for the legitimate worst cases, a valid upload padded to the limit with incompressible
bytes and a valid JSON body near its limit. Each gets its 202/413/422, and the server's peak RSS
(``VmHWM`` in ``/proc/PID/status``) stays within the bound the README documents:
``idle + 3 x max_request_bytes + 2 x max_sequence_bytes + 10 x max_json_request_bytes``.
"""

from __future__ import annotations

import io
import json
import os
import select
import socket
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from common.api_key_store import ApiKeyStore
from common.database import create_engine_for
from common.npz_writer import npy_bytes
from common.sequence_io import sequence_to_json_dict, sequence_to_npz_bytes
from tests.support.queue_fixtures import tiny_sequence
from worker.runtime.supervisor import hoi_refine_command

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")]

MIB = 1024 * 1024
REQUEST_LIMIT, SEQUENCE_LIMIT, JSON_LIMIT = 8 * MIB, 8 * MIB, 2 * MIB
BOUND = 3 * REQUEST_LIMIT + 2 * SEQUENCE_LIMIT + 10 * JSON_LIMIT


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def peak_rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


def _zip(members: list[tuple[str, bytes, int, int]]) -> bytes:
    """A zip by hand: (name, raw-deflated data, crc32, declared uncompressed size) per member, so a member can
    declare a size other than what its data inflates to."""
    out, central = io.BytesIO(), io.BytesIO()
    for name, data, crc, size in members:
        offset = out.tell()
        fname = name.encode()
        out.write(struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0x21, crc, len(data), size, len(fname), 0))
        out.write(fname + data)
        central.write(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0x21, crc, len(data), size,
                                  len(fname), 0, 0, 0, 0, 0, offset) + fname)  # fmt: skip
    cd = central.getvalue()
    n = len(members)
    return out.getvalue() + cd + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(cd), out.tell(), 0)


def _deflate(chunks: Iterator[bytes]) -> tuple[bytes, int, int]:
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    parts, crc, size = [], 0, 0
    for chunk in chunks:
        parts.append(comp.compress(chunk))
        crc, size = zlib.crc32(chunk, crc), size + len(chunk)
    parts.append(comp.flush())
    return b"".join(parts), crc, size


def _member(name: str, data: bytes) -> tuple[str, bytes, int, int]:
    deflated, crc, size = _deflate(iter([data]))
    return name, deflated, crc, size


def _valid_members() -> list[tuple[str, bytes, int, int]]:
    with np.load(io.BytesIO(sequence_to_npz_bytes(tiny_sequence(0).validate()))) as data:
        return [_member(f"{k}.npy", npy_bytes(data[k])) for k in data.files]


def honest_bomb() -> bytes:
    """An extra member that says (and is) 1 GiB of zeros: ~1 MiB on the wire."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": (1 << 30,)})
    zeros = (bytes(MIB) for _ in range(1024))
    deflated, crc, size = _deflate(iter([header.getvalue(), *zeros]))
    return _zip([*_valid_members(), ("extra.npy", deflated, crc, size)])


def lying_bomb() -> bytes:
    """object_pose declares a (5, 7) array (its header and its zip entry agree) but inflates to 1 GiB."""
    head = npy_bytes(np.zeros((5, 7)))
    deflated, _, _ = _deflate(iter([head, *(bytes(MIB) for _ in range(1024))]))
    members = [m for m in _valid_members() if m[0] != "object_pose.npy"]
    return _zip([*members, ("object_pose.npy", deflated, zlib.crc32(head), len(head))])


def many_members() -> bytes:
    """Members of 3 MiB of zeros each (under the member limit) adding up past the 8 MiB total."""
    extra = [_member(f"extra{i}.npy", npy_bytes(np.zeros(3 * MIB, np.uint8))) for i in range(4)]
    return _zip([*_valid_members(), *extra])


def padded_valid() -> bytes:
    """A valid sequence plus ~7 MiB of incompressible bytes: accepted (the extra member is never inflated)."""
    rng = np.random.default_rng(0)
    return _zip([*_valid_members(), _member("extra.npy", npy_bytes(rng.integers(0, 255, 7 * MIB, np.uint8)))])


def big_json() -> bytes:
    doc = sequence_to_json_dict(tiny_sequence(0, frames=1400).validate())
    doc["options"] = {"seed": 1}
    return json.dumps(doc).encode()


def chunked_upload(port: int, content_type: str, key: str, total: int) -> int:
    """Stream ``total`` bytes with Transfer-Encoding: chunked; return the status the server answers with."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {key}\r\nContent-Type: {content_type}"
                 "\r\nTransfer-Encoding: chunked\r\n\r\n".encode())  # fmt: skip
    prefix = b'--b\r\nContent-Disposition: form-data; name="sequence"; filename="s.npz"\r\n\r\n'
    chunk = bytes(MIB)
    sent = 0
    try:
        sock.sendall(b"%x\r\n%s\r\n" % (len(prefix), prefix))
        while sent < total:
            if select.select([sock], [], [], 0.02)[0]:
                break  # the server answered before the body ended
            sock.sendall(b"%x\r\n%s\r\n" % (len(chunk), chunk))
            sent += len(chunk)
    except (BrokenPipeError, ConnectionResetError):
        pass
    sock.settimeout(30)
    head = sock.recv(4096)
    sock.close()
    assert sent < total, "the server read the whole body"
    return int(head.split()[1])


@pytest.fixture()
def server(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], int, str]]:
    port = _free_port()
    env = {
        **os.environ, "HOI_REFINE_VAR_DIR": str(tmp_path / "var"), "HOI_REFINE_MAX_REQUEST_BYTES": str(REQUEST_LIMIT),
        "HOI_REFINE_MAX_SEQUENCE_BYTES": str(SEQUENCE_LIMIT), "HOI_REFINE_MAX_JSON_REQUEST_BYTES": str(JSON_LIMIT),
        "HOI_REFINE_MAX_ACTIVE_JOBS_PER_KEY": "1000",
    }  # fmt: skip
    env.pop("HOI_REFINE_DATABASE_URL", None)
    log = (tmp_path / "serve.log").open("wb")
    proc = subprocess.Popen([*hoi_refine_command(), "serve", "--port", str(port), "--log-level", "warning"],
                            env=env, stdout=log, stderr=subprocess.STDOUT)  # fmt: skip
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert proc.poll() is None and time.monotonic() < deadline, (tmp_path / "serve.log").read_text()
            time.sleep(0.3)
        url = f"sqlite:///{(tmp_path / 'var' / 'hoi-refine.sqlite3').resolve()}"
        engine = create_engine_for(url)
        key = ApiKeyStore(engine).create("memory test")[1]
        engine.dispose()
        yield proc, port, key
    finally:
        proc.terminate()
        proc.wait(30)
        log.close()


def test_hostile_uploads_keep_memory_within_the_documented_bound(
    server: tuple[subprocess.Popen[bytes], int, str],
) -> None:
    proc, port, key = server
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {key}"}, timeout=60)

    def upload(blob: bytes) -> httpx.Response:
        return client.post("/v1/jobs", files={"sequence": ("s.npz", blob, "application/octet-stream")})

    # Warm up every code path once (imports, thread pool, JSON models), then take the idle peak.
    assert upload(sequence_to_npz_bytes(tiny_sequence(0).validate())).status_code == 202
    small = {**sequence_to_json_dict(tiny_sequence(1).validate()), "options": {"seed": 1}}
    assert client.post("/v1/jobs", json=small).status_code == 202
    idle = peak_rss(proc.pid)

    statuses = {
        "chunked 1 GiB multipart": chunked_upload(port, "multipart/form-data; boundary=b", key, 1 << 30),
        "chunked 1 GiB json": chunked_upload(port, "application/json", key, 1 << 30),
        "honest 1 GiB member": upload(honest_bomb()).status_code,
        "lying 1 GiB member": upload(lying_bomb()).status_code,
        "members past the total": upload(many_members()).status_code,
        "valid, padded to the limit": upload(padded_valid()).status_code,
        "valid JSON near its limit": client.post(
            "/v1/jobs", content=big_json(), headers={"Content-Type": "application/json"}
        ).status_code,
    }
    peak = peak_rss(proc.pid)
    growth = peak - idle
    print(f"API peak RSS: idle {idle / MIB:.0f} MiB, after the attacks {peak / MIB:.0f} MiB (+{growth / MIB:.0f} MiB; "
          f"bound +{BOUND / MIB:.0f} MiB); answers {statuses}")  # fmt: skip
    assert statuses == {
        "chunked 1 GiB multipart": 413, "chunked 1 GiB json": 413, "honest 1 GiB member": 422,
        "lying 1 GiB member": 422, "members past the total": 422, "valid, padded to the limit": 202,
        "valid JSON near its limit": 202,
    }, statuses  # fmt: skip
    assert growth < BOUND, f"peak RSS grew by {growth / MIB:.0f} MiB, over the bound of {BOUND / MIB:.0f} MiB"
    assert client.get("/healthz").status_code == 200  # and the server is still there
    client.close()
