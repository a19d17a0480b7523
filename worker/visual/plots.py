"""PNG plots of a result (issue #18 item 3), from the result file alone (no re-simulation): matplotlib, Agg.

* ``errors.png``: per-frame E_t (cm) and E_r (deg), raw replay vs refined, with the success thresholds;
* ``contact_forces.png``: summed contact force magnitude per finger over time (the result's contacts: the
  refined trajectory of a refinement, the raw one of a raw replay);
* ``loss_history.png`` (refinements only): each window's best loss per CMA-ES generation, and each window's
  loss before and after optimisation.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from common.result_format import read_arrays, read_summary
from worker.simulation.metrics import SUCCESS_POSITION_CM, SUCCESS_ROTATION_DEG
from worker.visual.playback import contact_force_per_finger

PLOT_NAMES: tuple[str, ...] = ("errors.png", "contact_forces.png", "loss_history.png")
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
    written = [_errors(arrays, fps, out / "errors.png", dpi), _forces(arrays, summary, fps, out / "contact_forces.png",
                                                                        dpi)]
    if "window_loss_history" in arrays:
        written.append(_loss_history(arrays["window_loss_history"], summary, out / "loss_history.png", dpi))
    return written


def _errors(arrays: dict[str, np.ndarray], fps: float, path: Path, dpi: int) -> Path:
    plt = _pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for (ax, key, unit, limit) in (
        (axes[0], "e_t_cm", "E_t (cm)", SUCCESS_POSITION_CM),
        (axes[1], "e_r_deg", "E_r (deg)", SUCCESS_ROTATION_DEG),
    ):
        for name in ("raw", "refined"):
            values = arrays.get(f"metrics_{name}_{key}")
            if values is not None:
                t = np.arange(len(values)) / fps
                ax.plot(t, values, color=_COLOURS[name], label=f"{name} (mean {np.nanmean(values):.2f})")
        ax.axhline(limit, color="k", linestyle="--", linewidth=1, label=f"success limit {limit:g}")
        ax.set_ylabel(unit)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    axes[1].set_xlabel("time (s)")
    axes[0].set_title("object error per frame: raw replay vs refined")
    return _save(fig, path, dpi)


def _forces(arrays: dict[str, np.ndarray], summary: dict[str, Any], fps: float, path: Path, dpi: int) -> Path:
    plt = _pyplot()
    frames = int(summary.get("frames") or len(arrays["object_pose_sim"]))
    per_finger = contact_force_per_finger(arrays, frames)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    t = np.arange(frames) / fps
    for finger, values in per_finger.items():
        if finger == "palm" and not values.any():
            continue
        ax.plot(t, values, label=finger)
    which = "refined" if summary.get("kind") == "refine" else "raw replay"
    ax.set_title(f"contact force per finger ({which})")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("|force| (N)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8, ncol=3)
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
