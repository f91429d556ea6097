"""The asyncio transport on real loopback TCP: delivery, auth, hostility, limits, TLS."""

from __future__ import annotations

import asyncio
import logging

import pytest

from common.protocol import (
    Blob,
    OutboxFullError,
    PeerRejectedError,
    RejectedMessageError,
    SessionConfig,
)
from common.protocol.framing import encode_frame
from common.protocol.messages import encode_payload
from common.transport import Client, Delivery, Server, TransportConfig, run
from lab.tls import self_signed_contexts

SECRET = b"transport-test-secret-0123"
FAST = TransportConfig(reconnect_initial_delay=0.01, reconnect_max_delay=0.2)


def scfg(agent: str = "edge-0", role: str = "edge", **kw) -> SessionConfig:
    return SessionConfig(role=role, agent_id=agent, secret=kw.pop("secret", SECRET), **kw)


class Sink:
    """Collects deliveries; optional failure injection."""

    def __init__(self) -> None:
        self.items: list[Delivery] = []
        self.fail_once_at: int | None = None
        self.changed = asyncio.Event()

    async def __call__(self, d: Delivery) -> None:
        if self.fail_once_at is not None and d.message.channel == self.fail_once_at:
            self.fail_once_at = None
            raise RuntimeError("injected handler failure")
        self.items.append(d)
        self.changed.set()

    async def wait_for(self, n: int, timeout: float = 10.0) -> None:
        async def loop() -> None:
            while len(self.items) < n:
                self.changed.clear()
                await self.changed.wait()

        await asyncio.wait_for(loop(), timeout)


async def _pair(server_kw=None, client_kw=None, ccfg=None):
    server_sink, client_sink = Sink(), Sink()
    server = Server(scfg(), server_sink, transport=FAST, **(server_kw or {}))
    host, port = await server.start()
    client = Client(
        ccfg or scfg("robot-1", "robot"),
        client_sink,
        host,
        port,
        transport=FAST,
        **(client_kw or {}),
    )
    await client.start()
    return server, server_sink, client, client_sink


def test_both_directions_in_order_and_counters():
    async def main():
        server, ssink, client, csink = await _pair()
        try:
            for i in range(200):
                await client.send(Blob(i, bytes(i)))
            await client.flush()
            await asyncio.wait_for(client.wait_connected(), 5)
            for i in range(50):
                await server.send("robot-1", Blob(i, b"down"))
            await server.peer("robot-1").flush()
            await csink.wait_for(50)
            assert [d.message.channel for d in ssink.items] == list(range(200))
            assert [d.seq for d in ssink.items] == list(range(1, 201))
            assert {d.peer for d in ssink.items} == {"robot-1"}
            assert [d.message.channel for d in csink.items] == list(range(50))
            assert csink.items[0].peer == "edge-0" and csink.items[0].role == "edge"
            cc, sc = client.counters(), server.counters()["robot-1"]
            assert cc["tx"]["by_type"]["Blob"]["messages"] == 200
            assert sc["rx"]["by_type"]["Blob"]["bytes"] == cc["tx"]["by_type"]["Blob"]["bytes"]
            assert cc["outbox_messages"] == 0 and cc["connected"]
        finally:
            await client.close()
            await server.close()

    run(main())


def test_wrong_secret_is_refused_and_server_keeps_serving(caplog):
    async def main():
        server, ssink, good, _ = await _pair()
        bad = Client(
            scfg("mallory", "robot", secret=b"not-the-secret-at-all"),
            Sink(),
            *server.address,
            transport=FAST,
        )
        await bad.start()
        try:
            await good.send(Blob(1, b"before"))
            await asyncio.sleep(0.3)  # the impostor tries meanwhile
            await good.send(Blob(2, b"after"))
            await good.flush()
            assert [d.message.channel for d in ssink.items] == [1, 2]
            assert "mallory" not in server.peers
            # a wrong credential cannot get better by retrying: the client gives up, loudly
            assert not bad.peer.connected and bad.connections == 1
            with pytest.raises(PeerRejectedError, match="authentication failed"):
                await bad.send(Blob(3, b"never"))
        finally:
            await bad.close()
            await good.close()
            await server.close()

    with caplog.at_level(logging.INFO):
        run(main())
    assert "failed authentication" in caplog.text


@pytest.mark.parametrize(
    "garbage",
    [
        b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",  # bad magic
        encode_frame(0x100, encode_payload(Blob(0, b"x")), seq=1),  # unauthenticated app frame
        encode_frame(0x0001, b"\x93\x01\x02"),  # malformed Hello
        encode_frame(0x4242, b""),  # unknown type
        encode_frame(0x0001, b"\x90")[:-3] + b"\xff\xff\xff",  # bad CRC
        b"RS\x01\x00\x00\x01" + b"\0" * 8 + b"\xff\xff\xff\xff" + b"\0" * 4,  # oversized
    ],
)
def test_hostile_connection_closed_alone(garbage, caplog):
    async def main():
        server, ssink, client, _ = await _pair()
        try:
            await client.wait_connected(5)
            reader, writer = await asyncio.open_connection(*server.address)
            writer.write(garbage)
            await writer.drain()
            rest = await asyncio.wait_for(reader.read(), 5)  # server closes us (maybe a Close)
            assert rest == b"" or rest[:2] == b"RS"
            writer.close()
            await client.send(Blob(9, b"still fine"))
            await client.flush()
            assert [d.message.channel for d in ssink.items] == [9]
            assert client.peer.connected
        finally:
            await client.close()
            await server.close()

    with caplog.at_level(logging.WARNING):
        run(main())
    assert "unauthenticated" in caplog.text and "closed" in caplog.text


def test_max_peers_and_accept_roles():
    async def main():
        server = Server(
            scfg(),
            Sink(),
            transport=TransportConfig(max_peers=1, accept_roles=("robot",)),
        )
        host, port = await server.start()
        one = Client(scfg("r1", "robot"), Sink(), host, port, transport=FAST)
        two = Client(scfg("r2", "robot"), Sink(), host, port, transport=FAST)
        cloud = Client(scfg("c", "cloud"), Sink(), host, port, transport=FAST)
        try:
            await one.start()
            await one.wait_connected(5)
            await two.start()
            for _ in range(100):  # until r2 has tried (and been refused) at least once
                if two.connections >= 1 and two.peer._conn is None:
                    break
                await asyncio.sleep(0.05)
            assert not two.peer.connected and two.connections >= 1
            await one.close()
            await two.wait_connected(5)  # room again: r2 joins
            await two.close()
            await cloud.start()
            await asyncio.sleep(0.3)
            assert not cloud.peer.connected and "c" not in server.peers
        finally:
            await cloud.close()
            await server.close()

    run(main())


def test_failed_handler_is_retried_on_the_same_connection():
    """A local fault in the handler (not the sender's): the same delivery is tried again
    after a delay, in order, without dropping the connection or replaying the outbox."""

    async def main():
        server, ssink, client, _ = await _pair()
        ssink.fail_once_at = 3
        try:
            for i in range(6):
                await client.send(Blob(i, b"m"))
            await client.flush()
            assert [d.message.channel for d in ssink.items] == list(range(6))
            assert client.connections == 1
            assert server.peers["robot-1"].handler_failures == 1
            assert client.counters()["retransmitted_messages"] == 0
        finally:
            await client.close()
            await server.close()

    run(main())


def test_rejected_message_is_refused_once_with_the_reason_and_the_client_gives_up(caplog):
    """A handler that raises RejectedMessageError refuses the message for good: it reaches
    the handler once, the client is told why (``Reject``) and its sends and flushes raise
    PeerRejectedError; another client of the same server is served on."""

    async def main():
        server_sink = Sink()
        bad_calls = []

        async def handler(d: Delivery) -> None:
            if d.peer == "robot-bad":
                bad_calls.append(d.seq)
                raise RejectedMessageError("your calibration differs")
            await server_sink(d)

        server = Server(scfg(), handler, transport=FAST)
        host, port = await server.start()
        bad = Client(scfg("robot-bad", "robot"), Sink(), host, port, transport=FAST)
        good = Client(scfg("robot-good", "robot"), Sink(), host, port, transport=FAST)
        await bad.start()
        await good.start()
        try:
            await bad.send(Blob(0, b"x"))
            with pytest.raises(PeerRejectedError, match="your calibration differs"):
                await asyncio.wait_for(bad.flush(), 10)
            with pytest.raises(PeerRejectedError):
                await bad.send(Blob(1, b"y"))
            await asyncio.sleep(0.3)  # a redelivery would have happened by now
            assert bad.connections == 1 and bad_calls == [1]
            assert bad.peer.rejections == [(1, "your calibration differs")]
            for i in range(3):
                await good.send(Blob(i, b"g"))
            await good.flush()
            assert [d.message.channel for d in server_sink.items] == [0, 1, 2]
        finally:
            await bad.close()
            await good.close()
            await server.close()

    with caplog.at_level(logging.WARNING):
        run(main())
    assert "your calibration differs" in caplog.text


def test_send_waits_while_outbox_full_and_disconnected():
    async def main():
        sink = Sink()
        server = Server(scfg(), sink, transport=FAST)
        host, port = await server.start()
        await server.close()  # nobody listening: the client cannot deliver
        client = Client(
            scfg("r", "robot", max_outbox_messages=3), Sink(), host, port, transport=FAST
        )
        await client.start()
        try:
            for i in range(3):
                await client.send(Blob(i, b"q"))
            with pytest.raises(OutboxFullError):
                client.peer.send_nowait(Blob(99, b"q"))
            blocked = asyncio.create_task(client.send(Blob(3, b"q")))
            await asyncio.sleep(0.2)
            assert not blocked.done()  # backpressure, not a drop
            server2 = Server(scfg(), sink, transport=FAST)
            await server2.start(host, port)
            try:
                assert await asyncio.wait_for(blocked, 10) == 4
                await client.flush()
                assert [d.message.channel for d in sink.items] == [0, 1, 2, 3]
            finally:
                await client.close()
                await server2.close()
        finally:
            await client.close()

    run(main())


def test_tls_link(tmp_path):
    contexts = self_signed_contexts(tmp_path)
    assert contexts is not None
    server_ctx, client_ctx = contexts

    async def main():
        server, ssink, client, _ = await _pair(
            server_kw={"ssl": server_ctx},
            client_kw={"ssl": client_ctx, "server_hostname": "localhost"},
        )
        try:
            await client.send(Blob(1, b"secret payload" * 100))
            await client.flush()
            assert ssink.items[0].message.data == b"secret payload" * 100
        finally:
            await client.close()
            await server.close()

    run(main())


def test_peers_join_leave_and_are_forgotten():
    async def main():
        sink = Sink()
        server = Server(scfg(), sink, transport=FAST)
        host, port = await server.start()
        robots = [
            Client(scfg(f"r{i}", "robot"), Sink(), host, port, transport=FAST) for i in range(3)
        ]
        try:
            for i, robot in enumerate(robots):
                await robot.start()
                await robot.send(Blob(i, b"hi"))
            for robot in robots:
                await robot.flush()
            await robots[1].close()  # leaves
            await robots[0].send(Blob(10, b"still here"))
            await robots[0].flush()
            assert sorted(server.peers) == ["r0", "r1", "r2"]
            assert not server.peers["r1"].connected and server.peers["r2"].connected
            await server.forget("r1")
            assert sorted(server.counters()) == ["r0", "r2"]
            late = Client(scfg("r3", "robot"), Sink(), host, port, transport=FAST)
            await late.start()  # joins at any time
            await late.send(Blob(30, b"late"))
            await late.flush()
            await late.close()
        finally:
            for robot in robots:
                await robot.close()
            await server.close()
        return sorted((d.peer, d.message.channel) for d in sink.items)

    assert run(main()) == [("r0", 0), ("r0", 10), ("r1", 1), ("r2", 2), ("r3", 30)]


def test_stalled_sockets_cannot_lock_peers_out():
    """Sockets that connect, send a byte and stall (more than the peer cap, re-opened as fast
    as the server drops them) are counted apart from the peers: a robot still joins, and a
    peer cap of 2 still refuses the third peer with a reason."""

    async def main():
        transport = TransportConfig(max_peers=2, max_pending=4)
        server = Server(scfg(), Sink(), transport=transport)
        host, port = await server.start()
        stalled: list[asyncio.StreamWriter] = []
        stop = asyncio.Event()

        async def attacker() -> None:
            while not stop.is_set():
                _, w = await asyncio.open_connection(host, port)
                w.write(b"\x00")
                stalled.append(w)
                await asyncio.sleep(0.005)

        flood = asyncio.create_task(attacker())
        await asyncio.sleep(0.3)  # dozens of stalled sockets, far above both caps
        clients = [
            Client(scfg(f"r{i}", "robot"), Sink(), host, port, transport=FAST) for i in range(3)
        ]
        try:
            for c in clients[:2]:
                await c.start()
                await c.wait_connected(5)  # timed out before: "server full (64 peers)"
            await clients[2].start()
            await asyncio.sleep(0.5)
            assert not clients[2].peer.connected and "r2" not in server.peers
            assert len(stalled) > 2 * (transport.max_peers + transport.max_pending)
            assert len(server._pending) <= transport.max_pending
        finally:
            stop.set()
            await flood
            for w in stalled:
                w.close()
            for c in clients:
                await c.close()
            await server.close()

    run(main())


@pytest.mark.slow
def test_a_robot_joins_and_streams_while_200_stalled_connections_are_held():
    """Issue 18's lock-out, at scale: 200 connections from 10 other addresses send a byte and
    stall, all of them held; a new robot joins and streams 100 messages at 50 Hz on one
    connection. One address that floods is held to its share and pushes only itself out."""

    async def main():
        transport = TransportConfig()  # the defaults a service runs with
        server = Server(scfg(), Sink(), transport=transport)
        host, port = await server.start()
        stalled: list[asyncio.StreamWriter] = []
        for i in range(200):
            _, w = await asyncio.open_connection(
                host, port, local_addr=(f"127.0.0.{2 + i % 10}", 0)
            )
            w.write(b"\x00")
            stalled.append(w)
        await asyncio.sleep(0.2)
        assert len(server._pending) == 200
        sink = Sink()
        robot = Client(scfg("robot-new", "robot"), sink, host, port, transport=FAST)
        server_sink = server._handler
        await robot.start()
        try:
            await robot.wait_connected(5)
            for i in range(100):
                await robot.send(Blob(i, b"f" * 200))
                await asyncio.sleep(0.02)
            await robot.flush()
            assert [d.message.channel for d in server_sink.items] == list(range(100))
            assert robot.connections == 1
            assert robot.counters()["retransmitted_messages"] == 0
            assert len(server._pending) == 200  # every stalled connection is still held
            # one address floods: it keeps at most its share, the others keep theirs
            for _ in range(100):
                _, w = await asyncio.open_connection(host, port, local_addr=("127.0.0.99", 0))
                w.write(b"\x00")
                stalled.append(w)
            await asyncio.sleep(0.2)
            sources = [c.source for c in server._pending]
            assert sources.count("127.0.0.99") == transport.max_pending_per_source
            assert len(sources) == 200 + transport.max_pending_per_source
        finally:
            for w in stalled:
                w.close()
            await robot.close()
            await server.close()

    run(main())


def test_a_full_disk_holds_the_sender_back_without_a_reconnect_storm(caplog):
    """Issue 18: a receiver whose storage fails (here: four attempts raise ENOSPC) retries the
    same message with backoff on the same connection. The sender is held back by the window:
    no reconnect, re-sent bytes within one window, every message delivered once, in order."""
    import errno

    window = 16

    async def main():
        attempts = {"n": 0}
        got: list[int] = []

        async def handler(d: Delivery) -> None:
            if d.message.channel == 10 and attempts["n"] < 4:
                attempts["n"] += 1
                raise OSError(errno.ENOSPC, "database or disk is full")
            got.append(d.message.channel)

        transport = TransportConfig(handler_retry_initial=0.1)
        server = Server(scfg(window_messages=window), handler, transport=transport)
        host, port = await server.start()
        client = Client(
            scfg("robot-1", "robot", retransmit_timeout=0.2), Sink(), host, port, transport=FAST
        )
        await client.start()
        try:
            for i in range(200):
                await client.send(Blob(i, b"d" * 1000))
            await client.flush()
            assert got == list(range(200))
            assert attempts["n"] == 4 and server.peers["robot-1"].handler_failures == 4
            c = client.counters()
            assert client.connections == 1
            assert c["retransmitted_bytes"] <= window * 1100
        finally:
            await client.close()
            await server.close()

    with caplog.at_level(logging.WARNING):
        run(main())
    assert "database or disk is full" in caplog.text
