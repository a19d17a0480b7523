"""Retargeting a recorded hand to a robot: the project's damped least squares (``worker/robot/retarget.py``) against
the ``mink`` IK library (PyPI, QP-based differential IK on MuJoCo) with the same objective, on DexYCB dev sequences.

    pip install mink          # bench only: not a dependency of the product
    python bench/robot_retarget.py --robot-dir /path/to/dex-urdf --per-side 3 --out bench/results/robot_retarget.md

Both solve every frame from the previous frame's solution with the same weights (fingertips 1, other keypoints and
the wrist 0.02: ``retarget.TIP_WEIGHT`` etc.), the same pull of the root towards the recorded wrist and mount, the
same smoothness to the previous frame and the joint limits, and the same iteration budget (``retarget.ITERATIONS``,
``FIRST_FRAME_ITERATIONS``). Reported: the fingertip residual (mean distance of the robot's fingertip sites to the
recorded fingertips, mm), all sites' residual, and the time per frame.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common.geometry import quat_mul, quat_to_matrix  # noqa: E402
from common.sequence_io import load_sequence  # noqa: E402
from worker.hand.retarget import retarget_sequence  # noqa: E402
from worker.robot import Embodiment, resolve_hand  # noqa: E402
from worker.robot import retarget as R  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "dexycb" / "dev"


def sample(per_side: int) -> list[str]:
    names = [n.split("#")[0].strip() for n in (ROOT / "bench/samples/dev120.txt").read_text().splitlines()]
    sides: dict[str, list[str]] = {"right": [], "left": []}
    for name in filter(None, names):
        with np.load(DATA / name) as z:
            side = str(z["side"])
        if len(sides[side]) < per_side:
            sides[side].append(name)
    return sides["right"] + sides["left"]


def mink_retarget(human: R.HandReference, emb: Embodiment) -> tuple[np.ndarray, float]:
    """(T, J, 3) site positions solved by mink, and seconds per frame."""
    import mink

    model, layout = R.ik_model(emb)
    ids = list(emb.keypoint_ids)
    targets = human.keypoints[:, ids]
    mount_pos, mount_quat = R.fit_mount(emb, human)
    nom_pos = human.wrist_pos + np.einsum("tij,j->ti", quat_to_matrix(human.wrist_quat), mount_pos)
    nom_quat = quat_mul(human.wrist_quat, np.broadcast_to(mount_quat, human.wrist_quat.shape))
    weights = R.site_weights(emb)
    q0 = model.qpos0.copy()
    q0[:3], q0[3:7] = nom_pos[0], nom_quat[0]
    q0[layout.qpos_adr] = R.rest_joints(emb)
    config = mink.Configuration(model, q0)
    site_tasks = [mink.FrameTask(f"{emb.side}_kp{j}", "site", position_cost=float(np.sqrt(w)), orientation_cost=0.0)
                  for j, w in enumerate(weights)]
    root_name = f"{emb.side}_palm"
    root_task = mink.FrameTask(root_name, "body", position_cost=float(np.sqrt(R.LAMBDA_ROOT_POS)),
                               orientation_cost=float(np.sqrt(R.LAMBDA_ROOT_ROT)))
    posture = mink.PostureTask(model, cost=float(np.sqrt(R.LAMBDA_SMOOTH)))
    limits = [mink.ConfigurationLimit(model)]
    out = np.zeros(targets.shape)
    data = mujoco.MjData(model)
    t0 = time.perf_counter()
    for t in range(len(targets)):
        for task, target in zip(site_tasks, targets[t], strict=True):
            task.set_target(mink.SE3.from_translation(target))
        root_task.set_target(mink.SE3.from_rotation_and_translation(mink.SO3(nom_quat[t]), nom_pos[t]))
        posture.set_target(config.q.copy())
        for _ in range(R.FIRST_FRAME_ITERATIONS if t == 0 else R.ITERATIONS):
            vel = mink.solve_ik(config, [*site_tasks, root_task, posture], 1.0, "daqp", damping=R.DAMPING,
                                limits=limits)
            config.integrate_inplace(vel, 1.0)
        data.qpos[:] = config.q
        mujoco.mj_kinematics(model, data)
        out[t] = data.site_xpos[layout.site_ids]
    return out, (time.perf_counter() - t0) / len(targets)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot-dir", type=Path, required=True)
    ap.add_argument("--per-side", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "bench/results/robot_retarget.md")
    args = ap.parse_args()
    rows = []
    for name in sample(args.per_side):
        human = retarget_sequence(load_sequence(DATA / name))[0]
        for hand in ("allegro", "leap"):
            desc = resolve_hand(hand, args.robot_dir)
            assert desc is not None
            emb = Embodiment.from_description(desc, human.side)
            t0 = time.perf_counter()
            ours = R.retarget_robot(human, emb)
            ours_s = (time.perf_counter() - t0) / ours.num_frames
            mink_sites, mink_s = mink_retarget(human, emb)
            tips = list(emb.fingertips)
            target = ours.human_keypoints
            row = (name.removesuffix(".npz"), human.side, hand,
                   1000 * np.linalg.norm(ours.keypoints[:, tips] - target[:, tips], axis=-1).mean(),
                   1000 * np.linalg.norm(mink_sites[:, tips] - target[:, tips], axis=-1).mean(),
                   1000 * np.linalg.norm(ours.keypoints - target, axis=-1).mean(),
                   1000 * np.linalg.norm(mink_sites - target, axis=-1).mean(), 1000 * ours_s, 1000 * mink_s)
            rows.append(row)
            print(" ".join(f"{v:.1f}" if isinstance(v, float) else str(v) for v in row), flush=True)
    arr = np.array([r[3:] for r in rows], dtype=float)
    lines = ["# Retargeting to a robot hand: our damped least squares vs mink (bench/robot_retarget.py)", "",
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.machine()} "
             f"({_cpu()}), 2 cores shared with other engineers' work (load average above 10: the times are "
             "inflated alike for both), one thread. The same objective, weights and iteration budget for both "
             f"(module docstring); first {args.per_side} right and left sequences of bench/samples/dev120.txt.", "",
             "| | fingertips mm (ours) | fingertips mm (mink) | all sites mm (ours) | all sites mm (mink) | "
             "ms/frame (ours) | ms/frame (mink) |", "|---|---|---|---|---|---|---|"]
    for hand in ("allegro", "leap"):
        sel = np.array([r[2] == hand for r in rows])
        means = " | ".join(f"{v:.1f}" for v in arr[sel].mean(0))
        lines.append(f"| {hand} (mean of {int(sel.sum())}) | {means} |")
    lines += ["", "| sequence | side | hand | tips ours | tips mink | all ours | all mink | ms ours | ms mink |",
              "|---|---|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(f"{v:.1f}" if isinstance(v, float) else str(v) for v in r) + " |" for r in rows]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


def _cpu() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown CPU"


if __name__ == "__main__":
    raise SystemExit(main())
