"""Sender process for test_shaping.py and the benchmark: sends Blobs, waits until all are
delivered (acked), and writes timing and wire counters as JSON to ``--out``."""

from __future__ import annotations

import argparse
import json
import random
import time
from pathlib import Path

from common.protocol import Blob, SessionConfig
from common.transport import Client, Delivery, TransportConfig, run


async def main(args: argparse.Namespace) -> None:
    async def nothing(d: Delivery) -> None:
        """The receiver sends nothing back."""

    config = SessionConfig(role="robot", agent_id="robot-9", secret=args.secret.encode())
    transport = TransportConfig(reconnect_initial_delay=0.05, reconnect_max_delay=0.5)
    client = Client(config, nothing, args.host, args.port, transport=transport)
    await client.start()
    await client.wait_connected(30)
    rng = random.Random(args.seed)
    before = client.counters()["tx"]["bytes"]
    start = time.perf_counter()
    for i in range(args.count):
        await client.send(Blob(i, rng.randbytes(args.size)))
    await client.flush()
    seconds = time.perf_counter() - start
    counters = client.counters()
    await client.close()
    result = {
        "seconds": seconds,
        "messages": args.count,
        "payload_bytes": args.count * args.size,
        "wire_tx_bytes": counters["tx"]["bytes"] - before,
        "counters": counters,
    }
    Path(args.out).write_text(json.dumps(result))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--host", required=True)
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--secret", required=True)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--size", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    run(main(parser.parse_args()))
