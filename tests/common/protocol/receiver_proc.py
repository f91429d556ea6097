"""Receiver process for test_restart.py (run as a script; killed with SIGKILL on purpose).

A protocol Server whose handler appends one fixed-size record per message to a log file in a
single write(2). The log *is* the durable delivery position: on start the last complete
record gives the InboundPosition handed to the transport, so effect and position are atomic
and a restart neither loses nor repeats a message.
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import os
import struct

from common.protocol import InboundPosition, SessionConfig
from common.transport import Delivery, Server, TransportConfig, run

RECORD = struct.Struct("!16sQQ8s")  # sender stream id, seq, channel, sha256(data)[:8]


class LogStore:
    """DeliveryStore whose position is the last record of the append-only log."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        size = os.fstat(self.fd).st_size
        whole = size - size % RECORD.size
        if whole != size:
            os.ftruncate(self.fd, whole)  # a torn record from the kill is not delivered
        self.position: InboundPosition | None = None
        if whole:
            stream, seq, _, _ = RECORD.unpack(os.pread(self.fd, RECORD.size, whole - RECORD.size))
            self.position = InboundPosition(stream, seq)

    def load(self, peer: str) -> InboundPosition | None:
        return self.position

    def save(self, peer: str, position: InboundPosition) -> None:
        """Nothing to do: the handler's record already holds the position."""

    async def handle(self, d: Delivery) -> None:
        digest = hashlib.sha256(d.message.data).digest()[:8]
        os.write(self.fd, RECORD.pack(d.stream_id, d.seq, d.message.channel, digest))


async def main(host: str, port: int, log: str, secret: bytes) -> None:
    store = LogStore(log)
    config = SessionConfig(
        role="edge", agent_id="edge-0", secret=secret, heartbeat_interval=0.2, idle_timeout=1.0
    )
    server = Server(config, store.handle, store=store, transport=TransportConfig())
    await server.start(host, port)
    await asyncio.Event().wait()  # until killed


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--log", required=True)
    parser.add_argument("--secret", required=True)
    args = parser.parse_args()
    run(main(args.host, args.port, args.log, args.secret.encode()))
