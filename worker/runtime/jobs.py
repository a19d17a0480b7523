"""Job functions a worker can run: the refinement, and a physics-free self-test job.

A job function takes (payload bytes, options, progress, should_stop) and returns (result bytes,
summary); see ``worker.runtime.loop.JobFunction``. The refinement keeps one evaluator (a pool of C
MjData) per actor where the refinement allows it, so consecutive jobs reuse the threads and buffers.

The self-test job exercises the runtime (claim, heartbeat, cancel, crash recovery) in seconds without
MuJoCo: it "optimises" for ``max_generations`` generations of ``selftest_generation_seconds`` each and
returns a small deterministic NPZ derived from the payload and seed.
"""

from __future__ import annotations

import hashlib
import io
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import ConfigurationError, JobCancelledError
from common.job_options import JobOptions
from common.queue_types import Artifact
from worker.runtime.loop import ArtifactFn, JobFunction, ProgressFn, StopFn

#: Seconds per self-test "generation" (environment, so tests can set it for Ray actors too).
SELFTEST_GENERATION_ENV = "HOI_REFINE_SELFTEST_GENERATION_SECONDS"


def _progress_dict(value: Any) -> dict[str, Any]:
    """The refinement's progress record as a JSON-ready dict (it may be a dataclass or a dict)."""
    if isinstance(value, dict):
        raw = value
    elif hasattr(value, "to_dict"):
        raw = value.to_dict()
    elif hasattr(value, "__dataclass_fields__"):
        from dataclasses import asdict

        raw = asdict(value)
    else:
        raw = {"detail": str(value)}
    out: dict[str, Any] = {}
    for key, item in raw.items():
        if isinstance(item, np.generic):
            item = item.item()
        if item is None or isinstance(item, bool | int | float | str):
            out[str(key)] = item
    return out


class RefineJob:
    """Runs ``worker.refine.run.refine_sequence`` on a native-NPZ payload with ``threads`` threads.

    The evaluator (C MjData plus MuJoCo's rollout thread pool) is made by the first job and reused by the
    next ones: ``ensure_model`` re-makes only the MjData, because each sequence compiles its own model.
    """

    def __init__(self, threads: int) -> None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.threads = threads
        self._evaluator: Any = None

    def __call__(
        self, payload: bytes, options: JobOptions, progress: ProgressFn, should_stop: StopFn
    ) -> tuple[bytes, dict[str, Any]]:
        import mujoco

        from common.sequence_io import sequence_from_npz_bytes
        from common.settings import get_settings
        from worker.refine.evaluator import ParallelEvaluator
        from worker.refine.job_progress import JobProgress
        from worker.refine.run import refine_sequence

        # One document over the whole job (``common.progress``): the refinement's passes, then the derivation,
        # the verification below and the preview the worker loop draws after this function.
        tracker = JobProgress(options.restarts, options.polish, verify=True, preview=options.preview_video,
                              close_up=options.preview_video and options.preview_close_up)
        progress(tracker.preparing())
        seq = sequence_from_npz_bytes(payload)
        if self._evaluator is None:
            # Placeholder model: refine_sequence swaps in each job's own compiled scene (ensure_model).
            self._evaluator = ParallelEvaluator(mujoco.MjModel.from_xml_string("<mujoco/>"), self.threads)
        outcome = refine_sequence(
            seq,
            options,
            threads=self.threads,
            progress=lambda p: progress(_progress_dict(tracker.window(p))),
            should_stop=should_stop,
            evaluator=self._evaluator,
            cache_dir=get_settings().resolved_cache_dir(),
            mano_dir=get_settings().mano_dir,
        )
        blob = outcome.to_npz_bytes()
        summary = dict(outcome.summary)
        progress(tracker.stage("verify"))
        proof = verification(blob, cache_dir=get_settings().resolved_cache_dir(), mano_dir=get_settings().mano_dir,
                             threads=self.threads)
        summary["metrics"] = {**summary["metrics"], "verification": proof}
        if options.preview_video:  # the worker loop draws it next (``refine_preview``)
            progress(tracker.stage("preview"))
        return blob, summary


def verification(
    blob: bytes, cache_dir: Path | None = None, mano_dir: Path | None = None, threads: int = 1
) -> dict[str, Any]:
    """``verify`` on the finished result from a fresh replay, before it is stored (issue #15 item 2): the job's
    metrics then say whether it reproduced, and carry the digests a downloaded copy can be checked against
    (``hoi-refine verify`` prints both). A result that does not verify is still stored, flagged and explained.
    """
    from common.result_format import content_digest
    from worker.verification import check_result

    report = check_result(blob, cache_dir=cache_dir, mano_dir=mano_dir, threads=threads)
    return {
        "verified": not report.failures,
        "method": report.method,
        "exact": report.exact,
        "max_object_deviation_m": report.max_pos_diff_m,
        "checked_fields": len(report.checked),
        "checked_sha256": report.digest,
        "content_sha256": content_digest(blob),
        "failures": report.failures[:20],
    }


class SelfTestJob:
    """Physics-free job for runtime tests; honours ``should_stop`` once per generation like the refinement."""

    def __init__(self, threads: int = 1) -> None:
        self.threads = threads

    def __call__(
        self, payload: bytes, options: JobOptions, progress: ProgressFn, should_stop: StopFn
    ) -> tuple[bytes, dict[str, Any]]:
        generations = options.max_generations or 5
        seconds = float(os.environ.get(SELFTEST_GENERATION_ENV, "0.2"))
        digest = hashlib.sha256(payload + options.seed.to_bytes(4, "little")).digest()
        t0 = time.monotonic()
        for gen in range(generations):
            if should_stop():
                raise JobCancelledError(f"stopped at generation {gen}")
            time.sleep(seconds)
            progress({"window": 1, "windows": 1, "generation": gen + 1, "evaluations": (gen + 1) * 8})
        values = np.frombuffer(digest, dtype=np.uint8).astype(np.float64)
        buf = io.BytesIO()
        np.savez(buf, values=values)
        summary = {"kind": "selftest", "generations": generations, "wall_s": time.monotonic() - t0}
        return buf.getvalue(), summary


def refine_preview(result: bytes, options: JobOptions) -> list[Artifact]:
    """The preview stored with a refinement's result (``worker.visual.preview``), unless ``preview_video`` is off;
    with ``preview_close_up`` also the close-up video."""
    if not options.preview_video:
        return []
    from common.settings import get_settings
    from worker.visual.preview import preview_artifacts

    settings = get_settings()
    made = preview_artifacts(result, close_up=options.preview_close_up, cache_dir=settings.resolved_cache_dir(),
                             mano_dir=settings.mano_dir)
    return [Artifact(a.name, a.content_type, a.data, len(a.data)) for a in made]


def make_artifact_function(kind: str) -> ArtifactFn | None:
    """What a worker of ``kind`` stores beside a result: the refinement's preview; nothing for the self-test."""
    return refine_preview if kind == "refine" else None


def make_job_function(kind: str, threads: int) -> JobFunction:
    if kind == "refine":
        return RefineJob(threads)
    if kind == "selftest":
        return SelfTestJob(threads)
    raise ConfigurationError(f"unknown worker job kind {kind!r} (expected 'refine' or 'selftest')")
