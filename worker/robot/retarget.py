"""Kinematic retargeting of a recorded human hand to a robot hand (issue #55 item 2, "retarget first").

Per frame, the robot's root pose and actuated joints minimise

    sum_j w_j ||p_j(x) - h_j||^2 + LAMBDA_ROOT_POS ||p_root - p_nom||^2 + LAMBDA_ROOT_ROT ||log(R_nom R_root^T)||^2
        + LAMBDA_SMOOTH ||q - q_prev||^2

over the root's 6 degrees of freedom and the joints, within the joint limits: p_j the robot's keypoint sites,
h_j the human keypoints they stand for (fingertips weighted ``TIP_WEIGHT``, the other keypoints ``OTHER_WEIGHT``
and the wrist ``WRIST_WEIGHT``: a robot hand is larger than the recorded one and cannot match every keypoint, and
the fingertips are what touches the object; on three dev sequences the other keypoints at weight 1 left the
fingertips 28-44 mm off, at 0.02 13-18 mm, before the active set below), the nominal root pose the human
wrist's composed with the mount (``mount``: the description's, or fitted by aligning the robot's keypoint sites at
rest with the human hand's),
and q_prev the previous frame's solution (the warm start too). Damped least squares (Levenberg-Marquardt) on
MuJoCo's site Jacobians (``mj_jacSite``), with the joints held at a limit the step would push them past (an
active set; clipping after the step alone stalled against the limits and left the fingertips 12-22 mm off where
mink, a QP-based IK, reached 1 mm: ``bench/results/robot_retarget.md``); the object is ignored (the refinement
makes the grasp hold).

Given the frame rate, each joint's track is then brought within the robot's joint speed limits
(``worker.robot.speed.speed_limited``) and the keypoint sites recomputed on it: the reference the refinement
keeps the robot near is one the real hand can follow.
"""

from __future__ import annotations

import mujoco
import numpy as np

from common.geometry import FloatArray, matrix_to_quat, quat_mul, quat_to_matrix
from common.hand_description import HandDescription
from worker.hand.model import local_keypoints
from worker.hand.reference import HandReference
from worker.hand.retarget import kabsch
from worker.robot.embodiment import Embodiment
from worker.robot.fragment import robot_fragment
from worker.robot.reference import RobotReference
from worker.robot.speed import speed_limited
from worker.simulation.config import SimConfig

TIP_WEIGHT = 1.0
WRIST_WEIGHT = 0.02
OTHER_WEIGHT = 0.02
#: Regularisation (per m², per rad², per rad² of joint change) and LM damping.
LAMBDA_ROOT_POS = 1e-3
LAMBDA_ROOT_ROT = 1e-5
LAMBDA_SMOOTH = 1e-5
DAMPING = 1e-6
ITERATIONS = 15
FIRST_FRAME_ITERATIONS = 150


def ik_model(emb: Embodiment) -> tuple[mujoco.MjModel, IKLayout]:
    """The robot alone (root on a free joint, keypoint sites) for the IK, and where its variables sit."""
    frag = robot_fragment(emb, SimConfig(), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    xml = (f'<mujoco><compiler angle="radian" autolimits="true"/><asset>{frag.assets}</asset>'
           f'<worldbody>{frag.worldbody}</worldbody></mujoco>')
    model = mujoco.MjModel.from_xml_string(xml)
    joints = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{emb.side}_{n}") for n in frag.joint_names]
    sites = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"{emb.side}_kp{j}")
             for j in range(len(emb.keypoint_ids))]
    return model, IKLayout(np.asarray(model.jnt_qposadr[joints]), np.asarray(model.jnt_dofadr[joints]),
                           np.asarray(sites), emb.q_limits)


class IKLayout:
    """Addresses of the actuated joints (qpos, dof), the keypoint sites, and the joint limits; the root's free
    joint is qpos 0..6 / dof 0..5."""

    def __init__(self, qpos_adr: np.ndarray, dof_adr: np.ndarray, site_ids: np.ndarray, limits: FloatArray) -> None:
        self.qpos_adr, self.dof_adr, self.site_ids, self.limits = qpos_adr, dof_adr, site_ids, limits
        self.cols = np.concatenate([np.arange(6), dof_adr])


def site_weights(emb: Embodiment) -> FloatArray:
    w = np.full(len(emb.keypoint_ids), OTHER_WEIGHT)
    w[list(emb.fingertips)] = TIP_WEIGHT
    w[[i for i, k in enumerate(emb.keypoint_ids) if k == 0]] = WRIST_WEIGHT
    return w


def rest_joints(emb: Embodiment) -> FloatArray:
    """The joints at rest: 0 where the range allows, else the nearer limit."""
    return np.clip(np.zeros(emb.num_joints), emb.q_limits[:, 0], emb.q_limits[:, 1])


def fit_mount(emb: Embodiment, human: HandReference) -> tuple[FloatArray, FloatArray]:
    """The root's pose in the human wrist frame (pos, quat): the description's mount, else the rigid alignment
    of the robot's sites at rest with the human hand's keypoints
    at rest (its fitted geometry, all hinges 0), both in their root frames."""
    mount = emb.description.mount
    if mount is not None:
        pos = np.asarray(mount.pos, dtype=np.float64)
        quat = np.asarray(mount.quat, dtype=np.float64)
        if emb.side != emb.description.model_side:  # the mirror image (``canonical.mirror_xml``)
            pos, quat = pos * np.array([1.0, -1.0, 1.0]), np.array([quat[0], -quat[1], quat[2], -quat[3]])
        return pos, quat / np.linalg.norm(quat)
    model, layout = ik_model(emb)
    data = mujoco.MjData(model)
    data.qpos[layout.qpos_adr] = rest_joints(emb)
    mujoco.mj_kinematics(model, data)
    robot = data.site_xpos[layout.site_ids]  # root frame (root at the origin)
    hand = local_keypoints(human.geometry, np.zeros((1, 45)))[0][list(emb.keypoint_ids)]
    rot, shift = kabsch(robot, hand[None])
    return shift[0], matrix_to_quat(rot[0])


def retarget_robot(human: HandReference, emb: Embodiment, fps: float | None = None) -> RobotReference:
    """The robot's reference for one recorded hand (see the module docstring); with ``fps``, within the joint
    speed limits."""
    model, layout = ik_model(emb)
    data = mujoco.MjData(model)
    ids = list(emb.keypoint_ids)
    targets = human.keypoints[:, ids]  # (T, J, 3)
    mount_pos, mount_quat = fit_mount(emb, human)
    nom_pos = human.wrist_pos + np.einsum("tij,j->ti", quat_to_matrix(human.wrist_quat), mount_pos)
    nom_quat = quat_mul(human.wrist_quat, np.broadcast_to(mount_quat, human.wrist_quat.shape))
    weights = site_weights(emb)
    n = len(targets)
    out_pos, out_quat = np.zeros((n, 3)), np.zeros((n, 4))
    out_q, out_sites = np.zeros((n, emb.num_joints)), np.zeros(targets.shape)
    data.qpos[:3], data.qpos[3:7] = nom_pos[0], nom_quat[0]
    data.qpos[layout.qpos_adr] = rest_joints(emb)
    q_prev = None
    for t in range(n):
        solve_frame(model, data, layout, targets[t], weights, (nom_pos[t], nom_quat[t]), q_prev,
                    FIRST_FRAME_ITERATIONS if t == 0 else ITERATIONS)
        q_prev = data.qpos[layout.qpos_adr].copy()
        out_pos[t], out_quat[t], out_q[t] = data.qpos[:3], data.qpos[3:7], q_prev
        out_sites[t] = data.site_xpos[layout.site_ids]
    if fps is not None:
        limited = speed_limited(out_q, emb.velocity_limits, fps, emb.q_limits)
        for t in np.flatnonzero((limited != out_q).any(axis=1)).tolist():
            data.qpos[:3], data.qpos[3:7], data.qpos[layout.qpos_adr] = out_pos[t], out_quat[t], limited[t]
            mujoco.mj_kinematics(model, data)
            out_sites[t] = data.site_xpos[layout.site_ids]
        out_q = limited
    # Sign-continuous quaternions, as the human wrist track is.
    flip = np.cumprod(np.r_[1.0, np.sign(np.sum(out_quat[1:] * out_quat[:-1], axis=1) + 1e-12)])
    return RobotReference(human.side, emb, out_pos, out_quat * flip[:, None], out_q, out_sites, targets,
                          human.valid.copy())


def solve_frame(model: mujoco.MjModel, data: mujoco.MjData, layout: IKLayout, targets: FloatArray,
                weights: FloatArray, nominal: tuple[FloatArray, FloatArray], q_prev: FloatArray | None,
                iterations: int) -> None:
    """Damped least-squares iterations from ``data.qpos`` towards the frame's targets (module docstring)."""
    nv = len(layout.cols)
    jac = np.zeros((3, model.nv))
    n_sites = len(layout.site_ids)
    big_j = np.zeros((3 * n_sites, nv))
    w = np.repeat(weights, 3)
    reg = np.zeros(nv)
    reg[:3], reg[3:6], reg[6:] = LAMBDA_ROOT_POS, LAMBDA_ROOT_ROT, LAMBDA_SMOOTH
    r_nom = quat_to_matrix(nominal[1])
    dq = np.zeros(model.nv)
    for _ in range(iterations):
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        err = (targets - data.site_xpos[layout.site_ids]).ravel()
        for i, s in enumerate(layout.site_ids):
            mujoco.mj_jacSite(model, data, jac, None, int(s))
            big_j[3 * i: 3 * i + 3] = jac[:, layout.cols]
        # Regularisation residuals in the free joint's velocity coordinates: linear in world, angular in the
        # root's own frame (MuJoCo's convention for free joints).
        r_root = quat_to_matrix(data.qpos[3:7])
        reg_err = np.zeros(nv)
        reg_err[:3] = nominal[0] - data.qpos[:3]
        reg_err[3:6] = r_root.T @ _log(r_nom @ r_root.T)
        if q_prev is not None:
            reg_err[6:] = q_prev - data.qpos[layout.qpos_adr]
        jw = big_j.T * w
        lhs = jw @ big_j + np.diag(reg + DAMPING)
        rhs = jw @ err + reg * reg_err
        step = np.linalg.solve(lhs, rhs)
        # Joints at a limit that the step pushes further out are held there and the rest solved again (an active
        # set): clipping alone stalls the whole solve against a limit.
        q = data.qpos[layout.qpos_adr]
        blocked = ((q <= layout.limits[:, 0] + 1e-9) & (step[6:] < 0)) | ((q >= layout.limits[:, 1] - 1e-9)
                                                                         & (step[6:] > 0))
        if blocked.any():
            free = np.concatenate([np.ones(6, dtype=bool), ~blocked])
            step = np.zeros(nv)
            step[free] = np.linalg.solve(lhs[np.ix_(free, free)], rhs[free])
        dq[:] = 0.0
        dq[layout.cols] = step
        mujoco.mj_integratePos(model, data.qpos, dq, 1.0)
        data.qpos[layout.qpos_adr] = np.clip(data.qpos[layout.qpos_adr], layout.limits[:, 0], layout.limits[:, 1])
        if np.abs(step).max() < 1e-7:
            break
    mujoco.mj_kinematics(model, data)


def _log(rot: FloatArray) -> FloatArray:
    """Rotation vector of a rotation matrix."""
    cos = np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    v = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if angle < 1e-9:
        return v / 2.0
    if np.pi - angle < 1e-6:  # near pi: the axis from the symmetric part
        axis = np.sqrt(np.maximum((np.diag(rot) + 1.0) / 2.0, 0.0))
        return axis * angle
    return v * angle / (2.0 * np.sin(angle))


def robot_references(human: list[HandReference], desc: HandDescription, fps: float | None = None
                     ) -> list[RobotReference]:
    """The recorded hands' references (``worker.hand.retarget.retarget_sequence``) retargeted to the robot hand
    ``desc`` describes, one per side; with ``fps`` (the recording's), within the joint speed limits."""
    return [retarget_robot(r, Embodiment.from_description(desc, r.side), fps) for r in human]
