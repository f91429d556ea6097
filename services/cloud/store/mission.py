"""Missions: a new team of robots starting inside the map an earlier mission left.

A cloud state directory (``services.cloud.store.persistence``) can hold several missions, one after
the other; ``recslam cloud --state-dir DIR --mission NAME`` serves mission NAME: it resumes
NAME when that is the directory's current mission (a crash restart runs the same command line,
and must continue the same agents with exactly-once delivery from the stored edge positions),
and otherwise starts it (``CloudStore.enter_mission``: the stored edge positions are cleared,
the new mission's edges start their streams afresh). Without ``--mission`` the current
mission continues, as before missions existed.

The atlas agents of earlier missions are the *prior map* (``CloudApp`` keeps them by atlas
agent id, apart from the current mission's ``(robot, edge map)`` keys, so a new mission's
``robot0`` on edge map 0 is a new agent rather than the old one's continuation). The prior
map is read-only:

- no edge message reaches it: an edge names robots, and names resolve to current agents;
- map fusion holds its keyframes (and map points) fixed in the pose graph and the full BA,
  and MBP never removes them (``MapFusion.held_agents``);
- corrections go to the current mission's agents only, and the outputs (trajectories, ground
  truth overlay) are the current mission's;
- its keyframes stay in the place-recognition database and are merge targets: a new robot's
  keyframe that matches one merges the robot's map *into* the prior map (the query's map is
  re-expressed in the candidate's frame, ``services.cloud.fusion.merge.apply_match``), so the new
  mission's trajectories come out in the first mission's frame.

Why the operator chooses the mission at the cloud, rather than the edges carrying a mission
id: it is a property of the whole deployment, the same for every edge and robot; the cloud is
the only tier with durable map state; and only the operator knows whether a restart continues
a mission or begins another. A name (not a bare ``--new-mission`` switch) keeps a restart
policy that re-runs the same command line from starting a third mission.

:class:`MissionClock` measures what the target asks for: the data time from the mission's
first keyframe to the keyframe whose verified match put each robot's map into the prior map.
Sans-I/O: plain bookkeeping over the atlas.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping

from services.cloud.atlas.atlas import Atlas

log = logging.getLogger(__name__)

MISSION_FILE = "mission.json"
"""The cloud's mission report in its result folder (:meth:`MissionClock.report`)."""


class MissionClock:
    """When each robot of the current mission joined the prior map.

    ``prior``: the prior map's atlas agent ids; ``current``: the current mission's ``{atlas
    agent id: robot name}`` at start (a restarted cloud: robots already in the prior map are
    recorded with an unknown time)."""

    def __init__(
        self, name: str, atlas: Atlas, prior: Iterable[int], current: Mapping[int, str]
    ) -> None:
        self.name = name
        self.atlas = atlas
        self.prior = frozenset(prior)
        first = [
            atlas.keyframe(k).timestamp
            for a in current
            if a in atlas.agents()
            for k in atlas.keyframe_keys(agent_id=a)
        ]
        self.first_keyframe_s: float | None = min(first) if first else None
        self.joined: dict[str, float | None] = {}
        self.note_merge(None, current)

    def _prior_maps(self) -> set[int]:
        return {self.atlas.map_of_agent(i) for i in self.prior if i in self.atlas.agents()}

    def keyframe(self, t: float) -> None:
        """A new keyframe of the mission at data time ``t`` [s]."""
        if self.first_keyframe_s is None or t < self.first_keyframe_s:
            self.first_keyframe_s = t

    def note_merge(self, t: float | None, current: Mapping[int, str]) -> None:
        """After a merge at data time ``t``: record it for each robot of ``current`` whose map
        is now the prior map's."""
        if not self.prior:
            return
        prior = self._prior_maps()
        for a, name in current.items():
            if name in self.joined or a not in self.atlas.agents():
                continue
            if self.atlas.map_of_agent(a) not in prior:
                continue
            self.joined[name] = t
            if t is not None and self.first_keyframe_s is not None:
                log.info(
                    "mission %r: robot %s merged into the prior map %.2f s after the mission's "
                    "first keyframe",
                    self.name,
                    name,
                    t - self.first_keyframe_s,
                )

    def report(self, names: Iterable[str]) -> dict[str, object]:
        """``{"mission", "prior_agents", "prior_keyframes", "first_keyframe_s", "robots":
        {name: {"merged_s", "delay_s"}}, "in_prior_map", "first_merge_delay_s"}`` for the
        robot ``names`` of the mission; times in data seconds, the delay from the mission's
        first keyframe; None: not merged (or merged before a restart)."""
        t0 = self.first_keyframe_s
        robots: dict[str, dict[str, float | None]] = {}
        for name in sorted(set(names)):
            t = self.joined.get(name)
            robots[name] = {
                "merged_s": t,
                "delay_s": t - t0 if t is not None and t0 is not None else None,
            }
        delays = [float(d) for r in robots.values() if (d := r["delay_s"]) is not None]
        return {
            "mission": self.name,
            "prior_agents": len(self.prior),
            "prior_keyframes": sum(
                len(self.atlas.keyframe_keys(agent_id=i))
                for i in self.prior
                if i in self.atlas.agents()
            ),
            "first_keyframe_s": t0,
            "robots": robots,
            "in_prior_map": sorted(n for n in robots if n in self.joined),
            "first_merge_delay_s": min(delays) if delays else None,
        }
