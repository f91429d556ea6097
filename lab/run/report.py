"""The run report: ``REPORT_DIR/report.md``, ``report.json`` and PNGs from one run folder.

Inputs (see ``lab.run.orchestration``): the cloud's result folder (``results/eval/ate.json``
and its plots, ``results/cloud_maps.json``), the last edge and cloud counters
(``stats/{edge,cloud}.json``, with several edges one ``stats/edge-<name>.json`` each: a
robot's counters are summed over the edges that served it, its links are shown per edge, and
a table of sites gives each edge's robots and rates) and their history
(``stats/samples.jsonl``).

Bandwidth is the traffic counters of each link divided by the robots' streaming time
(first robot start to last robot exit), in kbit/s (1 kbit = 1000 bit), and divided by the
sequence's camera duration (the rate needed in real time, when the machine keeps up).
Robot→edge bytes are what the edge received from each robot (``RobotFrame``, keyframes
included: the robot's coded frames are one message type, so the counters cannot separate KF
from non-KF), edge→cloud what the cloud received from the edge. Bits per feature are not in
the counters; the report gives bits per frame instead.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lab.run.sites import SINGLE_EDGE, merge_edge_stats

log = logging.getLogger(__name__)

CAMERA_HZ = 20.0  # synthetic and EuRoC cameras
PLOTS = ("trajectories_joint.png", "trajectories_individual.png", "ate_over_time.png")


@dataclass(frozen=True)
class RunFacts:
    """What the orchestrator knows beyond the files: timing and exit codes.

    Attributes:
        stream_s: robots' streaming time (s): first robot start to last robot exit.
        wall_s: whole run (s), dataset build excluded.
        exit_codes: last exit code of every service.
        frames_sent: frames each robot's sequence holds (what it sends).
    """

    stream_s: float
    wall_s: float
    exit_codes: dict[str, int]
    frames_sent: dict[str, int]


def _load(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _kbps(nbytes: int, seconds: float) -> float:
    return 8.0 * nbytes / 1000.0 / seconds if seconds > 0 else 0.0


def _link(c: dict[str, Any], secs: float, camera_s: float) -> dict[str, Any]:
    """One link's row of the report from its transport counters (received side)."""
    return {
        "kbit_s": _kbps(c["rx"]["bytes"], secs),
        "kbit_s_camera": _kbps(c["rx"]["bytes"], camera_s),
        "by_type_kbit_s": {t: _kbps(e["bytes"], secs) for t, e in c["rx"]["by_type"].items()},
        "reverse_kbit_s": _kbps(c["tx"]["bytes"], secs),
        "duplicates_dropped": c.get("duplicates_dropped", 0),
        "retransmitted_messages": c.get("retransmitted_messages", 0),
    }


def collect(run_dir: Path, facts: RunFacts) -> dict[str, Any]:
    """Everything the report shows, as plain data (this is ``report.json``)."""
    run_dir = Path(run_dir)
    per_edge = edges_stats(run_dir)
    edge = merge_edge_stats(per_edge) if per_edge else {}
    cloud = _load(run_dir / "stats" / "cloud.json")
    ate = _load(run_dir / "results" / "eval" / "ate.json")
    frame_ate = _load(run_dir / "results" / "frames" / "eval" / "ate.json")
    maps = _load(run_dir / "results" / "cloud_maps.json")
    mission = _load(run_dir / "results" / "mission.json")
    prior_frame = _load(run_dir / "results" / "eval" / "ate_prior_frame.json")
    secs = facts.stream_s
    camera_s = max(facts.frames_sent.values(), default=0) / CAMERA_HZ

    links: dict[str, Any] = {}
    for edge_name, robot, c in sorted(
        (e, r, c) for e, st in per_edge.items() for r, c in st.get("links", {}).items()
    ):
        links[f"{robot}->{edge_name}"] = _link(c, secs, camera_s)
    for edge_id, c in sorted(cloud.get("links", {}).items()):
        links[f"{edge_id}->cloud"] = _link(c, secs, camera_s)

    robots: dict[str, Any] = {}
    for name, sent in sorted(facts.frames_sent.items()):
        r = edge.get("robots", {}).get(name, {})
        link = edge.get("links", {}).get(name, {})
        frame_bytes = link.get("rx", {}).get("by_type", {}).get("RobotFrame", {}).get("bytes", 0)
        decoded = r.get("frames_decoded", 0)
        agent = ate.get("agents", {}).get(name, {})
        frames = frame_ate.get("agents", {}).get(name, {})
        robot = _load(run_dir / "stats" / f"robot-{name}.json")
        poses = robot.get("poses", {})
        cores = robot.get("cores", [])
        # Frames coded and sent (the uplink budget may leave non-keyframes out); the
        # dataset's count when the robot wrote no stats.
        sent = robot.get("frames", sent)
        robots[name] = {
            "frames_in": facts.frames_sent[name],
            "frames_sent": sent,
            "frames_decoded": decoded,
            "frames_lost": sent - decoded,
            "frames_left_out": sum(c.get("frames_left_out", 0) for c in cores),
            "frames_dropped_live": sum(
                c.get("faults", {}).get("dropped_backpressure", 0) for c in cores
            ),
            "frames_skipped_stale": r.get("frames_skipped_stale", 0),
            "keyframes_decoded": r.get("keyframes_decoded"),
            "keyframes_uplinked": r.get("keyframes_uplinked"),
            "keyframes_kept_on_edge": sum((r.get("keyframes_kept_on_edge") or {}).values()),
            "vio_state": r.get("state"),
            "map": maps.get("robots", {}).get(name),
            "bits_per_frame": 8.0 * frame_bytes / decoded if decoded else None,
            "ate_rmse_m": agent.get("individual", {}).get("stats_m", {}).get("rmse"),
            "ate_under_joint_rmse_m": agent.get("under_joint", {}).get("stats_m", {}).get("rmse"),
            "keyframes_matched": agent.get("n_matched"),
            "frame_ate_rmse_m": frames.get("individual", {}).get("stats_m", {}).get("rmse"),
            "frames_matched": frames.get("n_matched"),
            "edges": edge.get("edge_of", {}).get(name, []),
            "poses_received": poses.get("received"),
            "poses_global": poses.get("with_global"),
            "pose_latency_s": {k: poses.get(f"{k}_s") for k in ("median", "p95", "max")},
        }
    sites = {
        name: {
            "robots": sorted(st.get("robots", {})),
            "robots_kbit_s": _kbps(
                sum(c["rx"]["bytes"] for c in st.get("links", {}).values()), secs
            ),
            "to_cloud_kbit_s": _kbps(
                cloud.get("links", {}).get(name, {}).get("rx", {}).get("bytes", 0), secs
            ),
        }
        for name, st in per_edge.items()
    }
    joint = ate.get("joint", {})
    return {
        "wall_s": facts.wall_s,
        "stream_s": secs,
        "camera_s": camera_s,
        "exit_codes": facts.exit_codes,
        "failed": sorted(n for n, c in facts.exit_codes.items() if c != 0),
        "robots": robots,
        "ate": {
            "joint_rmse_m": joint.get("stats_m", {}).get("rmse"),
            "frames_joint_rmse_m": frame_ate.get("joint", {}).get("stats_m", {}).get("rmse"),
            "joint_frame": maps.get("joint_frame"),
            "note": maps.get("note"),
            "align": ate.get("align"),
        },
        "map": {
            "keyframes_uplinked": sum((r.get("keyframes_uplinked") or 0) for r in robots.values()),
            "keyframes_after_mbp": cloud.get("keyframes"),
            "map_points_after_mbp": cloud.get("map_points"),
            "mbp_passes": cloud.get("mbp_passes"),
            "maps": cloud.get("maps"),
            "merges": cloud.get("merges"),
            "loops": cloud.get("loops"),
            "optimizations": cloud.get("optimizations"),
        },
        "links": links,
        "sites": sites,
        "mission": {
            "name": mission.get("mission"),
            "prior_agents": mission.get("prior_agents", 0),
            "prior_keyframes": mission.get("prior_keyframes", 0),
            "merge_delay_s": {n: r.get("delay_s") for n, r in mission.get("robots", {}).items()},
            "first_merge_delay_s": mission.get("first_merge_delay_s"),
            "joint_rmse_prior_frame_m": prior_frame.get("joint", {}).get("stats_m", {}).get("rmse"),
            "prior_frame_of": prior_frame.get("frame_of"),
        },
    }


def edges_stats(run_dir: Path) -> dict[str, dict[str, Any]]:
    """Each edge's last counters in ``run_dir/stats`` (``edge.json`` of the single edge,
    ``edge-<name>.json`` of each site), by edge name."""
    stats = Path(run_dir) / "stats"
    out = {SINGLE_EDGE: _load(stats / "edge.json")} if (stats / "edge.json").is_file() else {}
    for path in sorted(stats.glob("edge-*.json")):
        out[path.stem.removeprefix("edge-")] = _load(path)
    return out


def _fmt(x: Any, spec: str = ".3f") -> str:
    return "–" if x is None else format(x, spec)


def render_markdown(data: dict[str, Any]) -> str:
    """``report.md`` text from ``collect``'s data."""
    m, a = data["map"], data["ate"]
    lines = [
        "# recslam run report",
        "",
        f"Wall time {data['wall_s']:.0f} s (robots streaming {data['stream_s']:.0f} s). "
        f"Failed services: {', '.join(data['failed']) or 'none'}.",
        "",
        "## Accuracy (keyframe trajectories vs ground truth, SE(3)-aligned)",
        "",
        "| robot | map | ATE RMSE m (own / joint alignment) | frames sent | decoded | lost "
        "| KF uplinked | bits/frame |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in data["robots"].items():
        lines.append(
            f"| {name} | {r['map']} | {_fmt(r['ate_rmse_m'])} / "
            f"{_fmt(r['ate_under_joint_rmse_m'])} | {r['frames_sent']} | "
            f"{r['frames_decoded']} | {r['frames_lost']} | {r['keyframes_uplinked']} | "
            f"{_fmt(r['bits_per_frame'], '.0f')} |"
        )
    lines += [
        "",
        f"Joint ATE RMSE: {_fmt(a['joint_rmse_m'])} m"
        + ("" if a["joint_frame"] else f" — {a['note']}"),
        "",
        f"Every frame (the edge's frame poses placed on the final keyframes, "
        f"`run/results/frames/`): joint ATE RMSE {_fmt(a.get('frames_joint_rmse_m'))} m; "
        + ", ".join(
            f"{n} {_fmt(r.get('frame_ate_rmse_m'))} m ({r.get('frames_matched') or 0} poses)"
            for n, r in data["robots"].items()
        )
        + ".",
        "",
        "## Map",
        "",
        f"- keyframes uplinked by the edge (before MBP): {m['keyframes_uplinked']}",
        f"- keyframes / map points at the cloud (after MBP, {m['mbp_passes']} passes): "
        f"{m['keyframes_after_mbp']} / {m['map_points_after_mbp']}",
        f"- maps {m['maps']}, merges {m['merges']}, loops {m['loops']}, "
        f"global optimisations {m['optimizations']}",
        "",
        "## Bandwidth",
        "",
        f"kbit/s over the streaming time ({data['stream_s']:.0f} s); 'at camera rate' is the "
        f"same bytes over the sequence's duration ({data['camera_s']:.0f} s at 20 Hz): what "
        "the link carries when everything keeps up with the camera.",
        "",
        "| link | total | at camera rate | by message type | reverse | duplicates dropped |",
        "|---|---|---|---|---|---|",
    ]
    for name, link in data["links"].items():
        types = ", ".join(
            f"{t} {v:.1f}" for t, v in sorted(link["by_type_kbit_s"].items()) if v >= 0.05
        )
        lines.append(
            f"| {name} | {link['kbit_s']:.1f} | {link['kbit_s_camera']:.1f} | {types} | "
            f"{link['reverse_kbit_s']:.1f} | "
            f"{link['duplicates_dropped']} |"
        )
    if any(r.get("poses_received") is not None for r in data["robots"].values()):
        lines += [
            "",
            "## Each robot's pose, back on the robot",
            "",
            "The edge's pose of every frame it processed, received by the robot "
            "(`run/results/poses/<robot>.tum`; those of maps the cloud has placed also in its "
            "global map, `run/results/poses_global/`); latency from taking the frame to its "
            "pose on the robot, s.",
            "",
            "| robot | poses received / frames sent | in the global map | latency median | p95 "
            "| max |",
            "|---|---|---|---|---|---|",
        ]
        for name, r in data["robots"].items():
            lat = r.get("pose_latency_s") or {}
            lines.append(
                f"| {name} | {_fmt(r.get('poses_received'), 'd')} / {r['frames_sent']} "
                f"| {_fmt(r.get('poses_global'), 'd')} | {_fmt(lat.get('median'), '.2f')} "
                f"| {_fmt(lat.get('p95'), '.2f')} "
                f"| {_fmt(lat.get('max'), '.2f')} |"
            )
    if len(data.get("sites", {})) > 1:
        lines += [
            "",
            "## Sites",
            "",
            "| edge | robots | robots -> edge kbit/s | edge -> cloud kbit/s |",
            "|---|---|---|---|",
        ]
        for name, site in data["sites"].items():
            lines.append(
                f"| {name} | {', '.join(site['robots'])} | {site['robots_kbit_s']:.1f} | "
                f"{site['to_cloud_kbit_s']:.1f} |"
            )
    ms = data.get("mission", {})
    if ms.get("prior_agents"):
        delays = ", ".join(
            f"{n} {d:.1f} s" if d is not None else f"{n} not merged"
            for n, d in ms["merge_delay_s"].items()
        )
        lines += [
            "",
            "## Mission in a saved map",
            "",
            f"Mission {ms['name']!r} started inside a saved map ({ms['prior_agents']} agents, "
            f"{ms['prior_keyframes']} keyframes). Merged into it after (data time from the "
            f"mission's first keyframe): {delays or 'never'}. Joint ATE RMSE in the prior "
            f"mission's frame (its alignment, not re-aligned): "
            f"{_fmt(ms['joint_rmse_prior_frame_m'])} m.",
        ]
    lines += ["", "## Plots", ""]
    lines += [f"![{p}]({p})" for p in data.get("plots", [])]
    return "\n".join(lines) + "\n"


def write_report(run_dir: Path, out_dir: Path, facts: RunFacts) -> dict[str, Any]:
    """Write ``out_dir/report.{md,json}`` and copy the cloud's plots; returns the data."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = collect(run_dir, facts)
    plots = []
    for name in PLOTS:
        src = Path(run_dir) / "results" / "eval" / name
        if src.is_file():
            shutil.copy(src, out_dir / name)
            plots.append(name)
    data["plots"] = plots
    (out_dir / "report.json").write_text(json.dumps(data, indent=2))
    (out_dir / "report.md").write_text(render_markdown(data))
    log.info("report written to %s", out_dir)
    return data
