"""Bulk submit: finding sequences, loading them, and what is uploaded (reproducible bytes, content keys)."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from common.errors import ManoModelMissingError, SequenceValidationError, UnsupportedFormatError
from common.job_options import JobOptions
from common.sequence import HandTrack, ObjectSpec, Sequence
from common.sequence_io import save_sequence, sequence_from_npz_bytes
from service.submit.discovery import discover, is_dexycb_root, load_source
from service.submit.payload import content_digest, idempotency_key, sequence_payload

T = 5


def _sequence(name: str = "seq", lift: float = 0.01) -> Sequence:
    rng = np.random.default_rng(0)
    pose = np.zeros((T, 7))
    pose[:, 2] = 0.05 + lift * np.arange(T)
    pose[:, 3] = 1.0
    keypoints = 0.1 * rng.random((T, 21, 3)) + np.array([0.0, 0.0, 0.1])
    return Sequence(
        name=name,
        fps=30.0,
        object=ObjectSpec(name="box", mass_kg=0.2, primitive="box", size=np.array([0.03, 0.03, 0.05])),
        object_pose=pose,
        hands=[HandTrack(side="right", valid=np.ones(T, dtype=bool), keypoints=keypoints)],
        up=np.array([0.0, 0.0, 1.0]),
    )


def _dexycb_skeleton(root: Path) -> None:
    """Just enough of the DexYCB release layout to be recognised (loading is tested with the loader)."""
    (root / "calibration").mkdir(parents=True)
    for seq in ("20200709_141754", "20200709_141841"):
        (root / "20200709-subject-01" / seq).mkdir(parents=True)
        (root / "20200709-subject-01" / seq / "meta.yml").write_text("num_frames: 5\n")


def test_discover_files_folders_and_dexycb_roots(tmp_path: Path) -> None:
    data = tmp_path / "data"
    (data / "a" / "b").mkdir(parents=True)
    save_sequence(_sequence("one"), data / "one.npz")
    save_sequence(_sequence("two"), data / "a" / "b" / "two.json")
    (data / "notes.txt").write_text("not a sequence")
    (data / ".hidden").mkdir()
    save_sequence(_sequence("hidden"), data / ".hidden" / "h.npz")
    _dexycb_skeleton(data / "dexycb")
    out = data / "out"
    out.mkdir()
    (out / "manifest.json").write_text("{}")  # the output folder inside the input is never an input

    found = discover([data], "auto", exclude=[out])
    assert [(s.kind, s.label) for s in found] == [
        ("npz", "one"),
        ("json", "a__b__two"),
        ("dexycb", "dexycb__20200709-subject-01__20200709_141754"),
        ("dexycb", "dexycb__20200709-subject-01__20200709_141841"),
    ]
    assert all(s.path.is_absolute() for s in found)
    assert is_dexycb_root(data / "dexycb") and not is_dexycb_root(data)

    # Restricting the format, naming a file twice, and naming a root directly.
    assert [s.label for s in discover([data], "json", exclude=[out])] == ["a__b__two"]
    assert len(discover([data / "one.npz", data / "one.npz", data], "npz")) == 1
    assert [s.label for s in discover([data / "dexycb"], "dexycb")] == [
        "20200709-subject-01__20200709_141754",
        "20200709-subject-01__20200709_141841",
    ]


def test_discover_rejects_what_it_cannot_read(tmp_path: Path) -> None:
    with pytest.raises(UnsupportedFormatError, match="does not exist"):
        discover([tmp_path / "missing"])
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(UnsupportedFormatError, match=r"x\.txt"):
        discover([tmp_path / "x.txt"])
    with pytest.raises(UnsupportedFormatError, match="not a DexYCB root"):
        discover([tmp_path], "dexycb")
    with pytest.raises(UnsupportedFormatError, match="--format"):
        discover([tmp_path], "csv")  # type: ignore[arg-type]


def test_same_relative_names_under_two_roots_get_distinct_labels(tmp_path: Path) -> None:
    for root in ("r1", "r2"):
        (tmp_path / root).mkdir()
        save_sequence(_sequence(), tmp_path / root / "s.npz")
    labels = [s.label for s in discover([tmp_path / "r1", tmp_path / "r2"])]
    assert labels == ["s", "s~1"]


def test_invalid_file_fails_locally_with_the_field_named(tmp_path: Path) -> None:
    doc = json.loads(json.dumps({"fps": 30, "hands": [], "object": {"mass_kg": 1.0}, "object_pose": [[0] * 7]}))
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    (src,) = discover([tmp_path])
    with pytest.raises(SequenceValidationError, match="hands"):
        load_source(src)


def test_payload_is_reproducible_and_key_follows_content_and_options() -> None:
    seq = _sequence()
    seq.meta["source_path"] = "/somewhere/on/this/machine.npz"
    first = sequence_payload(seq)
    # The upload must not carry the clock (zip entries hold a time stamp): a resent POST must be identical.
    with zipfile.ZipFile(io.BytesIO(first)) as zf:
        assert {info.date_time for info in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    seq.meta["source_path"] = "/moved/elsewhere.npz"
    assert sequence_payload(seq) == first  # byte-identical: a resent POST carries the same body
    back = sequence_from_npz_bytes(first)
    assert "source_path" not in back.meta
    np.testing.assert_allclose(back.object_pose, seq.object_pose)

    key = idempotency_key(first, JobOptions())
    assert key == idempotency_key(first, JobOptions(seed=0))  # defaults spelled out or not: same job
    assert key != idempotency_key(first, JobOptions(seed=1))
    assert key != idempotency_key(first, JobOptions(loss_weights={"object_pose": 2.0}))
    assert key != idempotency_key(sequence_payload(_sequence(lift=0.02)), JobOptions())
    assert len(key) == 64 and int(key, 16) >= 0


def test_an_option_added_later_at_its_default_keeps_the_key() -> None:
    """A release that adds an option must not turn a resumed batch's finished jobs into new ones."""

    class LaterOptions(JobOptions):
        added_in_a_later_release: int = 7

    blob = sequence_payload(_sequence())
    key = idempotency_key(blob, JobOptions(seed=3))
    assert idempotency_key(blob, LaterOptions(seed=3)) == key
    assert idempotency_key(blob, LaterOptions(seed=3, added_in_a_later_release=8)) != key


def test_content_digest_ignores_the_zip_container(tmp_path: Path) -> None:
    seq = _sequence()
    arrays = dict(np.load(io.BytesIO(sequence_payload(seq))))
    np.savez(tmp_path / "b.npz", **dict(reversed(list(arrays.items()))))  # stored, not deflated; other order
    other = (tmp_path / "b.npz").read_bytes()
    assert other != sequence_payload(seq)
    assert content_digest(other) == content_digest(sequence_payload(seq))


def test_dexycb_dev_file_is_uploaded_self_contained(dexycb_dev_files: list[Path]) -> None:
    """The dev NPZs name a YCB object; the upload must carry its mesh so the server needs no YCB folder."""
    (src,) = discover([dexycb_dev_files[0]])
    seq = load_source(src)
    back = sequence_from_npz_bytes(sequence_payload(seq))  # no source_path: parsed without the YCB folder
    assert back.object.is_mesh and back.object.mesh_vertices is not None
    assert back.object.mesh_vertices.shape == seq.object.mesh_vertices.shape  # type: ignore[union-attr]
    assert back.name == seq.name and back.num_frames == seq.num_frames


def test_dexycb_release_sequences_load_and_pack(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A DexYCB release root (the loader's own test tree): one item per sequence, uploaded self-contained."""
    from tests.support.dexycb_tree import write_tree  # the tiny release tree its loader is tested on

    monkeypatch.delenv("HOI_REFINE_MANO_DIR", raising=False)
    dirs = write_tree(tmp_path / "release")
    labelled, mano_only = discover([tmp_path / "release"], "dexycb")
    assert (labelled.path, mano_only.path) == (dirs["s1"].resolve(), dirs["s2"].resolve())
    seq = load_source(labelled)
    back = sequence_from_npz_bytes(sequence_payload(seq))
    assert back.object.is_mesh and back.world_from_source is not None and back.num_frames == seq.num_frames
    # Hands known only by MANO parameters need a MANO model here: reported, never sent.
    with pytest.raises(ManoModelMissingError):
        load_source(mano_only)
