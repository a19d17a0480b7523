"""Verify every result in a folder (issue #54 item 3): find them, check each through ``verify_file``, in parallel.

``verify_file`` is the one place a file meets the verifier (``check_result``: stepwise where the result stores its
states), and it never raises: a file that cannot be read or does not verify becomes a ``FileVerdict`` saying so, so
one bad file does not stop the others. ``verify_files`` runs it over a process pool (each process its own MuJoCo
and NumPy: the checks share nothing) and reports each verdict as it arrives.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Literal

from common.result_format import RESULT_SUFFIX

Status = Literal["passed", "failed", "unreadable"]
STATUSES: tuple[Status, ...] = ("passed", "failed", "unreadable")
#: "right_wrist_pos: ... at frame 12 ...": the field before the first colon, the first frame named after it.
_FIELD = re.compile(r"^([A-Za-z0-9_.\[\]]+):")
_FRAME = re.compile(r"\bframe (\d+)\b")


@dataclass(frozen=True)
class Failure:
    """One failed check: the field it concerns, the frame (when the check names one) and the verifier's text."""

    field: str
    frame: int | None
    message: str

    @classmethod
    def parse(cls, text: str) -> Failure:
        name, at = _FIELD.match(text), _FRAME.search(text)
        return cls(name.group(1) if name else "result", int(at.group(1)) if at else None, text)


@dataclass(frozen=True)
class VerifyOptions:
    """What ``verify_file`` passes on to the verifier (``worker.verification.check_result``)."""

    allow_config: bool = False
    cache_dir: Path | None = None
    mano_dir: Path | None = None


@dataclass
class FileVerdict:
    """What verifying one file found. ``path`` as given (the command makes it relative to the folder)."""

    path: str
    status: Status
    failures: list[Failure] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    frames: int | None = None
    exact: bool | None = None
    max_pos_diff_m: float | None = None
    max_rot_diff_deg: float | None = None
    checked_sha256: str | None = None
    content_sha256: str | None = None
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def find_results(root: Path) -> list[Path]:
    """Every ``*.result.npz`` under ``root`` (recursively; a dataset release keeps them in ``results/``), sorted."""
    return sorted(p for p in root.rglob(f"*{RESULT_SUFFIX}") if p.is_file())


def verify_file(path: Path, options: VerifyOptions = VerifyOptions()) -> FileVerdict:
    """Verify one result file; never raises for a bad file (see the module docstring)."""
    from common.errors import HoiRefineError, UnsupportedFormatError
    from common.result_format import content_digest, read_arrays, read_summary
    from worker.verification.check import check_result

    start = time.perf_counter()
    verdict = FileVerdict(str(path), "unreadable")
    try:
        blob = path.read_bytes()
        read_summary(blob), read_arrays(blob)  # a damaged file fails here, before any simulation
        verdict.content_sha256 = content_digest(blob)
    except (OSError, HoiRefineError, ValueError) as exc:
        verdict.failures.append(Failure("file", None, f"cannot be read: {exc}"))
        verdict.seconds = time.perf_counter() - start
        return verdict
    try:
        report = check_result(blob, None, allow_config=options.allow_config, cache_dir=options.cache_dir,
                              mano_dir=options.mano_dir)
    except UnsupportedFormatError as exc:  # readable, but nothing the verifier can re-derive
        verdict.failures.append(Failure("summary", None, f"not verifiable: {exc}"))
    except HoiRefineError as exc:
        verdict.status = "failed"
        verdict.failures.append(Failure.parse(str(exc)))
    except Exception as exc:  # a forged file can break an assumption of the checker: it does not verify
        verdict.status = "failed"
        verdict.failures.append(Failure("result", None, f"the check stopped: {type(exc).__name__}: {exc}"))
    else:
        verdict.status = "failed" if report.failures or (report.config_changes and not options.allow_config) \
            else "passed"
        verdict.failures = [Failure.parse(f) for f in report.failures]
        verdict.failures += [Failure("config", None, f"non-default physics config {name}: {stored!r} (default "
                                     f"{default!r})") for name, default, stored in report.config_changes
                             if not options.allow_config]
        verdict.notes = list(report.config_notes)
        verdict.frames, verdict.exact, verdict.checked_sha256 = report.frames, report.exact, report.digest
        verdict.max_pos_diff_m, verdict.max_rot_diff_deg = report.max_pos_diff_m, report.max_rot_diff_deg
    verdict.seconds = time.perf_counter() - start
    return verdict


#: Result bytes worth one more process: a spawned checker spends seconds importing NumPy, SciPy, MuJoCo and the
#: worker before its first file, about what checking 2 MB of results takes (a 72-frame dev result, 450 KB: ~2 s).
#: Measured on 2 cores: three 12-frame results (220 KB) took 1.4 s in one process and 10 s on two.
BYTES_PER_PROCESS = 2 * 2**20


def default_jobs(paths: Sequence[Path] = ()) -> int:
    """The processes ``verify DIR`` uses unless told: one per ``BYTES_PER_PROCESS`` of result files, at most the cores
    this process may run on, at least one (in this process: a handful of small results never pay for a pool)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if not paths:
        return cores
    size = sum(Path(p).stat().st_size for p in paths if Path(p).exists())
    return max(1, min(cores, len(paths), size // BYTES_PER_PROCESS))


def verify_files(
    paths: Sequence[Path], options: VerifyOptions = VerifyOptions(), jobs: int = 1,
    on_done: Callable[[FileVerdict], None] | None = None,
) -> list[FileVerdict]:
    """``verify_file`` over ``paths`` on ``jobs`` processes (1: in this one); verdicts in the order of ``paths``.
    ``on_done`` sees each verdict when it is ready (a progress bar)."""
    verdicts: dict[Path, FileVerdict] = {}

    def done(path: Path, verdict: FileVerdict) -> None:
        verdicts[path] = verdict
        if on_done is not None:
            on_done(verdict)

    if jobs <= 1 or len(paths) <= 1:
        for path in paths:
            done(path, verify_file(path, options))
    else:
        # Spawned, not forked: the caller may run threads (a progress bar) that a fork would copy mid-lock.
        with ProcessPoolExecutor(max_workers=min(jobs, len(paths)), mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(verify_file, path, options): path for path in paths}
            for future in as_completed(futures):
                path = futures[future]
                try:
                    verdict = future.result()
                except Exception as exc:  # the checking process died (e.g. killed for memory): this file failed
                    verdict = FileVerdict(str(path), "failed",
                                          [Failure("result", None, f"the check stopped: {type(exc).__name__}: {exc}")])
                done(path, verdict)
    return [verdicts[p] for p in paths]
