"""Seeing and taking away results (issue #18): videos, Rerun recordings, plots and a plain-MuJoCo export.

Science-side only: nothing here imports Ray, SQLAlchemy, FastAPI or the queue. A result is rebuilt with the
same code ``hoi-refine verify`` uses (``resimulate``), then drawn (``render_video``), logged
(``write_recording``), plotted (``write_plots``, from the file alone) or exported (``export_result``);
``preview_artifacts`` makes what the service stores for a finished job.

The names below load their module on first use: rendering must pick its OpenGL backend before MuJoCo is
imported (``worker.visual.gl``), and ``hoi-refine --help`` stays fast.
"""

from __future__ import annotations

import importlib
from typing import Any

_PUBLIC: dict[str, str] = {
    "CameraSpec": "render",
    "auto_camera": "render",
    "parse_camera": "render",
    "render_frames": "render",
    "render_video": "render",
    "Playback": "playback",
    "Trajectory": "playback",
    "contact_force_per_finger": "playback",
    "load_result": "playback",
    "resimulate": "playback",
    "write_plots": "plots",
    "export_playback": "export",
    "export_result": "export",
    "PreviewArtifact": "preview",
    "preview_artifacts": "preview",
    "read_recording": "rerun_log",
    "read_scalars": "rerun_log",
    "write_recording": "rerun_log",
    "read_mp4": "video",
    "write_mp4": "video",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'worker.visual' has no attribute {name!r}")
    return getattr(importlib.import_module(f"worker.visual.{_PUBLIC[name]}"), name)
