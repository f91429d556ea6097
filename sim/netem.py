"""Bandwidth shaping with Linux ``tbf`` between two private network namespaces.

The test machines' kernels lack the ``netem`` qdisc, so delay/loss emulation is out, but a
token-bucket filter still shapes rate. :func:`shaped_link` creates two namespaces joined by a
veth pair with addresses in 10.213.x.0/30 that exist only inside those namespaces (nothing
is added to the caller's namespace; traffic cannot leave the machine), puts a ``tbf`` qdisc
on each end, yields, and deletes both namespaces (and with them the veth pair) on exit.
Needs root and iproute2; :func:`shaping_unavailable` says why not when it cannot run.

Its pieces (:class:`Tbf`, :func:`add_namespace`, :func:`veth_link`, :func:`netns_exec`,
:func:`delete_namespaces`) also build ``lab.netns``'s star of robot namespaces.
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
class Tbf:
    """One ``tbf`` qdisc: ``rate`` kbit/s (1 kbit = 1000 bit), bucket ``burst_bytes``, and
    ``latency_ms``, the longest a packet may wait in the queue before it is dropped (so the
    queue holds about rate × latency + burst bytes)."""

    rate_kbit: float
    burst_bytes: int = 4000
    latency_ms: int = 400

    def __post_init__(self) -> None:
        if not self.rate_kbit > 0:
            raise ShapingError(f"tbf rate must be positive, got {self.rate_kbit} kbit/s")
        if self.burst_bytes < 1600:
            raise ShapingError(f"tbf burst {self.burst_bytes} B is below one packet (1600 B)")
        if self.latency_ms <= 0:
            raise ShapingError(f"tbf latency must be positive, got {self.latency_ms} ms")

    def tc_args(self) -> list[str]:
        """The qdisc's ``tc`` parameters (after ``root``)."""
        rate_bit = round(self.rate_kbit * 1000)
        burst, latency = str(self.burst_bytes), f"{self.latency_ms}ms"
        return ["tbf", "rate", f"{rate_bit}bit", "burst", burst, "latency", latency]


def netns_exec(ns: str, argv: Sequence[str]) -> list[str]:
    """argv that runs ``argv`` inside network namespace ``ns``."""
    return ["ip", "netns", "exec", ns, *argv]


def add_namespace(ns: str, created: list[str]) -> None:
    """Create namespace ``ns`` (appended to ``created`` for the caller's cleanup), lo up."""
    run_checked(["ip", "netns", "add", ns])
    created.append(ns)
    run_checked(["ip", "-n", ns, "link", "set", "lo", "up"])


def delete_namespaces(names: Sequence[str]) -> None:
    """Delete namespaces (and with them their veth ends), ignoring ones already gone."""
    for ns in names:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)


def veth_link(
    a: tuple[str, str, str], b: tuple[str, str, str], shape_a: Tbf | None, shape_b: Tbf | None
) -> None:
    """A veth pair between ends ``a`` and ``b``, each ``(namespace, device, address)`` (a
    /30), up, with ``shape_a`` / ``shape_b`` as the root qdisc of that end (its egress)."""
    (ns_a, dev_a, _), (ns_b, dev_b, _) = a, b
    peer = ["peer", "name", dev_b, "netns", ns_b]
    run_checked(["ip", "-n", ns_a, "link", "add", dev_a, "type", "veth", *peer])
    for (ns, dev, addr), shape in ((a, shape_a), (b, shape_b)):
        run_checked(["ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", dev])
        run_checked(["ip", "-n", ns, "link", "set", dev, "up"])
        if shape is not None:
            run_checked(
                netns_exec(ns, ["tc", "qdisc", "add", "dev", dev, "root", *shape.tc_args()])
            )


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
        return netns_exec(ns, argv)


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
        tbf = Tbf(1000, burst_bytes=4096, latency_ms=50).tc_args()
        run_checked(netns_exec(probe, ["tc", "qdisc", "add", "dev", "lo", "root", *tbf]))
    except ShapingError as exc:
        return f"tbf qdisc unavailable: {exc}"
    finally:
        delete_namespaces([probe])
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
    tbf = Tbf(rate_kbit, burst_bytes, latency_ms)
    created: list[str] = []
    try:
        for ns in (ns_a, ns_b):
            add_namespace(ns, created)
        veth_link(
            (ns_a, veth_a, addr_a), (ns_b, veth_b, addr_b), tbf, tbf if both_directions else None
        )
        logger.info(
            "shaped link %s(%s) <-> %s(%s) at %d kbit/s", ns_a, addr_a, ns_b, addr_b, rate_kbit
        )
        yield ShapedLink(ns_a, ns_b, addr_a, addr_b, rate_kbit)
    finally:
        delete_namespaces(created)
