"""Offscreen frames of a re-simulated result (issue #18 item 1) with ``mujoco.Renderer``.

Each panel shows one trajectory (raw replay or refined) at one frame: the simulated hand(s) and object, the
recorded object as a translucent green ghost (an articulated object part by part, each part where the recording has
it, so the ghost opens as the recording does), every hand-object contact as a red arrow of the hand's force on the
object, its head at the contact point (``FORCE_ARROW_M_PER_N`` metres per newton, capped), and a caption with the
panel's name, the frame number and that frame's E_t / E_r (and E_a for an articulated object). Panels sit side by
side. The default camera (``auto_camera``) frames the recorded and simulated object and the hands near it over the
whole sequence, and looks across the line between two hands so that neither hides the other.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from common.geometry import FloatArray
from worker.visual.playback import Playback, Trajectory
from worker.visual.video import Frame

#: Contact force arrows: length per newton of force, and the longest arrow drawn.
FORCE_ARROW_M_PER_N = 0.01
FORCE_ARROW_MAX_M = 0.08
GHOST_RGBA = (0.2, 0.85, 0.3, 0.35)
OBJECT_RGBA = (0.95, 0.6, 0.2, 1.0)
HAND_RGBA = (0.85, 0.72, 0.62, 1.0)
TABLE_RGBA = (0.55, 0.6, 0.68, 1.0)
ARROW_RGBA = (0.95, 0.15, 0.1, 1.0)
#: Hand keypoints farther than this from the recorded object do not steer the automatic camera.
NEAR_OBJECT_M = 0.15
PANEL_TITLES = {"raw": "raw replay", "refined": "refined"}


@dataclass(frozen=True)
class CameraSpec:
    """A free camera: look at ``lookat`` from ``distance`` at ``azimuth`` / ``elevation`` (degrees), or a camera
    of the model by ``name``."""

    lookat: tuple[float, float, float] = (0.0, 0.0, 0.0)
    distance: float = 0.5
    azimuth: float = 135.0
    elevation: float = -25.0
    name: str | None = None


DEFAULT_AZIMUTH = 135.0


def auto_camera(playback: Playback, azimuth: float | None = None, elevation: float = -25.0) -> CameraSpec:
    """Frame the interaction over the whole sequence: the recorded and simulated object (every part), and the
    recorded hands where they are within ``NEAR_OBJECT_M`` of a part (a hand still far away would shrink
    everything). ``azimuth`` None: ``DEFAULT_AZIMUTH`` for one hand; with two, the view across the line between
    them nearest to it (``two_hand_azimuth``)."""
    ref = playback.object_pose_ref[:, :3]
    parts = playback.part_poses_ref[:, :, :3]  # (F, P, 3)
    points = [ref, parts.reshape(-1, 3), *(t.object_pose[:, :3] for t in playback.trajectories.values())]
    near_points = {}
    for side, kp in playback.keypoints_ref.items():
        dist = np.linalg.norm(kp[:, :, None, :] - parts[:, None, :, :], axis=3).min(axis=2)  # (F, 21)
        near_points[side] = kp[dist <= NEAR_OBJECT_M]
        points.append(near_points[side])
    if azimuth is None:
        azimuth = two_hand_azimuth(near_points)
    cloud = np.concatenate(points)
    cloud = cloud[np.isfinite(cloud).all(axis=1)]
    lo, hi = np.percentile(cloud, 1, axis=0), np.percentile(cloud, 99, axis=0)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 0.08)
    # 45 deg vertical field of view (MuJoCo's default): a sphere of ``radius`` fits at radius / sin(22.5 deg).
    # Looking a little higher moves the scene down, clear of the caption band at the top.
    distance = 1.2 * radius / np.sin(np.radians(22.5))
    lookat = (float(centre[0]), float(centre[1]), float(centre[2] + 0.08 * distance))
    return CameraSpec(lookat, distance, azimuth, elevation)


def two_hand_azimuth(near_points: dict[str, FloatArray], preferred: float = DEFAULT_AZIMUTH) -> float:
    """The azimuth (deg) looking across the horizontal line between two hands' points nearest to ``preferred``
    (``preferred`` itself for one hand, or hands less than 2 cm apart seen from above)."""
    centres = [p[np.isfinite(p).all(axis=1)].mean(axis=0) for p in near_points.values() if len(p)]
    if len(centres) != 2:
        return preferred
    d = centres[1] - centres[0]
    if float(np.hypot(d[0], d[1])) < 0.02:
        return preferred
    line = float(np.degrees(np.arctan2(d[1], d[0])))
    # MuJoCo's free camera looks along (cos az, sin az) horizontally: across the line is the line's angle +- 90.
    return min((line + 90.0, line - 90.0), key=lambda a: abs((a - preferred + 180.0) % 360.0 - 180.0)) % 360.0


def parse_camera(text: str, playback: Playback) -> CameraSpec:
    """``auto``, a camera name of the model, ``AZIMUTH,ELEVATION`` (auto framing from there) or
    ``AZIMUTH,ELEVATION,DISTANCE[,X,Y,Z]`` (degrees, metres)."""
    text = text.strip()
    if text in ("", "auto"):
        return auto_camera(playback)
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        model = playback.scene.model
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, text) < 0:
            raise ValueError(f"--camera {text!r}: not 'auto', numbers, or a camera of the scene") from None
        return CameraSpec(name=text)
    base = auto_camera(playback, *values[:2]) if len(values) >= 2 else None
    if len(values) == 2 and base is not None:
        return base
    if len(values) in (3, 6) and base is not None:
        lookat = tuple(values[3:6]) if len(values) == 6 else base.lookat
        return CameraSpec(lookat, values[2], values[0], values[1])  # type: ignore[arg-type]
    raise ValueError(f"--camera {text!r}: give AZIMUTH,ELEVATION or AZIMUTH,ELEVATION,DISTANCE[,X,Y,Z]")


class PanelRenderer:
    """Draws panels of one playback; owns one ``mujoco.Renderer`` (close it, or use as a context manager)."""

    def __init__(self, playback: Playback, width: int = 320, height: int = 240, camera: CameraSpec | None = None,
                 samples: int | None = None):
        """``samples``: multisample anti-aliasing of the offscreen buffer (None: the model's, 4 by default; 0 draws
        a job's stored preview a third faster on a software renderer, with jagged edges)."""
        from worker.visual.gl import offscreen_context_class

        if width < 16 or height < 16:
            raise ValueError(f"panel size must be at least 16x16, got {width}x{height}")
        if samples is not None and samples < 0:
            raise ValueError(f"samples must be >= 0, got {samples}")
        offscreen_context_class()
        self.playback = playback
        self.model = playback.scene.model
        vis = self.model.vis.global_
        vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
        if samples is not None:
            self.model.vis.quality.offsamples = samples
        self._colour(playback)
        self.renderer = mujoco.Renderer(self.model, height, width)
        self.data = mujoco.MjData(self.model)
        self.camera = camera or auto_camera(playback)
        self._cam = self._make_camera(self.camera)
        scene = playback.scene
        # Each object geom's part (0: the base; a rigid object's geoms all 0) and that part's body.
        self._geom_part = {int(g): max(int(scene.geom_part[g]), 0) if len(scene.geom_part) else 0
                           for g in scene.object_geom_ids}  # fmt: skip
        self._part_bodies = [int(b) for b in scene.object_part_body_ids] or [int(scene.object_body_id)]

    def _colour(self, playback: Playback) -> None:
        """Colours and a brighter headlight: visual fields only, the physics of the model is untouched."""
        m, scene = self.model, playback.scene
        for h in scene.hands.values():
            for b in h.body_ids:
                m.geom_rgba[m.geom_bodyid == b] = HAND_RGBA
        m.geom_rgba[np.asarray(scene.object_geom_ids)] = OBJECT_RGBA
        m.geom_rgba[scene.table_geom_id] = TABLE_RGBA
        m.vis.headlight.ambient[:] = 0.45
        m.vis.headlight.diffuse[:] = 0.6

    def _make_camera(self, spec: CameraSpec) -> mujoco.MjvCamera | str:
        if spec.name is not None:
            return spec.name
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = spec.lookat
        cam.distance, cam.azimuth, cam.elevation = spec.distance, spec.azimuth, spec.elevation
        return cam

    def close(self) -> None:
        self.renderer.close()

    def __enter__(self) -> PanelRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def panel(self, traj: Trajectory, frame: int) -> Frame:
        """One (H, W, 3) panel of ``traj`` at ``frame`` with the ghost, contact arrows and caption."""
        d = self.data
        d.qpos[:] = traj.qpos[frame]
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_camlight(self.model, d)
        self.renderer.update_scene(d, camera=self._cam)
        scn = self.renderer.scene
        self._add_ghost(scn, self.playback.part_poses_ref[frame])
        self._add_contacts(scn, traj, frame)
        image = self.renderer.render().copy()
        errors = f"E_t {traj.e_t_cm[frame]:.2f} cm  E_r {traj.e_r_deg[frame]:.1f} deg"
        if traj.e_a is not None:
            errors += f"  E_a {traj.e_a[frame]:.1f} {articulation_unit(self.playback)}"
        return caption(image, [f"{PANEL_TITLES.get(traj.name, traj.name)}  frame {frame + 1}/{len(traj.qpos)}",
                               errors])  # fmt: skip

    def _free_geom(self, scn: mujoco.MjvScene) -> mujoco.MjvGeom | None:
        if scn.ngeom >= scn.maxgeom:
            return None
        scn.ngeom += 1
        return scn.geoms[scn.ngeom - 1]

    def _add_ghost(self, scn: mujoco.MjvScene, ref_parts: FloatArray) -> None:
        """Copies of the object's geoms, each moved by its part's ref * sim^-1 (``ref_parts`` (P, 7), the recorded
        world pose of every part): the object, every part of it, where the recording has it."""
        d = self.data
        moves = []
        for k, body in enumerate(self._part_bodies):
            r_sim, r_ref = d.xmat[body].reshape(3, 3), _quat_mat(ref_parts[k, 3:])
            moves.append((r_ref @ r_sim.T, np.asarray(d.xpos[body]), ref_parts[k, :3]))
        for i in range(scn.ngeom):
            src = scn.geoms[i]
            part = self._geom_part.get(int(src.objid)) if src.objtype == mujoco.mjtObj.mjOBJ_GEOM else None
            if part is None:
                continue
            g = self._free_geom(scn)
            if g is None:
                return
            rel, sim_pos, ref_pos = moves[part]
            pos = ref_pos + rel @ (np.asarray(src.pos) - sim_pos)
            mat = rel @ np.asarray(src.mat).reshape(3, 3)
            mujoco.mjv_initGeom(g, int(src.type), np.asarray(src.size), pos, mat.ravel(), np.asarray(GHOST_RGBA))
            g.dataid = src.dataid  # the same mesh, for mesh geoms
            g.category = mujoco.mjtCatBit.mjCAT_DECOR

    def _add_contacts(self, scn: mujoco.MjvScene, traj: Trajectory, frame: int) -> None:
        c = traj.contacts
        rows = np.flatnonzero(np.asarray(c["contact_frame"]) == frame)
        for row in rows:
            force = np.asarray(c["contact_force"][row], dtype=np.float64)
            mag = float(np.linalg.norm(force))
            if mag < 1e-6:
                continue
            # The hand's force on the object, drawn pushing on it: the head at the contact point, the tail outside
            # (drawn from the point outwards, it would lie inside the object).
            end = np.asarray(c["contact_pos_world"][row], dtype=np.float64)
            start = end - force / mag * min(mag * FORCE_ARROW_M_PER_N, FORCE_ARROW_MAX_M)
            g = self._free_geom(scn)
            if g is None:
                return
            mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_ARROW, np.zeros(3), np.zeros(3), np.eye(3).ravel(),
                                np.asarray(ARROW_RGBA))  # fmt: skip
            mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_ARROW, 0.004, start, end)
            g.category = mujoco.mjtCatBit.mjCAT_DECOR  # mjv_initGeom leaves it unset: unset ones may not be drawn


def articulation_unit(playback: Playback) -> str:
    """The unit E_a is shown in: deg (revolute joints), cm (prismatic) or deg/cm (both kinds)."""
    units = {j.unit for j in playback.sequence.object.joints}
    return "deg/cm" if len(units) == 2 else "".join(units)


def _quat_mat(quat: FloatArray) -> FloatArray:
    out = np.empty(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, dtype=np.float64) / np.linalg.norm(quat))
    return out.reshape(3, 3)


def caption(image: Frame, lines: Sequence[str]) -> Frame:
    """Write ``lines`` in the top-left corner on a dark band (Pillow's built-in font)."""
    from PIL import Image, ImageDraw, ImageFont

    pil = Image.fromarray(image)
    draw = ImageDraw.Draw(pil)
    size = max(10, image.shape[0] // 20)
    font = ImageFont.load_default(size=size)
    band = (size + 4) * len(lines) + 4
    draw.rectangle((0, 0, image.shape[1], band), fill=(20, 20, 20))
    for i, line in enumerate(lines):
        draw.text((5, 3 + i * (size + 4)), line, fill=(240, 240, 240), font=font)
    return np.asarray(pil, dtype=np.uint8)


def render_frames(
    playback: Playback,
    which: Sequence[str] | None = None,
    width: int = 320,
    height: int = 240,
    camera: CameraSpec | None = None,
    frames: Sequence[int] | None = None,
    samples: int | None = None,
) -> Iterator[Frame]:
    """(height, width * len(which), 3) frames, the panels of ``which`` (default: every re-simulated trajectory)
    side by side, for every frame (or ``frames``); ``samples`` as for ``PanelRenderer``."""
    which = list(playback.trajectories) if which is None else which
    missing = [w for w in which if w not in playback.trajectories]
    if missing or not which:
        raise ValueError(f"trajectories {missing or list(which)} were not re-simulated "
                         f"(have {list(playback.trajectories)})")  # fmt: skip
    order = range(playback.num_frames) if frames is None else frames
    with PanelRenderer(playback, width, height, camera, samples) as r:
        for f in order:
            yield np.concatenate([r.panel(playback.trajectories[w], f) for w in which], axis=1)


def render_video(
    playback: Playback,
    out: str,
    which: Sequence[str] | None = None,
    width: int = 320,
    height: int = 240,
    camera: CameraSpec | None = None,
    samples: int | None = None,
) -> int:
    """Write every frame of ``which`` side by side to the MP4 ``out`` at the sequence's frame rate; returns
    the number of frames. ``samples`` as for ``PanelRenderer``."""
    from worker.visual.video import write_mp4

    return write_mp4(render_frames(playback, which, width, height, camera, samples=samples), out, playback.fps)
