"""The whole job's progress (worker/refine/job_progress.py, issue #53 item 4): a fraction that only goes forward
over a plan that grows, the stage texts, the job's ETA, and the heartbeat's document that keeps the queue's attempt
apart from the refinement's."""

from __future__ import annotations

import numpy as np
import pytest

from common.progress import STEPS, finished_progress
from worker.refine.job_progress import CLOSE_UP_PASSES, RESERVE_PER_PASS, TAIL_PASSES, JobProgress
from worker.refine.windowed import RefineProgress
from worker.runtime.heartbeat import Heartbeat


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _pass(windows: int, attempt: int = 1, sweep: int = 0, rescue: bool = False,
          attempts: int = 3) -> list[RefineProgress]:
    """One pass's window reports, each window finished."""
    return [RefineProgress(w, windows, 1.0, 10 * w, 0.0, 0.0, fraction=w / windows, attempt=attempt, attempts=attempts,
                           polish_sweep=sweep, rescue=rescue) for w in range(1, windows + 1)]  # fmt: skip


def _compiling() -> list[RefineProgress]:
    """The report ``refine_sequence`` sends before the rescue's finer parts compile."""
    return [RefineProgress(0, 0, float("nan"), 0, 0.0, 0.0, rescue=True, compiling_rescue=True)]


def _run(tracker: JobProgress, clock: Clock, passes: list[list[RefineProgress]]) -> list[dict]:
    docs = [tracker.preparing()]
    clock.now += 5.0
    for reports in passes:
        for p in reports:
            clock.now += 2.0
            docs.append(tracker.window(p))
    docs.append(tracker.window(RefineProgress(0, 0, float("nan"), 0, 0.0, 0.0, deriving=True)))
    clock.now += 1.0
    docs.append(tracker.stage("verify"))
    clock.now += 1.0
    docs.append(tracker.stage("preview"))
    return docs


def test_the_fraction_only_goes_forward_as_attempts_sweeps_and_a_rescue_join_the_plan() -> None:
    clock = Clock()
    tracker = JobProgress(2, verify=True, preview=True, clock=clock)
    passes = [_pass(5, 1), _pass(5, 2), _pass(5, 3), _pass(5, 3, sweep=1), _compiling(), _pass(5, 1, rescue=True),
              _pass(5, 1, sweep=1, rescue=True)]  # fmt: skip
    docs = _run(tracker, clock, passes)
    fractions = [d["fraction"] for d in docs]
    assert fractions == sorted(fractions)
    assert fractions[0] == 0.0 and 0.8 < fractions[-1] < 1.0  # the preview is still to draw
    stages = list(dict.fromkeys(d["stage"] for d in docs))
    assert stages == ["preparing", "attempt 1 of 3", "attempt 2 of 3", "attempt 3 of 3", "polish sweep 1",
                      "compiling finer parts for a rescue", "rescue on finer parts: attempt 1 of 3",
                      "rescue on finer parts: polish sweep 1",
                      "deriving the result", "verifying", "preview"]  # fmt: skip
    steps = list(dict.fromkeys(d["step"] for d in docs))
    assert steps == ["prepare", "attempt", "polish", "rescue_compile", "rescue", "derive", "verify", "preview"]
    assert all(s in STEPS for s in steps)
    # The evaluations add up over the job's passes (each pass reports its own from 0).
    assert docs[-4]["evaluations"] == 6 * 50
    # The window keys belong to the pass: the derivation's document has none.
    assert "window" not in docs[-3] and "refine_attempt" not in docs[-3]
    assert docs[2]["refine_attempt"] == 1 and docs[2]["refine_attempts"] == 3 and "polish_sweep" not in docs[2]
    sweep = next(d for d in docs if d["stage"] == "polish sweep 1")
    assert sweep["polish_sweep"] == 1 and sweep["refine_attempt"] == 3


def test_the_rescues_compilation_has_a_stage_holds_the_bar_and_stays_out_of_the_pace() -> None:
    clock = Clock()
    tracker = JobProgress(1, polish=False, verify=True, preview=True, clock=clock)
    tracker.preparing()
    for reports in (_pass(4, 1, attempts=2), _pass(4, 2, attempts=2)):
        for p in reports:
            clock.now += 5.0  # 20 s a pass
            last = tracker.window(p)
    compiling = tracker.window(_compiling()[0])
    assert (compiling["stage"], compiling["step"]) == ("compiling finer parts for a rescue", "rescue_compile")
    assert not {"window", "windows", "refine_attempt", "polish_sweep"} & set(compiling)
    assert compiling["fraction"] >= last["fraction"] and compiling["evaluations"] == 2 * 40
    # CoACD runs for minutes: the bar holds still and the ETA (the rescue's passes at 20 s, then the tail) stays.
    clock.now += 300.0
    later = tracker.window(_compiling()[0])
    assert later["fraction"] == compiling["fraction"]
    assert later["eta_s"] == compiling["eta_s"] and compiling["eta_s"] is not None and compiling["eta_s"] > 20.0
    # The rescue's first pass moves the bar on, at the passes' own pace (the 300 s of CoACD left out of it).
    rescue = _pass(4, 1, rescue=True, attempts=2)
    first = tracker.window(rescue[0])
    assert first["stage"] == "rescue on finer parts: attempt 1 of 2" and first["fraction"] > compiling["fraction"]
    for p in rescue[1:]:
        clock.now += 5.0
        doc = tracker.window(p)
    assert doc["eta_s"] < 60.0, doc
    clock.now += 2.0
    tracker.window(RefineProgress(0, 0, float("nan"), 0, 0.0, 0.0, deriving=True))
    clock.now += 2.0
    # The verification as long as the derivation, then the preview at under 20 s a pass (CoACD's 300 s left out).
    assert tracker.stage("verify")["eta_s"] < 2.0 + TAIL_PASSES["preview"] * 20.0


def test_the_close_up_weighs_on_the_previews_eta() -> None:
    etas = []
    for close_up in (False, True):
        clock = Clock()
        tracker = JobProgress(0, polish=False, verify=True, preview=True, close_up=close_up, clock=clock)
        etas.append(_run(tracker, clock, [_pass(4, attempts=1)])[-1]["eta_s"])  # the preview starts
    # Six seconds a pass (from its first report to the derivation): the close-up adds its share of a pass.
    assert etas[1] - etas[0] == pytest.approx(CLOSE_UP_PASSES * 6.0, abs=0.11)


def test_a_plan_that_does_not_grow_fills_the_bar_in_proportion() -> None:
    clock = Clock()
    tracker = JobProgress(0, polish=False, clock=clock)  # one pass and nothing that may follow
    docs = _run_no_tail(tracker, clock, 4)
    # One pass, then the derivation's share of the bar.
    share = 1.0 / (1.0 + TAIL_PASSES["derive"])
    assert [d["fraction"] for d in docs[1:5]] == [round(share * k / 4, 4) for k in range(1, 5)]
    assert docs[-1]["stage"] == "deriving the result" and docs[-1]["fraction"] == round(share, 4)


def _run_no_tail(tracker: JobProgress, clock: Clock, windows: int) -> list[dict]:
    docs = [tracker.preparing()]
    for p in _pass(windows, attempts=1):
        clock.now += 3.0
        docs.append(tracker.window(p))
    docs.append(tracker.window(RefineProgress(0, 0, float("nan"), 0, 0.0, 0.0, deriving=True)))
    return docs


def test_the_eta_is_the_whole_job_at_its_own_pace() -> None:
    clock = Clock()
    tracker = JobProgress(1, verify=True, preview=True, clock=clock)
    assert tracker.preparing()["eta_s"] is None  # no pace yet
    clock.now += 30.0  # preparing does not count in the pace of the passes
    reports = _pass(10)
    tracker.window(RefineProgress(1, 10, 1.0, 0, 0.0, 0.0, fraction=0.0, attempts=2))  # the pass starts
    for p in reports[:5]:
        clock.now += 2.0
        doc = tracker.window(p)
    # Half a pass in 10 s: 10 s more for this pass, the reserve for a pass that may follow (a polish sweep, a
    # second attempt) and the tail, at 20 s a pass.
    expected = 10.0 + 20.0 * (RESERVE_PER_PASS + sum(TAIL_PASSES.values()))
    assert abs(doc["eta_s"] - expected) < 0.11, doc
    assert doc["elapsed_s"] == 40.0
    # A second attempt starts: its whole pass joins the ETA.
    for p in reports[5:]:
        clock.now += 2.0
        tracker.window(p)
    doc = tracker.window(_pass(10, 2)[0])
    assert doc["eta_s"] > 20.0 * 0.9
    clock.now += 20.0  # the second pass, like the first
    # The derivation's time stands for the verification's, which repeats it.
    tracker.window(RefineProgress(0, 0, float("nan"), 0, 0.0, 0.0, deriving=True))
    clock.now += 3.0
    doc = tracker.stage("verify")
    assert abs(doc["eta_s"] - (3.0 + TAIL_PASSES["preview"] * 20.0)) < 0.11, doc


def test_a_finished_job_shows_done_without_its_last_window() -> None:
    clock = Clock()
    tracker = JobProgress(0, clock=clock)
    _run_no_tail(tracker, clock, 3)
    done = tracker.finished()
    assert (done["fraction"], done["stage"], done["step"], done["eta_s"]) == (1.0, "done", "done", 0.0)
    assert not {"window", "windows", "refine_attempt", "polish_sweep", "best_loss"} & set(done)
    assert done == finished_progress(tracker.window(RefineProgress(0, 0, 0.0, 0, 0.0, 0.0, deriving=True)))


def test_the_heartbeat_keeps_the_queue_attempt_apart_and_drops_an_ended_pass_keys() -> None:
    hb = Heartbeat(lambda progress: False, interval=60.0, base_progress={"worker_id": "w1", "pid": 7, "attempt": 2})
    clock = Clock()
    tracker = JobProgress(2, verify=True, clock=clock)
    hb.update(tracker.preparing())
    hb.update(tracker.window(_pass(3, 3, sweep=2)[0]))
    sent = hb.progress()
    assert sent["attempt"] == 2 and sent["refine_attempt"] == 3 and sent["polish_sweep"] == 2
    hb.update(tracker.stage("verify"))
    sent = hb.progress()
    assert sent["attempt"] == 2 and sent["worker_id"] == "w1" and sent["stage"] == "verifying"
    assert "polish_sweep" not in sent and "window" not in sent and "refine_attempt" not in sent
    hb.update({"stage": "preview"})  # a bare update still merges
    assert hb.progress()["step"] == "verify" and hb.progress()["stage"] == "preview"


def test_the_cli_and_the_demo_client_show_the_stage_and_the_whole_jobs_fraction() -> None:
    from worker.commands.progress import progress_text
    from worker.runtime.demo_client import progress_columns

    clock = Clock()
    tracker = JobProgress(2, clock=clock)
    tracker.window(_pass(4, 1)[3])
    clock.now += 10.0
    doc = tracker.window(_pass(4, 2)[1])
    line = progress_text(doc)
    assert f"{100 * doc['fraction']:3.0f}%  attempt 2 of 3  window 2/4" in line and "ETA" in line
    desc, fraction, info = progress_columns({"state": "RUNNING", "progress": doc})
    assert desc == "running: attempt 2 of 3" and fraction == doc["fraction"] and "window 2/4" in info
    assert progress_columns({"state": "QUEUED", "progress": None}) == ("queued", 0.0, "")


def test_a_long_jobs_later_passes_still_move_the_bar() -> None:
    clock = Clock()
    tracker = JobProgress(3, verify=True, preview=True, clock=clock)
    # Four failed attempts, ten polish sweeps, then the rescue's four attempts: 18 passes nobody planned at first.
    passes = [_pass(5, a, attempts=4) for a in range(1, 5)] + [_pass(5, 4, sweep=s, attempts=4) for s in range(1, 11)]
    passes += [_pass(5, a, rescue=True, attempts=4) for a in range(1, 5)]
    starts = []
    for reports in passes:
        for i, p in enumerate(reports):
            clock.now += 1.0
            doc = tracker.window(p)
            if i == 0:
                starts.append(doc["fraction"])
    assert starts == sorted(starts) and starts[-1] < 0.95
    assert float(np.diff(starts).min()) > 0.002
