"""A sequence at a whole multiple of its frame rate (issue #52 item 6: the method's OakInk-V2 protocol runs at 60 Hz).

Frame ``i`` of the result is time ``i / factor`` of the original: object positions, hand keypoints and joint values
interpolate linearly, object rotations by slerp; a new frame's hand is valid when both original frames around it
are. Hands given only as MANO parameters are refused (decode them first): interpolating axis-angle poses is not
interpolating the hand.
"""

from __future__ import annotations

import numpy as np

from common.geometry import slerp_frames
from common.sequence import HandTrack, Sequence


def _lerp(values: np.ndarray, times: np.ndarray) -> np.ndarray:
    i0 = np.minimum(np.floor(times).astype(np.int64), len(values) - 2)
    u = (times - i0).reshape((-1,) + (1,) * (values.ndim - 1))
    return np.asarray((1 - u) * values[i0] + u * values[i0 + 1])


def resample_sequence(seq: Sequence, factor: int) -> Sequence:
    """``seq`` at ``factor`` times its frame rate ((T - 1) * factor + 1 frames over the same span)."""
    if not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor must be a positive integer, got {factor!r}")
    if factor == 1:
        return seq
    times = np.arange((seq.num_frames - 1) * factor + 1, dtype=np.float64) / factor
    pose = seq.object_pose
    object_pose = np.concatenate([_lerp(pose[:, :3], times), slerp_frames(pose[:, 3:], times)], axis=1)
    hands = []
    for hand in seq.hands:
        if hand.keypoints is None:
            raise ValueError(f"the {hand.side} hand has no keypoints: decode its MANO parameters before resampling")
        i0 = np.minimum(np.floor(times).astype(np.int64), seq.num_frames - 2)
        valid = hand.valid[i0] & hand.valid[i0 + 1] | (times == i0) & hand.valid[i0]
        hands.append(HandTrack(side=hand.side, valid=np.asarray(valid, dtype=bool),
                               keypoints=_lerp(hand.keypoints, times)))  # fmt: skip
    return Sequence(
        name=f"{seq.name}__x{factor}", fps=seq.fps * factor, object=seq.object, object_pose=object_pose, hands=hands,
        frame_start=seq.frame_start * factor, world_from_source=seq.world_from_source, up=seq.up,
        meta={**seq.meta, "resampled": f"x{factor} from {seq.fps:g} fps"},
        articulation=None if seq.articulation is None else _lerp(seq.articulation, times),
    ).validate()
