"""The states of a job, defined once (DESIGN §2; like procrastinate's ``jobs.Status``).

QUEUED -> RUNNING -> SUCCEEDED | FAILED | CANCELLED; a retryable failure, an expired lease or a graceful
worker shutdown sends a RUNNING job back to QUEUED, and ``retry`` sends a FAILED one back.

The values are the strings stored in ``jobs.state`` (the migration's CHECK constraint names them) and sent
in the API's JSON. ``JobState`` is a ``StrEnum``, so a member *is* its string: it compares equal to
``"QUEUED"``, formats as ``QUEUED`` in messages, and is bound to SQL as that text.
"""

from __future__ import annotations

from enum import StrEnum


class JobState(StrEnum):
    #: Waiting for a worker: new, requeued after a retryable failure or an expired lease, or released.
    QUEUED = "QUEUED"
    #: Claimed by a worker, under a lease it renews by heartbeat.
    RUNNING = "RUNNING"
    #: Done; the result and its summary are stored.
    SUCCEEDED = "SUCCEEDED"
    #: Gave up: a non-retryable error, or the last allowed attempt failed.
    FAILED = "FAILED"
    #: Cancelled by its owner (at once when QUEUED, at the worker's next heartbeat when RUNNING).
    CANCELLED = "CANCELLED"


#: States a job never leaves on its own (only ``retry`` takes a FAILED job back to QUEUED).
FINISHED: frozenset[JobState] = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED})
#: States that count against an API key's limit of active jobs, and that ``delete`` refuses.
ACTIVE: frozenset[JobState] = frozenset({JobState.QUEUED, JobState.RUNNING})
