"""Sliding-window CMA-ES over keyframes (DESIGN §1.6, issue #3 items 3 and 7).

Window j is (k1, k2, k3, k4) = (j-2, j-1, j, j+1): only keyframe k3 = j is optimised, the earlier ones stay as
committed and the later ones hold the candidate's value (an offset persists until a later window changes it;
this also warm-starts keyframe j from keyframe j-1); the window's simulation starts from the committed state
at keyframe j-2 (see ``spline`` for why this is exact with a Catmull-Rom spline). After the window, the state
at keyframe j-1 is committed and the window slides by one keyframe. With two hands, each hand has its own CMA-
ES on its own keyframe j; the candidates of both are paired in the same rollouts (candidate i of the right
hand with candidate i of the left), and each hand's CMA-ES is told its own objective (object terms + its hand
terms). Each hand's best was scored beside random candidates of the other hand, never beside the other's best, so
before a window commits, the pair of bests is simulated together and kept only if it beats the best pair seen in
one rollout and the keyframes the window started from (``_confirmed``): a pair that was never simulated together
can drop an object each hand alone held.

A window is skipped (keyframe left at its current value) when the hand does not touch the object on the
window's frames and the current loss is already below ``skip_loss``: nothing there to fix.

A polish pass (``polish=True``) runs the windows again over the keyframes of a finished pass: each window starts
its CMA-ES from that pass's keyframe j and replaces keyframe j alone, so its lookahead frames are driven by the
later keyframes as that pass left them instead of by the held candidate. The first pass chose keyframe j before
any later keyframe existed; the polish lets it see them (one more greedy sweep; the caller keeps whichever
whole-sequence replay is better).

A window whose best loss is still above ``escalate_loss`` after the CMA-ES run gets a second, larger one
(``escalate_factor`` x the population, a wider initial step, its own random stream) started from the best
found: the greedy sliding window cannot undo a committed keyframe, so a grasp lost here is lost for good, and
the budget is better spent on the few windows where the object is slipping than on every window alike.

A first pass with ``rewind_windows`` > 0 (off in the product: being measured on ARCTIC, bench/results/
refine_arctic.md) goes back when a window stands out (its best loss, escalation included, ``rewind_ratio`` x the
median of the last optimised windows and above ``escalate_loss``): the object is usually lost
there because of keyframes committed a window or two earlier, which no later window can change. The pass runs that
window and the ``rewind_windows`` before it again from the state before them, drawing from other random streams,
and keeps whichever of the two runs has the lower sum of their windows' losses.

This module knows nothing of MuJoCo: it drives any ``WindowProblem``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import cma
import numpy as np

from common.errors import JobCancelledError
from common.geometry import FloatArray

#: The k-th rewind of a pass draws from random stream REWIND_STREAM + 2 k (+ 1 where a window escalates); the first
#: pass, the polish and the repair's rounds use the streams below it.
REWIND_STREAM = 1000
#: A standing-out window is judged against the median of this many optimised windows before it.
REWIND_RECENT = 8


class WindowProblem(Protocol):
    sides: tuple[str, ...]
    n_keyframes: int
    #: Windows before this keep their keyframe (keyframe 0 is the frame-0 state the simulation starts from).
    first_window: int

    def dim(self, side: str) -> int: ...

    def start_state(self) -> Any: ...

    def probe(self, j: int, state: Any, keyframes: dict[str, FloatArray]) -> tuple[dict[str, float], bool]:
        """Per-hand loss of the window with the current keyframes, and whether any hand touches the object."""

    def evaluate(
        self, j: int, state: Any, keyframes: dict[str, FloatArray], candidates: dict[str, FloatArray],
        hold: bool = True,
    ) -> dict[str, FloatArray]:
        """Per-hand losses (C,) with keyframe j of each hand replaced by its candidates (C, dim), and (``hold``)
        every later keyframe too."""

    def commit(self, j: int, state: Any, keyframes: dict[str, FloatArray]) -> Any:
        """The state at the start of window j + 1, simulated from ``state`` (start of window j)."""


@dataclass
class CmaSettings:
    popsize: int = 12
    max_generations: int = 8
    sigma0: float = 0.5
    #: Bound on every coordinate (unit-variance PCA, scaled rotation/translation): keeps poses plausible.
    bound: float = 3.0
    skip_loss: float = 2.0
    seed: int = 0
    #: A second, larger CMA-ES run for windows whose best loss stays above this (inf: never).
    escalate_loss: float = float("inf")
    escalate_factor: int = 2
    #: Stop a window's CMA-ES early when its best loss improved by less than ``stall_tolerance`` (relative) over
    #: the last ``stall_generations`` generations (0: always run ``max_generations``), but only once that loss is
    #: below ``stall_below`` (None: ``skip_loss``, the level at which an untouched window needs no work): a window
    #: still far off keeps searching, since the greedy window cannot undo what it commits.
    stall_generations: int = 0
    stall_tolerance: float = 0.01
    stall_below: float | None = float("inf")
    #: A first pass runs a standing-out window again with this many windows before it (0: never; module docstring).
    rewind_windows: int = 0
    #: A window stands out when its best loss is above this many times the median of the last optimised windows.
    rewind_ratio: float = 3.0
    #: At most this many rewinds per pass (each costs ``rewind_windows`` + 1 windows).
    rewind_max: int = 8


@dataclass(frozen=True)
class Band:
    """Windows ``start`` .. ``stop`` - 1 of a polish pass, run from ``state`` (the state at window ``start``'s first
    frame), drawing from random stream ``stream`` (and ``stream`` + 1 where a window escalates)."""

    start: int
    stop: int
    state: Any
    stream: int


@dataclass
class WindowLog:
    index: int
    skipped: bool
    touched: bool
    initial_loss: float
    best_loss: float
    evaluations: int
    history: list[float] = field(default_factory=list)  # best loss per generation
    escalated: bool = False
    #: The CMA-ES run ended before ``max_generations`` because the best loss stopped improving.
    stopped_early: bool = False
    #: The window stood out and the pass ran it again with the windows before it (``rewind_windows``); its
    #: evaluations then include those of the run that was not kept.
    rewound: bool = False


@dataclass
class RefineProgress:
    """What ``progress`` receives after every generation and window."""

    window: int  # 1-based index of the current window
    windows: int
    best_loss: float
    evaluations: int
    elapsed_s: float
    eta_s: float
    skipped: int = 0
    #: Of this pass's windows, done (0..1; ``elapsed_s`` / (``elapsed_s`` + ``eta_s``)).
    fraction: float = 0.0
    # Set by ``run.refine_sequence``: which pass of its plan this is (``job_progress`` turns them into the job's).
    attempt: int = 1  # the refinement's attempt (2, 3, ...: a further one after a failed or poor one, attempt_plan)
    attempts: int = 1  # the most attempts the job's options allow (restarts + 1)
    polish_sweep: int = 0  # the polish sweep over the best attempt (1-based); 0 in an attempt
    rescue: bool = False  # the plan's run on finer convex parts (run.RESCUE)
    deriving: bool = False  # the passes are over and the result is being derived (no window fields)
    #: The rescue's finer convex parts are being made and its scene compiled, before its first pass (no window fields).
    compiling_rescue: bool = False


def optimise_windows(
    problem: WindowProblem,
    settings: CmaSettings,
    keyframes: dict[str, FloatArray] | None = None,
    progress: Callable[[RefineProgress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    polish: bool = False,
    band: Band | None = None,
) -> tuple[dict[str, FloatArray], list[WindowLog]]:
    """Run every window in order; returns the final keyframes per hand and one log per window. ``polish``: a
    pass over ``keyframes`` (required then) that changes one keyframe per window, see the module docstring.
    ``band``: a polish pass over its windows only, from its state (``worker.refine.repair``)."""
    if (polish or band is not None) and keyframes is None:
        raise ValueError("a polish pass needs the keyframes of a finished pass")
    kf = {s: np.zeros((problem.n_keyframes, problem.dim(s))) for s in problem.sides}
    if keyframes is not None:
        kf = {s: keyframes[s].copy() for s in problem.sides}
    logs: list[WindowLog] = []
    state = problem.start_state() if band is None else band.state
    first, n_win = (problem.first_window, problem.n_keyframes) if band is None else (band.start, band.stop)
    polish = polish or band is not None
    confirm = len(problem.sides) > 1  # a pair of per-hand bests is simulated together before it is committed
    n_todo = n_win - first
    t_start = time.perf_counter()
    evaluations = 0

    def report(j: int, best: float, finished: bool = False) -> None:
        if progress is None:
            return
        elapsed = time.perf_counter() - t_start
        done = j - first + (1.0 if finished else 0.5)
        eta = elapsed / done * (n_todo - done)
        skipped = sum(w.skipped for w in logs)
        index = j - first + 1
        progress(RefineProgress(index, n_todo, best, evaluations, elapsed, eta, skipped, done / n_todo))

    def window(j: int, state: Any, stream: int) -> WindowLog:
        """Optimise window j from ``state`` (the state at its first frame) into ``kf``, drawing from ``stream``."""
        nonlocal evaluations
        _check_stop(should_stop)
        if not polish:
            for side in problem.sides:  # hold the last optimised offset over the keyframes not optimised yet
                kf[side][j:] = kf[side][j - 1] if j > 0 else kf[side][j]
        base, touched = problem.probe(j, state, kf)
        evaluations += 1
        base_total = float(sum(base.values()))
        log = WindowLog(j, False, touched, base_total, base_total, 1)
        if not touched and base_total < settings.skip_loss:
            log.skipped = True
            return log
        best = _optimise_one(problem, settings, j, state, kf, base, log, should_stop, report, stream, polish, confirm)
        evaluations += log.evaluations - 1
        if log.best_loss > settings.escalate_loss:
            log.escalated = True
            before = log.evaluations
            _optimise_one(problem, _escalated(settings), j, state, kf, best, log, should_stop, report, stream + 1,
                          polish, confirm)
            evaluations += log.evaluations - before
        return log

    # The polish draws from random streams of its own (2), apart from the first pass's (0, 1), a band from the ones
    # its round names, and the k-th rewind from REWIND_STREAM + 2 k.
    stream = (2 if polish else 0) if band is None else band.stream
    starts: dict[int, Any] = {}  # the state at the first frame of each window, for a rewind
    rewinds, calm_from = 0, first  # a rewind's windows are not rewound again
    for j in range(first, n_win):
        starts[j] = state
        logs.append(window(j, state, stream))
        if (not polish and settings.rewind_windows > 0 and rewinds < settings.rewind_max and j >= calm_from
                and _stands_out(logs, settings)):
            back = max(first, j - settings.rewind_windows)
            before_kf = {s: kf[s].copy() for s in problem.sides}
            before_logs, before_starts = logs[back - first:], {i: starts[i] for i in range(back, j + 1)}
            del logs[back - first:]
            redo = starts[back]
            for i in range(back, j + 1):
                starts[i] = redo
                logs.append(window(i, redo, REWIND_STREAM + 2 * rewinds))
                if i < j:
                    redo = problem.commit(i, redo, kf)
            rewinds, calm_from = rewinds + 1, j + settings.rewind_windows + 1
            again, discarded = logs[back - first:], before_logs
            if sum(w.best_loss for w in again) >= sum(w.best_loss for w in before_logs):  # ties keep the first run
                for side in problem.sides:
                    kf[side][:] = before_kf[side]
                logs[back - first:], discarded = before_logs, again
                starts.update(before_starts)
            logs[-1].rewound = True
            logs[-1].evaluations += sum(w.evaluations for w in discarded)
        report(j, logs[-1].best_loss, finished=True)
        state = problem.commit(j, starts[j], kf)
        starts.pop(j - settings.rewind_windows, None)  # no rewind reaches it any more
    return kf, logs


def _optimise_one(
    problem: WindowProblem,
    settings: CmaSettings,
    j: int,
    state: Any,
    kf: dict[str, FloatArray],
    base: dict[str, float],
    log: WindowLog,
    should_stop: Callable[[], bool] | None,
    report: Callable[..., None],
    attempt: int = 0,
    polish: bool = False,
    confirm: bool = False,
) -> dict[str, float]:
    """CMA-ES on keyframe j of every hand, started from ``kf`` (whose losses are ``base``); writes the best
    keyframe into ``kf`` (and, unless ``polish``, every later one) and adds to ``log``; returns each hand's best
    loss. ``confirm`` (several hands): see ``_confirmed``."""
    strategies: dict[str, Any] = {}
    for i, side in enumerate(problem.sides):
        opts = {
            # Seed per window, hand and attempt so none share random streams; never 0 (= time-seeded in cma).
            "seed": 1 + (settings.seed * 1_000_003 + j * 7919 + i * 104_729 + attempt * 15_485_863) % (2**31 - 2),
            "popsize": settings.popsize,
            "bounds": [-settings.bound, settings.bound],
            "verbose": -9,
            "verb_log": 0,
            "verb_disp": 0,
            "maxiter": settings.max_generations,
            "tolfun": 1e-9,
            "tolx": 1e-9,
            "CMA_diagonal": False,
        }
        strategies[side] = cma.CMAEvolutionStrategy(kf[side][j].copy(), settings.sigma0, opts)
    best = {s: (base[s], kf[s][j].copy()) for s in problem.sides}
    start = {s: kf[s][j].copy() for s in problem.sides}
    pair: tuple[float, dict[str, FloatArray], dict[str, float]] = (float(sum(base.values())), start, base)
    evals = 0
    for _gen in range(settings.max_generations):
        _check_stop(should_stop)
        asked = {s: np.asarray(es.ask(), dtype=np.float64) for s, es in strategies.items()}
        losses = problem.evaluate(j, state, kf, asked, hold=not polish)
        evals += settings.popsize
        if confirm:
            totals = np.sum([np.where(np.isfinite(v), v, 1e12) for v in losses.values()], axis=0)
            k = int(np.argmin(totals))
            if totals[k] < pair[0]:
                pair = (float(totals[k]), {s: asked[s][k].copy() for s in problem.sides},
                        {s: float(v[k]) for s, v in losses.items()})
        for side, es in strategies.items():
            values = losses[side]
            values = np.where(np.isfinite(values), values, 1e12)
            es.tell(list(asked[side]), values.tolist())
            k = int(np.argmin(values))
            if values[k] < best[side][0]:
                best[side] = (float(values[k]), asked[side][k].copy())
        total = float(sum(b[0] for b in best.values()))
        log.history.append(total)
        report(j, total)
        if _stalled(log.history, settings):
            log.stopped_early = True
            break
    if confirm:
        chosen, losses_now, probes = _confirmed(problem, j, state, kf, best, pair, start, base, hold=not polish)
        best = {s: (losses_now[s], chosen[s]) for s in problem.sides}
        evals += probes
    for side in problem.sides:
        kf[side][j if polish else slice(j, None)] = best[side][1]
    log.best_loss = float(sum(b[0] for b in best.values()))
    log.evaluations += evals
    return {s: b[0] for s, b in best.items()}


def _confirmed(
    problem: WindowProblem, j: int, state: Any, kf: dict[str, FloatArray], best: dict[str, tuple[float, FloatArray]],
    pair: tuple[float, dict[str, FloatArray], dict[str, float]], start: dict[str, FloatArray],
    base: dict[str, float], hold: bool = False,
) -> tuple[dict[str, FloatArray], dict[str, float], int]:
    """Keyframe j of every hand for a window, of three: each hand's best (scored beside random candidates of the
    other hand, never together, so the pair may lose the object where each alone held it), the best pair scored in
    one rollout, and the keyframe the window started from. Each hand's best is probed together (``hold``: with the
    later keyframes holding it, as the first pass evaluates); the lowest total loss wins. Returns the keyframes,
    their per-hand losses and the probes made (one)."""
    combined = {s: b[1] for s, b in best.items()}
    trial = {s: kf[s].copy() for s in problem.sides}
    for s in problem.sides:
        trial[s][j if not hold else slice(j, None)] = combined[s]
    together, _ = problem.probe(j, state, trial)
    options = [(float(sum(together.values())), combined, together), (float(sum(base.values())), start, base), pair]
    _, chosen, losses = min(options, key=lambda o: o[0])
    return chosen, losses, 1


def _stands_out(logs: list[WindowLog], settings: CmaSettings) -> bool:
    """Whether the last window's best loss is above ``escalate_loss`` and ``rewind_ratio`` x the median of the
    (up to ``REWIND_RECENT``) optimised windows before it, at least three of them."""
    last = logs[-1]
    if last.skipped or last.best_loss <= settings.escalate_loss:
        return False
    recent = [w.best_loss for w in logs[:-1] if not w.skipped][-REWIND_RECENT:]
    return len(recent) >= 3 and last.best_loss > settings.rewind_ratio * float(np.median(recent))


def _stalled(history: list[float], settings: CmaSettings) -> bool:
    """True when the best loss is below the stall level and improved by no more than ``stall_tolerance``
    (relative) over the last ``stall_generations`` generations: more generations would polish, not fix."""
    k = settings.stall_generations
    below = settings.skip_loss if settings.stall_below is None else settings.stall_below
    if k <= 0 or len(history) <= k or history[-1] >= below:
        return False
    before, now = history[-k - 1], history[-1]
    return before - now <= settings.stall_tolerance * abs(before)


def _escalated(settings: CmaSettings) -> CmaSettings:
    """The settings of a hard window's second run: a larger population and a wider first step."""
    return replace(settings, popsize=settings.popsize * settings.escalate_factor, sigma0=settings.sigma0 * 1.5)


def _check_stop(should_stop: Callable[[], bool] | None) -> None:
    if should_stop is not None and should_stop():
        raise JobCancelledError("refinement cancelled")
