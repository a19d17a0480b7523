"""The simulation (DESIGN §1.4): physics settings, the object's MuJoCo model (convex parts cached by content),
the table fitted under the recorded object and its rest pose, the scene (hand + object + table in one
``MjModel``), stepping with the object moved only by contact, contact recording, the metrics (§1.7) and the
raw replay of a sequence's reference.
"""

from worker.simulation.config import SimConfig
from worker.simulation.contacts import ContactRecorder, empty_contact_columns
from worker.simulation.convex_cache import convex_parts
from worker.simulation.hand_mjcf import hand_mjcf
from worker.simulation.metrics import (
    SUCCESS_POSITION_CM,
    SUCCESS_ROTATION_DEG,
    compute_metrics,
    scalar_metrics,
)
from worker.simulation.object_model import centre_of_mass, object_mjcf
from worker.simulation.replay import ReplayResult, raw_replay, replay_result_bytes
from worker.simulation.scene import Scene, build_scene
from worker.simulation.stepping import HandTargets, RolloutRecord, initial_state, rollout, substep_controls
from worker.simulation.support_plane import SupportPlane
from worker.simulation.table_fit import fit_table

# ``rest_pose`` (the function) is not re-exported: it would hide its module ``worker.simulation.rest_pose``.
__all__ = [
    "SUCCESS_POSITION_CM",
    "SUCCESS_ROTATION_DEG",
    "ContactRecorder",
    "HandTargets",
    "ReplayResult",
    "RolloutRecord",
    "Scene",
    "SimConfig",
    "SupportPlane",
    "build_scene",
    "centre_of_mass",
    "compute_metrics",
    "convex_parts",
    "empty_contact_columns",
    "fit_table",
    "hand_mjcf",
    "initial_state",
    "object_mjcf",
    "raw_replay",
    "replay_result_bytes",
    "rollout",
    "scalar_metrics",
    "substep_controls",
]
