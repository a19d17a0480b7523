"""MANO pose <-> the built-in hand's pose (wrist + 45 hinges), MANO references, and MANO's PCA in hinge space.

* ``mano_hand_pose``: MANO parameters -> wrist position/rotation + hinge angles (source frame), exact
  (``hand_geometry`` module doc); ``mano_reference`` wraps it as a world-frame ``HandReference``, the
  MANO-input counterpart of ``worker.hand.retarget.retarget_hand`` (no IK needed).
* ``hand_pose_to_mano``: the way back, for the refined result's MANO parameters (DESIGN §1.7);
  ``mano_result_arrays`` / ``reference_mano_arrays`` give the result file's ``S_mano_*`` arrays.
* ``mano_pca_basis``: MANO's hand PCA for the control parameterisation (DESIGN §1.3). MANO's components
  live in its 45-D axis-angle space; the refinement needs a basis over the 45 hinge angles, so the components
  are mapped through the (smooth) rotation -> hinge conversion, linearised at MANO's mean pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from common.errors import SequenceValidationError
from common.geometry import FloatArray
from common.sequence import HandTrack, ManoParams, Sequence, Side
from worker.hand.mano.decode import full_hand_pose, load_mano_model, local_rotations
from worker.hand.mano.hand_geometry import (
    ManoHandGeometry,
    hinges_to_rotations,
    mano_hand_geometry,
    rotations_to_hinges,
)
from worker.hand.reference import HandReference


def mano_hand_pose(params: ManoParams, mgeo: ManoHandGeometry, mano_dir: Path | str | None = None
                   ) -> tuple[FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """Wrist position (T,3), wrist rotation (T,3,3) (columns = wrist-frame axes) and hinges (T,45)."""
    model = load_mano_model(mgeo.side, mano_dir)
    rot = local_rotations(params, model)
    wrist_rot = rot[:, 0] @ mgeo.wrist_frame  # G0 · Wt
    wrist_pos = mgeo.wrist_origin + np.asarray(params.trans, dtype=np.float64)  # the root turns about J0
    return wrist_pos, wrist_rot, rotations_to_hinges(rot, mgeo)


def hand_pose_to_mano(
    wrist_pos: FloatArray,
    wrist_quat: FloatArray,
    q: FloatArray,
    mgeo: ManoHandGeometry,
    betas: FloatArray,
    mano_dir: Path | str | None = None,
    pose_format: str = "axis_angle",
) -> ManoParams:
    """Built-in hand pose (same frame as the MANO source) -> MANO parameters.

    ``pose_format="axis_angle"`` gives 45 axis-angle values with ``flat_hand_mean=True`` (exact);
    ``"pca"`` gives 45 PCA coefficients with the mean subtracted (``flat_hand_mean=False``, DexYCB's form).
    """
    fingers = hinges_to_rotations(q, mgeo)
    t = fingers.shape[0]
    hand_pose = Rotation.from_matrix(fingers.reshape(-1, 3, 3)).as_rotvec().reshape(t, 45)
    g0 = Rotation.from_quat(np.asarray(wrist_quat, np.float64), scalar_first=True).as_matrix() @ mgeo.wrist_frame.T
    params = ManoParams(
        global_orient=Rotation.from_matrix(g0).as_rotvec(),
        hand_pose=hand_pose,
        trans=np.asarray(wrist_pos, np.float64) - mgeo.wrist_origin,
        betas=np.asarray(betas, np.float64).copy(),
        pose_format="axis_angle",
        flat_hand_mean=True,
    )
    if pose_format == "pca":
        model = load_mano_model(mgeo.side, mano_dir)
        coeffs = np.linalg.lstsq(model.hands_components.T, (hand_pose - model.hands_mean).T, rcond=None)[0].T
        params.hand_pose, params.pose_format, params.flat_hand_mean = coeffs, "pca", False
    elif pose_format != "axis_angle":
        raise ValueError(f"pose_format must be 'axis_angle' or 'pca', got {pose_format!r}")
    return params


def refined_mano_params(
    seq: Sequence,
    hand: HandTrack,
    wrist_pos_world: FloatArray,
    wrist_quat_world: FloatArray,
    q: FloatArray,
    mano_dir: Path | str | None = None,
    pose_format: str = "axis_angle",
) -> ManoParams:
    """MANO parameters (in the sequence's source frame, the hand's betas) for a world-frame built-in hand pose,
    e.g. the refined trajectory (DESIGN §1.7 "MANO parameters when MANO is used")."""
    if hand.mano is None:
        raise ValueError(f"the {hand.side} hand has no MANO parameters")
    source_from_world = np.linalg.inv(seq.world_transform())
    pos = np.asarray(wrist_pos_world, np.float64) @ source_from_world[:3, :3].T + source_from_world[:3, 3]
    rot = Rotation.from_matrix(source_from_world[:3, :3]) * Rotation.from_quat(wrist_quat_world, scalar_first=True)
    mgeo = mano_hand_geometry(mano_dir, hand.side, hand.mano.betas)
    return hand_pose_to_mano(
        pos, rot.as_quat(scalar_first=True), q, mgeo, hand.mano.betas, mano_dir, pose_format=pose_format
    )


def mano_result_arrays(
    seq: Sequence, hand: HandTrack, wrist_pos_world: FloatArray, wrist_quat_world: FloatArray, q: FloatArray,
    mano_dir: Path | str | None = None,
) -> dict[str, np.ndarray]:  # fmt: skip
    """The result file's optional MANO fields for one hand (``S_mano_*``, the sequence NPZ's key names)."""
    m = refined_mano_params(seq, hand, wrist_pos_world, wrist_quat_world, q, mano_dir)
    s = hand.side
    return {
        f"{s}_mano_global_orient": m.global_orient, f"{s}_mano_hand_pose": m.hand_pose,
        f"{s}_mano_trans": m.trans, f"{s}_mano_betas": m.betas,
        f"{s}_mano_pose_format": np.array(m.pose_format), f"{s}_mano_flat_hand_mean": np.array(m.flat_hand_mean),
    }  # fmt: skip


def mano_reference(seq: Sequence, hand: HandTrack, mano_dir: Path | str | None = None) -> HandReference:
    """World-frame reference of a MANO hand on its own MANO geometry (invalid frames interpolated)."""
    if hand.mano is None:
        raise ValueError(f"the {hand.side} hand has no MANO parameters")
    valid = np.asarray(hand.valid, dtype=bool)
    if not valid.any():
        raise SequenceValidationError.single(f"hands[{hand.side}].valid", "no frame has a valid hand")
    mgeo = mano_hand_geometry(mano_dir, hand.side, hand.mano.betas)
    pos, rot, q = mano_hand_pose(hand.mano, mgeo, mano_dir)
    world = seq.world_transform()
    pos = pos @ world[:3, :3].T + world[:3, 3]
    rot = world[:3, :3] @ rot
    t_all, vidx = np.arange(len(valid), dtype=np.float64), np.flatnonzero(valid)
    for arr in (pos, q):
        for c in range(arr.shape[1]):
            arr[:, c] = np.interp(t_all, t_all[vidx], arr[vidx, c])
    rots = Rotation.from_matrix(rot[vidx])
    if len(vidx) > 1:
        rots = Slerp(t_all[vidx], rots)(np.clip(t_all, vidx[0], vidx[-1]))
    else:
        rots = Rotation.from_matrix(np.repeat(rot[vidx], len(valid), axis=0))
    quat = rots.as_quat(scalar_first=True)
    for i in range(1, len(quat)):
        if np.dot(quat[i], quat[i - 1]) < 0:
            quat[i] = -quat[i]
    if quat[0, 0] < 0:
        quat = -quat
    from worker.hand.model import forward_keypoints

    fitted = forward_keypoints(mgeo.geometry, pos, quat, q)
    # Targets as in ``retarget_keypoints``: observed keypoints where the hand has them (valid frames), else
    # the MANO hand's own; the residual is then the MANO fit's distance to the observation.
    targets, residual = fitted.copy(), np.where(valid, 0.0, np.nan)
    if hand.keypoints is not None:
        observed = seq.keypoints_world(hand)
        targets[valid] = observed[valid]
        residual[valid] = 1e3 * np.linalg.norm(fitted[valid] - observed[valid], axis=2).mean(axis=1)
    return HandReference(
        side=hand.side, geometry=mgeo.geometry, wrist_pos=pos, wrist_quat=quat, q=q, keypoints=targets,
        valid=valid.copy(), residual_mm=residual, from_mano=True,
    )  # fmt: skip


def reference_mano_arrays(seq: Sequence, references: list[HandReference], mano_dir: Path | str | None = None
                          ) -> dict[str, np.ndarray]:  # fmt: skip
    """``S_mano_*`` result arrays of the hands whose reference came from MANO, at the references' own poses
    (what a raw replay drives; a refinement passes its refined trajectory to ``mano_result_arrays`` instead)."""
    out: dict[str, np.ndarray] = {}
    for ref in references:
        if ref.from_mano:
            hand = next(h for h in seq.hands if h.side == ref.side)
            out.update(mano_result_arrays(seq, hand, ref.wrist_pos, ref.wrist_quat, ref.q, mano_dir))
    return out


@dataclass(frozen=True)
class ManoPoseBasis:
    """MANO's hand PCA. Hinge space (what the refinement uses, DESIGN §1.3 ``q = q_ref + B · δθ``):
    ``mean`` (45,) hinge angles of MANO's mean pose, ``components`` (n,45) hinge change per unit PCA
    coefficient (so ``B = components[:10].T``). MANO space: ``mean_axis_angle`` (45,), ``components_axis_angle``
    (n,45) exactly as in the model file."""

    side: Side
    mean: FloatArray
    components: FloatArray
    mean_axis_angle: FloatArray
    components_axis_angle: FloatArray


def mano_pca_basis(
    mano_dir: Path | str | None, side: Side, betas: FloatArray | None = None, n_components: int = 45
) -> ManoPoseBasis:
    """MANO's PCA basis for ``side``, also expressed over the hinges (central differences at the mean pose)."""
    model = load_mano_model(side, mano_dir)
    comps = model.hands_components[:n_components]
    mgeo = mano_hand_geometry(mano_dir, side, np.zeros(10) if betas is None else betas)
    eps = 1e-3
    # Rows: mean, then mean ± eps·c_i for every component; all as flat-hand axis-angle poses.
    poses = np.concatenate([model.hands_mean[None], model.hands_mean + eps * comps, model.hands_mean - eps * comps])
    params = ManoParams(
        global_orient=np.zeros((len(poses), 3)), hand_pose=poses, trans=np.zeros((len(poses), 3)),
        betas=np.zeros(10), flat_hand_mean=True,
    )  # fmt: skip
    q = rotations_to_hinges(local_rotations(params, model), mgeo)
    n = len(comps)
    jac = (q[1 : 1 + n] - q[1 + n :]) / (2 * eps)
    assert np.allclose(full_hand_pose(params, model), poses)
    return ManoPoseBasis(side, q[0], jac, model.hands_mean.copy(), comps.copy())
