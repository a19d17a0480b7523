"""The MuJoCo scene: hand(s) + object + table with the paper's settings (DESIGN §1.4).

``build_scene(seq, references, config)`` compiles one ``MjModel`` and returns a ``Scene`` with index handles,
so callers never look names up in loops:

* per hand (``scene.hands[side]``): ``actuator_ids`` (H,) and ``qpos_adr`` / ``dof_adr`` (H,) of its actuated
  joints in control order (H = 45 hinges in HINGE_NAMES order for the human hand, a robot's own joints otherwise:
  ``worker.simulation.hand_fragment``), ``q_limits`` (H, 2), ``mocap_id``, ``root_qpos_adr`` (root free joint),
  ``keypoint_site_ids`` (J,), ``keypoint_sensor_adr`` (J,) into ``sensordata`` (framepos, world) and
  ``keypoint_ids`` (J,) which of the 21 human keypoints each stands for (all 21 in order for the human hand),
  ``body_ids`` / ``body_names`` (the root ``{side}_palm`` first, then every body under it),
  ``penetration_sensor_adr`` (the hand's deepest object contact, ``penetration_sensor_xml``);
* object: ``object_body_id``, ``object_qpos_adr`` (7 values from there: pos, quat wxyz), ``object_dof_adr``
  (6: linear world, angular *body* frame — MuJoCo's free-joint convention), ``object_geom_ids``,
  ``object_sensor_adr`` (13 values from there: framepos 3, framequat 4, framelinvel 3, frameangvel 3, world);
* ``substeps_per_frame``; ``object_init_pose`` (7,) the frame-0 pose used (the recorded frame 0 or the rest
  pose, ``worker.simulation.rest_pose``) and ``table`` the plane under it (``worker.simulation.table_fit``);
* an articulated object (``common.articulation``): ``object_part_body_ids`` (P,) base first and
  ``object_part_names``, ``object_joint_qpos_adr`` / ``object_joint_dof_adr`` (J,), ``object_joint_kinds``,
  ``object_articulation_sensor_adr`` (J ``jointpos`` values from there), ``object_part_sensor_adr`` (per part
  beyond the base 7 values: framepos 3, framequat 4 of its body frame), ``object_init_articulation`` (J,) the
  recorded frame-0 values it starts from, and ``geom_part`` (ngeom,) the part of each object geom (-1 elsewhere);
  a rigid object has one part and none of the rest (sensor addresses -1);
* ``object_hold_eq``: the weld ``object_hold`` that holds the object at ``object_init_pose`` (inactive in the
  model; -1 when there is none) and ``object_release_frame``: it is active on the steps before that frame
  (``SimConfig.hold_until_m``, ``SimConfig.unsupported_drift``; ``hold_active``).

Collisions: hand geoms collide with object geoms only, object geoms with hand and table (contype/conaffinity
bits in ``sim_config``). Sensors make ``mujoco.rollout`` recordings self-sufficient.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from common.geometry import FloatArray, IntArray
from common.primitive_surface import posed_surface_points
from common.sequence import Sequence
from worker.hand.reference import HandReference
from worker.simulation.config import SimConfig
from worker.simulation.hand_fragment import HandFragment, hand_fragment
from worker.simulation.object_model import (
    OBJECT_BODY,
    OBJECT_HOLD,
    OBJECT_JOINT,
    joint_name,
    object_hold_xml,
    object_mjcf,
    part_body_name,
)
from worker.simulation.rest_pose import moved_frame, rest_pose, resting_frames
from worker.simulation.support_plane import SupportPlane
from worker.simulation.table_fit import TableChoice, TableFit, fit_table, option_xml, table_geom_xml

__all__ = ["HandHandles", "Scene", "SimConfig", "build_scene"]


@dataclass(frozen=True)
class HandHandles:
    """Indices of one hand inside the compiled model (see the module docstring)."""

    side: str
    actuator_ids: IntArray
    qpos_adr: IntArray
    dof_adr: IntArray
    mocap_id: int
    palm_body_id: int
    root_qpos_adr: int
    root_dof_adr: int
    keypoint_site_ids: IntArray
    keypoint_sensor_adr: IntArray
    body_ids: IntArray
    body_names: tuple[str, ...]
    #: (J,) which human keypoint (``common.sequence.JOINT_NAMES``) each keypoint site stands for.
    keypoint_ids: IntArray = field(default_factory=lambda: np.arange(21))
    #: (H, 2) the actuated joints' ranges (the servos' control ranges).
    q_limits: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    #: sensordata index of ``{side}_penetration``: the signed distance of the hand's deepest contact with the
    #: object (<= 0 while penetrating, 0 without a contact), read by the refinement's penetration loss.
    penetration_sensor_adr: int = -1


@dataclass
class Scene:
    """A compiled scene and its index handles. ``xml`` is the MJCF it was compiled from."""

    model: mujoco.MjModel
    config: SimConfig
    fps: float
    substeps_per_frame: int
    hands: dict[str, HandHandles]
    object_body_id: int
    object_qpos_adr: int
    object_dof_adr: int
    object_geom_ids: IntArray
    object_sensor_adr: int
    table_geom_id: int
    object_init_pose: FloatArray
    table: SupportPlane
    object_collision: str
    xml: str
    body_side: dict[int, str] = field(default_factory=dict)
    object_hold_eq: int = -1
    object_release_frame: int = 0
    #: How far the object drifts on its table when simulated alone (``table_fit.TableFit.drift``).
    table_drift: float = 0.0
    #: The table fit whole: its candidates and their scores, and which one the scene stands on.
    table_fit: TableFit | None = None
    object_part_body_ids: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    object_part_names: tuple[str, ...] = ()
    object_joint_qpos_adr: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    object_joint_dof_adr: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    object_joint_kinds: tuple[str, ...] = ()
    object_articulation_sensor_adr: int = -1
    object_part_sensor_adr: int = -1
    object_init_articulation: FloatArray = field(default_factory=lambda: np.zeros(0))
    geom_part: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def articulated(self) -> bool:
        return len(self.object_joint_qpos_adr) > 0

    @property
    def sides(self) -> tuple[str, ...]:
        return tuple(self.hands)

    def make_data(self) -> mujoco.MjData:
        return mujoco.MjData(self.model)

    def table_summary(self) -> dict[str, Any]:
        """The result's ``table``: the plane, and the fit's candidate with the start pose and its drift
        (``TableFit.to_summary``; ``verify`` builds its scene on them, ``TableChoice.from_summary``)."""
        return self.table.to_dict() if self.table_fit is None else self.table_fit.to_summary()

    def hold_summary(self) -> dict[str, Any]:
        """The result's ``object_hold``: the frame the hold ends (0: none) and whether it lasts until the recording
        moves the object because no table holds it (``SimConfig.unsupported_drift``). Not the drift itself: a
        simulated quantity whose last bits differ between hosts, where these two facts do not."""
        release = self.hold_release_frame
        unsupported = release > 0 and self.config.unsupported(self.table_drift)
        return {"release_frame": release, "until_recording_moves": unsupported}

    @property
    def hold_release_frame(self) -> int:
        """The frame the object's hold ends (0 without a hold)."""
        return int(self.object_release_frame) if self.object_hold_eq >= 0 else 0

    def hold_active(self, steps: np.ndarray) -> np.ndarray:
        """Whether the object is held on each of these physics steps (``held_steps``; never without a hold)."""
        return held_steps(steps, self.hold_release_frame, self.substeps_per_frame)


def held_steps(steps: np.ndarray, release_frame: int, substeps_per_frame: int) -> np.ndarray:
    """The object's hold schedule, one definition for every rollout path: held on every physics step before
    ``release_frame``'s (step k takes frame k // substeps_per_frame towards the next)."""
    return np.asarray(steps) < release_frame * substeps_per_frame


def _ids(model: mujoco.MjModel, kind: mujoco.mjtObj, names: list[str]) -> IntArray:
    out = np.array([mujoco.mj_name2id(model, kind, n) for n in names], dtype=np.int64)
    missing = [n for n, i in zip(names, out, strict=True) if i < 0]
    if missing:
        raise RuntimeError(f"scene is missing {missing[:3]}")
    return out


def hand_handles(model: mujoco.MjModel, fragment: HandFragment) -> HandHandles:
    """One hand's handles, found by the names its fragment promises (``worker.simulation.hand_fragment``)."""
    s = fragment.side
    names = [f"{s}_{h}" for h in fragment.joint_names]
    joint_ids = _ids(model, mujoco.mjtObj.mjOBJ_JOINT, names)
    palm = int(_ids(model, mujoco.mjtObj.mjOBJ_BODY, [f"{s}_palm"])[0])
    # The root first, then its subtree in model order (for the human hand: palm, then the 15 segments).
    body_ids = np.array([palm] + [b for b in range(palm + 1, model.nbody) if _under(model, b, palm)], dtype=np.int64)
    mocap_body = int(_ids(model, mujoco.mjtObj.mjOBJ_BODY, [f"{s}_mocap"])[0])
    root = int(_ids(model, mujoco.mjtObj.mjOBJ_JOINT, [f"{s}_root"])[0])
    kp_names = [f"{s}_kp{j}" for j in range(len(fragment.keypoint_ids))]
    sensors = _ids(model, mujoco.mjtObj.mjOBJ_SENSOR, kp_names)
    penetration = int(_ids(model, mujoco.mjtObj.mjOBJ_SENSOR, [f"{s}_penetration"])[0])
    return HandHandles(
        side=s,
        actuator_ids=_ids(model, mujoco.mjtObj.mjOBJ_ACTUATOR, names),
        qpos_adr=model.jnt_qposadr[joint_ids].astype(np.int64),
        dof_adr=model.jnt_dofadr[joint_ids].astype(np.int64),
        mocap_id=int(model.body_mocapid[mocap_body]),
        palm_body_id=palm,
        root_qpos_adr=int(model.jnt_qposadr[root]),
        root_dof_adr=int(model.jnt_dofadr[root]),
        keypoint_site_ids=_ids(model, mujoco.mjtObj.mjOBJ_SITE, kp_names),
        keypoint_sensor_adr=model.sensor_adr[sensors].astype(np.int64),
        body_ids=body_ids,
        body_names=tuple(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(b)) or "" for b in body_ids),
        keypoint_ids=np.asarray(fragment.keypoint_ids, dtype=np.int64),
        q_limits=np.asarray(fragment.q_limits, dtype=np.float64),
        penetration_sensor_adr=int(model.sensor_adr[penetration]),
    )


def _under(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False


def penetration_sensor_xml(side: str) -> str:
    """A contact sensor over the hand's contacts with the object's base body (``body2``: of an articulated object,
    not the parts below it, which a hand must press to move them): the smallest signed distance among them.

    MuJoCo reduces the step's contacts in C while it computes its sensors, so every batched rollout records the
    hand's deepest penetration per substep in its sensordata, without Python walking ``data.contact``; it reads
    nothing back into the physics (with it, dev40's refinements took the same steps to the same figures).
    """
    return (f'<contact name="{side}_penetration" subtree1="{side}_palm" body2="{OBJECT_BODY}" data="dist" '
            'reduce="mindist" num="1"/>')


def articulation_sensor_xml(n_parts: int) -> list[str]:
    """An articulated object's sensors (none for a rigid one): every joint's value, then every further part's
    body-frame position and orientation (the refinement's part-frame contact targets read them)."""
    values = [f'<jointpos name="object_arti{k}" joint="{joint_name(k)}"/>' for k in range(n_parts)]
    poses = [
        line
        for k in range(1, n_parts + 1)
        for line in (f'<framepos name="object_p{k}_pos" objtype="xbody" objname="{part_body_name(k)}"/>',
                     f'<framequat name="object_p{k}_quat" objtype="xbody" objname="{part_body_name(k)}"/>')
    ]  # fmt: skip
    return values + poses


def scene_xml(
    seq: Sequence,
    references: list[HandReference] | list[Any],
    config: SimConfig,
    start: tuple[FloatArray, SupportPlane],
    *,
    cache_dir: Path | None = None,
    hold: bool = False,
) -> tuple[str, str, int]:
    """The scene's MJCF, the object's collision method and its number of geoms. ``start``: the object's
    frame-0 pose and the table under it (``fit_table``'s); ``cache_dir``: where convex parts are cached;
    ``hold``: with the (inactive) weld ``object_hold`` of the object to the world at its frame-0 pose."""
    pose0, table = start
    obj = object_mjcf(seq.object, config, pose0[:3], pose0[3:], cache_dir=cache_dir)
    fragments = [hand_fragment(r, config) for r in references]
    xml = _scene_document(config, table, fragments, obj.assets, obj.body, object_hold_xml(config) if hold else "",
                          articulation_sensor_xml(len(seq.object.parts)))
    return xml, obj.collision, obj.num_geoms


def _scene_document(config: SimConfig, table: SupportPlane, fragments: list[HandFragment], object_assets: str,
                    object_body: str, object_equality: str, object_sensors: list[str]) -> str:
    """The scene MJCF from the hands' fragments and the object's parts."""
    sensors = [
        f'<framepos name="object_pos" objtype="body" objname="{OBJECT_BODY}"/>',
        f'<framequat name="object_quat" objtype="body" objname="{OBJECT_BODY}"/>',
        f'<framelinvel name="object_linvel" objtype="body" objname="{OBJECT_BODY}"/>',
        f'<frameangvel name="object_angvel" objtype="body" objname="{OBJECT_BODY}"/>',
    ] + [f.sensors for f in fragments] + [penetration_sensor_xml(f.side) for f in fragments]
    sensors += object_sensors
    return f"""<mujoco model="hoi-refine-scene">
  <compiler angle="radian" autolimits="true"/>
  {option_xml(config)}
  <size memory="8M"/>
  <asset>
{object_assets}
{chr(10).join(f.assets for f in fragments)}
  </asset>
  <worldbody>
    {table_geom_xml(config, table)}
{chr(10).join(f.worldbody for f in fragments)}
{object_body}
  </worldbody>
  <equality>
{chr(10).join(f.equality for f in fragments)}
{object_equality}
  </equality>
  <actuator>
{chr(10).join(f.actuators for f in fragments)}
  </actuator>
  <sensor>
{chr(10).join(sensors)}
  </sensor>
</mujoco>
"""


def build_scene(
    seq: Sequence, references: list[HandReference] | list[Any], config: SimConfig | None = None, *,
    cache_dir: Path | None = None, table: TableChoice | None = None,
) -> Scene:
    """Compile the scene for a sequence and its retargeted hands (one ``HandReference`` per hand). ``cache_dir``:
    where a mesh object's convex parts are cached on disk (None: memory only); ``table``: a result's stored table
    choice, stood on instead of the fit's own (``fit_table``'s ``choice``)."""
    config = config or SimConfig()
    if not references:
        raise ValueError("references must hold at least one HandReference")
    keypoints = [r.keypoints for r in references]
    poses = seq.object_pose_world()
    arti0 = initial_articulation(seq)
    surface = posed_surface_points(seq.object, arti0, config.primitive_surface_spacing_m)
    start = rest_pose(poses, surface, keypoints, config.rest_approach_m)
    release = resting_frames(poses, surface, keypoints, config.hold_until_m)  # 0 when there is no hold
    fit = fit_table(seq, config, start, cache_dir=cache_dir, articulation=arti0, choice=table)
    pose0, plane, drift = fit.pose, fit.plane, fit.drift
    if release > 0 and config.unsupported(drift):
        # No table holds the object as recorded (it leaned on something not simulated): released when the hand
        # comes near, it falls before the grasp forms, so it is held until the recording moves it, less the lead.
        lead = round(config.unsupported_lead_s * seq.fps)
        release = max(release, moved_frame(poses) - lead)
    xml, collision, ngeom = scene_xml(seq, references, config, (pose0, plane), cache_dir=cache_dir, hold=release > 0)
    model = mujoco.MjModel.from_xml_string(xml)
    hold_eq = int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, OBJECT_HOLD)) if release > 0 else -1
    hands: dict[str, HandHandles] = {}
    body_side: dict[int, str] = {}
    for fragment in (hand_fragment(r, config) for r in references):
        hands[fragment.side] = hand_handles(model, fragment)
        body_side.update({int(b): fragment.side for b in hands[fragment.side].body_ids})
    obj_joint = int(_ids(model, mujoco.mjtObj.mjOBJ_JOINT, [OBJECT_JOINT])[0])
    obj_sensor = int(_ids(model, mujoco.mjtObj.mjOBJ_SENSOR, ["object_pos"])[0])
    geom_ids = _ids(model, mujoco.mjtObj.mjOBJ_GEOM, [f"object_{i}" for i in range(ngeom)])
    obj = seq.object
    n_parts = len(obj.parts)
    part_bodies = _ids(model, mujoco.mjtObj.mjOBJ_BODY, [part_body_name(k) for k in range(n_parts + 1)])
    joints = _ids(model, mujoco.mjtObj.mjOBJ_JOINT, [joint_name(k) for k in range(n_parts)])
    geom_part = np.full(model.ngeom, -1, dtype=np.int64)
    body_part = {int(b): k for k, b in enumerate(part_bodies)}
    geom_part[geom_ids] = [body_part[int(model.geom_bodyid[g])] for g in geom_ids]
    arti_sensor = part_sensor = -1
    if n_parts:
        arti_sensor = int(model.sensor_adr[_ids(model, mujoco.mjtObj.mjOBJ_SENSOR, ["object_arti0"])[0]])
        part_sensor = int(model.sensor_adr[_ids(model, mujoco.mjtObj.mjOBJ_SENSOR, ["object_p1_pos"])[0]])
    return Scene(
        model=model,
        config=config,
        fps=float(seq.fps),
        substeps_per_frame=config.substeps_per_frame(seq.fps),
        hands=hands,
        object_body_id=int(_ids(model, mujoco.mjtObj.mjOBJ_BODY, [OBJECT_BODY])[0]),
        object_qpos_adr=int(model.jnt_qposadr[obj_joint]),
        object_dof_adr=int(model.jnt_dofadr[obj_joint]),
        object_geom_ids=geom_ids,
        object_sensor_adr=int(model.sensor_adr[obj_sensor]),
        table_geom_id=int(_ids(model, mujoco.mjtObj.mjOBJ_GEOM, ["table"])[0]),
        object_init_pose=pose0,
        table=plane,
        object_collision=collision,
        xml=xml,
        body_side=body_side,
        object_hold_eq=hold_eq,
        object_release_frame=release,
        table_drift=drift,
        table_fit=fit,
        object_part_body_ids=part_bodies,
        object_part_names=tuple(obj.part_names),
        object_joint_qpos_adr=model.jnt_qposadr[joints].astype(np.int64),
        object_joint_dof_adr=model.jnt_dofadr[joints].astype(np.int64),
        object_joint_kinds=tuple(j.kind for j in obj.joints),
        object_articulation_sensor_adr=arti_sensor,
        object_part_sensor_adr=part_sensor,
        object_init_articulation=arti0 if arti0 is not None else np.zeros(0),
        geom_part=geom_part,
    )


def initial_articulation(seq: Sequence) -> FloatArray | None:
    """The recorded frame-0 joint values, within the limits (None for a rigid object)."""
    if not seq.object.parts:
        return None
    assert seq.articulation is not None
    limits = np.array([j.limits for j in seq.object.joints], dtype=np.float64)
    return np.clip(seq.articulation[0], limits[:, 0], limits[:, 1])

