"""A dataset release's format (issue #54 item 4): its layout and the columns of its two Parquet tables (name,
Arrow type, unit and meaning), defined once: ``hoi-refine dataset export`` builds its schemas from them, its
datasheet and ``docs/dataset.md`` list them, ``hoi-refine verify`` checks a release's tables against its results.

Layout of a release folder::

    README.md           the datasheet: counts, success, error distributions, failure reasons, versions, columns
    index.parquet       one row per sequence (INDEX_COLUMNS)
    contacts.parquet    one row per hand-object contact of every sequence (CONTACT_COLUMNS)
    results/NAME.result.npz   each sequence's result file as the worker stored it (``common.result_format``)
    plots/*.png         the datasheet's figures
    SHA256SUMS          SHA-256 of every other file (``common.release_manifest``; ``sha256sum -c SHA256SUMS``)
"""

from __future__ import annotations

from dataclasses import dataclass

import pyarrow as pa

RESULTS_DIR = "results"
PLOTS_DIR = "plots"
INDEX_FILE = "index.parquet"
CONTACTS_FILE = "contacts.parquet"
DATASHEET_FILE = "README.md"


@dataclass(frozen=True)
class Column:
    name: str
    type: pa.DataType
    unit: str  # "" when unitless
    meaning: str


def _xyz(prefix: str, unit: str, meaning: str) -> list[Column]:
    return [Column(f"{prefix}_{axis}", pa.float64(), unit, f"{meaning} ({axis})") for axis in "xyz"]


CONTACT_COLUMNS: tuple[Column, ...] = (
    Column("sequence", pa.string(), "", "the sequence's name (index.parquet `sequence`)"),
    Column("frame", pa.int32(), "", "frame, 0-based"),
    Column("hand", pa.string(), "", "hand side: right or left"),
    Column("body", pa.string(), "", "the hand body touching (palm, a finger segment; a robot hand's link)"),
    Column("part", pa.string(), "", "the object part touched (articulated objects; null for a rigid object)"),
    *_xyz("world", "m", "contact point, world frame"),
    *_xyz("object", "m", "contact point in the object's frame (the touched part's frame for an articulated object)"),
    *_xyz("normal", "", "contact normal, world frame, unit length, pointing from the object to the hand"),
    *_xyz("force", "N", "force the hand exerts on the object at the point, world frame"),
    *_xyz("torque", "N m", "torsional / rolling friction torque the hand exerts on the object, world frame"),
    Column("depth", pa.float64(), "m", "penetration depth, >= 0"),
)

#: Protocols and stages of the metric columns: all frames, and the paper's (frames 10 onward); the raw replay
#: (the recording retargeted, not optimised) and the refined result.
PROTOCOLS: tuple[str, ...] = ("all_frames", "paper")
STAGES: tuple[str, ...] = ("raw", "refined")
#: Metric key in a result summary -> (Arrow type, unit, meaning).
METRICS: dict[str, tuple[pa.DataType, str, str]] = {
    "success": (pa.bool_(), "", "every frame within 3 cm / 30 deg of the recorded object (and 15 deg per joint)"),
    "E_t": (pa.float64(), "cm", "mean object position error"),
    "E_r": (pa.float64(), "deg", "mean object rotation error"),
    "max_E_t": (pa.float64(), "cm", "largest per-frame object position error"),
    "max_E_r": (pa.float64(), "deg", "largest per-frame object rotation error"),
    "E_j": (pa.float64(), "cm", "mean hand keypoint error against the recorded hand"),
    "E_ft": (pa.float64(), "cm", "mean fingertip error against the recorded hand"),
    "E_a": (pa.float64(), "deg or cm", "mean joint error of an articulated object (cm for a sliding part)"),
    "penetration_mean_mm": (pa.float64(), "mm", "mean over frames of the deepest hand-object penetration"),
    "penetration_max_mm": (pa.float64(), "mm", "deepest hand-object penetration of the sequence"),
    "hand_only_fraction": (pa.float64(), "", "share of lifted frames in which the hand alone holds the object"),
}


def metric_column(protocol: str, stage: str, key: str) -> str:
    return f"{protocol}_{stage}_{key}"


_METRIC_COLUMNS = tuple(
    Column(metric_column(p, s, k), t, u, f"{m}: {s} stage, {'all frames' if p == 'all_frames' else 'frames 10 on'}")
    for p in PROTOCOLS for s in STAGES for k, (t, u, m) in METRICS.items()
)  # fmt: skip

#: Packages whose versions a result records (``summary.versions``), each an index column ``version_<name>``.
VERSIONED: tuple[str, ...] = ("hoi-refine", "python", "mujoco", "numpy", "scipy", "cma")

INDEX_COLUMNS: tuple[Column, ...] = (
    Column("sequence", pa.string(), "", "the sequence's name (unique in the release)"),
    Column("result_file", pa.string(), "", "the result file, relative to the release (null: the job has none)"),
    Column("job_id", pa.string(), "", "the service's job (exported from a batch; null from a folder)"),
    Column("job_state", pa.string(), "", "the job's state (SUCCEEDED, FAILED, CANCELLED; null from a folder)"),
    Column("job_error", pa.string(), "", "a job without a result: its last error"),
    Column("frames", pa.int32(), "", "frames simulated"),
    Column("fps", pa.float64(), "1/s", "frame rate"),
    Column("object", pa.string(), "", "the object's name"),
    Column("hands", pa.string(), "", "hand sides driven, comma-separated (right, left)"),
    Column("contacts", pa.int64(), "", "rows of this sequence in contacts.parquet"),
    Column("outcome", pa.string(), "", "executable, not_executable, or unknown (a result older than outcomes)"),
    Column("executable", pa.bool_(), "", "success on the paper protocol (null: unknown)"),
    Column("reason", pa.string(), "", "the most telling reason code (common/outcome.py ReasonCode)"),
    Column("reason_frame", pa.int32(), "", "the frame the reason concerns, 0-based"),
    Column("reason_value", pa.float64(), "reason_unit", "the reason's evidence"),
    Column("reason_unit", pa.string(), "", "the unit of reason_value"),
    Column("reason_message", pa.string(), "", "the reason in one sentence"),
    Column("reasons", pa.string(), "", "every reason code, most telling first, ';'-separated"),
    *_METRIC_COLUMNS,
    Column("file_sha256", pa.string(), "", "SHA-256 of the result file's bytes (as in SHA256SUMS)"),
    Column("content_sha256", pa.string(), "", "SHA-256 of the result's content but its wall-clock timings "
           "(what `hoi-refine verify` prints)"),
    Column("worker_verified", pa.bool_(), "", "the worker re-derived the result before storing it and it matched "
           "(null from a folder)"),
    Column("checked_sha256", pa.string(), "", "SHA-256 over what the worker's verification checked (null from a "
           "folder)"),
    Column("seed", pa.int64(), "", "the refinement's seed"),
    *(Column(f"version_{name.replace('-', '_')}", pa.string(), "", f"{name}'s version") for name in VERSIONED),
    Column("cpu", pa.string(), "", "the CPU model that made the result"),
    Column("numpy_simd", pa.string(), "", "NumPy's SIMD dispatch there (the replay is bit-exact on the same kind)"),
    Column("versions_json", pa.string(), "", "every recorded version (JSON object)"),
    Column("physics_json", pa.string(), "", "the MuJoCo settings the result was simulated with (JSON object: "
           "timestep, substeps, solver, friction, ...)"),
    Column("config_json", pa.string(), "", "the whole refinement config (JSON: physics, keyframes, CMA-ES, loss "
           "weights)"),
    Column("options_json", pa.string(), "", "the job options (JSON)"),
)


def schema(columns: tuple[Column, ...]) -> pa.Schema:
    """The Arrow schema, each field's unit and meaning in its metadata (``field.metadata[b"unit"]``)."""
    return pa.schema([pa.field(c.name, c.type, metadata={"unit": c.unit, "meaning": c.meaning}) for c in columns])
