"""The cloud's application: reacts to the edges' messages with the map-fusion blocks.

:class:`CloudApp` is synchronous and owns every mutable piece of the cloud: the
:class:`~services.cloud.fusion.map_fusion.MapFusion` (atlas, keyframe database) and the
:class:`~services.cloud.store.persistence.CloudStore`. The network service runs all of its methods
on one worker thread (so the atlas has a single owner and the event loop never blocks on
decoding, verification, SQLite or MBP); only the pure pose-graph solve runs elsewhere.
Building the optimisations, applying them (the corrections) and MBP are the base class's,
:class:`~services.cloud.app_optimization.AppOptimization`.

Per message (:meth:`CloudApp.handle`): decode (``services.cloud.fusion.uplink``), apply to the
atlas, then commit what changed *together with the edge link's delivered position* in one
SQLite transaction. The transport acknowledges after the handler returns, so an
acknowledged keyframe is durable, and a restarted cloud tells the edge where to resume:
nothing acknowledged is lost and nothing is applied twice (:class:`PositionStore`).

Robots are named by strings on the wire (``KeyframeUpdate.agent_id``) and each robot's edge may
start a new map for it (``map_id``, e.g. after tracking was lost): every (edge, robot, edge map)
triple has its own frame, so it is one *atlas agent* (:data:`~services.cloud.agents.AgentKey`),
numbered 0, 1, ... in order of appearance. Several edges (sites) share one cloud: the edge is part
of the key, so two edges' agents never mix (an edge can only address its own), a robot that moves to
another edge becomes a new agent there whose map merges by place recognition as any other, and
merging across edges is the same as within one. The table of agents (robot name, edge, edge map) is
persisted with the keyframes. Corrections go back per atlas agent, to the edge that serves it, in
that edge map's frame.

Missions (:mod:`services.cloud.store.mission`): the agents of earlier missions in the state
directory are the read-only *prior map* (:attr:`CloudApp._prior`, by atlas agent id, apart
from the current mission's ``(robot, edge map)`` keys); new robots relocalise against it and
their maps merge into it.

Each robot's sensors (``AgentSensors``, sent by its edge before the robot's first keyframe)
are persisted by robot name (``services.cloud.fusion.robot_sensors``; robot names are unique in a
team, so a robot seen on a second edge keeps the sensors it first announced, and other
sensors from another edge are logged and ignored): every atlas agent of that robot, on any
edge, projects with its camera (``MapFusion.cameras``) and its keyframes decode with its image
size; a robot without one (recordings made before calibrations travelled) uses the fallback
camera the service was given.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.calibration import CameraCalibration
from common.evaluation.trajectory import Trajectory
from common.links import CodecTimer
from common.links.edge_cloud import (
    AgentSensors,
    AgentStatus,
    CullEvent,
    FramePoses,
    KeyframePoses,
    KeyframeUpdate,
    KeyframeUpdateCoded,
    MapPointUpdate,
    MapPointUpdateCoded,
    read_frame_poses,
)
from common.map_view import GroundTruth
from common.protocol.errors import RemoteProtocolError
from common.protocol.messages import Message
from common.protocol.store import InboundPosition
from common.vocabulary import Vocabulary
from services.cloud.agents import AgentKey, AtlasAgent
from services.cloud.app_optimization import AppOptimization
from services.cloud.atlas.atlas import Atlas, AtlasSnapshot, KeyframeInput, make_key
from services.cloud.fusion.map_fusion import FusionEvents, MapFusion
from services.cloud.fusion.rebase import FrameRebase, rebased_keyframe
from services.cloud.fusion.robot_sensors import RobotSensorBook
from services.cloud.fusion.uplink import (
    DecodedKeyframe,
    KeyframeDecoders,
    UplinkError,
    decode_cull_event,
    decode_keyframe_poses,
    decode_keyframe_update,
    decode_map_point_update,
)
from services.cloud.service_config import CloudServiceConfig
from services.cloud.store.frame_trajectories import FrameTrack
from services.cloud.store.ground_truth import references_in_maps
from services.cloud.store.map_source import AgentInfo, CloudView
from services.cloud.store.mission import MissionClock
from services.cloud.store.output import robot_trajectories
from services.cloud.store.persistence import CloudStore

log = logging.getLogger(__name__)


class PositionStore:
    """The transport's ``DeliveryStore`` over the cloud's SQLite positions.

    ``load`` answers from a cache that :class:`CloudApp` fills from the database at start and
    updates after each commit (so the event-loop thread never touches SQLite); ``save`` does
    nothing: the position is written by the app in the same transaction as the message's
    effect, which is what makes delivery exactly-once across a cloud crash."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._positions: dict[str, InboundPosition] = {}

    def load(self, peer: str) -> InboundPosition | None:
        with self._lock:
            return self._positions.get(peer)

    def save(self, peer: str, position: InboundPosition) -> None:
        """No-op (see the class docstring)."""

    def set(self, peer: str, position: InboundPosition) -> None:
        with self._lock:
            self._positions[peer] = position


@dataclass
class Reaction:
    """What one message changed: maps that need an optimisation now (loop / merge), new
    keyframes per map, whether maps were merged, and what map fusion did with the message's
    keyframe (``events``: its verifications and loops / merges; None for other messages)."""

    urgent_maps: set[int] = field(default_factory=set)
    new_keyframes: dict[int, int] = field(default_factory=dict)
    merged: bool = False
    events: FusionEvents | None = None


class CloudApp(AppOptimization):
    """Message handling, optimisation hand-off, MBP and outputs over one atlas.

    Not thread-safe: call everything from one thread (the service's worker).
    """

    def __init__(
        self,
        fusion: MapFusion,
        store: CloudStore,
        vocabulary: Vocabulary,
        config: CloudServiceConfig,
        positions: PositionStore | None = None,
    ) -> None:
        self.fusion = fusion
        self.store = store
        self.vocabulary = vocabulary
        self.config = config
        self.positions = positions or PositionStore()
        # The current mission's agents by (edge, robot, edge map); earlier missions' by id.
        self._agents: dict[AgentKey, AtlasAgent] = {}
        self._prior: dict[int, AtlasAgent] = {}
        self.sensors = RobotSensorBook(store.sensors(), fusion.camera)
        missions = store.agent_missions()
        for aid, (name, edge, edge_map) in store.agents().items():
            a = AtlasAgent(aid, name, edge, edge_map)
            if missions.get(aid, store.mission) < store.mission:
                a.status = "prior"
                self._prior[aid] = a
            else:
                self._agents[edge, name, edge_map] = a
            self._use_camera(aid, name)
        fusion.held_agents = frozenset(self._prior)
        self._supersede()
        self.mission = MissionClock(
            store.missions().get(store.mission, ""), self.atlas, self._prior, self._names()
        )
        for edge, (stream, seq) in store.positions().items():
            self.positions.set(edge, InboundPosition(stream, seq))
        self._mbp_done: dict[int, int] = {}  # map -> keyframes at its last MBP pass
        self._pruned_points: set[int] = set()  # removed by MBP (not by the edge's culling)
        self._pruned_keyframes: set[int] = set()
        self.messages = 0
        self.rejected = 0
        self.rebase = FrameRebase()  # the edge's payloads placed through their anchors
        self.codec_timer = CodecTimer()
        self.frames = FrameTrack()  # the robots' frames relative to their keyframes
        self.decoders = KeyframeDecoders(vocabulary)  # one feature decoder per codec config
        # (edge agent id, edge map id) -> (keyframe id, descriptors) of the newest keyframe
        # received: what the next one's carried descriptors name (``fill_carried``)
        self._last_descriptors: dict[tuple[str, int], tuple[int, np.ndarray]] = {}
        # CPU time of the worker's stages (``stage.*``: map fusion's per keyframe, the
        # commits, building and applying optimisations, MBP), for ``--stats-out``.
        self.stage_timer = fusion.timer
        self._changes = 0  # bumped by every atlas mutation (the view is rebuilt only then)
        self._view_cache: tuple[int, AtlasSnapshot] | None = None

    @property
    def atlas(self) -> Atlas:
        return self.fusion.atlas

    # ------------------------------------------------------------------ agents
    def _agent(
        self, name: str, edge_id: str, edge_map: int, create: bool = True
    ) -> tuple[AtlasAgent, bool]:
        """The current mission's agent (``edge_id``, robot ``name``, ``edge_map``) and whether
        it is new. An edge only ever addresses its own agents; a message that may not start one
        (``create`` False: culls, pose updates) for an agent the edge never had raises
        UplinkError. New agents are numbered after the prior map's too."""
        a = self._agents.get((edge_id, name, edge_map))
        if a is not None:
            return a, False
        if not create:
            raise UplinkError(f"edge {edge_id!r} has no agent of robot {name!r} map {edge_map}")
        known = [*self._agents.values(), *self._prior.values()]
        next_id = max((x.agent_id for x in known), default=-1) + 1
        a = self._agents[edge_id, name, edge_map] = AtlasAgent(next_id, name, edge_id, edge_map)
        log.info("new agent %d: robot %r, map %d of edge %r", next_id, name, edge_map, edge_id)
        self._supersede()
        self._use_camera(next_id, name)
        return a, True

    def _supersede(self) -> None:
        """Mark every robot's agents but its newest superseded: the robot moved on from their
        maps, which are fragments now (``MapFusion.is_fragment``)."""
        newest: dict[str, int] = {}
        for a in self._agents.values():
            newest[a.name] = max(newest.get(a.name, a.agent_id), a.agent_id)
        self.fusion.superseded_agents = {
            a.agent_id for a in self._agents.values() if newest[a.name] != a.agent_id
        }

    def _use_camera(self, agent_id: int, name: str) -> None:
        cam = self.sensors.camera(name)
        if cam is not None:
            self.fusion.cameras[agent_id] = cam
        sensors = self.sensors.sensors.get(name)
        if sensors is not None:
            self.fusion.imus[agent_id] = sensors.imu

    def _sensors(
        self, edge_id: str, msg: AgentSensors, position: dict[str, tuple[bytes, int]]
    ) -> Reaction:
        """A robot's sensors: remembered (durably) and used by all its atlas agents."""
        learnt = self.sensors.learn(edge_id, msg)
        self.store.commit(self.atlas, positions=position, sensors=dict([learnt] if learnt else []))
        for a in self._agents.values():  # the prior map's agents keep the camera they had
            if a.name == msg.agent_id:
                self._use_camera(a.agent_id, a.name)
        return Reaction()

    def agents(self) -> dict[int, tuple[str, str, int]]:
        """The current mission's ``{atlas agent id: (robot name, edge id, edge map id)}``."""
        return {a.agent_id: (a.name, a.edge_id, a.edge_map) for a in self._agents.values()}

    def prior_agents(self) -> dict[int, tuple[str, str, int]]:
        """Earlier missions' agents (the prior map), as :meth:`agents`."""
        return {a.agent_id: (a.name, a.edge_id, a.edge_map) for a in self._prior.values()}

    def _names(self) -> dict[int, str]:
        return {a.agent_id: a.name for a in self._agents.values()}

    def mission_report(self) -> dict[str, object]:
        """The current mission and its merges into the prior map (``MissionClock.report``)."""
        return self.mission.report(a.name for a in self._agents.values())

    def _rows(self, a: AtlasAgent) -> dict[int, tuple[str, str, int]]:
        return {a.agent_id: (a.name, a.edge_id, a.edge_map)}

    # ------------------------------------------------------------------ messages
    def handle(self, edge_id: str, message: Message, stream_id: bytes, seq: int) -> Reaction:
        """Apply one message from ``edge_id`` and make it durable with its position.

        Raises :class:`UplinkError` for a malformed message (nothing is applied)."""
        self.messages += 1
        self._changes += 1
        position = {edge_id: (stream_id, seq)}
        if isinstance(message, KeyframeUpdate | KeyframeUpdateCoded):
            reaction = self._keyframe(edge_id, message, position)
        elif isinstance(message, KeyframePoses):
            reaction = self._keyframe_poses(edge_id, message, position)
        elif isinstance(message, MapPointUpdate | MapPointUpdateCoded):
            reaction = self._map_points(edge_id, message, position)
        elif isinstance(message, CullEvent):
            reaction = self._cull(edge_id, message, position)
        elif isinstance(message, AgentSensors):
            reaction = self._sensors(edge_id, message, position)
        elif isinstance(message, FramePoses):
            try:
                t, t_kf, T = read_frame_poses(message)
            except RemoteProtocolError as exc:
                raise UplinkError(str(exc)) from exc
            self.frames.add(message.agent_id, t, t_kf, T)
            self.store.commit(self.atlas, positions=position)
            reaction = Reaction()
        elif isinstance(message, AgentStatus):
            a, changed = self._agent(message.agent_id, edge_id, message.map_id)
            a.status, a.frames = message.state, message.frames
            a.link_counters = dict(message.link_counters)
            a.detail = message.detail
            for other in self._agents.values():  # every map of that robot on that edge
                if other.name == a.name and other.edge_id == a.edge_id:
                    self.fusion.imu.set_time_offset(other.agent_id, message.time_offset_ns)
            # Its position is saved too: a stale position would make the edge's replay
            # start at messages it no longer holds.
            agents = self._rows(a) if changed else None
            self.store.commit(self.atlas, positions=position, agents=agents)
            reaction = Reaction()
        else:
            log.warning("ignoring %s from edge %s", type(message).__name__, edge_id)
            self.skip(edge_id, stream_id, seq)
            return Reaction()
        self.positions.set(edge_id, InboundPosition(stream_id, seq))
        return reaction

    def skip(self, edge_id: str, stream_id: bytes, seq: int) -> None:
        """Record a message as delivered without effect (ignored or given up on)."""
        self.store.commit(self.atlas, positions={edge_id: (stream_id, seq)})
        self.positions.set(edge_id, InboundPosition(stream_id, seq))

    def _keyframe(
        self,
        edge_id: str,
        msg: KeyframeUpdate | KeyframeUpdateCoded,
        position: dict[str, tuple[bytes, int]],
    ) -> Reaction:
        a, _ = self._agent(msg.agent_id, edge_id, msg.map_id)
        t0, c0 = time.perf_counter(), self.stage_timer.clock()
        try:
            d = decode_keyframe_update(
                msg,
                a.agent_id,
                self.vocabulary,
                self.sensors.codec(a.name),
                self.decoders,
                lambda kf_id: self._descriptors_of(msg.agent_id, msg.map_id, a.agent_id, kf_id),
            )
        except UplinkError:
            self.rejected += 1
            raise
        self.codec_timer.add(f"decode.{type(msg).__name__}", time.perf_counter() - t0)
        self.stage_timer.add("stage.decode", self.stage_timer.clock() - c0)
        if d.keyframe is not None:
            self._last_descriptors[(msg.agent_id, msg.map_id)] = (
                msg.keyframe_id,
                d.keyframe.descriptors,
            )
        if (T_fix := self.rebase.correction(self.atlas, a.agent_id, d.anchor)) is not None:
            d = rebased_keyframe(d, T_fix)
        if d.imu is not None:
            self.fusion.imu.add(a.agent_id, d.imu.timestamps_ns, d.imu.gyro, d.imu.accel)
        key = make_key(a.agent_id, d.keyframe_id)
        kf = d.keyframe
        if kf is None:  # pose-only update of a keyframe the cloud has
            kf = self._pose_only(a, d)
            if kf is None:
                self.store.commit(self.atlas, positions=position, agents=self._rows(a))
                return Reaction()
        is_new = not self.atlas.has_keyframe(key) and key not in self.atlas.removed_keyframes()
        events = self.fusion.add_keyframe(kf)
        a.last_seen = d.timestamp_ns * 1e-9
        if is_new and self.atlas.has_keyframe(key):
            self.mission.keyframe(kf.timestamp)
        reaction = Reaction(urgent_maps=set(events.maps_to_optimize), events=events)
        merged = any(o.merge is not None for o in events.outcomes)
        if merged:
            self.mission.note_merge(kf.timestamp, self._names())
        agents = self._rows(a)
        if merged or events.outcomes:
            with self.stage_timer.span("stage.save_all"):
                self.store.save_all(self.atlas, positions=position, agents=agents)
            reaction.merged = merged
        else:
            mps: list[int] = []
            if self.atlas.has_keyframe(key):
                mk = self.atlas.keyframe(key).map_point_keys
                mps = np.unique(mk[mk >= 0]).tolist()
            with self.stage_timer.span("stage.commit"):
                self.store.commit(self.atlas, [key], mps, positions=position, agents=agents)
        if is_new and self.atlas.has_keyframe(key):
            reaction.new_keyframes[self.atlas.map_id_of_keyframe(key)] = 1
        return reaction

    def _descriptors_of(
        self, name: str, map_id: int, agent_id: int, keyframe_id: int
    ) -> np.ndarray | None:
        """Descriptors (M, 32) of keyframe ``keyframe_id`` of robot ``name``'s map ``map_id``
        as received: the newest received (kept here), else the atlas's (its rows stay; a
        restarted cloud), else None."""
        last = self._last_descriptors.get((name, map_id))
        if last is not None and last[0] == keyframe_id:
            return last[1]
        key = make_key(agent_id, keyframe_id)
        return self.atlas.keyframe(key).descriptors if self.atlas.has_keyframe(key) else None

    def _pose_only(self, a: AtlasAgent, d: DecodedKeyframe) -> KeyframeInput | None:
        """The atlas input of a pose-only update (None: the cloud no longer has it)."""
        key = make_key(a.agent_id, d.keyframe_id)
        if not self.atlas.has_keyframe(key):
            self._gone(a, d)
            return None
        v = self.atlas.keyframe(key)
        real = ~v.virtual
        ids = d.map_point_ids if d.map_point_ids.size == real.sum() else None
        return KeyframeInput(
            agent_id=a.agent_id,
            keyframe_id=d.keyframe_id,
            timestamp=v.timestamp,
            T_world_body=d.T_world_body,
            keypoints=v.keypoints[real],
            levels=v.levels[real],
            descriptors=v.descriptors[real],
            word_ids=v.word_ids[real],
            map_point_ids=ids if ids is not None else np.full(int(real.sum()), -1),
            velocity=d.velocity,
            bias_gyro=d.bias_gyro,
            bias_accel=d.bias_accel,
        )

    def _gone(self, a: AtlasAgent, d: DecodedKeyframe) -> None:
        """Log a state update of a keyframe the cloud does not hold."""
        # A keyframe the cloud pruned (MBP) or the edge culled is routine; others not.
        routine = make_key(a.agent_id, d.keyframe_id) in self.atlas.removed_keyframes()
        log.log(
            logging.DEBUG if routine else logging.WARNING,
            "pose update of %s keyframe %s/%d",
            "removed" if routine else "unknown",
            d.agent_name,
            d.keyframe_id,
        )

    def _keyframe_poses(
        self, edge_id: str, msg: KeyframePoses, position: dict[str, tuple[bytes, int]]
    ) -> Reaction:
        """New states of known keyframes; each map point follows its reference keyframe."""
        a, _ = self._agent(msg.agent_id, edge_id, msg.map_id, create=False)
        t0 = time.perf_counter()
        try:
            updates = decode_keyframe_poses(msg)
        except UplinkError:
            self.rejected += 1
            raise
        self.codec_timer.add("decode.KeyframePoses", time.perf_counter() - t0)
        anchor = updates[0].anchor if updates else None
        if (T_fix := self.rebase.correction(self.atlas, a.agent_id, anchor)) is not None:
            updates = [rebased_keyframe(d, T_fix) for d in updates]
        for d in updates:
            state = (d.T_world_body, d.velocity, d.bias_gyro, d.bias_accel)
            if not self.atlas.refresh_keyframe(a.agent_id, d.keyframe_id, *state):
                self._gone(a, d)
        # (their new states only; held relative to their keyframes, the points follow: no
        # point row changes)
        self.store.commit(self.atlas, positions=position, agents=self._rows(a))
        return Reaction()

    def _map_points(
        self,
        edge_id: str,
        msg: MapPointUpdate | MapPointUpdateCoded,
        position: dict[str, tuple[bytes, int]],
    ) -> Reaction:
        a, _ = self._agent(msg.agent_id, edge_id, msg.map_id)
        t0 = time.perf_counter()
        try:
            points = decode_map_point_update(
                msg, a.agent_id, functools.partial(self.rebase.correction, self.atlas, a.agent_id)
            )
        except UplinkError:
            self.rejected += 1
            raise
        self.codec_timer.add(f"decode.{type(msg).__name__}", time.perf_counter() - t0)
        self.fusion.add_map_points(points)
        # (new points and changed observations are whole rows, re-sent positions only theirs;
        # the atlas' unsaved changes say which)
        self.store.commit(self.atlas, positions=position, agents=self._rows(a))
        return Reaction()

    def _cull(
        self, edge_id: str, msg: CullEvent, position: dict[str, tuple[bytes, int]]
    ) -> Reaction:
        a, _ = self._agent(msg.agent_id, edge_id, msg.map_id, create=False)
        try:
            kf_ids, mp_ids = decode_cull_event(msg)
        except UplinkError:
            self.rejected += 1
            raise
        kf_keys = [make_key(a.agent_id, int(i)) for i in kf_ids]
        mp_keys = [make_key(a.agent_id, int(i)) for i in mp_ids]
        touched: set[int] = set()
        for k in kf_keys:
            if self.atlas.has_keyframe(k):
                mk = self.atlas.keyframe(k).map_point_keys
                touched.update(mk[mk >= 0].tolist())
                self.fusion.remove_keyframe(k)
        for m in mp_keys:
            if self.atlas.has_map_point(m):
                self.atlas.remove_map_point(m)
        self.store.commit(
            self.atlas, kf_keys, [*mp_keys, *touched], positions=position, agents=self._rows(a)
        )
        return Reaction()

    # ------------------------------------------------------------------ outputs
    def trajectories(self, retired: bool = True) -> tuple[dict[str, Trajectory], dict[str, int]]:
        """Keyframe trajectories ``T_map_body`` per robot name, and each robot's map id
        (:func:`services.cloud.store.output.robot_trajectories`; ``retired``: also the keyframes MBP
        removed, through their anchors)."""
        agents: dict[str, list[int]] = {}
        for a in self._agents.values():
            if a.agent_id in self.atlas.agents():
                agents.setdefault(a.name, []).append(a.agent_id)
        return robot_trajectories(self.atlas, agents, retired)

    def frame_trajectories(self, keyframes: Mapping[str, Trajectory]) -> dict[str, Trajectory]:
        """Every frame's trajectory per robot, placed on ``keyframes`` (:meth:`trajectories`;
        :class:`services.cloud.store.frame_trajectories.FrameTrack`)."""
        return self.frames.trajectories(keyframes)

    def ground_truth(
        self,
        references: Mapping[str, Trajectory],
        max_points: int = 3000,
        max_dt_ns: int = 20_000_000,
    ) -> tuple[GroundTruth, ...]:
        """Each robot's reference trajectory in its map's frame, for the dashboard
        (:func:`services.cloud.store.ground_truth.references_in_maps`)."""
        agents: dict[str, list[int]] = {}
        for a in self._agents.values():
            agents.setdefault(a.name, []).append(a.agent_id)
        return references_in_maps(self.atlas, agents, references, max_points, max_dt_ns)

    def view(
        self,
        counters: dict[str, dict] | None = None,
        references: Mapping[str, Trajectory] | None = None,
    ) -> CloudView:
        """Plain data for the dashboard's map source (built on the worker thread; the atlas
        snapshot is rebuilt only after the atlas changed)."""
        if self._view_cache is None or self._view_cache[0] != self._changes:
            with self.stage_timer.span("stage.view"):
                self._view_cache = (self._changes, self.atlas.snapshot())
        snap = self._view_cache[1]
        agents = tuple(
            AgentInfo(
                agent_id=a.agent_id,
                name=a.name,
                edge_id=a.edge_id,
                status=a.status,
                frames=a.frames,
                keyframes=len(self.atlas.keyframe_keys(agent_id=a.agent_id)),
                last_seen=a.last_seen,
                map_id=self.atlas.map_of_agent(a.agent_id)
                if a.agent_id in self.atlas.agents()
                else a.agent_id,
                link_counters=dict(a.link_counters),
                detail=a.detail,
            )
            for a in sorted(
                [*self._agents.values(), *self._prior.values()], key=lambda x: x.agent_id
            )
        )
        return CloudView(
            atlas=snap,
            agents=agents,
            pruned_keyframes=frozenset(self._pruned_keyframes),
            pruned_points=frozenset(self._pruned_points),
            edge_counters=counters or {},
            ground_truth=self.ground_truth(references) if references else None,
        )

    def close(self) -> None:
        self.store.close()


def open_app(
    state_dir: str | Path | None,
    camera: CameraCalibration | None,
    vocabulary: Vocabulary,
    config: CloudServiceConfig,
    positions: PositionStore | None = None,
) -> CloudApp:
    """The cloud's :class:`CloudApp` on ``state_dir`` (resumed if it holds a previous run;
    None: in memory, nothing kept, for tests and replays that drive the app without a
    folder); ``camera``: the fallback for robots whose calibration never arrives."""
    store = CloudStore(state_dir)
    if config.store.mission is not None:
        store.enter_mission(config.store.mission)
    atlas = store.load()
    wg = None
    if config.word_group_level is not None:
        words = range(vocabulary.n_words)
        wg = vocabulary.ancestor_at_level(list(words), config.word_group_level)
    fusion = MapFusion(camera, vocabulary.idf, config.domain, atlas, wg)
    return CloudApp(fusion, store, vocabulary, config, positions)
