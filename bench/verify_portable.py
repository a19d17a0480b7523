"""Stepwise verification off-host (issue #54 item 2): honest results pass with other NumPy / OpenBLAS kernels forced,
forgeries fail there naming field and frame, and what storing the states costs.

    .venv/bin/python bench/verify_portable.py --results DIR [--make 8] [--forge NAME.npz]

``--make N`` first refines every k-th sequence of the dev120 sample (N of them; ``--names FILE``: these instead)
into DIR with a cheap budget (``--max-generations 2 --restarts 0``) or, ``--budget full``, the product's default
budget (restarts, polish, rescue), one thread each, plus the built-in hinged box (``HINGED_BOX``; results that
exist are kept). Then every result in DIR is verified in a
subprocess under each kernel set of ``KERNELS`` (this build's own, NumPy without AVX-512 + OpenBLAS Haswell: what
an AVX2 host runs, and NumPy's baseline + OpenBLAS Nehalem: an SSE-only host's kernels), recording the largest
stepwise deviation per state field, the whole-rollout drift, and the time of the stepwise check against the full
re-simulation. ``--forge`` (default: the first result) builds the forgeries of ``tests/integration`` and the new
ones and verifies each under the AVX2 kernels (and in the container). Prints the tables and writes
``bench/results/verify_portable.md``.

``--container IMAGE`` adds the kernel set "container": each ``--one`` subprocess runs inside the project's image
(``docker run --network host``, the results folder mounted read-only at /data, this bench folder over the image's
/app/bench, so the harness is this one and the code under test the image's own). The image's ``worker`` and
``common`` must be this tree's: their digests (``code_digest``) are compared first and named in the report.
``--cache DIR`` keeps each verification's figures (keyed by the result file, the kernel set and the code's digest),
so a later run redoes only what changed; ``--rows-only`` fills it and stops.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import io
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.provenance import KERNELS  # noqa: E402

FIELDS = ("qpos", "qvel", "qacc_warmstart", "ctrl", "mocap_pos", "mocap_quat")
#: ``--make``'s refinement options per budget (``hoi-refine refine`` arguments; the hinged box's as job options).
BUDGETS: dict[str, list[str]] = {"cheap": ["--max-generations", "2", "--restarts", "0"], "full": []}
HINGED_BOX_OPTIONS: dict[str, dict[str, Any]] = {"cheap": {"popsize": 4, "max_generations": 1}, "full": {}}
HINGED_BOX = "zz_hinged_box_example.npz"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--results", type=Path, required=True, help="folder of refinement results (made by --make)")
    p.add_argument("--make", type=int, default=0, help="refine this many dev120 sequences into --results first")
    p.add_argument("--budget", choices=tuple(BUDGETS), default="cheap",
                   help="--make's refinement budget: cheap (2 generations, no restarts) or full (the product's "
                        "defaults)")
    p.add_argument("--make-only", action="store_true", help="--make, then stop (no verification)")
    p.add_argument("--names", type=Path, default=None,
                   help="--make: refine these dev120 sequences (one file name a line) instead of every k-th")
    p.add_argument("--forge", type=Path, default=None, help="the result the forgeries start from (default: first)")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "verify_portable.md")
    p.add_argument("--note", action="append", default=[], help="a paragraph for the report (how the sample was made)")
    p.add_argument("--one", type=Path, default=None, help=argparse.SUPPRESS)  # subprocess: verify one, print JSON
    p.add_argument("--old-way", action="store_true", help=argparse.SUPPRESS)  # --one without the stored states
    p.add_argument("--substeps", type=Path, nargs=2, default=None, help=argparse.SUPPRESS)  # subprocess: RESULT STATES
    p.add_argument("--hinged-box", type=Path, default=None, help=argparse.SUPPRESS)  # subprocess: make it there
    p.add_argument("--code-digest", action="store_true", help=argparse.SUPPRESS)  # print code_digest() and stop
    p.add_argument("--container", default=None, metavar="IMAGE",
                   help="also verify every result and forgery inside this image (the 'container' kernel set)")
    p.add_argument("--cache", type=Path, default=None, help="keep each verification's figures here and reuse them")
    p.add_argument("--rows-only", action="store_true", help="verify the results (into --cache), no report")
    p.add_argument("--skip-old-way", action="store_true", help="leave out the old-way verification of each file")
    p.add_argument("--add-presettle", action="store_true",
                   help="first add presettle_state_sim to the results in --results made before it was stored "
                   "(computed on this build from each result's own preparation; a refinement made since gives the "
                   "same file with that array)")
    return p.parse_args(argv)


# ------------------------------------------------------------------------------------------- one verification


def verify_one(path: Path, old_way: bool = False) -> dict[str, Any]:
    """``check_result`` of one file with the full re-simulation timed apart; the figures as JSON. ``old_way``: the
    file without its stored states (as an older result: whole re-simulation within the cross-host tolerances)."""
    import worker.verification.check as check
    from common.cpu_kind import numpy_simd
    from common.result_format import STEPWISE_KEYS, read_arrays, read_summary, write_result_npz

    blob = path.read_bytes()
    if old_way:
        arrays = {k: v for k, v in read_arrays(blob).items() if k not in STEPWISE_KEYS}
        blob = write_result_npz(arrays, read_summary(blob))

    timed: dict[str, float] = {}
    derive = check.derive_result

    def timed_derive(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        out = derive(*args, **kwargs)
        timed["derive_s"] = time.perf_counter() - t0
        return out

    check.derive_result = timed_derive
    import worker.refine.derive as derive_module

    prepare = derive_module.prepare

    def timed_prepare(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        out = prepare(*args, **kwargs)
        timed["prepare_s"] = timed.get("prepare_s", 0.0) + time.perf_counter() - t0
        return out

    derive_module.prepare = timed_prepare
    t0 = time.perf_counter()
    report = check.check_result(blob)
    total = time.perf_counter() - t0
    return {
        "verified": report.verified, "method": report.method, "failures": report.failures[:6],
        "drift_m": report.max_pos_diff_m, "drift_deg": report.max_rot_diff_deg, "exact_rollout": report.exact,
        "stepwise": {k: r.to_dict() for k, r in report.stepwise.items()}, "total_s": total,
        "derive_s": timed.get("derive_s", float("nan")), "prepare_s": timed.get("prepare_s", float("nan")),
        "simd": numpy_simd(), "frames": report.frames, "code": code_digest(), "notes": report.config_notes[-8:],
    }


def code_files() -> dict[str, str]:
    """SHA-256 of each file of the ``worker`` and ``common`` packages this process imports (compiled files left
    out), by its path in the package: the code that verifies."""
    import common
    import worker

    out = {}
    for package in (common, worker):
        base = Path(str(package.__file__)).resolve().parent
        for f in sorted(base.rglob("*")):
            if f.is_file() and "__pycache__" not in f.parts and f.suffix != ".pyc":
                out[f"{package.__name__}/{f.relative_to(base).as_posix()}"] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def code_digest(files: dict[str, str] | None = None) -> str:
    """One SHA-256 over ``code_files``."""
    return hashlib.sha256(json.dumps(files or code_files(), sort_keys=True).encode()).hexdigest()


#: The image of the "container" kernel set (``--container``), and its code's digest as checked.
CONTAINER: dict[str, str] = {}
#: ``code_digest`` of this tree (``main``).
HOST_CODE = ""
CONTAINER_ROOT = "/app"


def docker_command(image: str, args: list[str], mounts: dict[Path, str]) -> list[str]:
    """``docker run`` of this script inside ``image`` with ``args``: host networking, ``mounts`` (host folder ->
    container path) read-only, this bench folder over the image's, as the image's user."""
    volumes = [f"{ROOT / 'bench'}:{CONTAINER_ROOT}/bench:ro", *(f"{h.resolve()}:{c}:ro" for h, c in mounts.items())]
    return ["docker", "run", "--rm", "--network", "host", *(x for v in volumes for x in ("-v", v)),
            "-w", CONTAINER_ROOT, image, "python", f"{CONTAINER_ROOT}/bench/verify_portable.py", *args]


def container_code(image: str) -> dict[str, str]:
    """``code_files`` of the image's own ``worker`` and ``common`` (the installed copy its verifier imports)."""
    run = subprocess.run(docker_command(image, ["--results", "/tmp", "--code-digest"], {}), capture_output=True,
                         text=True, timeout=600)
    if run.returncode != 0:
        raise RuntimeError(f"{image}: {(run.stdout + run.stderr)[-1000:]}")
    return dict(json.loads(run.stdout.strip().splitlines()[-1]))


def run_one(path: Path, kernel: str, old_way: bool = False, cache: Path | None = None) -> dict[str, Any]:
    """``verify_one`` of ``path`` in a subprocess with kernel set ``kernel`` (``KERNELS`` or "container");
    ``cache``: a folder of earlier figures, reused when the file, the kernel set and the code are the same."""
    code = CONTAINER["code"] if kernel == "container" else HOST_CODE
    key = hashlib.sha256(path.read_bytes()).hexdigest()[:24] + f"-{kernel}-{int(old_way)}-{code[:16]}"
    hit = None if cache is None else cache / f"{path.stem}-{key}.json"
    if hit is not None and hit.exists():
        return dict(json.loads(hit.read_text()))
    flags = ["--one", *(["--old-way"] if old_way else [])]
    if kernel == "container":
        cmd = docker_command(CONTAINER["image"], ["--results", "/data", *flags[:1], f"/data/{path.name}", *flags[1:]],
                             {path.parent: "/data"})
        env = dict(os.environ)
    else:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--results", str(path.parent), flags[0], str(path),
               *flags[1:]]
        env = {**os.environ, **KERNELS[kernel], "PYTHONPATH": str(ROOT)}
    run = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=1800)
    if run.returncode != 0:
        return {"verified": False, "error": (run.stdout + run.stderr)[-2000:]}
    out = dict(json.loads(run.stdout.strip().splitlines()[-1]))
    if hit is not None:
        hit.parent.mkdir(parents=True, exist_ok=True)
        hit.write_text(json.dumps(out))
    return out


# ------------------------------------------------------------------------------------- frames or control steps


def _refined_controls(path: Path) -> tuple[Any, np.ndarray]:
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import settled_start
    from worker.refine.replay import window_problem
    from worker.refine.result import prepare_from_result

    prep, keyframes = prepare_from_result(path.read_bytes())
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        control, _ = window_problem(prep, ev, start, {}).build_control(keyframes, 0, prep.num_frames - 1)
    return prep, control[0]


def substep_states(path: Path) -> np.ndarray:
    """The refined replay's integration state after every physics step (row 0: the start), on this build."""
    import mujoco

    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import settled_start
    from worker.refine.replay import INTEGRATION_STATE, frame_states, replay
    from worker.refine.result import prepare_from_result

    prep, keyframes = prepare_from_result(path.read_bytes())
    model = prep.layout.model
    n = (prep.num_frames - 1) * prep.layout.substeps + 1
    states = np.zeros((n + 1, mujoco.mj_stateSize(model, INTEGRATION_STATE)))

    def keep(i: int, d: Any) -> None:
        mujoco.mj_getState(model, d, states[i + 1], INTEGRATION_STATE)

    with ParallelEvaluator(model, 1) as ev:
        start, _ = settled_start(prep, ev)
        states[0] = frame_states(prep, start, 1)[0]
        replay(prep, ev, start, keyframes, record_contacts=False, on_step=keep)
    return states


def steps_against_frames(path: Path, states_file: Path) -> dict[str, float]:
    """On this process's kernels: the largest deviation of one physics step, and of one frame's steps, each from
    the stored state (``substep_states`` of the original build) — whether frames are too coarse."""
    import mujoco

    from worker.refine.evaluator import CONTROL_SPEC
    from worker.refine.replay import INTEGRATION_STATE
    from worker.verification.stepwise import StateLayout

    states = np.load(states_file)
    prep, control = _refined_controls(path)
    model, spf = prep.layout.model, prep.layout.substeps
    layout, data = StateLayout(model), mujoco.MjData(model)
    worst = {"step_qpos": 0.0, "step_qvel": 0.0, "frame_qpos": 0.0, "frame_qvel": 0.0}
    for i in range(len(control)):
        mujoco.mj_setState(model, data, states[i], INTEGRATION_STATE)
        mujoco.mj_setState(model, data, control[i], CONTROL_SPEC)
        mujoco.mj_step(model, data)
        reached = np.zeros(layout.size)
        mujoco.mj_getState(model, data, reached, INTEGRATION_STATE)
        d = layout.differences(states[i + 1], reached)
        worst["step_qpos"] = max(worst["step_qpos"], float(d["qpos"].max()))
        worst["step_qvel"] = max(worst["step_qvel"], float(d["qvel"].max()))
    for f in range(0, len(control) - spf, spf):
        mujoco.mj_setState(model, data, states[f], INTEGRATION_STATE)
        for i in range(f, f + spf):
            mujoco.mj_setState(model, data, control[i], CONTROL_SPEC)
            mujoco.mj_step(model, data)
        reached = np.zeros(layout.size)
        mujoco.mj_getState(model, data, reached, INTEGRATION_STATE)
        d = layout.differences(states[f + spf], reached)
        worst["frame_qpos"] = max(worst["frame_qpos"], float(d["qpos"].max()))
        worst["frame_qvel"] = max(worst["frame_qvel"], float(d["qvel"].max()))
    return {**worst, "substeps_per_frame": float(spf)}


def steps_table(files: list[Path]) -> list[str]:
    out = ["## Frames or control steps?", "",
           "The refined replay's state after every physics step recorded on this build; then, with other kernels "
           "forced, each step from its stored state and each frame's steps from the frame's stored state (largest "
           "per-dof deviation, m or rad / m/s or rad/s). Where a frame's steps stay at the last bits as one step "
           "does, frames suffice and storing every step would multiply the size by the substeps per frame.", "",
           "| result | kernels | substeps / frame | one step: qpos | qvel | one frame: qpos | qvel |",
           "|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        for path in files:
            states_file = Path(tmp) / "states.npy"
            np.save(states_file, substep_states(path))
            for kernel in ("original", "avx2", "sse"):
                env = {**os.environ, **KERNELS[kernel], "PYTHONPATH": str(ROOT)}
                run = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--results", str(path.parent),
                                      "--substeps", str(path), str(states_file)], env=env, cwd=ROOT,
                                     capture_output=True, text=True, timeout=1800)
                if run.returncode != 0:
                    out.append(f"| {path.stem} | {kernel} | error: {(run.stderr or run.stdout)[-200:]} | | | | |")
                    continue
                r = json.loads(run.stdout.strip().splitlines()[-1])
                out.append(f"| {path.stem} | {kernel} | {r['substeps_per_frame']:.0f} | {r['step_qpos']:.2g} | "
                           f"{r['step_qvel']:.2g} | {r['frame_qpos']:.2g} | {r['frame_qvel']:.2g} |")
                print(out[-1], flush=True)
    return out


# ------------------------------------------------------------------------------------------------- results


def make_results(folder: Path, count: int, budget: str = "cheap", names_file: Path | None = None) -> None:
    """Refine the sample into ``folder`` (see the module docstring), each sequence in its own process."""
    folder.mkdir(parents=True, exist_ok=True)
    if names_file is not None:
        names = [n for n in names_file.read_text().split() if n.endswith(".npz")][:count]
    else:
        every = [n for n in (ROOT / "bench" / "samples" / "dev120.txt").read_text().split() if n.endswith(".npz")]
        names = every[:: max(1, len(every) // count)][:count]
    data = ROOT.parent / "shared" / "data" / "dexycb" / "dev"
    for name in [HINGED_BOX, *names]:  # the articulated one first: the sample may be cut short
        out = folder / name
        if out.exists():
            continue
        tmp = folder / f"{name}.tmp"
        t0 = time.perf_counter()
        if name == HINGED_BOX:
            subprocess.run([sys.executable, str(Path(__file__).resolve()), "--results", str(folder), "--budget",
                            budget, "--hinged-box", str(tmp)], cwd=ROOT, check=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
        else:
            subprocess.run([sys.executable, "-m", "common.cli", "refine", str(data / name), "--out", str(tmp),
                            *BUDGETS[budget], "--no-wall-clock", "--quiet", "--threads", "1"],
                           cwd=ROOT, check=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True)
        tmp.rename(out)
        print(f"refined {name} ({budget} budget) in {time.perf_counter() - t0:.0f} s", flush=True)


def make_hinged_box(out: Path, budget: str) -> None:
    """The built-in hinged box (``worker.example.hinged_box``: two hands, a lid on a hinge) refined into ``out``."""
    from common.job_options import JobOptions
    from worker.example.hinged_box import hinged_box_sequence, short_hinged_box_sequence
    from worker.refine.run import refine_sequence

    seq = hinged_box_sequence() if budget == "full" else short_hinged_box_sequence()
    outcome = refine_sequence(seq, JobOptions(**HINGED_BOX_OPTIONS[budget]), threads=1)
    out.write_bytes(outcome.to_npz_bytes(wall_clock=False))


def add_presettle(path: Path) -> bool:
    """Add the pre-settle state to a result made before results stored it (``--add-presettle``); False if it has
    one."""
    from common.result_format import PRESETTLE_STATE_KEY, read_arrays, read_summary, write_result_npz
    from worker.refine.prepare import presettle_state
    from worker.refine.result import prepare_from_result

    blob = path.read_bytes()
    arrays = read_arrays(blob)
    if PRESETTLE_STATE_KEY in arrays:
        return False
    prep = prepare_from_result(blob)[0]
    tmp = path.with_suffix(".presettle.tmp")
    tmp.write_bytes(write_result_npz({**arrays, PRESETTLE_STATE_KEY: presettle_state(prep)}, read_summary(blob),
                                     wall_clock=False))
    tmp.rename(path)
    return True


def state_sizes(path: Path) -> dict[str, Any]:
    """Bytes the stored states and inputs take: per frame (uncompressed) and per sequence (as stored, compressed)."""
    blob = path.read_bytes()
    with zipfile.ZipFile(io.BytesIO(blob)) as zf:
        info = {i.filename: i for i in zf.infolist()}
    from common.result_format import STEPWISE_KEYS, read_arrays

    arrays = read_arrays(blob)
    states = arrays["state_sim"]
    frames = int(states.shape[0])
    controls = arrays.get("control_sim")
    ncontrol = 0 if controls is None else int(controls.shape[1])
    steps_per_frame = 0 if controls is None else (len(controls) - 1) // max(frames - 1, 1)
    members = [k for k in STEPWISE_KEYS if f"{k}.npy" in info]
    stored = sum(info[f"{k}.npy"].compress_size for k in members)
    raw = sum(info[f"{k}.npy"].file_size for k in members)
    return {"frames": frames, "nstate": int(states.shape[1]), "ncontrol": ncontrol,
            "per_frame": 8 * (int(states.shape[1]) + steps_per_frame * ncontrol),
            "stored": stored, "uncompressed": raw, "result": len(blob)}


# ----------------------------------------------------------------------------------------------- forgeries


def forgeries(path: Path, folder: Path) -> list[tuple[str, str, Path]]:
    """(name, what it changes, file) of every forgery of ``path``; ``folder`` receives the files."""
    from common.job_options import JobOptions
    from common.result_format import read_arrays, read_summary, write_result_npz
    from worker.refine.derive import add_attempt_metrics, attempt_figures, derive_result
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import settled_start
    from worker.refine.replay import replay
    from worker.refine.result import prepare_from_result
    from worker.simulation.config import SimConfig
    from worker.simulation.metrics import scalar_metrics
    from worker.verification.stepwise import StateLayout

    blob = path.read_bytes()
    arrays, summary = read_arrays(blob), read_summary(blob)
    prep, keyframes = prepare_from_result(blob)
    side = next(iter(prep.spaces))
    layout = StateLayout(prep.layout.model)
    qpos0, obj = layout.slices["qpos"].start, prep.scene.object_qpos_adr
    out: list[tuple[str, str, Path]] = []

    def add(name: str, what: str, a: dict[str, np.ndarray], s: dict[str, Any]) -> None:
        file = folder / f"{name}.npz"
        file.write_bytes(write_result_npz(a, s, wall_clock=False))
        out.append((name, what, file))

    refined = summary["metrics"]["refined"]
    # The forgeries of tests/integration/test_verify_forgeries.py.
    add("summary_E_t", "metrics.refined.E_t rewritten to 0.01 cm",
        arrays, {**summary, "metrics": {**summary["metrics"], "refined": {**refined, "E_t": 0.01}}})
    hold = summary["object_hold"]
    add("object_hold", "object_hold.release_frame + 5", arrays,
        {**summary, "object_hold": {**hold, "release_frame": hold["release_frame"] + 5}})
    add("per_frame_metrics", "metrics_refined_e_t_cm zeroed",
        {**arrays, "metrics_refined_e_t_cm": np.zeros_like(arrays["metrics_refined_e_t_cm"])}, summary)
    add("keypoints", f"{side}_keypoints_sim replaced by the reference",
        {**arrays, f"{side}_keypoints_sim": arrays[f"{side}_keypoints_ref"].copy()}, summary)
    wrist = arrays[f"{side}_wrist_pos"].copy()
    wrist[:, 2] += 0.05
    add("wrist_5cm", f"{side}_wrist_pos raised 5 cm", {**arrays, f"{side}_wrist_pos": wrist}, summary)
    add("reference", "object_pose_ref replaced by the simulated trajectory",
        {**arrays, "object_pose_ref": arrays["object_pose_sim"].copy()}, summary)
    add("forces_x10", "contact_force x 10", {**arrays, "contact_force": arrays["contact_force"] * 10}, summary)
    moved = arrays["object_pose_sim"].copy()
    moved[20, 0] += 0.002
    add("trajectory_2mm_frame20", "object_pose_sim moved 2 mm at frame 20 (states untouched)",
        {**arrays, "object_pose_sim": moved}, summary)
    options = JobOptions.model_validate(summary["options"])
    stored: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in summary["config"]["sim"].items()}
    sticky = SimConfig(**{**stored, "hand_friction": (3.0, 0.02, 0.001), "object_friction": 3.0})
    derived = derive_result(arrays["sequence_npz"].tobytes(), options, sticky, summary["config"]["rotation_pivot"],
                            keyframes)
    metrics = {k: scalar_metrics(v) for k, v in derived.metrics.items()}
    add_attempt_metrics(metrics["refined"], [{**attempt_figures(derived.metrics["refined"])}])
    sim = {**summary["config"]["sim"], "hand_friction": [3.0, 0.02, 0.001], "object_friction": 3.0}
    add("friction_3", "friction 3.0 and the whole result re-derived under it",
        {**arrays, **derived.arrays}, {**summary, "metrics": metrics, "config": {**summary["config"], "sim": sim},
                                       "attempts": summary["attempts"][:1],
                                       "num_contacts": len(derived.final.contacts["contact_frame"])})

    add_table_forgery(add, arrays, summary, prep, keyframes)

    # New: forged states.
    states = arrays["state_sim"].copy()
    pose = arrays["object_pose_sim"].copy()
    states[12, qpos0 + obj] += 0.05
    pose[12, 0] += 0.05
    add("teleport_5cm", "object moved 5 cm at frame 12 in its state and trajectory",
        {**arrays, "state_sim": states, "object_pose_sim": pose}, summary)
    states = arrays["state_sim"].copy()
    body = prep.scene.object_body_id
    states[8:, layout.slices["xfrc_applied"].start + 6 * body + 2] = 0.5
    add("force_stored", "0.5 N upwards on the object (xfrc_applied) from frame 8", {**arrays, "state_sim": states},
        summary)
    spf = prep.layout.substeps

    def push(i: int, d: Any) -> None:
        d.xfrc_applied[body, 2] = 2.0 if 10 * spf - 1 <= i < 12 * spf - 1 else 0.0

    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        rec = replay(prep, ev, start, keyframes, on_step=push, record_states=True)
    assert rec.states is not None
    hidden = rec.states.copy()
    hidden[:, layout.slices["xfrc_applied"]] = 0.0
    add("force_hidden", "simulated with a 2 N push during frames 10-11, the force zeroed in the stored states",
        {**arrays, "state_sim": hidden, "object_pose_sim": rec.object_pose}, summary)
    states = arrays["state_sim"].copy()
    states[15, qpos0 + int(prep.scene.hands[side].qpos_adr[5])] += 0.05
    add("hand_off_controls", "a finger bent 0.05 rad off its controls at frame 15", {**arrays, "state_sim": states},
        summary)
    add_shift(add, arrays, summary, prep, keyframes, layout)
    add_input_forgeries(add, arrays, summary, prep, keyframes)
    return out


def add_input_forgeries(add: Any, arrays: dict[str, np.ndarray], summary: dict[str, Any], prep: Any,
                        keyframes: dict[str, np.ndarray]) -> None:
    """Forged inputs: a stored servo target the keyframes do not give; and the forger's better try, the refined
    replay simulated under inputs pushed off the keyframes' (a finger's target and the wrist's height over frames
    10-20) with every array stored from that simulation, so states and inputs agree with each other."""
    from worker.refine.derive import build_arrays, replay_metrics
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import settled_start
    from worker.refine.replay import replay
    from worker.verification.stepwise import StateLayout

    side = next(iter(prep.spaces))
    model, spf = prep.layout.model, prep.layout.substeps
    hand = prep.scene.hands[side]
    actuator = int(hand.actuator_ids[2])
    controls = arrays["control_sim"].copy()
    controls[13 * spf + 3 :, actuator] += 0.05
    add("inputs_stored_off", "control_sim: a servo target +0.05 rad from frame 13 on (states untouched)",
        {**arrays, "control_sim": controls}, summary)
    layout = StateLayout(model)
    placed = arrays["presettle_state_sim"].copy()
    placed[layout.slices["qpos"].start + prep.scene.object_qpos_adr + 1] += 0.002
    add("start_placed_off", "presettle_state_sim: the object placed 2 mm off its recorded pose before the settling",
        {**arrays, "presettle_state_sim": placed}, summary)
    pushed = arrays["control_sim"].copy()
    steps = slice(10 * spf, 21 * spf)
    pushed[steps, actuator] += 0.1
    pushed[steps, model.nu + model.neq + 3 * hand.mocap_id + 2] += 0.003
    with ParallelEvaluator(model, 1) as ev:
        start, _ = settled_start(prep, ev)
        rec = replay(prep, ev, start, keyframes, record_states=True, control=pushed)
    raw = dataclasses.replace(rec, object_pose=arrays["raw_object_pose_sim"])  # only the refined replay is forged
    m_raw = {"per_frame": {k[len("metrics_raw_"):]: arrays[k] for k in arrays if k.startswith("metrics_raw_")}}
    forged = build_arrays(prep, arrays["sequence_npz"].tobytes(), keyframes, rec, raw, m_raw,
                          replay_metrics(prep, rec))
    keep = ("raw_object_pose_sim", "raw_state_sim", "raw_control_sim", "raw_object_articulation_sim")
    add("inputs_resimulated", "refined replay simulated under a finger target +0.1 rad and the wrist 3 mm higher "
        "over frames 10-20, every array stored from it", {**arrays, **{k: v for k, v in forged.items()
                                                                       if k not in keep}}, summary)


def add_table_forgery(add: Any, arrays: dict[str, np.ndarray], summary: dict[str, Any], prep: Any,
                      keyframes: dict[str, np.ndarray]) -> None:
    """The result re-derived whole (every attempt, figure and the outcome) on a table candidate that scores more
    than ``score_margin`` worse than the best: consistent in itself, on a table the fit would not choose."""
    from common.job_options import JobOptions
    from worker.refine.derive import add_attempt_metrics, attempt_figures, derive_result
    from worker.refine.outcome import classify_outcome, was_rescued
    from worker.simulation.config import SimConfig
    from worker.simulation.metrics import scalar_metrics
    from worker.simulation.table_fit import TableChoice, score_margin
    from worker.verification.check import _attempt_details, _attempt_keyframes

    fit = prep.scene.table_fit
    best = min(fit.scores)
    far = [i for i, score in enumerate(fit.scores) if score > best + score_margin(score)]
    if not far:
        return
    i = min(far, key=lambda k: fit.scores[k])
    sim: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in summary["config"]["sim"].items()}
    attempt_kf = _attempt_keyframes(arrays, list(prep.spaces))
    details = _attempt_details(summary, attempt_kf, sim["convex_detail"])
    derived = derive_result(arrays["sequence_npz"].tobytes(), JobOptions.model_validate(summary["options"]),
                            SimConfig(**sim), summary["config"]["rotation_pivot"], keyframes, attempt_kf,
                            attempt_details=details, table=TableChoice(i, *fit.candidates[i]))
    metrics = {k: scalar_metrics(v) for k, v in derived.metrics.items()}
    attempts = [{**a, **attempt_figures(m)} for a, m in zip(summary["attempts"], derived.attempt_metrics,
                                                            strict=True)]
    add_attempt_metrics(metrics["refined"], attempts)
    contact = derived.final.contact_frames
    outcome = classify_outcome(derived.prep, derived.metrics["refined"], derived.final.object_pose,
                               hand_contact=None if contact is None else contact.hand,
                               rescued=was_rescued(derived.prep))
    forged = {**summary, "metrics": metrics, "attempts": attempts, "table": derived.prep.scene.table_summary(),
              "object_hold": derived.prep.scene.hold_summary(),
              "num_contacts": len(derived.final.contacts["contact_frame"]), "outcome": outcome.model_dump(mode="json")}
    add("table_far", f"the table replaced by fit candidate {i} (drift {fit.scores[i]:.3g} against the best's "
        f"{best:.3g}) and the whole result re-derived on it", {**arrays, **derived.arrays}, forged)


def add_shift(add: Any, arrays: dict[str, np.ndarray], summary: dict[str, Any], prep: Any,
              keyframes: dict[str, np.ndarray], layout: Any) -> None:
    """The new forgery: the refined trajectory moved 3 mm (z) over frames 20-30, with everything that depends on it
    moved along (states, the contacts' world points, per-frame and summary metrics): within the old cross-host
    tolerance (5 mm + 10 %). Added twice: with states, and without them (an older result, verified the old way)."""
    from common.result_format import CONTACT_KEYS, STEPWISE_KEYS
    from worker.refine.derive import build_arrays, replay_metrics
    from worker.refine.replay import ReplayRecord
    from worker.simulation.contacts import contact_frames
    from worker.simulation.metrics import scalar_metrics

    frames = np.arange(20, min(31, len(arrays["object_pose_sim"])))
    pose = arrays["object_pose_sim"].copy()
    pose[frames, 2] += 0.003
    contacts: dict[str, np.ndarray] = {k: arrays[k].copy() for k in CONTACT_KEYS}
    rows = np.isin(contacts["contact_frame"], frames)
    contacts["contact_pos_world"][rows, 2] += 0.003
    final = ReplayRecord(pose, arrays["object_vel_sim"], {s: arrays[f"{s}_keypoints_sim"] for s in prep.spaces},
                         contacts, 0)
    final = dataclasses.replace(final, contact_frames=contact_frames(
        contacts["contact_frame"], contacts["contact_depth"], np.flatnonzero(arrays["object_table_contact"]),
        len(pose)))
    m_ref = replay_metrics(prep, final)
    raw_rec = ReplayRecord(arrays["raw_object_pose_sim"], arrays["object_vel_sim"], final.keypoints, contacts, 0)
    m_raw = {"per_frame": {k[len("metrics_raw_"):]: arrays[k] for k in arrays if k.startswith("metrics_raw_")}}
    forged = build_arrays(prep, arrays["sequence_npz"].tobytes(), keyframes, final, raw_rec, m_raw, m_ref)
    forged = {**arrays, **{k: v for k, v in forged.items() if k.startswith("metrics_refined_")},
              "object_pose_sim": pose, "contact_pos_world": contacts["contact_pos_world"]}
    states = arrays["state_sim"].copy()
    states[frames, layout.slices["qpos"].start + prep.scene.object_qpos_adr + 2] += 0.003
    scalars = scalar_metrics(m_ref)
    old = summary["metrics"]["refined"]
    for key in ("attempts", "success_first_attempt"):
        if key in old:
            scalars[key] = old[key]
    if "paper" in old and "success_first_attempt" in old["paper"]:
        scalars["paper"]["success_first_attempt"] = old["paper"]["success_first_attempt"]
    s = {**summary, "metrics": {**summary["metrics"], "refined": scalars}}
    add("shift_3mm_states", "trajectory + states + contacts + metrics moved 3 mm over frames 20-30",
        {**forged, "state_sim": states}, s)
    add("shift_3mm_old_way", "the same without states (verified the old way)",
        {k: v for k, v in forged.items() if k not in STEPWISE_KEYS}, s)


# ------------------------------------------------------------------------------------------------- report


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.one is not None:
        print(json.dumps(verify_one(args.one, args.old_way)))
        return 0
    if args.substeps is not None:
        print(json.dumps(steps_against_frames(*args.substeps)))
        return 0
    if args.code_digest:
        print(json.dumps(code_files()))
        return 0
    if args.hinged_box is not None:
        make_hinged_box(args.hinged_box, args.budget)
        return 0
    if args.make:
        make_results(args.results, args.make, args.budget, args.names)
        if args.make_only:
            return 0
    if args.add_presettle:
        for path in sorted(args.results.glob("*.npz")):
            if add_presettle(path):
                print(f"added presettle_state_sim to {path.name}", flush=True)
    global HOST_CODE
    HOST_CODE = code_digest()
    kernels = list(KERNELS)
    header = ""
    if args.container:
        theirs, mine = container_code(args.container), code_files()
        CONTAINER.update(image=args.container, code=code_digest(theirs))
        kernels.append("container")
        differ = sorted(k for k in set(theirs) | set(mine) if theirs.get(k) != mine.get(k))
        header = (f"Container: **container** `{args.container}`, each verification a `docker run --network host` "
                  "with the results mounted read-only (`--one` inside the image: its own installed code and "
                  "libraries, no kernels forced). Its `worker` + `common` against this tree's, file by file "
                  f"({len(mine)} files): " + ("identical" if not differ else f"{len(differ)} differ: "
                                               + ", ".join(differ[:12])) + ".")
        print(header, flush=True)
    files = sorted(p for p in args.results.glob("*.npz"))
    lines = ["# Stepwise verification off-host (issue #54)", "",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared with other "
             f"sessions); {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Sample: {len(files)} results in "
             f"`{args.results}`. Kernels forced in a subprocess: " + "; ".join(
                 f"**{k}** {' '.join(f'{a}={b!r}' for a, b in v.items()) or '(none)'}" for k, v in KERNELS.items()),
             "", *([header, ""] if header else [])]
    for note in args.note:
        lines += [note, ""]
    rows: list[dict[str, Any]] = []
    for path in files:
        for kernel in kernels:
            r = run_one(path, kernel, cache=args.cache)
            r.update(name=path.stem, kernel=kernel)
            if kernel != "original" and not args.skip_old_way:  # the same file as an older result, without states
                old = run_one(path, kernel, old_way=True, cache=args.cache)
                r["old_way"] = "error" if "error" in old else (
                    "passes" if old["verified"] else "FAILS: " + "; ".join(old["failures"])[:160])
            rows.append(r)
            print(json.dumps({k: r.get(k) for k in ("name", "kernel", "verified", "drift_m", "total_s",
                                                    "derive_s")}), flush=True)
    if args.rows_only:
        return 0
    lines += [*summary_lines(rows, kernels), "", *deviation_table(rows), "", *timing_table(rows, kernels), "",
              *size_table(files), ""]
    lines += [*steps_table(files[:2]), ""]
    if files:
        with tempfile.TemporaryDirectory() as tmp:
            os.chmod(tmp, 0o755)  # the container's user reads the forgeries
            forged = forgeries(args.forge or files[0], Path(tmp))
            lines += forgery_table(forged, args.forge or files[0], kernels, args.cache)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def summary_lines(rows: list[dict[str, Any]], kernels: list[str]) -> list[str]:
    """The largest honest deviations over every result and kernel set against the tolerances."""
    from worker.verification.stepwise import STATE_TOLERANCES

    passed = [r for r in rows if r.get("verified")]
    failed = [f"{r['name']} ({r['kernel']})" for r in rows if not r.get("verified")]
    out = ["## Summary", "",
           f"{len(passed)} of {len(rows)} verifications passed ({len({r['name'] for r in rows})} results x "
           f"{len(kernels)} kernel sets); failed: {', '.join(failed) or 'none'}. The deviations below are those of "
           "the verified ones.", "",
           "| state field | largest honest deviation, frames 1.. | at frame 0 (re-settled start) | tolerance | "
           "tolerance at frame 0 |", "|---|---|---|---|---|"]
    good = passed
    for f in ("running_qpos", "running_qvel"):
        worst = max((s.get("running", {}).get(f, {}).get("value", 0.0) for r in good for s in r["stepwise"].values()),
                    default=0.0)
        out.append(f"| {f} (signed sum of the per-frame deviations, largest) | {worst:.3g} | | "
                   f"{getattr(STATE_TOLERANCES, f):g} | |")
    inputs = max(((s.get("controls") or {}).get("value", 0.0) for r in good for s in r["stepwise"].values()),
                 default=0.0)
    out.append(f"| stored inputs (control_sim) against the keyframes' | {inputs:.3g} | | "
               f"{STATE_TOLERANCES.inputs:g} | |")
    for f in ("qpos", "qvel", "qacc_warmstart", "ctrl", "mocap_pos", "mocap_quat", "time"):
        step = max((s["largest"].get(f, {}).get("value", 0.0) for r in good for s in r["stepwise"].values()),
                   default=0.0)
        start = max((s["start"].get(f, {}).get("value", 0.0) for r in good for s in r["stepwise"].values()),
                    default=0.0)
        out.append(f"| {f} | {step:.3g} | {start:.3g} | {STATE_TOLERANCES.of(f):g} | "
                   f"{STATE_TOLERANCES.of(f, 0):g} |")
    ties = [f"{r['name']} ({r['kernel']}): {n}" for r in rows for n in r.get("notes", []) if "near tie" in n]
    out += ["", "Table choices re-derived as a near tie (the stored candidate accepted within the margin, "
            "`worker.simulation.table_fit.score_margin`): " + ("; ".join(ties) or "none") + "."]
    drift = max((r["drift_m"] for r in good), default=0.0)
    olds = [r for r in rows if "old_way" in r]
    out += ["", f"Largest whole-rollout drift (the figure the old check compared within 5 mm + 10 %): "
            f"{drift * 1000:.3g} mm. The same files without their states (the old way) off the original kernels: "
            f"{sum(r['old_way'] == 'passes' for r in olds)} of {len(olds)} pass."]
    return out


def deviation_table(rows: list[dict[str, Any]]) -> list[str]:
    out = ["## Largest stepwise deviation per result (refined and raw replay, every frame from the stored one before)",
           "", "Each cell: the largest |stored - reached| over frames 1.. and both replays (m or rad for qpos, m/s or "
           "rad/s for qvel, per-dof; 0 = bit-identical). `start`: frame 0 against the start re-settled here. "
           "`drift`: the whole re-simulation's largest object deviation (reported, not pass/fail).", "",
           "`old way`: the same file without its states, verified as an older result (whole re-simulation within "
           "5 mm / 5 deg + 10 %).", "",
           "`inputs`: the stored inputs of every step against those the keyframes give here (the replay steps under "
           "the stored ones).", "",
           "| result | kernels | verified | inputs | " + " | ".join(FIELDS)
           + " | start qpos / qvel | drift (mm) | old way |",
           "|---|---|---|---|" + "---|" * len(FIELDS) + "---|---|---|"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['name']} | {r['kernel']} | ERROR | | " + " | ".join("" for _ in FIELDS) + " | | | |")
            continue
        sw = r["stepwise"].values()
        cells = []
        for f in FIELDS:
            worst = max((s["largest"].get(f, {}).get("value", 0.0) for s in sw), default=0.0)
            cells.append(f"{worst:.2g}")
        start = [max((s["start"].get(f, {}).get("value", 0.0) for s in sw), default=0.0) for f in ("qpos", "qvel")]
        ok = "yes" if r["verified"] else "NO: " + "; ".join(r["failures"])[:200]
        inputs = [s["controls"]["value"] for s in sw if s.get("controls")]
        stored_inputs = f"{max(inputs):.2g}" if len(inputs) == len(sw) and inputs else "-"
        out.append(f"| {r['name']} | {r['kernel']} | {ok} | {stored_inputs} | " + " | ".join(cells)
                   + f" | {start[0]:.2g} / {start[1]:.2g} | {r['drift_m'] * 1000:.3g} | {r.get('old_way', '')} |")
    return out


def timing_table(rows: list[dict[str, Any]], kernels: list[str]) -> list[str]:
    good = [r for r in rows if "error" not in r]
    out = ["## Time: stepwise check against the full re-simulation", "",
           "Stepwise: both replays, each frame from its stored state (Python-stepped, contacts recorded). Full: "
           "`derive_result`, the whole re-simulation verify runs as well (preparation: retargeting, scene, "
           "controls; settling, raw and refined replay, every restart). Both need the preparation, which is part of "
           "the full figure. Seconds on this shared 2-core machine (other sessions running).", "",
           "| kernels | results | frames (mean) | stepwise s (mean) | full re-simulation s (mean) | of which "
           "preparation s | verify total s |", "|---|---|---|---|---|---|---|"]
    for kernel in kernels:
        mine = [r for r in good if r["kernel"] == kernel]
        if not mine:
            continue
        step = np.mean([sum(s["seconds"] for s in r["stepwise"].values()) for r in mine])
        out.append(f"| {kernel} | {len(mine)} | {np.mean([r['frames'] for r in mine]):.0f} | {step:.2f} | "
                   f"{np.mean([r['derive_s'] for r in mine]):.2f} | {np.mean([r['prepare_s'] for r in mine]):.2f} | "
                   f"{np.mean([r['total_s'] for r in mine]):.2f} |")
    return out


def size_table(files: list[Path]) -> list[str]:
    from common.settings import Settings

    limits = Settings()
    sizes = [state_sizes(p) for p in files]
    out = ["## What storing the states and inputs costs", "",
           "Per replay and frame: the integration state (`state values`) and the inputs of each physics step of the "
           "frame (`input values` a step).", "",
           "| result | frames | state values | input values / step | bytes / frame / replay | stored (both replays, "
           "compressed) | uncompressed | result file |", "|---|---|---|---|---|---|---|---|"]
    for p, s in zip(files, sizes, strict=True):
        out.append(f"| {p.stem} | {s['frames']} | {s['nstate']} | {s['ncontrol']} | {s['per_frame']} | "
                   f"{s['stored'] / 1024:.0f} KiB | {s['uncompressed'] / 1024:.0f} KiB | "
                   f"{s['result'] / 1024:.0f} KiB |")
    if sizes:
        per = max(s["per_frame"] for s in sizes)
        worst = 2 * per * limits.max_frames
        out += ["", f"At the service's frame limit ({limits.max_frames} frames) the states and inputs of the largest "
                f"scene here ({per // 8} values a frame) take {worst / 2**20:.1f} MiB uncompressed over four members, "
                "each under a third of that. A result is not an upload: the request limit "
                f"({limits.max_request_bytes / 2**20:.0f} MiB) and the NPZ limits of sequences "
                "(`common.npz_safe.NpzLimits`) do not apply to it, and the service stores results in the database "
                "with no size limit of its own."]
    return out


def forgery_table(forged: list[tuple[str, str, Path]], source: Path, kernels: list[str],
                  cache: Path | None = None) -> list[str]:
    """Each forgery verified with the avx2 kernels forced (and in the container): verdict and first failure."""
    where = [k for k in ("avx2", "container") if k in kernels]
    out = [f"## Forgeries of `{source.stem}`, verified with the {' and '.join(where)} kernel sets", "",
           "| forgery | what it changes | kernels | verdict | first failure (field and frame) |",
           "|---|---|---|---|---|"]
    for name, what, path in forged:
        os.chmod(path, 0o644)
        for kernel in where:
            r = run_one(path, kernel, cache=cache)
            if "error" in r:
                verdict, text = "error", r["error"][-300:].replace("\n", " ")
            else:
                verdict = "accepted" if r["verified"] else "FAILS"
                text = (r["failures"] or [""])[0]
            out.append(f"| {name} | {what} | {kernel} | {verdict} | {text.replace('|', '/')[:400]} |")
            print(out[-1], flush=True)
    return out


if __name__ == "__main__":
    sys.exit(main())
