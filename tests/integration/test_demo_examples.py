"""``hoi-refine demo --example hinged_box`` (issue #52 item 7): the built-in two-handed articulated example end to
end, raw, locally and through the service; the default demo stays the one-hand box."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import pytest

from common.cli import main
from common.errors import InputError
from common.job_options import JobOptions
from common.metrics_table import ARTICULATED_SUCCESS_LABEL
from common.result_format import read_arrays, read_summary
from worker.example.catalogue import DEFAULT_EXAMPLE, example_named
from worker.simulation.metrics import SUCCESS_ARTICULATION

#: A cheap budget: the demo's plumbing is under test here, not the refinement (the lead's tests hold that).
CHEAP = JobOptions(max_generations=2, popsize=6, restarts=0, polish=False)


def test_the_catalogue() -> None:
    assert DEFAULT_EXAMPLE == "box" and example_named("box").build_short().name == "synthetic_grasp_and_lift_24f"
    hinged = example_named("hinged_box").build_short()
    assert [h.side for h in hinged.hands] == ["right", "left"] and hinged.object.part_names == ["base", "lid"]
    with pytest.raises(InputError, match="box, hinged_box"):
        example_named("teapot")
    # The metrics table's label states the articulation limits the metrics use.
    assert f"E_a <= {SUCCESS_ARTICULATION['revolute']:g} deg | {SUCCESS_ARTICULATION['prismatic']:g} cm" in (
        ARTICULATED_SUCCESS_LABEL)


def test_demo_raw_hinged_box(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "raw.npz"
    assert main(["demo", "--raw", "--example", "hinged_box", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "two-handed hinged box" in text and "raw replay: hinged_box" in text and "articulation error E_a" in text
    arrays = read_arrays(out.read_bytes())
    assert {"right_keypoints_sim", "left_keypoints_sim", "object_articulation_sim", "contact_part"} <= set(arrays)


@pytest.mark.usefixtures("offscreen_gl")
def test_local_demo_hinged_box(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from worker.runtime.commands.demo import run_local_demo

    assert run_local_demo(threads=1, short=True, out_dir=tmp_path, example="hinged_box", options=CHEAP) == 0
    text = capsys.readouterr().out
    assert "hinged_box_32f" in text and "articulation error E_a" in text
    # Two hands on an articulated object: the outcome is classified too, and printed before the metrics.
    assert text.index("outcome: ") < text.index("articulation error E_a")
    summary = read_summary((tmp_path / "hinged_box_32f.result.npz").read_bytes())
    assert isinstance(summary["outcome"]["executable"], bool)
    arrays = read_arrays((tmp_path / "hinged_box_32f.result.npz").read_bytes())
    assert {"object_articulation_sim", "contact_part", "left_keypoints_sim", "right_keypoints_sim"} <= set(arrays)
    assert (tmp_path / "hinged_box_32f.mp4").stat().st_size > 1000
    assert (tmp_path / "hinged_box_32f_plots" / "articulation.png").is_file()


@pytest.mark.slow
def test_service_demo_hinged_box(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Through ``hoi-refine up`` (API + Ray + a worker) and the public API, as ``make demo`` runs."""
    from worker.runtime.demo_client import run_demo

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = int(sock.getsockname()[1])
    assert run_demo(out_dir=tmp_path, workers=1, port=port, short=True, options=CHEAP, example="hinged_box",
                    timeout_s=1200) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "submitted 'hinged_box_32f'" in text and "articulation error E_a" in text
    contacts = json.loads((tmp_path / "hinged_box_32f.contacts.json").read_text())["contacts"]
    assert contacts and {c["part"] for c in contacts} <= {"base", "lid"} and {c["hand"] for c in contacts} <= {
        "right", "left"}
    assert read_summary((tmp_path / "hinged_box_32f.result.npz").read_bytes())["sides"] == ["right", "left"]
