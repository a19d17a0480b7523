"""A Rerun recording (``.rrd``) of a re-simulated result (issue #18 item 2), with ``rerun-sdk``.

Entities (timeline ``frame``, one tick per video frame):

* ``world/<run>/hand/<geom>`` and ``world/<run>/object/<geom>`` for each re-simulated run (``raw``,
  ``refined``): every geom as a mesh logged once (static) and its pose per frame (``Transform3D``);
* ``world/recorded/object/<geom>``: the object at its recorded pose (translucent green; an articulated object's
  geoms each at its part's recorded pose), and ``world/recorded/hand_<side>``: the recorded hand keypoints and
  skeleton (both hands);
* ``world/<run>/contacts``: contact points, and ``world/<run>/forces``: the hand's force on the object as
  arrows ending at the contact (0.01 m per newton);
* ``metrics/E_t/<run>``, ``metrics/E_r/<run>``: per-frame object errors; ``forces/<run>/<finger>``: summed
  contact force per finger (two hands: ``forces/<run>/<side>/<finger>``);
* an articulated object: ``metrics/E_a/<run>`` (the frame's largest joint error, deg or cm) and
  ``articulation/<joint>/<run>`` and ``articulation/<joint>/recorded``: every joint's value (deg or cm).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from common.geometry import FloatArray, quat_to_matrix
from worker.visual.playback import Playback, contact_force_per_finger
from worker.visual.render import FORCE_ARROW_M_PER_N

#: Keypoint pairs of the MANO21 skeleton (wrist 0; per finger base..tip, 4 keypoints from 1 + 4 * f).
SKELETON = [(0, 1 + 4 * f) for f in range(5)] + [(1 + 4 * f + j, 2 + 4 * f + j) for f in range(5) for j in range(3)]
_COLOURS = {"hand": (217, 184, 158, 255), "object": (242, 153, 51, 255), "ghost": (51, 217, 77, 90),
            "raw": (214, 39, 40, 255), "refined": (31, 119, 180, 255)}  # fmt: skip


def geom_mesh(model: mujoco.MjModel, g: int) -> tuple[FloatArray, np.ndarray] | None:
    """Vertices (V, 3) in the geom's frame and triangles (T, 3) of geom ``g``; None for planes and others."""
    import trimesh

    kind, size = int(model.geom_type[g]), model.geom_size[g]
    t = mujoco.mjtGeom
    if kind == t.mjGEOM_MESH:
        m = int(model.geom_dataid[g])
        v0, nv = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
        f0, nf = int(model.mesh_faceadr[m]), int(model.mesh_facenum[m])
        return np.asarray(model.mesh_vert[v0 : v0 + nv], dtype=np.float64), np.asarray(model.mesh_face[f0 : f0 + nf])
    if kind == t.mjGEOM_BOX:
        mesh = trimesh.creation.box(extents=2 * size)
    elif kind == t.mjGEOM_CAPSULE:
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[8, 8])
    elif kind == t.mjGEOM_CYLINDER:
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=16)
    elif kind in (t.mjGEOM_SPHERE, t.mjGEOM_ELLIPSOID):
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        mesh.apply_scale(size if kind == t.mjGEOM_ELLIPSOID else size[0])
    else:
        return None
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)


def write_recording(playback: Playback, out: Path | str | None = None, spawn: bool = False) -> Path | None:
    """Log the playback to ``out`` (an ``.rrd`` file) and/or a spawned viewer; returns ``out``."""
    import rerun as rr

    rec = rr.RecordingStream("hoi-refine", recording_id=f"hoi-refine-{playback.summary.get('sequence', '')}")
    sinks: list[Any] = []
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(out)))
    if spawn:
        rec.spawn(connect=False)  # the viewer process; it listens on the default port the GrpcSink sends to
        sinks.append(rr.GrpcSink())
    if not sinks:
        raise ValueError("write_recording needs a file to write (out) or a viewer to spawn")
    rec.set_sinks(*sinks)
    try:
        _log(rec, playback)
    finally:
        rec.flush()
        rec.disconnect()
    return out


def hand_bones(keypoint_ids: np.ndarray) -> np.ndarray:
    """(B, 2) the skeleton's bones between keypoint sites a hand has (a robot places a subset of the 21, issue
    #55), as indices into its sites."""
    where = {int(k): i for i, k in enumerate(keypoint_ids)}
    return np.array([(where[a], where[b]) for a, b in SKELETON if a in where and b in where], dtype=np.int64
                    ).reshape(-1, 2)


def _log(rec: Any, pb: Playback) -> None:
    # Whole columns per entity (``send_columns``), not one ``log`` call per entity and frame: the recording is
    # made after every job, and row-by-row logging was thousands of Python calls for a few hundred frames.
    import rerun as rr

    scene, model = pb.scene, pb.scene.model
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    hand_geoms = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in scene.body_side]
    object_geoms = [int(g) for g in scene.object_geom_ids]
    meshes = {g: geom_mesh(model, g) for g in (*hand_geoms, *object_geoms)}
    drawn = [g for g in (*hand_geoms, *object_geoms) if meshes[g] is not None]
    name = {g: mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}" for g in meshes}
    group_of = {g: "hand" for g in hand_geoms} | {g: "object" for g in object_geoms}
    for run in pb.trajectories:
        for g in drawn:
            v, f = meshes[g]  # type: ignore[misc]
            rec.log(f"world/{run}/{group_of[g]}/{name[g]}",
                    rr.Mesh3D(vertex_positions=v, triangle_indices=f, albedo_factor=_COLOURS[group_of[g]]),
                    static=True)  # fmt: skip
    drawn_objects = [g for g in drawn if group_of[g] == "object"]
    for g in drawn_objects:
        v, f = meshes[g]  # type: ignore[misc]
        rec.log(
            f"world/recorded/object/{name[g]}",
            rr.Mesh3D(vertex_positions=v, triangle_indices=f, albedo_factor=_COLOURS["ghost"]),
            static=True,
        )
    frames = rr.TimeColumn("frame", sequence=np.arange(pb.num_frames))
    data = mujoco.MjData(model)
    for run, traj in pb.trajectories.items():
        pos, rot = _geom_poses(model, data, traj.qpos, drawn)
        for i, g in enumerate(drawn):
            rec.send_columns(
                f"world/{run}/{group_of[g]}/{name[g]}",
                indexes=[frames],
                columns=rr.Transform3D.columns(translation=pos[:, i], mat3x3=rot[:, i]),
            )
        _log_contacts(rec, run, traj.contacts, pb.num_frames, frames)
        rec.send_columns(f"metrics/E_t/{run}", indexes=[frames], columns=rr.Scalars.columns(scalars=traj.e_t_cm))
        rec.send_columns(f"metrics/E_r/{run}", indexes=[frames], columns=rr.Scalars.columns(scalars=traj.e_r_deg))
        # One hand: ``forces/<run>/<finger>``; two: ``forces/<run>/<side>/<finger>``, each hand on its own.
        sides = [None] if len(scene.hands) < 2 else list(scene.hands)
        for side in sides:
            where = f"forces/{run}" if side is None else f"forces/{run}/{side}"
            for finger, values in contact_force_per_finger(traj.contacts, pb.num_frames, side).items():
                rec.send_columns(f"{where}/{finger}", indexes=[frames], columns=rr.Scalars.columns(scalars=values))
        if traj.e_a is not None:
            rec.send_columns(f"metrics/E_a/{run}", indexes=[frames], columns=rr.Scalars.columns(scalars=traj.e_a))
        if traj.articulation is not None:
            _log_joints(rec, pb, traj.articulation, run, frames)
    if pb.articulation_ref is not None:
        _log_joints(rec, pb, pb.articulation_ref, "recorded", frames)
    # The recorded object: each geom carried by its part's recorded pose at its fixed place in the part's frame.
    mujoco.mj_kinematics(model, data)
    bodies = [int(b) for b in scene.object_part_body_ids] or [int(scene.object_body_id)]
    ref_parts = pb.part_poses_ref[: pb.num_frames]
    for g in drawn_objects:
        part = max(int(scene.geom_part[g]), 0) if len(scene.geom_part) else 0
        body = bodies[part]
        r_body = data.xmat[body].reshape(3, 3)
        local_pos = r_body.T @ (data.geom_xpos[g] - data.xpos[body])
        local_rot = r_body.T @ data.geom_xmat[g].reshape(3, 3)
        ref = ref_parts[:, part]
        r_ref = quat_to_matrix(ref[:, 3:])
        rec.send_columns(f"world/recorded/object/{name[g]}", indexes=[frames],
                         columns=rr.Transform3D.columns(translation=ref[:, :3] + r_ref @ local_pos,
                                                        mat3x3=r_ref @ local_rot))  # fmt: skip
    for side, all_kp in pb.keypoints_ref.items():
        kp = all_kp[: pb.num_frames]
        bones = hand_bones(scene.hands[side].keypoint_ids)
        strips: Any = np.stack([kp[:, bones[:, 0]], kp[:, bones[:, 1]]], axis=2).reshape(-1, 2, 3)  # (F * bones, 2, 3)
        n = len(strips)
        rec.send_columns(
            f"world/recorded/hand_{side}",
            indexes=[frames],
            columns=rr.LineStrips3D.columns(
                strips=strips, colors=np.tile(_COLOURS["ghost"][:3], (n, 1)), radii=np.full(n, 0.002)
            ).partition([len(bones)] * len(kp)),
        )


def _log_joints(rec: Any, pb: Playback, values: FloatArray, run: str, frames: Any) -> None:
    """Every joint's value per frame, in its display unit (deg or cm), as ``articulation/<joint>/<run>``."""
    import rerun as rr

    for k, joint in enumerate(pb.sequence.object.joints):
        shown = np.asarray(values[: pb.num_frames, k], dtype=np.float64) * joint.display_scale()
        entity = re.sub(r"[^A-Za-z0-9_.-]", "_", joint.name)  # a joint's name is free text; a path is not
        rec.send_columns(f"articulation/{entity}/{run}", indexes=[frames],
                         columns=rr.Scalars.columns(scalars=shown))  # fmt: skip


def _geom_poses(
    model: mujoco.MjModel, data: mujoco.MjData, qpos: FloatArray, geoms: list[int]
) -> tuple[FloatArray, FloatArray]:
    """World position (F, G, 3) and rotation (F, G, 3, 3) of ``geoms`` at each frame's ``qpos``."""
    pos = np.empty((len(qpos), len(geoms), 3))
    rot = np.empty((len(qpos), len(geoms), 3, 3))
    for frame, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        pos[frame] = data.geom_xpos[geoms]
        rot[frame] = data.geom_xmat[geoms].reshape(-1, 3, 3)
    return pos, rot


def _log_contacts(rec: Any, run: str, contacts: dict[str, np.ndarray], num_frames: int, frames: Any) -> None:
    import rerun as rr

    at = np.asarray(contacts["contact_frame"], dtype=np.int64)
    rows = np.flatnonzero((at >= 0) & (at < num_frames))
    rows = rows[np.argsort(at[rows], kind="stable")]  # frame order, each frame's contacts in stored order
    counts = np.bincount(at[rows], minlength=num_frames)
    pos = np.asarray(contacts["contact_pos_world"], dtype=np.float64).reshape(-1, 3)[rows]
    force = np.asarray(contacts["contact_force"], dtype=np.float64).reshape(-1, 3)[rows]
    colours = np.tile(_COLOURS[run][:3], (len(rows), 1))
    rec.send_columns(f"world/{run}/contacts", indexes=[frames],
                     columns=rr.Points3D.columns(positions=pos, radii=np.full(len(rows), 0.003),
                                                 colors=colours).partition(counts))  # fmt: skip
    # The hand's force on the object, its head at the contact point (as in the video).
    vectors = force * FORCE_ARROW_M_PER_N
    rec.send_columns(f"world/{run}/forces", indexes=[frames],
                     columns=rr.Arrows3D.columns(vectors=vectors, origins=pos - vectors,
                                                 colors=colours).partition(counts))  # fmt: skip


def read_recording(path: Path | str) -> dict[str, int]:
    """Entity paths of an ``.rrd`` file and their number of logged rows (to check a recording)."""
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    for chunk in RrdReader(path).stream():
        counts[chunk.entity_path] = counts.get(chunk.entity_path, 0) + chunk.num_rows
    return counts


def read_scalars(path: Path | str, entity: str) -> FloatArray:
    """The values of a ``Scalars`` entity, in frame order."""
    from rerun.chunk import RrdReader

    rows: list[tuple[int, float]] = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        frame_col = next(n for n in names if n == "frame" or n.endswith(":frame"))
        scalar_col = next(n for n in names if "Scalar" in n or n.endswith(":scalars"))
        frames = batch.column(names.index(frame_col)).to_pylist()
        values = batch.column(names.index(scalar_col))
        flat = [v[0] if isinstance(v, list) else v for v in values.to_pylist()]  # Scalars: one-element lists
        rows += list(zip(frames, flat, strict=True))
    rows.sort()
    return np.array([v for _, v in rows], dtype=np.float64)
