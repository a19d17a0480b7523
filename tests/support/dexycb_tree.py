"""A tiny DexYCB release tree (calibration, a cube model, 2 sequences of 6 frames with a known table frame),
for the DexYCB loader's tests and the submit tool's discovery tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

T = 6
HALF = 0.04  # cube half-size (m)
SUBJECT = "20200709-subject-01"
BETAS = [0.5, -0.3, 0.1, 0.0, 0.2, -0.1, 0.05, 0.0, 0.0, 0.01]


def master_from_table() -> np.ndarray:
    """A camera looking down at the table: table +z maps to a camera direction with -y (up in OpenCV)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("xyz", [-125.0, 5.0, 10.0], degrees=True).as_matrix()
    out[:3, 3] = [0.1, 0.3, 0.9]
    return out


def _write_cube(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    corners = [(x, y, z) for x in (-HALF, HALF) for y in (-HALF, HALF) for z in (-HALF, HALF)]
    faces = [(1, 3, 2), (1, 2, 5), (1, 5, 3), (8, 6, 7), (8, 7, 4), (8, 4, 6),
             (2, 4, 3), (2, 6, 4), (5, 7, 6), (5, 6, 2), (3, 7, 5), (3, 4, 7)]  # fmt: skip
    lines = [f"v {x} {y} {z}" for x, y, z in corners] + [f"f {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def _object_track(master_from_table: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """Cube resting on the table at frame 0 (rotated 30 deg about table z), then lifted 1 cm a frame."""
    rot_table = Rotation.from_euler("z", 30, degrees=True)
    rot_cam = Rotation.from_matrix(master_from_table[:3, :3]) * rot_table
    pos_table = np.array([[0.3, 0.2, HALF + 0.01 * i] for i in range(T)])
    pos_cam = pos_table @ master_from_table[:3, :3].T + master_from_table[:3, 3]
    return pos_cam, rot_cam


def write_tree(root: Path) -> dict[str, Path]:
    m = master_from_table()
    cal = root / "calibration"
    (cal / "extrinsics_20200702_151821").mkdir(parents=True)
    (cal / "extrinsics_20200702_151821" / "extrinsics.yml").write_text(
        yaml.safe_dump(
            {
                "master": "840412060917",
                "extrinsics": {
                    "840412060917": [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0],
                    "apriltag": m[:3].ravel().tolist(),
                },
            }
        )
    )
    for calib in ("20200709_right", "20200709_left"):
        (cal / f"mano_{calib}").mkdir(parents=True)
        (cal / f"mano_{calib}" / "mano.yml").write_text(yaml.safe_dump({"betas": BETAS}))
    _write_cube(root / "models" / "010_potted_meat_can" / "textured_simple.obj")

    pos_cam, rot_cam = _object_track(m)
    rng = np.random.default_rng(0)
    dirs = {}
    # Sequence 1: right hand, two objects (grasp the second), toolkit pose_y layout, master labels.
    s1 = root / SUBJECT / "20200709_141754"
    s1.mkdir(parents=True)
    pose_y = np.zeros((T, 2, 7), np.float32)
    pose_y[:, 0] = [0, 0, 0, 1, 0.5, 0.5, 0.5]
    pose_y[:, 1, :4] = rot_cam.as_quat()  # x y z w
    pose_y[:, 1, 4:] = pos_cam
    pose_m = rng.normal(0, 0.1, (T, 1, 51)).astype(np.float32)
    pose_m[:2] = 0.0  # hand not yet in view
    np.savez(s1 / "pose.npz", pose_y=pose_y, pose_m=pose_m)
    meta = {
        "serials": ["836212060125", "840412060917"], "num_frames": T, "ycb_ids": [1, 9], "ycb_grasp_ind": 1,
        "mano_sides": ["right"], "mano_calib": ["20200709_right"], "extrinsics": "20200702_151821",
    }  # fmt: skip
    (s1 / "meta.yml").write_text(yaml.safe_dump(meta))
    (s1 / "840412060917").mkdir()
    joints = pos_cam[:, None, None, :] + rng.normal(0, 0.05, (T, 1, 21, 3))
    joints[:2] = -1.0  # the toolkit's marker for "no hand"
    for i in range(T):
        np.savez(s1 / "840412060917" / f"labels_{i:06d}.npz", joint_3d=joints[i].astype(np.float32))
    dirs["s1"] = s1
    # Sequence 2: both hands, [R|t] pose_y layout, no labels (MANO only).
    s2 = root / SUBJECT / "20200709_141841"
    s2.mkdir(parents=True)
    mats = np.zeros((T, 1, 3, 4), np.float32)
    mats[:, 0, :, :3] = rot_cam.as_matrix()
    mats[:, 0, :, 3] = pos_cam
    pose_m2 = rng.normal(0, 0.1, (T, 2, 51)).astype(np.float32)
    pose_m2[4:, 1] = 0.0  # left hand leaves
    np.savez(s2 / "pose.npz", pose_y=mats, pose_m=pose_m2)
    meta2 = dict(meta, ycb_ids=[9], ycb_grasp_ind=0, mano_sides=["right", "left"],
                 mano_calib=["20200709_right", "20200709_left"])  # fmt: skip
    (s2 / "meta.yml").write_text(yaml.safe_dump(meta2))
    dirs["s2"] = s2
    return dirs
