"""PNG plots of evaluated trajectories (matplotlib, Agg canvas; no pyplot global state).

Each function takes per-agent :class:`~common.evaluation.metrics.AteResult` (the estimate
already aligned into the ground-truth frame) and writes one PNG.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from common.evaluation.metrics import AteResult

log = logging.getLogger(__name__)

_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def _colour(i: int) -> str:
    return _COLOURS[i % len(_COLOURS)]


def _save(fig: Figure, path: Path | str, dpi: int) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(out, dpi=dpi)
    log.debug("wrote %s", out)
    return out


def plot_trajectories(
    results: Mapping[str, AteResult], path: Path | str, title: str = "", dpi: int = 110
) -> Path:
    """Top view (x-y) and side view (x-z) of ground truth (dashed) vs aligned estimate (solid)."""
    fig = Figure(figsize=(12, 5.5), layout="constrained")
    ax_top, ax_side = fig.subplots(1, 2)
    for i, (agent, res) in enumerate(results.items()):
        c = _colour(i)
        ref, est = res.ref.p_world_body, res.est_aligned.p_world_body
        for ax, (a, b) in ((ax_top, (0, 1)), (ax_side, (0, 2))):
            ax.plot(ref[:, a], ref[:, b], "--", color=c, alpha=0.6, lw=1.0, label=f"{agent} GT")
            ax.plot(est[:, a], est[:, b], "-", color=c, lw=1.4, label=f"{agent} est.")
            ax.plot(est[:1, a], est[:1, b], "o", color=c, ms=4)
    ax_top.set(xlabel="x [m]", ylabel="y [m]", title="top view (x-y)")
    ax_side.set(xlabel="x [m]", ylabel="z [m]", title="side view (x-z)")
    for ax in (ax_top, ax_side):
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    ax_top.legend(fontsize=8, loc="best")
    fig.suptitle(title)
    return _save(fig, path, dpi)


def plot_ate_over_time(
    panels: Mapping[str, Mapping[str, AteResult]],
    path: Path | str,
    title: str = "",
    dpi: int = 110,
) -> Path:
    """ATE [m] over time, one subplot per entry of ``panels`` (e.g. joint, individual).

    Time is in seconds from the earliest associated stamp of all agents and panels.
    """
    all_results = [r for panel in panels.values() for r in panel.values()]
    t0 = min(int(r.timestamps_ns[0]) for r in all_results) if all_results else 0
    fig = Figure(figsize=(11, 3.2 * max(len(panels), 1)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(max(len(panels), 1), 1, sharex=True))
    for ax, (label, panel) in zip(axes, panels.items(), strict=False):
        for i, (agent, res) in enumerate(panel.items()):
            t = (res.timestamps_ns - t0).astype(np.float64) * 1e-9
            ax.plot(
                t,
                res.errors_m,
                color=_colour(i),
                lw=1.0,
                label=f"{agent} (RMSE {res.stats.rmse:.4f} m)",
            )
        ax.set(ylabel="ATE [m]", title=label)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title)
    return _save(fig, path, dpi)
