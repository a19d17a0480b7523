"""``hoi-refine inspect`` / ``replay`` / ``demo --raw`` through the real command-line entry point."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.cli import main
from common.result_format import read_summary
from common.sequence_io import sequence_to_npz_bytes
from worker.example.sequences import short_example_sequence


@pytest.fixture()
def example_file(tmp_path: Path) -> Path:
    path = tmp_path / "example.npz"
    path.write_bytes(sequence_to_npz_bytes(short_example_sequence()))
    return path


def test_inspect_valid_file(example_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inspect", str(example_file)]) == 0
    out = capsys.readouterr().out
    assert "synthetic_box" in out and "24 at 30 fps" in out and "valid" in out


def test_inspect_invalid_file_names_the_field(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    seq = short_example_sequence()
    seq.object.mass_kg = -2.0
    seq.object_pose = seq.object_pose.copy()
    seq.object_pose[3, 3:] = [2.0, 0.0, 0.0, 0.0]
    bad = tmp_path / "bad.npz"
    bad.write_bytes(sequence_to_npz_bytes(seq))
    assert main(["inspect", str(bad)]) == 2
    captured = capsys.readouterr()
    assert "object.mass_kg" in captured.err and "object_pose" in captured.err


def test_replay_writes_a_result(example_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "result.npz"
    assert main(["replay", str(example_file), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "E_t" in text and "IK residual" in text and text.index("outcome (raw replay") < text.index("E_t")
    summary = read_summary(out.read_bytes())
    assert summary["kind"] == "replay" and np.isfinite(summary["metrics"]["raw"]["E_t"])


def test_replay_missing_file_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(tmp_path / "nope.npz")]) == 2
    assert "nope.npz" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["verify", "plot", "export"])
def test_a_result_that_is_missing_or_a_folder_is_a_clear_error(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for path in (tmp_path / "nope.npz", tmp_path):
        assert main([command, str(path)]) == 2
        err = capsys.readouterr().err
        if command == "verify" and path.is_dir():  # verify checks every result under a folder: here there is none
            assert err == f"hoi-refine: error: no *.result.npz under {path}\n", err
        else:
            assert err.startswith(f"hoi-refine: error: {path}: ") and "Traceback" not in err


@pytest.mark.slow
def test_demo_raw(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--raw"]) == 0
    assert "raw replay: synthetic_grasp_and_lift" in capsys.readouterr().out
