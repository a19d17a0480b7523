"""A robot hand described as data (issue #55 item 1): its model, actuated joints, servo gains and the
correspondence from the human hand's keypoints to sites on the robot.

A description names its model in one of two ways:

* ``model``: a URDF or MJCF file, relative to the description file's folder or to the robot folder
  (``HOI_REFINE_ROBOT_DIR``); what a user writes and what the shipped Allegro and LEAP correspondences do;
* ``model_xml``: the *packed* form, a self-contained MJCF of the robot alone (meshes inline as vertices), made
  from ``model`` by ``worker.robot.pack_description``. Only this form travels with a job (the API, the result,
  ``verify``), so a result re-simulates without the model's files.

``HandDescription`` checks the structure (pydantic); ``packed_model_problems`` checks a packed model's names
without MuJoCo (bodies and joints named in the description exist, joints are limited), so the API answers a bad
description with field-named 422s; the worker checks the compiled model again (``worker.robot.embodiment``).
Errors name fields as ``hand.keypoints.thumb4.body``.

Defaults: the position servos' gains are the human hand's (``worker.simulation.config.SimConfig.finger_kp`` /
``finger_kv``, 50 N·m/rad and 3 N·m·s/rad: a first-order lag of 60 ms that the servo targets' lead
``finger_lead_s`` compensates) unless ``actuator`` says otherwise; a joint's range, velocity and effort limits are
the model's unless the joint entry gives them.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from common.errors import FieldProblem, InputError
from common.safe_text import text_problem
from common.sequence import JOINT_NAMES

#: Names that resolve to a shipped correspondence (``worker/robot/data/<name>.json``) whose model lies in the
#: robot folder (``HOI_REFINE_ROBOT_DIR``: a checkout of the public dex-urdf repository).
BUILTIN_ROBOTS: tuple[str, ...] = ("allegro", "leap")
#: The human hand (the built-in MANO-topology hand), the default.
HUMAN = "human"
#: A packed model larger than this is refused (the Allegro packs to ~14 kB, the LEAP to ~40 kB).
MAX_MODEL_XML_CHARS = 2_000_000

Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]


class HandDescriptionError(InputError):
    """A hand description failed validation; ``problems`` lists every field at fault (``hand.``-prefixed)."""

    title = "Invalid hand description"

    def __init__(self, problems: list[FieldProblem]) -> None:
        self.problems = list(problems)
        super().__init__("; ".join(str(p) for p in self.problems))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class JointSpec(_Strict):
    """One actuated joint (a hinge or slide of the model), in control order."""

    name: str = Field(min_length=1, max_length=128)
    #: Position range (rad or m); the model's own when omitted (a joint without either is refused).
    range: tuple[Finite, Finite] | None = None
    #: Speed limit (rad/s or m/s) for the smoothness metrics; the model's (URDF ``limit velocity``) when omitted.
    velocity: Finite | None = Field(default=None, gt=0)
    #: Actuator force limit (N·m or N) for the force-margin metric and the servo's force range.
    effort: Finite | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _range_order(self) -> JointSpec:
        if self.range is not None and not self.range[0] < self.range[1]:
            raise ValueError(f"range must be [lower, upper] with lower < upper, got {list(self.range)}")
        return self


class SiteSpec(_Strict):
    """Where a human keypoint sits on the robot: a body of the model and an offset in its frame (m)."""

    body: str = Field(min_length=1, max_length=128)
    pos: Vec3 = (0.0, 0.0, 0.0)


class ActuatorSpec(_Strict):
    """Position servo gains (None: the human hand's, see the module docstring)."""

    kp: Finite | None = Field(default=None, gt=0, le=1e5)
    kv: Finite | None = Field(default=None, ge=0, le=1e4)


class MountSpec(_Strict):
    """The robot's root body pose in the built-in human hand's wrist frame, the retargeting's start.
    None: fitted by aligning the robot's wrist and knuckle sites with the human hand's at rest."""

    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: tuple[Finite, Finite, Finite, Finite] = (1.0, 0.0, 0.0, 0.0)


class HandDescription(_Strict):
    """See the module docstring."""

    name: str = Field(min_length=1, max_length=64)
    model: str | None = Field(default=None, max_length=1024)
    model_xml: str | None = Field(default=None, max_length=MAX_MODEL_XML_CHARS)
    #: Which hand the model is; the other side is its mirror image through the root body's xz plane.
    model_side: Literal["right", "left"] = "right"
    #: The body welded to the wrist (None: the model's root body, the one child of the world).
    root_body: str | None = Field(default=None, max_length=128)
    joints: list[JointSpec] = Field(min_length=1, max_length=64)
    actuator: ActuatorSpec = ActuatorSpec()
    #: Human keypoint name (``common.sequence.JOINT_NAMES``) -> robot site. At least the thumb tip and one other
    #: fingertip: the retargeting and the contact terms work on these.
    keypoints: dict[str, SiteSpec] = Field(min_length=2, max_length=21)
    mount: MountSpec | None = None
    #: Radius (m) of the distal segments the grasp-reach term measures from the object (fingertip pads).
    tip_radius: Finite = Field(default=0.01, gt=0, le=0.05)

    @field_validator("name")
    @classmethod
    def _safe_name(cls, value: str) -> str:
        problem = text_problem(value, 64)
        if problem:
            raise ValueError(problem)
        return value

    @field_validator("keypoints")
    @classmethod
    def _known_keypoints(cls, value: dict[str, SiteSpec]) -> dict[str, SiteSpec]:
        unknown = [k for k in value if k not in JOINT_NAMES]
        if unknown:
            raise ValueError(f"unknown human keypoint {unknown[0]!r}; known: {', '.join(JOINT_NAMES)}")
        if "thumb4" not in value:
            raise ValueError("must place thumb4 (the thumb tip): the grasp is formed against the thumb")
        if not any(k in value for k in ("index4", "middle4", "ring4", "pinky4")):
            raise ValueError("must place at least one fingertip besides the thumb's (index4, middle4, ...)")
        return value

    @model_validator(mode="after")
    def _one_model(self) -> HandDescription:
        if (self.model is None) == (self.model_xml is None):
            raise ValueError("give exactly one of model (a URDF/MJCF path) and model_xml (a packed model)")
        names = [j.name for j in self.joints]
        if len(set(names)) != len(names):
            raise ValueError("joints: each joint may be listed once")
        return self

    @property
    def packed(self) -> bool:
        return self.model_xml is not None

    def keypoint_order(self) -> list[str]:
        """The placed keypoints in ``JOINT_NAMES`` order: the order of the robot's keypoint sites."""
        return [k for k in JOINT_NAMES if k in self.keypoints]

    def fingertip_sites(self) -> tuple[int, ...]:
        """Indices of the fingertips (``*4``) among the keypoint sites, thumb first."""
        return tuple(i for i, k in enumerate(self.keypoint_order()) if k.endswith("4"))


def parse_hand_description(data: object, prefix: str = "hand") -> HandDescription:
    """A ``HandDescription`` from decoded JSON/YAML; ``HandDescriptionError`` naming every field at fault."""
    try:
        return HandDescription.model_validate(data)
    except ValidationError as exc:
        raise HandDescriptionError([
            FieldProblem(".".join([prefix, *map(str, e["loc"])]), e["msg"].removeprefix("Value error, "))
            for e in exc.errors()
        ]) from None


def packed_model_problems(desc: HandDescription, prefix: str = "hand") -> list[FieldProblem]:
    """What is wrong with a packed description's names, read from its MJCF without compiling it: the model must
    parse, have the root body, every keypoint's body and every joint (limited, or given a range)."""
    assert desc.model_xml is not None
    try:
        root = ET.fromstring(desc.model_xml)
    except ET.ParseError as exc:
        return [FieldProblem(f"{prefix}.model_xml", f"not XML: {exc}")]
    if root.tag != "mujoco":
        return [FieldProblem(f"{prefix}.model_xml", f"not an MJCF document (root element <{root.tag}>)")]
    bodies = {b.get("name") for b in root.iter("body")}
    joints = {j.get("name"): j for j in root.iter("joint")}
    problems: list[FieldProblem] = []
    if desc.root_body is not None and desc.root_body not in bodies:
        problems.append(FieldProblem(f"{prefix}.root_body", f"no body named {desc.root_body!r} in the model"))
    for name, site in desc.keypoints.items():
        if site.body not in bodies:
            problems.append(FieldProblem(f"{prefix}.keypoints.{name}.body",
                                         f"no body named {site.body!r} in the model"))
    for i, spec in enumerate(desc.joints):
        joint = joints.get(spec.name)
        if joint is None:
            problems.append(FieldProblem(f"{prefix}.joints.{i}.name", f"no joint named {spec.name!r} in the model"))
        elif spec.range is None and joint.get("range") is None:
            problems.append(FieldProblem(f"{prefix}.joints.{i}.range",
                                         f"joint {spec.name!r} has no limits: give a range"))
    return problems


def check_packed(desc: HandDescription, prefix: str = "hand") -> HandDescription:
    """``desc`` if it is packed and its names check out; ``HandDescriptionError`` otherwise."""
    if not desc.packed:
        raise HandDescriptionError([FieldProblem(
            f"{prefix}.model", "a model path cannot travel with a job: pack the description first "
            "(hoi-refine hand pack), which inlines the model as model_xml")])
    problems = packed_model_problems(desc, prefix)
    if problems:
        raise HandDescriptionError(problems)
    return desc
