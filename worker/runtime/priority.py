"""Run the physics at a lower CPU priority than the API (issue #20 item 3).

On one machine (``hoi-refine up``) the workers' MuJoCo threads would otherwise take the cores from the
API's status polls: p50 546 ms at 200 polls/s in the old bench/results/api_load.md. A worker process raises
its nice value (``HOI_REFINE_WORKER_NICE``, default 10) so the scheduler serves the API first and gives the
physics everything left over; throughput of the physics is unchanged when the API is idle.

Linux keeps the nice value per thread (``setpriority(PRIO_PROCESS, tid)``), and a new thread inherits its
creator's, so every thread that exists now is lowered, and threads started later (the MuJoCo pool, the
heartbeat) inherit it from the thread that starts them.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

log = logging.getLogger(__name__)


def lower_priority(niceness: int) -> int:
    """Raise every thread of this process to at least ``niceness`` (never lower it); returns the nice value
    of the calling thread afterwards. 0 leaves everything as it is."""
    if niceness <= 0:
        return os.getpriority(os.PRIO_PROCESS, 0)
    tasks = Path("/proc/self/task")
    tids = [int(p.name) for p in tasks.iterdir()] if tasks.is_dir() else [0]
    for tid in tids:
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) < niceness:
                os.setpriority(os.PRIO_PROCESS, tid, niceness)
        except (ProcessLookupError, PermissionError) as exc:  # a thread that just ended; a capped limit
            log.debug("could not renice thread %d: %s", tid, exc)
    return os.getpriority(os.PRIO_PROCESS, 0)


def lower_this_thread(by: int) -> int:
    """Raise the calling thread's nice value by ``by`` (capped at 19; threads it starts later inherit it);
    returns the nice value afterwards. Lowering a thread's priority needs no privilege."""
    tid = threading.get_native_id()
    now = os.getpriority(os.PRIO_PROCESS, tid)
    if by > 0 and now < 19:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, now + by))
    return os.getpriority(os.PRIO_PROCESS, tid)
