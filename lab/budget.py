"""The rate–accuracy–latency curve: the whole job over shaped links, with and without the
fresh-before-complete rules (``benchmarks/bench_budget.py``).

Each row is one whole run (cloud, edge and robots as processes, ``lab.run.orchestration``)
over links shaped by kernel ``tbf`` in network namespaces (``lab.netns``; or the throttling
proxy, ``--shaper proxy``), named ``LINK[/MODE]``:

- ``LINK``: ``unlimited`` or the link's rate in kbit/s per robot (each direction);
- no mode: today's recorder (every frame, in order, the playback waits for tracking);
- ``/fresh``: the robots play as live drivers (``recslam robot --live``), with
  ``--uplink-budget LINK`` (none when unlimited), and the edge gives its VIO no non-keyframe
  more than ``--max-vio-lag`` behind (0.5 s);
- ``/auto``: the same with ``--uplink-budget auto`` (the robot measures the link's rate);
- ``/cloudN`` (after the mode): the edge's ``--cloud-budget N`` (kbit/s, or ``auto``): robot
  keyframes go up to the cloud only as far apart as N carries them (the edge->cloud link is
  not shaped here: the row shows what the edge sends under the budget);
- ``/cut`` (after the mode): every robot's link goes down :data:`CUT` s after the robots
  started, for the time given there (tbf: ``ip link set down`` on the robots' veth ends).

Per row: rates both ways, frames in / sent / decoded (lost = sent − decoded: must be 0), what
the rules left out, the pose latency at the robot (camera → pose back; the worst robot's
median / p95 / max), keyframes, maps, joint ATE of the keyframes and of every frame.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.errors import RecslamError

log = logging.getLogger(__name__)

MODES = ("", "fresh", "auto")
MAX_VIO_LAG_S = 0.5
CUT = (30.0, 20.0)
"""The outage of a ``/cut`` row: (at, for) seconds after the robots started."""


@dataclass(frozen=True)
class Row:
    """One run: the link's rate (None: unlimited) and the mode (one of :data:`MODES`)."""

    link_kbps: float | None
    mode: str = ""
    cut: bool = False
    cloud: str = ""  # the edge's --cloud-budget ("": none)

    @property
    def name(self) -> str:
        link = "unlimited" if self.link_kbps is None else f"{self.link_kbps:g}"
        name = f"{link}/{self.mode}" if self.mode else link
        name = f"{name}/cloud{self.cloud}" if self.cloud else name
        return name + "/cut" if self.cut else name

    def robot_args(self) -> tuple[str, ...]:
        if not self.mode:
            return ()
        if self.mode == "auto":
            return ("--live", "--uplink-budget", "auto")
        if self.link_kbps is None:
            return ("--live",)
        return ("--live", "--uplink-budget", f"{self.link_kbps:g}")

    def edge_args(self) -> tuple[str, ...]:
        lag = ("--max-vio-lag", f"{MAX_VIO_LAG_S:g}") if self.mode else ()
        return (*lag, "--cloud-budget", self.cloud) if self.cloud else lag


def parse_rows(text: str) -> list[Row]:
    """``unlimited,unlimited/fresh,50,50/fresh,50/auto`` -> rows (RecslamError names a bad
    item)."""
    rows = []
    for item in (x.strip() for x in text.split(",") if x.strip()):
        link, *parts = item.split("/")
        cut = bool(parts) and parts[-1] == "cut"
        parts = parts[:-1] if cut else parts
        cloud = parts.pop().removeprefix("cloud") if parts and parts[-1][:5] == "cloud" else None
        mode = parts[0] if len(parts) == 1 else "" if not parts else "?"
        if mode not in MODES:
            raise RecslamError(f"row {item!r}: mode must be one of fresh, auto (or none)")
        if cloud is not None and not _cloud_budget_ok(cloud):
            raise RecslamError(f"row {item!r}: LINK[/MODE][/cloudN][/cut], N kbit/s or auto")
        cloud = cloud or ""
        if link == "unlimited":
            rows.append(Row(None, mode, cut, cloud))
            continue
        try:
            kbps = float(link)
        except ValueError:
            raise RecslamError(f"row {item!r}: {link!r} is not kbit/s or 'unlimited'") from None
        if not kbps > 0:
            raise RecslamError(f"row {item!r}: the rate must be positive")
        rows.append(Row(kbps, mode, cut, cloud))
    if not rows:
        raise RecslamError("no rows")
    return rows


def _cloud_budget_ok(text: str) -> bool:
    try:
        return text == "auto" or float(text) > 0
    except ValueError:
        return False


def run_rows(
    data: Path,
    robots: tuple[str, ...],
    rows: list[Row],
    out: Path,
    timeout_s: float,
    shaper: str = "tbf",
    progress: Callable[[str], None] = log.info,
) -> list[dict[str, Any]]:
    """Every row in turn (``OUT/<row>/``); returns the table rows (also ``OUT/budget.json``)."""
    from lab.bandwidth import run_budget

    if not data.is_dir():
        raise RecslamError(f"--data {data}: no such dataset folder (recslam dataset synth)")
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for row in rows:
        progress(f"== {row.name}: robots {' '.join(row.robot_args())}; edge {row.edge_args()}")
        t = time.perf_counter()
        result = run_budget(
            data,
            robots,
            row.link_kbps,
            out / row.name.replace("/", "-"),
            timeout_s,
            shaper,
            robot_args=row.robot_args(),
            edge_args=row.edge_args(),
            cut=CUT if row.cut else None,
        )
        result["row"] = row.name
        if row.cut:
            result["recovery_s"] = _recovery(out / row.name.replace("/", "-"))
        results.append(result)
        (out / "budget.json").write_text(json.dumps(results, indent=1, default=str))
        progress(f"   done in {time.perf_counter() - t:.0f} s: {result}")
    return results


def _recovery(out: Path) -> float | None:
    """The slowest robot's time from reconnecting until its pose latency stayed under 1 s
    (``lab.bandwidth.recovery_s``; None if a robot never got there)."""
    from lab.bandwidth import recovery_s

    times = []
    for path in sorted((out / "run" / "stats").glob("robot-*.json")):
        series = json.loads(path.read_text()).get("latency_series", [])
        times.append(recovery_s(series, CUT[0] + CUT[1]))
    return None if not times or None in times else max(t for t in times if t is not None)


def _f(x: Any, spec: str) -> str:
    return "–" if x is None or x != x else format(x, spec)


def _cm(x: Any) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def table(results: list[dict[str, Any]]) -> str:
    """The markdown table of :func:`run_rows`' results."""
    lines = [
        "| row | up kbit/s | down kbit/s | to cloud kbit/s | frames in / sent / decoded | "
        "lost | left out (budget) | dropped (live) | skipped (VIO late) | poses back | "
        "latency median / p95 / max s | keyframes | maps | joint ATE keyframes cm | "
        "joint ATE every frame cm | robots' own ATE (mean) cm | streaming s | "
        "latency < 1 s again after reconnecting s | keyframes to cloud / kept on edge |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lost = r["frames_sent"] - r["frames_decoded"]
        lines.append(
            f"| {r['row']} | {_f(r['achieved_kbit_s'], '.1f')} | "
            f"{_f(r.get('down_kbit_s'), '.1f')} | {_f(r.get('to_cloud_kbit_s'), '.1f')} | "
            f"{r.get('frames_in')} / {r['frames_sent']} / {r['frames_decoded']} | {lost} | "
            f"{r.get('left_out')} | {r.get('dropped_live')} | {r.get('skipped_stale')} | "
            f"{r.get('poses_received')} | {_f(r.get('latency_median_s'), '.2f')} / "
            f"{_f(r.get('latency_p95_s'), '.2f')} / {_f(r.get('latency_max_s'), '.2f')} | "
            f"{r['keyframes']} | {r.get('maps')} | {_cm(r['ate_joint_m'])} | "
            f"{_cm(r.get('frames_ate_joint_m'))} | {_cm(r['ate_own_mean_m'])} | "
            f"{_f(r['stream_s'], '.0f')} | {_f(r.get('recovery_s'), '.1f')} | "
            f"{r.get('keyframes_uplinked', '–')} / {r.get('kept_on_edge', '–')} |"
        )
    return "\n".join(lines) + "\n"


def plot(results: list[dict[str, Any]], path: Path) -> None:
    """Latency p95 and joint ATE per row (log latency: minutes against a second)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["row"] for r in results]
    x = range(len(names))
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    p95 = [r.get("latency_p95_s") or float("nan") for r in results]
    med = [r.get("latency_median_s") or float("nan") for r in results]
    a1.bar([i - 0.2 for i in x], med, 0.4, label="median")
    a1.bar([i + 0.2 for i in x], p95, 0.4, label="p95")
    a1.axhline(1.0, color="k", ls="--", lw=1, label="1 s target")
    a1.set_yscale("log")
    a1.set_ylabel("pose latency at the robot [s] (worst robot)")
    a1.set_xticks(list(x), names, rotation=30, ha="right")
    a1.legend()
    kf = [100 * (r["ate_joint_m"] or float("nan")) for r in results]
    fr = [100 * (r.get("frames_ate_joint_m") or float("nan")) for r in results]
    a2.bar([i - 0.2 for i in x], kf, 0.4, label="keyframes")
    a2.bar([i + 0.2 for i in x], fr, 0.4, label="every frame")
    a2.set_yscale("log")
    a2.set_ylabel("joint ATE [cm] (no bar: no map)")
    a2.set_xticks(list(x), names, rotation=30, ha="right")
    a2.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
