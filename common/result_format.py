"""The result file: one NPZ holding trajectories, contacts and a JSON summary (DESIGN §1.7).

Written by the worker (``replay`` and ``refine``), stored by the queue, read by the service. Keys every
result has (F = frames, N = contacts over all frames):

* ``summary_json``: JSON text — metrics (``metrics.raw`` / ``metrics.refined``), config, seed, versions (the
  numeric packages and the CPU kind, ``common.cpu_kind``, that the figures depend on), and the deterministic
  ``timings`` counters (simulated steps, candidate evaluations, rollouts). Read it with
  ``read_summary``, which also merges in ``timings_json``.
* ``timings_json`` (absent when written without the wall clock): JSON text — the run-dependent ``timings``
  figures (``is_wall_clock``: seconds ``*_s``, ``sim_share``, ``steps_per_second``, ``threads``).
* ``object_pose_sim`` (F,7) world x y z qw qx qy qz; ``object_vel_sim`` (F,6) linear, angular (world).
* per hand side S: ``S_q_target`` (F,45), ``S_wrist_pos`` (F,3), ``S_wrist_quat`` (F,4),
  ``S_keypoints_sim`` (F,21,3); refinement adds ``S_keyframes`` (K,13+) and optional MANO fields.
* contacts, one row per contact: ``contact_frame`` (N,) int, ``contact_hand`` (N,) str side,
  ``contact_body`` (N,) str hand body name, ``contact_pos_world`` (N,3), ``contact_pos_object`` (N,3),
  ``contact_normal`` (N,3) world (from object to hand), ``contact_force`` (N,3) world,
  ``contact_torque`` (N,3) world, ``contact_depth`` (N,) penetration in metres (>= 0).
* ``state_sim`` / ``raw_state_sim`` (F, S) float64 (refinement results since issue #54): the refined and the raw
  replay's MuJoCo integration state (``mjSTATE_INTEGRATION``) at every frame, read by ``verify``'s stepwise check
  (``worker.verification.stepwise``).
* ``control_sim`` / ``raw_control_sim`` (T, C) float64 (since the stepwise check steps under them): the inputs
  each replay set before every physics step (T = (F - 1) * substeps + 1; the columns MuJoCo's ctrl, equality
  switches, mocap positions and quaternions), so that check steps under the very bits the replay stepped under
  on any host; ``verify`` checks them against the keyframes' within 1e-9. ``presettle_state_sim`` (S,): the
  integration state the settling to frame 0 starts from (hands at their frame-0 targets, the object placed), so
  that check settles to frame 0 from the same bits too.
* an articulated object (``common.articulation``) adds ``object_articulation_sim`` / ``_ref`` (F,J) joint values
  (radians / metres) and ``contact_part`` (N,) str: the object part touched, whose frame ``contact_pos_object``
  is then given in.

Members are written by ``common.npz_writer`` in a fixed order — ``summary_json``, ``timings_json``, then the
arrays sorted by key — with fixed zip timestamps, so equal results give equal bytes; without the wall clock
two runs with the same input, options and seed give identical files. ``content_digest`` hashes everything but
``timings_json``, to compare results whose wall clock differs.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from typing import Any

import numpy as np

from common.errors import UnsupportedFormatError
from common.npz_writer import deterministic_npz_bytes

#: How a result file's name ends (``hoi-refine refine --out``, ``submit``'s downloads, a dataset release).
RESULT_SUFFIX = ".result.npz"
SUMMARY_KEY = "summary_json"
TIMINGS_KEY = "timings_json"
#: Members that are JSON text rather than data arrays (``read_arrays`` leaves them out).
JSON_KEYS: tuple[str, ...] = (SUMMARY_KEY, TIMINGS_KEY)
#: ``timings`` entries that depend on the machine or the run, not on input, options and seed.
_WALL_CLOCK_NAMES = frozenset({"sim_share", "steps_per_second", "threads"})

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


#: Each replay's integration state per frame (refinement results since issue #54): for ``verify``'s stepwise check,
#: in the NPZ only (the JSON form of a result leaves them out: 3 KB a frame as text is no one's reading).
INTEGRATION_STATE_KEYS: tuple[str, ...] = ("state_sim", "raw_state_sim")
#: Each replay's inputs per physics step, stored beside its states (the refined replay's, then the raw one's).
INTEGRATION_CONTROL_KEYS: tuple[str, ...] = ("control_sim", "raw_control_sim")
#: The integration state the settling to frame 0 starts from (both replays start from its settled state).
PRESETTLE_STATE_KEY = "presettle_state_sim"
#: What the JSON form of a result leaves out: the stepwise check's states and inputs.
STEPWISE_KEYS: tuple[str, ...] = (*INTEGRATION_STATE_KEYS, *INTEGRATION_CONTROL_KEYS, PRESETTLE_STATE_KEY)


#: Contact columns of an articulated object's result only.
PART_CONTACT_KEYS: tuple[str, ...] = ("contact_part",)


def is_wall_clock(key: str) -> bool:
    """Whether a ``timings`` entry is run-dependent: seconds (``*_s``), rates and shares of them, the threads."""
    return key.endswith("_s") or key in _WALL_CLOCK_NAMES


def write_result_npz(arrays: dict[str, Any], summary: dict[str, Any], wall_clock: bool = True) -> bytes:
    """Serialise a result; ``summary`` must be JSON-serialisable.

    ``summary["timings"]`` is split: the wall-clock entries (``is_wall_clock``) go to ``timings_json``, or are
    dropped when ``wall_clock`` is False (for reproducibility checks), the deterministic counters stay.
    """
    missing = [k for k in CONTACT_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"result is missing contact arrays {missing}")
    clashing = [k for k in JSON_KEYS if k in arrays]
    if clashing:
        raise ValueError(f"{clashing} are reserved for the JSON members")
    stored = dict(summary)
    members: dict[str, Any] = {SUMMARY_KEY: None}  # first member; filled in below
    if "timings" in summary:
        timings: dict[str, Any] = summary["timings"]
        stored["timings"] = {k: v for k, v in timings.items() if not is_wall_clock(k)}
        if wall_clock:
            members[TIMINGS_KEY] = _json_array({k: v for k, v in timings.items() if is_wall_clock(k)})
    members[SUMMARY_KEY] = _json_array(stored)
    members.update((k, arrays[k]) for k in sorted(arrays))
    return deterministic_npz_bytes(members)


def _json_array(doc: dict[str, Any]) -> np.ndarray:
    return np.array(json.dumps(doc, sort_keys=True))


def _open(blob: bytes) -> Any:
    try:
        return np.load(io.BytesIO(blob), allow_pickle=False)
    except Exception as exc:
        raise UnsupportedFormatError(f"not a hoi-refine result file: {exc}") from exc


def read_summary(blob: bytes) -> dict[str, Any]:
    """The summary, its ``timings`` holding the deterministic counters and (when stored) the wall clock."""
    with _open(blob) as data:
        if SUMMARY_KEY not in data.files:
            raise UnsupportedFormatError("not a hoi-refine result file: no summary_json")
        out: dict[str, Any] = json.loads(str(data[SUMMARY_KEY]))
        if TIMINGS_KEY in data.files:
            out["timings"] = {**out.get("timings", {}), **json.loads(str(data[TIMINGS_KEY]))}
        return out


def read_arrays(blob: bytes) -> dict[str, np.ndarray]:
    """The data arrays (the JSON members excluded: ``read_summary`` reads those)."""
    with _open(blob) as data:
        return {k: data[k] for k in data.files if k not in JSON_KEYS}


def content_digest(blob: bytes) -> str:
    """SHA-256 (hex) over every member but ``timings_json``: equal for two runs whose only difference is the
    wall clock. Hashes names and uncompressed bytes in sorted name order, so neither the compressor nor the
    member order matters."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(blob))
    except zipfile.BadZipFile as exc:
        raise UnsupportedFormatError(f"not a hoi-refine result file: {exc}") from exc
    digest = hashlib.sha256()
    with zf:
        for name in sorted(zf.namelist()):
            if name == f"{TIMINGS_KEY}.npy":
                continue
            payload = zf.read(name)
            # Lengths frame each field, so no two different member lists hash the same byte stream.
            digest.update(f"{len(name)}:{name}:{len(payload)}:".encode())
            digest.update(payload)
    return digest.hexdigest()


def read_contacts(blob: bytes, start: int | None = None, end: int | None = None) -> list[dict[str, Any]]:
    """Contacts with ``start <= frame < end`` as JSON-ready dicts, in frame order; ``part`` names the object part
    touched (an articulated object's result; None for a rigid one), in whose frame ``position_object`` is."""
    with _open(blob) as data:
        cols = {k: data[k] for k in (*CONTACT_KEYS, *PART_CONTACT_KEYS) if k in data.files}
    parts = cols.get("contact_part")
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
                "part": None if parts is None else str(parts[i]),
            }
        )
    return rows
