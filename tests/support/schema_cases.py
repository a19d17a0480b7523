"""Generated submissions made to satisfy what a JSON schema cannot say, so that the positive-data check of
``tests/integration/test_api_schemathesis.py`` holds ``POST /v1/jobs`` to the schema's word too.

Each rule below crosses fields or files, is stated in the schema's descriptions, and is checked by
``common.sequence.Sequence.validate`` (or, for MANO, needs the operator's model files); everything else in the
body stays as generated: one frame count T (at most the server's max_frames) for every per-frame array, unit
quaternions, one hand per side, exactly one of mesh and primitive, a primitive's size count by kind, a mesh
whose faces index its vertices and that is not flat, a rigid world transform, a non-zero up, an NPZ file's
content in the multipart form, an Idempotency-Key used for one payload only, an articulated object's parts and
joint values that fit together (one jointed part whose parent is the base, values within its limits, format version
2; none with format version 1), and no robot hand description in the options (one is valid only against the model
it names, which a generated description does not have).
"""

from __future__ import annotations

import hashlib
import math
from typing import Any

from common.sequence import PRIMITIVE_SIZE_LEN
from tests.support.queue_fixtures import tiny_payload

TETRAHEDRON = {
    "vertices": [[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05]],
    "faces": [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
}
IDENTITY = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]


def consistent_body(case: Any, max_frames: int) -> bool:
    """Make ``case``'s body (a ``POST /v1/jobs`` submission, JSON or multipart) satisfy the rules above; a negative
    case (data the schema refuses, which the server must refuse too) is left alone. True when the body was made
    consistent (a submission generated positive)."""
    body = case.body
    if (case.operation.method.upper(), case.operation.path) != ("POST", "/v1/jobs") or not isinstance(body, dict):
        return False
    meta = case.meta
    if meta is None or meta.generation.mode.is_negative or any(c.mode.is_negative for c in meta.components.values()):
        return False
    # An Idempotency-Key names one payload (another payload under the same key is a 422, a state the schema
    # cannot know), so a generated key is made this payload's own.
    for name in [h for h in case.headers or {} if h.lower() == "idempotency-key"]:
        digest = hashlib.sha256(repr(sorted(body.items())).encode()).hexdigest()[:16]
        case.headers = {**case.headers, name: f"{digest}-{case.headers[name]}"[:200]}
    if "object_pose" in body:
        case.body = consistent_sequence(body, max_frames)
    if isinstance(case.body.get("options"), dict) and case.body["options"].get("hand") is not None:
        case.body = {**case.body, "options": {**case.body["options"], "hand": None}}
    if "sequence" in body:
        case.body = {**case.body, "sequence": tiny_payload()}
        # Schemathesis re-checks an edited body against the schema, and counts any body holding a file as not
        # matching it (a file cannot be checked), which would turn this positive case into a negative one; the
        # file is the one thing changed, so the edited body is taken as generated (schemathesis is pinned).
        case._record_starting_state()
    return True


def consistent_sequence(body: dict[str, Any], max_frames: int) -> dict[str, Any]:
    body = dict(body)
    frames = min(len(body["object_pose"]), max_frames)
    body["object_pose"] = [[*row[:3], *unit_quaternion(row[3:])] for row in body["object_pose"][:frames]]
    obj = dict(body["object"])
    if obj.get("mesh") is not None:
        obj.update(mesh=TETRAHEDRON, primitive=None)
    else:
        primitive = obj.get("primitive") or {"kind": "box", "size": [0.02]}
        count = PRIMITIVE_SIZE_LEN[primitive["kind"]]
        obj["primitive"] = {**primitive, "size": (primitive["size"] * count)[:count]}
    if obj.get("parts"):
        part = {**obj["parts"][0], "mesh": TETRAHEDRON, "primitive": None}
        part["joint"] = {**part["joint"], "parent": obj.get("base_part") or "base", "axis": [0.0, 0.0, 1.0],
                         "origin": None, "limits": [-1.0, 1.0]}  # fmt: skip
        if part["name"] == (obj.get("base_part") or "base"):
            part["name"] = part["name"] + "_part"
        obj["parts"] = [part]
        body["articulation"] = [[0.0]] * frames
        body["format_version"] = 2
    else:
        obj["parts"] = []
        body["articulation"] = None
        body["format_version"] = 1
    body["object"] = obj
    hands, sides = [], set()
    for hand in body["hands"]:
        hand = dict(hand)
        if hand["side"] in sides:
            hand["side"] = "left" if hand["side"] == "right" else "right"
        sides.add(hand["side"])
        hand["valid"] = stretched(hand["valid"], frames)
        if not any(hand["valid"]):
            hand["valid"][0] = True
        # MANO needs the operator's model files (none here): such a hand is sent as keypoints.
        hand["mano"] = None
        keypoints = hand.get("keypoints") or [[[0.01 * j, 0.0, 0.1] for j in range(21)]]
        hand["keypoints"] = stretched(keypoints, frames)
        hands.append(hand)
    body["hands"] = hands
    if body.get("world_from_camera") is not None:
        body["world_from_camera"] = IDENTITY
    if body.get("up") is not None and math.hypot(*body["up"]) < 1e-6:
        body["up"] = [0.0, 0.0, 1.0]
    return body


def unit_quaternion(q: list[float]) -> list[float]:
    norm = math.hypot(*q)
    return [c / norm for c in q] if 1e-6 < norm < math.inf else [1.0, 0.0, 0.0, 0.0]


def stretched(values: list[Any], length: int) -> list[Any]:
    """``values`` repeated or cut to ``length`` items."""
    return (values * (length // len(values) + 1))[:length]
