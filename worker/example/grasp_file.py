"""The example's solved grasp: solved by least squares (``grasp_synthesis``), its thumb chosen by simulation
(``grasp_hold``), shipped in ``worker/example/data/example_grasp.npz`` and read back by ``cached_box_grasp``
(``python -m worker.example.grasp_file`` solves it again and rewrites the file).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from common.geometry import FloatArray
from worker.example.box_geometry import BOX_HALF, MASS_KG, BoxGrasp
from worker.example.grasp_hold import select_thumb
from worker.example.grasp_synthesis import close_to_contact, synthesize_box_grasp
from worker.hand.model import JOINT_LOWER, JOINT_UPPER, TEMPLATE_HAND_LENGTH, HandGeometry, default_geometry

#: The solved example grasp shipped with the package (solving takes ~40 s on 2 shared cores).
GRASP_FILE = Path(__file__).parent / "data" / "example_grasp.npz"
_GRASP_VERSION = 2


def _grasp_key(hand_length: float, half: tuple[float, float, float], mass: float) -> FloatArray:
    return np.array([_GRASP_VERSION, hand_length, *half, mass], dtype=np.float64)


def finalize_grasp(geometry: HandGeometry, grasp: BoxGrasp, half: FloatArray, mass: float) -> BoxGrasp:
    """Stop each finger 4 mm inside the box (``close_to_contact``), then choose the thumb by simulated holding
    (``grasp_hold``); the open hand is a quarter of the final hinge angles."""
    q = close_to_contact(geometry, grasp, half, penetration=0.004)
    q = select_thumb(geometry, grasp, q, np.asarray(half), mass)
    q_open = np.clip(0.25 * q, JOINT_LOWER, JOINT_UPPER)
    q_open[:9] = 0.0  # the thumb comes in straight (its closing path is checked against the box)
    return BoxGrasp(grasp.wrist_rot, grasp.wrist_pos, q, q_open, grasp.cost)


def write_grasp_file(
    hand_length: float, half: tuple[float, float, float], mass: float, path: Path = GRASP_FILE
) -> BoxGrasp:
    """Solve, finalise and store the example grasp (``python -m worker.example.grasp_file`` rewrites it)."""
    geometry = default_geometry("right", hand_length)
    grasp = finalize_grasp(geometry, synthesize_box_grasp(geometry, np.array(half)), np.array(half), mass)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        path,
        key=_grasp_key(hand_length, half, mass),
        wrist_rot=grasp.wrist_rot,
        wrist_pos=grasp.wrist_pos,
        q=grasp.q,
        q_open=grasp.q_open,
        cost=np.array(grasp.cost),
    )
    return grasp


@lru_cache(maxsize=4)
def cached_box_grasp(hand_length: float, half: tuple[float, float, float], mass: float) -> BoxGrasp:
    """The finalised box grasp for the right template hand of ``hand_length``: read from the shipped file when
    it was made for these inputs, else solved now (~1 min; memoised per process)."""
    if GRASP_FILE.is_file():
        with np.load(GRASP_FILE) as data:
            key = _grasp_key(hand_length, half, mass)
            if data["key"].shape == key.shape and np.allclose(data["key"], key):
                return BoxGrasp(
                    wrist_rot=data["wrist_rot"],
                    wrist_pos=data["wrist_pos"],
                    q=data["q"],
                    q_open=data["q_open"],
                    cost=float(data["cost"]),
                )
    geometry = default_geometry("right", hand_length)
    return finalize_grasp(geometry, synthesize_box_grasp(geometry, np.array(half)), np.array(half), mass)


if __name__ == "__main__":
    solved = write_grasp_file(TEMPLATE_HAND_LENGTH, BOX_HALF, MASS_KG)
    print(f"wrote {GRASP_FILE} (residual {solved.cost:.4f})")
