"""A robot hand's part of the scene MJCF (``worker.simulation.hand_fragment.HandFragment``), written from its
side's canonical MJCF (``Embodiment.xml``) by renaming every element with the side's prefix.

Chosen over ``MjSpec.attach`` because the scene is one MJCF text that results, ``verify`` and the export carry
as is: the fragment is text spliced into it, as the human hand's is. The robot's root body becomes
``{side}_palm`` with a free joint welded to the mocap body ``{side}_mocap`` (as the human hand's palm); its geoms
collide with the object only and take the hand's contact settings (friction, condim, solref, solimp of
``SimConfig``); its joints keep the model's damping and friction loss and get ``SimConfig.hinge_armature`` where
the model has no armature (light links need it for stable contacts, as the human hand's do); bodies get gravity
compensation with ``SimConfig.hand_gravcomp``. Position servos drive the actuated joints (gains: the description's,
else the human hand's ``finger_kp`` / ``finger_kv``; force range: the joint's effort limit where known).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from common.geometry import FloatArray
from worker.robot.canonical import fmt
from worker.robot.embodiment import Embodiment
from worker.simulation.config import HAND_BIT, OBJECT_BIT, SimConfig
from worker.simulation.hand_fragment import HandFragment
from worker.simulation.hand_mjcf import hand_equality_xml

#: Names of the scene's own parts of a hand (``hand_fragment``): a robot element of that name gets a "_" appended.
RESERVED = frozenset({"palm", "mocap", "root", "penetration", "wrist"})


def robot_fragment(emb: Embodiment, config: SimConfig, wrist_pos: FloatArray, wrist_quat: FloatArray) -> HandFragment:
    """The fragment of ``emb`` with its root at the given pose (the reference's frame 0)."""
    side = emb.side
    doc = ET.fromstring(emb.xml)
    rename = {emb.root_body: f"{side}_palm"}

    def name(n: str | None) -> str:
        # The names the scene gives the hand's own parts are kept for them: a robot's "palm" link is "right_palm_".
        n = n or ""
        return rename.get(n, f"{side}_{n}" + ("_" if n in RESERVED or n.startswith("kp") else ""))

    assets = []
    for mesh in doc.iter("mesh"):
        mesh.set("name", name(mesh.get("name")))
        assets.append(ET.tostring(mesh, encoding="unicode"))
    world = doc.find("worldbody")
    assert world is not None
    root = world.find("body")
    assert root is not None
    bodies = {b.get("name", ""): b for b in root.iter("body")}
    for body in root.iter("body"):
        body.set("name", name(body.get("name")))
        if config.hand_gravcomp:
            body.set("gravcomp", "1")
    root.set("pos", fmt(wrist_pos))
    root.set("quat", fmt(wrist_quat))
    root.insert(0, ET.Element("freejoint", name=f"{side}_root"))
    limits = dict(zip(emb.joint_names, emb.q_limits, strict=True))
    for joint in root.iter("joint"):
        if joint.get("name") in limits:  # the description's range where it gives one
            joint.set("range", fmt(limits[joint.get("name", "")]))
        joint.set("name", name(joint.get("name")))
        if "armature" not in joint.attrib:
            joint.set("armature", f"{config.hinge_armature:g}")
    for geom in root.iter("geom"):
        geom.set("name", name(geom.get("name")))
        if "mesh" in geom.attrib:
            geom.set("mesh", name(geom.get("mesh")))
        geom.attrib.update({
            "contype": str(HAND_BIT), "conaffinity": str(OBJECT_BIT), "condim": str(config.hand_condim),
            "friction": fmt(config.hand_friction), "solref": fmt(config.contact_solref),
            "solimp": fmt(config.contact_solimp), "group": "1",
        })  # fmt: skip
    for site in root.iter("site"):
        site.set("name", name(site.get("name")))
    for j, (body_name, pos) in enumerate(zip(emb.site_bodies, emb.site_pos, strict=True)):
        ET.SubElement(bodies[body_name], "site", name=f"{side}_kp{j}", pos=fmt(pos), size="0.004")
    equality = [hand_equality_xml(side, config)]
    eq = doc.find("equality")
    for coupling in [] if eq is None else list(eq):
        for key in ("joint1", "joint2"):
            if key in coupling.attrib:
                coupling.set(key, name(coupling.get(key)))
        equality.append(ET.tostring(coupling, encoding="unicode"))
    joints = tuple(name(j)[len(side) + 1:] for j in emb.joint_names)  # the scene's names, less the side's prefix
    mocap = f'<body name="{side}_mocap" mocap="true" pos="{fmt(wrist_pos)}" quat="{fmt(wrist_quat)}"/>'
    ET.indent(root)
    return HandFragment(
        side=side,
        assets="\n".join(assets),
        worldbody=mocap + "\n" + ET.tostring(root, encoding="unicode"),
        equality="\n".join(equality),
        actuators=actuator_xml(emb, config, joints),
        sensors="\n".join(f'<framepos name="{side}_kp{j}" objtype="site" objname="{side}_kp{j}"/>'
                          for j in range(len(emb.keypoint_ids))),
        joint_names=joints,
        keypoint_ids=emb.keypoint_ids,
        q_limits=emb.q_limits.copy(),
    )


def servo_gains(emb: Embodiment, config: SimConfig) -> tuple[float, float]:
    """(kp, kv) of the robot's position servos: the description's, else the human hand's."""
    return (emb.kp if emb.kp is not None else config.finger_kp, emb.kv if emb.kv is not None else config.finger_kv)


def actuator_xml(emb: Embodiment, config: SimConfig, joints: tuple[str, ...]) -> str:
    """One position servo per actuated joint (``joints``: their scene names less the side's prefix), control range
    = the joint's range, force range = its effort."""
    kp, kv = servo_gains(emb, config)
    out = []
    for name, (lo, hi), effort in zip(joints, emb.q_limits, emb.effort_limits, strict=True):
        force = f' forcerange="{-effort:.6g} {effort:.6g}"' if np.isfinite(effort) else ""
        out.append(f'<position name="{emb.side}_{name}" joint="{emb.side}_{name}" kp="{kp:g}" kv="{kv:g}" '
                   f'ctrlrange="{lo:.9g} {hi:.9g}"{force}/>')
    return "\n".join(out)
