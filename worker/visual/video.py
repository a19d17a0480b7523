"""MP4 files from RGB frames with imageio-ffmpeg (it ships its own ffmpeg binary: nothing to install).

H.264 in yuv420p with the index at the front (``+faststart``), so browsers play it while it downloads.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

Frame = npt.NDArray[np.uint8]


def write_mp4(frames: Iterable[Frame], path: Path | str, fps: float, quality: int = 23) -> int:
    """Write (H, W, 3) uint8 frames (H and W even) to ``path``; returns the number of frames written.

    ``quality``: x264's constant rate factor (lower is better, 23 its default)."""
    import imageio_ffmpeg

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer: Any = None  # imageio-ffmpeg's generator: send(frame), close()
    count = 0
    try:
        for frame in frames:
            if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
                raise ValueError(f"frames must be (H, W, 3) uint8, got {frame.shape} {frame.dtype}")
            if writer is None:
                h, w = frame.shape[:2]
                if h % 2 or w % 2:
                    raise ValueError(f"frame size must be even for yuv420p, got {w}x{h}")
                writer = imageio_ffmpeg.write_frames(
                    str(path), (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p", macro_block_size=2,
                    output_params=["-crf", str(quality), "-movflags", "+faststart"], ffmpeg_log_level="error",
                )  # fmt: skip
                writer.send(None)  # start the ffmpeg process
            writer.send(np.ascontiguousarray(frame))
            count += 1
    finally:
        if writer is not None:
            writer.close()
    if count == 0:
        raise ValueError("no frames to write")
    return count


def read_mp4(path: Path | str) -> tuple[npt.NDArray[np.uint8], float]:
    """All frames of a video as (N, H, W, 3) uint8 and its frame rate (for checks and tests)."""
    import subprocess

    import imageio_ffmpeg

    # The size and rate from imageio-ffmpeg's header parsing; closing the generator at once stops its ffmpeg.
    # The frames from one ffmpeg run whose pipes subprocess closes (imageio-ffmpeg's reader leaves a finished
    # process's stdout open).
    reader = imageio_ffmpeg.read_frames(str(path))
    try:
        meta = next(reader)
    finally:
        reader.close()
    w, h = meta["size"]
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "rgb24", "-"]
    raw = subprocess.run(cmd, capture_output=True, check=True).stdout
    frames = np.frombuffer(raw, dtype=np.uint8).reshape(-1, h, w, 3)
    return frames, float(meta["fps"])
