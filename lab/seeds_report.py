"""Reporting of ``recslam experiment seeds``: ``seeds.md``, ``seeds.json`` and ``seeds.png`` from
:func:`lab.seeds_run.run_seeds`'s data."""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path
from typing import Any

from lab.seeds import SeedTargets, fmt_cm, summarize

log = logging.getLogger(__name__)


def _mark(ok: bool) -> str:
    return "met" if ok else "**missed**"


def generator_text(g: dict[str, Any] | None) -> str:
    """A run's generator settings in words (``"default flights and room"`` when None)."""
    if not g:
        return "default flights and room"
    words = [f"flight {g['flight']}", f"world {g['world']}"]
    if g.get("trajectory_files"):
        words[0] = "recorded flights " + ", ".join(g["trajectory_files"])
    if g.get("exposure_steps"):
        words.append("exposure steps")
    if g.get("motion_blur_ms"):
        words.append(f"motion blur {g['motion_blur_ms']:g} ms")
    return ", ".join(words)


def seeds_markdown(data: dict[str, Any], table: str = "seeds") -> str:
    """The sweep as markdown: provenance, verdict, one row per run."""
    runs: dict[str, dict[str, Any]] = data["runs"]
    s = data["summary"]
    t = data["targets"]
    gens = sorted(
        {generator_text((r.get("dataset") or {}).get("generator")) for r in runs.values()}
    )
    harder = gens != ["default flights and room"]
    title = "# Joint ATE over the generator's seeds"
    lines = [
        f"{title}: harder worlds ({'; '.join(gens)})" if harder else title,
        "",
        f"Command: `{data['command']}`; commit {data['commit']}; {data['date']}. Each row is "
        "one run of the whole job as `recslam demo --no-dashboard` runs it (cloud, edge and "
        "robots as separate processes on loopback, coded wire), on the synthetic dataset of "
        "that seed. ATE: RMSE of the cloud's keyframe trajectories after SE(3) alignment, joint "
        "(all robots, one transform; only when they ended in one map) and per robot (each "
        "aligned alone), in cm; also the joint ATE after a Sim(3) alignment and its scale: "
        "how much of a run's error is one error of the whole map's scale.",
        "",
    ]
    if harder:
        lines += [
            "Generator settings of these runs (`recslam dataset synth` options, issue 17 item "
            f"5): {'; '.join(gens)}. The targets are those of the default flights; on harder "
            "flights they are stated, not expected.",
            "",
        ]
    if s is not None:
        lines += [
            f"Over {s['runs']} runs: median joint ATE **{fmt_cm(s['median_joint_m'])} cm** "
            f"(target ≤ {fmt_cm(t['median_joint_m'])}: {_mark(s['met']['median'])}), worst "
            f"**{fmt_cm(s['worst_joint_m'])} cm** (≤ {fmt_cm(t['worst_joint_m'])}: "
            f"{_mark(s['met']['worst'])}), worst robot {fmt_cm(s['worst_robot_m'])} cm "
            f"(≤ {fmt_cm(t['robot_m'])}: {_mark(s['met']['robots'])}), one map in "
            f"{s['one_map']} of {s['runs']} ({_mark(s['met']['one_map'])}); runs with lost "
            f"frames or a failed service: {s['failures']}; loop / merge constraints "
            f"contradicting the ground truth (> 0.3 m or 10°, a false merge or loop): "
            f"{s.get('wrong_constraints', '–')} of {s.get('constraints', '–')}.",
            "",
        ]
    if len(gens) > 1:
        lines += [*_by_generator(runs, SeedTargets(**t)), ""]
    names = sorted({n for r in runs.values() for n in r["per_robot_m"]})
    head = " | ".join(f"{n} cm" for n in names)
    lines += [
        f"| run | dataset | joint ATE cm | {head} | joint ATE Sim(3) cm | scale | maps "
        "| merges | loops | frames lost | wrong constraints | failed |",
        "|---|---|---|" + "---|" * len(names) + "---|---|---|---|---|---|---|---|",
    ]
    for name, r in sorted(runs.items(), key=lambda kv: _order(kv[0])):
        d = r.get("dataset") or {}
        ds = (
            f"{d.get('robots')} x {d.get('seconds'):g} s, seed {d.get('seed')}"
            if d.get("seconds") is not None
            else "–"
        )
        if d.get("generator"):
            ds += f", {generator_text(d['generator'])}"
        cells = " | ".join(fmt_cm(r["per_robot_m"].get(n)) for n in names)
        scale = r.get("scale")
        lines.append(
            f"| {name} | {ds} | {fmt_cm(r['joint_m'])} | {cells} "
            f"| {fmt_cm(r.get('sim3_joint_m'))} | {'–' if scale is None else f'{scale:.4f}'} "
            f"| {r['maps']} | {r['merges']} | {r['loops']} | {r['frames_lost']} "
            f"| {_wrong(r)} | {', '.join(r['failed']) or '–'} |"
        )
    if data["errors"]:
        lines += ["", "Runs that did not finish:", ""] + [f"- {e}" for e in data["errors"]]
    lines += ["", f"![{table}.png]({table}.png)", ""]
    return "\n".join(lines)


def _wrong(r: dict[str, Any]) -> str:
    """``wrong / all (max error)`` of a run's loop and merge constraints, or –."""
    if r.get("constraints") is None:
        return "–"
    worst = (
        ""
        if r.get("max_constraint_err_m") is None
        else f" (max {100 * r['max_constraint_err_m']:.1f} cm, {r['max_constraint_err_deg']:.1f}°)"
    )
    return f"{r['wrong_constraints']} / {r['constraints']}{worst}"


def _by_generator(runs: dict[str, dict[str, Any]], targets: SeedTargets) -> list[str]:
    """One row per generator setting: the summary of its runs (:func:`lab.seeds.summarize`)."""
    groups: dict[str, dict[str, dict[str, Any]]] = {}
    for name, r in runs.items():
        text = generator_text((r.get("dataset") or {}).get("generator"))
        groups.setdefault(text, {})[name] = r
    lines = [
        "| generator | runs | median joint ATE cm | worst joint ATE cm | worst robot cm "
        "| one map | wrong constraints |",
        "|---|---|---|---|---|---|---|",
    ]
    for text, group in sorted(groups.items()):
        g = summarize(group, targets)
        lines.append(
            f"| {text} | {g['runs']} | {fmt_cm(g['median_joint_m'])} "
            f"| {fmt_cm(g['worst_joint_m'])} | {fmt_cm(g['worst_robot_m'])} "
            f"| {g['one_map']} of {g['runs']} "
            f"| {g.get('wrong_constraints', '–')} of {g.get('constraints', '–')} |"
        )
    return lines


def _order(name: str) -> tuple[str, int, str]:
    """Runs by their generator tag, then seed (``seed-10`` after ``seed-9``), then name."""
    m = re.search(r"^(.*?)seed-(\d+)$", name)
    if m:
        return (m.group(1), int(m.group(2)), name)
    digits = re.search(r"\d+", name)
    return ("", int(digits.group()) if digits else 1 << 30, name)


def seeds_plot(data: dict[str, Any], path: Path) -> None:
    """Joint ATE per run (bars) with each robot's (dots) and the targets (lines)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = sorted(data["runs"].items(), key=lambda kv: _order(kv[0]))
    t = data["targets"]
    fig, ax = plt.subplots(figsize=(max(5.0, 0.8 * len(runs) + 2), 3.6))
    xs = range(len(runs))
    joint = [100 * (r["joint_m"] or 0.0) for _, r in runs]
    ax.bar(xs, joint, color="#4c78a8", label="joint")
    for x, (_, r) in zip(xs, runs, strict=True):
        vals = [100 * v for v in r["per_robot_m"].values() if v is not None]
        ax.plot([x] * len(vals), vals, "o", color="#f58518", ms=4, label=None)
    ax.plot([], [], "o", color="#f58518", ms=4, label="each robot")
    ax.axhline(100 * t["median_joint_m"], color="#54a24b", ls="--", lw=1, label="median target")
    ax.axhline(100 * t["worst_joint_m"], color="#e45756", ls="--", lw=1, label="worst target")
    ax.set_xticks(list(xs), [n for n, _ in runs], rotation=30, ha="right")
    ax.set_ylabel("ATE cm")
    ax.set_title("Joint and per-robot ATE per run")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_seeds(
    data: dict[str, Any], out: Path, results: Path | None, name: str = "seeds"
) -> list[Path]:
    """``NAME.md``, ``NAME.json``, ``NAME.png`` into ``out`` (the markdown and the plot also
    copied to ``results``)."""
    out.mkdir(parents=True, exist_ok=True)
    md, js, png = out / f"{name}.md", out / f"{name}.json", out / f"{name}.png"
    md.write_text(seeds_markdown(data, name))
    js.write_text(json.dumps(data, indent=2, default=str))
    seeds_plot(data, png)
    files = [md, js, png]
    if results is not None:
        results.mkdir(parents=True, exist_ok=True)
        for f in (md, png):
            shutil.copy2(f, results / f.name)
            files.append(results / f.name)
    log.info("wrote %s", ", ".join(str(f) for f in files))
    return files
