"""Robots in network namespaces of their own, each linked to a hub namespace by a veth pair
shaped with kernel ``tbf`` in both directions: the topology of
``recslam experiment bandwidth --shaper tbf``.

::

    namespace rsbw<pid>-0   veth 10.215.0.2 ──tbf── 10.215.0.1 veth ┐
    namespace rsbw<pid>-1   veth 10.215.1.2 ──tbf── 10.215.1.1 veth ┤ namespace rsbw<pid>-hub
    ...                                                               ┘ (edge, cloud on its lo)

Nothing is added to the caller's own namespace (no interface, address, route or firewall
rule); the addresses exist only inside the namespaces, so traffic cannot leave the machine.
Each veth end gets ``tc qdisc add dev X root tbf rate R burst B latency L`` (its egress: the
robot's end shapes robot→edge, the hub's end edge→robot). :func:`star` creates it all,
yields, and deletes the namespaces (and with them their veth pairs) on the way out, also
after an error; it first deletes namespaces of this prefix left by a process that no longer
runs. Needs root and iproute2 (``ip``, ``tc``); :func:`check_available` says why not.

The services run inside with ``ip netns exec NS``: :meth:`Star.placement` gives
``lab.run.orchestration`` the argv prefixes and addresses.
"""

from __future__ import annotations

import logging
import os
import re
import subprocess
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

from lab.run.orchestration import Placement
from sim.netem import (
    ShapingError,
    Tbf,
    add_namespace,
    delete_namespaces,
    netns_exec,
    shaping_unavailable,
    veth_link,
)

log = logging.getLogger(__name__)

PREFIX = "rsbw"
"""Namespaces of this module are named ``rsbw<pid>-hub`` and ``rsbw<pid>-<i>``."""

_SUBNET = "10.215"


@dataclass(frozen=True)
class Leaf:
    """One robot's namespace and its link: ``addr`` its address, ``hub_addr`` the hub's end."""

    name: str
    namespace: str
    addr: str
    hub_addr: str
    device: str
    hub_device: str


@dataclass(frozen=True)
class Star:
    """A hub namespace and one shaped leaf namespace per name (see the module docstring)."""

    hub: str
    leaves: dict[str, Leaf]
    shape: Tbf | None

    def exec_argv(self, namespace: str, argv: Sequence[str]) -> list[str]:
        """argv that runs ``argv`` inside ``namespace``."""
        return netns_exec(namespace, argv)

    def set_links(self, up: bool) -> None:
        """Take every robot's link down (an outage: nothing passes either way) or up again."""
        for leaf in self.leaves.values():
            state = "up" if up else "down"
            subprocess.run(
                ["ip", "-n", leaf.namespace, "link", "set", leaf.device, state], check=True
            )
        log.info("robot links %s", "up" if up else "down")

    def placement(self, hub_services: Sequence[str] = ("cloud", "edge")) -> Placement:
        """Cloud and edge in the hub (the edge listening on every hub address), each leaf's
        robot in its namespace reaching the edge at its link's hub address."""
        prefix = {name: tuple(self.exec_argv(self.hub, [])) for name in hub_services}
        for name, leaf in self.leaves.items():
            prefix[name] = tuple(self.exec_argv(leaf.namespace, []))
        edge_host = {name: leaf.hub_addr for name, leaf in self.leaves.items()}
        return Placement(prefix=prefix, edge_listen_host="0.0.0.0", edge_host=edge_host)


def check_available() -> None:
    """Raise ShapingError naming why namespaces with tbf cannot be made here (not root, no
    ``ip`` / ``tc``, no namespaces, no tbf qdisc)."""
    reason = shaping_unavailable()
    if reason is not None:
        raise ShapingError(f"kernel tbf shaping in network namespaces unavailable: {reason}")


def namespaces() -> list[str]:
    """Names of the network namespaces ``ip netns list`` shows."""
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=False)
    return [line.split()[0] for line in out.stdout.splitlines() if line.strip()]


def cleanup_leftovers(prefix: str = PREFIX) -> list[str]:
    """Delete namespaces of ``prefix`` whose creating process no longer runs; returns them."""
    pattern = re.compile(rf"^{re.escape(prefix)}(\d+)-")
    removed = []
    for ns in namespaces():
        m = pattern.match(ns)
        if m is None or _alive(int(m.group(1))):
            continue
        delete_namespaces([ns])
        removed.append(ns)
    if removed:
        log.warning("deleted namespaces left by an earlier run: %s", ", ".join(removed))
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextmanager
def star(names: Sequence[str], shape: Tbf | None, prefix: str = PREFIX) -> Iterator[Star]:
    """Create the hub and one leaf namespace per name (at most 250), each link shaped with
    ``shape`` in both directions (None: not shaped, same topology); delete them on exit."""
    check_available()
    if not 0 < len(names) <= 250:
        raise ShapingError(f"1..250 leaves, got {len(names)}")
    cleanup_leftovers(prefix)
    tag = f"{prefix}{os.getpid()}"
    hub = f"{tag}-hub"
    created: list[str] = []
    try:
        add_namespace(hub, created)
        leaves = {}
        for i, name in enumerate(names):
            leaf = Leaf(
                name=name,
                namespace=f"{tag}-{i}",
                addr=f"{_SUBNET}.{i}.2",
                hub_addr=f"{_SUBNET}.{i}.1",
                device=f"rsbw{i}r",
                hub_device=f"rsbw{i}h",
            )
            add_namespace(leaf.namespace, created)
            veth_link(
                (leaf.namespace, leaf.device, leaf.addr),
                (hub, leaf.hub_device, leaf.hub_addr),
                shape,
                shape,
            )
            leaves[name] = leaf
        log.info(
            "namespaces %s: %d robots linked to %s, %s",
            tag,
            len(leaves),
            hub,
            "unshaped" if shape is None else f"tbf {' '.join(shape.tc_args()[1:])} each way",
        )
        yield Star(hub, leaves, shape)
    finally:
        delete_namespaces(created[::-1])
