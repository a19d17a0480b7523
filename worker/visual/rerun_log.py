"""A Rerun recording (``.rrd``) of a re-simulated result (issue #18 item 2), with ``rerun-sdk``.

Entities (timeline ``frame``, one tick per video frame):

* ``world/<run>/hand/<geom>`` and ``world/<run>/object/<geom>`` for each re-simulated run (``raw``,
  ``refined``): every geom as a mesh logged once (static) and its pose per frame (``Transform3D``);
* ``world/recorded/object/<geom>``: the object at its recorded pose (translucent green), and
  ``world/recorded/hand_<side>``: the recorded hand keypoints and skeleton;
* ``world/<run>/contacts``: contact points, and ``world/<run>/forces``: the hand's force on the object as
  arrows ending at the contact (0.01 m per newton);
* ``metrics/E_t/<run>``, ``metrics/E_r/<run>``: per-frame object errors; ``forces/<run>/<finger>``: summed
  contact force per finger.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from common.geometry import FloatArray
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


def _log(rec: Any, pb: Playback) -> None:
    import rerun as rr

    scene, model = pb.scene, pb.scene.model
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    hand_geoms = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in scene.body_side]
    object_geoms = [int(g) for g in scene.object_geom_ids]
    meshes = {g: geom_mesh(model, g) for g in (*hand_geoms, *object_geoms)}
    name = {g: mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}" for g in meshes}
    runs = list(pb.trajectories)
    for run in runs:
        for group, geoms in (("hand", hand_geoms), ("object", object_geoms)):
            for g in geoms:
                if meshes[g] is not None:
                    v, f = meshes[g]  # type: ignore[misc]
                    rec.log(f"world/{run}/{group}/{name[g]}",
                            rr.Mesh3D(vertex_positions=v, triangle_indices=f, albedo_factor=_COLOURS[group]),
                            static=True)  # fmt: skip
    for g in object_geoms:
        if meshes[g] is not None:
            v, f = meshes[g]  # type: ignore[misc]
            rec.log(f"world/recorded/object/{name[g]}",
                    rr.Mesh3D(vertex_positions=v, triangle_indices=f, albedo_factor=_COLOURS["ghost"]), static=True)
    data = mujoco.MjData(model)
    body = scene.object_body_id
    forces = {run: contact_force_per_finger(t.contacts, pb.num_frames) for run, t in pb.trajectories.items()}
    for frame in range(pb.num_frames):
        rec.set_time("frame", sequence=frame)
        for run, traj in pb.trajectories.items():
            data.qpos[:] = traj.qpos[frame]
            mujoco.mj_kinematics(model, data)
            for group, geoms in (("hand", hand_geoms), ("object", object_geoms)):
                for g in geoms:
                    if meshes[g] is not None:
                        rec.log(f"world/{run}/{group}/{name[g]}",
                                rr.Transform3D(translation=data.geom_xpos[g], mat3x3=data.geom_xmat[g].reshape(3, 3)))
            _log_contacts(rec, run, traj.contacts, frame)
            rec.log(f"metrics/E_t/{run}", rr.Scalars(float(traj.e_t_cm[frame])))
            rec.log(f"metrics/E_r/{run}", rr.Scalars(float(traj.e_r_deg[frame])))
            for finger, values in forces[run].items():
                rec.log(f"forces/{run}/{finger}", rr.Scalars(float(values[frame])))
        # The recorded object: each geom's pose in the body frame, carried by the recorded body pose (the last
        # run's kinematics give the geom-in-body offsets).
        r_body = data.xmat[body].reshape(3, 3)
        ref = pb.object_pose_ref[frame]
        r_flat = np.empty(9)
        mujoco.mju_quat2Mat(r_flat, ref[3:] / np.linalg.norm(ref[3:]))
        r_ref = r_flat.reshape(3, 3)
        for g in object_geoms:
            if meshes[g] is not None:
                local_pos = r_body.T @ (data.geom_xpos[g] - data.xpos[body])
                local_rot = r_body.T @ data.geom_xmat[g].reshape(3, 3)
                rec.log(f"world/recorded/object/{name[g]}",
                        rr.Transform3D(translation=ref[:3] + r_ref @ local_pos, mat3x3=r_ref @ local_rot))
        for side, kp in pb.keypoints_ref.items():
            pts = kp[frame]
            rec.log(f"world/recorded/hand_{side}", rr.LineStrips3D([[pts[a], pts[b]] for a, b in SKELETON],
                                                                   colors=[_COLOURS["ghost"][:3]], radii=0.002))


def _log_contacts(rec: Any, run: str, contacts: dict[str, np.ndarray], frame: int) -> None:
    import rerun as rr

    rows = np.flatnonzero(np.asarray(contacts["contact_frame"]) == frame)
    pos = np.asarray(contacts["contact_pos_world"], dtype=np.float64).reshape(-1, 3)[rows]
    force = np.asarray(contacts["contact_force"], dtype=np.float64).reshape(-1, 3)[rows]
    rec.log(f"world/{run}/contacts", rr.Points3D(pos, radii=0.003, colors=[_COLOURS[run][:3]]))
    # The hand's force on the object, its head at the contact point (as in the video).
    vectors = force * FORCE_ARROW_M_PER_N
    rec.log(f"world/{run}/forces", rr.Arrows3D(vectors=vectors, origins=pos - vectors, colors=[_COLOURS[run][:3]]))


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
