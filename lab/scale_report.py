"""Reporting of ``recslam experiment scale``: ``scale.md``, ``scale.png`` and ``scale.json`` of
:func:`lab.scale_run.run_scale`'s rows (the replays themselves are in :mod:`lab.scale` and
:mod:`lab.scale_live`)."""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lab.scale import (
    KEYFRAME_STAGES,
    OTHER_STAGES,
    SOLVES,
    AgentCopy,
    CoreRow,
    ScaleConfig,
    TeamRow,
)

log = logging.getLogger(__name__)


def _f(x: float, spec: str = ".2f") -> str:
    return "–" if x is None or not math.isfinite(x) else format(x, spec)


def _spread(values: Sequence[float], spec: str = ".2f") -> str:
    """``a`` for one run, ``median (min–max)`` for several."""
    v = [x for x in values if x is not None and math.isfinite(x)]
    if not v:
        return "–"
    if len(v) == 1:
        return format(v[0], spec)
    return f"{format(float(np.median(v)), spec)} ({format(min(v), spec)}–{format(max(v), spec)})"


def _keeps_up(r: TeamRow) -> bool:
    """The cloud kept up: it applied the last message within 5 s of its slot and its queue
    at the end of the replay was no longer than a tenth of what was sent."""
    return r.drain_s <= 5.0 and r.queue_end <= max(50, r.messages // 10)


def scale_markdown(
    config: ScaleConfig,
    rows: Sequence[Sequence[TeamRow]],
    copies: Sequence[Sequence[AgentCopy]],
    cores: Sequence[CoreRow] = (),
) -> str:
    """``scale.md``: how it was made, the table, the stages, the verdict."""
    labels = [lbl for lbl, _ in (*KEYFRAME_STAGES, *OTHER_STAGES, *SOLVES)]
    cpus = os.cpu_count()
    command = config.command or "recslam experiment scale"
    lines = [
        "# Many robots at one cloud: cost against agents and keyframes",
        "",
        f"Made {datetime.date.today().isoformat()} by `{command}` "
        "(`lab/scale.py`, `lab/scale_live.py`) on this machine "
        f"({cpus} cores, shared with other work). Recordings: "
        + ", ".join(f"`{p}`" for p in config.recordings)
        + ". Each team is made of copies of the recordings' robots, round-robin over the "
        "recordings, each copy's robots renamed `s<i>-robotN` and sent by its own fake edge "
        f"`site<i>`; a recording used again is shifted {config.shift_s:g} s later per round "
        "(its keyframes are the same as its first copy's: it merges with its twin at once). "
        f"Schedule `{config.schedule}`"
        + (
            " (each message at the camera time of its robot's latest keyframe: camera rate)"
            if config.schedule == "camera"
            else " (each message when the recording's cloud received it)"
        )
        + ". The uplink is played over loopback TCP to a real `recslam cloud` process "
        "pinned to one core (`taskset -c 0`: its event loop, its worker thread and its "
        "optimizer process share it; defaults otherwise: full BA on, MBP at shutdown only); "
        "the fake edges run in the replaying process on the other core.",
        "",
        "- **CPU per keyframe**: CPU time (`time.thread_time`) of each stage on the cloud's "
        "worker thread (its `--stats-out` `stages`), summed over the run and divided by the "
        "keyframes it applied: what a loaded machine's other processes do not inflate; solves run "
        "in the optimizer process (wall time). *worker*: all the worker's CPU (every "
        "message, building and applying optimisations, the dashboard's snapshot) per "
        "keyframe; *busy*: that over the time until the cloud had applied everything (1.0 = "
        "a whole core); *cloud CPU*: the cloud processes' user + system CPU time over the "
        "same time (/proc, optimizer included; > busy: the event loop, the solves). *busy "
        "wall*: the worker's wall time over that time (with SQLite's fsync per message and "
        "the other processes' share of the core); *ms/msg wall*: per message applied.",
        "- **Queue**: messages the edges had sent and the cloud had not applied yet (their "
        "outboxes: acknowledged after the cloud's handler), sampled every 0.5 s; *end*: at "
        "the last message's slot. *drain*: seconds after the last slot until the cloud had "
        "applied everything.",
        "- **Correction latency**: from a keyframe's slot in the schedule (its arrival at "
        "camera rate: queueing counts) to the first `PoseCorrection` the edge received "
        "that covers it; *corrected*: the share of keyframes that got one before the end.",
        "- **RSS**: peak resident memory of the cloud and its children.",
        "- **Shed**: seconds the cloud was overloaded and shed the work that only refines the "
        "map (`recslam cloud --overload-busy`: no full BA while running, no early loop "
        "candidates, a slower dashboard refresh) before the final stats were read.",
        "",
    ]
    head = (
        "| agents | edges | keyframes | messages | worker ms/KF | busy | busy wall | "
        "ms/msg wall | cloud CPU | "
        "queue max | queue end | drain s | latency median s | latency p95 s | corrected | "
        "RSS MB | maps | shed s | keeps up |"
    )
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for runs in rows:
        r0 = runs[0]
        lines.append(
            "| "
            + " | ".join(
                [
                    str(r0.agents),
                    str(r0.edges),
                    str(r0.keyframes),
                    str(r0.messages),
                    _spread([r.worker_ms_per_keyframe for r in runs], ".1f"),
                    _spread([r.worker_busy for r in runs]),
                    _spread([r.worker_busy_wall for r in runs]),
                    _spread([r.messages_ms_wall for r in runs], ".1f"),
                    _spread([r.cloud_cpu for r in runs]),
                    _spread([r.queue_max for r in runs], ".0f"),
                    _spread([r.queue_end for r in runs], ".0f"),
                    "not drained"
                    if any(math.isinf(r.drain_s) for r in runs)
                    else _spread([r.drain_s for r in runs], ".1f"),
                    _spread([r.latency["median"] for r in runs]),
                    _spread([r.latency["p95"] for r in runs]),
                    _spread([r.corrected for r in runs]),
                    _spread([r.rss_max_mb for r in runs], ".0f"),
                    _spread([r.maps for r in runs], ".0f"),
                    _spread([r.overloaded_s for r in runs], ".0f"),
                    "yes" if all(_keeps_up(r) for r in runs) else "**no**",
                ]
            )
            + " |"
        )
    lines += [
        "",
        "CPU per keyframe by stage (ms, the worker thread's CPU time; solves: wall time in the "
        "optimizer process, on the same core):",
        "",
        "| agents | " + " | ".join(labels) + " |",
        "|" + "---|" * (len(labels) + 1),
    ]
    for runs in rows:
        cells = [_spread([r.stage_ms[lbl] for r in runs], ".2f") for lbl in labels]
        lines.append(f"| {runs[0].agents} | " + " | ".join(cells) + " |")
    if cores:
        lines += [
            "",
            "The same teams through the service's core in one process (`core_replay`: the "
            "same input in the same order, solves in-process taking no time on the replay's "
            "clock, full BA on), ms per keyframe:",
            "",
            "| agents | keyframes | worker ms/KF | " + " | ".join(labels) + " | replay s |",
            "|" + "---|" * (len(labels) + 4),
        ]
        for c in cores:
            cells = [f"{c.stage_ms[lbl]:.2f}" for lbl in labels]
            lines.append(
                f"| {c.agents} | {c.keyframes} | {c.worker_ms_per_keyframe:.1f} | "
                + " | ".join(cells)
                + f" | {c.seconds:.0f} |"
            )
    lines += ["", *bound_lines(rows)]
    lines += ["", "Teams:", ""]
    for runs, cs in zip(rows, copies, strict=False):
        desc = "; ".join(
            f"site{c.index}: recording {c.recording} robots {','.join(c.robots)}"
            + (f" +{c.shift_s:g} s" if c.shift_s else "")
            for c in cs
        )
        lines.append(f"- {runs[0].agents} agents ({len(runs)} run(s)): {desc}")
    lines.append("")
    return "\n".join(lines)


def bound_lines(rows: Sequence[Sequence[TeamRow]]) -> list[str]:
    """What bounds the cloud, per team: its largest stages per keyframe and where the
    worker's time went (CPU vs wall)."""
    out = ["What bounds the cloud (largest stages per keyframe, first run of each team):", ""]
    for runs in rows:
        r = runs[0]
        top = sorted(r.stage_ms.items(), key=lambda kv: -kv[1])[:4]
        stages = ", ".join(f"{k} {v:.0f} ms" for k, v in top)
        out.append(
            f"- {r.agents} agents: worker CPU {r.worker_busy:.2f} of a core, wall "
            f"{r.worker_busy_wall:.2f} (the difference: fsync and the core's other "
            f"processes); {stages}"
        )
    return out


def rows_from_json(path: Path) -> list[list[TeamRow]]:
    """The rows :func:`write_scale` saved in ``scale.json`` (to rewrite the report)."""
    data = json.loads(Path(path).read_text())
    rows = []
    for runs in data:
        rows.append(
            [TeamRow(**{**r, "queue_trace": [tuple(x) for x in r["queue_trace"]]}) for r in runs]
        )
    return rows


def scale_plot(rows: Sequence[Sequence[TeamRow]], path: Path) -> None:
    """``scale.png``: CPU per keyframe by stage, the queue over time, correction latency."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(16, 4.8))
    agents = [runs[0].agents for runs in rows]
    x = np.arange(len(agents))
    bottom = np.zeros(len(agents))
    cmap = plt.get_cmap("tab20")
    colours = [cmap(i) for i in range(20)]
    for i, (label, _) in enumerate((*KEYFRAME_STAGES, *OTHER_STAGES)):
        h = np.array([np.median([r.stage_ms[label] for r in runs]) for runs in rows])
        ax[0].bar(x, h, bottom=bottom, label=label, color=colours[i % len(colours)])
        bottom += h
    ax[0].set_xticks(x, [str(a) for a in agents])
    ax[0].set_xlabel("agents")
    ax[0].set_ylabel("worker CPU per keyframe [ms]")
    ax[0].set_title("cloud worker cost per keyframe")
    ax[0].legend(fontsize=7)
    for runs in rows:
        t, q = zip(*runs[0].queue_trace, strict=True) if runs[0].queue_trace else ((), ())
        ax[1].plot(t, q, label=f"{runs[0].agents} agents")
    ax[1].set_xlabel("time [s]")
    ax[1].set_ylabel("messages sent, not yet applied")
    ax[1].set_title("cloud queue (one core)")
    ax[1].legend(fontsize=8)
    med = [np.median([r.latency["median"] for r in runs]) for runs in rows]
    p95 = [np.median([r.latency["p95"] for r in runs]) for runs in rows]
    ax[2].plot(agents, med, "o-", label="median")
    ax[2].plot(agents, p95, "s--", label="p95")
    ax[2].set_xscale("log", base=2)
    ax[2].set_xticks(agents, [str(a) for a in agents])
    ax[2].set_xlabel("agents")
    ax[2].set_ylabel("keyframe arrival -> first correction [s]")
    ax[2].set_title("correction latency")
    ax[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _jsonable(rows: Sequence[Sequence[TeamRow]]) -> list[list[dict[str, Any]]]:
    return [[dataclasses.asdict(r) for r in runs] for runs in rows]


def write_scale(
    config: ScaleConfig,
    rows: Sequence[Sequence[TeamRow]],
    copies: Sequence[Sequence[AgentCopy]],
    cores: Sequence[CoreRow] = (),
) -> list[Path]:
    """Write ``scale.md`` and ``scale.png`` into ``config.out``, ``scale.json`` (every row,
    queue traces included) into ``config.work``."""
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    md = out / "scale.md"
    md.write_text(scale_markdown(config, rows, copies, cores))
    Path(config.work).mkdir(parents=True, exist_ok=True)
    js = Path(config.work) / "scale.json"
    js.write_text(json.dumps(_jsonable(rows), indent=1, default=str))
    png = out / "scale.png"
    scale_plot(rows, png)
    log.info("wrote %s, %s, %s", md, js, png)
    return [md, js, png]
