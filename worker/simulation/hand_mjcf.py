"""MJCF of the built-in hand, generated from a ``HandGeometry`` (DESIGN §1.1, §1.4).

The palm is a free body welded to a mocap body (``{side}_mocap``); 15 capsule segments with 3 hinges per joint
(named ``{side}_{HINGE_NAMES[i]}``), position servos with the same names, and sites ``{side}_kp{j}`` at the
21 keypoints, each with a ``framepos`` sensor ``{side}_kp{j}``. The body chain reproduces
``hand_model.finger_kinematics`` exactly (MuJoCo composes a body's hinges in order: R = R_body·R0·R1·R2).
A body listed in ``HandGeometry.part_meshes`` (the MANO hand's per-part convex hulls) gets a mesh geom of the
same name instead of its box/capsule (assets from ``hand_asset_xml``); bodies, hinges, sites, actuators and
sensors are the same either way, so the refinement, contacts and metrics do not see the difference.
"""

from __future__ import annotations

import numpy as np

from common.geometry import FloatArray, matrix_to_quat
from worker.hand.model import (
    AXIS_VECTORS,
    FINGER_BASE_KEYPOINT,
    FINGERS,
    HINGE_AXES,
    HINGE_NAMES,
    JOINT_LIMITS,
    HandGeometry,
)
from worker.simulation.config import HAND_BIT, OBJECT_BIT, SimConfig


def fmt(values: FloatArray | list[float] | tuple[float, ...]) -> str:
    """Space-separated numbers for MJCF attributes."""
    return " ".join(f"{float(v):.9g}" for v in np.ravel(values))




def segment_body_name(side: str, finger: int, segment: int) -> str:
    return f"{side}_{FINGERS[finger]}{segment + 1}"


def hand_body_names(side: str) -> list[str]:
    """Palm first, then the 15 segments finger-major."""
    return [f"{side}_palm"] + [segment_body_name(side, f, j) for f in range(5) for j in range(3)]


def mesh_asset_name(side: str, part: str) -> str:
    return f"{side}_{part}_hull"


def hand_asset_xml(geometry: HandGeometry) -> str:
    """``<mesh>`` assets of the hand's part hulls ("" for a capsule hand). Vertices only: MuJoCo takes their
    convex hull for collision and for the mass/inertia from ``hand_density``."""
    return "\n".join(
        f'<mesh name="{mesh_asset_name(geometry.side, part)}" vertex="{fmt(verts)}"/>'
        for part, verts in geometry.part_meshes.items()
    )


def _part_geom(geometry: HandGeometry, part: str, common: str) -> str | None:
    """The mesh geom of body ``part`` when the geometry has its hull; the geom keeps the body's name."""
    if part not in geometry.part_meshes:
        return None
    side = geometry.side
    return f'<geom name="{side}_{part}" type="mesh" mesh="{mesh_asset_name(side, part)}" {common}/>'


def hand_worldbody_xml(geometry: HandGeometry, config: SimConfig, wrist_pos: FloatArray, wrist_quat: FloatArray) -> str:
    """The mocap body and the hand's body tree, placed at the given wrist pose."""
    side = geometry.side
    s = geometry.scale
    gc = ' gravcomp="1"' if config.hand_gravcomp else ""
    geom_common = (
        f'contype="{HAND_BIT}" conaffinity="{OBJECT_BIT}" condim="{config.hand_condim}" '
        f'friction="{fmt(config.hand_friction)}" solref="{fmt(config.contact_solref)}" '
        f'solimp="{fmt(config.contact_solimp)}" density="{config.hand_density:g}" group="1"'
    )
    pose = f'pos="{fmt(wrist_pos)}" quat="{fmt(wrist_quat)}"'
    lines = [f'<body name="{side}_mocap" mocap="true" {pose}/>']
    lines.append(f'<body name="{side}_palm" {pose}{gc}>')
    lines.append(f'  <freejoint name="{side}_root"/>')
    # Palm: a box spanning wrist -> knuckles and index -> pinky (metacarpals), palm thickness from anthropometry.
    knuckles = geometry.bases[1:]
    x0, x1 = 0.1 * float(np.linalg.norm(knuckles[2])), float(knuckles[:, 0].mean())
    # Each side of the box reaches past the outermost knuckle by that finger's own radius (index on one side,
    # pinky on the other; which is which depends on the hand side, so a left palm mirrors the right one).
    lo, hi = int(np.argmin(knuckles[:, 1])), int(np.argmax(knuckles[:, 1]))
    y0 = float(knuckles[lo, 1]) - float(geometry.radii[1 + lo, 0])
    y1 = float(knuckles[hi, 1]) + float(geometry.radii[1 + hi, 0])
    half = [(x1 - x0) / 2, (y1 - y0) / 2, geometry.palm_half_thickness]
    centre = [(x0 + x1) / 2, (y0 + y1) / 2, 0.0]
    box = f'<geom name="{side}_palm" type="box" size="{fmt(half)}" pos="{fmt(centre)}" {geom_common}/>'
    lines.append("  " + (_part_geom(geometry, "palm", geom_common) or box))
    lines.append(f'  <site name="{side}_kp0" pos="0 0 0" size="{0.004 * s:.4g}"/>')
    distal_ends = geometry.distal_capsule_ends()
    for f in range(5):
        base_kp = FINGER_BASE_KEYPOINT[f]
        indent = "  "
        for j in range(3):
            name = segment_body_name(side, f, j)
            if j == 0:
                where = f'pos="{fmt(geometry.bases[f])}" quat="{fmt(matrix_to_quat(geometry.rest_rot[f]))}"'
            else:
                where = f'pos="{fmt([geometry.lengths[f, j - 1], 0, 0])}"'
            lines.append(f'{indent}<body name="{name}" {where}{gc}>')
            for h in range(3):
                k = 9 * f + 3 * j + h
                lo, hi = JOINT_LIMITS[k]
                lines.append(
                    f'{indent}  <joint name="{side}_{HINGE_NAMES[k]}" type="hinge" axis="{fmt(AXIS_VECTORS[h])}" '
                    f'range="{lo:.6g} {hi:.6g}" armature="{config.hinge_armature:g}" '
                    f'damping="{config.hinge_damping:g}"/>'
                )
            length, radius = float(geometry.lengths[f, j]), float(geometry.radii[f, j])
            end = float(distal_ends[f]) if j == 2 else length  # HandGeometry.distal_capsule_ends
            hull = _part_geom(geometry, f"{FINGERS[f]}{j + 1}", geom_common)
            lines.append(
                f"{indent}  "
                + (hull or f'<geom name="{name}" type="capsule" fromto="0 0 0 {end:.6g} 0 0" size="{radius:.6g}" '
                   f"{geom_common}/>")
            )  # fmt: skip
            lines.append(f'{indent}  <site name="{side}_kp{base_kp + j}" pos="0 0 0" size="{0.003 * s:.4g}"/>')
            if j == 2:
                lines.append(
                    f'{indent}  <site name="{side}_kp{base_kp + 3}" pos="{length:.6g} 0 0" size="{0.003 * s:.4g}"/>'
                )
            indent += "  "
        for j in reversed(range(3)):
            lines.append("  " * (j + 1) + "</body>")
    lines.append("</body>")
    return "\n".join(lines)


def hand_actuator_xml(side: str, config: SimConfig) -> str:
    """45 position servos in HINGE_NAMES order, control range = joint range."""
    out = []
    for k, hinge in enumerate(HINGE_NAMES):
        lo, hi = JOINT_LIMITS[k]
        out.append(
            f'<position name="{side}_{hinge}" joint="{side}_{hinge}" kp="{config.finger_kp:g}" '
            f'kv="{config.finger_kv:g}" ctrlrange="{lo:.6g} {hi:.6g}"/>'
        )
    return "\n".join(out)


def hand_equality_xml(side: str, config: SimConfig) -> str:
    """Weld the palm to its mocap body with identity relative pose (DESIGN §1.4 weld solref/solimp)."""
    return (
        f'<weld name="{side}_wrist" body1="{side}_mocap" body2="{side}_palm" relpose="0 0 0 1 0 0 0" '
        f'solref="{fmt(config.weld_solref)}" solimp="{fmt(config.weld_solimp)}"/>'
    )


def hand_sensor_xml(side: str) -> str:
    """framepos sensors of the 21 keypoint sites (world frame), in keypoint order."""
    return "\n".join(f'<framepos name="{side}_kp{j}" objtype="site" objname="{side}_kp{j}"/>' for j in range(21))


def hand_mjcf(geometry: HandGeometry, config: SimConfig | None = None) -> str:
    """A standalone MJCF document holding only this hand (for inspection and tests)."""
    config = config or SimConfig()
    side = geometry.side
    return f"""<mujoco model="hoi-refine-hand-{side}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{config.timestep:.9g}" integrator="{config.integrator}"/>
  <asset>
{hand_asset_xml(geometry)}
  </asset>
  <worldbody>
{hand_worldbody_xml(geometry, config, np.zeros(3), np.array([1.0, 0, 0, 0]))}
  </worldbody>
  <equality>{hand_equality_xml(side, config)}</equality>
  <actuator>
{hand_actuator_xml(side, config)}
  </actuator>
  <sensor>
{hand_sensor_xml(side)}
  </sensor>
</mujoco>
"""


__all__ = [
    "HINGE_AXES", "fmt", "hand_asset_xml", "hand_body_names", "hand_mjcf", "matrix_to_quat", "mesh_asset_name",
    "segment_body_name",
]  # fmt: skip
