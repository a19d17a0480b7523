"""``hoi-refine verify DIR`` (issue #54 item 3): every result under a folder on a process pool; a folder mixing good,
forged and unreadable files reports each (field and frame for the forgery) and exits 1; all good exits 0; bad input
exits 2; ``verify FILE`` works as before."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from common.cli import main
from tests.support.results import cheap_result, forged


@pytest.fixture(scope="module")
def good() -> list[bytes]:
    return [cheap_result(seed=0), cheap_result(seed=1, offset_x=0.005)]


def test_a_mixed_folder_reports_each_file_and_exits_1(
    good: list[bytes], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "nested" / "deeper").mkdir(parents=True)
    (tmp_path / "a.result.npz").write_bytes(good[0])
    (tmp_path / "nested" / "deeper" / "b.result.npz").write_bytes(good[1])
    (tmp_path / "nested" / "wrist.result.npz").write_bytes(forged(good[0], "right_wrist_pos", 0.05, from_frame=6))
    (tmp_path / "truncated.result.npz").write_bytes(good[1][: len(good[1]) // 2])
    (tmp_path / "text.result.npz").write_text("not a result")
    (tmp_path / "notes.txt").write_text("not looked at")  # only *.result.npz are results
    report_path = tmp_path / "report.json"

    rc = main(["verify", str(tmp_path), "--jobs", "2", "--report", str(report_path)])

    assert rc == 1
    captured = capsys.readouterr()
    out = captured.out
    assert "2 passed, 1 failed, 2 unreadable" in out and "verify: FAILED" in out
    # Not a terminal: a line per result on stderr, each ending its line, the last one counting all five.
    progress = [line for line in captured.err.splitlines() if line.startswith("verify ")]
    assert len(progress) == 5 and progress[-1].startswith("verify 5/5: "), captured.err
    assert "passed 2" in progress[-1] and "failed 1" in progress[-1] and "unreadable 2" in progress[-1]
    report = json.loads(report_path.read_text())
    status = {f["path"]: f["status"] for f in report["files"]}
    assert status == {"a.result.npz": "passed", "nested/deeper/b.result.npz": "passed",
                      "nested/wrist.result.npz": "failed", "text.result.npz": "unreadable",
                      "truncated.result.npz": "unreadable"}
    assert report["counts"] == {"passed": 2, "failed": 1, "unreadable": 2} and report["all_passed"] is False
    files = {f["path"]: f for f in report["files"]}
    wrist = [f for f in files["nested/wrist.result.npz"]["failures"] if f["field"] == "right_wrist_pos"]
    assert wrist and wrist[0]["frame"] == 6, files["nested/wrist.result.npz"]["failures"]
    assert files["a.result.npz"]["exact"] is True and files["a.result.npz"]["checked_sha256"]
    for name in ("text.result.npz", "truncated.result.npz"):
        first = files[name]["failures"][0]
        assert first["field"] == "file" and "cannot be read" in first["message"]
    # The table names every file that did not pass, with the forgery's field and frame.
    for name in ("nested/wrist.result.npz", "text.result.npz", "truncated.result.npz", "right_wrist_pos"):
        assert name in out


def test_a_folder_of_good_results_exits_0_and_one_file_still_verifies(good: list[bytes], tmp_path: Path) -> None:
    for i, blob in enumerate(good):
        (tmp_path / f"r{i}.result.npz").write_bytes(blob)
    report_path = tmp_path / "report.json"
    assert main(["verify", str(tmp_path), "--jobs", "1", "--report", str(report_path)]) == 0
    assert json.loads(report_path.read_text())["counts"] == {"passed": 2, "failed": 0, "unreadable": 0}
    assert main(["verify", str(tmp_path / "r0.result.npz")]) == 0


def test_bad_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["verify", str(tmp_path)]) == 2  # no results in it
    assert "no *.result.npz" in capsys.readouterr().err
    assert main(["verify", str(tmp_path / "missing")]) == 2
    (tmp_path / "r.result.npz").write_bytes(b"")
    capsys.readouterr()
    assert main(["verify", str(tmp_path / "r.result.npz"), "--jobs", "2"]) == 2  # a folder's options, on a file
    assert "apply to a folder" in capsys.readouterr().err
    assert main(["verify", str(tmp_path), "--threads", "2"]) == 2  # a file's options, on a folder
    assert "apply to one result file" in capsys.readouterr().err


def test_a_handful_of_small_results_are_checked_without_a_pool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Unless --jobs says otherwise, one process per ``BYTES_PER_PROCESS`` of results, up to the cores: starting a
    checker costs seconds, more than a few small results take in this process."""
    from worker.verification import folder

    monkeypatch.setattr(folder.os, "sched_getaffinity", lambda _: {0, 1, 2, 3}, raising=False)
    small = [tmp_path / f"s{i}.result.npz" for i in range(3)]
    for p in small:
        p.write_bytes(b"x" * 80_000)
    assert folder.default_jobs(small) == 1
    big = [tmp_path / f"b{i}.result.npz" for i in range(12)]
    for p in big:
        p.write_bytes(b"x" * 500_000)
    assert folder.default_jobs(big) == 12 * 500_000 // folder.BYTES_PER_PROCESS == 2
    assert folder.default_jobs(big * 10) == 4  # the cores
    assert folder.default_jobs() == 4
