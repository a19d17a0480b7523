"""The table under the frame-0 object, chosen by simulation (DESIGN §1.4: the object starts at rest).

The recorded frame-0 pose is a vision estimate a few degrees and millimetres off any pose the object could rest
in on a level table (see ``support_plane``). Candidates: the level table at z = 0 (the object snapped onto it),
a level shelf under an object recorded above the table (on another object: ``SimConfig.table_shelf``), and the
hull faces of the recorded object that could carry it as recorded, each for two start poses: frame 0 and the
mean over the approach (``rest_pose``). Each is tried in a model of the object and the table alone for
``SimConfig.table_fit_s``; the one that leaves the object closest to that mean wins (score: degrees +
millimetres), so a lying cylinder balanced on one narrow strip of its side, which rolls away, loses to the level
table, and a box recorded 4 degrees tilted rests exactly as recorded on a table tilted under it. The fit is
deterministic and costs a few hundred physics steps of one free body per candidate.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np

from common.geometry import FloatArray, quat_to_matrix, rotation_error_deg
from common.primitive_surface import posed_surface_points
from common.sequence import Sequence
from worker.simulation.config import OBJECT_BIT, TABLE_BIT, SimConfig
from worker.simulation.hand_mjcf import fmt
from worker.simulation.object_model import OBJECT_JOINT, centre_of_mass, joint_name, object_mjcf
from worker.simulation.support_plane import SupportPlane, support_candidates

#: Candidate tilted faces tried (most nearly level first).
MAX_CANDIDATES = 6


def option_xml(config: SimConfig) -> str:
    """The MJCF ``<option>`` element of the paper's simulation settings."""
    return (
        f'<option timestep="{config.timestep:.12g}" integrator="{config.integrator}" solver="{config.solver}"\n'
        f'          jacobian="{config.jacobian}" iterations="{config.iterations}" '
        f'noslip_iterations="{config.noslip_iterations}" cone="{config.cone}" impratio="{config.impratio:g}"/>'
    )


def table_geom_xml(config: SimConfig, plane: SupportPlane) -> str:
    """The table: a plane geom colliding with the object only."""
    return (
        f'<geom name="table" type="plane" size="0 0 1" pos="{fmt(plane.point)}" quat="{fmt(plane.quat())}"\n'
        f'          contype="{TABLE_BIT}" conaffinity="{OBJECT_BIT}" condim="3"\n'
        f'          friction="{config.table_friction:g} 0.005 0.0001" solref="{fmt(config.contact_solref)}"\n'
        f'          solimp="{fmt(config.contact_solimp)}"/>'
    )


def level_start_pose(recorded: FloatArray, vertices_world: FloatArray, config: SimConfig) -> FloatArray:
    """The recorded pose placed exactly on a level table at z = 0 when its lowest point is within
    ``config.snap_to_table_m`` of it or below it (vision poses float or sink by a few millimetres)."""
    pose = recorded.copy()
    bottom = float(vertices_world[:, 2].min())
    if bottom < config.snap_to_table_m:
        pose[2] -= bottom
    return pose


class TableFit(NamedTuple):
    """The fit's choice: the object's frame-0 world pose, the table under it, and how far the object drifts from
    its rest pose on that table when simulated alone for ``SimConfig.table_fit_s`` (degrees + millimetres). A large
    drift means no table holds the object as recorded: it leaned on something the scene does not have."""

    pose: FloatArray
    plane: SupportPlane
    drift: float


def fit_table(
    seq: Sequence, config: SimConfig, rest_pose: FloatArray | None = None, *, cache_dir: Path | None = None,
    articulation: FloatArray | None = None,
) -> TableFit:
    """Frame-0 world pose of the object and the table plane under it (see the module docstring).

    ``rest_pose`` (7,): the object's pose at rest estimated over the frames before a hand comes near
    (``rest_pose``). The object then starts from it or from the recorded frame 0, on whichever table
    leaves it closest to that estimate: a mean over noisy frames is not always a pose the object can rest in
    exactly (a banana averaged over a 3 degree drift rocks 2.5 degrees off it), frame 0 may be. None: frame 0,
    scored against itself. ``articulation`` (J,): an articulated object's joint values at the start.
    """
    frame0 = seq.object_pose_world()[0].copy()
    target = frame0 if rest_pose is None else np.asarray(rest_pose, dtype=np.float64).copy()
    starts = [frame0] if np.array_equal(target, frame0) else [frame0, target]
    surface = posed_surface_points(seq.object, articulation, spacing=0)  # primitives are tessellated on each call
    candidates = [c for start in starts for c in _start_candidates(seq, config, surface, start)]
    # Simulated even when there is one candidate: its drift says whether the scene can hold the object at all.
    scores = _drift_scores(seq, config, target, candidates, cache_dir, articulation)
    best = int(np.argmin(scores))
    return TableFit(*candidates[best], scores[best])


def _start_candidates(
    seq: Sequence, config: SimConfig, surface: FloatArray, start: FloatArray
) -> list[tuple[FloatArray, SupportPlane]]:
    """The level table under ``start`` (snapped onto it) and the tilted hull faces that hold it as it is;
    ``surface``: the object's surface vertices (object frame)."""
    rot = quat_to_matrix(start[3:])
    verts = surface @ rot.T + start[:3]
    level = (level_start_pose(start, verts, config), SupportPlane.level())
    if config.table_max_tilt_deg <= 0:
        return [level]
    bottom = float(verts[:, 2].min())
    # Recorded above the table: resting on another object, which is not simulated. A level shelf under its lowest
    # point holds it where it was (a banana 10 cm up otherwise falls before the hand arrives); the shelf collides
    # with the object only, like the table.
    shelf = [(start, SupportPlane.level(bottom))] if config.table_shelf and bottom >= config.snap_to_table_m else []
    com = rot @ centre_of_mass(seq.object) + start[:3]  # the base part's: the parts hang from it
    tilted = support_candidates(verts, config.table_max_tilt_deg, limit=MAX_CANDIDATES, centre_of_mass=com)
    return [level] + shelf + [(start, plane) for plane in tilted]


def _drift_scores(
    seq: Sequence,
    config: SimConfig,
    target: FloatArray,
    candidates: list[tuple[FloatArray, SupportPlane]],
    cache_dir: Path | None,
    articulation: FloatArray | None = None,
) -> list[float]:
    """Degrees + millimetres between ``target`` and where the object is after ``config.table_fit_s``."""
    model, data, table, adr, joints = _alone_model(seq, config, target, cache_dir)
    steps = round(config.table_fit_s / model.opt.timestep)
    scores = []
    for pose, plane in candidates:
        mujoco.mj_resetData(model, data)
        data.mocap_pos[table] = plane.point
        data.mocap_quat[table] = plane.quat()
        data.qpos[adr : adr + 7] = pose
        if joints:
            data.qpos[joints] = articulation
        for _ in range(steps):
            mujoco.mj_step(model, data)
        end = data.qpos[adr : adr + 7]
        angle = float(rotation_error_deg(end[3:], target[3:]))
        scores.append(angle + 1000 * float(np.linalg.norm(end[:3] - target[:3])))
    return scores


def _alone_model(
    seq: Sequence, config: SimConfig, target: FloatArray, cache_dir: Path | None
) -> tuple[mujoco.MjModel, mujoco.MjData, int, int, list[int]]:
    """The object and a table alone: model, data, the table's mocap index, the object's qpos address and its
    joints' qpos addresses."""
    obj = object_mjcf(seq.object, config, target[:3], target[3:], cache_dir=cache_dir)
    xml = f"""<mujoco model="table-fit">
  <compiler angle="radian" autolimits="true"/>
  {option_xml(config)}
  <asset>
{obj.assets}
  </asset>
  <worldbody>
    <body name="table_body" mocap="true">
      {table_geom_xml(config, SupportPlane.level())}
    </body>
{obj.body}
  </worldbody>
</mujoco>
"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    # The table rides a mocap body: MuJoCo computes world-body geom frames once, so moving a static geom
    # between candidates would not move its collisions.
    table = int(model.body_mocapid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "table_body")])
    adr = int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, OBJECT_JOINT)])
    joints = [int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint_name(k))])
              for k in range(len(seq.object.parts))]  # fmt: skip
    return model, data, table, adr, joints


def released_motion(
    seq: Sequence, config: SimConfig, pose: FloatArray, plane: SupportPlane, frames: int, *,
    cache_dir: Path | None = None, articulation: FloatArray | None = None,
) -> FloatArray:
    """(frames + 1, 7) the object's pose at each video frame when released at ``pose`` on ``plane`` with nothing
    else in the scene (no hand, no hold): how an object no table holds falls or rolls before a hand arrives."""
    model, data, table, adr, joints = _alone_model(seq, config, pose, cache_dir)
    data.mocap_pos[table] = plane.point
    data.mocap_quat[table] = plane.quat()
    data.qpos[adr : adr + 7] = pose
    if joints and articulation is not None:
        data.qpos[joints] = articulation
    substeps = config.substeps_per_frame(seq.fps)
    out = [np.array(data.qpos[adr : adr + 7])]
    for _ in range(frames):
        for _ in range(substeps):
            mujoco.mj_step(model, data)
        out.append(np.array(data.qpos[adr : adr + 7]))
    return np.stack(out)
