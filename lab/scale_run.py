"""``recslam experiment scale`` end to end: every team size replayed live to a cloud process
(:mod:`lab.scale_live`), optionally through the core in process (:mod:`lab.scale`), and the
report written (:mod:`lab.scale_report`). Kept apart from the three so that they import
:mod:`lab.scale` and this module drives them, one way."""

from __future__ import annotations

import logging
from typing import Any

from lab.scale import (
    CoreRow,
    ScaleConfig,
    TeamRow,
    core_replay,
    load_recordings,
    plan_copies,
    robots_of,
    team_row,
    timeline,
)
from lab.scale_live import LiveConfig, run_live
from lab.scale_report import write_scale

log = logging.getLogger(__name__)


def run_scale(config: ScaleConfig, live_config: Any = None) -> list[list[TeamRow]]:
    """Every team size, ``config.runs`` live replays each; writes the report; the rows (per
    team size, per run)."""

    live_cfg = live_config or LiveConfig()
    recordings = load_recordings(config.recordings)
    robots = [robots_of(r) for r in recordings]
    rows: list[list[TeamRow]] = []
    cores: list[CoreRow] = []
    for n in config.agents:
        copies = plan_copies(robots, n, config.shift_s)
        sends = timeline(recordings, copies, config.schedule)
        runs = []
        for k in range(config.runs):
            work = config.work / f"agents-{n}" / f"run{k}"
            log.info("%d agents (%d copies), run %d: %d messages", n, len(copies), k, len(sends))
            runs.append(team_row(n, run_live(sends, work, live_cfg)))
            r = runs[-1]
            log.info(
                "%d agents: %d keyframes, queue max %d, latency median %.2f s p95 %.2f s, "
                "worker busy %.0f %%",
                n,
                r.keyframes,
                r.queue_max,
                r.latency["median"],
                r.latency["p95"],
                100 * r.worker_busy,
            )
        rows.append(runs)
        if config.core:
            work = config.work / f"agents-{n}" / "core"
            cores.append(core_replay(sends, n, work / "state"))
        plans = [plan_copies(robots, m, config.shift_s) for m in config.agents[: len(rows)]]
        write_scale(config, rows, plans, cores)
    return rows
