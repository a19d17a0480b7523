"""Cheap real refinement results for tests of tools that read many of them (verify DIR, dataset export): a
12-frame synthetic push refined with one CMA-ES generation of 4 candidates (about a second each)."""

from __future__ import annotations

from common.job_options import JobOptions
from common.result_format import read_arrays, read_summary, write_result_npz
from common.sequence import Sequence

#: Job options that make a result in about a second (no restarts, one generation per window).
CHEAP_OPTIONS = JobOptions(popsize=4, max_generations=1, restarts=0)


def cheap_options(seed: int) -> JobOptions:
    return CHEAP_OPTIONS.model_copy(update={"seed": seed})


def push(frames: int = 12, offset_x: float = 0.0) -> Sequence:
    from tests.support.synthetic_push import push_sequence

    return push_sequence(frames=frames, offset_x=offset_x)


def cheap_result(seed: int = 0, offset_x: float = 0.0) -> bytes:
    """A refinement result file (bytes) of the synthetic push, as the worker's refinement writes it."""
    from worker.refine.run import refine_sequence

    outcome = refine_sequence(push(offset_x=offset_x), cheap_options(seed))
    return outcome.to_npz_bytes()


def forged(blob: bytes, key: str = "right_wrist_pos", delta: float = 0.05, from_frame: int = 6) -> bytes:
    """``blob`` with one stored array moved by ``delta`` from ``from_frame`` on (the rest left as it was)."""
    arrays = read_arrays(blob)
    moved = arrays[key].copy()
    moved[from_frame:] += delta
    arrays[key] = moved
    return write_result_npz(arrays, read_summary(blob))


def cheap_articulated_result() -> bytes:
    """A refinement result of the short hinged box (two hands, a lid on a hinge): contacts name the part touched."""
    from worker.example.hinged_box import short_hinged_box_sequence
    from worker.refine.run import refine_sequence

    options = CHEAP_OPTIONS.model_copy(update={"polish": False})
    return refine_sequence(short_hinged_box_sequence(), options).to_npz_bytes()
