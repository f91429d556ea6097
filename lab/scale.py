"""Many robots at one cloud: uplink recordings replayed as 3, 6, 12, 24 ... agents.

``recslam demo --record-uplink FILE`` (``recslam cloud --record``) records every message the
edge sent the cloud (:mod:`services.cloud.store.recording`). This module turns several such
recordings into the uplink of a larger team and measures what the cloud pays for it:

- **Copies** (:func:`plan_copies`): a team of N agents is made of copies of the recordings'
  robots, taken round-robin over the recordings (each of the default world's seeds flies in
  the same room, so agents of different seeds merge). Copy ``i`` renames every robot
  ``robot0`` -> ``s<i>-robot0`` and is sent by its own fake edge ``site<i>``, so copies are
  distinct agents whether the cloud keys agents by (robot, edge map) or by (edge, robot, edge
  map). A recording used a second time (more agents than recorded robots) is shifted in time
  by ``shift_s`` per round; its keyframes are identical to the first copy's (a spatial shift
  would change nothing the cloud sees: each agent has its own map frame), so such copies
  merge at once with their twins: the cost of a duplicate team, stated in the report.
- **Schedule** (:func:`copy_stream`): ``recorded`` plays each message at the time the
  recording's cloud received it; ``camera`` at the camera time of its robot's latest keyframe
  (the rate the robots fly at, even if the recorded run's edge lagged).
- **Live replay** (:mod:`lab.scale_live`): the timeline is played over real TCP to a real
  ``recslam cloud`` process (pinned to one core), one fake edge per copy; the cloud's
  per-stage timings and worker queue come from its ``--stats-out``, its memory and CPU from
  ``/proc``, the queue from the edges' outboxes (sent, not yet applied), and each keyframe's
  correction latency from the ``PoseCorrection`` messages the edges get back
  (:func:`correction_latencies`).
- **Core replay** (:func:`core_replay`): the same timeline through the service's
  :class:`~services.cloud.core.CloudCore` in this process (:func:`lab.table3.replay`, solves
  take no time): deterministic input, CPU per stage without the network.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from common.errors import RecslamError
from common.links.edge_cloud import (
    KeyframeUpdate,
    KeyframeUpdateCoded,
    PoseCorrection,
    PoseCorrectionCoded,
    decode_pose_correction,
)
from common.protocol.messages import Message
from services.cloud.store.recording import Record

log = logging.getLogger(__name__)

KeyframeKey = tuple[str, int, int]
"""A keyframe as the edges name it: (robot name, edge map id, keyframe id)."""

SCHEDULES = ("recorded", "camera")


class ScaleError(RecslamError):
    """A scale experiment cannot be set up (too few recordings, a bad schedule ...)."""


@dataclass(frozen=True)
class AgentCopy:
    """One copy of (some of) a recording's robots: ``robots`` of recording ``recording``,
    renamed with ``prefix``, sent by fake edge ``edge``, ``shift_s`` later."""

    index: int
    recording: int
    robots: tuple[str, ...]
    prefix: str
    edge: str
    shift_s: float


@dataclass(frozen=True)
class Send:
    """One message of the team's uplink: at ``t`` seconds after the start, by ``edge``;
    ``keyframe``: the keyframe it brings to the cloud first (None: any other message)."""

    t: float
    edge: str
    message: Message
    keyframe: KeyframeKey | None = None


def robots_of(records: Iterable[Record]) -> tuple[str, ...]:
    """The robot names of a recording's messages, sorted."""
    return tuple(sorted({str(getattr(r.message, "agent_id", "")) for r in records} - {""}))


def plan_copies(
    robots: Sequence[Sequence[str]], agents: int, shift_s: float = 5.0
) -> list[AgentCopy]:
    """Copies of the recordings' robots (``robots[k]``: recording ``k``'s) that make a team
    of ``agents``: round-robin over the recordings, a whole recording per copy (the last one
    takes as many robots as are missing); round ``r`` over the recordings is ``r * shift_s``
    later."""
    if agents < 1:
        raise ScaleError(f"agents must be >= 1, got {agents}")
    if not robots or any(not r for r in robots):
        raise ScaleError("every recording must hold at least one robot")
    out: list[AgentCopy] = []
    left = agents
    i = 0
    while left > 0:
        k = i % len(robots)
        take = tuple(sorted(robots[k]))[:left]
        out.append(AgentCopy(i, k, take, f"s{i}-", f"site{i}", (i // len(robots)) * shift_s))
        left -= len(take)
        i += 1
    return out


def rename(message: Message, prefix: str) -> Message:
    """``message`` with its robot renamed ``prefix + agent_id``."""
    name = str(getattr(message, "agent_id"))  # noqa: B009  (every uplink message has one)
    renamed: Message = dataclasses.replace(cast(Any, message), agent_id=prefix + name)
    return renamed


def _camera_t0(records: Sequence[Record]) -> float:
    stamps = [
        r.message.timestamp_ns
        for r in records
        if isinstance(r.message, KeyframeUpdate | KeyframeUpdateCoded)
    ]
    if not stamps:
        raise ScaleError("a recording without keyframes")
    return min(stamps) * 1e-9


def copy_stream(records: Sequence[Record], copy: AgentCopy, schedule: str = "camera") -> list[Send]:
    """The messages of ``copy`` (its robots' records, renamed), each with its time
    (``schedule``, module docstring) plus the copy's shift; in the recording's order."""
    if schedule not in SCHEDULES:
        raise ScaleError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    mine = [r for r in records if getattr(r.message, "agent_id", None) in copy.robots]
    if not mine:
        return []
    t_first = min(r.t_recv for r in records)
    cam0 = _camera_t0(records) if schedule == "camera" else 0.0
    latest: dict[str, float] = {}  # robot -> camera time of its latest keyframe
    seen: set[KeyframeKey] = set()
    out: list[Send] = []
    for r in mine:
        m = r.message
        name = str(m.agent_id)  # type: ignore[attr-defined]
        first: KeyframeKey | None = None
        if isinstance(m, KeyframeUpdate | KeyframeUpdateCoded):
            key = (copy.prefix + name, int(m.map_id), int(m.keyframe_id))
            if key not in seen:
                seen.add(key)
                first = key
            latest[name] = max(latest.get(name, 0.0), m.timestamp_ns * 1e-9 - cam0)
        t = r.t_recv - t_first if schedule == "recorded" else latest.get(name, 0.0)
        out.append(Send(t + copy.shift_s, copy.edge, rename(m, copy.prefix), first))
    return out


def timeline(
    recordings: Sequence[Sequence[Record]], copies: Sequence[AgentCopy], schedule: str = "camera"
) -> list[Send]:
    """Every copy's messages merged by time (stable: each robot's stay in their order)."""
    sends = [s for c in copies for s in copy_stream(recordings[c.recording], c, schedule)]
    sends.sort(key=lambda s: s.t)
    return sends


@dataclass(frozen=True)
class Received:
    """A pose correction an edge got: at ``t`` (seconds after the start) for robot
    ``robot``'s map ``map_id``, covering ``keyframe_ids``."""

    t: float
    robot: str
    map_id: int
    keyframe_ids: tuple[int, ...]


def received(t: float, message: PoseCorrection | PoseCorrectionCoded) -> Received:
    """The keyframes a correction covers (decoded as the edge decodes it)."""
    ids, _ = decode_pose_correction(message)
    return Received(t, message.agent_id, int(message.map_id), tuple(int(i) for i in ids))


def correction_latencies(
    arrivals: Mapping[KeyframeKey, float], corrections: Iterable[Received]
) -> dict[KeyframeKey, float]:
    """Per keyframe: the time from its arrival to the first correction at or after it that
    covers it (keyframes never covered are left out)."""
    first: dict[KeyframeKey, float] = {}
    for c in sorted(corrections, key=lambda c: c.t):
        for kf in c.keyframe_ids:
            key = (c.robot, c.map_id, kf)
            t_arr = arrivals.get(key)
            if t_arr is not None and key not in first and c.t >= t_arr:
                first[key] = c.t - t_arr
    return first


def summarize(values: Iterable[float]) -> dict[str, float]:
    """Median, p95, max and count of ``values`` (NaN when there are none)."""
    v = np.asarray(list(values), np.float64)
    if v.size == 0:
        return {"n": 0, "median": math.nan, "p95": math.nan, "max": math.nan}
    return {
        "n": int(v.size),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(v.max()),
    }


def records_of(sends: Sequence[Send]) -> list[Record]:
    """The timeline as recording records (one stream per edge, ``t_recv`` its time), for
    :func:`lab.table3.replay`."""
    seq: dict[str, int] = {}
    out = []
    for s in sends:
        seq[s.edge] = seq.get(s.edge, 0) + 1
        out.append(Record(s.edge, s.edge.encode(), seq[s.edge], s.message, s.t))
    return out


def load_recordings(paths: Sequence[Path]) -> list[list[Record]]:
    """Every message record of each recording (a truncated tail dropped)."""
    from services.cloud.store.recording import read_recording

    return [list(read_recording(p, allow_truncated_tail=True)) for p in paths]


# ------------------------------------------------------------------ one team, summarized
KEYFRAME_STAGES = (
    ("decode", ("stage.decode",)),
    ("insert", ("stage.insert",)),
    ("place recognition", ("stage.place_recognition",)),
    ("verification", ("stage.verification",)),
    ("merge", ("stage.merge",)),
    ("database", ("stage.database",)),
    ("commit", ("stage.commit", "stage.save_all")),
)
"""The stages of a new keyframe on the cloud's worker (row label, stats keys)."""
OTHER_STAGES = (
    ("build", ("stage.pose_graph_build", "stage.full_ba_build")),
    ("apply + corrections", ("stage.pose_graph_apply", "stage.full_ba_apply", "stage.corrections")),
    ("MBP", ("stage.mbp",)),
    ("dashboard view", ("stage.view",)),
)
"""The worker's other stages: optimisation (the solves run in the optimizer process), MBP,
the dashboard's atlas snapshot (every ``publish_every_s`` when the atlas changed)."""
SOLVES = (("pose graph solve", ("solve.pose_graph",)), ("full BA solve", ("solve.full_ba",)))


def _seconds(table: Mapping[str, Mapping[str, float]], keys: Sequence[str]) -> float:
    return float(sum(table.get(k, {}).get("seconds", 0.0) for k in keys))


@dataclass
class TeamRow:
    """One team size's measurements (times in seconds unless named _ms)."""

    agents: int
    edges: int
    keyframes: int
    messages: int
    duration_s: float
    drain_s: float
    late_max_s: float
    stage_ms: dict[str, float]
    worker_ms_per_keyframe: float
    worker_busy: float
    worker_busy_wall: float
    messages_ms_wall: float
    cloud_cpu: float
    queue_max: int
    queue_end: int
    worker_queue_max: int
    latency: dict[str, float]
    corrected: float
    rss_max_mb: float
    maps: int
    merges: int
    optimizations: int
    queue_trace: list[tuple[float, int]]
    overloaded_s: float = 0.0  # the cloud shedding work (CloudStats.overload)
    full_bas_deferred: int = 0


def team_row(agents: int, live: Any) -> TeamRow:
    """Summarize one live replay (:class:`lab.scale_live.LiveResult`)."""
    st = live.stats
    stages: dict[str, dict[str, float]] = dict(st.get("stages", {}))
    stages.update(st.get("codec_cpu", {}))
    # per keyframe the cloud applied (decoded): a cloud that fell behind applied fewer
    n_kf = max(1, int(stages.get("stage.decode", {}).get("messages", len(live.arrivals))))
    ms = {
        label: 1e3 * _seconds(stages, keys) / n_kf
        for label, keys in (*KEYFRAME_STAGES, *OTHER_STAGES, *SOLVES)
    }
    handle = sum(v["seconds"] for k, v in stages.items() if k.startswith("handle."))
    wall = sum(v["seconds"] for k, v in stages.items() if k.startswith("wall."))
    busy_worker = handle + _seconds(stages, [k for _, ks in OTHER_STAGES for k in ks])
    busy_wall = wall + _seconds(stages, [k for _, ks in OTHER_STAGES for k in ks])
    lat = summarize(correction_latencies(live.arrivals, live.corrections).values())
    during = [s for s in live.samples if s["t"] <= live.duration_s]
    return TeamRow(
        agents=agents,
        edges=live.edges,
        keyframes=len(live.arrivals),
        messages=live.sent,
        duration_s=live.duration_s,
        drain_s=live.applied_s - live.duration_s if live.drained else math.inf,
        late_max_s=live.late_max_s,
        stage_ms=ms,
        worker_ms_per_keyframe=1e3 * busy_worker / n_kf,
        worker_busy=busy_worker / max(live.applied_s, 1e-9),
        worker_busy_wall=busy_wall / max(live.applied_s, 1e-9),
        messages_ms_wall=1e3 * wall / max(1, live.sent),
        cloud_cpu=live.cloud_cpu_s / max(live.applied_s, 1e-9),
        queue_max=max((s["queue"] for s in live.samples), default=0),
        queue_end=during[-1]["queue"] if during else 0,
        worker_queue_max=int(st.get("worker_queue_max", 0)),
        latency=lat,
        corrected=lat["n"] / max(1, len(live.arrivals)),
        rss_max_mb=live.rss_max_mb,
        maps=len(st.get("maps", [])),
        merges=int(st.get("merges", 0)),
        optimizations=int(st.get("optimizations", 0)),
        queue_trace=[(float(s["t"]), int(s["queue"])) for s in live.samples],
        overloaded_s=float(st.get("overload", {}).get("overloaded_s", 0.0)),
        full_bas_deferred=int(st.get("overload", {}).get("full_bas_deferred", 0)),
    )


@dataclass(frozen=True)
class ScaleConfig:
    """``recslam experiment scale``: recordings, team sizes, schedule, where to work.

    Attributes:
        recordings: uplink recordings (``recslam demo --record-uplink``).
        agents: team sizes.
        schedule: ``camera`` or ``recorded`` (module docstring).
        shift_s: time shift of each further round over the recordings.
        work: scratch folder (one sub-folder per team size and run).
        out: where scale.md, scale.json and scale.png go.
        runs: live replays per team size (their spread is reported).
        command: the command line that ran it (for the report).
        core: also replay each team through the core in-process (:func:`core_replay`).
    """

    recordings: tuple[Path, ...]
    agents: tuple[int, ...] = (3, 6, 12, 24)
    schedule: str = "camera"
    shift_s: float = 5.0
    work: Path = Path("/tmp/recslam-scale")
    out: Path = Path("benchmarks/results")
    runs: int = 1
    command: str = ""
    core: bool = False


@dataclass
class CoreRow:
    """A team through the service's core in this process (:func:`core_replay`): CPU per
    keyframe per stage (ms), solves included, and the end state."""

    agents: int
    keyframes: int
    messages: int
    stage_ms: dict[str, float]
    worker_ms_per_keyframe: float
    seconds: float
    maps: int
    merges: int
    optimizations: int


def core_replay(
    sends: Sequence[Send], agents: int, state_dir: Path, full_ba: bool = True
) -> CoreRow:
    """``sends`` through a fresh cloud app and the service's core (:func:`lab.table3.replay`,
    modelled schedule, solves in this thread taking no time on the replay's clock): the
    same input in the same order every time, CPU per stage without the network."""
    import time

    from common.vocabulary import Vocabulary
    from lab.table3 import replay, service_config
    from services.cloud.core_actions import SolveRequest, SolveResult, solve
    from sim.cloud import default_camera

    solves: dict[str, dict[str, float]] = {}

    def timed(request: SolveRequest) -> SolveResult:
        t0 = time.thread_time()  # CPU, as the cloud's stage timer
        try:
            return solve(request)
        finally:
            e = solves.setdefault(f"solve.{request.kind.name.lower()}", {"seconds": 0.0})
            e["seconds"] += time.thread_time() - t0

    res = replay(
        records_of(sends),
        default_camera(),
        Vocabulary.load(),
        service_config(mbp=False),
        state_dir,
        f"{agents} agents",
        full_ba=full_ba,
        solve_fn=timed,
    )
    stages = {**res.stages, **solves}
    n_kf = max(1, res.keyframes_received)
    ms = {
        label: 1e3 * _seconds(stages, keys) / n_kf
        for label, keys in (*KEYFRAME_STAGES, *OTHER_STAGES, *SOLVES)
    }
    worker = sum(v for k, v in ms.items() if k not in dict(SOLVES))
    return CoreRow(
        agents=agents,
        keyframes=res.keyframes_received,
        messages=res.messages,
        stage_ms=ms,
        worker_ms_per_keyframe=worker,
        seconds=res.seconds,
        maps=len(res.maps),
        merges=res.merges,
        optimizations=res.optimizations,
    )
