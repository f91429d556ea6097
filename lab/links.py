"""``recslam experiment links``: the system's bit budget, raw vs coded wire, side by side.

For each dataset, each run index and each wire format (``common.links.WireFormat``: the edge's
``--wire``; robots and cloud accept both) the whole job runs as ``recslam demo --no-dashboard``
does it (``lab.run.orchestration.run_and_report``) into ``OUT/<dataset>/<wire>/run<k>/``
(``report.json`` etc., the run folder in ``run/``). From each run this module reads
(:func:`read_run`):

- the traffic counters of every link, by direction and message type (the edge's
  ``stats/edge.json``: robot→edge = what the edge received from a robot, edge→robot what it
  sent; the cloud's ``stats/cloud.json``: edge→cloud = what the cloud received, cloud→edge
  what it sent), as kbit/s at camera rate: bytes over the sequence's camera duration
  (``report.json`` ``camera_s``, frames / 20 Hz, 1 kbit = 1000 bit), per robot (mean over the
  robots; the worst robot for the verdict) on the robot links, total on the cloud link;
- messages and bytes per type (bits per message), keyframes uplinked and the peak number of
  map points at the cloud (``stats/samples.jsonl``; before MBP, a lower bound of the distinct
  points sent, so bits per point are an upper bound);
- the codec CPU (``codec_cpu`` in the stats, when the services time their codecs);
- joint and per-robot ATE, frames sent / decoded / lost, maps, merges, loops (``report.json``).

Message types are whatever the counters hold; a type ``XCoded`` is shown on the row of ``X``
(its raw counterpart). Runs of a (dataset, wire) are summarised as mean and min–max
(:func:`summarize`). :mod:`lab.links_report` writes ``OUT/links.md``, ``links.json`` and
``links.png`` (and copies md + png to ``--results``).
"""

from __future__ import annotations

import datetime
import json
import logging
import shutil
import subprocess
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from common.errors import RecslamError
from common.links import WireFormat

log = logging.getLogger(__name__)

ROBOT_DIRECTIONS = ("robot->edge", "edge->robot")
"""Directions of the robot↔edge links (one link per robot; rates per robot)."""
CLOUD_DIRECTIONS = ("edge->cloud", "cloud->edge")
"""Directions of the edge↔cloud link (rates in total)."""
DIRECTIONS = ROBOT_DIRECTIONS + CLOUD_DIRECTIONS
CODED_SUFFIX = "Coded"

Stat = dict[str, float]
"""``{"mean": m, "min": lo, "max": hi, "n": runs}`` of one number over runs."""
RunMetrics = dict[str, Any]
"""What :func:`read_run` reads from one run (plain JSON data)."""


class LinksError(RecslamError):
    """A run folder is incomplete, or the options are wrong."""


@dataclass(frozen=True)
class Targets:
    """The bit budget (kbit/s at camera rate).

    robot_edge_kbit_s: robot→edge, per robot (default 150).
    edge_robot_kbit_s: edge→robot, per robot (default 25).
    edge_cloud_kbit_s: edge→cloud for ``edge_cloud_robots`` robots (default 600 for 3; scaled
        in proportion for another number of robots).
    """

    robot_edge_kbit_s: float = 150.0
    edge_robot_kbit_s: float = 25.0
    edge_cloud_kbit_s: float = 600.0
    edge_cloud_robots: int = 3


@dataclass(frozen=True)
class LinksConfig:
    """Options of the experiment (built once by the CLI).

    datasets: dataset folders (one EuRoC-layout sequence per robot each).
    out: output folder; runs: runs per (dataset, wire); wires: formats, in table order.
    results: also copy ``links.md`` and ``links.png`` here (None = no copy).
    timeout_s: per-run timeout; rate: the robots' playback rate ("realtime" or "max").
    from_runs: do not run; build the tables from the run folders already under ``out``.
    command: the command line, for the report.
    """

    datasets: tuple[Path, ...] = (Path("data/synth"),)
    out: Path = Path("out/links")
    runs: int = 1
    wires: tuple[WireFormat, ...] = (WireFormat.RAW, WireFormat.CODED)
    results: Path | None = Path("benchmarks/results")
    timeout_s: float = 1800.0
    rate: str = "realtime"
    from_runs: bool = False
    command: str = ""
    targets: Targets = field(default_factory=Targets)


# ---------------------------------------------------------------------- options
def parse_wires(text: str) -> tuple[WireFormat, ...]:
    """``"raw,coded"`` -> ``(WireFormat.RAW, WireFormat.CODED)`` (order kept, no repeats)."""
    out: list[WireFormat] = []
    for item in text.split(","):
        item = item.strip().lower()
        if not item:
            continue
        try:
            wire = WireFormat(item)
        except ValueError:
            names = ", ".join(w.value for w in WireFormat)
            raise LinksError(f"--wire: {item!r} is not one of {names}") from None
        if wire not in out:
            out.append(wire)
    if not out:
        raise LinksError("--wire: no wire format given")
    return tuple(out)


def parse_datasets(values: Sequence[str]) -> tuple[Path, ...]:
    """Repeated and / or comma-separated ``--data`` values -> folders (order kept)."""
    out: list[Path] = []
    for value in values:
        for item in value.split(","):
            if item.strip() and Path(item.strip()) not in out:
                out.append(Path(item.strip()))
    return tuple(out)


def dataset_names(datasets: Sequence[Path]) -> dict[str, Path]:
    """A short unique name per dataset folder (its name; ``-2``, ``-3``... on a clash)."""
    out: dict[str, Path] = {}
    for path in datasets:
        base = Path(path).resolve().name or "data"
        name, k = base, 1
        while name in out:
            k += 1
            name = f"{base}-{k}"
        out[name] = Path(path)
    return out


def run_folder(out: Path, dataset: str, wire: WireFormat, k: int) -> Path:
    """``OUT/<dataset>/<wire>/run<k>`` (k from 1): one run's report folder."""
    return Path(out) / dataset / wire.value / f"run{k}"


# ---------------------------------------------------------------------- one run
def load_json(path: Path) -> dict[str, Any]:
    """A run's JSON file ({} if missing; LinksError naming it if it is not JSON)."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except ValueError as exc:
        raise LinksError(f"{path}: not JSON ({exc})") from None


def _kbps(nbytes: float, seconds: float) -> float:
    return 8.0 * nbytes / 1000.0 / seconds if seconds > 0 else 0.0


def link_counters(stats_dir: Path) -> dict[str, dict[str, dict[str, Any]]]:
    """``{direction: {endpoint: transport counters}}`` from the edge's and the cloud's stats
    (endpoint: the robot, or the edge; counters ``{"bytes", "messages", "by_type": {type:
    {"bytes", "messages"}}}``)."""
    edge = load_json(Path(stats_dir) / "edge.json")
    cloud = load_json(Path(stats_dir) / "cloud.json")
    out: dict[str, dict[str, dict[str, Any]]] = {d: {} for d in DIRECTIONS}
    for robot, c in edge.get("links", {}).items():
        out["robot->edge"][robot] = c.get("rx", {})
        out["edge->robot"][robot] = c.get("tx", {})
    for edge_id, c in cloud.get("links", {}).items():
        out["edge->cloud"][edge_id] = c.get("rx", {})
        out["cloud->edge"][edge_id] = c.get("tx", {})
    return out


def _direction(counters: dict[str, dict[str, Any]], camera_s: float, per_robot: bool) -> dict:
    """One direction's numbers: total kbit/s (per endpoint when ``per_robot``), the worst
    endpoint's, and per type messages, bytes (summed) and kbit/s (like the total)."""
    n = max(len(counters), 1) if per_robot else 1
    totals = {e: _kbps(c.get("bytes", 0), camera_s) for e, c in counters.items()}
    types: dict[str, dict[str, float]] = {}
    for c in counters.values():
        for t, e in c.get("by_type", {}).items():
            acc = types.setdefault(t, {"messages": 0, "bytes": 0})
            acc["messages"] += e.get("messages", 0)
            acc["bytes"] += e.get("bytes", 0)
    for acc in types.values():
        acc["kbit_s"] = _kbps(acc["bytes"], camera_s) / n
    return {
        "endpoints": len(counters),
        "kbit_s": sum(totals.values()) / n,
        "kbit_s_max": max(totals.values(), default=0.0),
        "types": dict(sorted(types.items())),
    }


def _peak_map_points(samples_path: Path) -> int | None:
    """The largest map-point count the cloud reported while running (None: no samples)."""
    if not samples_path.is_file():
        return None
    peak = None
    for line in samples_path.read_text().splitlines():
        if not line.strip():
            continue
        n = json.loads(line).get("cloud", {}).get("map_points")
        if n is not None and (peak is None or n > peak):
            peak = n
    return peak


def read_run(report_dir: Path) -> RunMetrics:
    """The numbers of one run from its report folder (``report.json`` and ``run/stats/``)."""
    report_dir = Path(report_dir)
    report = load_json(report_dir / "report.json")
    if not report:
        raise LinksError(f"{report_dir}: no report.json (the run did not finish)")
    stats_dir = report_dir / "run" / "stats"
    edge, cloud = load_json(stats_dir / "edge.json"), load_json(stats_dir / "cloud.json")
    camera_s = float(report.get("camera_s") or 0.0)
    counters = link_counters(stats_dir)
    links = {
        d: _direction(counters[d], camera_s, per_robot=d in ROBOT_DIRECTIONS) for d in DIRECTIONS
    }
    robots = report.get("robots", {})
    per_robot = {}
    for name, r in robots.items():
        per_robot[name] = {
            **{
                d: _kbps(counters[d].get(name, {}).get("bytes", 0), camera_s)
                for d in ROBOT_DIRECTIONS
            },
            "ate_m": r.get("ate_rmse_m"),
            "ate_joint_m": r.get("ate_under_joint_rmse_m"),
            "frames_sent": r.get("frames_sent"),
            "frames_decoded": r.get("frames_decoded"),
            "frames_lost": r.get("frames_lost"),
            "keyframes_uplinked": r.get("keyframes_uplinked"),
        }
    own = [r["ate_m"] for r in per_robot.values() if r["ate_m"] is not None]
    m = report.get("map", {})
    maps = m.get("maps")
    index = report_dir.name.removeprefix("run")
    return {
        "folder": str(report_dir),
        "run": int(index) if index.isdigit() else 1,
        "camera_s": camera_s,
        "stream_s": report.get("stream_s"),
        "wall_s": report.get("wall_s"),
        "robots": len(robots),
        "failed": list(report.get("failed", [])),
        "links": links,
        "per_robot": per_robot,
        "items": {
            "frames_decoded": sum(r.get("frames_decoded") or 0 for r in robots.values()),
            "keyframes_uplinked": m.get("keyframes_uplinked"),
            "map_points_peak": _peak_map_points(stats_dir / "samples.jsonl"),
        },
        "codec_cpu": {
            where: s["codec_cpu"]
            for where, s in (("edge", edge), ("cloud", cloud))
            if s.get("codec_cpu")
        },
        "accuracy": {
            "ate_joint_m": report.get("ate", {}).get("joint_rmse_m"),
            "ate_robot_mean_m": sum(own) / len(own) if own else None,
            "frames_sent": sum(r.get("frames_sent") or 0 for r in robots.values()),
            "frames_decoded": sum(r.get("frames_decoded") or 0 for r in robots.values()),
            "frames_lost": sum(r.get("frames_lost") or 0 for r in robots.values()),
            "keyframes_uplinked": m.get("keyframes_uplinked"),
            "keyframes_after_mbp": m.get("keyframes_after_mbp"),
            "map_points_after_mbp": m.get("map_points_after_mbp"),
            "maps": len(maps) if isinstance(maps, list) else maps,
            "merges": m.get("merges"),
            "loops": m.get("loops"),
        },
    }


# ---------------------------------------------------------------------- summaries
def summarize(values: Iterable[float | None]) -> Stat | None:
    """Mean, min and max of the values that are not None (None when there are none)."""
    xs = [float(v) for v in values if v is not None]
    if not xs:
        return None
    return {"mean": sum(xs) / len(xs), "min": min(xs), "max": max(xs), "n": len(xs)}


def stat_of(runs: Sequence[RunMetrics], get: Callable[[RunMetrics], float | None]) -> Stat | None:
    """:func:`summarize` of ``get(run)`` over the runs (a missing key counts as None)."""
    values = []
    for run in runs:
        try:
            values.append(get(run))
        except (KeyError, TypeError, ZeroDivisionError):
            values.append(None)
    return summarize(values)


def aggregate(runs: Sequence[Any]) -> Any:
    """The runs' nested dicts merged key by key, every number replaced by its :data:`Stat`
    (lists and strings are left out)."""
    dicts = [r for r in runs if isinstance(r, dict)]
    if dicts:
        keys = sorted({k for d in dicts for k in d})
        out = {k: aggregate([d.get(k) for d in dicts]) for k in keys}
        return {k: v for k, v in out.items() if v is not None}
    numbers = [r for r in runs if isinstance(r, int | float) and not isinstance(r, bool)]
    return summarize(numbers) if numbers else None


def family(type_name: str) -> str:
    """The row a message type is shown on: ``KeyframeUpdateCoded`` -> ``KeyframeUpdate``."""
    if type_name.endswith(CODED_SUFFIX) and len(type_name) > len(CODED_SUFFIX):
        return type_name[: -len(CODED_SUFFIX)]
    return type_name


def family_sum(run: RunMetrics, direction: str, fam: str, key: str) -> float | None:
    """Sum of ``key`` ("messages", "bytes", "kbit_s") over the direction's types of ``fam``
    (None when the run has none of them)."""
    types = run["links"][direction]["types"]
    members = [e[key] for t, e in types.items() if family(t) == fam]
    return sum(members) if members else None


def bits_per_message(run: RunMetrics, direction: str, fam: str) -> float | None:
    n = family_sum(run, direction, fam, "messages")
    b = family_sum(run, direction, fam, "bytes")
    return 8.0 * b / n if n and b is not None else None


def prefix_bits_per_item(run: RunMetrics, direction: str, prefix: str, item: str) -> float | None:
    """Bits of the direction's message types named ``prefix...`` per ``run["items"][item]``."""
    count = run["items"].get(item)
    types = run["links"][direction]["types"]
    nbytes = sum(e["bytes"] for t, e in types.items() if t.startswith(prefix))
    return 8.0 * nbytes / count if count and nbytes else None


def codec_ms(run: RunMetrics, where: str, key: str) -> float | None:
    """Codec CPU per message (ms) of ``key`` ("encode.Type") at ``where`` ("edge"/"cloud")."""
    e = run["codec_cpu"].get(where, {}).get(key)
    if not e or not e.get("messages"):
        return None
    return 1000.0 * e["seconds"] / e["messages"]


def link_value(run: RunMetrics, direction: str, key: str) -> float | None:
    """``key`` of the run's link ``direction`` (e.g. "kbit_s")."""
    return run["links"][direction][key]


def verdict(runs: Sequence[RunMetrics], targets: Targets) -> list[dict[str, Any]]:
    """The budget checks of one (dataset, wire): robot→edge and edge→robot of the worst
    robot, edge→cloud in total (limit scaled to the number of robots); means over runs."""
    robots = max((r["robots"] for r in runs), default=0)
    scale = robots / targets.edge_cloud_robots if robots else 1.0
    checks = [
        ("robot->edge", "kbit_s_max", targets.robot_edge_kbit_s, "per robot, worst"),
        ("edge->robot", "kbit_s_max", targets.edge_robot_kbit_s, "per robot, worst"),
        ("edge->cloud", "kbit_s", targets.edge_cloud_kbit_s * scale, f"{robots} robots"),
    ]
    out = []
    for direction, key, limit, what in checks:
        s = stat_of(runs, partial(link_value, direction=direction, key=key))
        value = s["mean"] if s is not None else None
        ok = None if value is None else value <= limit
        out.append({"link": direction, "value": value, "limit": limit, "ok": ok, "what": what})
    return out


# ---------------------------------------------------------------------- the experiment
def git_commit(repo: Path | None = None) -> str:
    """``git rev-parse --short HEAD`` (+ a note when tracked files are modified)."""
    cwd = repo or Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=cwd,
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=cwd,
            check=True,
            capture_output=True,
            text=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + (" (with uncommitted changes)" if dirty.strip() else "")


def run_one(
    dataset: Path, report_dir: Path, wire: WireFormat, config: LinksConfig, label: str
) -> dict[str, Any]:
    """One whole run (``recslam demo --no-dashboard --wire WIRE``) into ``report_dir``."""
    return run_job(dataset, report_dir, wire, config.rate, config.timeout_s, label)


def run_job(
    dataset: Path,
    report_dir: Path,
    wire: WireFormat,
    rate: str,
    timeout_s: float,
    label: str,
    mbp: bool = True,
    mbp_every: int = 0,
    record_uplink: Path | None = None,
) -> dict[str, Any]:
    """One whole run of ``dataset`` (as ``recslam demo --no-dashboard --wire WIRE`` runs it,
    with ``--no-mbp`` / ``--mbp-every`` as ``mbp`` / ``mbp_every`` say, and the cloud's uplink
    recorded to ``record_uplink``) into ``report_dir`` (replaced); its ``report.json``;
    progress every 30 s in the log."""
    from lab.run.orchestration import JobConfig, progress_line, run_and_report

    if report_dir.exists():
        shutil.rmtree(report_dir)
    job = JobConfig(
        dataset=dataset,
        run_dir=report_dir / "run",
        rate=rate,
        wire=wire,
        mbp=mbp,
        mbp_every=mbp_every,
        record_uplink=record_uplink,
    )
    last = [0.0]

    def progress(sample: dict[str, Any], elapsed: float) -> None:
        if elapsed - last[0] >= 30.0:
            last[0] = elapsed
            log.info("%s %s", label, progress_line(sample, elapsed))

    return run_and_report(
        job, report_dir, timeout_s, progress, lambda line: log.info("%s %s", label, line)
    )


def find_runs(out: Path, wires: Sequence[WireFormat]) -> dict[str, dict[str, list[Path]]]:
    """``{dataset: {wire: [report folders]}}`` of the finished runs under ``out``."""
    found: dict[str, dict[str, list[Path]]] = {}
    for report in sorted(Path(out).glob("*/*/run*/report.json")):
        folder = report.parent
        wire, dataset = folder.parent.name, folder.parent.parent.name
        if wire in {w.value for w in wires}:
            found.setdefault(dataset, {}).setdefault(wire, []).append(folder)
    for per_wire in found.values():
        for folders in per_wire.values():
            folders.sort(key=lambda p: int(p.name[3:]) if p.name[3:].isdigit() else 0)
    return found


def build_data(
    folders: dict[str, dict[str, list[Path]]],
    config: LinksConfig,
    paths: dict[str, Path] | None = None,
    errors: Sequence[str] = (),
) -> dict[str, Any]:
    """``links.json``: per dataset and wire the runs' numbers, their summary and the verdict."""
    datasets: dict[str, Any] = {}
    wires = [w.value for w in config.wires]
    for name, per_wire in folders.items():
        entry: dict[str, Any] = {
            "path": str(paths[name]) if paths and name in paths else None,
            "wires": {},
        }
        for wire in wires:
            runs = [read_run(f) for f in per_wire.get(wire, [])]
            if not runs:
                continue
            entry["wires"][wire] = {
                "runs": runs,
                "summary": aggregate(runs),
                "verdict": verdict(runs, config.targets),
            }
        all_runs = [r for w in entry["wires"].values() for r in w["runs"]]
        entry["robots"] = max((r["robots"] for r in all_runs), default=0)
        entry["camera_s"] = max((r["camera_s"] for r in all_runs), default=0.0)
        datasets[name] = entry
    return {
        "command": config.command,
        "commit": git_commit(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "runs": config.runs,
        "from_runs": config.from_runs,
        "wires": wires,
        "targets": asdict(config.targets),
        "errors": list(errors),
        "datasets": datasets,
    }
