"""No loss, no duplicates across SIGKILL restarts of the receiving process (a real subprocess)."""

from __future__ import annotations

import asyncio
import hashlib
import os
import random
import socket
import sys
from pathlib import Path

import pytest

from common.protocol import Blob, SessionConfig
from common.transport import Client, Delivery, TransportConfig, run

RECEIVER = Path(__file__).with_name("receiver_proc.py")
RECORD_SIZE = 40
SECRET = "restart-test-secret-0123456789"
N, KILLS = 3000, 6


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_log(path: Path) -> list[tuple[bytes, int, int, bytes]]:
    data = path.read_bytes()
    out = []
    for off in range(0, len(data) - len(data) % RECORD_SIZE, RECORD_SIZE):
        rec = data[off : off + RECORD_SIZE]
        out.append((rec[:16], int.from_bytes(rec[16:24]), int.from_bytes(rec[24:32]), rec[32:]))
    return out


@pytest.mark.slow
def test_receiver_process_killed_and_restarted(tmp_path):
    log = tmp_path / "delivered.log"
    port = free_port()
    rng = random.Random(21)
    payloads = [rng.randbytes(rng.randint(1, 4000)) for _ in range(N)]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parents[3]))

    async def spawn() -> asyncio.subprocess.Process:
        return await asyncio.create_subprocess_exec(
            sys.executable,
            str(RECEIVER),
            "--port",
            str(port),
            "--log",
            str(log),
            "--secret",
            SECRET,
            env=env,
        )

    async def nothing(d: Delivery) -> None:
        raise AssertionError("the receiver sends nothing")

    async def main() -> tuple[int, dict]:
        proc = await spawn()
        config = SessionConfig(
            role="robot",
            agent_id="robot-7",
            secret=SECRET.encode(),
            heartbeat_interval=0.2,
            idle_timeout=1.0,
            window_messages=128,
        )
        transport = TransportConfig(reconnect_initial_delay=0.02, reconnect_max_delay=0.2)
        client = Client(config, nothing, "127.0.0.1", port, transport=transport)
        await client.start()
        kills = 0

        async def produce() -> None:
            for i, data in enumerate(payloads):
                await client.send(Blob(i, data))

        producer = asyncio.create_task(produce())
        kill_rng = random.Random(5)
        try:
            while kills < KILLS:
                target = (kills + 1) * N // (KILLS + 2) + kill_rng.randint(-50, 50)
                while not log.exists() or log.stat().st_size // RECORD_SIZE < target:
                    await asyncio.sleep(0.002)
                proc.kill()  # SIGKILL: no cleanup, maybe mid-record
                await proc.wait()
                kills += 1
                await asyncio.sleep(kill_rng.uniform(0.0, 0.3))
                proc = await spawn()
            await producer
            await asyncio.wait_for(client.flush(), 60)
            counters = client.counters()
        finally:
            producer.cancel()
            await client.close()
            proc.kill()
            await proc.wait()
        return kills, counters

    kills, counters = run(main())
    records = read_log(log)
    channels = [channel for _, _, channel, _ in records]
    assert kills == KILLS
    assert counters["retransmitted_messages"] > 0  # unacked messages were replayed
    assert counters["connections"] > KILLS
    assert len(channels) == N, f"{len(channels)} records for {N} messages"
    assert channels == list(range(N))  # 0 lost, 0 duplicated, 0 reordered
    assert [seq for _, seq, _, _ in records] == list(range(1, N + 1))
    assert len({stream for stream, _, _, _ in records}) == 1
    for (_, _, channel, digest), data in zip(records, payloads, strict=True):
        assert digest == hashlib.sha256(data).digest()[:8], channel
