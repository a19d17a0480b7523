"""Simulation settings (DESIGN §1.4, the paper's values as defaults); re-exported by ``worker.simulation.scene``."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from common.primitive_surface import SPACING_M

#: contype / conaffinity bits: the hand collides with the object only, the object with hand and table.
HAND_BIT, OBJECT_BIT, TABLE_BIT = 1, 2, 4
#: ``SimConfig.convex_detail``'s values, the product's first.
CONVEX_DETAILS = ("coarse", "fine")


@dataclass(frozen=True)
class SimConfig:
    """Every physics setting of a scene. Defaults are DESIGN §1.4; the rest are documented choices."""

    timestep: float = 1.0 / 240.0
    integrator: str = "implicitfast"
    solver: str = "Newton"
    #: Constraint Jacobian layout (MuJoCo ``jacobian``). MuJoCo's ``auto`` picks dense below 60 degrees of freedom,
    #: and a one-hand scene has 57; but the hand is a tree of short chains, so the Newton solver's factorisation is
    #: far cheaper sparse: x1.5-2.0 physics steps per second on DexYCB replays, the same trajectory to 0.1 mm
    #: (issue #19, bench/results/speed_experiments.md). ``auto`` until then.
    jacobian: str = "sparse"
    iterations: int = 10
    #: No noslip pass (issue #19): it was half of every physics step, and ``impratio`` holds the grasps instead.
    #: Until then: 10 iterations with impratio 1 (bench/results/speed_experiments.md).
    noslip_iterations: int = 0
    #: Ratio of frictional to normal constraint impedance (MuJoCo ``impratio``, elliptic cones only). Above 1 the
    #: friction constraints are stiffer than the normal ones, so a pinched grasp creeps less without the noslip
    #: pass: with impratio 1 and no noslip, grasps slipped (dev40: SR 87.5%, larger E_r); 10 kept them; 30 and
    #: 100 made the Newton solver slower without holding better.
    impratio: float = 10.0
    #: Elliptic cones hold DexYCB grasps far better than pyramidal ones (static holds: 7-8/10 vs 4/10).
    cone: str = "elliptic"
    #: Contact impedance 0.99 from the surface on (0.995 at 1 mm): the timestep floors the time constant at 8.3 ms
    #: (``refsafe``), so the steady penetration under a load scales with (1 - d) / d and d is the lever left.
    #: (0.9, 0.99, 0.001) until issue #19 held contacts ~2x deeper (mean per-frame maximum 1.0 vs 0.5 mm).
    contact_solimp: tuple[float, float, float] = (0.99, 0.995, 0.001)
    contact_solref: tuple[float, float] = (0.003, 1.0)
    weld_solimp: tuple[float, float, float] = (0.8, 0.95, 0.01)
    weld_solref: tuple[float, float] = (0.01, 1.0)
    #: Seconds the wrist's mocap target runs ahead of the wrist track it is driven along. The weld pulls the palm
    #: towards a mocap body whose velocity MuJoCo takes as zero, so the palm trails a moving target by a fixed
    #: time: twice the weld time constant (a critically damped spring's ramp lag, 20 ms) less the one timestep
    #: by which each substep's target already leads (``worker.simulation.stepping``). Without the lead a hand swept at a
    #: DexYCB lift's 0.9 m/s trails by 14 mm (9.5 mm at 290 deg/s), which the grasp carries into the object;
    #: with 16 ms, 0.4 mm (0.35 mm) (tests/integration/test_scene_physics.py). 0 drives the mocap along the track.
    wrist_lead_s: float = 0.016
    #: Finger position servos (N·m/rad, N·m·s/rad). With implicitfast the kv term is integrated implicitly, so
    #: the light finger segments stay stable; the servo behaves like a first-order lag of kv/kp = 60 ms.
    finger_kp: float = 50.0
    finger_kv: float = 3.0
    #: Seconds the hinge servo targets run ahead of the reference hinge track: the servos trail a moving target
    #: by kv/kp = 60 ms (less the timestep by which each substep's target leads), so without it a closing grasp
    #: reaches the object late. 0 drives the servos along the reference itself.
    finger_lead_s: float = 0.056
    #: Hinge armature (kg·m²) and passive damping. The armature matters: with light segments alone (1e-4) the
    #: contact solver resolves penetration by throwing the fingers back instead of building grip force, and raw
    #: replay of DexYCB lifts nothing (0/16); 3e-3 lifts 4/16 with the same hand tracking and steps faster.
    hinge_armature: float = 3e-3
    hinge_damping: float = 0.0
    #: Hand tissue density (kg/m³) -> segment masses from the capsule volumes.
    hand_density: float = 1100.0
    #: Cancel gravity on the hand (the wrist is kinematic; finger weight would only bias the servos).
    hand_gravcomp: bool = True
    #: Sliding, torsional, rolling friction of hand-object contacts (condim 6: soft-finger + rolling).
    hand_friction: tuple[float, float, float] = (1.0, 0.02, 0.001)
    hand_condim: int = 6
    #: Object friction when the sequence gives none; table friction.
    object_friction: float = 1.0
    table_friction: float = 0.8
    object_condim: int = 6
    #: Seconds the hand holds its frame-0 pose (fingers settle, object comes to rest) before frame 0 is recorded.
    settle_seconds: float = 0.1
    #: A frame-0 object whose lowest point is within this distance of the table is placed exactly on it.
    snap_to_table_m: float = 0.015
    #: The table is laid under the frame-0 object as recorded (``support_plane``) when the face it rests
    #: on is within this many degrees of level; 0 keeps a level table at z = 0 (and the snap above). 25, not the
    #: few degrees of annotation error: objects in DexYCB scenes also lean on others that are not simulated (a
    #: marker recorded 19 degrees up on one end falls flat on a level table before the hand arrives); the table
    #: friction holds the object up to atan(0.8) = 39 degrees.
    table_max_tilt_deg: float = 25.0
    #: Seconds each candidate table is simulated with the object alone (``table_fit``). 1.5, not the 0.5 before
    #: issue #15's support fix: a marker on a 7 degree face stays within 1 mm for 0.4 s, then rolls 18 cm away
    #: before the hand arrives.
    table_fit_s: float = 1.5
    #: A level shelf under an object recorded above the table (resting on another object, which is not simulated)
    #: is one of the tables tried: a banana recorded 7 cm up otherwise falls before the hand arrives.
    table_shelf: bool = True
    #: The object starts from the mean of its recorded poses over the frames before any hand keypoint comes
    #: within this distance of its surface and before the recorded object moves (``worker.simulation.rest_pose``: the
    #: recording jitters and drifts while the object rests); 0 starts it from the recorded frame 0.
    rest_approach_m: float = 0.02
    #: Hold the object where it starts (a weld to the world, ``object_hold``) over the frames it rests untouched
    #: in the recording: until a recorded hand keypoint comes within this distance of its surface, or it moves
    #: (``rest_pose.resting_frames``); 0: no hold. DexYCB objects rest on supports the scene lacks (other objects,
    #: the table's real shape): an extra-large clamp recorded standing fell 23 degrees while the hand was still
    #: far away, which no hand motion can undo; held until the hand is 2 cm away it is grasped standing (issue #15).
    #: 5 cm let it fall again before the hand arrived. On dev120 it changed no other outcome beyond the
    #: refinement's chaos (bench/results/refine_dev120.md). The cost: a simulated hand far off its recording
    #: reaches the object while it is still welded (tests/support/synthetic_push.py). Every motion of the object
    #: is still made by simulated contact.
    hold_until_m: float = 0.02
    #: Unless no table holds the object as recorded: when the table the fit chooses (``table_fit``) still lets the
    #: object drift more than this from its rest pose in ``table_fit_s`` (degrees + millimetres), it leaned on
    #: something the scene does not have (a scissors standing 12 cm tall, a clamp on its end, a box on its edge)
    #: and, released as the hand came near, fell before the grasp formed. It is then held until the recorded object
    #: moves (``rest_pose.moved_frame``). 10: the object drifts farther in the fit than the noise of a resting
    #: recording (``rest_pose.MAX_SHIFT_M``, ``MAX_TURN_DEG``); a slower drift does little in the ~0.3 s between the
    #: hand coming near and the recording moving the object, and holding a marker that drifted 8.2 on its shelf
    #: until then lost its grasp (the hand closed on an object that could not yet respond). dev120's drifts: six
    #: sequences at 16-126, that marker at 8.2, every other at most 1.4. 0: the hand's approach alone releases it.
    unsupported_drift: float = 10.0
    #: Seconds before the recording moves such an object that its hold ends. ``moved_frame`` sees the object move
    #: only once it is 5 mm or 10 degrees off, a frame or two into the lift; released there, the grasp had to take an
    #: object at rest from a hand already lifting fast, and an extra-large clamp swung 40-70 degrees into the hand
    #: (12.5 mm penetration). Two frames at 30 fps: on dev120's six such sequences the clamp then succeeded with
    #: 0.35 mm mean penetration (6.2 before), and five of six succeeded either way (a pudding box with a 14 cm lift in
    #: five frames failed instead).
    unsupported_lead_s: float = 2.0 / 30.0
    #: A primitive object's surface, for the approach above and the refinement's contact terms, sampled at most
    #: this far apart (``common.primitive_surface``); 0: its tessellation's vertices alone (a box's 8 corners, a
    #: cylinder's two rims), so a fingertip on a face reads the distance to a corner. Meshes are not affected.
    #: 0.005 refined real motions with primitive stand-ins far better than the vertices (30 dev120 sequences,
    #: paper's protocol: SR 25 -> 28 of 30, E_t 1.80 -> 0.72 cm, E_r 5.61 -> 3.14 deg; bench/results/
    #: refine_dev120_primitive.md against _vertices.md). On the known-answer box (tests/integration/
    #: test_refine_known_answer.py) it changes how far the controls come back by no more than the seed does (medians
    #: over 11 seeds: hinge targets 0.83 -> 0.79, wrist position 0.73 -> 0.69, rotation 0.77 -> 0.81 of the start
    #: error); the approach detection reads the same points but changed nothing there, the contact terms did.
    #: The built-in example (the synthetic box lift of ``make demo``, seed 0) got slower and less exact with it:
    #: 20.5 -> 52.3 s, E_t 0.50 -> 0.73 cm, E_r 1.21 -> 2.72 deg (paper's protocol), both first-attempt successes, 7
    #: windows escalated instead of 0. With the corners alone the example had no fingertip contact target and no
    #: grip frame at all (0 and 0; with the points 121 targets on 43 frames, 34 grip frames): its contact terms were
    #: off, and now it is refined with the whole loss, as a mesh is, whose terms also raise the windows' losses
    #: above the escalation level.
    primitive_surface_spacing_m: float = SPACING_M  # 0.005
    #: How finely a non-convex mesh is split into convex collision parts (``convex_cache.CONVEX_DETAIL_PARAMS``):
    #: ``coarse`` (CoACD threshold 0.08, at most 16 parts) or ``fine`` (0.04, at most 32). The product refines on
    #: the coarse parts and uses the fine ones only as a rescue, when every attempt on the coarse ones failed
    #: (``worker.refine.run``): as the only geometry the fine parts lost more grasps than they saved (dev120's
    #: decomposed sequences: SR 82.8 -> 75.9 % on 29; bench/results/refine_dev120_coacd_fine_part.md), while the
    #: sequences that fail on the coarse parts mostly did better on the fine ones (dev120_experiments.md).
    convex_detail: str = "coarse"
    #: An articulated object's joints (issue #52), unless its file gives a joint's own values: viscous damping
    #: (N m s/rad, N s/m) and dry friction as a multiple of the largest gravity load the joint carries (the
    #: part and what hangs from it, weighed at their reach from the axis: N m, or N for a sliding part), so a part
    #: stays where the hands leave it at any angle, as the lids, covers and caps of the recordings do (a laptop
    #: screen, a waffle iron's lid), and a hand still moves it with a few times the part's weight. MuJoCo's dry
    #: friction is a soft constraint that creeps under a steady load; the stiffest reference (``_solref``: MuJoCo
    #: raises it to two timesteps) and impedance (``_solimp``) with 3x the load hold an ARCTIC laptop's screen
    #: open at 2.3 rad on its table to 0.008 rad in 5 s, where MuJoCo's defaults (0.02 s, 0.9-0.95) with 1.5x let it
    #: fall open by 0.5 rad (bench/results/arctic_experiments.md).
    articulation_damping: float = 0.01
    articulation_friction_factor: float = 3.0
    articulation_friction_solref: tuple[float, float] = (0.004, 1.0)
    articulation_friction_solimp: tuple[float, float, float] = (0.999, 0.999, 0.001)

    def __post_init__(self) -> None:
        if self.convex_detail not in CONVEX_DETAILS:
            raise ValueError(f"convex_detail must be one of {', '.join(CONVEX_DETAILS)}, got {self.convex_detail!r}")

    def unsupported(self, table_drift: float) -> bool:
        """Whether an object that drifts this far on its fitted table is one no table holds (``unsupported_drift``)."""
        return 0 < self.unsupported_drift < table_drift

    def lead_frames(self, substeps_per_frame: int) -> tuple[float, float]:
        """(``wrist_lead_s``, ``finger_lead_s``) in video frames of ``substeps_per_frame`` physics steps."""
        frame_s = substeps_per_frame * self.timestep
        return self.wrist_lead_s / frame_s, self.finger_lead_s / frame_s

    def substeps_per_frame(self, fps: float) -> int:
        """Physics steps per video frame (8 at 30 fps with the 1/240 s timestep)."""
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        return max(1, round(1.0 / (fps * self.timestep)))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: Settings a result does not record were, before they existed, these: the mocap and servos followed their tracks,
#: the object started from frame 0, MuJoCo's impratio 1 and automatic Jacobian (until issue #19), a 0.5 s table
#: fit without the shelf candidate (until issue #15's support fix), no hold before the hand arrives, a primitive
#: object's surface known by its tessellation's vertices only (until issue #15's primitive surface points).
OLDER_SIM_DEFAULTS: dict[str, Any] = {"wrist_lead_s": 0.0, "finger_lead_s": 0.0, "rest_approach_m": 0.0,
                                      "impratio": 1.0, "jacobian": "auto", "table_fit_s": 0.5, "table_shelf": False,
                                      "hold_until_m": 0.0, "primitive_surface_spacing_m": 0.0,
                                      "unsupported_drift": 0.0, "unsupported_lead_s": 0.0}
