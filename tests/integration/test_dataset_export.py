"""``hoi-refine dataset export`` (issue #54 item 4): a release from a folder of results, and from a batch through a
real API (uvicorn on a socket, SQLite) whose jobs a real worker loop refined. The release reads back with pyarrow
alone (index and contacts equal the results' own values), its checksums match the files, and ``verify`` accepts it
(and catches a file changed after export)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from common.api_client import ApiClient
from common.cli import main
from common.database import create_engine_for
from common.queue import JobQueue
from common.result_format import CONTACT_KEYS, content_digest, read_arrays, read_summary
from common.sequence_io import sequence_to_npz_bytes
from common.settings import Settings
from tests.support.live_server import serve_app
from tests.support.results import cheap_articulated_result, cheap_options, cheap_result, push

AXES = "xyz"
VECTORS = {"contact_pos_world": "world", "contact_pos_object": "object", "contact_normal": "normal",
           "contact_force": "force", "contact_torque": "torque"}


def checksums_match(release: Path) -> dict[str, str]:
    """SHA256SUMS read and checked with hashlib alone; returns it. Every file but itself is listed."""
    listed = {}
    for line in (release / "SHA256SUMS").read_text().splitlines():
        digest, rel = line.split("  ", 1)
        listed[rel] = digest
        assert hashlib.sha256((release / rel).read_bytes()).hexdigest() == digest, rel
    on_disk = {p.relative_to(release).as_posix() for p in release.rglob("*") if p.is_file()} - {"SHA256SUMS"}
    assert set(listed) == on_disk
    return listed


def assert_release_matches(release: Path, results: dict[str, bytes]) -> list[dict[str, object]]:
    """index.parquet and contacts.parquet (read with pyarrow alone) hold each result's own values."""
    index = pq.read_table(release / "index.parquet").to_pylist()
    contacts = pq.read_table(release / "contacts.parquet").to_pydict()
    assert sorted(r["sequence"] for r in index if r["result_file"]) == sorted(results)
    for row in (r for r in index if r["result_file"]):
        blob = results[str(row["sequence"])]
        assert (release / str(row["result_file"])).read_bytes() == blob
        summary = read_summary(blob)
        assert row["file_sha256"] == hashlib.sha256(blob).hexdigest() and row["content_sha256"] == content_digest(blob)
        assert row["frames"] == summary["frames"] and row["hands"] == "right" and row["object"]
        assert row["paper_refined_E_t"] == summary["metrics"]["refined"]["paper"]["E_t"]
        assert row["all_frames_raw_E_r"] == summary["metrics"]["raw"]["E_r"]
        assert row["paper_refined_penetration_max_mm"] == summary["metrics"]["refined"]["paper"]["penetration_max_mm"]
        assert row["executable"] == summary["metrics"]["refined"]["paper"]["success"]
        assert row["outcome"] == ("executable" if row["executable"] else "not_executable")
        assert row["version_mujoco"] == summary["versions"]["mujoco"]
        assert json.loads(str(row["physics_json"])) == summary["config"]["sim"]
        arrays = read_arrays(blob)
        mine = [i for i, s in enumerate(contacts["sequence"]) if s == row["sequence"]]
        assert row["contacts"] == len(mine) == len(arrays["contact_frame"]) > 0
        assert [contacts["frame"][i] for i in mine] == arrays["contact_frame"].tolist()
        assert [contacts["body"][i] for i in mine] == arrays["contact_body"].tolist()
        assert [contacts["hand"][i] for i in mine] == arrays["contact_hand"].tolist()
        assert all(contacts["part"][i] is None for i in mine)  # a rigid object
        assert np.array_equal([contacts["depth"][i] for i in mine], arrays["contact_depth"])
        for key, prefix in VECTORS.items():
            got = np.array([[contacts[f"{prefix}_{a}"][i] for a in AXES] for i in mine])
            assert np.array_equal(got, arrays[key]), key
        assert set(CONTACT_KEYS) - {"contact_frame", "contact_hand", "contact_body", "contact_depth"} == set(VECTORS)
    # Units travel in the Parquet fields' metadata.
    schema = pq.read_schema(release / "contacts.parquet")
    assert schema.field("force_x").metadata[b"unit"] == b"N" and schema.field("world_z").metadata[b"unit"] == b"m"
    return index


def test_a_folder_export_round_trips_and_verifies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "results"
    (src / "s1").mkdir(parents=True)
    blobs = [cheap_result(seed=0), cheap_result(seed=1, offset_x=0.005)]
    (src / "a.result.npz").write_bytes(blobs[0])
    (src / "s1" / "b.result.npz").write_bytes(blobs[1])
    release = tmp_path / "release"

    assert main(["dataset", "export", "--from", str(src), "--out", str(release), "--title", "Push test"]) == 0

    index = assert_release_matches(release, {read_summary(b)["sequence"]: b for b in blobs})
    assert all(r["job_id"] is None for r in index)
    listed = checksums_match(release)
    assert {"README.md", "index.parquet", "contacts.parquet", "plots/object_errors.png"} <= set(listed)
    sheet = (release / "README.md").read_text()
    assert sheet.startswith("# Push test") and "| 2 | 2 | " in sheet and "plots/object_errors.png" in sheet
    assert "`force_x`" in sheet and "mujoco" in sheet

    capsys.readouterr()
    assert main(["verify", str(release), "--jobs", "2"]) == 0
    assert "2 passed, 0 failed, 0 unreadable; SHA256SUMS: 7 files, all match" in capsys.readouterr().out
    # A table changed after export: the manifest catches it, verify fails.
    with (release / "contacts.parquet").open("ab") as f:
        f.write(b"\0")
    assert main(["verify", str(release), "--jobs", "1"]) == 1
    assert "checksum differs" in capsys.readouterr().out
    # An export never overwrites a folder.
    assert main(["dataset", "export", "--from", str(src), "--out", str(release)]) == 2
    # A folder holding a file that is not a result exports nothing, naming the file, and leaves nothing behind.
    (src / "s1" / "broken.result.npz").write_bytes(b"not a zip")
    assert main(["dataset", "export", "--from", str(src), "--out", str(tmp_path / "again")]) == 2
    assert "broken.result.npz" in capsys.readouterr().err
    assert not (tmp_path / "again").exists() and not (tmp_path / "again.partial").exists()


def test_an_articulated_result_exports_the_parts_touched(tmp_path: Path) -> None:
    src = tmp_path / "results"
    src.mkdir()
    blob = cheap_articulated_result()
    (src / "hinged.result.npz").write_bytes(blob)
    release = tmp_path / "release"
    assert main(["dataset", "export", "--from", str(src), "--out", str(release)]) == 0

    row = pq.read_table(release / "index.parquet").to_pylist()[0]
    assert row["hands"] == "right,left"
    assert row["all_frames_refined_E_a"] == read_summary(blob)["metrics"]["refined"]["E_a"]
    parts = pq.read_table(release / "contacts.parquet", columns=["part", "object_x"]).to_pydict()["part"]
    assert parts == read_arrays(blob)["contact_part"].tolist() and {"base", "lid"} <= set(parts)
    assert main(["verify", str(release), "--jobs", "1"]) == 0


def test_outcome_reasons_reach_the_index_and_the_datasheet(tmp_path: Path) -> None:
    from common.outcome import Outcome, OutcomeReason, ReasonCode
    from common.result_format import write_result_npz

    blob = cheap_result(seed=0)
    summary = read_summary(blob)
    reasons = [OutcomeReason(code=ReasonCode.SLIPPED, frame=11, value=3.4, unit="cm", message="It slips."),
               OutcomeReason(code=ReasonCode.RESCUED_ON_FINER_PARTS, message="Kept on finer parts.")]
    summary["outcome"] = Outcome(executable=False, reasons=reasons).model_dump(mode="json")
    src = tmp_path / "results"
    src.mkdir()
    (src / "a.result.npz").write_bytes(write_result_npz(read_arrays(blob), summary))
    release = tmp_path / "release"
    assert main(["dataset", "export", "--from", str(src), "--out", str(release)]) == 0

    row = pq.read_table(release / "index.parquet").to_pylist()[0]
    assert (row["outcome"], row["executable"], row["reason"], row["reason_frame"], row["reason_value"],
            row["reason_unit"], row["reasons"]) == ("not_executable", False, "slipped", 11, 3.4, "cm",
                                                    "slipped;rescued_on_finer_parts")
    assert "| `slipped` | 1 | the object slips out of the grasp |" in (release / "README.md").read_text()


def test_tables_rewritten_with_their_checksums_fail_verify(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import pyarrow as pa

    from common.release_manifest import write_manifest

    src = tmp_path / "results"
    src.mkdir()
    (src / "a.result.npz").write_bytes(cheap_result(seed=0))
    release = tmp_path / "release"
    assert main(["dataset", "export", "--from", str(src), "--out", str(release)]) == 0
    contacts = pq.read_table(release / "contacts.parquet")
    force = contacts.column("force_x").to_pylist()
    force[3] *= 2.0  # a contact's force doubled: every file's checksum rewritten to match
    pq.write_table(contacts.set_column(contacts.schema.get_field_index("force_x"), contacts.schema.field("force_x"),
                                       pa.array(force)), release / "contacts.parquet")
    index = pq.read_table(release / "index.parquet")
    edited = index.to_pylist()
    edited[0]["executable"], edited[0]["outcome"] = True, "executable"  # a failure relabelled a success
    pq.write_table(pa.Table.from_pylist(edited, schema=index.schema), release / "index.parquet")
    (release / "SHA256SUMS").unlink()
    write_manifest(release)
    report_path = tmp_path / "report.json"
    capsys.readouterr()

    assert main(["verify", str(release), "--jobs", "1", "--report", str(report_path)]) == 1

    out = capsys.readouterr().out
    assert "SHA256SUMS: 6 files, all match" in out and "release tables: 1 sequences, 3 differences" in out
    problems = json.loads(report_path.read_text())["release_tables"]["problems"]
    frame = contacts.column("frame").to_pylist()[3]
    assert {(p["file"], p["column"], p["frame"]) for p in problems} == {
        ("contacts.parquet", "force_x", frame), ("index.parquet", "executable", None),
        ("index.parquet", "outcome", None)}


@pytest.fixture
def live_api(db_url: str) -> Iterator[tuple[str, str, JobQueue]]:
    """The API under uvicorn on a loopback socket, on a migrated SQLite database."""
    from service.app import create_app

    engine = create_engine_for(db_url)
    app = create_app(Settings(max_active_jobs_per_key=50), engine)
    _, key = app.state.api_keys.create("dataset")
    with serve_app(app) as base:
        yield base, key, app.state.queue
    engine.dispose()


def test_a_batch_export_through_the_api(live_api: tuple[str, str, JobQueue], tmp_path: Path) -> None:
    from worker.runtime.jobs import RefineJob
    from worker.runtime.loop import WorkerLoop

    base, key, queue = live_api
    with ApiClient(base, key) as client:
        batch = client.create_batch("push-release")
        ids = [client.submit(sequence_to_npz_bytes(push(offset_x=dx)), f"push{i}.npz", cheap_options(i),
                             batch_id=batch["id"])["id"] for i, dx in enumerate((0.0, 0.005, 0.01))]
        # An unfinished batch is not exported.
        assert main(["dataset", "export", "--batch", batch["id"], "--api", base, "--key", key,
                     "--out", str(tmp_path / "early")]) == 2
        client.cancel(ids[2])
        loop = WorkerLoop(queue, RefineJob(1), worker_id="w1", lease_seconds=60, idle_poll_seconds=0.05)
        assert [loop.run_once(), loop.run_once()] == ["succeeded", "succeeded"]
        downloads = {j["name"]: client.result(j["id"]) for j in client.jobs(batch_id=batch["id"])
                     if j["state"] == "SUCCEEDED"}
        proofs = {i: client.job(i)[0]["summary"]["metrics"]["verification"] for i in ids[:2]}
    release = tmp_path / "release"

    assert main(["dataset", "export", "--batch", batch["id"], "--api", base, "--key", key, "--out", str(release)]) == 0

    index = pq.read_table(release / "index.parquet").to_pylist()
    by_name = {r["sequence"]: r for r in index}
    names = [f"synthetic-push-yaw0-dx{dx}" for dx in ("0", "0.005", "0.01")]
    assert set(by_name) == set(names) and set(downloads) == set(names[:2])
    cancelled = by_name[names[2]]
    assert cancelled["job_state"] == "CANCELLED" and cancelled["result_file"] is None and cancelled["job_id"] == ids[2]
    assert_release_matches(release, downloads)
    for name in downloads:
        row = by_name[name]
        assert row["worker_verified"] is True and row["checked_sha256"] == proofs[row["job_id"]]["checked_sha256"]
        assert row["content_sha256"] == proofs[row["job_id"]]["content_sha256"]
    checksums_match(release)
    assert "without a result" in (release / "README.md").read_text()
    assert main(["verify", str(release)]) == 0
