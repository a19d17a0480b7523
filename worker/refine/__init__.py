"""Physics-in-the-loop refinement (DESIGN §1 steps 3-7, issue #3).

Modules, in pipeline order:

* ``spline``     keyframe schedule (K = round(fps / 6)) and Catmull-Rom interpolation weights;
* ``controls``   offsets [10 pose-PCA coefficients, 3 wrist rotation (, 3 translation)] -> per-substep
                 hinge targets and wrist mocap poses;
* ``evaluator``  ``ParallelEvaluator``: a pool of MjData behind ``mujoco.rollout`` (reusable across jobs);
                 ``warp_evaluator.WarpEvaluator`` runs its batched rollouts on MuJoCo Warp (optional ``.[gpu]``
                 extra, so not imported here; ``bench/gpu_rollout.py``);
* ``losses``     the loss terms over recorded frames, default weights;
* ``problem``    ``SimWindowProblem``: controls -> rollouts -> losses for one window;
* ``windowed``   the sliding-window CMA-ES (``optimise_windows``), progress and cancellation;
* ``prepare``    references, scene, control spaces and loss targets of a sequence;
* ``replay``     the from-scratch replay of keyframes and the window problem it shares with the optimiser;
* ``run``        ``refine_sequence`` (the entry point the Ray worker calls);
* ``derive``     ``derive_result``: the result's replays, metrics and arrays from its inputs (the worker and
                 ``verify`` call the same function);
* ``result``     the result summary (and the visual tools' rebuild of a result's problem);
* ``environment`` what a result records of the environment that made it (packages, CPU kind);

``verify`` (recompute and compare everything a result claims) is its own sub-package, ``worker.verification``,
above this one: it calls ``derive`` and reads ``prepare``.
"""

import warnings

# cma warns at import when matplotlib is absent; only its plotting needs it and we never plot.
warnings.filterwarnings("ignore", message="Could not import matplotlib", category=UserWarning)

from worker.refine.evaluator import ParallelEvaluator  # noqa: E402  (after the warnings filter: it imports cma)
from worker.refine.prepare import Prepared  # noqa: E402
from worker.refine.replay import ReplayRecord  # noqa: E402
from worker.refine.run import RefineOutcome, refine_sequence  # noqa: E402
from worker.refine.windowed import RefineProgress  # noqa: E402

# Not re-exported: the functions named like their modules (``prepare``, ``replay``): a package attribute of that
# name would hide the module (``import worker.refine.prepare as m`` would then bind the function).
__all__ = [
    "ParallelEvaluator",
    "Prepared",
    "RefineOutcome",
    "RefineProgress",
    "ReplayRecord",
    "refine_sequence",
]
