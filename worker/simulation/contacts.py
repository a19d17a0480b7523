"""Per-frame hand-object contacts in the ``common.result_format`` columns (DESIGN §1.7).

For each active hand-object contact: the hand side and body, the contact point in world and object frames,
the normal (world, pointing from the object to the hand), the 6-D wrench from ``mj_contactForce`` rotated
out of the contact frame — **exerted by the hand on the object**, world frame, about the contact point — and
the penetration depth (>= 0). With an articulated object, each row also names the part touched
(``contact_part``), and the object-frame point is in that part's frame. Object-table contacts are not reported
as rows; ``frames`` says per frame whether the object touched the table (and a hand), and how deep the deepest
hand-object contact was (``worker.simulation.metrics``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import numpy as np

from common.result_format import CONTACT_KEYS, PART_CONTACT_KEYS

if TYPE_CHECKING:
    from worker.simulation.metrics import ContactFrames
    from worker.simulation.scene import Scene


class ContactRecorder:
    """Accumulates contact rows over frames; ``columns()`` gives the result arrays."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        model = scene.model
        self._is_object = np.zeros(model.ngeom, dtype=bool)
        self._is_object[scene.object_geom_ids] = True
        self._geom_side = [scene.body_side.get(int(model.geom_bodyid[g]), "") for g in range(model.ngeom)]
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(model.nbody)]
        self._geom_body = [names[int(model.geom_bodyid[g])] for g in range(model.ngeom)]
        self._parts = scene.articulated
        self._rows: dict[str, list[object]] = {k: [] for k in CONTACT_KEYS + PART_CONTACT_KEYS}
        self._f6 = np.zeros(6)
        self._table_frames: set[int] = set()

    def add(self, data: mujoco.MjData, frame: int) -> int:
        """Record the current contacts of ``data`` as frame ``frame``; returns how many were added."""
        model = self.scene.model
        obj = self.scene.object_body_id
        obj_pos, obj_rot = data.xpos[obj], data.xmat[obj].reshape(3, 3)
        part_names = self.scene.object_part_names
        added = 0
        for i in range(data.ncon):
            c = data.contact[i]
            g1, g2 = int(c.geom[0]), int(c.geom[1])
            if c.efc_address < 0 or self._is_object[g1] == self._is_object[g2]:
                continue
            hand_geom = g2 if self._is_object[g1] else g1
            side = self._geom_side[hand_geom]
            if not side:
                self._table_frames.add(frame)  # object-table: no row, but the frame is not hand-held alone
                continue
            mujoco.mj_contactForce(model, data, i, self._f6)
            frame_rot = c.frame.reshape(3, 3)  # rows: normal (geom1 -> geom2), tangents
            force = frame_rot.T @ self._f6[:3]  # on geom2 by geom1, world
            torque = frame_rot.T @ self._f6[3:]
            sign = 1.0 if self._is_object[g1] else -1.0  # object is geom1: normal already object -> hand
            rows = self._rows
            rows["contact_frame"].append(frame)
            rows["contact_hand"].append(side)
            rows["contact_body"].append(self._geom_body[hand_geom])
            rows["contact_pos_world"].append(np.array(c.pos))
            if self._parts:  # the point in the touched part's frame
                part = int(self.scene.geom_part[g1 if self._is_object[g1] else g2])
                body = int(self.scene.object_part_body_ids[part])
                rows["contact_part"].append(part_names[part])
                rows["contact_pos_object"].append(data.xmat[body].reshape(3, 3).T @ (c.pos - data.xpos[body]))
            else:
                rows["contact_pos_object"].append(obj_rot.T @ (c.pos - obj_pos))
            rows["contact_normal"].append(sign * frame_rot[0])
            # geom1 = object: the returned wrench acts on the hand, so the hand's on the object is its negative.
            rows["contact_force"].append(-sign * force)
            rows["contact_torque"].append(-sign * torque)
            rows["contact_depth"].append(max(0.0, -float(c.dist)))
            added += 1
        return added

    def __len__(self) -> int:
        return len(self._rows["contact_frame"])

    def frames(self, n_frames: int) -> ContactFrames:
        """Per frame 0..n_frames-1: deepest hand-object penetration (m), hand contact, table contact."""

        frame = np.asarray(self._rows["contact_frame"], dtype=np.int64)
        depth = np.asarray(self._rows["contact_depth"], dtype=np.float64)
        return contact_frames(frame, depth, np.fromiter(self._table_frames, dtype=np.int64), n_frames)

    def columns(self) -> dict[str, np.ndarray]:
        """The CONTACT_KEYS arrays (empty arrays of the right shapes when there were no contacts)."""
        r = self._rows
        n = len(self)

        def vec(key: str) -> np.ndarray:
            return np.asarray(r[key], dtype=np.float64).reshape(n, 3)

        return {
            "contact_frame": np.asarray(r["contact_frame"], dtype=np.int64).reshape(n),
            "contact_hand": np.asarray(r["contact_hand"], dtype="<U5").reshape(n),
            "contact_body": np.asarray(r["contact_body"], dtype="<U32").reshape(n),
            "contact_pos_world": vec("contact_pos_world"),
            "contact_pos_object": vec("contact_pos_object"),
            "contact_normal": vec("contact_normal"),
            "contact_force": vec("contact_force"),
            "contact_torque": vec("contact_torque"),
            "contact_depth": np.asarray(r["contact_depth"], dtype=np.float64).reshape(n),
        } | ({"contact_part": np.asarray(r["contact_part"], dtype="<U64").reshape(n)} if self._parts else {})


def empty_contact_columns() -> dict[str, np.ndarray]:
    """CONTACT_KEYS arrays with zero rows."""
    return {
        "contact_frame": np.zeros(0, dtype=np.int64),
        "contact_hand": np.zeros(0, dtype="<U5"),
        "contact_body": np.zeros(0, dtype="<U32"),
        **{k: np.zeros((0, 3)) for k in CONTACT_KEYS[3:8]},
        "contact_depth": np.zeros(0),
    }


def contact_frames(
    contact_frame: np.ndarray, contact_depth: np.ndarray, table_frames: np.ndarray, n_frames: int
) -> ContactFrames:
    """``ContactFrames`` from contact rows (frame, depth) and the frames with an object-table contact."""
    from worker.simulation.metrics import ContactFrames

    frame = np.asarray(contact_frame, dtype=np.int64)
    if frame.size and (frame.min() < 0 or frame.max() >= n_frames):
        raise ValueError(f"contact frames must lie in 0..{n_frames - 1}")
    pen = np.zeros(n_frames)
    np.maximum.at(pen, frame, np.asarray(contact_depth, dtype=np.float64))
    hand = np.zeros(n_frames, dtype=bool)
    hand[frame] = True
    table = np.zeros(n_frames, dtype=bool)
    table[np.asarray(table_frames, dtype=np.int64)] = True
    return ContactFrames(pen, hand, table)
