"""Preview images of a synthetic dataset: a contact sheet of frames and a top view of flights."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from common.data.synth.scene import Scene
from common.data.synth.trajectory import Motion


def contact_sheet(samples: list[list[np.ndarray]], scale: float = 0.5) -> np.ndarray:
    """Rows of sample frames (one row per robot) -> one uint8 image with labels."""
    rows = []
    for k, frames in enumerate(samples):
        small = [
            cv2.resize(f, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) for f in frames
        ]
        row = np.concatenate([np.pad(s, 2, constant_values=255) for s in small], axis=1)
        cv2.putText(row, f"robot{k}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, 255, 3, cv2.LINE_AA)
        cv2.putText(row, f"robot{k}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, 0, 1, cv2.LINE_AA)
        rows.append(row)
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1])), constant_values=255) for r in rows]
    return np.concatenate(rows, axis=0)


def plot_top_view(scene: Scene, trajectories: Sequence[Motion], seconds: float, path: Path) -> None:
    """Top view PNG of the room, its boxes and every robot's flight (start marked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, ax = plt.subplots(figsize=(9, 7.5), dpi=100)
    lo, hi = scene.room_lo, scene.room_hi
    ax.add_patch(Rectangle(lo[:2], hi[0] - lo[0], hi[1] - lo[1], fill=False, lw=2))
    for box in scene.boxes:
        ax.add_patch(
            Rectangle(
                box.lo[:2], box.hi[0] - box.lo[0], box.hi[1] - box.lo[1], color="0.6", alpha=0.8
            )
        )
        ax.text(
            (box.lo[0] + box.hi[0]) / 2,
            (box.lo[1] + box.hi[1]) / 2,
            f"{box.name}\n{box.hi[2]:.2f} m",
            ha="center",
            va="center",
            fontsize=7,
        )
    t = np.arange(0.0, seconds, 0.05)
    for k, traj in enumerate(trajectories):
        st = traj.evaluate(t)
        p = st.p_world_body
        (line,) = ax.plot(p[:, 0], p[:, 1], lw=1.2, label=f"robot{k}")
        ax.plot(p[0, 0], p[0, 1], "o", color=line.get_color(), ms=7)
        # Viewing direction every 2 s.
        fwd = st.T_world_cam()[:, :3, 2]
        idx = np.arange(0, len(t), 40)
        ax.quiver(
            p[idx, 0],
            p[idx, 1],
            fwd[idx, 0],
            fwd[idx, 1],
            color=line.get_color(),
            scale=25,
            width=0.003,
            alpha=0.7,
        )
    ax.set_xlim(lo[0] - 0.2, hi[0] + 0.2)
    ax.set_ylim(lo[1] - 0.2, hi[1] + 0.2)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"synthetic room, {len(trajectories)} robots x {seconds:g} s (o = start)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
