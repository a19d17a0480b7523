"""A video that shows the grasp (issue #53 item 7): the automatic camera holds the hand(s) and the object of every
frame, checked with MuJoCo's own camera (the points projected, no pixels read); it fills the view instead of leaving
the hand a corner; a two-handed sequence keeps both hands in view; the close-up follows the object with the fingers
at it; the default panel is 640x480 and ``hoi-refine render --close-up`` writes that view."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from common.geometry import FloatArray
from common.sequence import Sequence
from worker.visual.framing import View, project
from worker.visual.playback import Playback, resimulate
from worker.visual.render import (
    CLOSE_UP_NEAR_M,
    NEAR_OBJECT_M,
    PANEL_SIZE,
    CameraSpec,
    auto_camera,
    caption_band,
    framing_points,
)


def _raw_playback(seq: Sequence) -> Playback:
    from worker.simulation.replay import raw_replay, replay_result_bytes

    return resimulate(replay_result_bytes(raw_replay(seq)), seq)


@pytest.fixture(scope="module")
def one_hand() -> Playback:
    from worker.example import short_example_sequence

    return _raw_playback(short_example_sequence())


@pytest.fixture(scope="module")
def two_hands() -> Playback:
    from worker.example.hinged_box import short_hinged_box_sequence

    return _raw_playback(short_hinged_box_sequence())


def mujoco_projection(playback: Playback, spec: CameraSpec, points: FloatArray, frame: int = 0) -> FloatArray:
    """(N, 2) normalised image coordinates (x right, y up, -1..1) of ``points`` through the camera MuJoCo renders
    with for ``spec`` at ``frame`` (``mjv_updateScene``'s two eyes averaged, as ``mjr_render`` draws a mono view)."""
    model = playback.scene.model
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = spec.lookat if spec.track is None else spec.track[frame]
    cam.distance, cam.azimuth, cam.elevation = spec.distance, spec.azimuth, spec.elevation
    scene = mujoco.MjvScene(model, 100)
    mujoco.mjv_updateScene(model, data, mujoco.MjvOption(), None, cam, mujoco.mjtCatBit.mjCAT_ALL, scene)
    eye = mujoco.mjv_averageCamera(scene.camera[0], scene.camera[1])
    forward, up = np.asarray(eye.forward), np.asarray(eye.up)
    right = np.cross(forward, up)
    rel = np.asarray(points) - np.asarray(eye.pos)
    depth = rel @ forward
    half_height = eye.frustum_top / eye.frustum_near  # tan(fovy / 2)
    aspect = PANEL_SIZE[0] / PANEL_SIZE[1]
    assert (depth > 0).all()
    return np.stack([(rel @ right) / (depth * half_height * aspect), (rel @ up) / (depth * half_height)], axis=1)


def _finite(points: FloatArray) -> FloatArray:
    flat = np.asarray(points).reshape(-1, 3)
    return flat[np.isfinite(flat).all(axis=1)]


def _top_below_caption() -> float:
    return 1.0 - 2.0 * caption_band(PANEL_SIZE[1]) / PANEL_SIZE[1]


def _assert_in_view(xy: FloatArray) -> None:
    assert np.abs(xy[:, 0]).max() <= 1.0, xy[:, 0].max()
    assert xy[:, 1].min() >= -1.0 and xy[:, 1].max() <= _top_below_caption(), (xy[:, 1].min(), xy[:, 1].max())


def test_the_camera_holds_the_hand_and_object_of_every_frame_and_fills_the_view(one_hand: Playback) -> None:
    spec = auto_camera(one_hand)
    objects, hands = framing_points(one_hand, NEAR_OBJECT_M, whole_hand=True)
    object_xy = mujoco_projection(one_hand, spec, _finite(objects))
    hand_xy = mujoco_projection(one_hand, spec, _finite(hands["right"]))
    assert len(hand_xy) >= 21 * one_hand.num_frames // 2  # the hand is near the object over most of the sequence
    for xy in (object_xy, hand_xy):
        _assert_in_view(xy)
    # Fitted, not padded: the points span most of the image one way or the other.
    both = np.concatenate([object_xy, hand_xy])
    span = both.max(axis=0) - both.min(axis=0)
    assert span[0] > 1.4 or span[1] > 1.4, span
    # ``framing.project`` is the same projection.
    view = View(np.asarray(spec.lookat), spec.distance, spec.azimuth, spec.elevation)
    fovy = float(one_hand.scene.model.vis.global_.fovy)
    assert np.allclose(project(_finite(objects), view, fovy, PANEL_SIZE[0] / PANEL_SIZE[1]), object_xy, atol=1e-9)


def test_a_two_handed_sequence_keeps_both_hands_in_view(two_hands: Playback) -> None:
    spec = auto_camera(two_hands)
    objects, hands = framing_points(two_hands, NEAR_OBJECT_M, whole_hand=True)
    assert set(hands) == {"left", "right"}
    _assert_in_view(mujoco_projection(two_hands, spec, _finite(objects)))
    for side, points in hands.items():
        assert len(_finite(points)), side
        _assert_in_view(mujoco_projection(two_hands, spec, _finite(points)))
    # The view looks across the line between the hands (neither hides the other): their centres sit apart.
    centres = [mujoco_projection(two_hands, spec, _finite(p)).mean(axis=0) for p in hands.values()]
    assert abs(centres[0][0] - centres[1][0]) > 0.2


def test_the_close_up_follows_the_object_with_the_fingers_at_it(one_hand: Playback) -> None:
    wide, close = auto_camera(one_hand), auto_camera(one_hand, close_up=True)
    assert close.track is not None and close.track.shape == (one_hand.num_frames, 3)
    assert close.distance < 0.6 * wide.distance
    objects, hands = framing_points(one_hand, CLOSE_UP_NEAR_M, whole_hand=False, simulated_objects=False)
    fingers_seen = 0
    for f in range(one_hand.num_frames):
        _assert_in_view(mujoco_projection(one_hand, close, _finite(objects[f]), f))
        near = _finite(hands["right"][f])
        if len(near):
            _assert_in_view(mujoco_projection(one_hand, close, near, f))
            fingers_seen += 1
    assert fingers_seen >= one_hand.num_frames // 3
    # The look-at point moves with the recorded object (lifted 20 cm in this example).
    lift = one_hand.part_poses_ref[-1, 0, 2] - one_hand.part_poses_ref[0, 0, 2]
    assert abs((close.track[-1, 2] - close.track[0, 2]) - lift) < 0.03


def test_the_default_panel_is_640x480_and_the_cli_writes_the_close_up(one_hand: Playback, tmp_path: Path) -> None:
    import inspect

    from worker.visual.render import PanelRenderer, render_video

    assert PANEL_SIZE == (640, 480)
    params = inspect.signature(render_video).parameters
    assert (params["width"].default, params["height"].default) == PANEL_SIZE
    params = inspect.signature(PanelRenderer).parameters
    assert (params["width"].default, params["height"].default) == PANEL_SIZE
    from worker.visual.preview import PREVIEW_SIZE

    assert PREVIEW_SIZE == PANEL_SIZE


@pytest.mark.usefixtures("offscreen_gl")
def test_render_close_up_on_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from common.cli import main as cli_main
    from common.sequence_io import sequence_to_npz_bytes
    from worker.example import short_example_sequence
    from worker.simulation.replay import raw_replay, replay_result_bytes
    from worker.visual import read_mp4

    seq = short_example_sequence()
    result, sequence = tmp_path / "raw.npz", tmp_path / "seq.npz"
    result.write_bytes(replay_result_bytes(raw_replay(seq)))
    sequence.write_bytes(sequence_to_npz_bytes(seq))
    assert cli_main(["render", str(result), "--sequence", str(sequence), "--close-up", "--size", "96x72"]) == 0
    frames, _fps = read_mp4(tmp_path / "raw.mp4")
    assert frames.shape == (seq.num_frames, 72, 96, 3) and frames.std() > 10
    assert cli_main(["render", str(result), "--sequence", str(sequence), "--out", str(tmp_path / "d.mp4")]) == 0
    assert read_mp4(tmp_path / "d.mp4")[0].shape[1:] == (480, 640, 3)  # the default size
    assert "640x480" in capsys.readouterr().out
