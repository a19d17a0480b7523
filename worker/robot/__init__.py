"""Robot hands (issue #55): a hand described as data, its model compiled into the scene, the recorded hand
retargeted to it, and what the refinement needs of it.

* ``common.hand_description``: the description (model, actuated joints, servo gains, keypoint correspondence);
* ``embodiment``: read / resolve (``allegro``, ``leap``: ``data/*.json`` over the dex-urdf models), pack (the model
  inlined as self-contained MJCF), check against the compiled model (``Embodiment``, field-named errors);
* ``canonical``: a compiled model written back as MJCF, and its mirror image (the left hand of a right model);
* ``fragment``: the robot's part of the scene MJCF (``worker.simulation.hand_fragment.HandFragment``);
* ``retarget``: kinematic retargeting (damped least squares on MuJoCo site Jacobians) -> ``RobotReference``;
* ``basis``: the robot's pose coordinates (PCA of its retargeted motion) and fingertip segments;
* ``metrics``: joint-limit and actuator-force margins, smoothness against the model's limits.

The physics and optimisation code imports the modules it needs directly (``worker.refine.prepare``); this package
imports none of Ray or the database.
"""

from worker.robot.embodiment import Embodiment, pack_description, read_description, resolve_hand
from worker.robot.reference import RobotReference
from worker.robot.retarget import retarget_robot, robot_references

__all__ = [
    "Embodiment",
    "RobotReference",
    "pack_description",
    "read_description",
    "resolve_hand",
    "retarget_robot",
    "robot_references",
]
