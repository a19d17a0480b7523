"""One hand's part of the scene MJCF, whatever the hand (issue #55): the built-in human hand's from
``hand_mjcf`` or a robot's (``worker.robot.fragment``). ``scene.scene_xml`` splices one per hand into the scene and
``scene.build_scene`` finds each hand's handles by the names a fragment promises:

* bodies: the root ``{side}_palm`` (free joint ``{side}_root``, welded to the mocap body ``{side}_mocap``) and
  the rest of the hand under it;
* actuated joints and their position servos, both named ``{side}_{joint}`` for ``joint_names`` (control order);
* keypoint sites with ``framepos`` sensors, both ``{side}_kp{j}`` for j < len(keypoint_ids), site j standing for
  human keypoint ``keypoint_ids[j]`` (``common.sequence.JOINT_NAMES``; the human hand has all 21 in order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import FloatArray
from worker.hand.model import HINGE_NAMES, JOINT_LIMITS
from worker.hand.reference import HandReference
from worker.simulation.config import SimConfig
from worker.simulation.hand_mjcf import (
    hand_actuator_xml,
    hand_asset_xml,
    hand_equality_xml,
    hand_sensor_xml,
    hand_worldbody_xml,
)

HUMAN_KEYPOINTS: tuple[int, ...] = tuple(range(21))


@dataclass(frozen=True)
class HandFragment:
    """MJCF pieces of one hand (see the module docstring)."""

    side: str
    assets: str
    worldbody: str
    equality: str
    actuators: str
    sensors: str
    joint_names: tuple[str, ...]
    keypoint_ids: tuple[int, ...]
    q_limits: FloatArray  # (H, 2) the actuated joints' ranges, as the pipeline clips to them


def human_fragment(ref: HandReference, config: SimConfig) -> HandFragment:
    """The built-in (or MANO) hand's fragment at its reference's frame-0 wrist pose."""
    return HandFragment(
        side=ref.side,
        assets=hand_asset_xml(ref.geometry),
        worldbody=hand_worldbody_xml(ref.geometry, config, ref.wrist_pos[0], ref.wrist_quat[0]),
        equality=hand_equality_xml(ref.side, config),
        actuators=hand_actuator_xml(ref.side, config),
        sensors=hand_sensor_xml(ref.side),
        joint_names=HINGE_NAMES,
        keypoint_ids=HUMAN_KEYPOINTS,
        q_limits=np.asarray(JOINT_LIMITS, dtype=np.float64),
    )


def hand_fragment(ref: object, config: SimConfig) -> HandFragment:
    """The fragment of any hand reference: a ``HandReference`` is the human hand; any other reference makes its
    own (``fragment(config)``, e.g. ``worker.robot.RobotReference``)."""
    if isinstance(ref, HandReference):
        return human_fragment(ref, config)
    make = getattr(ref, "fragment", None)
    if make is None:
        raise TypeError(f"{type(ref).__name__} is not a hand reference (no fragment(config))")
    fragment = make(config)
    assert isinstance(fragment, HandFragment)
    return fragment

