"""Replay one robot's edge journal in process: what the edge's VIO made of each frame and what
its session sent the cloud.

An edge journals every robot message before it acknowledges it (``services.edge.journal``), so
``--state-dir``'s ``<robot>.journal`` of any run (a demo, a budget row, a drill) holds exactly
what that robot's edge received. :func:`replay_journal` feeds it through the edge's own code:
:meth:`RobotSession.decode` → :class:`VioRunner` (the worker's containment) →
:meth:`RobotSession.on_result` (as the edge does while replaying its journal after a restart:
no robot feedback), and keeps each frame's VIO outcome and every cloud message in order. No
network, no cloud (so no corrections come back), one process: a run's VIO and cloud uplink can
be re-examined, or re-run with other :class:`VioConfig` / :class:`EdgeSessionConfig`, without
running the job again. A journal holds one robot run after another when the robot was
restarted; each ``RobotSensors`` record starts a fresh session, as it does on the edge.

:func:`point_sends` and :func:`cloud_bytes` summarise the uplink (used by
``benchmarks/bench_cloud_uplink.py``).
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.links.edge_cloud import MapPointUpdateCoded
from common.links.edge_cloud_payloads import decode_points
from common.links.robot_edge import RobotFrame, RobotSensors, RobotSequenceEnd, read_sensors
from common.protocol.messages import Message, decode_payload, encode_payload
from common.vocabulary import Vocabulary
from services.edge.journal import JournalStore
from services.edge.robot_session import RobotSession
from services.edge.session_config import EdgeSessionConfig
from services.edge.vio.types import TrackingStatus, VioConfig
from services.edge.worker import VioRunner, WorkerSpec

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayedFrame:
    """The VIO's outcome for one journaled frame (``status`` None: the VIO failed on it and
    re-initialised, as ``WorkResult.failed`` says; ``T_world_body`` (4, 4) in its map, None
    then)."""

    timestamp_ns: int
    robot_keyframe: bool
    status: TrackingStatus | None
    map_id: int
    n_inliers: int
    reason: str
    T_world_body: np.ndarray | None = None


@dataclass
class JournalReplay:
    """One robot's replay: its frames' outcomes, the cloud messages in the order the session
    made them, and for each robot keyframe (by camera time) the stream track number of each
    of its features (``RobotSession.numbers``), for codec counterfactuals."""

    agent: str
    frames: list[ReplayedFrame] = field(default_factory=list)
    cloud: list[Message] = field(default_factory=list)
    keyframe_tracks: dict[int, np.ndarray] = field(default_factory=dict)
    runs: int = 0
    sessions: list[RobotSession] = field(default_factory=list)
    runners: list[VioRunner] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        """Camera time from the first to the last frame (s)."""
        if len(self.frames) < 2:
            return 0.0
        return (self.frames[-1].timestamp_ns - self.frames[0].timestamp_ns) * 1e-9


def journal_agents(state_dir: Path | str) -> list[str]:
    """The robots the edge state folder ``state_dir`` holds journals of."""
    store = JournalStore(Path(state_dir))
    try:
        return store.agents()
    finally:
        store.close()


def journal_messages(state_dir: Path | str, agent: str) -> list[Message]:
    """``agent``'s journalled robot -> edge messages in the edge state folder ``state_dir``, in
    the order the edge accepted them (``JournalError`` for an unreadable journal)."""
    store = JournalStore(Path(state_dir))
    try:
        records = store.journal(agent).read()
    finally:
        store.close()
    return [decode_payload(rec.type_id, rec.payload) for rec in records]


def replay_journal(
    state_dir: Path | str,
    agent: str,
    vocabulary: Vocabulary | None = None,
    vio: VioConfig | None = None,
    session: EdgeSessionConfig | None = None,
) -> JournalReplay:
    """Replay ``agent``'s journal in the edge state folder ``state_dir`` (see the module
    docstring); ``vio`` / ``session``: the edge's options to replay with (default: the edge's
    defaults). Raises ``JournalError`` for an unreadable journal, ``CodecError`` for a frame
    that does not decode (the edge would have refused it)."""
    vocab = vocabulary or Vocabulary.load()
    out = JournalReplay(agent)
    sess: RobotSession | None = None
    runner: VioRunner | None = None
    for msg in journal_messages(state_dir, agent):
        if isinstance(msg, RobotSensors):
            sensors = read_sensors(msg)
            sess = RobotSession(agent, sensors.camera, vocab, session)
            runner = VioRunner(
                WorkerSpec(agent, sensors.camera, sensors.imu, vio or VioConfig(), out.runs)
            )
            out.sessions.append(sess)
            out.runners.append(runner)
            out.runs += 1
        elif isinstance(msg, RobotSequenceEnd) and sess is not None:
            out.cloud.extend(sess.release_points())
        elif isinstance(msg, RobotFrame):
            if sess is None or runner is None:
                raise ValueError(f"{agent}: a frame before the robot's RobotSensors")
            item = sess.decode(msg)
            assert item.obs is not None  # (decode always makes one)
            if item.obs.is_keyframe:
                out.keyframe_tracks[msg.timestamp_ns] = sess.numbers.copy()
            res = runner.step(item)
            out.cloud.extend(sess.on_result(res, replaying=True).cloud)
            r = res.result
            out.frames.append(
                ReplayedFrame(
                    msg.timestamp_ns,
                    bool(item.obs.is_keyframe),
                    None if r is None else r.status,
                    -1 if r is None else r.map_id,
                    0 if r is None else r.n_inliers,
                    res.failed if r is None else r.reason,
                    None if r is None else r.T_world_body,
                )
            )
    logger.info("%s: %d frames replayed in %d run(s)", agent, len(out.frames), out.runs)
    return out


def cloud_bytes(messages: list[Message]) -> Counter[str]:
    """Payload bytes per message type (msgpack, as the link frames them, framing excluded)."""
    out: Counter[str] = Counter()
    for m in messages:
        out[type(m).__name__] += len(encode_payload(m))
    return out


@dataclass(frozen=True)
class PointSends:
    """How the map points went up: ``sends`` point entries in all, ``distinct`` points,
    ``with_rows`` entries that brought new observations, and the move (m) of each other
    re-send from the position that point was last sent at (raw message coordinates: the
    edge's frame, so without cloud corrections it is the VIO's own refinement)."""

    sends: int
    distinct: int
    with_rows: int
    moves_m: np.ndarray


def point_sends(messages: list[Message]) -> PointSends:
    """:class:`PointSends` of the ``MapPointUpdateCoded`` messages among ``messages``."""
    last: dict[tuple[int, int], np.ndarray] = {}
    sends = with_rows = 0
    moves: list[float] = []
    for m in messages:
        if not isinstance(m, MapPointUpdateCoded):
            continue
        batch = decode_points(m.points)
        map_id = int(m.map_id)
        gained = set(batch.observations[:, 0].tolist())
        for pid, p in zip(batch.ids.tolist(), batch.p_world, strict=True):
            key = (map_id, pid)
            sends += 1
            if pid in gained:
                with_rows += 1
            elif key in last:
                moves.append(float(np.linalg.norm(p - last[key])))
            last[key] = p
    return PointSends(sends, len(last), with_rows, np.array(moves))
