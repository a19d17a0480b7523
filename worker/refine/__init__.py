"""Physics-in-the-loop refinement (DESIGN §1 steps 3-7, issue #3).

Modules, in pipeline order:

* ``spline``     keyframe schedule (K = round(fps / 6)) and Catmull-Rom interpolation weights;
* ``controls``   offsets [10 pose-PCA coefficients, 3 wrist rotation (, 3 translation)] -> per-substep
                 hinge targets and wrist mocap poses;
* ``evaluator``  ``ParallelEvaluator``: a pool of MjData behind ``mujoco.rollout`` (reusable across jobs);
* ``losses``     the six loss terms over recorded frames, default weights;
* ``problem``    ``SimWindowProblem``: controls -> rollouts -> losses for one window;
* ``windowed``   the sliding-window CMA-ES (``optimise_windows``), progress and cancellation;
* ``prepare``    references, scene, control spaces and loss targets of a sequence;
* ``run``        ``refine_sequence`` (the entry point the Ray worker calls) and the from-scratch replay;
* ``derive``     ``derive_result``: the result's replays, metrics and arrays from its inputs (the worker and
                 ``verify`` call the same function);
* ``result``     the result summary;
* ``verify``     ``verify_result`` / ``check_result`` (with ``verify_arrays``, ``verify_summary``,
                 ``verify_report``): recompute and compare everything a result claims.
"""

import warnings

# cma warns at import when matplotlib is absent; only its plotting needs it and we never plot.
warnings.filterwarnings("ignore", message="Could not import matplotlib", category=UserWarning)
