"""GUI panels: map counts, agents table (with live ATE, each agent's robot and edge), the
edges (sites: which robots each serves, its link rates), per-link bandwidth plots (uPlot).

:func:`edge_rates` (pure) sums the recent bandwidth samples per edge; :func:`bandwidth_series`
(pure) bins bandwidth samples into kbit/s per link, direction and
message type; :class:`Panels` shows a :class:`StatsSnapshot` in the viser GUI.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import viser
import viser.uplot as uplot

from common.map_view import BandwidthSample, Direction, StatsSnapshot

log = logging.getLogger(__name__)

SERIES_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2")


@dataclass(frozen=True, eq=False)
class LinkSeries:
    """kbit/s of one link over time: ``t_s (B,)`` bin ends relative to the newest sample
    (≤ 0), and for each label (``"keyframe ↑"``, ...) a ``(B,)`` array."""

    link: str
    t_s: np.ndarray
    kbit_s: dict[str, np.ndarray]


def bandwidth_series(
    samples: tuple[BandwidthSample, ...], window_s: float = 60.0, bin_s: float = 1.0
) -> list[LinkSeries]:
    """Bin samples of the last ``window_s`` seconds into ``bin_s`` bins, per link (sorted:
    robot links first, then the rest), one series per message type and direction."""
    if not samples:
        return []
    t = np.array([s.time for s in samples])
    t_end = float(t.max())
    n_bins = max(int(np.ceil(window_s / bin_s)), 1)
    t0 = t_end - n_bins * bin_s
    out = []
    links = sorted({s.link for s in samples}, key=lambda name: (not name.startswith("robot"), name))
    for link in links:
        series: dict[str, np.ndarray] = {}
        for s in samples:
            if s.link != link or s.time <= t0:
                continue
            arrow = "↑" if s.direction is Direction.UP else "↓"
            label = f"{s.message_type} {arrow}"
            arr = series.setdefault(label, np.zeros(n_bins))
            b = min(max(int(np.ceil((s.time - t0) / bin_s)) - 1, 0), n_bins - 1)  # (lo, hi] bins
            arr[b] += s.n_bytes * 8 / 1000.0 / bin_s
        edges = t0 + bin_s * np.arange(1, n_bins + 1) - t_end  # bin ends, newest at 0
        out.append(LinkSeries(link, edges, dict(sorted(series.items()))))
    return out


def counts_markdown(stats: StatsSnapshot) -> str:
    c = stats.counts
    return (
        "| | all | with MBP |\n|---|---:|---:|\n"
        f"| Keyframes | {c.keyframes} | {c.keyframes_kept} |\n"
        f"| Map points | {c.map_points} | {c.map_points_kept} |\n"
        f"| Loops | {c.loops} | |\n| Merges | {c.merges} | |\n"
        + (f"\n**Cloud:** {stats.status}\n" if stats.status else "")
    )


def agent_label(agent_id: int, name: str | None) -> str:
    """How the dashboard names an agent: its robot's name (the one the robot, its files and
    its logs use), or ``agent N`` before the cloud knows it. The cloud numbers agents in the
    order they joined, so "robot 0" could be ``robot1``: the number alone misled."""
    return name or f"agent {agent_id}"


def agents_markdown(stats: StatsSnapshot, ate_m: dict[int, float | None]) -> str:
    """Agents table; ``ate_m`` supplies the live ATE where the source gave none."""
    rows = [
        "| Robot | Edge | Status | Frames | KFs | Last seen | ATE |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for a in stats.agents:
        ate = a.ate_rmse_m if a.ate_rmse_m is not None else ate_m.get(a.agent_id)
        ate_txt = f"{ate:.3f} m" if ate is not None else "–"
        ago = max(stats.time - a.last_seen, 0.0)
        rows.append(
            f"| {agent_label(a.agent_id, a.name)} | {a.edge or '–'} | {a.status.value} "
            f"| {a.frames} | {a.keyframes} | {ago:.1f} s ago | {ate_txt} |"
        )
    if not stats.agents:
        rows.append("| – | | no agents yet | | | | |")
    # Why a robot is where it is (a refused VI initialisation's numbers, its camera-IMU
    # offset): a line each under the table, not a column (they run long).
    why = [f"- **{agent_label(a.agent_id, a.name)}**: {a.detail}" for a in stats.agents if a.detail]
    return "\n".join(rows) + "\n" + ("\n" + "\n".join(why) + "\n" if why else "")


@dataclass(frozen=True)
class EdgeRates:
    """One edge (site): the robots it serves and its links' kbit/s over the recent window
    (``robots_up``: all its robots -> it, ``robots_down`` back; ``cloud_up``: it -> cloud,
    ``cloud_down`` back)."""

    edge: str
    robots: tuple[str, ...]
    robots_up: float
    robots_down: float
    cloud_up: float
    cloud_down: float


def edge_rates(stats: StatsSnapshot, window_s: float = 10.0) -> list[EdgeRates]:
    """Per edge, sorted by name: the robots of the agents it serves and its link rates over
    the last ``window_s`` seconds of bandwidth samples (links ``"robot→edge"`` and
    ``"edge→cloud"``)."""
    names = {a.edge for a in stats.agents if a.edge}
    names |= {s.link.rsplit("→", 1)[0] for s in stats.bandwidth if s.link.endswith("→cloud")}
    t0 = stats.time - window_s
    kbit = 8.0 / 1000.0 / window_s
    out = []
    for edge in sorted(names):
        rate = {("robots", d): 0.0 for d in Direction} | {("cloud", d): 0.0 for d in Direction}
        for s in stats.bandwidth:
            if s.time <= t0:
                continue
            src, _, dst = s.link.rpartition("→")
            if dst == edge:
                rate["robots", s.direction] += s.n_bytes * kbit
            elif src == edge and dst == "cloud":
                rate["cloud", s.direction] += s.n_bytes * kbit
        robots = tuple(sorted({a.name for a in stats.agents if a.edge == edge and a.name}))
        up, down = Direction.UP, Direction.DOWN
        out.append(
            EdgeRates(
                edge,
                robots,
                rate["robots", up],
                rate["robots", down],
                rate["cloud", up],
                rate["cloud", down],
            )
        )
    return out


def edges_markdown(stats: StatsSnapshot, window_s: float = 10.0) -> str:
    """Edges table: each edge's robots and link rates (kbit/s, last ``window_s`` s)."""
    rows = [
        f"kbit/s over the last {window_s:g} s\n",
        "| Edge | Robots | robots→edge ↑/↓ | edge→cloud ↑/↓ |",
        "|---|---|---:|---:|",
    ]
    for e in edge_rates(stats, window_s):
        rows.append(
            f"| {e.edge} | {', '.join(e.robots) or '–'} | {e.robots_up:.1f} / "
            f"{e.robots_down:.1f} | {e.cloud_up:.1f} / {e.cloud_down:.1f} |"
        )
    if len(rows) == 3:
        rows.append("| – | no edges yet | | |")
    return "\n".join(rows) + "\n"


class Panels:
    """The GUI side: toggles are added by the viewer; this class owns the stats panels."""

    def __init__(self, server: viser.ViserServer, window_s: float = 60.0) -> None:
        self._server = server
        self._window_s = window_s
        gui = server.gui
        with gui.add_folder("Map"):
            self.counts = gui.add_markdown("*waiting for the map…*")
        with gui.add_folder("Agents"):
            self.agents = gui.add_markdown("*waiting for agents…*")
        with gui.add_folder("Edges"):
            self.edges = gui.add_markdown("*waiting for edges…*")
        self._bw_folder = gui.add_folder("Bandwidth (kbit/s)")
        self._plots: dict[str, tuple[tuple[str, ...], viser.GuiUplotHandle]] = {}
        self.last_update = 0.0
        self._last: object = None

    def update(self, stats: StatsSnapshot, ate_m: dict[int, float | None]) -> None:
        """Refresh every panel from one stats snapshot (nothing is sent when unchanged)."""
        key = (stats, tuple(sorted(ate_m.items())))
        if key == self._last:
            return
        self._last = key
        with self._server.atomic():
            self.counts.content = counts_markdown(stats)
            self.agents.content = agents_markdown(stats, ate_m)
            self.edges.content = edges_markdown(stats)
            for ls in bandwidth_series(stats.bandwidth, self._window_s):
                self._update_plot(ls)
        self.last_update = time.monotonic()

    def _update_plot(self, ls: LinkSeries) -> None:
        labels = tuple(ls.kbit_s)
        known = self._plots.get(ls.link)
        if not labels:  # a link silent for the whole window: its plot (if any) drops to 0
            if known is not None:
                known[1].data = (ls.t_s, *(np.zeros_like(ls.t_s) for _ in known[0]))
            return
        data = (ls.t_s, *(ls.kbit_s[k] for k in labels))
        if known is not None and known[0] == labels:
            known[1].data = data
            return
        if known is not None:
            known[1].remove()
        series: list[uplot.Series] = [uplot.Series(label="t [s]")]
        for i, lab in enumerate(labels):
            series.append(
                uplot.Series(label=lab, stroke=SERIES_COLORS[i % len(SERIES_COLORS)], width=1.5)
            )
        with self._bw_folder:
            handle = self._server.gui.add_uplot(
                data,
                tuple(series),
                title=ls.link,
                aspect=2.0,
                scales={"x": uplot.Scale(time=False, auto=True), "y": uplot.Scale(auto=True)},
            )
        self._plots[ls.link] = (labels, handle)
