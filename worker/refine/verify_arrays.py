"""``verify``'s array checks: stored arrays against the fresh derivation, and against each other."""

from __future__ import annotations

from typing import Any

import numpy as np

from common.result_format import CONTACT_KEYS
from worker.refine.verify_report import CROSS_HOST, Tolerances, VerifyReport


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
        from worker.metrics import rotation_error_deg

        pos = np.linalg.norm(s[:, :3] - f[:, :3], axis=1)
        rot = rotation_error_deg(s[:, 3:], f[:, 3:])
        self.report.exact = bool(np.array_equal(s, f))
        self.report.max_pos_diff_m = float(pos.max())
        self.report.max_rot_diff_deg = 0.0 if self.report.exact else float(rot.max())

    def array(self, key: str, tol: float | None, unit: str = "", required: bool = True) -> None:
        """Stored ``key`` against the derivation: equal (``tol`` None) or within ``tol`` (max abs)."""
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
        worst = float(d.max()) if d.size else 0.0
        if (tol is None and worst > 0) or (tol is not None and worst > tol):
            at = np.unravel_index(int(np.argmax(d)), d.shape)
            where = f" at frame {at[0]}" if d.ndim and key not in CONTACT_KEYS else f" at row {at[0]}"
            limit = "exact on this build" if tol is None else f"tolerance {tol:g}{unit}"
            self.fail(f"{key}: largest difference {worst:.6g}{unit}{where} ({limit})")

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
        def t(v: float) -> float | None:
            return None if tol is None else v

        if tol is not None:  # positions and rotations separately (a quaternion's sign is a convention)
            self.report.checked.append("object_pose_sim")
            if self.report.max_pos_diff_m > tol.object_pos_m or self.report.max_rot_diff_deg > tol.object_rot_deg:
                self.fail(f"object_pose_sim: object trajectory differs from the re-simulation by "
                          f"{self.report.max_pos_diff_m * 1000:.3f} mm / {self.report.max_rot_diff_deg:.3f} deg "
                          f"(tolerance {tol.object_pos_m * 1000:g} mm / {tol.object_rot_deg:g} deg)")
            self._pose_within("raw_object_pose_sim", tol)
        else:
            self.array("object_pose_sim", None)
            self.array("raw_object_pose_sim", None)
        if tol is None:
            self.array("object_vel_sim", None)
        else:
            self._relative_l1("object_vel_sim", self.stored.get("object_vel_sim"), self.fresh["object_vel_sim"],
                              tol.object_vel_rel)
        for s in sides:
            key = f"{s}_keypoints_sim"
            self.array(key, t(CROSS_HOST.keypoints_m), " m")
            st, fr = self.stored.get(key), self.fresh.get(key)
            if st is not None and fr is not None and st.shape == fr.shape:
                self.report.max_keypoint_diff_m = max(self.report.max_keypoint_diff_m,
                                                      float(np.linalg.norm(st - fr, axis=-1).max()))
        per = {"e_t_cm": CROSS_HOST.max_cm, "e_r_deg": CROSS_HOST.max_deg, "e_j_cm": CROSS_HOST.max_cm,
               "e_ft_cm": CROSS_HOST.max_cm, "penetration_mm": CROSS_HOST.penetration_mm, "hand_only": 1.0}
        for name in ("raw", "refined"):
            for k, v in per.items():
                # hand_only flips where a contact flickers on another host; its fraction is checked instead.
                if tol is None or k != "hand_only":
                    self.array(f"metrics_{name}_{k}", t(v), required=k in ("e_t_cm", "e_r_deg"))
        if tol is None:
            self.array("object_table_contact", None, required=False)

    def _pose_within(self, key: str, tol: Tolerances) -> None:
        from worker.metrics import rotation_error_deg

        s, f = self.stored.get(key), self.fresh[key]
        self.report.checked.append(key)
        if s is None or s.shape != f.shape:
            self.fail(f"{key}: shape {None if s is None else s.shape}, re-simulation {f.shape}")
            return
        pos = float(np.linalg.norm(s[:, :3] - f[:, :3], axis=1).max())
        rot = float(rotation_error_deg(s[:, 3:], f[:, 3:]).max())
        if pos > tol.object_pos_m or rot > tol.object_rot_deg:
            self.fail(f"{key}: differs from the re-simulation by {pos * 1000:.3f} mm / {rot:.3f} deg")

    def contacts(self, derived: Any, tol: Tolerances | None) -> None:
        if tol is None:  # the same contacts, row for row
            for k in CONTACT_KEYS:
                self.array(k, None)
            return
        for k in CONTACT_KEYS:
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
        from worker.hand_model import quat_to_matrix as q2m

        rot = np.stack([q2m(q) for q in pose[frames, 3:]]) if frames.size else np.zeros((0, 3, 3))
        expect = np.einsum("nji,nj->ni", rot, world - pose[frames, :3]) if frames.size else local
        d = np.abs(expect - local)
        if d.size and d.max() > 1e-9:
            self.fail(f"contact_pos_object: not the world point in the stored object frame (largest difference "
                      f"{d.max():.3g} m at row {int(np.argmax(d.max(axis=1)))})")


def net_force(arrays: dict[str, np.ndarray], n: int) -> np.ndarray:
    out = np.zeros((n, 3))
    frames = np.asarray(arrays["contact_frame"], dtype=np.int64)
    ok = (frames >= 0) & (frames < n)
    np.add.at(out, frames[ok], np.asarray(arrays["contact_force"], dtype=np.float64)[ok])
    return out


def check_stored_metrics(
    report: VerifyReport, arrays: dict[str, np.ndarray], summary: dict[str, Any], sides: list[str]
) -> None:
    """The metrics of the *stored* trajectories and contacts against the stored per-frame arrays and summary:
    tight on any host, so a rewritten figure fails even where the re-simulation is only within tolerance."""
    from worker.contacts import contact_frames
    from worker.metrics import compute_metrics, scalar_metrics

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
        m = compute_metrics(pose, ref, kp_sim, kp_ref, valid, contacts)
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
