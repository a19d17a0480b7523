"""An articulated object from a URDF: its links as parts, its revolute/prismatic joints (``common.articulation``).

Reads what an object URDF (such as the ARCTIC objects' files in dexmachina's assets) says of each link — its
mass and collision mesh (OBJ/PLY/STL/GLB, relative to the URDF, ``scale`` and ``origin`` applied) — and of each
joint — type, parent and child, origin (xyz + roll-pitch-yaw), axis and limits. The base part is the link no joint
moves. A joint's ``<dynamics>`` is not read: values tuned for another simulator (dexmachina's notebook cover has no
friction and would flop under gravity, which no recording shows) give way to ``SimConfig.articulation_*``.
Every problem is an ``UnsupportedFormatError`` naming the file and element.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import cast

import numpy as np

from common.articulation import JointKind, ObjectJoint
from common.errors import UnsupportedFormatError
from common.geometry import FloatArray, matrix_to_quat
from common.mesh_io import load_mesh_file
from common.sequence import ObjectPart, ObjectSpec

#: URDF joint types and ours; "continuous" is a revolute joint without limits (given +-2 pi here).
_KINDS = {"revolute": "revolute", "continuous": "revolute", "prismatic": "prismatic"}


def _floats(text: str | None, n: int, where: str, default: tuple[float, ...]) -> FloatArray:
    if text is None:
        return np.array(default, dtype=np.float64)
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError as exc:
        raise UnsupportedFormatError(f"{where}: expected {n} numbers, got {text!r}") from exc
    if values.shape != (n,) or not np.all(np.isfinite(values)):
        raise UnsupportedFormatError(f"{where}: expected {n} finite numbers, got {text!r}")
    return values


def rpy_matrix(rpy: FloatArray) -> FloatArray:
    """URDF's roll-pitch-yaw (fixed axes x, then y, then z): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cx, sx, cy, sy, cz, sz = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return np.asarray(rz @ ry @ rx)


def _origin(element: ET.Element | None, where: str) -> tuple[FloatArray, FloatArray]:
    """(xyz, rotation matrix) of an ``<origin>`` (identity when absent)."""
    if element is None:
        return np.zeros(3), np.eye(3)
    return (_floats(element.get("xyz"), 3, f"{where} origin xyz", (0.0, 0.0, 0.0)),
            rpy_matrix(_floats(element.get("rpy"), 3, f"{where} origin rpy", (0.0, 0.0, 0.0))))


def _link_shape(link: ET.Element, base_dir: Path, where: str) -> ObjectSpec:
    name = link.get("name") or ""
    mass_el = link.find("inertial/mass")
    if mass_el is None:
        raise UnsupportedFormatError(f"{where}: link {name!r} has no <inertial><mass>")
    mass = float(_floats(mass_el.get("value"), 1, f"{where}: link {name!r} mass", (0.0,))[0])
    collision = link.find("collision")
    mesh = None if collision is None else collision.find("geometry/mesh")
    if collision is None or mesh is None or not mesh.get("filename"):
        raise UnsupportedFormatError(f"{where}: link {name!r} has no <collision> mesh (needed for its shape)")
    filename = str(mesh.get("filename")).removeprefix("file://")
    path = Path(filename) if Path(filename).is_absolute() else base_dir / filename
    vertices, faces = load_mesh_file(path)
    scale = _floats(mesh.get("scale"), 3, f"{where}: link {name!r} mesh scale", (1.0, 1.0, 1.0))
    xyz, rot = _origin(collision.find("origin"), f"{where}: link {name!r} collision")
    return ObjectSpec(name=name, mass_kg=mass, mesh_vertices=(vertices * scale) @ rot.T + xyz, mesh_faces=faces)


def _end(joint: ET.Element, tag: str, where: str) -> str:
    """The link named by a joint's ``<parent>`` or ``<child>``."""
    element = joint.find(tag)
    if element is None or not element.get("link"):
        raise UnsupportedFormatError(f"{where}: joint {joint.get('name')!r} has no <{tag} link=...>")
    return str(element.get("link"))


def object_from_urdf(path: Path, name: str | None = None) -> ObjectSpec:
    """The object a URDF describes (see the module docstring); ``name`` overrides the robot's name."""
    where = path.name
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise UnsupportedFormatError(f"{where}: not a readable URDF ({exc})") from exc
    links = {link.get("name") or "": link for link in root.findall("link")}
    joints = root.findall("joint")
    movable = [j for j in joints if j.get("type") in _KINDS]
    fixed = [j for j in joints if j.get("type") not in _KINDS]
    if fixed:
        raise UnsupportedFormatError(f"{where}: joint {fixed[0].get('name')!r} of type {fixed[0].get('type')!r} "
                                     f"(only {', '.join(sorted(_KINDS))} joints are read)")
    children = {_end(j, "child", where) for j in movable}
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise UnsupportedFormatError(f"{where}: expected one base link that no joint moves, got {roots}")
    base = roots[0]
    # Parents before children: walk the tree from the base.
    order: list[ET.Element] = []
    frontier = [base]
    while frontier:
        parent = frontier.pop(0)
        for j in movable:
            if _end(j, "parent", where) == parent:
                order.append(j)
                frontier.append(_end(j, "child", where))
    if len(order) != len(movable):
        raise UnsupportedFormatError(f"{where}: the joints do not form a tree from {base!r}")
    obj = _link_shape(links[base], path.parent, where)
    obj.name = name or root.get("name") or base
    obj.base_part = base
    for j in order:
        jw = f"{where}: joint {j.get('name')!r}"
        child = _end(j, "child", where)
        if child not in links:
            raise UnsupportedFormatError(f"{jw}: child link {child!r} is not defined")
        xyz, rot = _origin(j.find("origin"), jw)
        kind = _KINDS[str(j.get("type"))]
        limit = j.find("limit")
        default = (-2 * np.pi, 2 * np.pi)
        lo = float(limit.get("lower", default[0])) if limit is not None else default[0]
        hi = float(limit.get("upper", default[1])) if limit is not None else default[1]
        axis = j.find("axis")
        joint = ObjectJoint(
            name=str(j.get("name")), kind=cast(JointKind, kind),
            parent=_end(j, "parent", where),
            axis=_floats(None if axis is None else axis.get("xyz"), 3, f"{jw} axis", (1.0, 0.0, 0.0)),
            origin_pos=xyz, origin_quat=matrix_to_quat(rot), limits=np.array([lo, hi]),
        )  # fmt: skip
        obj.parts.append(ObjectPart(_link_shape(links[child], path.parent, where), joint))
    return obj
