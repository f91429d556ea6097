"""The cloud app's optimisation side: pose graphs and full BA out and back, corrections, MBP.

:class:`AppOptimization` is a base of :class:`~services.cloud.app.CloudApp`, which sets the
attributes declared here; the service's :class:`~services.cloud.core.CloudCore` decides when each
runs. :meth:`AppOptimization.optimization_problem` and :meth:`AppOptimization.full_ba_problem`
build a map's problem with a token of the atlas' merge state, the solve runs elsewhere, and
:meth:`AppOptimization.apply_optimization` writes it back (unless maps were merged meanwhile)
and returns the :class:`Correction` for each agent in the map, in its edge map's frame.
:meth:`AppOptimization.prune` runs MBP on a map (:meth:`AppOptimization.prune_due`: every
``MbpScheduleConfig.every_keyframes`` new keyframes) and keeps what it removed for the
dashboard.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from common.geometry import inverse_T
from common.links import CodecTimer, WireFormat
from common.links.edge_cloud import (
    MapPlacement,
    PoseCorrection,
    PoseCorrectionCoded,
    encode_map_placement,
    encode_pose_correction,
)
from services.cloud.agents import AgentKey, AtlasAgent
from services.cloud.atlas.atlas import Atlas, split_key
from services.cloud.fusion.map_fusion import MapFusion
from services.cloud.optimization.full_ba import FullBAProblem, FullBAResult
from services.cloud.optimization.global_optimization import PoseGraphProblem, PoseGraphResult
from services.cloud.optimization.mbp import MbpReport
from services.cloud.service_config import CloudServiceConfig
from services.cloud.store.persistence import CloudStore

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Correction:
    """A pose correction to send: the edge serving the robot, the message, and where that
    robot's map sits in the global map (sent after it)."""

    edge_id: str
    message: PoseCorrection | PoseCorrectionCoded
    placement: MapPlacement | None = None


class AppOptimization:
    """The optimisation hand-off and MBP of :class:`~services.cloud.app.CloudApp`."""

    fusion: MapFusion
    store: CloudStore
    config: CloudServiceConfig
    stage_timer: CodecTimer
    _agents: dict[AgentKey, AtlasAgent]
    _mbp_done: dict[int, int]  # map -> keyframes at its last MBP pass
    _pruned_points: set[int]  # removed by MBP (not by the edge's culling)
    _pruned_keyframes: set[int]
    _changes: int  # bumped by every atlas mutation

    if TYPE_CHECKING:  # CloudApp's

        @property
        def atlas(self) -> Atlas: ...

    def optimization_problem(self, map_id: int) -> tuple[PoseGraphProblem, int] | None:
        """The pose graph of ``map_id`` and a token of the atlas' merge state (None if the map
        is gone or too small)."""
        if map_id not in self.atlas.maps() or self.atlas.n_keyframes(map_id) < 2:
            return None
        with self.stage_timer.span("stage.pose_graph_build"):
            return self.fusion.pose_graph(map_id), len(self.atlas.merges())

    def full_ba_problem(self, map_id: int) -> tuple[FullBAProblem, int] | None:
        """The full bundle adjustment of ``map_id`` and the merge-state token (None if the
        map is gone, too small, or full BA is switched off)."""
        if not self.config.domain.full_ba.enabled or map_id not in self.atlas.maps():
            return None
        if self.atlas.n_keyframes(map_id) < 2:
            return None
        with self.stage_timer.span("stage.full_ba_build"):
            return self.fusion.full_ba_problem(map_id), len(self.atlas.merges())

    def apply_optimization(
        self, map_id: int, result: PoseGraphResult | FullBAResult, token: int
    ) -> list[Correction] | None:
        """Write an optimisation back (None if maps were merged meanwhile: then the poses are
        in a stale frame and the caller should optimise again); returns the corrections."""
        if token != len(self.atlas.merges()) or map_id not in self.atlas.maps():
            return None
        kind = "full_ba" if isinstance(result, FullBAResult) else "pose_graph"
        with self.stage_timer.span(f"stage.{kind}_apply"):
            n = self.fusion.apply_optimization(result)
            self._changes += 1
            self.store.commit_poses(self.atlas)  # what it changed (Atlas.unsaved)
        log.info(
            "map %d: applied optimisation of %d keyframes (error %.3g -> %.3g)",
            map_id,
            n,
            result.initial_error,
            result.final_error,
        )
        with self.stage_timer.span("stage.corrections"):
            return self.corrections(map_id)

    def corrections(self, map_id: int) -> list[Correction]:
        """Current keyframe poses of every agent in ``map_id``, each in its own map frame, each
        with the placement of that frame in ``map_id`` (:class:`MapPlacement`)."""
        out = []
        for a in self._agents.values():
            if a.agent_id not in self.atlas.agents():
                continue
            keys = self.atlas.keyframe_keys(map_id=map_id, agent_id=a.agent_id)
            if not keys:
                continue
            T_agent_map = inverse_T(self.atlas.T_map_agent(a.agent_id))
            ids = np.array([split_key(k)[1] for k in keys], np.int64)
            T = np.array([T_agent_map @ self.atlas.T_map_body(k) for k in keys])
            coded = self.config.wire is WireFormat.CODED
            msg = encode_pose_correction(a.name, a.edge_map, ids, T, coded)
            T_global_map = self.atlas.T_map_agent(a.agent_id)
            place = encode_map_placement(a.name, a.edge_map, map_id, T_global_map)
            out.append(Correction(a.edge_id, msg, place))
        return out

    def shed(self, overloaded: bool) -> None:
        """Shed (or take up again) the app's optional work: the early loop candidates."""
        self.fusion.recognizer.shed_early = overloaded

    def prune_due(self, map_id: int) -> bool:
        every = self.config.mbp.every_keyframes
        on = self.config.domain.mbp.enabled and self.config.mbp.running.enabled
        if not on or every <= 0 or map_id not in self.atlas.maps():
            return False
        n = self.atlas.n_keyframes(map_id)
        return n - self._mbp_done.get(map_id, 0) >= every

    def prune(self, map_id: int, final: bool = False) -> MbpReport:
        """MBP on ``map_id`` (then the whole atlas is saved). While running (not ``final``)
        each agent's ``MbpScheduleConfig.settle_keyframes`` newest keyframes are kept and the
        pass has ``MbpScheduleConfig.running``'s options; the final pass (at shutdown) keeps
        ``MbpScheduleConfig.keep_recent`` and has ``CloudConfig.mbp``'s."""
        before = set(self.atlas.map_point_keys(map_id))
        schedule = self.config.mbp
        keep, mbp = schedule.keep_recent, self.config.domain.mbp
        if not final:
            keep, mbp = max(keep, schedule.settle_keyframes), schedule.running
        with self.stage_timer.span("stage.mbp"):
            report = self.fusion.prune(map_id, keep, mbp)
        self._changes += 1
        self._pruned_points |= before - set(self.atlas.map_point_keys(map_id))
        self._pruned_keyframes.update(report.removed_keyframes)
        self._mbp_done[map_id] = self.atlas.n_keyframes(map_id)
        self.store.save_all(self.atlas)
        log.info(
            "MBP map %d: keyframes %d -> %d, map points %d -> %d",
            map_id,
            report.keyframes_before,
            report.keyframes_after,
            report.map_points_before,
            report.map_points_after,
        )
        return report
