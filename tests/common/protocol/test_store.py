"""Delivery positions on disk, traffic counters, and a server restarted on a FileDeliveryStore."""

from __future__ import annotations

import asyncio

import pytest

from common.protocol import (
    Blob,
    FileDeliveryStore,
    FileOutboxStore,
    InboundPosition,
    LocalProtocolError,
    MemoryDeliveryStore,
    SessionConfig,
    TrafficCounters,
)
from common.transport import Client, Delivery, Server, TransportConfig, run

SECRET = b"store-test-secret-0123456789"


def test_file_store_round_trip_and_corruption(tmp_path):
    store = FileDeliveryStore(tmp_path / "pos", fsync=True)
    assert store.load("robot/1") is None
    store.save("robot/1", InboundPosition(b"\x01" * 16, 42))
    assert FileDeliveryStore(tmp_path / "pos").load("robot/1") == InboundPosition(b"\x01" * 16, 42)
    (path,) = (tmp_path / "pos").iterdir()
    assert "/" not in path.name
    path.write_text("{not json")
    with pytest.raises(LocalProtocolError, match="corrupt delivery position"):
        store.load("robot/1")
    mem = MemoryDeliveryStore()
    mem.save("a", InboundPosition(b"", 3))
    assert mem.load("a") == InboundPosition(b"", 3) and mem.load("b") is None


def test_counters_snapshot_is_plain_data():
    c = TrafficCounters()
    c.record("tx", "Blob", 30)
    c.record("tx", "Blob", 40)
    c.record("rx", "Ack", 23)
    other = TrafficCounters()
    other.record("tx", "Hello", 100)
    other.connections = 1
    c.merge(other)
    snap = c.snapshot()
    assert snap["tx"] == {
        "messages": 3,
        "bytes": 170,
        "by_type": {"Blob": {"messages": 2, "bytes": 70}, "Hello": {"messages": 1, "bytes": 100}},
    }
    assert snap["rx"]["bytes"] == 23 and snap["connections"] == 1
    c.record("tx", "Blob", 1)
    assert snap["tx"]["bytes"] == 170  # a copy, not a view


def test_server_restart_on_file_store_neither_loses_nor_repeats(tmp_path):
    """The receiving server is cut right after delivering message 49 (before its ack leaves),
    then recreated on the same FileDeliveryStore: the client replays what it holds unacked
    and the new server drops what its store says was delivered."""
    store_dir = tmp_path / "positions"
    got: list[int] = []
    cut = asyncio.Event()
    servers: list[Server] = []

    async def handler(d: Delivery) -> None:
        got.append(d.message.channel)
        if d.message.channel == 49 and not cut.is_set():
            servers[0].cut_all()  # crash: the ack for 49 (and maybe earlier) never leaves
            cut.set()

    async def main() -> dict:
        cfg = SessionConfig("edge", "edge-0", SECRET)
        fast = TransportConfig(reconnect_initial_delay=0.01, reconnect_max_delay=0.05)
        servers.append(Server(cfg, handler, store=FileDeliveryStore(store_dir, fsync=False)))
        host, port = await servers[0].start()
        client = Client(SessionConfig("robot", "r", SECRET), handler, host, port, transport=fast)
        await client.start()
        for i in range(100):
            await client.send(Blob(i, b"a"))
            if i == 60:
                await cut.wait()
                await servers[0].close()
                unacked = client.peer.link.first_unacked
                servers.append(
                    Server(cfg, handler, store=FileDeliveryStore(store_dir, fsync=False))
                )
                await servers[1].start(host, port)
        await asyncio.wait_for(client.flush(), 10)
        counters = client.counters()
        await client.close()
        await servers[1].close()
        return {"unacked_at_restart": unacked, **counters}

    result = run(main())
    assert got == list(range(100))
    # delivered-but-unacknowledged messages existed at the restart: without the store the new
    # server would have accepted them again as a new stream, and `got` would show repeats
    assert result["unacked_at_restart"] <= 50


def test_outbox_file_restores_a_restarted_sender(tmp_path):
    cfg = SessionConfig("robot", "r", SECRET)
    link = cfg.new_link()
    for i in range(3):
        link.enqueue(Blob(i, bytes([i]) * 5))
    link.acknowledge(1)
    store = FileOutboxStore(tmp_path / "outbox.bin", fsync=False)
    assert store.load() is None
    store.save(link.outbound_state())
    restored = cfg.new_link(outbound=store.load())
    assert restored.out_stream_id == link.out_stream_id
    assert list(restored.outbox) == [2, 3] and restored.next_seq == 4
    assert restored.outbox[3].payload == link.outbox[3].payload
    (tmp_path / "outbox.bin").write_bytes(b"\x93\x01")
    with pytest.raises(LocalProtocolError, match="corrupt outbox file"):
        store.load()
