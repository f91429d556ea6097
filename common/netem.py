"""Bandwidth shaping with Linux ``tbf`` between two private network namespaces.

The test machines' kernels lack the ``netem`` qdisc, so delay/loss emulation is out, but a
token-bucket filter still shapes rate. :func:`shaped_link` creates two namespaces joined by a
veth pair with addresses in 10.213.x.0/30 that exist only inside those namespaces (nothing
is added to the caller's namespace; traffic cannot leave the machine), puts a ``tbf`` qdisc
on each end, yields, and deletes both namespaces (and with them the veth pair) on exit.
Needs root and iproute2; :func:`shaping_unavailable` says why not when it cannot run.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

from common.errors import RecslamError

logger = logging.getLogger(__name__)


class ShapingError(RecslamError):
    """A namespace, veth or qdisc command failed."""


@dataclass(frozen=True)
class ShapedLink:
    """Two namespaces joined by a shaped veth pair: run programs with :meth:`exec_argv`."""

    ns_a: str
    ns_b: str
    addr_a: str
    addr_b: str
    rate_kbit: int

    def exec_argv(self, ns: str, argv: Sequence[str]) -> list[str]:
        """argv that runs ``argv`` inside namespace ``ns``."""
        return ["ip", "netns", "exec", ns, *argv]


def shaping_unavailable() -> str | None:
    """None if :func:`shaped_link` can run here, else the reason it cannot."""
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces and tc need root"
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"iproute2 tool {tool!r} not installed"
    probe = f"rsprobe{os.getpid()}"
    try:
        run_checked(["ip", "netns", "add", probe])
    except ShapingError as exc:
        return f"cannot create a network namespace: {exc}"
    try:
        run_checked(
            [
                "ip",
                "netns",
                "exec",
                probe,
                "tc",
                "qdisc",
                "add",
                "dev",
                "lo",
                "root",
                "tbf",
                "rate",
                "1mbit",
                "burst",
                "4kb",
                "latency",
                "50ms",
            ]
        )
    except ShapingError as exc:
        return f"tbf qdisc unavailable: {exc}"
    finally:
        subprocess.run(["ip", "netns", "del", probe], capture_output=True, check=False)
    return None


def run_checked(argv: Sequence[str]) -> None:
    """Run an `ip` / `tc` command; ShapingError with its stderr when it fails."""
    proc = subprocess.run(list(argv), capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise ShapingError(f"{' '.join(argv)}: {proc.stderr.strip() or proc.returncode}")


@contextmanager
def shaped_link(
    rate_kbit: int,
    *,
    burst_bytes: int = 5000,
    latency_ms: int = 200,
    both_directions: bool = True,
) -> Iterator[ShapedLink]:
    """Create namespaces A and B joined by veth, shaped by tbf at ``rate_kbit`` kbit/s.

    Args:
        rate_kbit: token rate (kbit/s, 1 kbit = 1000 bit) on A's egress (and B's).
        burst_bytes: bucket size in bytes (>= MTU).
        latency_ms: longest a packet may wait in the tbf queue before being dropped.
        both_directions: also shape B -> A (acks of the protocol travel that way).
    """
    tag = f"{os.getpid() % 100000}"
    ns_a, ns_b = f"rs{tag}a", f"rs{tag}b"
    veth_a, veth_b = f"rsv{tag}a", f"rsv{tag}b"
    octet = os.getpid() % 250
    addr_a, addr_b = f"10.213.{octet}.1", f"10.213.{octet}.2"
    tbf = [
        "tbf",
        "rate",
        f"{rate_kbit}kbit",
        "burst",
        str(burst_bytes),
        "latency",
        f"{latency_ms}ms",
    ]
    created: list[str] = []
    try:
        for ns in (ns_a, ns_b):
            run_checked(["ip", "netns", "add", ns])
            created.append(ns)
            run_checked(["ip", "-n", ns, "link", "set", "lo", "up"])
        run_checked(
            [
                "ip",
                "link",
                "add",
                veth_a,
                "netns",
                ns_a,
                "type",
                "veth",
                "peer",
                "name",
                veth_b,
                "netns",
                ns_b,
            ]
        )
        for ns, dev, addr in ((ns_a, veth_a, addr_a), (ns_b, veth_b, addr_b)):
            run_checked(["ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", dev])
            run_checked(["ip", "-n", ns, "link", "set", dev, "up"])
        run_checked(
            ["ip", "netns", "exec", ns_a, "tc", "qdisc", "add", "dev", veth_a, "root", *tbf]
        )
        if both_directions:
            run_checked(
                ["ip", "netns", "exec", ns_b, "tc", "qdisc", "add", "dev", veth_b, "root", *tbf]
            )
        logger.info(
            "shaped link %s(%s) <-> %s(%s) at %d kbit/s", ns_a, addr_a, ns_b, addr_b, rate_kbit
        )
        yield ShapedLink(ns_a, ns_b, addr_a, addr_b, rate_kbit)
    finally:
        for ns in created:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)
