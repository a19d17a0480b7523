"""The ARCTIC release layout as sequences (issue #52 item 5a): MANO hands and a two-part object from ARCTIC's files.

What ``zc-alexfan/arctic`` documents (``docs/data/data_doc.md``) and its own code reads (``src/arctic/
preprocess_dataset.py``, ``common/object_tensors.py``, ``common/body_models.py``):

* ``raw_seqs/<subject>/<seq>.mano.npy``: a pickled dict (read by ``common.safe_pickle``, no code runs) with per
  side ``right`` / ``left``: ``rot`` (T, 3) global axis-angle, ``pose`` (T, 45) axis-angle, ``trans`` (T, 3) metres,
  ``shape`` (10,) or (T, 10) betas, ``fitting_err``. ARCTIC builds its MANO layers without PCA and with
  ``flat_hand_mean=False``; the hands are decoded later, through smplx, with the user's MANO files
  (``HOI_REFINE_MANO_DIR``; without them refining fails naming that setting, ``worker.hand.mano.ensure``).
* ``<seq>.object.npy``: (T, 7) per frame the articulation angle (radians), the object's rotation (axis-angle) and
  its translation in **millimetres**, all in ARCTIC's world (z up, the same world as the dexmachina-processed files,
  ``common.arctic``).
* ``meta/object_vtemplates/<object>/``: the object in its canonical frame, in millimetres. ``top.obj`` and
  ``bottom.obj`` (each part its own mesh) when both are there, else ``mesh.obj`` split by ``parts.json`` (per
  vertex 1 top, 0 bottom; a face goes to the part most of its vertices belong to). The top part turns about the
  object frame's -z axis through its origin (``object_tensors.py``: ``z_axis = [0, 0, -1]``, the top's vertices
  rotated by the angle about it before the global pose).

The sequence: the object's base part ``bottom`` posed by ``object_pose``, the part ``top`` hung from it by the
revolute joint ``rotation`` (the dexmachina URDFs' name for the same joint) about (0, 0, -1) at the origin, its
limits the recording's range widened to include 0 (the closed pose); both hands as MANO parameters; ``up`` = +z.
ARCTIC gives no masses: each part weighs ``DENSITY_KG_M3`` times the volume of its convex hull.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from common.arctic import ARCTIC_FPS, object_name_of
from common.articulation import ObjectJoint
from common.errors import SequenceValidationError, UnsupportedFormatError
from common.geometry import FloatArray, IntArray
from common.mesh_io import load_mesh_file
from common.safe_pickle import load_object_npy
from common.sequence import HandTrack, ManoParams, ObjectPart, ObjectSpec, Sequence

MANO_SUFFIX = ".mano.npy"
OBJECT_SUFFIX = ".object.npy"
#: The templates folder under the release's data root (``<root>/raw_seqs/<subject>/<seq>.mano.npy``).
TEMPLATES = Path("meta") / "object_vtemplates"
BASE_PART, TOP_PART, JOINT_NAME = "bottom", "top", "rotation"
#: The top part's axis in the object frame (``object_tensors.py``).
TOP_AXIS = (0.0, 0.0, -1.0)
MM = 1e-3
#: Mass per convex-hull volume (kg/m^3) for ARCTIC's massless templates: the dexmachina URDFs' masses of six of the
#: same objects over their parts' hull volumes range from 53 (the box's lid) to 2650 (the waffle iron's base), with
#: the median near 300 (measured with this module's ``hull_mass``, not stored: the files may not be copied).
DENSITY_KG_M3 = 300.0
MIN_PART_MASS_KG = 0.01


def release_files(path: Path) -> tuple[Path, Path, str]:
    """(``.mano.npy``, ``.object.npy``, sequence name) of the sequence ``path`` names (either file)."""
    name = path.name
    for suffix in (MANO_SUFFIX, OBJECT_SUFFIX):
        if name.endswith(suffix):
            stem = name[: -len(suffix)]
            return path.with_name(stem + MANO_SUFFIX), path.with_name(stem + OBJECT_SUFFIX), stem
    stem = name.split(".")[0]
    raise UnsupportedFormatError(f"{name}: an ARCTIC release sequence is read from its {stem}{MANO_SUFFIX} (with the "
                                 f"{stem}{OBJECT_SUFFIX} beside it)")


def template_dir(mano_path: Path, object_dir: Path | None) -> Path:
    """The object's template folder: ``object_dir``, else ``<root>/meta/object_vtemplates/<object>``."""
    if object_dir is not None:
        return object_dir
    return mano_path.resolve().parents[2] / TEMPLATES / object_name_of(mano_path)


def load_arctic_release(path: Path, object_dir: Path | None = None, max_frames: int | None = None) -> Sequence:
    """An ARCTIC release sequence (see the module docstring); ``object_dir`` overrides the template folder."""
    mano_path, object_path, stem = release_files(path)
    for p in (mano_path, object_path):
        if not p.is_file():
            raise UnsupportedFormatError(f"{stem}: {p.name} is missing (an ARCTIC sequence is a .mano.npy and a "
                                         ".object.npy side by side)")
    params = _object_params(object_path)
    t = len(params)
    folder = template_dir(mano_path, object_dir)
    obj = object_from_template(folder, object_name_of(mano_path))
    angle = params[:, :1].copy()
    lo, hi = min(0.0, float(angle.min())), float(angle.max())
    obj.parts[0].joint.limits = np.array([lo, hi])
    mano = load_object_npy(mano_path)
    if not isinstance(mano, dict):
        raise UnsupportedFormatError(f"{mano_path.name}: expected a pickled dict with 'right' and 'left'")
    hands = [_hand(mano, side, t, mano_path.name) for side in ("right", "left")]
    seq = Sequence(
        name=stem, fps=ARCTIC_FPS, object=obj, object_pose=object_pose(params), hands=hands,
        up=np.array([0.0, 0.0, 1.0]), articulation=angle,
        meta={"source": "arctic (release)", "subject": mano_path.parent.name, "object": obj.name,
              "limits_from_recording.rotation": f"[{lo:.6g}, {hi:.6g}]"},
    )  # fmt: skip
    return seq.validate(max_frames=max_frames)


def _object_params(path: Path) -> FloatArray:
    data = load_object_npy(path)
    arr = np.asarray(data) if isinstance(data, np.ndarray) else None
    if arr is None or arr.dtype.kind not in "iuf" or arr.ndim != 2 or arr.shape[1] != 7 or len(arr) < 1:
        shape = getattr(data, "shape", type(data).__name__)
        raise UnsupportedFormatError(f"{path.name}: expected (T, 7) numbers [angle, axis-angle (3), translation "
                                     f"(3) mm], got {shape}")  # fmt: skip
    return np.asarray(arr, dtype=np.float64)


def object_pose(params: FloatArray) -> FloatArray:
    """(T, 7) base poses (metres, wxyz quaternions, sign-continuous) from the (T, 7) object parameters."""
    from scipy.spatial.transform import Rotation

    quat = Rotation.from_rotvec(params[:, 1:4]).as_quat(scalar_first=True)
    for i in range(1, len(quat)):
        if np.dot(quat[i], quat[i - 1]) < 0:
            quat[i] = -quat[i]
    return np.concatenate([params[:, 4:7] * MM, quat], axis=1)


def _hand(mano: dict[str, Any], side: str, t: int, where: str) -> HandTrack:
    d = mano.get(side)
    if not isinstance(d, dict):
        raise UnsupportedFormatError(f"{where}: no {side!r} hand (a dict of rot, pose, trans, shape)")

    def field(key: str, shape: tuple[int, ...]) -> FloatArray:
        if key not in d:
            raise UnsupportedFormatError(f"{where}: {side}.{key} is missing")
        arr = np.asarray(d[key])
        if arr.dtype.kind not in "iuf" or arr.shape != shape:
            raise UnsupportedFormatError(f"{where}: {side}.{key} must be {shape} numbers, got {arr.shape} {arr.dtype}")
        return np.asarray(arr, dtype=np.float64)

    rot, pose, trans = field("rot", (t, 3)), field("pose", (t, 45)), field("trans", (t, 3))
    shape = np.asarray(d.get("shape"))
    # ARCTIC's loader repeats one (10,) shape over the frames; the documentation says per frame: take either.
    if shape.dtype.kind not in "iuf" or shape.shape not in ((10,), (t, 10)):
        raise UnsupportedFormatError(f"{where}: {side}.shape must be (10,) or ({t}, 10) numbers, got {shape.shape}")
    betas = np.asarray(shape, dtype=np.float64).reshape(-1, 10).mean(axis=0)
    valid: np.ndarray = np.isfinite(np.concatenate([rot, pose, trans], axis=1)).all(axis=1)
    # Invalid frames keep finite placeholders (validation wants finite arrays); ``valid`` says to ignore them.
    rot, pose, trans = (np.where(valid[:, None], a, 0.0) for a in (rot, pose, trans))
    params = ManoParams(global_orient=rot, hand_pose=pose, trans=trans, betas=betas, pose_format="axis_angle",
                        flat_hand_mean=False)  # fmt: skip
    return HandTrack(side=side, valid=valid, mano=params)  # type: ignore[arg-type]


def object_from_template(folder: Path, name: str) -> ObjectSpec:
    """The two-part object of an ARCTIC template folder (module docstring), its joint's limits still to be set."""
    if not folder.is_dir():
        raise UnsupportedFormatError(f"no ARCTIC object template folder {folder} (give it: --object-dir)")
    try:
        if (folder / "top.obj").is_file() and (folder / "bottom.obj").is_file():
            bottom, top = (load_mesh_file(folder / f"{part}.obj") for part in (BASE_PART, TOP_PART))
        elif (folder / "mesh.obj").is_file() and (folder / "parts.json").is_file():
            bottom, top = split_by_parts(*load_mesh_file(folder / "mesh.obj"), _part_labels(folder / "parts.json"))
        else:
            raise UnsupportedFormatError(f"{folder.name}: an ARCTIC template needs top.obj + bottom.obj or mesh.obj + "
                                         "parts.json")
    except SequenceValidationError as exc:
        raise UnsupportedFormatError(f"{folder.name}: {exc}") from exc
    (bv, bf), (tv, tf) = bottom, top
    bv, tv = bv * MM, tv * MM
    joint = ObjectJoint(
        name=JOINT_NAME, kind="revolute", parent=BASE_PART, axis=np.array(TOP_AXIS), origin_pos=np.zeros(3),
        origin_quat=np.array([1.0, 0.0, 0.0, 0.0]), limits=np.array([0.0, 0.0]),
    )  # fmt: skip
    top_shape = ObjectSpec(name=TOP_PART, mass_kg=hull_mass(tv), mesh_vertices=tv, mesh_faces=tf)
    return ObjectSpec(name=name, mass_kg=hull_mass(bv), mesh_vertices=bv, mesh_faces=bf, base_part=BASE_PART,
                      parts=[ObjectPart(top_shape, joint)])  # fmt: skip


def _part_labels(path: Path) -> np.ndarray:
    import json

    try:
        labels = np.asarray(json.loads(path.read_text()))
    except (ValueError, UnicodeDecodeError) as exc:
        raise UnsupportedFormatError(f"{path.name}: not JSON ({exc})") from exc
    if labels.ndim != 1 or labels.dtype.kind not in "biu" or not np.isin(labels, (0, 1)).all():
        raise UnsupportedFormatError(f"{path.name}: expected a list of 0 (bottom) / 1 (top) per mesh vertex")
    return labels.astype(np.int64)


def split_by_parts(vertices: FloatArray, faces: IntArray, labels: np.ndarray
                   ) -> tuple[tuple[FloatArray, IntArray], tuple[FloatArray, IntArray]]:
    """(bottom, top) meshes of a mesh labelled per vertex (0 bottom, 1 top); a face goes where most of its vertices
    are, and each part keeps only the vertices its faces use."""
    if len(labels) != len(vertices):
        raise UnsupportedFormatError(f"parts.json labels {len(labels)} vertices, mesh.obj has {len(vertices)}")
    face_top = labels[faces].sum(axis=1) >= 2
    out = []
    for chosen in (~face_top, face_top):
        f = faces[chosen]
        used = np.unique(f)
        if len(used) < 4:
            part = "top" if chosen is face_top else "bottom"
            raise UnsupportedFormatError(f"parts.json leaves the {part} part {len(used)} vertices")
        remap = np.full(len(vertices), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        out.append((vertices[used], remap[f]))
    return out[0], out[1]


def hull_mass(vertices: FloatArray) -> float:
    """``DENSITY_KG_M3`` times the volume of the points' convex hull (at least ``MIN_PART_MASS_KG``)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        volume = float(ConvexHull(vertices).volume)
    except (QhullError, ValueError):
        volume = 0.0
    return max(MIN_PART_MASS_KG, DENSITY_KG_M3 * volume)
