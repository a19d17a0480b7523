"""Offscreen frames of a re-simulated result (issue #18 item 1) with ``mujoco.Renderer``.

Each panel shows one trajectory (raw replay or refined) at one frame: the simulated hand(s) and object, the
recorded object as a translucent green ghost (an articulated object part by part, each part where the recording has
it, so the ghost opens as the recording does), every hand-object contact as a red arrow of the hand's force on the
object, its head at the contact point (``FORCE_ARROW_M_PER_N`` metres per newton, capped), and a caption with the
panel's name, the frame number and that frame's E_t / E_r (and E_a for an articulated object). Panels sit side by
side, ``PANEL_SIZE`` (640x480) each by default: the fingers and contacts need the pixels. The default camera
(``auto_camera``) fits the view to the recorded and simulated object and the hands near it over the whole sequence
(``framing.fit_view``: every point inside the image, below the caption), and looks across the line between two hands
so that neither hides the other. The close-up (``auto_camera(close_up=True)``, ``hoi-refine render --close-up``)
follows the recorded object and frames it with the fingers at it.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

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
#: A hand steers the automatic camera in the frames where one of its keypoints is this close to the object's
#: surface (its parts' boxes): its whole reach from afar would shrink the grasp; both hands count.
NEAR_OBJECT_M = 0.08
#: The close-up frames the object and the hand keypoints this close to its surface: the fingers at the grasp.
CLOSE_UP_NEAR_M = 0.05
#: The close-up follows the recorded object, smoothed over this many frames (annotation jitter would shake it).
CLOSE_UP_SMOOTHING_FRAMES = 5
PANEL_TITLES = {"raw": "raw replay", "refined": "refined"}
#: A panel's default size: large enough for the fingers and contact arrows to be seen.
PANEL_SIZE = (640, 480)
CAPTION_LINES = 2


@dataclass(frozen=True)
class CameraSpec:
    """A free camera: look at ``lookat`` from ``distance`` at ``azimuth`` / ``elevation`` (degrees), or a camera
    of the model by ``name``. ``track``: a look-at point per frame (F, 3) instead of ``lookat`` (the close-up)."""

    lookat: tuple[float, float, float] = (0.0, 0.0, 0.0)
    distance: float = 0.5
    azimuth: float = 135.0
    elevation: float = -25.0
    name: str | None = None
    track: FloatArray | None = field(default=None, compare=False)


DEFAULT_AZIMUTH = 135.0


def auto_camera(playback: Playback, azimuth: float | None = None, elevation: float = -25.0,
                size: tuple[int, int] = PANEL_SIZE, close_up: bool = False) -> CameraSpec:
    """Frame the interaction over the whole sequence in panels of ``size`` (width, height): the recorded and
    simulated object (every part, its whole geometry) and the recorded and simulated hands in the frames where they
    are within ``NEAR_OBJECT_M`` of it (a hand still far away would shrink everything), fitted to the image below the
    caption (``framing.fit_view``). ``close_up``: the object and the hand keypoints within ``CLOSE_UP_NEAR_M`` of it,
    the camera following the recorded object. ``azimuth`` None: ``DEFAULT_AZIMUTH`` for one hand; with two, the view
    across the line between them nearest to it (``two_hand_azimuth``)."""
    from worker.visual.framing import fit_view

    # The close-up leaves out the simulated objects: it is about the grasp of the recorded one (a raw replay's
    # dropped object would widen it to the fall).
    objects, hands = framing_points(playback, CLOSE_UP_NEAR_M if close_up else NEAR_OBJECT_M, whole_hand=not close_up,
                                    simulated_objects=not close_up)
    if azimuth is None:
        azimuth = two_hand_azimuth(hands)
    width, height = size
    fovy, band = float(playback.scene.model.vis.global_.fovy), caption_band(height) / height
    track = None
    if close_up:
        track = _smoothed(playback.part_poses_ref[:, 0, :3], CLOSE_UP_SMOOTHING_FRAMES)
        objects = objects - track[:, None, :]
        hands = {side: kp - track[:, None, :] for side, kp in hands.items()}
    cloud = np.concatenate([objects.reshape(-1, 3), *(h.reshape(-1, 3) for h in hands.values())])
    view = fit_view(cloud, azimuth, elevation, fovy, width / height, band)
    lookat = tuple(float(v) for v in view.lookat)
    if track is not None:
        track = track + view.lookat
        lookat = tuple(float(v) for v in track[0])
    return CameraSpec(lookat, view.distance, view.azimuth, view.elevation, track=track)  # type: ignore[arg-type]


def framing_points(playback: Playback, near_m: float, whole_hand: bool,
                   simulated_objects: bool = True) -> tuple[FloatArray, dict[str, FloatArray]]:
    """What the automatic camera frames: (F, N, 3) the corners of every object geom's box where the recording (and
    with ``simulated_objects`` each re-simulated trajectory) has the object, and per hand (F, K, 3) its recorded and
    simulated keypoints near the object (within ``near_m`` of a part's box in that frame; ``whole_hand``: every
    keypoint of a frame where one is), NaN elsewhere."""
    model, scene = playback.scene.model, playback.scene
    ref = playback.part_poses_ref  # (F, P, 7)
    boxes = _part_boxes(model, scene, ref.shape[1])
    objects = [_transform(corners, ref[:, k]) for k, corners in enumerate(boxes)]
    if simulated_objects:
        objects += [_transform(boxes[0], t.object_pose) for t in playback.trajectories.values()]
    lo_hi = [(c.min(axis=0), c.max(axis=0)) for c in boxes]
    hands: dict[str, FloatArray] = {}
    for side, kp_ref in playback.keypoints_ref.items():
        simulated = [t.keypoints[side] for t in playback.trajectories.values() if side in t.keypoints]
        kp = np.concatenate([kp_ref, *simulated], axis=1)
        dist = np.min([_box_distance(kp, ref[:, k], lo, hi) for k, (lo, hi) in enumerate(lo_hi)], axis=0)  # (F, K)
        near = dist <= near_m
        if whole_hand:
            near = np.repeat(near.any(axis=1, keepdims=True), kp.shape[1], axis=1)
        hands[side] = np.where(near[..., None], kp, np.nan)
    return np.concatenate(objects, axis=1), hands


def _part_boxes(model: mujoco.MjModel, scene: object, parts: int) -> list[FloatArray]:
    """Per part, the corners (M, 3) of its geoms' bounding boxes in the part's body frame."""
    geom_part = getattr(scene, "geom_part", np.zeros(0))
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    corners: list[list[FloatArray]] = [[] for _ in range(parts)]
    for g in getattr(scene, "object_geom_ids", []):
        g = int(g)
        part = max(int(geom_part[g]), 0) if len(geom_part) else 0
        centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        local = centre + signs * half
        corners[min(part, parts - 1)].append(model.geom_pos[g] + local @ _quat_mat(model.geom_quat[g]).T)
    return [np.concatenate(c) if c else np.zeros((1, 3)) for c in corners]


def _transform(local: FloatArray, poses: FloatArray) -> FloatArray:
    """(F, M, 3): ``local`` points (M, 3) at each of ``poses`` (F, 7: x y z qw qx qy qz)."""
    return np.einsum("fij,mj->fmi", _quat_mats(poses[:, 3:]), local) + poses[:, None, :3]


def _box_distance(points: FloatArray, poses: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """(F, K) distance of ``points`` (F, K, 3) to the box ``lo``..``hi`` of a body at ``poses`` (F, 7)."""
    local = np.einsum("fji,fkj->fki", _quat_mats(poses[:, 3:]), points - poses[:, None, :3])
    outside = np.maximum(np.maximum(lo - local, local - hi), 0.0)
    dist = np.linalg.norm(outside, axis=2)
    return np.where(np.isfinite(dist), dist, np.inf)


def _quat_mats(quats: FloatArray) -> FloatArray:
    """(F, 3, 3) rotation matrices of unit quaternions (F, 4) wxyz."""
    q = np.asarray(quats, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)  # fmt: skip


def _smoothed(track: FloatArray, frames: int) -> FloatArray:
    """``track`` (F, 3) averaged over a window of ``frames`` (shorter at the ends)."""
    half = frames // 2
    return np.stack([track[max(i - half, 0): i + half + 1].mean(axis=0) for i in range(len(track))])


def two_hand_azimuth(near_points: dict[str, FloatArray], preferred: float = DEFAULT_AZIMUTH) -> float:
    """The azimuth (deg) looking across the horizontal line between two hands' points nearest to ``preferred``
    (``preferred`` itself for one hand, or hands less than 2 cm apart seen from above)."""
    finite = [p.reshape(-1, 3) for p in near_points.values()]
    centres = [p[np.isfinite(p).all(axis=1)].mean(axis=0) for p in finite if np.isfinite(p).all(axis=1).any()]
    if len(centres) != 2:
        return preferred
    d = centres[1] - centres[0]
    if float(np.hypot(d[0], d[1])) < 0.02:
        return preferred
    line = float(np.degrees(np.arctan2(d[1], d[0])))
    # MuJoCo's free camera looks along (cos az, sin az) horizontally: across the line is the line's angle +- 90.
    return min((line + 90.0, line - 90.0), key=lambda a: abs((a - preferred + 180.0) % 360.0 - 180.0)) % 360.0


def parse_camera(text: str, playback: Playback, size: tuple[int, int] = PANEL_SIZE,
                 close_up: bool = False) -> CameraSpec:
    """``auto``, a camera name of the model, ``AZIMUTH,ELEVATION`` (auto framing from there) or
    ``AZIMUTH,ELEVATION,DISTANCE[,X,Y,Z]`` (degrees, metres); the automatic framing for panels of ``size``, a
    close-up with ``close_up`` (``auto_camera``)."""
    text = text.strip()
    if text in ("", "auto"):
        return auto_camera(playback, size=size, close_up=close_up)
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        model = playback.scene.model
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, text) < 0:
            raise ValueError(f"--camera {text!r}: not 'auto', numbers, or a camera of the scene") from None
        return CameraSpec(name=text)
    base = auto_camera(playback, values[0], values[1], size, close_up) if len(values) >= 2 else None
    if len(values) == 2 and base is not None:
        return base
    if len(values) in (3, 6) and base is not None:
        lookat = tuple(values[3:6]) if len(values) == 6 else base.lookat
        return CameraSpec(lookat, values[2], values[0], values[1])  # type: ignore[arg-type]
    raise ValueError(f"--camera {text!r}: give AZIMUTH,ELEVATION or AZIMUTH,ELEVATION,DISTANCE[,X,Y,Z]")


class PanelRenderer:
    """Draws panels of one playback; owns one ``mujoco.Renderer`` (close it, or use as a context manager)."""

    def __init__(self, playback: Playback, width: int = PANEL_SIZE[0], height: int = PANEL_SIZE[1],
                 camera: CameraSpec | None = None, samples: int | None = None):
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
        self.camera = camera or auto_camera(playback, size=(width, height))
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
        if self.camera.track is not None and isinstance(self._cam, mujoco.MjvCamera):
            self._cam.lookat[:] = self.camera.track[frame]
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
    size = _caption_font_size(image.shape[0])
    font = ImageFont.load_default(size=size)
    band = caption_band(image.shape[0], len(lines))
    draw.rectangle((0, 0, image.shape[1], band), fill=(20, 20, 20))
    for i, line in enumerate(lines):
        draw.text((5, 3 + i * (size + 4)), line, fill=(240, 240, 240), font=font)
    return np.asarray(pil, dtype=np.uint8)


def _caption_font_size(height: int) -> int:
    return max(10, height // 20)


def caption_band(height: int, lines: int = CAPTION_LINES) -> int:
    """The height in pixels of the caption's band at the top of a panel ``height`` pixels high."""
    return (_caption_font_size(height) + 4) * lines + 4


def render_frames(
    playback: Playback,
    which: Sequence[str] | None = None,
    width: int = PANEL_SIZE[0],
    height: int = PANEL_SIZE[1],
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
    width: int = PANEL_SIZE[0],
    height: int = PANEL_SIZE[1],
    camera: CameraSpec | None = None,
    samples: int | None = None,
) -> int:
    """Write every frame of ``which`` side by side to the MP4 ``out`` at the sequence's frame rate; returns
    the number of frames. ``samples`` as for ``PanelRenderer``."""
    from worker.visual.video import write_mp4

    return write_mp4(render_frames(playback, which, width, height, camera, samples=samples), out, playback.fps)
