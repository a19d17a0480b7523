"""Hand descriptions (issue #55 item 1): a test-written robot hand packs and compiles into a scene fragment; every
kind of bad description is refused naming the field at fault, in the file (CLI), the packed form (API) and
against the compiled model."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest
from pydantic import ValidationError

from common.hand_description import HandDescriptionError, check_packed, parse_hand_description
from common.job_options import JobOptions
from tests.support.robot_hand import JOINTS, description, write_robot_hand
from worker.robot import Embodiment, resolve_hand
from worker.robot.canonical import canonical_xml, mirror_xml
from worker.robot.fragment import robot_fragment
from worker.simulation.config import SimConfig


def _problem_fields(exc: HandDescriptionError) -> set[str]:
    return {p.field for p in exc.problems}


def test_a_test_written_hand_packs_self_contained(tmp_path: Path) -> None:
    packed = resolve_hand(write_robot_hand(tmp_path))
    assert packed is not None and packed.model is None and packed.model_xml is not None
    assert "file=" not in packed.model_xml  # nothing outside the text
    assert [j.velocity for j in packed.joints] == [8.0] * len(JOINTS)
    for side in ("right", "left"):
        emb = Embodiment.from_description(packed, side)
        assert emb.joint_names == tuple(JOINTS) and emb.q_limits.shape == (20, 2)
        assert emb.fingertips == (4, 8, 12, 16, 20)  # the five tips among the 21 sites
    assert resolve_hand("human") is None and resolve_hand(None) is None


def test_the_canonical_model_has_the_source_kinematics(tmp_path: Path) -> None:
    write_robot_hand(tmp_path)
    source = mujoco.MjModel.from_xml_path(str(tmp_path / "test_hand.xml"))
    canon = mujoco.MjModel.from_xml_string(canonical_xml(source))
    d1, d2 = mujoco.MjData(source), mujoco.MjData(canon)
    rng = np.random.default_rng(0)
    for _ in range(3):
        q = rng.uniform(source.jnt_range[:, 0], source.jnt_range[:, 1])
        d1.qpos[:], d2.qpos[:] = q, q
        mujoco.mj_kinematics(source, d1)
        mujoco.mj_kinematics(canon, d2)
        for b in range(1, canon.nbody):
            name = mujoco.mj_id2name(canon, mujoco.mjtObj.mjOBJ_BODY, b)
            np.testing.assert_allclose(d2.xpos[b], d1.xpos[mujoco.mj_name2id(source, mujoco.mjtObj.mjOBJ_BODY, name)],
                                       atol=1e-9)
    np.testing.assert_allclose(canon.body_mass.sum(), source.body_mass.sum())


def test_the_left_hand_is_the_mirror_image(tmp_path: Path) -> None:
    write_robot_hand(tmp_path)
    right = mujoco.MjModel.from_xml_string(canonical_xml(mujoco.MjModel.from_xml_path(str(tmp_path / "test_hand.xml"))))
    left = mujoco.MjModel.from_xml_string(mirror_xml(canonical_xml(right)))
    dr, dl = mujoco.MjData(right), mujoco.MjData(left)
    q = np.linspace(0.1, 0.9, right.nq) * (right.jnt_range[:, 1] - right.jnt_range[:, 0]) + right.jnt_range[:, 0]
    dr.qpos[:], dl.qpos[:] = q, q  # the same joint angles give the mirrored pose
    mujoco.mj_kinematics(right, dr)
    mujoco.mj_kinematics(left, dl)
    np.testing.assert_allclose(dl.xpos, dr.xpos * np.array([1.0, -1.0, 1.0]), atol=1e-9)


def test_the_fragment_names_everything_with_the_side(tmp_path: Path) -> None:
    packed = resolve_hand(write_robot_hand(tmp_path))
    assert packed is not None
    frags = [robot_fragment(Embodiment.from_description(packed, s), SimConfig(), np.zeros(3), np.array([1.0, 0, 0, 0]))
             for s in ("right", "left")]
    xml = ("<mujoco><asset>" + "".join(f.assets for f in frags) + "</asset><worldbody>"
           + "".join(f.worldbody for f in frags) + "</worldbody><equality>" + "".join(f.equality for f in frags)
           + "</equality><actuator>" + "".join(f.actuators for f in frags) + "</actuator><sensor>"
           + "".join(f.sensors for f in frags) + "</sensor></mujoco>")
    model = mujoco.MjModel.from_xml_string(xml)  # two hands side by side: no name clashes
    assert model.nu == 40 and model.nsensor == 2 * 21
    for side in ("right", "left"):
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"{side}_palm") >= 0
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{side}_root") >= 0
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, f"{side}_index_flex1") >= 0
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"{side}_kp12") >= 0
    # The servos are force-limited at the description's effort.
    np.testing.assert_allclose(model.actuator_forcerange[0], [-2.0, 2.0])


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"keypoints": {**description()["keypoints"], "index4": {"body": "no_such_link"}}},
         "hand.keypoints.index4.body"),
        ({"joints": [{"name": "no_such_joint"}] + [{"name": j} for j in JOINTS[1:]]}, "hand.joints.0.name"),
        ({"root_body": "nowhere"}, "hand.root_body"),
        ({"model": "missing.urdf"}, "hand.model"),
    ],
)
def test_names_missing_from_the_model_are_field_named(tmp_path: Path, change: dict[str, Any], field: str) -> None:
    with pytest.raises(HandDescriptionError) as err:
        resolve_hand(write_robot_hand(tmp_path, **change))
    assert field in _problem_fields(err.value), err.value


def test_a_joint_without_limits_needs_a_range(tmp_path: Path) -> None:
    folder = tmp_path / "unlimited"
    path = write_robot_hand(folder)
    model = folder / "test_hand.xml"
    model.write_text(re.sub(r'(<joint name="index_flex2"[^>]*?) range="[^"]*"', r"\1", model.read_text()))
    with pytest.raises(HandDescriptionError) as err:
        resolve_hand(path)
    assert _problem_fields(err.value) == {f"hand.joints.{JOINTS.index('index_flex2')}.range"}
    joints = [{"name": j, **({"range": [0.0, 1.5]} if j == "index_flex2" else {})} for j in JOINTS]
    path.write_text(json.dumps({**description(), "joints": joints}))
    packed = resolve_hand(path)  # a range in the description is enough
    assert packed is not None
    assert Embodiment.from_description(packed, "right").q_limits[JOINTS.index("index_flex2")].tolist() == [0.0, 1.5]


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"keypoints": {"index4": {"body": "index_tip"}}}, "hand.keypoints"),  # no thumb tip
        ({"keypoints": {**description()["keypoints"], "little9": {"body": "base"}}}, "hand.keypoints"),
        ({"joints": [{"name": "index_flex2", "range": [1.0, 0.5]}]}, "hand.joints.0"),
        ({"joints": []}, "hand.joints"),
        ({"tip_radius": -1}, "hand.tip_radius"),
        ({"unknown": 1}, "hand.unknown"),
        ({"actuator": {"kp": float("nan")}}, "hand.actuator.kp"),
    ],
)
def test_structural_problems_are_field_named(change: dict[str, Any], field: str) -> None:
    with pytest.raises(HandDescriptionError) as err:
        parse_hand_description({**description(), **change})
    assert field in _problem_fields(err.value), err.value


def test_only_a_packed_description_travels_with_a_job(tmp_path: Path) -> None:
    with pytest.raises(HandDescriptionError) as err:
        check_packed(parse_hand_description(description()))
    assert _problem_fields(err.value) == {"hand.model"}
    with pytest.raises(ValidationError, match="hand"):
        JobOptions.model_validate({"hand": description()})
    packed = resolve_hand(write_robot_hand(tmp_path))
    assert packed is not None
    data = packed.model_dump(mode="json")
    assert JobOptions.model_validate({"hand": data}).hand == packed  # the API's JSON round trip
    broken = {**data, "keypoints": {**data["keypoints"], "thumb4": {"body": "gone", "pos": [0, 0, 0]}}}
    with pytest.raises(ValidationError, match=r"hand\.keypoints\.thumb4\.body"):
        JobOptions.model_validate({"hand": broken})


def test_the_cli_names_the_hand_at_fault(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from common.cli import main as cli_main

    monkeypatch.delenv("HOI_REFINE_ROBOT_DIR", raising=False)
    seq = tmp_path / "missing.npz"  # the hand is checked before the sequence is read
    assert cli_main(["refine", str(seq), "--out", str(tmp_path / "r.npz"), "--hand", "allegro"]) == 2
    assert "HOI_REFINE_ROBOT_DIR" in capsys.readouterr().err
    bad = write_robot_hand(tmp_path / "bad", keypoints={**description()["keypoints"], "thumb4": {"body": "gone"}})
    assert cli_main(["refine", str(seq), "--out", str(tmp_path / "r.npz"), "--hand", str(bad)]) == 2
    assert "hand.keypoints.thumb4.body: no body named 'gone'" in capsys.readouterr().err
    assert cli_main(["hand", "pack", str(write_robot_hand(tmp_path / "ok")), "--out", str(tmp_path / "p.json")]) == 0
    packed = json.loads((tmp_path / "p.json").read_text())
    assert packed["model"] is None and packed["model_xml"].startswith("<mujoco")
