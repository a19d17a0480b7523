"""What the service keeps beside a finished job's result (issue #18 item 4): a cheap preview.

One re-simulation (raw replay and refined, with the refined controls recorded) feeds the video (640x480 per
panel, every frame, the camera framing the hands and object: ``render.auto_camera``), optionally a close-up video
(the same panels, the camera following the recorded object with the fingers at it: ``auto_camera(close_up=True)``),
the Rerun recording and the plain-MuJoCo export (zipped); the plots come from the file alone. The worker stores
them with the result (``worker.runtime``); the API serves them by name.
"""

from __future__ import annotations

import io
import tempfile
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

VIDEO = "video.mp4"
CLOSE_UP = "close_up.mp4"
RECORDING = "recording.rrd"
EXPORT = "export.zip"
PLOTS_PREFIX = "plots/"
PREVIEW_SIZE = (640, 480)  # ``render.PANEL_SIZE`` (this module imports MuJoCo only once the backend is chosen)
#: No multisample anti-aliasing in the stored video: on the software renderer of a CPU worker the 4x default was
#: a third of the preview's drawing time (``hoi-refine render`` keeps it).
PREVIEW_SAMPLES = 0


@dataclass(frozen=True)
class PreviewArtifact:
    name: str  # VIDEO, CLOSE_UP, RECORDING, EXPORT or PLOTS_PREFIX + file name
    content_type: str
    data: bytes


def preview_artifacts(
    blob: bytes,
    size: tuple[int, int] = PREVIEW_SIZE,
    recording: bool = True,
    export: bool = True,
    *,
    close_up: bool = False,
    cache_dir: Path | None = None,
    mano_dir: Path | None = None,
) -> list[PreviewArtifact]:
    """The preview of a refinement result: video, plots and (optionally) the close-up video, recording and export.
    ``cache_dir``, ``mano_dir``: as for ``resimulate``."""
    from worker.visual.gl import prefer_offscreen_backend

    prefer_offscreen_backend()
    from worker.visual.export import export_playback
    from worker.visual.playback import resimulate
    from worker.visual.plots import write_plots
    from worker.visual.render import auto_camera, render_video
    from worker.visual.rerun_log import write_recording

    out: list[PreviewArtifact] = []
    pb = resimulate(blob, record_controls=export, cache_dir=cache_dir, mano_dir=mano_dir)
    with tempfile.TemporaryDirectory(prefix="hoi-refine-preview-") as tmp, ThreadPoolExecutor(1) as pool:
        root = Path(tmp)
        # The video draws on its own thread (the GL calls and the encoder release the GIL) while this one makes
        # the plots, the recording and the export: the preview runs after every job, on one core otherwise.
        video = pool.submit(render_video, pb, str(root / VIDEO), ("raw", "refined"), size[0], size[1],
                            samples=PREVIEW_SAMPLES)
        # The close-up after it on the same thread: one GL context at a time.
        near = None if not close_up else pool.submit(
            render_video, pb, str(root / CLOSE_UP), ("raw", "refined"), size[0], size[1],
            auto_camera(pb, size=size, close_up=True), samples=PREVIEW_SAMPLES)  # fmt: skip
        plots = write_plots(blob, root / "plots")
        if recording:
            write_recording(pb, root / RECORDING)
        folder = export_playback(pb, root / "export") if export else None
        video.result()
        out.append(PreviewArtifact(VIDEO, "video/mp4", (root / VIDEO).read_bytes()))
        if near is not None:
            near.result()
            out.append(PreviewArtifact(CLOSE_UP, "video/mp4", (root / CLOSE_UP).read_bytes()))
        for path in plots:
            out.append(PreviewArtifact(PLOTS_PREFIX + path.name, "image/png", path.read_bytes()))
        if recording:
            out.append(PreviewArtifact(RECORDING, "application/octet-stream", (root / RECORDING).read_bytes()))
        if folder is not None:
            out.append(PreviewArtifact(EXPORT, "application/zip", _zip(folder, "export")))
    return out


def _zip(folder: Path, top: str) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                zf.write(path, f"{top}/{path.relative_to(folder)}")
    return buf.getvalue()
