"""Issue #18 "Must show": a rendered video (frame count, size, not blank, the lifted box rises), a Rerun recording
read back, plots, and the plain-MuJoCo export replayed in a fresh process with only mujoco + numpy.

All on one short real refinement (``tests/visual_fixtures.py``): the raw replay drops the box, the refined hand
lifts it 20 cm.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from common.cli import main as cli_main
from common.errors import UnsupportedFormatError
from common.geometry import rotation_error_deg
from common.result_format import read_arrays, read_summary
from worker.visual import Playback, read_mp4, read_recording, read_scalars, render_video, resimulate, write_recording
from worker.visual.render import OBJECT_RGBA
from worker.visual.standalone_replay import TOLERANCE_DEG, TOLERANCE_MM


@pytest.fixture(scope="module")
def playback(short_refine_result: bytes) -> Playback:
    return resimulate(short_refine_result, record_controls=True)


def object_pixels(panel: np.ndarray) -> np.ndarray:
    """(N, 2) row, column of the pixels showing the solid (orange) object."""
    rgb = panel.astype(np.int64)
    target = (np.array(OBJECT_RGBA[:3]) * 255).astype(np.int64)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    # Shading darkens the faces: same hue, lower value. Red well above blue, green in between.
    mask = (r > 0.55 * target[0]) & (r - b > 80) & (g > 0.45 * r) & (g < 0.85 * r)
    return np.argwhere(mask)


def test_resimulation_reproduces_the_stored_refined_trajectory(playback: Playback, short_refine_result: bytes) -> None:
    stored = read_arrays(short_refine_result)
    refined = playback.trajectories["refined"]
    assert np.allclose(refined.object_pose, stored["object_pose_sim"], atol=1e-9)
    assert np.allclose(refined.e_t_cm, stored["metrics_refined_e_t_cm"], atol=1e-9)
    # The raw replay is the one the refinement reported: same per-frame errors.
    assert np.allclose(playback.trajectories["raw"].e_t_cm, stored["metrics_raw_e_t_cm"], atol=1e-9)
    assert playback.trajectories["raw"].qpos.shape == (playback.num_frames, playback.scene.model.nq)


@pytest.mark.usefixtures("offscreen_gl")
def test_video_has_every_frame_is_not_blank_and_shows_the_lift(playback: Playback, tmp_path: Path) -> None:
    out = tmp_path / "preview.mp4"
    assert render_video(playback, str(out), ("raw", "refined"), 320, 240) == playback.num_frames
    frames, fps = read_mp4(out)
    assert frames.shape == (playback.num_frames, 240, 640, 3)
    assert fps == pytest.approx(playback.fps)
    for frame in frames:
        assert frame.std() > 10, "a blank frame"
        assert len(np.unique(frame.reshape(-1, 3)[::7], axis=0)) > 50
    # The refined hand lifts the box: its pixels rise (image rows decrease) as far as the simulated box does.
    refined = [object_pixels(f[:, 320:]) for f in (frames[0], frames[-1])]
    assert min(len(p) for p in refined) > 200, "the box is not visible"
    rise_px = refined[0][:, 0].mean() - refined[1][:, 0].mean()
    assert rise_px > 40, f"the lifted box moved only {rise_px:.1f} px up"
    lift_m = playback.trajectories["refined"].object_pose[-1, 2] - playback.trajectories["refined"].object_pose[0, 2]
    assert lift_m > 0.1
    # The raw replay drops it: its box stays near the table.
    raw = [object_pixels(f[:, :320]) for f in (frames[0], frames[-1])]
    assert abs(raw[0][:, 0].mean() - raw[1][:, 0].mean()) < rise_px / 3


def test_the_stored_preview_has_every_part_and_its_video_shows_the_lift(
    short_refine_result: bytes, tmp_path: Path
) -> None:
    """What a worker stores beside a result: the video (drawn on its own thread, without anti-aliasing), the plots,
    the recording and the export, all from one re-simulation."""
    import io
    import zipfile

    from worker.visual.preview import CLOSE_UP, EXPORT, PLOTS_PREFIX, RECORDING, VIDEO, preview_artifacts

    parts = {a.name: a for a in preview_artifacts(short_refine_result)}
    assert {VIDEO, RECORDING, EXPORT} <= set(parts) and CLOSE_UP not in parts  # the close-up only when asked
    assert sum(name.startswith(PLOTS_PREFIX) for name in parts) == 3
    (tmp_path / VIDEO).write_bytes(parts[VIDEO].data)
    frames, _ = read_mp4(tmp_path / VIDEO)
    refined = [object_pixels(f[:, 640:]) for f in (frames[0], frames[-1])]
    assert frames.shape[1:] == (480, 1280, 3) and min(len(p) for p in refined) > 800  # 640x480 panels
    assert refined[0][:, 0].mean() - refined[1][:, 0].mean() > 80  # the box rises, as with anti-aliasing
    names = zipfile.ZipFile(io.BytesIO(parts[EXPORT].data)).namelist()
    assert "export/scene.xml" in names and "export/controls.npz" in names
    (tmp_path / RECORDING).write_bytes(parts[RECORDING].data)
    assert read_recording(tmp_path / RECORDING)
    with pytest.raises(ValueError, match="samples"):
        render_video(resimulate(short_refine_result), str(tmp_path / "x.mp4"), samples=-1)


def test_rerun_recording_is_written_and_read_back(playback: Playback, tmp_path: Path) -> None:
    out = write_recording(playback, tmp_path / "run.rrd")
    assert out is not None and out.stat().st_size > 10_000
    entities = read_recording(out)
    for run in ("raw", "refined"):
        assert f"/world/{run}/object/object_0" in entities
        assert sum(1 for e in entities if e.startswith(f"/world/{run}/hand/")) == 16  # palm + 15 segments
        values = read_scalars(out, f"/metrics/E_t/{run}")
        assert values.shape == (playback.num_frames,)
        assert np.allclose(values, playback.trajectories[run].e_t_cm, atol=1e-6)
    assert "/world/recorded/hand_right" in entities
    assert entities["/world/refined/forces"] == playback.num_frames
    forces = read_scalars(out, "/forces/refined/thumb")
    assert forces.max() > 0.1  # the thumb presses the box while it is lifted


def _only_mujoco_and_numpy(tmp_path: Path) -> Path:
    """A folder holding links to the mujoco and numpy packages (and numpy's bundled libraries), nothing else."""
    import mujoco

    site = Path(np.__file__).resolve().parent.parent
    assert Path(mujoco.__file__).resolve().parent.parent == site
    sandbox = tmp_path / "site"
    sandbox.mkdir()
    for name in ("mujoco", "numpy", "numpy.libs"):
        if (site / name).exists():
            (sandbox / name).symlink_to(site / name)
    return sandbox


def test_export_replays_in_a_fresh_process_with_only_mujoco_and_numpy(playback: Playback, tmp_path: Path) -> None:
    from worker.visual import export_playback

    folder = export_playback(playback, tmp_path / "export")
    for name in ("scene.xml", "controls.npz", "trajectories.npz", "contacts.npz", "export.json", "replay.py"):
        assert (folder / name).is_file(), name
    meta = json.loads((folder / "export.json").read_text())
    assert meta["frames"] == playback.num_frames and "slerp" in meta["interpolation"]
    # -S: no site-packages; -s: no user site; PYTHONPATH: only the two packages. Anything else fails to import.
    env = {"PATH": os.environ.get("PATH", ""), "PYTHONPATH": str(_only_mujoco_and_numpy(tmp_path)),
           "MUJOCO_GL": "disable"}  # fmt: skip
    probe = subprocess.run([sys.executable, "-s", "-S", "-c", "import scipy"], env=env, capture_output=True,
                           text=True, cwd=tmp_path)  # fmt: skip
    assert probe.returncode != 0 and "No module named 'scipy'" in probe.stderr
    run = subprocess.run([sys.executable, "-s", "-S", "replay.py"], env=env, capture_output=True, text=True,
                         cwd=folder, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert "OK: the replay follows the stored trajectory" in run.stdout
    replayed = np.load(folder / "replayed_object_pose.npy")
    stored = playback.trajectories["refined"].object_pose
    pos_mm = 1000 * np.linalg.norm(replayed[:, :3] - stored[:, :3], axis=1)
    assert pos_mm.max() <= TOLERANCE_MM
    assert rotation_error_deg(replayed[:, 3:], stored[:, 3:]).max() <= TOLERANCE_DEG
    assert replayed[-1, 2] - replayed[0, 2] > 0.1  # the lift itself is replayed


@pytest.mark.usefixtures("offscreen_gl")
def test_plots_and_the_cli(short_refine_result: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    result = tmp_path / "short.npz"
    result.write_bytes(short_refine_result)
    assert cli_main(["plot", str(result)]) == 0
    plots = sorted((tmp_path / "short_plots").iterdir())
    assert [p.name for p in plots] == ["contact_forces.png", "errors.png", "loss_history.png"]
    for p in plots:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000
    assert cli_main(["render", str(result), "--which", "refined", "--size", "160x120", "--camera", "90,-10"]) == 0
    frames, _ = read_mp4(tmp_path / "short.mp4")
    assert frames.shape == (read_summary(short_refine_result)["frames"], 120, 160, 3)
    assert cli_main(["render", str(result), "--size", "161x120"]) == 2
    assert "--size" in capsys.readouterr().err
    assert cli_main(["render", str(result), "--camera", "nowhere"]) == 2
    assert cli_main(["view", str(result)]) == 0
    assert "/world/refined/object/object_0" in read_recording(tmp_path / "short.rrd")
    assert cli_main(["export", str(result)]) == 0
    assert (tmp_path / "short_export" / "replay.py").is_file() and (tmp_path / "short_export" / "scene.xml").is_file()
    assert cli_main(["render", str(tmp_path / "missing.npz")]) == 2


@pytest.mark.usefixtures("osmesa_gl")
def test_the_osmesa_fallback_renders_the_same_video(short_refine_result: bytes, tmp_path: Path) -> None:
    """``MUJOCO_GL=osmesa`` (set before the process starts, as the help says) renders through Debian's OSMesa."""
    result = tmp_path / "short.npz"
    result.write_bytes(short_refine_result)
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa", "PYTHONPATH": str(root)}
    code = f"import sys; from common.cli import main; sys.exit(main(['render', {str(result)!r}, '--size', '96x64']))"
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    frames, _ = read_mp4(tmp_path / "short.mp4")
    assert frames.shape == (read_summary(short_refine_result)["frames"], 64, 192, 3)
    assert frames.std() > 10


@pytest.mark.usefixtures("offscreen_gl")
def test_a_raw_replay_result_with_its_sequence(tmp_path: Path) -> None:
    from common.sequence_io import sequence_to_npz_bytes
    from worker.example import short_example_sequence
    from worker.simulation.replay import raw_replay, replay_result_bytes

    seq = short_example_sequence()
    raw = raw_replay(seq)
    result, sequence = tmp_path / "raw.npz", tmp_path / "seq.npz"
    result.write_bytes(replay_result_bytes(raw))
    sequence.write_bytes(sequence_to_npz_bytes(seq))
    with pytest.raises(UnsupportedFormatError, match="--sequence"):
        resimulate(result.read_bytes())
    pb = resimulate(result.read_bytes(), seq)  # checked against the stored raw replay inside
    assert list(pb.trajectories) == ["raw"]
    assert np.array_equal(pb.trajectories["raw"].object_pose, raw.record.object_pose)
    with pytest.raises(UnsupportedFormatError, match="trajectories"):
        resimulate(result.read_bytes(), seq, which=("refined",))
    assert cli_main(["render", str(result), "--sequence", str(sequence), "--size", "64x48"]) == 0
    assert read_mp4(tmp_path / "raw.mp4")[0].shape == (seq.num_frames, 48, 64, 3)
    assert cli_main(["export", str(result), "--sequence", str(sequence)]) == 0
    assert json.loads((tmp_path / "raw_export" / "export.json").read_text())["trajectory"] == "raw"


def test_a_file_that_is_not_a_refinement_is_refused(tmp_path: Path) -> None:
    from tests.support.queue_fixtures import fake_result

    blob, _ = fake_result()
    with pytest.raises(UnsupportedFormatError, match="not a refinement or raw-replay result"):
        resimulate(blob)
    with pytest.raises(UnsupportedFormatError, match="no such result file"):
        from worker.visual import load_result

        load_result(tmp_path / "missing.npz")
    with pytest.raises(UnsupportedFormatError, match="is a folder, not a result file"):
        load_result(tmp_path)
