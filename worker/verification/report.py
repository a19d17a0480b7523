"""What ``verify`` reports and the tolerances it applies on another host (``worker.verification.check``)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any


@dataclass(frozen=True)
class Tolerances:
    """How far a re-simulation on another x86_64 host may stray from the stored result (SI units unless named).

    Why there is any difference: MuJoCo's arithmetic is the same on every x86_64 host, but NumPy and OpenBLAS
    pick CPU-specific kernels (AVX-512 vs AVX2) whose results differ in the last bit, in the retargeting, the
    table fit and the per-substep controls; a contact-rich replay grows 1e-16 into millimetres (an honest result
    failed verify by 0.066 mm from one extra quaternion normalisation).

    Measured by re-deriving 16 dev results made on this AVX-512 host with NumPy's AVX-512 kernels off and
    OpenBLAS's Haswell kernels forced (``NPY_DISABLE_CPU_FEATURES``, ``OPENBLAS_CORETYPE``: what an AVX2 host
    runs): a held object deviated 0.004-1.4 mm / 0.006-1.6 deg, keypoints up to 2.9 mm; velocities and the net
    contact force per frame jump where a contact flickers (relative L1 up to 0.42 and 0.23); a raw replay whose
    object fell deviated 7.2 mm / 8.0 deg — a falling, tumbling object is where the dynamics are most sensitive.
    So the object may deviate by a base (``object_pos_m`` / ``object_rot_deg``, ~3.5x / ~3x the largest held
    deviation) plus ``drift_fraction`` of that frame's tracking error (a dropped object 20 cm off may stray 2 cm
    more); the other bounds are the measured maxima with a margin of 2-3x. All stay well below what a forgery needs
    (a 5 cm wrist move, forces x10, a rewritten figure — and figures are also checked, tightly, against the stored
    trajectories). Inputs that no simulation touches (controls from keyframes, the reference) only see last-bit
    differences: ``inputs``.
    """

    inputs: float = 1e-6  # m / rad / unitless: controls, reference keypoints and object poses
    #: The per-frame figures (errors in cm / deg, penetration in mm) where the re-simulation is bit-identical:
    #: NumPy computes them with CPU-specific kernels (AVX-512's vectorised arctan2 against AVX2's give the same
    #: rotation error ~1e-15 deg apart), so even an exact replay on another host may differ in the last bits.
    #: Far below anything a figure is read to.
    figures_last_bits: float = 1e-9
    object_pos_m: float = 5e-3
    object_rot_deg: float = 5.0
    drift_fraction: float = 0.1
    #: Compared over the whole sequence: the L1 norm of the per-frame difference relative to the re-simulation's.
    object_vel_rel: float = 1.0
    force_rel: float = 0.6  # the per-frame net hand force on the object
    keypoints_m: float = 1e-2  # per frame, and the per-frame E_j / E_ft
    mean_keypoint_cm: float = 0.3  # E_j, E_ft
    penetration_mm: float = 3.0  # per frame and sequence maximum
    penetration_mean_mm: float = 0.5
    fraction: float = 0.15  # hand_only_fraction
    #: Where the comparison is against records made at the stored states (``STEPWISE``): contacts row for row
    #: within this (m, N, N m; None: only the per-frame net force, ``force_rel``), the table-contact and hand-only
    #: flags exactly, and a success never flips.
    contact_rows: float | None = None
    #: The articulation error E_a is in cm (every joint prismatic) rather than degrees (``for_joints``).
    articulation_cm: bool = False

    def for_joints(self, kinds: tuple[str, ...]) -> Tolerances:
        """These tolerances for an object with joints of ``kinds``: E_a is read in cm when every joint is
        prismatic, else in degrees (a mixed object's frames take the larger, the rotation's, bound)."""
        return replace(self, articulation_cm=bool(kinds) and all(k == "prismatic" for k in kinds))

    def summary_limit(self, key: str, value: float) -> float | None:
        """The tolerance of summary figure ``key`` whose re-computed value is ``value`` (None: must be equal).
        The articulation error (E_a, an articulated object's joints against the recording) is bounded as the
        object's rotation (or position, ``articulation_cm``) is: its joints move with the same dynamics, so the
        same drift reaches them (the hinged box with other kernels forced: 7e-7 deg over a re-simulation that
        drifted 4e-6 mm)."""
        pos_cm, rot = 100.0 * self.object_pos_m, self.object_rot_deg
        arti = pos_cm if self.articulation_cm else rot
        table = {
            "E_t": pos_cm + self.drift_fraction * value, "max_E_t": pos_cm + self.drift_fraction * value,
            "E_r": rot + self.drift_fraction * value, "max_E_r": rot + self.drift_fraction * value,
            "E_a": arti + self.drift_fraction * value, "max_E_a": arti + self.drift_fraction * value,
            "E_j": self.mean_keypoint_cm, "E_ft": self.mean_keypoint_cm,
            "penetration_mean_mm": self.penetration_mean_mm, "penetration_max_mm": self.penetration_mm,
            "hand_only_fraction": self.fraction,
        }
        return table.get(key)


CROSS_HOST = Tolerances()
#: Against the records a stepwise check made at the stored states (``worker.verification.stepwise``): each
#: frame's pose, keypoints and contacts are computed at the very state stored, so they agree on any host to far
#: below anything a figure is read to (measured: ``bench/results/verify_portable.md``); only the inputs no
#: simulation touches keep ``inputs``. Rotations: the angle between two equal unit quaternions reads up to ~2e-6 deg
#: (arccos of a dot product rounded below 1), so 1e-5 deg.
STEPWISE = Tolerances(object_pos_m=1e-9, object_rot_deg=1e-5, drift_fraction=0.0, object_vel_rel=1e-9,
                      force_rel=1e-6, keypoints_m=1e-9, mean_keypoint_cm=1e-7, penetration_mm=1e-6,
                      penetration_mean_mm=1e-6, fraction=0.0, contact_rows=1e-6)


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
    #: "stepwise": each stored frame's state checked against the one before it, the arrays and figures against
    #: the records made at those states (``worker.verification.stepwise``); "rollout": a result without stored
    #: states, checked against a whole re-simulation (exact here, within ``CROSS_HOST`` elsewhere).
    method: str = "rollout"
    #: per replay ("refined", "raw"): a ``worker.verification.stepwise.StepwiseReport`` (not imported here: that
    #: module reports into this one)
    stepwise: dict[str, Any] = field(default_factory=dict)

    @property
    def verified(self) -> bool:
        return not self.failures

    def to_dict(self) -> dict[str, Any]:
        return {
            "verified": self.verified, "method": self.method,
            "stepwise": {k: v.to_dict() for k, v in self.stepwise.items()},
            "notes": list(self.config_notes),
            "frames": self.frames, "exact": self.exact, "max_pos_diff_m": self.max_pos_diff_m,
            "max_rot_diff_deg": self.max_rot_diff_deg, "max_keypoint_diff_m": self.max_keypoint_diff_m,
            "config_changes": [{"setting": n, "default": d, "stored": s} for n, d, s in self.config_changes],
            "checked": len(self.checked), "failures": list(self.failures), "digest": self.digest,
        }
