"""``verify``: recompute everything a refinement result claims and compare (issue #15 item 1).

From the embedded sequence (or ``--sequence``) and the stored keyframes, ``worker.refine.derive.derive_result``
runs again — the same function that made the result — in a fresh model: the raw and the refined replay (and each
restart), contacts, every derived array and both protocols' metrics. Then:

1. **Config.** The stored physics config (``config.sim``, the rotation pivot) against the product's defaults for
   the result's version: a setting the result does not record reads as the default of the versions before it
   existed (``OLDER_DEFAULTS``); any other difference is reported by name, default and stored value, and fails
   unless ``allow_config`` (the re-simulation always uses the stored config).
2. **Consistency** (tight, whatever the host): the summary metrics recomputed from the stored trajectories and
   contacts, the stored per-frame metric arrays, the contacts' object-frame points against their world points
   and the stored object pose, the first attempt's success.
3. **Re-simulation.** Every stored array and summary figure against the fresh derivation. On the build that made
   the result the replay is bit-identical (``exact``), and then everything must be equal. On another host it is
   not: NumPy and OpenBLAS pick CPU-specific kernels (AVX-512 or AVX2) whose last bits differ, and contact-rich
   dynamics grow a 1e-16 difference into millimetres (measured: ``CROSS_HOST``). Then each field is compared
   within a physical tolerance instead (``Tolerances``).

Any difference fails naming the field and its largest difference. The report carries a SHA-256 over everything
that was checked (stored arrays and summary parts), so two parties can tell they checked the same content.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.errors import ResultMismatchError, UnsupportedFormatError
from common.job_options import JobOptions
from common.result_format import CONTACT_KEYS, read_arrays, read_summary
from common.sequence import Sequence
from common.sequence_io import sequence_to_npz_bytes

#: Settings a result does not record were, before they existed, these (the mocap and servos followed their
#: tracks, the object started from frame 0, the hand turned about the wrist).
OLDER_DEFAULTS: dict[str, Any] = {"wrist_lead_s": 0.0, "finger_lead_s": 0.0, "rest_approach_m": 0.0}
OLDER_PIVOT = "wrist"


@dataclass(frozen=True)
class Tolerances:
    """How far a re-simulation on another x86_64 host may stray from the stored result (SI units unless named).

    Measured by re-deriving results made on this host (AVX-512) with NumPy's AVX-512 kernels disabled and
    OpenBLAS's Haswell kernels forced (``NPY_DISABLE_CPU_FEATURES``, ``OPENBLAS_CORETYPE``: what an AVX2 host
    runs), on dev sequences: object 0.07-2.1 mm, keypoints up to a few mm where a finger slips differently; the
    sequence-level figures (E_t, E_r, penetration mean) move far less than the per-frame ones. The bounds are
    those figures with a margin of ~2-3x, and stay well below what a forgery needs to change a metric (a 5 cm
    wrist move, forces x10). Inputs that no simulation touches (controls from keyframes, the reference) only see
    last-bit differences: ``inputs``.
    """

    inputs: float = 1e-6  # m / rad / unitless: controls, reference keypoints and object poses
    object_pos_m: float = 5e-3
    object_rot_deg: float = 3.0
    #: Velocities and contact forces jump frame by frame where a contact flickers (2.3 m/s, rad/s at one frame
    #: for a 0.75 mm trajectory deviation), so they are compared over the whole sequence: the L1 norm of the
    #: per-frame difference relative to the re-simulation's.
    object_vel_rel: float = 0.5
    keypoints_m: float = 1e-2
    mean_cm: float = 0.2  # E_t, E_j, E_ft (sequence means, cm)
    mean_deg: float = 1.0  # E_r
    max_cm: float = 0.6  # max_E_t and per-frame errors (cm)
    max_deg: float = 3.0  # max_E_r and per-frame rotation errors (deg)
    penetration_mm: float = 3.0  # per frame and sequence maximum
    penetration_mean_mm: float = 0.5
    fraction: float = 0.15  # hand_only_fraction
    force_rel: float = 0.5  # relative L1 difference of the per-frame net hand force on the object


CROSS_HOST = Tolerances()


@dataclass
class VerifyReport:
    frames: int = 0
    exact: bool = False  # the re-simulated object trajectory equals the stored one bit for bit
    max_pos_diff_m: float = 0.0  # largest object position deviation, stored vs re-simulated
    max_rot_diff_deg: float = 0.0
    max_keypoint_diff_m: float = 0.0
    relative_l1: dict[str, float] = field(default_factory=dict)  # cross-host comparisons of jumpy quantities
    config_changes: list[tuple[str, Any, Any]] = field(default_factory=list)  # (setting, default, stored)
    config_notes: list[str] = field(default_factory=list)  # settings the result predates
    checked: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    digest: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "frames": self.frames, "exact": self.exact, "max_pos_diff_m": self.max_pos_diff_m,
            "max_rot_diff_deg": self.max_rot_diff_deg, "max_keypoint_diff_m": self.max_keypoint_diff_m,
            "config_changes": [{"setting": n, "default": d, "stored": s} for n, d, s in self.config_changes],
            "checked": len(self.checked), "failures": list(self.failures), "digest": self.digest,
        }


def verify_result(blob: bytes, sequence: Sequence | None = None, allow_config: bool = False) -> dict[str, Any]:
    """``check_result``, raising ``ResultMismatchError`` naming every failing field; returns the report as a dict
    (``VerifyReport.to_dict``)."""
    report = check_result(blob, sequence, allow_config)
    if report.failures:
        raise ResultMismatchError("result does not verify:\n  " + "\n  ".join(report.failures))
    return report.to_dict()


def check_result(blob: bytes, sequence: Sequence | None = None, allow_config: bool = False) -> VerifyReport:
    """See the module docstring; failures are listed in the report, not raised."""
    from worker.refine.derive import derive_result
    from worker.scene import SimConfig

    summary = read_summary(blob)
    if summary.get("kind") != "refine":
        raise UnsupportedFormatError(f"not a refinement result (kind {summary.get('kind')!r})")
    arrays = read_arrays(blob)
    if sequence is not None:
        seq_bytes = sequence_to_npz_bytes(sequence)
    elif "sequence_npz" in arrays:
        seq_bytes = arrays["sequence_npz"].tobytes()
    else:
        raise UnsupportedFormatError("the result embeds no sequence; pass --sequence")
    report = VerifyReport()
    config = summary.get("config", {})
    sim, pivot = _config(config, report, allow_config)
    options = JobOptions.model_validate(summary["options"])
    sides = list(summary.get("sides") or [k[: -len("_keyframes")] for k in arrays if k.endswith("_keyframes")
                                          and not k.endswith("_attempt_keyframes")])
    keyframes = {s: arrays.get(f"{s}_keyframes") for s in sides}
    attempt_kf = _attempt_keyframes(arrays, sides)
    try:
        derived = derive_result(seq_bytes, options, SimConfig(**sim), pivot, keyframes,  # type: ignore[arg-type]
                                attempt_kf)
    except ValueError as exc:
        raise ResultMismatchError(f"the stored controls do not fit the sequence: {exc}") from exc
    c = _Checker(report, arrays, derived.arrays)
    c.compare_trajectory()
    tol = None if report.exact else CROSS_HOST
    c.inputs(sides, tol)
    c.simulated(sides, tol)
    c.contacts(derived, tol)
    c.consistency(derived, sides)
    _check_summary(report, summary, derived, attempt_kf, tol)
    _check_stored_metrics(report, arrays, summary, sides)
    report.frames = int(derived.prep.num_frames)
    report.digest = _digest(arrays, summary, report.checked)
    return report


# ---------------------------------------------------------------------------------------------- config


def _config(config: dict[str, Any], report: VerifyReport, allow_config: bool) -> tuple[dict[str, Any], str]:
    """The stored sim settings (older defaults filled in) and pivot; config differences into the report."""
    from worker.refine.prepare import ROTATION_PIVOT
    from worker.scene import SimConfig

    defaults = SimConfig().to_dict()
    stored: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in config.get("sim", {}).items()}
    unknown = sorted(set(stored) - set(defaults))
    if unknown:
        raise UnsupportedFormatError(f"config.sim has settings this version does not know: {', '.join(unknown)}")
    for name, default in defaults.items():
        if name not in stored:  # the result predates the setting: the behaviour of its time
            stored[name] = OLDER_DEFAULTS.get(name, default)
            report.config_notes.append(f"{name} not recorded (older result): read as {stored[name]}")
        elif _differs(stored[name], default):
            report.config_changes.append((f"sim.{name}", _plain(default), _plain(stored[name])))
    pivot = config.get("rotation_pivot")
    if pivot is None:
        pivot = OLDER_PIVOT
        report.config_notes.append(f"rotation_pivot not recorded (older result): read as {OLDER_PIVOT!r}")
    elif pivot != ROTATION_PIVOT:
        report.config_changes.append(("rotation_pivot", ROTATION_PIVOT, pivot))
    if report.config_changes and not allow_config:
        for name, default, value in report.config_changes:
            report.failures.append(f"config {name}: {value!r} differs from the default {default!r} "
                                   "(--allow-config accepts a non-default physics config)")
    return stored, str(pivot)


def _differs(a: Any, b: Any) -> bool:
    if isinstance(a, tuple | list) or isinstance(b, tuple | list):
        return list(a) != list(b) if isinstance(a, tuple | list) and isinstance(b, tuple | list) else True
    return bool(a != b)


def _plain(v: Any) -> Any:
    return list(v) if isinstance(v, tuple) else v


def _attempt_keyframes(arrays: dict[str, np.ndarray], sides: list[str]) -> list[dict[str, np.ndarray]] | None:
    stacks = {s: arrays.get(f"{s}_attempt_keyframes") for s in sides}
    if any(v is None for v in stacks.values()):
        return None
    n = {int(v.shape[0]) for v in stacks.values() if v is not None}
    if len(n) != 1:
        raise ResultMismatchError("attempt keyframes: the hands list different numbers of attempts")
    return [{s: np.asarray(v[i]) for s, v in stacks.items() if v is not None} for i in range(n.pop())]


# ---------------------------------------------------------------------------------------------- arrays


class _Checker:
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
        self._relative_l1("contact_force", _net_force(self.stored, n), _net_force(self.fresh, n), tol.force_rel,
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


def _net_force(arrays: dict[str, np.ndarray], n: int) -> np.ndarray:
    out = np.zeros((n, 3))
    frames = np.asarray(arrays["contact_frame"], dtype=np.int64)
    ok = (frames >= 0) & (frames < n)
    np.add.at(out, frames[ok], np.asarray(arrays["contact_force"], dtype=np.float64)[ok])
    return out


# ---------------------------------------------------------------------------------------------- summary


def _check_summary(
    report: VerifyReport, summary: dict[str, Any], derived: Any, attempt_kf: list[Any] | None,
    tol: Tolerances | None,
) -> None:
    """The summary's metrics (raw, refined, both protocols), attempts and success against the derivation, and
    against the metrics of the *stored* trajectories (consistency, tight on any host)."""
    from worker.metrics import scalar_metrics
    from worker.refine.run import add_attempt_metrics, attempt_figures

    stored = summary.get("metrics", {})
    attempts = summary.get("attempts") or []
    fresh = {k: scalar_metrics(v) for k, v in derived.metrics.items()}
    if attempt_kf is not None:
        fresh_attempts = [attempt_figures(m) for m in derived.attempt_metrics]
    elif len(attempts) <= 1:
        fresh_attempts = [attempt_figures(derived.metrics["refined"])]
    else:
        fresh_attempts = []
        report.config_notes.append("restarts' keyframes not stored (older result): attempts not re-simulated")
    add_attempt_metrics(fresh["refined"], fresh_attempts if len(attempts) == len(fresh_attempts) else [])
    for name in ("raw", "refined"):
        if name not in stored:
            report.failures.append(f"metrics.{name}: missing")
            continue
        for key in ("E_t", "E_r", "E_j", "E_ft", "success"):
            if key not in stored[name]:
                report.failures.append(f"metrics.{name}.{key}: missing")
        _compare_dict(report, f"metrics.{name}", stored[name], fresh[name], tol)
    if attempts and fresh_attempts:
        if len(attempts) != len(fresh_attempts):
            report.failures.append(f"attempts: {len(attempts)} listed, {len(fresh_attempts)} re-simulated")
        for i, (a, b) in enumerate(zip(attempts, fresh_attempts, strict=False)):
            _compare_dict(report, f"attempts[{i}]", {k: v for k, v in a.items() if k in b}, b, tol)
    report.checked.extend(["summary.metrics", "summary.attempts", "summary.config"])


def _check_stored_metrics(
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
        _compare_consistent(report, f"metrics.{name}", summary.get("metrics", {}).get(name, {}), mine)


def _compare_consistent(report: VerifyReport, path: str, stored: Any, mine: dict[str, Any]) -> None:
    """Every figure in ``mine`` equals the stored one up to rounding (1e-9 relative)."""
    if not isinstance(stored, dict):
        return
    for key, value in mine.items():
        if key not in stored:
            continue
        if isinstance(value, dict):
            _compare_consistent(report, f"{path}.{key}", stored[key], value)
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


#: Tolerance of each summary figure on another host (``Tolerances``); names not listed must be equal.
def _summary_tol(key: str, tol: Tolerances) -> float | None:
    table = {
        "E_t": tol.mean_cm, "E_j": tol.mean_cm, "E_ft": tol.mean_cm, "E_r": tol.mean_deg,
        "max_E_t": tol.max_cm, "max_E_r": tol.max_deg,
        "penetration_mean_mm": tol.penetration_mean_mm, "penetration_max_mm": tol.penetration_mm,
        "hand_only_fraction": tol.fraction,
    }
    return table.get(key)


def _compare_dict(report: VerifyReport, path: str, stored: Any, fresh: Any, tol: Tolerances | None) -> None:
    if isinstance(fresh, dict):
        if not isinstance(stored, dict):
            report.failures.append(f"{path}: not a mapping")
            return
        for key, value in stored.items():
            if key not in fresh:
                if path.endswith("paper") or key in ("attempts", "success_first_attempt"):
                    report.failures.append(f"{path}.{key}: stored but not re-computed")
                continue  # e.g. figures of a newer version
            _compare_dict(report, f"{path}.{key}", value, fresh[key], tol)
        return
    name = path.rsplit(".", 1)[-1]
    if isinstance(fresh, bool) or isinstance(stored, bool):
        if bool(stored) != bool(fresh) or type(stored) is not type(fresh):
            if tol is not None and name == "success" and _near_threshold(path, report):
                return
            report.failures.append(f"{path}: stored {stored!r}, re-computed {fresh!r}")
        return
    if fresh is None or stored is None:
        if fresh is not None or stored is not None:
            report.failures.append(f"{path}: stored {stored!r}, re-computed {fresh!r}")
        return
    if not isinstance(stored, int | float):
        report.failures.append(f"{path}: stored {stored!r} is not a number")
        return
    a, b = float(stored), float(fresh)
    if np.isnan(a) and np.isnan(b):
        return
    limit = None if tol is None else _summary_tol(name, tol)
    if tol is not None and limit is None and name not in ("frames", "lifted_frames", "first_frame", "attempts"):
        limit = 1e-9
    diff = abs(a - b) if not (np.isnan(a) or np.isnan(b)) else float("inf")
    if (limit is None and a != b) or (limit is not None and diff > limit):
        report.failures.append(f"{path}: stored {a:.6g}, re-computed {b:.6g} (difference {diff:.3g}"
                               f"{'' if limit is None else f', tolerance {limit:g}'})")


def _near_threshold(path: str, report: VerifyReport) -> bool:
    """On another host a success decided within the tolerance of a threshold may flip; noted, not failed."""
    report.config_notes.append(f"{path} differs on re-simulation but is decided within the cross-host tolerance")
    return True


def _digest(arrays: dict[str, np.ndarray], summary: dict[str, Any], checked: list[str]) -> str:
    """SHA-256 over the checked stored arrays (name, dtype, shape, bytes) and the checked summary parts."""
    h = hashlib.sha256()
    for key in sorted({k for k in checked if k in arrays} | {"sequence_npz"} & set(arrays)):
        a = np.ascontiguousarray(arrays[key])
        h.update(f"{key}:{a.dtype.str}:{a.shape}:".encode())
        h.update(a.tobytes())
    parts = {k: summary.get(k) for k in ("metrics", "attempts", "config", "options", "seed", "sides", "frames")}
    h.update(json.dumps(parts, sort_keys=True).encode())
    return h.hexdigest()
