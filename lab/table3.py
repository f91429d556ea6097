"""The paper's Table 3 from a recorded run: keyframes, map points and ATE with and without MBP.

``recslam demo --record-uplink FILE`` (``recslam cloud --record``) records every uplink
message the cloud applied, in order, with its receive time. :func:`replay` feeds such a
recording to a fresh :class:`~services.cloud.app.CloudApp` (own SQLite state directory)
through the service's own :class:`~services.cloud.core.CloudCore`, synchronously and
deterministically: ``now`` is each record's receive time, the core's timer fires before the
first record received at or after its deadline, every solve runs in this process and takes
no time; after the last record the scheduled pose graphs run (the service's debounce timer
would fire), then the core's shutdown sequence. So the optimisation / full BA / MBP schedule
is the service's, not a copy of it (``services/cloud/core.py`` describes it).

:func:`run_table3` replays three times — MBP off, MBP as the service runs it (at shutdown) and
MBP also every 100 keyframes while running, everything else identical, full BA on — computes
per-robot and joint ATE of the keyframe trajectories (every keyframe received: the ones MBP
retired through their anchors; and over the kept keyframes only) with the cloud report's
alignment
(:func:`common.evaluation.metrics.compute_joint_ate`, SE(3)), scores loop detection of the
MBP-on replay (:mod:`lab.loop_scoring`) and writes ``table3.md``, ``loop_detection.md``,
``table3.json`` and ``table3.png``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.calibration import CameraCalibration
from common.errors import RecslamError
from common.evaluation.metrics import AlignMode, AteConfig, JointAteResult, compute_joint_ate
from common.evaluation.results import load_groundtruth
from common.evaluation.trajectory import Trajectory
from common.links.edge_cloud import KeyframeUpdate, KeyframeUpdateCoded
from common.vocabulary import Vocabulary
from lab.loop_scoring import (
    Detection,
    GroundTruthPoses,
    KeyframeInfo,
    LoopCriterion,
    LoopScores,
    QueryEvent,
    score_loops,
)
from lab.replay_schedule import RecordedSteps, SolveClock
from services.cloud.app import CloudApp, Reaction, open_app
from services.cloud.config import CloudConfig, MbpConfig
from services.cloud.core import CloudCore
from services.cloud.core_actions import SolveRequest, SolveResult, solve
from services.cloud.optimization.mbp import REASONS, backbone
from services.cloud.service_config import CloudServiceConfig, MbpScheduleConfig
from services.cloud.store.recording import Record, Step, has_schedule, read_schedule

log = logging.getLogger(__name__)


def service_config(mbp: bool, every_keyframes: int | None = None) -> CloudServiceConfig:
    """The cloud service's default configuration with MBP switched on or off (and, if given,
    MBP also every ``every_keyframes`` new keyframes while running)."""
    domain = CloudConfig(mbp=dataclasses.replace(MbpConfig(), enabled=mbp))
    cfg = CloudServiceConfig(domain=domain)
    if every_keyframes is not None:
        cfg = dataclasses.replace(cfg, mbp=MbpScheduleConfig(every_keyframes=every_keyframes))
    return cfg


def without_full_ba(config: CloudServiceConfig) -> CloudServiceConfig:
    """``config`` with the full bundle adjustment switched off."""
    full = dataclasses.replace(config.domain.full_ba, enabled=False)
    return dataclasses.replace(config, domain=dataclasses.replace(config.domain, full_ba=full))


@dataclass
class ReplayResult:
    """What one replay ended with (counts at the end) and what it observed on the way."""

    label: str
    mbp: bool
    messages: int
    failed: int
    keyframes_received: int
    keyframes: int
    map_points: int
    maps: list[int]
    merges: int
    loops: int
    optimizations: int
    mbp_passes: int
    seconds: float
    trajectories: dict[str, Trajectory]
    map_of_robot: dict[str, int]
    full_bas: int = 0
    kept_trajectories: dict[str, Trajectory] = field(default_factory=dict)
    info: dict[int, KeyframeInfo] = field(default_factory=dict)
    backbone: dict[str, int] = field(default_factory=dict)
    detections: list[Detection] = field(default_factory=list)
    queries: list[QueryEvent] = field(default_factory=list)
    schedule: str = "modelled"
    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    """The app's stage and codec timings at the end (``CloudApp.stage_timer``,
    ``codec_timer``: ``{"stage.place_recognition": {"seconds": s, "messages": n}, ...}``)."""
    covisible: dict[int, dict[int, int]] = field(default_factory=dict)
    """Every keyframe of the atlas at the end: ``{other keyframe: map points both see}``
    (the keyframes a shutdown MBP pass removed are missing)."""


class _Observations:
    """What map fusion did with each new keyframe (from the core's reactions): the
    keyframes the cloud held when it was queried and every verified candidate."""

    def __init__(self, app: CloudApp) -> None:
        self.app = app
        self.info: dict[int, KeyframeInfo] = {}
        self.detections: list[Detection] = []
        self.queries: list[QueryEvent] = []
        self._names: dict[int, str] = {}

    def _name(self, agent_id: int) -> str:
        if agent_id not in self._names:
            self._names = {a: n for a, (n, _, _) in self.app.agents().items()}
        return self._names.get(agent_id, str(agent_id))

    def add(self, reaction: Reaction, held: np.ndarray) -> None:
        """``reaction`` of a keyframe message; ``held (K,)`` the keys before it."""
        events = reaction.events
        if events is None or not reaction.new_keyframes:
            return  # not a new keyframe (an update, or one the cloud pruned)
        kf = self.app.atlas.keyframe(events.key)
        self.info[events.key] = KeyframeInfo(events.key, self._name(kf.agent_id), kf.timestamp)
        held_keys = set(held.tolist())
        connected = [k for k, _ in self.app.atlas.covisible(events.key) if k in held_keys]
        self.queries.append(QueryEvent(events.key, held, np.array(connected, np.int64)))
        accepted = {(o.loop.key_b, o.loop.key_a): o for o in events.outcomes}
        for v in events.verifications:
            o = accepted.get((v.query_key, v.candidate_key)) if v.accepted else None
            kind = "rejected" if o is None else ("merge" if o.merge is not None else "loop")
            self.detections.append(
                Detection(
                    v.query_key,
                    v.candidate_key,
                    np.array(v.T_cbody_qbody),
                    o is not None,
                    kind,
                    v.reason,
                    int(v.n_inliers),
                )
            )


def replay(
    records: Iterable[Record | Step],
    camera: CameraCalibration,
    vocab: Vocabulary,
    config: CloudServiceConfig,
    state_dir: Path,
    label: str = "",
    full_ba: bool = False,
    solve_fn: Callable[[SolveRequest], SolveResult] = solve,
    latency_scale: float = 0.0,
    schedule: str = "modelled",
    covisibility: bool = False,
) -> ReplayResult:
    """Feed ``records`` to a fresh CloudApp on ``state_dir`` (must be empty) through the
    service's core (module docstring); without ``full_ba`` the full bundle adjustment is
    switched off (else it runs when ``config.domain.full_ba.enabled``). ``solve_fn`` solves
    each of the core's requests (default: :func:`services.cloud.core_actions.solve`).

    ``schedule``: ``recorded`` drives the core through the steps the service recorded
    (``records`` from :func:`services.cloud.store.recording.read_schedule` of a version-2
    recording; each message at the ``now`` the service gave it): the service's own run, solve
    for solve, as long as this configuration schedules as the service's did (else
    ReplayDivergedError names the first step that does not fit). ``modelled``: the core's own
    timer on the records' receive times (steps are ignored), each solve taking
    ``latency_scale`` times its wall time here (0: no time, its result applies before the
    next record; 1: records received meanwhile are handled first, as the service handles
    messages while its optimizer process solves). ``covisibility``: fill
    :attr:`ReplayResult.covisible` from the atlas at the end."""
    if latency_scale < 0 or not math.isfinite(latency_scale):
        raise RecslamError(f"latency_scale must be finite and >= 0, got {latency_scale}")
    if schedule not in ("recorded", "modelled"):
        raise RecslamError(f"schedule must be recorded or modelled, got {schedule!r}")
    t0 = time.perf_counter()
    if not full_ba:
        config = without_full_ba(config)
    app = open_app(state_dir, camera, vocab, config)
    if app.atlas.n_keyframes():
        app.close()
        raise RecslamError(f"{state_dir}: not an empty state directory")
    core = CloudCore(app)
    clock = SolveClock(core, solve_fn, latency_scale)
    steps = RecordedSteps(core, solve_fn)
    recorded = schedule == "recorded"
    obs = _Observations(app)
    messages = failed = 0
    now = -math.inf
    try:
        for rec in records:
            if isinstance(rec, Step):
                if recorded:
                    steps.step(rec)
                continue
            if recorded:
                if rec.t_core is None:
                    raise RecslamError(
                        f"record at offset {rec.offset}: no schedule recorded (a version-1 "
                        "recording); replay it with schedule='modelled'"
                    )
                now = rec.t_core
            else:
                now = max(now, rec.t_recv)
                clock.advance(now)
            messages += 1
            keyframe = isinstance(rec.message, KeyframeUpdate | KeyframeUpdateCoded)
            held = np.array(app.atlas.keyframe_keys(), np.int64) if keyframe else None
            try:
                reaction = core.handle(rec.edge_id, rec.message, rec.stream_id, rec.seq, now)
            except RecslamError as exc:  # applied live, so this replay's config differs
                log.warning(
                    "record at offset %d (%s) failed: %s; skipped",
                    rec.offset,
                    type(rec.message).__name__,
                    exc,
                )
                failed += 1
                app.skip(rec.edge_id, rec.stream_id, rec.seq)
                continue
            if held is not None:
                obs.add(reaction, held)
        if recorded and steps.shut_down:
            steps.finish()
        else:  # the service's run ended without its shutdown round (or is modelled)
            clock.t = max(clock.t, now, steps.t)
            now = clock.finish()
            now = clock.run(core.flush, now)
            now = clock.run(core.shutdown, now)
        log.info("%s: %d full BA passes", label, core.full_bas)
        trajs, maps = app.trajectories()
        kept, _ = app.trajectories(retired=False)
        a = app.atlas
        return ReplayResult(
            label=label,
            mbp=config.domain.mbp.enabled,
            messages=messages,
            failed=failed,
            keyframes_received=len(obs.info),
            keyframes=a.n_keyframes(),
            map_points=a.n_map_points(),
            maps=a.maps(),
            merges=len(a.merges()),
            loops=len(a.loops()),
            optimizations=core.optimizations,
            mbp_passes=core.mbp_passes,
            full_bas=core.full_bas,
            seconds=time.perf_counter() - t0,
            trajectories=trajs,
            map_of_robot=maps,
            kept_trajectories=kept,
            info=obs.info,
            detections=obs.detections,
            queries=obs.queries,
            backbone=backbone_breakdown(app),
            schedule=schedule,
            stages={**app.stage_timer.snapshot(), **app.codec_timer.snapshot()},
            covisible={k: dict(a.covisible(k)) for k in a.keyframe_keys()} if covisibility else {},
        )
    finally:
        app.close()


def replay_recording(
    recording: Path,
    camera: CameraCalibration,
    vocab: Vocabulary,
    config: CloudServiceConfig,
    label: str = "",
    **options: Any,
) -> ReplayResult:
    """:func:`replay` of the recording file ``recording`` (a truncated tail allowed, as a run
    that was cut leaves it) on a fresh, temporary state directory; ``options`` are
    :func:`replay`'s (``full_ba``, ``solve_fn``, ``schedule`` ...)."""
    with tempfile.TemporaryDirectory() as tmp:
        return replay(
            read_schedule(recording, allow_truncated_tail=True),
            camera,
            vocab,
            config,
            Path(tmp) / "state",
            label,
            **options,
        )


def backbone_breakdown(app: CloudApp) -> dict[str, int]:
    """Why the final atlas' keyframes would be kept by one more MBP pass, summed over maps (a
    diagnostic of :func:`services.cloud.optimization.mbp.backbone` with MBP's settings, even when
    the replay ran without MBP): ``kept_by_one_more_pass`` and its partition by reason
    (``protected``: each agent's first and ``MbpScheduleConfig.keep_recent`` newest;
    ``not_covered``: the other keyframes see too little of it; ``covers_removed``: a removed
    keyframe would lose its coverage; ``connector``: the kept keyframes would fall apart), and
    ``loop_endpoints``: keyframes at a loop / merge constraint (not protected: MBP moves the
    constraint onto the absorbing keyframe)."""
    atlas = app.atlas
    out = {"keyframes": atlas.n_keyframes(), "loop_endpoints": 0, "kept_by_one_more_pass": 0}
    out.update(dict.fromkeys(REASONS, 0))
    ends = {k for e in atlas.loops() for k in (e.key_a, e.key_b)}
    out["loop_endpoints"] = len(ends)
    for m in atlas.maps():
        bb = backbone(atlas, m, app.config.domain.mbp, app.config.mbp.keep_recent)
        out["kept_by_one_more_pass"] += len(bb.kept)
        for why in bb.reasons.values():
            out[why] += 1
    return out


def joint_ate(
    references: dict[str, Trajectory],
    trajectories: dict[str, Trajectory],
    align: AlignMode = AlignMode.SE3,
) -> JointAteResult | None:
    """Joint and per-robot ATE (SE(3) as the cloud's report, or ``align``) of a replay's
    trajectories."""
    est = {n: t for n, t in trajectories.items() if n in references and len(t) >= 3}
    if not est:
        return None
    return compute_joint_ate({n: references[n] for n in est}, est, AteConfig(align=align))


def common_keyframes(a: ReplayResult, b: ReplayResult) -> tuple[dict, dict]:
    """Both replays' trajectories of kept keyframes (retired ones left out) restricted to the
    keyframe stamps both kept."""
    out_a, out_b = {}, {}
    for name in sorted(set(a.kept_trajectories) & set(b.kept_trajectories)):
        ta, tb = a.kept_trajectories[name], b.kept_trajectories[name]
        both = np.intersect1d(ta.timestamps_ns, tb.timestamps_ns)
        if both.size >= 3:
            out_a[name] = ta.select(np.flatnonzero(np.isin(ta.timestamps_ns, both)))
            out_b[name] = tb.select(np.flatnonzero(np.isin(tb.timestamps_ns, both)))
    return out_a, out_b


@dataclass
class Table3:
    """Both replays, their ATE and the loop scores of the MBP-on replay."""

    recording: Path
    dataset: Path
    off: ReplayResult
    on: ReplayResult
    ate_off: JointAteResult | None
    ate_on: JointAteResult | None
    ate_common_off: JointAteResult | None
    ate_common_on: JointAteResult | None
    ate_kept_on: JointAteResult | None
    loops: LoopScores
    references: dict[str, Trajectory]
    midrun: ReplayResult | None = None
    ate_midrun: JointAteResult | None = None
    ate_kept_midrun: JointAteResult | None = None


def run_table3(
    recording: Path,
    dataset: Path,
    camera: CameraCalibration,
    vocab: Vocabulary,
    criterion: LoopCriterion | None = None,
    work_dir: Path | None = None,
    progress: Callable[[str], None] | None = None,
    midrun_every: int = 100,
    latency_scale: float = 0.0,
) -> Table3:
    """Replay ``recording`` without MBP, with MBP as the service runs it (at shutdown) and
    with MBP also every ``midrun_every`` keyframes while running (0: not), each with the
    server's full-BA schedule and solves taking ``latency_scale`` times their wall time
    (:func:`replay`), and evaluate them against ``dataset``."""
    say = progress or (lambda _msg: None)
    results: dict[Any, ReplayResult] = {}
    runs: list[tuple[bool | str, str, int | None]] = [
        (False, "without MBP", None),
        (True, "with MBP (at shutdown)", None),
    ]
    if midrun_every > 0:
        runs.append(("midrun", f"with MBP every {midrun_every} keyframes", midrun_every))
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        for key, label, every in runs:
            say(f"replaying {recording} {label}")
            # The service's recorded schedule where this configuration schedules as the
            # service did (MBP only at shutdown, or not at all); pruning while running
            # reshapes the map and with it the schedule: modelled.
            mode = "recorded" if every is None and has_schedule(recording) else "modelled"
            records = read_schedule(recording, allow_truncated_tail=True)
            results[key] = replay(
                records,
                camera,
                vocab,
                service_config(key is not False, every),
                Path(tmp) / str(key),
                label,
                full_ba=True,
                latency_scale=latency_scale,
                schedule=mode,
            )
            r = results[key]
            say(
                f"  {label}: {r.keyframes} keyframes, {r.map_points} map points, maps {r.maps}, "
                f"{r.merges} merges, {r.loops} loops ({r.seconds:.0f} s)"
            )
    off, on = results[False], results[True]
    names = sorted(
        set(off.trajectories) | set(on.trajectories) | {i.robot for i in on.info.values()}
    )
    references, _ = load_groundtruth(names, dataset) if names else ({}, {})
    a_off, a_on = common_keyframes(off, on)
    ate_c = {}
    for key, trajs in (("off", a_off), ("on", a_on)):
        ate_c[key] = (
            compute_joint_ate({n: references[n] for n in trajs}, trajs, AteConfig())
            if trajs
            else None
        )
    gt = GroundTruthPoses(
        references, camera.T_body_cam, (criterion or LoopCriterion()).max_gt_gap_s
    )
    loops = score_loops(on.detections, on.queries, on.info, gt, criterion)
    mid = results.get("midrun")
    return Table3(
        recording,
        dataset,
        off,
        on,
        joint_ate(references, off.trajectories),
        joint_ate(references, on.trajectories),
        ate_c["off"],
        ate_c["on"],
        joint_ate(references, on.kept_trajectories),
        loops,
        references,
        mid,
        joint_ate(references, mid.trajectories) if mid else None,
        joint_ate(references, mid.kept_trajectories) if mid else None,
    )


# ---------------------------------------------------------------------- report
