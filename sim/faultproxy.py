"""Fault-injecting TCP proxy (asyncio) for link tests and bandwidth experiments.

Sits between a client and a server on loopback and, per connection, can cut the connection
(RST) after a random number of forwarded bytes, stall a direction, throttle it to a byte
rate, and split writes at random boundaries. ``cut_all()`` cuts every live connection on
demand. Deterministic for a given ``FaultConfig.seed`` (up to scheduling).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from dataclasses import dataclass

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FaultConfig:
    """Faults applied to every proxied connection.

    Attributes:
        cut_after_bytes: (lo, hi): abort a connection after a uniformly drawn number of
            bytes forwarded in both directions together; None = never.
        stall_probability: per forwarded piece, chance of pausing that direction.
        stall_seconds: (lo, hi) duration of a stall (s).
        rate_bytes_per_s: throttle per direction (bytes/s); None = unlimited.
        max_write_bytes: split forwarded data into random pieces of 1..this many bytes;
            None = forward reads as they come.
        seed: random seed.
    """

    cut_after_bytes: tuple[int, int] | None = None
    stall_probability: float = 0.0
    stall_seconds: tuple[float, float] = (0.05, 0.2)
    rate_bytes_per_s: float | None = None
    max_write_bytes: int | None = None
    seed: int = 0


@dataclass
class ProxyStats:
    connections: int = 0
    cuts: int = 0
    stalls: int = 0
    bytes_up: int = 0  # client -> server
    bytes_down: int = 0  # server -> client


class _Pipe:
    """One proxied connection (both directions)."""

    def __init__(
        self,
        proxy: FaultProxy,
        client: tuple[asyncio.StreamReader, asyncio.StreamWriter],
        upstream: tuple[asyncio.StreamReader, asyncio.StreamWriter],
    ) -> None:
        self.proxy = proxy
        self.client, self.upstream = client, upstream
        cfg = proxy.config
        lo_hi = cfg.cut_after_bytes
        self.budget = proxy.rng.randint(*lo_hi) if lo_hi else None
        self.forwarded = 0
        self.done = asyncio.Event()

    def cut(self) -> None:
        if not self.done.is_set():
            self.proxy.stats.cuts += 1
            for _, writer in (self.client, self.upstream):
                writer.transport.abort()
            self.done.set()

    def close(self) -> None:
        if not self.done.is_set():
            for _, writer in (self.client, self.upstream):
                writer.close()
            self.done.set()

    async def pump(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, up: bool
    ) -> None:
        cfg, rng, stats = self.proxy.config, self.proxy.rng, self.proxy.stats
        try:
            while not self.done.is_set():
                data = await reader.read(65536)
                if not data:
                    self.close()
                    return
                while data and not self.done.is_set():
                    n = rng.randint(1, cfg.max_write_bytes) if cfg.max_write_bytes else len(data)
                    piece, data = data[:n], data[n:]
                    if self.budget is not None and self.forwarded + len(piece) >= self.budget:
                        piece = piece[: self.budget - self.forwarded]
                        writer.write(piece)
                        await writer.drain()
                        self.cut()
                        return
                    if cfg.stall_probability and rng.random() < cfg.stall_probability:
                        stats.stalls += 1
                        await asyncio.sleep(rng.uniform(*cfg.stall_seconds))
                    if cfg.rate_bytes_per_s:
                        await asyncio.sleep(len(piece) / cfg.rate_bytes_per_s)
                    await self.proxy.flowing.wait()
                    if self.done.is_set():
                        return
                    writer.write(piece)
                    await writer.drain()
                    self.forwarded += len(piece)
                    if up:
                        stats.bytes_up += len(piece)
                    else:
                        stats.bytes_down += len(piece)
        except (OSError, RuntimeError):
            self.cut()


class FaultProxy:
    """Forward ``listen`` -> ``target`` with faults from ``config``.

    Args:
        target_host, target_port: the real server.
        config: faults to inject.
    """

    def __init__(self, target_host: str, target_port: int, config: FaultConfig) -> None:
        self.target = (target_host, target_port)
        self.config = config
        self.rng = random.Random(config.seed)
        self.stats = ProxyStats()
        self._pipes: set[_Pipe] = set()
        self._tasks: set[asyncio.Task[None]] = set()
        self._server: asyncio.base_events.Server | None = None
        self.address: tuple[str, int] | None = None
        self.flowing = asyncio.Event()
        self.flowing.set()

    def freeze(self) -> None:
        """Stop forwarding in every connection (a black hole) until :meth:`thaw`."""
        self.flowing.clear()

    def thaw(self) -> None:
        self.flowing.set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._on_client, host, port)
        name = self._server.sockets[0].getsockname()
        self.address = (name[0], name[1])
        return self.address

    def cut_all(self) -> int:
        """Abort every live connection now; returns how many were cut."""
        pipes = [p for p in self._pipes if not p.done.is_set()]
        for pipe in pipes:
            pipe.cut()
        return len(pipes)

    @property
    def live_connections(self) -> int:
        return sum(not p.done.is_set() for p in self._pipes)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for pipe in list(self._pipes):
            pipe.cut()
        if self._tasks:  # cut pipes end their tasks; cancel only stragglers
            _, pending = await asyncio.wait(list(self._tasks), timeout=2.0)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        try:
            upstream = await asyncio.open_connection(*self.target)
        except OSError as exc:
            logger.info("proxy: upstream %s:%d unreachable: %r", *self.target, exc)
            writer.transport.abort()
            return
        self.stats.connections += 1
        pipe = _Pipe(self, (reader, writer), upstream)
        self._pipes.add(pipe)
        try:
            await asyncio.gather(
                pipe.pump(reader, upstream[1], up=True), pipe.pump(upstream[0], writer, up=False)
            )
        finally:
            pipe.close()
            self._pipes.discard(pipe)
            for w in (writer, upstream[1]):
                w.close()
                with contextlib.suppress(OSError, RuntimeError):
                    await w.wait_closed()
