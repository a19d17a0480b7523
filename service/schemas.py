"""Request and response bodies of the ``/v1`` API (like full-stack-fastapi-template's ``models.py``).

``JobCreate`` mirrors the native JSON sequence form (``common.sequence_io.sequence_to_json_dict``) plus an
``options`` object; the types here catch malformed JSON early with the field named, and
``sequence_from_json_dict`` then checks the content (shapes, quaternions, frame counts).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from common.job_options import JobOptions
from common.job_state import JobState
from common.queue_types import JobRecord
from common.safe_text import FREE_TEXT_PATTERN, MAX_META_ENTRIES, MAX_META_KEY_CHARS, MAX_META_VALUE_CHARS, TEXT_PATTERN
from common.sequence import MAX_ABS_VALUE, MAX_FPS, MAX_MASS_KG, MAX_NAME_CHARS, MIN_FRAMES

VertexIndex = Annotated[int, Field(ge=0, le=2**31 - 1)]
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


class ObjectIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: Name = "object"
    mass_kg: float = Field(gt=0, le=MAX_MASS_KG)
    friction: float | None = Field(default=None, gt=0, le=10)
    primitive: PrimitiveIn | None = Field(default=None, description="exactly one of primitive and mesh")
    mesh: MeshIn | None = Field(default=None, description="exactly one of primitive and mesh")


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
    format_version: Literal[1] = 1
    name: Annotated[Name, Field(min_length=1)] = "sequence"
    fps: float = Field(gt=0, le=MAX_FPS)
    frame_start: int = Field(default=0, ge=0, le=2**31 - 1)
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
    meta: Meta = Field(default_factory=dict)
    options: JobOptions = Field(default_factory=JobOptions)
    batch_id: str | None = Field(default=None, max_length=32, description="Submit into this batch (POST /v1/batches)")


class ProgressPublic(BaseModel):
    """What the worker last reported; ``eta_s`` is estimated from the window rate when the worker gives none."""

    model_config = ConfigDict(extra="allow")
    window: int | None = None
    windows: int | None = None
    best_loss: float | None = None
    evaluations: int | None = None
    eta_s: float | None = None


class JobError(BaseModel):
    attempt: int
    at: str
    error: str
    worker: str | None = None


class JobPublic(BaseModel):
    id: str
    batch_id: str | None = None
    name: str
    state: JobState
    attempt: int
    max_attempts: int
    priority: int
    num_frames: int
    options: dict[str, Any]
    cancel_requested: bool
    created_at: datetime
    queued_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    progress: ProgressPublic | None
    errors: list[JobError]
    #: ``metrics`` (raw replay and refined) and run facts from the result summary, once SUCCEEDED.
    summary: dict[str, Any] | None = None

    @classmethod
    def from_record(cls, job: JobRecord) -> JobPublic:
        progress = None
        if job.progress is not None:
            progress = ProgressPublic.model_validate(job.progress)
            if progress.eta_s is None and job.state == JobState.RUNNING and job.started_at:
                # Rate up to the last heartbeat (updated_at), not up to now: the representation, and so its
                # ETag, then changes only when the job does.
                progress.eta_s = _eta(progress, (job.updated_at - job.started_at).total_seconds())
        return cls(
            id=job.id, batch_id=job.batch_id, name=job.name, state=job.state,
            attempt=job.attempt, max_attempts=job.max_attempts, priority=job.priority, num_frames=job.num_frames,
            options=job.options, cancel_requested=job.cancel_requested, created_at=job.created_at,
            queued_at=job.queued_at, started_at=job.started_at, finished_at=job.finished_at,
            updated_at=job.updated_at, progress=progress, errors=[JobError.model_validate(e) for e in job.errors],
            summary=job.summary,
        )  # fmt: skip


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
    frame: int
    hand: str
    body: str
    position_world: list[float]
    position_object: list[float]
    normal: list[float]
    force: list[float]
    torque: list[float]
    depth: float


class ContactsPublic(BaseModel):
    job_id: str
    start: int | None
    end: int | None
    count: int
    contacts: list[ContactPublic]


class MetricsPublic(BaseModel):
    job_id: str
    metrics: dict[str, Any] = Field(description="``raw`` (reference replay) and ``refined`` metrics, DESIGN §1.8")


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
    arrays: dict[str, Any] = Field(description="Every array of the result file as nested lists")


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
