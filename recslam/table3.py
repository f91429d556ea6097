"""The paper's Table 3 from a recorded run: keyframes, map points and ATE with and without MBP.

``recslam demo --record-uplink FILE`` (``recslam cloud --record``) records every uplink
message the cloud applied, in order, with its receive time. :func:`replay` feeds such a
recording to a fresh :class:`~services.cloud.app.CloudApp` (own SQLite state directory) and
replicates :class:`~services.cloud.server.CloudServer`'s schedule synchronously and
deterministically:

- after each message, the maps it made urgent (loop / merge) and every map with
  ``optimize_every_keyframes`` new keyframes are scheduled, as in ``CloudServer._react``;
- the server optimises ``debounce_s`` after the first trigger; the replay does it before
  the first recorded message received ``debounce_s`` or more after the triggering one (the
  solve itself is taken as instantaneous), and once more after the last message;
- each optimisation is built, solved in this process and applied, then MBP runs on the map
  when ``prune_due`` (as ``CloudServer.optimize_map``);
- with ``replay(..., full_ba=True)`` the full bundle adjustment follows the server's
  schedule too: after a map's optimisation once it has ``full_ba_every_keyframes`` new
  keyframes since its last one, before a record that arrived ``full_ba_quiet_s`` or more
  after the last new keyframe ("quiet"), and at the end (the server's shutdown budget).

:func:`run_table3` replays twice — MBP on and MBP off, everything else identical — computes
per-robot and joint ATE of the keyframe trajectories with the cloud report's alignment
(:func:`common.evaluation.metrics.compute_joint_ate`, SE(3)), scores loop detection of the
MBP-on replay (:mod:`recslam.loop_scoring`) and writes ``table3.md``, ``loop_detection.md``,
``table3.json`` and ``table3.png``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.calibration import CameraCalibration
from common.errors import RecslamError
from common.evaluation.metrics import AteConfig, JointAteResult, compute_joint_ate
from common.evaluation.results import load_groundtruth
from common.evaluation.trajectory import Trajectory
from common.vocabulary import Vocabulary
from recslam.loop_scoring import (
    Detection,
    GroundTruthPoses,
    KeyframeInfo,
    LoopCriterion,
    LoopScores,
    QueryEvent,
    score_loops,
)
from services.cloud.app import CloudApp
from services.cloud.atlas import make_key
from services.cloud.config import CloudConfig, CloudServiceConfig, MbpConfig
from services.cloud.full_ba import solve_full_ba
from services.cloud.global_optimization import optimize_pose_graph
from services.cloud.map_fusion import FusionEvents, MapFusion
from services.cloud.mbp import select_backbone
from services.cloud.persistence import CloudStore
from services.cloud.recording import Record, read_recording

log = logging.getLogger(__name__)


def service_config(mbp: bool) -> CloudServiceConfig:
    """The cloud service's default configuration with MBP switched on or off."""
    domain = CloudConfig(mbp=dataclasses.replace(MbpConfig(), enabled=mbp))
    return CloudServiceConfig(domain=domain)


def open_app(
    state_dir: Path, camera: CameraCalibration, vocab: Vocabulary, config: CloudServiceConfig
) -> CloudApp:
    """A CloudApp on ``state_dir`` built as ``CloudServer`` builds it."""
    store = CloudStore(state_dir)
    atlas = store.load()
    wg = None
    if config.word_group_level is not None:
        wg = vocab.ancestor_at_level(list(range(vocab.n_words)), config.word_group_level)
    fusion = MapFusion(camera, vocab.idf, config.domain, atlas, wg)
    return CloudApp(fusion, store, vocab, config)


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
    info: dict[int, KeyframeInfo] = field(default_factory=dict)
    backbone: dict[str, int] = field(default_factory=dict)
    detections: list[Detection] = field(default_factory=list)
    queries: list[QueryEvent] = field(default_factory=list)


class _Observer:
    """Wraps ``fusion.add_keyframe`` of one app to collect queries and verifications."""

    def __init__(self, app: CloudApp) -> None:
        self.app = app
        self.info: dict[int, KeyframeInfo] = {}
        self.detections: list[Detection] = []
        self.queries: list[QueryEvent] = []
        self._names: dict[int, str] = {}
        self._add = app.fusion.add_keyframe
        app.fusion.add_keyframe = self._add_keyframe  # type: ignore[method-assign]

    def _name(self, agent_id: int) -> str:
        if agent_id not in self._names:
            self._names = {a: n for a, (n, _, _) in self.app.agents().items()}
        return self._names.get(agent_id, str(agent_id))

    def _add_keyframe(self, kf: Any, detect: bool = True) -> FusionEvents:
        atlas = self.app.atlas
        key = make_key(kf.agent_id, kf.keyframe_id)
        new = not atlas.has_keyframe(key)
        held = np.array(atlas.keyframe_keys(), np.int64) if new else None
        events = self._add(kf, detect)
        if not new or not atlas.has_keyframe(key):
            return events
        self.info[key] = KeyframeInfo(key, self._name(kf.agent_id), float(kf.timestamp))
        assert held is not None
        self.queries.append(QueryEvent(key, held))
        accepted = {(o.loop.key_b, o.loop.key_a): o for o in events.outcomes}
        for v in events.verifications:
            o = accepted.get((v.query_key, v.candidate_key)) if v.accepted else None
            kind = "rejected" if o is None else ("merge" if o.merge is not None else "loop")
            self.detections.append(
                Detection(v.query_key, v.candidate_key, np.array(v.T_cbody_qbody),
                          o is not None, kind, v.reason, int(v.n_inliers))
            )  # fmt: skip
        return events


def replay(
    records: Iterable[Record],
    camera: CameraCalibration,
    vocab: Vocabulary,
    config: CloudServiceConfig,
    state_dir: Path,
    label: str = "",
    full_ba: bool = False,
) -> ReplayResult:
    """Feed ``records`` to a fresh CloudApp on ``state_dir`` (must be empty) with the
    server's optimisation / MBP schedule (module docstring); ``full_ba`` adds the full
    bundle adjustment's schedule (when ``config.domain.full_ba.enabled``)."""
    t0 = time.perf_counter()
    app = open_app(state_dir, camera, vocab, config)
    if app.atlas.n_keyframes():
        app.close()
        raise RecslamError(f"{state_dir}: not an empty state directory")
    obs = _Observer(app)
    dirty: set[int] = set()
    since: dict[int, int] = {}
    counts = {"optimizations": 0, "mbp": 0, "failed": 0, "messages": 0, "full_ba": 0}
    trigger_t: float | None = None
    full_on = full_ba and config.domain.full_ba.enabled
    since_full: dict[int, int] = {}
    last_kf_t = -1e18

    def full_ba_map(m: int, max_seconds: float | None = None) -> None:
        since_full[m] = 0
        built = app.full_ba_problem(m)
        if built is None:
            return
        cfg = config.domain.full_ba
        if max_seconds is not None:
            cfg = dataclasses.replace(cfg, max_seconds=max_seconds)
        result = solve_full_ba(built[0], cfg, config.domain.optimization)
        if app.apply_optimization(m, result, built[1]) is not None:
            counts["full_ba"] += 1

    def full_ba_changed(max_seconds: float | None = None) -> None:
        for m in sorted(m for m, n in since_full.items() if n > 0):
            full_ba_map(m, max_seconds)

    def optimize_due() -> None:
        nonlocal dirty
        maps, dirty = sorted(dirty), set()
        for m in maps:
            since[m] = 0
            built = app.optimization_problem(m)
            if built is None:
                continue
            problem, token = built
            result = optimize_pose_graph(problem, config.domain.optimization)
            if app.apply_optimization(m, result, token) is None:
                dirty.add(m)  # cannot happen synchronously; kept for parity with the server
                continue
            counts["optimizations"] += 1
            if app.prune_due(m):
                app.prune(m)
                counts["mbp"] += 1
            if full_on and since_full.get(m, 0) >= config.full_ba_every_keyframes:
                full_ba_map(m)

    try:
        for rec in records:
            if trigger_t is not None and rec.t_recv >= trigger_t + config.debounce_s:
                trigger_t = None
                optimize_due()
            quiet = config.full_ba_quiet_s
            if (full_on and quiet > 0 and trigger_t is None and not dirty
                    and rec.t_recv >= last_kf_t + quiet):  # fmt: skip
                full_ba_changed()
            counts["messages"] += 1
            try:
                reaction = app.handle(rec.edge_id, rec.message, rec.stream_id, rec.seq)
            except RecslamError as exc:  # applied live, so this replay's config differs
                log.warning("record at offset %d (%s) failed: %s; skipped", rec.offset,
                            type(rec.message).__name__, exc)  # fmt: skip
                counts["failed"] += 1
                app.skip(rec.edge_id, rec.stream_id, rec.seq)
                continue
            trigger = bool(reaction.urgent_maps)
            dirty.update(reaction.urgent_maps)
            for m in reaction.urgent_maps:
                since_full[m] = since_full.get(m, 0) + 1
            if reaction.new_keyframes:
                last_kf_t = rec.t_recv
            for m, n in reaction.new_keyframes.items():
                since_full[m] = since_full.get(m, 0) + n
                since[m] = since.get(m, 0) + n
                if since[m] >= config.optimize_every_keyframes:
                    dirty.add(m)
                    trigger = True
            if trigger and trigger_t is None:
                trigger_t = rec.t_recv
        if dirty:
            optimize_due()
        if full_on and config.full_ba_at_shutdown_s > 0:
            full_ba_changed(config.full_ba_at_shutdown_s)
        log.info("%s: %d full BA passes", label, counts["full_ba"])
        trajs, maps = app.trajectories()
        a = app.atlas
        return ReplayResult(
            label=label, mbp=config.domain.mbp.enabled, messages=counts["messages"],
            failed=counts["failed"], keyframes_received=len(obs.info),
            keyframes=a.n_keyframes(), map_points=a.n_map_points(), maps=a.maps(),
            merges=len(a.merges()), loops=len(a.loops()),
            optimizations=counts["optimizations"], mbp_passes=counts["mbp"],
            seconds=time.perf_counter() - t0, trajectories=trajs, map_of_robot=maps,
            info=obs.info, detections=obs.detections, queries=obs.queries,
            backbone=backbone_breakdown(app),
        )  # fmt: skip
    finally:
        app.close()


def backbone_breakdown(app: CloudApp) -> dict[str, int]:
    """Why the final atlas' keyframes are kept, summed over maps (a diagnostic of MBP's
    selection, :func:`services.cloud.mbp.select_backbone`, with MBP's settings even when
    the replay ran without MBP): ``loop_endpoints`` (protected), ``first_or_recent``
    (protected: each agent's first and ``mbp_keep_recent`` newest, not loop endpoints),
    ``no_strong_neighbour`` (no strongly covisible keyframe: MBP can never remove them) and
    ``kept_by_one_more_pass`` (what one more MBP pass on the final map would keep)."""
    atlas = app.atlas
    mbp = app.config.domain.mbp
    keep_recent = app.config.mbp_keep_recent
    out = {"keyframes": atlas.n_keyframes(), "loop_endpoints": 0, "first_or_recent": 0,
           "no_strong_neighbour": 0, "kept_by_one_more_pass": 0}  # fmt: skip
    ends = {k for e in atlas.loops() for k in (e.key_a, e.key_b)}
    for m in atlas.maps():
        keys = atlas.keyframe_keys(map_id=m)
        out["loop_endpoints"] += len(ends & set(keys))
        recent: set[int] = set()
        for agent in atlas.agents_in_map(m):
            ak = atlas.keyframe_keys(map_id=m, agent_id=agent)
            recent.update(ak[:1] + (ak[-keep_recent:] if keep_recent > 0 else []))
        out["first_or_recent"] += len(recent - ends)
        npts = {k: int((atlas.keyframe(k).map_point_keys >= 0).sum()) for k in keys}
        for a in keys:
            strong = [b for b, w in atlas.covisible(a, mbp.min_shared)
                      if b in npts and w >= mbp.cover_ratio * min(npts[a], npts[b])]  # fmt: skip
            out["no_strong_neighbour"] += not strong
        out["kept_by_one_more_pass"] += len(select_backbone(atlas, m, mbp, keep_recent))
    return out


def joint_ate(references: dict[str, Trajectory], result: ReplayResult) -> JointAteResult | None:
    """Joint and per-robot ATE (SE(3), as the cloud's report) of a replay's trajectories."""
    est = {n: t for n, t in result.trajectories.items() if n in references and len(t) >= 3}
    if not est:
        return None
    return compute_joint_ate({n: references[n] for n in est}, est, AteConfig())


def common_keyframes(a: ReplayResult, b: ReplayResult) -> tuple[dict, dict]:
    """Both replays' trajectories restricted to the keyframe stamps both kept."""
    out_a, out_b = {}, {}
    for name in sorted(set(a.trajectories) & set(b.trajectories)):
        ta, tb = a.trajectories[name], b.trajectories[name]
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
    loops: LoopScores
    references: dict[str, Trajectory]


def run_table3(
    recording: Path,
    dataset: Path,
    camera: CameraCalibration,
    vocab: Vocabulary,
    criterion: LoopCriterion | None = None,
    work_dir: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> Table3:
    """Replay ``recording`` without and with MBP and evaluate both against ``dataset``."""
    say = progress or (lambda _msg: None)
    results = {}
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        for mbp in (False, True):
            label = "with MBP" if mbp else "without MBP"
            say(f"replaying {recording} {label}")
            records = read_recording(recording, allow_truncated_tail=True)
            results[mbp] = replay(records, camera, vocab, service_config(mbp),
                                  Path(tmp) / ("mbp" if mbp else "nombp"), label)  # fmt: skip
            r = results[mbp]
            say(f"  {label}: {r.keyframes} keyframes, {r.map_points} map points, maps {r.maps}, "
                f"{r.merges} merges, {r.loops} loops ({r.seconds:.0f} s)")  # fmt: skip
    off, on = results[False], results[True]
    names = sorted(
        set(off.trajectories) | set(on.trajectories) | {i.robot for i in on.info.values()}
    )
    references, _ = load_groundtruth(names, dataset) if names else ({}, {})
    a_off, a_on = common_keyframes(off, on)
    ate_c = {}
    for key, trajs in (("off", a_off), ("on", a_on)):
        ate_c[key] = compute_joint_ate({n: references[n] for n in trajs}, trajs, AteConfig()) \
            if trajs else None  # fmt: skip
    gt = GroundTruthPoses(
        references, camera.T_body_cam, (criterion or LoopCriterion()).max_gt_gap_s
    )
    loops = score_loops(on.detections, on.queries, on.info, gt, criterion)
    return Table3(recording, dataset, off, on, joint_ate(references, off),
                  joint_ate(references, on), ate_c["off"], ate_c["on"], loops,
                  references)  # fmt: skip


# ---------------------------------------------------------------------- report
def _f(x: float | None, spec: str = ".3f") -> str:
    return "–" if x is None else format(x, spec)


def _pct(new: float, old: float) -> str:
    return "–" if not old else f"{100.0 * (new - old) / old:+.1f} %"


def _ate_cells(ate: JointAteResult | None, names: list[str]) -> list[str]:
    cells = []
    for n in names:
        ind = ate.individual.get(n) if ate is not None else None
        cells.append(_f(ind.stats.rmse if ind is not None else None))
    cells.append(_f(ate.stats.rmse if ate is not None else None))
    return cells


def table3_markdown(t: Table3) -> str:
    """``table3.md``: the table, the targets and how it was made."""
    names = sorted(t.references)
    off, on = t.off, t.on
    kf_red = 100.0 * (off.keyframes - on.keyframes) / off.keyframes if off.keyframes else 0.0
    j_off = t.ate_off.stats.rmse if t.ate_off is not None else None
    j_on = t.ate_on.stats.rmse if t.ate_on is not None else None
    ate_ok = j_off is not None and j_on is not None and j_on <= j_off * 1.05 + 0.005
    head = " | ".join(f"ATE {n} m" for n in names)
    lines = [
        "# Table 3: map backbone profiling (MBP) on the synthetic 3-robot dataset",
        "",
        f"Recording `{t.recording}` ({off.messages} uplink messages, "
        f"{off.keyframes_received} keyframes received) of one `recslam demo` run on "
        f"`{t.dataset}`, replayed through a fresh `CloudApp` twice with the cloud's default "
        "configuration, MBP off and on; optimisation and MBP follow the service's schedule "
        "synchronously (`recslam/table3.py`). Keyframes / map points: the cloud atlas at the "
        "end. ATE: RMSE of the cloud's keyframe trajectories (`T_map_body`) against ground "
        "truth after SE(3) alignment (the cloud report's), per robot aligned alone and "
        "joint (all robots, one transform: meaningful when all are in one map). "
        "Generated by `recslam experiment table3`.",
        "",
        f"| | keyframes | map points | {head} | ATE joint m | maps | merges | loops "
        "| optimisations | MBP passes |",
        "|---|---|---|" + "---|" * len(names) + "---|---|---|---|---|---|",
    ]
    for r, ate in ((off, t.ate_off), (on, t.ate_on)):
        cells = _ate_cells(ate, names)
        lines.append(
            f"| {r.label} | {r.keyframes} | {r.map_points} | {' | '.join(cells)} | "
            f"{len(r.maps)} | {r.merges} | {r.loops} | {r.optimizations} | {r.mbp_passes} |"
        )
    lines.append(
        f"| change | {_pct(on.keyframes, off.keyframes)} | {_pct(on.map_points, off.map_points)}"
        f" | " + " | ".join("" for _ in names) + f" | {_pct(j_on or 0.0, j_off or 0.0)} "
        "| | | | | |"
    )
    lines += [
        "",
        "ATE over only the keyframes both replays kept (same poses compared):",
        "",
        f"| | {head} | ATE joint m |",
        "|---|" + "---|" * len(names) + "---|",
        f"| without MBP | {' | '.join(_ate_cells(t.ate_common_off, names))} |",
        f"| with MBP | {' | '.join(_ate_cells(t.ate_common_on, names))} |",
        "",
        "Targets (issue #6): keyframes reduced by ≥ 40 %: "
        f"**{'met' if kf_red >= 40.0 else 'not met'}** ({kf_red:.1f} %); joint ATE not worse "
        "(within 5 % + 5 mm): "
        f"**{'met' if ate_ok else 'not met'}** ({_f(j_off, '.4f')} m → {_f(j_on, '.4f')} m).",
        "",
        "Why keyframes are kept (final atlas; MBP's selection rules, see "
        "`recslam.table3.backbone_breakdown`; categories overlap except the first two):",
        "",
        "| | keyframes | loop / merge endpoints (protected) | first or newest per robot "
        "(protected) | no strongly covisible neighbour | kept by one more MBP pass now |",
        "|---|---|---|---|---|---|",
        *[
            f"| {r.label} | {b.get('keyframes', '–')} | {b.get('loop_endpoints', '–')} | "
            f"{b.get('first_or_recent', '–')} | {b.get('no_strong_neighbour', '–')} | "
            f"{b.get('kept_by_one_more_pass', '–')} |"
            for r, b in ((off, off.backbone), (on, on.backbone))
        ],
        "",
        f"Replay time: {off.seconds:.0f} s without, {on.seconds:.0f} s with MBP; "
        f"messages that failed in a replay: {off.failed} / {on.failed}.",
        "",
        "![trajectories and map size](table3.png)",
        "",
    ]
    return "\n".join(lines)


def loop_markdown(t: Table3) -> str:
    """``loop_detection.md``: precision / recall of the MBP-on replay, definitions first."""
    s = t.loops
    c = s.criterion
    lines = [
        "# Loop / merge detection against ground truth (synthetic 3-robot dataset)",
        "",
        f"From the MBP-on replay of `{t.recording}` (`recslam experiment table3`, "
        "`recslam/loop_scoring.py`). Ground truth: each robot's body pose at the keyframe's "
        f"stamp (nearest within {c.max_gt_gap_s * 1e3:.0f} ms) in the dataset's common room "
        "frame; camera pose = body pose · `T_body_cam` of the dataset's calibration.",
        "",
        "Definitions:",
        "",
        "- **TP**: an accepted loop or merge whose verified relative pose (query body in the "
        "matched keyframe's body frame, from PnP against the matched metric map) is within "
        f"{c.max_trans_err_m:g} m and {c.max_rot_err_deg:g}° of the ground-truth relative pose "
        "(maps are visual-inertial, hence metric: no scale is fitted; a scale error shows as "
        "translation error). **FP**: any other accepted one. **Precision** = TP / accepted.",
        "- **Revisit partner** of a new keyframe: a keyframe the cloud held when the new one "
        "was queried — another robot's, or the same robot's more than "
        f"{c.same_robot_min_gap_s:g} s apart — with ground-truth camera centres within "
        f"{c.revisit_dist_m:g} m and optical axes within {c.revisit_angle_deg:g}°. "
        "**Recall** = new keyframes with a revisit partner for which a TP loop / merge was "
        "found / new keyframes with a revisit partner. The cloud accepts at most one match per "
        "keyframe and a loop is only needed now and then, so a low recall is expected; it "
        "measures how often a revisit is closed, not whether the maps merge.",
        "- **Rejected**: candidates place recognition proposed and geometric verification "
        "refused (by reason, numbers left out); 'at a true place' = of those, the ones whose "
        "two keyframes' ground-truth cameras are within the revisit thresholds (verification "
        "keeps no pose for a rejected candidate, so the place is judged, not a transform).",
        "",
        "| accepted | TP | FP | precision | queries | with revisit partner | found | recall "
        "| rejected | rejected at a true place |",
        "|---|---|---|---|---|---|---|---|---|---|",
        f"| {len(s.accepted)} | {s.true_positives} | {s.false_positives} | "
        f"{_f(s.precision, '.3f')} | {s.queries} | {s.queries_with_partner} | {s.found} | "
        f"{_f(s.recall, '.3f')} | {len(s.rejected)} | {s.rejected_true} |",
        "",
        "Rejections by reason: "
        + (", ".join(f"{k} {v}" for k, v in s.rejected_reasons.most_common()) or "none"),
        "",
        "Accepted detections:",
        "",
        "| kind | query (robot, t s) | match (robot, t s) | inliers | GT distance m "
        "| trans err m | rot err ° | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    t_min = min((i.timestamp_s for i in t.on.info.values()), default=0.0)
    for d in s.accepted:
        verdict = {True: "TP", False: "FP", None: "no GT"}[d.true]
        lines.append(
            f"| {d.detection.kind} | {d.query.robot}, {d.query.timestamp_s - t_min:.1f} | "
            f"{d.match.robot}, {d.match.timestamp_s - t_min:.1f} | {d.detection.n_inliers} | "
            f"{_f(d.gt_distance_m, '.2f')} | {_f(d.trans_err_m, '.3f')} | "
            f"{_f(d.rot_err_deg, '.2f')} | {verdict} |"
        )
    lines += ["", f"(t = seconds after the first keyframe, t0 = {t_min:.3f} s)", ""]
    return "\n".join(lines)


def table3_json(t: Table3) -> dict[str, Any]:
    """Plain numbers of both replays and the loop scores."""

    def row(r: ReplayResult, ate: JointAteResult | None) -> dict[str, Any]:
        return {
            "keyframes": r.keyframes, "keyframes_received": r.keyframes_received,
            "map_points": r.map_points, "maps": r.maps, "merges": r.merges, "loops": r.loops,
            "optimizations": r.optimizations, "mbp_passes": r.mbp_passes,
            "messages": r.messages, "failed": r.failed, "seconds": r.seconds,
            "ate_joint_m": ate.stats.rmse if ate is not None else None,
            "ate_m": {n: a.stats.rmse for n, a in ate.individual.items()} if ate else {},
            "backbone": r.backbone,
        }  # fmt: skip

    s = t.loops
    return {
        "recording": str(t.recording),
        "dataset": str(t.dataset),
        "without_mbp": row(t.off, t.ate_off),
        "with_mbp": row(t.on, t.ate_on),
        "loops": {
            "criterion": dataclasses.asdict(s.criterion),
            "accepted": len(s.accepted),
            "tp": s.true_positives,
            "fp": s.false_positives,
            "precision": s.precision,
            "queries": s.queries,
            "with_partner": s.queries_with_partner,
            "found": s.found,
            "recall": s.recall,
            "rejected": len(s.rejected),
            "rejected_true": s.rejected_true,
        },
    }


def plot_table3(t: Table3, path: Path) -> Path:
    """Top views of the jointly aligned keyframe trajectories without / with MBP over the
    ground truth, and a bar chart of keyframes and map points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, r, ate in ((axes[0], t.off, t.ate_off), (axes[1], t.on, t.ate_on)):
        for i, (name, ref) in enumerate(sorted(t.references.items())):
            c = colors[i % len(colors)]
            ax.plot(ref.p_world_body[:, 0], ref.p_world_body[:, 1], color=c, alpha=0.3, lw=1)
            if ate is not None and name in ate.under_joint:
                p = ate.under_joint[name].est_aligned.p_world_body
                ax.plot(p[:, 0], p[:, 1], ".", color=c, ms=3, label=f"{name} ({len(p)} kf)")
        joint = f"joint ATE {ate.stats.rmse:.3f} m" if ate is not None else "no ATE"
        ax.set_title(f"{r.label}: {r.keyframes} keyframes, {joint}")
        ax.set_aspect("equal")
        ax.set_xlabel("x m (ground-truth frame)")
        ax.set_ylabel("y m")
        ax.legend(fontsize=8)
    ax = axes[2]
    x = np.arange(2)
    ax.bar(x - 0.2, [t.off.keyframes, t.on.keyframes], 0.4, label="keyframes")
    ax2 = ax.twinx()
    ax2.bar(x + 0.2, [t.off.map_points, t.on.map_points], 0.4, color=colors[1],
            label="map points")  # fmt: skip
    ax.set_xticks(x, ["without MBP", "with MBP"])
    ax.set_ylabel("keyframes")
    ax2.set_ylabel("map points")
    ax.set_title("map size at the end")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_table3(t: Table3, out: Path, results: Path | None = None) -> list[Path]:
    """Write ``table3.md``, ``loop_detection.md``, ``table3.json`` and ``table3.png`` into
    ``out`` (and the md / png files into ``results`` too, e.g. benchmarks/results)."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "table3.md", out / "loop_detection.md", out / "table3.json"]
    files[0].write_text(table3_markdown(t))
    files[1].write_text(loop_markdown(t))
    files[2].write_text(json.dumps(table3_json(t), indent=2) + "\n")
    files.append(plot_table3(t, out / "table3.png"))
    if results is not None:
        results.mkdir(parents=True, exist_ok=True)
        for f in (files[0], files[1], files[3]):
            target = results / f.name
            target.write_bytes(f.read_bytes())
            files.append(target)
    return files
