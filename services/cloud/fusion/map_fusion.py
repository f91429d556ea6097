"""Map fusion (paper Section VI.B) as one front object over the cloud's domain blocks.

:class:`MapFusion` owns the atlas, the keyframe database and the place recognizer. A service
feeds what the edges send (:meth:`add_map_point`, :meth:`add_keyframe`); each new keyframe is
queried for places seen before (intra- and inter-robot alike), candidates are verified, and a
verified match merges two maps or adds a loop constraint. Maps that gained a constraint are
reported in :attr:`FusionEvents.maps_to_optimize`; the service then runs
:func:`~services.cloud.optimization.global_optimization.optimize_pose_graph` off its event loop on
:meth:`pose_graph` and hands the result back with :meth:`apply_optimization`; when there is time
it does the same with the full bundle adjustment (:meth:`full_ba_problem`,
:func:`~services.cloud.optimization.full_ba.solve_full_ba`).
Sans-I/O: no sockets, clocks or threads here.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from common.calibration import EUROC_IMU, CameraCalibration, ImuCalibration
from common.errors import RecslamError
from common.links import CodecTimer
from services.cloud.atlas.atlas import Atlas, KeyframeInput, MapPointInput, make_key, split_key
from services.cloud.config import CloudConfig, MbpConfig
from services.cloud.fusion.merge import MatchOutcome, apply_match
from services.cloud.fusion.place_recognition import KeyframeDatabase, PlaceRecognizer
from services.cloud.fusion.verification import VerificationResult, verify_candidate
from services.cloud.optimization.full_ba import (
    FullBAProblem,
    FullBAResult,
    apply_full_ba,
    build_full_ba,
)
from services.cloud.optimization.global_optimization import (
    PoseGraphProblem,
    PoseGraphResult,
    apply_pose_graph,
    build_pose_graph,
)
from services.cloud.optimization.inertial import ImuStore
from services.cloud.optimization.mbp import MbpReport, run_mbp

log = logging.getLogger(__name__)


class FusionError(RecslamError):
    """Map fusion cannot go on with an input (e.g. a keyframe of an agent with no camera)."""


def reason_kind(reason: str) -> str:
    """A verification reason without its numbers (``"tilt 98.2 deg"`` -> ``"tilt deg"``)."""
    return " ".join(w for w in reason.split() if not re.fullmatch(r"[\d./]+", w)) or reason


@dataclass
class FusionEvents:
    """What one keyframe caused: verification results, loops / merges, maps to optimise."""

    key: int
    verifications: list[VerificationResult] = field(default_factory=list)
    outcomes: list[MatchOutcome] = field(default_factory=list)
    maps_to_optimize: set[int] = field(default_factory=set)


class MapFusion:
    """Atlas + place recognition + verification + merging for all agents.

    camera: the fallback camera of agents whose robot's calibration never arrived (recordings
    made before calibrations travelled); :attr:`cameras` holds each agent's own (the service
    sets it from the edges' ``AgentSensors``); :meth:`camera_of` picks. idf (S,): the shared
    vocabulary's idf weights; word_group (S,) optional word -> vocabulary node id for
    word-guided matching (see :func:`verify_candidate`)."""

    def __init__(
        self,
        camera: CameraCalibration | None,
        idf: np.ndarray,
        config: CloudConfig,
        atlas: Atlas | None = None,
        word_group: np.ndarray | None = None,
    ) -> None:
        self.camera = camera
        self.cameras: dict[int, CameraCalibration] = {}  # atlas agent id -> its robot's
        self.imus: dict[int, ImuCalibration] = {}  # atlas agent id -> its robot's IMU
        self.imu = ImuStore()  # the IMU the edges forwarded (for the VI full BA)
        self._fallback_used: set[int] = set()
        self.config = config
        self.atlas = atlas if atlas is not None else Atlas()
        self.word_group = word_group
        self.recognizer = PlaceRecognizer(KeyframeDatabase(idf), config.place_recognition)
        for key in self.atlas.keyframe_keys():  # restored atlas: rebuild the database
            self.recognizer.add(self.atlas, key)
        # Agents whose keyframes and points stay where they are (a prior map, see
        # services.cloud.store.mission): held in every optimisation, never pruned.
        self.held_agents: frozenset[int] = frozenset()
        # Agents whose robot has moved on to a newer map (the service marks them): a map of
        # such agents only is a fragment (``is_fragment``), which may merge with a scale.
        self.superseded_agents: set[int] = set()
        # Verification outcomes so far, by reason ("ok" or the rejection's first word).
        self.verification_counts: Counter[str] = Counter()
        # CPU time (this thread's) of the stages of a new keyframe (``stage.insert``,
        # ``.place_recognition``, ``.verification``, ``.merge``, ``.database``): one call per
        # keyframe each.
        self.timer = CodecTimer(clock=time.thread_time)

    def camera_of(self, agent_id: int) -> CameraCalibration:
        """The camera of atlas agent ``agent_id``: its robot's own, else the fallback (logged
        once per agent); FusionError when there is neither."""
        cam = self.cameras.get(agent_id)
        if cam is not None:
            return cam
        if self.camera is None:
            raise FusionError(f"agent {agent_id}: no calibration received and no fallback camera")
        if agent_id not in self._fallback_used:
            self._fallback_used.add(agent_id)
            log.warning("agent %d: no calibration received; using the fallback camera", agent_id)
        return self.camera

    def imu_of(self, agent_id: int) -> ImuCalibration:
        """The IMU calibration of atlas agent ``agent_id``: its robot's own, else EuRoC's
        ADIS16448 (the synthetic generator's too)."""
        return self.imus.get(agent_id, EUROC_IMU)

    def add_map_point(self, mp: MapPointInput) -> int:
        return self.atlas.add_map_point(mp)

    def add_map_points(self, mps: Sequence[MapPointInput]) -> list[int]:
        return self.atlas.add_map_points(mps)

    def add_keyframe(self, kf: KeyframeInput, detect: bool = True) -> FusionEvents:
        """Insert a keyframe (an update of a known one only refreshes its state), then detect,
        verify and act on places seen before."""
        known = self.atlas.has_keyframe(make_key(kf.agent_id, kf.keyframe_id))
        with self.timer.span("stage.insert"):
            key = self.atlas.add_keyframe(kf)
        events = FusionEvents(key)
        if known or not self.atlas.has_keyframe(key):
            return events
        if detect:
            with self.timer.span("stage.place_recognition"):
                candidates = self.recognizer.detect(self.atlas, key)
            verify_s = merge_s = 0.0
            for cand in candidates:
                same_map = self.atlas.map_id_of_keyframe(key) == self.atlas.map_id_of_keyframe(
                    cand.candidate_key
                )
                if same_map and any(o.loop.key_b == key for o in events.outcomes):
                    continue
                fragment = None if same_map else self._fragment_of(key, cand.candidate_key)
                t0 = self.timer.clock()
                res = verify_candidate(
                    self.atlas,
                    key,
                    cand.candidate_key,
                    self.camera_of(kf.agent_id),
                    self.config.verification,
                    self.word_group,
                    early=cand.early(self.config.place_recognition),
                    max_scale_change=0.0
                    if fragment is None
                    else self.config.merge.fragment_max_scale_change,
                )
                verify_s += self.timer.clock() - t0
                events.verifications.append(res)
                self.verification_counts[reason_kind(res.reason)] += 1
                log.info(
                    "candidate %d (agent %d) for keyframe %d (agent %d), score %.3f: %s "
                    "(%d inliers, ratio %.2f; totals %s)",
                    cand.candidate_key,
                    self.atlas.keyframe(cand.candidate_key).agent_id,
                    key,
                    kf.agent_id,
                    cand.score,
                    "accepted" if res.accepted else res.reason,
                    res.n_inliers,
                    res.inlier_ratio,
                    dict(self.verification_counts),
                )
                if not res.accepted:
                    continue
                t0 = self.timer.clock()
                outcome = apply_match(self.atlas, res, self.config.merge, fragment)
                merge_s += self.timer.clock() - t0
                events.outcomes.append(outcome)
                events.maps_to_optimize.add(self.atlas.map_id_of_keyframe(key))
                self.recognizer.reset_consistency(kf.agent_id)
                break  # one accepted match per keyframe
            self.timer.add("stage.verification", verify_s)
            self.timer.add("stage.merge", merge_s)
        with self.timer.span("stage.database"):
            self.recognizer.add(self.atlas, key)
        return events

    def is_fragment(self, map_id: int) -> bool:
        """Whether every agent of ``map_id`` was superseded by a newer map of its robot (and
        none is held): no edge sends that map's poses any more, so it may take a scale."""
        agents = self.atlas.agents_in_map(map_id)
        return bool(agents) and all(
            a in self.superseded_agents and a not in self.held_agents for a in agents
        )

    def _fragment_of(self, key: int, candidate_key: int) -> int | None:
        """The map of ``candidate_key`` or, else, of ``key`` that is a fragment, or None."""
        for k in (candidate_key, key):
            m = self.atlas.map_id_of_keyframe(k)
            if self.is_fragment(m):
                return m
        return None

    def remove_keyframe(self, key: int) -> None:
        """Drop a keyframe the edge culled (atlas and keyframe database)."""
        self.atlas.remove_keyframe(key)
        if key in self.recognizer.db:
            self.recognizer.db.remove(key)

    def _held(self, keys: np.ndarray) -> np.ndarray:
        """Indices into ``keys`` (keyframe or map point keys) of the held agents' items."""
        if not self.held_agents:
            return np.zeros(0, np.int64)
        agent = [split_key(k)[0] for k in keys.tolist()]
        return np.flatnonzero([a in self.held_agents for a in agent]).astype(np.int64)

    def pose_graph(self, map_id: int) -> PoseGraphProblem:
        """Plain pose-graph problem of a map (give it to ``optimize_pose_graph`` elsewhere);
        the held agents' keyframes are held, one of them fixes the gauge."""
        problem = build_pose_graph(self.atlas, map_id, self.config.optimization)
        held = self._held(problem.keys)
        if held.size:
            problem = dataclasses.replace(problem, held=held, fixed=int(held[0]))
        return problem

    def full_ba_problem(self, map_id: int) -> FullBAProblem:
        """Plain full-BA problem of a map (give it to ``solve_full_ba`` elsewhere); the held
        agents' keyframes and map points are held."""
        problem = build_full_ba(
            self.atlas,
            map_id,
            self.camera_of,
            self.config.full_ba,
            self.config.optimization,
            self.imu,
            self.imu_of,
        )
        held = self._held(problem.keys)
        if not held.size:
            return problem
        held_points = self._held(problem.point_keys)
        # Observations between a held keyframe and a held point constrain nothing that moves:
        # left out (the prior map's own observations would otherwise dominate the solve).
        kf_held = np.zeros(problem.keys.shape[0], bool)
        kf_held[held] = True
        pt_held = np.zeros(problem.point_keys.shape[0], bool)
        pt_held[held_points] = True
        use = ~(kf_held[problem.obs_kf] & pt_held[problem.obs_point])
        return dataclasses.replace(
            problem,
            held=held,
            fixed=int(held[0]),
            held_points=held_points,
            obs_kf=problem.obs_kf[use],
            obs_point=problem.obs_point[use],
            obs_xy=problem.obs_xy[use],
            obs_sigma=problem.obs_sigma[use],
            dropped_observations=problem.dropped_observations + int((~use).sum()),
        )

    def apply_optimization(self, result: PoseGraphResult | FullBAResult) -> int:
        """Write a result back; the held agents' keyframes and points are left exactly as
        they are (their priors kept them within ``prior_sigma`` anyway)."""
        keep = np.setdiff1d(np.arange(result.keys.shape[0]), self._held(result.keys))
        if keep.size < result.keys.shape[0]:
            result = dataclasses.replace(
                result, keys=result.keys[keep], T_world_body=result.T_world_body[keep]
            )
        if isinstance(result, FullBAResult):
            pts = np.setdiff1d(np.arange(result.point_keys.shape[0]), self._held(result.point_keys))
            if pts.size < result.point_keys.shape[0]:
                result = dataclasses.replace(
                    result, point_keys=result.point_keys[pts], p_world=result.p_world[pts]
                )
            return apply_full_ba(self.atlas, result)
        return apply_pose_graph(self.atlas, result)

    def prune(
        self, map_id: int, keep_recent: int = 5, config: MbpConfig | None = None
    ) -> MbpReport:
        """Run MBP on a map (the held agents' keyframes stay; ``config``: in place of the
        configured ``mbp``) and drop the removed keyframes from the database."""
        cfg = self.config.mbp if config is None else config
        report = run_mbp(self.atlas, map_id, self.camera_of, cfg, keep_recent, self.held_agents)
        for key in report.removed_keyframes:
            self.recognizer.db.remove(key)
        return report
