"""A hand description (``common.hand_description``) made concrete: read, resolved, packed and checked against the
compiled model (issue #55 item 1).

* ``read_description(spec, robot_dir)``: ``allegro`` / ``leap`` (the shipped correspondences,
  ``worker/robot/data/``, whose models lie under ``robot_dir``, a checkout of the public dex-urdf repository) or a
  JSON/YAML file of the user's;
* ``pack_description``: compiles the model (URDF or MJCF) and inlines it as ``model_xml`` (``canonical``);
* ``Embodiment.from_description``: a packed description compiled and checked, one side's (a left hand from a
  right model is its mirror image, ``canonical.mirror_xml``), with everything the rest of the pipeline reads:
  joint names and limits, servo gains, the keypoint sites and which of the 21 human keypoints each stands for.

Every problem raises ``HandDescriptionError`` naming the field (``hand.keypoints.thumb4.body`` ...).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import yaml

from common.errors import FieldProblem
from common.geometry import FloatArray
from common.hand_description import (
    BUILTIN_ROBOTS,
    HandDescription,
    HandDescriptionError,
    parse_hand_description,
)
from common.sequence import JOINT_NAMES, Side
from worker.robot.canonical import canonical_xml, compile_source, mirror_xml

DATA_DIR = Path(__file__).with_name("data")
#: Mirror of a position in a root-frame (y -> -y): the left hand's site offsets (``canonical.mirror_xml``).
MIRROR = np.array([1.0, -1.0, 1.0])


def read_description(spec: str | Path, robot_dir: Path | None = None) -> tuple[HandDescription, Path]:
    """The description ``spec`` names and the folder its ``model`` path is relative to: a shipped name
    (``BUILTIN_ROBOTS``, models under ``robot_dir``) or a JSON/YAML file (models relative to its folder)."""
    if str(spec) in BUILTIN_ROBOTS:
        if robot_dir is None:
            raise HandDescriptionError([FieldProblem(
                "hand", f"{spec} needs the robot models: pass --robot-dir or set HOI_REFINE_ROBOT_DIR to a checkout "
                "of the public dex-urdf repository")])
        path = DATA_DIR / f"{spec}.json"
        base = robot_dir
    else:
        path = Path(spec)
        base = path.parent
        if not path.is_file():
            raise HandDescriptionError([FieldProblem("hand", f"no such hand description file: {path} (or name one "
                                                     f"of {', '.join(BUILTIN_ROBOTS)})")])
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (OSError, ValueError, yaml.YAMLError) as exc:
        raise HandDescriptionError([FieldProblem("hand", f"cannot read {path.name}: {exc}")]) from None
    desc = parse_hand_description(data)
    if desc.model is not None and robot_dir is not None and not (base / desc.model).exists():
        base = robot_dir  # a user's file may name its model inside the robot folder too
    return desc, base


def pack_description(desc: HandDescription, base_dir: Path) -> HandDescription:
    """The packed form: the model compiled and written back as self-contained MJCF (``model_xml``), checked."""
    if desc.packed:
        packed = desc
    else:
        assert desc.model is not None
        path = (base_dir / desc.model).resolve()
        source = compile_source(path)
        xml = canonical_xml(source, desc.root_body)
        packed = urdf_velocity_limits(desc, path).model_copy(update={"model": None, "model_xml": xml})
    Embodiment.from_description(packed, packed.model_side)  # every name checked against the compiled model
    return packed


def resolve_hand(spec: str | Path | None, robot_dir: Path | None = None) -> HandDescription | None:
    """``--hand``'s value as a packed description (None or ``human``: the built-in human hand)."""
    if spec is None or str(spec) == "human":
        return None
    desc, base = read_description(spec, robot_dir)
    return pack_description(desc, base)


@dataclass
class Embodiment:
    """One side's robot hand, compiled and checked (see the module docstring). ``xml``: the canonical MJCF of that
    side (mirrored for the other side than the model's); ``keypoint_ids`` (J,): which of the 21 human keypoints
    each site stands for, in ``JOINT_NAMES`` order; ``site_bodies`` / ``site_pos``: where each site sits."""

    description: HandDescription
    side: Side
    xml: str
    root_body: str
    joint_names: tuple[str, ...]
    q_limits: FloatArray  # (H, 2)
    velocity_limits: FloatArray  # (H,) rad/s (inf: none known)
    effort_limits: FloatArray  # (H,) N·m (inf: none known)
    kp: float | None
    kv: float | None
    keypoint_ids: tuple[int, ...]
    site_bodies: tuple[str, ...]
    site_pos: FloatArray  # (J, 3) in each body's frame

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def fingertips(self) -> tuple[int, ...]:
        """Indices (into the sites) of the fingertips, thumb first."""
        return tuple(i for i, k in enumerate(self.keypoint_ids) if JOINT_NAMES[k].endswith("4"))

    @classmethod
    def from_description(cls, desc: HandDescription, side: Side) -> Embodiment:
        if desc.model_xml is None:
            raise HandDescriptionError([FieldProblem("hand.model", "pack the description first (pack_description)")])
        xml = desc.model_xml if side == desc.model_side else mirror_xml(desc.model_xml)
        try:
            model = mujoco.MjModel.from_xml_string(xml)
        except ValueError as exc:
            raise HandDescriptionError([FieldProblem("hand.model_xml", f"MuJoCo cannot compile it: {exc}")]) from None
        problems: list[FieldProblem] = []
        root = int(model.body_parentid.tolist().index(0, 1)) if model.nbody > 1 else -1
        root_name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, root) if root > 0 else None
        q_limits, velocity, effort = [], [], []
        for i, spec in enumerate(desc.joints):
            j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, spec.name)
            if j < 0:
                problems.append(FieldProblem(f"hand.joints.{i}.name", f"no joint named {spec.name!r} in the model"))
                continue
            if int(model.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
                problems.append(FieldProblem(f"hand.joints.{i}.name", f"joint {spec.name!r} is not a hinge or slide"))
            if spec.range is not None:
                lo, hi = spec.range
            elif model.jnt_limited[j]:
                lo, hi = (float(v) for v in model.jnt_range[j])
            else:
                problems.append(FieldProblem(f"hand.joints.{i}.range", f"joint {spec.name!r} has no limits in the "
                                             "model: give a range"))
                continue
            q_limits.append((lo, hi))
            velocity.append(spec.velocity or np.inf)
            frc = model.jnt_actfrcrange[j] if model.jnt_actfrclimited[j] else (-np.inf, np.inf)
            effort.append(spec.effort or float(max(abs(frc[0]), abs(frc[1]))))
        bodies, positions = [], []
        for name in desc.keypoint_order():
            site = desc.keypoints[name]
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, site.body)
            if b < 0:
                problems.append(FieldProblem(f"hand.keypoints.{name}.body",
                                             f"no body named {site.body!r} in the model"))
            elif not _in_subtree(model, b, root):
                problems.append(FieldProblem(f"hand.keypoints.{name}.body",
                                             f"body {site.body!r} is not part of the hand"))
            bodies.append(site.body)
            pos = np.asarray(site.pos, dtype=np.float64)
            positions.append(pos if side == desc.model_side else pos * MIRROR)
        if problems:
            raise HandDescriptionError(problems)
        assert root_name is not None
        return cls(
            description=desc, side=side, xml=xml, root_body=root_name,
            joint_names=tuple(j.name for j in desc.joints), q_limits=np.asarray(q_limits, dtype=np.float64),
            velocity_limits=np.asarray(velocity, dtype=np.float64), effort_limits=np.asarray(effort, dtype=np.float64),
            kp=desc.actuator.kp, kv=desc.actuator.kv,
            keypoint_ids=tuple(JOINT_NAMES.index(k) for k in desc.keypoint_order()),
            site_bodies=tuple(bodies), site_pos=np.asarray(positions, dtype=np.float64).reshape(-1, 3),
        )  # fmt: skip


def urdf_velocity_limits(desc: HandDescription, path: Path) -> HandDescription:
    """``desc`` with each joint's speed limit taken from the URDF's ``<limit velocity>`` where the description
    gives none (MuJoCo's compiler does not keep it)."""
    if path.suffix.lower() != ".urdf":
        return desc
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return desc
    speeds = {}
    for joint in root.iter("joint"):
        limit = joint.find("limit")
        if limit is not None and limit.get("velocity"):
            speeds[joint.get("name")] = float(limit.get("velocity", "0"))
    joints = [j if j.velocity is not None or not speeds.get(j.name)
              else j.model_copy(update={"velocity": speeds[j.name]}) for j in desc.joints]
    return desc.model_copy(update={"joints": joints})


def _in_subtree(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False

