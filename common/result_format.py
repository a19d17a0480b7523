"""The result file: one NPZ holding trajectories, contacts and a JSON summary (DESIGN §1.7).

Written by the worker (``replay`` and ``refine``), stored by the queue, read by the service. Keys every
result has (F = frames, N = contacts over all frames):

* ``summary_json``: JSON text — metrics (``metrics.raw`` / ``metrics.refined``), config, seed, versions,
  timings. Read it with ``read_summary``.
* ``object_pose_sim`` (F,7) world x y z qw qx qy qz; ``object_vel_sim`` (F,6) linear, angular (world).
* per hand side S: ``S_q_target`` (F,45), ``S_wrist_pos`` (F,3), ``S_wrist_quat`` (F,4),
  ``S_keypoints_sim`` (F,21,3); refinement adds ``S_keyframes`` (K,13+) and optional MANO fields.
* contacts, one row per contact: ``contact_frame`` (N,) int, ``contact_hand`` (N,) str side,
  ``contact_body`` (N,) str hand body name, ``contact_pos_world`` (N,3), ``contact_pos_object`` (N,3),
  ``contact_normal`` (N,3) world (from object to hand), ``contact_force`` (N,3) world,
  ``contact_torque`` (N,3) world, ``contact_depth`` (N,) penetration in metres (>= 0).
"""

from __future__ import annotations

import io
import json
from typing import Any

import numpy as np

from common.errors import UnsupportedFormatError

CONTACT_KEYS: tuple[str, ...] = (
    "contact_frame",
    "contact_hand",
    "contact_body",
    "contact_pos_world",
    "contact_pos_object",
    "contact_normal",
    "contact_force",
    "contact_torque",
    "contact_depth",
)


def write_result_npz(arrays: dict[str, Any], summary: dict[str, Any]) -> bytes:
    """Serialise a result; ``summary`` must be JSON-serialisable."""
    missing = [k for k in CONTACT_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"result is missing contact arrays {missing}")
    buf = io.BytesIO()
    np.savez_compressed(buf, summary_json=np.array(json.dumps(summary, sort_keys=True)), **arrays)
    return buf.getvalue()


def _open(blob: bytes) -> Any:
    try:
        return np.load(io.BytesIO(blob), allow_pickle=False)
    except Exception as exc:
        raise UnsupportedFormatError(f"not a hoi-refine result file: {exc}") from exc


def read_summary(blob: bytes) -> dict[str, Any]:
    with _open(blob) as data:
        if "summary_json" not in data.files:
            raise UnsupportedFormatError("not a hoi-refine result file: no summary_json")
        out: dict[str, Any] = json.loads(str(data["summary_json"]))
        return out


def read_arrays(blob: bytes) -> dict[str, np.ndarray]:
    with _open(blob) as data:
        return {k: data[k] for k in data.files}


def read_contacts(blob: bytes, start: int | None = None, end: int | None = None) -> list[dict[str, Any]]:
    """Contacts with ``start <= frame < end`` as JSON-ready dicts, in frame order."""
    with _open(blob) as data:
        cols = {k: data[k] for k in CONTACT_KEYS}
    frames = cols["contact_frame"]
    mask = np.ones(frames.shape, dtype=bool)
    if start is not None:
        mask &= frames >= start
    if end is not None:
        mask &= frames < end
    rows = []
    for i in np.flatnonzero(mask):
        rows.append(
            {
                "frame": int(frames[i]),
                "hand": str(cols["contact_hand"][i]),
                "body": str(cols["contact_body"][i]),
                "position_world": cols["contact_pos_world"][i].tolist(),
                "position_object": cols["contact_pos_object"][i].tolist(),
                "normal": cols["contact_normal"][i].tolist(),
                "force": cols["contact_force"][i].tolist(),
                "torque": cols["contact_torque"][i].tolist(),
                "depth": float(cols["contact_depth"][i]),
            }
        )
    return rows
