"""Request and response bodies of the ``/v1`` API (like full-stack-fastapi-template's ``models.py``).

``JobCreate`` mirrors the native JSON sequence form (``common.sequence_io.sequence_to_json_dict``) plus an
``options`` object; the types here catch malformed JSON early with the field named, and
``sequence_from_json_dict`` then checks the content (shapes, quaternions, frame counts).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from common.articulation import MAX_PARTS
from common.batch_metrics import OUTCOMES, UNKNOWN
from common.job_options import JobOptions
from common.job_state import JobState
from common.json_int import JsonInt, integral_float_as_int
from common.outcome import REASON_DESCRIPTIONS
from common.progress import STEPS
from common.queue_types import JobRecord
from common.safe_text import FREE_TEXT_PATTERN, MAX_META_ENTRIES, MAX_META_KEY_CHARS, MAX_META_VALUE_CHARS, TEXT_PATTERN
from common.sequence import MAX_ABS_VALUE, MAX_FPS, MAX_MASS_KG, MAX_NAME_CHARS, MIN_FRAMES
from service import links

VertexIndex = Annotated[int, Field(ge=0, le=2**31 - 1), BeforeValidator(integral_float_as_int)]
#: Every number of a per-frame array or a mesh (``common.sequence`` refuses larger magnitudes).
Coordinate = Annotated[float, Field(ge=-MAX_ABS_VALUE, le=MAX_ABS_VALUE)]
Vec3 = Annotated[list[Coordinate], Field(min_length=3, max_length=3)]
#: Names may hold no control or bidi formatting character (``common.safe_text``); the server checks that itself,
#: naming the code point, so the pattern is stated in the schema only.
Name = Annotated[str, Field(max_length=MAX_NAME_CHARS, json_schema_extra={"pattern": TEXT_PATTERN})]
#: (Stated as propertyNames: a key pattern on the dict's key type would become patternProperties, which leaves keys
#: that do not match it unconstrained.)
Meta = Annotated[
    dict[str, str],
    Field(
        max_length=MAX_META_ENTRIES,
        json_schema_extra={
            "propertyNames": {"maxLength": MAX_META_KEY_CHARS, "pattern": TEXT_PATTERN},
            "additionalProperties": {"type": "string", "maxLength": MAX_META_VALUE_CHARS, "pattern": FREE_TEXT_PATTERN},
        },
    ),
]


class PrimitiveIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    kind: Literal["box", "cylinder", "sphere", "capsule"]
    size: list[Annotated[float, Field(gt=0, le=5)]] = Field(
        min_length=1, max_length=3,
        description="metres: box half-extents (3); cylinder/capsule (radius, half-length); sphere r (1)",
    )  # fmt: skip


class MeshIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    vertices: list[Vec3] = Field(min_length=4, description="metres; the mesh at most 5 m across and not flat")
    faces: list[Annotated[list[VertexIndex], Field(min_length=3, max_length=3)]] = Field(
        min_length=4, description="vertex indices, each below the number of vertices"
    )


class OriginIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    pos: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0], description="the part frame's origin in its "
                      "parent's frame at joint value 0 (m)")  # fmt: skip
    quat: Annotated[list[Coordinate], Field(min_length=4, max_length=4)] = Field(
        default_factory=lambda: [1.0, 0.0, 0.0, 0.0], description="the part frame's orientation in its parent's "
        "frame at joint value 0 (w x y z)")  # fmt: skip


class JointIn(BaseModel):
    """The joint that hangs a part from its parent, in URDF's conventions."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: Annotated[Name, Field(min_length=1)]
    type: Literal["revolute", "prismatic"]
    parent: str = Field(description="the base part's name (object.base_part) or a part listed before this one")
    axis: Vec3 = Field(description="unit vector in the part's frame (normalised; must not be zero)")
    origin: OriginIn | None = Field(default=None, description="default: the parent's frame")
    limits: Annotated[list[Coordinate], Field(min_length=2, max_length=2)] = Field(
        description="lower, upper (rad for revolute, m for prismatic); every recorded value must lie within")
    damping: float | None = Field(default=None, ge=0, le=1000, description="N m s/rad or N s/m; default: the "
                                  "simulation's setting")  # fmt: skip
    friction: float | None = Field(default=None, ge=0, le=1000, description="N m or N; default: the simulation's "
                                   "setting")  # fmt: skip


class PartIn(BaseModel):
    """A part of an articulated object beyond its base: its shape (a mesh or a primitive) and its joint."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: Name
    mass_kg: float = Field(gt=0, le=MAX_MASS_KG)
    friction: float | None = Field(default=None, gt=0, le=10)
    primitive: PrimitiveIn | None = Field(default=None, description="exactly one of primitive and mesh")
    mesh: MeshIn | None = Field(default=None, description="exactly one of primitive and mesh")
    joint: JointIn


class ObjectIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: Name = "object"
    mass_kg: float = Field(gt=0, le=MAX_MASS_KG)
    friction: float | None = Field(default=None, gt=0, le=10)
    primitive: PrimitiveIn | None = Field(default=None, description="exactly one of primitive and mesh")
    mesh: MeshIn | None = Field(default=None, description="exactly one of primitive and mesh")
    base_part: Annotated[Name, Field(min_length=1)] | None = Field(default=None, description="an articulated "
                                                                   "object's base part name (default "
                                   "'base'): this shape, posed by object_pose")  # fmt: skip
    parts: list[PartIn] = Field(default_factory=list, max_length=MAX_PARTS, description="an articulated object's "
                                "further parts, parents before children (format_version 2)")  # fmt: skip


class ManoIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    global_orient: list[Vec3] = Field(min_length=MIN_FRAMES, description="(T, 3) axis-angle")
    hand_pose: list[list[Coordinate]] = Field(
        min_length=MIN_FRAMES, description="(T, 45) axis-angle, or (T, 1-45) PCA coefficients"
    )
    trans: list[Vec3] = Field(min_length=MIN_FRAMES, description="(T, 3) metres")
    betas: list[Coordinate] = Field(default_factory=lambda: [0.0] * 10)
    pose_format: Literal["axis_angle", "pca"] = "axis_angle"
    flat_hand_mean: bool = False


class HandIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    side: Literal["right", "left"]
    valid: list[bool] = Field(
        min_length=MIN_FRAMES,
        json_schema_extra={"contains": {"const": True}},
        description="(T,) per frame: is the hand tracked? At least one frame must be",
    )
    keypoints: list[Annotated[list[Vec3], Field(min_length=21, max_length=21)]] | None = Field(
        default=None, min_length=MIN_FRAMES, description="(T, 21, 3) metres; a hand needs keypoints or MANO parameters"
    )
    mano: ManoIn | None = Field(default=None, description="MANO parameters (the server needs the MANO model files)")


class JobCreate(BaseModel):
    """A sequence in the native JSON form, with the job's options."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    format: Literal["hoi-refine-sequence"] = "hoi-refine-sequence"
    format_version: Literal[1, 2] = Field(default=1, description="2 for an articulated object (object.parts)")
    name: Annotated[Name, Field(min_length=1)] = "sequence"
    fps: float = Field(gt=0, le=MAX_FPS)
    frame_start: JsonInt = Field(default=0, ge=0, le=2**31 - 1)
    object: ObjectIn
    object_pose: list[Annotated[list[Coordinate], Field(min_length=7, max_length=7)]] = Field(
        min_length=MIN_FRAMES,
        description="(T, 7): x y z qw qx qy qz per frame, the quaternion of unit length; T is every per-frame "
        "array's length, at most the server's HOI_REFINE_MAX_FRAMES",
    )
    hands: list[HandIn] = Field(min_length=1, max_length=2, description="at most one per side")
    world_from_camera: list[Annotated[list[Coordinate], Field(min_length=4, max_length=4)]] | None = Field(
        default=None, min_length=4, max_length=4, description="4x4 rigid transform source -> world"
    )
    up: Vec3 | None = Field(default=None, description="non-zero; ignored when world_from_camera is given")
    articulation: list[list[Coordinate]] | None = Field(
        default=None, min_length=MIN_FRAMES,
        description="(T, J) every joint's recorded value per frame (rad / m), J = len(object.parts), each within "
        "its joint's limits",
    )
    meta: Meta = Field(default_factory=dict)
    options: JobOptions = Field(default_factory=JobOptions)
    batch_id: str | None = Field(default=None, max_length=32, description="Submit into this batch (POST /v1/batches)")


class ProgressPublic(BaseModel):
    """What the worker last reported. A worker older than the whole-job ``fraction`` reported only its window
    within the current pass: then ``eta_s`` is estimated here from the window rate when it gives none."""

    model_config = ConfigDict(extra="allow")
    fraction: float | None = Field(default=None, description="0..1 over the whole job; only goes forward")
    stage: str | None = Field(default=None, description="what runs now, e.g. 'attempt 2 of 4', 'polish sweep 3', "
                              "'compiling finer parts for a rescue', 'rescue on finer parts: attempt 1 of 4', "
                              "'verifying', 'preview', 'done'")  # fmt: skip
    step: str | None = Field(default=None, description="the same for programs: " + ", ".join(STEPS))
    eta_s: float | None = Field(default=None, description="seconds until the whole job is done (0 when done)")
    elapsed_s: float | None = Field(default=None, description="seconds since the job's computation started")
    attempt: int | None = Field(default=None, description="the queue's attempt at the job (as the job's attempt)")
    refine_attempt: int | None = Field(default=None, description="the refinement's own attempt (1, then restarts)")
    refine_attempts: int | None = Field(default=None, description="the most refinement attempts the options allow")
    polish_sweep: int | None = Field(default=None, description="the polish sweep running, if one is")
    window: int | None = Field(default=None, description="sliding window within the current attempt or sweep")
    windows: int | None = Field(default=None, description="windows in the current attempt or sweep")
    best_loss: float | None = None
    evaluations: int | None = Field(default=None, description="candidate evaluations in the job so far")


OutcomeStatus = Literal[OUTCOMES]  # type: ignore[valid-type]


class ReasonPublic(BaseModel):
    """Why a sequence is not executable (or was rescued), with its evidence."""

    code: str = Field(
        description="machine-readable class of the reason: "
        + "; ".join(f"{code.value}: {text}" for code, text in REASON_DESCRIPTIONS.items())
    )
    frame: int | None = Field(description="the frame it was found at, when it has one")
    value: float | None = Field(description="the measured figure, in ``unit``")
    unit: str | None = Field(description="unit of ``value`` (e.g. cm/frame, deg/frame, cm, frames)")
    message: str = Field(description="one sentence for a person")


class OutcomePublic(BaseModel):
    """Whether the refined sequence is executable: it passes the success test (every frame within 3 cm and 30
    deg of the recorded object) on ``protocol``; ``unknown`` for a result made before outcomes existed."""

    status: OutcomeStatus = Field(description="executable, not_executable, or unknown")
    protocol: str | None = Field(description="the protocol the test is judged on: paper = frames 10 onward")
    reasons: list[ReasonPublic] = Field(description="the first reasons (the result's summary holds them all)")
    reasons_total: int = Field(description="how many reasons the result gives")
    E_t: float | None = Field(description="refined object position error, cm, on ``metrics_protocol``")
    E_r: float | None = Field(description="refined object rotation error, deg, on ``metrics_protocol``")
    metrics_protocol: str | None = Field(description="the protocol E_t and E_r are measured on")

    @classmethod
    def from_record(cls, job: JobRecord) -> OutcomePublic | None:
        if job.state != JobState.SUCCEEDED:
            return None
        detail = job.outcome_detail or {}
        return cls(
            status=job.outcome or UNKNOWN, protocol=detail.get("protocol"), reasons=detail.get("reasons") or [],
            reasons_total=int(detail.get("reasons_total") or 0), E_t=detail.get("E_t"), E_r=detail.get("E_r"),
            metrics_protocol=detail.get("protocol_metrics"),
        )  # fmt: skip


class LinkPublic(BaseModel):
    href: str = Field(description="URL relative to the API's base URL (GET, same API key)")
    type: str = Field(description="media type of what the URL returns")
    title: str


class FilePublic(BaseModel):
    """A file stored beside the result (preview video, Rerun recording, export, plots)."""

    name: str = Field(description="the stored name, e.g. video.mp4 or plots/errors.png")
    href: str = Field(description="URL relative to the API's base URL (GET, same API key)")
    type: str = Field(description="media type")
    size_bytes: int


class JobError(BaseModel):
    attempt: int
    at: str
    error: str
    worker: str | None = None


def hand_name(options: dict[str, Any]) -> str:
    """The name of a job's hand (``JobOptions.hand``): "human" without a robot description."""
    hand = (options or {}).get("hand")
    return str(hand.get("name", "robot")) if isinstance(hand, dict) else "human"


class JobPublic(BaseModel):
    id: str
    batch_id: str | None = None
    name: str
    state: JobState
    outcome: OutcomePublic | None = Field(
        default=None, description="once SUCCEEDED: whether the refined sequence is executable, and why not"
    )
    attempt: int = Field(description="the queue's run of this job: 1, then +1 each time it is requeued")
    max_attempts: int
    priority: int
    num_frames: int
    options: dict[str, Any]
    #: The hand that executes the motion (issue #55): "human" (the built-in hand) or the robot description's name.
    hand: str = "human"
    cancel_requested: bool
    created_at: datetime
    queued_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    progress: ProgressPublic | None
    errors: list[JobError]
    #: ``metrics`` (raw replay and refined) and run facts from the result summary, once SUCCEEDED.
    summary: dict[str, Any] | None = Field(
        default=None,
        description="the result's summary once SUCCEEDED (only on GET /v1/jobs/{id}); preview.files are URLs",
    )
    links: dict[str, LinkPublic] = Field(
        default_factory=dict,
        description="self, events, input, dashboard, batch; once SUCCEEDED result, result_npz, contacts, metrics "
        "and each stored file's route (video, recording, export, plots)",
    )
    files: list[FilePublic] = Field(default_factory=list, description="files stored beside the result")

    @classmethod
    def from_record(cls, job: JobRecord) -> JobPublic:
        progress = None
        if job.progress is not None:
            progress = ProgressPublic.model_validate(job.progress)
            older = progress.fraction is None
            if older and progress.eta_s is None and job.state == JobState.RUNNING and job.started_at:
                # Rate up to the last heartbeat (updated_at), not up to now: the representation, and so its
                # ETag, then changes only when the job does.
                progress.eta_s = _eta(progress, (job.updated_at - job.started_at).total_seconds())
        return cls(
            id=job.id, batch_id=job.batch_id, name=job.name, state=job.state,
            attempt=job.attempt, max_attempts=job.max_attempts, priority=job.priority, num_frames=job.num_frames,
            options=job.options, hand=hand_name(job.options), cancel_requested=job.cancel_requested,
            created_at=job.created_at,
            queued_at=job.queued_at, started_at=job.started_at, finished_at=job.finished_at,
            updated_at=job.updated_at, progress=progress, errors=[JobError.model_validate(e) for e in job.errors],
            summary=_with_preview_urls(job.id, job.summary), outcome=OutcomePublic.from_record(job),
            links=links.job_links(job.id, job.state, job.batch_id, [(f.name, f.content_type) for f in job.files]),
            files=links.file_entries(job.id, [(f.name, f.content_type, f.size_bytes) for f in job.files]),
        )  # fmt: skip


def _with_preview_urls(job_id: str, summary: dict[str, Any] | None) -> dict[str, Any] | None:
    """The summary with ``preview.files`` (stored names) as the URLs that serve them."""
    preview = summary.get("preview") if summary else None
    if summary is None or not isinstance(preview, dict) or not isinstance(preview.get("files"), list):
        return summary
    urls = [links.artifact_href(job_id, n) if isinstance(n, str) else None for n in preview["files"]]
    return {**summary, "preview": {**preview, "files": [u for u in urls if u is not None]}}


def _eta(progress: ProgressPublic, elapsed_s: float) -> float | None:
    if not progress.window or not progress.windows or progress.window <= 0:
        return None
    return elapsed_s / progress.window * max(progress.windows - progress.window, 0)


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int
    next_page_token: str | None = Field(
        description="Opaque token issued by the service: pass it as page_token for the next page; null on the last page"
    )


class JobEventPublic(BaseModel):
    id: int
    at: datetime
    kind: str = Field(description="submitted, claimed, progress, requeued, released, cancel_requested, cancelled, "
                      "succeeded, failed, retried, batched, deleted")  # fmt: skip
    detail: dict[str, Any]


class JobEventsPublic(BaseModel):
    job_id: str
    events: list[JobEventPublic]


class ContactPublic(BaseModel):
    """One hand-object contact in one frame; the wrench is the one the hand exerts on the object."""

    frame: int = Field(description="frame index (0-based)")
    hand: str = Field(description="hand side: right or left")
    body: str = Field(description="hand body touching the object (palm, thumb1 ... pinky3)")
    position_world: list[float] = Field(description="contact point, world frame, m (x, y, z)")
    position_object: list[float] = Field(description="contact point in the frame of the object part touched (the "
                                         "object's own for a rigid object), m (x, y, z)")
    normal: list[float] = Field(description="contact normal, world frame, unit vector from the object to the hand")
    force: list[float] = Field(description="force of the hand on the object, world frame, N (x, y, z)")
    torque: list[float] = Field(description="torque of the hand on the object about the contact point, world "
                                "frame, N·m (x, y, z)")  # fmt: skip
    depth: float = Field(description="penetration depth, m (>= 0)")
    part: str | None = Field(default=None, description="the object part touched (an articulated object), else null")


class ContactsPublic(BaseModel):
    job_id: str
    start: int | None
    end: int | None
    count: int
    contacts: list[ContactPublic]


class MetricsPublic(BaseModel):
    job_id: str
    metrics: dict[str, Any] = Field(
        description="``raw`` (replay of the recording) and ``refined``: E_t (cm), E_r (deg), E_j and E_ft (cm), "
        "success, penetration (mm) over all frames, the same on the paper's protocol under ``paper`` (frames 10 "
        "onward); ``verification`` (the worker's replay of the stored result); ``outcome`` when the result has one"
    )


class PlotPublic(BaseModel):
    name: str = Field(description="file name, e.g. errors.png")
    url: str = Field(description="where to GET the PNG (same API key)")
    size_bytes: int


class PlotsPublic(BaseModel):
    job_id: str
    plots: list[PlotPublic]


class ResultJson(BaseModel):
    job_id: str
    summary: dict[str, Any]
    arrays: dict[str, Any] = Field(description="Every array of the result file as nested lists, but the per-frame "
                                   "integration states and per-step inputs (state_sim, raw_state_sim, control_sim, "
                                   "raw_control_sim: in the NPZ, for verify)")


class ProblemField(BaseModel):
    field: str
    problem: str


class Problem(BaseModel):
    """RFC 9457 problem details (``application/problem+json``)."""

    type: str = "about:blank"
    title: str
    status: int
    detail: str | None = None
    errors: list[ProblemField] | None = None
