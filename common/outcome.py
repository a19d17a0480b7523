"""A refinement result's outcome: whether it is executable, and why not (issue #53 items 1-2).

A job that ran to the end is ``SUCCEEDED`` whatever the refinement achieved; what it achieved is the result's
``outcome``, stored in the result summary (``summary["outcome"]``) and copied into the job's metrics::

    "outcome": {"executable": bool, "protocol": "paper",
                "reasons": [{"code": str, "frame": int | null, "value": float | null, "unit": str | null,
                             "message": str}, ...]}

``executable`` is success on ``protocol``: the paper's (frames 10 onward every frame within 3 cm / 30 deg of the
recorded object, ``worker.simulation.metrics``). The job's metrics (``summary["metrics"]``,
``GET /v1/jobs/{id}/metrics``) carry the same object under ``outcome``. ``reasons`` explain a result that is not
executable, found from the sequence's own data and its simulation (``worker.refine.outcome``), most telling first;
an executable result has none, except a rescued one (kept on the finer convex parts), which carries
``rescued_on_finer_parts``, and a robot hand's whose motion exceeds the robot's joint speed limits, which carries
``robot_too_fast`` (the object is held in simulation, but the real hand cannot move that fast). Each reason is one
of the fixed ``ReasonCode`` set: machine-readable (code, the frame it concerns, a value in a stated unit) and one
human sentence. The set, the units and the schema are defined here once, so the service, the client and the worker
share them.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

#: The protocol ``executable`` is judged on (``metrics.refined.paper``).
PROTOCOL: Literal["paper"] = "paper"


class ReasonCode(StrEnum):
    """Why a result is not executable (or, for ``RESCUED_ON_FINER_PARTS``, how an executable one was reached).
    A member *is* its string (lowercase snake_case), as stored in the JSON."""

    #: The recorded object turns or moves between two frames faster than any grasp can follow (an annotation
    #: jump): value in deg/frame or cm/frame, at frame (the later of the two).
    RECORDING_TOO_FAST = "recording_too_fast"
    #: The object is not supported as recorded at the start: released where it rests, it falls or rolls before
    #: the hand touches it. value: how far (cm or deg), frame: when it had moved that far.
    UNSUPPORTED_START = "unsupported_start"
    #: The hand is annotated in too few frames to be driven along it. value: the annotated share (fraction),
    #: frame: the first frame of the longest gap.
    HAND_SPARSE = "hand_sparse"
    #: The simulated hand never touches the object. value: the closest the recorded hand comes to its surface
    #: (cm), frame: where it comes closest.
    NO_CONTACT = "no_contact"
    #: The recorded fingers pass through the object's simulated geometry (e.g. an opening the convex parts
    #: fill). value: the deepest recorded fingertip inside it (mm), frame: where.
    FINGERS_THROUGH_OBJECT = "fingers_through_object"
    #: The hand touches the object but never lifts it where the recording does. value: the largest height the
    #: simulated object reaches above its start while the recorded one is lifted (cm), frame: the first frame
    #: past the limit.
    NOT_LIFTED = "not_lifted"
    #: The object slips out of (or turns in) the grasp. value: the error at the first frame past the limit (cm or
    #: deg), frame: that frame.
    SLIPPED = "slipped"
    #: The object leaves the 3 cm / 30 deg limit and none of the checks above explains why. value and frame: as
    #: ``SLIPPED``.
    OFF_TRACK = "off_track"
    #: The refinement stopped before its whole plan ran, on its evaluation or time budget (a job option) or
    #: because an earlier reason says no grasp can follow the recording. value: the candidate evaluations
    #: spent (unit "evaluations") or seconds (unit "s"); frame: null.
    PLAN_CUT_SHORT = "plan_cut_short"
    #: The result was reached on the finer convex parts after every attempt on the product's parts failed
    #: (carried by executable results too). frame and value: null.
    RESCUED_ON_FINER_PARTS = "rescued_on_finer_parts"
    #: A robot hand's simulated joints or commanded servo targets move faster than the robot's joint speed limits
    #: (carried by executable results too: the real hand cannot follow them). value: the largest joint speed over
    #: its limit (unit "ratio"), frame: where (``worker.robot.metrics``).
    ROBOT_TOO_FAST = "robot_too_fast"


#: A one-line description of each code, for documentation, the dashboard's legend and ``--help`` texts.
REASON_DESCRIPTIONS: dict[ReasonCode, str] = {
    ReasonCode.RECORDING_TOO_FAST: "the recorded object turns or moves faster than any grasp can follow",
    ReasonCode.UNSUPPORTED_START: "the object is not supported as recorded: it falls or rolls before contact",
    ReasonCode.HAND_SPARSE: "the hand is annotated in too few frames",
    ReasonCode.NO_CONTACT: "the hand never touches the object",
    ReasonCode.FINGERS_THROUGH_OBJECT: "the recorded fingers pass through the object's geometry",
    ReasonCode.NOT_LIFTED: "the hand touches the object but does not lift it",
    ReasonCode.SLIPPED: "the object slips out of the grasp",
    ReasonCode.OFF_TRACK: "the object leaves the 3 cm / 30 deg limit for no reason found",
    ReasonCode.PLAN_CUT_SHORT: "the refinement stopped before its whole plan ran",
    ReasonCode.RESCUED_ON_FINER_PARTS: "kept on the object's finer convex parts",
    ReasonCode.ROBOT_TOO_FAST: "the robot hand's joints move faster than its speed limits",
}

#: Codes that explain why a result is not executable (every code but the informative ones).
FAILURE_CODES: frozenset[ReasonCode] = frozenset(ReasonCode) - {ReasonCode.RESCUED_ON_FINER_PARTS,
                                                                 ReasonCode.PLAN_CUT_SHORT, ReasonCode.ROBOT_TOO_FAST}

#: The units a reason's ``value`` is stated in.
Unit = Literal["deg/frame", "cm/frame", "cm", "deg", "mm", "fraction", "evaluations", "s", "ratio"]


class OutcomeReason(BaseModel):
    """One reason: a code from ``ReasonCode``, the frame it concerns (0-based; null when none), a value in
    ``unit`` (null when none) and one human sentence."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    code: ReasonCode
    frame: int | None = Field(default=None, ge=0, description="0-based frame the reason concerns, if any")
    value: float | None = Field(default=None, description="The evidence, in `unit`")
    unit: Unit | None = Field(default=None, description="The unit of `value`")
    message: str = Field(description="One human sentence")


class Outcome(BaseModel):
    """A result's outcome: ``executable`` on ``protocol``, and the reasons (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    executable: bool = Field(description="Success on the paper's protocol: every frame from 10 on within 3 cm / 30 deg")
    protocol: Literal["paper"] = PROTOCOL
    reasons: list[OutcomeReason] = Field(default_factory=list, description="Most telling first")

    @property
    def codes(self) -> list[ReasonCode]:
        return [r.code for r in self.reasons]

    @property
    def rescued(self) -> bool:
        return ReasonCode.RESCUED_ON_FINER_PARTS in self.codes

    def primary(self) -> OutcomeReason | None:
        """The most telling failure reason (the first of ``FAILURE_CODES``), None for an executable result."""
        return next((r for r in self.reasons if r.code in FAILURE_CODES), None)


def outcome_of(summary: dict[str, Any]) -> Outcome | None:
    """The outcome of a result summary (or of a job's metrics, which carry the same keys). A summary made before
    outcomes existed gets ``executable`` from its paper-protocol success and no reasons; None when it has neither
    (a raw replay, a failed job)."""
    stored = summary.get("outcome")
    if stored is not None:
        return Outcome.model_validate(stored)
    nested = summary.get("metrics")
    metrics: dict[str, Any] = nested if isinstance(nested, dict) else summary
    refined = metrics.get("refined") or {}
    paper = refined.get(PROTOCOL)
    if not isinstance(paper, dict) or "success" not in paper:
        return None
    return Outcome(executable=bool(paper["success"]))
