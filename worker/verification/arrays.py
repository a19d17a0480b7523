"""``verify``'s array checks: stored arrays against the fresh derivation, and against each other."""

from __future__ import annotations

from typing import Any

import numpy as np

from common.geometry import quat_to_matrix, rotation_error_deg
from common.hand_description import parse_hand_description
from common.result_format import CONTACT_KEYS, PART_CONTACT_KEYS
from worker.simulation.contacts import contact_frames
from worker.simulation.metrics import ArticulationFrames, compute_metrics, scalar_metrics
from worker.verification.report import CROSS_HOST, Tolerances, VerifyReport


class ArrayChecker:
    """Compares stored arrays with the derivation's, recording what was checked and every failure."""

    def __init__(self, report: VerifyReport, stored: dict[str, np.ndarray], fresh: dict[str, np.ndarray]) -> None:
        self.report, self.stored, self.fresh = report, stored, fresh

    def fail(self, text: str) -> None:
        self.report.failures.append(text)

    def compare_trajectory(self) -> None:
        s, f = self.stored.get("object_pose_sim"), self.fresh["object_pose_sim"]
        if s is None or s.shape != f.shape:
            self.fail(f"object_pose_sim: shape {None if s is None else s.shape}, re-simulation {f.shape}")
            return
        pos = np.linalg.norm(s[:, :3] - f[:, :3], axis=1)
        rot = rotation_error_deg(s[:, 3:], f[:, 3:])
        self.report.exact = bool(np.array_equal(s, f))
        self.report.max_pos_diff_m = float(pos.max())
        self.report.max_rot_diff_deg = 0.0 if self.report.exact else float(rot.max())

    def array(self, key: str, tol: float | np.ndarray | None, unit: str = "", required: bool = True) -> None:
        """Stored ``key`` against the derivation: equal (``tol`` None) or within ``tol`` (max abs; an (F,) array
        gives each frame its own)."""
        fresh = self.fresh.get(key)
        stored = self.stored.get(key)
        if fresh is None:
            return
        if stored is None:
            if required:
                self.fail(f"{key}: missing from the result")
            return
        self.report.checked.append(key)
        if stored.shape != fresh.shape:
            self.fail(f"{key}: shape {stored.shape}, re-computed {fresh.shape}")
            return
        if stored.dtype.kind in "USb" or fresh.dtype.kind in "USb":
            if not np.array_equal(stored, fresh):
                bad = np.flatnonzero(np.asarray(stored != fresh).reshape(len(stored), -1).any(axis=1))
                self.fail(f"{key}: differs from the re-computation in {bad.size} rows (first {int(bad[0])})")
            return
        a, b = stored.astype(np.float64), fresh.astype(np.float64)
        nan = np.isnan(a) != np.isnan(b)
        if nan.any():
            self.fail(f"{key}: NaN where the re-computation has a value (or the reverse) at "
                      f"{int(np.argwhere(nan)[0][0])}")
            return
        d = np.nan_to_num(np.abs(a - b), nan=0.0)
        if d.size == 0:
            return
        limit = np.zeros(d.shape) if tol is None else np.broadcast_to(
            np.reshape(tol, np.shape(tol) + (1,) * (d.ndim - np.ndim(tol))), d.shape)
        excess = d - limit
        if excess.max() > 0:
            at = np.unravel_index(int(np.argmax(excess)), d.shape)
            where = f" at frame {at[0]}" if key not in CONTACT_KEYS else f" at row {at[0]}"
            text = "exact on this build" if tol is None else f"tolerance {float(limit[at]):.4g}{unit}"
            self.fail(f"{key}: largest difference {float(d[at]):.6g}{unit}{where} ({text})")

    def inputs(self, sides: list[str], tol: Tolerances | None) -> None:
        t = None if tol is None else tol.inputs
        self.array("object_pose_ref", t)
        for s in sides:
            for k in ("keyframes", "q_target", "wrist_pos", "wrist_quat", "keypoints_ref", "valid"):
                self.array(f"{s}_{k}", t)
            for k in self.fresh:
                if k.startswith(f"{s}_mano_"):
                    self.array(k, t)
            self.array(f"{s}_attempt_keyframes", t, required=False)

    def simulated(self, sides: list[str], tol: Tolerances | None) -> None:
        def t(v: float | np.ndarray) -> float | np.ndarray | None:
            return None if tol is None else v

        if tol is None:
            for key in ("object_pose_sim", "raw_object_pose_sim", "object_vel_sim"):
                self.array(key, None)
        else:  # positions and rotations separately (a quaternion's sign is a convention)
            for key, name in (("object_pose_sim", "refined"), ("raw_object_pose_sim", "raw")):
                self._pose_within(key, *self._pose_tolerance(name, tol))
            self._relative_l1("object_vel_sim", self.stored.get("object_vel_sim"), self.fresh["object_vel_sim"],
                              tol.object_vel_rel)
        for s in sides:
            key = f"{s}_keypoints_sim"
            self.array(key, t((tol or CROSS_HOST).keypoints_m), " m")
            st, fr = self.stored.get(key), self.fresh.get(key)
            if st is not None and fr is not None and st.shape == fr.shape:
                self.report.max_keypoint_diff_m = max(self.report.max_keypoint_diff_m,
                                                      float(np.linalg.norm(st - fr, axis=-1).max()))
        for name in ("raw", "refined"):
            host = tol or CROSS_HOST
            pos, rot = self._pose_tolerance(name, host)
            per: dict[str, float | np.ndarray] = {
                "e_t_cm": 100.0 * pos, "e_r_deg": rot, "e_j_cm": 100.0 * host.keypoints_m,
                "e_ft_cm": 100.0 * host.keypoints_m, "penetration_mm": host.penetration_mm,
                "hand_only": 0.0,
            }
            for k, v in per.items():
                # hand_only flips where a contact flickers on another host; its fraction is checked instead.
                if tol is None or k != "hand_only" or tol.contact_rows is not None:
                    limit = CROSS_HOST.figures_last_bits if tol is None else v  # exact replay: NumPy's last bits
                    self.array(f"metrics_{name}_{k}", limit, required=k in ("e_t_cm", "e_r_deg"))
        if tol is None or tol.contact_rows is not None:
            self.array("object_table_contact", None, required=False)
        for key in ("object_articulation_sim", "raw_object_articulation_sim"):  # an articulated object's joints
            if key in self.fresh:
                self.array(key, None if tol is None else np.radians(tol.object_rot_deg), " rad/m")
        if "object_articulation_ref" in self.fresh:
            self.array("object_articulation_ref", t(tol.inputs if tol is not None else 0.0))
        for name in ("raw", "refined"):
            for k in ("e_a", "a_ok"):
                if f"metrics_{name}_{k}" in self.fresh:
                    limit = CROSS_HOST.figures_last_bits if tol is None else (
                        tol.object_rot_deg if k == "e_a" else 1.0)
                    self.array(f"metrics_{name}_{k}", limit)

    def _pose_tolerance(self, name: str, tol: Tolerances) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame position (m) and rotation (deg) tolerance of the ``name`` replay: the base plus
        ``drift_fraction`` of that frame's re-simulated tracking error (see ``Tolerances``)."""
        e_t = np.nan_to_num(self.fresh.get(f"metrics_{name}_e_t_cm", np.zeros(1)), nan=0.0)
        e_r = np.nan_to_num(self.fresh.get(f"metrics_{name}_e_r_deg", np.zeros(1)), nan=0.0)
        return tol.object_pos_m + tol.drift_fraction * e_t / 100.0, tol.object_rot_deg + tol.drift_fraction * e_r

    def _pose_within(self, key: str, pos_tol: np.ndarray, rot_tol: np.ndarray) -> None:
        s, f = self.stored.get(key), self.fresh[key]
        self.report.checked.append(key)
        if s is None or s.shape != f.shape:
            self.fail(f"{key}: shape {None if s is None else s.shape}, re-simulation {f.shape}")
            return
        pos = np.linalg.norm(s[:, :3] - f[:, :3], axis=1)
        rot = rotation_error_deg(s[:, 3:], f[:, 3:])
        over = np.maximum(pos / pos_tol, rot / rot_tol)
        if over.max() > 1.0:
            i = int(np.argmax(over))
            self.fail(f"{key}: differs from the re-simulation by {pos[i] * 1000:.3f} mm / {rot[i]:.3f} deg at "
                      f"frame {i} (tolerance there {pos_tol[i] * 1000:.3g} mm / {rot_tol[i]:.3g} deg)")

    def contacts(self, derived: Any, tol: Tolerances | None) -> None:
        parts = [k for k in PART_CONTACT_KEYS if k in self.fresh]  # an articulated object's contacts name the part
        if tol is None or tol.contact_rows is not None:  # the same contacts, row for row
            for k in CONTACT_KEYS + tuple(parts):
                self.array(k, None if tol is None or k in ("contact_frame", "contact_hand", "contact_body")
                           else tol.contact_rows)
            return
        for k in CONTACT_KEYS + tuple(parts):
            if k not in self.stored:
                self.fail(f"{k}: missing from the result")
                return
            self.report.checked.append(k)
        n = int(derived.prep.num_frames)
        self._relative_l1("contact_force", net_force(self.stored, n), net_force(self.fresh, n), tol.force_rel,
                          what="per-frame net hand force on the object")

    def _relative_l1(self, key: str, mine: np.ndarray | None, theirs: np.ndarray, limit: float,
                     what: str = "") -> None:
        """sum_f |mine_f - theirs_f| / sum_f |theirs_f| within ``limit`` (see ``Tolerances.object_vel_rel``)."""
        self.report.checked.append(key)
        if mine is None or mine.shape != theirs.shape:
            self.fail(f"{key}: shape {None if mine is None else mine.shape}, re-simulation {theirs.shape}")
            return
        d = np.linalg.norm(mine - theirs, axis=1)
        rel = float(d.sum()) / max(float(np.linalg.norm(theirs, axis=1).sum()), 1e-9)
        self.report.relative_l1[key] = rel
        if rel > limit:
            self.fail(f"{key}: {what or 'per-frame values'} differ from the re-simulation by {rel:.0%} "
                      f"(relative L1, tolerance {limit:.0%}; largest at frame {int(np.argmax(d))})")

    def consistency(self, derived: Any, sides: list[str]) -> None:
        """Stored arrays against each other (no simulation): the contacts' object-frame points and the stored
        per-frame metrics against those recomputed from the stored trajectories."""
        pose, frames = self.stored.get("object_pose_sim"), self.stored.get("contact_frame")
        world, local = self.stored.get("contact_pos_world"), self.stored.get("contact_pos_object")
        if pose is None or frames is None or world is None or local is None:
            return
        if frames.size and (frames.min() < 0 or frames.max() >= len(pose)):
            self.fail("contact_frame: frame numbers outside the sequence")
            return
        frame_pose = pose[frames]
        obj = derived.prep.seq.object
        if obj.parts:  # each point is in the frame of the part it touches, posed by the stored joint values
            names, arti = self.stored.get("contact_part"), self.stored.get("object_articulation_sim")
            if names is None or arti is None or arti.shape != (len(pose), len(obj.parts)):
                self.fail("contact_part / object_articulation_sim: missing or misshapen for an articulated object")
                return
            index = {name: i for i, name in enumerate(obj.part_names)}
            unknown = [str(n) for n in names if str(n) not in index]
            if unknown:
                self.fail(f"contact_part: {unknown[0]!r} is not a part of the object")
                return
            parts = obj.part_poses(pose[frames], arti[frames])
            frame_pose = parts[np.arange(len(frames)), [index[str(n)] for n in names]]
        rot = np.stack([quat_to_matrix(q) for q in frame_pose[:, 3:]]) if frames.size else np.zeros((0, 3, 3))
        expect = np.einsum("nji,nj->ni", rot, world - frame_pose[:, :3]) if frames.size else local
        d = np.abs(expect - local)
        if d.size and d.max() > 1e-9:
            self.fail(f"contact_pos_object: not the world point in the stored object (part) frame (largest "
                      f"difference {d.max():.3g} m at row {int(np.argmax(d.max(axis=1)))})")


def net_force(arrays: dict[str, np.ndarray], n: int) -> np.ndarray:
    out = np.zeros((n, 3))
    frames = np.asarray(arrays["contact_frame"], dtype=np.int64)
    ok = (frames >= 0) & (frames < n)
    np.add.at(out, frames[ok], np.asarray(arrays["contact_force"], dtype=np.float64)[ok])
    return out


def check_stored_metrics(
    report: VerifyReport, arrays: dict[str, np.ndarray], summary: dict[str, Any], sides: list[str],
    joint_kinds: tuple[str, ...] = (),
) -> None:
    """The metrics of the *stored* trajectories and contacts against the stored per-frame arrays and summary:
    tight on any host, so a rewritten figure fails even where the re-simulation is only within tolerance."""
    ref = arrays.get("object_pose_ref")
    if ref is None:
        return
    n = len(ref)
    for name, pose_key in (("refined", "object_pose_sim"), ("raw", "raw_object_pose_sim")):
        pose = arrays.get(pose_key)
        if pose is None or pose.shape != ref.shape:
            continue
        kp_sim, kp_ref, valid = {}, {}, {}
        if name == "refined":  # the raw replay's keypoints and contacts are not stored: re-simulated only
            for s in sides:
                keys = (f"{s}_keypoints_sim", f"{s}_keypoints_ref", f"{s}_valid")
                if all(k in arrays and len(arrays[k]) == n for k in keys):
                    kp_sim[s], kp_ref[s], valid[s] = (arrays[k] for k in keys)
        contacts = None
        if name == "refined" and "object_table_contact" in arrays and "contact_frame" in arrays:
            try:
                contacts = contact_frames(arrays["contact_frame"], arrays["contact_depth"],
                                          np.flatnonzero(arrays["object_table_contact"]), n)
            except ValueError as exc:
                report.failures.append(f"contact_frame: {exc}")
        hand = (summary.get("options") or {}).get("hand")  # a robot hand: its fingertip sites (issue #55)
        tips = None if hand is None else {s: parse_hand_description(hand).fingertip_sites() for s in kp_sim}
        arti = None
        arti_sim = arrays.get("object_articulation_sim" if name == "refined" else "raw_object_articulation_sim")
        arti_ref = arrays.get("object_articulation_ref")
        if joint_kinds and arti_sim is not None and arti_ref is not None:
            arti = ArticulationFrames(arti_sim, arti_ref, joint_kinds)
        try:
            m = compute_metrics(pose, ref, kp_sim, kp_ref, valid, contacts, arti, tips)
        except ValueError as exc:
            report.failures.append(f"metrics.{name}: the stored arrays do not fit together ({exc})")
            continue
        for key, val in m["per_frame"].items():
            stored = arrays.get(f"metrics_{name}_{key}")
            if stored is None or (not kp_sim and key in ("e_j_cm", "e_ft_cm")):
                continue
            if stored.shape != val.shape:
                report.failures.append(f"metrics_{name}_{key}: shape {stored.shape}, stored data give {val.shape}")
                continue
            d = np.abs(np.nan_to_num(stored - val, nan=0.0))
            if (np.isnan(stored) != np.isnan(val)).any() or d.max(initial=0.0) > 1e-9:
                report.failures.append(f"metrics_{name}_{key}: not the metric of the stored trajectory "
                                       f"(largest difference {d.max(initial=0.0):.6g} at frame {int(np.argmax(d))})")
        mine = scalar_metrics(m)
        if not kp_sim:
            for block in (mine, mine["paper"]):
                for key in ("E_j", "E_ft"):
                    block.pop(key, None)
        compare_consistent(report, f"metrics.{name}", summary.get("metrics", {}).get(name, {}), mine)


def compare_consistent(report: VerifyReport, path: str, stored: Any, mine: dict[str, Any]) -> None:
    """Every figure in ``mine`` equals the stored one up to rounding (1e-9 relative)."""
    if not isinstance(stored, dict):
        return
    for key, value in mine.items():
        if key not in stored:
            continue
        if isinstance(value, dict):
            compare_consistent(report, f"{path}.{key}", stored[key], value)
            continue
        s = stored[key]
        if isinstance(value, bool) or value is None or s is None:
            if s != value:
                report.failures.append(f"{path}.{key}: stored {s!r}, but the stored trajectory gives {value!r}")
            continue
        a, b = float(s), float(value)
        if np.isnan(a) and np.isnan(b):
            continue
        if not abs(a - b) <= 1e-9 * max(1.0, abs(b)):
            report.failures.append(f"{path}.{key}: stored {a:.6g}, but the stored trajectory gives {b:.6g}")
