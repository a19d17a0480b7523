"""A small robot hand the tests write themselves (issue #55): an MJCF model and its hand description.

Human-sized and human-shaped, so the built-in example's grasp (synthesised for the built-in human hand) fits it:
the template hand's palm, finger bases, rest frames, segment lengths and capsule radii
(``worker.hand.model.default_geometry``), but a robot's joints: 4 per finger (MCP abduction and flexion, PIP and
DIP flexion; the thumb's CMC abduction and flexion, MCP and IP flexion), 20 in all, no twists. Its keypoint sites
are where the human hand's keypoints are (the fingertip at the end of the distal capsule)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from common.geometry import matrix_to_quat
from worker.hand.model import FINGERS, JOINT_LIMITS, default_geometry

#: (joint, hinge) of each finger's 4 joints, in HINGE_NAMES terms: axis 0 abduction (z), 1 flexion (-y).
HINGES = ((0, 0), (0, 1), (1, 1), (2, 1))
AXES = {0: "0 0 1", 1: "0 -1 0"}
JOINTS = [f"{f}_{n}" for f in FINGERS for n in ("abd", "flex1", "flex2", "flex3")]


def _fmt(values: Any) -> str:
    return " ".join(f"{float(v):.6g}" for v in np.ravel(values))


def model_xml() -> str:
    g = default_geometry("right")
    knuckles = g.bases[1:]
    x0, x1 = 0.1 * float(np.linalg.norm(knuckles[2])), float(knuckles[:, 0].mean())
    y0 = float(knuckles[:, 1].min()) - float(g.radii[1:, 0].max())
    y1 = float(knuckles[:, 1].max()) + float(g.radii[1:, 0].max())
    palm = (f'<geom name="palm" type="box" size="{_fmt([(x1 - x0) / 2, (y1 - y0) / 2, g.palm_half_thickness])}" '
            f'pos="{_fmt([(x0 + x1) / 2, (y0 + y1) / 2, 0])}"/>')
    fingers = []
    for f, finger in enumerate(FINGERS):
        names = ("abd", "flex1", "flex2", "flex3")
        xml, close = "", ""
        for j in range(3):
            where = (f'pos="{_fmt(g.bases[f])}" quat="{_fmt(matrix_to_quat(g.rest_rot[f]))}"' if j == 0
                     else f'pos="{_fmt([g.lengths[f, j - 1], 0, 0])}"')
            length, radius = float(g.lengths[f, j]), float(g.radii[f, j])
            end = float(g.distal_capsule_ends()[f]) if j == 2 else length
            joints = ""
            for k, (joint, hinge) in enumerate(HINGES):
                if joint == j:
                    lo, hi = JOINT_LIMITS[9 * f + 3 * joint + hinge]
                    joints += f'<joint name="{finger}_{names[k]}" axis="{AXES[hinge]}" range="{lo:.4g} {hi:.4g}"/>'
            mass = 1100 * np.pi * radius**2 * length
            xml += (f'<body name="{finger}{j + 1}" {where}><inertial pos="{length / 2:.4g} 0 0" mass="{mass:.4g}" '
                    f'diaginertia="{_fmt([mass * radius**2 / 2, mass * length**2 / 12, mass * length**2 / 12])}"/>'
                    f'{joints}<geom type="capsule" fromto="0 0 0 {end:.5g} 0 0" size="{radius:.5g}"/>')
            close += "</body>"
        fingers.append(xml + f'<body name="{finger}_tip" pos="{g.lengths[f, 2]:.5g} 0 0"/>' + close)
    return (f'<mujoco model="test_hand"><compiler angle="radian"/><worldbody><body name="base">'
            f'<inertial pos="0.04 0 0" mass="0.3" diaginertia="3e-4 3e-4 2e-4"/>{palm}{"".join(fingers)}'
            "</body></worldbody></mujoco>")


def description(model: str = "test_hand.xml") -> dict[str, Any]:
    keypoints: dict[str, Any] = {"wrist": {"body": "base"}}
    for finger in FINGERS:
        for k in (1, 2, 3):
            keypoints[f"{finger}{k}"] = {"body": f"{finger}{k}"}
        keypoints[f"{finger}4"] = {"body": f"{finger}_tip"}
    return {"name": "test-hand", "model": model, "joints": [{"name": j, "velocity": 8.0, "effort": 2.0}
                                                             for j in JOINTS],
            "keypoints": keypoints, "tip_radius": 0.008}


def write_robot_hand(folder: Path, **changes: Any) -> Path:
    """The model and its description (with ``changes`` applied) in ``folder``; returns the description's path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "test_hand.xml").write_text(model_xml())
    path = folder / "test_hand.json"
    path.write_text(json.dumps({**description(), **changes}))
    return path
