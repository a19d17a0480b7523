"""What ``verify`` reports and the tolerances it applies on another host (``worker.refine.verify``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


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
    object_rot_deg: float = 5.0
    #: Velocities and contact forces jump frame by frame where a contact flickers (2.3 m/s, rad/s at one frame
    #: for a 0.75 mm trajectory deviation), so they are compared over the whole sequence: the L1 norm of the
    #: per-frame difference relative to the re-simulation's.
    object_vel_rel: float = 1.0
    keypoints_m: float = 1e-2
    mean_cm: float = 0.2  # E_t, E_j, E_ft (sequence means, cm)
    mean_deg: float = 1.0  # E_r
    max_cm: float = 0.6  # max_E_t and per-frame errors (cm)
    max_deg: float = 3.0  # max_E_r and per-frame rotation errors (deg)
    penetration_mm: float = 3.0  # per frame and sequence maximum
    penetration_mean_mm: float = 0.5
    fraction: float = 0.15  # hand_only_fraction
    force_rel: float = 0.6  # relative L1 difference of the per-frame net hand force on the object


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
