"""Through a 1 Mbit/s tbf-shaped veth between two private network namespaces (root only):
everything arrives exactly once and the link really is shaped."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sim.netem import shaped_link, shaping_unavailable

HERE = Path(__file__).parent
SECRET = "shaping-test-secret-0123456789"
RATE_KBIT, COUNT, SIZE = 1000, 150, 1000

_reason = shaping_unavailable()
pytestmark = [
    pytest.mark.root,
    pytest.mark.skipif(_reason is not None, reason=f"tbf shaping unavailable: {_reason}"),
]


def read_channels(log: Path) -> list[int]:
    data = log.read_bytes()
    return [int.from_bytes(data[o + 24 : o + 32]) for o in range(0, len(data) - 39, 40)]


@pytest.mark.slow
def test_tbf_link_delivers_everything_at_the_shaped_rate(tmp_path):
    log, out = tmp_path / "delivered.log", tmp_path / "sender.json"
    env = dict(os.environ, PYTHONPATH=str(HERE.parents[2]))
    with shaped_link(RATE_KBIT) as link:
        receiver = subprocess.Popen(
            link.exec_argv(
                link.ns_b,
                [
                    sys.executable,
                    str(HERE / "receiver_proc.py"),
                    "--host",
                    link.addr_b,
                    "--port",
                    "7411",
                    "--log",
                    str(log),
                    "--secret",
                    SECRET,
                ],
            ),
            env=env,
        )
        try:
            sender = subprocess.run(
                link.exec_argv(
                    link.ns_a,
                    [
                        sys.executable,
                        str(HERE / "sender_proc.py"),
                        "--host",
                        link.addr_b,
                        "--port",
                        "7411",
                        "--secret",
                        SECRET,
                        "--count",
                        str(COUNT),
                        "--size",
                        str(SIZE),
                        "--out",
                        str(out),
                    ],
                ),
                env=env,
                timeout=120,
                capture_output=True,
                text=True,
            )
            assert sender.returncode == 0, sender.stderr
            deadline = time.monotonic() + 10  # the last records land just before the acks
            while len(read_channels(log)) < COUNT and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            receiver.kill()
            receiver.wait()
    result = json.loads(out.read_text())
    assert read_channels(log) == list(range(COUNT))
    rate_bit_s = 8 * result["wire_tx_bytes"] / result["seconds"]
    # shaping is in effect: the protocol cannot beat the token bucket (+ burst allowance)
    assert rate_bit_s <= 1.25 * RATE_KBIT * 1000, rate_bit_s
    assert result["wire_tx_bytes"] > COUNT * SIZE
