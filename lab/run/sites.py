"""Sites: which robots each edge of a run serves, and counters over several edges.

Pure helpers of :mod:`lab.run.orchestration` and :mod:`lab.run.report` (no processes, no
files): the ``--sites`` / ``--move`` syntax of ``recslam demo``, the round-robin assignment
of ``--edges N``, and one edge-shaped view of several edges' counters.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

from common.errors import RecslamError


class SitesError(RecslamError, ValueError):
    """A malformed ``--sites`` / ``--move``, or sites that do not match the robots."""


SINGLE_EDGE = "edge"
"""The name of the one edge of a run without sites (its stats file is ``stats/edge.json``)."""


def edge_stats_name(edge: str) -> str:
    """The stats file stem of edge ``edge``: ``edge`` for the single edge, ``edge-<name>``
    for a site (``lab.run.report`` reads every ``stats/edge*.json``)."""
    return "edge" if edge == SINGLE_EDGE else f"edge-{edge}"


def parse_sites(text: str) -> dict[str, tuple[str, ...]]:
    """``edgeA=robot0,robot1;edgeB=robot2`` -> ``{edgeA: (robot0, robot1), edgeB: (robot2,)}``
    (SitesError on an empty or repeated name)."""
    sites: dict[str, tuple[str, ...]] = {}
    seen: set[str] = set()
    for part in filter(None, (p.strip() for p in text.split(";"))):
        edge, sep, robots = part.partition("=")
        names = tuple(r.strip() for r in robots.split(",") if r.strip())
        if not sep or not edge.strip() or not names:
            raise SitesError(f"--sites part {part!r} is not EDGE=ROBOT[,ROBOT...]")
        if edge.strip() in sites or seen & set(names) or len(set(names)) < len(names):
            raise SitesError(f"--sites {text!r}: an edge or a robot named twice")
        sites[edge.strip()] = names
        seen |= set(names)
    if not sites:
        raise SitesError(f"--sites {text!r} names no edge")
    return sites


def parse_move(text: str) -> tuple[str, int, str]:
    """``robot0@150=edge1`` -> ``(robot0, 150, edge1)``: robot0 moves to edge1 at frame 150."""
    found = re.fullmatch(r"\s*([^@=\s]+)@(\d+)=([^@=\s]+)\s*", text)
    if found is None:
        raise SitesError(f"--move {text!r} is not ROBOT@FRAME=EDGE")
    return found.group(1), int(found.group(2)), found.group(3)


def assign_sites(
    robots: Sequence[str], edges: int = 1, sites: Mapping[str, Sequence[str]] | None = None
) -> dict[str, tuple[str, ...]]:
    """Edge name -> its robots: ``sites`` as given (every robot of ``robots`` must be on one
    edge, no other), else one edge ``edge`` (``edges`` 1) or ``edge0``.. with the robots
    round-robin."""
    if sites:
        named = [r for rs in sites.values() for r in rs]
        if sorted(named) != sorted(robots):
            raise SitesError(f"sites name robots {sorted(named)}, the dataset has {sorted(robots)}")
        return {e: tuple(rs) for e, rs in sites.items()}
    if edges < 1:
        raise SitesError(f"edges must be >= 1, got {edges}")
    if edges == 1:
        return {SINGLE_EDGE: tuple(robots)}
    return {f"edge{i}": tuple(robots[i::edges]) for i in range(edges)}


def merge_edge_stats(per_edge: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """One edge-shaped counter set over several edges: per robot (and per robot link) the
    integers summed over the edges that served it (a robot that moved has frames at both),
    the rest (e.g. its VIO state) from the last edge that has it; ``edge_of`` robot -> the
    edges that served it, in the given order."""
    if len(per_edge) == 1:
        only = dict(next(iter(per_edge.values())))
        name = next(iter(per_edge))
        only["edge_of"] = {r: [name] for r in only.get("robots", {})}
        return only
    out: dict[str, Any] = {"robots": {}, "links": {}, "edge_of": {}}
    for edge, st in per_edge.items():
        for section in ("robots", "links"):
            for robot, c in st.get(section, {}).items():
                out[section][robot] = _sum_counters(out[section].get(robot), c)
        for robot in st.get("robots", {}):
            out["edge_of"].setdefault(robot, []).append(edge)
    return out


def _sum_counters(a: Any, b: Any) -> Any:
    if a is None:
        return b
    if isinstance(a, dict) and isinstance(b, dict):
        return {k: _sum_counters(a.get(k), b.get(k)) if k in a else b[k] for k in {*a, *b}}
    if isinstance(a, int | float) and isinstance(b, int | float) and not isinstance(a, bool):
        return a + b
    return b if b is not None else a


def parse_restart(text: str) -> tuple[str, float]:
    """``edge1@20`` -> ``("edge1", 20.0)``: kill and restart edge1 20 s into the run."""
    found = re.fullmatch(r"\s*([^@\s]+)@(\d+(?:\.\d*)?)\s*", text)
    if found is None:
        raise SitesError(f"--restart-edge {text!r} is not EDGE@SECONDS")
    return found.group(1), float(found.group(2))
