"""Options of one refinement job: the contract between the API, the bulk tool, the CLI and the worker.

Everything here is optional; ``None`` means "the refinement's documented default" (see ``worker.refine``).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from common.hand_description import HandDescription, packed_model_problems
from common.json_int import JsonInt, OptionalJsonInt

#: Loss terms of DESIGN §1.5; each weight may be set (0 disables the term, for ablations).
LossName = Literal[
    "object_pose",
    "object_velocity",
    "object_excursion",
    "hand_joints",
    "fingertip_contact",
    "control_consistency",
    "hand_velocity",
    "penetration",
    "grasp_reach",
    "robot_joints",
    "robot_speed",
    "object_articulation",
]
LOSS_NAMES: tuple[str, ...] = LossName.__args__  # type: ignore[attr-defined]


class JobOptions(BaseModel):
    # Every float finite (issue #16): JSON's non-standard Infinity/NaN are refused, not stored.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    seed: JsonInt = Field(default=0, ge=0, le=2**31 - 1,
                          description="CMA-ES seed; same input+options+seed => same bytes")
    keyframe_interval: OptionalJsonInt = Field(
        default=None, ge=1, le=240, description="Frames between control keyframes; default round(fps / 6)"
    )
    max_generations: OptionalJsonInt = Field(default=None, ge=1, le=1000, description="CMA-ES generations per window")
    popsize: OptionalJsonInt = Field(default=None, ge=2, le=256, description="CMA-ES population size")
    loss_weights: dict[LossName, Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)]] = Field(
        default_factory=dict, description="Overrides of the default loss weights (each finite, >= 0)"
    )
    free_wrist_translation: bool = Field(default=False, description="Also optimise a 3-D wrist translation offset")
    restarts: JsonInt = Field(
        default=3, ge=0, le=5,
        description="Further attempts when the result fails the success criterion (every frame within 3 cm / "
        "30 deg) or the first attempt's object error is above the published method's mean (0.67 cm + 2.97 deg): "
        "the lookahead's rotation error charged, with the job's seed then others; the best attempt is kept",
    )  # fmt: skip
    polish: bool = Field(
        default=True,
        description="After the attempts, when the best one's object error is above half the published method's "
        "mean, another sweep over its windows in which each keyframe sees the later ones; kept only if better, "
        "and repeated from it while kept and still above that level (at most 10 sweeps)",
    )
    tail: Literal["full", "bounded"] = Field(
        default="full",
        description="'full': the whole plan runs (attempts, polish sweeps, the rescue on finer convex parts). "
        "'bounded': when the first attempt fails where the recording turns the object faster than any grasp can "
        "follow (more than 45 deg between two frames at 30 fps, and the result leaves the 3 cm / 30 deg limit there "
        "and not before), the rest of the plan is skipped and the result's outcome says plan_cut_short: a fraction "
        "of the time, for a result that stays a failure (and is often worse than the full plan's)",
    )
    evaluation_budget: int | None = Field(
        default=None, ge=1, le=100_000_000,
        description="Start no further attempt, polish sweep or rescue once this many candidate evaluations (CMA-ES "
        "candidates simulated) are spent; the run under way finishes and the first attempt always runs whole. "
        "The result's outcome then says plan_cut_short. Default: no budget",
    )  # fmt: skip
    hand: HandDescription | None = Field(
        default=None,
        description="The hand that executes the motion: None, the built-in human hand; a packed robot hand "
        "description (its model inlined, actuated joints, keypoint correspondence; "
        "`hoi-refine hand pack allegro|leap|FILE` makes one)",
    )
    two_hands: Literal["per_hand", "joint"] = Field(
        default="per_hand",
        description="With two hands: 'per_hand' runs a CMA-ES per hand on paired rollouts, each minimising the "
        "object's terms plus its own hand's (the published method); 'joint' one CMA-ES over both hands' keyframes "
        "minimising the object's terms once plus both hands'",
    )
    # Off by default until measured beyond ARCTIC's mixer, which it took to success for about a third of a run
    # more (bench/results/refine_arctic.md).
    local_repair: bool = Field(
        default=False,
        description="With two hands or an articulated object: the polish of a failed attempt re-optimises only the "
        "keyframes around its first frame past the success limit (a few rounds, at most half the first pass's "
        "evaluations) instead of sweeping the whole sequence; one hand on a rigid object keeps the sweeps",
    )
    priority: JsonInt = Field(default=0, ge=-100, le=100, description="Higher runs first (queue only)")
    preview_video: bool = Field(
        default=True,
        description="After the job succeeds, the worker also renders a preview video (640x480 per panel, raw vs "
        "refined), plots, a Rerun recording and a plain-MuJoCo export, served under /v1/jobs/{id}/video etc. "
        "(the service only; no effect on the result)",
    )
    # Off by default: the preview already costs seconds per job, and the close-up's video adds to that
    # (bench/results/video_framing.md). Ignored without preview_video, so that no pair of values is refused.
    preview_close_up: bool = Field(
        default=False,
        description="With preview_video: also a close-up video (the camera follows the recorded object and frames it "
        "with the fingers at it), served at /v1/jobs/{id}/close-up; adds a few seconds to the preview "
        "(the service only; no effect on the result)",
    )

    @field_validator("hand")
    @classmethod
    def _packed_hand(cls, value: HandDescription | None) -> HandDescription | None:
        if value is None:
            return value
        if value.model_xml is None:
            raise ValueError("model: a path cannot travel with a job: pack the description (hoi-refine hand pack), "
                             "which inlines the model as model_xml")
        problems = packed_model_problems(value, "hand")
        if problems:
            raise ValueError("; ".join(str(p) for p in problems))
        return value

    def model_post_init(self, __context: object) -> None:
        for name, weight in self.loss_weights.items():
            if not weight >= 0:  # also rejects NaN
                raise ValueError(f"loss_weights.{name} must be >= 0, got {weight}")
