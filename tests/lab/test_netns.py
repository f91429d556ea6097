"""A tbf-shaped link between a robot's namespace and the hub (``lab.netns``), checked with
real TCP transfers each way: the goodput is near the tbf rate; nothing is left behind.

Root only (network namespaces and tc); skipped with the reason otherwise. The transfer is a
measurement of the kernel's shaper, so its bound is wide (± 30 %)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from lab.netns import PREFIX, Tbf, cleanup_leftovers, namespaces, star
from sim.netem import ShapingError, shaping_unavailable

_reason = shaping_unavailable()
pytestmark = [
    pytest.mark.root,
    pytest.mark.skipif(_reason is not None, reason=f"tbf in namespaces unavailable: {_reason}"),
]

RATE_KBIT = 200
SIZE = 100_000  # bytes: 4 s at 200 kbit/s, the 4000 B burst is 4 % of it

RECEIVER = """
import json, socket, sys, time
srv = socket.create_server((sys.argv[1], int(sys.argv[2])))
print("ready", flush=True)
conn, _ = srv.accept()
n, first, last = 0, None, None
while chunk := conn.recv(65536):
    now = time.monotonic()
    first = now if first is None else first
    n, last = n + len(chunk), now
print(json.dumps({"bytes": n, "seconds": last - first}), flush=True)
"""

SENDER = """
import socket, sys
with socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=60) as s:
    s.sendall(b"x" * int(sys.argv[3]))
"""


REACH = """
import socket, sys
try:  # nobody listens there: refused means the hub answered
    socket.create_connection((sys.argv[1], 7599), timeout=1).close()
except ConnectionRefusedError:
    sys.exit(0)
except OSError:
    sys.exit(1)
"""


def transfer(link_star, from_ns: str, to_ns: str, to_addr: str, port: int) -> dict:
    """Send SIZE bytes from ``from_ns`` to ``to_addr`` in ``to_ns``; the receiver's count."""
    receiver = subprocess.Popen(
        link_star.exec_argv(to_ns, [sys.executable, "-c", RECEIVER, to_addr, str(port)]),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert receiver.stdout is not None and receiver.stdout.readline().strip() == "ready"
        sender = [sys.executable, "-c", SENDER, to_addr, str(port), str(SIZE)]
        subprocess.run(
            link_star.exec_argv(from_ns, sender),
            check=True,
            timeout=120,
        )
        out, _ = receiver.communicate(timeout=120)
    finally:
        receiver.kill()
        receiver.wait()
    return json.loads(out)


@pytest.mark.slow
def test_a_shaped_link_carries_tcp_at_the_tbf_rate_both_ways() -> None:
    with star(["robot0"], Tbf(RATE_KBIT)) as s:
        leaf = s.leaves["robot0"]
        assert {s.hub, leaf.namespace} <= set(namespaces())
        up = transfer(s, leaf.namespace, s.hub, leaf.hub_addr, 7501)  # robot -> edge
        down = transfer(s, s.hub, leaf.namespace, leaf.addr, 7502)  # edge -> robot
        qdiscs = subprocess.run(
            s.exec_argv(leaf.namespace, ["tc", "qdisc", "show", "dev", leaf.device]),
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        made = (s.hub, leaf.namespace)
    assert "tbf" in qdiscs and "rate 200Kbit" in qdiscs
    for result in (up, down):
        assert result["bytes"] == SIZE
        kbit_s = 8 * result["bytes"] / result["seconds"] / 1000
        assert 0.7 * RATE_KBIT <= kbit_s <= 1.3 * RATE_KBIT, (result, kbit_s)
    assert not set(made) & set(namespaces())  # deleted on the way out


def test_an_unshaped_star_is_much_faster_than_the_shaped_rate() -> None:
    with star(["robot0"], None) as s:
        leaf = s.leaves["robot0"]
        up = transfer(s, leaf.namespace, s.hub, leaf.hub_addr, 7503)
    assert up["bytes"] == SIZE
    assert 8 * SIZE / up["seconds"] / 1000 > 10 * RATE_KBIT


def test_a_cut_link_passes_nothing_until_it_is_up_again() -> None:
    """``Star.set_links``: an outage drill (the budget experiment's ``/cut`` rows)."""
    with star(["robot0"], None) as s:
        leaf = s.leaves["robot0"]
        reach = s.exec_argv(leaf.namespace, [sys.executable, "-c", REACH, leaf.hub_addr])
        assert subprocess.run(reach, capture_output=True).returncode == 0
        s.set_links(False)
        assert subprocess.run(reach, capture_output=True).returncode != 0
        s.set_links(True)
        assert subprocess.run(reach, capture_output=True).returncode == 0


def test_namespaces_are_deleted_after_an_error_and_leftovers_of_dead_runs_cleaned() -> None:
    with pytest.raises(RuntimeError, match="inside"), star(["a", "b"], Tbf(100)) as s:
        made = [s.hub, *(leaf.namespace for leaf in s.leaves.values())]
        raise RuntimeError("inside")
    assert not set(made) & set(namespaces())
    dead = next(p for p in range(4_000_000, 4_100_000) if not os.path.exists(f"/proc/{p}"))
    stale = f"{PREFIX}{dead}-hub"
    subprocess.run(["ip", "netns", "add", stale], check=True)
    mine = f"{PREFIX}{os.getpid()}-x"  # a running process's: kept
    subprocess.run(["ip", "netns", "add", mine], check=True)
    try:
        assert cleanup_leftovers() == [stale]
        assert stale not in namespaces() and mine in namespaces()
    finally:
        for ns in (stale, mine):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)


def test_tbf_parameters_are_checked() -> None:
    assert Tbf(50).tc_args() == ["tbf", "rate", "50000bit", "burst", "4000", "latency", "400ms"]
    for bad in ({"rate_kbit": 0}, {"rate_kbit": 50, "burst_bytes": 100}):
        with pytest.raises(ShapingError):
            Tbf(**bad)
