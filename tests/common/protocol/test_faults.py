"""Exactly-once, in-order delivery through a fault-injecting proxy on loopback TCP.

10,000 client->server messages (mostly small, a few up to 1 MB) and 2,000 server->client
messages cross >= 100 forced disconnects, random cuts mid-frame, stalls (some longer than
the idle timeout, so heartbeats must declare the peer dead) and writes split at odd
boundaries. Asserts 0 lost, 0 duplicated, 0 reordered, and every payload intact.
"""

from __future__ import annotations

import asyncio
import hashlib
import itertools
import logging
import random

import pytest

from common.protocol import Blob, SessionConfig
from common.transport import Client, Delivery, Server, TransportConfig, run
from sim.faultproxy import FaultConfig, FaultProxy

SECRET = b"fault-test-secret-0123456789"
UP, DOWN, CUTS = 10_000, 2_000, 100
FAST = TransportConfig(reconnect_initial_delay=0.005, reconnect_max_delay=0.1)


def config(agent: str, role: str) -> SessionConfig:
    return SessionConfig(
        role=role,
        agent_id=agent,
        secret=SECRET,
        max_frame_size=2 * 1024 * 1024,
        heartbeat_interval=0.2,
        idle_timeout=0.8,
        handshake_timeout=2.0,
        retransmit_timeout=0.5,
        window_messages=64,
        window_bytes=3 * 1024 * 1024,
        max_outbox_messages=256,
    )


def payload(i: int, rng: random.Random) -> bytes:
    """Message i: mostly 10 B..2 kB, every 700th between 256 kB and 1 MB."""
    size = rng.randint(256 * 1024, 1024 * 1024) if i % 700 == 350 else rng.randint(10, 2000)
    body = rng.randbytes(size)
    return hashlib.sha256(body).digest()[:8] + body


def intact(data: bytes) -> bool:
    return hashlib.sha256(data[8:]).digest()[:8] == data[:8]


class Recorder:
    def __init__(self, target: int) -> None:
        self.channels: list[int] = []
        self.corrupt = 0
        self.target = target
        self.done = asyncio.Event()

    async def __call__(self, d: Delivery) -> None:
        self.channels.append(d.message.channel)
        self.corrupt += not intact(d.message.data)
        if len(self.channels) >= self.target:
            self.done.set()


def check(channels: list[int], n: int) -> tuple[int, int, int]:
    """(lost, duplicated, reordered)."""
    seen = set(channels)
    lost = n - len(seen & set(range(n)))
    duplicated = len(channels) - len(seen)
    reordered = sum(1 for a, b in itertools.pairwise(channels) if b < a)
    return lost, duplicated, reordered


@pytest.mark.slow
def test_exactly_once_in_order_across_100_cuts():
    async def main():
        up_rec, down_rec = Recorder(UP), Recorder(DOWN)
        server = Server(config("edge-0", "edge"), up_rec, transport=FAST)
        host, port = await server.start()
        faults = FaultConfig(
            cut_after_bytes=(20_000, 3_000_000),
            stall_probability=0.0004,
            stall_seconds=(0.05, 1.2),
            max_write_bytes=3000,
            seed=3,
        )
        proxy = FaultProxy(host, port, faults)
        phost, pport = await proxy.start()
        client = Client(config("robot-1", "robot"), down_rec, phost, pport, transport=FAST)
        await client.start()
        rng = random.Random(11)

        async def produce_up():
            for i in range(UP - 1):
                await client.send(Blob(i, payload(i, rng)))
            # The last message only once the link was cut CUTS times: a fast run would
            # otherwise deliver everything before the chaos reached its count.
            while proxy.stats.cuts < CUTS:
                await asyncio.sleep(0.01)
            await client.send(Blob(UP - 1, payload(UP - 1, rng)))

        async def produce_down():
            await client.wait_connected(10)
            down_rng = random.Random(12)
            for i in range(DOWN):
                await server.send("robot-1", Blob(i, payload(i + 1, down_rng)))

        async def chaos():
            cut_rng = random.Random(13)
            loop = asyncio.get_running_loop()
            while not (up_rec.done.is_set() and down_rec.done.is_set()):
                # cut after 5..40 more deliveries, or after 50..150 ms, whichever comes first
                mark = len(up_rec.channels) + len(down_rec.channels)
                step = cut_rng.randint(5, 40)
                deadline = loop.time() + cut_rng.uniform(0.05, 0.15)
                while (
                    len(up_rec.channels) + len(down_rec.channels) < mark + step
                    and loop.time() < deadline
                    and not up_rec.done.is_set()
                ):
                    await asyncio.sleep(0.005)
                proxy.cut_all()

        chaos_task = asyncio.create_task(chaos())
        try:
            await asyncio.wait_for(
                asyncio.gather(
                    produce_up(), produce_down(), up_rec.done.wait(), down_rec.done.wait()
                ),
                timeout=150,
            )
            await client.flush()
            await server.peer("robot-1").flush()
        finally:
            chaos_task.cancel()
            await asyncio.gather(chaos_task, return_exceptions=True)
            await client.close()
            await server.close()
            await proxy.close()
        return up_rec, down_rec, proxy.stats, client.counters(), client.connections

    up_rec, down_rec, stats, counters, connections = run(main())
    assert check(up_rec.channels, UP) == (0, 0, 0)
    assert check(down_rec.channels, DOWN) == (0, 0, 0)
    assert up_rec.channels == list(range(UP)) and down_rec.channels == list(range(DOWN))
    assert up_rec.corrupt == 0 and down_rec.corrupt == 0
    assert stats.cuts >= CUTS, stats
    assert connections > CUTS
    assert counters["retransmitted_messages"] > 0  # replays really happened
    assert stats.stalls > 0


def test_throttled_link_delivers_everything():
    async def main():
        rec = Recorder(200)
        server = Server(config("edge-0", "edge"), rec, transport=FAST)
        host, port = await server.start()
        proxy = FaultProxy(host, port, FaultConfig(rate_bytes_per_s=200_000, max_write_bytes=700))
        client = Client(config("r", "robot"), Recorder(0), *await proxy.start(), transport=FAST)
        await client.start()
        rng = random.Random(5)
        try:
            for i in range(200):
                await client.send(Blob(i, payload(i + 1, rng)))
            await asyncio.wait_for(client.flush(), 60)
        finally:
            await client.close()
            await server.close()
            await proxy.close()
        return rec, proxy.stats

    rec, stats = run(main())
    assert rec.channels == list(range(200)) and rec.corrupt == 0
    assert stats.cuts == 0 and stats.bytes_up > 200 * 10


@pytest.mark.slow
def test_heartbeats_detect_a_black_hole_and_the_link_recovers(caplog):
    async def main():
        rec = Recorder(2)
        server = Server(config("edge-0", "edge"), rec, transport=FAST)
        host, port = await server.start()
        proxy = FaultProxy(host, port, FaultConfig())
        client = Client(config("r", "robot"), Recorder(0), *await proxy.start(), transport=FAST)
        await client.start()
        try:
            await client.send(Blob(0, payload(0, random.Random(1))))
            await client.flush()
            proxy.freeze()  # TCP stays up, nothing moves: only heartbeats can tell
            await client.send(Blob(1, payload(1, random.Random(2))))
            await asyncio.sleep(2.0)  # > idle_timeout (0.8 s) + handshake_timeout retries
            stuck_connections = client.connections
            proxy.thaw()
            await asyncio.wait_for(client.flush(), 10)
        finally:
            await client.close()
            await server.close()
            await proxy.close()
        return rec, stuck_connections

    with caplog.at_level(logging.INFO):
        rec, stuck_connections = run(main())
    assert rec.channels == [0, 1]
    assert "peer silent" in caplog.text
    assert stuck_connections >= 2  # the dead link was dropped and redialled
