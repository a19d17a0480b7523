"""Replay an exported hoi-refine result in plain MuJoCo: needs only ``mujoco`` and ``numpy``.

Usage, inside the exported folder (or give the folder as the argument):

    python replay.py [FOLDER]

It loads ``scene.xml``, restores the settled start state from ``controls.npz``, applies the stored controls
(hinge servo targets ``ctrl``, the wrist's mocap pose ``mocap_pos`` / ``mocap_quat`` and which welds are on,
``eq_active``: the object is held where it starts until the hand comes) at every physics step,
reads the object's pose at every video frame, and prints how far it lands from the simulated and the
recorded object trajectories in ``trajectories.npz``; for an articulated object (``object_joints`` in
``export.json``) also every joint's value against the simulated and recorded ones (deg, or cm for a sliding
joint). Exit status 1 when the replay leaves the simulated trajectory by more than 1 mm or 1 degree, or a
joint's value by more than 1 degree or 1 mm (a different MuJoCo build can round differently).

This file is copied verbatim into every export by ``hoi-refine export``; it imports nothing of hoi-refine.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import mujoco
import numpy as np

TOLERANCE_MM = 1.0
TOLERANCE_DEG = 1.0


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Geodesic angle (deg) between wxyz quaternions (..., 4)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(2.0 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0)))


def replay(folder: Path) -> np.ndarray:
    """The object's body pose (F, 7: x y z qw qx qy qz) at every frame of a replay of the stored controls."""
    return replay_with_joints(folder)[0]


def replay_with_joints(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The object's body pose (F, 7) and its joints' values (F, J: rad or m; J = 0 for a rigid object) at every
    frame of a replay of the stored controls."""
    meta = json.loads((folder / "export.json").read_text())
    model = mujoco.MjModel.from_xml_path(str(folder / "scene.xml"))
    data = mujoco.MjData(model)
    c = np.load(folder / "controls.npz")
    ctrl, mocap_pos, mocap_quat = c["ctrl"], c["mocap_pos"], c["mocap_quat"]
    # Exports made before the object's hold have no switches: their welds stay as the model declares them.
    eq_active = c["eq_active"] if "eq_active" in c.files else np.repeat(model.eq_active0[None], len(ctrl), axis=0)
    substeps, frames = int(meta["substeps_per_frame"]), int(meta["frames"])
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, meta["object_body"])
    joint_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j["mjcf"]) for j in meta.get("object_joints", [])]
    qadr = np.array([model.jnt_qposadr[j] for j in joint_ids], dtype=np.int64)
    mujoco.mj_resetData(model, data)
    mujoco.mj_setState(model, data, c["start_state"], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    data.qacc_warmstart[:] = c["start_warmstart"]
    mujoco.mj_forward(model, data)
    poses = np.empty((frames, 7))
    joints = np.empty((frames, len(qadr)))
    poses[0] = np.concatenate([data.xpos[body], data.xquat[body]])
    joints[0] = data.qpos[qadr]
    for i in range(ctrl.shape[0]):
        data.ctrl[:] = ctrl[i]
        data.mocap_pos[:] = mocap_pos[i]
        data.mocap_quat[:] = mocap_quat[i]
        data.eq_active[:] = eq_active[i]
        mujoco.mj_step(model, data)
        frame = (i + 1) // substeps
        if (i + 1) % substeps == 0 and frame < frames:
            # mj_step leaves xpos/xquat at the state before the step: recompute at the frame's state.
            mujoco.mj_kinematics(model, data)
            poses[frame] = np.concatenate([data.xpos[body], data.xquat[body]])
            joints[frame] = data.qpos[qadr]
    return poses, joints


def main(argv: list[str]) -> int:
    folder = Path(argv[1]) if len(argv) > 1 else Path(__file__).resolve().parent
    poses, joints = replay_with_joints(folder)
    t = np.load(folder / "trajectories.npz")
    ok = False
    for name in ("object_pose_sim", "object_pose_ref"):
        stored = t[name]
        pos_mm = 1000.0 * np.linalg.norm(poses[:, :3] - stored[:, :3], axis=1)
        rot = rotation_error_deg(poses[:, 3:], stored[:, 3:])
        what = "simulated (stored)" if name == "object_pose_sim" else "recorded"
        print(f"vs {what} object: position error max {pos_mm.max():.4f} mm (mean {pos_mm.mean():.4f}), "
              f"rotation error max {rot.max():.4f} deg (mean {rot.mean():.4f})")
        if name == "object_pose_sim":
            ok = pos_mm.max() <= TOLERANCE_MM and rot.max() <= TOLERANCE_DEG
    specs = json.loads((folder / "export.json").read_text()).get("object_joints", [])
    for k, spec in enumerate(specs):
        for name in ("object_articulation_sim", "object_articulation_ref"):
            if name not in t.files:
                continue
            err = np.abs(joints[:, k] - t[name][:, k]) * float(spec["scale"])
            what = "simulated (stored)" if name == "object_articulation_sim" else "recorded"
            print(f"joint {spec['name']} vs {what}: error max {err.max():.4f} {spec['unit']} (mean {err.mean():.4f})")
            if name == "object_articulation_sim":
                # 1 degree, or 1 mm (0.1 cm) for a sliding joint.
                ok = ok and err.max() <= (TOLERANCE_DEG if spec["unit"] == "deg" else TOLERANCE_MM / 10.0)
    np.save(folder / "replayed_object_pose.npy", poses)
    if specs:
        np.save(folder / "replayed_object_articulation.npy", joints)
    print("OK: the replay follows the stored trajectory" if ok else "MISMATCH beyond 1 mm / 1 deg")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
