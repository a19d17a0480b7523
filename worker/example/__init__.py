"""The built-in example: a synthetic grasp-and-lift of a box by the right template hand, with vision-like
errors in the observed hand, so the whole pipeline runs with no data and no MANO licence. Its grasp is solved
once (``grasp_synthesis`` + ``grasp_hold``) and shipped (``grasp_file``).
"""

from worker.example.box_geometry import BOX_HALF, MASS_KG
from worker.example.sequences import Timeline, example_sequence, short_example_sequence, synthetic_grasp_and_lift

__all__ = [
    "BOX_HALF",
    "MASS_KG",
    "Timeline",
    "example_sequence",
    "short_example_sequence",
    "synthetic_grasp_and_lift",
]
