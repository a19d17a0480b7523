"""A small robot hand the tests write themselves (issue #55): MJCF model and hand description, human-sized so the
built-in example's box fits its grasp. Five fingers of hinges on capsules, a box palm; the fingers point along the
palm's +z and flex towards +x, as Allegro's do."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def _finger(name: str, pos: str, lengths: tuple[float, float, float], abd: bool = True) -> str:
    l1, l2, l3 = lengths
    abd_joint = f'<joint name="{name}_abd" axis="1 0 0" range="-0.3 0.3"/>' if abd else ""
    return f"""
      <body name="{name}1" pos="{pos}">
        <inertial pos="0 0 {l1 / 2}" mass="0.02" diaginertia="4e-6 4e-6 1e-6"/>
        {abd_joint}
        <joint name="{name}_flex1" axis="0 1 0" range="-0.2 1.6"/>
        <geom type="capsule" fromto="0 0 0 0 0 {l1}" size="0.009"/>
        <body name="{name}2" pos="0 0 {l1}">
          <inertial pos="0 0 {l2 / 2}" mass="0.015" diaginertia="2e-6 2e-6 1e-6"/>
          <joint name="{name}_flex2" axis="0 1 0" range="0 1.7"/>
          <geom type="capsule" fromto="0 0 0 0 0 {l2}" size="0.008"/>
          <body name="{name}3" pos="0 0 {l2}">
            <inertial pos="0 0 {l3 / 2}" mass="0.01" diaginertia="1e-6 1e-6 5e-7"/>
            <joint name="{name}_flex3" axis="0 1 0" range="0 1.6"/>
            <geom type="capsule" fromto="0 0 0 0 0 {l3}" size="0.0075"/>
            <body name="{name}_tip" pos="0 0 {l3}"/>
          </body>
        </body>
      </body>"""


MODEL_XML = f"""<mujoco model="test_hand">
  <compiler angle="radian"/>
  <worldbody>
    <body name="base">
      <inertial pos="0 0 0.045" mass="0.2" diaginertia="2e-4 2e-4 1e-4"/>
      <geom name="palm" type="box" size="0.012 0.04 0.045" pos="0 0 0.045"/>
      {_finger("index", "0 0.03 0.09", (0.045, 0.028, 0.022))}
      {_finger("middle", "0 0.01 0.09", (0.048, 0.03, 0.023))}
      {_finger("ring", "0 -0.01 0.088", (0.045, 0.028, 0.022))}
      {_finger("pinky", "0 -0.03 0.083", (0.036, 0.022, 0.02))}
      {_finger("thumb", "0.02 0.045 0.025", (0.04, 0.032, 0.025), abd=True)}
    </body>
  </worldbody>
</mujoco>
"""

FINGERS = ("thumb", "index", "middle", "ring", "pinky")
JOINTS = [f"{f}_{j}" for f in FINGERS for j in ("abd", "flex1", "flex2", "flex3")]


def description(model: str = "test_hand.xml") -> dict[str, Any]:
    keypoints: dict[str, Any] = {"wrist": {"body": "base"}}
    for finger in FINGERS:
        for k in (1, 2, 3):
            keypoints[f"{finger}{k}"] = {"body": f"{finger}{k}"}
        keypoints[f"{finger}4"] = {"body": f"{finger}_tip", "pos": [0.0, 0.0, 0.0075]}  # the end of the cap
    return {"name": "test-hand", "model": model, "joints": [{"name": j, "velocity": 8.0, "effort": 2.0}
                                                             for j in JOINTS],
            "keypoints": keypoints, "tip_radius": 0.008}


def write_robot_hand(folder: Path, **changes: Any) -> Path:
    """The model and its description (with ``changes`` applied) in ``folder``; returns the description's path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "test_hand.xml").write_text(MODEL_XML)
    path = folder / "test_hand.json"
    path.write_text(json.dumps({**description(), **changes}))
    return path
