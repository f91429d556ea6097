"""Reporting of ``recslam experiment links``: ``links.md``, ``links.json`` and ``links.png``
from :func:`lab.links.build_data`'s data (the runs and their numbers are in :mod:`lab.links`).
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from lab.links import (
    DIRECTIONS,
    ROBOT_DIRECTIONS,
    RunMetrics,
    Stat,
    bits_per_message,
    codec_ms,
    family,
    family_sum,
    prefix_bits_per_item,
    stat_of,
)

log = logging.getLogger(__name__)

SMALL_KBIT_S = 0.05
"""Message types below this rate (kbit/s at camera rate, every format) share one row."""
RATIO = ("raw", "coded")
"""The ratio column: the first format's number over the second's."""
ITEMS = (
    ("robot->edge", "RobotFrame", "frames_decoded", "RobotFrame* per frame decoded"),
    ("edge->cloud", "Keyframe", "keyframes_uplinked", "Keyframe* per keyframe uplinked"),
    (
        "edge->cloud",
        "MapPoint",
        "map_points_peak",
        "MapPoint* per map point (peak count at the cloud, before MBP: an upper bound)",
    ),
)
"""Bits per item: (direction, message-type prefix, ``items`` key, label)."""
ARROW = {d: d.replace("->", "→") for d in DIRECTIONS}

Runs = dict[str, list[RunMetrics]]
"""The runs of one dataset per wire format."""
Getter = Callable[[RunMetrics], Any]
"""One number of a run (None or a KeyError: no value)."""


def fmt(s: Stat | None, spec: str = ".1f") -> str:
    """``mean`` or, over several runs that differ, ``mean (min–max)``; ``–`` for no value."""
    if s is None:
        return "–"
    text, lo, hi = (format(s[k], spec) for k in ("mean", "min", "max"))
    return f"{text} ({lo}–{hi})" if s["n"] > 1 and lo != hi else text


def ratio(a: Stat | None, b: Stat | None) -> str:
    """``×(a / b)`` of the means (``–`` when either is missing or b is 0)."""
    if a is None or b is None or not b["mean"]:
        return "–"
    return f"×{a['mean'] / b['mean']:.3g}"


def _has_ratio(wires: Sequence[str]) -> bool:
    return all(w in wires for w in RATIO)


def _cells(
    runs: Runs, wires: Sequence[str], get: Callable[[RunMetrics], Any], spec: str = ".1f"
) -> list[str]:
    """One cell per wire, plus the ratio cell when both formats ran."""
    stats = {w: stat_of(runs.get(w, []), get) for w in wires}
    cells = [fmt(stats[w], spec) for w in wires]
    if _has_ratio(wires):
        cells.append(ratio(stats[RATIO[0]], stats[RATIO[1]]))
    return cells


def families(runs: Runs, direction: str) -> dict[str, list[str]]:
    """``{row: [message types]}`` of a direction over every run, largest rate first."""
    members: dict[str, set[str]] = {}
    peak: dict[str, float] = {}
    for rs in runs.values():
        for r in rs:
            for t, e in r["links"][direction]["types"].items():
                members.setdefault(family(t), set()).add(t)
                peak[family(t)] = max(peak.get(family(t), 0.0), e["kbit_s"])
    order = sorted(members, key=lambda f: (-peak[f], f))
    return {f: sorted(members[f]) for f in order}


def family_label(fam: str, members: Sequence[str]) -> str:
    """``KeyframeUpdate(+Coded)`` when both forms appear, else the one type name."""
    if len(members) == 1:
        return members[0]
    extra = [m[len(fam) :] for m in members if m != fam]
    return fam + "".join(f"(+{x})" for x in extra)


def at(*path: str) -> Getter:
    """A getter of ``run[path[0]][path[1]]...``."""

    def get(run: RunMetrics) -> Any:
        x: Any = run
        for key in path:
            x = x[key]
        return x

    return get


def _sum_of(getters: Sequence[Getter]) -> Getter:
    """A getter of the sum of the getters' values (those not None)."""

    def get(run: RunMetrics) -> float:
        values = [g(run) for g in getters]
        return sum(v for v in values if v is not None)

    return get


def _row(label: str, runs: Runs, wires: Sequence[str], get: Getter, spec: str = ".1f") -> str:
    return f"| {label} | " + " | ".join(_cells(runs, wires, get, spec)) + " |"


def _split_small(runs: Runs, direction: str) -> tuple[dict[str, list[str]], list[str]]:
    """The direction's rows, and the families too small for a row of their own."""
    rows, small = {}, []
    for fam, members in families(runs, direction).items():
        get = partial(family_sum, direction=direction, fam=fam, key="kbit_s")
        means = [s["mean"] for rs in runs.values() if (s := stat_of(rs, get)) is not None]
        if max(means, default=0.0) < SMALL_KBIT_S:
            small.append(fam)
        else:
            rows[fam] = members
    return rows, small


def _link_name(direction: str) -> str:
    return ARROW[direction] + (" (per robot)" if direction in ROBOT_DIRECTIONS else " (total)")


def _ratio_head(wires: Sequence[str]) -> str:
    return " | raw / coded" if _has_ratio(wires) else ""


def rate_table(runs: Runs, wires: Sequence[str]) -> list[str]:
    """kbit/s at camera rate per direction and message type."""
    n = len(wires) + _has_ratio(wires)
    lines = [
        f"| link | message type | {' | '.join(wires)}{_ratio_head(wires)} |",
        "|---|---|" + "---|" * n,
    ]
    for d in DIRECTIONS:
        total = _cells(runs, wires, at("links", d, "kbit_s"))
        lines.append(
            f"| {_link_name(d)} | **all** | " + " | ".join(f"**{c}**" for c in total) + " |"
        )
        if d in ROBOT_DIRECTIONS:
            lines.append(_row("| all, worst robot", runs, wires, at("links", d, "kbit_s_max")))
        rows, small = _split_small(runs, d)
        for fam, members in rows.items():
            get: Getter = partial(family_sum, direction=d, fam=fam, key="kbit_s")
            lines.append(_row(f"| {family_label(fam, members)}", runs, wires, get))
        if small:
            get = _sum_of([partial(family_sum, direction=d, fam=f, key="kbit_s") for f in small])
            lines.append(_row(f"| other ({', '.join(small)})", runs, wires, get, ".2f"))
    return lines


def robot_table(runs: Runs, wires: Sequence[str]) -> list[str]:
    """Per robot: both robot-link rates, ATE (own / joint alignment), frames decoded."""
    names = sorted({n for rs in runs.values() for r in rs for n in r["per_robot"]})
    cols = [
        ("robot→edge kbit/s", "robot->edge", ".1f"),
        ("edge→robot kbit/s", "edge->robot", ".1f"),
        ("ATE m", "ate_m", ".3f"),
        ("ATE m (joint alignment)", "ate_joint_m", ".3f"),
        ("frames decoded", "frames_decoded", ".0f"),
    ]
    head = " | ".join(f"{label} {w}" for label, _, _ in cols for w in wires)
    lines = [f"| robot | {head} |", "|---|" + "---|" * (len(cols) * len(wires))]
    for name in names:
        cells = [
            fmt(stat_of(runs.get(w, []), at("per_robot", name, key)), spec)
            for _, key, spec in cols
            for w in wires
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def bits_table(runs: Runs, wires: Sequence[str]) -> list[str]:
    """Messages and bits per message of each type, then bits per frame / keyframe / point."""
    msgs = " | ".join(f"messages {w}" for w in wires)
    bits = " | ".join(f"bits/message {w}" for w in wires)
    n = 2 * len(wires) + _has_ratio(wires)
    lines = [
        f"| link | message type | {msgs} | {bits}{_ratio_head(wires)} |",
        "|---|---|" + "---|" * n,
    ]
    for d in DIRECTIONS:
        rows, _ = _split_small(runs, d)
        for i, (fam, members) in enumerate(rows.items()):
            count = partial(family_sum, direction=d, fam=fam, key="messages")
            counts = [fmt(stat_of(runs.get(w, []), count), ".0f") for w in wires]
            cells = _cells(runs, wires, partial(bits_per_message, direction=d, fam=fam), ".0f")
            link = ARROW[d] if i == 0 else ""
            label = family_label(fam, members)
            lines.append(f"| {link} | {label} | " + " | ".join(counts + cells) + " |")
    lines += [
        "",
        f"| bits per item | {' | '.join(wires)}{_ratio_head(wires)} |",
        "|---|" + "---|" * (n - len(wires)),
    ]
    for d, prefix, item, label in ITEMS:
        get = partial(prefix_bits_per_item, direction=d, prefix=prefix, item=item)
        lines.append(_row(f"{ARROW[d]} {label}", runs, wires, get, ".0f"))
    return lines


def codec_table(runs: Runs, wires: Sequence[str]) -> list[str]:
    """Codec CPU per message (ms) of every timed step; a note when no run timed any."""
    keys = sorted(
        {
            (where, k)
            for rs in runs.values()
            for r in rs
            for where, t in r["codec_cpu"].items()
            for k in t
        }
    )
    if not keys:
        return ["No codec timings in these runs' stats (no `codec_cpu` in edge.json / cloud.json)."]
    msgs = " | ".join(f"messages {w}" for w in wires)
    ms = " | ".join(f"ms/message {w}" for w in wires)
    lines = [f"| where | step | {msgs} | {ms} |", "|---|---|" + "---|" * (2 * len(wires))]
    for where, key in keys:
        count = at("codec_cpu", where, key, "messages")
        counts = [fmt(stat_of(runs.get(w, []), count), ".0f") for w in wires]
        per = partial(codec_ms, where=where, key=key)
        cells = [fmt(stat_of(runs.get(w, []), per), ".3f") for w in wires]
        lines.append(f"| {where} | {key} | " + " | ".join(counts + cells) + " |")
    return lines


ACCURACY = (
    ("joint ATE m", ("ate_joint_m",), ".3f"),
    ("ATE per robot (own alignment), mean m", ("ate_robot_mean_m",), ".3f"),
    ("frames sent", ("frames_sent",), ".0f"),
    ("frames decoded", ("frames_decoded",), ".0f"),
    ("frames lost", ("frames_lost",), ".0f"),
    ("keyframes uplinked", ("keyframes_uplinked",), ".0f"),
    (
        "keyframes / map points at the cloud after MBP",
        ("keyframes_after_mbp", "map_points_after_mbp"),
        ".0f",
    ),
    ("maps", ("maps",), ".0f"),
    ("merges", ("merges",), ".0f"),
    ("loops", ("loops",), ".0f"),
)
"""Rows of the accuracy table: label, ``accuracy`` keys (one cell each, joined by /), format."""


def accuracy_table(runs: Runs, wires: Sequence[str]) -> list[str]:
    """ATE, frames, maps, merges per format; failed services, timing and runs."""

    def cell(w: str, getters: Sequence[Getter], spec: str) -> str:
        return " / ".join(fmt(stat_of(runs.get(w, []), g), spec) for g in getters)

    lines = [f"| | {' | '.join(wires)} |", "|---|" + "---|" * len(wires)]
    rows = [(label, [at("accuracy", k) for k in keys], spec) for label, keys, spec in ACCURACY]
    rows.append(("robots streaming / whole run s", [at("stream_s"), at("wall_s")], ".0f"))
    for label, getters, spec in rows:
        lines.append(f"| {label} | " + " | ".join(cell(w, getters, spec) for w in wires) + " |")
    failed = [
        ", ".join(sorted({f for r in runs.get(w, []) for f in r["failed"]})) or "none"
        for w in wires
    ]
    lines.append("| failed services | " + " | ".join(failed) + " |")
    lines.append("| runs | " + " | ".join(str(len(runs.get(w, []))) for w in wires) + " |")
    return lines


def verdict_line(wire: str, checks: Sequence[dict[str, Any]]) -> str:
    """``**coded**: robot→edge 120.3 ≤ 150 ✓ (per robot, worst) · ... — 2 of 3 targets met``."""
    parts, met = [], 0
    for c in checks:
        if c["value"] is None:
            parts.append(f"{ARROW[c['link']]} n/a")
            continue
        met += bool(c["ok"])
        sign, mark = ("≤", "✓") if c["ok"] else (">", "✗")
        parts.append(
            f"{ARROW[c['link']]} {c['value']:.1f} {sign} {c['limit']:g} {mark} ({c['what']})"
        )
    return f"**{wire}**: " + " · ".join(parts) + f" — {met} of {len(checks)} targets met"


def render_markdown(data: dict[str, Any]) -> str:
    """``links.md`` text."""
    wires = data["wires"]
    t = data["targets"]
    counts = sorted(
        {len(w["runs"]) for d in data["datasets"].values() for w in d["wires"].values()}
    )
    several = any(c > 1 for c in counts)
    lines = [
        "# Link bit budget: " + " vs ".join(wires) + " wire",
        "",
        f"Command: `{data['command']}`; commit {data['commit']}; {data['date']}.",
        "",
    ]
    data_lines = []
    for name, d in data["datasets"].items():
        where = f"`{d['path']}`" if d["path"] else "existing run folders"
        data_lines.append(
            f"`{name}` ({where}: {d['robots']} robots, {d['camera_s']:.1f} s of camera)"
        )
    lines += [
        "Data: " + "; ".join(data_lines) + ". Each run is the whole job as `recslam demo "
        "--no-dashboard --rate realtime --wire W` runs it (cloud, edge and robots as separate "
        "processes on loopback; the edge's `--wire` sets the format of everything the edge sends, "
        "the robots' frames are coded in both).",
        "",
        "Rates are kbit/s at camera rate: a link's bytes (the transport's counters, framing and "
        "control messages included) over the sequence's camera duration (frames / 20 Hz), "
        "1 kbit = 1000 bit: what the link carries when everything keeps up with the camera. "
        "Robot↔edge links per robot (mean over the robots; 'worst robot' = the largest), "
        "edge↔cloud in total. A type `XCoded` is shown on the row of `X`."
        + (" 'raw / coded' is the ratio of the means." if _has_ratio(wires) else ""),
        "",
        f"Targets: robot→edge ≤ {t['robot_edge_kbit_s']:g} kbit/s per robot, edge→robot ≤ "
        f"{t['edge_robot_kbit_s']:g} kbit/s per robot, edge→cloud ≤ {t['edge_cloud_kbit_s']:g} "
        f"kbit/s for {t['edge_cloud_robots']} robots (scaled to the number of robots).",
        "",
    ]
    if several:
        lines += [
            f"Runs per format: {', '.join(map(str, counts))}. Every number is the mean over the "
            "runs, with the min–max spread over the runs in brackets (none: the runs agree).",
            "",
        ]
    else:
        lines += ["One run per format: no spread over runs.", ""]
    if data["errors"]:
        lines += ["Runs that failed (left out):", ""] + [f"- {e}" for e in data["errors"]] + [""]
    for name, d in data["datasets"].items():
        runs: Runs = {w: e["runs"] for w, e in d["wires"].items()}
        present = [w for w in wires if w in runs]
        lines += [f"## {name}", "", "Verdict (means over runs):", ""]
        lines += [f"- {verdict_line(w, d['wires'][w]['verdict'])}" for w in present]
        lines += ["", "### kbit/s at camera rate", "", *rate_table(runs, present)]
        lines += ["", "### Per robot (kbit/s at camera rate, ATE)", "", *robot_table(runs, present)]
        lines += ["", "### Bits per message", ""]
        lines += [
            f"Types under {SMALL_KBIT_S} kbit/s in every format are left out (the 'other' rows "
            "above). Bits per item: the bytes of every type whose name starts so, per item.",
            "",
        ]
        lines += bits_table(runs, present)
        lines += ["", "### Codec CPU per message (ms, wall clock of the codec calls)", ""]
        lines += codec_table(runs, present)
        lines += ["", "### Accuracy and map", "", *accuracy_table(runs, present)]
        lines.append("")
    lines += ["![links.png](links.png)", ""]
    return "\n".join(lines)


def _rates_panel(ax: Any, name: str, d: dict[str, Any], wires: Sequence[str], t: dict) -> None:
    """Grouped bars: mean kbit/s per direction and format, min–max whiskers over runs (when
    several), the worst robot (▼) on the robot links, the targets dashed; log scale."""
    width = 0.8 / max(len(wires), 1)
    for i, w in enumerate(wires):
        runs = d["wires"][w]["runs"]
        stats = [stat_of(runs, at("links", dd, "kbit_s")) for dd in DIRECTIONS]
        xs = [j + (i - (len(wires) - 1) / 2) * width for j in range(len(DIRECTIONS))]
        means = [s["mean"] if s else 0.0 for s in stats]
        err = None
        if len(runs) > 1:
            err = [
                [s["mean"] - s["min"] if s else 0.0 for s in stats],
                [s["max"] - s["mean"] if s else 0.0 for s in stats],
            ]
        bars = ax.bar(xs, means, width, yerr=err, capsize=3, label=w)
        ax.bar_label(bars, labels=[f"{m:.1f}" for m in means], fontsize=7, label_type="center")
        for j, dd in enumerate(DIRECTIONS):
            worst = stat_of(runs, at("links", dd, "kbit_s_max"))
            if dd in ROBOT_DIRECTIONS and worst is not None:
                ax.plot(
                    xs[j],
                    worst["mean"],
                    "k_",
                    ms=14,
                    mew=2,
                    label="worst robot" if i + j == 0 else None,
                )
    scale = d["robots"] / t["edge_cloud_robots"] if d["robots"] else 1.0
    limits = {
        "robot->edge": t["robot_edge_kbit_s"],
        "edge->robot": t["edge_robot_kbit_s"],
        "edge->cloud": t["edge_cloud_kbit_s"] * scale,
    }
    for j, dd in enumerate(DIRECTIONS):
        if dd in limits:
            label = "target" if j == 0 else None
            ax.hlines(limits[dd], j - 0.45, j + 0.45, colors="k", linestyles="--", label=label)
    ax.set_yscale("log")
    ax.set_xticks(range(len(DIRECTIONS)))
    ax.set_xticklabels(
        [ARROW[dd] + ("\nper robot" if dd in ROBOT_DIRECTIONS else "\ntotal") for dd in DIRECTIONS]
    )
    ax.set_ylabel("kbit/s at camera rate")
    ax.set_title(f"{name}: link rates")
    ax.legend(fontsize=8)


def _ate_panel(ax: Any, name: str, d: dict[str, Any], wires: Sequence[str]) -> None:
    """Joint ATE of every run (x: the run's index), one series per format."""
    last = 1
    for i, w in enumerate(wires):
        points = [
            (r["run"], r["accuracy"]["ate_joint_m"])
            for r in d["wires"][w]["runs"]
            if r["accuracy"]["ate_joint_m"] is not None
        ]
        if points:
            ks, ates = zip(*points, strict=True)
            last = max(last, *ks)
            ax.plot([k + 0.05 * (i - (len(wires) - 1) / 2) for k in ks], ates, "o-", label=w)
    ax.set_xticks(range(1, last + 1))
    ax.set_xlim(0.5, last + 0.5)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("run")
    ax.set_ylabel("joint ATE RMSE (m)")
    ax.set_title(f"{name}: joint ATE per run")
    ax.legend(fontsize=8)


def plot(data: dict[str, Any], path: Path) -> None:
    """``links.png``: per dataset (one row each), the link rates of both formats and the
    joint ATE of every run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(data["datasets"])
    fig, axes = plt.subplots(
        len(names),
        2,
        figsize=(13, 4.2 * len(names)),
        squeeze=False,
        gridspec_kw={"width_ratios": [2.2, 1]},
    )
    for row, name in enumerate(names):
        d = data["datasets"][name]
        wires = [w for w in data["wires"] if w in d["wires"]]
        _rates_panel(axes[row][0], name, d, wires, data["targets"])
        _ate_panel(axes[row][1], name, d, wires)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_links(data: dict[str, Any], out: Path, results: Path | None) -> list[Path]:
    """Write ``links.md``, ``links.json`` and ``links.png`` into ``out`` (md and png also into
    ``results`` unless None); returns the files written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "links.md", out / "links.json", out / "links.png"]
    files[0].write_text(render_markdown(data))
    files[1].write_text(json.dumps(data, indent=2))
    plot(data, files[2])
    if results is not None:
        results = Path(results)
        results.mkdir(parents=True, exist_ok=True)
        for f in (files[0], files[2]):
            shutil.copy(f, results / f.name)
            files.append(results / f.name)
    log.info("wrote %s", ", ".join(str(f) for f in files))
    return files
