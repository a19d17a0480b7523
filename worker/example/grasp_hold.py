"""Pick the example grasp's thumb by simulation: among sampled thumb poses that touch the box, the one that
holds it best while the hand lifts (DESIGN §1.4 physics, default ``SimConfig``).

The least-squares grasp (``grasp_synthesis``) places the finger pads on the box, but whether a grasp *holds*
depends on contact details the kinematic residual cannot see; a short simulated squeeze-and-lift per candidate
(0.75 s, ~40 ms each) decides. Seeded and deterministic.
"""

from __future__ import annotations

import mujoco
import numpy as np

from common.geometry import FloatArray, matrix_to_quat
from common.sequence import HandTrack, ObjectSpec, Sequence
from worker.example.box_geometry import BoxGrasp, box_sdf, capsule_samples
from worker.hand.model import JOINT_LOWER, JOINT_UPPER, HandGeometry, forward_keypoints
from worker.hand.reference import HandReference
from worker.simulation.scene import build_scene
from worker.simulation.stepping import HandTargets, pose_hands


def _candidates(
    geometry: HandGeometry, grasp: BoxGrasp, q: FloatArray, half: FloatArray, n: int, seed: int
) -> FloatArray:
    """Thumb samples (k,45) whose pad sinks 2-6 mm into the box while the rest of the thumb stays outside,
    ordered by how far towards the -x face (opposite the fingers) the thumb tip lies."""
    rng = np.random.default_rng(seed)
    samples = np.tile(q, (n, 1))
    samples[:, :9] = rng.uniform(JOINT_LOWER[:9], JOINT_UPPER[:9], (n, 9))
    pts, radii, tips = capsule_samples(geometry, samples)
    world = pts[:, 0] @ grasp.wrist_rot.T + grasp.wrist_pos
    clearance = box_sdf(world, half) - radii[:, 0]
    pad = clearance[:, 2, 4:].min(axis=1)
    rest = np.concatenate([clearance[:, :2].reshape(n, -1), clearance[:, 2, :4]], axis=1).min(axis=1)
    tip_x = (tips[:, 0] @ grasp.wrist_rot.T + grasp.wrist_pos)[:, 0]
    ok = np.flatnonzero((pad < -0.002) & (pad > -0.006) & (rest > 0.0))
    # The thumb closes from straight (all zeros) along a straight line in hinge space: it must not sweep
    # through the box on the way (it would knock the box over before the grasp forms).
    clear_path = np.ones(len(ok), dtype=bool)
    for alpha in np.linspace(0.0, 0.85, 12):
        path = samples[ok].copy()
        path[:, :9] *= alpha
        p_pts, p_radii, _ = capsule_samples(geometry, path)
        p_world = p_pts[:, 0] @ grasp.wrist_rot.T + grasp.wrist_pos
        clear_path &= (box_sdf(p_world, half) - p_radii[:, 0]).min(axis=(1, 2)) > -0.0005
    ok = ok[clear_path]
    return samples[ok[np.argsort(tip_x[ok])]]


def select_thumb(
    geometry: HandGeometry,
    grasp: BoxGrasp,
    q: FloatArray,
    half: FloatArray,
    mass: float,
    n: int = 20000,
    top: int = 80,
    seed: int = 1,
) -> FloatArray:
    """Hinges ``q`` (45,) with the thumb replaced by the sampled pose that best holds the box while lifting."""
    cands = _candidates(geometry, grasp, q, half, n, seed)[:top]
    if len(cands) == 0:
        return q
    wpos = grasp.wrist_pos + np.array([0.0, 0.0, half[2]])  # box resting on the table
    wquat = matrix_to_quat(grasp.wrist_rot)
    frames = 2
    pos_t, quat_t, q_t = np.tile(wpos, (frames, 1)), np.tile(wquat, (frames, 1)), np.tile(q, (frames, 1))
    seq = Sequence(
        name="grasp-hold",
        fps=30.0,
        object=ObjectSpec(name="box", mass_kg=mass, primitive="box", size=np.asarray(half)),
        object_pose=np.tile([0.0, 0.0, half[2], 1.0, 0.0, 0.0, 0.0], (frames, 1)),
        hands=[HandTrack("right", np.ones(frames, dtype=bool), forward_keypoints(geometry, pos_t, quat_t, q_t))],
        world_from_source=np.eye(4),
    ).validate()
    ref = HandReference("right", geometry, pos_t, quat_t, q_t, np.zeros((frames, 21, 3)), np.ones(frames, bool),
                        np.zeros(frames))  # fmt: skip
    scene = build_scene(seq, [ref])
    model, data = scene.model, scene.make_data()
    a = scene.object_qpos_adr
    errors = []
    for cand in cands:
        mujoco.mj_resetData(model, data)
        pose_hands(scene, data, {"right": HandTargets(np.tile(cand, (frames, 1)), pos_t, quat_t)}, 0)
        data.qpos[a : a + 7] = [0.0, 0.0, half[2], 1.0, 0.0, 0.0, 0.0]
        for _ in range(60):  # squeeze on the table for 0.25 s
            mujoco.mj_step(model, data)
        for k in range(120):  # lift 6 cm in 0.42 s, hold
            data.mocap_pos[0] = wpos + np.array([0.0, 0.0, 0.06 * min(1.0, (k + 1) / 100)])
            mujoco.mj_step(model, data)
        target = np.array([0.0, 0.0, half[2] + 0.06])
        errors.append(float(np.linalg.norm(data.qpos[a : a + 3] - target)))
    return np.asarray(cands[int(np.argmin(errors))])
