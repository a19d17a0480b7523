"""Small articulated sequences for format, API and corpus tests (issue #52): built here from primitives and fixed
numbers, so the bad-input corpus written from them stays byte-stable whatever the built-in examples become."""

from __future__ import annotations

import numpy as np

from common.articulation import ObjectJoint
from common.sequence import HandTrack, ManoParams, ObjectPart, ObjectSpec, Sequence, Side

#: Each hand and the side of the box it starts on (x sign).
SIDE_SIGNS: tuple[tuple[Side, float], ...] = (("right", 1.0), ("left", -1.0))


def lid_joint(**overrides: object) -> ObjectJoint:
    values: dict[str, object] = dict(
        name="hinge", kind="revolute", parent="base", axis=np.array([1.0, 0.0, 0.0]),
        origin_pos=np.array([0.0, -0.03, 0.02]), origin_quat=np.array([1.0, 0.0, 0.0, 0.0]),
        limits=np.array([0.0, 1.5]),
    )  # fmt: skip
    values.update(overrides)
    return ObjectJoint(**values)  # type: ignore[arg-type]


def tiny_articulated_sequence(seed: int = 0, frames: int = 5, name: str = "tiny-hinged") -> Sequence:
    """A 10 x 6 x 4 cm box (base part ``base``) with a 1 cm lid hinged along its back top edge, opened from 0 to 0.5
    rad, and two hands (keypoints) around it. Not validated: callers break it first or validate it."""
    rng = np.random.default_rng(seed)
    pose = np.zeros((frames, 7))
    pose[:, 2] = 0.02
    pose[:, 3] = 1.0
    lid = ObjectSpec(name="lid", mass_kg=0.05, primitive="box", size=np.array([0.05, 0.03, 0.005]))
    obj = ObjectSpec(name="hinged", mass_kg=0.3, primitive="box", size=np.array([0.05, 0.03, 0.02]),
                     parts=[ObjectPart(lid, lid_joint())])  # fmt: skip
    hands = [
        HandTrack(side=side, valid=np.ones(frames, dtype=bool),
                  keypoints=rng.normal(scale=0.03, size=(frames, 21, 3)) + np.array([0.08 * sign, 0.0, 0.08]))
        for side, sign in SIDE_SIGNS
    ]  # fmt: skip
    return Sequence(name=name, fps=30.0, object=obj, object_pose=pose, hands=hands, up=np.array([0.0, 0.0, 1.0]),
                    articulation=np.linspace(0.0, 0.5, frames)[:, None])  # fmt: skip


def drawer_cabinet_sequence(frames: int = 6, parts: int = 3, mano: bool = False) -> Sequence:
    """A chain of parts exercising every joint field: a revolute door on the base (damping, friction, a tilted
    origin), a prismatic drawer on the base (a non-unit axis, a part friction), and from there revolute knobs each
    hung from the part before it (a mesh part first); ``parts`` of them in all (up to ``MAX_PARTS``). Two hands,
    each with keypoints and, with ``mano``, MANO parameters."""
    rng = np.random.default_rng(3)
    verts = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.015, 0.0], [0.0, 0.0, 0.01], [0.02, 0.015, 0.01]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [1, 4, 2], [2, 4, 3]])
    half = np.sin(0.2)
    out = [
        ObjectPart(ObjectSpec(name="door", mass_kg=0.2, primitive="box", size=np.array([0.1, 0.005, 0.1])),
                   ObjectJoint(name="door_hinge", kind="revolute", parent="cabinet", axis=np.array([0.0, 0.0, 1.0]),
                               origin_pos=np.array([0.1, -0.1, 0.0]),
                               origin_quat=np.array([np.cos(0.2), 0.0, 0.0, half]), limits=np.array([-0.1, 1.8]),
                               damping=0.05, friction=0.01)),
        ObjectPart(ObjectSpec(name="drawer", mass_kg=0.3, primitive="box", size=np.array([0.08, 0.08, 0.03]),
                              friction=0.7),
                   ObjectJoint(name="drawer_slide", kind="prismatic", parent="cabinet", axis=np.array([0.0, -3.0, 4.0]),
                               origin_pos=np.array([0.0, 0.0, -0.05]), origin_quat=np.array([1.0, 0.0, 0.0, 0.0]),
                               limits=np.array([0.0, 0.25]), damping=0.5, friction=0.02)),
    ]  # fmt: skip
    for k in range(parts - 2):
        parent = out[-1].shape.name
        shape = (ObjectSpec(name=f"knob{k}", mass_kg=0.01, mesh_vertices=verts.copy(), mesh_faces=faces.copy())
                 if k == 0 else ObjectSpec(name=f"knob{k}", mass_kg=0.01, primitive="sphere", size=np.array([0.01])))
        out.append(ObjectPart(shape, ObjectJoint(
            name=f"knob{k}_turn", kind="revolute", parent=parent, axis=np.array([0.0, 1.0, 0.0]),
            origin_pos=np.array([0.0, -0.01, 0.0]), origin_quat=np.array([1.0, 0.0, 0.0, 0.0]),
            limits=np.array([-3.0, 3.0]), damping=0.0, friction=0.0)))  # fmt: skip
    obj = ObjectSpec(name="cabinet", mass_kg=2.0, primitive="box", size=np.array([0.1, 0.1, 0.1]), friction=0.5,
                     base_part="cabinet", parts=out)  # fmt: skip
    t = np.linspace(0.0, 1.0, frames)
    values = np.stack([1.2 * t, 0.2 * t] + [np.sin(3 * t + k) for k in range(parts - 2)], axis=1)
    pose = np.tile([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0], (frames, 1))
    hands = []
    for side in ("right", "left"):
        hand = HandTrack(side=side, valid=np.ones(frames, dtype=bool),
                         keypoints=rng.normal(0.0, 0.05, (frames, 21, 3)))
        if mano:
            hand.mano = ManoParams(global_orient=rng.normal(0, 0.5, (frames, 3)),
                                   hand_pose=rng.normal(0, 0.2, (frames, 45)), trans=rng.normal(0, 0.1, (frames, 3)),
                                   betas=rng.normal(0, 0.5, 10))  # fmt: skip
        hands.append(hand)
    return Sequence(name="cabinet", fps=60.0, object=obj, object_pose=pose, hands=hands,
                    world_from_source=np.eye(4), articulation=values, meta={"kind": "test cabinet"})  # fmt: skip
