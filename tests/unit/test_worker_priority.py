"""Workers lower their CPU priority below the API's: every thread of the process, including threads that
existed before and threads started after (run in a child process: the test process keeps its priority)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHILD = textwrap.dedent(
    """
    import os, threading
    from worker.runtime.priority import lower_priority

    base = os.getpriority(os.PRIO_PROCESS, 0)
    ready, done = threading.Event(), threading.Event()
    seen = {}

    def older():
        ready.set()
        done.wait()
        seen["older"] = os.getpriority(os.PRIO_PROCESS, 0)

    t = threading.Thread(target=older)
    t.start()
    ready.wait()
    main = lower_priority(base + 5)
    again = lower_priority(base + 2)  # never lowers the nice value back
    newer = []
    t2 = threading.Thread(target=lambda: newer.append(os.getpriority(os.PRIO_PROCESS, 0)))
    t2.start(); t2.join()
    done.set(); t.join()
    print(base, main, again, seen["older"], newer[0])
    """
)


def test_lower_priority_renices_existing_and_future_threads() -> None:
    out = subprocess.run([sys.executable, "-c", CHILD], cwd=ROOT, capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})  # fmt: skip
    base, main, again, older, newer = map(int, out.stdout.split())
    target = min(base + 5, 19)
    assert (main, again, older, newer) == (target, target, target, target)


THREAD_CHILD = textwrap.dedent(
    """
    import os, threading
    from worker.runtime.priority import lower_this_thread

    base = os.getpriority(os.PRIO_PROCESS, 0)
    seen = []

    def finishing():
        seen.append(lower_this_thread(4))
        child = threading.Thread(target=lambda: seen.append(os.getpriority(os.PRIO_PROCESS, 0)))
        child.start(); child.join()
        seen.append(lower_this_thread(30))  # capped at 19

    t = threading.Thread(target=finishing)
    t.start(); t.join()
    print(base, os.getpriority(os.PRIO_PROCESS, 0), *seen)
    """
)


def test_lower_this_thread_lowers_only_the_caller_and_what_it_starts() -> None:
    out = subprocess.run([sys.executable, "-c", THREAD_CHILD], cwd=ROOT, capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})  # fmt: skip
    base, main, lowered, inherited, capped = map(int, out.stdout.split())
    assert main == base  # the calling process's other threads keep their priority
    assert lowered == inherited == min(base + 4, 19) and capped == 19
