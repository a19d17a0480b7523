"""What one sequence is uploaded as, and the Idempotency-Key derived from it.

The upload is the native NPZ (``common.sequence_io.sequence_to_npz_bytes``) without machine-local meta, so
the same sequence always gives the same bytes: the service fingerprints what it stores and answers a reused
Idempotency-Key with another fingerprint by 422, so a POST repeated after a timeout or a crash must be
byte-identical. The key itself is computed from the arrays (name, dtype, shape, raw bytes), not from the zip
container, so it does not depend on zlib's version or the entry order either.
"""

from __future__ import annotations

import hashlib
import io

import numpy as np

from common.api_client import options_key_json
from common.job_options import JobOptions
from common.sequence import Sequence
from common.sequence_io import sequence_from_npz_bytes, sequence_to_npz_bytes

#: Bumped if the key derivation changes (old manifests then resubmit instead of colliding).
KEY_SCHEME = b"hoi-refine-submit/2"
#: Meta entries that describe where a file lay on this machine, not what it holds: left out of the upload
#: so that moving or re-mounting a dataset does not change the key.
_LOCAL_META = ("source_path",)


def _npz_arrays(blob: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def content_digest(npz_blob: bytes) -> str:
    """sha256 over the arrays of an NPZ (name, dtype, shape, C-order bytes), independent of the container."""
    h = hashlib.sha256()
    for name, arr in sorted(_npz_arrays(npz_blob).items()):
        a = np.ascontiguousarray(arr)
        h.update(name.encode())
        h.update(b"\0" + a.dtype.str.encode() + b"\0" + repr(a.shape).encode() + b"\0")
        h.update(a.tobytes())
    return h.hexdigest()


def sequence_payload(seq: Sequence, max_frames: int | None = None) -> bytes:
    """The reproducible native-NPZ upload for ``seq``, checked by parsing it back as the server will."""
    meta = {k: v for k, v in seq.meta.items() if k not in _LOCAL_META}
    original = seq.meta
    seq.meta = meta
    try:
        blob = sequence_to_npz_bytes(seq)
    finally:
        seq.meta = original
    # Parse it back: what fails here would fail on the server, and must never be sent.
    sequence_from_npz_bytes(blob, max_frames=max_frames)
    return blob


def idempotency_key(payload: bytes, options: JobOptions) -> str:
    """sha256 of (canonical sequence content + the options set apart from their defaults), hex: same input =>
    same job."""
    h = hashlib.sha256(KEY_SCHEME + b"\0")
    h.update(content_digest(payload).encode() + b"\0")
    h.update(options_key_json(options).encode())
    return h.hexdigest()
