"""Seeing a two-handed articulated result (issue #52 item 8): the re-simulation starts the object at its recorded
frame-0 joint values and reproduces the stored joint values; the video's ghost shows every part where the recording
has it and the camera sees both hands; the Rerun recording and the plots carry E_a, the joint values and both hands;
the plain-MuJoCo export replays the articulation and its replay.py reports the joint error."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
from PIL import Image

from common.cli import main as cli_main
from common.geometry import quat_to_matrix
from common.result_format import read_arrays
from worker.example.hinged_box import short_hinged_box_sequence
from worker.visual import Playback, read_recording, read_scalars, resimulate, write_recording
from worker.visual.render import PanelRenderer, two_hand_azimuth


@pytest.fixture(scope="module")
def playback(short_hinged_result: bytes) -> Playback:
    return resimulate(short_hinged_result, record_controls=True)


def test_resimulation_reproduces_the_stored_joint_values(playback: Playback, short_hinged_result: bytes) -> None:
    stored = read_arrays(short_hinged_result)
    assert playback.articulated and playback.joint_labels() == ["lid_hinge (deg)"]
    assert set(playback.keypoints_ref) == {"right", "left"}
    assert playback.part_poses_ref.shape == (playback.num_frames, 2, 7)
    refined, raw = playback.trajectories["refined"], playback.trajectories["raw"]
    np.testing.assert_array_equal(refined.articulation, stored["object_articulation_sim"])
    np.testing.assert_array_equal(raw.articulation, stored["raw_object_articulation_sim"])
    np.testing.assert_allclose(refined.e_a, stored["metrics_refined_e_a"], atol=1e-12)
    np.testing.assert_allclose(raw.e_a, stored["metrics_raw_e_a"], atol=1e-12)
    # The recorded lid pose is the forward kinematics of the recorded base pose and hinge angle.
    recorded = playback.sequence.object.part_poses(stored["object_pose_ref"], stored["object_articulation_ref"])
    np.testing.assert_allclose(playback.part_poses_ref[:, 1], recorded[:, 1])


def test_a_raw_replay_starts_at_the_recorded_joint_values() -> None:
    """A lid recorded 0.4 rad open at frame 0 starts there in the re-simulation (the product's initial state), not
    at the joint's zero."""
    from worker.simulation.replay import raw_replay, replay_result_bytes

    seq = short_hinged_box_sequence()
    assert seq.articulation is not None
    seq.articulation = seq.articulation + 0.4
    seq = seq.validate()
    blob = replay_result_bytes(raw_replay(seq))
    pb = resimulate(blob, seq)
    qpos0 = pb.trajectories["raw"].qpos[0, pb.scene.object_joint_qpos_adr]
    assert seq.articulation is not None
    np.testing.assert_allclose(pb.scene.object_init_articulation, seq.articulation[0])
    assert abs(float(qpos0[0]) - 0.4) < 0.02  # the settled start: the hands hold the lid where it was recorded
    np.testing.assert_array_equal(pb.trajectories["raw"].articulation, read_arrays(blob)["object_articulation_sim"])


def test_the_camera_looks_across_two_hands() -> None:
    # Hands apart along +y: the view looks along +-x, the one nearer the default 135 deg.
    assert two_hand_azimuth({"right": np.array([[0.0, -0.2, 0.1]]), "left": np.array([[0.0, 0.2, 0.1]])}) == 180.0
    assert two_hand_azimuth({"right": np.array([[0.1, 0.0, 0.1]]), "left": np.array([[-0.1, 0.0, 0.1]])}) == 90.0
    assert two_hand_azimuth({"right": np.array([[0.1, 0.0, 0.1]])}) == 135.0  # one hand: the default


@pytest.mark.usefixtures("offscreen_gl")
def test_the_ghost_shows_every_part_where_the_recording_has_it(playback: Playback) -> None:
    frame = playback.num_frames - 1
    # The recording's lid turned 0.5 rad further than it was: the ghost lid must follow, the ghost base not.
    seq = playback.sequence
    arti = seq.articulation.copy()
    arti[frame] += 0.5
    ref_parts = seq.object.part_poses(playback.object_pose_ref, arti)[frame]
    scene, model = playback.scene, playback.scene.model
    with PanelRenderer(playback, 64, 48) as r:
        d = r.data
        d.qpos[:] = playback.trajectories["refined"].qpos[frame]
        mujoco.mj_kinematics(model, d)
        r.renderer.update_scene(d, camera=r._cam)
        scn = r.renderer.scene
        first = scn.ngeom
        r._add_ghost(scn, ref_parts)
        ghosts = [scn.geoms[i] for i in range(first, scn.ngeom)]
    object_geoms = [int(g) for g in scene.object_geom_ids]
    assert len(ghosts) == len(object_geoms)
    for g, ghost in zip(object_geoms, ghosts, strict=True):
        part = int(scene.geom_part[g])
        # Expected: the geom's fixed place in its part's frame, carried by that part's recorded pose.
        r_part = quat_to_matrix(ref_parts[part, 3:])
        local_rot = quat_to_matrix(model.geom_quat[g])
        np.testing.assert_allclose(ghost.pos, ref_parts[part, :3] + r_part @ model.geom_pos[g], atol=1e-5)
        np.testing.assert_allclose(np.asarray(ghost.mat).reshape(3, 3), r_part @ local_rot, atol=1e-5)
    # The simulated lid stays where the simulation has it: 0.5 rad from its ghost.
    lid = [g for g in object_geoms if scene.geom_part[g] == 1]
    assert lid
    sim_rot = d.geom_xmat[lid[0]].reshape(3, 3)
    ghost_rot = np.asarray(ghosts[object_geoms.index(lid[0])].mat).reshape(3, 3)
    angle = np.degrees(np.arccos(np.clip((np.trace(sim_rot.T @ ghost_rot) - 1) / 2, -1, 1)))
    refined = playback.trajectories["refined"]
    expected = np.degrees(abs(arti[frame, 0] - refined.articulation[frame, 0]))  # about 0.5 rad
    assert expected > 20 and abs(angle - expected) <= refined.e_r_deg[frame] + 0.5  # the bases differ by E_r


@pytest.mark.usefixtures("offscreen_gl")
def test_recording_plots_and_cli_show_the_articulation_and_both_hands(
    playback: Playback, short_hinged_result: bytes, tmp_path: Path
) -> None:
    out = write_recording(playback, tmp_path / "run.rrd")
    assert out is not None
    entities = read_recording(out)
    for run in ("raw", "refined"):
        np.testing.assert_allclose(read_scalars(out, f"/metrics/E_a/{run}"), playback.trajectories[run].e_a, atol=1e-6)
        np.testing.assert_allclose(read_scalars(out, f"/articulation/lid_hinge/{run}"),
                                   np.degrees(playback.trajectories[run].articulation[:, 0]), atol=1e-6)
        assert f"/forces/{run}/right/thumb" in entities and f"/forces/{run}/left/thumb" in entities
    np.testing.assert_allclose(read_scalars(out, "/articulation/lid_hinge/recorded"),
                               np.degrees(playback.articulation_ref[:, 0]), atol=1e-6)
    assert "/world/recorded/hand_right" in entities and "/world/recorded/hand_left" in entities
    assert sum(1 for e in entities if e.startswith("/world/recorded/object/")) == len(playback.scene.object_geom_ids)
    # The CLI: plot (E_a panel, joint values, a force panel per hand), render, view and export.
    result = tmp_path / "hinged.npz"
    result.write_bytes(short_hinged_result)
    assert cli_main(["plot", str(result), "--out", str(tmp_path / "plots")]) == 0
    sizes = {}
    for p in (tmp_path / "plots").iterdir():
        with Image.open(p) as image:
            sizes[p.name] = image.size
    assert sizes["errors.png"][1] == 750 and sizes["contact_forces.png"][0] == 1400  # 3 panels; 2 hands side by side
    assert "articulation.png" in sizes
    assert cli_main(["render", str(result), "--out", str(tmp_path / "r.mp4"), "--size", "96x64"]) == 0
    assert cli_main(["view", str(result), "--out", str(tmp_path / "r.rrd")]) == 0


def test_the_export_replays_the_articulation_and_reports_the_joint_error(playback: Playback, tmp_path: Path) -> None:
    from worker.visual import export_playback

    folder = export_playback(playback, tmp_path / "export")
    meta = json.loads((folder / "export.json").read_text())
    assert meta["object_joints"] == [{"mjcf": "object_joint0", "name": "lid_hinge", "kind": "revolute", "unit": "deg",
                                      "scale": float(np.degrees(1.0))}]  # fmt: skip
    assert (folder / "object.obj").is_file() and (folder / "object_part1.obj").is_file()
    with np.load(folder / "trajectories.npz") as t:
        assert {"object_articulation_sim", "object_articulation_ref", "raw_object_articulation_sim"} <= set(t.files)
    with np.load(folder / "contacts.npz") as c:
        assert set(c["contact_part"]) <= {"base", "lid"} and len(c["contact_part"]) == len(c["contact_frame"])
    env = {"PATH": os.environ.get("PATH", ""), "MUJOCO_GL": "disable"}
    run = subprocess.run([sys.executable, "replay.py"], env=env, capture_output=True, text=True, cwd=folder,
                         timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert "joint lid_hinge vs simulated (stored): error max 0.0000 deg" in run.stdout
    assert "joint lid_hinge vs recorded: error max" in run.stdout
    replayed = np.load(folder / "replayed_object_articulation.npy")
    np.testing.assert_allclose(replayed, playback.trajectories["refined"].articulation, atol=1e-9)
    # A replay whose joint leaves the stored values is a mismatch (exit 1).
    with np.load(folder / "trajectories.npz") as t:
        arrays = {k: t[k] for k in t.files}
    arrays["object_articulation_sim"] = arrays["object_articulation_sim"] + np.radians(2.0)
    np.savez(folder / "trajectories.npz", **arrays)
    bad = subprocess.run([sys.executable, "replay.py"], env=env, capture_output=True, text=True, cwd=folder,
                         timeout=300)  # fmt: skip
    assert bad.returncode == 1 and "MISMATCH" in bad.stdout
