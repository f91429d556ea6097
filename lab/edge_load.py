"""How one edge holds up as robots are added: stalls, timeouts and duplicates per run.

A run is the whole job as ``recslam demo --no-dashboard`` runs it (:func:`lab.links.run_job`);
:func:`read_run` takes from its folder what issue #20 item 0 asks for:

- the edge's longest event-loop stall and its stall histogram (``stats/edge.json``,
  ``loop_stalls``, measured by :mod:`common.transport.stalls`);
- peer timeouts: every ``PeerTimeoutError`` a service logged (``run/logs/*.log``), by log;
- per robot link: connections (1 = never reconnected), duplicates dropped, resent messages
  and late acks (a resend held back because the peer was talking, ``recovery.py``);
- joint and per-robot ATE, frames sent / decoded.

:func:`write_table` turns runs into a markdown table and a PNG.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lab.links import load_json

log = logging.getLogger(__name__)

_TIMEOUT = re.compile(r"PeerTimeoutError: (.*)$")


def timeouts(logs: Path) -> dict[str, int]:
    """``{log name: PeerTimeoutError lines}`` of every ``*.log`` in ``logs``."""
    out: dict[str, int] = {}
    for path in sorted(Path(logs).glob("*.log")):
        n = sum(
            1 for line in path.read_text(errors="replace").splitlines() if _TIMEOUT.search(line)
        )
        if n:
            out[path.stem] = n
    return out


def read_run(report_dir: Path) -> dict[str, Any]:
    """The numbers of one finished run in ``report_dir`` (``report.json`` + ``run/``)."""
    report_dir = Path(report_dir)
    rep = load_json(report_dir / "report.json")
    run = report_dir / "run"
    edge = load_json(run / "stats" / "edge.json")
    stalls = edge.get("loop_stalls", {})
    links = edge.get("links", {})
    robots = rep.get("robots", {})
    per_robot = {}
    for name, r in sorted(robots.items()):
        c = links.get(name, {})
        per_robot[name] = {
            "ate_m": r.get("ate_rmse_m"),
            "frames_sent": r.get("frames_sent"),
            "frames_decoded": r.get("frames_decoded"),
            "connections": c.get("connections"),
            "duplicates": c.get("duplicates_dropped", 0),
            "resent": c.get("retransmitted_messages", 0),
            "late_acks": c.get("late_acks", 0),
        }
    cloud_link = load_json(run / "stats" / "cloud.json").get("links", {})
    return {
        "folder": str(report_dir),
        "robots": len(robots),
        "joint_m": rep.get("ate", {}).get("joint_rmse_m"),
        "maps": len(rep.get("map", {}).get("maps", [])),
        "stall_max_s": stalls.get("max_s"),
        "stalls_over_1s": stalls.get("over_1s"),
        "timeouts": timeouts(run / "logs"),
        "duplicates": sum(r["duplicates"] for r in per_robot.values()),
        "reconnects": sum(max(0, (r["connections"] or 1) - 1) for r in per_robot.values()),
        "edge_cloud_connections": {e: c.get("connections") for e, c in cloud_link.items()},
        "frames_lost": sum(
            int(r.get("frames_sent") or 0) - int(r.get("frames_decoded") or 0)
            for r in per_robot.values()
        ),
        "per_robot": per_robot,
        "camera_s": rep.get("camera_s"),
        "wall_s": rep.get("wall_s"),
    }


def _s(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _cm(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.2f}"


def write_table(runs: Sequence[dict[str, Any]], out_md: Path, header: str) -> Path:
    """``out_md`` (markdown) and its PNG beside it, one row per run; returns the PNG path."""
    lines = [
        header,
        "",
        "| robots | longest loop stall [s] | stalls > 1 s | peer timeouts (all logs) | "
        "reconnects | duplicates dropped | frames lost | late acks (no resend) | maps | "
        "joint ATE [cm] | worst robot [cm] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        worst = max(
            (x["ate_m"] for x in r["per_robot"].values() if x["ate_m"] is not None), default=None
        )
        late = sum(x["late_acks"] for x in r["per_robot"].values())
        t = sum(r["timeouts"].values())
        lines.append(
            f"| {r['robots']} | {_s(r['stall_max_s'])} | "
            f"{r['stalls_over_1s']} | {t} | {r['reconnects']} | {r['duplicates']} | "
            f"{r['frames_lost']} | {late} | {r['maps']} | {_cm(r['joint_m'])} | {_cm(worst)} |"
        )
    out_md.parent.mkdir(parents=True, exist_ok=True)
    out_md.write_text("\n".join(lines) + "\n")
    png = out_md.with_suffix(".png")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    n = [f"{r['robots']} robots" for r in runs]
    axes[0].bar(n, [r["stall_max_s"] or 0 for r in runs], color="tab:blue")
    axes[0].axhline(10.0, color="tab:red", ls="--", lw=1, label="idle timeout (10 s)")
    axes[0].set(title="edge: longest event-loop stall", ylabel="s")
    axes[0].legend(fontsize=8)
    axes[1].bar(n, [r["duplicates"] for r in runs], color="tab:orange", label="duplicates")
    axes[1].plot(n, [sum(r["timeouts"].values()) for r in runs], "k^", label="timeouts")
    axes[1].set(title="duplicates dropped / peer timeouts")
    axes[1].legend(fontsize=8)
    axes[2].bar(n, [100 * (r["joint_m"] or 0) for r in runs], color="tab:green")
    axes[2].axhline(2.0, color="tab:red", ls="--", lw=1, label="target 2 cm")
    axes[2].set(title="joint ATE", ylabel="cm")
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png
