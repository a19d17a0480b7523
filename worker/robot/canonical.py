"""A robot model, whatever its source (URDF or MJCF), as one self-contained MJCF written from the *compiled* model.

MuJoCo compiles the source (URDF included; ``balanceinertia`` on, since public URDFs carry inertias that break the
triangle inequality, and static links kept as bodies so the root link stays a body); this module writes the
compiled kinematic tree back as plain MJCF: bodies with their poses and explicit inertials, hinge and slide joints
(axis, range, damping, armature, friction loss, force range), geoms (primitives; meshes as the vertices of their
convex hull, which is all MuJoCo collides with, expressed in the body frame so no mesh file is needed), sites, and
joint-coupling equalities (URDF ``mimic``). Everything the simulation uses, nothing it does not (visual meshes,
tendons and actuators of the source are left out; a source with tendons is refused: they would change the
kinematics). The result is the packed form's ``model_xml`` (``common.hand_description``) and the input of the
scene fragment (``worker.robot.fragment``) and of the mirror image (``mirror_xml``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial import ConvexHull

from common.errors import FieldProblem
from common.geometry import FloatArray, quat_to_matrix
from common.hand_description import HandDescriptionError

#: Geom types written back (MuJoCo enum -> MJCF name).
GEOM_TYPES = {
    int(mujoco.mjtGeom.mjGEOM_PLANE): "plane", int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule", int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder", int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_MESH): "mesh",
}  # fmt: skip
#: A collision mesh is its convex hull, at most this many vertices (MuJoCo's ``maxhullvert``): the LEAP's fingertip
#: meshes have 6,000 vertices and hulls of ~1,000, which would make the packed model a megabyte.
MAX_HULL_VERTICES = 64
JOINT_TYPES = {int(mujoco.mjtJoint.mjJNT_HINGE): "hinge", int(mujoco.mjtJoint.mjJNT_SLIDE): "slide"}


def fmt(values: FloatArray | list[float] | tuple[float, ...] | float) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.ravel(values))


def compile_source(path: Path, field: str = "hand.model") -> mujoco.MjModel:
    """Compile a URDF or MJCF file with the settings above; a compile error names ``field``."""
    if not path.is_file():
        raise HandDescriptionError([FieldProblem(field, f"no such file: {path}")])
    try:
        spec = mujoco.MjSpec.from_file(str(path))
        spec.compiler.balanceinertia = True
        spec.compiler.fusestatic = False
        for mesh in spec.meshes:
            mesh.maxhullvert = MAX_HULL_VERTICES
        return spec.compile()
    except Exception as exc:  # MuJoCo raises ValueError with the parser's message
        raise HandDescriptionError([FieldProblem(field, f"MuJoCo cannot compile {path.name}: {exc}")]) from None


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(model, kind, i) or ""


def canonical_xml(model: mujoco.MjModel, root_body: str | None = None, field: str = "hand.model") -> str:
    """The compiled ``model``'s subtree under ``root_body`` (None: the one child of the world) as MJCF."""
    problems = []
    if model.ntendon:
        problems.append(FieldProblem(field, f"the model has {model.ntendon} tendons, which are not supported"))
    world_children = [b for b in range(1, model.nbody) if model.body_parentid[b] == 0]
    if root_body is None:
        if len(world_children) != 1:
            problems.append(FieldProblem("hand.root_body", f"the model has {len(world_children)} bodies under the "
                                         "world: name the one welded to the wrist"))
            root = -1
        else:
            root = world_children[0]
    else:
        root = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, root_body)
        if root < 0:
            problems.append(FieldProblem("hand.root_body", f"no body named {root_body!r} in the model"))
    if problems:
        raise HandDescriptionError(problems)
    free = [j for j in range(model.njnt) if model.jnt_bodyid[j] == root]
    for j in range(model.njnt):
        if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_BALL) or (
                int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE) and j not in free):
            raise HandDescriptionError([FieldProblem(field, f"joint {_name(model, mujoco.mjtObj.mjOBJ_JOINT, j)!r}: "
                                                     "ball and free joints inside the hand are not supported")])
    doc = ET.Element("mujoco", model=_name(model, mujoco.mjtObj.mjOBJ_BODY, root) or "robot")
    ET.SubElement(doc, "compiler", angle="radian", autolimits="true")
    asset = ET.SubElement(doc, "asset")
    world = ET.SubElement(doc, "worldbody")
    _write_body(model, root, world, asset, is_root=True)
    _write_equalities(model, doc)
    ET.indent(doc)
    return ET.tostring(doc, encoding="unicode")


def _write_body(model: mujoco.MjModel, b: int, parent: ET.Element, asset: ET.Element, is_root: bool = False) -> None:
    name = _name(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}"
    attrs = {"name": name}
    if not is_root:  # the root's pose is the wrist's, set by the scene
        attrs.update(pos=fmt(model.body_pos[b]), quat=fmt(model.body_quat[b]))
    el = ET.SubElement(parent, "body", attrs)
    if model.body_mass[b] > 0:
        ET.SubElement(el, "inertial", pos=fmt(model.body_ipos[b]), quat=fmt(model.body_iquat[b]),
                      mass=f"{float(model.body_mass[b]):.9g}", diaginertia=fmt(model.body_inertia[b]))
    for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
        kind = JOINT_TYPES.get(int(model.jnt_type[j]))
        if kind is None:  # the root's own free joint: the scene gives the root one of its own
            continue
        d = int(model.jnt_dofadr[j])
        jattrs = {"name": _name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}", "type": kind,
                  "pos": fmt(model.jnt_pos[j]), "axis": fmt(model.jnt_axis[j])}
        if model.jnt_limited[j]:
            jattrs["range"] = fmt(model.jnt_range[j])
        for key, value in (("damping", model.dof_damping[d]), ("armature", model.dof_armature[d]),
                           ("frictionloss", model.dof_frictionloss[d])):
            if value > 0:
                jattrs[key] = f"{float(value):.9g}"
        if model.jnt_actfrclimited[j]:
            jattrs["actuatorfrcrange"] = fmt(model.jnt_actfrcrange[j])
        ET.SubElement(el, "joint", jattrs)
    for g in range(model.body_geomadr[b], model.body_geomadr[b] + model.body_geomnum[b]):
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue  # visual only
        _write_geom(model, g, el, asset)
    for s in range(model.nsite):
        if model.site_bodyid[s] == b:
            ET.SubElement(el, "site", name=_name(model, mujoco.mjtObj.mjOBJ_SITE, s) or f"site{s}",
                          pos=fmt(model.site_pos[s]), quat=fmt(model.site_quat[s]))
    for child in range(b + 1, model.nbody):
        if model.body_parentid[child] == b:
            _write_body(model, child, el, asset)


def _write_geom(model: mujoco.MjModel, g: int, body: ET.Element, asset: ET.Element) -> None:
    kind = GEOM_TYPES.get(int(model.geom_type[g]))
    name = _name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
    if kind is None or kind == "plane":
        raise HandDescriptionError([FieldProblem("hand.model", f"geom {name!r}: type not supported in a hand")])
    attrs = {"name": name, "type": kind, "rgba": fmt(model.geom_rgba[g])}
    if kind == "mesh":
        m = int(model.geom_dataid[g])
        verts = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        graph = int(model.mesh_graphadr[m])
        if graph >= 0:  # the hull MuJoCo computed (at most MAX_HULL_VERTICES): its vertices' indices
            n = int(model.mesh_graph[graph])
            verts = verts[model.mesh_graph[graph + 2 + n: graph + 2 + 2 * n]]
        # In the body frame, so MuJoCo's own recentring of the mesh cannot move it (module docstring).
        body_verts = model.geom_pos[g] + verts @ quat_to_matrix(model.geom_quat[g]).T
        hull = body_verts[ConvexHull(body_verts).vertices] if len(body_verts) > 4 else body_verts
        ET.SubElement(asset, "mesh", name=f"{name}_hull", vertex=" ".join(f"{v:.6g}" for v in hull.ravel()))
        attrs["mesh"] = f"{name}_hull"
    else:
        attrs.update(size=fmt(model.geom_size[g][: {"sphere": 1, "capsule": 2, "cylinder": 2}.get(kind, 3)]),
                     pos=fmt(model.geom_pos[g]), quat=fmt(model.geom_quat[g]))
    body.append(ET.Element("geom", attrs))


def _write_equalities(model: mujoco.MjModel, doc: ET.Element) -> None:
    """Joint couplings (``mimic``); other equality kinds are refused (they would tie the hand to the world)."""
    eqs = []
    for e in range(model.neq):
        if int(model.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT):
            raise HandDescriptionError([FieldProblem("hand.model", "only joint-coupling equalities are supported")])
        j1, j2 = int(model.eq_obj1id[e]), int(model.eq_obj2id[e])
        attrs = {"joint1": _name(model, mujoco.mjtObj.mjOBJ_JOINT, j1), "polycoef": fmt(model.eq_data[e][:5])}
        if j2 >= 0:
            attrs["joint2"] = _name(model, mujoco.mjtObj.mjOBJ_JOINT, j2)
        eqs.append(ET.Element("joint", attrs))
    if eqs:
        ET.SubElement(doc, "equality").extend(eqs)


# ---------------------------------------------------------------------------------------------- mirror

_M = np.array([1.0, -1.0, 1.0])  # reflection through the root frame's xz plane


def _mirror_quat(q: FloatArray) -> FloatArray:
    """The rotation M R M (a proper rotation) of quaternion ``q`` (w, x, y, z)."""
    return np.array([q[0], -q[1], q[2], -q[3]])


def mirror_xml(xml: str) -> str:
    """The mirror image of a canonical MJCF (``canonical_xml``) through its root body's xz plane: the left hand of
    a right hand. Positions and vertices reflect (y -> -y), frames become M R M, and a hinge's axis a becomes
    -M a so that the same joint angle gives the mirrored pose (joint ranges, and so the controls, are unchanged);
    a slide's axis becomes M a. Boxes, capsules and the like are symmetric in their own frames."""
    doc = ET.fromstring(xml)
    for el in doc.iter():
        if el.tag in ("body", "geom", "site", "inertial", "joint"):
            if "pos" in el.attrib:
                el.set("pos", fmt(_M * _floats(el.get("pos"))))
            if "quat" in el.attrib:
                el.set("quat", fmt(_mirror_quat(_floats(el.get("quat")))))
        if el.tag == "joint" and "axis" in el.attrib:
            axis = _M * _floats(el.get("axis"))
            el.set("axis", fmt(-axis if el.get("type", "hinge") == "hinge" else axis))
        if el.tag == "mesh" and "vertex" in el.attrib:
            el.set("vertex", fmt(_floats(el.get("vertex")).reshape(-1, 3) * _M))
    return ET.tostring(doc, encoding="unicode")


def _floats(text: str | None) -> FloatArray:
    return np.array([float(v) for v in (text or "").split()])
