"""Reader for DexYCB in its native layout (as released, and as read by NVlabs' dex-ycb-toolkit).

Layout::

    <root>/<subject>/<sequence>/meta.yml      serials, num_frames, ycb_ids, ycb_grasp_ind, mano_sides,
                                              mano_calib, extrinsics
    <root>/<subject>/<sequence>/pose.npz      pose_y (T, n_obj, 7): qx qy qz qw tx ty tz, master camera
                                              (the toolkit's layout; (T, n_obj, 3, 4) [R|t] is read too);
                                              pose_m (T, n_hands, 51): 3 global + 45 PCA pose, 3 trans
    <root>/<subject>/<sequence>/<serial>/labels_000000.npz   per camera: joint_3d (n_hands, 21, 3)
    <root>/calibration/mano_<calib>/mano.yml                 betas (10,)
    <root>/calibration/extrinsics_<name>/extrinsics.yml      master: <serial>; extrinsics: {<serial>: 12
                                                             floats, apriltag: 12 floats} (3x4 row-major)
    <root>/models/<ycb name>/textured_simple.obj

Frames: the poses are in the master camera frame. The toolkit maps master-frame points into the AprilTag
(table) frame with ``p_tag = R_tag^-1 (p - t_tag)`` (``sequence_loader.py``, the point-cloud crop), i.e.
``extrinsics['apriltag']`` is master_from_table, so ``world_from_source = inverse(apriltag)``: +z up out
of the table, table plane z = 0 (DESIGN §1 "gravity-aligned world frame").

MANO parameters follow DexYCB's convention (``use_pca=True, ncomps=45, flat_hand_mean=False``); a frame
whose ``pose_m`` row is all zeros has no hand. Keypoints come from the master camera's ``labels_*.npz``
(``joint_3d``); without them the hands carry only MANO parameters, which needs a MANO model
(``HOI_REFINE_MANO_DIR``; decoding is ``worker.hand.mano.ensure_keypoints``).
"""

from __future__ import annotations

import json
import re
from functools import lru_cache
from pathlib import Path
from typing import Any, cast

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from common.errors import ManoModelMissingError, SequenceValidationError
from common.geometry import FloatArray
from common.mesh_io import load_mesh_file
from common.npz_safe import Spec
from common.safe_text import shown
from common.sequence import NUM_JOINTS, HandTrack, ManoParams, ObjectSpec, Sequence
from common.sequence_npz import ParseLimits, open_npz
from common.settings import get_settings

#: DexYCB records at 30 fps; meta.yml does not say so.
DEXYCB_FPS = 30.0
META_KEYS = ("num_frames", "ycb_ids", "ycb_grasp_ind", "mano_sides", "mano_calib", "extrinsics")
MASSES_FILE = Path(__file__).resolve().parent / "data" / "ycb_masses.json"
MAX_YAML_BYTES = 1 << 20
#: Calibration and camera names become folder names under the DexYCB root.
SAFE_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,99}")


@lru_cache(maxsize=1)
def ycb_classes() -> dict[int, str]:
    """DexYCB class id (``ycb_ids`` entries, 1-21) -> YCB object name."""
    table = json.loads(MASSES_FILE.read_text())["objects"]
    return {int(v["ycb_id"]): name for name, v in table.items()}


@lru_cache(maxsize=1)
def ycb_masses() -> dict[str, float]:
    """Object name -> mass in kg (objects without a known mass are left out)."""
    table = json.loads(MASSES_FILE.read_text())["objects"]
    return {name: float(v["mass_kg"]) for name, v in table.items() if v["mass_kg"] is not None}


def is_dexycb_sequence_dir(path: Path) -> bool:
    return path.is_dir() and (path / "meta.yml").is_file() and (path / "pose.npz").is_file()


def _read_yaml(path: Path, what: str) -> dict[str, Any]:
    if not path.is_file():
        raise SequenceValidationError.single(what, f"{path.name} does not exist")
    if path.stat().st_size > MAX_YAML_BYTES:
        raise SequenceValidationError.single(what, f"is larger than {MAX_YAML_BYTES} bytes")
    try:
        doc = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise SequenceValidationError.single(what, f"is not valid YAML ({type(exc).__name__})") from exc
    if not isinstance(doc, dict):
        raise SequenceValidationError.single(what, "is not a YAML mapping")
    return doc


def _meta_int(meta: dict[str, Any], key: str) -> int:
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 10**7:
        raise SequenceValidationError.single(f"meta.yml:{key}", f"must be a non-negative integer, got {shown(value)}")
    return value


def _meta_list(meta: dict[str, Any], key: str, kind: type) -> list[Any]:
    value = meta[key]
    if not isinstance(value, list) or not value or len(value) > 64 or not all(
        isinstance(v, kind) and not isinstance(v, bool) for v in value
    ):
        raise SequenceValidationError.single(f"meta.yml:{key}", f"must be a non-empty list of {kind.__name__}")
    return [kind(v) for v in value]


def _floats(values: Any, field: str) -> FloatArray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (ValueError, TypeError, OverflowError) as exc:
        raise SequenceValidationError.single(field, "must be a list of numbers") from exc
    if not np.all(np.isfinite(arr)):
        raise SequenceValidationError.single(field, "contains NaN or Inf")
    return arr


def _load_npz(path: Path, field: str, specs: dict[str, Spec], limits: ParseLimits) -> dict[str, np.ndarray] | None:
    """The members of ``specs`` from an NPZ read through ``SafeNpz``; None when one is missing."""
    with open_npz(path.read_bytes(), limits) as npz:
        if not all(k in npz for k in specs):
            return None
        try:
            return {k: npz.get(k, spec) for k, spec in specs.items()}
        except SequenceValidationError as exc:
            raise SequenceValidationError.single(f"{field}:{exc.problems[0].field}", exc.problems[0].problem) from exc


def _rigid_3x4(values: Any, field: str) -> FloatArray:
    arr = _floats(values, field)
    if arr.size != 12:
        raise SequenceValidationError.single(field, f"must hold 12 numbers (a 3x4 [R|t]), got {arr.size}")
    out = np.eye(4)
    out[:3, :] = arr.reshape(3, 4)
    return out


def world_from_master(extrinsics: dict[str, Any], field: str = "extrinsics.yml") -> FloatArray:
    """The table frame from an extrinsics.yml document: ``inverse(apriltag)`` (see module doc)."""
    table = extrinsics.get("extrinsics", {})
    if not isinstance(table, dict) or "apriltag" not in table:
        raise SequenceValidationError.single(
            field, "has no 'apriltag' entry: the table frame is needed for the gravity direction"
        )
    master_from_table = _rigid_3x4(table["apriltag"], f"{field}.apriltag")
    # Re-orthonormalise: YAML float round-off would fail the rigidity check in Sequence.validate.
    u, _, vt = np.linalg.svd(master_from_table[:3, :3])
    master_from_table[:3, :3] = u @ vt
    return np.asarray(np.linalg.inv(master_from_table), dtype=np.float64)


def object_poses(pose_y: np.ndarray, index: int) -> tuple[FloatArray, np.ndarray]:
    """(T, 7) ``x y z qw qx qy qz`` poses of object ``index`` and its (T,) validity mask.

    ``pose_y`` is (T, n, 7) ``qx qy qz qw tx ty tz`` (pose.npz) or (T, n, 3, 4) ``[R|t]`` (labels files).
    Invalid rows (zero or identity-zero, as the toolkit marks them) take the nearest valid frame's pose.
    """
    if pose_y.ndim == 3 and pose_y.shape[2] == 7:
        rows = np.asarray(pose_y[:, index], dtype=np.float64)
        valid = np.linalg.norm(rows[:, :4], axis=1) > 0.5
        valid &= np.any(rows != [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], axis=1)
        quat_xyzw, trans = rows[:, :4], rows[:, 4:]
    elif pose_y.ndim == 4 and pose_y.shape[2:] == (3, 4):
        mats = np.asarray(pose_y[:, index], dtype=np.float64)
        valid = np.abs(np.linalg.det(mats[:, :, :3]) - 1.0) < 1e-2
        quat_xyzw = np.tile([0.0, 0.0, 0.0, 1.0], (len(mats), 1))
        if valid.any():
            quat_xyzw[valid] = Rotation.from_matrix(mats[valid, :, :3]).as_quat()
        trans = mats[:, :, 3]
    else:
        raise SequenceValidationError.single(
            "pose.npz:pose_y", f"must have shape (T, n_obj, 7) or (T, n_obj, 3, 4), got {pose_y.shape}"
        )
    if not valid.any():
        raise SequenceValidationError.single("pose.npz:pose_y", f"object {index} has no valid pose in any frame")
    good = np.flatnonzero(valid)
    nearest = good[np.abs(np.arange(len(valid))[:, None] - good[None, :]).argmin(axis=1)]
    quat = quat_xyzw[nearest] / np.linalg.norm(quat_xyzw[nearest], axis=1, keepdims=True)
    out = np.concatenate([trans[nearest], quat[:, [3, 0, 1, 2]]], axis=1)
    return out, valid


def _master_keypoints(seq_dir: Path, master: str, num_frames: int, n_hands: int) -> FloatArray | None:
    """(T, n_hands, 21, 3) joints from the master camera's labels files, or None if any is missing."""
    cam = seq_dir / master
    files = [cam / f"labels_{i:06d}.npz" for i in range(num_frames)]
    if not all(f.is_file() for f in files):
        return None
    out = np.zeros((num_frames, n_hands, NUM_JOINTS, 3))
    for i, f in enumerate(files):
        label = _load_npz(f, f.name, {"joint_3d": Spec("iuf", None)}, ParseLimits())
        if label is None:
            return None
        raw = np.asarray(label["joint_3d"], dtype=np.float64)
        if raw.size % (NUM_JOINTS * 3) or raw.size > 4 * NUM_JOINTS * 3:
            raise SequenceValidationError.single(f"{f.name}:joint_3d", f"must hold (n_hands, 21, 3), got {raw.shape}")
        j = raw.reshape(-1, NUM_JOINTS, 3)
        if j.shape[0] != n_hands:
            raise SequenceValidationError.single(
                f"{f.name}:joint_3d", f"holds {j.shape[0]} hands but meta.yml lists {n_hands}"
            )
        out[i] = j
    return out


def _require_mano_files(sides: list[str]) -> None:
    mano_dir = get_settings().mano_dir
    for side in sides:
        fname = f"MANO_{side.upper()}.pkl"
        if mano_dir is None or not (Path(mano_dir) / fname).is_file():
            where = "is not set" if mano_dir is None else f"({mano_dir}) has no {fname}"
            raise ManoModelMissingError(
                f"this DexYCB sequence has no master-camera labels (joint_3d), so its {side} hand is given "
                f"only as MANO parameters; decoding them needs {fname}, but HOI_REFINE_MANO_DIR {where}"
            )


def load_dexycb_native(
    seq_dir: Path | str,
    root: Path | str | None = None,
    max_frames: int | None = None,
    mass_kg: float | None = None,
) -> Sequence:
    """Build a validated ``Sequence`` from ``<root>/<subject>/<sequence>`` (``root`` defaults to two up).

    ``mass_kg`` overrides the shipped masses table (needed for 051_large_clamp, which has no entry).
    """
    seq_dir = Path(seq_dir)
    if seq_dir.name == "meta.yml":
        seq_dir = seq_dir.parent
    root_dir = Path(root) if root is not None else seq_dir.resolve().parent.parent
    meta = _read_yaml(seq_dir / "meta.yml", "meta.yml")
    missing = [k for k in META_KEYS if k not in meta]
    if missing:
        raise SequenceValidationError.single(f"meta.yml:{missing[0]}", "is missing")
    num_frames = _meta_int(meta, "num_frames")
    limits = ParseLimits(max_frames=max_frames) if max_frames is not None else ParseLimits()
    if num_frames > limits.max_frames:
        raise SequenceValidationError.single("meta.yml:num_frames", f"{num_frames} is more than {limits.max_frames}")
    ycb_ids = _meta_list(meta, "ycb_ids", int)
    sides = _meta_list(meta, "mano_sides", str)
    calibs = _meta_list(meta, "mano_calib", str)
    for name_ in (*calibs, str(meta["extrinsics"])):
        if not SAFE_NAME.fullmatch(name_):  # these name folders under the root: no '..' or '/'
            raise SequenceValidationError.single("meta.yml", f"calibration name {shown(name_)} is not a plain name")
    data = _load_npz(
        seq_dir / "pose.npz", "pose.npz",
        {"pose_y": Spec("iuf", None), "pose_m": Spec("iuf", ("T", "O", 51))}, limits,
    )  # fmt: skip
    if data is None:
        raise SequenceValidationError.single("pose.npz", "must hold pose_y and pose_m")
    pose_y, pose_m = np.asarray(data["pose_y"], dtype=np.float64), np.asarray(data["pose_m"], dtype=np.float64)
    if pose_y.ndim not in (3, 4) or not np.all(np.isfinite(pose_y)):
        raise SequenceValidationError.single("pose.npz:pose_y", f"must be finite (T, n_obj, 7), got {pose_y.shape}")
    if pose_y.shape[0] != num_frames or pose_m.shape[0] != num_frames:
        raise SequenceValidationError.single(
            "pose.npz", f"has {pose_y.shape[0]} / {pose_m.shape[0]} frames but meta.yml num_frames is {num_frames}"
        )
    if pose_y.shape[1] != len(ycb_ids):
        raise SequenceValidationError.single(
            "pose.npz:pose_y", f"holds {pose_y.shape[1]} objects but meta.yml ycb_ids lists {len(ycb_ids)}"
        )
    if pose_m.ndim != 3 or pose_m.shape[1:] != (len(sides), 51) or len(calibs) != len(sides):
        raise SequenceValidationError.single(
            "pose.npz:pose_m",
            f"must have shape (T, {len(sides)}, 51) to match meta.yml mano_sides/mano_calib, got {pose_m.shape}",
        )

    # --- the grasped object
    grasp = _meta_int(meta, "ycb_grasp_ind")
    if not 0 <= grasp < len(ycb_ids):
        raise SequenceValidationError.single("meta.yml:ycb_grasp_ind", f"{grasp} is not an index into ycb_ids")
    name = ycb_classes().get(ycb_ids[grasp])
    if name is None:
        raise SequenceValidationError.single("meta.yml:ycb_ids", f"unknown DexYCB object id {ycb_ids[grasp]}")
    mass = mass_kg if mass_kg is not None else ycb_masses().get(name)
    if mass is None:
        raise SequenceValidationError.single(
            "object.mass_kg", f"no mass is known for {name}; pass mass_kg to load_dexycb_native"
        )
    vertices, faces = load_mesh_file(root_dir / "models" / name / "textured_simple.obj", field="models")
    pose, obj_valid = object_poses(pose_y, grasp)

    # --- the table frame
    extr_file = root_dir / "calibration" / f"extrinsics_{meta['extrinsics']}" / "extrinsics.yml"
    extr = _read_yaml(extr_file, "extrinsics.yml")
    world = world_from_master(extr)
    serials = meta.get("serials") if isinstance(meta.get("serials"), list) else None
    master = str(extr.get("master", (serials or [""])[0]))
    if not SAFE_NAME.fullmatch(master):
        raise SequenceValidationError.single("extrinsics.yml:master", f"{shown(master)} is not a camera serial")

    # --- hands
    keypoints = _master_keypoints(seq_dir, master, num_frames, len(sides))
    if keypoints is None:
        _require_mano_files(sides)
    hands = []
    for h, (side, calib) in enumerate(zip(sides, calibs, strict=True)):
        mano_doc = _read_yaml(root_dir / "calibration" / f"mano_{calib}" / "mano.yml", "mano.yml")
        betas = _floats(mano_doc.get("betas"), "mano.yml:betas").reshape(-1)
        pm = pose_m[:, h]
        valid = np.any(pm != 0.0, axis=1)
        kp = None
        if keypoints is not None:
            kp = keypoints[:, h].copy()
            kp[~valid] = 0.0  # the toolkit fills hand-less frames with -1
        hands.append(
            HandTrack(
                side=cast(Any, side),
                valid=valid,
                keypoints=kp,
                mano=ManoParams(
                    global_orient=pm[:, :3].copy(),
                    hand_pose=pm[:, 3:48].copy(),
                    trans=pm[:, 48:51].copy(),
                    betas=betas,
                    pose_format="pca",
                    flat_hand_mean=False,
                ),
            )
        )

    subject, sequence = seq_dir.resolve().parent.name, seq_dir.resolve().name
    seq = Sequence(
        name=f"{subject}__{sequence}",
        fps=float(_floats(meta.get("fps", DEXYCB_FPS), "meta.yml:fps").reshape(-1)[:1].sum()),
        object=ObjectSpec(name=name, mass_kg=float(mass), mesh_vertices=vertices, mesh_faces=faces),
        object_pose=pose,
        hands=hands,
        world_from_source=world,
        meta={
            "source": "dexycb-native",
            "subject": subject,
            "sequence": sequence,
            "source_path": str(seq_dir),
            "master_serial": master,
            "object_frames_filled": str(int((~obj_valid).sum())),
            "keypoints": "master-camera labels" if keypoints is not None else "MANO (decode needed)",
        },
    )
    return seq.validate(max_frames=max_frames)
