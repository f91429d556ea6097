"""An edge whose robot's VIO is slow stays a live peer: no timeout, no resend, no duplicate.

Real TCP on loopback, a real EdgeServer and a robot playing coded frames. The robot's VIO
takes 1 s per frame and the edge queues at most 2 frames, so its handler holds each frame's
acknowledgement for about a second, twice the robot's retransmission timeout. The edge's loop
keeps heartbeating meanwhile, so the robot counts a late ack, adapts its timeout to the
slow acks and resends nothing (before
``common/protocol/recovery.py``, each late ack was a resend and a duplicate at the edge).
"""

from __future__ import annotations

import asyncio
import time

import pytest

from common.transport import TransportConfig
from services.edge.app import EdgeConfig
from services.edge.server import EdgeServer, EdgeServiceConfig
from services.edge.worker import ThreadWorker, WorkerSpec, WorkItem, WorkResult
from sim.robot import play, sim_sensors
from tests.services.edge.test_edge_service import SECRET, sim_frames, vocab  # noqa: F401

pytestmark = pytest.mark.timeout(240)
STEP_S = 1.0


class _SlowWorker(ThreadWorker):
    """The real VIO on its thread, one second per frame."""

    def _step(self, item: WorkItem) -> WorkResult:
        time.sleep(STEP_S)
        return super()._step(item)


def _slow(spec: WorkerSpec, kind: str) -> _SlowWorker:
    return _SlowWorker(spec)


@pytest.mark.slow
def test_slow_vio_makes_late_acks_not_duplicates(vocab, sim_frames) -> None:  # noqa: F811
    seq, frames = sim_frames
    frames = frames[:8]

    async def main():
        edge = EdgeServer(
            SECRET,
            vocab,
            EdgeConfig(worker="thread", max_queued_frames=2),
            EdgeServiceConfig(agent_id="edge-1", heartbeat_interval_s=0.2, idle_timeout_s=3.0),
            transport=TransportConfig(accept_roles=("robot",)),
            worker_factory=_slow,
        )
        _, port = await edge.start()
        try:
            result = await play(
                frames,
                "127.0.0.1",
                port,
                "slow",
                SECRET,
                sim_sensors(seq),
                retransmit_timeout_s=0.5,
            )
            await asyncio.wait_for(edge.flush(), 60)
            stats = edge.stats()
            link = edge.server.counters()["slow"]
        finally:
            await edge.stop()
        return result, stats, link

    result, stats, link = asyncio.run(main())
    robot = result.counters
    assert robot["connections"] == 1  # never timed out, never reconnected
    assert robot["retransmitted_messages"] == 0
    assert robot["late_acks"] >= 1  # then the timeout adapted to the ~1 s acks
    assert stats["robots"]["slow"]["frames_decoded"] == len(frames)
    assert stats["robots"]["slow"]["frames_processed"] == len(frames)
    assert link["duplicates_dropped"] == 0
    assert stats["loop_stalls"]["samples"] > 0
    assert stats["loop_stalls"]["max_s"] < STEP_S  # the slow VIO never held the loop
