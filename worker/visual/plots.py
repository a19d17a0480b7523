"""PNG plots of a result (issue #18 item 3), from the result file alone (no re-simulation): matplotlib, Agg.

* ``errors.png``: per-frame E_t (cm) and E_r (deg), raw replay vs refined, with the success thresholds, and for an
  articulated object E_a (the frame's largest joint error, deg or cm) with its threshold;
* ``articulation.png`` (an articulated object only): every joint's value per frame, recorded, raw replay and
  refined (deg for a revolute joint, cm for a prismatic one);
* ``contact_forces.png``: summed contact force magnitude per finger over time (the result's contacts: the
  refined trajectory of a refinement, the raw one of a raw replay), one panel per hand;
* ``loss_history.png`` (refinements only): each window's best loss per CMA-ES generation, and each window's
  loss before and after optimisation.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from common.result_format import read_arrays, read_summary
from worker.simulation.metrics import SUCCESS_ARTICULATION, SUCCESS_POSITION_CM, SUCCESS_ROTATION_DEG
from worker.visual.playback import contact_force_per_finger

PLOT_NAMES: tuple[str, ...] = ("errors.png", "contact_forces.png", "loss_history.png", "articulation.png")
_COLOURS = {"raw": "#d62728", "refined": "#1f77b4"}


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # no display; safe to call again
    import matplotlib.pyplot as plt

    return plt


def write_plots(blob: bytes, out_dir: Path | str, dpi: int = 100) -> list[Path]:
    """Write the plots of a result file's bytes into ``out_dir``; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary, arrays = read_summary(blob), read_arrays(blob)
    fps = float(summary.get("fps") or 30.0)
    joints = _joints(arrays)
    written = [_errors(arrays, fps, joints, out / "errors.png", dpi),
               _forces(arrays, summary, fps, out / "contact_forces.png", dpi)]  # fmt: skip
    if "object_articulation_ref" in arrays:
        written.append(_articulation(arrays, fps, joints, out / "articulation.png", dpi))
    if "window_loss_history" in arrays:
        written.append(_loss_history(arrays["window_loss_history"], summary, out / "loss_history.png", dpi))
    return written


def _joints(arrays: dict[str, np.ndarray]) -> list[tuple[str, str]]:
    """(name, kind) of every joint of an articulated result: from the embedded sequence (refinements), else
    unnamed revolute joints (a raw replay embeds none; ``hoi-refine plot`` reads the file alone)."""
    if "object_articulation_ref" not in arrays:
        return []
    if "sequence_npz" in arrays:
        from common.sequence_io import sequence_from_npz_bytes

        obj = sequence_from_npz_bytes(arrays["sequence_npz"].tobytes()).object
        return [(j.name, j.kind) for j in obj.joints]
    return [(f"joint {k}", "revolute") for k in range(arrays["object_articulation_ref"].shape[1])]


def _errors(arrays: dict[str, np.ndarray], fps: float, joints: list[tuple[str, str]], path: Path, dpi: int) -> Path:
    plt = _pyplot()
    panels = [("e_t_cm", "E_t (cm)", [("", SUCCESS_POSITION_CM)]),
              ("e_r_deg", "E_r (deg)", [("", SUCCESS_ROTATION_DEG)])]
    if any(f"metrics_{name}_e_a" in arrays for name in ("raw", "refined")):
        kinds = sorted({kind for _, kind in joints})
        unit = "/".join("deg" if k == "revolute" else "cm" for k in kinds) or "deg"
        panels.append(("e_a", f"E_a ({unit})", [(f" ({k})" if len(kinds) > 1 else "", SUCCESS_ARTICULATION[k])
                                                 for k in kinds]))  # fmt: skip
    fig, axes = plt.subplots(len(panels), 1, figsize=(7, 2.5 * len(panels)), sharex=True)
    for ax, (key, unit, limits) in zip(axes, panels, strict=True):
        for name in ("raw", "refined"):
            values = arrays.get(f"metrics_{name}_{key}")
            if values is not None:
                t = np.arange(len(values)) / fps
                ax.plot(t, values, color=_COLOURS[name], label=f"{name} (mean {np.nanmean(values):.2f})")
        for what, limit in limits:
            ax.axhline(limit, color="k", linestyle="--", linewidth=1, label=f"success limit{what} {limit:g}")
        ax.set_ylabel(unit)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    axes[-1].set_xlabel("time (s)")
    axes[0].set_title("object error per frame: raw replay vs refined")
    return _save(fig, path, dpi)


def _articulation(arrays: dict[str, np.ndarray], fps: float, joints: list[tuple[str, str]], path: Path,
                  dpi: int) -> Path:
    """Every joint's value per frame: recorded, raw replay, refined (or the raw replay's own, for a replay)."""
    plt = _pyplot()
    ref = arrays["object_articulation_ref"]
    runs = [("recorded", ref, "#2ca02c")]
    if "raw_object_articulation_sim" in arrays:  # a refinement: the raw replay and the refined run
        runs += [("raw", arrays["raw_object_articulation_sim"], _COLOURS["raw"]),
                 ("refined", arrays["object_articulation_sim"], _COLOURS["refined"])]  # fmt: skip
    elif "object_articulation_sim" in arrays:
        runs.append(("raw", arrays["object_articulation_sim"], _COLOURS["raw"]))
    fig, axes = plt.subplots(len(joints), 1, figsize=(7, 2.5 * len(joints)), sharex=True, squeeze=False)
    t = np.arange(len(ref)) / fps
    for k, (ax, (name, kind)) in enumerate(zip(axes[:, 0], joints, strict=True)):
        scale, unit = (np.degrees(1.0), "deg") if kind == "revolute" else (100.0, "cm")
        for label, values, colour in runs:
            ax.plot(t, values[:, k] * scale, color=colour, label=label, linestyle=":" if label == "recorded" else "-")
        ax.set_ylabel(f"{name} ({unit})")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    axes[-1, 0].set_xlabel("time (s)")
    axes[0, 0].set_title("joint values per frame")
    return _save(fig, path, dpi)


def _forces(arrays: dict[str, np.ndarray], summary: dict[str, Any], fps: float, path: Path, dpi: int) -> Path:
    """Contact force per finger over time; two hands side by side, each its own panel."""
    plt = _pyplot()
    frames = int(summary.get("frames") or len(arrays["object_pose_sim"]))
    sides = [s for s in ("right", "left") if f"{s}_keypoints_sim" in arrays]
    panels: list[str | None] = list(sides) if len(sides) == 2 else [None]
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 3.5), squeeze=False, sharey=True)
    t = np.arange(frames) / fps
    which = "refined" if summary.get("kind") == "refine" else "raw replay"
    for ax, side in zip(axes[0], panels, strict=True):
        for finger, values in contact_force_per_finger(arrays, frames, side).items():
            if finger == "palm" and not values.any():
                continue
            ax.plot(t, values, label=finger)
        ax.set_title(f"contact force per finger ({which}{'' if side is None else f', {side} hand'})")
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, ncol=3)
    axes[0, 0].set_ylabel("|force| (N)")
    return _save(fig, path, dpi)


def _loss_history(history: np.ndarray, summary: dict[str, Any], path: Path, dpi: int) -> Path:
    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.5))
    cmap = plt.get_cmap("viridis")
    n = max(len(history), 1)
    for i, row in enumerate(history):
        row = row[np.isfinite(row)]
        if len(row):
            ax1.plot(np.arange(1, len(row) + 1), row, color=cmap(i / n), linewidth=1)
    ax1.set_xlabel("CMA-ES generation")
    ax1.set_ylabel("best window loss")
    ax1.set_title("per window (dark: first, light: last)", fontsize=9)
    ax1.grid(alpha=0.3)
    windows = summary.get("windows", {}).get("per_window", [])
    if windows:
        k = [w["keyframe"] for w in windows]
        ax2.plot(k, [w["initial_loss"] for w in windows], "o-", color=_COLOURS["raw"], label="before")
        ax2.plot(k, [w["best_loss"] for w in windows], "o-", color=_COLOURS["refined"], label="after")
        ax2.legend(fontsize=8)
    ax2.set_xlabel("optimised keyframe")
    ax2.set_ylabel("window loss")
    ax2.set_title("loss per window", fontsize=9)
    ax2.grid(alpha=0.3)
    return _save(fig, path, dpi)


def _save(fig: Any, path: Path, dpi: int) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    _pyplot().close(fig)
    return path
