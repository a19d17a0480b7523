"""A self-contained folder a user can take anywhere (issue #18 item 6): plain MJCF, controls, trajectories and
a replay script that needs only ``mujoco`` and ``numpy``.

Folder contents:

* ``scene.xml``: the exact MJCF the result was simulated with (hand(s), object with its convex parts inline,
  table, every physics setting in ``<option>``: timestep, integrator, solver, noslip, contact and weld
  parameters); ``object.obj`` the object's visual mesh in its body frame (mesh objects only; an articulated
  object's further parts as ``object_part<k>.obj``, k from 1, each in its own body's frame);
* ``controls.npz``: per physics step (S = (F - 1) * substeps + 1) ``ctrl`` (S, nu) hinge servo targets,
  ``mocap_pos`` (S, nmocap, 3) and ``mocap_quat`` (S, nmocap, 4) the wrist's mocap pose, already interpolated
  (hinge targets and wrist positions linearly between frames, wrist rotations by slerp, each step driving
  towards the sample at its end); ``eq_active`` (S, neq) which equality constraints are on at each step (the
  wrist welds always; the weld ``object_hold`` that holds the object until the hand comes); ``start_state``
  (mjSTATE_FULLPHYSICS) and ``start_warmstart`` the settled frame-0 state; per frame, per hand side S:
  ``S_q_target`` (F, 45), ``S_wrist_pos`` (F, 3), ``S_wrist_quat`` (F, 4) the refined tracks before
  interpolation;
* ``trajectories.npz``: ``object_pose_sim`` (F, 7) the simulated object, ``object_pose_ref`` the recorded one,
  ``raw_object_pose_sim`` the raw replay's, ``object_vel_sim``, per side ``S_keypoints_sim`` / ``_ref``; an
  articulated object adds ``object_articulation_sim`` / ``_ref`` / ``raw_object_articulation_sim`` (F, J) joint
  values (rad / m);
* ``contacts.npz``: the per-frame contacts (``common.result_format.CONTACT_KEYS``, and ``contact_part`` for an
  articulated object);
* ``export.json``: frame rate, substeps, timestep, names (actuators, mocap bodies, object body; an articulated
  object's ``object_joints``: per joint its MJCF name, its name in the sequence, its kind and unit), metrics;
* ``replay.py``: ``worker.visual.standalone_replay`` copied verbatim.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from common.result_format import CONTACT_KEYS, PART_CONTACT_KEYS, read_summary
from common.sequence import Sequence
from worker.visual.playback import Playback, main_trajectory, resimulate

FILES: tuple[str, ...] = ("scene.xml", "controls.npz", "trajectories.npz", "contacts.npz", "export.json", "replay.py")


def export_result(
    blob: bytes, out_dir: Path | str, sequence: Sequence | None = None, *, cache_dir: Path | None = None,
    mano_dir: Path | None = None,
) -> Path:
    """Write the export folder of a result (the refined trajectory, or a raw replay's); returns its path.
    ``cache_dir``, ``mano_dir``: as for ``resimulate``."""
    main = main_trajectory(read_summary(blob))
    pb = resimulate(blob, sequence, which=(main,), record_controls=True, cache_dir=cache_dir, mano_dir=mano_dir)
    return export_playback(pb, out_dir)


def export_playback(pb: Playback, out_dir: Path | str) -> Path:
    """``export_result`` from a playback re-simulated with ``record_controls=True``."""
    from worker.simulation.object_model import OBJECT_BODY

    if pb.controls is None:
        raise ValueError("the playback holds no controls: resimulate(..., record_controls=True)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene, arrays, model = pb.scene, pb.arrays, pb.scene.model
    (out / "scene.xml").write_text(scene.xml)
    for k, shape in enumerate(pb.sequence.object.part_shapes()):
        if shape.mesh_vertices is not None and shape.mesh_faces is not None:
            _write_obj(out / ("object.obj" if k == 0 else f"object_part{k}.obj"), shape.mesh_vertices, shape.mesh_faces)
    per_frame = {f"{s}_{k}": arrays[f"{s}_{k}"] for s in scene.hands for k in ("q_target", "wrist_pos", "wrist_quat")}
    controls: dict[str, Any] = {
        "ctrl": pb.controls.ctrl,
        "mocap_pos": pb.controls.mocap_pos,
        "mocap_quat": pb.controls.mocap_quat,
        "eq_active": pb.controls.eq_active,
        "start_state": pb.controls.start_physics,
        "start_warmstart": pb.controls.start_warmstart,
        **per_frame,
    }
    _savez(out / "controls.npz", controls)
    traj_keys = ["object_pose_sim", "object_pose_ref", "raw_object_pose_sim", "object_vel_sim",
                 "object_articulation_sim", "object_articulation_ref", "raw_object_articulation_sim"]
    traj_keys += [f"{s}_{k}" for s in scene.hands for k in ("keypoints_sim", "keypoints_ref", "valid")]
    _savez(out / "trajectories.npz", {k: arrays[k] for k in traj_keys if k in arrays})
    _savez(out / "contacts.npz", {k: arrays[k] for k in (*CONTACT_KEYS, *PART_CONTACT_KEYS) if k in arrays})
    (out / "export.json").write_text(json.dumps(_meta(pb, model, OBJECT_BODY), indent=1, sort_keys=True))
    from worker.visual import standalone_replay

    (out / "replay.py").write_text(Path(standalone_replay.__file__).read_text())
    return out


def _names(model: mujoco.MjModel, kind: mujoco.mjtObj, ids: Any) -> list[str]:
    return [mujoco.mj_id2name(model, kind, int(i)) or "" for i in ids]


def _meta(pb: Any, model: mujoco.MjModel, object_body: str) -> dict[str, Any]:
    from worker.simulation.object_model import joint_name

    mocap_bodies = [b for b in range(model.nbody) if model.body_mocapid[b] >= 0]
    mocap_bodies.sort(key=lambda b: int(model.body_mocapid[b]))
    joints = [{"mjcf": joint_name(k), "name": j.name, "kind": j.kind, "unit": j.unit, "scale": j.display_scale()}
              for k, j in enumerate(pb.sequence.object.joints)]  # fmt: skip
    return {
        "sequence": pb.summary.get("sequence"),
        "trajectory": main_trajectory(pb.summary),  # whose controls: the refined hand, or a raw replay's
        "fps": pb.fps,
        "frames": pb.num_frames,
        "substeps_per_frame": int(pb.scene.substeps_per_frame),
        "timestep": float(model.opt.timestep),
        "steps": int(pb.controls.ctrl.shape[0]),
        "object_body": object_body,
        "object_joints": joints,
        "actuators": _names(model, mujoco.mjtObj.mjOBJ_ACTUATOR, range(model.nu)),
        "mocap_bodies": _names(model, mujoco.mjtObj.mjOBJ_BODY, mocap_bodies),
        "interpolation": "controls.npz ctrl/mocap_* hold one row per physics step, already interpolated between "
        "frames (hinge targets and wrist positions linearly, wrist rotations by slerp; step k of frame f drives "
        "towards the sample at (k + 1) / substeps_per_frame); frame f is the state after step f * substeps - 1",
        "quaternions": "w x y z",
        "metrics": pb.summary.get("metrics"),
        "versions": pb.summary.get("versions"),
        "mujoco_used_for_export": mujoco.__version__,
    }


def _savez(path: Path, arrays: dict[str, Any]) -> None:
    np.savez_compressed(path, allow_pickle=False, **arrays)


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in np.asarray(vertices, dtype=np.float64)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces, dtype=np.int64)]
    path.write_text("\n".join(lines) + "\n")
